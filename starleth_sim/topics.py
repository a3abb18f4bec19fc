"""The ROS 2 interface names of ``sim_node`` (ROS-free, so that bag analysis and other tools
can use them without importing rclpy)."""

TOPIC_CLOCK = "/clock"
TOPIC_JOINT_STATES = "/joint_states"
TOPIC_BASE_STATE = "/starleth/base_state"
TOPIC_IMU = "/starleth/imu"
TOPIC_SOLVER = "/starleth/solver"
TOPIC_ROBOT_DESCRIPTION = "/robot_description"
TOPIC_EFFORT_COMMANDS = "/joint_group_effort_controller/commands"
TOPIC_JOINT_COMMANDS = "/joint_commands"
TOPIC_WRENCH = "~/wrench"
TOPIC_WRENCH_PERSISTENT = "~/wrench/persistent"


def foot_wrench_topic(foot: str) -> str:
    """/starleth/<foot>/wrench for a foot contact name such as 'LF_foot'."""
    return f"/starleth/{foot}/wrench"
