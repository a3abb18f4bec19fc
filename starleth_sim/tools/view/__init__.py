"""Seeing a run: starleth-view (a recorded run as one self-contained HTML page),
starleth-layout (the Foxglove layout of robots under namespaces) and live_log (a client of
sim_node's live view)."""
