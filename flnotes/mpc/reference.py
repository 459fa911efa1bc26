"""The reference solve of eq. (MPC_form_miqp): the program as written in the paper, solved cold by SCIP.

The states ``z(0..N_p)`` are variables tied by the dynamics rows, the network is encoded at every
predicted step with :func:`flnotes.encode` (the big-M encoding of eq. MIP_general, one copy per step),
and SCIP solves it through cvxpy from scratch at every call. Slow on purpose: it is the yardstick the
levers of :class:`flnotes.MPCOptions` are checked against (``backend="cvxpy-scip"``).
"""
from __future__ import annotations

import time
import warnings
from typing import Optional

import numpy as np

from ..bounds import NodeBounds
from ..encoding import encode
from ..result import StepResult
from ..solvers import BOX_TOL
from ..solvers.scip import _quiet_c_output
from ..tightening import EmptyBoxError
from .levers import node_bounds, repeat_bounds
from .options import MPCOptions
from .prediction import Prediction
from .region import region_exact

Array = np.ndarray

#: SCIP's feasibility tolerance here (``numerics/feastol``): the engine's (:class:`flnotes.solvers.ScipSolver`, 1e-9),
#: not SCIP's default 1e-6, under which the reference labelled optimal plans up to 6.3e-5 (relative) above a cheaper
#: plan that passes the forward-pass check (the big-M rows let a binary sit 1e-6 off its value).
SCIP_FEASTOL = 1e-9

#: How far (relative to ``max(1, |bound|)``) a plan of SCIP may lie outside the ``v``-box and still be moved onto its
#: face: SCIP keeps a bound to its tolerance on the transformed (presolved, aggregated) program, which for ``v`` tied
#: to the states by the dynamics rows was measured up to 1.9e-5 outside ``v_hi`` at a feasibility tolerance of 1e-6.
#: The moved plan is what the controller checks (forward pass) and whose cost it reports.
V_BOX_SNAP = 1e-4


class ReferenceProgram:
    """Eq. (MPC_form_miqp) written with cvxpy and :func:`flnotes.encode`, solved cold by SCIP."""

    def __init__(self, pred: Prediction, opts: MPCOptions, box: NodeBounds):
        self.pred, self.opts, self.box = pred, opts, box
        self._box_problem = None

    def _build(self, nb: NodeBounds, u_in: Array) -> dict:
        import cvxpy as cp

        p = self.pred
        N, nz, m = p.N, p.nz, p.m
        Zv, Vv = cp.Variable((N + 1, nz), name="z"), cp.Variable((N, m), name="v")
        z0, zr = cp.Parameter(nz, name="z0"), cp.Parameter((N + 1, nz), name="z_ref")
        X = cp.vstack([Zv[:N].T, Vv.T])                                      # (n_in, N): [z(k); v(k)] per column
        enc = encode(p.net, X, bounds=nb)
        cons = [Zv[0] == z0,
                Zv[1:].T == p.Ad @ Zv[:N].T + p.Bd @ Vv.T,                   # (MPC_form_miqp_c)
                Zv[1:] >= p.z_lo[None], Zv[1:] <= p.z_hi[None],              # (MPC_form_miqp_d)
                Vv >= p.v_lo[None], Vv <= p.v_hi[None],
                cp.abs(enc.output) <= u_in[:, None]]                         # (MPC_form_miqp_b), eq. (Phi_NN_ep)
        if p.F is not None:
            cons.append(p.F @ Zv[N] <= p.g)                                  # terminal set
        cons += enc.constraints
        E = Zv - zr
        cost = sum(cp.quad_form(E[k], p.Wk[k]) for k in range(N + 1) if np.any(p.Wk[k])) \
            + sum(cp.quad_form(Vv[k], p.R) for k in range(N))
        return dict(prob=cp.Problem(cp.Minimize(cost), cons), z=Zv, v=Vv, z0=z0, zr=zr, n_bin=enc.n_binaries, u=u_in,
                    ybar=enc.ybar, yund=enc.yund)

    def solve(self, z0: Array, z_ref: Array, u_in: Array, time_limit: Optional[float] = None,
              gap: float = 1e-6) -> StepResult:
        """One cold solve; ``u_in`` is the output bound written in the rows. ``v`` is ``None`` without a plan."""
        import cvxpy as cp

        from ..solvers.cvxpy_bridge import ScipConic  # cvxpy on demand: importing flnotes does not load it

        p = self.pred
        t0 = time.perf_counter()
        if self.opts.bounds == "box":  # bounds do not depend on the state: the problem is kept
            if self._box_problem is None or not np.array_equal(self._box_problem["u"], u_in):
                self._box_problem = self._build(repeat_bounds(self.box, p.N), u_in)
            cv = self._box_problem
        else:  # per-step bounds are constants of this program: rebuilt (cold, by design of this path)
            try:
                lo, hi = p.boxes(z0)
            except EmptyBoxError as exc:
                return StepResult(None, "infeasible", backend="cvxpy-scip", message=f"infeasible: {exc}",
                                  solve_time=time.perf_counter() - t0)
            nb = node_bounds(p, self.opts, self.box, lo, hi)
            if nb is None:
                return StepResult(None, "infeasible", backend="cvxpy-scip", solve_time=time.perf_counter() - t0,
                                  message="infeasible: a step's LP bounds exclude |Phi_NN| <= u_max^eps")
            cv = self._build(nb, u_in)
        cv["z0"].value, cv["zr"].value = z0, z_ref
        opts = {"limits/gap": gap, "numerics/feastol": SCIP_FEASTOL}
        if time_limit is not None:
            opts["limits/time"] = float(time_limit)
        scip = ScipConic()  # cvxpy's SCIP interface, the lock released while SCIP runs, the cost's cones as norms
        try:
            # cvxpy warns on infinite bounds and on SCIP's "gaplimit" status; SoPlex prints its tolerance notices to the
            # C streams (filtered out as in the engine's SCIP back-end)
            with warnings.catch_warnings(), _quiet_c_output():
                warnings.simplefilter("ignore", RuntimeWarning)
                warnings.simplefilter("ignore", UserWarning)
                cv["prob"].solve(solver=scip, scip_params=opts)
            st, failed = cv["prob"].status, False
        except cp.error.SolverError as exc:  # e.g. SCIP stopped at the time limit without a point
            st, failed = f"error: {exc}", True
        # cvxpy keeps the last solve's statistics when it raises: those are an earlier solve's (a kept problem)
        extra = None if failed else getattr(cv["prob"].solver_stats, "extra_stats", None)
        extra = extra if isinstance(extra, dict) else {}
        model = extra.get("model")
        scip_status = str(extra.get("scip_status", scip.status or st))
        nodes, bound = 0, np.nan
        if model is not None:
            nodes, bound = int(model.getNNodes()), float(model.getDualbound())
        if scip_status in ("optimal", "gaplimit"):
            status = "optimal"
        elif scip_status == "timelimit":
            status = "time_limit"
        elif "infeasible" in scip_status or "infeasible" in st:
            status = "infeasible"
        else:
            status = "error"
        res = StepResult(None, status, bound=bound, nodes=nodes, n_binaries=int(cv["n_bin"]), rounds=1,
                         encoded_steps=tuple(range(p.N)), backend="cvxpy-scip", message=f"SCIP status {scip_status}")
        if status in ("optimal", "time_limit") and cv["v"].value is not None:
            V = np.asarray(cv["v"].value, float).reshape(p.N, p.m)
            # SCIP keeps variable bounds to its tolerance on its transformed program: a plan on the v-box face up to
            # V_BOX_SNAP outside it is moved onto it (the checks that follow, the forward pass among them, see the
            # plan the controller applies, and its cost is that plan's)
            out = np.maximum(V - p.v_hi, p.v_lo - V)
            tol = V_BOX_SNAP * np.maximum(1.0, np.maximum(np.abs(p.v_lo), np.abs(p.v_hi)))
            if np.all(out <= tol):
                if np.any(out > BOX_TOL):
                    res.message += f"; moved onto the v-box face (SCIP's plan was {float(out.max()):.1e} outside)"
                V = np.clip(V, p.v_lo, p.v_hi)
            f, c0 = p.linear(z0, z_ref)
            res.objective = p.cost(V, f, c0)
            if status == "optimal" and p.violated(z0, V).size:
                # SCIP's plan over u_max^eps by its tolerance, made exact on a linear region before the controller
                # tightens the rows (which would remove a flat piece or a ridge of the network at u_max^eps whole)
                hidden = [(yb.value, yu.value) for yb, yu in zip(cv["ybar"], cv["yund"])]
                scip_pattern = (None if any(a is None or b is None for a, b in hidden) else
                                [np.asarray(a, float).T > np.asarray(b, float).T for a, b in hidden])
                W = region_exact(p, z0, f, c0, V, scip_pattern, res.objective, gap)
                if W is not None:
                    V = W.reshape(p.N, p.m)
                    res.message += "; made exact on its linear region (QP)"
            res.v, res.v_pred, res.z_pred = V[0].copy(), V, p.predict(z0, V)
            res.objective = p.cost(V, f, c0)
            b = min(bound, res.objective) if np.isfinite(bound) else np.nan
            res.bound, res.gap = b, (abs(res.objective - b) / max(1.0, abs(res.objective)) if np.isfinite(b) else np.nan)
        res.solve_time = time.perf_counter() - t0
        return res
