"""ROS 2 bags without ROS: the dataset -> MCAP converter, bag replay through the Localizer, bag scoring.

``messages`` builds and reads Jazzy messages with ``rosbags`` types, ``bagfile`` writes single-file
MCAP bags atomically and reads bags in stamp order; ``convert``, ``replay`` and ``evaluate_bag``
are the ``vlocnetpp`` sub-commands. See docs/bags.md.
"""
