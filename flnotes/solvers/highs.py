"""HiGHS back-end (highspy): MILPs and continuous QPs, every status mapped, optima cross-checked.

Part of :mod:`flnotes.solvers` (see its docstring for what "optimal" means and the tolerance policy).
"""
from __future__ import annotations

import numbers
import time

import numpy as np
import scipy.sparse as sp

from .base import Solver, _confirm, _require
from .problem import FEAS_TOL, MIQPResult, _result
from .scip import _hinf


# ---------------------------------------------------------------------------
# HiGHS
# ---------------------------------------------------------------------------
#: Iterations of HiGHS's QP solver per variable and row of a continuous QP before it is stopped as cycling (the
#: MPC relaxations it solves need about 0.2 per variable and row; the cycling one ran 74 per second of CPU).
QP_ITERATIONS_PER_SIZE = 5

#: HiGHS's QP regularization for the second solve of a QP stopped at its iteration limit (HiGHS's default: 1e-7);
#: with it the QP that had cycled was solved in 229 iterations.
QP_RETRY_REGULARIZATION = 1e-9


def qp_iteration_limit(n: int, m: int) -> int:
    """The iteration limit of HiGHS's QP solver on a continuous QP with ``n`` variables and ``m`` rows."""
    return 1000 + QP_ITERATIONS_PER_SIZE * (int(n) + int(m))


#: HiGHS options and values :meth:`HighsSolver.check_options` has set on a model without error.
_CHECKED_PARAMS: set = set()

#: HiGHS options refused in ``params``: those :class:`HighsSolver` sets itself, and those that stop the search early
#: or change the program (with why).
RESERVED_PARAMS = {"time_limit": "set by solve(time_limit=...)", "mip_rel_gap": "set by solve(gap=...)",
                   "mip_abs_gap": "set by solve(gap=...)", "mip_max_nodes": "set by solve(node_limit=...)",
                   "threads": "set by the option threads (1: HiGHS keeps one thread pool per process)",
                   "output_flag": "set by the back-end (it is silent)",
                   "log_to_console": "set by the back-end (it is silent)", "log_file": "set by the back-end",
                   "objective_bound": "a bound on the objective makes the program another one",
                   "objective_target": "it stops the search at a target, not at the optimum",
                   "mip_max_leaves": "it stops the search (give node_limit= to solve())",
                   "mip_max_improving_sols": "it stops the search (give node_limit= to solve())",
                   "mip_max_stall_nodes": "it stops the search (give node_limit= to solve())",
                   "simplex_iteration_limit": "it stops the search (give time_limit= or node_limit= to solve())"}


def _finite(x: numbers.Real) -> bool:
    """``x`` is finite as a float (an integer too large for one is not)."""
    try:
        return bool(np.isfinite(float(x)))
    except OverflowError:
        return False


class HighsSolver(Solver):
    """HiGHS (Huangfu & Hall 2018) through highspy, one persistent ``Highs`` object.

    MILPs go to its branch and cut, continuous QPs to its active-set QP
    solver. A warm start is passed with ``setSolution`` (an incumbent).

    HiGHS's QP solver can cycle: on a relaxation of an MPC program (308
    variables, 678 rows) it ran 72,920 iterations in 3 s without proving the
    optimum it already held, where 229 iterations solve it with a smaller
    regularization. So a continuous QP runs with an iteration limit
    (:func:`qp_iteration_limit`); at the limit it is solved once more with the
    regularization :data:`QP_RETRY_REGULARIZATION`, and a second stop is an
    ``"error"`` that says so, never an unending solve. ``params`` that set
    ``qp_iteration_limit`` or ``qp_regularization_value`` replace this.

    Warnings
    --------
    On the small big-M programs of this package HiGHS returns sub-optimal
    points with status "optimal" (proved at the root) in every setting
    measured. On 600 MSD Lcost programs (400 states all over the box, 200
    along closed loops, every one solved without screening) against the exact
    1-D method: presolve off gave 4, 3, 3, 3 wrong optima with feasibility
    tolerances 1e-6, 1e-7, 1e-8, 1e-9 (up to 46 % above the optimum; 1e-9
    also declared 4 feasible programs infeasible); presolve on gave 1 wrong
    optimum (29 % above) with every tolerance, and was the fastest at 1e-8.
    The wrong states of the two settings were different. Hence the settings
    (presolve on, tolerances 1e-8) and, for a MILP, a cross-check: an optimum
    is accepted only when a second solve with presolve off agrees within the
    gap; otherwise SCIP decides, warm-started with the better point
    (``cross_check=False`` skips it). An "infeasible" MILP is confirmed by
    SCIP. SCIP remains the ``"auto"`` choice for MILPs; ``make bench``
    checks every back-end against the exact method on diverse states.
    """

    name = "highs"
    supports_miqp = False
    supports_node_limit = True
    OPTIONS = ("threads", "params", "cross_check")

    @classmethod
    def _check_values(cls, options: dict) -> None:
        if not isinstance(options.get("cross_check", True), (bool, np.bool_)):
            raise ValueError(f"the HiGHS option cross_check must be True or False, got {options['cross_check']!r}")
        if options.get("threads", 1) != 1:
            raise ValueError(f"the HiGHS option threads must be 1, got {options['threads']!r}: HiGHS keeps one thread "
                             f"pool per process, and a model with another count then fails ('Not Set')")
        params = options.get("params", {})
        for k, v in params.items():
            if k in RESERVED_PARAMS:
                raise ValueError(f"the HiGHS option {k!r} is refused in params: {RESERVED_PARAMS[k]}")
            if isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) and not _finite(v):
                raise ValueError(f"the HiGHS option {k!r} (option params) must be a finite number, got {v!r}")
        new = [(k, v) for k, v in params.items() if (k, repr(v)) not in _CHECKED_PARAMS]
        if new:  # HiGHS answers a refused option with a status, not an exception: each is tried once on a model
            hp = _require("highs")
            h = hp.Highs()
            h.setOptionValue("output_flag", False)
            for k, v in new:
                if not isinstance(k, str) or h.setOptionValue(k, v.item() if isinstance(v, np.generic) else v) \
                        != hp.HighsStatus.kOk:
                    raise ValueError(f"the HiGHS option {k!r} = {v!r} (option params) is refused by HiGHS (an "
                                     f"unknown option or a value of the wrong type or range)")
                _CHECKED_PARAMS.add((k, repr(v)))

    def _build(self) -> None:
        hp = _require("highs")
        self._hp = hp
        p = self.problem
        h = hp.Highs()
        h.setOptionValue("output_flag", False)
        h.setOptionValue("threads", int(self.options.get("threads", 1)))
        if p.is_mip:
            # Measured on 600 MSD Lcost programs all over the box against the exact 1-D method (see the class
            # docstring): presolve on with tolerances 1e-8 gave the fewest wrong optima (1, presolve off: 3-4)
            # and the shortest times; the cross-check in _solve catches the rest.
            h.setOptionValue("presolve", "on")
            h.setOptionValue("mip_feasibility_tolerance", 1e-8)
            h.setOptionValue("primal_feasibility_tolerance", 1e-8)
        self._qp = p.H is not None and not p.is_mip
        params = self.options.get("params", {})
        self._qp_retry = self._qp and not {"qp_iteration_limit", "qp_regularization_value"} & set(params)
        if self._qp and "qp_iteration_limit" not in params:
            h.setOptionValue("qp_iteration_limit", qp_iteration_limit(p.n, p.m))
        for k, v in params.items():
            h.setOptionValue(k, v.item() if isinstance(v, np.generic) else v)
        lp = hp.HighsLp()
        lp.num_col_, lp.num_row_ = p.n, p.m
        lp.col_cost_ = p.c
        lp.col_lower_, lp.col_upper_ = _hinf(p.lb), _hinf(p.ub)
        lp.row_lower_, lp.row_upper_ = _hinf(p.rl), _hinf(p.ru)
        Ac = p.A.tocsc()
        Ac.sort_indices()
        lp.a_matrix_.format_ = hp.MatrixFormat.kColwise
        lp.a_matrix_.start_ = Ac.indptr.astype(np.int32)
        lp.a_matrix_.index_ = Ac.indices.astype(np.int32)
        lp.a_matrix_.value_ = Ac.data
        lp.a_matrix_.num_col_, lp.a_matrix_.num_row_ = p.n, p.m
        if p.is_mip:
            lp.integrality_ = [hp.HighsVarType.kInteger if i else hp.HighsVarType.kContinuous for i in p.integrality]
        lp.offset_ = p.c0
        st = h.passModel(lp)
        if st == hp.HighsStatus.kError:
            raise ValueError("HiGHS rejected the model (passModel returned an error)")
        if p.H is not None:
            Ht = sp.tril(p.H, format="csc")
            Ht.sort_indices()
            hess = hp.HighsHessian()
            hess.dim_ = p.n
            hess.format_ = hp.HessianFormat.kTriangular
            hess.start_ = Ht.indptr.astype(np.int32)
            hess.index_ = Ht.indices.astype(np.int32)
            hess.value_ = Ht.data
            if h.passHessian(hess) == hp.HighsStatus.kError:
                raise ValueError("HiGHS rejected the Hessian H (it must be positive semidefinite)")
        self._h = h
        self._idx_n = np.arange(p.n, dtype=np.int32)
        self._idx_m = np.arange(p.m, dtype=np.int32)

    def _push(self, changed: dict) -> None:
        p, h = self.problem, self._h
        if "c" in changed:
            h.changeColsCost(p.n, self._idx_n, p.c)
        h.changeObjectiveOffset(p.c0)
        if "bounds" in changed:
            h.changeColsBounds(p.n, self._idx_n, _hinf(p.lb), _hinf(p.ub))
        if "rows" in changed and p.m:
            h.changeRowsBounds(p.m, self._idx_m, _hinf(p.rl), _hinf(p.ru))
        if "A" in changed:
            vals = p.A.data
            for k in changed["A"]:
                h.changeCoeff(int(self._Arow[k]), int(self._Acol[k]), float(vals[k]))

    def _solve(self, ws, time_limit, gap, t0) -> MIQPResult:
        hp, h, p = self._hp, self._h, self.problem
        h.changeObjectiveOffset(p.c0)
        h.setOptionValue("time_limit", float(time_limit) if time_limit else hp.kHighsInf)
        nl = getattr(self, "_node_limit", None)
        if p.is_mip:
            h.setOptionValue("mip_max_nodes", 2**31 - 1 if nl is None else int(nl))  # a work budget (Solver.solve)
        h.setOptionValue("mip_rel_gap", gap)
        h.setOptionValue("mip_abs_gap", gap)
        if p.is_mip:
            h.clearSolver()  # a fresh search on the new data (the model is kept)
        if ws is not None and p.is_mip:
            sol = hp.HighsSolution()
            sol.col_value = ws
            sol.value_valid = True
            h.setSolution(sol)
        h.run()
        ms = h.getModelStatus()
        retried = ""
        if self._qp and ms == hp.HighsModelStatus.kIterationLimit:
            # the active-set QP solver cycled (see the class docstring): once more with a smaller regularization
            first = h.getInfo().qp_iteration_count
            if self._qp_retry:
                default = h.getOptionValue("qp_regularization_value")[1]
                h.setOptionValue("qp_regularization_value", QP_RETRY_REGULARIZATION)
                h.clearSolver()
                h.run()
                h.setOptionValue("qp_regularization_value", default)
                ms = h.getModelStatus()
                retried = f" (after {first} QP iterations, solved again with regularization {QP_RETRY_REGULARIZATION:g})"
            if ms == hp.HighsModelStatus.kIterationLimit:
                return _result(p, "error", None, -np.inf, 0, t0, self.name,
                               f"HiGHS's QP solver stopped at its iteration limit without proving an optimum{retried}"
                               f" (cycling); set params={{'qp_iteration_limit': ...}} or use another back-end")
        info = h.getInfo()
        w = None
        if info.primal_solution_status == hp.kSolutionStatusFeasible:
            w = np.array(h.getSolution().col_value)
        nodes = int(info.mip_node_count) if p.is_mip else 0
        status = HIGHS_STATUS.get(ms.name, "error")
        text = h.modelStatusToString(ms) + retried
        bound = (info.mip_dual_bound if p.is_mip else np.nan) if status in ("optimal", "time_limit") else -np.inf
        if status == "optimal":
            if w is None or p.violation(w) > FEAS_TOL:
                status = "error"
                text += (": no point" if w is None else f": the point violates the program by {p.violation(w):.1e}")
        if status == "infeasible" and p.is_mip:
            # HiGHS has declared feasible big-M programs infeasible with the optimum on the network bound:
            # SCIP confirms (or refutes) the claim
            return _confirm(self, p, "scip", None, time_limit, gap, t0, f"highs: {text}", nodes)
        if status == "optimal" and p.is_mip and self.options.get("cross_check", True):
            params = dict(self.options.get("params", {}), presolve="off")
            left = None if time_limit is None else max(time_limit - (time.perf_counter() - t0), 1e-3)
            other = HighsSolver(p, params=params, cross_check=False,
                                **{k: v for k, v in self.options.items() if k == "threads"}).solve(
                time_limit=left, gap=gap)
            J = p.objective(w)
            if not (other.status == "optimal" and abs(other.objective - J) <= gap * max(1.0, abs(J))):
                best = w if other.w is None or p.objective(w) <= other.objective else other.w
                return _confirm(self, p, "scip", best, time_limit, gap, t0,
                                f"highs: {text} at {J:.9g}, but {other.status} at {other.objective:.9g} with "
                                f"presolve off", nodes + other.nodes)
            nodes += other.nodes
            text += " (presolve on and off agree)"
        if status == "time_limit" and w is not None and p.violation(w) > FEAS_TOL:
            w = None
        return _result(p, status, w if status in ("optimal", "time_limit") else None, bound, nodes, t0, self.name, text)


#: HiGHS model status -> result status. Only kOptimal is a proof; the limits return the incumbent without proof;
#: kUnboundedOrInfeasible and every error are errors (no program here is unbounded: its variables are boxed).
HIGHS_STATUS = {"kOptimal": "optimal", "kInfeasible": "infeasible",
                "kTimeLimit": "time_limit", "kIterationLimit": "time_limit", "kSolutionLimit": "time_limit",
                "kInterrupt": "time_limit", "kHighsInterrupt": "time_limit", "kMemoryLimit": "time_limit",
                "kObjectiveBound": "time_limit", "kObjectiveTarget": "time_limit",
                "kUnboundedOrInfeasible": "error", "kUnbounded": "error", "kModelEmpty": "error", "kNotset": "error",
                "kLoadError": "error", "kModelError": "error", "kPresolveError": "error", "kSolveError": "error",
                "kPostsolveError": "error", "kUnknown": "error"}
