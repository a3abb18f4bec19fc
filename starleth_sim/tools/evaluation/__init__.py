"""starleth-eval: the paper's evaluation, headless, with its tasks and report."""
