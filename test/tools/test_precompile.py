"""starleth-precompile (tools/precompile.py): makes the kernels ready in parallel processes
(the C physics kernels, the controller's and the ROS codec's numba kernels into numba's
on-disk cache), so that processes started later only load them; --cold measures a first run
without touching the caches in use; a progress line says what compiles."""
import glob
import io
import os

import pytest

from starleth_sim.tools import precompile as P


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_every_unit_is_known_and_the_command_line_rejects_the_rest(capsys):
    units = [u for u, _ in P.UNITS]
    assert sorted(units) == ["controller", "physics", "ros-codec"]
    with pytest.raises(ValueError, match="unknown unit"):
        P.compile_unit("step:HmJ")
    with pytest.raises(SystemExit) as e:
        P.main(["step:HmJ"])
    assert e.value.code == 2 and "unknown unit(s) step:HmJ" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        P.main(["--jobs", "0", "ros-codec"])
    assert e.value.code == 2 and "--jobs must be at least 1" in capsys.readouterr().err


def test_worker_processes_write_the_cache_that_later_processes_load(tmp_path, monkeypatch):
    """The workers are fresh interpreters (spawn): they compile into the cache directory of
    the environment (here an empty NUMBA_CACHE_DIR, read by each worker's numba at import),
    and each unit is reported, with a line as it starts (not a terminal)."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    out = io.StringIO()
    wall, failed = P.precompile(jobs=2, units=["ros-codec", "physics"], stream=out)
    assert failed == [] and wall > 0
    lines = out.getvalue().splitlines()
    assert sorted(line.split()[0] for line in lines if "compiling" not in line) == \
        ["physics", "ros-codec"]
    assert sum("compiling" in line for line in lines) == 2
    for kernel in ("parse_joint_command", "parse_effort_array"):
        assert glob.glob(str(tmp_path / "**" / f"cdr.{kernel}-*.nbi"), recursive=True), kernel
        assert glob.glob(str(tmp_path / "**" / f"cdr.{kernel}-*.nbc"), recursive=True), kernel


def test_cold_compiles_into_an_empty_cache_and_leaves_the_one_in_use(tmp_path, monkeypatch,
                                                                     capsys):
    """--cold: every unit into a temporary NUMBA_CACHE_DIR and build directory (removed
    after), each unit's seconds and the total printed; the cache of the environment and the
    built physics module are left as they were."""
    from starleth_sim.physics import kernel_build
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    module = kernel_build.inplace_path()
    before = os.stat(module).st_mtime_ns if os.path.exists(module) else None
    assert P.main(["--cold", "ros-codec", "physics"]) == 0
    out = capsys.readouterr().out
    assert "cold compilation" in out and "total" in out
    for unit in ("ros-codec", "physics"):
        assert any(line.split()[:1] == [unit] and line.rstrip().endswith(" s")
                   for line in out.splitlines()), (unit, out)
    assert os.listdir(tmp_path) == []           # the real cache: untouched
    after = os.stat(module).st_mtime_ns if os.path.exists(module) else None
    assert after == before
    assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path)


def test_the_progress_line_says_what_compiles_and_for_how_long():
    """On a terminal: one line rewritten in place ("compiling kernels: <unit> <s> s (<s> of
    about <s> s)"), each finished unit on a line of its own; the estimate is the longest
    processing time first over the processes."""
    out = Terminal()
    prog = P.Progress(out, ["controller", "ros-codec", "physics"], jobs=2)
    assert prog.estimate == max(P.ESTIMATE["controller"],
                                P.ESTIMATE["ros-codec"] + P.ESTIMATE["physics"])
    prog.begin()
    text = out.getvalue()
    assert "\rcompiling kernels: controller 0 s, ros-codec 0 s" in text.replace("\033[K", "")
    prog.done("ros-codec", 2.5, None)
    prog.done("controller", 9.0, None)
    prog.done("physics", 3.0, "BuildError: no C compiler")
    prog.end()
    text = out.getvalue().replace("\033[K", "")
    assert "physics 0 s" in text                # started when ros-codec finished
    assert "  controller     9.0 s" in text and "FAILED: BuildError: no C compiler" in text


def test_a_failing_unit_is_reported_and_fails_the_command(tmp_path, monkeypatch, capsys):
    """No C compiler (CC names one that fails): the physics unit reports the build error,
    the other units still run, and the command exits with status 1 (make test goes on to
    the tests, which then say what is wrong)."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CC", "false")
    assert P.main(["--cold", "--jobs", "1", "physics", "ros-codec"]) == 1
    out = capsys.readouterr()
    assert "physics" in out.out and "FAILED: BuildError" in out.out
    assert "ros-codec" in out.out
    assert "1 unit(s) failed" in out.err and "physics" in out.err
