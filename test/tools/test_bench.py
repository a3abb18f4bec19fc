"""starleth-bench --vs-mujoco: MuJoCo on the same URDF is the same robot doing the same
thing (a cross-check of mass, geometry and contact against an independent simulator: with
its feet sticking, the same posture above its soft contacts' sink), and a missing mujoco is
said plainly. Speed is the bench's business, not a test's."""
import builtins

import numpy as np
import pytest

from starleth_sim.tools.bench import bench


def _stand(runner, steps):
    """Settles `runner`, stands it `steps` more physics steps; how far its loaded feet
    moved meanwhile [m]."""
    runner.run(bench.SETTLE_STEPS)
    start = runner.contact_points()
    runner.run(steps)
    return bench.creep(runner, start)


def test_mujoco_model_is_our_robot_and_stands_like_ours():
    mujoco = pytest.importorskip("mujoco")
    ours = bench.SimulatorStanding("HmJ")
    _, model = bench.mujoco_model(ours.sim.description, 2.5e-3, 0.8)
    _, stick = bench.mujoco_model(ours.sim.description, 2.5e-3, 0.8, bench.NOSLIP_ITERATIONS)
    assert model.nv == ours.sim.coords.nv == 18
    assert model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert model.opt.solver == mujoco.mjtSolver.mjSOL_NEWTON
    assert (model.opt.noslip_iterations, stick.opt.noslip_iterations) == \
        (0, bench.NOSLIP_ITERATIONS)
    # the same mass, from the same URDF read by two parsers
    assert np.sum(model.body_mass) == pytest.approx(ours.sim.description.total_mass, rel=1e-9)
    soft = bench.MujocoStanding(mujoco, model, ours.sim)
    mj = bench.MujocoStanding(mujoco, stick, ours.sim)
    assert mj.weight == pytest.approx(ours.weight, rel=1e-3)
    # MuJoCo's regularised friction lets standing feet creep; its noslip pass and our
    # Coulomb law stick
    creep = [_stand(r, 2000) for r in (soft, mj, ours)]
    assert creep[0] > bench.CREEP_TOLERANCE > max(creep[1:])
    for r in (mj, ours):
        assert r.normal_force() / r.weight == pytest.approx(1.0, abs=bench.FORCE_TOLERANCE)
    # MuJoCo's soft contacts sink, our hard ones do not: the base is lower by the sink, the
    # posture above the feet is the same
    assert ours.sink() == pytest.approx(0.0, abs=1e-5) and mj.sink() > 1e-4
    assert ours.height() - mj.height() == pytest.approx(mj.sink(), abs=bench.HEIGHT_TOLERANCE)


def test_vs_mujoco_prints_the_table_and_the_check(capsys):
    pytest.importorskip("mujoco")
    assert bench.main(["--vs-mujoco", "--rounds", "1", "--steps", "100", "HmJ"]) == 0
    out = capsys.readouterr().out
    assert "MuJoCo" in out and "HmJ" in out and "like with like: yes" in out


def test_vs_mujoco_without_mujoco_says_so(monkeypatch, capsys):
    real_import = builtins.__import__

    def no_mujoco(name, *args, **kwargs):
        if name == "mujoco":
            raise ImportError("No module named 'mujoco'")
        return real_import(name, *args, **kwargs)
    monkeypatch.setattr(builtins, "__import__", no_mujoco)
    assert bench.main(["--vs-mujoco", "--rounds", "1", "--steps", "10", "HmJ"]) == 2
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1
    assert "mujoco is not installed" in out[0] and "requirements-bench.txt" in out[0]


def test_impedance_prints_both_steps_side_by_side(capsys):
    assert bench.main(["--impedance", "--rounds", "1", "--steps", "5", "HmJ", "Cm"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[2:]]
    assert [r[:2] for r in rows] == [["HmJ", "1"], ["Cm", "2"]]
    for r in rows:      # µs per control step, and their ratio
        torque, imp, ratio = (float(x) for x in r[2:])
        assert torque > 0 and imp > 0 and ratio == pytest.approx(imp / torque, abs=0.01)


def test_mujoco_model_of_another_robot_is_ours_reduced_to_our_contacts():
    """Go1 from its URDF: MuJoCo's model has its mass, its degrees of freedom and our
    contact points as its only collision geometry (the URDF's meshes, cylinders and boxes
    dropped), and stands on its four feet like ours."""
    mujoco = pytest.importorskip("mujoco")
    from starleth_sim.physics.config import ConfigError
    from starleth_sim.robots import load_robot, urdf_file
    try:
        urdf_file(load_robot("go1"))
    except ConfigError as e:
        pytest.skip(str(e))
    ours = bench.SimulatorStanding("HmJ", "go1")
    desc = ours.sim.description
    _, model = bench.mujoco_model(desc, 2.5e-3, 0.8)
    assert model.nv == ours.sim.coords.nv == 6 + len(desc.joint_names)
    assert np.sum(model.body_mass) == pytest.approx(desc.total_mass, rel=1e-6)
    spheres = model.geom_type == mujoco.mjtGeom.mjGEOM_SPHERE
    assert spheres.sum() == len(desc.contacts) == model.ngeom - 1      # and the ground
    radii = sorted(max(c.radius, bench.CORNER_RADIUS) for c in desc.contacts)
    assert sorted(model.geom_size[spheres, 0]) == pytest.approx(radii)
    _, stick = bench.mujoco_model(desc, 2.5e-3, 0.8, bench.NOSLIP_ITERATIONS)
    mj = bench.MujocoStanding(mujoco, stick, ours.sim)
    for r in (mj, ours):
        assert _stand(r, 2600) < bench.CREEP_TOLERANCE
        assert r.normal_force() / r.weight == pytest.approx(1.0, abs=bench.FORCE_TOLERANCE)
    assert mj.data.ncon == 4 and mj.loaded().sum() == 4       # the feet only
    assert ours.height() - mj.height() == pytest.approx(mj.sink(), abs=bench.HEIGHT_TOLERANCE)


def test_bad_robot_gives_one_line(capsys):
    assert bench.main(["--vs-mujoco", "--robot", "no_such_robot", "HmJ"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no_such_robot" in err[0]
