"""Running a trained model: checkpoints, sensor inputs as tensors, one frame predicted, its outputs through
the V2X codec, and how fast this machine runs it."""
