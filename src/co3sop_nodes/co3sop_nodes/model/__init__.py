"""Co3SOP-Base and its baselines in plain PyTorch (ROS-free): the vehicle half and the ego half."""
