"""One solver layer for the mixed-integer programs of the controllers.

The CLF-CBF programs (eq. CLF_CBF with the costs eq. LP_cost / eq. QP_cost) and
the MPC (eq. MPC_form_miqp) are all instances of

    min  0.5 w'H w + c'w + c0
    s.t. rl <= A w <= ru,   lb <= w <= ub,   w_i integer where integrality[i] == 1,

with the big-M constraints of eq. (MIP_general) inside ``A``. A controller
builds the program once (:class:`MIQP`), hands it to :func:`make_solver`, and
at every control step only changes numbers in place (:meth:`Solver.update`:
the measured state enters through ``lb``/``ub`` or ``rl``/``ru``, the
reference through ``c``, new node bounds through the big-M coefficients of
``A``) before calling :meth:`Solver.solve`. The back-ends keep their model
between calls:

* ``"highs"``: HiGHS through highspy (MILPs and continuous QPs; HiGHS has no
  mixed-integer QP solver);
* ``"scip"``: SCIP through PySCIPOpt, the reference MIQP solver (the quadratic
  objective becomes an epigraph constraint ``t >= 0.5 w'Hw``);
* ``"daqp"``: DAQP, a dual active-set QP solver with its own depth-first
  branch and bound over binary constraints, written for hybrid MPC
  (Arnström, Bemporad & Axehill 2022);
* ``"gurobi"``, ``"cplex"``: commercial solvers, used only when installed.

``"auto"`` picks SCIP for a MILP (on the book's small big-M programs it was
measured faster than HiGHS and never wrong, while HiGHS returned sub-optimal
points as optimal at a few states, see :class:`HighsSolver`), HiGHS for a
continuous program and DAQP for a mixed-integer QP (the fastest exact back-end
measured on the MPC programs, see the chapter "Making it real-time"). Every
back-end reports the same :class:`MIQPResult`, with the objective re-evaluated
from the returned ``w`` (constants included) so that back-ends can be compared
number for number.

What "optimal" means
--------------------
A result has status ``"optimal"`` only when the optimum is proven: by a solver
status that is a proof (HiGHS ``kOptimal``, SCIP ``optimal``/``gaplimit``,
DAQP exit flag 1; every other status of each back-end is mapped explicitly, see
:data:`HIGHS_STATUS`, :data:`SCIP_STATUS`, :data:`DAQP_STATUS`) *and* a returned
point that satisfies the program's rows, bounds and integrality to
:data:`FEAS_TOL`. A claim that is not a proof is verified by an independent
solver instead of being trusted: DAQP's exit flags other than 1 (its flag 4,
returned after proximal-point iterations on the singular ``H`` of the big-M
programs, is not documented as optimal and was measured sub-optimal up to 12x)
and its "infeasible" on a mixed-integer program (its depth-first branch and
bound has declared feasible big-M programs infeasible) are re-solved by SCIP
(HiGHS for a continuous program), warm-started with DAQP's point; HiGHS's
"infeasible" on a mixed-integer program is confirmed by SCIP. The result's
``message`` says when this happened.

The tolerance policy (one place, used by the controllers): :data:`BOX_TOL`
for a measured state on the face of the domain box, :data:`FEAS_TOL` for the
solvers' rows, and the network bound checked with the forward pass to
:data:`BOUND_TOL` (round-off of the forward pass itself); the controllers
tighten ``u_max^eps`` in the rows they hand to a solver until the returned
point passes that check (:func:`next_margin`).
"""
from __future__ import annotations

import importlib
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.sparse as sp

from .systems import condense

Array = np.ndarray

#: Back-ends by name; ``"auto"`` is also accepted by :func:`make_solver`.
BACKENDS = ("highs", "scip", "daqp", "gurobi", "cplex")

#: What to install for each back-end.
_INSTALL = {"highs": "highspy", "scip": "PySCIPOpt", "daqp": "daqp", "gurobi": "gurobipy", "cplex": "cplex"}
_MODULE = {"highs": "highspy", "scip": "pyscipopt", "daqp": "daqp", "gurobi": "gurobipy", "cplex": "cplex"}

_INF = 1e20  # anything at least this large is infinite for every back-end

#: A measured state at most this far outside the domain box counts as on its face and is projected onto it
#: (the same number as :meth:`flnotes.FLSystem.in_domain`'s default); farther out is a ``ValueError``.
BOX_TOL = 1e-9
#: Largest violation of a program's rows, bounds and integrality accepted in a solver's point (the solvers'
#: feasibility tolerances are at most this).
FEAS_TOL = 1e-7
#: ``|Phi_NN(z, v)| <= u_max^eps + BOUND_TOL`` is how the network bound is checked with the forward pass: the
#: round-off of the forward pass itself, nothing of a solver's tolerance.
BOUND_TOL = 1e-12


# ---------------------------------------------------------------------------
# Problem and result
# ---------------------------------------------------------------------------
@dataclass
class MIQP:
    """``min 0.5 w'Hw + c'w + c0  s.t.  rl <= A w <= ru,  lb <= w <= ub``, integers where ``integrality == 1``.

    Attributes
    ----------
    H
        (n, n) symmetric positive semidefinite cost matrix, or ``None`` for a
        MILP (an all-zero ``H`` is treated as ``None``).
    c, c0
        Linear cost (n,) and constant.
    A, rl, ru
        (m, n) constraint matrix and row bounds (m,); a row with
        ``rl == ru`` is an equality, ``-inf``/``inf`` leave a side free.
    lb, ub
        Variable bounds (n,), possibly infinite.
    integrality
        (n,) array of 0 (continuous) and 1 (integer). The big-M encoding of
        eq. (MIP_general) only needs binaries (integers with bounds [0, 1]).
    """

    H: Optional[sp.csc_matrix]
    c: Array
    c0: float
    A: sp.csr_matrix
    rl: Array
    ru: Array
    lb: Array
    ub: Array
    integrality: Array

    def __post_init__(self) -> None:
        self.c = _vec(self.c, None, "c")
        n = self.c.size
        self.c0 = float(self.c0)
        if not np.isfinite(self.c0):
            raise ValueError(f"c0 must be finite, got {self.c0}")
        if self.H is not None:
            H = sp.csc_matrix(self.H, dtype=float)
            if H.shape != (n, n):
                raise ValueError(f"H must have shape ({n}, {n}) to match c, got {H.shape}")
            if H.nnz and not np.all(np.isfinite(H.data)):
                raise ValueError("H contains NaN or inf")
            if H.nnz and abs(H - H.T).max() > 1e-9 * max(1.0, abs(H).max()):
                raise ValueError("H must be symmetric: pass (H + H.T) / 2")
            H.eliminate_zeros()
            self.H = H if H.nnz else None
        A = sp.csr_matrix(self.A, dtype=float)
        if A.ndim != 2 or A.shape[1] != n:
            raise ValueError(f"A must have shape (m, {n}) to match c, got {A.shape}")
        if A.nnz and not np.all(np.isfinite(A.data)):
            raise ValueError("A contains NaN or inf")
        A.sort_indices()
        self.A = A
        m = A.shape[0]
        self.rl = _vec(self.rl, m, "rl", allow_inf=True)
        self.ru = _vec(self.ru, m, "ru", allow_inf=True)
        self.lb = _vec(self.lb, n, "lb", allow_inf=True)
        self.ub = _vec(self.ub, n, "ub", allow_inf=True)
        _check_order(self.rl, self.ru, "rl", "ru")
        _check_order(self.lb, self.ub, "lb", "ub")
        integ = np.asarray(self.integrality)
        if integ.shape != (n,):
            raise ValueError(f"integrality must have shape ({n},) to match c, got {integ.shape}")
        if not np.all(np.isin(integ, (0, 1))):
            raise ValueError("integrality must contain only 0 (continuous) and 1 (integer)")
        self.integrality = integ.astype(np.int8)

    @property
    def n(self) -> int:
        """Number of variables."""
        return self.c.size

    @property
    def m(self) -> int:
        """Number of constraint rows."""
        return self.A.shape[0]

    @property
    def n_integer(self) -> int:
        """Number of integer variables that are not fixed by their bounds (what branch and bound sees)."""
        return int(np.sum((self.integrality == 1) & (self.lb < self.ub)))

    @property
    def is_mip(self) -> bool:
        return bool(np.any(self.integrality == 1))

    def objective(self, w: Array) -> float:
        """``0.5 w'Hw + c'w + c0`` at ``w``."""
        w = np.asarray(w, float)
        val = self.c @ w + self.c0
        if self.H is not None:
            val += 0.5 * w @ (self.H @ w)
        return float(val)

    def violation(self, w: Array) -> float:
        """Largest violation of rows, bounds and integrality at ``w`` (0 when feasible)."""
        w = np.asarray(w, float)
        Aw = self.A @ w
        v = [0.0]
        if self.m:
            v += [np.max(self.rl - Aw), np.max(Aw - self.ru)]
        v += [np.max(self.lb - w), np.max(w - self.ub)]
        iw = w[self.integrality == 1]
        if iw.size:
            v.append(np.max(np.abs(iw - np.round(iw))))
        return float(max(v))

    def copy(self) -> "MIQP":
        return MIQP(None if self.H is None else self.H.copy(), self.c.copy(), self.c0, self.A.copy(), self.rl.copy(),
                    self.ru.copy(), self.lb.copy(), self.ub.copy(), self.integrality.copy())


@dataclass
class MIQPResult:
    """What every back-end returns.

    Attributes
    ----------
    status
        ``"optimal"`` (within the requested gap), ``"time_limit"`` (the
        incumbent, if any, is returned; ``w`` may be ``None``),
        ``"infeasible"`` or ``"error"``.
    w
        The solution (n,), or ``None``.
    objective
        ``0.5 w'Hw + c'w + c0`` re-evaluated at ``w`` (``nan`` without one).
    bound
        A lower bound on the optimum proved by the solver (``-inf`` if none).
    gap
        ``|objective - bound| / max(1, |objective|)``.
    nodes
        Branch-and-bound nodes (0 for a continuous program).
    time
        Wall-clock seconds of :meth:`Solver.solve` (data transfer included).
    backend
        The back-end's name.
    message
        The solver's own status text.
    """

    status: str
    w: Optional[Array]
    objective: float
    bound: float
    gap: float
    nodes: int
    time: float
    backend: str
    message: str = ""


def _result(problem: MIQP, status: str, w, bound: float, nodes: int, t0: float, backend: str, message: str) -> MIQPResult:
    if w is not None:
        w = np.asarray(w, float).copy()
        obj = problem.objective(w)
    else:
        obj = np.nan
    if status == "optimal" and not np.isfinite(bound):
        bound = obj
    if status == "optimal":
        bound = min(bound, obj)
    gap = abs(obj - bound) / max(1.0, abs(obj)) if (w is not None and np.isfinite(bound)) else np.inf
    return MIQPResult(status=status, w=w, objective=obj, bound=float(bound), gap=float(gap), nodes=int(nodes),
                      time=time.perf_counter() - t0, backend=backend, message=str(message))


# ---------------------------------------------------------------------------
# Checks
# ---------------------------------------------------------------------------
def _vec(x, n: Optional[int], name: str, allow_inf: bool = False) -> Array:
    a = np.asarray(x, float)
    if a.ndim == 0 and n is not None:
        a = np.full(n, float(a))
    if a.ndim != 1 or (n is not None and a.shape != (n,)):
        want = f"({n},)" if n is not None else "(n,)"
        raise ValueError(f"{name} must have shape {want}, got {np.shape(x)}")
    if np.any(np.isnan(a)) or (not allow_inf and not np.all(np.isfinite(a))):
        raise ValueError(f"{name} contains NaN{'' if allow_inf else ' or inf'}")
    return a.copy()


def _check_order(lo: Array, hi: Array, lo_name: str, hi_name: str) -> None:
    bad = np.flatnonzero(lo > hi)
    if bad.size:
        i = bad[0]
        raise ValueError(f"{lo_name}[{i}] = {lo[i]} > {hi_name}[{i}] = {hi[i]}: every lower bound must be <= its upper bound")


def _require(backend: str):
    try:
        return importlib.import_module(_MODULE[backend])
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError(f"the {backend!r} back-end needs the Python package {_INSTALL[backend]!r}: "
                          f"pip install {_INSTALL[backend]} (or choose another backend from {BACKENDS})") from exc


def next_margin(margin: float, excess: float, scale: float = 1.0) -> float:
    """The tightening of ``u_max^eps`` to try after a returned point exceeded it by ``excess``.

    At least ``1e-9 * max(1, scale)`` and at least twice the excess above the previous margin,
    and at least four times the previous margin: a solver whose tolerance let the point
    through moves only when the bound moves by more than its tolerance.
    At most ``1e-4 * max(1, scale)``: an excess that needs more is not a solver tolerance, and the
    point is then reported as failing the forward-pass check (never applied as a solution).
    """
    return float(min(max(4.0 * margin, margin + 2.0 * excess, 1e-9 * max(1.0, scale)), 1e-4 * max(1.0, scale)))


def project_to_box(z: Array, lo: Array, hi: Array, name: str = "z") -> Array:
    """``z`` clipped onto the box ``[lo, hi]`` when it lies at most :data:`BOX_TOL` outside it.

    A measured state on the face of the box, off by round-off, is the state on the face; farther
    out is a ``ValueError`` naming ``name``.
    """
    z = np.asarray(z, float)
    out = np.maximum(lo - z, z - hi)
    if np.any(out > BOX_TOL):
        i = int(np.argmax(out))
        raise ValueError(f"{name}[{i}] = {z[i]!r} lies {out[i]:.3g} outside the box [{lo[i]}, {hi[i]}] "
                         f"(tolerance {BOX_TOL:g}): start inside the box")
    return np.clip(z, lo, hi)


def available_backends() -> tuple[str, ...]:
    """The back-ends whose Python package can be imported here (commercial ones need a license too)."""
    out = []
    for b in BACKENDS:
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

    def __init__(self, problem: MIQP, **options):
        if not isinstance(problem, MIQP):
            raise ValueError(f"problem must be an flnotes.miqp.MIQP, got {type(problem).__name__}")
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
            c0 = float(c0)
            if not np.isfinite(c0):
                raise ValueError(f"c0 must be finite, got {c0}")
            p.c0 = c0
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
              gap: float = 1e-6) -> MIQPResult:
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
        """
        ws = None
        if warm_start is not None:
            ws = np.asarray(warm_start, float)
            if ws.shape != (self.problem.n,):
                raise ValueError(f"warm_start must have shape ({self.problem.n},), got {ws.shape}")
            if not np.all(np.isfinite(ws)):
                ws = None
        if time_limit is not None and not time_limit > 0:
            raise ValueError(f"time_limit must be positive seconds or None, got {time_limit}")
        if not gap >= 0:
            raise ValueError(f"gap must be >= 0, got {gap}")
        t0 = time.perf_counter()
        try:
            return self._solve(ws, time_limit, float(gap), t0)
        except (ValueError, ImportError):
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
        One of :data:`BACKENDS`, or ``"auto"``: SCIP for a MILP, HiGHS for a
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
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose 'auto' or one of {BACKENDS}")
    _require(backend)
    cls = {"highs": HighsSolver, "scip": ScipSolver, "daqp": DaqpSolver, "gurobi": GurobiSolver,
           "cplex": CplexSolver}[backend]
    return cls(problem, **options)


# ---------------------------------------------------------------------------
# HiGHS
# ---------------------------------------------------------------------------
class HighsSolver(Solver):
    """HiGHS (Huangfu & Hall 2018) through highspy, one persistent ``Highs`` object.

    MILPs go to its branch and cut, continuous QPs to its active-set QP
    solver. A warm start is passed with ``setSolution`` (an incumbent).

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
        for k, v in self.options.get("params", {}).items():
            h.setOptionValue(k, v)
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
        info = h.getInfo()
        w = None
        if info.primal_solution_status == hp.kSolutionStatusFeasible:
            w = np.array(h.getSolution().col_value)
        nodes = int(info.mip_node_count) if p.is_mip else 0
        status = HIGHS_STATUS.get(ms.name, "error")
        text = h.modelStatusToString(ms)
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

#: SCIP status -> result status. "optimal" and "gaplimit" (the requested gap is proven) are proofs; the limits
#: return the incumbent without proof; "unbounded", "inforunbd", "unknown", "terminate" are errors.
SCIP_STATUS = {"optimal": "optimal", "gaplimit": "optimal", "infeasible": "infeasible",
               "timelimit": "time_limit", "nodelimit": "time_limit", "totalnodelimit": "time_limit",
               "stallnodelimit": "time_limit", "memlimit": "time_limit", "sollimit": "time_limit",
               "bestsollimit": "time_limit", "restartlimit": "time_limit", "userinterrupt": "time_limit",
               "primallimit": "time_limit", "duallimit": "time_limit",
               "unbounded": "error", "inforunbd": "error", "unknown": "error", "terminate": "error"}


def _confirm(solver: "Solver", p: MIQP, backend: str, w, time_limit, gap, t0, claim: str, nodes: int) -> MIQPResult:
    """Re-solve ``p`` with ``backend`` (warm-started with ``w`` when it is feasible) to check a claim that is no proof.

    Returns the verifying solver's result, its message prefixed with the claim that was checked.
    """
    if backend not in available_backends():  # pragma: no cover - SCIP and HiGHS are requirements
        return _result(p, "time_limit" if w is not None else "error", w, -np.inf, nodes, t0, solver.name,
                       f"{claim}, not a proof, and {backend!r} is not installed to verify it")
    left = None if time_limit is None else max(time_limit - (time.perf_counter() - t0), 1e-3)
    ws = w if (w is not None and p.violation(w) <= FEAS_TOL) else None
    opts = {k: v for k, v in solver.options.items() if k == "threads"}
    out = make_solver(p, backend, **opts).solve(warm_start=ws, time_limit=left, gap=gap)
    out.message = f"{claim}, not a proof: verified by {backend}: {out.message}"
    out.nodes += int(nodes)
    out.backend = solver.name
    out.time = time.perf_counter() - t0
    return out


class _quiet_c_output:
    """Silence file descriptors 1 and 2 (C-level output of a solver library) inside a ``with`` block."""

    def __enter__(self):
        import os
        import sys

        try:
            sys.stdout.flush()
            sys.stderr.flush()
            self._null = os.open(os.devnull, os.O_WRONLY)
            self._saved = (os.dup(1), os.dup(2))
            os.dup2(self._null, 1)
            os.dup2(self._null, 2)
        except OSError:
            self._saved = None
        return self

    def __exit__(self, *exc):
        import os

        if self._saved is not None:
            os.dup2(self._saved[0], 1)
            os.dup2(self._saved[1], 2)
            for fd in (*self._saved, self._null):
                os.close(fd)
        return False


def _hinf(a: Array) -> Array:
    from highspy import kHighsInf
    out = np.asarray(a, float).copy()
    out[out >= _INF] = kHighsInf
    out[out <= -_INF] = -kHighsInf
    return out


# ---------------------------------------------------------------------------
# SCIP
# ---------------------------------------------------------------------------
class ScipSolver(Solver):
    """SCIP (Bestuzheva et al. 2021) through PySCIPOpt: the reference solver for mixed-integer QPs.

    The quadratic objective is written with an epigraph variable,
    ``min t + c'w + c0`` s.t. ``0.5 w'Hw <= t``, which SCIP recognizes as a
    convex quadratic constraint. The model is persistent: between solves it
    is returned to the problem stage (``freeTransform``) and bounds, row
    sides and coefficients are changed in place (``chgVarLb/Ub``,
    ``chgLhs/chgRhs``, ``chgCoefLinear``); the linear objective is reset with
    ``setObjective``. A warm start is added as a solution (``addSol``).
    """

    name = "scip"

    def _build(self) -> None:
        scip = _require("scip")
        p = self.problem
        m = scip.Model()
        m.hideOutput()
        m.setParam("parallel/maxnthreads", int(self.options.get("threads", 1)))
        # tighter than SCIP's default 1e-6: the comparisons between back-ends are at 1e-6 relative
        m.setParam("numerics/feastol", float(self.options.get("feastol", 1e-9)))
        for k, v in self.options.get("params", {}).items():
            m.setParam(k, v)
        self._inf = m.infinity()
        self._x = [m.addVar(name=f"w{i}", vtype="I" if p.integrality[i] else "C", lb=self._s(p.lb[i]),
                            ub=self._s(p.ub[i])) for i in range(p.n)]
        A = p.A
        self._cons = []
        for r in range(p.m):
            s, e = A.indptr[r], A.indptr[r + 1]
            expr = scip.quicksum(float(a) * self._x[j] for a, j in zip(A.data[s:e], A.indices[s:e]))
            cons = m.addCons(self._range(expr, p.rl[r], p.ru[r]), name=f"r{r}")
            self._cons.append(cons)
        self._t = None
        if p.H is not None:
            self._t = m.addVar(name="t", lb=None, ub=None)
            Hu = sp.triu(p.H, format="coo")
            quad = scip.quicksum((0.5 if i == j else 1.0) * float(v) * self._x[i] * self._x[j]
                                 for i, j, v in zip(Hu.row, Hu.col, Hu.data))
            m.addCons(quad - self._t <= 0, name="epigraph")
        self._m, self._scip = m, scip
        self._polisher = None  # a HiGHS QP with the integers fixed, built at the first polish
        self._set_objective()

    def _s(self, v: float):
        return None if abs(v) >= _INF else float(v)

    def _range(self, expr, lo: float, hi: float):
        if lo == hi:
            return expr == float(lo)
        lo_f, hi_f = lo > -_INF, hi < _INF
        if lo_f and hi_f:
            return (float(lo) <= expr) <= float(hi)
        if lo_f:
            return expr >= float(lo)
        if hi_f:
            return expr <= float(hi)
        return expr <= self._inf

    def _set_objective(self) -> None:
        p, scip = self.problem, self._scip
        nz = np.flatnonzero(p.c)
        obj = scip.quicksum(float(p.c[i]) * self._x[i] for i in nz)
        if self._t is not None:
            obj = obj + self._t
        self._m.setObjective(obj, "minimize", clear=True)

    def _push(self, changed: dict) -> None:
        m, p = self._m, self.problem
        m.freeTransform()
        if "c" in changed:
            self._set_objective()
        if "bounds" in changed:
            for i in range(p.n):
                # widen first, so that lb <= ub holds at every moment
                m.chgVarLb(self._x[i], None)
                m.chgVarUb(self._x[i], None)
                m.chgVarLb(self._x[i], self._s(p.lb[i]))
                m.chgVarUb(self._x[i], self._s(p.ub[i]))
        if "rows" in changed:
            for r, cons in enumerate(self._cons):
                m.chgLhs(cons, None)
                m.chgRhs(cons, None)
                m.chgLhs(cons, self._s(p.rl[r]))
                m.chgRhs(cons, self._s(p.ru[r]))
        if "A" in changed:
            vals = p.A.data
            for k in changed["A"]:
                m.chgCoefLinear(self._cons[int(self._Arow[k])], self._x[int(self._Acol[k])], float(vals[k]))

    def _solve(self, ws, time_limit, gap, t0) -> MIQPResult:
        m, p = self._m, self.problem
        m.freeTransform()
        m.setParam("limits/time", float(time_limit) if time_limit else 1e20)
        m.setParam("limits/gap", 0.5 * gap)  # SCIP divides by min(|primal|, |dual|): keep a margin
        m.setParam("limits/absgap", 0.5 * gap)
        if ws is not None and self._warm_ok(ws):
            sol = m.createSol()
            for i in range(p.n):
                m.setSolVal(sol, self._x[i], float(ws[i]))
            if self._t is not None:
                m.setSolVal(sol, self._t, float(0.5 * ws @ (p.H @ ws)) + 1e-9)
            m.addSol(sol, free=True)
        with _quiet_c_output():  # SoPlex prints tolerance notices straight to the C streams
            m.optimize()
        st = m.getStatus()
        nodes = m.getNNodes() if p.is_mip else 0
        w = None
        if m.getNSols() > 0:
            best = m.getBestSol()
            w = np.array([m.getSolVal(best, x) for x in self._x])
        try:
            bound = m.getDualbound() + p.c0
        except Exception:
            bound = -np.inf
        if abs(bound) >= 1e19:
            bound = -np.inf
        if w is not None and p.H is not None:
            w = self._polish(w)
        status = SCIP_STATUS.get(st, "error")
        if status == "optimal" and (w is None or p.violation(w) > FEAS_TOL):
            status = "error"
            st += ": no point" if w is None else f": the point violates the program by {p.violation(w):.1e}"
        if status == "time_limit" and w is not None and p.violation(w) > FEAS_TOL:
            w = None
        if status == "infeasible":
            return _result(p, "infeasible", None, np.inf, nodes, t0, self.name, st)
        return _result(p, status, w if status in ("optimal", "time_limit") else None,
                       bound if status != "error" else -np.inf, nodes, t0, self.name, st)

    def _polish(self, w: Array) -> Array:
        """The QP optimum with the integers fixed at ``w``'s (HiGHS), when it is better than ``w``.

        SCIP enforces the epigraph ``0.5 w'Hw <= t`` through cutting planes, to
        a tolerance that is relative: near a zero optimum its point can be off
        by 1e-5 in the objective. Re-solving the convex QP of the same integer
        assignment removes that error and never makes the point worse.
        """
        p = self.problem
        ints = p.integrality == 1
        lb, ub = p.lb.copy(), p.ub.copy()
        lb[ints] = ub[ints] = np.clip(np.round(w[ints]), p.lb[ints], p.ub[ints])
        try:
            if self._polisher is None:
                self._polisher = make_solver(MIQP(p.H, p.c, p.c0, p.A, p.rl, p.ru, lb, ub,
                                                  np.zeros(p.n, int)), "highs")
            else:
                self._polisher.update(c=p.c, c0=p.c0, rl=p.rl, ru=p.ru, lb=lb, ub=ub, A=p.A)
            r = self._polisher.solve()
        except Exception:  # polishing is an improvement, never a requirement
            return w
        if r.status == "optimal" and r.w is not None and r.objective < p.objective(w) \
                and p.violation(r.w) <= 1e-7:
            return r.w
        return w


# ---------------------------------------------------------------------------
# DAQP
# ---------------------------------------------------------------------------
class DaqpSolver(Solver):
    """DAQP (Arnström, Bemporad & Axehill 2022): dual active-set QP with branch and bound over binaries.

    Every variable's bounds become DAQP's "simple bounds"; a binary variable
    gets the ``BINARY`` sense (16: one of its two bounds must hold with
    equality), an equality row or a fixed variable the ``EQUALITY`` sense (5).
    DAQP's branch and bound is depth first and prunes every node whose
    relaxation is not better than ``fval_bound``.

    Positive semidefinite ``H``. DAQP factors ``H``; for the big-M programs
    ``H`` is zero on the network's variables. With ``reg=delta`` (default
    ``1e-6``) ``delta`` is added to the zero diagonal: DAQP solves the
    perturbed problem ``J_r(w) = J(w) + 0.5 delta sum w_i^2`` with a positive
    definite ``H`` (its exit flag 1 is then a proof for ``J_r``) and, with
    ``B = 0.5 delta sum max(lb_i^2, ub_i^2)`` over the perturbed variables,
    ``J <= J_r <= J + B`` on the box, so ``J* >= J_r(w) - B``: the returned
    point is certified optimal when ``B`` is within the requested gap (the
    result's ``bound``), and verified by SCIP otherwise. With ``reg=None``
    DAQP's proximal-point iterations (``eps_prox``) handle the singular
    directions instead; they end with the undocumented exit flag 4, which is
    no proof (measured up to 12x sub-optimal on the CLF-CBF programs), so
    every such answer is verified.

    Warm start. A feasible warm start ``w_ws`` gives the incumbent bound
    ``fval_bound = J(w_ws) + B``: DAQP then only explores nodes that can beat
    it. If none does (exit flag -1 under the bound), ``w_ws`` is optimal
    provided DAQP's branch and bound is right, which on the degenerate big-M
    rows it has not always been: an exit flag -1 on a mixed-integer program
    (with or without warm start) is verified by SCIP unless the option
    ``verify_infeasible=False`` is given (``make bench`` measures both).
    """

    name = "daqp"

    def _build(self) -> None:
        daqp = _require("daqp")
        p = self.problem
        bad = np.flatnonzero((p.integrality == 1) & ((p.lb < 0) | (p.ub > 1)) & (p.lb < p.ub))
        if bad.size:
            raise ValueError(f"the 'daqp' back-end supports binary integers only (bounds within [0, 1]); "
                             f"variable {bad[0]} has bounds [{p.lb[bad[0]]}, {p.ub[bad[0]]}]: use backend='scip' or 'highs'")
        self._daqp = daqp
        reg = self.options.get("reg", 1e-6)
        H = np.zeros((p.n, p.n)) if p.H is None else p.H.toarray()
        self._eps_prox = 0.0
        self._dreg = np.zeros(p.n)  # the diagonal added to H (reg mode)
        if p.H is None or not _is_pd(H):
            if reg:
                d = (np.abs(np.diag(H)) <= 1e-12).astype(float)
                self._dreg = float(reg) * d
                if not _is_pd(H + np.diag(self._dreg)):
                    self._dreg = self._dreg + float(reg)
                H = H + np.diag(self._dreg)
            else:
                self._eps_prox = float(self.options.get("eps_prox", 1e-6))
                if p.H is None:
                    H = None if self._eps_prox else H
        self._H = H
        self._Ad = p.A.toarray()
        self._model = None
        # the big-M rows are degenerate: DAQP's default cycling guard (10 iterations without progress)
        # stops too early on them
        self._settings = dict(eps_prox=self._eps_prox, primal_tol=float(self.options.get("primal_tol", 1e-7)),
                              cycle_tol=1000, progress_tol=1e-10)
        self._settings.update(self.options.get("params", {}))

    def _sense(self) -> Array:
        p = self.problem
        s = np.zeros(p.n + p.m, dtype=np.int32)
        binary = (p.integrality == 1) & (p.lb < p.ub)
        s[:p.n][binary] = 16
        s[:p.n][p.lb == p.ub] = 5
        s[p.n:][p.rl == p.ru] = 5
        return s

    def _bounds(self) -> tuple[Array, Array]:
        p = self.problem
        lb, ub = p.lb.copy(), p.ub.copy()
        ib = p.integrality == 1
        lb[ib], ub[ib] = np.ceil(lb[ib] - 1e-9), np.floor(ub[ib] + 1e-9)
        bu, bl = np.concatenate([ub, p.ru]), np.concatenate([lb, p.rl])
        bu[bu >= _INF] = np.inf
        bl[bl <= -_INF] = -np.inf
        return bu, bl

    def _push(self, changed: dict) -> None:
        if "A" in changed:
            self._Ad[self._Arow[changed["A"]], self._Acol[changed["A"]]] = self.problem.A.data[changed["A"]]

    def _solve(self, ws, time_limit, gap, t0) -> MIQPResult:
        p = self.problem
        incumbent = None
        if ws is not None and p.is_mip:
            w0 = ws.copy()
            ib = p.integrality == 1
            w0[ib] = np.round(w0[ib])
            if self._warm_ok(w0):
                incumbent = w0
        res = self._attempt(incumbent, time_limit, t0, eps_prox=None, gap=gap)
        if res.status == "error" and "retry" not in res.message:
            # DAQP may cycle on the degenerate big-M rows: once more with a stronger proximal term
            retry = self._attempt(incumbent, time_limit, t0, eps_prox=1e-4, gap=gap)
            if retry.status != "error":
                retry.message += " (after a retry with eps_prox=1e-4)"
                res = retry
        verifier = "scip" if p.is_mip else "highs"
        if res.status == "unproven":
            return _confirm(self, p, verifier, res.w, time_limit, gap, t0, f"daqp: {res.message}", res.nodes)
        if res.status == "infeasible" and ((p.is_mip and self.options.get("verify_infeasible", True)) or self._eps_prox):
            # DAQP's branch and bound (and its proximal iterations on a singular H) have declared feasible
            # big-M programs infeasible, or found nothing below a warm start that was not optimal
            return _confirm(self, p, verifier, incumbent, time_limit, gap, t0, f"daqp: {res.message}", res.nodes)
        if res.status == "error":
            fb = self.options.get("fallback", "scip")
            if fb and fb != "daqp":
                return _confirm(self, p, fb if p.is_mip else "highs", incumbent, time_limit, gap, t0,
                                f"daqp failed ({res.message})", res.nodes)
        return res

    def _attempt(self, incumbent, time_limit, t0, eps_prox=None, gap: float = 1e-6) -> MIQPResult:
        """One DAQP call on the program with its fixed variables substituted out."""
        daqp, p = self._daqp, self.problem
        bu_all, bl_all = self._bounds()
        lbv, ubv = bl_all[: p.n], bu_all[: p.n]
        fixed = lbv == ubv
        free = np.flatnonzero(~fixed)
        xf = np.where(fixed, lbv, 0.0)
        H = self._H
        c_r = p.c[free].copy()
        if H is not None and fixed.any():
            c_r += H[np.ix_(free, np.flatnonzero(fixed))] @ xf[fixed]
        Hr = None if H is None else H[np.ix_(free, free)]
        A = self._Ad
        shift = A @ xf if p.m else np.zeros(0)
        Ar = A[:, free] if p.m else np.zeros((0, free.size))
        ru, rl = bu_all[p.n:] - shift, bl_all[p.n:] - shift
        keep = np.any(Ar != 0.0, axis=1) if p.m else np.zeros(0, bool)
        if p.m and np.any(~keep & ((rl > 1e-9) | (ru < -1e-9))):
            return _result(p, "infeasible", None, np.inf, 0, t0, self.name, "a row without free variables is violated")
        Ar, ru, rl = Ar[keep], ru[keep], rl[keep]
        bu = np.r_[ubv[free], ru]
        bl = np.r_[lbv[free], rl]
        sense = np.zeros(bu.size, dtype=np.int32)
        sense[: free.size][(p.integrality[free] == 1)] = 16
        sense[free.size:][rl == ru] = 5
        settings = dict(self._settings)
        if eps_prox is not None:
            settings["eps_prox"] = eps_prox
        elif self._eps_prox and Hr is not None and free.size and np.all(np.abs(np.diag(Hr)) > 0):
            try:  # the fixed variables may have carried all the singular directions
                np.linalg.cholesky(Hr)
                settings["eps_prox"] = 0.0
            except np.linalg.LinAlgError:
                pass
        if Hr is None and not settings.get("eps_prox"):
            Hr = np.zeros((free.size, free.size))
        if time_limit:
            settings["time_limit"] = max(float(time_limit) - (time.perf_counter() - t0), 1e-3)
        # reg mode: DAQP minimizes J_r(w) = J(w) + 0.5 sum_i dreg_i w_i^2 with J <= J_r <= J + B on the box
        dr = self._dreg
        B = 0.0
        if np.any(dr > 0):
            big = np.maximum(np.abs(lbv), np.abs(ubv))[dr > 0]
            B = float(0.5 * np.sum(dr[dr > 0] * big ** 2)) if np.all(np.isfinite(big)) else np.inf
        if incumbent is not None and np.isfinite(B):
            # the reduced objective of the incumbent: the full objective minus the constant of the fixed part.
            # Any w better than the incumbent has J_r(w) < J(incumbent) + B: nodes above that are pruned.
            J_full = p.objective(incumbent)
            const = p.c0 + p.c[fixed] @ xf[fixed] + (0.5 * xf @ (H @ xf) if H is not None else 0.0)
            J = J_full + B - const
            settings["fval_bound"] = J - 1e-9 * max(1.0, abs(J_full))
        if free.size == 0:
            w = xf.copy()
            ok = p.violation(w) <= 1e-6
            return _result(p, "optimal" if ok else "infeasible", w if ok else None, np.nan, 0, t0, self.name,
                           "every variable is fixed")
        x, fval, flag, info = daqp.solve(Hr, c_r, Ar, bu, bl, sense, **settings)
        nodes = int(info.get("nodes", 0)) if p.is_mip else 0

        def full(xr):
            w = xf.copy()
            w[free] = np.asarray(xr, float)
            ib = p.integrality == 1
            w[ib] = np.round(w[ib])
            return w

        retry_note = "" if eps_prox is None else " retry"
        status = DAQP_STATUS.get(int(flag), "unproven" if flag > 0 else "error")
        msg = f"exitflag {flag} ({_DAQP_FLAGS.get(int(flag), 'not documented')}){retry_note}"
        if status in ("optimal", "unproven"):
            w = full(x)
            if p.violation(w) > FEAS_TOL:
                w = None
                msg += " but the point violates the program"
            cand = [v for v in (w, incumbent) if v is not None]
            best = min(cand, key=p.objective) if cand else None
            if status == "optimal" and w is not None and B > 0:
                # certificate of the perturbed problem: J* >= J_r(w) - B
                bound = p.objective(w) + 0.5 * float(dr @ w ** 2) - B
                if incumbent is not None:
                    bound = min(bound, p.objective(incumbent))
                J_best = p.objective(best)
                if abs(J_best - bound) <= gap * max(1.0, abs(J_best)):
                    return _result(p, "optimal", best, bound, nodes, t0, self.name,
                                   msg + f" (regularized by {float(dr.max()):.0e}: gap certified {B:.1e})")
                return _result(p, "unproven", best, bound, nodes, t0, self.name,
                               msg + f" (regularized: perturbation {B:.1e} above the gap)")
            if status == "optimal" and w is not None:
                return _result(p, "optimal", best, np.nan, nodes, t0, self.name, msg)
            return _result(p, "unproven" if best is not None else "error", best, -np.inf, nodes, t0, self.name, msg)
        if status == "infeasible":
            if incumbent is not None:  # nothing better than the warm start under fval_bound
                return _result(p, "infeasible", incumbent, np.nan, nodes, t0, self.name,
                               msg + ": nothing better than the warm start")
            return _result(p, "infeasible", None, np.inf, nodes, t0, self.name, msg)
        if status == "time_limit":
            return _result(p, "time_limit", incumbent, -np.inf, nodes, t0, self.name, msg)
        return _result(p, "error", None, -np.inf, nodes, t0, self.name, msg)


#: DAQP exit flag -> status. Only flag 1 is a proof. Flag 2 ("soft optimal": soft constraints were relaxed; none
#: are declared here) and every undocumented positive flag (4 is returned after proximal-point iterations on a
#: singular H) give a point without proof, verified by another solver (:meth:`DaqpSolver._solve`); -1 is a claim
#: of infeasibility, verified on mixed-integer programs.
DAQP_STATUS = {1: "optimal", 2: "unproven", -1: "infeasible", -2: "error", -3: "error", -4: "error", -5: "error",
               -6: "error", -7: "time_limit", -8: "error"}
_DAQP_FLAGS = {1: "optimal", 2: "soft optimal", -1: "infeasible", -2: "cycling", -3: "unbounded",
               -4: "iteration limit", -5: "nonconvex", -6: "overdetermined initial active set",
               -7: "time limit reached", -8: "unsupported problem"}


def _is_pd(H: Array) -> bool:
    try:
        np.linalg.cholesky(H + 0.0)
    except np.linalg.LinAlgError:
        return False
    d = np.linalg.eigvalsh(H)
    return bool(d.min() > 1e-10 * max(1.0, d.max()))


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


class CplexSolver(Solver):
    """IBM CPLEX through its Python API (the Community Edition limits the program size)."""

    name = "cplex"

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
