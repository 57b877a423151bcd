"""Streaming inference: the Localizer (one frame at a time, temporal state, refinement), input preprocessing,
checkpoints and the ONNX backend and export."""
