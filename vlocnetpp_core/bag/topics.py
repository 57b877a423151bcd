"""The topic names and frame conventions of this package's bags and node, in one place.

Inputs (what ``convert`` writes and the node subscribes to by default), ground truth and labels
(what ``convert`` writes and ``evaluate-bag`` scores against) and the localizer's outputs (what
the node publishes and ``replay`` writes; ``NETWORK_POSE_TOPIC`` only with a keyframe map).
``DEFAULT_MAX_GAP_S`` is the stamp gap after which the localizer resets its temporal state, and after
which ``evaluate-bag`` starts a new sequence.
"""

from __future__ import annotations

IMAGE_TOPIC = "/camera/image_raw"
COMPRESSED_TOPIC = IMAGE_TOPIC + "/compressed"  # image_transport's naming
IMAGE_TOPICS = (IMAGE_TOPIC, COMPRESSED_TOPIC)
DEPTH_TOPIC = "/camera/depth/image_raw"
CAMERA_INFO_TOPIC = "/camera/camera_info"
SEMANTIC_TOPIC = "/camera/semantic"
GROUND_TRUTH_TOPIC = "/ground_truth/pose"
TF_TOPIC = "/tf"  # tf2_msgs/TFMessage; convert --robot-frame writes map -> robot here
TF_STATIC_TOPIC = "/tf_static"  # ... and robot -> camera here, once

POSE_TOPIC = "/vlocnet/pose"
POSE_WITH_COVARIANCE_TOPIC = (
    "/vlocnet/pose_with_covariance"  # the same pose with its 6x6 covariance (robot_localization's input)
)
ODOMETRY_TOPIC = "/vlocnet/odometry"
SEGMENTATION_TOPIC = "/vlocnet/segmentation"
# With a keyframe map (refinement on): the network's own global pose (PoseStamped), beside the published one on
# POSE_TOPIC
NETWORK_POSE_TOPIC = "/vlocnet/network_pose"
OUTPUT_TOPICS = (POSE_TOPIC, POSE_WITH_COVARIANCE_TOPIC, ODOMETRY_TOPIC, SEGMENTATION_TOPIC, NETWORK_POSE_TOPIC)
DIAGNOSTICS_TOPIC = "/diagnostics"

MAP_FRAME = "map"
ODOM_FRAME = "odom"
DEFAULT_MAX_GAP_S = 1.0
