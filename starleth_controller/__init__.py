"""StarlETH locomotion controller (pure Python, no ROS) and its ROS 2 node."""
