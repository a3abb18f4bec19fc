"""The robot library: robot specs (``robots/<name>.yaml``: a robot's URDF, its contacts, feet,
standing height, the limits its URDF lacks, its physics overrides; doc/physics.md) and the
descriptions built from them. Reading specs and finding their URDFs is
starleth_interface.robot's (shared with the controllers); the library's API is here.

    from starleth_sim.robots import available_robots, robot_description
    desc = robot_description("go1")        # a library name, a spec path or a URDF path
    Simulator.from_preset("HmJ", robot="go1")
"""
from starleth_interface.robot.library import (
                                              INSTALL_HINT,
                                              available_robots,
                                              load_robot,
                                              package_dirs,
                                              robot_urdf,
                                              urdf_file,
)
from starleth_interface.robot.spec import RobotSpec

from ..physics.robot_build import (
                                              config_with_robot,
                                              description_from_spec,
                                              recorded_description,
                                              robot_description,
                                              spec_text,
                                              starleth_description,
)

__all__ = ["available_robots", "load_robot", "robot_description", "description_from_spec",
           "recorded_description", "spec_text",
           "starleth_description", "config_with_robot", "urdf_file", "robot_urdf", "package_dirs",
           "RobotSpec", "INSTALL_HINT"]
