"""The Fast DDS profile the ``localizer`` program gives its own participant, so that its memory stays bounded
whatever its publishers do.

rmw_fastrtps (Jazzy's default RMW) creates every DataReader with the ``PREALLOCATED_WITH_REALLOC``
history memory policy: a payload, once grown to a message's size, is kept for reuse and never
freed. A reliable subscription whose keep-last history is shallower than a bursting publisher's
(depth 50 against the node's 10) with large, fragmented messages of varying sizes grows that pool
storm after storm (docs/node.md, "Memory under bad input"). With the ``DYNAMIC`` policy a payload
is freed when its sample is taken or dropped.

rmw_fastrtps reads its settings from the process environment when it creates the participant:
``FASTRTPS_DEFAULT_PROFILES_FILE`` (an XML profile file, loaded once per process) and
``RMW_FASTRTPS_USE_QOS_FROM_XML=1`` (take the history memory policy, the publication mode and data
sharing from that XML instead of rmw's built-in choices). :func:`apply` sets both for this process
only, before ``rclpy.init``, pointing at a file it writes: the user's own profiles (the file
``FASTRTPS_DEFAULT_PROFILES_FILE`` names and a ``DEFAULT_FASTRTPS_PROFILES.xml`` in the working
directory, which Fast DDS would load too) with what rmw would otherwise have forced filled in
where the user set nothing: readers ``DYNAMIC`` (the one change), writers
``PREALLOCATED_WITH_REALLOC`` with the publication mode of ``RMW_FASTRTPS_PUBLICATION_MODE``
(default ``SYNCHRONOUS``), data sharing off, discovery histories ``PREALLOCATED_WITH_REALLOC``.
A value the user set is kept, and named in the log line.

It also gives the participant the default transports (shared memory, UDPv4) with a shared-memory segment of
:data:`SHM_SEGMENT_BYTES` instead of Fast DDS's 512 KiB, where neither the user's profile nor
``FASTDDS_BUILTIN_TRANSPORTS`` chooses transports. The segment is the *sender's*: a publisher of messages larger
than 512 KiB (a 640x480 depth or colour image) with the default one delivers them with up to ~0.5 s of jitter to
a subscriber in another process (docs/node.md, "Camera transport"); with this one within a few milliseconds. The
locators are those of the default transports, so every default participant still talks to one with this profile.
The project's programs that publish camera frames (the node's segmentation; the soak, replay and latency tools,
:class:`vlocnetpp_ros.dds_client.DdsClient`) apply it; a camera driver takes ``config/fastdds_camera.xml``.

Nothing is done when ``RMW_FASTRTPS_USE_QOS_FROM_XML`` is already set (the user configures Fast DDS: ``0`` switches
this off), when another RMW is chosen, or when a user profile cannot be parsed (said so: their
file is then used as it is).
"""

from __future__ import annotations

import os
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import MutableMapping
from dataclasses import dataclass, field
from pathlib import Path

PROFILES_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
USE_XML_ENV = "RMW_FASTRTPS_USE_QOS_FROM_XML"
SKIP_CWD_ENV = "SKIP_DEFAULT_XML_FILE"
CWD_FILE = "DEFAULT_FASTRTPS_PROFILES.xml"
NAMESPACE = "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"
READER_POLICY = "DYNAMIC"
REALLOC = "PREALLOCATED_WITH_REALLOC"
BUILTIN_TRANSPORTS_ENV = "FASTDDS_BUILTIN_TRANSPORTS"
SHM_SEGMENT_BYTES = 8 * 1024 * 1024  # a few 640x480 or one 1280x720 colour + depth pair in flight
SHM_MAX_MESSAGE_BYTES = 4 * 1024 * 1024  # one 1280x720 32FC1 depth image (3.7 MB) unfragmented
TRANSPORT_IDS = ("vlocnetpp_shm", "vlocnetpp_udpv4")
_TRANSPORT_TAGS = ("userTransports", "builtinTransports", "useBuiltinTransports")


@dataclass
class Applied:
    """What :func:`apply` did: ``message`` for the log, ``restore()`` once the participant exists (deletes the
    written file and puts the environment back as it was)."""

    message: str
    changed: bool = False
    path: Path | None = None
    _saved: dict[str, str | None] = field(default_factory=dict)
    _environ: MutableMapping[str, str] | None = None

    def restore(self) -> None:
        for key, value in self._saved.items():
            if value is None:
                self._environ.pop(key, None)
            else:
                self._environ[key] = value
        self._saved = {}
        if self.path is not None:
            self.path.unlink(missing_ok=True)
            self.path = None


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _strip_namespaces(root: ET.Element) -> None:
    for element in root.iter():
        if isinstance(element.tag, str):
            element.tag = _local(element.tag)


def _child(parent: ET.Element, *path: str) -> ET.Element:
    """The element at ``path`` under ``parent``, made where missing."""
    for name in path:
        found = parent.find(name)
        parent = found if found is not None else ET.SubElement(parent, name)
    return parent


def _fill(parent: ET.Element, path: tuple[str, ...], value: str, kept: list[str], what: str) -> None:
    """Set the text at ``path`` unless the user set it (then record it in ``kept``)."""
    existing = parent.find("/".join(path))
    if existing is not None and (existing.text or "").strip():
        if existing.text.strip() != value:
            kept.append(f"{what} {existing.text.strip()}")
        return
    _child(parent, *path).text = value


def user_files(environ: MutableMapping[str, str], cwd: Path) -> list[Path]:
    """The profile files Fast DDS would load for this process: the environment's, then the working directory's."""
    files = [Path(environ[PROFILES_ENV])] if environ.get(PROFILES_ENV) else []
    if environ.get(SKIP_CWD_ENV) != "1" and (cwd / CWD_FILE).is_file():
        files.append(cwd / CWD_FILE)
    return files


def _add_transports(profiles: ET.Element, participant: ET.Element) -> None:
    """Shared memory with a :data:`SHM_SEGMENT_BYTES` segment, and UDPv4, as ``participant``'s only transports."""
    descriptors = profiles.find("transport_descriptors")
    if descriptors is None:  # first: Fast DDS resolves a participant's transport ids as it parses it
        descriptors = ET.Element("transport_descriptors")
        profiles.insert(0, descriptors)
    known = {e.findtext("transport_id") for e in descriptors.findall("transport_descriptor")}
    shm, udp = TRANSPORT_IDS
    if shm not in known:
        shm_descriptor = ET.SubElement(descriptors, "transport_descriptor")
        for tag, text in (
            ("transport_id", shm),
            ("type", "SHM"),
            ("segment_size", str(SHM_SEGMENT_BYTES)),
            ("maxMessageSize", str(SHM_MAX_MESSAGE_BYTES)),
        ):
            ET.SubElement(shm_descriptor, tag).text = text
    if udp not in known:
        udp_descriptor = ET.SubElement(descriptors, "transport_descriptor")
        ET.SubElement(udp_descriptor, "transport_id").text = udp
        ET.SubElement(udp_descriptor, "type").text = "UDPv4"
    rtps = _child(participant, "rtps")
    users = ET.SubElement(rtps, "userTransports")
    for transport_id in TRANSPORT_IDS:
        ET.SubElement(users, "transport_id").text = transport_id
    ET.SubElement(rtps, "useBuiltinTransports").text = "false"


def merged_profiles(
    files: list[Path], publication_mode: str | None, transports: bool = True
) -> tuple[ET.ElementTree, list[str]]:
    """One ``<dds>`` document with the profiles of ``files`` and rmw's settings filled in (readers ``DYNAMIC``;
    with ``transports``, the large shared-memory segment for participants whose transports the user did not
    choose); also what the user set that differs from the node's choice. Raises ``OSError`` / ``ET.ParseError``."""
    root = ET.Element("dds", {"xmlns": NAMESPACE})
    for path in files:
        top = ET.parse(path).getroot()
        _strip_namespaces(top)
        for element in [top] if top.tag != "dds" else list(top):
            root.append(element)
    profiles = root.find("profiles")
    if profiles is None:
        profiles = ET.SubElement(root, "profiles")
    kept: list[str] = []
    mode = {"ASYNCHRONOUS": "ASYNCHRONOUS", "AUTO": None}.get(publication_mode or "", "SYNCHRONOUS")
    for kind, name in (
        ("participant", "vlocnetpp_participant"),
        ("data_writer", "vlocnetpp_writer"),
        ("data_reader", "vlocnetpp_reader"),
    ):
        found = [e for p in root.iter("profiles") for e in p.findall(kind)]
        if not any(e.get("is_default_profile", "").lower() == "true" for e in found):
            found.append(ET.SubElement(profiles, kind, {"profile_name": name, "is_default_profile": "true"}))
        for element in found:
            label = f"{kind} {element.get('profile_name', '?')}:"
            if kind == "participant":
                for policy in ("readerHistoryMemoryPolicy", "writerHistoryMemoryPolicy"):
                    _fill(element, ("rtps", "builtin", policy), REALLOC, kept, f"{label} {policy}")
                if not any(element.find(f"rtps/{tag}") is not None for tag in _TRANSPORT_TAGS):
                    if transports:
                        _add_transports(profiles, element)
                elif element.get("profile_name") != name:
                    kept.append(f"{label} transports")
                continue
            policy = READER_POLICY if kind == "data_reader" else REALLOC
            _fill(element, ("historyMemoryPolicy",), policy, kept, f"{label} historyMemoryPolicy")
            _fill(element, ("qos", "data_sharing", "kind"), "OFF", kept, f"{label} data_sharing")
            if kind == "data_writer" and mode is not None:
                _fill(element, ("qos", "publishMode", "kind"), mode, kept, f"{label} publishMode")
    ET.indent(root)
    return ET.ElementTree(root), kept


def apply(environ: MutableMapping[str, str] | None = None, cwd: Path | None = None) -> Applied:
    """Point this process's rmw_fastrtps at the merged profile (see the module doc); call before ``rclpy.init``."""
    environ = os.environ if environ is None else environ
    cwd = Path.cwd() if cwd is None else cwd
    rmw = environ.get("RMW_IMPLEMENTATION", "") or "rmw_fastrtps_cpp"
    if not rmw.startswith("rmw_fastrtps"):
        return Applied(f"RMW {rmw}: no Fast DDS profile applied")
    if USE_XML_ENV in environ:
        return Applied(
            f"{USE_XML_ENV}={environ[USE_XML_ENV]} is set: the Fast DDS QoS are left as configured "
            "(history memory policy not changed; see docs/node.md, 'Memory under bad input')"
        )
    files = user_files(environ, cwd)
    try:
        tree, kept = merged_profiles(
            files, environ.get("RMW_FASTRTPS_PUBLICATION_MODE"), transports=not environ.get(BUILTIN_TRANSPORTS_ENV)
        )
    except (OSError, ET.ParseError) as err:
        return Applied(
            f"cannot merge the Fast DDS profile {', '.join(map(str, files))} ({err}): used as it is, "
            "history memory policy not changed"
        )
    fd, name = tempfile.mkstemp(prefix="vlocnetpp_fastdds_", suffix=".xml")
    with os.fdopen(fd, "wb") as out:
        tree.write(out, encoding="UTF-8", xml_declaration=True)
    saved = {key: environ.get(key) for key in (PROFILES_ENV, USE_XML_ENV, SKIP_CWD_ENV)}
    environ.update({PROFILES_ENV: name, USE_XML_ENV: "1", SKIP_CWD_ENV: "1"})
    merged = f", merged with {', '.join(map(str, files))}" if files else ""
    ours = f"profiles/transport_descriptors/transport_descriptor[transport_id='{TRANSPORT_IDS[0]}']"
    segment = (
        f", shared-memory segment {SHM_SEGMENT_BYTES >> 20} MiB (large messages sent without delay)"
        if tree.getroot().find(ours) is not None
        else ""
    )
    kept_text = f"; kept the user's {'; '.join(kept)}" if kept else ""
    return Applied(
        f"Fast DDS: DataReaders use the {READER_POLICY} history memory policy (memory bounded under bursts from "
        f"deeper publishers){segment}{merged}{kept_text}",
        True,
        Path(name),
        saved,
        environ,
    )
