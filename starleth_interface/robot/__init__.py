"""What the simulator and the controllers both need of a robot, read from its robot spec and
its URDF (ROS-free; nothing of starleth_sim): the robot library (``library``: what a `robot`
names, its spec, its URDF), the spec's schema (``spec``), the URDF checks and model
(``urdf``), contact points of collision geometry (``contact_points``), the feet
(``feet``), the legs found from the tree and the standing posture (``legs``) and the
scaling rule (``scaling``). starleth_sim.robots builds the simulator's RobotDescription
from them."""
