"""Command-line tools over the physics core and the ROS layer: starleth-bench,
starleth-bench-ros, starleth-eval, starleth-analyze, starleth-demo, starleth-view."""
