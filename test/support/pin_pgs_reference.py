"""Reference frictional-contact solver backed by Pinocchio's own PGS solver.

Problem (OUR convention)
------------------------
nc contacts, Lambda in R^{3nc}, ordered per contact as [L_N, L_T1, L_T2]
(normal FIRST).  xi = G Lambda + c, with G the (symmetric PSD) Delassus matrix.
Exact Coulomb law (NCP, not the CCP / Anitescu relaxation), for each contact i:

    L_N >= 0, xi_N >= 0, L_N xi_N = 0
    ||L_T|| <= mu_i L_N
    ||L_T|| <  mu_i L_N  =>  xi_T = 0                       (sticking)
    ||L_T|| == mu_i L_N  =>  xi_T = -s L_T, s >= 0          (sliding, max. dissipation)
    (L_N == 0: contact open, xi_T unconstrained)

Pinocchio (4.x, new constraint API) orders each 3D contact block as
[T1, T2, N] (normal LAST) and uses the same sign convention
(velocity y = G x + g, x in the Coulomb cone).  ``pin_pgs_solve`` permutes
G and c into Pinocchio's ordering, runs ``pinocchio.PGSConstraintSolver`` on a
``pinocchio.DelassusOperatorDense`` built from the permuted G, with one
``PointContactConstraintModel`` (CoulombFrictionCone set, friction mu_i) per
contact, and permutes the impulses back.

Notes on Pinocchio 4.1's PGS (read from the shipped headers
``include/pinocchio/src/algorithm/solvers/pgs-solver.hxx``):
  * Per contact block: the normal impulse is updated first with the plain
    normal velocity (fz <- max(0, fz - w*y_N/G_NN)), then the tangential
    impulse with a projected step onto the disk of radius mu*fz using the step
    w/min(G_T1T1, G_T2T2).  A fixed point of this iteration is exactly the
    Coulomb NCP above (no De Saxce correction in the update), i.e. the NCP
    is solved regardless of ``settings.solve_ncp``.  In 4.1 that flag only
    changes the recorded statistic ``stats.dual_feasibility_ncp`` (when
    ``stat_record`` is True); it does not change the iterates.
  * CAVEAT: that tangential step 1/min(G_T1T1, G_T2T2) is too long when the
    2x2 tangential Delassus block is anisotropic (it needs < 2/lambda_max of
    the block); pin's PGS then ends in a limit cycle and never converges
    (29 of 500 random 4-contact problems in the self-check).  By default
    (``tangent_rotation=True``) we therefore rotate each contact's tangent
    basis (an exact equivalence for the isotropic Coulomb cone and for
    maximal dissipation) so that the two tangential diagonal entries are
    equal (= trace/2), which makes the per-block step stable, and rotate the
    result back.  ``tangent_rotation=False`` gives raw Pinocchio behaviour.
    Lowering ``over_relaxation`` (e.g. 0.3) is another (slower) remedy, and
    is used automatically as a fallback when pin still reports
    non-convergence (``fallback_relaxations``; needed e.g. for PSD G with
    mu close to 1).  PGS for the Coulomb NCP has no general convergence
    guarantee, so always check ``info['converged']`` / ``check_coulomb_ncp``.
  * pin's absolute stopping test uses a product complementarity lambda.xi;
    with a nonzero tolerance it may stop early when impulses are tiny, so the
    complementarity tolerances are set to 0 by default (see pin_pgs_solve).
  * ``result.iterations`` is a 0-based counter (0 = stopped after 1 sweep).
  * The geometry of the pinocchio Model used to build the constraint models is
    irrelevant: the solver only queries each constraint's size and its
    friction cone; the Delassus matrix is taken from DelassusOperatorDense.

Run ``python test/support/pin_pgs_reference.py`` for the self-checks.
"""

import warnings

import numpy as np
import pinocchio as pin

__all__ = ["pin_pgs_solve", "check_coulomb_ncp", "ncp_residuals"]


# ----------------------------------------------------------------------------
# ordering helpers
# ----------------------------------------------------------------------------
def _ours_to_pin_perm(nc):
    """Index array p such that x_pin = x_ours[p] (per contact [N,T1,T2] -> [T1,T2,N])."""
    base = 3 * np.arange(nc)[:, None]
    return (base + np.array([1, 2, 0])[None, :]).ravel()


def _tangent_rotation(G, nc):
    """Block-diagonal orthogonal R (identity on normals) such that in the basis
    Lambda = R Lambda', the tangential 2x2 blocks of R^T G R have equal diagonals."""
    R = np.eye(3 * nc)
    rot45 = np.array([[1.0, -1.0], [1.0, 1.0]]) / np.sqrt(2.0)
    for i in range(nc):
        s = slice(3 * i + 1, 3 * i + 3)
        _, V = np.linalg.eigh(0.5 * (G[s, s] + G[s, s].T))
        if np.linalg.det(V) < 0:
            V[:, 1] = -V[:, 1]
        R[s, s] = V @ rot45  # a proper rotation; diag of (V rot45)^T B (V rot45) = tr(B)/2
    return R


# ----------------------------------------------------------------------------
# dummy pinocchio model used only to instantiate the constraint models
# ----------------------------------------------------------------------------
_DUMMY_MODEL = None


def _dummy_model():
    global _DUMMY_MODEL
    if _DUMMY_MODEL is None:
        _DUMMY_MODEL = pin.buildSampleModelHumanoid()
    return _DUMMY_MODEL


def _build_constraints(mu, model=None, joint_ids=None):
    model = _dummy_model() if model is None else model
    cmodels = pin.StdVec_ConstraintModel()
    cdatas = pin.StdVec_ConstraintData()
    for i, mu_i in enumerate(mu):
        jid = 1 if joint_ids is None else int(joint_ids[i])
        cm = pin.PointContactConstraintModel(model, jid)
        cm.setFriction(float(mu_i))
        assert cm.residualSize() == 3
        cdatas.append(cm.createData())
        cmodels.append(cm)
    return cmodels, cdatas


# ----------------------------------------------------------------------------
# solver
# ----------------------------------------------------------------------------
def pin_pgs_solve(
    G,
    c,
    mu,
    max_iterations=10000,
    tol=1e-12,
    over_relaxation=1.0,
    lam0=None,
    return_info=False,
    tangent_rotation=True,
    complementarity_tol=0.0,
    fallback_relaxations=(0.7, 0.4, 0.2),
    _model=None,
    _joint_ids=None,
):
    """Solve the Coulomb NCP  xi = G Lambda + c  with pinocchio.PGSConstraintSolver.

    G: (3nc,3nc) symmetric PSD, c: (3nc,), mu: (nc,) friction coefficients.
    Ordering per contact is OUR convention [N, T1, T2].
    tol is used for pin's absolute/relative feasibility tolerances.  pin's
    complementarity measure is a product lambda.xi (scale dependent), so with a
    nonzero complementarity_tol it can stop early when impulses are small (seen:
    NCP violation 4e-9 with tol=1e-12); by default complementarity_tol=0, so
    pin stops on its relative-step test ||dx||_inf <= tol*||x||_inf (or on an
    exactly zero complementarity).  lam0 is an optional warm start (our ordering).
    tangent_rotation: rotate each tangent basis so pin's tangential PGS step is
    stable (exact reformulation, see module doc); False = raw pin behaviour.
    fallback_relaxations: if pin reports non-convergence (PGS limit cycle, seen
    for large mu / PSD G), re-solve from scratch with these smaller
    over_relaxation values in turn until pin converges; () = raw pin behaviour.
    Returns Lambda (our ordering); with return_info=True returns (Lambda, info).
    (long: Pinocchio's PGS set up, run and its result converted in one piece: the
    reference the prox is checked against)"""
    G = np.asarray(G, dtype=float)
    c = np.asarray(c, dtype=float).ravel()
    n = c.size
    if n % 3 != 0 or G.shape != (n, n):
        raise ValueError("G must be (3nc,3nc) and c of size 3nc")
    nc = n // 3
    mu = np.broadcast_to(np.asarray(mu, dtype=float), (nc,))

    if tangent_rotation:
        R = _tangent_rotation(G, nc)
        G = R.T @ G @ R
        c = R.T @ c
        if lam0 is not None:
            lam0 = R.T @ np.asarray(lam0, float).ravel()

    p = _ours_to_pin_perm(nc)
    G_pin = np.ascontiguousarray(G[np.ix_(p, p)])
    c_pin = np.ascontiguousarray(c[p])

    delassus = pin.DelassusOperatorDense(G_pin)
    cmodels, cdatas = _build_constraints(mu, _model, _joint_ids)

    def run_pin(omega):
        settings = pin.PGSSolverSettings()
        settings.max_iterations = int(max_iterations)
        settings.absolute_feasibility_tol = float(tol)
        settings.relative_feasibility_tol = float(tol)
        settings.absolute_complementarity_tol = float(complementarity_tol)
        settings.relative_complementarity_tol = float(complementarity_tol)
        settings.over_relaxation = float(omega)
        settings.solve_ncp = True  # (only affects recorded stats in pin 4.1, see module doc)
        settings.checkValidity()
        result = pin.PGSSolverResult()
        if lam0 is not None:
            result.setConstraintImpulseGuess(
                np.ascontiguousarray(np.asarray(lam0, float).ravel()[p])
            )
        solver = pin.PGSConstraintSolver(n)
        converged = solver.solve(delassus, c_pin, cmodels, cdatas, settings, result)
        return bool(converged), result

    omegas = [float(over_relaxation)] + [
        float(w) for w in fallback_relaxations if float(w) < float(over_relaxation)
    ]
    total_iterations = 0
    for omega in omegas:
        converged, result = run_pin(omega)
        total_iterations += int(result.iterations) + 1
        if converged:
            break

    lam_pin = np.asarray(result.retrieveConstraintImpulses()).ravel()
    lam = np.empty(n)
    lam[p] = lam_pin
    if tangent_rotation:
        lam = R @ lam
    if not converged:
        warnings.warn(
            f"pinocchio PGS did not converge in {result.iterations} iterations "
            f"(complementarity {result.complementarity:.2e}, "
            f"dual feasibility {result.dual_feasibility:.2e})",
            RuntimeWarning,
            stacklevel=2,
        )
    if return_info:
        info = dict(
            converged=bool(converged),
            iterations=int(result.iterations),  # pin's counter of the last run (0 = 1 sweep)
            total_sweeps=total_iterations,
            over_relaxation_used=omega,
            complementarity=float(result.complementarity),
            dual_feasibility=float(result.dual_feasibility),
            primal_feasibility=float(result.primal_feasibility),
        )
        return lam, info
    return lam


# ----------------------------------------------------------------------------
# checker
# ----------------------------------------------------------------------------
def ncp_residuals(G, c, mu, lam, tol=1e-9):
    """Per-condition max violations of the exact Coulomb NCP (our ordering).

    tol is only used to classify a contact as open (mu*L_N <= tol), sticking
    (||L_T|| < mu*L_N - tol) or sliding (otherwise).  All residuals are
    absolute (impulse units for cone conditions, velocity units for xi
    conditions, product units for L_N*xi_N).  'natural_map' is the
    classification-free residual
        |min(L_N, xi_N)|  and  ||L_T - Proj_{disk(mu L_N)}(L_T - xi_T)||.
    """
    G = np.asarray(G, float)
    c = np.asarray(c, float).ravel()
    lam = np.asarray(lam, float).ravel()
    nc = c.size // 3
    mu = np.broadcast_to(np.asarray(mu, float), (nc,))
    xi = G @ lam + c
    r = dict(
        lamN_neg=0.0,
        xiN_neg=0.0,
        compl_N=0.0,
        cone=0.0,
        stick_xiT=0.0,
        slide_perp=0.0,
        slide_dir=0.0,
        natural_map=0.0,
    )
    for i in range(nc):
        lN, lT = lam[3 * i], lam[3 * i + 1 : 3 * i + 3]
        xN, xT = xi[3 * i], xi[3 * i + 1 : 3 * i + 3]
        nlT = np.linalg.norm(lT)
        rad = mu[i] * lN
        r["lamN_neg"] = max(r["lamN_neg"], -lN)
        r["xiN_neg"] = max(r["xiN_neg"], -xN)
        r["compl_N"] = max(r["compl_N"], abs(lN * xN))
        r["cone"] = max(r["cone"], nlT - rad)
        if rad <= tol:
            pass  # open contact (or mu=0): xi_T free, L_T must be ~0 (checked by 'cone')
        elif nlT < rad - tol:
            r["stick_xiT"] = max(r["stick_xiT"], np.linalg.norm(xT))
        else:
            t = -lT / nlT  # sliding direction xi_T must point to
            a = float(xT @ t)
            r["slide_perp"] = max(r["slide_perp"], np.linalg.norm(xT - a * t))
            r["slide_dir"] = max(r["slide_dir"], -a)
        # natural-map residual
        rN = abs(min(lN, xN))
        z = lT - xT
        R = mu[i] * max(lN, 0.0)
        nz = np.linalg.norm(z)
        proj = z if nz <= R else (z * (R / nz) if nz > 0 else z)
        r["natural_map"] = max(r["natural_map"], rN, np.linalg.norm(lT - proj))
    return {k: max(v, 0.0) for k, v in r.items()}


def check_coulomb_ncp(G, c, mu, lam, tol=1e-9):
    """Max violation of the exact Coulomb NCP (our ordering [N,T1,T2]); see ncp_residuals."""
    return max(ncp_residuals(G, c, mu, lam, tol).values())


# ----------------------------------------------------------------------------
# self-checks
# ----------------------------------------------------------------------------
def _random_spd(rng, n, cond=10.0):
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    return Q @ np.diag(np.geomspace(1.0, cond, n)) @ Q.T


def _random_problem(rng, nc=4, ndof=18, c_in_range=False):
    W = rng.standard_normal((ndof, 3 * nc))
    M = _random_spd(rng, ndof)
    G = W.T @ np.linalg.solve(M, W)
    G = 0.5 * (G + G.T)
    # c_in_range: c = W^T u (a contact velocity of some generalized velocity u),
    # the physically meaningful case when G is only PSD (ndof < 3nc)
    c = W.T @ rng.standard_normal(ndof) if c_in_range else rng.standard_normal(3 * nc)
    mu = rng.uniform(0.2, 1.0, nc)
    return G, c, mu


def _classify(lam, mu, tol=1e-8):
    out = []
    for i in range(len(mu)):
        lN, nlT = lam[3 * i], np.linalg.norm(lam[3 * i + 1 : 3 * i + 3])
        if mu[i] * lN <= tol:
            out.append("open")
        elif nlT < mu[i] * lN - tol:
            out.append("stick")
        else:
            out.append("slide")
    return out


if __name__ == "__main__":
    np.set_printoptions(precision=6, suppress=False, linewidth=120)
    ok = True

    def report(name, G, c, mu, lam, info, expected=None, tol=1e-9):
        global ok
        viol = check_coulomb_ncp(G, c, mu, lam)
        err = None if expected is None else float(np.max(np.abs(lam - expected)))
        passed = viol < tol and (err is None or err < tol)
        ok &= passed
        print(f"[{'PASS' if passed else 'FAIL'}] {name}")
        print(f"    lam      = {lam}")
        if expected is not None:
            print(f"    expected = {np.asarray(expected)}   max|err| = {err:.3e}")
        print(f"    xi       = {G @ lam + c}")
        print(f"    NCP max violation = {viol:.3e}   pin info = {info}")

    mu1 = np.array([0.5])

    # (1a) single contact, diagonal G, sticking: Lambda = -G^{-1} c, inside cone
    G1 = np.diag([2.0, 3.0, 3.0])
    c = np.array([-1.0, 0.1, 0.0])
    lam, info = pin_pgs_solve(G1, c, mu1, return_info=True)
    report("single contact, diag G, sticking", G1, c, mu1, lam, info,
           np.array([0.5, -0.1 / 3.0, 0.0]))

    # (1b) single contact, diagonal G, sliding: L_N = 1/2, L_T = -mu L_N e1,
    # xi_T1 = 4.25 = s*0.25, s=17
    c = np.array([-1.0, 5.0, 0.0])
    lam, info = pin_pgs_solve(G1, c, mu1, return_info=True)
    report("single contact, diag G, sliding", G1, c, mu1, lam, info, np.array([0.5, -0.25, 0.0]))

    # (1c) single contact, normal/tangent coupling G_NT1 = 0.5, sliding along -T1:
    #   xi_N = 2 L_N + 0.5 (-mu L_N) - 1 = 0  =>  L_N = 1/(2 - 0.5 mu) = 1/1.75
    #   xi_T1 = 0.5 L_N - 3 mu L_N + 5 = 5 - L_N > 0 (=> s > 0),  xi_T2 = 0
    G1c = np.array([[2.0, 0.5, 0.0], [0.5, 3.0, 0.0], [0.0, 0.0, 3.0]])
    LN = 1.0 / 1.75
    lam, info = pin_pgs_solve(G1c, c, mu1, return_info=True)
    report("single contact, coupled G, sliding", G1c, c, mu1, lam, info,
           np.array([LN, -0.5 * LN, 0.0]))

    # (1d) single contact, separating: c_N > 0 => Lambda = 0
    c = np.array([1.0, 5.0, -2.0])
    lam, info = pin_pgs_solve(G1c, c, mu1, return_info=True)
    report("single contact, separating", G1c, c, mu1, lam, info, np.zeros(3))

    # (2) random 4-contact problems G = W^T M^-1 W (W 18x12, M SPD 18x18), c ~ N(0,1)
    def run_random(tag, n_prob, seed, ndof=18, c_in_range=False, nc=4, **kw):
        rng = np.random.default_rng(seed)
        worst, n_conv, n_fail, n_fb, iters = 0.0, 0, 0, 0, []
        kinds = {"open": 0, "stick": 0, "slide": 0}
        for k in range(n_prob):
            G, c, mu = _random_problem(rng, nc=nc, ndof=ndof, c_in_range=c_in_range)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                lam, info = pin_pgs_solve(G, c, mu, return_info=True, **kw)
            v = check_coulomb_ncp(G, c, mu, lam)
            worst = max(worst, v)
            n_conv += info["converged"]
            n_fb += info["over_relaxation_used"] != kw.get("over_relaxation", 1.0)
            n_fail += v >= 1e-9
            iters.append(info["total_sweeps"])
            for st in _classify(lam, mu):
                kinds[st] += 1
            if k == 0 and not kw and ndof == 18:
                report(f"{tag}: first problem", G, c, mu, lam, info)
                print(f"    mu = {mu}, contact states = {_classify(lam, mu)}")
                print(f"    residuals = {ncp_residuals(G, c, mu, lam)}")
        print(
            f"    {tag}: {n_prob} problems, worst NCP violation {worst:.3e}, "
            f"#violation>=1e-9: {n_fail}, pin converged flag {n_conv}/{n_prob}, "
            f"used fallback omega: {n_fb}, "
            f"sweeps median/max {int(np.median(iters))}/{max(iters)}, states {kinds}"
        )
        return worst, n_fail

    worst, _ = run_random("random 4 contacts (default, tangent_rotation=True)", 500, 0)
    passed = worst < 1e-9
    ok &= passed
    print(f"[{'PASS' if passed else 'FAIL'}] random 4-contact SPD problems, NCP violation < 1e-9")
    # informational: raw pinocchio behaviour (no tangent-basis rotation) and PSD Delassus (W 8x12)
    raw = dict(tangent_rotation=False, fallback_relaxations=())
    run_random("INFO raw pin (no rotation, no fallback)", 500, 0, **raw)
    run_random("INFO raw pin, over_relaxation=0.3", 500, 0, over_relaxation=0.3,
               max_iterations=100000, **raw)
    run_random("INFO rotation but no fallback", 500, 0, fallback_relaxations=())
    run_random("INFO no rotation, with fallback", 500, 0, tangent_rotation=False)
    run_random("INFO complementarity_tol=1e-12 (pin-style early stop)", 500, 0,
               complementarity_tol=1e-12)
    run_random("INFO PSD G (W 8x12, rank 8), c = W^T u", 200, 2, ndof=8, c_in_range=True)
    run_random("INFO PSD G, c = W^T u, no fallback", 200, 2, ndof=8, c_in_range=True,
               fallback_relaxations=())
    run_random("INFO 8 contacts, W 30x24", 200, 3, ndof=30, nc=8)
    run_random("INFO PSD G (W 8x12, rank 8), c random (may have no solution)", 200, 2, ndof=8)

    # (3) model geometry must not matter: other model / other joints / placements
    G, c, mu = _random_problem(np.random.default_rng(1))
    lam_a = pin_pgs_solve(G, c, mu)
    other = pin.Model()
    jid = other.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Random(), "ff")
    other.appendBodyToJoint(jid, pin.Inertia.Random(), pin.SE3.Identity())
    jid2 = other.addJoint(jid, pin.JointModelRX(), pin.SE3.Random(), "rx")
    other.appendBodyToJoint(jid2, pin.Inertia.Random(), pin.SE3.Identity())
    lam_b = pin_pgs_solve(G, c, mu, _model=other, _joint_ids=[1, 2, 2, 1])
    lam_c = pin_pgs_solve(G, c, mu, _joint_ids=[3, 7, 12, 20])
    d = max(np.max(np.abs(lam_a - lam_b)), np.max(np.abs(lam_a - lam_c)))
    passed = d == 0.0
    ok &= passed
    print(f"[{'PASS' if passed else 'FAIL'}] model/joint independence: max diff = {d:.3e}")

    # (4) the CCP would differ: check our NCP checker rejects the Anitescu/CCP solution of (1c)
    #     (sanity check of the checker, not of pin): CCP sliding has xi_N = mu*||xi_T|| != 0.
    lam_ccp_like = np.array([LN, -0.5 * LN, 0.0]) * 1.1
    v = check_coulomb_ncp(G1c, np.array([-1.0, 5.0, 0.0]), mu1, lam_ccp_like)
    passed = v > 1e-3
    ok &= passed
    print(f"[{'PASS' if passed else 'FAIL'}] checker rejects a wrong answer (violation {v:.3e})")

    print("ALL PASS" if ok else "SOME CHECKS FAILED")
    raise SystemExit(0 if ok else 1)
