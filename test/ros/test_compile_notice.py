"""Compilation said out loud (starleth_interface.compile_notice): a block that compiles says so
within `after` seconds, again every `every` seconds, and how long it took; one that loads
from the cache says nothing; a start-up timeout counts only silence (compile lines in a
process's log restart it)."""
import time

import pytest

from starleth_interface.compile_notice import (SLOW_COMPILE_ENV, CompileNotice, Deadline,
                                               LogWatch, shows_compiling)


@pytest.mark.serial   # the length of a block
def test_a_long_block_says_it_compiles_and_how_long_it_took():
    lines = []
    with CompileNotice("the widgets", lines.append, estimate=9.0, after=0.05,
                       every=0.1) as notice:
        notice.compiling()
        time.sleep(0.6)
    assert notice.announced and 0.6 <= notice.seconds < 5.0
    assert lines[0].startswith("compiling the widgets (numba") and "about 9 s" in lines[0]
    assert any(line.startswith("still compiling the widgets: ") for line in lines[1:-1])
    assert lines[-1] == f"the widgets: compiled in {notice.seconds:.1f} s"
    assert all(shows_compiling(line) for line in lines)


def test_a_short_block_says_nothing():
    lines = []
    with CompileNotice("the widgets", lines.append, after=0.5) as notice:
        notice.compiling()
    assert lines == [] and not notice.announced


def test_a_block_that_loads_from_the_cache_says_nothing_however_long():
    """No compile event (numba loading its cache, or anything else slow): no compile line."""
    lines = []
    with CompileNotice("the widgets", lines.append, after=0.05) as notice:
        time.sleep(0.3)
    assert lines == [] and not notice.announced


def test_numba_compiling_in_the_block_is_said():
    """A numba function compiled in the block (no cache: a new function) is announced."""
    import numba
    lines = []

    @numba.njit
    def add(a, b):
        return a + b
    with CompileNotice("the adder", lines.append, after=0.0):
        add(1.0, 2.0)
        time.sleep(0.2)     # (the watcher's look, every 0.05 s)
    assert lines and lines[0].startswith("compiling the adder") and \
        lines[-1].startswith("the adder: compiled in"), lines


def test_a_failing_block_says_so_and_raises():
    lines = []
    try:
        with CompileNotice("the widgets", lines.append, after=0.0) as notice:
            notice.compiling()
            time.sleep(0.2)
            raise RuntimeError("broken")
    except RuntimeError:
        pass
    else:
        raise AssertionError("the error was swallowed")
    assert lines[-1].endswith("(failed)")


def test_the_slow_compile_stand_in_lengthens_every_block(monkeypatch):
    monkeypatch.setenv(SLOW_COMPILE_ENV, "0.3")
    lines = []
    with CompileNotice("the widgets", lines.append, after=0.1) as notice:
        pass
    assert notice.seconds >= 0.3 and lines[0].startswith("compiling the widgets")


@pytest.mark.serial   # deadlines
def test_a_deadline_counts_silence_not_compilation(tmp_path):
    """Expired `timeout` after the last compile line of the logs, however long before."""
    log = tmp_path / "node.log"
    log.write_text("[INFO] starting\n")
    d = Deadline(1.0, [log])
    for k in range(6):                    # 1.8 s of compile lines, every 0.3 s
        time.sleep(0.3)
        with open(log, "a") as f:
            f.write(f"[INFO] [node]: still compiling the kernels: {k} s\n")
        assert not d.expired()
    assert "still compiling the kernels: 5 s" in d.watch.last
    with open(log, "a") as f:             # other lines are not compilation
        f.write("[INFO] [node]: waiting for the robot description\n")
    time.sleep(1.1)
    assert d.expired()


def test_a_line_being_written_is_read_once_whole(tmp_path):
    log = tmp_path / "node.log"
    watch = LogWatch([log, tmp_path / "missing.log"])
    assert not watch.progress()
    log.write_text("[INFO] compil")
    assert not watch.progress()
    with open(log, "a") as f:
        f.write("ing the controller's kernels\n")
    assert watch.progress() and watch.last == "[INFO] compiling the controller's kernels"
    assert not watch.progress()
