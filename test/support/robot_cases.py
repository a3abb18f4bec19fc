"""Robots the tests share: a library robot's data (skipped without it) and a robot the
controller cannot drive (StarlETH with an ankle on one leg)."""
from __future__ import annotations

import pytest

from starleth_interface.config_checks import ConfigError
from starleth_sim.physics.description import urdf_path
from starleth_sim.robots import load_robot, urdf_file


def needs_data(name):
    """Skips (with the one-line reason, which says `make robots`) when the robot's URDF is
    missing."""
    try:
        urdf_file(load_robot(name))
    except ConfigError as e:
        pytest.skip(str(e))


def ankle_urdf_text() -> str:
    """StarlETH with a revolute ankle (and its mass) on the LF foot: 13 joints, 3 legs of 3
    joints."""
    with open(urdf_path()) as f:
        urdf = f.read()
    ankle = urdf.replace('<joint name="LF_FOOT_FIXED" type="fixed">',
                         '<joint name="LF_ANKLE" type="revolute"><axis xyz="0 1 0"/>'
                         '<limit lower="-1" upper="1" effort="5" velocity="10"/>')
    return ankle.replace('<link name="LF_FOOT">', '<link name="LF_FOOT"><inertial><mass '
                         'value="0.05"/><inertia ixx="1e-3" ixy="0" ixz="0" iyy="1e-3" '
                         'iyz="0" izz="1e-3"/></inertial>')


def ankle_urdf(tmp_path) -> str:
    """ankle_urdf_text written to tmp_path/ankle.urdf; its path."""
    path = tmp_path / "ankle.urdf"
    path.write_text(ankle_urdf_text())
    return str(path)
