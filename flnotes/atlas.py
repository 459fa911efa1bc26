"""A bound atlas: LP node bounds of a ReLU network on a grid of cells over its domain, computed once and read
for any box inside the domain.

LP tightening (:func:`flnotes.lp_bounds`) with the output bound ``|Phi_NN| <= u`` (eq. Phi_NN_ep) gives, for a
cell ``C`` of the grid, bounds ``L^k <= W^k y^{k-1} + b^k <= U^k`` (eq. MIP_general_c) that hold at every point of
``C`` whose output meets the bound. A box ``B`` inside the domain lies in the union of the cells it meets, so the
elementwise minimum of their ``L`` and maximum of their ``U`` hold at every point of ``B`` whose output meets the
bound: valid node bounds for ``B``, read with a few array reductions instead of two LPs per neuron
(:meth:`BoundAtlas.cover`). A cell without such a point (its LP relaxation is empty) is left out of every cover.
The cells are smaller than the boxes an MPC asks about, and each cell's LP relaxation is tighter than a box's, so
the cover can be tighter than the box's own LP bounds.

The MPC reads its node bounds from an atlas where it would otherwise solve LPs (``fl.MPC(..., atlas=...)``,
:mod:`flnotes.mpc.levers`): exact, since the bounds stay valid. An atlas costs ``2 n`` LPs per cell for ``n``
neurons, once per network, domain and bound ``u`` (about 90 s on one core for the MSD's (20, 20, 20) network on
16 x 16 x 6 cells): the book ships the MSD's (:func:`shipped_atlas`), and :func:`bound_atlas` computes one for another
network.
"""
from __future__ import annotations

import hashlib
import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping, Optional, Sequence, Union

import numpy as np

from ._checks import as_floats, as_vector, brief, check_box, check_boxes, check_int, check_seed
from .network import ReLUNet, fingerprint
from .tightening import EmptyBoxError, lp_bounds

Array = np.ndarray

__all__ = ["BoundAtlas", "bound_atlas", "check_atlas", "load_atlas", "shipped_atlas"]

#: The folder of the shipped atlases.
DATA = Path(__file__).resolve().parent / "data"

#: Points of the fixed sample that :func:`check_atlas` checks an atlas on.
N_SAMPLE = 4096

#: The atlases shipped in ``flnotes/data``: file name -> (the cells per input of its grid, the :attr:`BoundAtlas.digest`
#: of the file as written by :func:`write_shipped_atlases`, the fingerprint of its network). For that network a file
#: that is missing, unreadable or whose contents differ is refused.
SHIPPED = {"MSD.atlas.npz": ((16, 16, 6), "8017837e4d0b1d440ae56f6d4b9e6118e80e5d9d72012de4397243f997b5429d",
                           "33c77a133143ebad174d280c8f5ca919a89da189484095fa55fffc5b6ce603e7")}


@dataclass(frozen=True, eq=False)
class BoundAtlas:
    """LP node bounds of a network on the cells of a grid over its domain (see the module).

    Attributes
    ----------
    edges
        Per input, the grid's increasing edges; cell ``c`` of input ``i`` is ``[edges[i][c], edges[i][c + 1]]``.
    L, U
        Per hidden layer, shape ``cells + (n_k,)``: the cell's bounds of eq. (MIP_general_c); ``+inf`` and ``-inf``
        for a cell without an input whose output meets ``|Phi_NN| <= u``.
    u
        The output bound the cells were tightened with, shape (n_out,).
    net_id
        :func:`flnotes.network.fingerprint` of the network.

    The constructor checks the fields: real numbers (no booleans or strings), edges finite and strictly increasing,
    each cell's bounds finite or, for an empty cell, ``+inf`` and ``-inf`` throughout, ``u`` finite and > 0, shapes
    consistent (``ValueError`` naming the field). Whether the bounds hold (``L <= U`` included) is
    :func:`check_atlas`'s to judge.
    """

    edges: tuple
    L: tuple
    U: tuple
    u: Array
    net_id: str

    def __post_init__(self) -> None:
        def frozen(a, name: str) -> Array:
            a = as_floats(a, name)  # real numbers only: booleans, strings and the like are refused by name
            if np.any(np.isnan(a)):
                raise ValueError(f"{name} must not hold NaN")
            # backed by bytes: read-only for good (an atlas is shared by every controller of its network)
            return np.frombuffer(np.ascontiguousarray(a).tobytes(), dtype=float).reshape(a.shape)

        def parts(x, name: str, what: str) -> tuple:
            if isinstance(x, (str, bytes, Mapping, set, frozenset)) or not isinstance(x, Iterable) or (
                    isinstance(x, np.ndarray) and x.ndim == 0):
                raise ValueError(f"BoundAtlas.{name} must be a tuple (or list) of arrays, {what}, got {brief(x)}")
            return tuple(frozen(a, f"BoundAtlas.{name}[{i}]") for i, a in enumerate(x))

        if not isinstance(self.net_id, str):
            raise TypeError(f"BoundAtlas.net_id must be a str (fingerprint(net)), got {type(self.net_id).__name__}")
        edges = parts(self.edges, "edges", "one per input")
        if not edges or any(e.ndim != 1 or e.size < 2 or not np.all(np.isfinite(e)) or np.any(np.diff(e) <= 0)
                            for e in edges):
            raise ValueError("BoundAtlas.edges must be one finite, strictly increasing array of at least 2 edges per "
                             "input")
        cells = tuple(e.size - 1 for e in edges)
        L, U = parts(self.L, "L", "one per hidden layer"), parts(self.U, "U", "one per hidden layer")
        if not L or len(L) != len(U) or any(a.shape != b.shape or a.ndim != len(cells) + 1 or a.shape[:-1] != cells
                                            for a, b in zip(L, U)):
            raise ValueError(f"BoundAtlas.L and U must hold, per hidden layer, arrays of the same shape cells + (n_k,) "
                             f"with cells = {cells} (from the edges)")
        _check_cell_bounds(L, U)
        u = frozen(self.u, "BoundAtlas.u")
        if u.ndim != 1 or u.size == 0 or not np.all(np.isfinite(u)) or np.any(u <= 0):
            raise ValueError(f"BoundAtlas.u must be a positive, finite vector (n_out,), got {u}")
        for k, v in dict(edges=edges, L=L, U=U, u=u).items():
            object.__setattr__(self, k, v)

    @property
    def digest(self) -> str:
        """SHA-256 of the atlas's contents (edges, bounds, ``u``, network): the shipped atlas is checked against its
        recorded digest (:data:`SHIPPED`)."""
        h = hashlib.sha256(self.net_id.encode())
        for a in (*self.edges, *self.L, *self.U, self.u):
            h.update(repr(a.shape).encode())
            h.update(a.tobytes())
        return h.hexdigest()

    @property
    def cells(self) -> tuple:
        """Cells per input."""
        return tuple(len(e) - 1 for e in self.edges)

    @property
    def lo(self) -> Array:
        """The domain's lower corner."""
        return np.array([e[0] for e in self.edges])

    @property
    def hi(self) -> Array:
        """The domain's upper corner."""
        return np.array([e[-1] for e in self.edges])

    @property
    def empty(self) -> Array:
        """Cells (shape ``cells``) without an input whose output meets the bound."""
        return np.isinf(self.L[0][..., 0]) & (self.L[0][..., 0] > 0)

    def covers(self, lo: Array, hi: Array) -> Array:
        """Per box (rows of ``lo, hi``, shape (T, n_in), or one box (n_in,)), whether it lies in the domain.

        ``lo <= hi`` must be numbers of these shapes (``±inf`` for a box without end, which no domain holds), or a
        number for every input (``ValueError`` naming them otherwise, NaN included)."""
        lo2, hi2, _ = check_boxes(lo, hi, len(self.edges), infinite=True)
        return self._covers(lo2, hi2)

    def _covers(self, lo: Array, hi: Array) -> Array:
        """:meth:`covers` without the checks of its numbers (the callers here pass checked boxes)."""
        lo, hi = np.atleast_2d(np.asarray(lo, float)), np.atleast_2d(np.asarray(hi, float))
        if lo.shape != hi.shape or lo.ndim != 2 or lo.shape[1] != len(self.edges):
            raise ValueError(f"lo and hi must have shape (T, {len(self.edges)}), got {lo.shape} and {hi.shape}")
        return np.all(lo >= self.lo, axis=1) & np.all(hi <= self.hi, axis=1)

    def cover(self, lo: Array, hi: Array) -> tuple[list, list]:
        """Node bounds of the boxes ``lo, hi`` (shape (T, n_in), or one box (n_in,); each inside the domain) from the
        cells they meet.

        Returns ``(L, U)``, per hidden layer an array (T, n_k): the minimum of the cells' ``L`` and the maximum of
        their ``U``. A box that meets only empty cells gets ``L = +inf``, ``U = -inf`` (no admissible input in it).
        ``lo <= hi`` must be finite numbers of these shapes, or a number for every input (``ValueError`` naming them
        otherwise).
        """
        lo2, hi2, _ = check_boxes(lo, hi, len(self.edges))
        return self._cover(lo2, hi2)

    def _cover(self, lo: Array, hi: Array) -> tuple[list, list]:
        """:meth:`cover` without the checks of its numbers (the callers here pass checked boxes)."""
        lo, hi = np.atleast_2d(np.asarray(lo, float)), np.atleast_2d(np.asarray(hi, float))
        if lo.shape != hi.shape or lo.shape[1] != len(self.edges):
            raise ValueError(f"lo and hi must have shape (T, {len(self.edges)}), got {lo.shape} and {hi.shape}")
        if np.any(lo > hi):
            raise ValueError("a box is empty (lo > hi in some input)")
        if not np.all(self._covers(lo, hi)):
            raise ValueError("a box reaches outside the atlas's domain: its cells say nothing there")
        out_L = [np.empty((lo.shape[0], a.shape[-1])) for a in self.L]
        out_U = [np.empty((lo.shape[0], a.shape[-1])) for a in self.U]
        for t in range(lo.shape[0]):
            # the cells [edges[c], edges[c+1]] meeting [lo, hi]: edges[c+1] >= lo and edges[c] <= hi
            sl = tuple(slice(int(np.searchsorted(e[1:], lo[t, i], side="left")),
                             int(np.searchsorted(e[:-1], hi[t, i], side="right")))
                       for i, e in enumerate(self.edges))
            for k in range(len(self.L)):
                out_L[k][t] = self.L[k][sl].reshape(-1, self.L[k].shape[-1]).min(axis=0)
                out_U[k][t] = self.U[k][sl].reshape(-1, self.U[k].shape[-1]).max(axis=0)
        return out_L, out_U

    def save(self, path: Union[str, Path]) -> None:
        """Write the atlas to an ``.npz`` file (:func:`load_atlas` reads it)."""
        np.savez_compressed(path, n_in=len(self.edges), n_layers=len(self.L), u=self.u, net_id=self.net_id,
                            **{f"edges{i}": e for i, e in enumerate(self.edges)},
                            **{f"L{k}": a for k, a in enumerate(self.L)}, **{f"U{k}": a for k, a in enumerate(self.U)})


def _check_cell_bounds(L: tuple, U: tuple) -> None:
    """Every cell's bounds are finite in every hidden layer or, for a cell without an input whose output meets the
    bound (``L[0]`` of its first neuron ``+inf``), ``L = +inf`` and ``U = -inf`` throughout; else ``ValueError``
    naming the first bad cell. (``L <= U`` is a matter of the bounds holding: :func:`check_atlas`.)"""
    empty = np.isposinf(L[0][..., :1])
    for k, (a, b) in enumerate(zip(L, U)):
        bad = np.where(empty, ~(np.isposinf(a) & np.isneginf(b)), ~(np.isfinite(a) & np.isfinite(b)))
        if np.any(bad):
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValueError(
                f"BoundAtlas.L[{k}] and U[{k}] at cell {idx[:-1]}, neuron {idx[-1]}: L = {float(a[idx])!r}, "
                f"U = {float(b[idx])!r}; a cell's bounds must be finite, or L = +inf and U = -inf in every layer for a "
                f"cell without an admissible input (L[0] = +inf marks it)")


def _first_crossed(atlas: "BoundAtlas") -> Optional[str]:
    """Where a cell with an admissible input has a lower bound above its upper bound (``L > U``), else ``None``."""
    for k, (a, b) in enumerate(zip(atlas.L, atlas.U)):
        bad = np.isfinite(a) & (a > b)
        if np.any(bad):
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            return (f"at cell {idx[:-1]}, neuron {idx[-1]} of hidden layer {k + 1}: L = {float(a[idx])!r} > "
                    f"U = {float(b[idx])!r}")
    return None


def load_atlas(path: Union[str, Path]) -> BoundAtlas:
    """The atlas written by :meth:`BoundAtlas.save` (check it against its network with :func:`check_atlas`)."""
    with np.load(path, allow_pickle=False) as f:
        n_in, n_layers = int(f["n_in"]), int(f["n_layers"])
        return BoundAtlas(tuple(np.array(f[f"edges{i}"], float) for i in range(n_in)),
                          tuple(np.array(f[f"L{k}"], float) for k in range(n_layers)),
                          tuple(np.array(f[f"U{k}"], float) for k in range(n_layers)),
                          np.array(f["u"], float), str(f["net_id"]))


def bound_atlas(net: ReLUNet, lo, hi, u, cells: Sequence[int]) -> BoundAtlas:
    """LP node bounds (:func:`flnotes.lp_bounds` with ``out_bounds=(-u, u)``) on every cell of a grid over the box.

    Parameters
    ----------
    net
        The network (at least one hidden layer).
    lo, hi
        The domain box over the network's input ``[z, v]``, shape (n_in,).
    u
        The output bound ``u_max^eps`` (eq. Phi_NN_ep), positive, shape (n_out,) or a number: the atlas serves
        every controller whose ``u_max^eps`` is at most this.
    cells
        Cells per input (positive integers, n_in of them): equal widths per input.

    Returns
    -------
    BoundAtlas
        Checked on a fixed sample (:func:`check_atlas`) before it is returned.
    """
    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    if net.K < 2:
        raise ValueError("the network has no hidden layer: it has no node bounds to keep")
    lo, hi = check_box(lo, hi, net.n_in)
    if np.any(hi <= lo):
        raise ValueError("the domain box needs hi > lo in every input")
    u = as_vector(u, net.n_out, "u")
    if np.any(u <= 0):
        raise ValueError(f"u must be positive and finite, got {u}")
    if isinstance(cells, (str, bytes, dict, set, frozenset)):
        raise ValueError(f"cells must be {net.n_in} positive integers in order (a tuple, list or array), got {cells!r}")
    cells = tuple(cells) if hasattr(cells, "__iter__") else (cells,)
    if len(cells) != net.n_in:
        raise ValueError(f"cells must be {net.n_in} positive integers (cells per input), got {cells!r}")
    cells = tuple(check_int(c, "each of cells", 1, "cells per input") for c in cells)
    edges = tuple(np.linspace(lo[i], hi[i], c + 1) for i, c in enumerate(cells))
    widths = [len(b) for b in net.b[:-1]]
    L = [np.full(cells + (n,), np.inf) for n in widths]
    U = [np.full(cells + (n,), -np.inf) for n in widths]
    for idx in itertools.product(*(range(c) for c in cells)):
        c_lo = np.array([edges[i][j] for i, j in enumerate(idx)])
        c_hi = np.array([edges[i][j + 1] for i, j in enumerate(idx)])
        try:
            nb = lp_bounds(net, c_lo, c_hi, out_bounds=(-u, u))
        except EmptyBoxError:
            continue
        for k in range(len(widths)):
            L[k][idx], U[k][idx] = nb.L[k], nb.U[k]
    atlas = BoundAtlas(edges, tuple(L), tuple(U), u, fingerprint(net))
    check_atlas(net, atlas)
    return atlas


def check_atlas(net: ReLUNet, atlas: BoundAtlas, seed: int = 0) -> None:
    """Raise ValueError unless ``atlas`` is of ``net`` (same :func:`flnotes.network.fingerprint`, shapes) and
    holds at a fixed sample of its domain: every point whose output meets ``|Phi_NN| <= u`` has its pre-activations
    within its cell's bounds. A sample cannot prove the bounds: it finds an atlas computed for another network, box or
    bound, or one changed grossly, not bounds lowered below the cells' true extremes but above the sample's. Use
    atlases from :func:`bound_atlas` or the shipped ones (whose contents are checked against a recorded digest).

    ``seed`` is the seed of the sample: an integer >= 0, ``None`` for a fresh random sample, or numpy's own seed
    objects (a ``Generator``, ``BitGenerator`` or ``SeedSequence``), as ``np.random.default_rng`` takes them."""
    if not isinstance(atlas, BoundAtlas):
        raise TypeError(f"expected a flnotes.BoundAtlas, got {type(atlas).__name__}")
    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    seed = check_seed(seed, "seed", "the seed of the sample the atlas is checked on, or None for a fresh one")
    if atlas.net_id != fingerprint(net):
        raise ValueError("the atlas was computed for another network (its parameters differ): compute it with "
                         "fl.bound_atlas(net, lo, hi, u, cells)")
    widths = [len(b) for b in net.b[:-1]]
    if len(atlas.edges) != net.n_in or [a.shape[-1] for a in atlas.L] != widths or atlas.u.shape != (net.n_out,):
        raise ValueError("the atlas's shapes do not fit the network (inputs, hidden layers or outputs)")
    crossed = _first_crossed(atlas)
    if crossed is not None:
        raise ValueError(f"the atlas does not hold: {crossed} (no pre-activation lies between them; a cell's bounds "
                         f"need L <= U): compute it with fl.bound_atlas(net, lo, hi, u, cells)")
    X = np.random.default_rng(seed).uniform(atlas.lo, atlas.hi, size=(N_SAMPLE, net.n_in))
    out, pre = net.forward(X)
    ok = np.all(np.abs(out) <= atlas.u, axis=1)
    idx = tuple(np.clip(np.searchsorted(e, X[:, i], side="right") - 1, 0, len(e) - 2)
                for i, e in enumerate(atlas.edges))
    for k, a in enumerate(pre):
        L, U = atlas.L[k][idx], atlas.U[k][idx]
        tol = 1e-9 * (1.0 + np.abs(a))
        bad = ok[:, None] & ((a < L - tol) | (a > U + tol))
        if np.any(bad):
            i = int(np.flatnonzero(bad.any(axis=1))[0])
            raise ValueError(f"the atlas does not hold for this network: at x = {X[i]} (output within u) a "
                             f"pre-activation of hidden layer {k + 1} leaves its cell's bounds")


def shipped_atlas(net: ReLUNet, lo, hi, u) -> Optional[BoundAtlas]:
    """The shipped atlas of ``net`` (``flnotes/data``, :data:`SHIPPED`) when it serves the box ``[lo, hi]`` and the
    bound ``u`` (the box inside its domain, ``u`` at most its own), else ``None``.

    ``lo <= hi`` must be finite numbers (n_in,) each and ``u`` finite numbers > 0, one per output or one for all
    (``ValueError`` naming the argument otherwise; ``TypeError`` for a ``net`` that is no network)."""
    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    lo, hi = check_box(lo, hi, net.n_in)
    u = as_vector(u, net.n_out, "u")
    if np.any(u <= 0):
        raise ValueError(f"u must be positive (the output bound u_max^eps, one per output or one for all), got "
                         f"{brief(u.tolist())}")
    net_id = fingerprint(net)
    for name, (_, digest, shipped_for) in SHIPPED.items():
        if shipped_for != net_id:
            continue
        atlas = _load_shipped(DATA / name)
        if atlas.digest != digest:  # checked at every call: the object handed out is the file as shipped
            raise ValueError(f"the shipped atlas {name} is not the one written by flnotes.atlas.write_shipped_atlases "
                             "(its contents changed): restore it, or pass atlas=False")
        if atlas._covers(lo, hi)[0] and np.all(u <= atlas.u):
            return atlas
    return None


_SHIPPED_CACHE: dict = {}


def _load_shipped(path: Path) -> BoundAtlas:
    if path not in _SHIPPED_CACHE:
        try:
            _SHIPPED_CACHE[path] = load_atlas(path)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"the shipped atlas {path.name} cannot be read ({type(exc).__name__}: {exc}): restore "
                             "the package's data folder, or pass atlas=False") from None
    return _SHIPPED_CACHE[path]


def write_shipped_atlases(folder: Optional[Union[str, Path]] = None) -> list[str]:
    """Compute and write the atlases of :data:`SHIPPED` (the MSD's network of the book, on its domain box, with
    ``u = u_max - eps`` of its certified ``eps``). Only to change them on purpose: commit the files and record
    their digests (:attr:`BoundAtlas.digest`, returned beside each name) and their network's fingerprint in
    :data:`SHIPPED`."""
    from . import paper

    folder = DATA if folder is None else Path(folder)
    out = []
    for name, (cells, _, _) in SHIPPED.items():
        system = name.split(".atlas")[0]
        net, _ = paper.paper_net(system)
        sysm = paper.system(system)
        eps = float(np.max(paper.paper_eps(system).upper))
        atlas = bound_atlas(net, sysm.lo, sysm.hi, np.asarray(sysm.u_max, float) - eps, cells)
        atlas.save(folder / name)
        out.append(f"{name} (digest {atlas.digest})")
    return out
