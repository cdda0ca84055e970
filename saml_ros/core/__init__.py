"""ROS-free core: layouts, systems, problem specs, models, primal-dual trainer, buffer, checkpoints, MPC."""
