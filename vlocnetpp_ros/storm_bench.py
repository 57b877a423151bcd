"""``python -m vlocnetpp_ros.storm_bench``: the localizer node's resident memory over storms of malformed messages
from publishers of a chosen reliability and history depth.

A benchmark, not a test (``test/test_node_storm.py`` is the test). For each publisher kind
(``--publisher reliable:50``, ``best_effort:1``, ...) and input (``--input raw``: image, depth and
camera info; ``compressed``: ``CompressedImage``) it starts a fresh node (the ``localizer`` program
of ``--install PREFIX``, a colcon install tree, else as :func:`vlocnetpp_ros.replay_bridge.localizer_command`
finds it), sends ``--storms`` storms of ``--messages`` malformed messages of every class of
:mod:`vlocnetpp_ros.storm` for that input (a good frame every ``--good-every``; a pause of ``--pause-ms``
after every 10 messages), checks after each storm that the node answers a good frame (resent until
answered: best-effort frames may be lost), waits for the node's once-a-second heap trim and reads
its ``VmRSS``. Prints a Markdown table (also ``storm_bench.md`` and ``storm_bench.json`` in ``--out``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference.checkpoint import shipped_checkpoint
from vlocnetpp_ros import conversions, storm
from vlocnetpp_ros.dds_client import RECORD, DdsClient
from vlocnetpp_ros.latency_bench import proc_status_mb
from vlocnetpp_ros.replay_bridge import _NodeProcess, localizer_command, node_arguments

INPUTS = {"raw": ("image", "depth", "camera_info"), "compressed": ("compressed",)}
TRIM_WAIT_S = 2.5  # the node trims its heap once a second, after its diagnostics
STRANGE_STAMPS = ("stamp_zero", "stamp_backwards", "stamp_far_future")


@dataclass(frozen=True)
class PublisherKind:
    """A publisher's reliability and keep-last history depth, written ``reliable:50`` / ``best_effort:1``."""

    reliability: str  # "reliable" or "best_effort"
    depth: int

    @classmethod
    def parse(cls, text: str) -> PublisherKind:
        name, _, depth = text.partition(":")
        if name not in ("reliable", "best_effort") or not depth.isdigit() or int(depth) < 1:
            raise UserError(f"publisher kind {text!r}: expected reliable:DEPTH or best_effort:DEPTH with DEPTH >= 1")
        return cls(name, int(depth))

    def qos(self) -> QoSProfile:
        reliability = ReliabilityPolicy.RELIABLE if self.reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.depth, reliability=reliability)

    def __str__(self) -> str:
        return f"{self.reliability}:{self.depth}"


class StormPublisher(DdsClient):
    """Publishers of one kind to a node's inputs under ``namespace`` and the stamps of the node's poses."""

    def __init__(self, namespace: str, kind: PublisherKind, inputs: str, width: int, height: int, seed: int = 0):
        super().__init__("vlocnetpp_storm", namespace)
        topics = {
            "image": (Image, "camera/image"),
            "depth": (Image, "camera/depth"),
            "camera_info": (CameraInfo, "camera/camera_info"),
            "compressed": (CompressedImage, "camera/image/compressed"),
        }
        self.pubs = {
            k: self.node.create_publisher(topics[k][0], f"{namespace}/{topics[k][1]}", kind.qos())
            for k in INPUTS[inputs]
        }
        self.poses: set[float] = set()
        self.sub = self.node.create_subscription(
            PoseStamped,
            f"{namespace}/vlocnet/pose",
            lambda m: self.poses.add(conversions.stamp_to_seconds(m.header.stamp)),
            RECORD,
        )
        rng = np.random.default_rng(seed)
        base = cv2.resize(
            rng.integers(0, 256, (height // 8 + 4, width // 8 + 4, 3), dtype=np.uint8), (width + 32, height + 16)
        )
        self.frames = [np.ascontiguousarray(base[k : k + height, 2 * k : 2 * k + width]) for k in range(8)]
        self.metres = np.full((height, width), 3.0, np.float32)
        self.size = (width, height)
        self.stamp = 10.0
        self.sent = 0

    def connected(self) -> bool:
        return all(p.get_subscription_count() > 0 for p in self.pubs.values()) and self.sub.get_publisher_count() > 0

    def good(self, gap_s: float = 0.05) -> float:
        """A good frame (with its depth when the node takes depth), ``gap_s`` after the last stamp; returns its
        stamp."""
        self.stamp += gap_s
        header = Header(stamp=conversions.seconds_to_stamp(self.stamp), frame_id="camera")
        frame = self.frames[int(self.stamp * 20) % len(self.frames)]
        if "compressed" in self.pubs:
            ok, png = cv2.imencode(".png", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            self.pubs["compressed"].publish(CompressedImage(header=header, format="png", data=png.tobytes()))
        else:
            self.pubs["depth"].publish(conversions.array_to_image(self.metres, "32FC1", header))
            self.pubs["image"].publish(conversions.array_to_image(frame, "rgb8", header))
        return conversions.stamp_to_seconds(header.stamp)  # as the pose's stamp reads back

    def storm(self, rng: np.random.Generator, count: int, good_every: int, pause_s: float) -> None:
        """``count`` malformed messages of every class of the inputs, a good frame every ``good_every``."""
        classes = storm.classes_for(list(self.pubs))
        for i, (cls, msg) in enumerate(storm.bad_messages(rng, classes, count, 0.0, *self.size)):
            if i % good_every == 0:
                self.good()
            if cls.name not in STRANGE_STAMPS:
                msg.header.stamp = conversions.seconds_to_stamp(self.stamp)
            elif cls.name == "stamp_backwards":
                msg.header.stamp = conversions.seconds_to_stamp(self.stamp - 3.0)
            self.pubs[cls.kind].publish(msg)
            self.sent += 1
            if i % 10 == 9:
                self.spin_until(time.monotonic() + pause_s)

    def answered(self, node: _NodeProcess, timeout_s: float = 60.0) -> float:
        """Send good frames (after a stamp gap: localised from the image alone) until the node answers one;
        returns the seconds it took. Raises :class:`UserError` when the node died or did not answer."""
        start = time.monotonic()
        while time.monotonic() - start < timeout_s:
            node.check_alive()
            stamp = self.good(gap_s=100.0)
            if self.spin_until(time.monotonic() + 2.0, lambda stamp=stamp: stamp in self.poses):
                return time.monotonic() - start
        raise UserError(f"the node did not answer a good frame within {timeout_s:.0f} s:\n{node.tail()}")


def run_kind(
    kind: PublisherKind,
    inputs: str,
    checkpoint: str | Path,
    storms: int,
    messages: int,
    width: int,
    height: int,
    good_every: int = 50,
    pause_s: float = 0.02,
    seed: int = 0,
    command: list[str] | None = None,
    env: dict[str, str] | None = None,
    startup_timeout_s: float = 120.0,
) -> dict:
    """One node, one publisher kind: ``{"rss_mb": [start, after storm 1, ...], "answer_s": [...], ...}``."""
    namespace = f"/vlocnetpp_storm_{os.getpid()}"
    argv = (command or localizer_command()) + node_arguments(
        namespace, checkpoint, inputs == "compressed", inputs == "raw", 1.0, "cpu"
    )
    argv += ["-p", "num_threads:=1"]
    pub = StormPublisher(namespace, kind, inputs, width, height, seed)
    node = _NodeProcess(argv, env=env)
    rng = np.random.default_rng(seed)
    try:
        start = time.monotonic()
        while not pub.spin_until(time.monotonic() + 0.2, pub.connected):
            node.check_alive()
            if time.monotonic() - start > startup_timeout_s:
                raise UserError(f"the localizer node did not connect within {startup_timeout_s:.0f} s:\n{node.tail()}")
        answer_s = [pub.answered(node)]
        pub.spin_until(time.monotonic() + TRIM_WAIT_S)
        rss = [proc_status_mb(node.proc.pid, "VmRSS")]
        storm_s = []
        for _ in range(storms):
            t0 = time.monotonic()
            pub.storm(rng, messages, good_every, pause_s)
            storm_s.append(time.monotonic() - t0)
            answer_s.append(pub.answered(node))
            pub.spin_until(time.monotonic() + TRIM_WAIT_S)
            rss.append(proc_status_mb(node.proc.pid, "VmRSS"))
        return {
            "publisher": str(kind),
            "input": inputs,
            "rss_mb": rss,
            "answer_s": answer_s,
            "storm_s": storm_s,
            "peak_rss_mb": proc_status_mb(node.proc.pid, "VmHWM"),
            "messages_sent": pub.sent,
            "alive": node.proc.poll() is None,
        }
    finally:
        node.stop()
        pub.close()


def table(results: list[dict]) -> str:
    """The runs as a Markdown table: RSS at the start and after each storm, growth after the first storm."""
    rows = [
        "| publisher | input | RSS start, after storms 1.. (MiB) | growth after storm 1 (MiB) | answered after each |",
        "|---|---|---|---|---|",
    ]
    for r in results:
        rss = r["rss_mb"]
        rows.append(
            f"| {r['publisher']} | {r['input']} | {', '.join(f'{v:.0f}' for v in rss)} | {rss[-1] - rss[1]:+.0f} | "
            f"{'yes' if r['alive'] else 'no'} |"
        )
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m vlocnetpp_ros.storm_bench", description=__doc__.splitlines()[0])
    p.add_argument(
        "--publisher",
        action="append",
        default=None,
        metavar="reliable:50",
        help="reliability:depth of the storming publisher (repeatable; default reliable:50)",
    )
    p.add_argument(
        "--input", action="append", choices=sorted(INPUTS), default=None, help="node inputs (repeatable; default raw)"
    )
    p.add_argument("--storms", type=int, default=4)
    p.add_argument("--messages", type=int, default=10_000, help="malformed messages per storm (default 10,000)")
    p.add_argument("--good-every", type=int, default=50)
    p.add_argument(
        "--pause-ms",
        type=float,
        default=0.0,
        help="pause after every 10 messages (default 0: as fast as the publisher can)",
    )
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--checkpoint", default=None, help="default: the shipped lite model")
    p.add_argument("--install", default=None, metavar="PREFIX", help="run the node of this colcon install tree")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, metavar="DIR", help="writes storm_bench.json and storm_bench.md here")
    args = p.parse_args(argv)
    try:
        if min(args.storms, args.messages, args.good_every, args.width, args.height) < 1 or args.pause_ms < 0:
            raise UserError("need positive --storms, --messages, --good-every and frame size, and --pause-ms >= 0")
        kinds = [PublisherKind.parse(k) for k in (args.publisher or ["reliable:50"])]
        command, env = _install_command(Path(args.install)) if args.install else (None, None)
        checkpoint = args.checkpoint or shipped_checkpoint()
        results = []
        for kind in kinds:
            for inputs in args.input or ["raw"]:
                results.append(
                    run_kind(
                        kind,
                        inputs,
                        checkpoint,
                        args.storms,
                        args.messages,
                        args.width,
                        args.height,
                        args.good_every,
                        args.pause_ms / 1000.0,
                        args.seed,
                        command,
                        env,
                    )
                )
                print(table(results[-1:]).splitlines()[-1], flush=True)
    except (UserError, FileNotFoundError) as err:
        print(f"storm_bench: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    text = table(results)
    print(text)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "storm_bench.json").write_text(json.dumps({"settings": vars(args), "results": results}, indent=1))
        (out / "storm_bench.md").write_text(text + "\n")
    return 0


def _install_command(install: Path) -> tuple[list[str], dict[str, str]]:
    """The ``localizer`` program of a colcon install tree and the environment ``source setup.bash`` would give it."""
    prefix = install / "vlocnetpp_ros"
    exe = prefix / "lib" / "vlocnetpp_ros" / "localizer"
    sites = sorted((prefix / "lib").glob("python3*/site-packages"))
    if not exe.is_file() or not sites:
        raise UserError(f"{install} is not a colcon install tree of vlocnetpp_ros (no {exe})")
    env = dict(os.environ)
    env["PYTHONPATH"] = f"{sites[0]}:{env.get('PYTHONPATH', '')}".rstrip(":")
    env["AMENT_PREFIX_PATH"] = f"{prefix}:{env.get('AMENT_PREFIX_PATH', '')}".rstrip(":")
    return [str(exe)], env


if __name__ == "__main__":
    sys.exit(main())
