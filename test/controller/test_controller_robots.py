"""The controller on every robot of the library, headless (Simulator + StarlethController, HmJ):
it stands 2 s at its trunk height (the scaled one of robot_params.py) and then trots at
0.3 m/s · √λ for 4 s, covering at least 0.8 x the commanded distance without a fall; its
leg kinematics are Pinocchio's; a robot that is not four 3-joint legs is refused in one line;
the foot wrench topics are ROS names for any foot name.
Figures (per robot): doc/performance.md."""
import numpy as np
import pinocchio as pin
import pytest
from robot_cases import ankle_urdf, needs_data

from starleth_controller import RobotModel
from starleth_controller import kernels as K
from starleth_controller.model import NotAQuadruped
from starleth_controller.node_parameters import default_wrench_topics
from starleth_controller.robot_params import params_for_robot
from starleth_interface.topics import foot_wrench_topic
from starleth_sim.robots import available_robots
from starleth_sim.tools.common.gait_run import run_gait

ROBOTS = available_robots()
STAND, TROT = 2.0, 4.0       # s


@pytest.mark.parametrize("name", ROBOTS)
def test_every_robot_stands_and_trots(name):
    needs_data(name)
    model = RobotModel(robot=name)
    height = params_for_robot(model).height
    stand = run_gait("HmJ", "stand", STAND, robot=name)
    assert stand["error"] is None and stand["max_tilt"] < 0.2
    # the trunk stays near its height reference (within 10 % of it, no fall)
    assert stand["min_height"] > 0.9 * height, (stand["min_height"], height)
    run = run_gait("HmJ", "trot", STAND + TROT, stand_time=STAND, robot=name)
    commanded = run["speed"] * TROT
    assert run["speed"] == pytest.approx(0.3 * np.sqrt(model.scale.length), rel=1e-12)
    assert run["error"] is None and run["max_tilt"] < 0.5
    assert run["min_height"] > 0.8 * height and not run["knee_trunk_contacts"]
    assert run["distance"] >= 0.8 * commanded, (run["distance"], commanded)


@pytest.mark.parametrize("name", ROBOTS)
def test_leg_kinematics_are_pinocchios(name):
    """Foot centres and their Jacobians (kernels.leg_kinematics) against Pinocchio's frames at
    random postures around the standing one, and IK(FK(q)) = q."""
    needs_data(name)
    m = RobotModel(robot=name)
    rng = np.random.default_rng(1)
    reach = m.geometry[0, 0] + m.geometry[0, 1] + m.geometry[0, 2]
    centre, contact = np.zeros((4, 3)), np.zeros((4, 3))
    Jf, Jc = np.zeros((4, 3, 3)), np.zeros((4, 3, 3))
    for _ in range(5):
        q = pin.neutral(m.model)
        q[:3] = rng.normal(size=3) * 0.1
        quat = rng.normal(size=4)
        q[3:7] = quat / np.linalg.norm(quat)
        qj = m.nominal_joint_positions(0.8 * reach) + rng.uniform(-0.2, 0.2, 12)
        q[m.iq] = qj
        pin.forwardKinematics(m.model, m.data, q)
        pin.computeJointJacobians(m.model, m.data, q)
        R = m.data.oMi[1].rotation
        K.leg_kinematics(qj, R, q[:3], m.hip, m.geometry, centre, contact, Jf, Jc)
        for k in range(4):
            joint = m.data.oMi[m.foot_joint[k]]
            p = joint.act(m.foot_local[k])
            J6 = pin.getJointJacobian(m.model, m.data, m.foot_joint[k], pin.LOCAL_WORLD_ALIGNED)
            Jv = J6[:3] - pin.skew(p - joint.translation) @ J6[3:]
            np.testing.assert_allclose(centre[k], p, atol=1e-10)
            np.testing.assert_allclose(Jf[k], Jv[:, m.leg_iv[k]], atol=1e-10)
            np.testing.assert_allclose(m.leg_ik(k, R.T @ (p - q[:3])), qj[3 * k:3 * k + 3],
                                       atol=1e-10)


def test_a_robot_without_four_3_joint_legs_is_refused_in_one_line(tmp_path):
    """StarlETH with an ankle on one leg (13 joints, 3 legs of 3 joints): one line naming
    the file and why."""
    path = ankle_urdf(tmp_path)
    with pytest.raises(NotAQuadruped) as e:
        RobotModel(robot=str(path))
    message = str(e.value)
    assert "\n" not in message and "ankle.urdf" in message
    assert "13 moving joints, 3 3-joint legs" in message


@pytest.mark.parametrize("foot, token", [("LF_foot", "LF_foot"), ("foot.1", "foot_1"),
                                         ("3rd leg", "_3rd_leg"), ("FL--FOOT", "FL_FOOT")])
def test_foot_wrench_topics_are_ros_names_for_any_foot_name(foot, token):
    """controller_node's default wrench topics (sim_node's rule) from any URDF name: a valid
    ROS topic name (rclpy's check), the name itself where it is one."""
    from rclpy.validate_topic_name import validate_topic_name
    topic = foot_wrench_topic(foot)
    assert topic == f"starleth/{token}/wrench"
    validate_topic_name(topic)
    assert default_wrench_topics([foot]) == [topic]


def figures(name):
    """The row of doc/performance.md's table of a robot: λ, μ, trot speed, commanded and
    covered distance, the trunk height standing (reference, and the base's at the end of the
    stand) and the lowest during the trot."""
    model = RobotModel(robot=name)
    stand = run_gait("HmJ", "stand", STAND, robot=name)
    run = run_gait("HmJ", "trot", STAND + TROT, stand_time=STAND, robot=name)
    commanded = run["speed"] * TROT
    return (f"| {name} | {model.mass:.2f} | {model.scale.length:g} | {model.scale.mass:g} | "
            f"{params_for_robot(model).height:.3f} | {stand['min_height']:.3f} | "
            f"{run['speed']:.3f} | {commanded:.3f} | {run['distance']:.3f} | "
            f"{run['distance'] / commanded:.2f} | {run['min_height']:.3f} |")


if __name__ == "__main__":     # the table of doc/performance.md
    print("| robot | mass [kg] | λ | μ | trunk height [m] | lowest standing [m] | trot "
          "[m/s] | commanded [m] | covered [m] | ratio | lowest trotting [m] |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for robot in ROBOTS:
        print(figures(robot), flush=True)
