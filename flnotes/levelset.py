"""The MPC's level-set program: eq. (MPC_form_miqp) restricted to the plans cheaper than a level ``J_up``.

Constraint generation, level-set node bounds and a warm start, all exact.

See :class:`HorizonMIQP`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.sparse as sp

from .solvers import BACKENDS, BOUND_TOL, FEAS_TOL, MIQP, make_solver, next_margin, project_to_box
from .solvers.problem import Array, _vec
from .systems import condense

# ---------------------------------------------------------------------------
# The MPC program of eq. (MPC_form_miqp), solved exactly and fast
# ---------------------------------------------------------------------------
#: Solver of the convex relaxations whose optimum centers the level set: it must be the exact optimum (a
#: perturbed one would shift the ellipsoid), so HiGHS's active-set QP, not DAQP's regularized one.
_RELAX = "highs"


@dataclass
class HorizonResult:
    """What :meth:`HorizonMIQP.solve` returns.

    Attributes
    ----------
    status
        ``"optimal"``, ``"time_limit"`` (a feasible plan without proof), ``"infeasible"`` or ``"error"``.
    v_pred, z_pred
        The plan, shapes (N_p, m) and (N_p + 1, n_z); ``None`` without one.
    objective
        Cost of eq. (MPC_form_miqp_a) of the plan, constants included.
    bound
        Proven lower bound on the optimum.
    gap
        ``|objective - bound| / max(1, |objective|)``.
    nodes
        Branch-and-bound nodes over all rounds.
    time
        Seconds for the whole call.
    n_binaries
        Binaries of the last mixed-integer program solved (after the levers).
    encoded_steps
        Predicted steps whose network constraint was encoded in that program.
    rounds
        Mixed-integer programs solved.
    screened
        True when the QP without the network constraint was already optimal.
    message
        What happened, in words.
    """

    status: str
    v_pred: Optional[Array]
    z_pred: Optional[Array]
    objective: float
    bound: float
    gap: float
    nodes: int
    time: float
    n_binaries: int
    encoded_steps: tuple
    rounds: int
    screened: bool
    backend: str
    message: str = ""


class HorizonMIQP:
    """Eq. (MPC_form_miqp) for one network, solved to global optimality with the real-time levers.

    The program, condensed (``z(k) = Sx[k] z0 + Su[k] V``, ``V = [v(0); ...; v(N_p-1)]``):

        min  J(V) = 0.5 V'H V + f(z0, z_ref)'V + c0(z0, z_ref)
        s.t. |Phi_NN(z(k), v(k))| <= u_max^eps,  k = 0..N_p-1        (MPC_form_miqp_b)
             z(k) in [z_lo, z_hi], k = 1..N_p,  v(k) in [v_lo, v_hi]  (MPC_form_miqp_d)

    with ``J`` the cost ``sum_k ||z(k) - z_ref(k)||_Q^2 + ||v(k)||_R^2 (+ ||z(N_p) - z_ref(N_p)||_P^2)``.
    Every lever is exact (the returned plan is a global optimum) and is a switch:

    * ``screening``: the QP without the network constraint first; when its optimum meets
      ``|Phi_NN| <= u_max^eps`` at every step (forward pass) it is the optimum.
    * ``bounds``: the node bounds of eq. (MIP_general_c) per predicted step: ``"box"``
      (FBBT on the domain box, the paper's setting), ``"horizon"`` (FBBT on the reachable
      boxes with ``z(0)`` fixed), ``"lp"`` (these, LP-tightened with ``|Phi_NN| <= u_max^eps``,
      :func:`flnotes.tightening.lp_bounds`), ``"levelset"`` (FBBT on the reachable boxes
      intersected with the level set of the relaxation, see below).
    * ``eliminate_stable``: stable neurons are substituted (``y = a`` or ``y = 0``) and get no
      binary; with ``False`` every neuron keeps its binary (fixed by its bounds).
    * ``encode``: ``"needed"`` encodes the network only at steps whose output bounds do not
      already lie within ``[-u_max^eps, u_max^eps]`` over the step's box; ``"all"`` at every step.
    * ``lazy``: constraint generation. Of the steps that need encoding, only those where the
      QP plan (or the previous solve) violated the constraint are encoded; the optimum is checked
      at every step with the forward pass and violated steps are added until it passes. Each
      program is a relaxation of the restricted one, so a plan that passes is its optimum.
    * ``warm_start``: a feasible plan (the previous one shifted) is an incumbent: the branch and
      bound only explores nodes that can beat it, and the level set uses its cost.

    The level set (``bounds="levelset"``). With ``(V_c, J_c)`` the optimum of a convex
    relaxation, every feasible ``V`` has ``J(V) >= J_c + 0.5 ||V - V_c||_H^2``
    (:func:`flnotes.tightening.ellipsoid_box`). A plan cheaper than a level ``J_up`` thus lies in an
    ellipsoid whose projection on ``(z(k), v(k))`` is a small box; FBBT on these boxes leaves
    few unstable neurons, and steps whose output is provably within the bound need no
    encoding at all. The restricted program (these bounds, plus the boxes as rows) contains
    every plan cheaper than ``J_up`` and nothing infeasible, so its optimum is the global
    optimum whenever it is below ``J_up``; otherwise ``J_up`` is raised (or, when ``J_up`` is a
    warm start's cost, the warm start is optimal). ``J_up`` starts at the warm start's cost or
    at ``J_c`` plus a small margin that is multiplied by 4 per round.

    Parameters
    ----------
    net
        ``Phi_NN``.
    Ad, Bd
        Discrete dynamics (n_z, n_z), (n_z, m).
    horizon
        ``N_p``.
    Q, R, P
        Weights (n_z, n_z), (m, m), terminal (n_z, n_z) or ``None``.
    z_lo, z_hi, v_lo, v_hi
        The state box ``X_z`` and the input range.
    u_eps
        ``u_max - eps`` (m,).
    backend
        Solver of the mixed-integer programs (:func:`make_solver`), default DAQP.
    bounds, screening, eliminate_stable, encode, warm_start, lazy
        The levers above.
    refine
        Rounds of level-set shrinking with the restricted program's own relaxation as the
        new center (each is valid for every plan cheaper than ``J_up``). Default 0: with
        constraint generation the extra relaxations cost more than they save (measured on
        the book's Quad-1D MPC, ``make bench``).
    root
        Start the level set from the relaxation of the whole program instead of the QP
        without the network (tighter center, but one larger relaxation per call).
    lp
        LP-based tightening (with ``|Phi_NN| <= u_max^eps``) of the encoded steps on top of
        the FBBT bounds: ``True``, ``False`` (default, the fastest measured with the level
        set and constraint generation at ``N_p = 10``), or ``"auto"`` (only when FBBT leaves
        more than ``lp_threshold`` unstable neurons in the encoded steps).
    solver_options
        Passed to :func:`make_solver`.
    """

    def __init__(self, net, Ad: Array, Bd: Array, horizon: int, Q: Array, R: Array, P: Optional[Array] = None, *,
                 z_lo: Array, z_hi: Array, v_lo: Array, v_hi: Array, u_eps, backend: str = "daqp",
                 bounds: str = "levelset", screening: bool = True, eliminate_stable: bool = True,
                 encode: str = "needed", warm_start: bool = True, lazy: bool = True, refine: int = 0, root: bool = False,
                 lp=False, lp_threshold: int = 40, solver_options: Optional[dict] = None):
        from .bounds import fbbt

        if bounds not in ("box", "horizon", "lp", "levelset"):
            raise ValueError(f"bounds must be 'box', 'horizon', 'lp' or 'levelset', got {bounds!r}")
        if encode not in ("needed", "all"):
            raise ValueError(f"encode must be 'needed' or 'all', got {encode!r}")
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if int(horizon) != horizon or horizon < 1:
            raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
        self.net, self.N = net, int(horizon)
        self.Ad, self.Bd = np.atleast_2d(np.asarray(Ad, float)), np.atleast_2d(np.asarray(Bd, float))
        nz, m = self.Bd.shape
        if self.Ad.shape != (nz, nz):
            raise ValueError(f"Ad must have shape ({nz}, {nz}) to match Bd {self.Bd.shape}, got {self.Ad.shape}")
        if net.n_in != nz + m or net.n_out != m:
            raise ValueError(f"net must map R^{nz + m} -> R^{m} for these dynamics, got R^{net.n_in} -> R^{net.n_out}")
        self.nz, self.m = nz, m
        self.Q, self.R = np.asarray(Q, float).reshape(nz, nz), np.asarray(R, float).reshape(m, m)
        self.P = np.zeros((nz, nz)) if P is None else np.asarray(P, float).reshape(nz, nz)
        self.z_lo, self.z_hi = _vec(z_lo, nz, "z_lo"), _vec(z_hi, nz, "z_hi")
        self.v_lo, self.v_hi = _vec(v_lo, m, "v_lo"), _vec(v_hi, m, "v_hi")
        self.u_eps = _vec(u_eps, m, "u_eps") if np.ndim(u_eps) else np.full(m, float(u_eps))
        if np.any(self.u_eps <= 0):
            raise ValueError(f"u_eps = u_max - eps must be positive, got {self.u_eps}")
        self.backend, self.bounds, self.screening = backend, bounds, bool(screening)
        self.eliminate_stable, self.encode, self.warm_start = bool(eliminate_stable), encode, bool(warm_start)
        self.lazy = bool(lazy)
        self._active_prev: tuple = ()  # steps encoded in the last solve (shifted by one for the next)
        #: How much ``u_max^eps`` is tightened in the rows handed to the solver (grows when a returned plan's
        #: forward pass exceeds ``u_max^eps + BOUND_TOL``; see the module docstring's tolerance policy).
        self.margin = 0.0
        if lp not in (True, False, "auto"):
            raise ValueError(f"lp must be True, False or 'auto', got {lp!r}")
        self.refine, self.root, self.lp, self.lp_threshold = int(refine), bool(root), lp, int(lp_threshold)
        self.verbose = False  # print the level-set rounds
        self._nb_override = None
        self.solver_options = dict(solver_options or {})
        N = self.N
        self.Sx, self.Su, self.H = condense(self.Ad, self.Bd, N, self.Q, self.R, self.P)
        Su = self.Su
        self.Wk = [self.Q] * N + [self.P]
        self.H_inv = np.linalg.inv(self.H)
        # rows mapping V to the network input [z(k); v(k)] of every step: (N, n_in, N m)
        T = np.zeros((N, nz + m, N * m))
        for k in range(N):
            T[k, :nz] = Su[k]
            T[k, nz:, k * m:(k + 1) * m] = np.eye(m)
        self.T = T
        self.box_bounds = fbbt(net, np.r_[self.z_lo, self.v_lo], np.r_[self.z_hi, self.v_hi])
        # the state box as rows of V (k = 1..N), used by every program
        self._A_state = Su[1:].reshape(N * nz, N * m)

    # -- the cost ------------------------------------------------------------------
    def _linear(self, z0: Array, z_ref: Array) -> tuple[Array, float]:
        E = self.Sx @ z0 - z_ref
        f = 2 * sum(self.Su[k].T @ self.Wk[k] @ E[k] for k in range(self.N + 1))
        c0 = float(sum(E[k] @ self.Wk[k] @ E[k] for k in range(self.N + 1)))
        return f, c0

    def cost(self, V: Array, f: Array, c0: float) -> float:
        V = np.asarray(V, float).reshape(-1)
        return float(0.5 * V @ self.H @ V + f @ V + c0)

    def predict(self, z0: Array, V: Array) -> Array:
        return self.Sx @ z0 + self.Su @ np.asarray(V, float).reshape(-1)

    def feasible(self, z0: Array, V: Array, tol: float = FEAS_TOL) -> bool:
        """Does the plan meet eq. (MPC_form_miqp_b)-(d)?

        The network bound by the forward pass to :data:`BOUND_TOL` (round-off only), the boxes of
        the predicted states and inputs to ``tol`` (a solver's feasibility tolerance).
        """
        V = np.asarray(V, float).reshape(self.N, self.m)
        Z = self.predict(z0, V)
        if np.any(Z[1:] < self.z_lo - tol) or np.any(Z[1:] > self.z_hi + tol):
            return False
        if np.any(V < self.v_lo - tol) or np.any(V > self.v_hi + tol):
            return False
        return bool(np.all(np.abs(self.net(np.hstack([Z[: self.N], V]))) <= self.u_eps + BOUND_TOL))

    # -- pieces ----------------------------------------------------------------------
    def _qp(self, f: Array, z0: Array, extra=None) -> tuple[Optional[Array], float]:
        """The QP without the network constraint (DAQP; H is positive definite)."""
        import daqp

        N = self.N
        Zf = (self.Sx @ z0)[1:].reshape(-1)
        bu = np.r_[np.tile(self.v_hi, N), np.tile(self.z_hi, N) - Zf]
        bl = np.r_[np.tile(self.v_lo, N), np.tile(self.z_lo, N) - Zf]
        x, fval, flag, _ = daqp.solve(self.H, f, self._A_state, bu, bl, np.zeros(len(bu), dtype=np.int32))
        if flag not in (1, 2):
            return None, np.inf
        return np.asarray(x, float), float(fval)

    def _boxes(self, z0: Array) -> tuple[Array, Array]:
        from .tightening import horizon_boxes

        lo, hi = horizon_boxes(self.Ad, self.Bd, z0, self.z_lo, self.z_hi, self.v_lo, self.v_hi, self.N)
        return lo, hi

    def _level_boxes(self, z0: Array, V_c: Array, delta: float, lo: Array, hi: Array) -> tuple[Array, Array]:
        from .tightening import ellipsoid_box

        nz = self.nz
        off = np.zeros(nz + self.m)
        lo2, hi2 = lo.copy(), hi.copy()
        Zf = self.Sx @ z0
        for k in range(self.N):
            off[:nz] = Zf[k]
            a, b = ellipsoid_box(self.T[k], self.H_inv, V_c, off, delta)
            lo2[k], hi2[k] = np.maximum(lo2[k], a - 1e-9), np.minimum(hi2[k], b + 1e-9)
        return lo2, hi2

    def _node_bounds(self, lo: Array, hi: Array, steps=None, use_lp: bool = True):
        from .bounds import NodeBounds, fbbt
        from .tightening import EmptyBoxError, lp_bounds

        if self.bounds == "box":
            b = self.box_bounds
            rep = lambda a: np.repeat(np.asarray(a)[None], self.N, axis=0)
            return NodeBounds([rep(L) for L in b.L], [rep(U) for U in b.U], rep(b.out_L), rep(b.out_U), "box")
        nb = fbbt(self.net, lo, hi)
        if use_lp and (self.bounds == "lp" or self.lp):
            todo = list(range(self.N)) if steps is None else sorted(steps)
            todo = [k for k in todo if nb.out_L[k].min() < -self.u_eps.max() or nb.out_U[k].max() > self.u_eps.min()]
            n_unst = sum(int(u[todo].sum()) for u in nb.unstable) if todo else 0
            if todo and (self.bounds == "lp" or self.lp is True or n_unst > self.lp_threshold):
                prior = NodeBounds([L[todo] for L in nb.L], [U[todo] for U in nb.U], nb.out_L[todo], nb.out_U[todo])
                try:
                    t = lp_bounds(self.net, lo[todo], hi[todo], out_bounds=(-self.u_eps, self.u_eps), prior=prior,
                                  skip_stable=True)
                except EmptyBoxError:  # no input of some step's box meets the output bound
                    return None
                for layer in range(len(nb.L)):
                    nb.L[layer][todo], nb.U[layer][todo] = t.L[layer], t.U[layer]
                nb.method = "lp"
        return nb

    def program(self, z0: Array, f: Array, c0: float, nb, steps, lo: Optional[Array] = None,
                hi: Optional[Array] = None) -> tuple[MIQP, list]:
        """The condensed big-M program with the network encoded at ``steps`` (compact form).

        Variables ``w = [V | y (unstable neurons) | alpha (unstable neurons)]``. Per unstable
        neuron with pre-activation ``a`` (affine in ``w``): ``y >= 0``, ``y >= a``,
        ``y <= U alpha``, ``y <= a - L (1 - alpha)``, i.e. eq. (MIP_general_b)-(MIP_general_c) with
        ``yund = y - a``; a stable neuron is ``y = a`` (active) or ``y = 0`` (inactive) plus the row
        ``L <= a <= U`` that keeps the substitution exact; ``|y^K| <= u_max^eps`` per encoded step;
        the state box; optional boxes ``lo <= [z(k); v(k)] <= hi`` for every step (rows). With
        ``eliminate_stable=False`` stable neurons keep a variable and a binary fixed by its bounds.
        Returns the :class:`MIQP` and per step the index arrays of the binaries.
        """
        net, N, nz, m = self.net, self.N, self.nz, self.m
        nV = N * m
        Zf = self.Sx @ z0
        steps = list(steps)
        # count variables
        n_unit = []
        for k in steps:
            cnt = []
            for layer in range(net.K - 1):
                L, U = np.asarray(nb.L[layer])[k], np.asarray(nb.U[layer])[k]
                cnt.append(int(((L < 0) & (U > 0)).sum()) if self.eliminate_stable else L.size)
            n_unit.append(cnt)
        n_y = int(sum(sum(c) for c in n_unit))
        n = nV + 2 * n_y
        rows, rl, ru = [], [], []
        lb = np.r_[np.tile(self.v_lo, N), np.zeros(2 * n_y)]
        ub = np.r_[np.tile(self.v_hi, N), np.full(n_y, np.inf), np.ones(n_y)]
        integ = np.r_[np.zeros(nV + n_y, dtype=int), np.ones(n_y, dtype=int)]
        # state box rows
        A_state = np.zeros((N * nz, n))
        A_state[:, :nV] = self._A_state
        rows.append(A_state)
        rl.append(np.tile(self.z_lo, N) - Zf[1:].reshape(-1))
        ru.append(np.tile(self.z_hi, N) - Zf[1:].reshape(-1))
        if lo is not None:  # boxes of every step as rows (the level-set restriction)
            Tb = np.zeros((N * (nz + m), n))
            Tb[:, :nV] = self.T.reshape(N * (nz + m), nV)
            off = np.hstack([Zf[:N], np.zeros((N, m))]).reshape(-1)
            rows.append(Tb)
            rl.append(lo.reshape(-1) - off)
            ru.append(hi.reshape(-1) - off)
        iy_next, ia_next = nV, nV + n_y
        alphas = []
        for s, k in enumerate(steps):
            Y = np.zeros((net.n_in, n))
            Y[:, :nV] = self.T[k]
            y0 = np.r_[Zf[k], np.zeros(m)]
            al_k = []
            for layer, (W, b) in enumerate(zip(net.W[:-1], net.b[:-1])):
                Aa, a0 = W @ Y, W @ y0 + b
                L, U = np.asarray(nb.L[layer], float)[k], np.asarray(nb.U[layer], float)[k]
                act, ina = L >= 0, U <= 0
                unst = ~(act | ina)
                var = unst if self.eliminate_stable else np.ones_like(unst)
                idx = np.flatnonzero(var)
                iy = iy_next + np.arange(idx.size)
                ia = ia_next + np.arange(idx.size)
                iy_next += idx.size
                ia_next += idx.size
                Yn = np.zeros_like(Aa)
                yn0 = np.zeros_like(a0)
                sub = act & ~var                                     # substituted active neurons
                Yn[sub], yn0[sub] = Aa[sub], a0[sub]
                Yn[idx, iy] = 1.0
                # rows of the encoded neurons
                Up, Lm = np.maximum(U[idx], 0.0), np.minimum(L[idx], 0.0)
                R1 = Aa[idx].copy()
                R1[np.arange(idx.size), iy] -= 1.0          # a - y <= 0
                R2 = np.zeros((idx.size, n))
                R2[np.arange(idx.size), iy] = 1.0
                R2[np.arange(idx.size), ia] = -Up
                R3 = -Aa[idx]
                R3[np.arange(idx.size), iy] += 1.0
                R3[np.arange(idx.size), ia] -= Lm  # y - a - L alpha <= -L
                rows += [R1, R2, R3]
                rl += [np.full(idx.size, -np.inf)] * 3
                ru += [-a0[idx], np.zeros(idx.size), a0[idx] - Lm]
                ub[iy] = Up
                lb[ia], ub[ia] = np.where(L[idx] >= 0, 1.0, 0.0), np.where(U[idx] <= 0, 0.0, 1.0)
                # stable substituted neurons: L <= a <= U keeps the substitution exact
                st = np.flatnonzero(~var)
                if st.size:
                    rows.append(Aa[st])
                    rl.append(L[st] - a0[st])
                    ru.append(U[st] - a0[st])
                al_k.append(ia)
                Y, y0 = Yn, yn0
            out, o0 = net.W[-1] @ Y, net.W[-1] @ y0 + net.b[-1]
            u_in = self.u_eps - self.margin  # tightened by what a solver's tolerance let through before
            rows.append(out)
            rl.append(-u_in - o0)
            ru.append(u_in - o0)    # eq. (Phi_NN_ep)
            alphas.append(np.concatenate(al_k) if al_k else np.zeros(0, int))
        A = np.vstack(rows)
        Hf = sp.block_diag([sp.csc_matrix(self.H), sp.csc_matrix((n - nV, n - nV))], format="csc")
        c = np.r_[f, np.zeros(n - nV)]
        prob = MIQP(Hf, c, c0, sp.csr_matrix(A), np.concatenate(rl), np.concatenate(ru), lb, ub, integ)
        return prob, alphas

    def vector(self, z0: Array, V: Array, nb, steps, prob: MIQP) -> Array:
        """The program's ``w`` for a plan ``V`` (the network's hidden values from its forward pass)."""
        N, m = self.N, self.m
        V = np.asarray(V, float).reshape(N, m)
        Z = self.predict(z0, V)
        w = np.zeros(prob.n)
        w[: N * m] = V.reshape(-1)
        steps = list(steps)
        if not steps:
            return w
        _, pre = self.net.forward(np.hstack([Z[steps], V[steps]]))
        n_y = (prob.n - N * m) // 2
        iy, ia = N * m, N * m + n_y
        for s, k in enumerate(steps):
            for layer in range(self.net.K - 1):
                L, U = np.asarray(nb.L[layer])[k], np.asarray(nb.U[layer])[k]
                var = ((L < 0) & (U > 0)) if self.eliminate_stable else np.ones(L.size, bool)
                a = pre[layer][s][var]
                w[iy:iy + a.size] = np.maximum(a, 0.0)
                w[ia:ia + a.size] = np.clip((a > 0).astype(float), (L[var] >= 0).astype(float), (U[var] > 0).astype(float))
                iy += a.size
                ia += a.size
        return w

    # -- the solve ---------------------------------------------------------------------
    def solve(self, z0: Array, z_ref: Array, warm_start: Optional[Array] = None, time_limit: Optional[float] = None,
              gap: float = 1e-6) -> HorizonResult:
        """Solve eq. (MPC_form_miqp) for the measured ``z0`` and the reference ``z_ref`` (N_p + 1, n_z).

        ``warm_start`` is a plan ``V`` of shape (N_p, m) (e.g. the previous one shifted); it is
        used only if it is feasible.
        """
        from .tightening import EmptyBoxError

        t0 = time.perf_counter()
        N, nz, m = self.N, self.nz, self.m
        z0 = project_to_box(_vec(z0, nz, "z0"), self.z_lo, self.z_hi, "z0")
        z_ref = np.asarray(z_ref, float)
        if z_ref.shape == (nz,):
            z_ref = np.repeat(z_ref[None], N + 1, axis=0)
        if z_ref.shape != (N + 1, nz):
            raise ValueError(f"z_ref must have shape ({N + 1}, {nz}) (k = 0..N_p) or ({nz},), got {z_ref.shape}")
        f, c0 = self._linear(z0, z_ref)
        stats = dict(nodes=0, rounds=0)

        def done(status, V, bound, msg, screened=False, n_bin=0, steps=()):
            if V is None:
                return HorizonResult(status, None, None, np.nan, bound, np.inf, stats["nodes"],
                                     time.perf_counter() - t0, n_bin, tuple(steps), stats["rounds"], screened,
                                     self.backend, msg)
            V = np.asarray(V, float).reshape(N, m)
            obj = self.cost(V, f, c0)
            bound = min(bound, obj)
            g = abs(obj - bound) / max(1.0, abs(obj)) if np.isfinite(bound) else np.inf
            return HorizonResult(status, V, self.predict(z0, V), obj, bound, g, stats["nodes"],
                                 time.perf_counter() - t0, n_bin, tuple(int(s) for s in steps), stats["rounds"],
                                 screened, self.backend, msg)

        # incumbent from the warm start
        inc_V, inc_J = None, np.inf
        if self.warm_start and warm_start is not None:
            Vw = np.asarray(warm_start, float).reshape(-1)
            if Vw.shape == (N * m,) and np.all(np.isfinite(Vw)) and self.feasible(z0, Vw):
                inc_V, inc_J = Vw, self.cost(Vw, f, c0)
        # relaxation without the network: screening and the first level-set center
        V_c, J_c = None, -np.inf
        if self.screening or self.bounds == "levelset":
            V_q, fq = self._qp(f, z0)
            if V_q is None:
                return done("infeasible", None, np.inf, "the QP without the network constraint is infeasible")
            V_c, J_c = V_q, fq + c0
            if self.screening and self.feasible(z0, V_q):
                self._active_prev = ()
                return done("optimal", V_q, J_c, "screened: the QP optimum meets the network constraint", True)
        try:
            lo_h, hi_h = self._boxes(z0)
        except EmptyBoxError as exc:
            return done("infeasible", None, np.inf, f"infeasible: {exc}")
        active = set(self._violated(z0, V_c)) if V_c is not None else set()
        active |= {k - 1 for k in self._active_prev if k >= 1}

        def remaining():
            return None if time_limit is None else max(time_limit - (time.perf_counter() - t0), 1e-3)

        if self.bounds == "levelset" and self.root:
            # a better global center: the convex relaxation of the whole program (FBBT bounds on the
            # reachable boxes, valid for every admissible plan); J(V) >= J_root + 0.5 ||V - V_root||_H^2
            nb0 = self._node_bounds(lo_h, hi_h)
            st0 = self._steps(nb0) if nb0 is not None else None
            if st0 is None:
                return done("infeasible", None, np.inf, "a step's output bounds exclude the admissible range")
            if st0:
                p0, _ = self.program(z0, f, c0, nb0, st0)
                r0 = make_solver(MIQP(p0.H, p0.c, p0.c0, p0.A, p0.rl, p0.ru, p0.lb, p0.ub,
                                      np.zeros(p0.n, dtype=int)), _RELAX).solve()
                if r0.status == "infeasible":
                    return done("infeasible", None, np.inf, "the relaxation of the program is infeasible")
                if r0.status == "optimal" and r0.objective > J_c:
                    V_c, J_c = r0.w[: N * m], r0.objective

        delta = None
        last = dict(n_bin=0, steps=())
        while True:
            if time_limit is not None and time.perf_counter() - t0 > time_limit:
                if inc_V is not None:
                    return done("time_limit", inc_V, J_c, "time limit: the warm start is returned", **last)
                return done("time_limit", None, J_c, "time limit without a feasible plan", **last)
            lo, hi = lo_h, hi_h
            J_up = np.inf
            full = self.bounds != "levelset"  # the program solved below is the whole program
            if self.bounds == "levelset":
                if delta is None:
                    delta = max(1e-3 * max(1.0, abs(J_c)), 1e-4)
                J_up = min(inc_J, J_c + delta)
                if not np.isfinite(J_up) or delta > 1e12 * max(1.0, abs(J_c)):
                    # the level set no longer restricts anything: solve the whole program
                    J_up, full, delta = np.inf, True, np.inf
                # shrink the boxes with the level set, refine the center with the program's relaxation
                empty = False
                cen_V, cen_J = V_c, J_c
                for r in range(0 if full else 1 + self.refine):
                    lo, hi = self._level_boxes(z0, cen_V, max(J_up - cen_J, 0.0), lo, hi)
                    if np.any(lo > hi + 1e-12):
                        empty = True
                        break
                    hi = np.maximum(hi, lo)
                    if r == self.refine:
                        break
                    nb = self._node_bounds(lo, hi, use_lp=False)  # FBBT while shrinking; LP once at the end
                    steps = self._steps(nb) if nb is not None else None
                    if steps is None:
                        empty = True
                        break
                    if not steps or sum(int(u[steps].sum()) for u in nb.unstable) <= 8:
                        break
                    prob, _ = self.program(z0, f, c0, nb, steps, lo, hi)
                    relax = MIQP(prob.H, prob.c, prob.c0, prob.A, prob.rl, prob.ru, prob.lb, prob.ub,
                                 np.zeros(prob.n, dtype=int))
                    rr = make_solver(relax, _RELAX).solve()
                    if rr.status == "infeasible":
                        empty = True
                        break
                    if rr.status != "optimal" or rr.objective <= cen_J:
                        break
                    cen_V, cen_J = rr.w[: N * m], rr.objective
                    if self.verbose:
                        print(f"    refine {r}: J_up {J_up:.6g} center {cen_J:.6g}")
                    if cen_J > J_up:
                        empty = True
                        break
                if not full:
                    full = bool(np.all(lo <= lo_h) and np.all(hi >= hi_h))  # the level set cut nothing
                if not empty and self.lp is not False:
                    # many binaries left: LP bounds (with |Phi_NN| <= u_max^eps) once, their relaxation as a
                    # last center, and FBBT on the shrunk boxes intersected with those LP bounds
                    nb_lp = self._node_bounds(lo, hi)
                    if nb_lp is None:
                        empty = True
                    elif nb_lp.method == "lp":
                        steps = self._steps(nb_lp)
                        if steps:
                            prob, _ = self.program(z0, f, c0, nb_lp, steps, lo, hi)
                            rr = make_solver(MIQP(prob.H, prob.c, prob.c0, prob.A, prob.rl, prob.ru, prob.lb, prob.ub,
                                                  np.zeros(prob.n, dtype=int)), _RELAX).solve()
                            if rr.status == "infeasible" or (rr.status == "optimal" and rr.objective > J_up):
                                empty = True
                            elif rr.status == "optimal" and rr.objective > cen_J:
                                cen_V, cen_J = rr.w[: N * m], rr.objective
                                lo, hi = self._level_boxes(z0, cen_V, max(J_up - cen_J, 0.0), lo, hi)
                                if np.any(lo > hi + 1e-12):
                                    empty = True
                                hi = np.maximum(hi, lo)
                        if not empty:
                            from .tightening import intersect
                            nb_f = self._node_bounds(lo, hi, use_lp=False)
                            pre_lp = intersect(nb_f, nb_lp, method="lp")
                            pre_lp.out_L, pre_lp.out_U = nb_f.out_L, nb_f.out_U  # FBBT's: valid on the whole box
                            self._nb_override = pre_lp
                if empty:  # nothing cheaper than J_up
                    self._nb_override = None
                    if full and inc_V is None:
                        return done("infeasible", None, np.inf, "no admissible plan: the node bounds exclude "
                                    "|Phi_NN| <= u_max^eps over the reachable boxes", **last)
                    if J_up >= inc_J or full:
                        return done("optimal", inc_V, inc_J, "the warm start is optimal (level set empty)", **last)
                    delta *= 4.0
                    continue
            nb = self._nb_override if self._nb_override is not None else self._node_bounds(lo, hi)
            self._nb_override = None
            steps = self._steps(nb) if nb is not None else None
            if steps is None:
                if full and inc_V is None:
                    return done("infeasible", None, np.inf, "a step's output bounds exclude the admissible range")
                if J_up >= inc_J or full:
                    return done("optimal", inc_V, inc_J, "the warm start is optimal (no admissible output)", **last)
                delta *= 4.0
                continue
            restrict = self.bounds == "levelset"
            # constraint generation: encode only the needed steps found active so far, add violated ones
            enc = sorted(set(steps) & active) if self.lazy else list(steps)
            while True:
                prob, _ = self.program(z0, f, c0, nb, enc, lo if restrict else None, hi if restrict else None)
                n_bin = prob.n_integer
                last = dict(n_bin=n_bin, steps=enc)
                if self.verbose:
                    print(f"  round: J_up {J_up:.6g} J_c {J_c:.6g} delta {delta} binaries {n_bin} steps {enc}")
                solver = make_solver(prob, self.backend, **self.solver_options)
                w0 = self.vector(z0, inc_V, nb, enc, prob) if inc_V is not None else None
                res = solver.solve(warm_start=w0, time_limit=remaining(), gap=gap)
                stats["nodes"] += res.nodes
                stats["rounds"] += 1
                if res.status != "optimal":
                    break
                viol = set(self._violated(z0, res.w[: N * m]))
                if viol & set(enc):
                    # an encoded step exceeds u_max^eps by more than round-off: the solver's tolerance let it
                    # through. Tighten the bound in the rows and solve again (at most a few times).
                    ex = self._excess(z0, res.w[: N * m], enc)
                    if stats.get("tightened", 0) >= 5:
                        return done("error", None, -np.inf, f"the optimum exceeds u_max^eps by {ex:.1e} after "
                                    f"tightening the rows by {self.margin:.1e}", **last)
                    stats["tightened"] = stats.get("tightened", 0) + 1
                    self.margin = next_margin(self.margin, ex, float(np.max(self.u_eps)))
                    continue
                new = sorted(viol - set(enc))
                if not new or not self.lazy:
                    break
                enc = sorted(set(enc) | set(new))
                active |= set(new)
            if res.status == "optimal":
                V = res.w[: N * m]
                J = self.cost(V, f, c0)
                if not self.feasible(z0, V):
                    return done("error", None, -np.inf, "the program's optimum fails the forward-pass check", **last)
                self._active_prev = tuple(enc)
                if full or J <= J_up + 1e-9 * max(1.0, abs(J_up)):
                    bound = res.bound if np.isfinite(res.bound) else J
                    return done("optimal", V, bound, f"{res.backend}: {res.message}", **last)
                if J < inc_J:  # feasible (checked above): a new incumbent
                    inc_V, inc_J = V, J
            elif res.status == "infeasible":
                if full and inc_V is None:
                    return done("infeasible", None, np.inf, "the program is infeasible", **last)
            elif res.status == "time_limit":
                cand = res.w[: N * m] if res.w is not None else None
                if cand is not None and self.feasible(z0, cand) and self.cost(cand, f, c0) < inc_J:
                    return done("time_limit", cand, -np.inf, f"time limit: {res.message}", **last)
                return done("time_limit", inc_V, -np.inf, f"time limit: {res.message}", **last)
            else:
                return done("error", inc_V, -np.inf, f"{res.backend}: {res.status} {res.message}", **last)
            # nothing below J_up in the restricted program
            if J_up >= inc_J or full:
                return done("optimal", inc_V, inc_J, "the warm start is optimal (nothing cheaper)", **last)
            delta *= 4.0

    def _violated(self, z0: Array, V: Array, tol: float = BOUND_TOL) -> list:
        """Predicted steps ``k`` where the plan ``V`` breaks ``|Phi_NN(z(k), v(k))| <= u_max^eps`` (forward pass)."""
        V = np.asarray(V, float).reshape(self.N, self.m)
        Z = self.predict(z0, V)
        out = np.abs(self.net(np.hstack([Z[: self.N], V])))
        return np.flatnonzero(np.any(out > self.u_eps + tol, axis=1)).tolist()

    def _excess(self, z0: Array, V: Array, steps) -> float:
        """``max |Phi_NN(z(k), v(k))| - u_max^eps`` over the predicted ``steps`` of the plan ``V``."""
        V = np.asarray(V, float).reshape(self.N, self.m)
        Z = self.predict(z0, V)
        st = list(steps)
        return float(np.max(np.abs(self.net(np.hstack([Z[: self.N], V])[st])) - self.u_eps))

    def _steps(self, nb):
        """Steps whose network constraint must be encoded; ``None`` when a step cannot meet it at all."""
        c = self.u_eps
        if self.encode == "all":
            return list(range(self.N))
        oL, oU = np.asarray(nb.out_L), np.asarray(nb.out_U)
        if np.any(np.any(oL > c, axis=1) | np.any(oU < -c, axis=1)):
            return None
        return [k for k in range(self.N) if np.any(oL[k] < -c) or np.any(oU[k] > c)]
