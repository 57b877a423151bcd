"""VLocNet++ core: network, data, training, evaluation and streaming inference. No ROS imports here."""

__version__ = "0.1.0"
