"""The big-M formulation of a ReLU network, eq. (MIP_general).

This module is the only place that knows the formulation. For every hidden
neuron ``j`` of layer ``k`` (eq. MIP_general_b, MIP_general_c)

    W^k y^{k-1} + b^k = ybar^k - yund^k,    ybar^k >= 0,  yund^k >= 0,
    ybar^k_j <= U^k_j alpha^k_j,            yund^k_j <= -L^k_j (1 - alpha^k_j),   alpha^k_j in {0, 1},

with ``y^k = ybar^k``, and the output ``y^K = W^K y^{K-1} + b^K`` (eq.
MIP_general_d). A stably active neuron (``L >= 0``) has ``alpha = 1`` fixed, a
stably inactive one (``U <= 0``) ``alpha = 0``: no binary is created for them.

Two forms are offered:

* :func:`encode` builds cvxpy constraints on a cvxpy expression (the teaching
  form, and the one the CLF-CBF and MPC programs are written with);
* :func:`bigm_form` returns the same constraints as sparse matrices over a
  flat variable vector, for solver interfaces that keep a persistent model
  (HiGHS, SCIP, DAQP) and update it in place.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
import scipy.sparse as sp

from ._checks import as_floats
from .bounds import NodeBounds, fbbt
from .network import ReLUNet

Array = np.ndarray


@dataclass
class Encoding:
    """What :func:`encode` returns.

    Attributes
    ----------
    output
        cvxpy expression of ``y^K = Phi_NN(x)``: shape (n_out,) or (n_out, T).
    constraints
        The constraints of eq. (MIP_general_b)-(MIP_general_c).
    alpha
        Binary variables, one per hidden layer (only the unstable neurons'
        entries; ``None`` for a layer without any).
    ybar, yund
        The nonnegative splits of each hidden pre-activation.
    n_binaries
        Total number of binaries created.
    """

    output: object
    constraints: list
    alpha: list
    ybar: list
    yund: list
    n_binaries: int
    hidden: list = field(default_factory=list)


def _as_params_or_arrays(bounds: Optional[NodeBounds], L, U, net: ReLUNet, T: Optional[int]):
    if bounds is not None:
        if not isinstance(bounds, NodeBounds):
            raise TypeError(f"bounds must be a flnotes.NodeBounds, e.g. bounds=fl.fbbt(net, lo, hi) or "
                            f"fl.lp_bounds(net, lo, hi), got {type(bounds).__name__}; to give the per-layer arrays "
                            f"yourself pass L=[L^1, ..., L^(K-1)] and U=[U^1, ..., U^(K-1)] instead")
        if L is not None or U is not None:
            raise ValueError("give either bounds= or L= and U=, not both")
        if len(bounds.L) != net.K - 1 or len(bounds.U) != net.K - 1:
            raise ValueError(f"bounds hold {len(bounds.L)} layers but the network has {net.K - 1} hidden layers: "
                             f"compute them for this network, bounds=fl.fbbt(net, lo, hi)")
        L, U = bounds.L, bounds.U
        if any(np.ndim(a) == 2 for a in L):
            # a batch from fbbt(net, lo, hi) with lo, hi of shape (T, n_in) stores (T, n_k) per layer;
            # encode works column-wise (one column per point), so bring them to (n_k, T)
            if T is None:
                raise ValueError("bounds hold a batch of boxes (arrays of shape (T, n_k)) but x is a single "
                                 "point of shape (n_in,): pass x of shape (n_in, T) or bounds for one box")
            if any(np.shape(a) != (T, W.shape[0]) for a, W in zip(L, net.W[:-1])):
                raise ValueError(f"bounds hold a batch of {np.shape(L[0])[0]} boxes but x has {T} columns: "
                                 f"call fbbt with lo, hi of shape ({T}, {net.n_in})")
            L, U = [np.asarray(a).T for a in L], [np.asarray(a).T for a in U]
    if L is None or U is None:
        raise ValueError("encode needs node bounds: pass bounds=fbbt(net, lo, hi) (or L= and U= lists)")
    for name, B in (("L", L), ("U", U)):
        if not isinstance(B, (list, tuple)):
            raise TypeError(f"{name} must be a list with one array (or cvxpy Parameter) per hidden layer, "
                            f"got {type(B).__name__}")
    if len(L) != net.K - 1 or len(U) != net.K - 1:
        raise ValueError(f"need one L and one U per hidden layer ({net.K - 1}), got {len(L)} and {len(U)}")
    return list(L), list(U)


def encode(net: ReLUNet, x, bounds: Optional[NodeBounds] = None, L: Optional[Sequence] = None,
           U: Optional[Sequence] = None) -> Encoding:
    """Big-M encoding of ``y = Phi_NN(x)`` for a cvxpy expression ``x`` (eq. MIP_general).

    Parameters
    ----------
    net
        The ReLU network.
    x
        cvxpy expression of the stacked input ``y^0 = [z, v]``: shape (n_in,)
        for one point (CLF-CBF), or (n_in, T) with one column per point
        (every step of an MPC horizon, all at once).
    bounds
        Node bounds valid for every admissible ``x`` (e.g. ``fbbt(net, lo, hi)``).
        Bounds for one box (arrays of shape (n_k,)) apply to every column; a
        batch from ``fbbt(net, lo, hi)`` with ``lo``, ``hi`` of shape
        (T, n_in) gives column ``t`` the bounds of box ``t``.
    L, U
        Alternatively, lists of per-layer bounds of shape (n_k,) or (n_k, T)
        (note: column-wise, the transpose of a batch ``NodeBounds``); these may be cvxpy
        ``Parameter`` objects of shape (n_k,) or (n_k, T) that are updated each
        control step without rebuilding anything. With parameters every neuron
        gets a binary, since stability is only known at solve time.

    Returns
    -------
    Encoding
        ``output`` is the cvxpy expression of ``Phi_NN(x)``; add
        ``constraints`` to the program, then impose e.g.
        ``cp.abs(enc.output) <= u_max - eps`` (eq. Phi_NN_ep).
    """
    import cvxpy as cp

    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    if not isinstance(x, cp.Expression):
        raise TypeError(f"x must be a cvxpy expression of the network input (e.g. cp.Variable({net.n_in})), got "
                        f"{type(x).__name__}; to evaluate the network at a numeric point call net(x), to solve the "
                        f"encoding with the input fixed use fl.forward_milp(net, x)")
    shape = tuple(x.shape)
    if len(shape) == 1:
        T = None
        if shape[0] != net.n_in:
            raise ValueError(f"x must have shape ({net.n_in},) or ({net.n_in}, T), got {shape}")
    elif len(shape) == 2 and shape[0] == net.n_in:
        T = shape[1]
    else:
        raise ValueError(f"x must have shape ({net.n_in},) or ({net.n_in}, T), got {shape}")
    Ls, Us = _as_params_or_arrays(bounds, L, U, net, T)
    cols = () if T is None else (T,)

    y = x
    cons, alphas, ybars, yunds = [], [], [], []
    n_bin = 0
    for k, (W, b) in enumerate(zip(net.W[:-1], net.b[:-1])):
        n_k = W.shape[0]
        bk = b if T is None else np.repeat(b[:, None], T, axis=1)
        Lk, Uk = Ls[k], Us[k]
        ybar = cp.Variable((n_k,) + cols, nonneg=True, name=f"ybar{k + 1}")
        yund = cp.Variable((n_k,) + cols, nonneg=True, name=f"yund{k + 1}")
        cons.append(W @ y + bk == ybar - yund)  # eq. (MIP_general_b)
        if isinstance(Lk, cp.Expression) or isinstance(Uk, cp.Expression):
            alpha = cp.Variable((n_k,) + cols, boolean=True, name=f"alpha{k + 1}")
            alpha_full = alpha
            n_bin += n_k * (T or 1)
            cons += [ybar <= cp.multiply(Uk, alpha_full), yund <= cp.multiply(-Lk, 1 - alpha_full)]
        else:
            Lk, Uk = _column_bounds(Lk, n_k, T, f"L^{k + 1}"), _column_bounds(Uk, n_k, T, f"U^{k + 1}")
            bad = np.argwhere(~(Lk <= Uk))  # NaN too: a neuron with no interval would get no binary
            if bad.size:
                j = tuple(bad[0])
                raise ValueError(f"L^{k + 1} <= U^{k + 1} must hold at every neuron (node bounds of a box), got "
                                 f"L = {Lk[j]!r} and U = {Uk[j]!r} at neuron {j[0]}: compute them with fl.fbbt or "
                                 f"fl.lp_bounds")
            alpha_full, alpha, nb = _alpha_expression(Lk, Uk, f"alpha{k + 1}")
            n_bin += nb
            # eq. (MIP_general_c) with alpha fixed for stable neurons
            cons += [ybar <= cp.multiply(np.maximum(Uk, 0.0), alpha_full),
                     yund <= cp.multiply(np.maximum(-Lk, 0.0), 1 - alpha_full)]
        alphas.append(alpha), ybars.append(ybar), yunds.append(yund)
        y = ybar
    bK = net.b[-1] if T is None else np.repeat(net.b[-1][:, None], T, axis=1)
    out = net.W[-1] @ y + bK  # eq. (MIP_general_d)
    return Encoding(output=out, constraints=cons, alpha=alphas, ybar=ybars, yund=yunds, n_binaries=n_bin, hidden=ybars)


def _column_bounds(B, n_k: int, T: Optional[int], name: str) -> Array:
    """Bounds of shape (n_k,) for one point, or (n_k, T) per column (an (n_k,) array applies to all)."""
    B = as_floats(B, name)
    if not np.all(np.isfinite(B)):
        raise ValueError(f"{name} must be finite node bounds (a big-M of inf is no bound): compute them with "
                         f"fl.fbbt or fl.lp_bounds on a bounded box")
    if T is None:
        if B.shape != (n_k,):
            raise ValueError(f"{name} of a layer with {n_k} neurons must have shape ({n_k},), got {B.shape}")
        return B
    if B.shape == (n_k,):
        return np.repeat(B[:, None], T, axis=1)
    if B.shape != (n_k, T):
        raise ValueError(f"{name} must have shape ({n_k},) or ({n_k}, {T}), got {B.shape}")
    return B


def _alpha_expression(L: Array, U: Array, name: str):
    """``alpha_full = P alpha + c``: binaries only where ``L < 0 < U``, constants elsewhere."""
    import cvxpy as cp

    unstable = (L < 0) & (U > 0)
    const = (L >= 0).astype(float)  # stably active -> 1, inactive -> 0
    n_free = int(unstable.sum())
    if n_free == 0:
        return const, None, 0
    if unstable.all():
        alpha = cp.Variable(L.shape, boolean=True, name=name)
        return alpha, alpha, n_free
    alpha = cp.Variable(n_free, boolean=True, name=name)
    flat = np.flatnonzero(unstable.reshape(-1, order="F"))
    P = sp.csr_matrix((np.ones(n_free), (flat, np.arange(n_free))), shape=(L.size, n_free))
    expr = P @ alpha
    if L.ndim == 2:
        expr = cp.reshape(expr, L.shape, order="F")
    return expr + const, alpha, n_free


# ---------------------------------------------------------------------------
# Matrix form for persistent solver models
# ---------------------------------------------------------------------------
@dataclass
class BigMForm:
    """Eq. (MIP_general) for one input point as sparse matrices over a flat vector ``w``.

    ``w = [x (n_in) | ybar^1, yund^1, alpha^1 | ... | ybar^{K-1}, yund^{K-1}, alpha^{K-1} | y^K (n_out)]``

    with ``A_eq w = b_eq``, ``A_ub w <= b_ub``, ``lb <= w <= ub`` and
    ``integrality[i] = 1`` for every ``alpha`` entry. The ``alpha`` of a
    stable neuron is fixed by ``lb = ub`` (a solver's presolve removes it, so
    it costs no branching); it stays marked integer so that the same model
    remains exact after :meth:`update` with bounds under which the neuron is
    unstable. ``x`` is left free (``-inf``/``inf``) for the caller to bound or fix.

    Attributes
    ----------
    x, out
        Index arrays of the input and output entries of ``w``.
    ybar, yund, alpha
        Index arrays per hidden layer.
    ub_rows_U, ub_rows_L
        Row indices (into ``A_ub``) of ``ybar - U alpha <= 0`` and
        ``yund + L alpha <= -L`` per layer, so that new bounds can be written in
        place by :meth:`update`.
    """

    n: int
    A_eq: sp.csr_matrix
    b_eq: Array
    A_ub: sp.csr_matrix
    b_ub: Array
    lb: Array
    ub: Array
    integrality: Array
    x: Array
    out: Array
    ybar: list
    yund: list
    alpha: list
    ub_rows_U: list
    ub_rows_L: list

    @property
    def n_binaries(self) -> int:
        """Binaries left free by the bounds the form was built with (its unstable neurons)."""
        a = np.concatenate(self.alpha) if self.alpha else np.zeros(0, int)
        return int(np.sum(self.lb[a] < self.ub[a]))

    def update(self, bounds: NodeBounds) -> tuple[sp.csr_matrix, Array, Array, Array]:
        """``(A_ub, b_ub, lb, ub)`` for new node bounds, with the same sparsity pattern.

        Only the big-M coefficients and the variable bounds change, so a
        persistent solver model can take them in place of the old ones.
        """
        if not isinstance(bounds, NodeBounds):
            raise TypeError(f"bounds must be a flnotes.NodeBounds, got {type(bounds).__name__}")
        if len(bounds.L) != len(self.ub_rows_U) or len(bounds.U) != len(self.ub_rows_U):
            raise ValueError(f"bounds must hold all {len(self.ub_rows_U)} hidden layers of the form, got "
                             f"{len(bounds.L)}: the layers left out would keep their old big-M values")
        for k, (L, U) in enumerate(zip(bounds.L, bounds.U)):
            if np.shape(L) != (len(self.ub_rows_U[k]),) or np.any(~(np.asarray(L) <= np.asarray(U))) \
                    or not (np.all(np.isfinite(L)) and np.all(np.isfinite(U))):
                raise ValueError(f"bounds of layer {k + 1} must be finite, of shape ({len(self.ub_rows_U[k])},) "
                                 f"with L <= U, got shape {np.shape(L)}")
        A_ub = self.A_ub.tolil(copy=True)
        b_ub, lb, ub = self.b_ub.copy(), self.lb.copy(), self.ub.copy()
        for k, (L, U) in enumerate(zip(bounds.L, bounds.U)):
            _write_layer(A_ub, b_ub, lb, ub, self, k, np.asarray(L, float), np.asarray(U, float))
        return A_ub.tocsr(), b_ub, lb, ub


def _write_layer(A_ub, b_ub, lb, ub, form: BigMForm, k: int, L: Array, U: Array) -> None:
    rU, rL = form.ub_rows_U[k], form.ub_rows_L[k]
    ia, ib, iu = form.alpha[k], form.ybar[k], form.yund[k]
    Up, Lm = np.maximum(U, 0.0), np.minimum(L, 0.0)
    for j in range(len(L)):
        A_ub[rU[j], ia[j]] = -Up[j]          # ybar - U alpha <= 0
        A_ub[rL[j], ia[j]] = -Lm[j]          # yund <= -L (1 - alpha)  <=>  yund - L alpha <= -L
        b_ub[rL[j]] = -Lm[j]
    ub[ib], ub[iu] = Up, -Lm
    active, inactive = L >= 0, U <= 0
    lb[ia], ub[ia] = np.where(active, 1.0, 0.0), np.where(inactive, 0.0, 1.0)


def bigm_form(net: ReLUNet, bounds: NodeBounds) -> BigMForm:
    """Eq. (MIP_general) for one point as a :class:`BigMForm` (see there for the layout)."""
    if not isinstance(bounds, NodeBounds):
        raise TypeError(f"bounds must be a flnotes.NodeBounds (e.g. fl.fbbt(net, lo, hi)), got {type(bounds).__name__}")
    if len(bounds.L) != net.K - 1:
        raise ValueError(f"bounds hold {len(bounds.L)} layers but the network has {net.K - 1} hidden layers")
    if np.ndim(bounds.L[0]) != 1:
        raise ValueError("bigm_form takes bounds for one input box (arrays of shape (n_k,)); stack copies for a horizon")
    n_in, n_out = net.n_in, net.n_out
    idx = n_in
    x = np.arange(n_in)
    ybars, yunds, alphas = [], [], []
    for W in net.W[:-1]:
        n_k = W.shape[0]
        ybars.append(np.arange(idx, idx + n_k))
        idx += n_k
        yunds.append(np.arange(idx, idx + n_k))
        idx += n_k
        alphas.append(np.arange(idx, idx + n_k))
        idx += n_k
    out = np.arange(idx, idx + n_out)
    idx += n_out
    n = idx

    eq_r, eq_c, eq_v, b_eq = [], [], [], []
    row = 0
    prev = x
    for k, (W, b) in enumerate(zip(net.W[:-1], net.b[:-1])):
        n_k = W.shape[0]
        Wc = sp.coo_matrix(W)
        eq_r += (row + Wc.row).tolist()
        eq_c += prev[Wc.col].tolist()
        eq_v += Wc.data.tolist()
        eq_r += list(range(row, row + n_k)) * 2
        eq_c += ybars[k].tolist() + yunds[k].tolist()
        eq_v += [-1.0] * n_k + [1.0] * n_k
        b_eq += (-b).tolist()
        row += n_k
        prev = ybars[k]
    Wc = sp.coo_matrix(net.W[-1])
    eq_r += (row + Wc.row).tolist()
    eq_c += prev[Wc.col].tolist()
    eq_v += Wc.data.tolist()
    eq_r += list(range(row, row + n_out))
    eq_c += out.tolist()
    eq_v += [-1.0] * n_out
    b_eq += (-net.b[-1]).tolist()
    row += n_out
    A_eq = sp.csr_matrix((eq_v, (eq_r, eq_c)), shape=(row, n))

    ub_r, ub_c, ub_v = [], [], []
    rows_U, rows_L = [], []
    r = 0
    for k in range(net.K - 1):
        n_k = len(ybars[k])
        rU, rL = np.arange(r, r + n_k), np.arange(r + n_k, r + 2 * n_k)
        rows_U.append(rU), rows_L.append(rL)
        ub_r += rU.tolist() * 2
        ub_c += ybars[k].tolist() + alphas[k].tolist()
        ub_v += [1.0] * n_k + [-1.0] * n_k
        ub_r += rL.tolist() * 2
        ub_c += yunds[k].tolist() + alphas[k].tolist()
        ub_v += [1.0] * n_k + [-1.0] * n_k
        r += 2 * n_k
    A_ub = sp.lil_matrix(sp.csr_matrix((ub_v, (ub_r, ub_c)), shape=(r, n)))
    b_ub = np.zeros(r)
    lb, ub = np.full(n, -np.inf), np.full(n, np.inf)
    integrality = np.zeros(n, dtype=int)
    for k in range(net.K - 1):
        lb[ybars[k]] = 0.0
        lb[yunds[k]] = 0.0
        integrality[alphas[k]] = 1
    form = BigMForm(n=n, A_eq=A_eq, b_eq=np.asarray(b_eq), A_ub=A_ub.tocsr(), b_ub=b_ub, lb=lb, ub=ub,
                    integrality=integrality, x=x, out=out, ybar=ybars, yund=yunds, alpha=alphas,
                    ub_rows_U=rows_U, ub_rows_L=rows_L)
    for k, (L, U) in enumerate(zip(bounds.L, bounds.U)):
        _write_layer(A_ub, b_ub, lb, ub, form, k, np.asarray(L, float), np.asarray(U, float))
    form.A_ub, form.b_ub, form.lb, form.ub = A_ub.tocsr(), b_ub, lb, ub
    # stable neurons: their alpha is fixed by lb == ub and needs no branching; it stays marked integer so
    # that a persistent model stays exact after update() with bounds under which the neuron is unstable
    form.integrality = integrality
    return form


def forward_milp(net: ReLUNet, x: Array, bounds: Optional[NodeBounds] = None) -> Array:
    """Solve eq. (MIP_general) with the input fixed to ``x`` (HiGHS via scipy) and return ``y^K``.

    With exact bounds the MILP has a single feasible point, the forward pass:
    this is the check that the encoding reproduces the network.
    """
    from scipy.optimize import LinearConstraint, milp, Bounds

    x = as_floats(x, "x").reshape(-1)
    if x.shape != (net.n_in,):
        raise ValueError(f"x must have shape ({net.n_in},), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"x contains NaN or inf: {x}")
    if bounds is None:
        bounds = fbbt(net, x, x)
    form = bigm_form(net, bounds)
    lb, ub = form.lb.copy(), form.ub.copy()
    lb[form.x], ub[form.x] = x, x
    res = milp(np.zeros(form.n), integrality=form.integrality, bounds=Bounds(lb, ub),
               constraints=[LinearConstraint(form.A_eq, form.b_eq, form.b_eq),
                            LinearConstraint(form.A_ub, -np.inf, form.b_ub)])
    if res.status != 0:
        raise RuntimeError(f"the big-M MILP with fixed input was not solved: {res.message}")
    return res.x[form.out]
