"""The node processes the demo and the tests start (starleth_sim.tools.common.child_process): a stop
signal is obeyed from the child's first instruction even where the parent runs with SIGINT
ignored (a background job of a shell without job control), and a child whose parent is
killed is ended, not orphaned."""
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from starleth_sim.tools.common.child_process import start_child_as_node

# the child: report when it is running, then sleep; a SIGINT ends it with KeyboardInterrupt
SLEEPER = "import sys, time; print('up', flush=True); time.sleep(60)"


def test_sigint_ends_a_child_started_from_a_parent_that_ignores_it():
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        plain = subprocess.Popen([sys.executable, "-c", SLEEPER], stdout=subprocess.PIPE)
        child = subprocess.Popen([sys.executable, "-c", SLEEPER], stdout=subprocess.PIPE,
                                 preexec_fn=start_child_as_node())
    finally:
        signal.signal(signal.SIGINT, old)
    try:
        for p in (plain, child):
            assert p.stdout.readline().strip() == b"up"
            p.send_signal(signal.SIGINT)
        # the child stops at once; the plain one inherited SIG_IGN and sleeps on (the case
        # the helper exists for: without it this check would not tell anything)
        assert child.wait(5) != 0
        with pytest.raises(subprocess.TimeoutExpired):
            plain.wait(0.5)
    finally:
        for p in (plain, child):
            p.kill()
            p.wait()


def alive(pid) -> bool:
    """The process exists and is not a zombie (a container's init may never reap it)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_child_whose_parent_is_killed_is_ended():
    parent = textwrap.dedent(f"""
        import subprocess, sys, time
        from starleth_sim.tools.common.child_process import start_child_as_node
        c = subprocess.Popen([sys.executable, "-c", {SLEEPER!r}], stdout=subprocess.DEVNULL,
                             preexec_fn=start_child_as_node())
        print(c.pid, flush=True)
        time.sleep(60)
    """)
    p = subprocess.Popen([sys.executable, "-c", parent], stdout=subprocess.PIPE)
    pid = int(p.stdout.readline())
    p.kill()                           # SIGKILL: the parent cannot stop its child itself
    p.wait()
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and alive(pid):
        time.sleep(0.05)
    if alive(pid):
        os.kill(pid, signal.SIGKILL)
        pytest.fail("the child outlived its killed parent by 10 s")


def test_stop_child_interrupts_and_kills_one_that_does_not_stop():
    """stop_child: a child that obeys SIGINT ends with its own status; one that ignores it is
    killed after the time-out (None)."""
    from starleth_sim.tools.common.child_process import stop_child
    ignoring = "import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); " \
               "print('up', flush=True); time.sleep(60)"
    obeying = subprocess.Popen([sys.executable, "-c", SLEEPER], stdout=subprocess.PIPE,
                               preexec_fn=start_child_as_node())
    deaf = subprocess.Popen([sys.executable, "-c", ignoring], stdout=subprocess.PIPE)
    for p in (obeying, deaf):
        assert p.stdout.readline().strip() == b"up"
    assert stop_child(obeying, 5.0) not in (0, None)    # KeyboardInterrupt: status 1
    t0 = time.monotonic()
    assert stop_child(deaf, 0.5) is None and deaf.poll() is not None
    assert time.monotonic() - t0 < 5.0
    assert stop_child(deaf) == deaf.returncode          # already ended: its status
