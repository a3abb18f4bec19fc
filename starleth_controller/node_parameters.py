"""The parameters of ``controller_node``: one schema (type, default, description, bounds) that
gives the ``declare_parameter`` descriptors and the checks of the values, at start-up
(``check_parameters``) and when one is set at runtime. No rclpy."""
from __future__ import annotations

from starleth_interface.ros_helpers import (
    CPU_SCHEDULING,
    CPU_SCHEDULING_HELP,
    EXECUTORS,
    ParameterSpec,
)
from starleth_interface.topics import (
    TOPIC_BASE_STATE,
    TOPIC_ESTIMATOR_ODOMETRY,
    TOPIC_FOOT_CONTACTS,
    TOPIC_IMU,
    TOPIC_JOINT_COMMANDS,
    TOPIC_JOINT_STATES,
    TOPIC_STATE_BUNDLE,
    foot_wrench_topic,
)

from .estimator import ESTIMATOR_PARAMETERS, EstimatorParams
from .inputs import MODES, ControllerParams


def default_wrench_topics(foot_names) -> list:
    """The foot wrench topics of a robot's feet (its foot contact names, the robot's foot
    order): the simulator's names (topics.foot_wrench_topic)."""
    return [foot_wrench_topic(f) for f in foot_names]


P = ParameterSpec
#: the node's parameters: type, default, description, bounds (one schema: it gives the
#: declare_parameter descriptors and the checks). Every number has a range: the contact
#: threshold up to 1000 N (StarlETH weighs ~250 N: a higher one never sees a contact), the
#: velocity clips up to 10 m/s and 10 rad/s (the trot is < 1 m/s), the periods up to 1 hour.
PARAMETERS = (
    P("mode", str, "stand", "stand | trot; settable at runtime (also through the ~/trot "
      "service)", read_only=False, choices=MODES),
    P("robot", str, "starleth", "the robot: a library name (robots/<name>.yaml: starleth, go1, "
      "...), a robot spec or a URDF path; its URDF and spec give the controller's model, "
      "feet and scaled gains (doc/controllers.md)"),
    P("urdf", str, "", "URDF path or XML text for the controller's model instead of `robot` "
      "(no spec: feet found on the legs, gains scaled by its size); empty = `robot`"),
    P("robot_description", bool, False, "true: build the model from the robot_description "
      "topic (transient local) instead of `urdf`"),
    P("joint_commands_topic", str, TOPIC_JOINT_COMMANDS, "sensor_msgs/JointState command "
      "topic (names + effort, stamped with the state answered); empty = off"),
    P("effort_array_topic", str, "", "also publish a std_msgs/Float64MultiArray of the 12 "
      "torques on this topic (e.g. /joint_group_effort_controller/commands); empty = off. Do "
      "not send both to a lockstep simulator."),
    P("state_input", str, "auto", "auto: the public state topics until a state bundle "
      "arrives, then the bundle alone | bundle | topics", choices=("auto", "bundle", "topics")),
    P("state_bundle_topic", str, TOPIC_STATE_BUNDLE, "std_msgs/Float64MultiArray state "
      "bundle input (sim_node's; layout in starleth_interface.state_bundle)"),
    P("joint_states_topic", str, TOPIC_JOINT_STATES, "sensor_msgs/JointState input"),
    P("state_source", str, "ground_truth", "ground_truth: the base state of base_state_topic "
      "(the simulator's) | estimator: the state estimator's (doc/estimator.md) from the "
      "joint states, the IMU and the foot contacts alone (no base state, no state bundle)",
      choices=("ground_truth", "estimator")),
    P("base_state_topic", str, TOPIC_BASE_STATE, "nav_msgs/Odometry input (ground truth)"),
    P("imu_topic", str, TOPIC_IMU, "sensor_msgs/Imu input (state_source estimator): "
      "orientation, angular velocity and proper acceleration, base frame"),
    P("foot_contacts_topic", str, TOPIC_FOOT_CONTACTS, "sensor_msgs/JointState input "
      "(state_source estimator): name = the feet's contact names, position = 1.0 contact / "
      "0.0 none"),
    P("estimator_odometry_topic", str, TOPIC_ESTIMATOR_ODOMETRY, "nav_msgs/Odometry output "
      "of the estimate every control step (state_source estimator; twist in the base "
      "frame); empty = off"),
    P("foot_wrench_topics", list, [], "geometry_msgs/WrenchStamped inputs, one per foot in "
      "the robot's foot order (its legs'); empty = starleth/<foot contact name>/wrench of "
      "each foot, sim_node's names"),
    P("cmd_vel_topic", str, "cmd_vel", "geometry_msgs/Twist velocity command"),
    P("twist_frame", str, "child", "frame of the Odometry twist's linear velocity: child "
      "(base, REP 105) | parent (world)", choices=("child", "parent")),
    P("contact_force_threshold", float, ControllerParams.contact_force_threshold,
      "a foot is in contact when |force| exceeds this times μ, the robot's mass over "
      "StarlETH's (doc/controllers.md) [N]", read_only=False, minimum=0.0, maximum=1000.0),
    P("max_linear_speed", float, 0.6, "clip of |(linear.x, linear.y)| of /cmd_vel [m/s]",
      read_only=False, minimum=0.0, maximum=10.0),
    P("max_yaw_rate", float, 1.0, "clip of |angular.z| of /cmd_vel [rad/s]", read_only=False,
      minimum=0.0, maximum=10.0),
    P("cmd_vel_timeout", float, 0.0, "seconds (the node's clock: sim time with use_sim_time) "
      "after the last cmd_vel when the velocity command falls back to zero; 0 = never",
      read_only=False, minimum=0.0, maximum=3600.0),
    P("state_reliability", str, "reliable", "QoS reliability of the state subscriptions: "
      "reliable | best_effort", choices=("reliable", "best_effort")),
    P("warn_throttle_period", float, 2.0, "minimum seconds between two warnings of the same "
      "problem (a kind and what it names)", read_only=False, minimum=0.0, maximum=3600.0),
    P("executor", str, "events", "events (rclpy's C++ EventsExecutor) | single_threaded",
      choices=EXECUTORS),
    P("cpu_scheduling", str, "default", CPU_SCHEDULING_HELP, choices=CPU_SCHEDULING),
    *(P(f"estimator.{name}", float, getattr(EstimatorParams, name), text, minimum=0.0,
        maximum=1e6) for name, text in ESTIMATOR_PARAMETERS),
    P("estimator.rolling_feet", bool, True, "the feet in contact roll with their shanks (the "
      "foot sphere's centre moves ρ ω × e_z; hard contacts, the robot); false: they stand "
      "still (the compliant preset Cm's feet, held by their tangential springs)"),
)
PARAMETERS_BY_NAME = {p.name: p for p in PARAMETERS}


def estimator_params(p) -> EstimatorParams:
    """The estimator's parameters of the node's (`p`: name -> value)."""
    return EstimatorParams(rolling_feet=bool(p["estimator.rolling_feet"]),
                           **{name: float(p[f"estimator.{name}"])
                              for name, _ in ESTIMATOR_PARAMETERS})


def check_parameters(p) -> None:
    """ValueError listing every parameter (`p`: name -> value) that breaks its schema."""
    errors = []
    for spec in PARAMETERS:
        try:
            spec.check(p[spec.name])
        except ValueError as e:
            errors.append(str(e))
    topics = p["foot_wrench_topics"]
    if not errors and topics and (len(topics) != 4 or
                                  not all(isinstance(t, str) and t for t in topics)):
        errors.append(f"parameter foot_wrench_topics: expected 4 topic names (the robot's "
                      f"feet in its legs' order) or none, got {topics!r}")
    if not errors and p["state_source"] == "estimator" and p["state_input"] == "bundle":
        errors.append("parameter state_input: bundle carries ground truth; state_source "
                      "estimator reads the sensor topics (state_input auto or topics)")
    if errors:
        raise ValueError("; ".join(errors))
