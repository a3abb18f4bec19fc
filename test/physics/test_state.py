"""The simulation state (starleth_sim.physics.state.SimState): a snapshot is a deep copy,
restoring one replays the same steps bit for bit, and a SimulationError rolls the state
back; the profiled and the prepared step (options of the one kernel) are the plain step."""
import copy
import pickle

import numpy as np
import pytest

from starleth_sim import SimulationError, Simulator
from starleth_sim.physics.diagnostics import FIELD_NAMES


def pd(sim, q_stand):
    return 120.0 * (q_stand - sim.joint_positions()) - 3.0 * sim.joint_velocities()


def run(sim, q_stand, n):
    out = []
    for _ in range(n):
        sim.step(pd(sim, q_stand))
        out.append(np.concatenate([sim.q, sim.u, np.ravel([c.impulse for c in sim.contacts])]))
    return np.array(out)


@pytest.mark.parametrize("preset", ["HmJ", "Cm", "HEJD"])
def test_restore_replays_bit_for_bit(preset):
    sim = Simulator.from_preset(preset)
    q_stand = sim.joint_positions().copy()
    run(sim, q_stand, 20)
    sim.apply_wrench("base", (30.0, 0.0, 0.0), duration=0.02)   # a timed wrench in flight
    run(sim, q_stand, 2)
    snap = sim.snapshot()
    t0, qd0 = sim.t, sim.joint_velocities()
    first = run(sim, q_stand, 15)
    assert snap.t == t0 and not np.shares_memory(snap.q, sim.state.q)
    sim.restore(snap)
    assert sim.t == t0
    np.testing.assert_array_equal(sim.joint_velocities(), qd0)   # no stale φ̇ cache
    np.testing.assert_array_equal(run(sim, q_stand, 15), first)
    sim.restore(snap)                                             # a snapshot is reusable
    np.testing.assert_array_equal(run(sim, q_stand, 15), first)


def contact_memory(state):
    """The contact memory of either contact model (hard: Λ and the active flags of the last
    step; compliant: closed, slip, anchors and forces of Alg. 1) and Λ_B of the bilateral
    constraints (empty in the minimal coordinates), and the prox's α memory."""
    arrays = (state.last_impulse, state.last_active, state.closed, state.slip, state.anchor,
              state.lam_compliant, state.last_bilateral, state.prox_memory)
    return [a.copy() for a in arrays if a is not None]


# every step is one kernel call, which must leave the state as it was (HmJ, Cm, HEJD, HMSD
# with its constant M, and profiled)
@pytest.mark.parametrize("preset, profile", [("HmJ", False), ("Cm", False), ("HEJD", False),
                                             ("HMSD", False), ("HEJD", True)])
@pytest.mark.parametrize("poison", ["nan velocity", "overflowing joint rate in the air"])
def test_failed_step_restores_the_state(preset, profile, poison):
    sim = Simulator.from_preset(preset, profile=profile)
    q_stand = sim.joint_positions().copy()
    run(sim, q_stand, 10)
    before = sim.snapshot()
    memory = contact_memory(before)
    assert any(np.any(a) for a in memory)          # standing: the memory is not all zero
    # poison the state: the step must fail and roll back. NaN fails at the mass matrix,
    # before anything is written. A joint rate of 1e300 rad/s with the robot lifted 1 m
    # (no contact in the active set, none closed) leaves M finite but makes h and u^E
    # infinite (the velocity-product terms overflow): the minimal-coordinate step fails at
    # its end, after the contact memory was updated (to "no contact")
    if poison == "nan velocity":
        sim.state.u[:] = np.nan
    else:
        sim.state.q[2] += 1.0
        sim.state.u[6] = 1e300
    poisoned = sim.snapshot()
    with pytest.raises(SimulationError):
        sim.step(np.zeros(12))
    np.testing.assert_array_equal(sim.state.q, poisoned.q)
    np.testing.assert_array_equal(sim.state.u, poisoned.u)
    assert sim.t == before.t
    for got, want in zip(contact_memory(sim.state), memory, strict=True):
        np.testing.assert_array_equal(got, want)


def test_a_failure_in_a_later_physics_step_of_the_period_undoes_the_earlier_ones():
    """Cm steps twice per control period, each physics step in its own kernel call
    (Simulator._control_period): when the second fails, the first is undone as well, and the
    reports stay those of the last period."""
    sim = Simulator.from_preset("Cm")
    assert sim.config.steps_per_control == 2
    q_stand = sim.joint_positions().copy()
    run(sim, q_stand, 10)
    before = sim.snapshot()
    memory = contact_memory(before)
    impulses = [c.impulse.copy() for c in sim.contacts]
    stepper = sim.stepper
    kernel_step = stepper.step
    moved = []

    def second_fails(*args, **kwargs):
        if moved:
            raise SimulationError("injected failure of the second physics step")
        out = kernel_step(*args, **kwargs)
        moved.append(not np.array_equal(sim.state.q, before.q))
        return out

    stepper.step = second_fails
    with pytest.raises(SimulationError, match="injected"):
        sim.step(pd(sim, q_stand))
    assert moved == [True]              # the first physics step had changed the state
    np.testing.assert_array_equal(sim.state.q, before.q)
    np.testing.assert_array_equal(sim.state.u, before.u)
    assert sim.t == before.t
    for got, want in zip(contact_memory(sim.state), memory, strict=True):
        np.testing.assert_array_equal(got, want)
    for c, want in zip(sim.contacts, impulses, strict=True):
        np.testing.assert_array_equal(c.impulse, want)
    # and it steps on as a simulator restored to that state does
    del stepper.step
    other = Simulator.from_preset("Cm")
    other.restore(before)
    np.testing.assert_array_equal(run(sim, q_stand, 5), run(other, q_stand, 5))


@pytest.mark.parametrize("preset", ["HmJ", "Cm", "HEJD", "HMSD"])
def test_profiled_step_is_the_same_step(preset):
    plain = Simulator.from_preset(preset)
    prof = Simulator.from_preset(preset, profile=True)
    q_stand = plain.joint_positions().copy()
    np.testing.assert_array_equal(run(prof, q_stand, 30), run(plain, q_stand, 30))
    for field in ("iterations", "max_iterations_step", "converged", "active_contacts",
                  "physics_steps", "projections", "loaded_contacts_opened_total"):
        assert getattr(prof.diagnostics, field) == getattr(plain.diagnostics, field), field
    assert [c.active for c in prof.contacts] == [c.active for c in plain.contacts]
    timings = prof.diagnostics.timings
    assert set(timings) == {"M_and_h", "M_inverse", "G", "prox", "rest"}
    assert timings["M_and_h"] > 0 and timings["M_inverse"] > 0 and timings["rest"] > 0
    if preset != "Cm":
        assert timings["G"] > 0 and timings["prox"] > 0
    assert not plain.diagnostics.timings


@pytest.mark.parametrize("preset", ["HmJ", "Cm"])
def test_stepper_step_without_torques_is_a_zero_torque_step(preset):
    """MoreauStepper.step given no torques (None or an empty vector) steps like zero
    torques; a vector of the wrong length is refused before anything is done."""
    from starleth_sim.physics.tree_step import report_size
    ref = Simulator.from_preset(preset)
    ref.step(np.zeros(12))
    nc = ref.stepper.nc
    buffers = (np.empty(report_size(nc, 12)), np.empty(nc, dtype=np.bool_))
    for tau in (None, np.zeros(0)):
        sim = Simulator.from_preset(preset)
        st = sim.stepper
        for _ in range(sim.config.steps_per_control):
            st.step(sim.state, tau, *buffers)
        assert sim.state.q.tobytes() == ref.state.q.tobytes()
        assert sim.state.u.tobytes() == ref.state.u.tobytes()
    sim = Simulator.from_preset(preset)
    q = sim.state.q
    with pytest.raises(ValueError, match="12 entries"):
        sim.stepper.step(sim.state, np.zeros(13), *buffers)
    assert sim.state.q is q


BILATERAL_PRESETS = ("HEJD", "HEJP", "HESD", "HESP", "HMJD", "HMJP", "HMSD", "HMSP")


@pytest.mark.parametrize("preset", BILATERAL_PRESETS)
def test_prepared_and_profiled_steps_of_a_cut_forest_are_the_plain_step(preset):
    """The extended and maximal coordinates step in one kernel (tree_step.forest_step: the
    cut joints' bilateral constraints, M of the trees or constant); prepared ahead
    (STEP_PREPARE, then STEP_PREPARED) and profiled (STEP_PROFILE) it gives the same result
    bit for bit: q, u, Λ and the applied torques over a walking-like PD (the feet lift and
    land), a timed push (f_ext: the kernel with the wrench's force) and a torque beyond the
    effort limits (saturated)."""
    plain = Simulator.from_preset(preset)
    phased = Simulator.from_preset(preset, profile=True)
    q_stand = plain.joint_positions().copy()
    lift = np.tile([0.0, 0.5, -1.0], 4) * np.repeat([1, -1, -1, 1], 3)   # diagonal pairs
    n_active = set()
    for k in range(160):
        phased.prepare()
        for sim in (plain, phased):
            if k == 60:
                sim.apply_wrench("base", (0.0, 150.0, 0.0), duration=0.02)
            target = q_stand + 0.4 * np.sin(2 * np.pi * k / 80) * lift
            tau = pd(sim, target)
            if k == 100:
                tau[1] = 1e4            # saturated at the joint's effort limit
            sim.step(tau)
        assert plain.q.tobytes() == phased.q.tobytes(), k
        assert plain.u.tobytes() == phased.u.tobytes(), k
        assert plain.applied_torque.tobytes() == phased.applied_torque.tobytes(), k
        for a, b in zip(plain.contacts, phased.contacts, strict=True):
            assert np.asarray(a.impulse).tobytes() == np.asarray(b.impulse).tobytes(), k
        if k == 100:
            assert 0 < plain.applied_torque[1] < 1e4
        n_active.add(plain.diagnostics.active_contacts)
    assert plain.diagnostics.physics_steps == 160
    assert len(n_active) > 1, n_active          # contacts were made and broken


@pytest.mark.parametrize("preset", ["HmJ", "HmS", "Cm"] + list(BILATERAL_PRESETS))
def test_a_steady_run_allocates_nothing(preset):
    """The kernels carve their work arrays from the calling thread's arena (csrc/arena.c): a
    request that does not fit is served by malloc, counted, and the arena grows to fit at
    the next call. Standing, after a push into the ground and with all 16 contact points
    active (the robot put 0.6 m into the ground), a run that has been through those states
    once goes through them again without a single allocation."""
    from starleth_sim.physics.kernels import scratch_arena_stats
    q_min = Simulator.from_preset("HmJ").q.copy()
    q_min[2] -= 0.6

    def episode(sim, q_stand):
        sim.reset()
        run(sim, q_stand, 30)
        sim.apply_wrench("base", (0.0, 0.0, -600.0), duration=0.01)    # pressed into the ground
        run(sim, q_stand, 10)
        sim.reset(q_min, np.zeros(q_min.shape[0] - 1), minimal=True)
        sim.step(pd(sim, q_stand))
        assert all(c.active for c in sim.contacts), preset
        run(sim, q_stand, 5)

    sim = Simulator.from_preset(preset)
    q_stand = sim.joint_positions().copy()
    before = scratch_arena_stats()[0]
    episode(sim, q_stand)
    first = scratch_arena_stats()[0] - before
    assert first < 20, f"{preset}: {first} requests missed the arena in the first episode"
    episode(sim, q_stand)
    again = scratch_arena_stats()[0] - before - first
    assert again == 0, f"{preset}: {again} requests allocated in the second episode"


@pytest.mark.parametrize("preset", ["HmJ", "HEJD"])
def test_a_packed_model_of_the_wrong_length_is_refused_not_read(preset):
    """The one-kernel steps read their model from packed buffers (tree_step.TreeStepModel,
    CutModel): a buffer one entry short or long, for the sizes its header claims, is a
    clear ValueError before anything is read or written."""
    from starleth_sim.physics.tree_step import forest_step, tree_step_hard
    sim = Simulator.from_preset(preset)
    st, s = sim.stepper, sim.state
    model = list(st._tree_model)
    out = (np.empty(7 * st.nc + 3 * 12), np.empty(st.nc, dtype=bool), np.empty_like(s.q),
           np.empty_like(s.u))

    def step(tree, cut=None):
        if preset == "HmJ":
            return tree_step_hard(0, False, (s.q, s.u, s.last_impulse, s.last_active,
                                             s.last_bilateral, s.prox_memory), np.zeros(12),
                                  np.zeros(0),
                                  out, tuple(tree))
        no_compliant = (np.zeros(0, dtype=bool),) * 2 + (np.zeros(0),) * 2
        return forest_step(0, (s.q, s.u, s.last_impulse, s.last_active, s.last_bilateral,
                               s.prox_memory, *no_compliant), np.zeros(12), np.zeros(0),
                           (*out, *st.coords.cut_motion_buffers()), tuple(tree),
                           tuple(cut or st._cut_model))
    q0 = s.q.copy()
    for k in (0, 1, 3):                 # floats, ints, workspace
        for change in (lambda a: a[:-1], lambda a: np.concatenate([a, a[:1]])):
            bad = list(model)
            bad[k] = change(model[k])
            if k == 3 and len(bad[k]) > len(model[k]):
                continue                # (a longer workspace is allowed: its tail unused)
            with pytest.raises(ValueError, match="TreeStepModel: buffer lengths"):
                step(bad)
    if preset == "HEJD":
        cf, ci, cw = st._cut_model
        for bad in ((cf[:-1], ci, cw), (cf, ci[:-1], cw), (cf, ci, cw[:-1])):
            with pytest.raises(ValueError, match="CutModel: buffer lengths"):
                step(model, bad)
    assert np.array_equal(s.q, q0)
    step(model)                         # the packed model as it is: one step


@pytest.mark.parametrize("coordinates", ["extended", "maximal"])
def test_compliant_contacts_in_a_cut_forest_stand_as_in_the_minimal_coordinates(coordinates):
    """forest_step with compliant contacts (Alg. 1 plus the prox solve of the cut joints'
    bilateral constraints): a PD-held robot stands as in the minimal coordinates (the same
    base height to 10 µm, the same vertical contact force to 0.1 N after 0.25 s)."""
    runs = []
    for coords in ("minimal", coordinates):
        extra = {} if coords == "minimal" else {"bilateral.method": "direct"}
        sim = Simulator.from_preset("Cm", coordinates=coords, **extra)
        q0 = sim.joint_positions().copy()
        for _ in range(100):
            sim.step(100.0 * (q0 - sim.joint_positions()) - 2.0 * sim.joint_velocities())
        runs.append((sim.q[2], sum(np.asarray(c.impulse)[2] for c in sim.contacts)
                     / sim.control_period))
    (z0, f0), (z1, f1) = runs
    assert f0 > 200.0 and abs(f1 - f0) < 0.1 and abs(z1 - z0) < 1e-5


def test_diagnostics_read_late_are_those_read_at_every_step():
    """Diagnostics are worked out from a step's figures when first read: those of a
    simulator read only at the end equal those of one read after every step (the
    cumulative counts included, with steps that did not converge), and a copy or a pickle
    holds the same fields."""
    read, late = (Simulator.from_preset("HmJ", **{"solver.max_iterations": 3})
                  for _ in range(2))
    zero = np.zeros(read.n_joints)
    for _ in range(40):
        read.step(zero)
        assert read.diagnostics.physics_steps >= 1
        late.step(zero)
    got, want = late.diagnostics, read.diagnostics
    assert want.nonconverged_steps > 0 and want.iterations > 0
    for name in FIELD_NAMES:
        if name != "step_time":
            assert getattr(got, name) == getattr(want, name), name
    assert got.physics_steps == 40
    for other in (copy.deepcopy(late.diagnostics), pickle.loads(pickle.dumps(got))):
        assert other == got
