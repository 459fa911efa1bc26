"""Gurobi back-end (optional, commercial): used only when gurobipy is installed.

Part of :mod:`flnotes.solvers` (see its docstring for what "optimal" means and the tolerance policy).
"""
from __future__ import annotations

import numpy as np

from .base import Solver, _require
from .problem import _INF, Array, MIQPResult, _result


# ---------------------------------------------------------------------------
# Commercial back-ends (only if installed)
# ---------------------------------------------------------------------------
class GurobiSolver(Solver):
    """Gurobi through gurobipy's matrix API (needs a license for larger programs)."""

    name = "gurobi"

    def _build(self) -> None:
        gp = _require("gurobi")
        p = self.problem
        env = gp.Env(empty=True)
        env.setParam("OutputFlag", 0)
        env.start()
        m = gp.Model(env=env)
        m.Params.Threads = int(self.options.get("threads", 1))
        for k, v in self.options.get("params", {}).items():
            m.setParam(k, v)
        vt = np.where(p.integrality == 1, gp.GRB.INTEGER, gp.GRB.CONTINUOUS)
        x = m.addMVar(p.n, lb=_ginf(p.lb, gp), ub=_ginf(p.ub, gp), vtype=vt)
        self._rows = m.addMConstr(p.A, x, gp.GRB.LESS_EQUAL, _ginf(p.ru, gp)) if p.m else None
        self._rows_lo = m.addMConstr(p.A, x, gp.GRB.GREATER_EQUAL, _ginf(p.rl, gp)) if p.m else None
        self._m, self._xv, self._gp = m, x, gp
        self._set_obj()
        m.update()

    def _set_obj(self) -> None:
        p, gp = self.problem, self._gp
        if p.H is not None:
            self._m.setMObjective(0.5 * p.H, p.c, p.c0, sense=gp.GRB.MINIMIZE)
        else:
            self._m.setMObjective(None, p.c, p.c0, sense=gp.GRB.MINIMIZE)

    def _push(self, changed: dict) -> None:
        p, gp = self.problem, self._gp
        self._set_obj()
        if "bounds" in changed:
            self._xv.LB, self._xv.UB = _ginf(p.lb, gp), _ginf(p.ub, gp)
        if "rows" in changed and p.m:
            self._rows.RHS, self._rows_lo.RHS = _ginf(p.ru, gp), _ginf(p.rl, gp)
        if "A" in changed:
            xs = self._xv.tolist()
            cu, cl = self._rows.tolist(), self._rows_lo.tolist()
            for k in changed["A"]:
                r, j, v = int(self._Arow[k]), int(self._Acol[k]), float(p.A.data[k])
                self._m.chgCoeff(cu[r], xs[j], v)
                self._m.chgCoeff(cl[r], xs[j], v)
        self._m.update()

    def _solve(self, ws, time_limit, gap, t0) -> MIQPResult:
        m, p, gp = self._m, self.problem, self._gp
        self._set_obj()
        m.Params.TimeLimit = float(time_limit) if time_limit else gp.GRB.INFINITY
        m.Params.MIPGap, m.Params.MIPGapAbs = gap, gap
        if ws is not None:
            self._xv.Start = ws
        m.optimize()
        st = m.Status
        w = np.array(self._xv.X) if m.SolCount > 0 else None
        nodes = int(m.NodeCount) if p.is_mip else 0
        bound = float(m.ObjBound) if p.is_mip and m.SolCount else np.nan
        if st == gp.GRB.OPTIMAL:
            return _result(p, "optimal", w, bound, nodes, t0, self.name, "OPTIMAL")
        if st in (gp.GRB.INFEASIBLE, gp.GRB.INF_OR_UNBD):
            return _result(p, "infeasible", None, np.inf, nodes, t0, self.name, f"status {st}")
        if st == gp.GRB.TIME_LIMIT:
            return _result(p, "time_limit", w, bound if np.isfinite(bound) else -np.inf, nodes, t0, self.name, "TIME_LIMIT")
        return _result(p, "error", w, -np.inf, nodes, t0, self.name, f"status {st}")


def _ginf(a: Array, gp) -> Array:
    out = np.asarray(a, float).copy()
    out[out >= _INF] = gp.GRB.INFINITY
    out[out <= -_INF] = -gp.GRB.INFINITY
    return out
