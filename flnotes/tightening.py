"""Tighter node bounds: LP-based bound tightening and the reachable boxes of an MPC horizon.

The big-M constants ``L^k_j``, ``U^k_j`` of eq. (MIP_general_c) decide how many
binaries a program needs (a neuron whose bounds do not straddle zero needs
none) and how weak its relaxation is. :func:`flnotes.fbbt` propagates a box
with interval arithmetic. Two levers give tighter, still valid, bounds:

* :func:`lp_bounds` (Grimstad & Andersson 2019, "relaxation-based" bound
  tightening): one LP relaxation of eq. (MIP_general) (binaries relaxed to
  ``[0, 1]``), and for every neuron in layer order the minimum and maximum
  of its pre-activation over that LP, each new bound written into the LP's
  big-M coefficients before the next neuron is processed. The LP contains
  every feasible point of the mixed-integer program, so ``[L, U]`` contains
  every feasible pre-activation. Each bound is the safe bound of the LP's
  duals (Neumaier & Shcherbina 2004), not the solver's optimum, so it holds
  whatever the solver's accuracy; an infeasible LP is believed only with a
  checked Farkas certificate. With ``out_bounds`` (``|y^K| <= u_max^eps`` of
  eq. (Phi_NN_ep)) the LP only contains inputs the controller can accept,
  which is where the bounds get much tighter.
* :func:`horizon_boxes`: with ``z(0)`` measured, the predicted states of the
  MPC (eq. MPC_form_miqp_c) can only reach a small box at each step; bounds
  computed on these boxes (``fbbt(net, lo, hi)`` with ``lo, hi`` of shape
  (N_p, n_in)) replace the bounds of the whole domain.

All bounds here are valid for the points a controller can select: intersecting
two valid bounds (:func:`intersect`) is valid too.
"""
from __future__ import annotations

import threading
import time
from typing import Optional, Sequence

import numpy as np

from ._checks import (as_floats, as_pair, as_state, as_vector, brief, check_bool, check_box, check_boxes,
                      check_count, check_int, check_number, one_number)
from .bounds import NodeBounds, _interval_affine, fbbt, interval_affine
from .network import ReLUNet, fingerprint

Array = np.ndarray

__all__ = ["EmptyBoxError", "lp_bounds", "horizon_boxes", "intersect", "propagate", "LPTightener", "ellipsoid_box"]


#: HiGHS's ``simplex_strategy`` of the LPs of :class:`LPTightener`: 4, the primal simplex (see its ``__init__``).
SIMPLEX_STRATEGY = 4


class DeadlineReached(RuntimeError):
    """LP tightening stopped at the caller's deadline (a controller's time limit); no bounds are returned."""


class EmptyBoxError(ValueError):
    """No admissible point exists (the LP relaxation or a reachable box is empty)."""


# ---------------------------------------------------------------------------
# Helpers on NodeBounds
# ---------------------------------------------------------------------------
def intersect(a: NodeBounds, b: NodeBounds, method: Optional[str] = None) -> NodeBounds:
    """Elementwise intersection of two valid bounds (valid, and at least as tight as either)."""
    for name, x in (("a", a), ("b", b)):
        if not isinstance(x, NodeBounds):
            raise TypeError(f"{name} must be a flnotes.NodeBounds (e.g. prior=fl.fbbt(net, lo, hi)), got "
                            f"{type(x).__name__}")
    if len(a.L) != len(b.L):
        raise ValueError(f"bounds have {len(a.L)} and {len(b.L)} hidden layers")
    if any(np.isnan(x).any() for x in (*a.L, *a.U, *b.L, *b.U, b.out_L, b.out_U)):
        raise ValueError(f"bounds ({b.method}) contain NaN: node bounds are numbers, L <= U")
    L = [np.maximum(x, y) for x, y in zip(a.L, b.L)]
    U = [np.minimum(x, y) for x, y in zip(a.U, b.U)]
    return NodeBounds(L, U, np.maximum(a.out_L, b.out_L), np.minimum(a.out_U, b.out_U),
                      method=method or f"{a.method}&{b.method}")


def propagate(net: ReLUNet, L: Sequence[Array], U: Sequence[Array], start: int = 0, outward: bool = True
              ) -> tuple[list[Array], list[Array], Array, Array]:
    """Interval propagation from layer ``start`` on: layers after it get ``max(their bounds, interval bounds)``.

    ``L[start]``, ``U[start]`` are kept; every later layer is intersected with
    the interval image of the previous one (what FBBT does from the input), rounded outward unless ``outward=False``
    (:func:`flnotes.bounds.interval_affine`).
    """
    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    if len(L) != net.K - 1 or len(U) != net.K - 1:
        raise ValueError(f"need one L and one U per hidden layer ({net.K - 1}), got {len(L)} and {len(U)}")
    L = [as_floats(x, f"L^{k + 1}").copy() for k, x in enumerate(L)]
    U = [as_floats(x, f"U^{k + 1}").copy() for k, x in enumerate(U)]
    for k, (a, b) in enumerate(zip(L, U)):
        if a.shape != b.shape or a.shape != L[0].shape[:-1] + (net.widths[k],) \
                or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))) or np.any(a > b):
            raise ValueError(f"L^{k + 1} <= U^{k + 1} must hold, finite, of shape ({net.widths[k]},) (or (T, "
                             f"{net.widths[k]}) in every layer), got shapes {a.shape} and {b.shape}")
    start = check_int(start, "start", 0, "the layer kept")
    if start >= net.K - 1:
        raise ValueError(f"start must be a hidden layer in 0..{net.K - 2}, got {start}")
    outward = check_bool(outward, "outward", "whether to widen the bounds by the rounding of their sums")
    return _propagate(net, L, U, start, outward)


def _propagate(net: ReLUNet, L: list, U: list, start: int, outward: bool) -> tuple[list[Array], list[Array], Array,
                                                                                   Array]:
    """:func:`propagate` on checked float arrays (the package's own calls; ``L``, ``U`` are changed in place)."""
    l, u = np.maximum(L[start], 0.0), np.maximum(U[start], 0.0)
    for k in range(start + 1, net.K - 1):
        Lk, Uk = _interval_affine(net.W[k], net.b[k], l, u, outward)
        L[k], U[k] = np.maximum(L[k], Lk), np.minimum(U[k], Uk)
        l, u = np.maximum(L[k], 0.0), np.maximum(U[k], 0.0)
    oL, oU = _interval_affine(net.W[-1], net.b[-1], l, u, outward)
    return L, U, oL, oU


# ---------------------------------------------------------------------------
# LP-based bound tightening
# ---------------------------------------------------------------------------
class LPTightener:
    """A persistent HiGHS LP of the relaxed eq. (MIP_general) for one network.

    Variables ``w = [x | y^1, alpha^1 | ... | y^{K-1}, alpha^{K-1}]`` with, per
    hidden neuron (pre-activation ``a = W_j y^{k-1} + b_j``),

        y >= 0,  y >= a,  y <= U alpha,  y <= a - L (1 - alpha),  0 <= alpha <= 1,

    which is eq. (MIP_general_b)-(MIP_general_c) with ``yund = y - a``
    eliminated and ``alpha`` relaxed (projected on ``(a, y)`` it is the
    triangle hull of the ReLU on ``[L, U]``). Optional output rows
    ``out_lo <= W^K y^{K-1} + b^K <= out_hi``. The input box and the big-M
    coefficients are changed in place; the LPs of one box are re-solved warm
    from the previous basis.

    The bounds of a box depend on that box (and ``prior``) only, never on the
    boxes tightened before: :meth:`tighten` first passes HiGHS the model as
    built again (:meth:`restart`). Left to carry over, the previous box's basis
    (a warm start into another optimal vertex of a degenerate LP) and the
    matrix layout (HiGHS drops an entry set to zero and appends it again when
    it comes back) changed the bounds in their last digits, hence the MPC's
    programs, and a closed loop's result depended on which loops had run
    before it in the same process.
    """

    def __init__(self, net: ReLUNet, out_bounds: Optional[tuple[Array, Array]] = None, tol: float = 1e-7):
        import highspy

        if not isinstance(net, ReLUNet):
            raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
        self.net, self.tol, self._hp = net, check_number(tol, "tol", "the relative margin added to every bound"), highspy
        n_in, widths = net.n_in, net.widths
        self.x = np.arange(n_in)
        self.y, self.alpha = [], []
        idx = n_in
        for n_k in widths:
            self.y.append(np.arange(idx, idx + n_k))
            idx += n_k
            self.alpha.append(np.arange(idx, idx + n_k))
            idx += n_k
        self.n = idx
        rows, cols, vals, rlo, rhi = [], [], [], [], []
        self.row_ge, self.row_U, self.row_L = [], [], []
        r = 0
        prev = self.x
        for k, (W, b) in enumerate(zip(net.W[:-1], net.b[:-1])):
            n_k = W.shape[0]
            yk, ak = self.y[k], self.alpha[k]
            ge, rU, rL = [], [], []
            for j in range(n_k):
                nzw = np.flatnonzero(W[j])
                # a - y <= -b   (y >= a)
                rows += [r] * (len(nzw) + 1)
                cols += prev[nzw].tolist() + [yk[j]]
                vals += W[j, nzw].tolist() + [-1.0]
                rlo.append(-np.inf)
                rhi.append(-b[j])
                ge.append(r)
                r += 1
                # y - U alpha <= 0
                rows += [r, r]
                cols += [yk[j], ak[j]]
                vals += [1.0, 0.0]
                rlo.append(-np.inf)
                rhi.append(0.0)
                rU.append(r)
                r += 1
                # y - a - L alpha <= -L   (y <= a - L (1 - alpha))
                rows += [r] * (len(nzw) + 2)
                cols += prev[nzw].tolist() + [yk[j], ak[j]]
                vals += (-W[j, nzw]).tolist() + [1.0, 0.0]
                rlo.append(-np.inf)
                rhi.append(b[j])
                rL.append(r)
                r += 1
            self.row_ge.append(np.array(ge))
            self.row_U.append(np.array(rU))
            self.row_L.append(np.array(rL))
            prev = yk
        self.row_out = None
        self.b_row_L = [np.asarray(b, float).copy() for b in net.b[:-1]]
        if out_bounds is not None:
            olo, ohi = check_out_bounds(out_bounds, net.n_out)
            W, b = net.W[-1], net.b[-1]
            ro = []
            for i in range(net.n_out):
                nzw = np.flatnonzero(W[i])
                rows += [r] * len(nzw)
                cols += prev[nzw].tolist()
                vals += W[i, nzw].tolist()
                rlo.append(olo[i] - b[i])
                rhi.append(ohi[i] - b[i])
                ro.append(r)
                r += 1
            self.row_out = np.array(ro)
        self.m = r
        import scipy.sparse as sp
        Ac = sp.csc_matrix((vals, (rows, cols)), shape=(r, self.n))
        Ac.sort_indices()
        # remember where the big-M entries sit (explicit zeros are kept by building with coo -> csc)
        inf = highspy.kHighsInf
        lp = highspy.HighsLp()
        lp.num_col_, lp.num_row_ = self.n, r
        lp.col_cost_ = np.zeros(self.n)
        lb, ub = np.full(self.n, -inf), np.full(self.n, inf)
        for k in range(len(widths)):
            lb[self.y[k]] = 0.0
            lb[self.alpha[k]], ub[self.alpha[k]] = 0.0, 1.0
        lp.col_lower_, lp.col_upper_ = lb, ub
        lp.row_lower_ = np.where(np.isfinite(rlo), rlo, -inf)
        lp.row_upper_ = np.where(np.isfinite(rhi), rhi, inf)
        lp.a_matrix_.format_ = highspy.MatrixFormat.kColwise
        lp.a_matrix_.start_, lp.a_matrix_.index_, lp.a_matrix_.value_ = Ac.indptr, Ac.indices, Ac.data
        lp.a_matrix_.num_col_, lp.a_matrix_.num_row_ = self.n, r
        h = highspy.Highs()
        h.setOptionValue("output_flag", False)
        h.setOptionValue("threads", 1)
        h.setOptionValue("presolve", "off")  # tiny LPs re-solved warm: presolve only costs time
        # Primal simplex: consecutive LPs differ in their cost (the next neuron), so the last optimal basis stays
        # primal feasible and the primal simplex goes on from it; the dual simplex (HiGHS's default) starts over
        # from a basis that is no longer dual feasible. Same optima to the LP's tolerances (covered by ``tol``);
        # measured on the LPs of hard cold MSD states: 1.3 times fewer seconds, 1.13 times per step.
        h.setOptionValue("simplex_strategy", SIMPLEX_STRATEGY)
        h.passModel(lp)
        self.h, self._lp = h, lp  # the model as built, passed again by restart()
        self._lb, self._ub = lb.copy(), ub.copy()
        # the model's data, kept beside HiGHS's copy for the safe bounds (see _safe_min)
        self._A0 = Ac.toarray()
        self._rl0 = np.where(np.isfinite(rlo), np.asarray(rlo, float), -np.inf)
        self._ru0 = np.where(np.isfinite(rhi), np.asarray(rhi, float), np.inf)
        self._A, self._rl, self._ru = self._A0.copy(), self._rl0.copy(), self._ru0.copy()
        self._absA = np.abs(self._A)
        self._cost = np.zeros(self.n)
        self._all = np.arange(self.n, dtype=np.int32)
        self.n_lp = 0
        self._box_set, self._known = False, [np.zeros(n_k, bool) for n_k in widths]  # what preactivation_range needs
        self.lock = threading.Lock()  # one tighten() at a time: HiGHS models are not thread-safe

    # -- model changes -------------------------------------------------------------
    def restart(self) -> None:
        """Back to the model as built (its matrix layout, no basis): what follows depends on nothing done before."""
        self.h.passModel(self._lp)
        self._box_set = False
        for known in self._known:
            known[:] = False
        self._lb[:], self._ub[:] = self._lp.col_lower_, self._lp.col_upper_
        self._A[:], self._rl[:], self._ru[:] = self._A0, self._rl0, self._ru0
        np.abs(self._A, out=self._absA)

    def set_box(self, lo: Array, hi: Array) -> None:
        """Bounds of the input ``x``: the box ``[lo, hi]``, finite, (n_in,) each (a number is taken for every
        input), ``lo <= hi``; anything else is a ``ValueError`` naming the argument.

        Node bounds that hold on a box hold on every box inside it, not on a larger one: a box that leaves the one
        set before makes the node bounds set for that one forgotten (:meth:`preactivation_range` asks for them again;
        the LP keeps its entries until they are set). Bounds set before any box are the caller's for the first box."""
        lo, hi = check_box(lo, hi, self.net.n_in)
        if self._box_set and not (np.all(lo >= self._lb[self.x]) and np.all(hi <= self._ub[self.x])):
            for known in self._known:
                known[:] = False
        self._set_box(lo, hi)

    def _set_box(self, lo: Array, hi: Array) -> None:
        """:meth:`set_box` without its checks (the callers here pass checked boxes)."""
        self._lb[self.x], self._ub[self.x] = lo, hi
        self._box_set = True
        self.h.changeColsBounds(len(self.x), self.x.astype(np.int32), np.asarray(lo, float), np.asarray(hi, float))

    def _layer_index(self, k, hidden: bool = True) -> int:
        """``k`` as the index (0-based) of a hidden layer, or of any layer (the output layer too) when not
        ``hidden``; else ``ValueError`` naming it."""
        n = self.net.K - 1 if hidden else self.net.K
        what = "hidden layers" if hidden else "layers (the output layer last)"
        k = check_int(k, "k", 0, f"the index of a layer, 0-based: the network has {n} {what}")
        if k >= n:
            raise ValueError(f"k must be the index (0-based) of one of the network's {n} {what}: 0..{n - 1}, got {k}")
        return k

    def _neuron_index(self, k: int, j) -> int:
        """``j`` as the index (0-based) of a neuron of layer ``k``, else ``ValueError`` naming it."""
        n = self.net.W[k].shape[0]
        j = check_int(j, "j", 0, f"the index of a neuron, 0-based: layer k = {k} has {n}")
        if j >= n:
            raise ValueError(f"j must be the index (0-based) of one of the {n} neurons of layer k = {k}: 0..{n - 1}, "
                             f"got {j}")
        return j

    def set_neuron(self, k: int, j: int, L: float, U: float) -> None:
        """Write the big-M constants of neuron ``j`` of hidden layer ``k`` (0-based) into the LP.

        ``k`` and ``j`` must be integers that index a hidden neuron of the network, ``L <= U`` finite numbers;
        anything else is a ``ValueError`` naming the argument."""
        k = self._layer_index(k)
        j = self._neuron_index(k, j)
        L = check_number(one_number(L, "L"), "L", "the neuron's lower node bound", low=-np.inf)
        U = check_number(one_number(U, "U"), "U", "the neuron's upper node bound", low=-np.inf)
        if L > U:
            raise ValueError(f"L must be <= U (the node bounds of neuron j = {j} of layer k = {k}), got L = {L!r} > "
                             f"U = {U!r}")
        self._set_neuron(k, j, L, U)

    def _set_neuron(self, k: int, j: int, L: float, U: float) -> None:
        """:meth:`set_neuron` without its checks (the callers here pass valid indices and bounds)."""
        h = self.h
        self._known[k][j] = True
        Up, Lm = max(U, 0.0), min(L, 0.0)
        ia = int(self.alpha[k][j])
        h.changeCoeff(int(self.row_U[k][j]), ia, -Up)
        h.changeCoeff(int(self.row_L[k][j]), ia, -Lm)
        h.changeRowBounds(int(self.row_L[k][j]), -self._hp.kHighsInf, float(self.b_row_L[k][j] - Lm))
        lo_a, hi_a = (1.0 if L >= 0 else 0.0), (0.0 if U <= 0 else 1.0)
        h.changeColBounds(ia, lo_a, hi_a)
        iy = int(self.y[k][j])
        h.changeColBounds(iy, 0.0, Up)
        rU, rL = int(self.row_U[k][j]), int(self.row_L[k][j])
        self._A[rU, ia], self._A[rL, ia] = -Up, -Lm
        self._absA[rU, ia], self._absA[rL, ia] = Up, -Lm
        self._rl[rL], self._ru[rL] = -np.inf, float(self.b_row_L[k][j] - Lm)
        self._lb[ia], self._ub[ia] = lo_a, hi_a
        self._lb[iy], self._ub[iy] = 0.0, Up

    def set_layer(self, k: int, L: Array, U: Array) -> None:
        """:meth:`set_neuron` for every neuron of hidden layer ``k``: ``L <= U`` finite, (n_k,) each (``ValueError``
        naming the argument otherwise)."""
        k = self._layer_index(k)
        n = self.net.W[k].shape[0]
        L_a, U_a = as_floats(L, "L"), as_floats(U, "U")
        for name, a, given in (("L", L_a, L), ("U", U_a, U)):
            if a.shape != (n,):
                raise ValueError(f"{name} must have shape ({n},) (one bound per neuron of layer k = {k}), got "
                                 f"{np.shape(given)}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be finite node bounds (layer k = {k}), got {brief(given)}")
        bad = np.flatnonzero(L_a > U_a)
        if bad.size:
            j = int(bad[0])
            raise ValueError(f"L must be <= U (node bounds of layer k = {k}), got L[{j}] = {L_a[j]!r} > U[{j}] = "
                             f"{U_a[j]!r}")
        self._set_layer(k, L_a, U_a)

    def _set_layer(self, k: int, L: Array, U: Array) -> None:
        """:meth:`set_layer` without its checks."""
        for j in range(len(L)):
            self._set_neuron(k, j, float(L[j]), float(U[j]))

    # -- LPs -----------------------------------------------------------------------
    def _optimize(self, cols: Array, coef: Array, sense: float) -> Optional[float]:
        """A valid lower bound of min (sense = 1), or upper bound of max (sense = -1), of ``coef' w[cols]`` over the
        LP; None when the LP is proven infeasible.

        The bound is not HiGHS's optimum but the safe bound of its duals (:meth:`_safe_min`): it holds whatever the
        LP solver's accuracy (on badly scaled networks HiGHS called non-optimal points optimal, by up to 1e-3
        relative). An infeasibility is believed only with a Farkas certificate (HiGHS's dual ray, checked the same
        way); otherwise, and on any other status, the bound is infinite: the caller keeps the one it has.
        """
        hp, h = self._hp, self.h
        cost = np.zeros(self.n)
        cost[cols] = sense * coef
        h.changeColsCost(self.n, self._all, cost)
        h.run()
        self.n_lp += 1
        st = h.getModelStatus()
        if st == hp.HighsModelStatus.kOptimal:
            lam = np.asarray(h.getSolution().row_dual, float)
            safe = self._safe_min(cost, lam)  # HiGHS's sign of the duals; the other sign when that one falls short
            obj = h.getInfo().objective_function_value
            if not safe >= obj - 1e-9 * (1.0 + abs(obj)):
                safe = max(safe, self._safe_min(cost, -lam))
            return sense * safe
        if st == hp.HighsModelStatus.kInfeasible:
            _, has_ray, ray = h.getDualRay()
            if has_ray:
                ray = np.asarray(ray, float)
                zero = np.zeros(self.n)
                if max(self._safe_min(zero, ray), self._safe_min(zero, -ray)) > 0.0:
                    return None
        # numerical trouble, or an infeasibility without a checked certificate: no bound
        return -np.inf if sense > 0 else np.inf

    def _safe_min(self, cost: Array, lam: Array) -> float:
        """A lower bound of ``min cost' w`` over ``rl <= A w <= ru, lb <= w <= ub`` from any row multipliers ``lam``
        (Neumaier & Shcherbina 2004): ``cost' w = lam' A w + d' w`` with ``d = cost - A' lam``, and each term is
        bounded below over the rows' and the variables' bounds, less a margin for the round-off of this sum. A
        positive value with ``cost = 0`` proves the rows infeasible (Farkas)."""
        rl, ru, lb, ub = self._rl, self._ru, self._lb, self._ub
        pos = lam > 0
        lam = np.where(pos, lam, np.minimum(lam, 0.0))
        lam[(pos & (rl == -np.inf)) | (~pos & (ru == np.inf))] = 0.0  # a side without a bound takes no multiplier
        side_r = np.where(pos, rl, ru)
        r = lam * np.where(lam != 0.0, side_r, 0.0)
        d = cost - self._A.T @ lam
        side_c = np.where(d > 0, lb, ub)
        c = d * np.where(d != 0.0, side_c, 0.0)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(c))):
            return -np.inf
        # round-off of d (|A|'|lam| + |cost|, times the unit round-off and the rows' count) and of the sums
        big = np.maximum(np.abs(np.where(np.isfinite(lb), lb, 0.0)), np.abs(np.where(np.isfinite(ub), ub, 0.0)))
        err = 1e-12 * (np.abs(r).sum() + np.abs(c).sum() + (self._absA.T @ np.abs(lam) + np.abs(cost)) @ big)
        return float(r.sum() + c.sum() - err)

    def preactivation_range(self, k: int, j: int) -> tuple[Optional[float], Optional[float]]:
        """LP minimum and maximum of ``W^k_j y^{k-1} + b^k_j`` (None: the LP is infeasible).

        ``k`` indexes a layer (0-based; ``K - 1`` the output layer) and ``j`` a neuron of it: integers of that
        range, else ``ValueError`` naming the argument."""
        k = self._layer_index(k, hidden=False)
        j = self._neuron_index(k, j)
        if not self._box_set:
            raise ValueError("set the input box first (set_box): the LP has no bounds on x yet")
        for i, known in enumerate(self._known):  # a neuron without node bounds has its big-M entries at zero, which
            missing = np.flatnonzero(~known)  # pins its pre-activation to 0: no relaxation of the network then
            if missing.size:
                raise ValueError(f"set the node bounds of every hidden neuron first (set_layer or set_neuron): neuron "
                                 f"j = {int(missing[0])} of layer {i} has none, and the LP then pins its pre-activation "
                                 f"to 0 (no relaxation of the network)")
        return self._preactivation_range(k, j)

    def _preactivation_range(self, k: int, j: int) -> tuple[Optional[float], Optional[float]]:
        """:meth:`preactivation_range` without its checks."""
        W, b = self.net.W[k], self.net.b[k]
        prev = self.x if k == 0 else self.y[k - 1]
        lo = self._optimize(prev, W[j], 1.0)
        if lo is None:
            return None, None
        hi = self._optimize(prev, W[j], -1.0)
        if hi is None:
            return None, None
        return lo + b[j], hi + b[j]

    def tighten(self, lo: Array, hi: Array, prior: Optional[NodeBounds] = None, output: bool = True,
                skip_stable: bool = False, deadline: Optional[float] = None) -> NodeBounds:
        """Bounds for the input box ``[lo, hi]`` (one box), starting from FBBT (intersected with ``prior``).

        ``skip_stable=True`` solves LPs only for neurons that are still unstable when their
        layer is reached (a stable neuron needs no binary; its bounds only feed the interval
        bounds of later layers): about half the LPs for the same binaries. With ``deadline`` (a
        ``time.perf_counter()`` value), :class:`DeadlineReached` is raised before an LP that would start after it.
        The result depends on the arguments only: the model is restarted first (:meth:`restart`). One call at a
        time per tightener (a lock): the LP is shared by every caller of :func:`lp_bounds` with the same network,
        and a controller answered at its cut-off can still be tightening in its thread while another solves.
        """
        with self.lock:
            return self._tighten(lo, hi, prior, output, skip_stable, deadline)

    def _tighten(self, lo: Array, hi: Array, prior: Optional[NodeBounds], output: bool, skip_stable: bool,
                 deadline: Optional[float]) -> NodeBounds:
        net = self.net
        self.restart()
        start = fbbt(net, lo, hi, outward=True)  # rounded outward: the LP's rows must not cut a point of the box
        if prior is not None:
            start = intersect(start, prior)
            _empty_if_crossed(start.L, start.U)
        L, U = [a.copy() for a in start.L], [a.copy() for a in start.U]
        self._set_box(lo, hi)
        for k in range(net.K - 1):
            self._set_layer(k, L[k], U[k])
        for k in range(net.K - 1):
            for j in range(len(L[k])):
                if skip_stable and (L[k][j] >= 0 or U[k][j] <= 0):
                    continue
                if deadline is not None and time.perf_counter() > deadline:
                    raise DeadlineReached("LP tightening stopped at the deadline")
                a_lo, a_hi = self._preactivation_range(k, j)
                if a_lo is None:
                    raise EmptyBoxError("the LP relaxation is infeasible: no input in the box gives an output "
                                        "within out_bounds")
                slack_lo, slack_hi = self.tol * (1 + abs(a_lo)), self.tol * (1 + abs(a_hi))
                L[k][j] = max(L[k][j], a_lo - slack_lo)
                U[k][j] = min(U[k][j], a_hi + slack_hi)
                if L[k][j] > U[k][j]:  # only by round-off: the LP was feasible
                    L[k][j] = U[k][j] = 0.5 * (L[k][j] + U[k][j])
                self._set_neuron(k, j, L[k][j], U[k][j])
            # later layers: interval bounds from the tightened layer
            L, U, oL, oU = _propagate(net, L, U, k, True)
            _empty_if_crossed(L, U)
            for kk in range(k + 1, net.K - 1):
                self._set_layer(kk, L[kk], U[kk])
        if output:
            Wk, bk = net.W[-1], net.b[-1]
            for i in range(net.n_out):
                o_lo = self._optimize(self.y[-1], Wk[i], 1.0)
                o_hi = self._optimize(self.y[-1], Wk[i], -1.0)
                if o_lo is not None and np.isfinite(o_lo):
                    oL[i] = max(oL[i], o_lo + bk[i] - self.tol * (1 + abs(o_lo)))
                if o_hi is not None and np.isfinite(o_hi):
                    oU[i] = min(oU[i], o_hi + bk[i] + self.tol * (1 + abs(o_hi)))
        return NodeBounds(L, U, oL, oU, method="lp")


def _empty_if_crossed(L: list, U: list) -> None:
    """:class:`EmptyBoxError` when valid bounds cross (``L > U`` beyond round-off): no point of the box gives an
    output within the bounds they were cut to."""
    for a, b in zip(L, U):
        if np.any(a > b + 1e-9 * (1.0 + np.abs(b))):
            raise EmptyBoxError("the node bounds cross: no input in the box gives an output within out_bounds (the "
                                "prior's bounds and the box's exclude each other)")


_TIGHTENERS: dict = {}
_TIGHTENERS_LOCK = threading.Lock()


def check_out_bounds(out_bounds, n_out: int) -> tuple[Array, Array]:
    """``(out_lo, out_hi)`` as two float vectors of shape ``(n_out,)`` (a number is the same bound on every output),
    ``out_lo <= out_hi``; an infinite end is one-sided (``-inf`` below, ``+inf`` above), NaN is refused.
    ``ValueError`` naming ``out_bounds`` otherwise."""
    olo, ohi = as_pair(out_bounds, "out_bounds")
    olo, ohi = (np.full(n_out, float(a)) if a.ndim == 0 else a  # a number: the same bound on every output
                for a in (as_floats(olo, "out_bounds[0]"), as_floats(ohi, "out_bounds[1]")))
    if olo.shape != (n_out,) or ohi.shape != (n_out,):
        raise ValueError(f"out_bounds must be a pair (out_lo, out_hi) of arrays of shape ({n_out},) (one per output "
                         f"of the network), got shapes {olo.shape} and {ohi.shape}")
    if np.isnan(olo).any() or np.isnan(ohi).any() or np.any(olo == np.inf) or np.any(ohi == -np.inf):
        raise ValueError(f"out_bounds must be numbers (out_lo < +inf, out_hi > -inf; -inf or +inf for a one-sided "
                         f"bound), got {olo} and {ohi}")
    if np.any(olo > ohi):
        raise ValueError(f"out_bounds is empty: out_lo = {olo} lies above out_hi = {ohi}")
    return olo, ohi


def _tightener(net: ReLUNet, out_bounds, tol: float) -> LPTightener:
    """One persistent LP per (network, output bounds), reused across calls (the model is only updated). The network
    is known by its parameters (:func:`flnotes.network.fingerprint`): one changed in place gets a new LP."""
    key = (fingerprint(net), None if out_bounds is None else (tuple(np.asarray(out_bounds[0], float)),
                                                               tuple(np.asarray(out_bounds[1], float))), float(tol))
    with _TIGHTENERS_LOCK:
        t = _TIGHTENERS.get(key)
        if t is None:
            if len(_TIGHTENERS) > 16:
                _TIGHTENERS.clear()
            t = _TIGHTENERS[key] = LPTightener(net, out_bounds=out_bounds, tol=tol)
        return t


def lp_bounds(net: ReLUNet, lo: Array, hi: Array, out_bounds: Optional[tuple[Array, Array]] = None,
              prior: Optional[NodeBounds] = None, tol: float = 1e-7, skip_stable: bool = False,
              deadline: Optional[float] = None) -> NodeBounds:
    """Node bounds by LP-based tightening (Grimstad & Andersson 2019), eq. (MIP_general) relaxed.

    Parameters
    ----------
    net
        The network.
    lo, hi
        Input box over ``y^0 = [z, v]``: shape (n_in,), or (T, n_in) for T
        boxes (each tightened on its own; the LP is reused).
    out_bounds
        ``(out_lo, out_hi)``, each (n_out,): restrict the LP to inputs whose
        output satisfies them, e.g. ``(-u_max_eps, u_max_eps)`` for
        eq. (Phi_NN_ep). The bounds are then valid for every point of the
        controller's feasible set (not for the whole box).
    prior
        Valid bounds to start from (intersected with FBBT), e.g. bounds of
        the whole domain computed once offline.
    tol
        Relative margin added to every bound (on top of the safe bound of the
        LP's duals, which already holds whatever the solver's accuracy).
    skip_stable
        Solve LPs only for neurons still unstable when reached (faster, same
        binaries; stable neurons keep their interval bounds).
    deadline
        A ``time.perf_counter()`` value (a controller's time limit): no LP starts after it.

    Returns
    -------
    NodeBounds
        ``method == "lp"`` (or ``"lp+out"`` with output bounds), never looser
        than FBBT on the same box.

    Raises
    ------
    EmptyBoxError
        When ``out_bounds`` cannot be met by any input of the box.
    DeadlineReached
        When ``deadline`` passes before the last LP.
    """
    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    lo2, hi2, batch = check_boxes(lo, hi, net.n_in)
    if out_bounds is not None:
        out_bounds = check_out_bounds(out_bounds, net.n_out)
    tol = check_number(tol, "tol", "the relative margin added to every bound")
    skip_stable = check_bool(skip_stable, "skip_stable", "whether to solve LPs only for unstable neurons")
    deadline = check_number(deadline, "deadline", "a time.perf_counter() value", none=True)
    if prior is not None and not isinstance(prior, NodeBounds):
        raise TypeError(f"prior must be a flnotes.NodeBounds (e.g. prior=fl.fbbt(net, lo, hi)), got "
                        f"{type(prior).__name__}")
    if prior is not None and np.ndim(prior.L[0]) == 2 and len(prior.L[0]) != len(lo2):
        raise ValueError(f"prior holds bounds of {len(prior.L[0])} boxes but lo, hi give {len(lo2)}: one prior per "
                         f"box (or one for all)")
    if net.K == 1:
        return _affine_bounds(net, lo2, hi2, out_bounds, batch)
    tightener = _tightener(net, out_bounds, tol)
    res = []
    for t in range(len(lo2)):
        pr = None
        if prior is not None:
            pr = prior if np.ndim(prior.L[0]) == 1 else NodeBounds([a[t] for a in prior.L], [a[t] for a in prior.U],
                                                                   prior.out_L[t], prior.out_U[t], prior.method)
        res.append(tightener.tighten(lo2[t], hi2[t], prior=pr, skip_stable=skip_stable, deadline=deadline))
    method = "lp+out" if out_bounds is not None else "lp"
    if not batch:
        b = res[0]
        b.method = method
        return b
    return NodeBounds([np.stack([r.L[k] for r in res]) for k in range(net.K - 1)],
                      [np.stack([r.U[k] for r in res]) for k in range(net.K - 1)],
                      np.stack([r.out_L for r in res]), np.stack([r.out_U for r in res]), method=method)


def _affine_bounds(net: ReLUNet, lo: Array, hi: Array, out_bounds, batch: bool) -> NodeBounds:
    """:func:`lp_bounds` of a network without a hidden layer: no node bounds, the output's exact interval over each
    box (cut to ``out_bounds``); :class:`EmptyBoxError` when an output's interval misses ``out_bounds``."""
    oL, oU = interval_affine(net.W[0], net.b[0], lo, hi, outward=True)  # rows: the boxes
    if out_bounds is not None:
        olo, ohi = np.asarray(out_bounds[0], float), np.asarray(out_bounds[1], float)
        if np.any(oL > ohi) or np.any(oU < olo):
            raise EmptyBoxError("no input in the box gives an output within out_bounds (the network is affine)")
        oL, oU = np.maximum(oL, olo), np.minimum(oU, ohi)
    method = "lp+out" if out_bounds is not None else "lp"
    return NodeBounds([], [], oL if batch else oL[0], oU if batch else oU[0], method=method)


# ---------------------------------------------------------------------------
# Reachable boxes along the horizon
# ---------------------------------------------------------------------------
def horizon_boxes(Ad: Array, Bd: Array, z0: Array, z_lo: Array, z_hi: Array, v_lo: Array, v_hi: Array,
                  horizon: int, first: Optional[tuple[Array, Array]] = None) -> tuple[Array, Array]:
    """Boxes containing ``[z(k), v(k)]``, k = 0..horizon-1, for every admissible input sequence.

    With ``z(0) = z0`` fixed and ``z(k+1) = Ad z(k) + Bd v(k)`` (eq. MPC_form_miqp_c),
    ``v(k)`` in ``[v_lo, v_hi]`` and ``z(k)`` in the state box ``[z_lo, z_hi]``
    (eq. MPC_form_miqp_d), two valid boxes are intersected at every step:
    the interval recursion ``Z(k+1) = (Ad Z(k) + Bd V) ∩ [z_lo, z_hi]`` (which
    uses the state constraint) and the exact box of the unconstrained
    convolution ``Ad^k z0 + sum_i Ad^(k-1-i) Bd V`` (which has no wrapping
    effect).

    Parameters
    ----------
    Ad, Bd
        Discrete dynamics, (n_z, n_z) and (n_z, m).
    z0
        Measured state (n_z,).
    z_lo, z_hi, v_lo, v_hi
        State and input boxes.
    horizon
        ``N_p``.
    first
        Optional pair ``(a, b)``, each (m,) with ``a <= b``: a narrower range of the first input, ``v(0)`` in
        ``[v_lo, v_hi]`` and in ``[a, b]`` (e.g. its exact admissible range at ``z0``,
        :meth:`flnotes.mpc.prediction.Prediction.first_range`); the later inputs keep ``[v_lo, v_hi]``.

    Returns
    -------
    lo, hi
        Arrays of shape (horizon, n_z + m): row ``k`` bounds ``[z(k), v(k)]``
        (row 0 has ``z(0) = z0`` exactly). Pass them to ``fbbt(net, lo, hi)``
        for per-step node bounds.

    Raises
    ------
    EmptyBoxError
        When ``z0`` lies outside the state box by more than
        :data:`flnotes.solvers.BOX_TOL` (closer, it is projected onto the box) or
        no admissible input keeps the state in the box.
    """
    Ad, Bd = np.atleast_2d(as_floats(Ad, "Ad")), np.atleast_2d(as_floats(Bd, "Bd"))
    if not (np.all(np.isfinite(Ad)) and np.all(np.isfinite(Bd))):
        raise ValueError("Ad and Bd must be finite (the discretized model): they contain NaN or inf")
    n_z = Ad.shape[0]
    if Ad.shape != (n_z, n_z):
        raise ValueError(f"Ad must be square, got {Ad.shape}")
    if Bd.ndim != 2 or Bd.shape[0] != n_z:
        raise ValueError(f"Bd must have shape ({n_z}, m), got {Bd.shape}")
    m = Bd.shape[1]
    z0 = as_state(z0, n_z, "z0")
    z_lo, z_hi = check_box(z_lo, z_hi, n_z, "z_lo", "z_hi")
    v_lo, v_hi = check_box(v_lo, v_hi, m, "v_lo", "v_hi")
    horizon = check_count(horizon, "horizon", 1, "steps of the prediction")
    from .solvers import BOX_TOL

    if np.any(z0 < z_lo - BOX_TOL) or np.any(z0 > z_hi + BOX_TOL):
        raise EmptyBoxError(f"z0 = {z0} lies outside the state box [{z_lo}, {z_hi}] (tolerance {BOX_TOL:g})")
    z0 = np.clip(z0, z_lo, z_hi)  # on the face of the box up to round-off: on the face
    v0_lo, v0_hi = v_lo, v_hi
    if first is not None:
        a, b = (as_vector(x, m, name) for x, name in zip(as_pair(first, "first"), ("first's a", "first's b")))
        if np.any(a > b):
            raise ValueError(f"first = (a, b) needs a <= b (a range of the first input), got a = {a}, b = {b}")
        v0_lo, v0_hi = np.maximum(v_lo, a), np.minimum(v_hi, b)
        if np.any(v0_lo > v0_hi):
            raise EmptyBoxError(f"the first input's range [{a}, {b}] misses the input box [{v_lo}, {v_hi}]")
    lo, hi = np.empty((horizon, n_z + m)), np.empty((horizon, n_z + m))
    lo[:, n_z:], hi[:, n_z:] = v_lo, v_hi
    lo[0, n_z:], hi[0, n_z:] = v0_lo, v0_hi
    c_v, r_v = 0.5 * (v_hi + v_lo), 0.5 * (v_hi - v_lo)
    c_0, r_0 = 0.5 * (v0_hi + v0_lo), 0.5 * (v0_hi - v0_lo)   # v(0)
    Bl, Bu = interval_affine(Bd, np.zeros(n_z), v_lo, v_hi)   # the box of Bd v
    B0l, B0u = interval_affine(Bd, np.zeros(n_z), v0_lo, v0_hi)
    center, rest = z0.copy(), np.zeros(n_z)                   # the convolution box: center +- radius
    AjB = Bd.copy()                                           # Ad^j Bd
    zl, zu = z0.copy(), z0.copy()
    for k in range(horizon):
        lo[k, :n_z], hi[k, :n_z] = zl, zu
        if k + 1 == horizon:
            break
        # interval recursion with the state constraint
        nl, nu = interval_affine(Ad, np.zeros(n_z), zl, zu)
        Bkl, Bku = (B0l, B0u) if k == 0 else (Bl, Bu)        # the box of Bd v(k)
        nl, nu = np.maximum(nl + Bkl, z_lo), np.minimum(nu + Bku, z_hi)
        # exact box of Ad^(k+1) z0 + sum_i Ad^(k-i) Bd v(i): v(0)'s term Ad^k Bd v(0), the others' summed by age
        # (rest = sum_{j<k} |Ad^j Bd| r_v, in order of the input's age; both orders give the same sum)
        center = Ad @ center + Bd @ (c_0 if k == 0 else c_v)
        radius = rest + np.abs(AjB) @ r_0
        rest = rest + np.abs(AjB) @ r_v
        AjB = Ad @ AjB
        zl, zu = np.maximum(nl, center - radius), np.minimum(nu, center + radius)
        if np.any(zl > zu + 1e-9 * (1 + np.abs(zu))):
            raise EmptyBoxError(f"no admissible input keeps the predicted state in the box at step {k + 1}")
        zl, zu = np.minimum(zl, zu), np.maximum(zl, zu)
    return lo, hi


# ---------------------------------------------------------------------------
# Optimality-based boxes: the level set of a convex relaxation
# ---------------------------------------------------------------------------
def ellipsoid_box(S: Array, H_inv: Array, V_c: Array, offset: Array, delta: float) -> tuple[Array, Array]:
    """Box of ``S V + offset`` over the ellipsoid ``0.5 (V - V_c)' H (V - V_c) <= delta``.

    With ``(V_c, J_c)`` the optimum of a convex QP relaxation ``min J(V)`` over a convex set
    ``C`` (``J`` convex quadratic with Hessian ``H``), every ``V`` in ``C`` satisfies

        J(V) >= J_c + 0.5 (V - V_c)' H (V - V_c)

    (the first-order optimality of ``V_c`` plus the exact second-order term). So every
    solution better than a level ``J_up`` lies in this ellipsoid with ``delta = J_up - J_c``,
    and the ``i``-th row of ``S V`` ranges over ``S_i V_c +- sqrt(2 delta S_i H^-1 S_i')``.
    These boxes, much smaller than the reachable boxes when the relaxation is tight, give
    node bounds that are valid for every improving solution (the MPC's "level-set" lever).

    Parameters
    ----------
    S
        (r, n) rows of the linear map (e.g. ``z(k) = Sx[k] z0 + Su[k] V`` stacked with ``v(k)``).
    H_inv
        (n, n) inverse of the positive definite Hessian ``H``.
    V_c
        (n,) center (the relaxation's optimum).
    offset
        (r,) constant added to ``S V``.
    delta
        ``J_up - J_c >= 0``.

    Returns
    -------
    lo, hi
        Arrays of shape (r,).
    """
    S = np.atleast_2d(as_floats(S, "S"))
    d = as_floats(delta, "delta").reshape(-1)
    if d.size != 1 or not d[0] >= 0:  # +inf: the whole space (no level set yet)
        raise ValueError(f"delta = J_up - J_c must be a number >= 0 (inf for no cut), got {delta!r}")
    delta = float(d[0])
    center = S @ as_floats(V_c, "V_c") + as_floats(offset, "offset")
    q = np.maximum(np.einsum("ij,jk,ik->i", S, as_floats(H_inv, "H_inv"), S), 0.0)
    rad = np.where(q > 0, np.sqrt(2.0 * delta * np.where(q > 0, q, 1.0)), 0.0)  # a row it cannot move: radius 0
    if center.shape != (S.shape[0],) or not np.all(np.isfinite(center)) or np.any(np.isnan(rad)):
        raise ValueError(f"the box of S V + offset must be finite of shape ({S.shape[0]},): check S, H_inv, V_c and "
                         f"offset (shapes (r, n), (n, n), (n,), (r,)), got a centre of shape {center.shape}")
    return center - rad, center + rad
