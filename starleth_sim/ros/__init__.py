"""The ROS 2 layer of the simulator: sim_node and what it is made of (parameters, the
ROS-free service logic, state conversions, CDR templates, TF, recording). Importing this
package does not import rclpy; ``starleth_sim.ros.sim_node`` does."""
