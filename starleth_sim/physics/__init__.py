"""The physics core: the robot description, the coordinate sets, kinematics and dynamics,
the contact laws, the prox solvers, Moreau's time-stepping and the public `Simulator`.
Imports numpy, numba and pinocchio only, never ROS."""
import os as _os

from .kernel_cache import drop_stale_kernel_caches as _drop_stale_kernel_caches

# numba's cache does not see changes in other files than a kernel's own (kernel_cache)
_drop_stale_kernel_caches(_os.path.dirname(_os.path.abspath(__file__)))
