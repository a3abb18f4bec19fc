"""The ROS 2 interface names of ``sim_node`` (ROS-free, so that bag analysis and other tools
can use them without importing rclpy).

Names are relative (REP 135 style): a node started with ``--ros-args -r __ns:=/robot1``
publishes ``/robot1/joint_states`` and so on, so that several robots share one ROS domain.
``/clock``, ``/tf`` and ``/tf_static`` are global, as ROS defines them; each robot's clock
goes into its namespace by a remap (``-r /clock:=clock``, as the launch file does), since
robots in one domain do not share one sim time. ``~/...`` names are private to the node
(``/robot1/sim_node/wrench``).
"""
import re

TOPIC_CLOCK = "/clock"
TOPIC_JOINT_STATES = "joint_states"
#: the simulator's ground-truth odometry (nav_msgs/Odometry: pose in the world, twist in the
#: base frame), exact whatever the sensors
TOPIC_BASE_STATE = "starleth/base_state"
TOPIC_IMU = "starleth/imu"
#: the feet's contact switches (sensor_msgs/JointState: name = the foot contact names,
#: position = flag 1.0 contact / 0.0 none, effort = the measured normal force [N])
TOPIC_FOOT_CONTACTS = "starleth/foot_contacts"
#: with noisy sensors, the exact values of the measured topics (Gazebo's convention): a
#: controller must not need them
GROUND_TRUTH_PREFIX = "ground_truth/"
TOPIC_GROUND_TRUTH_JOINT_STATES = GROUND_TRUTH_PREFIX + "joint_states"
TOPIC_GROUND_TRUTH_IMU = GROUND_TRUTH_PREFIX + "imu"
TOPIC_GROUND_TRUTH_FOOT_CONTACTS = GROUND_TRUTH_PREFIX + "foot_contacts"
TOPIC_SOLVER = "starleth/solver"
#: the state of a step in one message, sim_node -> controller_node (starleth_interface.state_bundle)
TOPIC_STATE_BUNDLE = "starleth/state_bundle"
#: controller_node's state estimate (state_source:=estimator; nav_msgs/Odometry)
TOPIC_ESTIMATOR_ODOMETRY = "estimator/odometry"
TOPIC_ROBOT_DESCRIPTION = "robot_description"
TOPIC_EFFORT_COMMANDS = "joint_group_effort_controller/commands"
#: ros2_control forward_command_controller topics: joint targets (joint order) that sim_node
#: tracks with the impedance law and the gains default_kp, default_kd
TOPIC_POSITION_COMMANDS = "joint_group_position_controller/commands"
TOPIC_VELOCITY_COMMANDS = "joint_group_velocity_controller/commands"
#: the applied torque of every physics step of a control step (recorded; for the replay)
TOPIC_APPLIED_TORQUE = "starleth/applied_torque"
TOPIC_JOINT_COMMANDS = "joint_commands"
TOPIC_CONTACT_MARKERS = "starleth/contact_markers"
#: the terrain (visualization_msgs/MarkerArray, latched; only with a terrain)
TOPIC_TERRAIN = "terrain"
TOPIC_TF = "/tf"
TOPIC_TF_STATIC = "/tf_static"
TOPIC_WRENCH = "~/wrench"
TOPIC_WRENCH_PERSISTENT = "~/wrench/persistent"


def topic_token(name: str) -> str:
    """`name` as one token of a ROS topic name: every character other than a letter, a digit
    or '_' becomes '_', repeated '_' one, and a leading digit gets a '_' before it
    ('LF_foot' stays, 'foot.1' -> 'foot_1', '3rd leg' -> '_3rd_leg')."""
    token = re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", name))
    return "_" + token if not token or token[0].isdigit() else token


#: a foot's wrench topic: _FOOT_WRENCH[0] + the foot's topic token + _FOOT_WRENCH[1]
_FOOT_WRENCH = ("starleth/", "/wrench")


def foot_wrench_topic(foot: str) -> str:
    """starleth/<foot>/wrench for a foot contact name such as 'LF_foot' (any URDF name: its
    topic_token)."""
    return _FOOT_WRENCH[0] + topic_token(foot) + _FOOT_WRENCH[1]


def split_foot_wrench_topic(topic: str) -> tuple[str, str] | None:
    """(namespace, foot token) of an absolute foot wrench topic
    ('/robot1/starleth/FL_foot/wrench' -> ('/robot1', 'FL_foot')), else None."""
    head, tail = _FOOT_WRENCH
    at = topic.rfind("/" + head)
    if at < 0 or not topic.startswith("/") or not topic.endswith(tail):
        return None
    foot = topic[at + 1 + len(head):len(topic) - len(tail)]
    if not foot or "/" in foot:
        return None
    return topic[:at], foot


def normalize_namespace(namespace: str | None) -> str:
    """'' (the root) or '/a/b' for any of None, '', '/', 'a/b', '/a/b/'."""
    ns = (namespace or "").strip().strip("/")
    return "/" + ns if ns else ""


def resolve(name: str, namespace: str | None = "") -> str:
    """The fully qualified topic name of a relative `name` in `namespace` ('/joint_states',
    '/robot1/joint_states'); absolute names are returned as they are. Private (~) names are
    not resolved here (they need the node name)."""
    if name.startswith("/"):
        return name
    return f"{normalize_namespace(namespace)}/{name}"


def namespace_of(topic: str, name: str) -> str | None:
    """The namespace under which the fully qualified `topic` is the relative `name`
    ('/robot1/joint_states', 'joint_states' -> '/robot1'; '/joint_states' -> ''), or None
    if it is not."""
    suffix = "/" + name
    if topic == suffix:
        return ""
    if topic.endswith(suffix) and topic.startswith("/"):
        return topic[:-len(suffix)]
    return None
