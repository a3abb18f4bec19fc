"""StarlETH locomotion controller (pure Python, no ROS) and its ROS 2 node.

The pure controller (``StarlethController``) follows Gehring et al., ICRA 2013 ("Control of
dynamic gaits for a quadrupedal robot") and its open-source descendant loco: virtual model
control of the trunk distributed onto the support feet by a QP (ProxQP), inverted-pendulum
foot placement and joint-space swing-leg control. Modes ``stand`` and ``trot``.

    from starleth_controller import StarlethController, RobotState, Command
    ctrl = StarlethController(urdf_path)            # URDF path or XML text
    tau = ctrl.update(RobotState.from_simulator(sim), Command("trot", forward=0.3))
"""
from .controller import StarlethController, SUPPORT, SWING, LOST_CONTACT
from .inputs import RobotState, Command, ControllerParams, VMCGains
from .force_distribution import ContactForceDistribution
from .model import RobotModel, JOINT_NAMES, LEGS, default_urdf_path

__all__ = ["StarlethController", "RobotState", "Command", "ControllerParams", "VMCGains",
           "ContactForceDistribution", "RobotModel", "JOINT_NAMES", "LEGS", "default_urdf_path",
           "SUPPORT", "SWING", "LOST_CONTACT"]
