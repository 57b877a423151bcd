"""Structure-based refinement: a map of the training images and PnP against it (no ROS).

* :mod:`.features`: SIFT keypoints and descriptors, ratio-test matching.
* :mod:`.keyframe_map`: the map (keyframes with pose, intrinsics, features and their 3D points), its file.
* :mod:`.build`: ``vlocnetpp map build``: a map from datasets (3D points from depth, else triangulated).
* :mod:`.pnp`: PnP with RANSAC, non-linear refinement and the covariance of the solution.
* :mod:`.refiner`: the refinement the :class:`~vlocnetpp_core.inference.localizer.Localizer` runs per frame (keyframes
  near a pose prior, checks, fallback) and the structure-based baseline (keyframes by image retrieval).

Conventions are the package's (docs/architecture.md): poses camera-to-world ``T_map,cam`` as ``t (3,)``
metres and ``q (4,)`` ``(w, x, y, z)``; the camera frame is the optical frame (x right, y down, z forward);
pixel centres at integer coordinates.
"""
