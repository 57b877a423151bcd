"""The camera: pinhole intrinsics (scaled with the image) and the camera's mounting on the robot (extrinsics, base frame
poses)."""
