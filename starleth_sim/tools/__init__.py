"""Command-line tools over the physics core and the ROS layer, one sub-package per job:
demo (starleth-demo), bench (starleth-bench, starleth-bench-ros, starleth-bench-floor),
view (starleth-view, starleth-layout), analysis (starleth-analyze), evaluation
(starleth-eval), replay (starleth-replay), sweep (starleth-sweep); common holds what several
of them use; precompile (starleth-precompile) makes the kernels ready."""
