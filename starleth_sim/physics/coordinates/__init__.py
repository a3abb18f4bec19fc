"""Sets of generalized coordinates: minimal, extended and maximal (see ``sets.py``).

A coordinate set provides q, u, q ⊕ Δt F(q) u, M, h, the contact force directions W_U, the
bilateral constraint directions W_B with their position-level violation g_B, and the mapping
to joint angles and base pose. The time-stepper and the contact laws are shared by all.
"""
from .forest import ForestCoordinates
from .sets import (
                   COORDINATE_SETS,
                   extended_coordinates,
                   make_coordinates,
                   maximal_coordinates,
                   minimal_coordinates,
)

__all__ = ["ForestCoordinates", "minimal_coordinates", "extended_coordinates",
           "maximal_coordinates", "make_coordinates", "COORDINATE_SETS"]
