"""An affine enclosure of a ReLU network over a box: ``a_j' x + r_lo_j <= Phi_NN,j(x) <= a_j' x + r_hi_j``.

Its use is the convex outer set of the input constraint (eq. Phi_NN_ep): every ``x`` of the box with
``|Phi_NN,j(x)| <= u_j`` lies in the slab

    -u_j - r_hi_j  <=  a_j' x  <=  u_j - r_lo_j,

two linear rows per output. The QP without the network that the MPC solves first (screening, the level set's
center) is a relaxation of eq. (MPC_form_miqp); with these rows at every predicted step it is a tighter one, and
its optimum is closer to the MIQP's. The level-set boxes are cut to the slab too (:func:`contract`). Where ``Phi``
is nearly affine in ``(z, v)`` (the MSD's ``Phi = v + s(z_2) + z_1``) the slab is narrow.

How it is computed (:func:`affine_enclosure`): ``a_j`` is the least-squares affine fit of output ``j`` on a fixed
sample of the box (any ``a_j`` gives a valid enclosure; a good fit a narrow one); ``r_hi_j`` and ``r_lo_j`` are
the maximum and minimum of ``Phi_NN,j(x) - a_j' x`` over the box, each a MILP of eq. (MIP_general) on the LP node
bounds of the box, solved by HiGHS (the package's back-end, whose optima are cross-checked) to a relative gap of
:data:`GAP` within :data:`NODE_LIMIT` nodes. The enclosure takes the proved bound (not the incumbent) widened by
:data:`PAD` (relative), so that it holds for every point of the box, and keeps the MILP's maximizer and
minimizer (``x_hi``, ``x_lo``) as witnesses of how tight it is. A fixed sample of the box is checked against it
before it is returned (a solver whose bound were wrong raises there, never gives a slab that cuts off a plan).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ._checks import as_batch, as_floats, brief, check_boxes, check_number
from .encoding import bigm_form
from .network import ReLUNet, fingerprint  # noqa: F401 - fingerprint: kept importable from here
from .solvers import MIQP, make_solver
from .tightening import lp_bounds

Array = np.ndarray

#: Relative gap of the enclosure's MILPs. The enclosure takes the proved bound, which holds whatever the gap; a
#: larger gap only leaves it up to this times ``max(1, |r|)`` looser than the tightest one.
GAP = 1e-4

#: Widening of each proved bound, times ``max(1, |r|)``, on top of the solver's: covers its feasibility tolerance
#: (1e-6 on rows whose coefficients are the weights), so that the enclosure holds for the forward pass in floating
#: point.
PAD = 1e-5

#: Branch-and-bound nodes each MILP may take (a work budget, the same on every machine): stopped there, the bound
#: proved so far is kept (valid, only looser). The MSD's (20, 20, 20) network needs about 500.
NODE_LIMIT = 20_000

#: Points of the fixed sample that fits ``a`` and checks the enclosure.
N_SAMPLE = 4096

_CACHE: dict = {}


@dataclass(frozen=True, eq=False)
class AffineEnclosure:
    """``a_j' x + r_lo_j <= Phi_NN,j(x) <= a_j' x + r_hi_j`` for every ``x`` in the box ``[lo, hi]``.

    Attributes
    ----------
    a
        (n_out, n_in): the affine part of each output.
    r_lo, r_hi
        (n_out,): proved bounds of ``Phi_NN,j(x) - a_j' x`` over the box (widened by :data:`PAD`).
    lo, hi
        (n_in,): the box.
    x_lo, x_hi
        (n_out, n_in): the MILPs' minimizers and maximizers, points of the box where the residual comes within
        the solver's gap of ``r_lo`` and ``r_hi``.
    net_id
        :func:`fingerprint` of the network it encloses.

    The arrays are read-only copies (the enclosure a cache hands out is the one it checked), of checked shapes,
    finite, with ``r_lo <= r_hi`` and ``lo < hi``. Whether the bounds hold is checked against a network by
    :func:`check_enclosure`.
    """

    a: Array
    r_lo: Array
    r_hi: Array
    lo: Array
    hi: Array
    x_lo: Array
    x_hi: Array
    net_id: str

    def __post_init__(self) -> None:
        for k in ("a", "r_lo", "r_hi", "lo", "hi", "x_lo", "x_hi"):
            v = np.array(getattr(self, k), dtype=float)  # a copy
            if not np.all(np.isfinite(v)):
                raise ValueError(f"AffineEnclosure.{k} must be finite, got {v}")
            v.setflags(write=False)
            object.__setattr__(self, k, v)
        n_out, n_in = self.a.shape if self.a.ndim == 2 else (-1, -1)
        want = dict(a=(n_out, n_in), r_lo=(n_out,), r_hi=(n_out,), lo=(n_in,), hi=(n_in,), x_lo=(n_out, n_in),
                    x_hi=(n_out, n_in))
        bad = [f"{k} {getattr(self, k).shape}" for k, sh in want.items() if n_out < 1 or getattr(self, k).shape != sh]
        if bad:
            raise ValueError(f"AffineEnclosure: a must be (n_out, n_in), r_lo and r_hi (n_out,), lo and hi (n_in,), "
                             f"x_lo and x_hi (n_out, n_in); got {', '.join(bad)} (a {self.a.shape})")
        if np.any(self.r_lo > self.r_hi) or np.any(self.lo >= self.hi):
            raise ValueError(f"AffineEnclosure: need r_lo <= r_hi and lo < hi, got r_lo = {self.r_lo}, "
                             f"r_hi = {self.r_hi}, lo = {self.lo}, hi = {self.hi}")
        if not isinstance(self.net_id, str):
            raise TypeError(f"AffineEnclosure.net_id must be a str (fingerprint(net)), got {self.net_id!r}")

    def _check_net(self, net) -> None:
        """``TypeError`` unless ``net`` is a :class:`ReLUNet`; ``ValueError`` unless it is the enclosure's network
        (its inputs and outputs, then its :func:`fingerprint`)."""
        if not isinstance(net, ReLUNet):
            raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
        if (net.n_out, net.n_in) != self.a.shape:
            raise ValueError(f"net must have {self.a.shape[1]} inputs and {self.a.shape[0]} outputs (those of the "
                             f"enclosure), got a network with {net.n_in} and {net.n_out}")
        if fingerprint(net) != self.net_id:
            raise ValueError("net must be the network the enclosure was computed for (its parameters differ): "
                             "compute the enclosure of this one with fl.affine_enclosure(net, lo, hi)")

    def residual(self, net: ReLUNet, X: Array) -> Array:
        """``Phi_NN(x) - a x`` at the points ``X`` (N, n_in) -> (N, n_out); one point (n_in,) is taken as (1, n_in).

        ``X`` must be finite numbers of that shape, ``net`` the network the enclosure was computed for
        (``ValueError``, or ``TypeError`` for no network, naming the argument otherwise)."""
        self._check_net(net)
        return self._residual(net, as_batch(X, self.a.shape[1], "X"))

    def _residual(self, net: ReLUNet, X: Array) -> Array:
        """:meth:`residual` without its checks."""
        X = np.atleast_2d(np.asarray(X, float))
        return net(X) - X @ self.a.T

    def contains(self, net: ReLUNet, X: Array, tol: float = 0.0) -> bool:
        """Do the points ``X`` (of the box) satisfy the enclosure (to ``tol``, a finite number >= 0)?"""
        self._check_net(net)
        X = as_batch(X, self.a.shape[1], "X")
        return self._contains(net, X, check_number(tol, "tol", "the margin allowed beyond the bounds"))

    def _contains(self, net: ReLUNet, X: Array, tol: float = 0.0) -> bool:
        """:meth:`contains` without its checks."""
        r = self._residual(net, X)
        return bool(np.all(r >= self.r_lo - tol) and np.all(r <= self.r_hi + tol))

    def slab(self, u: Array) -> tuple[Array, Array]:
        """Bounds ``(s_lo, s_hi)`` (n_out,) of ``a x`` over the points of the box with ``|Phi_NN(x)| <= u``:
        ``s_lo = -u - r_hi``, ``s_hi = u - r_lo``.

        ``u`` must be finite numbers >= 0, one per output (a number for a single output); anything else is a
        ``ValueError`` naming it."""
        u_a = as_floats(u, "u").reshape(-1)
        if u_a.shape != self.r_lo.shape:
            raise ValueError(f"u must have shape {self.r_lo.shape} (one bound per output), got {np.shape(u)}")
        if not np.all(np.isfinite(u_a)) or np.any(u_a < 0):
            raise ValueError(f"u must be finite output bounds >= 0, got {brief(u)}")
        return self._slab(u_a)

    def _slab(self, u: Array) -> tuple[Array, Array]:
        """:meth:`slab` without the checks of its numbers (the callers here pass the controller's bound)."""
        u = np.asarray(u, float).reshape(-1)
        if u.shape != self.r_lo.shape:
            raise ValueError(f"u must have shape {self.r_lo.shape} (one bound per output), got {u.shape}")
        return -u - self.r_hi, u - self.r_lo

    def covers(self, lo: Array, hi: Array) -> bool:
        """Does the enclosure's box contain the box ``[lo, hi]`` (every box, for a batch (T, n_in))?

        ``lo <= hi`` must be numbers of shape (n_in,) or (T, n_in) (``±inf`` for a box without end, which no
        enclosure holds), or a number for every input (of every box
        of a batch given as the other bound, as :meth:`flnotes.BoundAtlas.covers` takes it; ``ValueError`` naming
        them otherwise)."""
        lo2, hi2, _ = check_boxes(lo, hi, self.lo.shape[0], infinite=True)
        return self._covers(lo2, hi2)

    def _covers(self, lo: Array, hi: Array) -> bool:
        """:meth:`covers` without its checks."""
        return bool(np.all(self.lo <= np.asarray(lo, float)) and np.all(np.asarray(hi, float) <= self.hi))


def _fit(net: ReLUNet, lo: Array, hi: Array, X: Array) -> Array:
    """Least-squares affine fit of every output on the sample ``X``: the slopes (n_out, n_in)."""
    A = np.c_[(X - 0.5 * (lo + hi)) / np.maximum(hi - lo, 1e-300), np.ones(len(X))]
    coef = np.linalg.lstsq(A, net(X), rcond=None)[0]  # (n_in + 1, n_out), on scaled inputs
    return (coef[:-1] / np.maximum(hi - lo, 1e-300)[:, None]).T


def _extreme(net: ReLUNet, form, lo: Array, hi: Array, a_j: Array, j: int, sense: float) -> tuple[float, Array]:
    """``sense * max sense (Phi_NN,j(x) - a_j' x)`` over the box: the MILP's proved bound and its best point."""
    n = form.n
    c = np.zeros(n)
    c[form.out[j]] = -sense
    c[form.x] = sense * a_j  # minimize -sense * (y_j - a_j' x)
    lb, ub = form.lb.copy(), form.ub.copy()
    lb[form.x], ub[form.x] = lo, hi
    A = sp.vstack([form.A_eq, form.A_ub]).tocsr()
    rl = np.r_[form.b_eq, np.full(form.A_ub.shape[0], -np.inf)]
    ru = np.r_[form.b_eq, form.b_ub]
    prob = MIQP(None, c, 0.0, A, rl, ru, lb, ub, form.integrality)
    res = make_solver(prob, "highs").solve(gap=GAP, node_limit=NODE_LIMIT)
    if res.status not in ("optimal", "time_limit") or res.w is None or not np.isfinite(res.bound):
        raise RuntimeError(f"the enclosure's MILP (output {j}, {'max' if sense > 0 else 'min'}) was not solved: "
                           f"{res.status} {res.message}")
    return -sense * float(res.bound), np.clip(res.w[form.x], lo, hi)


def affine_enclosure(net: ReLUNet, lo: Array, hi: Array, seed: int = 0,
                     cache: bool = True) -> AffineEnclosure:
    """The affine enclosure of ``net`` over the box ``[lo, hi]`` (see the module's docstring).

    Parameters
    ----------
    net
        ``Phi_NN``.
    lo, hi
        The box, (n_in,) each, of positive width.
    seed
        Of the sample that fits ``a`` and checks the result.
    cache
        Keep the result in this process for this network (its :func:`fingerprint`), box and seed (the MILPs take
        seconds on a (20, 20, 20) network): a later call returns it.

    Raises
    ------
    RuntimeError
        When a MILP is not solved, or when a point of the check sample lies outside the proved bounds (a solver's
        bound that does not hold: nothing is returned then).
    """
    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise TypeError(f"seed must be a non-negative integer, got {seed!r}")
    if not isinstance(cache, bool):
        raise TypeError(f"cache must be True or False, got {cache!r}")
    lo2, hi2, batch = check_boxes(lo, hi, net.n_in)
    if batch:
        raise ValueError(f"lo and hi must be one box of shape ({net.n_in},), got {np.shape(lo)}")
    lo, hi = lo2[0], hi2[0]
    if not np.all(hi > lo):
        raise ValueError(f"the box must have positive width on every input: lo = {lo}, hi = {hi}")
    key = (fingerprint(net), lo.tobytes(), hi.tobytes(), int(seed))
    if cache and key in _CACHE:
        return _CACHE[key]
    X = np.random.default_rng(seed).uniform(lo, hi, size=(N_SAMPLE, net.n_in))
    enc = _compute(net, lo, hi, X, key[0])
    if cache:
        _CACHE[key] = enc
    return enc


def _compute(net: ReLUNet, lo: Array, hi: Array, X: Array, net_id: str) -> AffineEnclosure:
    """The MILPs of :func:`affine_enclosure` and the check of the result on the sample ``X``."""
    if net.K == 1:  # no hidden layer: Phi_NN(x) = W x + b is its own enclosure, exact
        W, b = net.W[0], net.b[0]
        pad = PAD * np.maximum(1.0, np.abs(b))
        x0 = np.repeat(lo[None], net.n_out, axis=0)
        return _checked(net, AffineEnclosure(W.copy(), b - pad, b + pad, lo.copy(), hi.copy(), x0, x0.copy(), net_id),
                        X)
    a = _fit(net, lo, hi, X)
    form = bigm_form(net, lp_bounds(net, lo, hi))
    r_lo, r_hi = np.zeros(net.n_out), np.zeros(net.n_out)
    x_lo, x_hi = np.zeros((net.n_out, net.n_in)), np.zeros((net.n_out, net.n_in))
    for j in range(net.n_out):
        r_hi[j], x_hi[j] = _extreme(net, form, lo, hi, a[j], j, 1.0)
        r_lo[j], x_lo[j] = _extreme(net, form, lo, hi, a[j], j, -1.0)
    r_hi += PAD * np.maximum(1.0, np.abs(r_hi))
    r_lo -= PAD * np.maximum(1.0, np.abs(r_lo))
    return _checked(net, AffineEnclosure(a, r_lo, r_hi, lo.copy(), hi.copy(), x_lo, x_hi, net_id), X)


def _checked(net: ReLUNet, enc: AffineEnclosure, X: Array) -> AffineEnclosure:
    """``enc``, once it holds at the sample ``X``, the witnesses and the box's two corners (else RuntimeError)."""
    pts = np.vstack([X, enc.x_lo, enc.x_hi, enc.lo, enc.hi])
    if not enc._contains(net, pts):
        r = enc._residual(net, pts)
        raise RuntimeError(f"the enclosure's proved bounds [{enc.r_lo}, {enc.r_hi}] do not hold at every sampled point "
                           f"(residuals from {r.min(axis=0)} to {r.max(axis=0)}): a solver's bound is wrong; "
                           "nothing is returned")
    return enc


def check_enclosure(net: ReLUNet, enc: AffineEnclosure, seed: int = 0) -> None:
    """Raise ValueError unless ``enc`` is of ``net`` (same :func:`fingerprint`) and holds at a fixed sample of its box
    (:data:`N_SAMPLE` points), its witnesses and its corners: the check an enclosure given by a caller gets (a sample
    cannot prove the bounds, but it finds any that were shifted, swapped or computed for another box)."""
    if not isinstance(enc, AffineEnclosure):
        raise TypeError(f"expected a flnotes.AffineEnclosure, got {type(enc).__name__}")
    if enc.net_id != fingerprint(net):
        raise ValueError("the enclosure was computed for another network (its parameters differ): compute it with "
                         "fl.affine_enclosure(net, lo, hi)")
    if enc.a.shape != (net.n_out, net.n_in):
        raise ValueError(f"the enclosure's a has shape {enc.a.shape}, the network needs ({net.n_out}, {net.n_in})")
    X = np.random.default_rng(seed).uniform(enc.lo, enc.hi, size=(N_SAMPLE, net.n_in))
    try:
        _checked(net, enc, X)
    except RuntimeError as exc:
        raise ValueError(f"the enclosure does not hold for this network: {exc}") from None


def outer_rows(enc: AffineEnclosure, T: Array, Zf: Array, u: Array, nz: int,
               z0_inside: bool = True) -> tuple[Array, Array, Array]:
    """The slab of every predicted step as rows over the plan: ``(G, g_lo, g_hi)`` with ``g_lo <= G V <= g_hi``.

    ``T`` (N_p, n_in, N_p m) maps the plan to the network inputs ``[z(k); v(k)] = T[k] V + [Zf[k]; 0]``, ``Zf``
    (N_p + 1, n_z) the free response; ``u`` the output bound. Step 0's rows are left out when ``z(0)`` lies
    outside the enclosure's box (``z0_inside`` False): the enclosure says nothing there.
    """
    s_lo, s_hi = enc._slab(u)
    N = T.shape[0]
    ks = [k for k in range(N) if k > 0 or z0_inside]
    G = np.vstack([enc.a @ T[k] for k in ks])                                  # (len(ks) n_out, N_p m)
    off = np.concatenate([enc.a[:, :nz] @ Zf[k] for k in ks])
    return G, np.tile(s_lo, len(ks)) - off, np.tile(s_hi, len(ks)) - off


def contract(enc: AffineEnclosure, lo: Array, hi: Array, u: Array, rounds: int = 2) -> tuple[Array, Array]:
    """Boxes ``lo, hi`` (T, n_in) cut to the slab ``s_lo <= a x <= s_hi`` (:meth:`AffineEnclosure.slab` of ``u``).

    Interval propagation on each output's row: input ``i`` is bounded by what the row leaves it when every other
    input takes its most favourable end, ``rounds`` times over the inputs. Every point of a box that lies in the slab
    stays, so a box that held every admissible point still does (exact); a box left without any has ``lo > hi``
    somewhere. Only boxes inside the enclosure's box may be cut (the slab says nothing outside).
    """
    lo, hi = np.array(lo, float), np.array(hi, float)
    s_lo, s_hi = enc._slab(u)
    for _ in range(int(rounds)):
        for j, a in enumerate(enc.a):
            pos, neg = np.maximum(a, 0.0), np.minimum(a, 0.0)
            for i in np.flatnonzero(np.abs(a) > 1e-12 * np.abs(a).max()):
                mn = lo @ pos + hi @ neg - (a[i] * (lo[:, i] if a[i] > 0 else hi[:, i]))  # min of the rest
                mx = hi @ pos + lo @ neg - (a[i] * (hi[:, i] if a[i] > 0 else lo[:, i]))  # max of the rest
                top, bottom = (s_hi[j] - mn) / a[i], (s_lo[j] - mx) / a[i]
                if a[i] < 0:
                    top, bottom = bottom, top
                hi[:, i] = np.minimum(hi[:, i], top)
                lo[:, i] = np.maximum(lo[:, i], bottom)
    return lo, hi
