"""One-switch plans at the input bounds: the first incumbent when the repaired relaxation fails.

Where a plan must move the state far (a cold state away from its reference, the input bound active at most
steps), the optimum of eq. (MPC_form_miqp) is often bang-bang: ``v(k)`` at one end of what the network bound
admits, then at the other. The relaxation repaired step by step along the QP without the network
(:func:`flnotes.mpc.fallback.qp_repair`) is greedy and can miss such a plan; the MPC then starts its branch and
bound without an incumbent, and a time limit may leave it with no plan although one exists.

:func:`one_switch_plans` tries the ``2 N_p`` plans ``v(k) = v_hi`` for ``k < s`` then ``v_lo``, and the reverse
(``s = 1..N_p``; ``s = N_p`` is the constant plan), each repaired step by step like
:func:`flnotes.mpc.fallback.repair_plan`, but on a coarser grid searched coarse to fine (:func:`nearest_admissible`).
A plan with its first ``s`` steps at one bound shares its repaired first ``s`` steps with the constant plan, so the
constant plans are repaired first and the switched ones continue from their states, every plan of both directions
in one batch per step. :func:`bang_bang_incumbent` keeps the cheapest plan that passes
:meth:`flnotes.mpc.prediction.Prediction.feasible`: the search only adds incumbents, it never changes the optimum
(``MPCOptions.bang_bang``).
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np

from .fallback import _admissible
from .prediction import Prediction

Array = np.ndarray


#: Points of the grid of :func:`nearest_admissible` over ``[v_lo, v_hi]``: 1/256 of the range, coarser than the
#: fallback's (:data:`flnotes.mpc.fallback.FEASIBLE_TAIL_GRID`); an incumbent is polished afterwards (the region QP).
GRID = 257

#: Every how many points of that grid are tried first (a coarse pass); the fine points between the last
#: inadmissible coarse point and the first admissible one are tried next.
COARSE_STRIDE = 16


def nearest_admissible(pred: Prediction, Z: Array, v: Array, last: bool = False,
                       n_grid: int = GRID) -> tuple[Array, Array]:
    """:func:`flnotes.mpc.fallback.feasible_tail` for one input, row by row, coarse to fine: ``Z`` (K, n_z) states,
    ``v`` (K,) guesses.

    Each ``v[i]`` is kept when admissible at ``Z[i]`` (``|Phi_NN(z, v)| <= u_max^eps``, ``A_d z + B_d v`` in the
    state box and, for the ``last`` step, in the terminal set). Otherwise the points of the grid of
    ``[v_lo, v_hi]`` (``n_grid`` points) are taken in order of distance from ``v[i]``: every
    :data:`COARSE_STRIDE`-th one first; from the first admissible of those, the finer points just before it in that
    order are tried, and the nearest admissible is returned. A row whose coarse points are all inadmissible keeps
    its guess. About ``n_grid / COARSE_STRIDE + COARSE_STRIDE`` forward passes per row instead of up to ``n_grid``,
    for a search that may pass over an admissible sliver narrower than the coarse step (``feasible_tail`` is then
    nearer, or finds an input where this finds none): fit for a heuristic, never for a check. Returns ``(v, ok)``,
    ``ok[i]`` whether ``v[i]`` is admissible.
    """
    Z, v = np.asarray(Z, float), np.array(v, float).reshape(-1)
    if pred.m != 1:
        raise ValueError(f"nearest_admissible searches one input; this program has m = {pred.m}")
    if Z.shape != (v.size, pred.nz):
        raise ValueError(f"Z must have shape ({v.size}, {pred.nz}) (one state per guess), got {Z.shape}")
    good = _admissible(pred, Z, v[:, None], last)
    bad = np.flatnonzero(~good)
    if not bad.size:
        return v, good
    grid = np.linspace(pred.v_lo[0], pred.v_hi[0], n_grid)
    # each row's grid in order of distance from its guess (ties in grid order)
    order = np.argsort(np.abs(grid[None, :] - v[bad, None]), axis=1, kind="stable")
    coarse = (order % COARSE_STRIDE == 0) | (order == n_grid - 1)
    cpos = np.nonzero(coarse)[1].reshape(bad.size, -1)  # positions in ``order`` of the coarse points, nearest first
    rows = np.arange(bad.size)[:, None]
    C = cpos.shape[1]
    ok = _admissible(pred, np.repeat(Z[bad], C, 0), grid[order[rows, cpos]].reshape(-1, 1), last).reshape(-1, C)
    found = ok.any(axis=1)
    if found.any():
        r = np.flatnonzero(found)
        j = np.argmax(ok[r], axis=1)
        hi = cpos[r, j]  # the first admissible coarse point
        lo = np.where(j > 0, cpos[r, np.maximum(j - 1, 0)] + 1, 0)  # just after the last inadmissible one
        width = int(np.max(hi - lo)) + 1
        pos = np.minimum(lo[:, None] + np.arange(width)[None, :], hi[:, None])  # padded with the admissible point
        cand = grid[order[r[:, None], pos]]
        ok2 = _admissible(pred, np.repeat(Z[bad[r]], width, 0), cand.reshape(-1, 1), last).reshape(-1, width)
        v[bad[r]] = cand[np.arange(r.size), np.argmax(ok2, axis=1)]
        good[bad[r]] = True
    return v, good


def one_switch_plans(pred: Prediction, z: Array, deadline: Optional[float] = None
                     ) -> Optional[tuple[Array, Array]]:
    """The ``2 N_p`` one-switch plans at the input bounds from ``z``, repaired step by step.

    Row ``s - 1`` (``s = 1..N_p``) of the plans (2 N_p, N_p): ``v_hi`` for the first ``s`` steps, then ``v_lo``;
    row ``N_p + s - 1``: the reverse (``s = N_p``: the constant plans). Each input is moved to an admissible one
    by :func:`nearest_admissible`. A plan whose repair finds no admissible input at a step is not continued (no
    later step can make it feasible): its later inputs stay at their guesses, and its flag (second array, (2 N_p,))
    is ``False``. One input only. ``None`` when the ``deadline`` (``time.perf_counter()``) passes before every plan
    is built. Check a plan with :meth:`flnotes.mpc.prediction.Prediction.feasible` (the terminal set and the
    boxes are checked there, as for every plan the MPC uses).
    """
    if pred.m != 1:
        raise ValueError(f"one-switch plans are built for one input; this program has m = {pred.m}")
    z = np.asarray(z, float).reshape(pred.nz)
    N = pred.N
    s = np.tile(np.arange(1, N + 1), 2)  # the switch of each row
    first = np.repeat([pred.v_hi[0], pred.v_lo[0]], N)
    V = np.where(np.arange(N)[None, :] < s[:, None], first[:, None], first[::-1][:, None])
    const = np.array([N - 1, 2 * N - 1])  # the constant plans
    alive = np.ones(2 * N, bool)
    # the rows of one direction share their first steps with its constant plan: the row switching after s steps
    # starts its own path at the constant plan's z(s)
    Z = np.repeat(z[None], 2 * N, 0)
    for k in range(N):
        if deadline is not None and time.perf_counter() > deadline:
            return None
        act = np.flatnonzero(((s <= k) | (s == N)) & alive)  # the constant plans and the rows switched before k
        if act.size:
            V[act, k], ok = nearest_admissible(pred, Z[act], V[act, k], last=k == N - 1)
            alive[act[~ok]] = False
            Z[act] = Z[act] @ pred.Ad.T + V[act, k, None] @ pred.Bd.T
        if k + 1 < N:  # the rows switching after k + 1 steps leave the constant plans here
            nxt = const - (N - 1 - k)
            Z[nxt], V[nxt, : k + 1], alive[nxt] = Z[const], V[const, : k + 1], alive[const]
    return V, alive


def bang_bang_incumbent(pred: Prediction, z: Array, f: Array, c0: float,
                        deadline: Optional[float] = None) -> Optional[tuple[Array, float]]:
    """The cheapest of :func:`one_switch_plans` that passes :meth:`Prediction.feasible`: ``(V flat, J)``, or ``None``
    (none passes, or the ``deadline`` came first). ``f``, ``c0``: the cost's linear part and constant
    (:meth:`Prediction.linear`)."""
    out = one_switch_plans(pred, z, deadline)
    if out is None:
        return None
    best = None
    for V, alive in zip(*out):
        if alive and pred.feasible(z, V):
            J = pred.cost(V, f, c0)
            if best is None or J < best[1]:
                best = (V.copy(), J)
    return best
