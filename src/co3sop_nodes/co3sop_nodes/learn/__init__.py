"""Training, evaluation and ablations of the model on generated (or converted) data (ROS-free)."""
