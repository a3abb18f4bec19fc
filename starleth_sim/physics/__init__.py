"""The physics core: the robot description, the coordinate sets, kinematics and dynamics,
the contact laws, the prox solvers, Moreau's time-stepping and the public `Simulator`.
Imports numpy and pinocchio only, never ROS; its kernels are C (``csrc/``, built and loaded
by :mod:`starleth_sim.physics.kernels`)."""
