"""The QoS profiles of sim_node's topics and services (doc/sim_node.md lists which topic has
which): reliable depth 10 for the state and the commands, best effort for /clock (ROS's
ClockQoS), transient local for what a late subscriber must still get (robot_description,
/tf_static), a deeper queue for /tf and one for the services."""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from starleth_interface.ros_helpers import service_qos


def _profile(depth, reliability=ReliabilityPolicy.RELIABLE,
             durability=DurabilityPolicy.VOLATILE) -> QoSProfile:
    return QoSProfile(depth=depth, reliability=reliability, durability=durability,
                      history=HistoryPolicy.KEEP_LAST)


#: the state topics of every step (joint_states, foot wrenches, base_state, imu, solver,
#: state_bundle, contact markers)
STATE_QOS = _profile(10)
#: /clock, as ROS's ClockQoS
CLOCK_QOS = _profile(1, reliability=ReliabilityPolicy.BEST_EFFORT)
#: robot_description and /tf_static: kept for subscribers that come later
LATCHED_QOS = _profile(1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: the subscriptions (commands and pushes)
COMMAND_QOS = _profile(10)
#: /tf
TF_QOS = _profile(100)

#: the services: requests and responses kept until served (100 callers at once are all
#: answered; the default depth of 10 loses the rest, and callers wait forever); their
#: clients need the same depth (starleth_interface.ros_helpers.service_qos)
SERVICE_QOS = service_qos()
