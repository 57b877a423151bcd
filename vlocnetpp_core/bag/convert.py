"""``vlocnetpp convert`` (alias ``convert-deeploc``): a DeepLoc / 7-Scenes split as a ROS 2 Jazzy MCAP bag.

Topics (every message of a frame has the frame's stamp; image frames are ``camera``):

=============================== =========================== ==========================================
``/camera/image_raw``           ``sensor_msgs/Image``       ``rgb8`` (without ``--compress``)
``/camera/image_raw/compressed`` ``sensor_msgs/CompressedImage`` PNG or JPEG (``--compress png|jpeg``)
``/camera/depth/image_raw``     ``sensor_msgs/Image``       ``32FC1`` metres, 0 = invalid (when depth exists)
``/camera/camera_info``         ``sensor_msgs/CameraInfo``  pinhole ``K``/``P``, zero distortion
``/camera/semantic``            ``sensor_msgs/Image``       ``mono8`` class ids, 255 = ignore (when labels exist)
``/ground_truth/pose``          ``geometry_msgs/PoseStamped`` ``T_wc`` in ``map``
=============================== =========================== ==========================================

With ``--robot-frame ROBOT --camera-extrinsics X,Y,Z,QW,QX,QY,QZ`` (``T_ROBOT,camera``, the camera's
pose in the robot frame) the ground truth is written as a robot's bag carries it instead:
``/tf`` ``map -> ROBOT`` per frame (``T_map,ROBOT = T_map,camera * T_ROBOT,camera^-1``) and one
``/tf_static`` ``ROBOT -> camera`` message at the first stamp, no ``/ground_truth/pose``; ``vlocnetpp
extract --tf map ROBOT --camera-extrinsics ...`` reads it back. ``--no-labels`` leaves out
``/camera/semantic``.

Stamps: the frames of a sequence are ``1 / --rate`` apart (default 20 Hz DeepLoc, 30 Hz 7-Scenes)
starting at 0 s, and each sequence starts :data:`vlocnetpp_core.data.sample.SEQUENCE_GAP_S` (10 s) after the previous
one ends, longer than the node's ``max_gap_s``, so a replay resets the temporal state between loops.
With ``--split all`` the test split follows the train split the same way.

The conversion streams (memory does not grow with the dataset): :data:`DECODE_THREADS` background
threads decode up to :data:`PREFETCH_FRAMES` frames ahead while the main thread serialises and writes
the current one, so PNG decoding (which releases the GIL) overlaps with writing on a machine with
two cores or more. The bag is written to a hidden temporary folder and renamed into place when
complete (see :mod:`vlocnetpp_core.bag.bagfile`); an error, Ctrl-C or SIGTERM leaves nothing.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vlocnetpp_core import geometry
from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagWriter
from vlocnetpp_core.bag.topics import (
    CAMERA_INFO_TOPIC,
    COMPRESSED_TOPIC,
    DEPTH_TOPIC,
    GROUND_TRUTH_TOPIC,
    IMAGE_TOPIC,
    MAP_FRAME,
    SEMANTIC_TOPIC,
    TF_STATIC_TOPIC,
    TF_TOPIC,
)
from vlocnetpp_core.data.formats import FORMATS
from vlocnetpp_core.data.sample import DatasetIndex, Frame, sequence_stamps
from vlocnetpp_core.errors import DataError, UserError
from vlocnetpp_core.interrupts import sigterm_as_interrupt
from vlocnetpp_core.outputs import refuse_existing

CAMERA_FRAME = "camera"
DEFAULT_RATE_HZ = {"deeploc": 20.0, "7scenes": 30.0}
PREFETCH_FRAMES = 4
DECODE_THREADS = 2


@dataclass
class ConvertSummary:
    """What :func:`convert` wrote: ``frames``, messages per topic, file ``size_bytes``, bag ``duration_s`` and
    ``wall_s``."""

    path: Path
    frames: int
    topics: dict[str, int] = field(default_factory=dict)
    size_bytes: int = 0
    duration_s: float = 0.0
    wall_s: float = 0.0

    def format(self) -> str:
        lines = [
            f"wrote {self.path}: {self.frames} frames, {self.size_bytes / 2**20:.1f} MiB, "
            f"{self.duration_s:.1f} s of bag time, in {self.wall_s:.1f} s "
            f"({self.frames / max(self.wall_s, 1e-9):.1f} frames/s)"
        ]
        lines += [f"  {topic:<32} {count} messages" for topic, count in self.topics.items()]
        return "\n".join(lines)


def frame_stamps(indexes: list[DatasetIndex], rate_hz: float) -> list[float]:
    """One stamp per record of ``indexes`` (in order): sequences at ``rate_hz`` laid end to end with
    :data:`~vlocnetpp_core.data.sample.SEQUENCE_GAP_S` between them, over all the given splits."""
    lengths = [len(r) for index in indexes for r in index.sequences]
    return [float(s) for seq in sequence_stamps(lengths, rate_hz) for s in seq]


def check_listed_images(index: DatasetIndex) -> None:
    """DeepLoc: every image named in ``poses.txt`` must exist (the reader skips missing ones; the converter
    refuses, naming the first missing file)."""
    if index.format != "deeploc":
        return
    from vlocnetpp_core.data.deeploc import find_deeploc_root, frame_number, read_poses

    split_dir = find_deeploc_root(index.root)[0] / index.split
    present = {frame_number(Path(r.image).name) for r in index.records}
    for n, name, _, _ in read_poses(split_dir / "poses.txt"):
        if n not in present:
            missing = split_dir / "LeftImages" / (name if Path(name).suffix else f"{name}.png")
            raise DataError(
                missing,
                f"image listed in {split_dir / 'poses.txt'} not found (use --skip-missing to leave such poses out)",
            )


def prefetched(frames: Iterable[tuple[DatasetIndex, int]], ahead: int = PREFETCH_FRAMES) -> Iterator[Frame]:
    """``index.load(i)`` of each ``(index, i)`` in order, decoded by :data:`DECODE_THREADS` background threads
    at most ``ahead`` frames ahead (a decoding error is raised here, at its frame). Closing the iterator
    early cancels the rest."""
    items = iter(frames)
    pool = ThreadPoolExecutor(max_workers=DECODE_THREADS, thread_name_prefix="convert-decode")
    pending: deque = deque()
    try:
        for index, i in items:
            pending.append(pool.submit(index.load, i))
            if len(pending) >= ahead:
                break
        while pending:
            frame = pending.popleft().result()
            nxt = next(items, None)
            if nxt is not None:
                pending.append(pool.submit(nxt[0].load, nxt[1]))
            yield frame
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def convert(
    indexes: list[DatasetIndex],
    out: str | Path,
    compress: str | None = None,
    rate_hz: float | None = None,
    force: bool = False,
    progress: bool = True,
    robot_frame: str | None = None,
    camera_extrinsics: tuple[np.ndarray, np.ndarray] | None = None,
    labels: bool = True,
) -> ConvertSummary:
    """Write the records of ``indexes`` (one or more splits, in order) as the bag ``out`` (see module doc).

    ``compress``: None (raw ``rgb8``), ``"png"`` or ``"jpeg"``. ``rate_hz``: None for the format's rate.
    ``robot_frame`` with ``camera_extrinsics`` ``(t (3,), q (4,) w,x,y,z)`` = ``T_robot,camera``: ground truth
    on ``/tf`` + ``/tf_static`` instead of ``/ground_truth/pose``. ``labels=False``: no ``/camera/semantic``.
    """
    from tqdm import tqdm

    if not indexes:
        raise UserError("nothing to convert")
    rate = rate_hz if rate_hz is not None else DEFAULT_RATE_HZ.get(indexes[0].format, 20.0)
    if not (math.isfinite(rate) and rate > 0):
        raise UserError(f"--rate must be a positive number of Hz, got {rate}")
    if compress not in (None, "png", "jpeg"):
        raise UserError(f"--compress must be png or jpeg, got {compress!r}")
    stamps = frame_stamps(indexes, rate)
    frames = [(index, i) for index in indexes for i in range(len(index))]
    image_topic = IMAGE_TOPIC if compress is None else COMPRESSED_TOPIC
    start = time.perf_counter()
    writer = BagWriter(out, force=force)
    loaded = prefetched(frames)
    with (
        sigterm_as_interrupt(),
        writer,
        closing(loaded),
        tqdm(total=len(frames), unit="frame", desc="convert", disable=not progress, file=sys.stderr) as bar,
    ):
        writer.add_topic(CAMERA_INFO_TOPIC, messages.CAMERA_INFO)
        writer.add_topic(image_topic, messages.IMAGE if compress is None else messages.COMPRESSED_IMAGE)
        if any(index.has_depth for index in indexes):
            writer.add_topic(DEPTH_TOPIC, messages.IMAGE)
        if labels and any(index.has_labels for index in indexes):
            writer.add_topic(SEMANTIC_TOPIC, messages.IMAGE)
        if robot_frame is None:
            writer.add_topic(GROUND_TRUTH_TOPIC, messages.POSE_STAMPED)
        else:
            _write_tf_static(writer, messages.seconds_to_ns(stamps[0]) if stamps else 0, robot_frame, camera_extrinsics)
        for frame, stamp in zip(loaded, stamps, strict=True):
            ns = messages.seconds_to_ns(stamp)
            writer.write(CAMERA_INFO_TOPIC, ns, messages.camera_info(ns, CAMERA_FRAME, frame.intrinsics))
            if compress is None:
                writer.write(image_topic, ns, messages.image(ns, CAMERA_FRAME, frame.image, "rgb8"))
            else:
                writer.write(image_topic, ns, messages.compressed_image(ns, CAMERA_FRAME, frame.image, compress))
            if frame.depth is not None:
                writer.write(DEPTH_TOPIC, ns, messages.image(ns, CAMERA_FRAME, frame.depth, "32FC1"))
            if labels and frame.labels is not None:
                writer.write(SEMANTIC_TOPIC, ns, messages.image(ns, CAMERA_FRAME, frame.labels, "mono8"))
            if robot_frame is None:
                writer.write(GROUND_TRUTH_TOPIC, ns, messages.pose_stamped(ns, MAP_FRAME, frame.t, frame.q))
            else:
                t_base, q_base = geometry.pose_compose(frame.t, frame.q, *geometry.pose_inverse(*camera_extrinsics))
                writer.write(
                    TF_TOPIC,
                    ns,
                    messages.tf_message([messages.transform_stamped(ns, MAP_FRAME, robot_frame, t_base, q_base)]),
                )
            del frame
            bar.update(1)
    return ConvertSummary(
        path=Path(out),
        frames=len(frames),
        topics=dict(writer.counts),
        size_bytes=Path(out).stat().st_size,
        duration_s=(stamps[-1] - stamps[0]) if stamps else 0.0,
        wall_s=time.perf_counter() - start,
    )


def _write_tf_static(
    writer: BagWriter, ns: int, robot_frame: str, camera_extrinsics: tuple[np.ndarray, np.ndarray] | None
) -> None:
    """Declare ``/tf`` and ``/tf_static`` and write the one ``robot_frame -> camera`` static transform at ``ns``."""
    if camera_extrinsics is None:
        raise UserError(
            "--robot-frame needs --camera-extrinsics X,Y,Z,QW,QX,QY,QZ (the camera's pose in the robot frame)"
        )
    if robot_frame in (MAP_FRAME, CAMERA_FRAME):
        raise UserError(f"--robot-frame must differ from {MAP_FRAME!r} and {CAMERA_FRAME!r}, got {robot_frame!r}")
    writer.add_topic(TF_TOPIC, messages.TF_MESSAGE)
    writer.add_topic(TF_STATIC_TOPIC, messages.TF_MESSAGE, latched=True)
    writer.write(
        TF_STATIC_TOPIC,
        ns,
        messages.tf_message([messages.transform_stamped(ns, robot_frame, CAMERA_FRAME, *camera_extrinsics)]),
    )


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", metavar="DIR", help="dataset folder (DeepLoc layout or a 7-Scenes scene)")
    p.add_argument("out", metavar="OUT.mcap", help="output bag: one MCAP file (ROS 2 Jazzy types)")
    p.add_argument("--format", choices=FORMATS, default=None, help="dataset format (default: detected from the layout)")
    p.add_argument(
        "--split",
        choices=("train", "test", "all"),
        default="test",
        help="split to convert; 'all' = train then test (default: test)",
    )
    p.add_argument(
        "--compress",
        nargs="?",
        const="png",
        choices=("png", "jpeg"),
        default=None,
        help="write /camera/image_raw/compressed (PNG, or JPEG quality 95) instead of raw rgb8 /camera/image_raw",
    )
    p.add_argument(
        "--rate",
        type=float,
        default=None,
        metavar="HZ",
        help="frame rate of the stamps (default 20 Hz DeepLoc, 30 Hz 7-Scenes)",
    )
    p.add_argument(
        "--intrinsics",
        default=None,
        metavar="FX,FY,CX,CY",
        help="camera intrinsics at the dataset image size (default: the reader's)",
    )
    p.add_argument(
        "--robot-frame",
        metavar="ROBOT",
        help="write the ground truth as /tf map -> ROBOT plus /tf_static ROBOT -> camera "
        "(needs --camera-extrinsics) instead of /ground_truth/pose",
    )
    p.add_argument(
        "--camera-extrinsics",
        metavar="X,Y,Z,QW,QX,QY,QZ",
        help="with --robot-frame: the camera's pose in ROBOT (T_robot,camera)",
    )
    p.add_argument("--no-labels", action="store_true", help="leave out /camera/semantic")
    p.add_argument(
        "--skip-missing", action="store_true", help="leave out poses whose image is missing instead of stopping"
    )
    p.add_argument("--force", action="store_true", help="replace OUT.mcap if it exists")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.data.dataset import available_splits, detect_format

    fmt = args.format or detect_format(args.dataset)
    if args.split == "all":
        splits = available_splits(args.dataset, fmt)
        if not splits:
            raise DataError(args.dataset, "no train or test split found")
    else:
        splits = [args.split]
    refuse_existing(args.out, args.force)
    indexes = [open_dataset(args.dataset, fmt, split, args.intrinsics) for split in splits]
    for index in indexes:
        for note in index.notes:
            print(f"note: {note}", file=sys.stderr)
        if not args.skip_missing:
            check_listed_images(index)
    extrinsics = None
    if (args.robot_frame is None) != (args.camera_extrinsics is None):
        raise UserError("--robot-frame ROBOT and --camera-extrinsics X,Y,Z,QW,QX,QY,QZ go together")
    if args.camera_extrinsics is not None:
        from vlocnetpp_core.bag.extract_cli import parse_extrinsics

        extrinsics = parse_extrinsics(args.camera_extrinsics)
    summary = convert(
        indexes,
        args.out,
        args.compress,
        args.rate,
        args.force,
        progress=not args.no_progress,
        robot_frame=args.robot_frame,
        camera_extrinsics=extrinsics,
        labels=not args.no_labels,
    )
    print(summary.format())
    return 0
