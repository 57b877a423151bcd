"""The Fast DDS profile the localizer program gives itself (vlocnetpp_ros/dds_profile.py): merged with the user's
profile files, the user's values kept, nothing done when the user configures Fast DDS, and accepted by Fast DDS."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from conftest import REPO

from vlocnetpp_ros import dds_profile

LARGE_DATA = REPO / "config" / "fastdds_large_data.xml"


def _texts(path: Path, xpath: str) -> list[str]:
    return [e.text for e in ET.parse(path).getroot().iterfind("/".join("{*}" + part for part in xpath.split("/")))]


def test_without_a_user_profile_readers_are_dynamic_and_the_environment_is_restored(tmp_path: Path):
    env: dict[str, str] = {}
    applied = dds_profile.apply(env, tmp_path)
    assert applied.changed and env[dds_profile.USE_XML_ENV] == "1" and env[dds_profile.SKIP_CWD_ENV] == "1"
    path = Path(env[dds_profile.PROFILES_ENV])
    assert _texts(path, "profiles/data_reader/historyMemoryPolicy") == ["DYNAMIC"]
    assert _texts(path, "profiles/data_writer/historyMemoryPolicy") == ["PREALLOCATED_WITH_REALLOC"]
    assert _texts(path, "profiles/data_writer/qos/publishMode/kind") == ["SYNCHRONOUS"]
    assert _texts(path, "profiles/participant/rtps/builtin/readerHistoryMemoryPolicy") == ["PREALLOCATED_WITH_REALLOC"]
    applied.restore()
    assert env == {} and not path.exists()


def test_the_default_transports_get_a_large_shared_memory_segment(tmp_path: Path):
    """Fast DDS's two default transports, the shared-memory one with SHM_SEGMENT_BYTES, unless the environment
    chooses the builtin transports."""
    env: dict[str, str] = {}
    applied = dds_profile.apply(env, tmp_path)
    path = Path(env[dds_profile.PROFILES_ENV])
    assert _texts(path, "profiles/participant/rtps/userTransports/transport_id") == list(dds_profile.TRANSPORT_IDS)
    assert _texts(path, "profiles/participant/rtps/useBuiltinTransports") == ["false"]
    assert _texts(path, "profiles/transport_descriptors/transport_descriptor/type") == ["SHM", "UDPv4"]
    assert _texts(path, "profiles/transport_descriptors/transport_descriptor/segment_size") == [
        str(dds_profile.SHM_SEGMENT_BYTES)
    ]
    assert "shared-memory segment 8 MiB" in applied.message
    applied.restore()
    env = {dds_profile.BUILTIN_TRANSPORTS_ENV: "UDPv4"}
    applied = dds_profile.apply(env, tmp_path)
    path = Path(env[dds_profile.PROFILES_ENV])
    assert (
        _texts(path, "profiles/participant/rtps/userTransports") == []
        and _texts(path, "profiles/transport_descriptors") == []
    )
    assert "shared-memory segment" not in applied.message
    applied.restore()


def test_the_camera_profile_gives_the_segment_the_node_gives_itself():
    """config/fastdds_camera.xml (for camera drivers) holds the transports dds_profile gives the node."""
    path = REPO / "config" / "fastdds_camera.xml"
    assert _texts(path, "transport_descriptors/transport_descriptor/transport_id") == list(dds_profile.TRANSPORT_IDS)
    assert _texts(path, "transport_descriptors/transport_descriptor/segment_size") == [
        str(dds_profile.SHM_SEGMENT_BYTES)
    ]
    assert _texts(path, "transport_descriptors/transport_descriptor/maxMessageSize") == [
        str(dds_profile.SHM_MAX_MESSAGE_BYTES)
    ]
    assert _texts(path, "participant/rtps/userTransports/transport_id") == list(dds_profile.TRANSPORT_IDS)
    assert _texts(path, "participant/rtps/useBuiltinTransports") == ["false"]


def test_the_users_files_are_merged_and_their_values_kept(tmp_path: Path):
    (tmp_path / dds_profile.CWD_FILE).write_text(
        '<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">'
        '<data_reader profile_name="/camera/image" is_default_profile="true">'
        "<historyMemoryPolicy>PREALLOCATED_WITH_REALLOC</historyMemoryPolicy></data_reader></profiles>"
    )
    env = {dds_profile.PROFILES_ENV: str(LARGE_DATA), "RMW_FASTRTPS_PUBLICATION_MODE": "ASYNCHRONOUS"}
    applied = dds_profile.apply(env, tmp_path)
    path = Path(env[dds_profile.PROFILES_ENV])
    assert _texts(path, "profiles/participant/rtps/builtinTransports") == ["LARGE_DATA"]  # the user's transports
    assert _texts(path, "profiles/data_reader/historyMemoryPolicy") == [
        "PREALLOCATED_WITH_REALLOC"
    ]  # the user's choice
    assert _texts(path, "profiles/data_writer/qos/publishMode/kind") == ["ASYNCHRONOUS"]
    assert str(LARGE_DATA) in applied.message and "shared-memory segment" not in applied.message
    assert "participant vlocnetpp_large_data: transports" in applied.message
    assert "data_reader /camera/image: historyMemoryPolicy PREALLOCATED_WITH_REALLOC" in applied.message
    applied.restore()
    assert env == {dds_profile.PROFILES_ENV: str(LARGE_DATA), "RMW_FASTRTPS_PUBLICATION_MODE": "ASYNCHRONOUS"}


def test_nothing_is_changed_when_the_user_configures_fast_dds_or_another_rmw_runs(tmp_path: Path):
    bad = tmp_path / "bad.xml"
    bad.write_text("<profiles><data_reader")
    for env in (
        {dds_profile.USE_XML_ENV: "0"},
        {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"},
        {dds_profile.PROFILES_ENV: str(bad)},
    ):
        before = dict(env)
        applied = dds_profile.apply(env, tmp_path)
        assert not applied.changed and env == before, applied.message
    assert "cannot merge" in applied.message and str(bad) in applied.message


@pytest.mark.parametrize("user_profile", [LARGE_DATA, None], ids=["large_data", "no_user_profile"])
def test_fast_dds_loads_the_merged_profile_without_an_error(tmp_path: Path, user_profile: Path | None):
    """A real participant from the merged profile (with the large-data profile, and alone with its own transports):
    Fast DDS's XML parser reports no error, and a message goes from a publisher to a subscription of the same
    node."""
    code = """
import sys, time
from vlocnetpp_ros import dds_profile
applied = dds_profile.apply()
import rclpy
from sensor_msgs.msg import Image
rclpy.init()
node = rclpy.create_node("dds_profile_probe")
got = []
node.create_subscription(Image, "/dds_profile_probe", got.append, 10)
pub = node.create_publisher(Image, "/dds_profile_probe", 10)
applied.restore()
end = time.monotonic() + 10
while not got and time.monotonic() < end:
    pub.publish(Image(width=640, height=480, encoding="rgb8", step=1920, data=bytes(640 * 480 * 3)))
    rclpy.spin_once(node, timeout_sec=0.1)
print(applied.message, len(got) > 0)
"""
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in (dds_profile.USE_XML_ENV, dds_profile.SKIP_CWD_ENV, "RMW_IMPLEMENTATION")
    }
    env.update(
        {
            "PYTHONPATH": str(REPO),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "ROS_DOMAIN_ID": str(150 + os.getpid() % 40),
        }
    )
    env.pop(dds_profile.PROFILES_ENV, None)
    if user_profile is not None:
        env[dds_profile.PROFILES_ENV] = str(user_profile)
    proc = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert "XMLPARSER" not in proc.stderr and "Error" not in proc.stderr, proc.stderr
    assert proc.stdout.strip().endswith("True") and "DYNAMIC" in proc.stdout, proc.stdout
