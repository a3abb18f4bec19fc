"""The benchmarks: starleth-bench (steps/s, beside MuJoCo), starleth-bench-ros (the ROS
interface of sim_node), starleth-bench-floor (the floor of the real loop) and bench.live (what
the live view costs)."""
