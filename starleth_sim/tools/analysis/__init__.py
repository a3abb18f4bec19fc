"""starleth-analyze: plots and a summary of recorded runs."""
