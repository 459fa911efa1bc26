"""Two inputs, exactly: the linear regions of ``v -> Phi_NN(z, v)`` in the ``v``-plane.

With ``z`` fixed the network ``Phi_NN(z, .)`` is continuous and piecewise affine
in ``v``: on each *linear region* ``R_r`` (a convex polygon of the ``v``-box,
where the activation pattern of every hidden neuron is constant) it equals
``A_r v + c_r``. For two inputs this module

* lists those regions (:func:`network_regions`): starting from the ``v``-box,
  layer by layer, each region is cut by the lines ``P_j v + p_j = 0`` of the
  neurons of the next layer whose pre-activation changes sign on it (the
  pre-activations of layer ``k`` are affine on a region of layers ``< k``);
  neurons that keep one sign on a region (almost all: a region is small) cost
  one evaluation at its vertices;
* gives the input sets of eq. (contraint_new_set) as polygons: the true
  ``V(z) = {v in box : |Phi(z, v)| <= u_max}`` when ``Phi`` is affine in ``v``
  (any input-affine plant, e.g. computed torque: :func:`admissible_polygon`),
  and the network's ``{v in box : |Phi_NN(z, v)| <= u_max^eps}`` of eq.
  (Phi_NN_ep), a union of convex polygons (:func:`network_polygons`);
* solves the CLF-CBF program of eq. (CLF_CBF) exactly
  (:func:`solve_exact_2d`): on each region the network constraint
  (CLF_CBF_b) is the four half-planes ``|A_r v + c_r| <= u_max^eps``, the CBF
  rows (CLF_CBF_d) more half-planes, so the feasible set is a union of
  convex polygons; the objective ``J(v) + max(0, a_V^T v + b_V)`` (the
  optimal ``delta`` of (CLF_CBF_c)) is minimized on each in closed form (a
  vertex for the linear cost, eq. LP_cost; a projection for the quadratic
  cost, eq. QP_cost), and the best is kept. The regions are visited best
  first (least lower bound of the cost) and dropped as soon as interval bounds
  of the output or a lower bound of the cost rule them out, so only a few are
  ever solved. This is the
  two-input analogue of :func:`flnotes.solve_exact_1d`;
  :func:`solve_exact_2d` is the solve of :class:`flnotes.ClfCbfController`
  with ``backend="exact"`` (the default) for two inputs, and :func:`compare_exact_mip` checks it
  against a MIP back-end state by state.

Three or more inputs would make the regions polytopes; this module is for two.

Polygons are arrays of vertices (k, 2) in counter-clockwise order.
"""
from __future__ import annotations

import heapq
import itertools
from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence

import numpy as np

from ._checks import as_state, as_vector
from .network import ReLUNet
from .systems import FLSystem

Array = np.ndarray

__all__ = ["LinearRegions", "network_regions", "admissible_polygon", "network_polygons", "input_sets", "affine_in_v",
           "clip_polygon", "polygon_area", "solve_exact_2d",
           "compare_exact_mip"]

_TOL = 1e-11


# ---------------------------------------------------------------------------
# Convex polygons
# ---------------------------------------------------------------------------
def _next(a: Array) -> Array:
    """``a`` shifted by one along its first axis (``np.roll(a, -1, axis=0)``, without its overhead)."""
    return np.concatenate((a[1:], a[:1]))


def _box_polygon(v_lo: Array, v_hi: Array) -> Array:
    (a, b), (c, d) = v_lo, v_hi
    return np.array([[a, b], [c, b], [c, d], [a, d]], float)


def _cut(V: Array, s: Array) -> tuple[Array, Array]:
    """Split the convex polygon ``V`` by the affine function with values ``s`` at its vertices.

    Returns the parts where ``s <= 0`` and ``s >= 0`` (each (k, 2), possibly empty),
    both counter-clockwise like ``V``; the new vertices lie on the line ``s = 0``.
    """
    sn = _next(s)
    cross = s * sn < 0
    Vn = _next(V)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(cross, s / (s - sn), 0.0)
    X = V + t[:, None] * (Vn - V)
    seq = np.stack([V, X], axis=1).reshape(-1, 2)
    neg = np.stack([s <= 0, cross], axis=1).ravel()
    pos = np.stack([s >= 0, cross], axis=1).ravel()
    return seq[neg], seq[pos]


def _snap(s: Array, scale: float) -> Array:
    """Values within rounding of zero are zero: no sliver polygons along a line through a vertex."""
    return np.where(np.abs(s) <= _TOL * scale, 0.0, s)


def _split_along(polygons: list, a: Array, b: float, scale: Optional[float] = None) -> list:
    """Every convex polygon cut in two by the line ``a^T v + b = 0`` where the line crosses it.

    Values within rounding of zero (``_TOL * scale``; by default the size of
    ``a^T v + b`` on the polygon) count as on the line, so no sliver is made.
    """
    out = []
    for Q in polygons:
        s = Q @ a + b
        sc = (1.0 + np.abs(Q).max() * np.abs(a).sum() + abs(b)) if scale is None else scale
        s = _snap(s, sc)
        if s.min() < 0 < s.max():
            out.extend(_cut(Q, s))
        else:
            out.append(Q)
    return out


def clip_polygon(V: Array, a: Array, b: float) -> Array:
    """The part of the convex polygon ``V`` (k, 2) where ``a^T v + b <= 0``; (0, 2) when empty."""
    V = np.asarray(V, float).reshape(-1, 2)
    if not len(V):
        return V
    a = np.asarray(a, float).reshape(2)
    s = V @ a + b
    s = _snap(s, max(1.0, float(np.abs(V).max() * np.abs(a).sum() + abs(b))))
    if np.all(s <= 0):
        return V
    if np.all(s > 0):
        return np.zeros((0, 2))
    return _cut(V, s)[0]


def polygon_area(V: Array) -> float:
    """Area of a polygon (k, 2) by the shoelace formula (positive for counter-clockwise)."""
    V = np.asarray(V, float).reshape(-1, 2)
    if len(V) < 3:
        return 0.0
    x, y = V[:, 0], V[:, 1]
    return 0.5 * float(x @ _next(y) - y @ _next(x))


def _clip_all(V: Array, G: Array, h: Array) -> Array:
    """``V`` cut by every half-plane ``G_j v + h_j <= 0``."""
    for a, b in zip(G, h):
        V = clip_polygon(V, a, b)
        if not len(V):
            break
    return V


def _project(V: Array, c: Array) -> Array:
    """The point of the convex polygon ``V`` nearest to ``c`` (``V`` may be degenerate: a segment or a point)."""
    E = _next(V) - V
    D = c - V
    if len(V) >= 3 and polygon_area(V) > 1e-14 and np.all(E[:, 0] * D[:, 1] - E[:, 1] * D[:, 0] >= 0):
        return c.copy()
    L2 = np.einsum("ij,ij->i", E, E)
    t = np.clip(np.einsum("ij,ij->i", D, E) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
    Q = V + t[:, None] * E
    return Q[np.argmin(np.einsum("ij,ij->i", Q - c, Q - c))]


# ---------------------------------------------------------------------------
# Linear regions of the network in v
# ---------------------------------------------------------------------------
def _two_input_state(net: ReLUNet, z: Array, who: str) -> Array:
    """``z`` as a vector, checked against a network over ``(z, v)`` with two inputs ``v`` and a hidden layer."""
    z = np.asarray(z, float).reshape(-1)
    if net.n_in != len(z) + 2:
        raise ValueError(f"{who} works in the plane of two inputs v: the network has n_in = {net.n_in} inputs and z "
                         f"has {len(z)} entries (need n_in = len(z) + 2)")
    if net.K < 2:
        raise ValueError(f"{who} needs a network with at least one hidden layer (an affine map has one region)")
    return z


@dataclass
class LinearRegions:
    """``Phi_NN(z, v) = A[r] v + c[r]`` on the convex polygon ``polygons[r]`` (fixed ``z``, two inputs).

    Attributes
    ----------
    polygons
        The regions, a list of (k_r, 2) vertex arrays, counter-clockwise; they tile
        the (possibly clipped) ``v``-box.
    A, c
        The affine map on each region: shapes (R, n_out, 2) and (R, n_out).
    """

    polygons: list
    A: Array
    c: Array

    @property
    def n_regions(self) -> int:
        return len(self.polygons)

    def __len__(self) -> int:
        return len(self.polygons)


def network_regions(net: ReLUNet, z: Array, v_lo: Array, v_hi: Array,
                    G: Optional[Array] = None, h: Optional[Array] = None) -> LinearRegions:
    """All linear regions of ``v -> Phi_NN(z, v)`` on the box ``[v_lo, v_hi]`` for a fixed ``z`` (two inputs).

    The network input is ``y^0 = [z, v]`` (eq. MIP_general_a). The
    pre-activations of the first layer, ``W^1 y^0 + b^1``, are affine in
    ``v``: ``P v + p``. On a region where the activation pattern of layers
    ``< k`` is fixed (``D = diag(pattern)``), layer ``k``'s pre-activations are
    affine too (``W^k D (P v + p) + b^k``), so each region is cut along the
    lines of the neurons of layer ``k`` whose pre-activation takes both signs
    at its vertices (exact: it is affine there); the others keep their sign on
    the whole region. After the last hidden layer the output is affine on
    each region.

    Parameters
    ----------
    net
        A network with input ``[z, v]``, ``v`` of two entries (``n_in = len(z) + 2``).
    z
        The fixed state, shape (n_in - 2,).
    v_lo, v_hi
        The ``v``-box, shape (2,).
    G, h
        Optional half-planes ``G v + h <= 0`` (shapes (q, 2), (q,)) that cut the
        box first (e.g. the CBF rows, which do not depend on the network):
        only regions meeting them are listed.

    Returns
    -------
    LinearRegions
    """
    z = _two_input_state(net, z, "network_regions")
    v_lo, v_hi = as_vector(v_lo, 2, "v_lo"), as_vector(v_hi, 2, "v_hi")
    if np.any(v_lo >= v_hi):
        raise ValueError(f"need v_lo < v_hi, got {v_lo} and {v_hi}")
    V0 = _box_polygon(v_lo, v_hi)
    if G is not None:
        G = np.asarray(G, float).reshape(-1, 2)
        h = np.asarray(h, float).reshape(-1)
        if len(h) != len(G):
            raise ValueError(f"G (q, 2) and h (q,) must have as many rows, got {G.shape} and {h.shape}")
        V0 = _clip_all(V0, G, h)
    n_out = net.n_out
    if not len(V0):
        return LinearRegions([], np.zeros((0, n_out, 2)), np.zeros((0, n_out)))
    W1 = net.W[0]
    regions = [(V0, W1[:, -2:], W1[:, :-2] @ z + net.b[0])]
    scale = max(1.0, float(np.abs(v_hi - v_lo).max()))
    for k in range(1, net.K):
        Wk, bk = net.W[k], net.b[k]
        new = []
        for V, P, p in regions:
            S = V @ P.T + p
            sc = scale * (np.abs(P).sum(1) + np.abs(p) + 1.0)
            S = np.where(np.abs(S) <= _TOL * sc, 0.0, S)
            js = np.flatnonzero((S.min(0) < 0) & (S.max(0) > 0))
            parts = [V]
            for j in js:
                parts = _split_along(parts, P[j], p[j], scale=sc[j])
            for Q in parts:
                on = (Q.mean(0) @ P.T + p) > 0
                DP, Dp = P * on[:, None], p * on
                new.append((Q, Wk @ DP, Wk @ Dp + bk))
        regions = new
    return LinearRegions([r[0] for r in regions], np.array([r[1] for r in regions]),
                         np.array([r[2] for r in regions]))


# ---------------------------------------------------------------------------
# The input sets as polygons
# ---------------------------------------------------------------------------
def affine_in_v(system: FLSystem, z: Array, rtol: float = 1e-9) -> tuple[Array, Array]:
    """``Phi(z, v) = beta(z) v + alpha(z)``: the matrix ``beta`` (m, m) and ``alpha`` (m,) at one ``z``.

    Exact for any plant affine in its input (``x' = f_0(x) + g(x) u``), whose
    linearizing map is affine in ``v``. Checked at random points of the ``v``-box:
    a map that is not affine in ``v`` raises ``ValueError``.
    """
    z = as_state(z, system.n_z, "z")
    m = system.m
    I = np.vstack([np.zeros(m), np.eye(m)])
    U = system.Phi(np.repeat(z[None], m + 1, axis=0), I)
    alpha, beta = U[0], (U[1:] - U[0]).T
    rng = np.random.default_rng(0)
    Vt = rng.uniform(system.lo[system.n_z:], system.hi[system.n_z:], (8, m))
    Ut = system.Phi(np.repeat(z[None], 8, axis=0), Vt)
    err = np.abs(Ut - (Vt @ beta.T + alpha))
    if np.any(err > rtol * (1.0 + np.abs(Ut))):
        raise ValueError(f"Phi of {system.name} is not affine in v at z = {z.tolist()} (deviation "
                         f"{err.max():.3g}): its input set is not a polygon; use network_polygons for the network's")
    return beta, alpha


def admissible_polygon(system: FLSystem, z: Array, u_bound: Optional[Array] = None) -> Array:
    """``V(z) = {v in v-box : |Phi(z, v)| <= u_max}`` of eq. (contraint_new_set) as a convex polygon.

    For a map affine in ``v`` (see :func:`affine_in_v`) each bound
    ``|beta_i v + alpha_i| <= u_max,i`` is a strip; ``V(z)`` is the ``v``-box cut
    by the ``2 m`` half-planes. Two inputs only.

    Parameters
    ----------
    system
        A system with ``m = 2`` whose ``Phi`` is affine in ``v``.
    z
        The state, shape (n_z,).
    u_bound
        The bound (default ``system.u_max``), shape (2,).

    Returns
    -------
    Array
        Vertices (k, 2), counter-clockwise; (0, 2) when ``V(z)`` is empty.
    """
    if system.m != 2:
        raise ValueError(f"admissible_polygon draws V(z) in the plane of two inputs; {system.name} has m = {system.m}")
    u = system.u_max if u_bound is None else as_vector(u_bound, 2, "u_bound")
    beta, alpha = affine_in_v(system, z)
    n_z = system.n_z
    V = _box_polygon(system.lo[n_z:], system.hi[n_z:])
    return _clip_all(V, np.vstack([beta, -beta]), np.r_[alpha - u, -alpha - u])


def network_polygons(net: ReLUNet, z: Array, v_lo: Array, v_hi: Array, bound: Array,
                     regions: Optional[LinearRegions] = None) -> list:
    """``{v in box : |Phi_NN(z, v)| <= u_max^eps}`` of eq. (Phi_NN_ep) at one ``z``: a list of convex polygons.

    On each linear region (:func:`network_regions`) the bound is ``2 n_out``
    half-planes; the non-empty pieces are returned (they may touch).

    Parameters
    ----------
    net, z, v_lo, v_hi
        As in :func:`network_regions`.
    bound
        ``u_max^eps = u_max - eps``, shape (n_out,).
    regions
        The result of :func:`network_regions`, if already computed.
    """
    R = network_regions(net, z, v_lo, v_hi) if regions is None else regions
    b = as_vector(bound, net.n_out, "bound")
    out = []
    for V, A, c in zip(R.polygons, R.A, R.c):
        Q = _clip_all(V, np.vstack([A, -A]), np.r_[c - b, -c - b])
        if len(Q):
            out.append(Q)
    return out


def input_sets(system: FLSystem, net: ReLUNet, eps: Any, states: Sequence[Array]) -> list:
    """The input sets of a two-input system at a few states, for drawing (:func:`flnotes.plots.multi.input_sets_plot`).

    Parameters
    ----------
    system
        A two-input :class:`flnotes.FLSystem` whose ``Phi`` is affine in ``v``.
    net, eps
        ``Phi_NN`` and its error bound (scalar or shape (2,)).
    states
        The states ``z``, each of shape (n_z,).

    Returns
    -------
    list of dict
        One per state: ``z``; ``true``, the polygon ``V(z)`` of eq. (contraint_new_set)
        (:func:`admissible_polygon`); ``network``, the convex pieces of
        ``{v : |Phi_NN(z, v)| <= u_max - eps}`` (:func:`network_polygons`);
        ``regions``, the linear regions of ``Phi_NN(z, .)`` (:func:`network_regions`);
        ``v_lo``, ``v_hi``, the ``v``-box.
    """
    if system.m != 2:
        raise ValueError(f"input_sets works in the plane of two inputs; {system.name} has m = {system.m}")
    eps = np.broadcast_to(np.asarray(eps, float), (2,))
    n_z = system.n_z
    v_lo, v_hi = system.lo[n_z:], system.hi[n_z:]
    out = []
    for z in states:
        z = as_state(z, n_z, "z")
        R = network_regions(net, z, v_lo, v_hi)
        out.append(dict(z=z, true=admissible_polygon(system, z),
                        network=network_polygons(net, z, v_lo, v_hi, system.u_max - eps, regions=R),
                        regions=R, v_lo=v_lo.copy(), v_hi=v_hi.copy()))
    return out


# ---------------------------------------------------------------------------
# The exact CLF-CBF solve for two inputs
# ---------------------------------------------------------------------------
def _objective(v: Array, d: dict, cost: str) -> tuple[float, float]:
    """``J(v) + delta*(v)`` and ``delta*(v) = max(0, a_V^T v + b_V)``."""
    delta = max(0.0, float(d["aV"] @ v + d["bV"]))
    J = float(d["aV"] @ v + d["Jc"]) if cost == "linear" else float((v - d["k"]) @ (v - d["k"]))
    return J + delta, delta


def _best_on_polygon(F: Array, d: dict, cost: str) -> Array:
    """Minimizer of ``J(v) + max(0, a_V^T v + b_V)`` over the convex polygon ``F`` (closed form)."""
    aV = d["aV"]
    if cost == "linear":
        # J + delta* = a_V^T v + J_c + max(0, a_V^T v + b_V) is non-decreasing in a_V^T v: a vertex minimizes it
        return F[np.argmin(F @ aV)]
    # Qcost: ||v - k||^2 on {a_V^T v + b_V <= 0}, ||v - (k - a_V/2)||^2 + const on the other side
    s = F @ aV + d["bV"]
    s = np.where(np.abs(s) <= _TOL * (1.0 + np.abs(F).max() * np.abs(aV).sum() + abs(d["bV"])), 0.0, s)
    F0, F1 = _cut(F, s) if s.min() < 0 < s.max() else ((F, F[:0]) if s.max() <= 0 else (F[:0], F))
    cand = []
    if len(F0):
        cand.append(_project(F0, d["k"]))
    if len(F1):
        cand.append(_project(F1, d["k"] - aV / 2))
    vals = [_objective(v, d, cost)[0] for v in cand]
    return cand[int(np.argmin(vals))]


def _hinges(A: Array, c: Array, d: dict, bound: Array, rho: tuple[float, float]) -> tuple[Array, Array, Array]:
    """The hinges ``w_j max(0, G_j v + e_j)`` of the softened objective on a region where ``Phi_NN = A v + c``.

    Rows: the CLF condition (CLF_CBF_c) (weight 1: the optimal ``delta``), the input bound
    ``+-(A_i v + c_i) - u_max^eps_i`` (weight ``rho_u``) and the CBF rows ``-(a_H v + b_H)`` (``rho_H``).
    """
    Gs = [d["aV"][None], A, -A]
    es = [np.array([d["bV"]]), c - bound, -c - bound]
    ws = [np.ones(1), np.full(len(c), rho[0]), np.full(len(c), rho[0])]
    if len(d["bH"]):
        Gs.append(-d["aH"])
        es.append(-d["bH"])
        ws.append(np.full(len(d["bH"]), rho[1]))
    return np.vstack(Gs), np.concatenate(es), np.concatenate(ws)


def _hinged_values(X: Array, G: Array, e: Array, w: Array, d: dict, cost: str) -> Array:
    """``J(v) + sum_j w_j max(0, G_j v + e_j)`` at the points ``X`` (n, 2)."""
    J = X @ d["aV"] + d["Jc"] if cost == "linear" else np.einsum("ij,ij->i", X - d["k"], X - d["k"])
    return J + np.maximum(0.0, X @ G.T + e) @ w


def _best_soft(V: Array, A: Array, c: Array, d: dict, cost: str, bound: Array, rho: tuple[float, float]) -> Array:
    """Minimizer of the softened objective on one linear region ``V`` where ``Phi_NN = A v + c``.

    The objective ``f(v) = J(v) + sum_j w_j max(0, G_j v + e_j)`` (:func:`_hinges`) is convex; the
    hinge lines ``G_j v + e_j = 0`` cut ``V`` into cells where ``f`` is ``J`` plus an affine function.
    Its minimizer over ``V`` lies in a cell's interior, inside an edge of a cell, or at a vertex. Every
    cell edge is a piece of a *segment*: a hinge line clipped to ``V`` or an edge of ``V``, cut at the
    points where the other lines cross it. So the candidates, all computed at once, are

    * on every piece ``[t_a, t_b]`` of a segment ``p + t u``: the minimizer of the piece's smooth function
      ``J + g^T v`` along the segment, clipped to the piece (a piece endpoint for the linear cost, where
      ``f`` is affine along the piece); by convexity of ``f`` along the segment, a minimizer at a vertex is
      the clipped point of the piece on its right or left;
    * in every cell adjacent to a piece (the active set at the piece's midpoint, with the segment's own
      hinge off and on): the unconstrained minimizer ``k - g/2`` of ``||v - k||^2 + g^T v`` (quadratic cost),
      kept when it lies in ``V``.

    Every candidate is a point of ``V``, and the minimizer is among them: the best one is returned (the
    same point the cell-by-cell enumeration gives, without building the cells).
    """
    G, e, w = _hinges(A, c, d, bound, rho)
    V = np.asarray(V, float)
    # the segments: the edges of V and each hinge line clipped to V (its chord: the extreme points, along the
    # line, of its crossings with the edges and of the vertices on it)
    Vn = _next(V)
    S = V @ G.T + e                                      # (n_v, L)
    Sn = _next(S)
    cross = S * Sn < 0
    on = cross | (S == 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(cross, S / np.where(cross, S - Sn, 1.0), 0.0)
    X = V[:, None, :] + t[..., None] * (Vn - V)[:, None, :]          # (n_v, L, 2)
    s = np.einsum("vlk,lk->vl", X, np.column_stack([G[:, 1], -G[:, 0]]))   # position along each line
    i0 = np.argmin(np.where(on, s, np.inf), axis=0)
    i1 = np.argmax(np.where(on, s, -np.inf), axis=0)
    L = np.arange(len(e))
    chord = on.any(0) & (s[i1, L] > s[i0, L])
    own = np.r_[np.full(len(V), -1), L[chord]]
    P0 = np.vstack([V, X[i0[chord], L[chord]]])
    P1 = np.vstack([Vn, X[i1[chord], L[chord]]])
    U = P1 - P0                                          # (n_s, 2)
    Gu = U @ G.T                                         # (n_s, L)
    Gp = P0 @ G.T + e
    with np.errstate(divide="ignore", invalid="ignore"):
        T = np.where(np.abs(Gu) > 1e-15, -Gp / Gu, 0.0)
    T = np.sort(np.clip(np.concatenate([np.zeros((len(U), 1)), T, np.ones((len(U), 1))], axis=1), 0.0, 1.0), axis=1)
    ta, tb = T[:, :-1], T[:, 1:]                         # the pieces (n_s, L + 1)
    if cost == "linear":
        X = P0[:, None, :] + T[:, :, None] * U[:, None, :]
        X = X.reshape(-1, 2)
    else:
        tm = 0.5 * (ta + tb)
        Mid = P0[:, None, :] + tm[:, :, None] * U[:, None, :]
        act = (Mid @ G.T + e) > 0                        # (n_s, L + 1, L)
        if np.any(own >= 0):
            rows = np.flatnonzero(own >= 0)
            act[rows, :, own[rows]] = False              # the segment's own hinge: off, then on below
        g = (act * w) @ G                                # (n_s, L + 1, 2)
        uu = np.einsum("ij,ij->i", U, U)
        lin = 2.0 * np.einsum("ij,ij->i", U, P0 - d["k"])[:, None] + np.einsum("skj,sj->sk", g, U)
        with np.errstate(divide="ignore", invalid="ignore"):
            ts = np.where(uu[:, None] > 0, -lin / (2.0 * uu[:, None]), 0.0)
        ts = np.clip(ts, ta, tb)
        on_seg = P0[:, None, :] + ts[:, :, None] * U[:, None, :]
        cells = [d["k"] - 0.5 * g]
        if np.any(own >= 0):
            rows = np.flatnonzero(own >= 0)
            cells.append(d["k"] - 0.5 * (g[rows] + w[own[rows]][:, None, None] * G[own[rows]][:, None, :]))
        inner = np.vstack([x.reshape(-1, 2) for x in cells])
        E = _next(V) - V
        D = inner[:, None, :] - V[None]
        inside = np.all(E[None, :, 0] * D[..., 1] - E[None, :, 1] * D[..., 0] >= 0, axis=1)
        X = np.vstack([on_seg.reshape(-1, 2), inner[inside]])
    f = _hinged_values(X, G, e, w, d, cost)
    return X[int(np.argmin(f))]


def _tail_bounds(net: ReLUNet, k: int, lo: Array, hi: Array, split: Optional[list] = None) -> tuple[Array, Array]:
    """Interval bounds of the output from the pre-activation box ``[lo, hi]`` of hidden layer ``k`` (0-based).

    ``split`` may hold ``(max(W, 0), min(W, 0), b)`` of every layer (computed once per solve).
    """
    split = split or [(np.maximum(W, 0.0), np.minimum(W, 0.0), b) for W, b in zip(net.W, net.b)]
    lo, hi = np.maximum(lo, 0.0), np.maximum(hi, 0.0)
    last = len(split) - 1
    for i in range(k + 1, len(split)):
        Wp, Wn, b = split[i]
        lo, hi = Wp @ lo + Wn @ hi + b, Wp @ hi + Wn @ lo + b
        if i < last:
            lo, hi = np.maximum(lo, 0.0), np.maximum(hi, 0.0)
    return lo, hi


def _lower_bound(V: Array, d: dict, cost: str) -> float:
    """A lower bound of ``J(v) + max(0, a_V^T v + b_V)`` on the polygon ``V`` (exact for the linear cost)."""
    s = V @ d["aV"]
    if cost == "linear":
        t = s.min()
        return float(t + d["Jc"] + max(0.0, t + d["bV"]))
    gap = np.maximum(0.0, np.maximum(V.min(0) - d["k"], d["k"] - V.max(0)))
    return float(gap @ gap + max(0.0, s.min() + d["bV"]))


def _into_bound(v: Array, F: Array, admissible: Callable[[Array], bool], steps: int = 60) -> Optional[Array]:
    """``v``, a minimizer on the convex polygon ``F`` whose forward pass breaks the bound by round-off, moved toward
    ``F``'s vertex mean to the first point (by bisection on the segment) that ``admissible`` accepts; ``None`` when
    that mean is not admissible either (``F`` a sliver on the bound, at the edge of feasibility: no point of it
    passes the forward-pass check, and the region counts as empty).

    The vertices of ``F`` are intersections of lines computed in floating point: at one of them the forward pass
    was measured 1.0e-12 over ``u_max^eps``, which the controller's check (to the forward pass's round-off) refused,
    and the step ended in ``"error"``. The move is by as little as bisection finds, so the cost changes by round-off
    too."""
    c = F.mean(0)
    if not admissible(c):
        return None
    lo, hi = 0.0, 1.0  # v + t (c - v): t = hi is admissible
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if admissible(v + mid * (c - v)):
            hi = mid
        else:
            lo = mid
    return v + hi * (c - v)


def solve_exact_2d(net: ReLUNet, z: Array, d: dict, cost: str, bound: Array, v_lo: Array, v_hi: Array,
                   soft: bool = False, rho: tuple[float, float] = (1e6, 1e4),
                   stats: Optional[dict] = None) -> Optional[tuple[Array, float, float]]:
    """Minimize the cost of eq. (CLF_CBF) over ``v`` exactly, for two inputs.

    ``d`` holds the data of the program at the current ``z``
    (:meth:`flnotes.ClfCbfController.program_data`: ``aV``, ``bV``, ``Jc``,
    ``aH``, ``bH``, ``k``). On a linear region ``R_r`` of ``Phi_NN(z, .)``
    (see :func:`network_regions`) the feasible set is the convex polygon
    ``R_r`` cut by ``|A_r v + c_r| <= u_max^eps`` (CLF_CBF_b) and
    ``a_H v + b_H >= 0`` (CLF_CBF_d); there ``J(v) + delta*(v)`` with
    ``delta*(v) = max(0, a_V^T v + b_V)`` (the least ``delta`` of (CLF_CBF_c)) is
    convex and minimized in closed form: for the linear cost (eq. LP_cost) at
    the vertex minimizing ``a_V^T v``; for the quadratic cost (eq. QP_cost) by
    projecting ``k(z)`` onto the part where ``a_V^T v + b_V <= 0`` and
    ``k(z) - a_V / 2`` onto the other part. The best region wins.

    The regions are not all listed: they are found by a best-first branch and
    bound over the cuts of :func:`network_regions` (the ``v``-box first cut by
    the CBF rows, which do not depend on the network). A partial region is
    dropped when the interval bounds of the network's output, propagated from
    its exact pre-activation ranges (an affine function's extremes on a
    polygon are at its vertices), exclude ``|Phi_NN| <= u_max^eps``, or when a
    lower bound of the cost on it cannot beat the best point found; the partial
    region with the least lower bound is split next, so the search stops as soon
    as no region left can beat the best point. Before any
    of this, the program without (CLF_CBF_b) is solved on the cut box: if its
    optimum satisfies the network bound it is the answer (screening).

    With ``soft=True`` the softened program of the fallback is solved instead
    (penalties ``rho = (rho_u, rho_H)`` on the violations of the input bound and
    of the CBF rows): the whole box, each region's objective minimized by
    :func:`_best_soft` (all candidates of its convex piecewise objective at
    once), regions ordered and dropped by a lower bound that adds the penalties
    of the violations the output's interval bounds and the CBF rows already imply.

    Parameters
    ----------
    net, z
        The network on ``[z, v]`` with two inputs ``v`` and the fixed state.
    d
        The program data.
    cost
        ``"linear"`` or ``"quadratic"``.
    bound
        ``u_max^eps``, shape (n_out,).
    v_lo, v_hi
        The ``v``-box, shape (2,).
    soft, rho
        The softened program and its penalty weights.
    stats
        If a dict is given, the counts ``regions`` (leaves solved), ``nodes``
        (partial regions visited) and ``screened`` are written into it.

    Returns
    -------
    (v, delta, objective), or None when the program is infeasible. Without ``soft``, ``v`` meets
    ``|Phi_NN(z, v)| <= u_max^eps`` by the forward pass with no tolerance, as the single-input method's: a region's
    minimizing vertex over the bound by round-off is moved into the region (:func:`_into_bound`), and a region with
    no point that passes (a sliver on the bound) counts as empty.
    """
    z = _two_input_state(net, z, "solve_exact_2d")
    if cost not in ("linear", "quadratic"):
        raise ValueError(f"cost must be 'linear' or 'quadratic', got {cost!r}")
    bound = as_vector(bound, net.n_out, "bound")
    v_lo, v_hi = as_vector(v_lo, 2, "v_lo"), as_vector(v_hi, 2, "v_hi")
    if np.any(v_lo >= v_hi):
        raise ValueError(f"need v_lo < v_hi, got {v_lo} and {v_hi}")
    st = dict(regions=0, nodes=0, screened=False)
    p = len(d["bH"])
    V0 = _box_polygon(v_lo, v_hi)
    if not soft and p:
        V0 = _clip_all(V0, -d["aH"], -d["bH"])
    if not len(V0):
        if stats is not None:
            stats.update(st)
        return None
    if not soft:   # screening: the program without the network constraint, on the cut box
        v = _best_on_polygon(V0, d, cost)
        if np.all(np.abs(net(np.concatenate([z, v]))) <= bound):
            st["screened"] = True
            if stats is not None:
                stats.update(st)
            f, delta = _objective(v, d, cost)
            return v, delta, f
    scale = max(1.0, float(np.abs(v_hi - v_lo).max()))
    ftol = 1e-9 * np.maximum(1.0, bound)
    best = [None, np.inf]
    W1 = net.W[0]
    split = [(np.maximum(W, 0.0), np.minimum(W, 0.0), b) for W, b in zip(net.W, net.b)]

    def leaf(V: Array, A: Array, c: Array) -> None:
        st["regions"] += 1
        if soft:
            v = _best_soft(V, A, c, d, cost, bound, rho)
            f = float(_hinged_values(v[None], *_hinges(A, c, d, bound, rho), d, cost)[0])
        else:
            F = _clip_all(V, np.vstack([A, -A]), np.r_[c - bound, -c - bound])
            if not len(F):
                return
            v = _best_on_polygon(F, d, cost)
            f = _objective(v, d, cost)[0]
            if f < best[1] and not admissible(v):  # a vertex whose forward pass is over the bound by round-off
                v = _into_bound(v, F, admissible)
                if v is None:  # no point of this region passes the forward-pass check
                    return
                f = _objective(v, d, cost)[0]
        if f < best[1]:
            best[0], best[1] = v, f

    def admissible(v: Array) -> bool:
        """``|Phi_NN(z, v)| <= u_max^eps`` by the forward pass, with no tolerance (the box and the CBF rows are the
        polygon's own, clipped to round-off: requiring them exactly too lost the optimum in a strip 1e-11 wide)."""
        return bool(np.all(np.abs(net(np.concatenate([z, v]))) <= bound))

    def lower(V: Array, olo: Array, ohi: Array) -> float:
        lb = _lower_bound(V, d, cost)
        if soft:
            lb += rho[0] * float(np.maximum(0.0, np.maximum(olo - bound, -ohi - bound)).sum())
            if p:
                lb += rho[1] * float(np.maximum(0.0, -(V @ d["aH"].T + d["bH"]).max(0)).sum())
        return lb

    frontier: list = []
    count = itertools.count()

    def push(V: Array, k: int, P: Array, p_: Array) -> None:
        """Bound the partial region ``V`` (layers ``< k`` fixed, layer ``k``'s pre-activations ``P v + p_``)."""
        S = V @ P.T + p_
        sc = scale * (np.abs(P).sum(1) + np.abs(p_) + 1.0)
        S = np.where(np.abs(S) <= _TOL * sc, 0.0, S)
        lo, hi = S.min(0), S.max(0)
        olo, ohi = _tail_bounds(net, k, lo, hi, split)
        if not soft and np.any((olo > bound + ftol) | (ohi < -bound - ftol)):
            return                                    # no point of V meets |Phi_NN| <= u_max^eps
        lb = lower(V, olo, ohi)
        if lb < best[1]:
            heapq.heappush(frontier, (lb, next(count), V, k, P, p_, S, lo, hi))

    # best first: the partial region with the least lower bound is split next; the search stops when no
    # region left can beat the best point found
    push(V0, 0, W1[:, -2:], W1[:, :-2] @ z + net.b[0])
    while frontier:
        lb, _, V, k, P, p_, S, lo, hi = heapq.heappop(frontier)
        if lb >= best[1]:
            break                                     # cannot beat the best point found
        st["nodes"] += 1
        js = np.flatnonzero((lo < 0) & (hi > 0))
        if len(js):
            j = js[np.argmax(np.minimum(-lo[js], hi[js]) / (hi[js] - lo[js]))]   # the most balanced cut
            for Q in _cut(V, S[:, j]):
                if len(Q):
                    push(Q, k, P, p_)
            continue
        on = (V.mean(0) @ P.T + p_) > 0
        Wn, bn = net.W[k + 1], net.b[k + 1]
        P2, p2 = Wn @ (P * on[:, None]), Wn @ (p_ * on) + bn
        if k + 1 == net.K - 1:
            leaf(V, P2, p2)
        else:
            push(V, k + 1, P2, p2)
    if stats is not None:
        stats.update(st)
    if best[0] is None:
        return None
    v = best[0]
    return v, _objective(v, d, cost)[1], best[1]


# ---------------------------------------------------------------------------
# The back-end for ClfCbfController
# ---------------------------------------------------------------------------
def compare_exact_mip(exact: Any, mip: Any, Z: Array, boundary_tol: float = 1e-7, fresh: bool = False) -> dict:
    """Solve eq. (CLF_CBF) at every state of ``Z`` with two controllers of the same program and compare.

    Parameters
    ----------
    exact, mip
        Two :class:`flnotes.ClfCbfController` for the same program (e.g.
        :func:`exact_pieces_controller` and its ``with_backend("scip")``).
    Z
        States, shape (N, n_z).
    boundary_tol
        An optimum counts as on the network's bound when ``min_i | |Phi_NN,i| - u_max^eps_i | <= boundary_tol``.
    fresh
        Solve each state with a new copy of ``mip`` (``mip.with_backend(mip.backend)``, built
        outside the timed step) instead of one persistent model updated in place. The program
        solved is the same either way: the small margin by which a MIP back-end tightens
        ``u_max^eps`` when its solver's tolerance lets a point through the forward-pass check is
        reset at every solve, so no state's answer depends on the states before it.

    Returns
    -------
    dict
        ``states``, ``max_rel_objective_gap`` (``|J_a - J_b| / max(1, |J_b|)``) over all
        states and ``max_rel_objective_gap_hard`` over those where neither fell back (the
        softened program's large penalties magnify a MIP solver's feasibility tolerance in
        its reported objective), ``same_status`` (count), ``fallback`` (count, first controller),
        ``boundary_optima`` (count), and per controller the wall-clock and CPU
        times per step in ms (``{name}_ms_min``, ``_median``, ``_max``,
        ``{name}_cpu_ms_max``); ``times_s``, the wall-clock times per step in seconds
        (``{"exact": (N,), "mip": (N,)}``, for :func:`flnotes.time_stats`).
    """
    Z = np.atleast_2d(np.asarray(Z, float))
    if Z.shape[1] != exact.system.n_z:
        raise ValueError(f"Z must have shape (N, {exact.system.n_z}), got {Z.shape}")
    gaps, hard, same, fb, bnd = [], [], 0, 0, 0
    t = {"exact": [], "mip": []}
    cpu = {"exact": [], "mip": []}
    for z in Z:
        other = mip.with_backend(mip.backend) if fresh else mip
        a, b = exact.step(z), other.step(z)
        for name, r in (("exact", a), ("mip", b)):
            t[name].append(r.solve_time * 1e3)
            cpu[name].append(r.info["cpu_time"] * 1e3)
        oa, ob = a.objective, b.objective
        gaps.append(abs(oa - ob) / max(1.0, abs(ob)))
        if not (a.fallback or b.fallback):
            hard.append(gaps[-1])
        same += a.status == b.status
        fb += bool(a.fallback)
        if not a.fallback:
            y = np.abs(exact.net(np.concatenate([z, a.v])))
            bnd += bool(np.min(np.abs(y - exact.u_eps)) <= boundary_tol)
    out = dict(states=len(Z), max_rel_objective_gap=float(np.max(gaps)),
               max_rel_objective_gap_hard=float(np.max(hard)) if hard else np.nan, same_status=same, fallback=fb,
               boundary_optima=bnd, times_s={k: np.array(v) * 1e-3 for k, v in t.items()})
    for name in ("exact", "mip"):
        ms, c = np.array(t[name]), np.array(cpu[name])
        out.update({f"{name}_ms_min": float(ms.min()), f"{name}_ms_median": float(np.median(ms)),
                    f"{name}_ms_max": float(ms.max()), f"{name}_cpu_ms_median": float(np.median(c)),
                    f"{name}_cpu_ms_max": float(c.max())})
    return out
