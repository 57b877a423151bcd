"""Pass 2 of ``vlocnetpp evaluate-bag``: ``/vlocnet/segmentation`` against ``/camera/semantic`` per sequence, and the
frames kept for the segmentation strip plot, streaming (label maps are never all in memory)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlocnetpp_core.bag import messages
from vlocnetpp_core.bag.bagfile import BagReader
from vlocnetpp_core.bag.topics import IMAGE_TOPICS, SEGMENTATION_TOPIC, SEMANTIC_TOPIC
from vlocnetpp_core.classes import CLASS_NAMES
from vlocnetpp_core.errors import DataError
from vlocnetpp_core.evaluation.metrics import confusion_matrix

_PENDING_LIMIT = 64  # label maps / masks waiting for their partner stamp (a partner never seen is dropped)


@dataclass
class SegmentationScores:
    """Pass 2 per sequence: ``confusion`` (or None without labels) and the ``samples`` kept for plots."""

    confusion: list[np.ndarray | None]
    samples: list[list[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]]]


def score_segmentation(
    reader: BagReader, where: dict[int, tuple[int, int]], sample_stamps: set[int], num_classes: int = len(CLASS_NAMES)
) -> SegmentationScores:
    """Pass 2: ``/vlocnet/segmentation`` against ``/camera/semantic`` for the frames in ``where`` (stamp ->
    (sequence, position)); camera images are decoded only for ``sample_stamps``."""
    n_seq = 1 + max((k for k, _ in where.values()), default=-1)
    scores = SegmentationScores([None] * n_seq, [[] for _ in range(n_seq)])
    have_labels = SEMANTIC_TOPIC in reader.topics
    image_topic = next((t for t in IMAGE_TOPICS if t in reader.topics), None) if sample_stamps else None
    if SEGMENTATION_TOPIC not in reader.topics or not (have_labels or image_topic):
        return scores
    topics = [SEGMENTATION_TOPIC] + ([SEMANTIC_TOPIC] if have_labels else []) + ([image_topic] if image_topic else [])
    pending: dict[
        int, dict[str, np.ndarray]
    ] = {}  # stamp -> the parts that arrived (topics may be logged at different times)
    for topic, _, msg in reader.messages(topics):
        ns = messages.stamp_ns(msg)
        if ns not in where or (topic == image_topic and ns not in sample_stamps):
            continue
        parts = pending.setdefault(ns, {})
        parts[topic] = messages.any_image_to_rgb(msg) if topic == image_topic else messages.image_to_array(msg)
        needed = (
            [SEGMENTATION_TOPIC]
            + ([SEMANTIC_TOPIC] if have_labels else [])
            + ([image_topic] if image_topic and ns in sample_stamps else [])
        )
        if not all(t in parts for t in needed):
            if len(pending) > _PENDING_LIMIT:
                del pending[min(pending)]
            continue
        del pending[ns]
        k, position = where[ns]
        mask, labels, image = parts[SEGMENTATION_TOPIC], parts.get(SEMANTIC_TOPIC), parts.get(image_topic)
        for other, what in ((labels, SEMANTIC_TOPIC), (None if image is None else image[..., 0], image_topic)):
            if other is not None and other.shape != mask.shape:
                raise DataError(
                    reader.path,
                    f"at stamp {ns / 1e9:.9f} s the {SEGMENTATION_TOPIC} mask is {mask.shape[1]}x{mask.shape[0]} "
                    f"but {what} is {other.shape[1]}x{other.shape[0]} "
                    "(the localizer publishes masks at the image size)",
                )
        if labels is not None:
            conf = confusion_matrix(labels, mask, num_classes)
            scores.confusion[k] = conf if scores.confusion[k] is None else scores.confusion[k] + conf
        if image is not None:
            scores.samples[k].append((position, image, mask, labels))
    return scores
