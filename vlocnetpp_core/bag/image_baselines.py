"""The baselines of ``vlocnetpp evaluate-bag`` that need the bag's camera images: the retrieval descriptors and the
structure-based poses of the scored frames (a third pass over the bag; :mod:`.evaluate_bag` reads the rest)."""

from __future__ import annotations

import numpy as np

from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagReader
from vlocnetpp_core.bag.topics import CAMERA_INFO_TOPIC, IMAGE_TOPICS
from vlocnetpp_core.errors import DataError


def describe_frames(
    reader: BagReader, where: dict[int, tuple[int, int]], refiner=None
) -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray]] | None]:
    """Pass 3: per sequence, the retrieval descriptors ``(N_k, D)`` of the camera images of the frames in ``where``
    (stamp -> (sequence, position)) and, with ``refiner`` (a :class:`~vlocnetpp_core.mapping.refiner.Refiner`), the
    structure-based baseline's poses ``(t (N_k, 3), q (N_k, 4))`` of those images (``Refiner.locate_image``; the
    intrinsics of the latest ``/camera/camera_info``, that of the image's log time included), else None.
    ``DataError`` when the bag has no camera image for one of them, or (with ``refiner``) no camera info before it."""
    from vlocnetpp_core.bag.replay import groups_by_log_time
    from vlocnetpp_core.evaluation.retrieval import describe

    image_topic = next((t for t in IMAGE_TOPICS if t in reader.topics), None)
    if image_topic is None:
        raise DataError(
            reader.path, f"no camera image topic ({' or '.join(IMAGE_TOPICS)}) to describe for the baselines"
        )
    lengths = np.bincount([k for k, _ in where.values()])
    out: list[np.ndarray | None] = [None] * len(lengths)
    seen = [np.zeros(n, bool) for n in lengths]
    located = None if refiner is None else [(np.zeros((n, 3)), np.zeros((n, 4))) for n in lengths]
    intrinsics = None
    for group in groups_by_log_time(
        reader.messages([image_topic] + ([CAMERA_INFO_TOPIC] if refiner is not None else []))
    ):
        for topic, _, msg in group:
            if topic == CAMERA_INFO_TOPIC:
                intrinsics = messages.intrinsics_from_camera_info(msg)
        for topic, _, msg in group:
            ns = messages.stamp_ns(msg)
            if topic != image_topic or ns not in where:
                continue
            k, position = where[ns]
            rgb = messages.any_image_to_rgb(msg)
            d = describe(rgb)
            if out[k] is None:
                out[k] = np.zeros((lengths[k], len(d)), np.float32)
            out[k][position], seen[k][position] = d, True
            if located is not None:
                if intrinsics is None:
                    raise DataError(
                        reader.path,
                        f"--map: no {CAMERA_INFO_TOPIC} up to the image at stamp {ns / 1e9:.9f} s "
                        "(the structure-based baseline needs the camera's intrinsics)",
                    )
                t, q, _ = refiner.locate_image(rgb, intrinsics, d)
                located[k][0][position], located[k][1][position] = t, q
    for k, ok in enumerate(seen):
        if not ok.all():
            raise DataError(
                reader.path, f"{image_topic} has no image for {int((~ok).sum())} scored frames of sequence {k}"
            )
    return out, located
