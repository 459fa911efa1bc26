"""The solver interface: a persistent model of one :class:`~flnotes.solvers.problem.MIQP`, updated in place.

Also the choice of a back-end (:func:`make_solver`) and the check of a solver's claim by another (:func:`_confirm`).

Part of :mod:`flnotes.solvers` (see its docstring for what "optimal" means and the tolerance policy).
"""
from __future__ import annotations

import importlib
import numbers
import time
from typing import Optional

import numpy as np
import scipy.sparse as sp

from .._checks import as_floats, check_number
from .problem import FEAS_TOL, MIQP, Array, MIQPResult, _check_order, _result, _vec

#: Back-ends by name; ``"auto"`` is also accepted by :func:`make_solver`.
SOLVER_BACKENDS = ("highs", "scip", "daqp", "gurobi", "cplex")


#: What to install for each back-end.
_INSTALL = {"highs": "highspy", "scip": "PySCIPOpt", "daqp": "daqp", "gurobi": "gurobipy", "cplex": "cplex"}


_MODULE = {"highs": "highspy", "scip": "pyscipopt", "daqp": "daqp", "gurobi": "gurobipy", "cplex": "cplex"}


def _require(backend: str):
    try:
        return importlib.import_module(_MODULE[backend])
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError(f"the {backend!r} back-end needs the Python package {_INSTALL[backend]!r}: "
                          f"pip install {_INSTALL[backend]} (or choose another backend from {SOLVER_BACKENDS})") from exc


def available_backends() -> tuple[str, ...]:
    """The back-ends whose Python package can be imported here (commercial ones need a license too)."""
    out = []
    for b in SOLVER_BACKENDS:
        try:
            importlib.import_module(_MODULE[b])
            out.append(b)
        except ImportError:
            pass
    return tuple(out)


# ---------------------------------------------------------------------------
# The solver interface
# ---------------------------------------------------------------------------
class Solver:
    """A persistent model of one :class:`MIQP`, re-solved with new data at every control step.

    Subclasses implement ``_build``, ``_push`` (send changed data to the
    back-end) and ``_solve``. The problem data kept in :attr:`problem` is
    always the current one.
    """

    name = "base"
    supports_miqp = True
    #: Whether :meth:`solve` takes a ``node_limit`` (a work budget of the branch and bound that does not depend on the
    #: machine's speed or load): SCIP (``limits/totalnodes``) and HiGHS (``mip_max_nodes``) do; DAQP's branch and
    #: bound (0.11) has a time limit and a per-node iteration limit but no node limit.
    supports_node_limit = False
    #: The options the back-end reads (:meth:`check_options`): any other is an error, never silently ignored.
    OPTIONS: tuple = ("threads", "params")

    def __init__(self, problem: MIQP, **options):
        if not isinstance(problem, MIQP):
            raise ValueError(f"problem must be an flnotes.solvers.MIQP, got {type(problem).__name__}")
        self.check_options(options)
        self.problem = problem.copy()
        self.options = dict(options)
        p = self.problem
        if p.is_mip and p.H is not None and not self.supports_miqp:
            raise ValueError(f"the {self.name!r} back-end cannot solve a mixed-integer QP (H is not None and "
                             f"{int(p.integrality.sum())} integer variables); use backend='daqp' or 'scip'")
        # the sparsity pattern of A, to map new values onto it
        coo = p.A.tocoo()
        self._Arow, self._Acol = coo.row.astype(np.int64), coo.col.astype(np.int64)
        self._pattern = sp.csr_matrix((np.ones(p.A.nnz), (self._Arow, self._Acol)), shape=p.A.shape)
        self._build()

    @classmethod
    def check_options(cls, options: dict) -> None:
        """Raise a ValueError naming the first option the back-end does not read (a misspelt one included) or whose
        value means nothing: ``threads`` a positive integer, ``params`` a dict of the solver's own parameters (each
        back-end checks their names and values against its library), and the back-end's own options."""
        if not isinstance(options, dict):
            raise ValueError(f"the {cls.name} back-end's options must be a dict, got {options!r}")
        unknown = sorted(set(options) - set(cls.OPTIONS), key=str)
        if unknown:
            hint = " (the solver's own parameters go in params={...})" if "params" in cls.OPTIONS else ""
            raise ValueError(f"the {cls.name} back-end has no option {unknown[0]!r}; its options are "
                             f"{sorted(cls.OPTIONS)}{hint}")
        threads = options.get("threads", 1)
        if isinstance(threads, bool) or not isinstance(threads, numbers.Integral) or threads < 1:
            raise ValueError(f"the {cls.name} option threads must be a positive integer, got {threads!r}")
        if not isinstance(options.get("params", {}), dict):
            raise ValueError(f"the {cls.name} option params must be a dict of the solver's own parameters, got "
                             f"{options['params']!r}")
        cls._check_values(options)

    @classmethod
    def _check_values(cls, options: dict) -> None:
        """The back-end's own options and its ``params`` (none here)."""

    # -- public API ----------------------------------------------------------
    def update(self, *, c=None, c0=None, rl=None, ru=None, lb=None, ub=None, A=None) -> None:
        """Change numbers of the program in place (the structure stays).

        Parameters
        ----------
        c, c0, rl, ru, lb, ub
            New values, same shapes as in the :class:`MIQP`.
        A
            New constraint matrix with the same sparsity pattern (entries may
            become zero; no new nonzeros).
        """
        p = self.problem
        changed = {}
        if c is not None:
            p.c = _vec(c, p.n, "c")
            changed["c"] = True
        if c0 is not None:
            p.c0 = check_number(c0, "c0", "the constant of the cost", low=-np.inf)
            changed["c0"] = True
        if rl is not None or ru is not None:
            new_rl = _vec(rl, p.m, "rl", allow_inf=True) if rl is not None else p.rl
            new_ru = _vec(ru, p.m, "ru", allow_inf=True) if ru is not None else p.ru
            _check_order(new_rl, new_ru, "rl", "ru")
            eq_old, eq_new = p.rl == p.ru, new_rl == new_ru
            p.rl, p.ru = new_rl, new_ru
            changed["rows"] = True
            if np.any(eq_old != eq_new):
                changed["row_kind"] = True
        if lb is not None or ub is not None:
            new_lb = _vec(lb, p.n, "lb", allow_inf=True) if lb is not None else p.lb
            new_ub = _vec(ub, p.n, "ub", allow_inf=True) if ub is not None else p.ub
            _check_order(new_lb, new_ub, "lb", "ub")
            p.lb, p.ub = new_lb, new_ub
            changed["bounds"] = True
        if A is not None:
            vals = self._values_on_pattern(A)
            old = p.A.data
            diff = np.flatnonzero(vals != old)
            if diff.size:
                p.A = sp.csr_matrix((vals, p.A.indices, p.A.indptr), shape=p.A.shape)
                changed["A"] = diff
        if changed:
            self._push(changed)

    def solve(self, warm_start: Optional[Array] = None, time_limit: Optional[float] = None,
              gap: float = 1e-6, node_limit: Optional[int] = None) -> MIQPResult:
        """Solve the current program.

        Parameters
        ----------
        warm_start
            A candidate solution (n,), e.g. the previous plan shifted by one
            step. Back-ends use it as an incumbent (or an initial working
            set); it never changes the optimum.
        time_limit
            Seconds; ``None`` for no limit.
        gap
            Relative optimality gap ``|obj - bound| / max(1, |obj|)`` at which
            the search stops.
        node_limit
            Branch-and-bound nodes at most (a positive integer; ``None``: no limit), for back-ends with
            :attr:`supports_node_limit`; the search stops there with status ``"time_limit"`` and its incumbent.
            Unlike a time limit, the same program stops at the same node on every machine and load.
        """
        ws = None
        if warm_start is not None:
            ws = as_floats(warm_start, "warm_start")
            if ws.shape != (self.problem.n,):
                raise ValueError(f"warm_start must have shape ({self.problem.n},), got {ws.shape}")
            if not np.all(np.isfinite(ws)):
                ws = None
        time_limit = check_number(time_limit, "time_limit", "seconds", strict=True, none=True)
        gap = check_number(gap, "gap", "the relative optimality gap")
        if node_limit is not None:
            if isinstance(node_limit, bool) or int(node_limit) != node_limit or node_limit < 1:
                raise ValueError(f"node_limit must be a positive integer or None, got {node_limit!r}")
            if not self.supports_node_limit and self.problem.is_mip:
                raise ValueError(f"the {self.name!r} back-end takes no node limit (its branch and bound stops on the "
                                 f"clock only): use backend='scip' for a work budget, or node_limit=None")
        self._node_limit = None if node_limit is None or not self.problem.is_mip else int(node_limit)
        t0 = time.perf_counter()
        try:
            return self._solve(ws, time_limit, float(gap), t0)
        except (ValueError, TypeError, ImportError, NameError, AttributeError, IndexError, KeyError, AssertionError):
            # a programming error (or bad input) stops with its message, never a quiet "error" status
            raise
        except Exception as exc:  # a solver failure is a result, not a crash of the control loop
            return _result(self.problem, "error", None, -np.inf, 0, t0, self.name, f"{type(exc).__name__}: {exc}")

    # -- helpers -------------------------------------------------------------
    def _values_on_pattern(self, A) -> Array:
        p = self.problem
        A = sp.csr_matrix(A, dtype=float)
        if A.shape != p.A.shape:
            raise ValueError(f"A must have shape {p.A.shape} (the same as when the solver was built), got {A.shape}")
        if A.nnz:
            S = A.copy()
            S.data = np.ones_like(S.data)
            outside = S - S.multiply(self._pattern)
            outside.eliminate_zeros()
            if outside.nnz:
                raise ValueError("A has nonzeros outside the sparsity pattern the solver was built with; "
                                 "build a new solver (make_solver) for a new structure")
            if not np.all(np.isfinite(A.data)):
                raise ValueError("A contains NaN or inf")
        return np.asarray(A[self._Arow, self._Acol], float).ravel()

    def _warm_ok(self, ws: Optional[Array], tol: float = 1e-7) -> bool:
        return ws is not None and self.problem.violation(ws) <= tol

    # -- to implement ----------------------------------------------------------
    def _build(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _push(self, changed: dict) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _solve(self, ws, time_limit, gap, t0) -> MIQPResult:  # pragma: no cover - abstract
        raise NotImplementedError


def make_solver(problem: MIQP, backend: str = "auto", **options) -> Solver:
    """A persistent solver for ``problem``.

    Parameters
    ----------
    problem
        The program; its structure (sizes, sparsity of ``A``, ``H``,
        integrality) is fixed from now on, its numbers change with
        :meth:`Solver.update`.
    backend
        One of :data:`SOLVER_BACKENDS`, or ``"auto"``: SCIP for a MILP, HiGHS for a
        continuous program, DAQP for a mixed-integer QP.
    **options
        Back-end options: ``threads`` (HiGHS, SCIP, commercial), ``params``
        (dict of native parameters), DAQP's ``reg`` (see :class:`DaqpSolver`).

    Returns
    -------
    Solver
    """
    if backend == "auto":
        backend = ("daqp" if problem.H is not None else "scip") if problem.is_mip else "highs"
    if backend not in SOLVER_BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose 'auto' or one of {SOLVER_BACKENDS}")
    _require(backend)
    return _solver_class(backend)(problem, **options)


def _solver_class(backend: str) -> type:
    """The :class:`Solver` subclass of one of :data:`SOLVER_BACKENDS`."""
    module = importlib.import_module(f"{__package__}.{backend}")  # one module per back-end
    return getattr(module, {"highs": "HighsSolver", "scip": "ScipSolver", "daqp": "DaqpSolver",
                            "gurobi": "GurobiSolver", "cplex": "CplexSolver"}[backend])


def check_options(backend: str, options: dict) -> None:
    """Raise a ValueError naming the first of ``options`` that back-end ``backend`` does not read, or whose value
    means nothing (:meth:`Solver.check_options`): a controller checks its solver options when it is built, not at
    the first program that reaches the back-end."""
    if backend not in SOLVER_BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {SOLVER_BACKENDS}")
    _solver_class(backend).check_options(options)


#: Solver models whose release is deferred (:func:`retire`): freeing a SCIP model took 1 to 6 ms on the Quad-1D's
#: programs at N_p = 20, which a time-limited step spent after its solver had stopped.
_RETIRED: list = []


def retire(solver: "Solver") -> None:
    """Keep ``solver`` alive until :func:`release_retired`: its model is freed then, not when the caller returns.

    A time-limited control step answers first and frees the models it built at the start of its next step, inside
    that step's budget (:class:`flnotes.MPC`).
    """
    _RETIRED.append(solver)


def release_retired() -> int:
    """Free the models kept by :func:`retire`; returns how many there were."""
    n = len(_RETIRED)
    _RETIRED.clear()
    return n


#: Seconds a verification needs at least to start under a time limit: with less time left no model is built (SCIP's
#: took 10 to 17 ms for the level-set programs of the Quad-1D at N_p = 20, and the steps that built one with less
#: time left answered that much after their limit).
VERIFY_MIN_LEFT = 0.02


def _confirm(solver: "Solver", p: MIQP, backend: str, w, time_limit, gap, t0, claim: str, nodes: int) -> MIQPResult:
    """Re-solve ``p`` with ``backend`` (warm-started with ``w`` when it is feasible) to check a claim that is no proof.

    Returns the verifying solver's result; its message says what that solver proved (or that it did not decide), then
    the claim that was checked.
    """
    if backend not in available_backends():  # pragma: no cover - SCIP and HiGHS are requirements
        return _result(p, "time_limit" if w is not None else "error", w, -np.inf, nodes, t0, solver.name,
                       f"{claim}, not a proof, and {backend!r} is not installed to verify it")
    ws = w if (w is not None and p.violation(w) <= FEAS_TOL) else None
    opts = {k: v for k, v in solver.options.items() if k == "threads" and backend != "highs"}  # HiGHS: one thread
    if backend == "scip":  # the caller's options for SCIP (DAQP's ``scip_options``); the MIQP-only ones not on an MILP
        opts.update({k: v for k, v in solver.options.get("scip_options", {}).items()
                     if p.H is not None or k not in ("objective", "miqp_params")})
    left = None if time_limit is None else time_limit - (time.perf_counter() - t0)
    verifier = None
    if left is None or left > VERIFY_MIN_LEFT:
        verifier = make_solver(p, backend, **opts)  # building the model takes time too: the time left is taken after
        left = None if time_limit is None else time_limit - (time.perf_counter() - t0)
    if verifier is None or (left is not None and left <= 1e-3):
        return _result(p, "time_limit", ws, -np.inf, nodes, t0, solver.name,
                       f"{claim}, not a proof, and the time limit came before {backend} could verify it")
    out = verifier.solve(warm_start=ws, time_limit=left, gap=gap)
    if time_limit is not None:
        retire(verifier)  # freed at the next release, not inside this time-limited call
    if out.status in ("optimal", "infeasible"):  # the message says first what was proven, and by which solver
        out.message = f"{out.status}, proven by {backend} ({out.message}); it re-solved the program to check {claim}"
    else:
        out.message = f"{claim}, not a proof; {backend} did not decide it: {out.message}"
    out.nodes += int(nodes)
    out.backend = solver.name
    out.time = time.perf_counter() - t0
    return out
