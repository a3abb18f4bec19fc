"""starleth-replay: a recorded run re-simulated open loop from its bag."""
