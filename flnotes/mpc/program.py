"""The program form of eq. (MPC_form_miqp) handed to a solver: condensed, with the free binaries only.

The predicted states are eliminated (``z(k) = Sx[k] z0 + Su[k] V``), the stable neurons substituted
(``y = a`` or ``y = 0``), and the network encoded only at the steps asked for. Because which neurons are
stable and which steps are encoded change with the measured state, the rows are assembled for each state
from matrices built once (:class:`flnotes.mpc.prediction.Prediction`); see :func:`compact_program`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Optional, Sequence

import numpy as np
import scipy.sparse as sp

from ..bounds import NodeBounds
from ..solvers import MIQP
from .prediction import Prediction

Array = np.ndarray


#: Orders of the binaries (and their ``y``) in the program's columns (``MPCOptions.branching``): DAQP branches on the
#: first fractional binary in column order. ``"layers"``: every encoded step's first-layer neurons (steps in order),
#: then the second layer's, and so on; ``"steps"``: step by step, each step's layers in order.
ORDERS = ("layers", "steps")


def _encoded(L: Array, U: Array, eliminate_stable: bool) -> Array:
    """Neurons that keep a variable and a binary: the unstable ones (``L < 0 < U``), or all of them."""
    return ((L < 0) & (U > 0)) if eliminate_stable else np.ones(L.size, bool)


def _offsets(nb: NodeBounds, steps: Sequence[int], n_layers: int, eliminate_stable: bool, order: str
             ) -> tuple[dict, int]:
    """Where the ``y`` (and ``alpha``) of each (step, hidden layer) start in their block, and the block's size."""
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    count = {(k, layer): int(_encoded(np.asarray(nb.L[layer])[k], np.asarray(nb.U[layer])[k], eliminate_stable).sum())
             for k in steps for layer in range(n_layers)}
    keys = ([(k, layer) for layer in range(n_layers) for k in steps] if order == "layers"
            else [(k, layer) for k in steps for layer in range(n_layers)])
    off, at = {}, 0
    for key in keys:
        off[key] = at
        at += count[key]
    return off, at


@dataclass(frozen=True)
class EncodedLayer:
    """One hidden layer of the network at an encoded step ``k`` of :func:`compact_program`, as rows over ``w``.

    The layer's input is ``x = Y w + y0`` (``[z(k); v(k)]`` for the first layer, the previous layer's ``y``
    after it) and its pre-activation ``a = Aa w + a0 = W x + b``. ``L, U`` are its node bounds at step ``k``,
    ``var`` marks the neurons that keep a variable (``idx`` their indices), ``iy, ia`` are the columns of their
    ``y`` and ``alpha``. ``out`` is the output's rows ``(W^K Y', W^K y0' + b^K)`` on the last hidden layer
    (``Y', y0'`` its ``y``), ``None`` on the others.
    """

    k: int
    layer: int
    Y: Array
    y0: Array
    Aa: Array
    a0: Array
    L: Array
    U: Array
    var: Array
    idx: Array
    iy: Array
    ia: Array
    out: Optional[tuple] = None


def encoded_layers(pred: Prediction, z0: Array, nb: NodeBounds, steps: Sequence[int], n: int,
                   eliminate_stable: bool = True, order: str = "layers") -> Iterator[EncodedLayer]:
    """The hidden layers of the encoded ``steps`` in the program's column layout (``n`` columns), step by step.

    The one place that lays out the program's neurons: :func:`compact_program` writes its rows from these, and
    a study of the program (cuts on its neurons, :mod:`flnotes.studies.cuts`) reads the same layout.
    """
    net, N, m = pred.net, pred.N, pred.m
    nV = N * m
    Zf = pred.Sx @ z0
    col0, n_y = _offsets(nb, list(steps), net.K - 1, eliminate_stable, order)
    for k in steps:
        Y = np.zeros((net.n_in, n))
        Y[:, :nV] = pred.T[k]
        y0 = np.r_[Zf[k], np.zeros(m)]
        for layer, (W, b) in enumerate(zip(net.W[:-1], net.b[:-1])):
            Aa, a0 = W @ Y, W @ y0 + b
            L, U = np.asarray(nb.L[layer], float)[k], np.asarray(nb.U[layer], float)[k]
            var = _encoded(L, U, eliminate_stable)
            idx = np.flatnonzero(var)
            iy = nV + col0[(k, layer)] + np.arange(idx.size)
            Yn, yn0 = np.zeros_like(Aa), np.zeros_like(a0)
            sub = (L >= 0) & ~var                                # substituted active neurons: y = a
            Yn[sub], yn0[sub] = Aa[sub], a0[sub]
            Yn[idx, iy] = 1.0
            out = (net.W[-1] @ Yn, net.W[-1] @ yn0 + net.b[-1]) if layer == net.K - 2 else None
            yield EncodedLayer(k, layer, Y, y0, Aa, a0, L, U, var, idx, iy, iy + n_y, out)
            Y, y0 = Yn, yn0


def compact_program(pred: Prediction, z0: Array, f: Array, c0: float, nb: NodeBounds, steps: Sequence[int],
                    u_in: Array, *, eliminate_stable: bool = True, lo: Optional[Array] = None,
                    hi: Optional[Array] = None, order: str = "layers",
                    first: Optional[tuple[Array, Array]] = None) -> MIQP:
    """The condensed big-M program with the network encoded at ``steps``.

    Variables ``w = [V | y (encoded neurons) | alpha (encoded neurons)]``. Per encoded neuron with
    pre-activation ``a`` (affine in ``w``): ``y >= 0``, ``y >= a``, ``y <= U alpha``,
    ``y <= a - L (1 - alpha)``, i.e. eq. (MIP_general_b)-(MIP_general_c) with ``yund = y - a``; a stable
    neuron is ``y = a`` (``L >= 0``) or ``y = 0`` (``U <= 0``) plus the row ``L <= a <= U`` that keeps the
    substitution exact; ``|y^K| <= u_in`` per encoded step (eq. Phi_NN_ep, ``u_in = u_max^eps`` less the
    solver margin); the state box and terminal rows; optional boxes ``lo <= [z(k); v(k)] <= hi`` for every
    step (the level-set restriction). With ``eliminate_stable=False`` every neuron keeps a variable and a
    binary (fixed by its bounds when stable). ``order`` (one of :data:`ORDERS`) places the binaries in the
    columns: the program is the same, DAQP's branching order is not.

    Parameters
    ----------
    pred
        The prediction model.
    z0
        Measured state (n_z,).
    f, c0
        The cost's linear part and constant (:meth:`Prediction.linear`).
    nb
        Node bounds per predicted step, arrays of shape (N_p, n_k) (eq. MIP_general_c).
    steps
        Predicted steps whose network constraint is encoded.
    u_in
        The output bound written in the rows, (m,).
    first
        ``(a, b)``: step 0's network constraint as the bounds ``a <= v(0) <= b``
        (:meth:`flnotes.mpc.prediction.Prediction.first_range` at ``u_in``); 0 must not be in ``steps`` then.
    """
    net, N, nz, m = pred.net, pred.N, pred.nz, pred.m
    nV = N * m
    Zf = pred.Sx @ z0
    steps = list(steps)
    n_y = _offsets(nb, steps, net.K - 1, eliminate_stable, order)[1]
    n = nV + 2 * n_y
    lb = np.r_[np.tile(pred.v_lo, N), np.zeros(2 * n_y)]
    ub = np.r_[np.tile(pred.v_hi, N), np.full(n_y, np.inf), np.ones(n_y)]
    integ = np.r_[np.zeros(nV + n_y, dtype=int), np.ones(n_y, dtype=int)]
    if first is not None:
        if 0 in steps:
            raise ValueError("step 0's constraint is given as the bounds first = (a, b): leave 0 out of steps")
        lb[:m], ub[:m] = np.maximum(lb[:m], first[0]), np.minimum(ub[:m], first[1])
    s_lo, s_hi = pred.state_bounds(z0)
    rows = [np.hstack([pred.A_state, np.zeros((pred.A_state.shape[0], n - nV))])]
    rl, ru = [s_lo], [s_hi]
    if lo is not None:
        Tb = np.zeros((N * (nz + m), n))
        Tb[:, :nV] = pred.T.reshape(N * (nz + m), nV)
        off = np.hstack([Zf[:N], np.zeros((N, m))]).reshape(-1)
        rows.append(Tb)
        rl.append(lo.reshape(-1) - off)
        ru.append(hi.reshape(-1) - off)
    for lay in encoded_layers(pred, z0, nb, steps, n, eliminate_stable, order):
        Aa, a0, idx, iy, ia, L, U = lay.Aa, lay.a0, lay.idx, lay.iy, lay.ia, lay.L, lay.U
        r = np.arange(idx.size)
        Up, Lm = np.maximum(U[idx], 0.0), np.minimum(L[idx], 0.0)
        R1 = Aa[idx].copy()
        R1[r, iy] -= 1.0                                         # a - y <= 0
        R2 = np.zeros((idx.size, n))
        R2[r, iy], R2[r, ia] = 1.0, -Up                          # y - U alpha <= 0
        R3 = -Aa[idx]
        R3[r, iy] += 1.0
        R3[r, ia] -= Lm                                          # y - a - L alpha <= -L
        rows += [R1, R2, R3]
        rl += [np.full(idx.size, -np.inf)] * 3
        ru += [-a0[idx], np.zeros(idx.size), a0[idx] - Lm]
        ub[iy] = Up
        lb[ia], ub[ia] = np.where(L[idx] >= 0, 1.0, 0.0), np.where(U[idx] <= 0, 0.0, 1.0)
        st = np.flatnonzero(~lay.var)                            # L <= a <= U keeps the substitution exact
        if st.size:
            rows.append(Aa[st])
            rl.append(L[st] - a0[st])
            ru.append(U[st] - a0[st])
        if lay.out is not None:
            Yo, o0 = lay.out
            rows.append(Yo)
            rl.append(-u_in - o0)
            ru.append(u_in - o0)                                 # eq. (Phi_NN_ep)
    H = sp.block_diag([sp.csc_matrix(pred.H), sp.csc_matrix((n - nV, n - nV))], format="csc")
    return MIQP(H, np.r_[f, np.zeros(n - nV)], c0, sp.csr_matrix(np.vstack(rows)), np.concatenate(rl),
                np.concatenate(ru), lb, ub, integ)


def plan_vector(pred: Prediction, z0: Array, V: Array, nb: NodeBounds, steps: Sequence[int], prob: MIQP,
                eliminate_stable: bool = True, order: str = "layers") -> Array:
    """The program's ``w`` for a plan ``V`` (the hidden values from the network's forward pass): a warm start
    (``steps``, ``eliminate_stable`` and ``order`` as the program was built with)."""
    N, m = pred.N, pred.m
    V = np.asarray(V, float).reshape(N, m)
    w = np.zeros(prob.n)
    w[: N * m] = V.reshape(-1)
    steps = list(steps)
    if not steps:
        return w
    Z = pred.predict(z0, V)
    _, pre = pred.net.forward(np.hstack([Z[steps], V[steps]]))
    col0, n_y = _offsets(nb, steps, pred.net.K - 1, eliminate_stable, order)
    if N * m + 2 * n_y != prob.n:
        raise ValueError(f"the program has {prob.n} variables, the layout of these steps and bounds {N * m + 2 * n_y}: "
                         "pass the steps, bounds, eliminate_stable and order the program was built with")
    for s, k in enumerate(steps):
        for layer in range(pred.net.K - 1):
            L, U = np.asarray(nb.L[layer])[k], np.asarray(nb.U[layer])[k]
            var = _encoded(L, U, eliminate_stable)
            a = pre[layer][s][var]
            iy = N * m + col0[(k, layer)]
            ia = iy + n_y
            w[iy:iy + a.size] = np.maximum(a, 0.0)
            w[ia:ia + a.size] = np.clip((a > 0).astype(float), (L[var] >= 0).astype(float), (U[var] > 0).astype(float))
    return w


def program_pattern(pred: Prediction, z0: Array, w: Array, nb: NodeBounds, steps: Sequence[int], prob: MIQP,
                    eliminate_stable: bool = True, order: str = "layers") -> list[Array]:
    """The activation pattern a program's point ``w`` stands for: the inverse of :func:`plan_vector`.

    At the encoded ``steps`` a neuron with a binary is active where its ``alpha`` rounds to 1 and a stable one
    where ``L >= 0``; at the other steps the pattern is the forward pass's at the plan ``V = w[:N_p m]``. A
    solver's point may lie past a face of the region its binaries name by the solver's tolerance, so the two
    patterns can differ at the encoded steps. Returns one (N_p, n_l) boolean array per hidden layer, as
    :func:`flnotes.mpc.region.region_rows` takes it.
    """
    N, m = pred.N, pred.m
    w = np.asarray(w, float)
    V = w[: N * m].reshape(N, m)
    _, pre = pred.net.forward(np.hstack([pred.predict(z0, V)[:N], V]))
    pattern = [a > 0.0 for a in pre]
    steps = list(steps)
    if not steps:
        return pattern
    col0, n_y = _offsets(nb, steps, pred.net.K - 1, eliminate_stable, order)
    if N * m + 2 * n_y != prob.n or w.shape != (prob.n,):
        raise ValueError(f"the program has {prob.n} variables, w {w.shape} and the layout of these steps and bounds "
                         f"{N * m + 2 * n_y}: pass the steps, bounds, eliminate_stable and order the program was built with")
    for k in steps:
        for layer in range(pred.net.K - 1):
            L, U = np.asarray(nb.L[layer])[k], np.asarray(nb.U[layer])[k]
            var = _encoded(L, U, eliminate_stable)
            ia = N * m + n_y + col0[(k, layer)]
            on = L >= 0.0
            on[var] = w[ia:ia + int(var.sum())] > 0.5
            pattern[layer][k] = on
    return pattern


def objective(prob: MIQP, w: Array) -> float:
    """``0.5 w'Hw + c'w + c0`` of a program."""
    w = np.asarray(w, float)
    return float(0.5 * w @ (prob.H @ w) + prob.c @ w + prob.c0)
