"""MPC with the network constraint along the whole horizon, eq. (MPC_form_miqp).

At each sampling instant the controller solves the mixed-integer quadratic
program (MIQP)

    min   sum_{k=0}^{N_p-1} ||z(k) - z_ref(k)||_Q^2 + ||v(k)||_R^2  (+ ||z(N_p) - z_ref(N_p)||_P^2)
    s.t.  |Phi_NN(z(k), v(k))| <= u_max^eps = u_max - eps,         k = 0..N_p-1   (MPC_form_miqp_b)
          z(k+1) = A_d z(k) + B_d v(k),                            k = 0..N_p-1   (MPC_form_miqp_c)
          z(k) in X_z, v(k) in the network's v-range,                             (MPC_form_miqp_d)
          z(0) = the measured state,

where the network constraint is the big-M encoding of eq. (MIP_general), one
copy per predicted step (``N_p * sum_k n_k`` binaries before stable neurons are
removed). ``X_z`` is the network's domain box: outside it the error bound
``eps`` is not claimed, so the predicted states must stay inside (here also
``z(N_p)``, so that a shifted plan stays admissible). Because
``|Phi - Phi_NN| <= eps`` on that box (eq. approx_err), every predicted step
satisfies the true input bound ``|Phi(z(k), v(k))| <= u_max`` for the nominal
model (Proposition 1).

The program is built once and re-solved with new data each step. The levers
that make it fast are switches of :class:`MPC`, so that each effect can be
measured. All of them are exact: they never change the optimum.

* ``bounds="horizon"``: node bounds recomputed every step by FBBT on the
  reachable boxes of the predicted states (``z(0)`` fixed to the measurement,
  boxes propagated with ``A_d``, ``B_d`` and intersected with ``X_z``, see
  :func:`flnotes.tightening.horizon_boxes`); neurons whose bounds do not
  straddle zero lose their binary. ``bounds="box"`` uses the domain box at
  every step (the paper's setting); ``bounds="lp"`` adds LP-based tightening
  restricted to ``|Phi_NN| <= u_max^eps`` (:func:`flnotes.tightening.lp_bounds`).
* ``bounds="levelset"`` (the default but with ``"cvxpy-scip"``): every plan cheaper than a level ``J_up``
  lies in an ellipsoid around the optimum of a convex relaxation, whose
  projection on each ``(z(k), v(k))`` is a small box; FBBT (and, when many
  neurons remain unstable, LP tightening) on these boxes leaves few binaries,
  and steps whose output provably meets the bound are not encoded at all.
  ``J_up`` starts at the warm start's cost and is raised until the restricted
  program's optimum lies below it, which makes it the global optimum
  (:class:`flnotes.levelset.HorizonMIQP`, chapter "Making it real-time").
* ``warm_start=True``: the previous plan shifted by one step (its last input
  repeated) is handed to the solver as a first incumbent when it is feasible.
* ``screening=True``: the QP without the network constraint is solved first;
  if its optimum satisfies ``|Phi_NN| <= u_max^eps`` at every predicted step
  (checked with the network's forward pass) it is the MIQP's optimum, since
  the MIQP's feasible set is a subset of the QP's.
* ``lazy=True`` (constraint generation): the network constraint is encoded
  only at the predicted steps where it was found violated (starting from the
  screening QP and the steps active in the previous plan); the program with
  these copies is solved, the plan is checked at every step with the forward
  pass, violated steps are added, and so on. Each round solves a relaxation
  of eq. (MPC_form_miqp), so a plan that passes the check is its optimum.
* ``formulation="sparse"`` keeps ``z(0..N_p)`` as variables tied by the
  dynamics rows (the form written in the paper); ``"condensed"`` eliminates
  them (``z(k) = A_d^k z(0) + sum_j A_d^{k-1-j} B_d v(j)``); both keep one
  persistent solver model per set of encoded steps and only update numbers.
  ``"compact"`` (the default with DAQP) is condensed too and rebuilt for each
  state with the stable neurons substituted out, no equality rows and only
  the free binaries (eq. MIP_general with ``yund = ybar - a``), which suits
  DAQP's dense branch and bound.
* Warm start polish: with ``formulation="compact"`` the warm start (shifted
  plan, or at the first step the screening QP's plan repaired step by step)
  is improved by the QP with its activation pattern fixed before the branch
  and bound starts; a better incumbent prunes more nodes.
* ``backend``: ``"cvxpy-scip"`` is the reference (the program written with
  :func:`flnotes.encode` and solved cold by SCIP through cvxpy, every copy
  encoded); the other backends keep persistent models of the matrix form (see
  :meth:`MPC.problem`) and only update their numbers.
* ``time_limit`` (seconds per control step, bounds and set-up included): when
  it is hit, the solver's best incumbent is returned if it satisfies the
  constraints at every predicted step (status ``"time_limit"``, its gap to the
  relaxation's bound recorded). Otherwise a fallback plan is applied
  (``fallback=True``, :meth:`MPC.fallback_plan`), safety first: the applied
  input satisfies ``|Phi_NN(z, v)| <= u_max^eps`` whenever any admissible ``v``
  exists at the measured state (the shifted previous plan if it is admissible,
  else a plan repaired step by step with :meth:`MPC.feasible_tail`, always
  tried, else an admissible first input found exactly by :meth:`MPC.safe_input`);
  when none exists, the least-violation input is applied and flagged
  (``input_admissible=False``). The same fallback applies when the program is
  infeasible or the solver fails. Nothing is silent: every step's status, gap,
  nodes, time and message are kept in :attr:`MPC.history`.

"Optimal" is claimed only when proven (see :mod:`flnotes.solvers`), and the
returned plan is checked with the network's forward pass at every predicted
step: ``|Phi_NN| <= u_max^eps`` holds in floating point (to the round-off
:data:`flnotes.solvers.BOUND_TOL`); when a solver's tolerance lets a point through
above it, the bound in the rows is tightened (:attr:`MPC.margin`) and the
program solved again. A measured state at most :data:`flnotes.solvers.BOX_TOL`
outside the domain box is projected onto it; farther out is a ``ValueError``.
"""
from __future__ import annotations

import time
import warnings
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np
import scipy.sparse as sp

from ._checks import as_vector, weight_matrix
from .bounds import NodeBounds, fbbt
from .encoding import bigm_form, encode
from .network import ReLUNet
from .simulate import StepResult
from .systems import FLSystem, condense
from .tightening import EmptyBoxError, horizon_boxes, lp_bounds
from .solvers import BOUND_TOL, FEAS_TOL, next_margin, project_to_box  # the tolerance policy, see flnotes.solvers

Array = np.ndarray

#: Exported to ``flnotes``; the chapter's measurement helpers below stay under ``flnotes.mpc``.
__all__ = ["MPC", "MPCStep", "sine_reference"]

#: Accepted ``backend`` names: the cvxpy reference and the persistent back-ends of :mod:`flnotes.solvers`.
BACKENDS = ("auto", "cvxpy-scip", "highs", "scip", "daqp", "gurobi", "cplex")

#: DAQP settings for the big-M programs: its cycling guard is loosened (the big-M rows are degenerate;
#: with the defaults DAQP may stop with "cycling" on them). Override with ``solver_options``.
DAQP_OPTIONS = {"params": {"cycle_tol": 1000, "progress_tol": 1e-10}}



# --------------------------------------------------------------------------- references
def sine_reference(amplitude: float = 1.5, omega: float = 1.0, n_z: int = 3, phase: float = 0.0
                   ) -> Callable[[Array], Array]:
    """A smooth reference ``x_ref(t) = amplitude sin(omega t + phase)`` with consistent derivatives.

    Returns a vectorized ``t -> z_ref(t)``: times of shape (T,) give (T, n_z)
    with column ``i`` the ``i``-th time derivative of ``x_ref``, as the
    Brunovsky state ``z = [x, x', x'', ...]`` requires.
    """
    if n_z < 1:
        raise ValueError(f"n_z must be >= 1, got {n_z}")

    def z_ref(t: Array) -> Array:
        t = np.atleast_1d(np.asarray(t, float))
        cols = [amplitude * omega**i * np.sin(omega * t + phase + i * np.pi / 2) for i in range(n_z)]
        return np.stack(cols, axis=-1)

    z_ref.__doc__ = f"x_ref(t) = {amplitude} sin({omega} t + {phase}) and its derivatives, shape (T, {n_z})"
    return z_ref


# --------------------------------------------------------------------------- results
@dataclass
class MPCStep:
    """One solve of eq. (MPC_form_miqp): the input to apply, the plan and the statistics.

    Attributes
    ----------
    v
        First predicted input ``v*(0)`` to apply, shape (m,); ``None`` when the
        program is infeasible and no previous plan exists.
    z_pred, v_pred
        Predicted trajectories, shapes (N_p + 1, n_z) and (N_p, m).
    u_nn_pred
        ``Phi_NN(z(k), v(k))`` along the plan, shape (N_p, m) (forward pass).
    status
        ``"optimal"``, ``"time_limit"`` (incumbent returned, see ``gap``),
        ``"infeasible"``, or the solver's word for another failure.
    objective, bound, gap
        Cost of the returned plan (eq. MPC_form_miqp_a), the solver's lower
        bound and the relative gap.
    nodes
        Branch-and-bound nodes, summed over the rounds (0 when screening
        returned the QP optimum).
    solve_time
        Seconds in the solvers (screening QP included).
    wall_time
        Seconds for the whole call (bounds, updates, solves, checks).
    screened
        True when the QP without the network constraint was already feasible
        for it, hence optimal.
    fallback
        True when ``v`` does not come from this solve (see :meth:`MPC.fallback_plan`).
    input_admissible
        True when the applied ``v`` satisfies ``|Phi_NN(z, v)| <= u_max^eps`` at the measured
        state (forward pass, to :data:`flnotes.solvers.BOUND_TOL`). False only on a fallback where no
        admissible ``v`` exists: then ``v`` is the least-violation input.
    warm_started
        True when the shifted previous plan was passed to the solver.
    n_binaries
        Binaries left free after stable-neuron elimination in the last program
        solved (the full count is ``MPC.n_binaries_full``).
    encoded_steps
        Predicted steps whose network constraint was encoded in the last program
        (all of them unless ``lazy``).
    rounds
        Programs solved in this call (constraint generation rounds; 0 when screened).
    backend, message
        Which solver ran, and anything it said.
    """

    v: Optional[Array]
    z_pred: Optional[Array]
    v_pred: Optional[Array]
    u_nn_pred: Optional[Array]
    status: str
    objective: float = np.nan
    bound: float = np.nan
    gap: float = np.nan
    nodes: int = 0
    solve_time: float = 0.0
    wall_time: float = 0.0
    screened: bool = False
    fallback: bool = False
    input_admissible: bool = True
    warm_started: bool = False
    n_binaries: int = 0
    encoded_steps: tuple = ()
    rounds: int = 0
    backend: str = ""
    message: str = ""

    @property
    def ok(self) -> bool:
        """A plan feasible for the whole program (optimal, or an incumbent at the time limit)."""
        return self.v is not None and not self.fallback and self.status in ("optimal", "time_limit")

    def as_info(self) -> dict:
        """The fields logged by :func:`flnotes.simulate` in ``StepResult.info``."""
        keys = ("z_pred", "v_pred", "u_nn_pred", "objective", "bound", "gap", "nodes", "solve_time", "wall_time",
                "screened", "warm_started", "n_binaries", "encoded_steps", "rounds", "backend", "message",
                "input_admissible")
        return {k: getattr(self, k) for k in keys}


# --------------------------------------------------------------------------- the matrix form
class _Program:
    """Eq. (MPC_form_miqp) as ``min .5 w'Hw + c'w + c0, rl <= A w <= ru, lb <= w <= ub`` with the
    network constraint encoded at the predicted steps ``steps`` only.

    Layout of ``w``: ``[z(0..N_p) | v(0..N_p-1) | copy 1 | copy 2 | ...]`` (sparse) or
    ``[v(0..N_p-1) | copy 1 | ...]`` (condensed). A copy is one :func:`flnotes.bigm_form` block without
    its input entries: ``ybar, yund, alpha`` of every hidden layer and the output ``y^K``; its input rows
    act on ``[z(k); v(k)]`` (sparse) or on ``v`` through ``z(k) = Sx[k] z(0) + Su[k] V`` (condensed).
    Rows: the dynamics (sparse) or the state box of ``z(1..N_p)`` (condensed), then per copy the
    equalities of eq. (MIP_general_b, d), then per layer the big-M rows of eq. (MIP_general_c).
    The big-M coefficients live at fixed positions of ``A.data`` (explicit zeros are kept), so that new
    node bounds change numbers only, never the sparsity pattern.
    """

    def __init__(self, mpc: "MPC", steps: Sequence[int], condensed: bool):
        N, nz, m, net = mpc.N, mpc.n_z, mpc.m, mpc.net
        self.mpc, self.steps, self.condensed = mpc, tuple(int(k) for k in steps), bool(condensed)
        form = mpc._form
        n_in = net.n_in
        rest = np.setdiff1d(np.arange(form.n), form.x)
        nb = len(rest)
        if condensed:
            self.iz = None
            self.iv = np.arange(N * m).reshape(N, m)
            off = N * m
        else:
            self.iz = np.arange((N + 1) * nz).reshape(N + 1, nz)
            self.iv = (N + 1) * nz + np.arange(N * m).reshape(N, m)
            off = (N + 1) * nz + N * m
        S = len(self.steps)
        n = off + S * nb
        g = np.full((S, form.n), -1)
        for j, k in enumerate(self.steps):
            g[j, rest] = off + j * nb + np.arange(nb)
            if not condensed:
                g[j, form.x] = np.r_[self.iz[k], self.iv[k]]
        self.n = n
        self.i_out = g[:, form.out]
        self.i_ybar = [g[:, a] for a in form.ybar]
        self.i_yund = [g[:, a] for a in form.yund]
        self.i_alpha = [g[:, a] for a in form.alpha]

        rows, cols, vals, rl, ru = [], [], [], [], []
        r = 0
        if condensed:  # state box of z(1..N) as rows Su[k] V in [zl - Sx z0, zh - Sx z0]
            self.r_box = np.arange(N * nz).reshape(N, nz)
            for k in range(1, N + 1):
                blk = mpc.Su[k][:, : k * m]
                rr, cc = np.nonzero(np.ones_like(blk))
                rows += (r + rr).tolist()
                cols += cc.tolist()
                vals += blk[rr, cc].tolist()
                r += nz
            rl += [0.0] * (N * nz)
            ru += [0.0] * (N * nz)
        else:  # (MPC_form_miqp_c): z(k+1) - Ad z(k) - Bd v(k) = 0
            for k in range(N):
                for i in range(nz):
                    rows += [r] * (1 + nz + m)
                    cols += [self.iz[k + 1, i], *self.iz[k], *self.iv[k]]
                    vals += [1.0, *(-mpc.Ad[i]), *(-mpc.Bd[i])]
                    r += 1
            rl += [0.0] * (N * nz)
            ru += [0.0] * (N * nz)
        # (MIP_general_b), (MIP_general_d): one copy per encoded step
        Aeq = form.A_eq.tocoo()
        isx = np.isin(Aeq.col, form.x)
        Ar = sp.coo_matrix((Aeq.data[~isx], (Aeq.row[~isx], Aeq.col[~isx])), shape=Aeq.shape)
        self._Ax = np.zeros((Aeq.shape[0], n_in))  # input columns of the equalities (first layer)
        np.add.at(self._Ax, (Aeq.row[isx], np.searchsorted(form.x, Aeq.col[isx])), Aeq.data[isx])
        self.r_eq = []
        for j, k in enumerate(self.steps):
            rows += (r + Ar.row).tolist()
            cols += g[j, Ar.col].tolist()
            vals += Ar.data.tolist()
            if condensed:  # input [z(k); v(k)] = T_k V + t_k(z0), T_k = [Su[k]; E_k]
                T = np.zeros((n_in, N * m))
                T[:nz] = mpc.Su[k]
                T[nz:, k * m:(k + 1) * m] = np.eye(m)
                AT = self._Ax @ T
                rr, cc = np.nonzero(np.abs(AT) > 0)
                rows += (r + rr).tolist()
                cols += self.iv.ravel()[cc].tolist()
                vals += AT[rr, cc].tolist()
            else:
                xr, xc = np.nonzero(self._Ax)
                rows += (r + xr).tolist()
                cols += g[j, form.x][xc].tolist()
                vals += self._Ax[xr, xc].tolist()
            self.r_eq.append(np.arange(r, r + Aeq.shape[0]))
            rl += form.b_eq.tolist()
            ru += form.b_eq.tolist()
            r += Aeq.shape[0]
        self._b_eq = form.b_eq.copy()
        # (MIP_general_c): ybar - U+ alpha <= 0 and yund - L- alpha <= -L-
        self.r_U, self.r_L = [], []
        for layer, nk in enumerate(net.widths):
            rU = r + np.arange(S * nk).reshape(S, nk)
            r += S * nk
            rL = r + np.arange(S * nk).reshape(S, nk)
            r += S * nk
            for rr, iy in ((rU, self.i_ybar[layer]), (rL, self.i_yund[layer])):
                rows += np.repeat(rr.ravel(), 2).tolist()
                cols += np.stack([iy.ravel(), self.i_alpha[layer].ravel()], 1).ravel().tolist()
                vals += [1.0, -1.0] * rr.size
                rl += [-np.inf] * rr.size
                ru += [0.0] * rr.size
            self.r_U.append(rU), self.r_L.append(rL)
        A = sp.csr_matrix((np.asarray(vals, float), (np.asarray(rows, int), np.asarray(cols, int))), shape=(r, n))
        A.sort_indices()
        self.A, self.rl, self.ru = A, np.asarray(rl, float), np.asarray(ru, float)
        self.p_U = [self._positions(rU, ia) for rU, ia in zip(self.r_U, self.i_alpha)]
        self.p_L = [self._positions(rL, ia) for rL, ia in zip(self.r_L, self.i_alpha)]

        if condensed:
            Hv = sp.csc_matrix(mpc._Hqp)
            self.H = sp.block_diag([Hv, sp.csc_matrix((n - N * m, n - N * m))], format="csc")
        else:
            Hd = sp.lil_matrix((n, n))
            for k in range(N + 1):
                Hd[np.ix_(self.iz[k], self.iz[k])] = 2 * mpc._Wk[k]
            for k in range(N):
                Hd[np.ix_(self.iv[k], self.iv[k])] = 2 * mpc.R
            self.H = Hd.tocsc()
        self.integrality = np.zeros(n, dtype=int)
        for ia in self.i_alpha:
            self.integrality[ia.ravel()] = 1
        self.lb, self.ub = np.full(n, -np.inf), np.full(n, np.inf)
        self.lb[self.iv], self.ub[self.iv] = mpc.v_lo, mpc.v_hi
        self.lb[self.i_out], self.ub[self.i_out] = -mpc.u_solve, mpc.u_solve  # eq. (Phi_NN_ep)
        for iy in self.i_ybar + self.i_yund:
            self.lb[iy] = 0.0
        self.c, self.c0 = np.zeros(n), 0.0

    def _positions(self, rows: Array, cols: Array) -> Array:
        A = self.A
        out = np.empty(rows.shape, int)
        for idx in np.ndindex(rows.shape):
            r, c = rows[idx], cols[idx]
            s, e = A.indptr[r], A.indptr[r + 1]
            out[idx] = s + int(np.searchsorted(A.indices[s:e], c))
        return out

    def set_data(self, z0: Array, R: Array, nb: NodeBounds, zl: Array, zh: Array) -> None:
        """Write the measured state, the reference and per-step node bounds (arrays (N_p, n_k)) in place."""
        mpc, N, nz = self.mpc, self.mpc.N, self.mpc.n_z
        st = list(self.steps)
        A, lb, ub, ru = self.A, self.lb, self.ub, self.ru
        for layer, (L, U) in enumerate(zip(nb.L, nb.U)):
            L, U = np.asarray(L)[st], np.asarray(U)[st]
            Up, Lm = np.maximum(U, 0.0), np.minimum(L, 0.0)
            A.data[self.p_U[layer]] = -Up                 # ybar <= U alpha
            A.data[self.p_L[layer]] = -Lm                 # yund <= -L (1 - alpha)
            ru[self.r_L[layer]] = -Lm
            ub[self.i_ybar[layer]], ub[self.i_yund[layer]] = Up, -Lm
            ia = self.i_alpha[layer]
            lb[ia] = np.where(L >= 0, 1.0, 0.0)           # stably active: alpha = 1
            ub[ia] = np.where(U <= 0, 0.0, 1.0)           # stably inactive: alpha = 0
        lb[self.i_out], ub[self.i_out] = -mpc.u_solve, mpc.u_solve  # eq. (Phi_NN_ep), tightened (see MPC.margin)
        Zfree = mpc.Sx @ z0                               # (N+1, nz): the free response
        if self.condensed:
            self.rl[self.r_box] = zl[1:] - Zfree[1:]
            self.ru[self.r_box] = zh[1:] - Zfree[1:]
            for j, k in enumerate(st):
                rhs = self._b_eq - self._Ax[:, :nz] @ Zfree[k]
                self.rl[self.r_eq[j]] = self.ru[self.r_eq[j]] = rhs
            E = Zfree - R
            f = 2 * sum(mpc.Su[k].T @ mpc._Wk[k] @ E[k] for k in range(N + 1))
            self.c = np.zeros(self.n)
            self.c[self.iv.ravel()] = f
            self.c0 = float(sum(E[k] @ mpc._Wk[k] @ E[k] for k in range(N + 1)))
        else:
            lb[self.iz[0]] = ub[self.iz[0]] = z0
            lb[self.iz[1:]], ub[self.iz[1:]] = zl[1:], zh[1:]
            self.c = np.zeros(self.n)
            self.c0 = 0.0
            for k in range(N + 1):
                self.c[self.iz[k]] = -2 * mpc._Wk[k] @ R[k]
                self.c0 += float(R[k] @ mpc._Wk[k] @ R[k])

    @property
    def n_free(self) -> int:
        """Binaries left free by the current node bounds."""
        if not self.steps:
            return 0
        ia = np.concatenate([a.ravel() for a in self.i_alpha])
        return int(np.sum(self.lb[ia] < self.ub[ia]))

    def miqp(self):
        from .solvers import MIQP

        return MIQP(self.H, self.c, self.c0, self.A.copy(), self.rl.copy(), self.ru.copy(), self.lb.copy(),
                    self.ub.copy(), self.integrality.copy())

    def vector(self, Z: Array, V: Array) -> Array:
        """The full ``w`` of a plan; the copies' hidden variables from the network's forward pass."""
        w = np.zeros(self.n)
        if not self.condensed:
            w[self.iz] = Z
        w[self.iv] = V
        if self.steps:
            st = list(self.steps)
            out, pre = self.mpc.net.forward(np.hstack([Z[st], V[st]]))
            for layer, a in enumerate(pre):
                w[self.i_ybar[layer]] = np.maximum(a, 0.0)
                w[self.i_yund[layer]] = np.maximum(-a, 0.0)
                w[self.i_alpha[layer]] = (a > 0).astype(float)
            ia = np.concatenate([a.ravel() for a in self.i_alpha])
            w[ia] = np.clip(w[ia], self.lb[ia], self.ub[ia])  # a fixed alpha wins where a pre-activation is 0
            w[self.i_out] = out
        return w

    def plan(self, w: Array, z0: Array) -> tuple[Array, Array]:
        """``(z_pred, v_pred)`` from a solution ``w``."""
        V = np.asarray(w)[self.iv]
        if self.condensed:
            return self.mpc.Sx @ z0 + self.mpc.Su @ V.reshape(-1), V
        return np.asarray(w)[self.iz], V


class _CompactProgram:
    """Eq. (MPC_form_miqp) condensed, with stable neurons substituted out; built anew for each state.

    The same constraints as eq. (MIP_general) with ``yund = ybar - a`` substituted (``a`` the
    pre-activation): per unstable neuron a variable ``y = ybar >= 0``, a binary ``alpha`` and the rows

        y - a >= 0,    y - U alpha <= 0,    y - a - L alpha <= -L,

    while a stably active neuron is the affine expression ``y = a`` and a stably inactive one ``y = 0``
    (no variable). Every pre-activation is an affine function of ``w = [V | y's | alpha's]``, propagated
    layer by layer. There are no equality rows and only the binaries that the node bounds leave free:
    the form for dense active-set solvers (DAQP), whose model is rebuilt at every call anyway.
    """

    condensed = True

    def __init__(self, mpc: "MPC", steps: Sequence[int], z0: Array, R: Array, nb: NodeBounds, zl: Array, zh: Array):
        N, nz, m, net = mpc.N, mpc.n_z, mpc.m, mpc.net
        self.mpc, self.steps = mpc, tuple(int(k) for k in steps)
        nV = N * m
        n_max = nV + 2 * len(self.steps) * net.n_hidden
        self.iv = np.arange(nV).reshape(N, m)
        rows_A, rl, ru = [], [], []
        lb, ub = list(np.tile(mpc.v_lo, N)), list(np.tile(mpc.v_hi, N))
        integ = [0] * nV
        Zfree = mpc.Sx @ z0
        # state box of z(1..N): Su[k] V in [zl - Sx z0, zh - Sx z0]   (MPC_form_miqp_d)
        for k in range(1, N + 1):
            blk = np.zeros((nz, n_max))
            blk[:, :nV] = mpc.Su[k]
            rows_A.append(blk)
            rl.append(zl[k] - Zfree[k])
            ru.append(zh[k] - Zfree[k])
        n = nV
        self.units = []  # per encoded step: list per layer of (index of y variables, index of alpha, unstable mask)
        for k in self.steps:
            T = np.zeros((net.n_in, n_max))
            T[:nz, :nV] = mpc.Su[k]
            T[nz:, k * m:(k + 1) * m] = np.eye(m)
            Y, y0 = T, np.r_[Zfree[k], np.zeros(m)]                    # input [z(k); v(k)] = Y w + y0
            per = []
            for layer, (W, b) in enumerate(zip(net.W[:-1], net.b[:-1])):
                Aa, a0 = W @ Y, W @ y0 + b                            # pre-activation a = Aa w + a0
                L, U = np.asarray(nb.L[layer])[k], np.asarray(nb.U[layer])[k]
                act, unst = L >= 0, (L < 0) & (U > 0)
                Yn, yn0 = np.zeros_like(Aa), np.zeros_like(a0)
                Yn[act], yn0[act] = Aa[act], a0[act]                  # stably active: y = a
                iy = np.flatnonzero(unst)
                idx_y = n + np.arange(iy.size)
                idx_al = n + iy.size + np.arange(iy.size)
                n += 2 * iy.size
                for j, yi, ai in zip(iy, idx_y, idx_al):
                    Yn[j, yi] = 1.0
                    r1 = -Aa[j].copy()
                    r1[yi] += 1.0                 # y - a >= 0
                    rows_A.append(r1[None])
                    rl.append([a0[j]])
                    ru.append([np.inf])
                    r2 = np.zeros(n_max)
                    r2[yi], r2[ai] = 1.0, -U[j]  # y - U alpha <= 0
                    rows_A.append(r2[None])
                    rl.append([-np.inf])
                    ru.append([0.0])
                    r3 = -Aa[j].copy()
                    r3[yi] += 1.0
                    r3[ai] -= L[j]  # y - a - L alpha <= -L
                    rows_A.append(r3[None])
                    rl.append([-np.inf])
                    ru.append([a0[j] - L[j]])
                lb += [0.0] * iy.size + [0.0] * iy.size
                ub += list(U[iy]) + [1.0] * iy.size
                integ += [0] * iy.size + [1] * iy.size
                per.append((idx_y, idx_al, unst))
                Y, y0 = Yn, yn0
            out, o0 = net.W[-1] @ Y, net.W[-1] @ y0 + net.b[-1]      # eq. (MIP_general_d), (Phi_NN_ep)
            rows_A.append(out)
            rl.append(-mpc.u_solve - o0)
            ru.append(mpc.u_solve - o0)
            self.units.append(per)
        A = np.vstack(rows_A)[:, :n]
        self.n = n
        self.A = sp.csr_matrix(A)
        self.rl, self.ru = np.concatenate([np.atleast_1d(x) for x in rl]), np.concatenate([np.atleast_1d(x) for x in ru])
        self.lb, self.ub = np.asarray(lb, float), np.asarray(ub, float)
        self.integrality = np.asarray(integ, int)
        self.H = sp.block_diag([sp.csc_matrix(mpc._Hqp), sp.csc_matrix((n - nV, n - nV))], format="csc")
        E = Zfree - R
        self.c = np.zeros(n)
        self.c[:nV] = 2 * sum(mpc.Su[k].T @ mpc._Wk[k] @ E[k] for k in range(N + 1))
        self.c0 = float(sum(E[k] @ mpc._Wk[k] @ E[k] for k in range(N + 1)))

    @property
    def n_free(self) -> int:
        return int(self.integrality.sum())

    def miqp(self):
        from .solvers import MIQP

        return MIQP(self.H, self.c, self.c0, self.A, self.rl, self.ru, self.lb, self.ub, self.integrality)

    def vector(self, Z: Array, V: Array) -> Array:
        w = np.zeros(self.n)
        w[self.iv] = V
        if self.steps:
            _, pre = self.mpc.net.forward(np.hstack([Z[list(self.steps)], V[list(self.steps)]]))
            for s, per in enumerate(self.units):
                for layer, (idx_y, idx_al, unst) in enumerate(per):
                    a = pre[layer][s][unst]
                    w[idx_y], w[idx_al] = np.maximum(a, 0.0), (a > 0).astype(float)
        return w

    def plan(self, w: Array, z0: Array) -> tuple[Array, Array]:
        V = np.asarray(w)[self.iv]
        return self.mpc.predict(z0, V), V


# --------------------------------------------------------------------------- the controller
class MPC:
    """The MIQP-based MPC of eq. (MPC_form_miqp) with the network constraint at every predicted step.

    Parameters
    ----------
    system
        The feedback-linearizable system (its Brunovsky pair, domain box and ``u_max``).
    net
        ``Phi_NN``, a ReLU network approximating ``Phi`` on ``system``'s domain box.
    eps
        Error bound of eq. (approx_err), shape (m,) or scalar: the constraint is
        ``|Phi_NN| <= u_max - eps`` (eq. Phi_NN_ep).
    horizon
        Prediction horizon ``N_p``.
    ts
        Sampling time ``t_s`` (seconds).
    Q, R
        Stage weights of ``l(z, v) = ||z - z_ref||_Q^2 + ||v||_R^2``, shapes
        (n_z, n_z) and (m, m) (scalars or vectors are made diagonal).
    P
        Optional terminal weight on ``z(N_p)``. The paper's cost
        (eq. MPC_form_miqp_a) stops at ``k = N_p - 1``: ``None`` (default)
        reproduces it.
    backend
        ``"cvxpy-scip"``: the reference, the program written with
        :func:`flnotes.encode` and solved cold by SCIP through cvxpy.
        ``"daqp"``, ``"scip"``, ``"gurobi"``, ``"cplex"``: through
        :func:`flnotes.solvers.make_solver`. ``"auto"`` is ``"daqp"``, the fastest
        exact back-end measured on this program.
    bounds
        ``"levelset"``, ``"box"``, ``"horizon"`` or ``"lp"``: see the module
        docstring. ``"auto"`` is ``"levelset"`` (the fastest measured), or ``"lp"``
        with ``backend="cvxpy-scip"``.
    warm_start, screening, lazy
        The exact levers described in the module docstring (``formulation`` does
        not apply to ``bounds="levelset"``, which builds its programs itself).
    formulation
        ``"sparse"``, ``"condensed"`` or ``"auto"`` (condensed for DAQP, sparse otherwise).
    time_limit
        Seconds per control step (bounds and set-up included), or ``None``. On
        hit: the best incumbent if it is feasible for the whole program
        (status ``"time_limit"``), else a fallback plan (``fallback=True``);
        see the module docstring.
    gap
        Relative optimality gap at which the solver stops.
    discretization
        ``"rk4"`` (the paper) or ``"exact"``; for chains of at most four
        integrators they coincide.
    v_box
        Range ``(v_lo, v_hi)`` of ``v`` in the program; default the network's domain box.
    solver_options
        Passed to :func:`flnotes.solvers.make_solver`.

    Examples
    --------
    >>> mpc = MPC(fl.quad1d(), net, eps=0.0322, horizon=10, ts=0.1, Q=[10, 1, 1], R=0.0175)
    >>> step = mpc(z, z_ref)            # z_ref of shape (horizon + 1, n_z), or (n_z,) for a constant one
    >>> step.v, step.z_pred, step.status, step.solve_time
    """

    def __init__(self, system: FLSystem, net: ReLUNet, eps, horizon: int = 10, ts: float = 0.1,
                 Q=None, R=None, P=None, *, backend: str = "auto", bounds: str = "auto",
                 warm_start: bool = True, screening: bool = True, lazy: bool = True, formulation: str = "auto",
                 time_limit: Optional[float] = None, gap: float = 1e-6, discretization: str = "rk4",
                 v_box: Optional[tuple] = None, solver_options: Optional[dict] = None):
        self._init_args = dict(system=system, net=net, eps=eps, horizon=horizon, ts=ts, Q=Q, R=R, P=P, backend=backend,
                               bounds=bounds, warm_start=warm_start, screening=screening, lazy=lazy,
                               formulation=formulation, time_limit=time_limit, gap=gap, discretization=discretization,
                               v_box=v_box, solver_options=solver_options)
        if net.n_in != system.n_in or net.n_out != system.m:
            raise ValueError(f"net maps R^{net.n_in} -> R^{net.n_out} but the system needs (z, v) in R^{system.n_in} "
                             f"-> u in R^{system.m}")
        if int(horizon) != horizon or horizon < 1:
            raise ValueError(f"horizon (N_p) must be a positive integer, got {horizon!r}")
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if bounds not in ("auto", "box", "horizon", "lp", "levelset"):
            raise ValueError(f"bounds must be 'auto', 'box', 'horizon', 'lp' or 'levelset', got {bounds!r}")
        from .solvers.base import _require

        for pkg in (("cvxpy", "scip") if backend == "cvxpy-scip" else ("daqp" if backend == "auto" else backend,)):
            if pkg == "cvxpy":
                try:
                    import cvxpy  # noqa: F401
                except ImportError as exc:  # pragma: no cover - cvxpy is a requirement
                    raise ImportError("backend='cvxpy-scip' needs cvxpy: pip install cvxpy") from exc
            else:
                _require(pkg)  # ImportError naming the package to install, here rather than at the first solve
        if bounds == "auto":
            bounds = "lp" if backend == "cvxpy-scip" else "levelset"
        if bounds == "levelset" and backend == "cvxpy-scip":
            raise ValueError("bounds='levelset' needs a persistent back-end ('daqp', 'scip', 'highs', 'gurobi', "
                             "'cplex'); 'cvxpy-scip' is the reference and encodes every step on the domain box")
        if formulation not in ("auto", "sparse", "condensed", "compact"):
            raise ValueError(f"formulation must be 'auto', 'sparse', 'condensed' or 'compact', got {formulation!r}")
        if time_limit is not None and not (np.isfinite(time_limit) and time_limit > 0):
            raise ValueError(f"time_limit must be a positive number of seconds or None, got {time_limit!r}")
        if not (np.isfinite(ts) and ts > 0):
            raise ValueError(f"ts must be a positive sampling time, got {ts!r}")
        self.system, self.net = system, net
        self.n_z, self.m, self.N = system.n_z, system.m, int(horizon)
        self.ts = float(ts)
        self.eps = as_vector(eps, self.m, "eps")
        self.u_eps = system.u_max - self.eps
        if np.any(self.eps < 0) or np.any(self.u_eps <= 0):
            raise ValueError(f"need 0 <= eps < u_max: eps = {self.eps}, u_max = {system.u_max} leaves no admissible "
                             f"input (u_max - eps = {self.u_eps})")
        self.Q = weight_matrix(Q if Q is not None else np.eye(self.n_z), self.n_z, "Q")
        self.R = weight_matrix(R if R is not None else np.eye(self.m), self.m, "R", definite=True)
        self.P = weight_matrix(P, self.n_z, "P") if P is not None else np.zeros((self.n_z, self.n_z))
        self.discretization = discretization
        self.Ad, self.Bd = system.discretize(self.ts, discretization)
        self.z_lo, self.z_hi = system.lo[: self.n_z].copy(), system.hi[: self.n_z].copy()
        vb = (system.lo[self.n_z:], system.hi[self.n_z:]) if v_box is None else v_box
        self.v_lo, self.v_hi = as_vector(vb[0], self.m, "v_box[0]"), as_vector(vb[1], self.m, "v_box[1]")
        self.backend, self.bounds = ("daqp" if backend == "auto" else backend), bounds
        self.warm_start, self.screening, self.lazy = bool(warm_start), bool(screening), bool(lazy)
        self.formulation = ("compact" if self.backend == "daqp" else "sparse") if formulation == "auto" else formulation
        self.time_limit, self.gap = time_limit, float(gap)
        self.solver_options = dict(DAQP_OPTIONS if self.backend == "daqp" else {}, **(solver_options or {}))
        self.box_bounds = fbbt(net, np.r_[self.z_lo, self.v_lo], np.r_[self.z_hi, self.v_hi])
        self._form = bigm_form(net, self.box_bounds)
        self._build_condensed()
        self._hz = None
        if bounds == "levelset":
            from .levelset import HorizonMIQP

            self._hz = HorizonMIQP(net, self.Ad, self.Bd, self.N, self.Q, self.R, self.P, z_lo=self.z_lo,
                                   z_hi=self.z_hi, v_lo=self.v_lo, v_hi=self.v_hi, u_eps=self.u_eps,
                                   backend=self.backend, bounds="levelset", screening=self.screening,
                                   warm_start=self.warm_start, lazy=self.lazy, solver_options=self.solver_options)
        #: How much ``u_max^eps`` is tightened in the rows handed to the solver (grows when a returned plan's
        #: forward pass exceeds ``u_max^eps`` beyond round-off; the tolerance policy of :mod:`flnotes.solvers`).
        self.margin = 0.0
        self.history: list[MPCStep] = []
        self._plan: Optional[tuple[Array, Array]] = None
        self._active_prev: tuple = ()
        self._programs: "OrderedDict[tuple, list]" = OrderedDict()  # steps -> [program, solver]
        self._cvx = None
        self._candidate: Optional[tuple[Array, Array]] = None
        self.last_program = None
        self._R = np.zeros((self.N + 1, self.n_z))

    # ------------------------------------------------------------------ sizes
    @property
    def n_binaries_full(self) -> int:
        """``N_p * sum_k n_k``: the binaries of eq. (MPC_form_miqp) without any elimination (paper, footnote)."""
        return self.N * self.net.n_hidden

    @property
    def last(self) -> Optional[MPCStep]:
        """The last step's details."""
        return self.history[-1] if self.history else None

    def reset(self) -> None:
        """Forget the previous plan and the history (called by :func:`flnotes.simulate` at the start of a run)."""
        self.history = []
        self._plan = None
        self._active_prev = ()
        if self._hz is not None:
            self._hz._active_prev = ()

    def set_previous_plan(self, plan: Optional[tuple[Array, Array]]) -> None:
        """Set (or clear, with ``None``) the plan ``(z_pred, v_pred)`` that the next call shifts for its warm start."""
        if plan is None:
            self._plan = None
            return
        Z, V = np.asarray(plan[0], float), np.asarray(plan[1], float)
        if Z.shape != (self.N + 1, self.n_z) or V.shape != (self.N, self.m):
            raise ValueError(f"plan must be (z_pred, v_pred) of shapes ({self.N + 1}, {self.n_z}) and ({self.N}, {self.m}), "
                             f"got {Z.shape} and {V.shape}")
        self._plan = (Z, V)

    def clone(self, **changes) -> "MPC":
        """A new controller with the same settings except ``changes`` (no history, no previous plan)."""
        return MPC(**{**self._init_args, **changes})

    # ------------------------------------------------------------------ prediction model
    def _build_condensed(self) -> None:
        """``z(k) = Sx[k] z0 + Su[k] V`` with ``V = [v(0); ...; v(N_p-1)]``, and the QP Hessian in ``V``."""
        self.Sx, self.Su, self._Hqp = condense(self.Ad, self.Bd, self.N, self.Q, self.R, self.P)
        self._Wk = [self.Q] * self.N + [self.P]

    def predict(self, z: Array, v_pred: Array) -> Array:
        """Predicted states ``z(0..N_p)`` of eq. (MPC_form_miqp_c) for inputs ``v_pred`` of shape (N_p, m)."""
        return self.Sx @ np.asarray(z, float) + self.Su @ np.asarray(v_pred, float).reshape(-1)

    def cost(self, z_pred: Array, v_pred: Array, z_ref: Array) -> float:
        """Eq. (MPC_form_miqp_a) for a plan: ``sum_k ||z(k) - z_ref(k)||_Q^2 + ||v(k)||_R^2`` (+ terminal)."""
        E = np.asarray(z_pred) - np.asarray(z_ref)
        return float(sum(E[k] @ self._Wk[k] @ E[k] for k in range(self.N + 1))
                     + sum(v @ self.R @ v for v in np.asarray(v_pred)))

    def violated_steps(self, z_pred: Array, v_pred: Array, tol: float = BOUND_TOL) -> Array:
        """Predicted steps ``k`` with ``|Phi_NN(z(k), v(k))| > u_max^eps + tol`` (forward pass)."""
        u = self.net(np.hstack([z_pred[: self.N], v_pred]))
        return np.flatnonzero(np.any(np.abs(u) > self.u_eps + tol, axis=1))

    def plan_feasible(self, z_pred: Array, v_pred: Array, tol: float = FEAS_TOL) -> bool:
        """Does a plan satisfy eq. (MPC_form_miqp_b)-(d)?

        The network bound by the forward pass to :data:`flnotes.solvers.BOUND_TOL` (round-off only),
        the boxes of the predicted states and inputs to ``tol``.
        """
        if np.any(z_pred[1:] < self.z_lo - tol) or np.any(z_pred[1:] > self.z_hi + tol):
            return False
        if np.any(v_pred < self.v_lo - tol) or np.any(v_pred > self.v_hi + tol):
            return False
        return self.violated_steps(z_pred, v_pred).size == 0

    def shifted_plan(self, z: Array) -> Optional[tuple[Array, Array]]:
        """The previous plan shifted by one step, re-predicted from the measured ``z``.

        The new last input is chosen by :meth:`feasible_tail`, so that the
        shifted plan satisfies eq. (MPC_form_miqp_b)-(d) whenever the previous
        one did and the plant followed the prediction (the nominal case).
        Returns ``(z_pred, v_pred)``, or ``None`` when there is no previous plan.
        """
        if self._plan is None:
            return None
        V = self._plan[1]
        V = np.vstack([V[1:], V[-1:]])
        Z = self.predict(z, V)
        V[-1] = self.feasible_tail(Z[-2], V[-1])
        return self.predict(z, V), V

    def repair_plan(self, z: Array, v_guess: Array, first: bool = True) -> tuple[Array, Array]:
        """A plan built step by step from ``v_guess`` (N_p, m): each input replaced by :meth:`feasible_tail`.

        A cheap first incumbent when no previous plan exists (e.g. from the
        screening QP's inputs); check it with :meth:`plan_feasible`. With
        ``first=False`` the first input is kept as given.
        """
        V = np.array(v_guess, float).reshape(self.N, self.m)
        zk = np.asarray(z, float)
        for k in range(self.N):
            if first or k:
                V[k] = self.feasible_tail(zk, V[k])
            zk = self.Ad @ zk + self.Bd @ V[k]
        return self.predict(z, V), V

    def feasible_tail(self, z: Array, v_guess: Array, n_grid: int = 2001) -> Array:
        """An input ``v`` with ``|Phi_NN(z, v)| <= u_max^eps`` and ``A_d z + B_d v`` in the state box, closest to ``v_guess``.

        Searched on a grid of the ``v``-range (single-input systems) and checked
        with the network's forward pass; ``v_guess`` is returned unchanged when
        it is admissible or when no grid point is.
        """
        v_guess = np.asarray(v_guess, float)
        cand = v_guess[None]
        if self.m == 1:
            cand = np.r_[v_guess, np.linspace(self.v_lo[0], self.v_hi[0], n_grid)][:, None]
        u = self.net(np.hstack([np.repeat(np.asarray(z)[None], len(cand), 0), cand]))
        nxt = z @ self.Ad.T + cand @ self.Bd.T
        ok = (np.all(np.abs(u) <= self.u_eps + BOUND_TOL, axis=1) & np.all(nxt >= self.z_lo, axis=1)
              & np.all(nxt <= self.z_hi, axis=1))
        if not ok.any() or ok[0]:
            return v_guess
        i = np.flatnonzero(ok)
        return cand[i[np.argmin(np.abs(cand[i] - v_guess).sum(axis=1))]].copy()

    # ------------------------------------------------------------------ node bounds
    def box_bounds_horizon(self) -> NodeBounds:
        """The domain-box node bounds repeated for every step (``bounds="box"``), arrays of shape (N_p, n_k)."""
        b = self.box_bounds
        rep = lambda a: np.repeat(np.asarray(a)[None], self.N, axis=0)
        return NodeBounds([rep(L) for L in b.L], [rep(U) for U in b.U], rep(b.out_L), rep(b.out_U), method="box")

    def node_bounds(self, z: Array, steps: Optional[Sequence[int]] = None) -> tuple[NodeBounds, Array, Array]:
        """Per-step node bounds for the measured ``z`` under the ``bounds`` switch.

        Returns the bounds (arrays of shape (N_p, n_k)) and the state boxes
        ``z_lo, z_hi`` of shape (N_p + 1, n_z) used as variable bounds. With
        ``bounds="lp"`` only the rows in ``steps`` (default: all) are
        LP-tightened, the others keep FBBT's (see :meth:`tighten`). Raises
        :class:`flnotes.tightening.EmptyBoxError` when no admissible input
        sequence exists.
        """
        N = self.N
        if self.bounds == "box":
            zl, zh = self.z_lo[None].repeat(N + 1, 0), self.z_hi[None].repeat(N + 1, 0)
            zl[0] = zh[0] = z
            return self.box_bounds_horizon(), zl, zh
        X_lo, X_hi = horizon_boxes(self.Ad, self.Bd, z, self.z_lo, self.z_hi, self.v_lo, self.v_hi, N + 1)
        zl, zh = X_lo[:, : self.n_z], X_hi[:, : self.n_z]
        X_lo, X_hi = X_lo[:N], X_hi[:N]
        nb = fbbt(self.net, X_lo, X_hi)
        nb.boxes, nb.tightened = (X_lo, X_hi), set()  # type: ignore[attr-defined]
        if self.bounds == "lp":
            self.tighten(nb, range(N) if steps is None else steps)
        return nb, zl, zh

    def tighten(self, nb: NodeBounds, steps: Sequence[int]) -> None:
        """LP-tighten (``bounds="lp"``) the rows ``steps`` of per-step bounds from :meth:`node_bounds`, in place.

        The LP of :func:`flnotes.tightening.lp_bounds` is restricted to
        ``|Phi_NN| <= u_max^eps``, so the bounds hold for every point the
        program can select at that step.
        """
        if self.bounds != "lp":
            return
        todo = sorted(set(int(k) for k in steps) - nb.tightened)  # type: ignore[attr-defined]
        if not todo:
            return
        X_lo, X_hi = nb.boxes  # type: ignore[attr-defined]
        prior = NodeBounds([L[todo] for L in nb.L], [U[todo] for U in nb.U], nb.out_L[todo], nb.out_U[todo])
        t = lp_bounds(self.net, X_lo[todo], X_hi[todo], out_bounds=(-self.u_eps, self.u_eps), prior=prior)
        for layer in range(len(nb.L)):
            nb.L[layer][todo], nb.U[layer][todo] = t.L[layer], t.U[layer]
        nb.tightened.update(todo)  # type: ignore[attr-defined]

    # ------------------------------------------------------------------ the matrix form
    def _program(self, steps: tuple) -> list:
        """The cached ``[program, solver]`` pair for a set of encoded steps (built on first use)."""
        key = tuple(sorted(steps))
        if key in self._programs:
            self._programs.move_to_end(key)
            return self._programs[key]
        entry = [_Program(self, key, self.formulation == "condensed"), None]
        self._programs[key] = entry
        while len(self._programs) > 32:
            self._programs.popitem(last=False)
        return entry

    def problem(self, z: Array, z_ref, steps: Optional[Sequence[int]] = None):
        """The assembled MIQP (:class:`flnotes.solvers.MIQP`) for state ``z`` and reference ``z_ref``.

        ``steps`` selects the predicted steps whose network constraint is
        encoded (default: all of them, i.e. eq. (MPC_form_miqp) itself). Node
        bounds follow the ``bounds`` switch. For benchmarks and inspection;
        ``mpc.last_program`` is the matrix layout behind it.
        """
        z = self._check_z(z)
        R = self._check_ref(z_ref)
        nb, zl, zh = self.node_bounds(z)
        steps = tuple(range(self.N)) if steps is None else tuple(sorted(int(k) for k in steps))
        if self.formulation == "compact":
            prog = _CompactProgram(self, steps, z, R, nb, zl, zh)
        else:
            prog = self._program(steps)[0]
            prog.set_data(z, R, nb, zl, zh)
        self.last_program = prog
        return prog.miqp()

    # ------------------------------------------------------------------ screening QP
    def _screen(self, z: Array, R: Array) -> tuple[Optional[tuple[Array, Array]], float, int]:
        """The QP of eq. (MPC_form_miqp) without (b), condensed, by DAQP.

        Returns ``((z_pred, v_pred) or None, time, DAQP exit flag)``; flag -1 means infeasible.
        """
        import daqp

        t0 = time.perf_counter()
        N, nz, m = self.N, self.n_z, self.m
        Zfree = self.Sx @ z
        f = 2 * sum(self.Su[k].T @ self._Wk[k] @ (Zfree[k] - R[k]) for k in range(N + 1))
        A = self.Su[1:].reshape(N * nz, N * m)
        bu = np.r_[np.tile(self.v_hi, N), (self.z_hi - Zfree[1:]).reshape(-1)]
        bl = np.r_[np.tile(self.v_lo, N), (self.z_lo - Zfree[1:]).reshape(-1)]
        x, _, flag, _ = daqp.solve(self._Hqp, f, A, bu, bl, np.zeros(len(bu), dtype=np.int32))
        dt = time.perf_counter() - t0
        if flag != 1:
            return None, dt, int(flag)
        V = np.asarray(x).reshape(N, m)
        return (self.predict(z, V), V), dt, int(flag)

    # ------------------------------------------------------------------ checks
    def _check_z(self, z) -> Array:
        z = np.asarray(z, float)
        if z.shape != (self.n_z,):
            raise ValueError(f"z must be the measured state of shape ({self.n_z},), got shape {z.shape}")
        if not np.all(np.isfinite(z)):
            raise ValueError(f"z contains NaN or inf: {z}")
        self.system.check_domain(z, what="the measured state z")
        return project_to_box(z, self.z_lo, self.z_hi, "z")  # on the face of the box up to BOX_TOL: on it

    def _check_ref(self, z_ref) -> Array:
        R = np.asarray(z_ref, float)
        if R.shape == (self.n_z,):
            R = np.repeat(R[None], self.N + 1, axis=0)
        if R.shape != (self.N + 1, self.n_z):
            raise ValueError(f"z_ref must have shape (horizon + 1, n_z) = ({self.N + 1}, {self.n_z}) (the reference "
                             f"for k = 0..N_p) or ({self.n_z},) for a constant reference; got shape {R.shape}")
        if not np.all(np.isfinite(R)):
            raise ValueError("z_ref contains NaN or inf")
        return R

    # ------------------------------------------------------------------ solving
    def __call__(self, z: Array, z_ref) -> MPCStep:
        """Solve eq. (MPC_form_miqp) for the measured ``z`` and the reference ``z_ref`` over the horizon.

        Parameters
        ----------
        z
            Measured state ``z(0)``, shape (n_z,), inside the domain box
            (``ValueError`` otherwise).
        z_ref
            Reference for ``k = 0..N_p``: shape (N_p + 1, n_z), or (n_z,) for a
            constant one (``ValueError`` otherwise).

        Returns
        -------
        MPCStep
            ``v`` to apply (first predicted input), predicted trajectories,
            status and statistics; appended to :attr:`history`. An infeasible
            program is reported (``status="infeasible"``), not raised.
        """
        t_start = time.perf_counter()
        z = self._check_z(z)
        R = self._check_ref(z_ref)
        self._R = R
        if self.backend == "cvxpy-scip":
            step = self._solve_cvxpy(z, R)
        elif self._hz is not None:
            step = self._solve_levelset(z, R)
        else:
            step = self._solve_persistent(z, R)
        if step.v is not None and not step.fallback and not self.plan_feasible(step.z_pred, step.v_pred):
            # never a plan that breaks the program labelled as a solution
            base = {k: getattr(step, k) for k in ("nodes", "solve_time", "n_binaries", "encoded_steps", "rounds",
                                                   "backend", "warm_started")}
            base["message"] = f"{step.message}; the returned plan fails the forward-pass check"
            step = self._fallback(z, "error", base)
        step.wall_time = time.perf_counter() - t_start
        if step.v is not None:
            self._plan = (step.z_pred, step.v_pred)
        self.history.append(step)
        return step

    @property
    def u_solve(self) -> Array:
        """``u_max^eps`` as written in the programs handed to a solver: ``u_eps - margin``."""
        return self.u_eps - self.margin

    def _result(self, Z: Array, V: Array, status: str, **kw) -> MPCStep:
        u = self.net(np.hstack([Z[: self.N], V]))
        kw["input_admissible"] = bool(kw.get("input_admissible", True)
                                      and np.all(np.abs(u[0]) <= self.u_eps + BOUND_TOL))
        return MPCStep(v=V[0].copy(), z_pred=Z, v_pred=V, u_nn_pred=u, status=status, **kw)

    def _fallback(self, z: Array, status: str, base: dict) -> MPCStep:
        """No proven plan from this solve: apply :meth:`fallback_plan` (flagged ``fallback=True``)."""
        base = dict(base)
        Z, V, what, ok = self.fallback_plan(z)
        base["message"] = (base.get("message", "") + f"; applied {what}").lstrip("; ")
        base["objective"] = self.cost(Z, V, self._R)
        return self._result(Z, V, status=status, fallback=True, input_admissible=ok, **base)

    def fallback_plan(self, z: Array) -> tuple[Array, Array, str, bool]:
        """The plan applied when a solve gives no proven plan (infeasible, time limit, solver failure).

        Safety first, in this order:

        1. the previous plan shifted by one step (:meth:`shifted_plan`), if it satisfies
           eq. (MPC_form_miqp_b)-(d) from the measured ``z``;
        2. a plan repaired step by step (:meth:`repair_plan`) from the shifted plan, then from the
           screening QP's plan, then from zero inputs, if one satisfies them;
        3. otherwise only the first input is made safe: if any ``v`` with
           ``|Phi_NN(z, v)| <= u_max^eps`` exists at the measured ``z`` (:meth:`safe_input`, exact
           for a single input), the closest one to the plan's is applied and the rest of the plan
           repaired step by step;
        4. when none exists, the least-violation input (smallest ``max |Phi_NN(z, v)| - u_max^eps``).

        Returns ``(z_pred, v_pred, what, admissible)``: ``what`` says which rule gave the plan,
        ``admissible`` whether its first input satisfies the network bound at ``z``.
        """
        z = np.asarray(z, float)
        shifted = self.shifted_plan(z)
        if shifted is not None and self.plan_feasible(*shifted):
            return shifted[0], shifted[1], "the previous plan shifted by one step", True
        guesses = []
        if shifted is not None:
            guesses.append((shifted[1], "the shifted previous plan"))
        if self._candidate is not None:
            guesses.append((self._candidate[1], "the QP plan"))
        guesses.append((np.zeros((self.N, self.m)), "zero inputs"))
        for V, what in guesses:
            plan = self.repair_plan(z, V)
            if self.plan_feasible(*plan):
                return plan[0], plan[1], f"{what} repaired step by step", True
        V = np.array(guesses[0][0], float)
        v0, ok = self.safe_input(z, V[0])
        V[0] = v0
        Zr, Vr = self.repair_plan(z, V, first=False)
        if ok:
            return Zr, Vr, ("an admissible first input (|Phi_NN(z, v)| <= u_max^eps at the measured state); "
                            "the rest of the plan violates the program"), True
        return Zr, Vr, ("the least-violation input: no v satisfies |Phi_NN(z, v)| <= u_max^eps at the measured "
                        "state (input bound violated, flagged)"), False

    def safe_input(self, z: Array, v_guess: Array) -> tuple[Array, bool]:
        """An input ``v`` with ``|Phi_NN(z, v)| <= u_max^eps`` closest to ``v_guess``, or the least-violation one.

        For a single input the admissible set is computed exactly
        (:func:`flnotes.control.exact_1d_feasible_set`); inputs that also keep ``A_d z + B_d v`` in
        the state box are preferred. For two inputs the admissible set is computed exactly as
        convex polygons over the network's linear regions (:func:`flnotes.pieces.network_polygons`)
        and the nearest admissible point to ``v_guess`` is returned; for more inputs, and for the
        least-violation input when nothing is admissible, a seeded sample of the ``v`` box (4096
        points) is searched. Returns ``(v, admissible)``; when nothing is admissible, ``v``
        minimizes ``max(|Phi_NN(z, v)| - u_max^eps)`` (exactly for a single input: over the pieces'
        knots and zero crossings).
        """
        from .control import exact_1d_feasible_set, network_pieces_1d

        z, v_guess = np.asarray(z, float), np.asarray(v_guess, float).reshape(self.m)
        phi_ok = lambda v: bool(np.all(np.abs(self.net(np.r_[z, v])) <= self.u_eps + BOUND_TOL))
        if self.m == 1:
            lo, hi = float(self.v_lo[0]), float(self.v_hi[0])
            iv = exact_1d_feasible_set(self.net, z, lo, hi, float(self.u_eps[0]))
            # the next state in the box: Bd v in [z_lo - Ad z, z_hi - Ad z], an interval of v
            a, b, Bc = self.z_lo - self.Ad @ z, self.z_hi - self.Ad @ z, self.Bd[:, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                l1 = np.where(Bc > 0, a / Bc, np.where(Bc < 0, b / Bc, -np.inf))
                u1 = np.where(Bc > 0, b / Bc, np.where(Bc < 0, a / Bc, np.inf))
            s_lo, s_hi = float(np.max(l1)), float(np.min(u1))
            for keep_state in (True, False):
                cand = []
                for l, h in np.asarray(iv).reshape(-1, 2):
                    if keep_state:
                        l, h = max(l, s_lo), min(h, s_hi)
                    if l <= h:
                        cand += [np.clip(v_guess[0], l, h), 0.5 * (l + h)]
                cand = sorted(cand, key=lambda v: abs(v - v_guess[0]))
                for v in cand:
                    if phi_ok([v]):
                        return np.array([v]), True
            pw = network_pieces_1d(self.net, z, lo, hi)
            v0, y0, sl = pw.knots[:-1], pw.values[:-1], pw.slope
            with np.errstate(divide="ignore", invalid="ignore"):
                cross = np.where(sl != 0, v0 - y0 / sl, v0)
            cand = np.r_[pw.knots, np.clip(cross, pw.knots[:-1], pw.knots[1:])]
            v = float(cand[np.argmin(np.abs(self.net(np.c_[np.repeat(z[None], cand.size, 0), cand])[:, 0]))])
            return np.array([v]), False
        if self.m == 2:  # the admissible set exactly, as convex polygons over the network's linear regions
            from .pieces import _project, network_polygons, network_regions

            regions = network_regions(self.net, z, self.v_lo, self.v_hi)
            polys = network_polygons(self.net, z, self.v_lo, self.v_hi, self.u_eps, regions=regions)
            cand = [_project(P, v_guess) for P in polys]
            cand = [v for v in sorted(cand, key=lambda v: float(np.sum((v - v_guess) ** 2))) if phi_ok(v)]
            if cand:
                return np.asarray(cand[0], float).copy(), True
        rng = np.random.default_rng(0)
        cand = np.vstack([v_guess, rng.uniform(self.v_lo, self.v_hi, (4096, self.m))])
        excess = np.max(np.abs(self.net(np.hstack([np.repeat(z[None], len(cand), 0), cand]))) - self.u_eps, axis=1)
        ok = np.flatnonzero(excess <= BOUND_TOL)
        if ok.size:
            return cand[ok[np.argmin(np.abs(cand[ok] - v_guess).sum(axis=1))]].copy(), True
        return cand[int(np.argmin(excess))].copy(), False

    def _solve_levelset(self, z: Array, R: Array) -> MPCStep:
        """``bounds="levelset"``: :meth:`flnotes.levelset.HorizonMIQP.solve`, warm-started with the shifted plan."""
        shifted = self.shifted_plan(z) if self.warm_start else None
        ws = shifted[1] if shifted is not None and self.plan_feasible(*shifted) else None
        r = self._hz.solve(z, R, warm_start=ws, time_limit=self.time_limit, gap=self.gap)
        base = dict(solve_time=r.time, nodes=int(r.nodes), rounds=int(r.rounds), warm_started=ws is not None,
                    n_binaries=int(r.n_binaries), encoded_steps=tuple(r.encoded_steps),
                    backend="qp-screening" if r.screened else self.backend, message=r.message)
        if r.v_pred is None or r.status not in ("optimal", "time_limit"):
            self._candidate = None
            return self._fallback(z, r.status, base)  # see fallback_plan
        Z, V = self.predict(z, r.v_pred), np.asarray(r.v_pred, float).reshape(self.N, self.m)
        return self._result(Z, V, r.status, objective=float(r.objective), bound=float(r.bound), gap=float(r.gap),
                            screened=bool(r.screened), **base)

    def _solve_persistent(self, z: Array, R: Array) -> MPCStep:
        from .solvers import make_solver

        t0 = time.perf_counter()
        self._candidate = None
        stats = dict(solve_time=0.0, nodes=0, rounds=0)
        # screening: the QP without the network constraint (exact when it satisfies it)
        active: set = set(range(self.N))
        qp = None
        if self.screening or self.lazy:
            qp, dt, flag = self._screen(z, R)
            stats["solve_time"] += dt
            if qp is not None:
                Zq, Vq = qp
                viol = self.violated_steps(Zq, Vq)
                if viol.size == 0 and self.screening:
                    obj = self.cost(Zq, Vq, R)
                    self._active_prev = ()
                    return self._result(Zq, Vq, "optimal", objective=obj, bound=obj, gap=0.0, screened=True,
                                        backend="qp-screening", **stats)
                if self.lazy:
                    active = set(viol.tolist()) | {k - 1 for k in self._active_prev if k >= 1}
                    if not active:
                        active = {0}
            elif flag == -1:  # no admissible trajectory even without the network constraint
                return self._fallback(z, "infeasible", dict(backend="qp-screening", message="the QP without the "
                                      "network constraint is infeasible (the state box cannot be kept)", **stats))
            # any other failure of the screening QP: no shortcut, every step encoded
        try:
            nb, zl, zh = self.node_bounds(z, steps=sorted(active))
        except EmptyBoxError as exc:
            return self._fallback(z, "infeasible", dict(backend=self.backend, message=f"infeasible: {exc}", **stats))
        shifted = self.shifted_plan(z) if self.warm_start else None
        if shifted is not None and not self.plan_feasible(*shifted):
            shifted = None
        tightened = 0
        if shifted is None and self._plan is None and qp is not None:  # no previous plan: repair the QP's
            self._candidate = self.repair_plan(z, qp[1])
            if self.warm_start and self.plan_feasible(*self._candidate):
                shifted = self._candidate
        while True:
            try:
                self.tighten(nb, active)
            except EmptyBoxError as exc:  # no input of some step's box meets |Phi_NN| <= u_max^eps
                return self._fallback(z, "infeasible", dict(backend=self.backend, message=f"infeasible: {exc}", **stats))
            if self.formulation == "compact":  # rebuilt for this state: only the free binaries exist
                prog = _CompactProgram(self, sorted(active), z, R, nb, zl, zh)
                solver = make_solver(prog.miqp(), backend=self.backend, **self.solver_options)
            else:  # persistent: one model per set of encoded steps, numbers updated in place
                entry = self._program(tuple(sorted(active)))
                prog = entry[0]
                prog.set_data(z, R, nb, zl, zh)
                if entry[1] is None:
                    entry[1] = make_solver(prog.miqp(), backend=self.backend, **self.solver_options)
                else:
                    entry[1].update(c=prog.c, c0=prog.c0, rl=prog.rl, ru=prog.ru, lb=prog.lb, ub=prog.ub, A=prog.A)
                solver = entry[1]
            self.last_program = prog
            w0 = prog.vector(*shifted) if shifted is not None else None
            if w0 is not None and self.formulation == "compact":
                w0, dt = self._polish(prog, w0, z)
                stats["solve_time"] += dt
            remaining = None
            if self.time_limit is not None:
                remaining = self.time_limit - (time.perf_counter() - t0)
                if remaining <= 0:  # the budget went into bounds and set-up: no solve at all
                    return self._fallback(z, "time_limit", dict(
                        warm_started=False, n_binaries=prog.n_free, encoded_steps=prog.steps, backend=self.backend,
                        message="time limit reached before the solve", **stats))
            res = solver.solve(warm_start=w0, time_limit=remaining, gap=self.gap)
            stats["solve_time"] += float(res.time)
            stats["nodes"] += int(res.nodes)
            stats["rounds"] += 1
            status = _status(res.status)
            bound, gap = float(res.bound), float(res.gap)
            if status == "time_limit" and res.w is not None and not np.isfinite(bound):
                bound = self._relaxation_bound(prog)
                obj = float(res.objective)
                gap = abs(obj - bound) / max(1.0, abs(obj)) if np.isfinite(bound) else np.nan
            base = dict(bound=bound, gap=gap, warm_started=w0 is not None,
                        n_binaries=prog.n_free, encoded_steps=prog.steps, backend=str(res.backend),
                        message=str(res.message), **stats)
            if res.w is None or status not in ("optimal", "time_limit"):
                return self._fallback(z, status, base)
            Z, V = prog.plan(res.w, z)
            viol = self.violated_steps(Z, V)
            new = set(viol.tolist()) - active
            if status == "optimal" and set(viol.tolist()) & set(prog.steps) and tightened < 5:
                # an encoded step exceeds u_max^eps beyond round-off (the solver's tolerance let it through):
                # tighten the bound in the rows and solve again
                u = np.abs(self.net(np.hstack([Z[: self.N], V])[list(prog.steps)]))  # the encoded steps
                self.margin = next_margin(self.margin, float(np.max(u - self.u_eps)), float(np.max(self.u_eps)))
                tightened += 1
                continue
            if status == "optimal" and not new:
                self._active_prev = prog.steps
                return self._result(Z, V, "optimal", objective=self.cost(Z, V, R), **base)
            if status == "time_limit":
                if self.plan_feasible(Z, V):  # an incumbent feasible for the whole program
                    return self._result(Z, V, "time_limit", objective=self.cost(Z, V, R), **base)
                return self._fallback(z, "time_limit", base)
            if self.time_limit is not None and time.perf_counter() - t0 >= self.time_limit:
                return self._fallback(z, "time_limit", base)
            active |= new

    def _polish(self, prog, w0: Array, z: Array) -> tuple[Array, float]:
        """Improve a feasible warm start: the QP with its activation pattern fixed (a convex piece of the program)."""
        from .solvers import MIQP, make_solver

        t0 = time.perf_counter()
        ib = np.flatnonzero(prog.integrality == 1)
        if ib.size == 0:
            return w0, 0.0
        lb, ub = prog.lb.copy(), prog.ub.copy()
        lb[ib] = ub[ib] = np.round(w0[ib])
        # a solver failure comes back as a result with status "error" (Solver.solve): the warm start is kept
        res = make_solver(MIQP(prog.H, prog.c, prog.c0, prog.A, prog.rl, prog.ru, lb, ub, prog.integrality),
                          backend="daqp", **DAQP_OPTIONS).solve()
        if res.w is not None and _status(res.status) == "optimal":
            w = np.asarray(res.w)
            Z, V = prog.plan(w, z)
            if self.plan_feasible(Z, V) and float(res.objective) <= _objective(prog, w0):
                return w, time.perf_counter() - t0
        return w0, time.perf_counter() - t0

    def _relaxation_bound(self, prog) -> float:
        """Lower bound on eq. (MPC_form_miqp): the continuous relaxation of the program with the encoded steps."""
        from .solvers import MIQP, make_solver

        res = make_solver(MIQP(prog.H, prog.c, prog.c0, prog.A, prog.rl, prog.ru, prog.lb, prog.ub,
                               np.zeros_like(prog.integrality)), backend="daqp", **DAQP_OPTIONS).solve()
        return float(res.bound) if _status(res.status) == "optimal" and res.w is not None else np.nan

    # ------------------------------------------------------------------ the reference: cvxpy + SCIP, cold
    def _build_cvxpy(self, bounds: Optional[NodeBounds]):
        import cvxpy as cp

        N, nz, m = self.N, self.n_z, self.m
        Zv, Vv = cp.Variable((N + 1, nz), name="z"), cp.Variable((N, m), name="v")
        z0, zr = cp.Parameter(nz, name="z0"), cp.Parameter((N + 1, nz), name="z_ref")
        X = cp.vstack([Zv[:N].T, Vv.T])                                      # (n_in, N): [z(k); v(k)] per column
        enc = encode(self.net, X, bounds=bounds if bounds is not None else self.box_bounds_horizon())
        cons = [Zv[0] == z0,
                Zv[1:].T == self.Ad @ Zv[:N].T + self.Bd @ Vv.T,             # (MPC_form_miqp_c)
                Zv[1:] >= self.z_lo[None], Zv[1:] <= self.z_hi[None],        # (MPC_form_miqp_d)
                Vv >= self.v_lo[None], Vv <= self.v_hi[None],
                cp.abs(enc.output) <= self.u_solve[:, None]]                 # (MPC_form_miqp_b), eq. (Phi_NN_ep)
        cons += enc.constraints
        E = Zv - zr
        cost = sum(cp.quad_form(E[k], self._Wk[k]) for k in range(N + 1) if np.any(self._Wk[k])) \
            + sum(cp.quad_form(Vv[k], self.R) for k in range(N))
        prob = cp.Problem(cp.Minimize(cost), cons)
        return dict(prob=prob, z=Zv, v=Vv, z0=z0, zr=zr, n_bin=enc.n_binaries)

    def _solve_cvxpy(self, z: Array, R: Array) -> MPCStep:
        """The reference path; when SCIP's tolerance lets the plan exceed ``u_max^eps``, the bound is tightened
        (:attr:`margin`) and the program solved again, as on the other paths."""
        for _ in range(6):
            step = self._solve_cvxpy_once(z, R)
            if step.fallback or step.status != "optimal":
                return step
            u = np.abs(step.u_nn_pred)
            ex = float(np.max(u - self.u_eps))
            if ex <= BOUND_TOL:
                return step
            self.margin = next_margin(self.margin, ex, float(np.max(self.u_eps)))
            self._cvx = None  # the bound is a constant of the cvxpy problem: rebuild it
        return step

    def _solve_cvxpy_once(self, z: Array, R: Array) -> MPCStep:
        import cvxpy as cp

        self._candidate = None
        if self.bounds == "box":
            if self._cvx is None:
                self._cvx = self._build_cvxpy(None)
            cv = self._cvx
        else:  # per-step bounds are constants of this program: rebuild it (cold, by design of this path)
            try:
                nb, _, _ = self.node_bounds(z)
            except EmptyBoxError as exc:
                return self._fallback(z, "infeasible", dict(backend="cvxpy-scip", message=f"infeasible: {exc}"))
            cv = self._build_cvxpy(nb)
        cv["z0"].value, cv["zr"].value = z, R
        opts = {"limits/gap": self.gap}
        if self.time_limit is not None:
            opts["limits/time"] = float(self.time_limit)
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings():  # cvxpy warns on infinite bounds and on SCIP's "gaplimit" status
                warnings.simplefilter("ignore", RuntimeWarning)
                warnings.simplefilter("ignore", UserWarning)
                cv["prob"].solve(solver=cp.SCIP, scip_params=opts)
            st = cv["prob"].status
        except cp.error.SolverError as exc:
            st = f"error: {exc}"
        dt = time.perf_counter() - t0
        extra = getattr(cv["prob"].solver_stats, "extra_stats", None)
        extra = extra if isinstance(extra, dict) else {}
        model = extra.get("model")
        scip_status = str(extra.get("scip_status", st))
        nodes, bound, gap = 0, np.nan, np.nan
        if model is not None:
            nodes, bound, gap = int(model.getNNodes()), float(model.getDualbound()), float(model.getGap())
        base = dict(bound=bound, gap=gap, nodes=nodes, solve_time=dt, n_binaries=cv["n_bin"], rounds=1,
                    encoded_steps=tuple(range(self.N)), backend="cvxpy-scip", message=f"SCIP status {scip_status}")
        if scip_status in ("optimal", "gaplimit"):
            status = "optimal"
        elif scip_status == "timelimit":
            status = "time_limit"
        elif "infeasible" in scip_status or "infeasible" in st:
            status = "infeasible"
        else:
            status = scip_status
        if status in ("optimal", "time_limit") and cv["v"].value is not None:
            Z, V = np.asarray(cv["z"].value), np.asarray(cv["v"].value)
            return self._result(Z, V, status, objective=self.cost(Z, V, R), **base)
        return self._fallback(z, status, base)

    # ------------------------------------------------------------------ the Controller protocol
    def step(self, z: Array, t: float, reference: Optional[Callable[[Array], Array]] = None) -> StepResult:
        """One sampling instant for :func:`flnotes.simulate`: ``z_ref(k) = reference(t + k t_s)``, k = 0..N_p.

        A step without a proven plan applies :meth:`fallback_plan` (``fallback=True``;
        ``info["input_admissible"]`` is False when even the first input had to violate
        ``|Phi_NN(z, v)| <= u_max^eps`` because no admissible one exists at ``z``).
        """
        if reference is None:
            R = np.zeros((self.N + 1, self.n_z))
        else:
            R = np.asarray(reference(t + self.ts * np.arange(self.N + 1)), float)
        s = self(z, R)
        if s.v is None:  # not reached: the fallback always gives an input (kept as the documented outcome)
            from .errors import SolverFailure

            raise SolverFailure(f"MPC at t = {t:.3f} s: status {s.status!r} and no input ({s.message})",
                                status=s.status)
        info = s.as_info()
        info["z_ref"] = R
        return StepResult(v=s.v, status=s.status, solve_time=s.wall_time, fallback=s.fallback, info=info)

    # ------------------------------------------------------------------ statistics
    def stats(self) -> dict:
        """Per-step statistics of :attr:`history` as arrays (one entry per call)."""
        h = self.history
        return dict(status=[s.status for s in h],
                    wall_ms=np.array([s.wall_time for s in h]) * 1e3,
                    solve_ms=np.array([s.solve_time for s in h]) * 1e3,
                    gap=np.array([s.gap for s in h]), nodes=np.array([s.nodes for s in h]),
                    n_binaries=np.array([s.n_binaries for s in h]),
                    encoded=np.array([len(s.encoded_steps) for s in h]),
                    rounds=np.array([s.rounds for s in h]),
                    screened=np.array([s.screened for s in h], bool), fallback=np.array([s.fallback for s in h], bool),
                    warm_started=np.array([s.warm_started for s in h], bool))

    def summary(self) -> dict:
        """Min/max/mean time per step (ms), time-limit hits, fallbacks, screened steps, binaries."""
        if not self.history:
            return dict(steps=0)
        s = self.stats()
        mi = ~s["screened"]
        return dict(
            steps=len(self.history), ms_min=float(s["wall_ms"].min()), ms_max=float(s["wall_ms"].max()),
            ms_mean=float(s["wall_ms"].mean()), ms_median=float(np.median(s["wall_ms"])),
            time_limit_hits=int(sum(st == "time_limit" for st in s["status"])),
            fallbacks=int(s["fallback"].sum()), screened=int(s["screened"].sum()), miqp_steps=int(mi.sum()),
            nodes_mean=float(s["nodes"][mi].mean()) if mi.any() else 0.0,
            binaries_full=self.n_binaries_full,
            binaries_mean=float(s["n_binaries"][mi].mean()) if mi.any() else 0.0,
            binaries_max=int(s["n_binaries"][mi].max()) if mi.any() else 0,
            encoded_mean=float(s["encoded"][mi].mean()) if mi.any() else 0.0,
            non_optimal=int(sum(st != "optimal" for st in s["status"])),
        )

    def __repr__(self) -> str:
        form = f"lazy={self.lazy}, " + ("" if self.bounds == "levelset" else f"formulation={self.formulation!r}, ")
        return (f"MPC({self.system.name}, N_p={self.N}, ts={self.ts}, backend={self.backend!r}, bounds={self.bounds!r}, "
                f"warm_start={self.warm_start}, screening={self.screening}, {form}time_limit={self.time_limit})")


def _objective(prog, w: Array) -> float:
    """``0.5 w'Hw + c'w + c0`` of a program's matrix form."""
    w = np.asarray(w, float)
    return float(0.5 * w @ (prog.H @ w) + prog.c @ w + prog.c0)


def _status(s) -> str:
    s = str(s).lower()
    if s in ("optimal", "opt", "solved"):
        return "optimal"
    if "time" in s or "limit" in s:
        return "time_limit"
    if "infeas" in s:
        return "infeasible"
    return s
