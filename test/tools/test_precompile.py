"""starleth-precompile (tools/precompile.py): makes the C extensions ready side by side (the
physics kernels, the controller's kernels, sim_node's command parsers), so that processes
started later only load them; --cold measures a fresh clone's build without touching the
modules in use; a progress line says what builds."""
import importlib.util
import io
import os

import pytest

from starleth_interface import c_extension
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


def test_a_unit_builds_a_module_that_loads_with_its_functions(tmp_path):
    """compile_unit into a directory (--cold's): the module file and its digest, and the
    module loads with the functions its Python side uses."""
    for unit, functions in (("controller", ("leg_kinematics", "position_controlled_torques")),
                            ("ros-codec", ("parse_joint_command", "parse_effort_array"))):
        P.compile_unit(unit, str(tmp_path))
        module = P.MODULES[unit]
        csrc, name = c_extension.csrc_of(module), module.rpartition(".")[2]
        path = tmp_path / (name + c_extension.SUFFIX)
        assert (tmp_path / (path.name + c_extension.DIGEST_SUFFIX)).read_text().strip() == \
            c_extension.source_digest(csrc)
        spec = importlib.util.spec_from_file_location(name, path)
        loaded = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(loaded)
        assert all(callable(getattr(loaded, f)) for f in functions), unit


def test_cold_builds_every_unit_and_leaves_the_modules_in_use(capsys):
    """--cold: every unit into a temporary build directory (removed after), each unit's
    seconds and the total printed; the modules in use are left as they were."""
    from starleth_sim.physics.kernels import build as kernel_build
    in_use = [kernel_build.inplace_path()] + [c_extension.module_path(m)
                                              for m in P.MODULES.values()]
    before = [os.stat(m).st_mtime_ns if os.path.exists(m) else None for m in in_use]
    assert P.main(["--cold"]) == 0
    out = capsys.readouterr().out
    assert "cold compilation" in out and "total" in out
    for unit, _ in P.UNITS:
        assert any(line.split()[:1] == [unit] and line.rstrip().endswith(" s")
                   for line in out.splitlines()), (unit, out)
    assert [os.stat(m).st_mtime_ns if os.path.exists(m) else None for m in in_use] == before


def test_the_progress_line_says_what_compiles_and_for_how_long():
    """On a terminal: one line rewritten in place ("compiling kernels: <unit> <s> s (<s> of
    about <s> s)"), each finished unit on a line of its own; the estimate is the longest
    processing time first over the jobs."""
    out = Terminal()
    prog = P.Progress(out, ["physics", "controller", "ros-codec"], jobs=2)
    assert prog.estimate == max(P.ESTIMATE["physics"],
                                P.ESTIMATE["controller"] + P.ESTIMATE["ros-codec"])
    prog.begin()
    text = out.getvalue()
    assert "\rcompiling kernels: physics 0 s, controller 0 s" in text.replace("\033[K", "")
    prog.done("controller", 0.7, None)
    prog.done("physics", 2.5, None)
    prog.done("ros-codec", 3.0, "BuildError: no C compiler")
    prog.end()
    text = out.getvalue().replace("\033[K", "")
    assert "ros-codec 0 s" in text              # started when controller finished
    assert "  physics        2.5 s" in text and "FAILED: BuildError: no C compiler" in text


def test_a_failing_unit_is_reported_and_fails_the_command(monkeypatch, capsys):
    """No C compiler (CC names one that fails): each unit reports the build error and the
    command exits with status 1 (make test goes on to the tests, which then say what is
    wrong)."""
    monkeypatch.setenv("CC", "false")
    assert P.main(["--cold", "--jobs", "1", "ros-codec", "controller"]) == 1
    out = capsys.readouterr()
    assert out.out.count("FAILED: BuildError") == 2
    assert "2 unit(s) failed" in out.err and "ros-codec" in out.err
