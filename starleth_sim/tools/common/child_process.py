"""How the demo and the tests start node processes (ROS-free): the child's stop signals and
its parent's death.

* A shell without job control starts its background commands with SIGINT ignored, and a
  child inherits that; a node then ignores SIGINT until its own handler is installed, after
  its imports (a second or two), so a stop sent early waits for the time-out and a kill. The
  child gets the default dispositions back before it runs.
* A parent killed with SIGKILL (a test run stopped by its CI's time-out) cannot stop its
  nodes; Linux sends the child SIGTERM when the parent goes (PR_SET_PDEATHSIG), which ends a
  node as a SIGTERM from a user does. Elsewhere this part does nothing.

``stop_child`` stops one as a user's Ctrl-C would (the benchmarks' children).
``start_child_as_node`` is a ``preexec_fn`` for ``subprocess.Popen``; call Popen from the main
thread (the parent-death signal follows the thread that started the child).
"""
from __future__ import annotations

import ctypes
import signal
import subprocess
import sys

PR_SET_PDEATHSIG = 1


def _set_parent_death_signal(sig) -> None:
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0)
    except (OSError, AttributeError):
        pass


def start_child_as_node(then=None):
    """A preexec_fn: SIGINT and SIGTERM at their defaults, SIGTERM when the parent dies, then
    `then()` if given."""
    def preexec():
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        _set_parent_death_signal(signal.SIGTERM)
        if then is not None:
            then()
    return preexec


def stop_child(proc, timeout: float = 20.0):
    """Stop the child `proc` (a subprocess.Popen) as a user's Ctrl-C would: SIGINT (a node
    finalises its recording and prints its summary), then SIGKILL if it has not ended
    within `timeout` seconds. Returns its exit status, None if it had to be killed."""
    if proc.poll() is not None:
        return proc.returncode
    proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        return None
