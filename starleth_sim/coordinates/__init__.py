"""Sets of generalized coordinates (minimal; extended and maximal follow in issue 6).

A coordinate set provides q, u, q ⊕ Δt u (F(q)), M, h, the contact force directions W_U,
bilateral directions W_B (none for the minimal set), and the mapping to joint angles and
base pose. The time-stepper and the contact laws are shared by all of them.
"""
from .minimal import MinimalCoordinates

__all__ = ["MinimalCoordinates"]
