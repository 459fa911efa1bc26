"""CPLEX back-end (optional, commercial): used only when the cplex package is installed.

Part of :mod:`flnotes.solvers` (see its docstring for what "optimal" means and the tolerance policy).
"""
from __future__ import annotations

import numpy as np

from .base import Solver, _require
from .problem import _INF, MIQPResult, _result


class CplexSolver(Solver):
    """IBM CPLEX through its Python API (the Community Edition limits the program size)."""

    name = "cplex"
    OPTIONS = ("threads",)

    def _build(self) -> None:
        cplex = _require("cplex")
        p = self.problem
        c = cplex.Cplex()
        for stream in (c.set_log_stream, c.set_results_stream, c.set_warning_stream, c.set_error_stream):
            stream(None)
        c.parameters.threads.set(int(self.options.get("threads", 1)))
        inf = cplex.infinity
        types = "".join("I" if i else "C" for i in p.integrality) if p.is_mip else ""
        c.variables.add(obj=p.c.tolist(), lb=np.clip(p.lb, -inf, inf).tolist(), ub=np.clip(p.ub, -inf, inf).tolist(),
                        types=types)
        senses, rhs, rng = [], [], []
        for r in range(p.m):
            lo, hi = p.rl[r], p.ru[r]
            if lo == hi:
                senses.append("E")
                rhs.append(lo)
                rng.append(0.0)
            elif lo > -_INF and hi < _INF:
                senses.append("R")
                rhs.append(lo)
                rng.append(hi - lo)
            elif hi < _INF:
                senses.append("L")
                rhs.append(hi)
                rng.append(0.0)
            else:
                senses.append("G")
                rhs.append(lo if lo > -_INF else -inf)
                rng.append(0.0)
        A = p.A
        rows = [cplex.SparsePair(ind=A.indices[A.indptr[r]:A.indptr[r + 1]].tolist(),
                                 val=A.data[A.indptr[r]:A.indptr[r + 1]].tolist()) for r in range(p.m)]
        if p.m:
            c.linear_constraints.add(lin_expr=rows, senses="".join(senses), rhs=rhs, range_values=rng)
        if p.H is not None:
            Hc = p.H.tocsc()
            c.objective.set_quadratic([cplex.SparsePair(ind=Hc.indices[Hc.indptr[j]:Hc.indptr[j + 1]].tolist(),
                                                        val=Hc.data[Hc.indptr[j]:Hc.indptr[j + 1]].tolist())
                                       for j in range(p.n)])
        self._c, self._cplex = c, cplex

    def _push(self, changed: dict) -> None:
        p, c, inf = self.problem, self._c, self._cplex.infinity
        if "c" in changed:
            c.objective.set_linear(list(zip(range(p.n), p.c.tolist())))
        if "bounds" in changed:
            c.variables.set_lower_bounds(list(zip(range(p.n), np.clip(p.lb, -inf, inf).tolist())))
            c.variables.set_upper_bounds(list(zip(range(p.n), np.clip(p.ub, -inf, inf).tolist())))
        if "rows" in changed:
            if "row_kind" in changed:
                raise ValueError("the 'cplex' back-end cannot turn an equality row into an inequality in place")
            for r in range(p.m):
                lo, hi = p.rl[r], p.ru[r]
                if lo == hi:
                    c.linear_constraints.set_rhs(r, lo)
                elif lo > -_INF and hi < _INF:
                    c.linear_constraints.set_rhs(r, lo)
                    c.linear_constraints.set_range_values(r, hi - lo)
                elif hi < _INF:
                    c.linear_constraints.set_rhs(r, hi)
                else:
                    c.linear_constraints.set_rhs(r, max(lo, -inf))
        if "A" in changed:
            c.linear_constraints.set_coefficients([(int(self._Arow[k]), int(self._Acol[k]), float(p.A.data[k]))
                                                   for k in changed["A"]])

    def _solve(self, ws, time_limit, gap, t0) -> MIQPResult:
        c, p = self._c, self.problem
        c.parameters.timelimit.set(float(time_limit) if time_limit else 1e75)
        if p.is_mip:
            c.parameters.mip.tolerances.mipgap.set(gap)
            c.parameters.mip.tolerances.absmipgap.set(gap)
            c.MIP_starts.delete()
            if ws is not None:
                c.MIP_starts.add(self._cplex.SparsePair(ind=list(range(p.n)), val=ws.tolist()),
                                 c.MIP_starts.effort_level.auto)
        c.solve()
        sol = c.solution
        st = sol.get_status_string()
        try:
            w = np.array(sol.get_values())
        except Exception:
            w = None
        nodes = int(sol.progress.get_num_nodes_processed()) if p.is_mip else 0
        try:
            bound = sol.MIP.get_best_objective() + p.c0 if p.is_mip else np.nan
        except Exception:
            bound = -np.inf
        s = st.lower()
        if "optimal" in s and "infeasible" not in s:
            return _result(p, "optimal", w, bound, nodes, t0, self.name, st)
        if "infeasible" in s:
            return _result(p, "infeasible", None, np.inf, nodes, t0, self.name, st)
        if "time limit" in s:
            return _result(p, "time_limit", w, bound, nodes, t0, self.name, st)
        return _result(p, "error", w, -np.inf, nodes, t0, self.name, st)
