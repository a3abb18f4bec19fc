"""The ROS 2 interface shared by the simulator's and the controller's nodes: topic names
(``topics``, ROS-free) and node helpers (``ros_helpers``: parameter schemas, executors,
throttled logs). It imports neither starleth_sim nor starleth_controller, so the controller
depends on the interface, not on the simulator."""
