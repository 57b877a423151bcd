"""Procedural synthetic campus in the DeepLoc layout: the embedded dataset of the package.

* :func:`render_dataset` writes a whole dataset (train and test loops, labels, depth, poses,
  intrinsics, previews) atomically; ``vlocnetpp synth`` is its command line.
* :class:`Campus` builds the static scene of a scene name; :func:`render_frame` renders one
  camera pose of it (RGB, class ids, depth), given a :class:`Lighting` and the
  :class:`DynamicObject` s present; :func:`plan_visit` gives the poses, lighting and moving
  objects of one loop.

Modules: ``layout`` (dimensions, class ids), ``campus`` (the scene: roads, buildings, landmarks,
vegetation), ``campus_furniture`` and ``campus_ground`` (its street furniture and ground colour),
``textures`` (the atlas, noise, sky), ``facades`` and ``object_strips`` (what is painted in it) and
``ground`` (appearance), ``prims`` (geometry),
``route`` (closed paths), ``lighting``, ``render`` (ray casting), ``drive`` (visits),
``preview`` and ``writer``.
"""

from vlocnetpp_core.synth.campus import Campus, DynamicObject
from vlocnetpp_core.synth.drive import Visit, plan_visit
from vlocnetpp_core.synth.lighting import DEFAULT_LIGHTING, Lighting, sample_lighting
from vlocnetpp_core.synth.render import render_frame
from vlocnetpp_core.synth.writer import DEFAULT_FRAMES_PER_LOOP, default_intrinsics, render_dataset

__all__ = [
    "Campus",
    "DynamicObject",
    "Lighting",
    "DEFAULT_LIGHTING",
    "sample_lighting",
    "render_frame",
    "Visit",
    "plan_visit",
    "render_dataset",
    "default_intrinsics",
    "DEFAULT_FRAMES_PER_LOOP",
]
