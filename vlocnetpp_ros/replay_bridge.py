"""``vlocnetpp replay --through-node``: play a bag to the real localizer node over DDS and record its answers.

The node (the ``localizer`` console script: next to ``sys.executable`` first, else the colcon
install tree, else ``python -m vlocnetpp_ros.node``) runs as a subprocess in a private namespace
``/vlocnetpp_replay_<pid>``, so a live camera or another replay on the same ROS domain is never
mixed in. This bridge publishes the bag's camera images (raw or compressed), ``CameraInfo`` and,
with ``use_depth``, depth to it as the stored CDR bytes (no re-encoding), and writes the output
bag as :func:`vlocnetpp_core.bag.replay.replay` does: the input topics plus what the node
published on ``vlocnet/pose``, ``vlocnet/pose_with_covariance``, ``vlocnet/odometry``, ``vlocnet/segmentation`` and,
with a keyframe map (``--map``, the node's parameter ``map``), ``vlocnet/network_pose`` (renamed to
``/vlocnet/*``), logged at the log time of the image they answer. The topics it waits for are derived
from the checkpoint (:func:`vlocnetpp_core.bag.replay.checkpoint_output_types`): a pose-only model's
node advertises no segmentation, so none is expected (a frame is answered by its three pose topics).

Pacing: at the bag's rate (image stamps mapped onto the wall clock; the node drops frames when
it is slower, as live), at a fixed ``rate_hz``, or with ``rate_hz = inf`` ("max") in lockstep:
the next image is published when the node answered the previous one, so every frame is processed
and the poses equal the in-process replay. The camera info is published (and given half a second
to arrive) before the first image, so the first frame already uses the bag's intrinsics.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter, deque
from contextlib import ExitStack
from pathlib import Path

from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from vlocnetpp_core.bag import messages, topics
from vlocnetpp_core.bag.bagfile import BagReader, BagWriter
from vlocnetpp_core.bag.replay import (
    ALL_OUTPUT_TYPES,
    ReplaySummary,
    checkpoint_output_types,
    choose_image_topic,
    copy_topics,
    groups_by_log_time,
)
from vlocnetpp_core.errors import DataError, UserError
from vlocnetpp_core.interrupts import sigterm_as_interrupt
from vlocnetpp_ros.dds_client import RECORD as _RECORD
from vlocnetpp_ros.dds_client import RELIABLE as _RELIABLE
from vlocnetpp_ros.dds_client import DdsClient

_OUTPUT_TYPES = {
    topics.POSE_TOPIC: PoseStamped,
    topics.POSE_WITH_COVARIANCE_TOPIC: PoseWithCovarianceStamped,
    topics.ODOMETRY_TOPIC: Odometry,
    topics.SEGMENTATION_TOPIC: Image,
    topics.NETWORK_POSE_TOPIC: PoseStamped,
}
CAMERA_INFO_SETTLE_S = 0.5


def localizer_command() -> list[str]:
    """How to start the node: the ``localizer`` script next to this Python, in the colcon install tree, or ``-m``."""
    exe = Path(sys.executable).parent / "localizer"
    if exe.is_file():
        return [str(exe)]
    try:
        from ament_index_python.packages import get_package_prefix

        installed = Path(get_package_prefix("vlocnetpp_ros")) / "lib" / "vlocnetpp_ros" / "localizer"
        if installed.is_file():
            return [str(installed)]
    except Exception:  # package not in AMENT_PREFIX_PATH, or ament_index not installed
        pass
    return [sys.executable, "-m", "vlocnetpp_ros.node"]


def node_arguments(
    namespace: str,
    checkpoint: str | Path,
    compressed: bool,
    use_depth: bool,
    max_gap_s: float,
    device: str,
    map_path: str | Path | None = None,
    refine_every: int = 1,
) -> list[str]:
    """``--ros-args`` for the node: inputs on ``<namespace>/camera/...``, outputs under ``<namespace>/vlocnet``;
    ``map_path``: the keyframe map to refine against every ``refine_every``-th frame (None: no refinement)."""
    params = {
        "checkpoint": str(Path(checkpoint).resolve()),
        "image_topic": f"{namespace}/camera/image",
        "use_compressed": "true" if compressed else "false",
        "camera_info_topic": f"{namespace}/camera/camera_info",
        "depth_topic": f"{namespace}/camera/depth" if use_depth else "",
        "max_gap_s": repr(float(max_gap_s)),
        "device": device,
        "map": "" if map_path is None else str(Path(map_path).resolve()),
        "refine_every": str(int(refine_every)),
    }
    args = ["--ros-args", "-r", f"__ns:={namespace}"]
    for name, value in params.items():
        args += ["-p", f"{name}:={value}" if value != "" else f"{name}:=''"]
    return args


def _die_with_parent() -> None:
    """In the child before exec (Linux): SIGTERM when the replay process dies, even by SIGKILL (no orphan node)."""
    import ctypes

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


class _NodeProcess:
    """The localizer subprocess; its output goes to a log file quoted when it fails."""

    def __init__(self, argv: list[str], env: dict[str, str] | None = None):
        self.log = tempfile.TemporaryFile(mode="w+b")
        self.proc = subprocess.Popen(
            argv,
            stdout=self.log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            preexec_fn=_die_with_parent if sys.platform == "linux" else None,
        )

    def tail(self, lines: int = 15) -> str:
        self.log.seek(0)
        return "\n".join(self.log.read().decode(errors="replace").splitlines()[-lines:])

    def check_alive(self) -> None:
        if self.proc.poll() is not None:
            raise UserError(f"the localizer node exited with code {self.proc.returncode}:\n{self.tail()}")

    def stop(self, timeout_s: float = 10.0) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


class _Bridge(DdsClient):
    """The rclpy side: publishers to the node, raw subscriptions to its outputs, spun from the caller's thread."""

    def __init__(self, namespace: str, compressed: bool, use_depth: bool, outputs: dict[str, str]):
        """``outputs``: the ``/vlocnet/*`` topics the node publishes for this checkpoint
        (``checkpoint_output_types``)."""
        super().__init__("vlocnetpp_replay_bridge", namespace)
        image_type = CompressedImage if compressed else Image
        self.image_pub = self.node.create_publisher(
            image_type, f"{namespace}/camera/image" + ("/compressed" if compressed else ""), _RELIABLE
        )
        self.info_pub = self.node.create_publisher(CameraInfo, f"{namespace}/camera/camera_info", _RELIABLE)
        self.depth_pub = (
            self.node.create_publisher(Image, f"{namespace}/camera/depth", _RELIABLE) if use_depth else None
        )
        self.received: deque[tuple[str, bytes]] = deque()
        self.subs = [
            self.node.create_subscription(
                msg_type,
                f"{namespace}{topic}",
                lambda data, topic=topic: self.received.append((topic, data)),
                _RECORD,
                raw=True,
            )
            for topic, msg_type in _OUTPUT_TYPES.items()
            if topic in outputs
        ]

    def connected(self) -> bool:
        pubs = [p for p in (self.image_pub, self.info_pub, self.depth_pub) if p is not None]
        return all(p.get_subscription_count() > 0 for p in pubs) and all(s.get_publisher_count() > 0 for s in self.subs)


def replay_through_node(
    bag: str | Path,
    out: str | Path,
    checkpoint: str | Path,
    image_topic: str | None = None,
    rate_hz: float | None = None,
    max_gap_s: float = 1.0,
    use_depth: bool = False,
    device: str = "cpu",
    force: bool = False,
    progress: bool = True,
    startup_timeout_s: float = 120.0,
    answer_timeout_s: float = 30.0,
    quiet_s: float = 3.0,
    map_path: str | Path | None = None,
    refine_every: int = 1,
) -> ReplaySummary:
    """Replay ``bag`` through the node into ``out`` (see module doc).

    ``map_path``: a keyframe map file the node refines against every ``refine_every``-th frame (None: none).
    ``rate_hz``: None (the bag's rate), Hz, or ``math.inf`` (lockstep). In lockstep a frame the
    node does not answer within ``answer_timeout_s`` is counted as skipped (``no_answer``); when
    paced, the replay ends once every frame is answered or nothing arrived for ``quiet_s``
    (frames the node dropped or rejected are counted as ``dropped_or_rejected``).
    """
    from tqdm import tqdm

    summary = ReplaySummary(Path(out))
    namespace = f"/vlocnetpp_replay_{os.getpid()}"
    start = time.perf_counter()
    outputs = checkpoint_output_types(
        checkpoint, map_path is not None
    )  # a clear error now rather than a node that fails to start
    with sigterm_as_interrupt(), BagReader(bag) as reader, ExitStack() as stack:
        topic = choose_image_topic(reader.topics, image_topic, reader.path)
        compressed = reader.topics[topic] == messages.COMPRESSED_IMAGE
        if use_depth and topics.DEPTH_TOPIC not in reader.topics:
            raise DataError(reader.path, f"--use-depth: the bag has no {topics.DEPTH_TOPIC} topic")
        writer = BagWriter(out, force=force)  # refuses an existing output before the node starts
        bridge = _Bridge(namespace, compressed, use_depth, outputs)
        stack.callback(bridge.close)
        node = _NodeProcess(
            localizer_command()
            + node_arguments(namespace, checkpoint, compressed, use_depth, max_gap_s, device, map_path, refine_every)
        )
        stack.callback(node.stop)
        bar = stack.enter_context(
            tqdm(total=reader.count(topic), unit="frame", desc="replay (node)", disable=not progress, file=sys.stderr)
        )
        deadline = time.monotonic() + startup_timeout_s
        while not bridge.spin_until(min(deadline, time.monotonic() + 0.2), bridge.connected):
            node.check_alive()
            if time.monotonic() > deadline:
                raise UserError(f"the localizer node did not connect within {startup_timeout_s:.0f} s:\n{node.tail()}")
        summary.startup_s = time.perf_counter() - start
        with writer:
            copy_topics(reader, writer, outputs)
            player = _Player(reader, writer, bridge, node, topic, use_depth, summary, bar, len(outputs))
            player.play(rate_hz, answer_timeout_s)
            player.finish(answer_timeout_s, quiet_s)
        summary.wall_s = time.perf_counter() - start - summary.startup_s
    return summary


class _Player:
    """Publishes the bag's frames to the node, paced, and writes the inputs and the node's answers."""

    def __init__(
        self,
        reader: BagReader,
        writer: BagWriter,
        bridge: _Bridge,
        node: _NodeProcess,
        topic: str,
        use_depth: bool,
        summary: ReplaySummary,
        bar,
        n_outputs: int,
    ):
        """``n_outputs``: how many output topics answer one frame."""
        self.reader, self.writer, self.bridge, self.node = reader, writer, bridge, node
        self.n_outputs = n_outputs
        self.topic, self.use_depth, self.summary, self.bar = topic, use_depth, summary, bar
        self.log_time_of: dict[int, int] = {}  # image stamp -> log time of the image in the bag
        self.answered: Counter = Counter()  # image stamp -> output topics received
        self.published = 0
        self.last_answer = time.monotonic()

    def record(self) -> None:
        """Write what the node published since the last call."""
        while self.bridge.received:
            out_topic, data = self.bridge.received.popleft()
            ns = messages.stamp_ns(messages.deserialize(data, ALL_OUTPUT_TYPES[out_topic]))
            self.writer.write_raw(out_topic, self.log_time_of.get(ns, ns), data)
            self.answered[ns] += 1
            self.last_answer = time.monotonic()
            if self.answered[ns] == self.n_outputs:
                self.summary.processed += 1
                self.bar.update(1)

    def _answered(self, stamp: int) -> bool:
        self.record()
        return self.answered[stamp] >= self.n_outputs

    def play(self, rate_hz: float | None, answer_timeout_s: float) -> None:
        bridge, bag_topics = self.bridge, self.reader.topics  # not ``topics``: that is the module of topic names
        first_info = True
        clock_start: tuple[float, int] | None = None  # (monotonic time, stamp ns) of the first image
        for group in groups_by_log_time(self.reader.messages(raw=True)):
            for t, ns, raw in group:
                if t in ALL_OUTPUT_TYPES:
                    continue
                self.writer.write_raw(t, ns, raw)
                if t == topics.CAMERA_INFO_TOPIC:
                    bridge.info_pub.publish(bytes(raw))
                    if first_info:  # let the node take the intrinsics before the first image
                        first_info = False
                        bridge.spin_until(time.monotonic() + CAMERA_INFO_SETTLE_S)
                elif t == topics.DEPTH_TOPIC and self.use_depth:
                    bridge.depth_pub.publish(bytes(raw))
            for t, ns, raw in group:
                if t != self.topic:
                    continue
                stamp = messages.stamp_ns(messages.deserialize(raw, bag_topics[t]))
                self.log_time_of[stamp] = ns
                if clock_start is None:
                    clock_start = (time.monotonic(), stamp)
                elif rate_hz is None:
                    bridge.spin_until(clock_start[0] + (stamp - clock_start[1]) / 1e9)
                elif math.isfinite(rate_hz):
                    bridge.spin_until(clock_start[0] + self.published / rate_hz)
                self.node.check_alive()
                bridge.image_pub.publish(bytes(raw))
                self.published += 1
                if rate_hz is not None and math.isinf(rate_hz):
                    if not bridge.spin_until(time.monotonic() + answer_timeout_s, lambda s=stamp: self._answered(s)):
                        self.summary.skipped["no_answer"] += 1
                        self.bar.update(1)
                self.record()

    def finish(self, answer_timeout_s: float, quiet_s: float) -> None:
        """Wait for the answers to the last frames: all in, or ``quiet_s`` without any (capped by
        ``answer_timeout_s``)."""
        deadline = time.monotonic() + answer_timeout_s
        self.last_answer = time.monotonic()

        def settled() -> bool:
            self.record()
            done = self.summary.processed + sum(self.summary.skipped.values()) >= self.published
            return done or time.monotonic() - self.last_answer > quiet_s

        self.bridge.spin_until(deadline, settled)
        self.record()
        missing = self.published - self.summary.processed - sum(self.summary.skipped.values())
        if missing > 0:
            self.summary.skipped["dropped_or_rejected"] += missing


def main(argv: list[str] | None = None) -> int:
    """``python -m vlocnetpp_ros.replay_bridge``: what ``vlocnetpp replay --through-node`` runs (same flags)."""
    import argparse

    from vlocnetpp_core.bag.replay_cli import add_arguments, map_argument, parse_rate
    from vlocnetpp_core.errors import UserError

    parser = argparse.ArgumentParser(prog="vlocnetpp replay --through-node", description=__doc__.splitlines()[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        summary = replay_through_node(
            args.bag,
            args.out,
            args.checkpoint,
            image_topic=args.image_topic,
            rate_hz=parse_rate(args.rate),
            max_gap_s=args.max_gap_s,
            use_depth=args.use_depth,
            device=args.device,
            force=args.force,
            progress=not args.no_progress,
            map_path=map_argument(args),
            refine_every=args.refine_every,
        )
    except UserError as err:
        print(f"vlocnetpp replay: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    print(summary.format())
    return 0


if __name__ == "__main__":
    sys.exit(main())
