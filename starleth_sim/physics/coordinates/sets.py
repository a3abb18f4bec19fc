"""The three sets of generalized coordinates of the paper (Eqn. 19-22, Table 1), all
instances of :class:`~starleth_sim.physics.coordinates.forest.ForestCoordinates`:

* minimal:  the kinematic tree on a free-flyer root, no bilateral constraints;
* extended: the subtrees hanging from the root (a quadruped's legs, at the HAA joints) cut
            free and re-attached by 5 bilateral constraints each;
* maximal:  every joint cut, each body a free rigid body with its frame at its centre of
            mass (constant mass matrix), 5 bilateral constraints per joint.
"""
from __future__ import annotations

from ..description import RobotDescription
from .forest import ForestCoordinates

# Each builder returns the ForestCoordinates of one set; the stepper sees no difference.


def minimal_coordinates(desc: RobotDescription) -> ForestCoordinates:
    return ForestCoordinates(desc, cut=(), name="minimal")


def extended_coordinates(desc: RobotDescription) -> ForestCoordinates:
    m = desc.model
    cut = [j for j in range(2, m.njoints) if m.parents[j] == 1]
    return ForestCoordinates(desc, cut=cut, name="extended")


def maximal_coordinates(desc: RobotDescription) -> ForestCoordinates:
    m = desc.model
    return ForestCoordinates(desc, cut=list(range(2, m.njoints)), com_frames=True,
                             name="maximal")


COORDINATE_SETS = {"minimal": minimal_coordinates, "extended": extended_coordinates,
                   "maximal": maximal_coordinates}


def make_coordinates(name: str, desc: RobotDescription,
                     second_surfaces: bool = False) -> ForestCoordinates:
    """The coordinate set `name` of `desc`; with second_surfaces (a terrain), two contact
    slots per contact sphere (ForestCoordinates.add_second_surface_slots)."""
    if name not in COORDINATE_SETS:
        raise ValueError(f"unknown coordinates '{name}' (known: {sorted(COORDINATE_SETS)})")
    coords = COORDINATE_SETS[name](desc)
    if second_surfaces:
        coords.add_second_surface_slots()
    return coords
