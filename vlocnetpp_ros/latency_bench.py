"""``python -m vlocnetpp_ros.latency_bench``: image-in -> pose-out latency of the real node over DDS,
interleaved with the bare :meth:`Localizer.step` on the same frames; what ``vlocnetpp bench`` runs
for ``node_latency_over_step`` (core never imports ROS, so this is a program of its own).

The node is the ``localizer`` program (as ``vlocnetpp replay --through-node`` starts it: see
:func:`vlocnetpp_ros.replay_bridge.localizer_command`) in a private namespace. Each round sends one
``rgb8`` frame (stamps 50 ms apart, so the temporal state carries on), waits for its
``PoseStamped`` (the latency: publish call to pose callback, both in this process) and for its
segmentation (the node has then finished the frame), and runs this process's own
:class:`Localizer` (same checkpoint, device, backend, threads) on the same frame; the order of the
two alternates each round so machine noise hits both alike. Frames before ``--warmup`` are not
counted. At the end the node's peak resident memory (``VmHWM``) is read from ``/proc``.

Transport (``--transport``): ``large_data`` (default) runs both sides with the shipped Fast DDS
profile ``config/fastdds_large_data.xml`` (shared memory for large messages; what docs/node.md
recommends for camera images), ``environment`` leaves the DDS settings of the environment as they are.

With ``--stream-hz R`` the node is then fed as a camera feeds it, without waiting for answers: frames at R per
second for ``--stream-s`` seconds; ``stream_answered_hz`` is the number of poses it published for them per second
(first frame sent to last pose received): the most frames a second the node gets through when R is above that.

Prints one JSON object: ``latency_s`` and ``step_s`` (lists, seconds per counted frame),
``node_peak_rss_mb``, ``node_rss_mb``, ``startup_s`` (and ``stream_answered_hz``, ``stream_sent``,
``refined_share``: the node's ``refined`` diagnostics after the stream, with a map). Exit code 2
with one line on stderr when the node cannot start or stops answering.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference.localizer import BACKENDS, Localizer
from vlocnetpp_core.threads import use_threads
from vlocnetpp_ros import conversions
from vlocnetpp_ros.dds_client import RELIABLE as _QOS
from vlocnetpp_ros.dds_client import DdsClient
from vlocnetpp_ros.replay_bridge import _NodeProcess, localizer_command, node_arguments

FRAME_INTERVAL_S = 0.05
PROFILE = "fastdds_large_data.xml"


def proc_status_mb(pid: int, key: str) -> float:
    """``VmHWM`` / ``VmRSS`` of a process in MiB (Linux ``/proc``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    raise UserError(f"no {key} in /proc/{pid}/status")


class _Probe(DdsClient):
    """Publisher of camera frames and recorder of the arrival time of the node's answers, by stamp."""

    def __init__(self, namespace: str):
        super().__init__("vlocnetpp_latency_bench", namespace)
        self.image_pub = self.node.create_publisher(Image, f"{namespace}/camera/image", _QOS)
        self.pose_at: dict[float, float] = {}
        self.diagnostics: dict[str, str] = {}  # the node's latest /diagnostics values
        self.seg_at: dict[float, float] = {}
        stamp_of = conversions.stamp_to_seconds
        self.subs = [
            self.node.create_subscription(
                PoseStamped,
                f"{namespace}/vlocnet/pose",
                lambda m: self.pose_at.setdefault(stamp_of(m.header.stamp), time.perf_counter()),
                _QOS,
            ),
            self.node.create_subscription(
                Image,
                f"{namespace}/vlocnet/segmentation",
                lambda m: self.seg_at.setdefault(stamp_of(m.header.stamp), time.perf_counter()),
                _QOS,
            ),
        ]
        self.node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: self._diagnostics(m, namespace), 10)

    def _diagnostics(self, msg: DiagnosticArray, namespace: str) -> None:
        for status in msg.status:
            if status.hardware_id == f"{namespace}/localizer":
                self.diagnostics = {kv.key: kv.value for kv in status.values}

    def connected(self) -> bool:
        return self.image_pub.get_subscription_count() > 0 and all(s.get_publisher_count() > 0 for s in self.subs)


def large_data_profile() -> Path:
    """``config/fastdds_large_data.xml`` of the installed package, else of the source tree."""
    candidates = []
    try:
        from ament_index_python.packages import get_package_share_directory

        candidates.append(Path(get_package_share_directory("vlocnetpp_ros")) / "config" / PROFILE)
    except Exception:  # PackageNotFoundError, or ament_index not importable
        pass
    candidates.append(Path(__file__).resolve().parents[1] / "config" / PROFILE)
    for path in candidates:
        if path.is_file():
            return path
    raise UserError(f"the Fast DDS profile {PROFILE} is missing (looked for {', '.join(map(str, candidates))})")


def measure(
    checkpoint: str,
    frames: np.ndarray,
    repetitions: int,
    warmup: int,
    device: str = "cpu",
    backend: str = "torch",
    num_threads: int = 0,
    transport: str = "large_data",
    startup_timeout_s: float = 120.0,
    answer_timeout_s: float = 30.0,
    map_path: str | None = None,
    refine_every: int = 1,
    stream_hz: float = 0.0,
    stream_s: float = 8.0,
) -> dict:
    """Run the node and the bare Localizer interleaved over ``frames (N, H, W, 3) uint8 RGB`` (cycled); see module doc.
    ``map_path``: both refine against this keyframe map every ``refine_every``-th frame; ``stream_hz`` > 0: then the
    node alone at that camera rate for ``stream_s`` seconds.

    ``transport="large_data"`` sets ``FASTRTPS_DEFAULT_PROFILES_FILE`` in this process (before its DDS
    participant exists) and so in the node's environment."""
    if transport == "large_data":
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(large_data_profile())
    elif transport != "environment":
        raise UserError(f"transport must be large_data or environment, got {transport!r}")
    namespace = f"/vlocnetpp_latency_{os.getpid()}"
    start = time.perf_counter()
    argv = localizer_command() + node_arguments(
        namespace, checkpoint, False, False, 1.0, device, map_path, refine_every
    )
    num_threads = use_threads(num_threads)  # the node resolves 0 the same way: both sides run alike
    argv += ["-p", f"backend:={backend}", "-p", f"num_threads:={num_threads}"]
    probe = _Probe(namespace)
    node = _NodeProcess(argv)
    try:
        while not probe.spin_until(time.monotonic() + 0.2, probe.connected):
            node.check_alive()
            if time.perf_counter() - start > startup_timeout_s:
                raise UserError(f"the localizer node did not connect within {startup_timeout_s:.0f} s:\n{node.tail()}")
        localizer = Localizer.from_checkpoint(
            checkpoint,
            device=device,
            num_threads=num_threads,
            backend=backend,
            map_path=map_path,
            refine_every=refine_every,
        )
        startup_s = time.perf_counter() - start
        latency, step = [], []
        for k in range(warmup + repetitions):
            image = frames[k % len(frames)]
            stamp = k * FRAME_INTERVAL_S
            msg = conversions.array_to_image(
                image, "rgb8", Header(stamp=conversions.seconds_to_stamp(stamp), frame_id="camera")
            )
            stamp = conversions.stamp_to_seconds(msg.header.stamp)
            if k % 2 == 0:
                node_s = _through_node(probe, node, msg, stamp, answer_timeout_s)
                bare_s = _bare(localizer, image, stamp)
            else:
                bare_s = _bare(localizer, image, stamp)
                node_s = _through_node(probe, node, msg, stamp, answer_timeout_s)
            if k >= warmup:
                latency.append(node_s)
                step.append(bare_s)
        streamed = _stream(probe, frames, warmup + repetitions, stream_hz, stream_s) if stream_hz > 0 else {}
        return {
            **streamed,
            "latency_s": latency,
            "step_s": step,
            "node_peak_rss_mb": proc_status_mb(node.proc.pid, "VmHWM"),
            "node_rss_mb": proc_status_mb(node.proc.pid, "VmRSS"),
            "startup_s": startup_s,
        }
    finally:
        node.stop()
        probe.close()


def _stream(probe: _Probe, frames: np.ndarray, first: int, rate_hz: float, seconds: float) -> dict:
    """Frames ``first, first + 1, ...`` published at ``rate_hz`` for ``seconds`` without waiting, then up to 2 s for
    the last answers, then the node's next diagnostics: ``{"stream_answered_hz", "stream_sent", "refined_share"}``
    (see the module docstring)."""
    count = max(2, round(rate_hz * seconds))
    stamps, start = [], time.monotonic()
    for i in range(count):
        probe.spin_until(start + i / rate_hz)
        stamp = (first + i) * FRAME_INTERVAL_S
        msg = conversions.array_to_image(
            frames[(first + i) % len(frames)],
            "rgb8",
            Header(stamp=conversions.seconds_to_stamp(stamp), frame_id="camera"),
        )
        stamps.append(conversions.stamp_to_seconds(msg.header.stamp))
        if i == 0:
            sent = time.perf_counter()
        probe.image_pub.publish(msg)
    probe.spin_until(time.monotonic() + 2.0, lambda: stamps[-1] in probe.pose_at)
    answered = [probe.pose_at[s] for s in stamps if s in probe.pose_at]
    span = max(answered) - sent if answered else float("inf")
    probe.diagnostics = {}
    probe.spin_until(time.monotonic() + 3.0, lambda: bool(probe.diagnostics))  # the node's next (1 Hz) diagnostics
    refined = probe.diagnostics.get("refined")
    return {
        "stream_answered_hz": len(answered) / span,
        "stream_sent": count,
        "refined_share": None if refined is None else float(refined),
    }


def _through_node(probe: _Probe, node: _NodeProcess, msg: Image, stamp: float, timeout_s: float) -> float:
    sent = time.perf_counter()
    probe.image_pub.publish(msg)
    if not probe.spin_until(time.monotonic() + timeout_s, lambda: stamp in probe.pose_at and stamp in probe.seg_at):
        node.check_alive()
        raise UserError(
            "the localizer node did not answer the frame stamped "
            f"{stamp:.3f} s within {timeout_s:.0f} s:\n{node.tail()}"
        )
    return probe.pose_at[stamp] - sent


def _bare(localizer: Localizer, image: np.ndarray, stamp: float) -> float:
    start = time.perf_counter()
    localizer.step(image, "rgb8", stamp)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vlocnetpp_ros.latency_bench", description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True, metavar="NAME.safetensors")
    parser.add_argument(
        "--frames", required=True, metavar="FRAMES.npy", help="(N, H, W, 3) uint8 RGB camera frames, cycled"
    )
    parser.add_argument("--repetitions", type=int, default=20, metavar="N", help="frames measured (default 20)")
    parser.add_argument(
        "--warmup", type=int, default=3, metavar="N", help="frames sent first and not measured (default 3)"
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--backend", choices=BACKENDS, default="torch")
    parser.add_argument(
        "--transport",
        choices=("large_data", "environment"),
        default="large_data",
        help="DDS settings of both sides: the shipped large-data Fast DDS profile (default) or the environment's",
    )
    parser.add_argument(
        "--num-threads",
        type=int,
        default=0,
        metavar="N",
        help="torch / ONNX Runtime threads of both sides (0: default)",
    )
    parser.add_argument(
        "--map", default=None, metavar="MAP.npz", help="keyframe map both sides refine against (default: none)"
    )
    parser.add_argument(
        "--refine-every", type=int, default=1, metavar="K", help="with --map: refine every K-th frame (default 1)"
    )
    parser.add_argument(
        "--stream-hz",
        type=float,
        default=0.0,
        metavar="R",
        help="then feed the node at R frames a second without waiting for answers (default 0: not done)",
    )
    parser.add_argument("--stream-s", type=float, default=8.0, metavar="S", help="seconds of --stream-hz (default 8)")
    args = parser.parse_args(argv)
    try:
        frames = np.load(args.frames)
        if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
            raise UserError(f"{args.frames}: expected (N, H, W, 3) uint8 frames, got {frames.shape} {frames.dtype}")
        result = measure(
            args.checkpoint,
            frames,
            args.repetitions,
            args.warmup,
            args.device,
            args.backend,
            args.num_threads,
            args.transport,
            map_path=args.map,
            refine_every=args.refine_every,
            stream_hz=args.stream_hz,
            stream_s=args.stream_s,
        )
    except UserError as err:
        print(f"latency_bench: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
