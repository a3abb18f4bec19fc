"""The stand / trot locomotion controller, after StarlETH's (pure Python, no ROS), for any
robot of four 3-joint legs (its model from the robot's URDF and spec, its gains scaled to
the robot: model.py, robot_params.py), and its ROS 2 node.

The pure controller (``StarlethController``) follows Gehring et al., ICRA 2013 ("Control of
dynamic gaits for a quadrupedal robot") and its open-source descendant loco: virtual model
control of the trunk distributed onto the support feet by a QP (ProxQP), inverted-pendulum
foot placement and joint-space swing-leg control. Modes ``stand`` and ``trot``.

    from starleth_controller import StarlethController, RobotState, Command
    ctrl = StarlethController(robot="go1")          # a library name, a spec or URDF path
    tau = ctrl.update(RobotState.from_simulator(sim), Command("trot", forward=0.3))
"""
from .controller import LOST_CONTACT, SUPPORT, SWING, StarlethController
from .force_distribution import ContactForceDistribution
from .inputs import Command, ControllerParams, RobotState, VMCGains
from .model import JOINT_NAMES, LEGS, RobotModel, default_urdf_path

__all__ = ["StarlethController", "RobotState", "Command", "ControllerParams", "VMCGains",
           "ContactForceDistribution", "RobotModel", "JOINT_NAMES", "LEGS", "default_urdf_path",
           "SUPPORT", "SWING", "LOST_CONTACT"]
