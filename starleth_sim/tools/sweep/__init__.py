"""starleth-sweep: a grid of headless runs with one results table."""
