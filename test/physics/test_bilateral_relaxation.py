"""The bilateral prox rows swept Gauss-Seidel with their own relaxation ω_B
(bilateral.relaxation; HMJP and HMSP: 1.5): the same fixed point as the paper's α/G_BB
rows, in far fewer sweeps on the maximal coordinates' chains (trotting, and lying at rest,
where the paper's rows crawl)."""
import numpy as np
import pytest
from test_bitexact import PUSH, trot_pd_torque

from starleth_sim import Simulator
from starleth_sim.physics.config import ConfigError

STEPS = 160              # control steps of test_bitexact's trot (it trots from step 100)
BEFORE_PUSH = 80         # steps before its push (after it, runs part chaotically)


def trot(preset, steps=STEPS, **overrides):
    """(states (q, u) of each step, mean prox iterations per step) of test_bitexact's run."""
    sim = Simulator.from_preset(preset, **overrides)
    q_stand = sim.joint_positions().copy()
    states, its = [], 0
    for k in range(steps):
        if k == int(round(PUSH[0] / sim.control_period)):
            sim.apply_wrench("base", PUSH[1], duration=PUSH[2])
        its += sim.step(trot_pd_torque(sim, q_stand, k)).iterations
        states.append(np.concatenate([sim.q, sim.u]))
    return np.array(states), its / steps


@pytest.mark.parametrize("preset", ["HMJP", "HMSP"])
def test_relaxed_bilateral_rows_solve_the_same_steps_in_fewer_sweeps(preset):
    assert Simulator.from_preset(preset).config.bilateral.relaxation == 1.5
    relaxed, its_relaxed = trot(preset)
    paper, its_paper = trot(preset, relaxation=0.0)
    assert its_relaxed < 0.75 * its_paper
    # the same physics: both as close to the direct method (Eqn. 20) solved tightly, within
    # what the tolerance T_rel = T_abs = 1e-6 leaves on slowly converging rows
    exact, _ = trot("HMJD", BEFORE_PUSH, tol_rel=1e-10, tol_abs=1e-10, max_iterations=100000)
    err_relaxed = np.abs(relaxed[:BEFORE_PUSH] - exact).max()
    err_paper = np.abs(paper[:BEFORE_PUSH] - exact).max()
    assert err_relaxed < 1e-3 and err_paper < 1e-3
    assert err_relaxed < 1.5 * err_paper


def test_a_fallen_robot_in_maximal_coordinates_solves_in_a_few_sweeps():
    # the paper's rows crawl at rest: each step's warm start carries the slow chain mode the
    # last solve left (its increments just under the tolerance); the relaxed rows clear it
    paper = Simulator.from_preset("HMJP", relaxation=0.0)
    zero = np.zeros(len(paper.joint_names))
    for _ in range(1200):                  # 3 s: collapsed, at rest on knees and trunk
        paper.step(zero)
    assert paper.q[2] < 0.15 and sum(c.active for c in paper.contacts) > 4
    start = paper.snapshot()
    crawling = [paper.step(zero).iterations for _ in range(40)]
    sim = Simulator.from_preset("HMJP")
    sim.restore(start)
    relaxed = [sim.step(zero).iterations for _ in range(40)]
    # (its first few solves clear the error the paper's solves left in the warm start)
    assert np.mean(relaxed[10:]) < 10 and np.mean(crawling) > 50
    assert np.abs(sim.q[:3] - paper.q[:3]).max() < 1e-4       # both lie where they lay


@pytest.mark.parametrize("overrides, message", [
    ({"relaxation": 2.0}, "bilateral.relaxation"),
    ({"relaxation": -0.5}, "bilateral.relaxation"),
    ({"relaxation": 1.5, "form": "velocity"}, "solver.form: delassus"),
])
def test_relaxation_is_validated(overrides, message):
    with pytest.raises(ConfigError, match=message):
        Simulator.from_preset("HEJP", **overrides)


@pytest.mark.parametrize("overrides", [{"method": "direct"}, {"alpha": "auto"}])
def test_relaxation_is_left_to_the_direct_method_and_auto(overrides):
    """HMJP's ω_B is not used where no bilateral prox row has a fixed α: bit for bit the
    same steps as without it."""
    with_it, _ = trot("HMJP", 20, **overrides)
    without, _ = trot("HMJP", 20, relaxation=0.0, **overrides)
    assert np.array_equal(with_it, without)
