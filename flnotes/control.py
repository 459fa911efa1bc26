"""CLF-CBF control with the network's input constraint, eq. (CLF_CBF).

At each state ``z`` the controller solves

    min_{v, delta}  J(v, z) + delta
    s.t.  |Phi_NN(z, v)| <= u_max^eps = u_max - eps              (CLF_CBF_b), via eq. (MIP_general)
          grad V(z)^T (A z + B v) <= -beta V(z) + delta, delta >= 0  (CLF_CBF_c)
          grad H(z)^T (A z + B v) >= -kappa H(z)                      (CLF_CBF_d)
          v_lo <= v <= v_hi                                           (the network's domain)

with the linear cost ``J = grad V(z)^T (A z + B v)`` (eq. LP_cost, a MILP:
"Lcost") or the quadratic cost ``J = ||v - k(z)||^2`` (eq. QP_cost, a MIQP:
"Qcost"). With ``z`` fixed every constraint is affine in ``v``; only the
network constraint needs binaries, and only for the neurons that interval
bounds (FBBT with ``z`` fixed) cannot decide.

Backends (all solve the same program exactly; they differ in speed):

* ``"cvxpy"``: the teaching form, written with :func:`flnotes.encode` on
  ``x = [z; v]`` with ``z`` and every ``z``-dependent coefficient a cvxpy
  ``Parameter``; built once, re-solved each step (HiGHS for the MILP, SCIP for
  the MIQP). cvxpy's per-solve overhead is several milliseconds.
* ``"highs"``, ``"scip"``, ...: a persistent solver model through
  :mod:`flnotes.solvers`, built once from :func:`flnotes.bigm_form`, whose
  big-M coefficients and bounds are updated in place each step.
* ``"exact"`` (single input only): for a fixed ``z``, ``Phi_NN(z, .)`` is
  piecewise affine in the scalar ``v``; its breakpoints are listed exactly
  (:func:`network_pieces_1d`), the feasible set is a union of intervals
  (:func:`exact_1d_feasible_set`) and the cost is minimized on each interval
  in closed form.

Infeasibility and the fallback
------------------------------
When the program is infeasible (e.g. the CBF condition and the input bound
conflict, or no ``v`` satisfies the input bound at this ``z``) the step
reports ``status="infeasible"``, ``fallback=True`` and applies the optimum of
the *softened* program: (CLF_CBF_b) and (CLF_CBF_d) get nonnegative slacks
``s_u``, ``s_H`` penalized in the cost with weights ``rho_u >> rho_H``
(default ``1e6`` and ``1e4``). The input bound, a physical limit, is thus
given up last, safety second, convergence (``delta``) first. When a solver
fails (error, time limit without a solution) the step reports that status
and applies the softened optimum if it can be computed, else ``k(z)``
clipped to ``[v_lo, v_hi]``; it never raises from inside a simulation.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Optional, Union

import numpy as np
import scipy.sparse as sp

from ._checks import as_state, as_floats, as_vector, box_in_domain, check_bool, check_number, one_number
from .bounds import NodeBounds, fbbt
from .config import one_blas_thread
from .network import ReLUNet
from .pieces import solve_exact_2d
from .simulate import StepResult
from .systems import FLSystem
from .solvers import BOUND_TOL, next_margin, project_to_box
from .solvers.base import check_options
from .solvers.scip import _quiet_c_output

Array = np.ndarray

__all__ = [
    "Certificate", "QuadraticCLF", "DistanceCBF", "as_certificate",
    "PiecewiseAffine1D", "network_pieces_1d", "exact_1d_feasible_set", "solve_exact_1d",
    "ClfCbfController", "AffineCBF", "ExponentialCBF", "cbf_condition_fails",
]

#: Backends of :class:`ClfCbfController`; the persistent ones need :mod:`flnotes.solvers`.
CLF_CBF_BACKENDS = ("auto", "exact", "cvxpy", "highs", "scip", "gurobi", "daqp")


# ---------------------------------------------------------------------------
# CLF and CBF: functions with gradients
# ---------------------------------------------------------------------------
class Certificate:
    """A scalar function of ``z`` with its gradient: a CLF ``V`` or a CBF ``H``.

    Subclasses implement :meth:`value` (vectorized: (N, n_z) -> (N,)) and
    :meth:`grad` ((n_z,) -> (n_z,)). Calling the object evaluates it on one
    point (a float) or on a batch (an array).
    """

    name: str = "certificate"

    def value(self, Z: Array) -> Array:  # pragma: no cover - interface
        raise NotImplementedError

    def grad(self, z: Array) -> Array:  # pragma: no cover - interface
        raise NotImplementedError

    def __call__(self, z: Array) -> Union[float, Array]:
        z = as_floats(z, "z")
        if z.ndim > 2:
            raise ValueError(f"z must be one state (n_z,) or a batch (N, n_z), got shape {z.shape}")
        out = as_floats(self.value(np.atleast_2d(z) if z.ndim else z.reshape(1, 1)), f"{self.name}(z)").reshape(-1)
        return float(out[0]) if z.ndim <= 1 else out


class QuadraticCLF(Certificate):
    """The quadratic CLF ``V(z) = z^T P z`` of Sec. IV-A, ``grad V(z) = 2 P z``.

    Parameters
    ----------
    P
        Symmetric positive definite matrix, shape (n_z, n_z).
    """

    name = "V"

    def __init__(self, P: Array):
        P = np.atleast_2d(as_floats(P, "P"))
        if P.ndim != 2 or P.shape[0] != P.shape[1]:
            raise ValueError(f"P must be a square matrix, got shape {P.shape}")
        if not np.all(np.isfinite(P)):
            raise ValueError(f"P contains NaN or inf: {P.tolist()}")
        if not np.allclose(P, P.T):
            raise ValueError("P must be symmetric: pass (P + P.T) / 2")
        if np.linalg.eigvalsh(P).min() <= 0:
            raise ValueError(f"P must be positive definite, its eigenvalues are {np.linalg.eigvalsh(P)}")
        self.P = P

    def value(self, Z: Array) -> Array:
        return np.einsum("ni,ij,nj->n", Z, self.P, Z)

    def grad(self, z: Array) -> Array:
        return 2.0 * self.P @ z

    def __repr__(self) -> str:
        return f"QuadraticCLF(P={self.P.tolist()})"


class DistanceCBF(Certificate):
    """The CBF ``H(z) = ||z - z_o|| - r_o`` of Sec. IV-A: negative inside the unsafe disc.

    ``grad H(z) = (z - z_o) / ||z - z_o||`` (set to zero at the centre, where
    it is undefined; there ``H = -r_o < 0`` anyway).

    Parameters
    ----------
    z_o
        Centre of the unsafe ball, shape (n_z,).
    r_o
        Its radius, > 0.
    """

    name = "H"

    def __init__(self, z_o: Array, r_o: float):
        self.z_o = as_floats(z_o, "z_o").reshape(-1)
        if not (self.z_o.size and np.all(np.isfinite(self.z_o))):
            raise ValueError(f"z_o must be the centre of the unsafe ball (a finite vector), got {z_o!r}")
        self.r_o = check_number(r_o, "r_o", "the radius of the unsafe ball", strict=True)

    def value(self, Z: Array) -> Array:
        if Z.shape[1] != len(self.z_o):
            raise ValueError(f"z must have {len(self.z_o)} entries like z_o, got shape {Z.shape}")
        return np.linalg.norm(Z - self.z_o, axis=1) - self.r_o

    def grad(self, z: Array) -> Array:
        d = np.asarray(z, float) - self.z_o
        n = np.linalg.norm(d)
        return d / n if n > 0 else np.zeros_like(d)

    def __repr__(self) -> str:
        return f"DistanceCBF(z_o={self.z_o.tolist()}, r_o={self.r_o})"


class AffineCBF(Certificate):
    """An affine barrier ``h(z) = c^T z + d``: the safe set is the half-space ``h(z) >= 0``.

    ``grad h = c``. On a Brunovsky chain a barrier on a position (``c^T B = 0``)
    has relative degree two: its first-order condition (CLF_CBF_d) does not
    contain ``v`` and cannot be enforced; use it through :class:`ExponentialCBF`.

    Parameters
    ----------
    c
        Normal of the boundary, shape (n_z,), not zero.
    d
        Offset.
    """

    name = "h"

    def __init__(self, c: Array, d: float):
        self.c = as_floats(c, "c").reshape(-1)
        if not np.all(np.isfinite(self.c)) or not np.any(self.c != 0):
            raise ValueError(f"c must be a finite, nonzero vector, got {self.c.tolist()}")
        self.d = check_number(d, "d", "the offset of the safe half-space", low=-np.inf)

    def value(self, Z: Array) -> Array:
        if Z.shape[1] != len(self.c):
            raise ValueError(f"z must have {len(self.c)} entries like c, got shape {Z.shape}")
        return Z @ self.c + self.d

    def grad(self, z: Array) -> Array:
        return self.c.copy()

    def __repr__(self) -> str:
        return f"AffineCBF(c={self.c.tolist()}, d={self.d})"


class ExponentialCBF(Certificate):
    """The exponential (second-order) CBF ``H_2 = dh/dt + k_1 h`` of a relative-degree-2 barrier ``h``.

    For ``z' = A z + B v`` and an affine ``h(z) = c^T z + d`` with
    ``c^T B = 0`` and ``c^T A B != 0`` (e.g. a bound on a position of a
    double integrator), ``dh/dt = c^T A z`` does not depend on ``v`` and

        H_2(z) = c^T A z + k_1 h(z),     grad H_2 = A^T c + k_1 c,

    so ``grad H_2^T B = c^T A B`` is never zero: the condition (CLF_CBF_d)
    written for ``H_2``, ``grad H_2^T (A z + B v) >= -kappa H_2(z)``, is a
    half-line in ``v`` that is never empty (without input bounds). Along any
    closed loop that keeps it, ``H_2(z(t)) >= 0`` for ``t >= 0`` if
    ``H_2(z(0)) >= 0``; then ``dh/dt >= -k_1 h``, so ``h(z(t)) >= h(z(0))
    e^{-k_1 t} >= 0``: the set ``{h >= 0} ∩ {H_2 >= 0}`` is forward invariant.
    Pass the object as ``H`` to :class:`ClfCbfController`; ``kappa`` of the
    controller plays the role of the second gain ``k_2``.

    Parameters
    ----------
    h
        The barrier, an :class:`AffineCBF`.
    A, B
        The Brunovsky pair, shapes (n_z, n_z) and (n_z, m).
    k1
        Gain > 0 of the inner condition ``dh/dt >= -k_1 h``.
    """

    name = "H2"

    def __init__(self, h: AffineCBF, A: Array, B: Array, k1: float):
        if not isinstance(h, AffineCBF):
            raise TypeError(f"h must be an AffineCBF, got {type(h).__name__}")
        A, B = np.atleast_2d(np.asarray(A, float)), np.asarray(B, float)
        B = B.reshape(len(B), -1)
        n = len(h.c)
        if A.shape != (n, n) or B.shape[0] != n:
            raise ValueError(f"A must be ({n}, {n}) and B ({n}, m) for h with {n} entries, got {A.shape} and {B.shape}")
        if not np.allclose(h.c @ B, 0.0):
            raise ValueError(f"h has relative degree one (c^T B = {(h.c @ B).tolist()} != 0): use it directly as H, "
                             "the first-order condition already contains v")
        if np.allclose(h.c @ A @ B, 0.0):
            raise ValueError("h has relative degree above two (c^T A B = 0): differentiate once more")
        if not (np.isfinite(k1) and k1 > 0):
            raise ValueError(f"k1 must be a positive gain, got {k1!r}")
        self.h, self.A, self.B, self.k1 = h, A, B, float(k1)
        self._g = A.T @ h.c + self.k1 * h.c

    def value(self, Z: Array) -> Array:
        """``H_2(z) = c^T A z + k_1 (c^T z + d)`` on a batch (N, n_z) -> (N,)."""
        return Z @ (self.A.T @ self.h.c) + self.k1 * self.h.value(Z)

    def grad(self, z: Array) -> Array:
        """``grad H_2 = A^T c + k_1 c`` (constant)."""
        return self._g.copy()

    def __repr__(self) -> str:
        return f"ExponentialCBF(h={self.h!r}, k1={self.k1})"


def cbf_condition_fails(H: Certificate, Z: Array, A: Array, B: Array, kappa: float, tol: float = 1e-12) -> Array:
    """Where no ``v`` at all satisfies the CBF condition (CLF_CBF_d), input bounds ignored.

    The condition ``grad H(z)^T (A z + B v) >= -kappa H(z)`` is affine in
    ``v``; if ``grad H(z)^T B != 0`` some ``v`` satisfies it. It fails for
    every ``v`` exactly where ``|grad H(z)^T B| <= tol`` and
    ``grad H(z)^T A z + kappa H(z) < 0``.

    Parameters
    ----------
    H
        The barrier function.
    Z
        States, shape (N, n_z).
    A, B
        The Brunovsky pair.
    kappa
        The CBF gain, > 0.

    Returns
    -------
    numpy.ndarray
        Boolean mask, shape (N,).
    """
    H = as_certificate(H, "H")
    Z = np.atleast_2d(as_floats(Z, "Z"))
    if Z.ndim != 2 or not np.all(np.isfinite(Z)):
        raise ValueError(f"Z must be finite states of shape (N, n_z), got shape {Z.shape}")
    A, B = as_floats(A, "A"), np.atleast_2d(as_floats(B, "B").T).T
    n = Z.shape[1]
    if A.shape != (n, n) or B.shape[0] != n or not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
        raise ValueError(f"A must be finite ({n}, {n}) and B finite ({n}, m), got shapes {A.shape} and {B.shape}")
    kappa = check_number(kappa, "kappa", "the CBF gain", strict=True)
    tol = check_number(tol, "tol", "the threshold of |grad H(z)^T B| read as no authority")
    at = [_certificate_at(H, z, "H") for z in Z]
    G, Hz = np.array([g for g, _ in at]).reshape(Z.shape), np.array([v for _, v in at])
    no_authority = np.all(np.abs(G @ B) <= tol, axis=1)
    return no_authority & (np.einsum("ni,ni->n", G, Z @ A.T) + kappa * Hz < 0)


class _FunctionCertificate(Certificate):
    def __init__(self, fn: Callable[[Array], float], grad: Callable[[Array], Array], name: str):
        self.fn, self._grad, self.name = fn, grad, name

    def value(self, Z: Array) -> Array:
        out = [as_floats(self.fn(z), f"{self.name}(z)").reshape(-1) for z in Z]
        if any(v.size != 1 for v in out):
            raise ValueError(f"{self.name}(z) must be one number per state, got {next(v for v in out if v.size != 1)}")
        return np.concatenate(out)

    def grad(self, z: Array) -> Array:
        return as_floats(self._grad(z), f"{self.name}.grad(z)").reshape(-1)


def as_certificate(obj: Any, name: str = "certificate") -> Certificate:
    """A :class:`Certificate` from one, from any object with ``__call__`` and ``grad``, or from ``(fn, grad)``."""
    if isinstance(obj, Certificate):
        return obj
    if isinstance(obj, tuple) and len(obj) == 2 and all(callable(f) for f in obj):
        return _FunctionCertificate(obj[0], obj[1], name)
    if callable(obj) and callable(getattr(obj, "grad", None)):
        return _FunctionCertificate(obj, obj.grad, name)
    raise ValueError(f"{name} must be a Certificate (e.g. QuadraticCLF, DistanceCBF), an object with __call__ "
                     f"and .grad, or a pair (fn, grad_fn); got {type(obj).__name__}")


def _certificate_at(c: Certificate, z: Array, name: str) -> tuple[Array, float]:
    """``grad c(z)`` (n_z,) and ``c(z)``, both finite real numbers, else ``ValueError`` naming ``name``: a NaN value
    or gradient would drop its row from eq. (CLF_CBF) without a word."""
    with np.errstate(all="ignore"):
        g = as_floats(c.grad(z), f"{name}.grad(z)").reshape(-1)
        v = as_floats(c(z), f"{name}(z)").reshape(-1)
    if g.shape != z.shape or not np.all(np.isfinite(g)):
        raise ValueError(f"{name}.grad(z) must be a finite vector of shape {z.shape} at z = {z}, got {g}")
    if v.shape != (1,) or not np.isfinite(v[0]):
        raise ValueError(f"{name}(z) must be a finite number at z = {z}, got {v}")
    return g, float(v[0])


def _cbf_list(H: Any) -> list[Certificate]:
    """None, one CBF (any form accepted by :func:`as_certificate`) or a list of them -> a list."""
    if H is None:
        return []
    is_pair = (isinstance(H, tuple) and len(H) == 2 and all(callable(f) for f in H)
               and not any(isinstance(f, Certificate) or hasattr(f, "grad") for f in H))
    if isinstance(H, (list, tuple)) and not is_pair:
        return [as_certificate(h, f"H[{i}]") for i, h in enumerate(H)]
    return [as_certificate(H, "H")]


# ---------------------------------------------------------------------------
# The exact 1-D method: Phi_NN(z, .) is piecewise affine in a scalar v
# ---------------------------------------------------------------------------
@dataclass
class PiecewiseAffine1D:
    """``Phi_NN(z, v)`` for fixed ``z`` as a continuous piecewise-affine function of the scalar ``v``.

    On ``[knots[i], knots[i+1]]`` it equals ``values[i] + slope[i] (v - knots[i])``.

    Attributes
    ----------
    knots
        Sorted breakpoints (shape (n+1,)), including the ends ``v_lo`` and ``v_hi``.
    values
        ``Phi_NN(z, knots)``, shape (n+1,).
    slope
        Slope of each piece, shape (n,).
    """

    knots: Array
    values: Array
    slope: Array

    @property
    def n_pieces(self) -> int:
        return len(self.slope)

    def __call__(self, v: Array) -> Array:
        """Evaluate by linear interpolation between knots (exact, the function is affine there); ``v`` must lie in
        ``[knots[0], knots[-1]]`` (outside it the pieces say nothing: ``ValueError``)."""
        v = as_floats(v, "v")
        tol = 1e-12 * max(1.0, float(self.knots[-1] - self.knots[0]))
        if np.any(~((v >= self.knots[0] - tol) & (v <= self.knots[-1] + tol))):
            raise ValueError(f"v must lie in the segment [{self.knots[0]}, {self.knots[-1]}] of the pieces, got "
                             f"{v[~((v >= self.knots[0] - tol) & (v <= self.knots[-1] + tol))].ravel()[:3]}")
        return self._at(v)

    def _at(self, v: Array) -> Array:
        """:meth:`__call__` without the checks (the package's own points of the segment)."""
        return np.interp(v, self.knots, self.values)


def _net_input_line(net: ReLUNet, z: Array, v: Array) -> Array:
    return np.hstack([np.broadcast_to(z, (len(v), len(z))), v[:, None]])


def network_pieces_1d(net: ReLUNet, z: Array, v_lo: float, v_hi: float) -> PiecewiseAffine1D:
    """All affine pieces of ``v -> Phi_NN(z, v)`` on ``[v_lo, v_hi]`` for a fixed ``z`` (single input).

    Walks the activation regions along the segment ``y^0 = [z, v]`` layer by
    layer: the pre-activations of layer 1 are affine in ``v``; once the knots
    hold every breakpoint of layers ``< k``, each pre-activation of layer ``k``
    is affine between consecutive knots, so its zero crossings are found exactly
    by linear interpolation and added to the knots (with the layer's values
    there, interpolated just as exactly). After the last hidden layer the
    output is affine between knots.

    Parameters
    ----------
    net
        A network with input ``[z, v]``, ``v`` scalar (``n_in = len(z) + 1``) and one output.
    z
        The fixed state, shape (n_in - 1,).
    v_lo, v_hi
        The segment of ``v``.

    Returns
    -------
    PiecewiseAffine1D
    """
    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    z = as_floats(z, "z").reshape(-1)
    if not np.all(np.isfinite(z)):
        raise ValueError(f"z contains NaN or inf: {z}")
    v_lo = check_number(v_lo, "v_lo", "the lower end of the segment of v", low=-np.inf)
    v_hi = check_number(v_hi, "v_hi", "the upper end of the segment of v", low=-np.inf)
    if net.n_in != len(z) + 1 or net.n_out != 1:
        raise ValueError(f"the exact 1-D method needs a single input v and a single output: the network has "
                         f"n_in = {net.n_in}, n_out = {net.n_out} and z has {len(z)} entries; use a MILP/MIQP backend")
    if not (np.isfinite(v_lo) and np.isfinite(v_hi) and v_lo < v_hi):
        raise ValueError(f"need finite v_lo < v_hi, got {v_lo!r}, {v_hi!r}")
    return _pieces_1d(net, z, v_lo, v_hi)


def _pieces_1d(net: ReLUNet, z: Array, v_lo: float, v_hi: float) -> PiecewiseAffine1D:
    """:func:`network_pieces_1d` without its checks (``z`` a finite float vector of ``n_in - 1`` entries, one output,
    finite ``v_lo < v_hi``): for callers that checked them, in a loop."""
    tol = 1e-12 * (v_hi - v_lo)  # relative to the segment: a short segment keeps its narrow pieces
    knots = np.array([v_lo, v_hi], float)
    W1 = net.W[0]
    pre = (W1[:, :-1] @ z + net.b[0])[None, :] + knots[:, None] * W1[None, :, -1]   # layer 1, affine in v
    for k in range(1, net.K):
        # pre (n_knots, n_k) is affine between consecutive knots: its zero crossings are exact roots
        sg = np.sign(pre)  # signs, not a product of values that can underflow
        i, j = np.nonzero(sg[:-1] * sg[1:] < 0)
        if len(i):
            a0, a1 = pre[i, j], pre[i + 1, j]
            t = a0 / (a0 - a1)
            roots = knots[i] + t * (knots[i + 1] - knots[i])
            at_roots = pre[i] + t[:, None] * (pre[i + 1] - pre[i])   # exact: affine between the two knots
            at_roots[np.arange(len(i)), j] = 0.0
            knots, pre = np.concatenate([knots, roots]), np.concatenate([pre, at_roots])
            order = np.argsort(knots, kind="stable")
            knots, pre = knots[order], pre[order]
            keep = np.empty(knots.size, bool)  # one knot per breakpoint
            keep[0], keep[1:] = True, knots[1:] - knots[:-1] > tol
            knots, pre = knots[keep], pre[keep]
            knots[0], knots[-1] = v_lo, v_hi
        pre = np.maximum(pre, 0.0) @ net.W[k].T + net.b[k]
    values = pre[:, 0]
    slope = (values[1:] - values[:-1]) / (knots[1:] - knots[:-1])
    return PiecewiseAffine1D(knots=knots, values=values, slope=slope)


def _merge(intervals: Array, tol: float = 0.0) -> Array:
    if len(intervals) == 0:
        return np.zeros((0, 2))
    iv = intervals[np.argsort(intervals[:, 0])]
    out = [iv[0].copy()]
    for a, b in iv[1:]:
        if a <= out[-1][1] + tol:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append(np.array([a, b]))
    return np.array(out)


def _pieces_within(pw: PiecewiseAffine1D, bound: float) -> Array:
    """Per piece, the sub-interval where ``|Phi_NN| <= bound`` (rows may be empty: lo > hi)."""
    v0, v1, y0, s = pw.knots[:-1], pw.knots[1:], pw.values[:-1], pw.slope
    with np.errstate(divide="ignore", invalid="ignore"):
        ra = v0 + (-bound - y0) / s
        rb = v0 + (bound - y0) / s
    lo = np.where(s > 0, ra, np.where(s < 0, rb, np.where(np.abs(y0) <= bound, -np.inf, np.inf)))
    hi = np.where(s > 0, rb, np.where(s < 0, ra, np.where(np.abs(y0) <= bound, np.inf, -np.inf)))
    return np.column_stack([np.maximum(lo, v0), np.minimum(hi, v1)])


def exact_1d_feasible_set(net: ReLUNet, z: Array, v_lo: float, v_hi: float, bound: float,
                          pieces: Optional[PiecewiseAffine1D] = None) -> Array:
    """The exact set ``{v in [v_lo, v_hi] : |Phi_NN(z, v)| <= bound}`` as disjoint closed intervals.

    This is eq. (Phi_NN_ep) at a fixed state for a single input: on each
    affine piece of ``Phi_NN(z, .)`` (see :func:`network_pieces_1d`) the
    condition is an interval; touching intervals are merged.

    Parameters
    ----------
    net, z, v_lo, v_hi
        As in :func:`network_pieces_1d`.
    bound
        ``u_max^eps = u_max - eps``, > 0.
    pieces
        The result of :func:`network_pieces_1d` if already computed, for this ``z`` and this segment (the segment
        is checked; the pieces do not record their ``z``, so that is the caller's part).

    Returns
    -------
    Array
        Shape (p, 2): rows ``[a_i, b_i]`` sorted, disjoint; (0, 2) when empty.
    """
    bound = check_number(one_number(bound, "bound"), "bound", "u_max^eps = u_max - eps", strict=True)
    if pieces is None:
        pw = network_pieces_1d(net, z, v_lo, v_hi)
    else:  # the pieces of this z on this segment: the segment at least is checked
        pw = pieces
        lo_hi = (check_number(v_lo, "v_lo", "the segment's lower end", low=-np.inf),
                 check_number(v_hi, "v_hi", "the segment's upper end", low=-np.inf))
        if not np.allclose(lo_hi, (pw.knots[0], pw.knots[-1]), rtol=1e-12, atol=1e-12):
            raise ValueError(f"pieces cover [{pw.knots[0]}, {pw.knots[-1]}] but v_lo, v_hi = {lo_hi}: pass the "
                             f"pieces of this segment (network_pieces_1d(net, z, v_lo, v_hi))")
    iv = _pieces_within(pw, bound)
    iv = iv[iv[:, 0] <= iv[:, 1]]
    # touching intervals merged: a gap of round-off (1e-12, less on a segment shorter than 1) is no gap
    return _merge(iv, tol=1e-12 * min(1.0, float(pw.knots[-1] - pw.knots[0])))


def _halfline(a: Array, b: Array) -> tuple[float, float]:
    """``{v : a_j v + b_j >= 0 for all j}`` as ``[lo, hi]`` (``lo > hi`` when empty)."""
    lo, hi = -np.inf, np.inf
    for aj, bj in zip(np.atleast_1d(a), np.atleast_1d(b)):
        if aj > 0:
            lo = max(lo, -bj / aj)
        elif aj < 0:
            hi = min(hi, -bj / aj)
        elif bj < 0:
            return np.inf, -np.inf
    return lo, hi


def _objective_1d(v: Array, d: dict, cost: str, pw: Optional[PiecewiseAffine1D] = None,
                  bound: float = 0.0, rho: tuple[float, float] = (0.0, 0.0)) -> tuple[Array, Array]:
    """``J(v) + delta*(v)`` (+ penalties of the softened program) at many scalar ``v``; also ``delta*``."""
    aV, bV = d["aV"][0], d["bV"]
    delta = np.maximum(0.0, aV * v + bV)
    J = aV * v + d["Jc"] if cost == "linear" else (v - d["k"][0]) ** 2
    f = J + delta
    if pw is not None:
        f = f + rho[0] * np.maximum(0.0, np.abs(pw._at(v)) - bound)
        if len(d["bH"]):
            f = f + rho[1] * np.maximum(0.0, -(np.outer(v, d["aH"][:, 0]) + d["bH"])).sum(axis=1)
    return f, delta


def solve_exact_1d(pw: PiecewiseAffine1D, d: dict, cost: str, bound: float, soft: bool = False,
                   rho: tuple[float, float] = (1e6, 1e4)) -> Optional[tuple[float, float, float]]:
    """Minimize the cost of eq. (CLF_CBF) over ``v`` exactly, for a single input.

    ``d`` holds the data of the program at the current ``z`` (see
    :meth:`ClfCbfController.program_data`). The objective ``J(v) + delta*(v)``
    with ``delta*(v) = max(0, a_V v + b_V)`` is convex and piecewise linear
    (Lcost) or piecewise quadratic (Qcost) on each feasible interval, so its
    minimum is at an interval end, at the kink of ``delta*`` or at a vertex of
    a quadratic piece: all candidates are evaluated, the best kept.

    With ``soft=True`` the softened program of the fallback is solved instead
    (penalties ``rho = (rho_u, rho_H)`` on the violations of the input bound
    and of the CBF condition), over every piece.

    Returns
    -------
    (v, delta, objective), or None when the program is infeasible.
    """
    bound = check_number(one_number(bound, "bound"), "bound", "u_max^eps = u_max - eps", strict=True)
    r = as_floats(rho, "rho")
    if r.shape != (2,) or not np.all(np.isfinite(r)) or np.any(r < 0):
        raise ValueError(f"rho must be two finite penalties >= 0 (rho_u, rho_H), got {rho!r}")
    rho = (float(r[0]), float(r[1]))
    aV, bV = d["aV"][0], d["bV"]
    if not soft:
        iv = _pieces_within(pw, bound)
        iv = iv[iv[:, 0] <= iv[:, 1]]
        lo, hi = _halfline(d["aH"][:, 0], d["bH"])
        iv = np.column_stack([np.maximum(iv[:, 0], lo), np.minimum(iv[:, 1], hi)]) if len(iv) else iv
        iv = iv[iv[:, 0] <= iv[:, 1]]
        if len(iv) == 0:
            return None
        pts = [iv[:, :1], iv[:, 1:]]
        extra = [-bV / aV] if aV != 0 else []
        if cost == "quadratic":
            extra += [d["k"][0], d["k"][0] - aV / 2]
        if extra:
            pts.append(np.clip(np.array(extra)[None, :], iv[:, :1], iv[:, 1:]))
        cand = np.concatenate(pts, axis=1).ravel()
        f, delta = _objective_1d(cand, d, cost)
    else:
        v0, v1, y0, s = pw.knots[:-1, None], pw.knots[1:, None], pw.values[:-1, None], pw.slope[:, None]
        rho_u, rho_H = rho
        aH, bH = d["aH"][:, 0], d["bH"]
        with np.errstate(divide="ignore", invalid="ignore"):
            kinks = [v0 + (bound - y0) / s, v0 + (-bound - y0) / s]
        glob = ([-bV / aV] if aV != 0 else []) + [-bj / aj for aj, bj in zip(aH, bH) if aj != 0]
        pts = [v0, v1] + kinks + ([np.full_like(v0, g) for g in glob])
        if cost == "quadratic":
            # stationary points of every quadratic piece: k - (sum of the active slopes) / 2
            slopes = np.array([0.0, aV])[:, None]
            for aj in aH:
                slopes = (slopes[:, None] + np.array([0.0, -rho_H * aj])[None, :]).reshape(-1, 1)
            g = slopes.ravel()[None, :] + np.column_stack([0 * s[:, 0], rho_u * s[:, 0], -rho_u * s[:, 0]])[:, :, None]
            pts.append(d["k"][0] - g.reshape(len(s), -1) / 2)
        P = np.concatenate([np.broadcast_to(p, (len(v0), p.shape[1])) for p in pts], axis=1)
        P = np.where(np.isfinite(P), P, v0)
        cand = np.clip(P, v0, v1).ravel()
        f, delta = _objective_1d(cand, d, cost, pw=pw, bound=bound, rho=rho)
    i = int(np.argmin(f))
    return float(cand[i]), float(delta[i]), float(f[i])


# ---------------------------------------------------------------------------
# The controller
# ---------------------------------------------------------------------------
@dataclass
class _Solution:
    status: str            # "optimal", "infeasible", "time_limit", "error: ..."
    v: Optional[Array] = None
    delta: float = np.nan
    objective: float = np.nan
    solver_time: float = np.nan
    slack_u: Optional[Array] = None
    slack_H: Optional[Array] = None
    detail: str = ""
    nodes: Optional[int] = None
    screened: bool = False  # settled by the screening program, no MIP solved


class ClfCbfController:
    """The CLF-CBF controller of eq. (CLF_CBF) with the network constraint (CLF_CBF_b).

    Parameters
    ----------
    system
        The feedback-linearized system (its ``A``, ``B``, ``u_max`` and the domain box).
    net
        ``Phi_NN``, a ReLU network on the stacked input ``[z, v]``.
    eps
        The approximation error bound of eq. (approx_err), scalar or shape (m,);
        the network's output is bounded by ``u_max^eps = u_max - eps``.
    V
        The CLF: a :class:`Certificate` (e.g. :class:`QuadraticCLF`), an object
        with ``__call__`` and ``grad``, or a pair ``(V, grad_V)``.
    H
        The CBF (same forms), a list of them (one condition (CLF_CBF_d) each), or None.
    k
        The nominal law ``k(z) -> v`` (eq. QP_cost); optional for the linear cost.
    cost
        ``"linear"`` (eq. LP_cost, Lcost, a MILP) or ``"quadratic"`` (eq. QP_cost, Qcost, a MIQP).
    beta, kappa
        The CLF decay rate and the CBF class-K gain (Table 1: 0.001 and 4).
    backend
        ``"exact"`` (one or two inputs: the linear pieces of ``Phi_NN(z, .)``
        enumerated and each solved in closed form, :func:`solve_exact_1d` and
        :func:`flnotes.pieces.solve_exact_2d`), ``"cvxpy"``, or a persistent solver through
        :mod:`flnotes.solvers` (``"highs"`` for the MILP; ``"scip"``, ``"gurobi"``
        for both; ``"daqp"`` is accepted, but on these programs it was measured
        slower than SCIP, see ``make bench``). ``"auto"``
        (default) takes ``"exact"`` for one or two inputs (the fastest exact
        method, measured) and otherwise the persistent SCIP model for both
        costs (on the MSD programs SCIP was faster than HiGHS and never wrong;
        HiGHS returned a sub-optimal point as optimal at a few states, see
        :class:`flnotes.solvers.HighsSolver`).
    solver
        For ``backend="cvxpy"``: the cvxpy solver name (default SCIP for both costs). SCIP takes the program's QP
        form through :class:`flnotes.solvers.cvxpy_bridge.ScipQP` (the solver layer's SCIP model, not cvxpy's conic
        interface, which was slow and failed near the domain edge); ``"HIGHS"`` was the Lcost default until it
        labelled optimal points of cost -166.2 and -1029.7 on MSD states where the optimum is -667.5 and -1434.7.
    v_lo, v_hi
        Box on ``v``, inside the system's domain box (where ``eps`` holds; a wider box is refused); default that
        domain box.
    penalty
        ``(rho_u, rho_H)``: weights of the slacks of the softened program used
        as the fallback (see the module docstring).
    screening
        Persistent back-ends only (default True): first solve the program
        without the network constraint, a small LP (Lcost) or QP (Qcost) in
        ``(v, delta)``. Its feasible set contains the program's, so if its
        optimum ``v*`` satisfies ``|Phi_NN(z, v*)| <= u_max^eps`` it is the
        program's optimum, and if it is infeasible so is the program; only
        otherwise does the branch and bound run. Exact, and it skips the MIP
        wherever the input bound is not active.
    time_limit
        Seconds per solve (None: no limit).
    gap
        Optimality gap ``|obj - bound| / max(1, |obj|)`` at which branch and
        bound stops (persistent backends; default 1e-6).
    solver_options
        Options for :func:`flnotes.solvers.make_solver` (e.g. ``params`` of the
        back-end); the HiGHS default switches off symmetry detection and the
        feasibility-jump heuristic, which only cost time on these small programs.
    name
        Label for plots and tables; default ``"Lcost"`` or ``"Qcost"``.

    Notes
    -----
    Call ``ctrl(z)`` for ``v`` alone, or ``ctrl.step(z, t)`` for a
    :class:`flnotes.StepResult` with the status, the wall-clock time of the
    whole step (bounds, update and solve) and ``info`` (objective, ``delta``,
    ``Phi_NN(z, v)``, number of binaries, the solver's own time, slacks).
    ``ctrl.history`` keeps every step since :meth:`reset`.
    """

    def __init__(self, system: FLSystem, net: ReLUNet, eps: Union[float, Array], V: Any, H: Any = None,
                 k: Optional[Callable[[Array], Array]] = None, cost: str = "linear", beta: float = 0.001,
                 kappa: float = 4.0, backend: str = "auto", solver: Optional[str] = None,
                 v_lo: Optional[Array] = None, v_hi: Optional[Array] = None,
                 penalty: tuple[float, float] = (1e6, 1e4), screening: bool = True,
                 time_limit: Optional[float] = None, gap: float = 1e-6, solver_options: Optional[dict] = None,
                 name: Optional[str] = None):
        self._kwargs = dict(system=system, net=net, eps=eps, V=V, H=H, k=k, cost=cost, beta=beta, kappa=kappa,
                            backend=backend, solver=solver, v_lo=v_lo, v_hi=v_hi, penalty=penalty,
                            screening=screening, time_limit=time_limit, gap=gap, solver_options=solver_options,
                            name=name)
        if not isinstance(system, FLSystem):
            raise TypeError(f"system must be a flnotes.FLSystem (e.g. fl.msd()), got {type(system).__name__}")
        if not isinstance(net, ReLUNet):
            raise TypeError(f"net must be a flnotes.ReLUNet (e.g. fl.paper_net('MSD')[0]), got {type(net).__name__}")
        cost = {"lcost": "linear", "qcost": "quadratic"}.get(str(cost).lower(), str(cost).lower())
        if cost not in ("linear", "quadratic"):
            raise ValueError(f"cost must be 'linear' (eq. LP_cost) or 'quadratic' (eq. QP_cost), got {cost!r}")
        if cost == "quadratic" and k is None:
            raise ValueError("the quadratic cost ||v - k(z)||^2 needs the nominal law k: pass k=lambda z: -K @ z")
        if net.n_in != system.n_in or net.n_out != system.m:
            raise ValueError(f"net must map [z, v] ({system.n_in} inputs) to u ({system.m} outputs); "
                             f"it has n_in = {net.n_in}, n_out = {net.n_out}")
        self.system, self.net, self.cost = system, net, cost
        n_z, m = system.n_z, system.m
        self.eps = as_vector(eps, m, "eps")
        self.u_eps = system.u_max - self.eps
        if np.any(self.eps < 0) or np.any(self.u_eps <= 0):
            raise ValueError(f"need 0 <= eps < u_max, got eps = {self.eps}, u_max = {system.u_max}: "
                             f"the network's output bound u_max - eps must stay positive")
        self.V = as_certificate(V, "V")
        self.H = _cbf_list(H)
        self.k = k
        self.beta = check_number(beta, "beta", "the CLF's decay rate", strict=True)
        self.kappa = check_number(kappa, "kappa", "the CBF's class-K gain", strict=True)
        self.v_lo, self.v_hi = box_in_domain(system.lo[n_z:] if v_lo is None else v_lo,
                                             system.hi[n_z:] if v_hi is None else v_hi,
                                             system.lo[n_z:], system.hi[n_z:], what="the v-box")
        pen = as_floats(penalty, "penalty")
        if pen.shape != (2,) or not all(np.isfinite(w) and w > 0 for w in pen):
            raise ValueError(f"penalty = (rho_u, rho_H) must be two positive finite weights (a zero or negative weight "
                             f"makes a slack free in the softened program), got {penalty!r}")
        self.penalty = (float(pen[0]), float(pen[1]))
        self.time_limit = check_number(time_limit, "time_limit", "seconds per step", strict=True, none=True)
        self.gap = check_number(gap, "gap", "the relative optimality gap")
        if self.gap >= 1:
            raise ValueError(f"gap must be a relative optimality gap in [0, 1) (e.g. 1e-6), got {gap!r}")
        self.screening = check_bool(screening, "screening", "solve the program without the network constraint first")
        self.name = name or ("Lcost" if cost == "linear" else "Qcost")
        if backend not in CLF_CBF_BACKENDS:
            raise ValueError(f"backend must be one of {CLF_CBF_BACKENDS}, got {backend!r}")
        if backend == "auto":
            backend = "exact" if m <= 2 else "scip"
        self.backend = backend
        if solver_options is not None and not isinstance(solver_options, dict):
            raise ValueError(f"solver_options must be a dict of the back-end's options, got {solver_options!r}")
        self.solver_options = dict(solver_options or {})
        if backend == "highs" and isinstance(self.solver_options.get("params", {}), dict):
            # measured on the MSD programs: these two HiGHS features cost more than they save on
            # programs with about ten free binaries (a given params entry wins)
            self.solver_options["params"] = dict(dict(mip_detect_symmetry=False,
                                                      mip_heuristic_run_feasibility_jump=False),
                                                 **self.solver_options.get("params", {}))
        if backend == "highs" and cost == "quadratic":
            raise ValueError("HiGHS has no mixed-integer QP solver: for cost='quadratic' (Qcost) use "
                             "backend='scip', 'exact' (single input) or 'cvxpy'")
        if backend == "exact" and m > 2:
            raise ValueError(f"backend='exact' lists the linear pieces of Phi_NN(z, .) over v in a line (m = 1) or "
                             f"a plane (m = 2); this system has m = {m} inputs: use backend='scip', 'highs' or "
                             f"'cvxpy'")
        if solver_options and backend in ("exact", "cvxpy"):
            raise ValueError(f"solver_options set a persistent back-end ('highs', 'scip', 'gurobi', 'daqp'); "
                             f"backend {backend!r} does not read them: choose one of those or leave solver_options "
                             f"unset")
        if backend not in ("exact", "cvxpy"):
            try:  # now, not at the first program
                check_options(backend, self.solver_options)
            except ValueError as exc:
                raise ValueError(f"solver_options: {exc}") from None
        if backend == "exact":
            self._impl = _ExactBackend(self) if m == 1 else _ExactPiecesBackend(self)
        elif backend == "cvxpy":
            self._impl = _CvxpyBackend(self, solver)
        else:
            self._impl = _MiqpBackend(self, backend)
        self.history: list[StepResult] = []

    # ------------------------------------------------------------- the data
    @property
    def p(self) -> int:
        """Number of CBF conditions."""
        return len(self.H)

    def program_data(self, z: Array) -> dict:
        """The ``z``-dependent coefficients of eq. (CLF_CBF), all affine in ``v``.

        ``a_V^T v + b_V <= delta`` is (CLF_CBF_c) with ``a_V = B^T grad V(z)``,
        ``b_V = grad V(z)^T A z + beta V(z)``; ``a_H v + b_H >= 0`` is
        (CLF_CBF_d) with rows ``B^T grad H_j(z)`` and ``grad H_j(z)^T A z +
        kappa H_j(z)``; the linear cost is ``a_V^T v + J_c`` with
        ``J_c = grad V(z)^T A z``.
        """
        A, B = self.system.A, self.system.B
        Az = A @ z
        gV, Vz = _certificate_at(self.V, z, "V")
        d = dict(V=Vz, aV=B.T @ gV, Jc=float(gV @ Az), bV=float(gV @ Az + self.beta * Vz))
        if self.H:
            at = [_certificate_at(h, z, "H" if len(self.H) == 1 else f"H[{j}]") for j, h in enumerate(self.H)]
            gH, Hz = np.array([g for g, _ in at]), np.array([v for _, v in at])
        else:
            gH, Hz = np.zeros((0, len(z))), np.zeros(0)
        d.update(H=Hz, aH=gH @ B, bH=gH @ Az + self.kappa * Hz)
        d["k"] = (as_vector(self.k(z), self.system.m, "k(z)") if self.k is not None
                  else np.zeros(self.system.m))
        return d

    def node_bounds(self, z: Array) -> NodeBounds:
        """FBBT bounds with ``z`` fixed and ``v`` in its box: most neurons become stable."""
        return fbbt(self.net, np.concatenate([z, self.v_lo]), np.concatenate([z, self.v_hi]))

    # ------------------------------------------------------------ stepping
    def reset(self) -> None:
        """Forget the history (called by :func:`flnotes.simulate` at the start of a run)."""
        self.history = []
        if hasattr(self._impl, "reset"):
            self._impl.reset()

    def __call__(self, z: Array) -> Array:
        """``v*(z)`` of eq. (CLF_CBF) (or the fallback); statistics in ``self.history[-1]``."""
        return self.step(z, 0.0).v

    def step(self, z: Array, t: float = 0.0, reference=None) -> StepResult:
        """Solve eq. (CLF_CBF) at ``z``; see the class docstring for the result.

        ``status`` is one of :data:`flnotes.STATUSES`: ``"optimal"``,
        ``"time_limit"`` (the solver's incumbent is applied), ``"infeasible"``
        or ``"error"`` (``message`` says what failed); in the last two cases
        ``fallback`` is True and ``info["fallback_rule"]`` says which rule gave
        ``v``: ``"softened program"`` or ``"k(z) clipped to the v box"``.
        With ``backend="cvxpy"`` and one or two inputs, the solver's answer is
        checked against the exact method; where they differ the exact optimum
        is returned and ``message`` says what the solver had claimed.
        A solver's point is checked with the network's forward pass: one that
        exceeds ``u_max^eps`` (beyond round-off) is an error, never applied as a
        solution. ``input_admissible`` says whether the applied ``v``
        satisfies ``|Phi_NN(z, v)| <= u_max^eps``: on the softened program's
        fallback the input bound carries the largest penalty ``rho_u`` (given
        up last, an exact penalty once ``rho_u`` exceeds its multiplier), and
        this flag records whether it was given up.

        Raises ``ValueError`` when ``z`` lies outside the network's domain box
        (beyond :data:`flnotes.solvers.BOX_TOL`; closer, it is projected onto the
        box), as :class:`flnotes.MPC` does: the error bound eps, hence
        ``|u| <= u_max``, is only guaranteed inside it. The step runs with one
        BLAS thread (:func:`flnotes.config.one_blas_thread`).
        """
        check_number(t, "t", "the time of the step in seconds (unused: the program depends on z only)", low=-np.inf)
        with one_blas_thread():
            return self._solve_step(z)

    def _solve_step(self, z: Array) -> StepResult:
        t0, c0 = time.perf_counter(), time.thread_time()
        z = as_state(z, self.system.n_z, "z")
        self.system.check_domain(z, what="the measured state z")
        z = project_to_box(z, self.system.lo[: self.system.n_z], self.system.hi[: self.system.n_z], "z")
        d = self.program_data(z)
        try:
            sol = self._impl.solve(z, d, soft=False)
        except (ValueError, TypeError, ImportError):  # a programming error stops the run with its message
            raise
        except Exception as exc:  # a solver failure is a result: reported, then the fallback
            sol = _Solution(status=f"error: {type(exc).__name__}: {exc}")
        if sol.v is not None and sol.status in ("optimal", "time_limit") and not self._admissible(z, sol.v):
            # never a point that breaks the network bound labelled as a solution
            ex = float(np.max(np.abs(self.net(np.concatenate([z, sol.v]))) - self.u_eps))
            sol = _Solution(status="error: the solver's point exceeds u_max^eps by " f"{ex:.1e} (forward pass)",
                            detail=sol.detail)
        status, fallback, rule, first = sol.status, False, None, sol
        if sol.v is None or sol.status == "infeasible":
            fallback, rule = True, "softened program"
            try:
                sol = self._impl.solve(z, d, soft=True)
            except (ValueError, TypeError, ImportError):
                raise
            except Exception as exc:
                sol = _Solution(status=f"error: {type(exc).__name__}: {exc}")
            if sol.v is None:
                rule = "k(z) clipped to the v box"
                sol = _Solution(status=sol.status, v=np.clip(d["k"], self.v_lo, self.v_hi), detail=sol.detail)
        v = _onto_box(np.asarray(sol.v, float).reshape(self.system.m), self.v_lo, self.v_hi)
        info = dict(delta=sol.delta, phi_nn=self.net(np.concatenate([z, v])), V=d["V"], H=d["H"],
                    solver_time=sol.solver_time, slack_u=sol.slack_u, slack_H=sol.slack_H,
                    z_in_domain=bool(self.system.in_domain(z)[0]))
        if fallback:
            info.update(fallback_rule=rule, fallback_detail=sol.detail)
        info["cpu_time"] = time.thread_time() - c0
        message = first.detail
        if status.startswith("error"):  # one set of status words (flnotes.STATUSES); the details go to the message
            status, message = "error", (status[len("error"):].lstrip(": ") + (f" ({first.detail})" if first.detail else ""))
        res = StepResult(v=v, status=status, objective=sol.objective, nodes=int(sol.nodes or 0),
                         solve_time=time.perf_counter() - t0, fallback=fallback,
                         input_admissible=self._admissible(z, v), screened=first.screened, backend=self.backend,
                         message=message, n_binaries=int(getattr(self._impl, "n_binaries", 0) or 0), info=info)
        self.history.append(res)
        return res

    def _admissible(self, z: Array, v: Array) -> bool:
        """``|Phi_NN(z, v)| <= u_max^eps`` by the forward pass, to the round-off :data:`flnotes.solvers.BOUND_TOL`."""
        return bool(np.all(np.abs(self.net(np.concatenate([z, np.asarray(v, float).reshape(-1)])))
                           <= self.u_eps + BOUND_TOL))

    def describe(self) -> str:
        """A few lines on the program this controller solves and how it is held in memory."""
        lines = [repr(self), f"  v in [{self.v_lo}, {self.v_hi}], |Phi_NN(z, v)| <= u_max^eps = {self.u_eps}"]
        impl = self._impl
        if isinstance(impl, _CvxpyBackend):
            pr = impl.problem
            nv = sum(int(np.prod(x.shape)) for x in pr.variables())
            nb = sum(int(np.prod(x.shape)) for x in pr.variables() if x.attributes.get("boolean"))
            lines.append(f"  cvxpy problem built once: {nv} scalar variables ({nb} binaries), "
                         f"{len(pr.constraints)} constraint blocks, {len(pr.parameters())} parameters "
                         f"({', '.join(sorted(p.name() for p in pr.parameters()))}); DPP: {pr.is_dpp()}; "
                         f"solver {impl.solver}")
        elif isinstance(impl, _MiqpBackend):
            P = impl.problem
            lines.append(f"  persistent {impl.backend} model: {P.n} variables ({int(P.integrality.sum())} binaries, "
                         f"those of stable neurons fixed each step), {P.m} rows; updated in place each step")
            if self.screening:
                lines.append("  screening: the program without the network constraint is solved first (HiGHS); "
                             "the MIP runs only when its optimum violates |Phi_NN| <= u_max^eps")
        else:
            lines.append("  no model: the pieces of Phi_NN(z, .) are listed at each z and the cost minimized per interval")
        return "\n".join(lines)

    def with_backend(self, backend: str, **changes) -> "ClfCbfController":
        """The same controller (same program) with another backend or other settings."""
        kw = dict(self._kwargs, backend=backend, **changes)
        if backend != self._kwargs["backend"] and "solver_options" not in changes:
            kw["solver_options"] = None
        return ClfCbfController(**kw)

    def stats(self) -> dict:
        """Counts and solve times (ms) over :attr:`history`."""
        st = np.array([r.solve_time for r in self.history]) * 1e3
        if not len(st):
            return dict(steps=0)
        return dict(steps=len(st), backend=self.backend,
                    non_optimal=int(sum(r.status != "optimal" for r in self.history)),
                    fallback=int(sum(r.fallback for r in self.history)),
                    ms_min=float(st.min()), ms_median=float(np.median(st)), ms_max=float(st.max()),
                    ms_mean=float(st.mean()))

    def __repr__(self) -> str:
        return (f"ClfCbfController({self.name}: cost={self.cost!r}, backend={self.backend!r}, "
                f"eps={self.eps.tolist()}, beta={self.beta}, kappa={self.kappa}, {self.p} CBF)")


# ---------------------------------------------------------------------------
# Backends
# ---------------------------------------------------------------------------
class _ExactBackend:
    """Single input: list the pieces of Phi_NN(z, .) and minimize in closed form."""

    n_binaries = 0

    def __init__(self, c: ClfCbfController):
        self.c = c

    def solve(self, z: Array, d: dict, soft: bool) -> _Solution:
        c = self.c
        t0 = time.perf_counter()
        pw = network_pieces_1d(c.net, z, c.v_lo[0], c.v_hi[0])
        out = solve_exact_1d(pw, d, c.cost, float(c.u_eps[0]), soft=soft, rho=c.penalty)
        dt = time.perf_counter() - t0
        if out is None:
            return _Solution(status="infeasible", solver_time=dt,
                             detail=f"proven infeasible: no v in [v_lo, v_hi] meets the constraints on any of the "
                                    f"{pw.n_pieces} linear pieces of Phi_NN(z, .)")
        v, delta, obj = out
        sol = _Solution(status="optimal", v=np.array([v]), delta=delta, objective=obj, solver_time=dt,
                        detail=f"proven optimal: the closed-form minimum over all {pw.n_pieces} linear pieces of "
                               f"Phi_NN(z, .) on [v_lo, v_hi]")
        if soft:
            sol.slack_u = np.maximum(0.0, np.abs(pw._at(np.array([v]))) - c.u_eps)
            sol.slack_H = np.maximum(0.0, -(d["aH"][:, 0] * v + d["bH"]))
        return sol


#: cvxpy status -> step status. Only "optimal" is a proof; an inaccurate answer is a point without proof
#: ("time_limit": applied only if it passes the forward-pass check) or an error.
_CVXPY_STATUS = {"optimal": "optimal", "optimal_inaccurate": "time_limit", "infeasible": "infeasible",
                 "infeasible_inaccurate": "error: infeasible_inaccurate", "user_limit": "time_limit",
                 "unbounded": "error: unbounded", "unbounded_inaccurate": "error: unbounded_inaccurate",
                 "infeasible_or_unbounded": "infeasible"}


class _ExactPiecesBackend:
    """Two inputs: list the linear regions of ``Phi_NN(z, .)`` and minimize on each in closed form.

    The interface of the controller's back-ends: ``solve(z, d, soft)`` returns
    the controller's solution record (status, ``v``, ``delta``, objective,
    time, slacks), exactly like the single-input ``"exact"`` back-end of
    :class:`flnotes.ClfCbfController`.
    """

    n_binaries = 0

    def __init__(self, c: Any):
        if c.system.m != 2:
            raise ValueError(f"the exact region method works in the plane of two inputs; this system has "
                             f"m = {c.system.m}: use backend='exact' (m = 1) or a MILP/MIQP backend")
        self.c = c

    def solve(self, z: Array, d: dict, soft: bool):
        c = self.c
        t0 = time.perf_counter()
        st: dict = {}
        out = solve_exact_2d(c.net, z, d, c.cost, c.u_eps, c.v_lo, c.v_hi, soft=soft, rho=c.penalty, stats=st)
        dt = time.perf_counter() - t0
        what = ("screening: the optimum without the network constraint satisfies it" if st["screened"] else
                f"{st['regions']} regions solved, {st['nodes']} partial regions visited")
        if out is None:
            return _Solution(status="infeasible", solver_time=dt, detail=f"{what}; empty feasible set")
        v, delta, obj = out
        sol = _Solution(status="optimal", v=np.asarray(v, float), delta=delta, objective=obj, solver_time=dt,
                        detail=what, screened=st["screened"], nodes=st["nodes"])
        if soft:
            sol.slack_u = np.maximum(0.0, np.abs(c.net(np.concatenate([z, v]))) - c.u_eps)
            sol.slack_H = np.maximum(0.0, -(d["aH"] @ v + d["bH"]))
        else:
            sol.slack_u, sol.slack_H = np.zeros(c.system.m), np.zeros(c.p)
        return sol


#: Largest violation of the program's rows (and the binaries' integrality) of a point that cvxpy's solver returned
#: under a time limit (status ``user_limit`` or ``optimal_inaccurate``) for the ``"cvxpy"`` back-end to keep it: HiGHS
#: stopped at 1 ms returned ``v = 0`` with every slack 0 where the CBF row needs -1.2 of slack.
LIMIT_POINT_TOL = 1e-6

#: How far outside the ``v``-box a solver's point may lie and still be applied on its face (:func:`_onto_box`).
V_BOX_TOL = 1e-6


def _onto_box(v: Array, v_lo: Array, v_hi: Array) -> Array:
    """``v`` on the face of the box ``[v_lo, v_hi]`` when round-off or a solver's feasibility tolerance left it at
    most :data:`V_BOX_TOL` outside (e.g. 9e-10 from SCIP, 1.8e-15 from the exact region method); farther out it is
    returned as it is (and the checks that follow see it)."""
    out = np.maximum(v - v_hi, v_lo - v)
    return np.clip(v, v_lo, v_hi) if np.all(out <= V_BOX_TOL) else v


#: How far inside every row a solver's point must lie for the ``"cvxpy"`` back-end to call the exact method wrong when
#: that method finds the program infeasible: at states on the edge of feasibility SCIP returned points 2.4e-13 over
#: the network bound (within the forward pass's round-off) where the exact method, with no tolerance, finds none;
#: the step then takes the exact method's answer and says how close the solver's point came.
EDGE_MARGIN = 1e-9

#: Relative difference (``/ max(1, |J|)``) within which the ``"cvxpy"`` back-end's optimum counts as the exact
#: method's (:meth:`_CvxpyBackend._checked`): the suite's tolerance for a reference.
EXACT_CHECK_TOL = 1e-6


class _CvxpyBackend:
    """The teaching form: cvxpy with Parameters, built once (DPP), re-solved each step; with one or two inputs every
    answer is checked against the exact method (:meth:`_checked`)."""

    def __init__(self, c: ClfCbfController, solver: Optional[str] = None):
        import cvxpy as cp

        self.c = c
        sysm, net = c.system, c.net
        n_z, m, p = sysm.n_z, sysm.m, c.p
        from .encoding import encode

        self.z = cp.Parameter(n_z, name="z")
        self.aV = cp.Parameter(m, name="a_V")
        self.bV = cp.Parameter(name="b_V")
        self.Jc = cp.Parameter(name="J_c")
        self.kz = cp.Parameter(m, name="k_z")
        self.L = [cp.Parameter(n, name=f"L{i + 1}") for i, n in enumerate(net.widths)]
        self.U = [cp.Parameter(n, name=f"U{i + 1}") for i, n in enumerate(net.widths)]
        self.cap_u = cp.Parameter(m, nonneg=True, name="cap_u")
        self.u_in = cp.Parameter(m, nonneg=True, name="u_max_eps")  # tightened when a point exceeds it
        self.v = cp.Variable(m, name="v")
        self.delta = cp.Variable(nonneg=True, name="delta")
        self.s_u = cp.Variable(m, nonneg=True, name="s_u")
        self.enc = encode(net, cp.hstack([self.z, self.v]), L=self.L, U=self.U)
        y = self.enc.output
        cons = list(self.enc.constraints) + [
            y <= self.u_in + self.s_u, -y <= self.u_in + self.s_u, self.s_u <= self.cap_u,   # (CLF_CBF_b)
            self.v >= c.v_lo, self.v <= c.v_hi,
            self.aV @ self.v + self.bV <= self.delta,                                  # (CLF_CBF_c)
        ]
        obj = self.delta + c.penalty[0] * cp.sum(self.s_u)
        if p:
            self.aH = cp.Parameter((p, m), name="a_H")
            self.bH = cp.Parameter(p, name="b_H")
            self.cap_H = cp.Parameter(p, nonneg=True, name="cap_H")
            self.s_H = cp.Variable(p, nonneg=True, name="s_H")
            cons += [self.aH @ self.v + self.bH + self.s_H >= 0, self.s_H <= self.cap_H]  # (CLF_CBF_d)
            obj = obj + c.penalty[1] * cp.sum(self.s_H)
        J = self.aV @ self.v + self.Jc if c.cost == "linear" else cp.sum_squares(self.v - self.kz)
        self.problem = cp.Problem(cp.Minimize(J + obj), cons)
        if not self.problem.is_dpp():
            raise RuntimeError("the CLF-CBF program is not DPP: cvxpy would recompile it each step")
        self.solver = solver or "SCIP"
        # SCIP takes the program's QP form through the solver layer (cvxpy's own SCIP interface hands the quadratic
        # cost to SCIP as a second-order cone: slow and failing near the domain edge, see the bridge's docstring)
        self._bridge = None
        if str(self.solver).upper() == "SCIP":
            from .solvers.cvxpy_bridge import ScipQP

            self.solver, self._bridge = "SCIP", ScipQP()
        self.n_binaries = self.enc.n_binaries
        self.big = 1e4
        self.margin = 0.0
        #: The exact method of one or two inputs that checks every answer of the program (None for more inputs).
        self.exact = (_ExactBackend(c) if m == 1 else _ExactPiecesBackend(c)) if m <= 2 else None

    def _opts(self) -> dict:
        tl = self.c.time_limit
        if self.solver == "HIGHS":
            # the settings measured best in flnotes.solvers.HighsSolver (presolve on, tolerances 1e-8; 1e-9 declared
            # feasible programs infeasible); with one or two inputs its answer is checked by the exact method
            o = dict(mip_rel_gap=1e-9, mip_abs_gap=1e-10, mip_feasibility_tolerance=1e-8,
                     primal_feasibility_tolerance=1e-8)
            if tl is not None:
                o["time_limit"] = float(tl)
            return o
        if self.solver == "SCIP":  # through flnotes.solvers.cvxpy_bridge.ScipQP: feasibility tolerance 1e-9
            return dict(gap=1e-9, time_limit=None if tl is None else float(tl))
        return {}

    def solve(self, z: Array, d: dict, soft: bool) -> _Solution:
        import cvxpy as cp

        c = self.c
        b = c.node_bounds(z)
        self.z.value = z
        for P, a in zip(self.L, b.L):
            P.value = a
        for P, a in zip(self.U, b.U):
            P.value = a
        self.aV.value, self.bV.value, self.Jc.value, self.kz.value = d["aV"], d["bV"], d["Jc"], d["k"]
        self.cap_u.value = np.full(c.system.m, self.big if soft else 0.0)
        if c.p:
            self.aH.value, self.bH.value = d["aH"], d["bH"]
            self.cap_H.value = np.full(c.p, self.big if soft else 0.0)
        self.margin = 0.0  # per solve: a margin kept from another state would shrink this state's program
        failed = None
        for _ in range(6):
            self.u_in.value = c.u_eps - self.margin
            try:
                with _quiet_c_output(), warnings.catch_warnings():  # SoPlex prints its notices to the C streams;
                    # cvxpy warns of an inaccurate solution: its status (optimal_inaccurate) is kept in the detail
                    warnings.filterwarnings("ignore", message="Solution may be inaccurate", category=UserWarning)
                    self.problem.solve(solver=self._bridge or self.solver, **self._opts())
            except cp.error.SolverError as exc:
                if soft or self.exact is None:
                    raise cp.error.SolverError(f"{exc}{self._scip_status()}") from exc
                r = None if self._bridge is None else self._bridge.result
                failed = (f"cvxpy/{self.solver}: the time limit came before a point{self._scip_status()}"
                          if r is not None and r.status == "time_limit" else
                          f"cvxpy/{self.solver} failed ({exc}{self._scip_status()})")
                break
            if soft or self.v.value is None or self.problem.status not in ("optimal", "optimal_inaccurate"):
                break
            v = _onto_box(np.asarray(self.v.value, float), c.v_lo, c.v_hi)  # the v applied (see below)
            ex = float(np.max(np.abs(c.net(np.concatenate([z, v]))) - c.u_eps))
            if ex <= BOUND_TOL:
                break
            self.margin = next_margin(self.margin, ex, float(np.max(c.u_eps)))  # see _MiqpBackend.solve
        if failed is not None:
            sol = _Solution(status=f"error: {failed}", detail=failed)
        else:
            raw = self.problem.status
            st = _CVXPY_STATUS.get(raw, f"error: {raw}")
            stats = self.problem.solver_stats
            sol = _Solution(status=st, solver_time=float(stats.solve_time or np.nan),
                            detail=f"cvxpy/{self.solver}: {raw}{self._scip_status()}")
            bad = self._violation() if self.v.value is not None and st == "time_limit" else 0.0
            if bad > LIMIT_POINT_TOL:  # a point under a limit that is no point of the program is not applied
                sol.detail += f"; its point under the limit violates the program by {bad:.1e}: dropped"
            elif self.v.value is not None and st in ("optimal", "time_limit"):
                sol.v = _onto_box(np.array(self.v.value, float), c.v_lo, c.v_hi)  # the checks see the v applied
                sol.delta = float(self.delta.value)
                sol.objective = float(self.problem.value)
                # the slacks this v needs (a solver may leave a slack above the need where its penalty is below its
                # tolerance)
                sol.slack_u = np.maximum(0.0, np.abs(c.net(np.concatenate([z, sol.v]))) - c.u_eps)
                sol.slack_H = np.maximum(0.0, -(np.asarray(d["aH"]) @ sol.v + d["bH"])) if c.p else np.zeros(0)
        return sol if soft or self.exact is None else self._checked(z, d, sol)

    def _feasible(self, z: Array, d: dict, v: Array, margin: float = 0.0) -> bool:
        """``v`` solves the unsoftened program with ``margin`` to spare: in the box, the CBF rows
        ``a_H v + b_H >= margin`` and ``|Phi_NN(z, v)| <= u_max^eps - margin`` by the forward pass (the CLF row always
        holds with its ``delta``)."""
        v = np.asarray(v, float).reshape(-1)
        rows = np.all(np.asarray(d["aH"]) @ v + np.asarray(d["bH"]) >= margin) if self.c.p else True
        phi = np.abs(self.c.net(np.concatenate([z, v])))
        return bool(rows and np.all(v >= self.c.v_lo) and np.all(v <= self.c.v_hi)
                    and np.all(phi <= self.c.u_eps - margin))

    def _violation(self) -> float:
        """How far the variables' values break the program: its rows (cvxpy's ``violation``) and the binaries'
        integrality."""
        worst = max((float(np.max(c.violation(), initial=0.0)) for c in self.problem.constraints), default=0.0)
        for x in self.problem.variables():
            if x.attributes.get("boolean") and x.value is not None:
                worst = max(worst, float(np.max(np.abs(x.value - np.round(x.value)), initial=0.0)))
        return worst

    def _scip_status(self) -> str:
        """SCIP's own status of the last solve through the bridge (with SCIP's error lines, if it wrote any)."""
        r = None if self._bridge is None else self._bridge.result
        return "" if r is None else f"; SCIP status {r.message}"

    def _checked(self, z: Array, d: dict, sol: _Solution) -> _Solution:
        """The program's answer checked against the exact method of one or two inputs (:func:`solve_exact_1d`,
        :func:`flnotes.pieces.solve_exact_2d`), which lists every linear piece of ``Phi_NN(z, .)``.

        An answer that agrees (the same status; an optimum whose cost is within :data:`EXACT_CHECK_TOL` of the exact
        one) is returned with the check in its ``detail``. Otherwise the solver's answer is not a proof: the exact
        optimum is returned, and ``detail`` says what the solver had claimed (cvxpy's solvers keep their own
        tolerances, e.g. HiGHS labelled as optimal a point of cost -1462.4 where the exact optimum is -1768.1, and
        SCIP failed on states near the domain edge).
        """
        ex = self.exact.solve(z, d, soft=False)
        kind = "the exact 1-D method" if self.c.system.m == 1 else "the exact region method"
        if ex.status == "infeasible":
            if sol.status == "infeasible":
                sol.detail += f"; infeasible, confirmed by {kind}"
                return sol
            if sol.v is not None and self._feasible(z, d, sol.v, margin=EDGE_MARGIN):  # pragma: no cover - a bug
                raise RuntimeError(f"{kind} found no admissible v at z = {z} but {sol.detail} returned an admissible "
                                   f"point {sol.v}: report this state")
            ex.detail = f"infeasible, proven by {kind} ({ex.detail}); the solver's answer was not confirmed: {sol.detail}"
            return ex
        J = ex.objective
        if sol.status == "optimal" and sol.v is not None and sol.objective <= J + EXACT_CHECK_TOL * max(1.0, abs(J)):
            sol.detail += f"; equal to the optimum of {kind} ({J:.10g})"
            return sol
        ex.slack_u, ex.slack_H = np.zeros(self.c.system.m), np.zeros(self.c.p)
        # the message says first what was proven, then what the solver had answered
        if sol.v is None:
            ex.detail = f"the optimum of {kind} ({ex.detail}) is returned; the solver gave no point: {sol.detail}"
        else:
            ex.detail = (f"the optimum of {kind} ({ex.detail}) is returned; the solver's point, at cost "
                         f"{sol.objective:.10g}, is not the optimum: {sol.detail}")
        return ex


class _MiqpBackend:
    """A persistent solver model through :mod:`flnotes.solvers`, built once, updated in place each step.

    Variables ``w = [BigMForm's w (x = [z, v], ybar, yund, alpha, ..., y^K) | delta | s_u (m) | s_H (p)]``.
    Rows: eq. (MIP_general) from :func:`flnotes.bigm_form`, ``+-y^K - s_u <= u_max^eps``
    (CLF_CBF_b), ``a_V^T v - delta <= -b_V`` (CLF_CBF_c), ``-a_H v - s_H <= b_H`` (CLF_CBF_d).
    ``z`` enters through ``lb = ub``; the slacks are fixed to 0 except in the softened program.

    Each step the big-M coefficients are rewritten from FBBT bounds with ``z`` fixed, exactly as
    :meth:`flnotes.BigMForm.update` does (``-max(U, 0)`` and ``-min(L, 0)`` on ``alpha``, the
    bounds of ``ybar``, ``yund``, and ``alpha`` fixed for stable neurons, so they cost no
    branching), but written straight into the constraint matrix's data array at precomputed
    positions: the model's sparsity never changes.
    """

    def __init__(self, c: ClfCbfController, backend: str):
        from .encoding import bigm_form
        from .solvers import MIQP, make_solver

        self.c = c
        net, m, p = c.net, c.system.m, c.p
        n_z = c.system.n_z
        # the structure, with every big-M coefficient present (placeholder bounds -1 <= pre <= 1)
        ones = [np.ones(n) for n in net.widths]
        self.form = F = bigm_form(net, NodeBounds([-o for o in ones], ones, np.zeros(net.n_out), np.zeros(net.n_out)))
        nf = F.n
        self.i_delta = nf
        self.i_su = nf + 1 + np.arange(m)
        self.i_sH = nf + 1 + m + np.arange(p)
        self.i_z, self.i_v = F.x[:n_z], F.x[n_z:]
        n = nf + 1 + m + p
        pad = lambda M: sp.hstack([sp.csr_matrix(M), sp.csr_matrix((M.shape[0], n - nf))], format="csr")
        out_rows = sp.lil_matrix((2 * m, n))
        for i in range(m):
            out_rows[i, F.out[i]], out_rows[i, self.i_su[i]] = 1.0, -1.0
            out_rows[m + i, F.out[i]], out_rows[m + i, self.i_su[i]] = -1.0, -1.0
        dyn = sp.lil_matrix((1 + p, n))
        dyn[0, self.i_v] = 1.0          # placeholders: a_V and a_H change with z
        dyn[0, self.i_delta] = -1.0
        for j in range(p):
            dyn[1 + j, self.i_v] = 1.0
            dyn[1 + j, self.i_sH[j]] = -1.0
        A = sp.vstack([pad(F.A_eq), pad(F.A_ub), out_rows.tocsr(), dyn.tocsr()], format="csr")
        A.sort_indices()
        n_eq, n_ub = F.A_eq.shape[0], F.A_ub.shape[0]
        r_ub = n_eq + np.arange(n_ub)
        self.r_clf = n_eq + n_ub + 2 * m
        self.r_cbf = self.r_clf + 1 + np.arange(p)

        def pos(rows, cols):
            rows, cols = np.broadcast_arrays(np.asarray(rows), np.asarray(cols))
            out = np.empty(rows.shape, int)
            for idx, (r, col) in enumerate(zip(rows.ravel(), cols.ravel())):
                s0, s1 = A.indptr[r], A.indptr[r + 1]
                k = s0 + int(np.searchsorted(A.indices[s0:s1], col))
                if k >= s1 or A.indices[k] != col:
                    raise RuntimeError("internal: entry missing from the model's sparsity pattern")
                out.flat[idx] = k
            return out

        alpha = np.concatenate(F.alpha)
        self.rU = r_ub[np.concatenate(F.ub_rows_U)]
        self.rL = r_ub[np.concatenate(F.ub_rows_L)]
        self.pU, self.pL = pos(self.rU, alpha), pos(self.rL, alpha)
        self.p_clf = pos(np.full(m, self.r_clf), self.i_v)
        self.p_cbf = pos(np.repeat(self.r_cbf, m), np.tile(self.i_v, p)).reshape(p, m)
        self.i_alpha, self.i_ybar, self.i_yund = alpha, np.concatenate(F.ybar), np.concatenate(F.yund)
        self._A = A
        rl = np.concatenate([F.b_eq, np.full(n_ub + 2 * m + 1 + p, -np.inf)])
        self.ru = np.concatenate([F.b_eq, F.b_ub, np.tile(c.u_eps, 2), [0.0], np.zeros(p)])
        self.lb = np.concatenate([F.lb, [0.0], np.zeros(m + p)])
        self.ub = np.concatenate([F.ub, [np.inf], np.zeros(m + p)])
        self.lb[self.i_z], self.ub[self.i_z] = 0.0, 0.0
        self.lb[self.i_v], self.ub[self.i_v] = c.v_lo, c.v_hi
        integ = np.concatenate([F.integrality, np.zeros(1 + m + p, int)])
        self.cvec = np.zeros(n)
        self.cvec[self.i_delta] = 1.0
        self.cvec[self.i_su], self.cvec[self.i_sH] = c.penalty[0], c.penalty[1]
        Hq = None
        if c.cost == "quadratic":
            Hq = sp.csc_matrix((np.full(m, 2.0), (self.i_v, self.i_v)), shape=(n, n))
        self.problem = MIQP(Hq, self.cvec, 0.0, A, rl, self.ru, self.lb, self.ub, integ)
        self.r_out = n_eq + n_ub + np.arange(2 * m)   # +-y^K - s_u <= u_max^eps
        #: how much u_max^eps is tightened in the rows handed to the solver (tolerance policy of flnotes.solvers)
        self.margin = 0.0
        self.backend = backend
        self.solver = make_solver(self.problem, backend=backend, **c.solver_options)
        self.n_binaries = None
        # the screening program: eq. (CLF_CBF) without (CLF_CBF_b), in r = [v (m), delta]
        # (rows: the CLF row [a_V, -1] and the CBF rows [-a_H, 0], placeholders until screen() writes them)
        rows = sp.csr_matrix(np.vstack([np.r_[np.ones(m), -1.0], np.c_[np.ones((p, m)), np.zeros(p)]]))
        Hr = sp.diags(np.r_[np.full(m, 2.0), 0.0], format="csc") if c.cost == "quadratic" else None
        self._relaxed = make_solver(MIQP(Hr, np.r_[np.zeros(m), 1.0], 0.0, rows, np.full(1 + p, -np.inf),
                                         np.zeros(1 + p), np.r_[c.v_lo, 0.0], np.r_[c.v_hi, np.inf],
                                         np.zeros(m + 1, int)), "highs")

    def screen(self, z: Array, d: dict) -> Optional[_Solution]:
        """The screening step (see ``screening``): the exact answer, or None when the branch and bound must run."""
        c, m, p = self.c, self.c.system.m, self.c.p
        A = sp.csr_matrix(np.vstack([np.r_[d["aV"], -1.0], np.c_[-d["aH"], np.zeros(p)]]))
        lin = np.r_[d["aV"], 1.0] if c.cost == "linear" else np.r_[-2.0 * d["k"], 1.0]
        c0 = d["Jc"] if c.cost == "linear" else float(d["k"] @ d["k"])
        self._relaxed.update(c=lin, c0=c0, A=A, ru=np.r_[-d["bV"], d["bH"]])
        r = self._relaxed.solve()
        if r.status == "infeasible":     # the program's feasible set lies inside this empty one
            return _Solution(status="infeasible", solver_time=r.time, nodes=0, screened=True,
                             detail="screening: infeasible without the network constraint")
        if r.status != "optimal" or r.w is None:
            return None
        v = np.clip(r.w[:m], c.v_lo, c.v_hi)
        if not np.all(np.abs(c.net(np.concatenate([z, v]))) <= c.u_eps):
            return None
        self.n_binaries = 0
        return _Solution(status="optimal", v=v, delta=float(r.w[m]), objective=float(r.objective),
                         solver_time=r.time, slack_u=np.zeros(m), slack_H=np.zeros(p), nodes=0, screened=True,
                         detail="screening: the optimum without the network constraint satisfies it")

    def write(self, z: Array, d: dict, bounds: NodeBounds, soft: bool) -> dict:
        """The new numbers of the program at ``z`` (keyword arguments of ``Solver.update``)."""
        c = self.c
        L = np.concatenate([np.asarray(a, float) for a in bounds.L])
        U = np.concatenate([np.asarray(a, float) for a in bounds.U])
        Up, Lm = np.maximum(U, 0.0), np.minimum(L, 0.0)
        data = self._A.data.copy()
        data[self.pU], data[self.pL] = -Up, -Lm           # ybar - U alpha <= 0,  yund - L alpha <= -L
        data[self.p_clf] = d["aV"]                          # a_V^T v - delta <= -b_V
        data[self.p_cbf] = -d["aH"]                         # -a_H v - s_H <= b_H
        A = sp.csr_matrix((data, self._A.indices, self._A.indptr), shape=self._A.shape)
        ru, lb, ub = self.ru.copy(), self.lb.copy(), self.ub.copy()
        ru[self.rL] = -Lm
        ru[self.r_out] = np.tile(c.u_eps - self.margin, 2)
        ru[self.r_clf] = -d["bV"]
        ru[self.r_cbf] = d["bH"]
        ub[self.i_ybar], ub[self.i_yund] = Up, -Lm
        lb[self.i_alpha], ub[self.i_alpha] = np.where(L >= 0, 1.0, 0.0), np.where(U <= 0, 0.0, 1.0)
        lb[self.i_z], ub[self.i_z] = z, z
        cap = np.inf if soft else 0.0
        ub[self.i_su], ub[self.i_sH] = cap, cap
        cvec = self.cvec.copy()
        if c.cost == "linear":
            cvec[self.i_v], c0 = d["aV"], d["Jc"]
        else:
            cvec[self.i_v], c0 = -2.0 * d["k"], float(d["k"] @ d["k"])
        self.n_binaries = int(np.sum((L < 0) & (U > 0)))
        return dict(c=cvec, c0=c0, ru=ru, lb=lb, ub=ub, A=A)

    def solve(self, z: Array, d: dict, soft: bool) -> _Solution:
        c = self.c
        if c.screening and not soft:
            sol = self.screen(z, d)
            if sol is not None:
                return sol
        nb = c.node_bounds(z)
        self.margin = 0.0  # per solve: a margin kept from another state would shrink this state's program
        for _ in range(6):
            self.solver.update(**self.write(z, d, nb, soft))
            r = self.solver.solve(time_limit=c.time_limit, gap=c.gap)
            if soft or r.w is None or r.status not in ("optimal", "time_limit"):
                break
            ex = float(np.max(np.abs(c.net(np.concatenate([z, r.w[self.i_v]]))) - c.u_eps))
            if ex <= BOUND_TOL:
                break
            # the solver's tolerance let the point through above u_max^eps: tighten the rows, solve again
            self.margin = next_margin(self.margin, ex, float(np.max(c.u_eps)))
        st = r.status if r.status != "error" else f"error: {r.backend}: {r.message}"
        sol = _Solution(status=st, solver_time=r.time, detail=f"{r.backend}: {r.message}", nodes=r.nodes)
        if r.w is not None and r.status in ("optimal", "time_limit"):
            w = r.w
            sol.v, sol.delta, sol.objective = w[self.i_v].copy(), float(w[self.i_delta]), float(r.objective)
            sol.slack_u, sol.slack_H = w[self.i_su].copy(), w[self.i_sH].copy()
        return sol
