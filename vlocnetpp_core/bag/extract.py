"""``vlocnetpp extract BAG OUT``: a robot's ROS 2 bag as a DeepLoc-layout dataset this package trains on.

Reads ``BAG`` (an ``.mcap`` / ``.db3`` file or a rosbag2 folder, with ``rosbags``, no ROS) twice:

1. scan: the header stamps of every camera and depth image, the camera info, and the poses, from
   ``--pose-topic`` (``Odometry``, ``PoseStamped``, ``PoseWithCovarianceStamped``) or from the
   ``--tf PARENT CHILD`` chain of ``/tf`` + ``/tf_static``
   (:mod:`~vlocnetpp_core.bag.pose_source`). The camera pose of an image is
   ``T_PARENT,CHILD(stamp) * T_CHILD,camera`` (``--camera-extrinsics``, identity by default),
   interpolated at the image's header stamp, never extrapolated;
2. write: the kept images (:mod:`~vlocnetpp_core.bag.extract_plan`: pose available, split by
   ``--test-ranges``, sequences cut at ``--max-gap-s``, ``--stride``, ``--min-motion``) and the
   depth image nearest in stamp within ``--depth-tolerance``, in the layout of
   :mod:`~vlocnetpp_core.bag.extract_writer`, inside a temporary folder renamed to ``OUT`` at the end.

Errors that stop it (a ``UserError`` naming the topic or frame; nothing is left behind): a missing
topic, a topic of the wrong type, an unsupported encoding, camera info of another size than the
images, no pose for any image, nothing left to write. Images that fail to decode, have another size
than the first, or have no pose are skipped and counted in the summary. See docs/own-robot.md.
"""

from __future__ import annotations

import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagReader
from vlocnetpp_core.bag.extract_plan import Plan, PlannedFrame, match_nearest, plan_frames
from vlocnetpp_core.bag.extract_scan import (
    ExtractOptions,
    Scan,
    Sources,
    camera_intrinsics,
    camera_poses,
    check_depth,
    image_size,
    resolve_sources,
    scan_bag,
)
from vlocnetpp_core.bag.extract_writer import DeepLocWriter, atomic_output_dir, check_output
from vlocnetpp_core.bag.pose_source import PoseChain
from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.errors import UserError
from vlocnetpp_core.inference import preprocess
from vlocnetpp_core.interrupts import sigterm_as_interrupt

__all__ = ["ExtractOptions", "ExtractSummary", "extract"]


@dataclass
class ExtractSummary:
    """What :func:`extract` wrote: ``frames`` and ``sequences`` per split, ``depth_frames``, ``images`` on the
    topic, ``skipped`` images per reason, ``notes`` for the user."""

    out: Path
    image_topic: str
    images: int
    frames: dict[str, int]
    sequences: dict[str, int]
    depth_frames: int
    skipped: Counter
    notes: list[str] = field(default_factory=list)
    wall_s: float = 0.0

    def format(self) -> str:
        splits = ", ".join(
            f"{s} {n} frames in {self.sequences[s]} sequence{'s' * (self.sequences[s] != 1)}"
            for s, n in self.frames.items()
            if n
        )
        line = (
            f"wrote {self.out}: {sum(self.frames.values())} of {self.images} images of {self.image_topic} ({splits}), "
            f"depth on {self.depth_frames}, in {self.wall_s:.1f} s"
        )
        if self.skipped:
            line += f"; skipped {sum(self.skipped.values())}: " + ", ".join(
                f"{k} {v}" for k, v in sorted(self.skipped.items())
            )
        return "\n".join([line] + [f"note: {n}" for n in self.notes])


# --------------------------------------------------------------------------- pass 2: write


def _decode_depth(msg: Any, topic: str, size: tuple[int, int]) -> np.ndarray | None:
    """``(H, W)`` float32 metres (32FC1) or uint16 millimetres (16UC1); None for a bad or wrongly sized one."""
    if msg.encoding not in preprocess.DEPTH_ENCODINGS:
        raise UserError(
            f"{topic}: unsupported depth encoding {msg.encoding!r} (supported: 32FC1 metres, 16UC1 millimetres)"
        )
    try:
        depth = messages.image_to_array(msg)
    except preprocess.FrameError:
        return None
    if depth.shape[::-1] != size:
        return None
    return depth if depth.dtype == np.uint16 else preprocess.depth_to_metres(depth, msg.encoding)


def write_frames(
    reader: BagReader,
    src: Sources,
    plan: Plan,
    depth_match: np.ndarray,
    writer: DeepLocWriter,
    size: tuple[int, int],
    progress: bool,
) -> None:
    """Second pass: decode and write the planned images and their matched depth (``depth_match[k]``: depth
    ordinal of ``plan.frames[k]`` or -1); undecodable or resized images are skipped into ``plan.skipped``."""
    from tqdm import tqdm

    by_image = {f.ordinal: f for f in plan.frames}
    by_depth: dict[int, list[PlannedFrame]] = {}
    for f, d in zip(plan.frames, depth_match, strict=True):
        if d >= 0:
            by_depth.setdefault(int(d), []).append(f)
    topics = reader.topics
    counters = {src.image: -1, src.depth: -1}
    total = reader.count(src.image) + (reader.count(src.depth) if src.depth else 0)
    with tqdm(total=total, unit="msg", desc="extract: write", disable=not progress, file=sys.stderr) as bar:
        for topic, _, raw in reader.messages([t for t in (src.image, src.depth) if t], raw=True):
            bar.update(1)
            counters[topic] += 1
            k = counters[topic]
            if topic == src.image:
                if k in by_image:
                    msg = messages.deserialize(raw, topics[topic])
                    if messages.stamp_ns(msg) != by_image[k].stamp_ns:  # both passes read the bag in the same order
                        raise UserError(
                            f"{topic}: message {k} has another stamp on the second read of the bag; "
                            "is it being written to?"
                        )
                    _write_image(msg, topic, by_image[k], writer, size, plan.skipped)
            elif k in by_depth:
                depth = _decode_depth(messages.deserialize(raw, topics[topic]), topic, size)
                for f in by_depth[k] if depth is not None else []:
                    writer.depth(f, depth)


def _write_image(
    msg: Any, topic: str, frame: PlannedFrame, writer: DeepLocWriter, size: tuple[int, int], skipped: Counter
) -> None:
    """Decode one camera message to RGB and write it; undecodable or resized images are counted in ``skipped``."""
    try:
        rgb = messages.any_image_to_rgb(msg)
    except preprocess.FrameError as err:
        if err.reason == "unsupported_encoding":
            raise UserError(f"{topic}: {err}") from err
        skipped[f"undecodable image ({err.reason})"] += 1
        return
    if rgb.shape[1::-1] != size:
        skipped["image size differs from the first image"] += 1
        return
    writer.image(frame, rgb)


# --------------------------------------------------------------------------- the whole run


def _frame_note(chain: PoseChain, scan: Scan, src: Sources, opts: ExtractOptions, notes: list[str]) -> None:
    """A note when the poses are of a named frame that is not the images' frame and no extrinsics were given."""
    frame = str(scan.first_image.header.frame_id).lstrip("/")
    named = src.tf is not None or bool(getattr(scan.pose, "child_frame_id", ""))
    if named and opts.camera_extrinsics is None and frame and chain.child != frame:
        notes.append(
            f"the poses are of frame {chain.child!r} but the images are in {frame!r} and no --camera-extrinsics was "
            f"given: the dataset holds the poses of {chain.child!r}, not of the camera "
            f"(use --tf {chain.parent} {frame}, or --camera-extrinsics)"
        )


def check_readback(root: Path, written: list[PlannedFrame]) -> list[str]:
    """Read the written dataset back with the DeepLoc reader; notes where it sees other sequences than were written."""
    from vlocnetpp_core.data.deeploc import read_deeploc

    notes = []
    for split in sorted({f.split for f in written}):
        index = read_deeploc(root, split)
        want = len({f.sequence for f in written if f.split == split})
        if len(index.sequences) != want:
            notes.append(
                f"{split}: the DeepLoc reader sees {len(index.sequences)} sequences where {want} were written: it also "
                "cuts where consecutive frames are over 5 m or 45 deg apart "
                "(a smaller --stride / --min-motion avoids it)"
            )
    return notes


def _provenance(bag: Path, src: Sources, opts: ExtractOptions, K: Intrinsics, plan: Plan, first_ns: int) -> dict:
    sel = opts.selection
    ext = opts.camera_extrinsics
    return {
        "bag": str(bag.resolve()),
        "image_topic": src.image,
        "camera_info_topic": src.camera_info,
        "depth_topic": src.depth,
        "pose_source": src.pose_name,
        "first_image_stamp_ns": int(first_ns),
        "intrinsics": K.to_dict(),
        "camera_extrinsics": None if ext is None else [*map(float, ext[0]), *map(float, ext[1])],
        "max_pose_gap_s": opts.max_pose_gap_s,
        "depth_tolerance_s": opts.depth_tolerance_s,
        "max_gap_s": sel.max_gap_s,
        "stride": sel.stride,
        "min_motion": [sel.min_motion_m, sel.min_motion_deg],
        "test_ranges": [list(r) for r in sel.test_ranges],
        "skipped": dict(plan.skipped),
    }


def extract(
    bag: str | Path, out: str | Path, opts: ExtractOptions, force: bool = False, progress: bool = True
) -> ExtractSummary:
    """Write the DeepLoc-layout dataset ``out`` from the bag ``bag`` (module doc); returns what was written."""
    start = time.perf_counter()
    out = Path(out)
    check_output(out, force)
    notes: list[str] = []
    with BagReader(bag) as reader:
        src = resolve_sources(reader.topics, opts, reader.path)
        scan = scan_bag(reader, src, progress)
        if not scan.image_stamps:
            raise UserError(f"{src.image}: the topic has no messages")
        size = image_size(scan.first_image, src.image)
        if src.depth is not None and scan.first_depth is not None:
            check_depth(scan.first_depth, src.depth, size)
        K = camera_intrinsics(scan, src, opts, size, notes)
        chain = scan.pose.chain(*src.tf) if src.tf is not None else scan.pose.chain()
        _frame_note(chain, scan, src, opts, notes)
        stamps = np.asarray(scan.image_stamps, dtype=np.int64)
        plan = plan_frames(stamps, *camera_poses(chain, stamps, src, opts), opts.selection)
        if not plan.frames:
            raise UserError(
                f"no frames left of the {len(stamps)} images of {src.image} (skipped: "
                + ", ".join(f"{k} {v}" for k, v in sorted(plan.skipped.items()))
                + ")"
            )
        depth_match = match_nearest(
            np.array([f.stamp_ns for f in plan.frames]), np.asarray(scan.depth_stamps), opts.depth_tolerance_s
        )
        with sigterm_as_interrupt(), atomic_output_dir(out, force) as tmp:
            writer = DeepLocWriter(tmp)
            try:
                write_frames(reader, src, plan, depth_match, writer, size, progress)
                written = writer.finish(plan.frames, K, _provenance(reader.path, src, opts, K, plan, int(stamps.min())))
            finally:
                writer.close()
            if not written:
                raise UserError(
                    f"{src.image}: none of the {len(plan.frames)} selected images could be decoded "
                    f"({', '.join(f'{k} {v}' for k, v in sorted(plan.skipped.items()))})"
                )
            notes += check_readback(tmp, written)
            depth_frames = len(set(writer.depths) & writer.images)
    splits = ("train", "test")
    return ExtractSummary(
        out=out,
        image_topic=src.image,
        images=len(stamps),
        frames={s: sum(f.split == s for f in written) for s in splits},
        sequences={s: len({f.sequence for f in written if f.split == s}) for s in splits},
        depth_frames=depth_frames,
        skipped=plan.skipped,
        notes=notes,
        wall_s=time.perf_counter() - start,
    )
