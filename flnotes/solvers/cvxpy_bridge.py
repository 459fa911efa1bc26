"""SCIP for cvxpy's mixed-integer programs: cvxpy writes the program, :class:`ScipSolver` solves it.

cvxpy's own SCIP interface is a conic one: it hands a quadratic cost to SCIP as a second-order cone (auxiliary
variables and rows), which SCIP separates as a nonlinear constraint, with ``optimize`` holding the interpreter lock.
On the CLF-CBF programs of one input with the quadratic cost (eq. QP_cost) that path was slow and fragile at the
suite's feasibility tolerance (1e-9): near the MSD's domain edge a step raised "Solver 'SCIP' failed" after 31 to
49 s, and one "optimal" step took 65 to 82 s (on 400 MSD states, half of them within 2 % of a face of the box, the
slowest step took 64.8 s there and 0.38 s here, at the same optima). :class:`ScipQP` is a cvxpy custom QP solver
instead: cvxpy canonicalizes the program as written (its QP form ``min 0.5 x'Px + q'x  s.t.  Ax = b, Fx <= g``,
bounds and binaries) and the solver layer's :class:`ScipSolver` solves that :class:`MIQP` (the separable epigraph
of the cost, feasibility tolerance 1e-9, the time limit passed to SCIP, SCIP running without the interpreter lock,
the point polished and checked against the rows to :data:`FEAS_TOL`), with SCIP's own settings
(``miqp_params="default"``). Not for every program: on the MPC reference's uncondensed programs (states as
variables, eq. MPC_form_miqp) this epigraph needed 10 s and more where cvxpy's cone form needed 0.03 s, and the
MPC reference keeps cvxpy's SCIP interface (:mod:`flnotes.mpc.reference`). A program without a quadratic cost (the
CLF-CBF's Lcost, a MILP) goes the same way, with the solver layer's SCIP settings for a MILP.

Usage: ``bridge = ScipQP(); problem.solve(solver=bridge, time_limit=..., gap=...)``; the solver layer's
:class:`MIQPResult` of the last solve is ``bridge.result`` (also when cvxpy raised ``SolverError`` for a result without
a point: its status and SCIP's message are kept there).

:class:`ScipConic` is cvxpy's conic SCIP interface itself (the cone form the MPC reference keeps), with three changes
and a check: SCIP runs without the interpreter lock (``optimizeNogil``: other threads of the process run meanwhile);
SCIP's output stays on the C streams instead of PySCIPOpt's ``redirectOutput``, whose process-wide error printer would
then run without the lock and crash the process (see :func:`flnotes.solvers.scip.default_error_printer`); and each second-order
cone is written as a norm, ``sqrt(sum x_i^2) <= t``, the form SCIP's cone handler recognises (cvxpy writes
``sum x_i^2 <= t^2``, which SCIP took for a nonconvex row and branched on; see :meth:`ScipConic.add_model_soc_constr`).
A program with cones whose continuous relaxation Clarabel certifies unbounded (the certificate checked) is not handed
to SCIP, which does not detect it with cones: a continuous one is cvxpy's ``unbounded`` (``infeasible`` or
``infeasible_or_unbounded`` as a second solve decides feasibility), a mixed-integer one an error (``status`` says why).
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np
import scipy.sparse as sp

import cvxpy.settings as s
from cvxpy.reductions.solution import Solution, failure_solution
from cvxpy.reductions.solvers.conic_solvers.scip_conif import SCIP as _CvxpyScip
from cvxpy.reductions.solvers.qp_solvers.qp_solver import QpSolver
from cvxpy.utilities.citations import CITATION_DICT

from .base import make_solver
from .problem import MIQP, MIQPResult

#: :class:`MIQPResult` status -> cvxpy status (a point under a limit is cvxpy's ``user_limit``, with the point).
STATUS = {"optimal": s.OPTIMAL, "time_limit": s.USER_LIMIT, "infeasible": s.INFEASIBLE, "error": s.SOLVER_ERROR}

#: SCIP's statuses of an unbounded program -> cvxpy's (the solver layer calls both errors: its programs are bounded).
UNBOUNDED = {"unbounded": s.UNBOUNDED, "inforunbd": s.INFEASIBLE_OR_UNBOUNDED}

#: The feasibility tolerances SCIP accepts here (SCIP refuses a value below 1e-17 or one that is not small).
FEASTOL_RANGE = (1e-12, 1e-3)

#: The options :class:`ScipQP` takes in ``problem.solve(solver=ScipQP(), **options)``.
OPTIONS = ("time_limit", "gap", "feastol", "miqp_params")


class ScipQP(QpSolver):
    """A cvxpy custom solver: the program's QP form solved by :class:`flnotes.solvers.ScipSolver` (see the module)."""

    MIP_CAPABLE = True
    BOUNDED_VARIABLES = True

    def __init__(self) -> None:
        super().__init__()
        #: The :class:`MIQPResult` of the last solve (None before the first).
        self.result: Optional[MIQPResult] = None

    def name(self) -> str:
        return "FLNOTES_SCIP"

    def cite(self, data) -> str:
        return CITATION_DICT["SCIP"]

    def import_solver(self) -> None:
        import pyscipopt  # noqa: F401

    @staticmethod
    def miqp(data: dict) -> MIQP:
        """cvxpy's QP data as an :class:`MIQP`: one row block ``[A; F]`` with sides ``[b, b]`` and ``[-inf, g]``."""
        n = int(data["n_var"])
        P = sp.csc_matrix(data[s.P], dtype=float)
        H = 0.5 * (P + P.T) if P.nnz else None
        A, F = sp.csr_matrix(data[s.A], dtype=float), sp.csr_matrix(data[s.F], dtype=float)
        b, g = np.asarray(data[s.B], float).ravel(), np.asarray(data[s.G], float).ravel()
        lb = np.full(n, -np.inf) if data.get(s.LOWER_BOUNDS) is None else np.asarray(data[s.LOWER_BOUNDS], float)
        ub = np.full(n, np.inf) if data.get(s.UPPER_BOUNDS) is None else np.asarray(data[s.UPPER_BOUNDS], float)
        integ = np.zeros(n, int)
        bools = np.asarray(data[s.BOOL_IDX], int)
        integ[bools] = 1
        integ[np.asarray(data[s.INT_IDX], int)] = 1
        lb[bools], ub[bools] = np.maximum(lb[bools], 0.0), np.minimum(ub[bools], 1.0)
        return MIQP(H, np.asarray(data[s.Q], float).ravel(), 0.0, sp.vstack([A, F], format="csr"),
                    np.concatenate([b, np.full(g.size, -np.inf)]), np.concatenate([b, g]), lb, ub, integ)

    def solve_via_data(self, data, warm_start: bool, verbose: bool, solver_opts, solver_cache=None):
        bad = sorted(set(solver_opts) - set(OPTIONS))
        if bad:
            raise ValueError(f"ScipQP takes the options {OPTIONS}, got {bad}")
        tl, feastol = solver_opts.get("time_limit"), solver_opts.get("feastol", 1e-9)
        if tl is not None and (isinstance(tl, bool) or not isinstance(tl, (int, float, np.number))
                               or not (np.isfinite(tl) and tl > 0)):
            raise ValueError(f"time_limit must be a positive finite number of seconds or None, got {tl!r}")
        if isinstance(feastol, bool) or not isinstance(feastol, (int, float, np.number)) \
                or not (FEASTOL_RANGE[0] <= feastol <= FEASTOL_RANGE[1]):
            raise ValueError(f"feastol (SCIP's numerics/feastol) must be a number in {list(FEASTOL_RANGE)}, "
                             f"got {feastol!r}")
        prob = self.miqp(data)
        opts = {"feastol": float(feastol)}
        if "miqp_params" in solver_opts or prob.H is not None:  # ScipSolver refuses it for a program without H
            opts["miqp_params"] = solver_opts.get("miqp_params", "default")
        self.result = None
        self.result = make_solver(prob, "scip", **opts).solve(time_limit=solver_opts.get("time_limit"),
                                                              gap=float(solver_opts.get("gap", 1e-9)))
        return self.result

    def invert(self, solution, inverse_data):
        status = STATUS[solution.status]
        raw = solution.message.split(" ", 1)[0].rstrip(":")  # SCIP's own status word
        if solution.status == "error" and raw in UNBOUNDED:
            status = UNBOUNDED[raw]
        attr = {s.SOLVE_TIME: solution.time, s.EXTRA_STATS: solution}
        if solution.w is None or status in (s.INFEASIBLE, s.UNBOUNDED, s.INFEASIBLE_OR_UNBOUNDED):
            return failure_solution(s.SOLVER_ERROR if status == s.USER_LIMIT else status, attr)
        return Solution(status, solution.objective + inverse_data[s.OFFSET],
                        {inverse_data[self.VAR_ID]: solution.w}, {}, attr)


class _NoLockModel:
    """A PySCIPOpt model whose ``optimize`` is ``optimizeNogil``; everything else is the model's own."""

    def __init__(self, model) -> None:
        self._model = model

    def optimize(self) -> None:
        self._model.optimizeNogil()

    def __getattr__(self, name: str):
        return getattr(self._model, name)


class ScipConic(_CvxpyScip):
    """cvxpy's conic SCIP interface (``cp.SCIP``), SCIP run without the interpreter lock and without PySCIPOpt's
    Python output relay (see the module), each cone written as a norm (:meth:`add_model_soc_constr`). Options as
    ``cp.SCIP``'s (``scip_params=...``). ``status`` is SCIP's own status of the last solve (also when cvxpy raised
    ``SolverError``, e.g. ``"timelimit"`` without a point), or, for a program with cones whose continuous relaxation
    is unbounded (not handed to SCIP), ``"unbounded"``, ``"infeasible"`` or ``"infeasible_or_unbounded"``
    (continuous) or a message starting ``"unbounded relaxation"`` (mixed-integer: cvxpy raises ``SolverError``)."""

    def __init__(self) -> None:
        super().__init__()
        #: SCIP's status of the last solve (None before the first).
        self.status: Optional[str] = None

    def name(self) -> str:
        return "FLNOTES_SCIP_CONIC"

    def solve_via_data(self, data, warm_start: bool, verbose: bool, solver_opts, solver_cache=None):
        # cvxpy's own method without model.redirectOutput(): SCIP writes (only when verbose) to the C streams
        from pyscipopt.scip import Model

        from .scip import default_error_printer

        default_error_printer()  # a Python printer installed by someone else would run without the lock below
        t0 = time.perf_counter()
        A, b, c, dims = self._define_data(data)
        self.status = None
        verdict = self._relaxation_verdict(A, b, c, dims, data) if dims[s.SOC_DIM] else None
        if verdict is not None:
            # SCIP does not detect an unbounded program with cones (without, its LPs do): it called a finite point
            # optimal, or searched on
            mip = bool(data[s.BOOL_IDX] or data[s.INT_IDX])
            if mip and verdict != "infeasible":
                self.status = ("unbounded relaxation: the continuous relaxation of this mixed-integer program is "
                               f"{verdict.replace('_', ' ')}, which SCIP does not detect with cones; bound the variables")
                status = s.SOLVER_ERROR
            else:
                self.status = verdict
                status = {"unbounded": s.UNBOUNDED, "infeasible": s.INFEASIBLE,
                          "infeasible_or_unbounded": s.INFEASIBLE_OR_UNBOUNDED}[verdict]
            return {"status": status, s.SOLVE_TIME: time.perf_counter() - t0, s.NUM_ITERS: 0,
                    "scip_status": self.status}
        model = Model()
        variables = self._create_variables(model, data, c)
        constraints = self._add_constraints(model, variables, A, b, dims)
        self._set_params(model, verbose, solver_opts, data, dims)
        out = self._solve(_NoLockModel(model), variables, constraints, data, dims)
        self.status = str(model.getStatus())
        return out

    @staticmethod
    def _relaxation_verdict(A, b, c, dims: dict, data: dict) -> Optional[str]:
        """``"unbounded"``, ``"infeasible"`` or ``"infeasible_or_unbounded"`` for a continuous relaxation that Clarabel
        certifies has no dual point (``DualInfeasible``), the certificate checked; ``None`` otherwise (SCIP decides).

        SCIP, with cones as nonlinear rows, does not detect an unbounded program: it called a finite point optimal
        (e.g. ``min t + x_0 + x_1  s.t.  ||x|| <= t``: -4e19 here, -1.1e17 with cvxpy's own interface) or, with
        integers, searched without end. The certificate is a direction ``d`` along which the rows hold and the cost
        decreases: it is checked (``c'd < 0`` and ``-M d`` in the cones, to 1e-7 of the data's scale), since on badly
        scaled data Clarabel gave one for a bounded program. Such a direction says "unbounded" only for a feasible
        program: a second solve with a zero cost decides feasibility. The rows are SCIP's (``A x = b``,
        ``A x <= b``, ``b - A x`` in the cones), the variables' bounds and the binaries' ``[0, 1]`` added to the
        inequalities."""
        import clarabel

        n = len(c)
        A = sp.csr_matrix(A)
        n_eq, n_leq = int(dims[s.EQ_DIM]), int(dims[s.LEQ_DIM])
        lb = np.full(n, -np.inf) if data.get(s.LOWER_BOUNDS) is None else np.asarray(data[s.LOWER_BOUNDS], float)
        ub = np.full(n, np.inf) if data.get(s.UPPER_BOUNDS) is None else np.asarray(data[s.UPPER_BOUNDS], float)
        for j in data[s.BOOL_IDX]:
            lb[j], ub[j] = max(lb[j], 0.0), min(ub[j], 1.0)
        lo, hi = np.flatnonzero(np.isfinite(lb)), np.flatnonzero(np.isfinite(ub))
        eye = sp.eye(n, format="csr")
        M = sp.vstack([A[:n_eq + n_leq], -eye[lo], eye[hi], A[n_eq + n_leq:]], format="csc")
        q = np.r_[b[:n_eq + n_leq], -lb[lo], ub[hi], b[n_eq + n_leq:]]
        n_nn = n_leq + lo.size + hi.size
        socs = [int(d) for d in dims[s.SOC_DIM]]
        cones = ([clarabel.ZeroConeT(n_eq)] if n_eq else []) + ([clarabel.NonnegativeConeT(n_nn)] if n_nn else []) + \
            [clarabel.SecondOrderConeT(d) for d in socs]
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        c = np.asarray(c, float)
        solve = lambda cost: clarabel.DefaultSolver(sp.csc_matrix((n, n)), cost, M, q, cones, settings).solve()  # noqa: E731
        sol = solve(c)
        if sol.status != clarabel.SolverStatus.DualInfeasible:
            return None
        d = np.asarray(sol.x, float)
        r = -(M @ d)  # must lie in the cones
        scale = max(1.0, float(abs(M).max()) if M.nnz else 1.0) * max(float(np.abs(d).max()), 1e-300)
        tol = 1e-7 * scale
        viol = [np.abs(r[:n_eq]).max(initial=0.0), (-r[n_eq:n_eq + n_nn]).max(initial=0.0)]
        k = n_eq + n_nn
        for dk in socs:
            viol.append(np.linalg.norm(r[k + 1:k + dk]) - r[k])
            k += dk
        if not (max(viol) <= tol and c @ d < -1e-7 * max(1e-300, float(np.abs(c).max())) * float(np.abs(d).max())):
            return None
        feas = solve(np.zeros(n)).status
        if feas == clarabel.SolverStatus.Solved:
            return "unbounded"
        return "infeasible" if feas == clarabel.SolverStatus.PrimalInfeasible else "infeasible_or_unbounded"

    def add_model_soc_constr(self, model, variables: list, rows, A, b) -> tuple:
        """The cone ``||x||_2 <= t`` (rows ``t = b_0 - A_0 w``, ``x_i = b_i - A_i w``) written as SCIP's norm,
        ``sqrt(sum_i x_i^2) - t <= 0``, where cvxpy writes ``sum_i x_i^2 <= t^2``.

        Both say the same with ``t >= 0``, but SCIP's cone handler recognised only the norm on the reference's
        programs: cvxpy's quadratic was taken for a nonconvex row, and SCIP branched on continuous variables at the
        feasibility tolerance 1e-9 without closing the gap (a one-step program of 8 binaries, 1 after presolve:
        no answer in 100 s; a 3-neuron one: "error in LP solver"). As the norm, both are solved in 0.1 s. Returns
        ``(constraint, equality rows, new variables)`` as cvxpy's method does."""
        from cvxpy.reductions.solvers.conic_solvers.scip_conif import VariableTypes
        from pyscipopt import quicksum, sqrt

        rows = list(rows)
        terms: dict = {i: [] for i in rows}
        for (i, j), a in A.items():
            if i in terms:
                terms[i].append((a, variables[j]))
        soc = [model.addVar(obj=0, name=f"soc_t_{i}", vtype=VariableTypes.CONTINUOUS, lb=0 if k == 0 else None,
                            ub=None) for k, i in enumerate(rows)]
        rows_eq = [model.addCons(soc[k] == b[i] - quicksum(a * v for a, v in terms[i])) for k, i in enumerate(rows)]
        if len(soc) == 1:  # a cone of t alone: t >= 0, the variable's bound
            return model.addCons(soc[0] >= 0), rows_eq, soc
        return model.addCons(sqrt(quicksum(x * x for x in soc[1:])) - soc[0] <= 0), rows_eq, soc


__all__ = ["ScipQP", "ScipConic", "STATUS", "UNBOUNDED", "FEASTOL_RANGE", "OPTIONS"]
