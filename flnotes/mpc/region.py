"""The program of eq. (MPC_form_miqp) on one activation region of the network: a convex QP.

Fix the binaries ``alpha^k`` of eq. (MIP_general_c) at every predicted step to the activation pattern of a plan
``V``. The big-M rows then say exactly that each hidden pre-activation keeps its sign, and the network is affine
in ``V`` on that set (a polyhedron, the plan's linear region along the horizon): ``Phi_NN(z(k), v(k)) =
C_k V + d_k``. The program restricted to it is the QP ``min J(V)`` over the boxes, the terminal rows, the
sign rows and ``|C_k V + d_k| <= u_max^eps``: every point it returns satisfies eq. (MPC_form_miqp) and costs
at most ``J(V)``. It is a primal heuristic: its optimum is the MIQP's when ``V`` lies in the optimum's region,
and the branch and bound still proves it (see :class:`flnotes.mpc.engine.NetworkEngine`).
"""
from __future__ import annotations

import threading

from typing import Optional

import numpy as np

from ..solvers import TIGHTENED_GAP
from .prediction import Prediction

Array = np.ndarray

#: Moves to neighbouring regions in the MPC's first incumbent (:func:`region_qp`; ``repair=True``). On the book's
#: Quad-1D at N_p = 20 with ``time_limit = t_s``, without moves 2 of 23 steps that hit the limit returned a plan more
#: than 1e-4 above the proven optimum (at most 3.3e-3); with up to 10 none of 27 did (at most 1e-9). A move costs
#: one QP of a fraction of a millisecond there.
REGION_MOVES = 10

#: The output rows of the region QP use ``u_max^eps`` less this: the active-set solution meets its rows to
#: round-off, and the forward-pass check (:data:`flnotes.solvers.BOUND_TOL`) allows round-off only.
REGION_MARGIN = 1e-10


def region_rows(pred: Prediction, z0: Array, V: Array, pattern: Optional[list] = None,
                margin: float = REGION_MARGIN) -> tuple[Array, Array, list]:
    """Rows ``G V' <= h``: an activation pattern at every predicted step, and the output bound there.

    With ``[z(k); v(k)] = T_k V' + c_k`` (:attr:`Prediction.T`) and ``D^l`` the diagonal 0/1 pattern of layer
    ``l``, the pre-activation ``a^l = W^l y^{l-1} + b^l`` is affine in ``V'`` on the region, with
    ``y^l = D^l a^l``; an active neuron gets ``-a^l <= 0``, an inactive one ``a^l <= 0`` (eq. MIP_general with
    the binary fixed), and the output ``W^L y^{L-1} + b^L`` gets ``|.| <= u_max^eps - REGION_MARGIN`` (``|.| <=
    u_max^eps`` where the output is constant on the region: a flat piece at exactly ``u_max^eps`` stays in).
    ``margin`` replaces ``REGION_MARGIN`` (0: a region whose admissible part is a face, e.g. a ridge of the network
    at ``u_max^eps``, keeps that face, and only the forward-pass check tells whether the QP's point meets the bound).
    ``pattern`` (one (N_p, n_l) boolean array per hidden layer) defaults to the pattern of ``V``
    (``a^l > 0`` at ``V``). Returns ``G`` (rows, N_p m), ``h`` and the pattern; the first rows are the sign rows,
    layer by layer, step by step, in the order of ``pattern``'s entries.
    """
    net, N, m, nz = pred.net, pred.N, pred.m, pred.nz
    V = np.asarray(V, float).reshape(N * m)
    A = pred.T  # (N, n_in, N m)
    c = np.zeros((N, nz + m))
    c[:, :nz] = (pred.Sx @ np.asarray(z0, float))[:N]
    G, h, pat = [], [], []
    for layer, (W, b) in enumerate(zip(net.W[:-1], net.b[:-1])):
        A, c = np.einsum("ij,kjl->kil", W, A), c @ W.T + b  # the pre-activations a = A V + c, (N, n_l, N m)
        on = (A @ V + c) > 0.0 if pattern is None else np.asarray(pattern[layer], bool)
        pat.append(on)
        s = np.where(on, -1.0, 1.0)
        G.append((s[..., None] * A).reshape(-1, N * m))
        h.append((-s * c).reshape(-1))
        A, c = A * on[..., None], c * on
    A, c = np.einsum("ij,kjl->kil", net.W[-1], A), c @ net.W[-1].T + net.b[-1]
    # an output constant on the region (a flat piece: every row coefficient zero) is met exactly wherever the
    # region is: it needs no margin, and one would remove a piece that lies at exactly u_max^eps
    flat = ~np.any(A != 0.0, axis=2)
    u = np.where(flat, pred.u_eps, pred.u_eps - margin)
    G += [A.reshape(-1, N * m), -A.reshape(-1, N * m)]
    h += [(u - c).reshape(-1), (u + c).reshape(-1)]
    return np.vstack(G), np.concatenate(h), pat


def _region_solve(pred: Prediction, z0: Array, f: Array, G: Array, h: Array):
    """The QP of :func:`region_qp` on the rows ``G V <= h``: the optimum and the rows' multipliers, or ``None``s."""
    x, _, _, lam = pred.qp_multipliers(f, z0, G, np.full(h.size, -np.inf), h)
    return x, lam


def region_qp(pred: Prediction, z0: Array, f: Array, V: Array, max_moves: int = 0,
              stop: Optional[threading.Event] = None, pattern: Optional[list] = None,
              margin: float = REGION_MARGIN) -> Optional[Array]:
    """The optimum of ``J`` over the linear region of the plan ``V`` (:func:`region_rows`), or ``None``.

    ``f`` is the cost's linear part (:meth:`Prediction.linear`). Solved by DAQP (an active-set method, exact on
    a strictly convex QP). With ``max_moves > 0`` the search then moves to neighbouring regions: where a sign row
    is active at the optimum with a positive multiplier, the cost decreases across it, and the optimum ``V*``
    (whose neuron there is at ``a = 0``, so ``V*`` lies in both regions) is re-optimized with those neurons'
    pattern flipped; it stops when no such row is left, the cost stops decreasing, or after ``max_moves``
    moves, or once ``stop`` is set (a controller answering at its cut-off). ``None`` when the first QP
    gives no optimum (an empty region: ``V`` violates its own output rows, or a box). ``pattern`` (as in
    :func:`region_rows`) gives the first region instead of ``V``'s own, e.g. a solver's binaries where ``V`` lies
    past the region's face by the solver's tolerance; ``margin`` is :func:`region_rows`'. Check the result with
    :meth:`Prediction.feasible`.
    """
    G, h, pat = region_rows(pred, z0, V, pattern, margin)
    x, lam = _region_solve(pred, z0, f, G, h)
    if x is None:
        return None
    cost = lambda w: 0.5 * w @ pred.H @ w + f @ w  # noqa: E731
    best, J = x, cost(x)
    sizes = [p.size for p in pat]
    for _ in range(max_moves):
        if stop is not None and stop.is_set():
            break
        flip = lam[: sum(sizes)] > 1e-9 * max(1.0, abs(J))
        if not flip.any():
            break
        parts = np.split(flip, np.cumsum(sizes)[:-1])
        pat = [p ^ q.reshape(p.shape) for p, q in zip(pat, parts)]
        G, h, pat = region_rows(pred, z0, best, pat, margin)
        x, lam = _region_solve(pred, z0, f, G, h)
        if x is None or not cost(x) < J - 1e-12 * max(1.0, abs(J)):
            break
        best, J = x, cost(x)
    return best


def region_exact(pred: Prediction, z0: Array, f: Array, c0: float, V: Array, solver_pattern: Optional[list],
                 J1: float, gap: float) -> Optional[Array]:
    """A solver's plan ``V`` that exceeds ``u_max^eps`` by its tolerance, made exact on a linear region.

    The QP of :func:`region_qp` on the region of ``V`` (forward pass), then on ``solver_pattern`` (the region the
    solver's binaries name: a plan past that region's face by the tolerance lies in a neighbour whose QP may be
    empty, e.g. beside a flat piece of the network at exactly ``u_max^eps``), each with :data:`REGION_MARGIN` and
    then without it (a region whose admissible part is a face, a ridge of the network at ``u_max^eps``). Returns
    the first plan that passes :meth:`Prediction.feasible` (the forward-pass check decides) and costs at most
    ``J1`` (the solver's objective, a lower bound on the program's optimum up to its gap and tolerance) plus
    ``max(gap, TIGHTENED_GAP)`` (relative), or ``None``; a tightened bound would remove such a piece or ridge whole.
    The floor :data:`flnotes.solvers.TIGHTENED_GAP` is the one a verdict of tightened rows is held to: ``J1`` comes
    from a point over the bound by the solver's tolerance, and below the floor the two cannot be told apart (on a
    two-input ridge, both outputs at ``u_max`` at every step, the region's plan cost 2e-9 (relative) more than ``J1``;
    held to a gap of 1e-9 the rows were tightened, which removed the ridge: "not proven").
    """
    tol = max(gap, TIGHTENED_GAP)
    V = np.asarray(V, float).reshape(-1)
    patterns = [None] + ([solver_pattern] if solver_pattern is not None else [])
    for margin in (REGION_MARGIN, 0.0):
        for pattern in patterns:
            W = region_qp(pred, z0, f, V, pattern=pattern, margin=margin)
            if W is not None and pred.feasible(z0, W) and pred.cost(W, f, c0) <= J1 + tol * max(1.0, abs(J1)):
                return W
    return None
