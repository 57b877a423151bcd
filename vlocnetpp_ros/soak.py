"""``python -m vlocnetpp_ros.soak``: the localizer node fed at camera rate for minutes with good and bad frames.

A benchmark, not a test: it starts the real node (the ``localizer`` program, as
:func:`vlocnetpp_ros.replay_bridge.localizer_command` finds it) in a private namespace with a depth
and a camera info topic, and every ``1 / rate_hz`` seconds sends either a good camera frame with
its depth image (stamps advance at the camera rate) or, with probability ``bad_fraction``, one
malformed message of a class of :mod:`vlocnetpp_ros.storm` on the image, depth or camera info
topic. It records when each good frame's ``PoseStamped`` comes back (latency: publish call to pose
callback, both in this process), samples the node's resident memory (``VmRSS``) every
``sample_s`` seconds, and reads the node's last ``/diagnostics``. The feeder publishes with the project's Fast DDS
profile (:class:`vlocnetpp_ros.dds_client.DdsClient`: an 8 MiB shared-memory segment, as a camera driver should
have for 640x480 images, docs/node.md "Camera transport").

Writes into ``--out``: ``soak.json`` (every figure and sample), ``soak.md`` (the table, also
printed) and ``soak.png`` (RSS and latency over time). A good frame without an answer was dropped
(by the node's one-slot mailbox when it was busy, or by the transport). The machine's load average
is recorded at the start and the end: other work on the CPU (a training job, ...) shows in latency
and drops, so quote it with the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from vlocnetpp_core.bag import topics
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference.checkpoint import shipped_checkpoint
from vlocnetpp_core.inference.localizer import BACKENDS
from vlocnetpp_ros import conversions, storm
from vlocnetpp_ros.dds_client import RECORD as _RECORD
from vlocnetpp_ros.dds_client import RELIABLE as _QOS
from vlocnetpp_ros.dds_client import DdsClient
from vlocnetpp_ros.latency_bench import proc_status_mb
from vlocnetpp_ros.replay_bridge import _NodeProcess, localizer_command, node_arguments


class _Feeder(DdsClient):
    """Publishers to the node (image, depth, camera info) and the arrival times of its poses and diagnostics."""

    def __init__(self, namespace: str):
        super().__init__("vlocnetpp_soak", namespace)
        self.pubs = {
            "image": self.node.create_publisher(Image, f"{namespace}/camera/image", _QOS),
            "depth": self.node.create_publisher(Image, f"{namespace}/camera/depth", _QOS),
            "camera_info": self.node.create_publisher(CameraInfo, f"{namespace}/camera/camera_info", _QOS),
        }
        self.pose_at: dict[float, float] = {}
        self.diagnostics: dict[str, str] = {}
        hardware_id = f"{namespace}/localizer"
        self.subs = [
            self.node.create_subscription(
                PoseStamped,
                f"{namespace}/vlocnet/pose",
                lambda m: self.pose_at.setdefault(conversions.stamp_to_seconds(m.header.stamp), time.monotonic()),
                _RECORD,
            ),
            self.node.create_subscription(
                DiagnosticArray, topics.DIAGNOSTICS_TOPIC, lambda m: self._diagnostics(m, hardware_id), 10
            ),
        ]

    def _diagnostics(self, msg: DiagnosticArray, hardware_id: str) -> None:
        for status in msg.status:
            if status.hardware_id == hardware_id:
                self.diagnostics = {kv.key: kv.value for kv in status.values}

    def connected(self) -> bool:
        return (
            all(p.get_subscription_count() > 0 for p in self.pubs.values()) and self.subs[0].get_publisher_count() > 0
        )


def _camera(width: int, height: int, seed: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
    """A few smooth RGB frames (cycled) and a depth image in metres with an invalid band."""
    rng = np.random.default_rng(seed)
    base = cv2.resize(
        rng.integers(0, 256, (height // 8 + 4, width // 8 + 4, 3), dtype=np.uint8), (width + 64, height + 32)
    )
    frames = [np.ascontiguousarray(base[k : k + height, 2 * k : 2 * k + width]) for k in range(16)]
    depth = np.full((height, width), 4.0, np.float32)
    depth[: height // 4] = 0.0
    return frames, depth


def run(
    checkpoint: str | Path,
    minutes: float,
    rate_hz: float,
    bad_fraction: float,
    width: int,
    height: int,
    backend: str = "torch",
    num_threads: int = 0,
    sample_s: float = 10.0,
    seed: int = 0,
    warmup_s: float = 60.0,
    startup_timeout_s: float = 120.0,
) -> dict:
    """Feed the node for ``minutes`` (see module doc); returns every figure and sample. The RSS "start"
    figure is the first sample after ``warmup_s`` (the transport's buffers and the model's grow until then)."""
    namespace = f"/vlocnetpp_soak_{os.getpid()}"
    argv = localizer_command() + node_arguments(namespace, checkpoint, False, True, 1.0, "cpu")
    argv += ["-p", f"backend:={backend}", "-p", f"num_threads:={num_threads}"]
    feeder = _Feeder(namespace)
    node = _NodeProcess(argv)
    rng = np.random.default_rng(seed)
    frames, metres = _camera(width, height, seed)
    classes = storm.classes_for(["image", "depth", "camera_info"])
    try:
        start = time.monotonic()
        while not feeder.spin_until(time.monotonic() + 0.2, feeder.connected):
            node.check_alive()
            if time.monotonic() - start > startup_timeout_s:
                raise UserError(f"the localizer node did not connect within {startup_timeout_s:.0f} s:\n{node.tail()}")
        sent: dict[float, float] = {}  # stamp -> publish time of the good frames
        bad_sent: dict[str, int] = {}
        samples: list[dict] = []
        load_start = os.getloadavg()
        t0 = next_tick = next_sample = time.monotonic()
        k = 0
        while next_tick < t0 + 60.0 * minutes:
            stamp = 100.0 + k / rate_hz
            if rng.random() < bad_fraction:
                cls = classes[int(rng.integers(len(classes)))]
                msg = cls.make(rng, stamp, width, height)
                if conversions.stamp_to_seconds(msg.header.stamp) in sent:  # stamp_backwards: off the camera's grid,
                    msg.header.stamp = (
                        conversions.seconds_to_stamp(  # so that its answer is never taken for a good frame's
                            conversions.stamp_to_seconds(msg.header.stamp) + 0.5 / rate_hz
                        )
                    )
                feeder.pubs[cls.kind].publish(msg)
                bad_sent[cls.name] = bad_sent.get(cls.name, 0) + 1
            else:
                header = Header(stamp=conversions.seconds_to_stamp(stamp), frame_id="camera")
                feeder.pubs["depth"].publish(conversions.array_to_image(metres, "32FC1", header))
                image = conversions.array_to_image(frames[k % len(frames)], "rgb8", header)
                sent[conversions.stamp_to_seconds(header.stamp)] = time.monotonic()
                feeder.pubs["image"].publish(image)
            k += 1
            if time.monotonic() >= next_sample:
                node.check_alive()
                samples.append(
                    {
                        "t_s": time.monotonic() - t0,
                        "rss_mb": proc_status_mb(node.proc.pid, "VmRSS"),
                        "answered": len(feeder.pose_at),
                        "sent": len(sent),
                    }
                )
                next_sample += sample_s
            next_tick += 1.0 / rate_hz
            feeder.spin_until(next_tick)
        feeder.spin_until(time.monotonic() + 5.0)  # the last answers and diagnostics
        samples.append(
            {
                "t_s": time.monotonic() - t0,
                "rss_mb": proc_status_mb(node.proc.pid, "VmRSS"),
                "answered": len(feeder.pose_at),
                "sent": len(sent),
            }
        )
        return _summary(
            sent,
            feeder.pose_at,
            bad_sent,
            samples,
            feeder.diagnostics,
            load_start,
            os.getloadavg(),
            dict(
                minutes=minutes,
                rate_hz=rate_hz,
                bad_fraction=bad_fraction,
                width=width,
                height=height,
                backend=backend,
                num_threads=num_threads,
                checkpoint=str(checkpoint),
                warmup_s=warmup_s,
            ),
            proc_status_mb(node.proc.pid, "VmHWM"),
        )
    finally:
        node.stop()
        feeder.close()


def _summary(
    sent: dict[float, float],
    pose_at: dict[float, float],
    bad_sent: dict[str, int],
    samples: list[dict],
    diagnostics: dict[str, str],
    load_start,
    load_end,
    settings: dict,
    peak_rss_mb: float,
) -> dict:
    answered = {s: pose_at[s] - t for s, t in sent.items() if s in pose_at}
    latency_ms = 1000.0 * np.array([answered[s] for s in sorted(answered)])

    def pct(q: float) -> float | None:
        return float(np.percentile(latency_ms, q)) if len(latency_ms) else None

    return {
        "settings": settings,
        "good_frames_sent": len(sent),
        "answered": len(answered),
        "dropped": len(sent) - len(answered),
        "bad_messages_sent": sum(bad_sent.values()),
        "bad_by_class": dict(sorted(bad_sent.items())),
        "latency_ms_p50": pct(50),
        "latency_ms_p99": pct(99),
        "latency_ms_max": float(latency_ms.max()) if len(latency_ms) else None,
        "latency_ms": latency_ms.round(2).tolist(),
        "latency_t_s": [sent[s] - min(sent.values()) for s in sorted(answered)],
        "rss_mb_start": next(s["rss_mb"] for s in samples if s["t_s"] >= min(settings["warmup_s"], samples[-1]["t_s"])),
        "rss_mb_end": samples[-1]["rss_mb"],
        "rss_mb_max": max(s["rss_mb"] for s in samples),
        "node_peak_rss_mb": peak_rss_mb,
        "samples": samples,
        "node_diagnostics": {
            k: v
            for k, v in diagnostics.items()
            if k.split(".")[0] in ("received", "processed", "dropped", "rejected", "ignored", "resets", "reset")
        },
        "loadavg_start": list(load_start),
        "loadavg_end": list(load_end),
    }


def table(result: dict) -> str:
    """The figures as a Markdown table."""
    s = result["settings"]
    rows = [
        (
            "run",
            f"{s['minutes']:g} min at {s['rate_hz']:g} Hz, {s['width']}x{s['height']} rgb8 + 32FC1 depth, "
            f"{100 * s['bad_fraction']:.0f}% bad messages, backend {s['backend']}",
        ),
        (
            "good frames sent / answered / dropped",
            f"{result['good_frames_sent']} / {result['answered']} / {result['dropped']}",
        ),
        ("bad messages sent", str(result["bad_messages_sent"])),
        (
            "latency p50 / p99 / max (ms)",
            " / ".join(
                "-" if result[k] is None else f"{result[k]:.0f}"
                for k in ("latency_ms_p50", "latency_ms_p99", "latency_ms_max")
            ),
        ),
        (
            f"node RSS after {s['warmup_s']:g} s / end / max (MiB)",
            f"{result['rss_mb_start']:.0f} / {result['rss_mb_end']:.0f} / {result['rss_mb_max']:.0f}",
        ),
        ("node diagnostics", ", ".join(f"{k} {v}" for k, v in result["node_diagnostics"].items())),
        (
            "load average start / end",
            f"{result['loadavg_start'][0]:.2f} / {result['loadavg_end'][0]:.2f} ({os.cpu_count()} CPUs)",
        ),
    ]
    return "\n".join(["| figure | value |", "|---|---|", *(f"| {a} | {b} |" for a, b in rows)])


def plot(result: dict, path: Path) -> None:
    """RSS (MiB) and latency (ms, each answered frame) over the run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    top.plot([s["t_s"] / 60 for s in result["samples"]], [s["rss_mb"] for s in result["samples"]], marker=".")
    top.set_ylabel("node RSS (MiB)")
    top.set_title(
        f"soak: {result['answered']} of {result['good_frames_sent']} good frames answered, "
        f"{result['bad_messages_sent']} bad messages"
    )
    bottom.plot(
        [t / 60 for t in result["latency_t_s"]], result["latency_ms"], ".", markersize=2, alpha=0.4, label="per frame"
    )
    for q, style in ((50, "-"), (99, "--")):
        if result[f"latency_ms_p{q}"] is not None:
            bottom.axhline(result[f"latency_ms_p{q}"], linestyle=style, color="k", label=f"p{q}")
    bottom.set_ylabel("latency (ms)")
    bottom.set_xlabel("minutes")
    bottom.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m vlocnetpp_ros.soak", description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default=None, metavar="NAME.safetensors", help="default: the shipped lite model")
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--rate-hz", type=float, default=15.0, help="camera rate (default 15, the lite target on 2 cores)")
    p.add_argument(
        "--bad-fraction", type=float, default=0.2, help="share of ticks that send a bad message (default 0.2)"
    )
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--backend", choices=BACKENDS, default="torch")
    p.add_argument("--num-threads", type=int, default=0, help="the node's num_threads (0: all cores but one)")
    p.add_argument("--sample-s", type=float, default=10.0, help="seconds between RSS samples (default 10)")
    p.add_argument(
        "--warmup-s", type=float, default=60.0, help="the RSS start figure is the first sample after this (default 60)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, metavar="DIR", help="writes soak.json, soak.md and soak.png here")
    args = p.parse_args(argv)
    try:
        if not (
            args.minutes > 0 and args.rate_hz > 0 and 0 <= args.bad_fraction < 1 and args.width > 0 and args.height > 0
        ):
            raise UserError("need --minutes > 0, --rate-hz > 0, 0 <= --bad-fraction < 1 and a positive frame size")
        checkpoint = args.checkpoint or shipped_checkpoint()
        result = run(
            checkpoint,
            args.minutes,
            args.rate_hz,
            args.bad_fraction,
            args.width,
            args.height,
            args.backend,
            args.num_threads,
            args.sample_s,
            args.seed,
            args.warmup_s,
        )
    except (UserError, FileNotFoundError) as err:
        print(f"soak: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "soak.json").write_text(json.dumps(result, indent=1))
    text = table(result)
    (out / "soak.md").write_text(text + "\n")
    plot(result, out / "soak.png")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
