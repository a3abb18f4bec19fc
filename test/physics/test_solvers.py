"""The four prox schemes (JOR/SOR x Delassus/velocity form) solve the same contact problems
as each other and as Pinocchio's own PGS solver (pin.PGSConstraintSolver)."""
import numpy as np
import pytest
from pin_pgs_reference import check_coulomb_ncp, pin_pgs_solve

from starleth_sim import Simulator
from starleth_sim.physics import prox
from starleth_sim.physics.step_kernels import (
    StepSettings,
    constraint_velocity,
    free_velocity,
    prepare_hard_contacts,
)

SCHEMES = [(f, s) for f in ("delassus", "velocity") for s in ("jor", "sor")]


def robot_problem(u_scale, seed, mu=0.8):
    """The contact problem of one HmJ step from the standing posture with random velocities."""
    sim = Simulator.from_preset("HmJ")
    rng = np.random.default_rng(seed)
    u = u_scale * rng.standard_normal(sim.coords.nv)
    st = sim.stepper
    q = sim.q
    q[2] -= 5e-3  # 5 mm overlap: all four feet stay closed at the midpoint
    qM = sim.coords.integrate(q, u, 0.5 * st.dt)
    tau = 5.0 * rng.standard_normal(12)
    M, h = sim.coords.dynamics(qM, u, tau)
    sim.coords.contact_kinematics(qM, st.ground, st.gap, st.position, st.Wt_all)
    nv = sim.coords.nv
    L, u_free = np.zeros((nv, nv)), np.zeros(nv)
    eps = np.zeros((sim.coords.n_contacts, 2))
    nc = sim.coords.n_contacts
    # the paper's active set and law (no hysteresis; no gap terms as every active g_N < 0),
    # the Delassus form with G formed
    paper = st.settings._replace(
        activation_gap=0.0, hysteresis=False, opening_gap=0.0, beta_velocity=0.0,
        prox=st.settings.prox._replace(form=prox.FORM_DELASSUS, bilateral_direct=False))
    problem = prepare_hard_contacts(
        paper, (M, u), (st.gap, st.Wt_all, np.zeros((0, nv)), np.zeros(0), eps),
        (sim.coords.tree.dof_parent, True, L), (np.zeros((nc, 3)), np.zeros(nc, dtype=bool)),
        None)
    arrays = problem.arrays()
    active, Wt, MinvW, bvec, G = (arrays[k] for k in ("active", "Wt", "MinvW", "b", "G"))
    assert problem.ok and len(active) == 4 and problem.n_active == 4
    free_velocity(h, st.dt, u, sim.coords.tree.dof_parent, L, u_free)
    np.testing.assert_allclose(u_free, u + np.linalg.solve(M, h) * st.dt, rtol=1e-10,
                               atol=1e-12)
    na = len(active)
    c = np.empty(Wt.shape[0])
    constraint_velocity(Wt, u_free, bvec, arrays["wp_ptr"], arrays["wp_idx"], c)
    np.testing.assert_allclose(c, Wt @ u_free + bvec, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(G, Wt @ np.linalg.solve(M, Wt.T), rtol=1e-10, atol=1e-12)
    return dict(M=M, Wt=Wt, MinvW=MinvW, u_free=u_free, bvec=bvec, c=c, G=G, na=na,
                mu=np.full(na, mu))


def solve(p, form, scheme, alpha=0.5, tol=1e-13, max_iter=200000, criterion=0):
    m = 3 * p["na"]
    r = np.empty(m)
    prox.prox_parameters(np.diag(p["G"]).copy(), p["na"], alpha, r)
    lam = np.zeros(m)
    u = np.empty(p["M"].shape[0])
    # the stepper's record, its ProxSettings inside (prox_solve reads those fields)
    settings = StepSettings(
        prox=prox.ProxSettings(
            form=prox.FORMS[form], scheme=prox.SCHEMES[scheme], tol_rel=0.0, tol_abs=float(tol),
            max_iterations=int(max_iter), criterion=int(criterion), bilateral_direct=False,
            alpha=float(alpha)),
        activation_gap=0.0, mu=0.0, fallback_alpha_factor=0.0, opening_gap=0.0, dt=0.0,
        beta_velocity=0.0, beta_projection=0.0, jacobian_gap=0.0, projection_tolerance=0.0,
        warm_start=False, hysteresis=False)
    it, status, res = prox.prox_solve(
        settings, prox.dense_problem_patterns(p["Wt"], p["MinvW"], p["G"]),
        (p["Wt"], p["MinvW"], p["u_free"], p["bvec"], p["G"], p["c"]), (p["na"], p["mu"], r),
        lam, (np.zeros((0, 0)), p["M"]), u)
    return lam, u, it, status


@pytest.mark.parametrize("u_scale,seed", [(0.0, 0), (0.05, 1), (0.5, 2), (1.0, 3)])
def test_prox_schemes_agree_with_each_other_and_with_pinocchio_pgs(u_scale, seed):
    p = robot_problem(u_scale, seed)
    ref = pin_pgs_solve(p["G"], p["c"], p["mu"], tol=1e-14)
    assert check_coulomb_ncp(p["G"], p["c"], p["mu"], ref) < 1e-9
    for form, scheme in SCHEMES:
        lam, u, it, status = solve(p, form, scheme)
        assert status == prox.STATUS_CONVERGED, (form, scheme, it)
        np.testing.assert_allclose(lam, ref, atol=1e-8, rtol=0, err_msg=f"{form}/{scheme}")
        # the end velocity is u_free + M^-1 W Λ (Eqn. 17) and satisfies ξ = W^T u^E (ε = 0)
        np.testing.assert_allclose(u, p["u_free"] + p["MinvW"] @ lam, atol=1e-10)
        np.testing.assert_allclose(p["Wt"] @ u, p["G"] @ lam + p["c"], atol=1e-10)


def test_problem_set_covers_stick_slip_and_open_contacts():
    """The cross-check above is only meaningful if it exercises every branch of the laws."""
    kinds = set()
    for u_scale, seed in [(0.0, 0), (0.05, 1), (0.5, 2), (1.0, 3)]:
        p = robot_problem(u_scale, seed)
        lam = pin_pgs_solve(p["G"], p["c"], p["mu"], tol=1e-14).reshape(-1, 3)
        for ln, t1, t2 in lam:
            if ln < 1e-12:
                kinds.add("open")
            elif np.hypot(t1, t2) < 0.8 * ln * (1 - 1e-6):
                kinds.add("stick")
            else:
                kinds.add("slip")
    assert kinds == {"open", "stick", "slip"}


@pytest.mark.parametrize("form,scheme", SCHEMES)
def test_energy_criterion_terminates_at_the_same_solution(form, scheme):
    p = robot_problem(0.5, 2)
    lam_ref, u_ref, _, _ = solve(p, form, scheme)
    lam, u, it, status = solve(p, form, scheme, tol=1e-14, criterion=prox.CRITERION_ENERGY)
    assert status == prox.STATUS_CONVERGED
    np.testing.assert_allclose(u, u_ref, atol=1e-6)


def test_too_aggressive_alpha_is_reported_not_accepted():
    """JOR on a box resting on 4 corners (rank-deficient G) needs α < ~0.5: α = 1.9 cycles."""
    from starleth_sim import load_preset
    from starleth_sim.physics.description import RobotDescription, box_urdf
    cfg = load_preset("HmJ").with_overrides(alpha=1.9, max_iterations=200,
                                            fallback_alpha_factor=0.0, tol_abs=1e-12)
    sim = Simulator(cfg, description=RobotDescription.from_urdf_xml(box_urdf()))
    q = sim.q
    q[2] -= 1e-9
    sim.reset(q)
    d = sim.step()
    assert not d.converged and d.status == "max_iterations"
    assert d.iterations == 200 and d.nonconverged_steps == 1
    assert np.all(np.isfinite(sim.q))
    # with the fallback (α·0.5, then accepted) the same step converges and says it retried
    sim2 = Simulator(cfg.with_overrides(fallback_alpha_factor=0.1), description=sim.description)
    sim2.reset(q)
    d2 = sim2.step()
    assert d2.converged and d2.retried


@pytest.mark.parametrize("m", [12, 40])
def test_delassus_of_block_sparse_rows_is_the_dense_product_bit_for_bit(m):
    """G = W^T M^{-1} W of rows that touch few of many blocks (the maximal coordinates): with
    more than DELASSUS_ENVELOPE_ROWS rows delassus sums only over the envelopes of the rows
    of M^{-1}W; the entries it does not reach are +0.0 and the others the same sums, bit for
    bit, as the plain loop over each row's nonzeros."""
    rng = np.random.default_rng(m)
    nv, blocks = 102, 17
    Wt = np.zeros((m, nv))
    for a in range(m):                       # each row on two random 6-velocity blocks
        for blk in rng.choice(blocks, 2, replace=False):
            Wt[a, 6 * blk:6 * blk + 6] = rng.normal(size=6) * (rng.random(6) < 0.8)
    Wt[0, :6] = -0.0                          # signed zeros are zeros of the pattern
    Minv = np.zeros((nv, nv))
    for blk in range(blocks):                # block-diagonal M^{-1}
        A = rng.normal(size=(6, 6))
        Minv[6 * blk:6 * blk + 6, 6 * blk:6 * blk + 6] = A @ A.T + 6 * np.eye(6)
    MinvW = np.ascontiguousarray(Minv @ Wt.T)
    MinvW[MinvW == 0.0] = 0.0
    wp_ptr, wp_idx = prox.row_pattern(Wt)
    mp_ptr, mp_idx = prox.col_pattern(MinvW)
    G = np.full((m, m), np.nan)
    prox.delassus(Wt, MinvW, G, wp_ptr, wp_idx, mp_ptr, mp_idx)
    ref = np.empty((m, m))
    for a in range(m):                       # the plain loop: every pair summed
        for b in range(a, m):
            s = 0.0
            for k in wp_idx[wp_ptr[a]:wp_ptr[a + 1]]:
                s += Wt[a, k] * MinvW[k, b]
            ref[a, b] = ref[b, a] = s
    assert G.tobytes() == ref.tobytes()
    np.testing.assert_allclose(G, Wt @ MinvW, rtol=1e-12, atol=1e-12)
    # most pairs of rows share no block: the envelopes leave entries out
    assert np.count_nonzero(ref == 0.0) > m * m // 2


def _dense_cholesky(A):
    """The textbook dense Cholesky (every sum over all k < j), in plain Python."""
    n = A.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        d = np.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = A[j, i]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
    return L


def _dense_solve(L, b):
    x = b.copy()
    n = len(x)
    for i in range(n):
        s = x[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return x


def _bilateral_problem(preset="HMJD", steps=60):
    """G (contact rows first) and the number of contact rows of a step of `preset` after
    `steps` steps of a posture hold."""
    from starleth_sim.physics.posture import PostureHold
    sim = Simulator.from_preset(preset)
    hold = PostureHold(sim.joint_positions())
    for _ in range(steps):
        sim.step(hold.torque(sim))
    st, c, s = sim.stepper, sim.coords, sim.state
    qM = c.integrate(s.q, s.u, 0.5 * st.dt)
    M, h = c.dynamics(qM, s.u, np.zeros(12)) if not c.constant_mass_matrix else (c.M_const, 0)
    c.contact_kinematics(qM, st.ground, st.gap, st.position, st.Wt_all)
    WtB, gB = c.bilateral(qM)
    bB = gB * (sim.config.bilateral.stabilization / st.dt)
    problem = prepare_hard_contacts(
        st.settings, (M, s.u), (st.gap, st.Wt_all, WtB, bB, st.eps),
        (c.tree.dof_parent, True, np.zeros((c.nv, c.nv))), (s.last_impulse, s.last_active),
        None)
    return problem.arrays()["G"], 3 * problem.n_active, problem.arrays()


def test_cholesky_with_the_envelope_is_the_dense_factor_bit_for_bit():
    """linalg.cholesky_upper_input sums only inside the envelope of G_BB (the maximal
    coordinates' G_BB: 60 rows, under half of the lower triangle in the envelope): the
    same L and the same solutions, bit for bit, as the dense textbook loops (also
    cholesky_solve_envelope, whose backward pass runs by the envelope's columns), and
    L Lᵀ = G_BB; also on a random SPD matrix with an envelope and on a dense one (with a -0.0 in the
    input, the same values)."""
    from starleth_sim.physics.linalg import (
        cholesky_solve_envelope,
        cholesky_solve_vec,
        cholesky_upper_input,
        envelope_columns,
    )
    G, o, _ = _bilateral_problem()
    rng = np.random.default_rng(5)
    n = 24
    B = rng.normal(size=(n, n)) * (rng.random((n, n)) < 0.3)
    S = B @ B.T + n * np.eye(n)
    for i in range(n):                    # an envelope: zeros left of a random first column
        f = rng.integers(0, i + 1)
        S[i, :f] = S[:f, i] = 0.0
    signed = S.copy()       # a -0.0 input (G's sums never give one: 0.0 + -0.0 is +0.0)
    signed[1, 3] = signed[3, 1] = -0.0
    cases = [("G_BB of HMJD", G, o), ("random envelope", S, 0),
             ("dense", B @ B.T + np.eye(n), 0), ("signed zero", signed, 0)]
    for name, A, off in cases:
        block = np.ascontiguousarray(A[off:, off:])
        m = block.shape[0]
        L = np.zeros((m, m))
        first = np.empty(m, dtype=np.int64)
        assert cholesky_upper_input(np.ascontiguousarray(A), off, L, first), name
        ref = _dense_cholesky(block)
        if name == "signed zero":   # the same values; a zero's sign may differ
            assert np.array_equal(L, ref)
            continue
        assert L.tobytes() == ref.tobytes(), name
        np.testing.assert_allclose(L @ L.T, block, rtol=0, atol=1e-12 * np.abs(block).max())
        b = rng.normal(size=m)
        x = b.copy()
        cholesky_solve_vec(L, first, x)
        assert x.tobytes() == _dense_solve(ref, b).tobytes(), name
        np.testing.assert_allclose(block @ x, b, rtol=0, atol=1e-9 * np.abs(b).max())
        # the backward pass by the envelope's columns: the same solution, bit for bit
        col_ptr, col_idx = envelope_columns(first)
        assert col_ptr[-1] == sum(i - first[i] for i in range(m)), name
        y = b.copy()
        cholesky_solve_envelope(L, first, col_ptr, col_idx, y)
        assert y.tobytes() == x.tobytes(), name
        if name == "G_BB of HMJD":
            inside = sum(i - first[i] + 1 for i in range(m))
            assert m == 60 and inside < 0.5 * m * (m + 1) / 2, inside   # worth the envelope
    # not positive definite: refused
    bad = -np.eye(3)
    assert not cholesky_upper_input(bad, 0, np.zeros((3, 3)), np.empty(3, dtype=np.int64))


def test_forest_solve_with_patterns_is_the_scanning_solve_bit_for_bit():
    """linalg.ltdl_solve_cols_pattern (the maximal coordinates' M^{-1}W and its column
    pattern from W's pattern) gives MinvW and prox.col_pattern(MinvW) of the scanning
    ltdl_solve_cols bit for bit, on the contact and bilateral rows of an HMSD step."""
    from starleth_sim.physics.linalg import ltdl, ltdl_solve_cols, ltdl_solve_cols_pattern
    _, _, problem = _bilateral_problem("HMSD")
    sim = Simulator.from_preset("HMSD")
    dof_parent = sim.coords.tree.dof_parent
    Wt = problem["Wt"]
    M = sim.coords.dynamics(sim.q, np.zeros(sim.coords.nv), np.zeros(12))[0]
    L = np.zeros_like(M)
    assert ltdl(M, dof_parent, L)
    assert np.count_nonzero(dof_parent == -1) > 10             # a forest of free bodies
    a = np.ascontiguousarray(Wt.T)
    b = a.copy()
    ltdl_solve_cols(L, dof_parent, a)
    ptr, idx = ltdl_solve_cols_pattern(L, dof_parent, b, *prox.row_pattern(Wt))
    assert a.tobytes() == b.tobytes()
    ref_ptr, ref_idx = prox.col_pattern(a)
    assert ptr.tolist() == ref_ptr.tolist() and idx.tolist() == ref_idx.tolist()
    np.testing.assert_allclose(M @ a, Wt.T, rtol=0, atol=1e-9)
