"""Sets of generalized coordinates: minimal, extended and maximal (see ``minimal.py``).

A coordinate set provides q, u, q ⊕ Δt F(q) u, M, h, the contact force directions W_U, the
bilateral constraint directions W_B with their position-level violation g_B, and the mapping
to joint angles and base pose. The time-stepper and the contact laws are shared by all.
"""
from .forest import ForestCoordinates
from .minimal import (COORDINATE_SETS, ExtendedCoordinates, MaximalCoordinates,
                      MinimalCoordinates, make_coordinates)

__all__ = ["ForestCoordinates", "MinimalCoordinates", "ExtendedCoordinates",
           "MaximalCoordinates", "make_coordinates", "COORDINATE_SETS"]
