"""ROS 2 nodes of the StarlETH simulator (``sim_node``). Importing this package does not import
rclpy; ``starleth_sim.nodes.sim_node`` does."""
