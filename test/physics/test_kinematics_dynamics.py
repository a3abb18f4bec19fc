"""The jitted contact kinematics and the inertial-velocity dynamics against Pinocchio."""
import numpy as np
import pinocchio as pin
import pytest

from starleth_sim import Simulator
from starleth_sim.physics.coordinates.forest import quat_rot


@pytest.fixture(scope="module")
def sim():
    return Simulator.from_preset("HmJ")


def random_state(sim, seed):
    rng = np.random.default_rng(seed)
    q = sim.coords.neutral()
    q[0:3] = rng.standard_normal(3)
    quat = rng.standard_normal(4)
    q[3:7] = quat / np.linalg.norm(quat)
    q[7:] = rng.uniform(-1.5, 1.5, q.shape[0] - 7)
    return q, rng.standard_normal(sim.coords.nv)


def pin_velocity(q, u):
    """u_pin = T u (pin's free-flyer linear velocity is in the body frame)."""
    R = np.zeros((3, 3))
    quat_rot(q, 0, R)
    up = u.copy()
    up[0:3] = R.T @ u[0:3]
    return up, R


@pytest.mark.parametrize("seed", range(5))
def test_contact_points_and_jacobians_match_pinocchio_frames(sim, seed):
    c = sim.coords
    q, u = random_state(sim, seed)
    g = sim.stepper.ground
    nc = c.n_contacts
    gap, pos, Wt = np.zeros(nc), np.zeros((nc, 3)), np.zeros((nc, 3, c.nv))
    c.contact_kinematics(q, g, gap, pos, Wt)
    model, data = c.model, c.model.createData()
    pin.framesForwardKinematics(model, data, q)
    pin.computeJointJacobians(model, data, q)
    up, R = pin_velocity(q, u)
    for i, spec in enumerate(sim.description.contacts):
        oMj = data.oMi[spec.joint]
        centre = oMj.act(spec.local)
        assert gap[i] == pytest.approx(centre[2] - spec.radius, abs=1e-12)
        np.testing.assert_allclose(pos[i], centre - spec.radius * g.n, atol=1e-12)
        # velocity of the material point at the contact: pin's joint Jacobian, shifted
        J6 = pin.getJointJacobian(model, data, spec.joint, pin.LOCAL_WORLD_ALIGNED)
        v_pin = J6[:3] @ up + np.cross(J6[3:] @ up, pos[i] - oMj.translation)
        np.testing.assert_allclose(Wt[i] @ u, g.frame @ v_pin, atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_mass_matrix_and_forces_are_pins_in_inertial_velocity(sim, seed):
    c = sim.coords
    q, u = random_state(sim, seed)
    tau = np.random.default_rng(seed).standard_normal(12)
    M, h = c.dynamics(q, u, tau)
    up, R = pin_velocity(q, u)
    model, data = c.model, c.model.createData()
    Mp = pin.crba(model, data, q)
    Mp = np.triu(Mp) + np.triu(Mp, 1).T
    # same kinetic energy, symmetric positive definite, trunk block m I
    assert 0.5 * u @ M @ u == pytest.approx(0.5 * up @ Mp @ up, rel=1e-12)
    np.testing.assert_allclose(M, M.T, atol=1e-12)
    np.testing.assert_allclose(M[:3, :3], sim.description.total_mass * np.eye(3), atol=1e-12)
    # same acceleration: u̇_pin = T u̇ + Ṫ u with Ṫ u = [-ω x v_body; 0]
    tau_full = np.zeros(c.nv)
    tau_full[c.joint_v] = tau
    a_pin = pin.aba(model, data, q, up, tau_full)
    a = np.linalg.solve(M, h)
    a_from = a.copy()
    a_from[0:3] = R.T @ a[0:3] - np.cross(up[3:6], up[0:3])
    np.testing.assert_allclose(a_from, a_pin, atol=1e-9)


def tumble(control_rate, seconds=0.5):
    sim = Simulator.from_preset("HmJ", control_rate=control_rate)
    q = sim.q
    q[2] = 5.0
    u = np.zeros(sim.coords.nv)
    u[0:3] = [1.0, -0.5, 3.0]
    u[3:6] = [2.0, -1.0, 4.0]
    u[6:] = 0.5
    sim.reset(q, u)
    c = sim.coords

    def energy():
        return c.kinetic_energy(sim.q, sim.u) + c.potential_energy(sim.q)

    mass = sim.description.total_mass

    def momentum_xy():
        up, _ = pin_velocity(sim.q, sim.u)
        pin.centerOfMass(c.model, c.data, sim.q, up)
        return mass * c.data.vcom[0][:2]
    E0, p0 = energy(), momentum_xy()
    for _ in range(int(round(seconds * control_rate))):
        sim.step()
        assert sim.diagnostics.active_contacts == 0
    return (energy() - E0) / E0, np.abs(momentum_xy() - p0).max() / np.abs(p0).max(), sim


def test_free_tumbling_body_energy_and_momentum_errors_are_first_order():
    """A tumbling robot in the air (no contact, no horizontal force): Moreau's scheme
    evaluates M at the midpoint, so energy and horizontal momentum are not exact discrete
    invariants, but their errors are small and shrink linearly with Δt."""
    e1, p1, sim = tumble(400.0)
    e2, p2, _ = tumble(800.0)
    assert abs(e1) < 5e-4 and p1 < 3e-3
    assert p1 / p2 == pytest.approx(2.0, rel=0.2)
    assert abs(e1 / e2) == pytest.approx(2.0, rel=0.1)
    assert abs(np.linalg.norm(sim.q[3:7]) - 1) < 1e-12


@pytest.mark.parametrize("preset", ["HmJ", "HEJD"])
def test_jitted_crba_rnea_match_pinocchio_on_the_forest(preset):
    """M and h of the jitted CRBA / RNEA (physics.rigid_body) against Pinocchio's CRBA and
    RNEA on the same forest, transformed to the paper's inertial root velocities
    (forest.from_pin_dynamics): the minimal tree and the extended forest of 5 floating
    trees, at random states, to rounding. And the step's one-call midpoint (q^M, M, h and
    the contact kinematics) equals the separate evaluations."""
    from starleth_sim.physics.coordinates.forest import from_pin_dynamics, to_pin_velocity
    sim = Simulator.from_preset(preset)
    c = sim.coords
    rng = np.random.default_rng(7)
    for _ in range(3):
        q = c.integrate(sim.q, rng.standard_normal(c.nv), 0.4)
        u = 2.0 * rng.standard_normal(c.nv)
        M, h = c.dynamics(q, u, None)
        Rs = np.zeros((c.roots.shape[0], 3, 3))
        up = np.zeros(c.nv)
        to_pin_velocity(q, u, c.roots, c.root_q, c.root_v, Rs, up)
        data = c.model.createData()
        Mp = pin.crba(c.model, data, q).copy()
        hp = -pin.nonLinearEffects(c.model, data, q, up)
        M_ref, h_ref = np.empty_like(M), np.empty_like(h)
        from_pin_dynamics(Mp, hp, Rs, c.root_v, up, M_ref, h_ref)
        np.testing.assert_allclose(M, M_ref, rtol=0, atol=1e-12 * np.abs(M_ref).max())
        np.testing.assert_allclose(h, h_ref, rtol=0, atol=1e-12 * np.abs(h_ref).max())
        g, nc = sim.stepper.ground, c.n_contacts
        gap, pos, Wt = np.zeros(nc), np.zeros((nc, 3)), np.zeros((nc, 3, c.nv))
        qM, M2, h2 = c.midpoint(q, u, 0.01, g, gap, pos, Wt)
        gap1, pos1, Wt1 = np.zeros(nc), np.zeros((nc, 3)), np.zeros((nc, 3, c.nv))
        qM1 = c.integrate(q, u, 0.005)
        M1, h1 = c.dynamics(qM1, u, None)
        c.contact_kinematics(qM1, g, gap1, pos1, Wt1)
        for a, b in ((qM, qM1), (M2, M1), (h2, h1), (gap, gap1), (pos, pos1), (Wt, Wt1)):
            np.testing.assert_array_equal(a, b)


# -- M's LTDL factor (linalg.ltdl) ------------------------------------------------------------
def _forest_spd(rng, dof_parent):
    """A random SPD matrix with the branch-induced sparsity of the forest dof_parent (the
    pattern of a joint-space inertia matrix: M = Σ over bodies of J_bᵀ I_b J_b, each body's
    Jacobian nonzero on its ancestors only)."""
    n = dof_parent.shape[0]
    M = 1e-3 * np.eye(n)
    for k in range(n):
        J = np.zeros((6, n))
        j = k
        while j != -1:
            J[:, j] = rng.standard_normal(6)
            j = dof_parent[j]
        A = rng.standard_normal((6, 6))
        M += J.T @ (A @ A.T + np.eye(6)) @ J
    return M


@pytest.mark.parametrize("preset", ["HmJ", "HEJD", "HMSD"])
def test_ltdl_solves_the_mass_matrix_like_numpy(preset):
    """The LTDL factor with the robot's forest (one tree; trees cut at joints; one body each)
    and random inertias: M^{-1} of vectors and of W-like columns (zero on all but one tree's
    dofs, or everywhere) to 1e-12 of numpy's solve, the column solve bit-identical to the
    vector solve, and an indefinite M refused."""
    from starleth_sim import Simulator
    from starleth_sim.physics import linalg
    par = Simulator.from_preset(preset).coords.tree.dof_parent
    n = par.shape[0]
    rng = np.random.default_rng(7)
    M = _forest_spd(rng, par)
    L = np.zeros((n, n))
    assert linalg.ltdl(M, par, L)
    B = rng.standard_normal((n, 5))
    roots = list(np.flatnonzero(par == -1)) + [n]
    B[roots[1]:, 1] = 0.0            # a column on the first tree only
    B[:, 2] = 0.0                    # an empty column
    X = B.copy()
    linalg.ltdl_solve_cols(L, par, X)
    ref = np.linalg.solve(M, B)
    assert np.abs(X - ref).max() <= 1e-12 * np.abs(ref).max()
    assert not X[:, 2].any()
    for c in range(B.shape[1]):
        x = B[:, c].copy()
        linalg.ltdl_solve_vec(L, par, x)
        assert x.tobytes() == X[:, c].tobytes()
    bad = M.copy()
    bad[n - 1, n - 1] = -1.0
    assert not linalg.ltdl(bad, par, L)
    bad = M.copy()
    bad[0, 0] = np.nan
    assert not linalg.ltdl(bad, par, L)


def test_ltdl_keeps_the_sparsity_of_the_tree():
    """No fill-in: the factor of the minimal coordinates' M (one tree: base, four legs) has
    nonzeros only between a dof and its ancestors, and it reproduces M = Lᵀ D L."""
    from starleth_sim import Simulator
    from starleth_sim.physics import linalg
    sim = Simulator.from_preset("HmJ")
    par = sim.coords.tree.dof_parent
    n = par.shape[0]
    M = _forest_spd(np.random.default_rng(3), par)
    ancestors = np.zeros((n, n), dtype=bool)
    for k in range(n):
        j = par[k]
        while j != -1:
            ancestors[k, j] = True
            j = par[j]
    assert not np.any(M[~(ancestors | ancestors.T | np.eye(n, dtype=bool))])
    L = np.full((n, n), np.nan)      # entries outside the pattern are neither read nor written
    assert linalg.ltdl(M, par, L)
    assert np.all(np.isnan(L[~(ancestors | np.eye(n, dtype=bool))]))
    Lu = np.where(ancestors, L, 0.0) + np.eye(n)
    D = np.diag(np.diag(L))
    np.testing.assert_allclose(Lu.T @ D @ Lu, M, rtol=1e-12, atol=1e-12 * np.abs(M).max())
