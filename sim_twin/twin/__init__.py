"""The twin: the MuJoCo model, hydraulics, reality profiles, the simulated machine (MuJoCo, Drake,
ROS 2 plant) and the process pools of batch work."""
