"""Contact force distribution (Gehring et al. 2013, Sec. III-C; loco's ContactForceDistribution).

Given the desired net wrench b = (F, M) on the trunk (M about a reference point, here the
centre of mass) and the support feet at r_i (relative to that point), find the ground reaction
forces f_i (on the robot) from the QP

    min_f  ½ (A f − b)ᵀ S (A f − b) + ½ ε fᵀ f
    s.t.   |f_x| ≤ μ f_z,  |f_y| ≤ μ f_z          (friction pyramid, flat-ground axes)
           f_z ≥ f_min
           |−J_iᵀ f_i + g_i| ≤ τ_max               (joint torque limits; optional, ours)

with A = [I … I; [r_1]× … [r_n]×]. Everything is expressed in the heading (yaw) frame so that
S weighs roll, pitch and yaw moments separately. The torque rows keep the distributed forces
realisable by the 20 N m actuators: when the wrench cannot be produced within the limits the
QP trades it off by S instead of letting the saturation distort it arbitrarily.

Solved with ProxQP (proxsuite, dense); one QP object per number of support legs is kept and
warm-started from its last solution. A solver failure is counted, reported in ``status`` and
answered with a safe fallback (the weight shared equally, vertical forces).
"""
from __future__ import annotations

import importlib
import math
import sys
import types

import numpy as np

from .kernels import qp_matrices, torque_rows


def _import_proxqp_portable():
    """proxsuite's ``proxqp`` from its portable build, not the AVX2 / AVX-512 one.

    proxsuite's ``__init__`` loads the most vectorised of its three builds. The AVX2 build
    rounds differently with the alignment of its internal buffers, so the same QPs solved in
    two processes differ by ~1e-10 N (measured: 3 different torque digests in 4 processes
    over 1,600 trotting updates; the portable build gave one digest in 4, at the same speed
    on these 18-variable QPs). Closed-loop runs, sweeps on a pool or on Ray and replays of
    them are then reproducible bit for bit. The choice is made by answering proxsuite's
    instruction-set probe with "none" while it loads; if proxsuite was already imported by
    someone else, its loaded build is used as it is."""
    if "proxsuite" not in sys.modules:
        probe = types.ModuleType("proxsuite.instructionset")
        probe.has_AVX2 = probe.has_AVX512F = lambda: False
        sys.modules["proxsuite.instructionset"] = probe
        try:
            importlib.import_module("proxsuite")
        finally:
            if sys.modules.get("proxsuite.instructionset") is probe:
                del sys.modules["proxsuite.instructionset"]
    return importlib.import_module("proxsuite").proxqp


try:
    proxqp = _import_proxqp_portable()
except ImportError as e:  # pragma: no cover
    raise ImportError("starleth_controller needs proxsuite (pip install proxsuite)") from e

_SOLVED = proxqp.QPSolverOutput.PROXQP_SOLVED


class ContactForceDistribution:
    def __init__(self, mu=0.7, min_normal_force=2.0, weights=(1, 1, 1, 20, 20, 5),
                 regularization=1e-4, max_normal_force=None, torque_limit=None,
                 eps_abs=1e-6, max_iter=200):
        self.mu = float(mu)
        self.min_normal_force = float(min_normal_force)
        self.max_normal_force = None if max_normal_force is None else float(max_normal_force)
        self.torque_limit = None if torque_limit is None else \
            np.broadcast_to(np.asarray(torque_limit, dtype=float), (3,)).copy()
        self.S = np.asarray(weights, dtype=float)
        self.eps = float(regularization)
        self.eps_abs = float(eps_abs)
        self.max_iter = int(max_iter)
        nt = 3 if self.torque_limit is not None else 0
        self._rows = 5 + nt                      # constraint rows per foot
        self._qp = {}
        self._C, self._l, self._u = {}, {}, {}
        self._A = {n: np.zeros((6, 3 * n)) for n in range(1, 5)}
        self._H = {n: np.zeros((3 * n, 3 * n)) for n in range(1, 5)}
        self._g = {n: np.zeros(3 * n) for n in range(1, 5)}
        for n in range(1, 5):
            a = self._A[n]
            for i in range(n):
                a[0:3, 3 * i:3 * i + 3] = np.eye(3)
            C = np.zeros((self._rows * n, 3 * n))
            lo = np.zeros(self._rows * n)
            up = np.full(self._rows * n, 1e20)
            for i in range(n):
                r = 5 * i
                c = 3 * i
                C[r + 0, c + 0], C[r + 0, c + 2] = -1.0, self.mu   # μ f_z − f_x ≥ 0
                C[r + 1, c + 0], C[r + 1, c + 2] = 1.0, self.mu    # μ f_z + f_x ≥ 0
                C[r + 2, c + 1], C[r + 2, c + 2] = -1.0, self.mu
                C[r + 3, c + 1], C[r + 3, c + 2] = 1.0, self.mu
                C[r + 4, c + 2] = 1.0                               # f_z ≥ f_min
                lo[r + 4] = self.min_normal_force
                if self.max_normal_force is not None:
                    up[r + 4] = self.max_normal_force
            self._C[n], self._l[n], self._u[n] = C, lo, up
        #: last solve: "solved" or proxsuite's status name; iterations; failures so far
        self.status = "none"
        self.iterations = 0
        self.solved = True
        self.failures = 0

    def __getstate__(self):
        """The state without the solver objects (proxsuite's QP cannot be copied or pickled:
        a deep copy of it crashes); a copy builds its own at its next solve, cold-started."""
        state = self.__dict__.copy()
        state["_qp"] = {}
        return state

    def _solve_qp(self, n, H, g, C, lo, up):
        qp = self._qp.get(n)
        if qp is None:
            qp = proxqp.dense.QP(3 * n, 0, self._rows * n)
            qp.settings.eps_abs = self.eps_abs
            qp.settings.eps_rel = 0.0
            qp.settings.max_iter = self.max_iter
            qp.settings.verbose = False
            qp.init(H, g, None, None, C, lo, up)
            qp.solve()   # (warm starting before a first solve crashes proxsuite 0.8)
            qp.settings.initial_guess = proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
            self._qp[n] = qp
        elif self.torque_limit is None:
            qp.update(H=H, g=g, update_preconditioner=False)
            qp.solve()
        else:
            qp.update(H=H, g=g, C=C, l=lo, u=up, update_preconditioner=False)
            qp.solve()
        return qp

    def solve(self, r, b, J=None, gleg=None):
        """r: (n, 3) support-foot positions relative to the reference point; b: desired
        wrench (6,); J: (n, 3, 3) contact Jacobians w.r.t. each leg's joints and gleg: (n, 3)
        the legs' gravity torques (needed with torque limits). All in the heading frame.
        Returns f (n, 3), the forces of the ground on the feet, heading frame."""
        n = r.shape[0]
        H, g, C, lo, up = self._H[n], self._g[n], self._C[n], self._l[n], self._u[n]
        qp_matrices(r, b, self.S, self.eps, self._A[n], H, g)
        if self.torque_limit is not None:
            if J is None or gleg is None:
                raise ValueError("torque-limited force distribution needs J and gleg")
            torque_rows(J, gleg, self.torque_limit, 5 * n, C, lo, up)
        qp = self._solve_qp(n, H, g, C, lo, up)
        results = qp.results              # each attribute read builds a binding object
        info = results.info
        st = info.status
        self.iterations = int(info.iter)
        x = results.x
        ok = st == _SOLVED and math.isfinite(float(x.sum()))
        if not ok:
            self.failures += 1
            self.status = str(st).split(".")[-1]
            x = np.zeros(3 * n)
            x[2::3] = max(b[2] / n, self.min_normal_force)
            self._qp.pop(n, None)     # no warm start from a failed problem
        else:
            self.status = "solved"
        self.solved = ok
        return x.reshape(n, 3)
