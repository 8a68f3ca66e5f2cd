"""The stand-in robot: the pybullet sim behind a ROS 2 face, for the ros2 backend on a machine without ROS 2."""
