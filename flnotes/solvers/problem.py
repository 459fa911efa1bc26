"""The problem type of the solver layer: the mixed-integer QP, its result record and the tolerance policy.

Part of :mod:`flnotes.solvers` (see its docstring for what "optimal" means and the tolerance policy).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.sparse as sp

from .._checks import as_floats, check_number

Array = np.ndarray


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


#: A verdict of rows whose ``u_max^eps`` was tightened (:func:`next_margin`) is a proof when it lies within
#: ``max(gap, TIGHTENED_GAP)`` (relative) of the untightened program's lower bound. The floor: that bound comes from a
#: point over the network bound by the solver's tolerance, so below it the two cannot be told apart (SCIP's plan in
#: cvxpy's cone form was measured 2.7e-8 over ``u_max^eps``, its cost 2e-9 below the optimum, at a gap of 1e-9).
#: A tightened bound that removes a flat piece or a ridge of the network moves the verdict far more (1.5e-5 to 1 %).
TIGHTENED_GAP = 1e-6


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
        self.c0 = check_number(self.c0, "c0", "the constant of the cost", low=-np.inf)
        if self.H is not None:
            H = sp.csc_matrix(_matrix(self.H, "H"), dtype=float)
            if H.shape != (n, n):
                raise ValueError(f"H must have shape ({n}, {n}) to match c, got {H.shape}")
            if H.nnz and not np.all(np.isfinite(H.data)):
                raise ValueError("H contains NaN or inf")
            if H.nnz and abs(H - H.T).max() > 1e-9 * max(1.0, abs(H).max()):
                raise ValueError("H must be symmetric: pass (H + H.T) / 2")
            H.eliminate_zeros()
            self.H = H if H.nnz else None
        A = sp.csr_matrix(_matrix(self.A, "A"), dtype=float)
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
        for lo_name, lo, hi_name, hi in (("rl", self.rl, "ru", self.ru), ("lb", self.lb, "ub", self.ub)):
            if np.any(lo == np.inf) or np.any(hi == -np.inf):
                raise ValueError(f"{lo_name} must be < +inf and {hi_name} > -inf (no row or variable can be held at "
                                 f"infinity): use -inf for no lower bound, +inf for no upper bound")
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
        """Largest violation of rows, bounds and integrality at ``w`` (0 when feasible; ``inf`` at a point with a NaN
        or an infinite entry, which no row can be checked at)."""
        w = as_floats(w, "w")
        if w.size != self.n:
            raise ValueError(f"w must be a point of shape ({self.n},), got {w.shape}")
        w = w.reshape(-1)
        if not np.all(np.isfinite(w)):
            return float("inf")
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
def _matrix(M, name: str):
    """A sparse matrix as it is (its entries are checked as floats after conversion), anything else through
    :func:`as_floats` (booleans, strings and masked entries refused by name)."""
    if sp.issparse(M):
        if M.dtype.kind not in "iuf":
            raise ValueError(f"{name} must hold real numbers, got a sparse matrix of {M.dtype}")
        return M
    return as_floats(M, name)


def _vec(x, n: Optional[int], name: str, allow_inf: bool = False) -> Array:
    a = as_floats(x, name)
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
