"""starleth-precompile (tools/precompile.py): compiles the kernels into numba's on-disk cache
in parallel processes, so that processes started later only load them; and the phase-by-phase
kernels are compiled once for both their profiled and unprofiled use."""
import glob
import io

import numpy as np
import pytest

from starleth_sim.physics.posture import PostureHold
from starleth_sim.physics.simulator import Simulator
from starleth_sim.tools import precompile as P


def test_every_unit_is_known_and_every_preset_is_covered():
    from starleth_sim.physics.config import PRESETS
    units = [u for u, _ in P.UNITS]
    assert len(units) == len(set(units))
    for kind in ("step", "profile", "prepare"):
        assert {f"{kind}:{p}" for p in PRESETS} <= set(units), kind
    assert {"controller", "ros-codec"} <= set(units)
    with pytest.raises(ValueError, match="unknown unit"):
        P.compile_unit("step")


def test_unknown_units_and_jobs_are_rejected_by_the_command_line(capsys):
    with pytest.raises(SystemExit) as e:
        P.main(["step:HmX"])
    assert e.value.code == 2 and "unknown unit(s) step:HmX" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        P.main(["--jobs", "0", "step:HmJ"])
    assert e.value.code == 2 and "--jobs must be at least 1" in capsys.readouterr().err


def test_worker_processes_write_the_cache_that_later_processes_load(tmp_path, monkeypatch):
    """The workers are fresh interpreters (spawn): they compile into the cache directory of
    the environment (here an empty NUMBA_CACHE_DIR, read by each worker's numba at import),
    and each unit is reported. (The cheap unit twice: a cold "step" unit takes minutes.)"""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    out = io.StringIO()
    wall, failed = P.precompile(jobs=2, units=["ros-codec", "ros-codec"], stream=out)
    assert failed == []
    lines = out.getvalue().splitlines()
    assert [line.split()[0] for line in lines] == ["ros-codec", "ros-codec"]
    assert wall > 0
    for kernel in ("parse_joint_command", "parse_effort_array"):
        assert glob.glob(str(tmp_path / "**" / f"cdr.{kernel}-*.nbi"), recursive=True), kernel
        assert glob.glob(str(tmp_path / "**" / f"cdr.{kernel}-*.nbc"), recursive=True), kernel


def test_phase_kernels_have_one_signature_for_profiled_prepared_and_pushed_steps():
    """The phase-by-phase kernels (a profiled step, a step prepared ahead, a step with a
    wrench) get a timings array, empty when not profiling: one compiled signature each,
    not one per use (each one more cost ≈ 45 s of cold compilation)."""
    from starleth_sim.physics import step_kernels as SK
    for profile in (True, False):
        sim = Simulator.from_preset("HmJ", profile=profile)
        hold = PostureHold(sim.joint_positions())
        sim.step(hold.torque(sim))
        sim.prepare()
        sim.step(hold.torque(sim))
        sim.apply_wrench("base", (10.0, 0.0, 0.0), duration=sim.control_period)
        sim.step(hold.torque(sim))
    for kernel in (SK.solve_hard_contacts, SK.prepare_hard_contacts,
                   SK.complete_hard_contacts):
        assert len(kernel.signatures) == 1, (kernel, kernel.signatures)
    # and the unprofiled run took no time into the (empty) array
    assert SK.NOT_TIMED.shape == (0,)
    assert np.all(sim.stepper.stats.timings == 0.0)


def test_a_failing_unit_is_reported_and_fails_the_command(monkeypatch, capsys):
    """A unit whose entry point raises is reported with its error; the other units still
    run, and the command exits with status 1 (make test goes on to the tests, which then
    say what is wrong)."""
    real = P.compile_unit

    def broken(unit):
        if unit == "ros-codec":
            raise RuntimeError("no parser today")
        return real(unit)
    monkeypatch.setattr(P, "compile_unit", broken)
    assert P.main(["--jobs", "1", "ros-codec", "step:HmJ"]) == 1
    out = capsys.readouterr()
    assert "ros-codec" in out.out and "FAILED: RuntimeError: no parser today" in out.out
    assert "step:HmJ" in out.out
    assert "1 unit(s) failed" in out.err and "ros-codec" in out.err
