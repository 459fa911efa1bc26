"""LP node bounds kept along the closed loop and reused on the boxes they contain (``MPCOptions.bound_cache``).

LP tightening (:func:`flnotes.lp_bounds`) with the output bound ``|Phi_NN| <= u_max^eps`` gives, for an input box
``B`` of ``[z(k); v(k)]``, bounds ``L <= W^k y^{k-1} + b^k <= U`` that hold at every point of ``B`` whose output meets
the bound (eq. MIP_general_c). They depend on the box and the network only, not on the measured state or the step
``k``. So for a later box ``B' ⊆ B`` they are valid again: every point of ``B'`` meeting the output bound is such a
point of ``B``. :meth:`BoundCache.prior` intersects the FBBT bounds of a new box with those of every kept box that
contains it, and the LP tightening starts from there: neurons already stable need no LP (``skip_stable``), and the
others get the LP on a relaxation with tighter big-M constants. The bounds stay valid, so the lever is exact.

Along the book's closed loops the level-set boxes of one step often lie inside boxes tightened at earlier steps
(chapter "Making it real-time" counts them and measures the effect on the book's Quad-1D and the systems not in the
book).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..bounds import NodeBounds

Array = np.ndarray

#: Boxes a :class:`BoundCache` keeps (the oldest are dropped first): a few closed-loop seconds of level-set boxes.
CACHE_BOXES = 512


class BoundCache:
    """LP node bounds of earlier input boxes, one row per box (first in, first out).

    Parameters
    ----------
    capacity
        Boxes kept (:data:`CACHE_BOXES`).

    Attributes
    ----------
    lo, hi
        The kept boxes, shape (n_boxes, n_in), or ``None`` while empty.
    L, U
        Their bounds per hidden layer, each of shape (n_boxes, n_k).
    served, asked
        Boxes that found a kept box containing them, and boxes asked for, since the last :meth:`clear`.
    """

    def __init__(self, capacity: int = CACHE_BOXES):
        if isinstance(capacity, bool) or int(capacity) != capacity or capacity < 1:
            raise ValueError(f"capacity must be a positive integer (boxes kept), got {capacity!r}")
        self.capacity = int(capacity)
        self.clear()

    def clear(self) -> None:
        """Forget every kept box."""
        self.lo: Optional[Array] = None
        self.hi: Optional[Array] = None
        self.L: list = []
        self.U: list = []
        self.served = 0
        self.asked = 0

    def __len__(self) -> int:
        return 0 if self.lo is None else int(self.lo.shape[0])

    @staticmethod
    def _check(lo: Array, hi: Array, nb: NodeBounds) -> tuple[Array, Array]:
        lo, hi = np.atleast_2d(np.asarray(lo, float)), np.atleast_2d(np.asarray(hi, float))
        if lo.shape != hi.shape:
            raise ValueError(f"lo and hi must have the same shape (n_boxes, n_in), got {lo.shape} and {hi.shape}")
        if any(np.shape(a) != (lo.shape[0], np.shape(a)[-1]) for a in list(nb.L) + list(nb.U)):
            raise ValueError(f"the bounds must hold one row per box ({lo.shape[0]}): arrays of shape (n_boxes, n_k)")
        return lo, hi

    def prior(self, lo: Array, hi: Array, nb: NodeBounds) -> NodeBounds:
        """``nb`` (bounds valid on the boxes ``lo, hi``, one row per box) intersected with the bounds of every kept
        box that contains a box. A box whose intersection would be empty keeps ``nb`` (the LPs then decide)."""
        lo, hi = self._check(lo, hi, nb)
        L, U = [np.array(a, float) for a in nb.L], [np.array(a, float) for a in nb.U]
        self.asked += lo.shape[0]
        if self.lo is None:
            return NodeBounds(L, U, nb.out_L, nb.out_U, method=nb.method)
        if self.lo.shape[1] != lo.shape[1]:
            raise ValueError(f"the boxes have {lo.shape[1]} inputs, the kept ones {self.lo.shape[1]}")
        t_lo, t_hi = 1e-12 * (1.0 + np.abs(lo)), 1e-12 * (1.0 + np.abs(hi))  # round-off of the box arithmetic
        inside = (np.all(self.lo[None] <= (lo + t_lo)[:, None], axis=2)
                  & np.all(self.hi[None] >= (hi - t_hi)[:, None], axis=2))  # (boxes asked, boxes kept)
        for t in np.flatnonzero(inside.any(axis=1)):
            m = inside[t]
            nL = [np.maximum(L[k][t], self.L[k][m].max(axis=0)) for k in range(len(L))]
            nU = [np.minimum(U[k][t], self.U[k][m].min(axis=0)) for k in range(len(U))]
            if all(np.all(a <= b) for a, b in zip(nL, nU)):
                self.served += 1
                for k in range(len(L)):
                    L[k][t], U[k][t] = nL[k], nU[k]
        return NodeBounds(L, U, nb.out_L, nb.out_U, method=nb.method)

    def add(self, lo: Array, hi: Array, nb: NodeBounds) -> None:
        """Keep the bounds ``nb`` of the boxes ``lo, hi`` (valid at every point of its box meeting the output bound)."""
        lo, hi = self._check(lo, hi, nb)
        if self.lo is None:
            self.lo, self.hi = lo.copy(), hi.copy()
            self.L, self.U = [np.array(a, float) for a in nb.L], [np.array(a, float) for a in nb.U]
        else:
            self.lo, self.hi = np.vstack([self.lo, lo]), np.vstack([self.hi, hi])
            self.L = [np.vstack([a, b]) for a, b in zip(self.L, nb.L)]
            self.U = [np.vstack([a, b]) for a, b in zip(self.U, nb.U)]
        drop = len(self) - self.capacity
        if drop > 0:
            self.lo, self.hi = self.lo[drop:], self.hi[drop:]
            self.L, self.U = [a[drop:] for a in self.L], [a[drop:] for a in self.U]
