"""Builds told from silence (starleth_interface.compile_notice): the build lines of the C
extensions (the physics kernels', the controller's, sim_node's command parsers') are what a
start-up timeout reads as progress; it counts only silence."""
import io
import os
import shutil
import time

import pytest

from starleth_interface import c_extension
from starleth_interface.compile_notice import Deadline, LogWatch, shows_compiling


def test_a_build_says_so_in_lines_a_deadline_reads_and_a_current_module_says_nothing(
        tmp_path):
    """ensure_built (a source checkout's first use of an extension): a line as it starts and
    one with its time, both build lines; the module is then current: nothing built, nothing
    said; an edit of a source builds it again."""
    csrc = tmp_path / "csrc"
    shutil.copytree(os.path.join(c_extension.HERE, "..", "starleth_sim", "ros", "csrc"), csrc)
    path = str(tmp_path / ("_cdr" + c_extension.SUFFIX))
    out = io.StringIO()
    assert c_extension.ensure_built(str(csrc), path, "the widgets", stream=out)
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("compiling the widgets") and "compiled in" in lines[1]
    assert all(shows_compiling(line) for line in lines) and len(lines) == 2
    out = io.StringIO()
    assert not c_extension.ensure_built(str(csrc), path, "the widgets", stream=out)
    assert out.getvalue() == ""
    with open(csrc / "cdr.c", "a") as f:
        f.write("\n/* an edit */\n")
    assert c_extension.ensure_built(str(csrc), path, "the widgets", stream=io.StringIO())


def test_the_physics_build_lines_are_build_lines_and_others_are_not():
    assert shows_compiling("compiling the physics kernels (C, once per change of their sources)")
    assert shows_compiling("\rcompiling the physics kernels (C): 3/21 sources, 1 s ")
    assert shows_compiling("the physics kernels: compiled in 2.1 s")
    assert not shows_compiling("[INFO] [sim_node]: waiting for the robot description")
    assert not shows_compiling("the rebuilding crew")


@pytest.mark.serial   # deadlines
def test_a_deadline_counts_silence_not_compilation(tmp_path):
    """Expired `timeout` after the last build line of the logs, however long before."""
    log = tmp_path / "node.log"
    log.write_text("[INFO] starting\n")
    d = Deadline(1.0, [log])
    for k in range(6):                    # 1.8 s of build lines, every 0.3 s
        time.sleep(0.3)
        with open(log, "a") as f:
            f.write(f"[INFO] [node]: still compiling the kernels: {k} s\n")
        assert not d.expired()
    assert "still compiling the kernels: 5 s" in d.watch.last
    with open(log, "a") as f:             # other lines are not builds
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
