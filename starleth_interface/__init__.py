"""What the simulator and the controllers share: the ROS 2 interface of their nodes (topic
names, ``topics``, ROS-free; node helpers, ``ros_helpers``: parameter schemas, executors,
throttled logs) and the robot description (``robot``: the robot library, specs, URDF checks,
legs, feet, the scaling rule; with ``config_checks`` and ``yaml_files``, ROS-free). It
imports neither starleth_sim nor starleth_controller, so the controller depends on the
interface, not on the simulator."""
