"""Node bounds ``L^k_j <= W^k y^{k-1} + b^k <= U^k_j`` for the big-M constants of eq. (MIP_general_c).

Feasibility-based bound tightening (FBBT) propagates an input box through the
network with interval arithmetic (Grimstad & Andersson 2019, Sec. 4.3): for
layer ``k`` with the box ``[y^{k-1}_lo, y^{k-1}_hi]`` of ``y^{k-1}`` (eq-04-fbbt),

    L^k = W^k_+ y^{k-1}_lo + W^k_- y^{k-1}_hi + b^k,   U^k = W^k_+ y^{k-1}_hi + W^k_- y^{k-1}_lo + b^k,
    y^k_lo = max(L^k, 0),                              y^k_hi = max(U^k, 0),

with ``W_+ = max(W, 0)`` and ``W_- = min(W, 0)``. A neuron with ``L >= 0`` is
stably active, one with ``U <= 0`` stably inactive: neither needs a binary.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._checks import as_floats, check_bool, check_box, check_boxes, check_number
from .network import ReLUNet

Array = np.ndarray


@dataclass
class NodeBounds:
    """Pre-activation bounds of every hidden neuron, one array per hidden layer.

    Attributes
    ----------
    L, U
        ``L[k-1]``, ``U[k-1]`` bound the pre-activations of hidden layer ``k``;
        each of shape (n_k,), or (T, n_k) for a batch of T input boxes.
    out_L, out_U
        Bounds of the network output ``y^K``, shape (n_out,) or (T, n_out).
    method
        How they were computed (``"fbbt"``, ``"lp"``, ...).
    """

    L: list[Array]
    U: list[Array]
    out_L: Array
    out_U: Array
    method: str = "fbbt"

    @property
    def active(self) -> list[Array]:
        """Stably active neurons (``L >= 0``): ``alpha = 1`` is forced."""
        return [L >= 0 for L in self.L]

    @property
    def inactive(self) -> list[Array]:
        """Stably inactive neurons (``U <= 0``): ``alpha = 0`` is forced."""
        return [U <= 0 for U in self.U]

    @property
    def unstable(self) -> list[Array]:
        """Neurons whose sign is not decided by the bounds: each needs a binary."""
        return [(L < 0) & (U > 0) for L, U in zip(self.L, self.U)]

    @property
    def n_unstable(self) -> int:
        """Number of binaries the encoding needs (summed over a batch)."""
        return int(sum(u.sum() for u in self.unstable))

    @property
    def n_stable(self) -> int:
        return int(sum(u.size - u.sum() for u in self.unstable))

    def width(self) -> list[Array]:
        """``U - L`` per layer: the big-M spread."""
        return [U - L for L, U in zip(self.L, self.U)]

    def contains(self, pre: list[Array], tol: float = 1e-9) -> bool:
        """Do the bounds contain the given pre-activations (as from :meth:`ReLUNet.preactivations`)?"""
        pre = list(pre) if hasattr(pre, "__iter__") else pre
        if not isinstance(pre, list) or len(pre) != len(self.L):
            raise ValueError(f"pre must hold {len(self.L)} arrays of pre-activations, one per hidden layer "
                             f"(net.preactivations(X)), got {type(pre).__name__}")
        tol = check_number(tol, "tol", "the slack of the containment")
        pre = [as_floats(a, f"pre[{k}]") for k, a in enumerate(pre)]
        for k, (a, L) in enumerate(zip(pre, self.L)):
            if a.ndim == 0 or a.shape[-1] != np.shape(L)[-1]:
                raise ValueError(f"pre[{k}] must hold pre-activations of layer {k + 1}: shape (N, {np.shape(L)[-1]}), "
                                 f"got {a.shape}")
        return all(np.all(a >= L - tol) and np.all(a <= U + tol) for a, L, U in zip(pre, self.L, self.U))

    def summary(self) -> str:
        per = [f"layer {k + 1}: {int(a.sum())} active, {int(i.sum())} inactive, {int(u.sum())} unstable"
               for k, (a, i, u) in enumerate(zip(self.active, self.inactive, self.unstable))]
        return f"{self.method} bounds: " + "; ".join(per)


#: Outward rounding of :func:`interval_affine` (``outward=True``): its bounds are widened by this times the number of
#: terms plus two, times ``|W| max(|l|, |u|) + |b|`` (twice the unit round-off: the bound of the floating-point error
#: of a sum of ``n`` products, Higham 2002, once for the bounds and once for the forward pass they must contain).
ROUNDING = 2.0 * np.finfo(float).eps


def interval_affine(W: Array, b: Array, l: Array, u: Array, outward: bool = True) -> tuple[Array, Array]:
    """Range of ``W y + b`` over the box ``l <= y <= u`` (rows of l, u are boxes).

    With ``outward=True`` (the default) it is widened by the floating-point error of its sums (:data:`ROUNDING`),
    so that it contains ``W y + b`` for every ``y`` of the box, computed exactly or by a forward pass in floating
    point. Without the widening, weights and biases of 1e6 gave a bound 140 units in the last place below a
    corner's pre-activation, and LP tightening declared a box 2e-12 wide empty. ``outward=False``: the plain
    floating-point interval.
    """
    W, b, l, u = as_floats(W, "W"), as_floats(b, "b"), as_floats(l, "l"), as_floats(u, "u")
    if W.ndim != 2 or b.shape != (W.shape[0],) or l.shape != u.shape or l.shape[-1:] != (W.shape[1],):
        raise ValueError(f"need W (p, n), b (p,) and l, u of shape (n,) or (T, n): got W {W.shape}, b {b.shape}, "
                         f"l {l.shape}, u {u.shape}")
    if not all(np.all(np.isfinite(a)) for a in (W, b, l, u)) or np.any(l > u):
        raise ValueError("W, b and the box must be finite, with l <= u in every coordinate")
    return _interval_affine(W, b, l, u, outward)


def _interval_affine(W: Array, b: Array, l: Array, u: Array, outward: bool = True) -> tuple[Array, Array]:
    """:func:`interval_affine` on float arrays with ``l <= u`` (the package's own propagation: no checks)."""
    Wp, Wm = np.maximum(W, 0.0), np.minimum(W, 0.0)
    L, U = l @ Wp.T + u @ Wm.T + b, u @ Wp.T + l @ Wm.T + b
    if not outward:
        return L, U
    mag = np.maximum(np.abs(l), np.abs(u)) @ np.abs(W).T + np.abs(b)
    err = ROUNDING * (W.shape[1] + 2) * mag
    return L - err, U + err


def _check_net_box(net: ReLUNet, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """``TypeError``/``ValueError`` naming ``net`` when it is not a network or its input size is not the box's;
    ``lo`` and ``hi`` as float arrays (:func:`as_floats`: numbers only, named)."""
    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    lo, hi = as_floats(lo, "lo"), as_floats(hi, "hi")
    d = np.shape(lo)[-1] if np.ndim(lo) else None
    if d is not None and d != net.n_in and np.shape(lo) == np.shape(hi):
        raise ValueError(f"net has {net.n_in} inputs but the box lo, hi has {d} dimensions: lo and hi must have "
                         f"shape ({net.n_in},) or (T, {net.n_in}), a box over the network's input (z, v)")
    return lo, hi


def fbbt(net: ReLUNet, lo: Array, hi: Array, outward: bool = True) -> NodeBounds:
    """Node bounds by interval propagation (FBBT, Grimstad & Andersson 2019, Sec. 4.3).

    Parameters
    ----------
    net
        The network.
    lo, hi
        Input box over ``y^0 = [z, v]``: shape (n_in,), or (T, n_in) for T
        boxes at once (e.g. the reachable boxes along an MPC horizon). A
        coordinate with ``lo == hi`` is fixed (a measured state).
    outward
        Round every interval outward by the error bound of its sums (:func:`interval_affine`), a few units in the
        last place, so that the bounds contain every pre-activation as a floating-point forward pass computes it
        (the default; ``False`` gives the plain intervals, which on badly scaled networks can be a few units in the
        last place too tight).

    Returns
    -------
    NodeBounds
        ``L``, ``U`` of shape (n_k,) (or (T, n_k)) per hidden layer, and the
        output bounds.
    """
    lo, hi = _check_net_box(net, lo, hi)
    outward = check_bool(outward, "outward", "whether to widen the bounds by the rounding of their sums")
    lo_a, hi_a, batch = check_boxes(lo, hi, net.n_in)
    l, u = lo_a, hi_a
    Ls, Us = [], []
    for W, b in zip(net.W[:-1], net.b[:-1]):
        L, U = _interval_affine(W, b, l, u, outward)
        Ls.append(L), Us.append(U)
        l, u = np.maximum(L, 0.0), np.maximum(U, 0.0)
    oL, oU = _interval_affine(net.W[-1], net.b[-1], l, u, outward)
    if not batch:
        Ls, Us, oL, oU = [a[0] for a in Ls], [a[0] for a in Us], oL[0], oU[0]
    return NodeBounds(Ls, Us, oL, oU, method="fbbt")


def sample_preactivations(net: ReLUNet, lo: Array, hi: Array, n: int = 100_000, seed: int = 0) -> list[Array]:
    """Pre-activations at ``n`` uniform samples of the box plus its corners (to check bounds)."""
    lo, hi = _check_net_box(net, lo, hi)
    lo, hi = check_box(lo, hi, net.n_in)
    X = np.random.default_rng(seed).uniform(lo, hi, (n, net.n_in))
    if net.n_in <= 12:
        corners = np.array(np.meshgrid(*[[a, b] for a, b in zip(lo, hi)], indexing="ij")).reshape(net.n_in, -1).T
        X = np.vstack([X, corners])
    return net.preactivations(X)
