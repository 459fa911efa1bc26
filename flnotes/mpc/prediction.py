"""The prediction model of eq. (MPC_form_miqp): condensing, cost, boxes, terminal rows, feasibility.

One place builds what every program form, lever and fallback of the MPC uses: the condensed prediction
``z(k) = Sx[k] z(0) + Su[k] V`` (``V = [v(0); ...; v(N_p-1)]``), the cost as a quadratic in ``V``, the
state box and the optional terminal set as rows in ``V``, the screening QP (the program without the
network constraint) and the one feasibility check of a plan (boxes to :data:`flnotes.solvers.FEAS_TOL`,
the network bound by the forward pass to :data:`flnotes.solvers.BOUND_TOL`).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from .._checks import as_floats
from ..enclosure import AffineEnclosure, contract, outer_rows
from ..network import ReLUNet
from ..solvers import BOUND_TOL, FEAS_TOL
from ..systems import condense
from ..tightening import ellipsoid_box, horizon_boxes

Array = np.ndarray

#: DAQP settings for the big-M programs: its cycling guard is loosened (the big-M rows are degenerate;
#: with the defaults DAQP may stop with "cycling" on them).
DAQP_OPTIONS = {"params": {"cycle_tol": 1000, "progress_tol": 1e-10}}


class Prediction:
    """The condensed model, cost and constraints of eq. (MPC_form_miqp) without the network rows.

    Parameters
    ----------
    net
        ``Phi_NN`` (for the forward-pass checks).
    Ad, Bd
        Discrete Brunovsky pair (n_z, n_z), (n_z, m).
    horizon
        ``N_p``.
    Q, R, P
        Weights of ``sum_k ||z(k) - z_ref(k)||_Q^2 + ||v(k)||_R^2 + ||z(N_p) - z_ref(N_p)||_P^2`` (``P``: the
        terminal weight ``P_f``).
    z_lo, z_hi, v_lo, v_hi
        The state box ``Z_z`` (eq. MPC_form_miqp_d), imposed on ``z(1..N_p)``, and the input range.
    u_eps
        ``u_max^eps = u_max - eps`` (m,), eq. (Phi_NN_ep).
    terminal
        Optional ``(F, g)``: the terminal constraint ``F z(N_p) <= g``.
    enclosure
        Optional :class:`flnotes.AffineEnclosure` of the network over a box that contains ``[z_lo, z_hi] x
        [v_lo, v_hi]``: :meth:`relaxation` then adds its slab at every step, and :meth:`level_boxes` cuts the
        boxes to it.

    Attributes
    ----------
    Sx, Su, H
        ``z(k) = Sx[k] z0 + Su[k] V`` and the Hessian of the cost in ``V`` (positive definite).
    T
        (N_p, n_z + m, N_p m): the network input ``[z(k); v(k)] = T[k] V + [Sx[k] z0; 0]``.
    """

    def __init__(self, net: ReLUNet, Ad: Array, Bd: Array, horizon: int, Q: Array, R: Array, P: Array, *,
                 z_lo: Array, z_hi: Array, v_lo: Array, v_hi: Array, u_eps: Array,
                 terminal: Optional[tuple[Array, Array]] = None, enclosure: Optional[AffineEnclosure] = None):
        self.net, self.N = net, int(horizon)
        self.Ad, self.Bd = np.asarray(Ad, float), np.asarray(Bd, float)
        self.nz, self.m = self.Bd.shape
        self.Q, self.R, self.P = Q, R, P
        self.z_lo, self.z_hi, self.v_lo, self.v_hi = z_lo, z_hi, v_lo, v_hi
        self.u_eps = np.asarray(u_eps, float)
        N, nz, m = self.N, self.nz, self.m
        self.Sx, self.Su, self.H = condense(self.Ad, self.Bd, N, Q, R, P)
        self.Wk = [Q] * N + [P]
        self.H_inv = np.linalg.inv(self.H)
        T = np.zeros((N, nz + m, N * m))
        for k in range(N):
            T[k, :nz] = self.Su[k]
            T[k, nz:, k * m:(k + 1) * m] = np.eye(m)
        self.T = T
        self.F = self.g = None
        rows = [self.Su[1:].reshape(N * nz, N * m)]
        if terminal is not None:
            F, g = (np.atleast_2d(as_floats(a, name)) for a, name in zip(terminal, ("terminal F", "terminal g")))
            g = g.reshape(-1)
            if F.ndim != 2 or F.shape[1] != nz or g.shape != (F.shape[0],):
                raise ValueError(f"terminal must be (F, g) with F of shape (r, {nz}) and g of shape (r,), got "
                                 f"{F.shape} and {g.shape}")
            if not (np.all(np.isfinite(F)) and np.all(np.isfinite(g))):
                raise ValueError("terminal (F, g) contains NaN or inf")
            self.F, self.g = F, g
            rows.append(F @ self.Su[N])
        #: The state rows in ``V``: ``z(1..N_p)`` in the box, then ``F z(N_p) <= g``; see :meth:`state_bounds`.
        self.A_state = np.vstack(rows)
        if enclosure is not None and not enclosure._covers(np.r_[z_lo, v_lo], np.r_[z_hi, v_hi]):
            raise ValueError("the enclosure's box must contain the program's box [z_lo, z_hi] x [v_lo, v_hi] (it says "
                             "nothing outside its box): compute it on the network's domain box")
        self.enclosure = enclosure

    # ------------------------------------------------------------------ the model and the cost
    def predict(self, z0: Array, V: Array) -> Array:
        """``z(0..N_p)`` of eq. (MPC_form_miqp_c) for the plan ``V`` ((N_p, m) or flat), shape (N_p + 1, n_z)."""
        return self.Sx @ np.asarray(z0, float) + self.Su @ np.asarray(V, float).reshape(-1)

    def linear(self, z0: Array, z_ref: Array) -> tuple[Array, float]:
        """``f``, ``c0`` of the cost ``J(V) = 0.5 V'HV + f'V + c0`` (eq. MPC_form_miqp_a) for ``z0`` and ``z_ref``."""
        E = self.Sx @ z0 - z_ref
        f = 2 * sum(self.Su[k].T @ self.Wk[k] @ E[k] for k in range(self.N + 1))
        c0 = float(sum(E[k] @ self.Wk[k] @ E[k] for k in range(self.N + 1)))
        return f, c0

    def cost(self, V: Array, f: Array, c0: float) -> float:
        """``J(V) = 0.5 V'HV + f'V + c0``."""
        V = np.asarray(V, float).reshape(-1)
        return float(0.5 * V @ self.H @ V + f @ V + c0)

    def plan_cost(self, Z: Array, V: Array, z_ref: Array) -> float:
        """Eq. (MPC_form_miqp_a) for a plan given as trajectories."""
        E = np.asarray(Z) - np.asarray(z_ref)
        return float(sum(E[k] @ self.Wk[k] @ E[k] for k in range(self.N + 1))
                     + sum(v @ self.R @ v for v in np.asarray(V).reshape(self.N, self.m)))

    # ------------------------------------------------------------------ constraints
    def state_bounds(self, z0: Array) -> tuple[Array, Array]:
        """Lower and upper bounds of ``A_state V``: the state box for ``k = 1..N_p`` and the terminal rows."""
        Zf = (self.Sx @ z0)[1:].reshape(-1)
        lo, hi = np.tile(self.z_lo, self.N) - Zf, np.tile(self.z_hi, self.N) - Zf
        if self.F is not None:
            lo = np.concatenate([lo, np.full(self.g.size, -np.inf)])
            hi = np.concatenate([hi, self.g - self.F @ (self.Sx[self.N] @ z0)])
        return lo, hi

    def _outputs(self, z0: Array, V: Array) -> Array:
        """``Phi_NN(z(k), v(k))`` at the predicted steps k = 0..N_p-1 of the plan ``V`` (forward pass), (N_p, m)."""
        V = np.asarray(V, float).reshape(self.N, self.m)
        return self.net(np.hstack([self.predict(z0, V)[: self.N], V]))

    def violated(self, z0: Array, V: Array, tol: float = BOUND_TOL) -> Array:
        """Predicted steps ``k`` with ``|Phi_NN(z(k), v(k))| > u_max^eps + tol`` (forward pass)."""
        return np.flatnonzero(np.any(np.abs(self._outputs(z0, V)) > self.u_eps + tol, axis=1))

    def near_bound(self, z0: Array, V: Array, frac: float) -> Array:
        """Predicted steps ``k`` of the plan ``V`` with ``|Phi_NN(z(k), v(k))| >= (1 - frac) u_max^eps`` for some
        input (forward pass): the steps at or near the network bound."""
        return np.flatnonzero(np.any(np.abs(self._outputs(z0, V)) >= (1.0 - frac) * self.u_eps, axis=1))

    def first_range(self, z0: Array, bound: Array) -> Optional[tuple[Array, Array]]:
        """The exact set of first inputs ``{v(0) in [v_lo, v_hi] : |Phi_NN(z0, v(0))| <= bound}`` when it is one
        interval ``[a, b]`` (one input only: :func:`flnotes.exact_1d_feasible_set`, eq. Phi_NN_ep at the measured
        state, where ``z(0) = z0`` is known); ``None`` for several inputs, an empty set or several intervals.

        Each end is checked as every plan is, by the forward pass to its round-off (``|Phi_NN(z0, a)| <= bound +``
        :data:`flnotes.solvers.BOUND_TOL`; an end past that would be moved inward by units in the last place), so
        every ``v(0)`` of ``[a, b]`` meets the bound as the check reads it, and every input outside it by more than the
        round-off of the ends (they are zeros of affine pieces, :func:`flnotes.exact_1d_feasible_set`) breaks it: the bounds
        ``a <= v(0) <= b`` are step 0's network constraint.
        """
        if self.m != 1:
            return None
        from ..control import exact_1d_feasible_set

        z0 = np.asarray(z0, float)
        u = float(np.asarray(bound, float).reshape(-1)[0])
        iv = exact_1d_feasible_set(self.net, z0, float(self.v_lo[0]), float(self.v_hi[0]), u)
        if iv.shape[0] != 1:
            return None
        a, b = float(iv[0, 0]), float(iv[0, 1])
        da, db = float(np.spacing(a)), float(np.spacing(b))
        for _ in range(64):  # inward by a step that doubles: a few units in the last place to 2^64 of them
            out = np.abs(self.net(np.array([np.r_[z0, a], np.r_[z0, b]]))[:, 0]) - BOUND_TOL
            if out[0] <= u and out[1] <= u:
                return np.array([a]), np.array([b])
            if out[0] > u:
                a, da = a + abs(da), 2.0 * da
            if out[1] > u:
                b, db = b - abs(db), 2.0 * db
            if a > b:
                return None
        return None

    def excess(self, z0: Array, V: Array, steps) -> float:
        """``max |Phi_NN(z(k), v(k))| - u_max^eps`` over the predicted ``steps`` of the plan ``V``."""
        V = np.asarray(V, float).reshape(self.N, self.m)
        X = np.hstack([self.predict(z0, V)[: self.N], V])[list(steps)]
        return float(np.max(np.abs(self.net(X)) - self.u_eps))

    def feasible(self, z0: Array, V: Array, tol: float = FEAS_TOL, network: bool = True) -> bool:
        """Does the plan ``V`` satisfy eq. (MPC_form_miqp_b)-(d) (and the terminal rows)?

        The boxes and terminal rows to ``tol`` (a solver's feasibility tolerance), the network bound by the
        forward pass to :data:`flnotes.solvers.BOUND_TOL` (round-off only; skipped with ``network=False``).
        """
        V = np.asarray(V, float).reshape(-1)
        if V.shape != (self.N * self.m,) or not np.all(np.isfinite(V)):
            return False
        lo, hi = self.state_bounds(z0)
        s = self.A_state @ V
        if np.any(s < lo - tol) or np.any(s > hi + tol):
            return False
        Vm = V.reshape(self.N, self.m)
        if np.any(Vm < self.v_lo - tol) or np.any(Vm > self.v_hi + tol):
            return False
        return (not network) or self.violated(z0, V).size == 0

    def qp(self, f: Array, z0: Array, G: Optional[Array] = None, g_lo: Optional[Array] = None,
           g_hi: Optional[Array] = None, fixed: Optional[Array] = None) -> tuple[Optional[Array], float, int]:
        """The QP ``min J(V)`` over the boxes and terminal rows (no network), plus optional rows ``g_lo <= G V <= g_hi``.

        Solved by DAQP (``H`` is positive definite). ``fixed``: the first ``len(fixed)`` entries of the flat ``V``
        (``v(0..k-1)``) held at these values exactly (finite and inside ``[v_lo, v_hi]``, else a ``ValueError``): the QP
        is solved over the later entries alone (:meth:`_qp_fixed`), and is infeasible (flag -1) where the held
        entries alone break a row. Returns ``(V or None, J - c0, DAQP exit flag)``; a plan only for flags 1 (optimal)
        and 2 (optimal, soft constraints); flag -1 means infeasible.
        """
        V, fval, flag, _ = self.qp_multipliers(f, z0, G, g_lo, g_hi, fixed=fixed)
        return V, fval, flag

    def relaxation(self, f: Array, z0: Array, first: Optional[tuple[Array, Array]] = None
                   ) -> tuple[Optional[Array], float, int]:
        """The convex relaxation of eq. (MPC_form_miqp) that the engine solves first: :meth:`qp` with, when the model
        has an :attr:`enclosure`, the slab that contains ``|Phi_NN(z(k), v(k))| <= u_max^eps`` at every step
        (:func:`flnotes.enclosure.outer_rows`; step 0's only when ``z0`` lies in the enclosure's box). Every plan of
        the program (to the forward-pass check's :data:`flnotes.solvers.BOUND_TOL`) satisfies its rows, so its optimum
        is a lower bound of the program's, and the tighter the slab the closer. ``first``: step 0's exact range
        (:meth:`first_range`), imposed on ``v(0)`` too. Returns what :meth:`qp` returns."""
        enc = self.enclosure
        if enc is None:
            V, fval, flag, _ = self.qp_multipliers(f, z0, first=first)
            return V, fval, flag
        z0 = np.asarray(z0, float)
        G, g_lo, g_hi = outer_rows(enc, self.T, self.Sx @ z0, self.u_eps + BOUND_TOL, self.nz, self._inside(z0))
        V, fval, flag, _ = self.qp_multipliers(f, z0, G, g_lo, g_hi, first=first)
        return V, fval, flag

    def qp_multipliers(self, f: Array, z0: Array, G: Optional[Array] = None, g_lo: Optional[Array] = None,
                       g_hi: Optional[Array] = None, first: Optional[tuple[Array, Array]] = None,
                       fixed: Optional[Array] = None) -> tuple[Optional[Array], float, int, Optional[Array]]:
        """:meth:`qp` and the multipliers of the rows ``G`` at its optimum (DAQP's: positive on an active upper
        bound ``g_hi``, negative on an active lower bound, zero on an inactive row); ``None`` without a plan.
        ``first = (a, b)``: ``v(0)`` within ``[a, b]`` as well (:meth:`first_range`); ``fixed``: as in :meth:`qp`.

        ``f`` must be ``N_p m`` finite numbers, ``z0`` one finite state, ``G`` a finite ``(r, N_p m)`` array given with
        ``g_lo`` and ``g_hi`` (numbers or ``r`` of them, no NaN; ``-inf`` and ``inf`` leave a side open): anything
        else is a ``ValueError`` that names it (DAQP reads arrays of the wrong size past their end without a word)."""
        import daqp

        f, z0, G, g_lo, g_hi = self._qp_arguments(f, z0, G, g_lo, g_hi)
        lo, hi = self.state_bounds(z0)
        A, bl, bu = self.A_state, lo, hi
        if G is not None:
            A, bl, bu = np.vstack([A, G]), np.concatenate([bl, g_lo]), np.concatenate([bu, g_hi])
        N = self.N
        # DAQP: the first N m constraints are simple bounds on V, the rest rows of A
        bu_all = np.concatenate([np.tile(self.v_hi, N), np.minimum(bu, 1e30)])
        bl_all = np.concatenate([np.tile(self.v_lo, N), np.maximum(bl, -1e30)])
        if first is not None:
            m = self.m
            bl_all[:m], bu_all[:m] = np.maximum(bl_all[:m], first[0]), np.minimum(bu_all[:m], first[1])
        if fixed is not None:
            fixed = np.asarray(fixed, float).reshape(-1)
            if first is not None:
                raise ValueError("give first (v(0)'s range) or fixed (the first steps' values), not both: fixed "
                                 "would replace first's bounds")
            if fixed.size > N * self.m:
                raise ValueError(f"fixed holds {fixed.size} inputs; the plan has N_p m = {N * self.m}")
            box_lo, box_hi = bl_all[: fixed.size], bu_all[: fixed.size]
            if not np.all(np.isfinite(fixed)) or np.any(fixed < box_lo - FEAS_TOL) or np.any(fixed > box_hi + FEAS_TOL):
                raise ValueError(f"fixed must be finite inputs inside [v_lo, v_hi] = [{self.v_lo}, {self.v_hi}], got "
                                 f"{fixed}")
            if fixed.size:
                return self._qp_fixed(f, A, bl, bu, bl_all[fixed.size:N * self.m], bu_all[fixed.size:N * self.m],
                                      fixed, None if G is None else len(G))
        # f copied: DAQP refuses a read-only buffer (e.g. a RepairState's f)
        x, fval, flag, info = daqp.solve(self.H, np.array(f, float), A, bu_all, bl_all,
                                         np.zeros(len(bu_all), dtype=np.int32))
        if flag not in (1, 2):
            return None, np.inf, int(flag), None
        lam = None if G is None else np.asarray(info["lam"], float)[len(bu_all) - len(G):]
        return np.asarray(x, float), float(fval), int(flag), lam

    def _qp_arguments(self, f, z0, G, g_lo, g_hi) -> tuple:
        """The arguments of :meth:`qp_multipliers` checked and read: ``(f, z0, G, g_lo, g_hi)`` as float arrays of
        the program's sizes (``g_lo``, ``g_hi`` broadcast to ``G``'s rows), else a ``ValueError`` naming the first that
        does not fit."""
        n = self.N * self.m
        f = f if type(f) is np.ndarray and f.dtype == np.float64 else as_floats(f, "f")
        sized = f.size == n and f.ndim <= 2
        if not sized or not np.all(np.isfinite(f)):
            raise ValueError(f"f (the cost's linear part, Prediction.linear) must be {n} finite numbers (N_p m), got "
                             f"shape {f.shape}" + (" with NaN or inf" if sized else ""))
        z0 = z0 if type(z0) is np.ndarray and z0.dtype == np.float64 else as_floats(z0, "z0")
        if z0.shape != (self.nz,) or not np.all(np.isfinite(z0)):
            raise ValueError(f"z0 must be one finite state of shape ({self.nz},), got shape {z0.shape}"
                             + ("" if z0.shape != (self.nz,) else " with NaN or inf"))
        if G is None:
            if g_lo is not None or g_hi is not None:
                raise ValueError("g_lo and g_hi bound the rows G V: give them with G (or drop them)")
            return f.reshape(-1), z0, None, None, None
        G = as_floats(G, "G")
        if G.ndim != 2 or G.shape[1] != n or not np.all(np.isfinite(G)):
            raise ValueError(f"G must be a finite array of rows of shape (r, {n}) (N_p m columns), got shape "
                             f"{G.shape}" + ("" if G.ndim != 2 or G.shape[1] != n else " with NaN or inf"))
        if g_lo is None or g_hi is None:
            raise ValueError("G needs both g_lo and g_hi (g_lo <= G V <= g_hi; -inf or inf leaves a side open)")
        sides = []
        for name, g in (("g_lo", g_lo), ("g_hi", g_hi)):
            g = as_floats(g, name)
            if g.ndim > 1 or g.size not in (1, len(G)) or np.any(np.isnan(g)):
                raise ValueError(f"{name} must be a number or {len(G)} numbers (one per row of G), not NaN, got "
                                 f"shape {g.shape}")
            sides.append(np.broadcast_to(g.reshape(-1), (len(G),)))
        return f.reshape(-1), z0, G, sides[0], sides[1]

    def _qp_fixed(self, f: Array, A: Array, bl: Array, bu: Array, v_lo: Array, v_hi: Array, fixed: Array,
                  n_G: Optional[int] = None) -> tuple[Optional[Array], float, int, Optional[Array]]:
        """:meth:`qp_multipliers` with the first ``n_x = len(fixed)`` entries of ``V`` held (checked by the caller):
        the QP over the free entries ``V_f`` alone, ``min 0.5 V_f' H_ff V_f + (f_f + H_fx fixed)' V_f`` subject to
        ``bl - A_x fixed <= A_f V_f <= bu - A_x fixed`` and ``v_lo <= V_f <= v_hi`` (the free entries' bounds). Its
        optimum is the one with the held entries' bounds set to their values, from a smaller QP whose working set does
        not have to take in the held bounds one by one. Rows ``A`` without a free entry are constants: they must hold
        to :data:`flnotes.solvers.FEAS_TOL`, the tolerance of :meth:`feasible` (otherwise the QP is infeasible, flag
        -1; DAQP holds the other rows to its own 1e-6), and get no multiplier (0); the last ``n_G`` rows of ``A`` are
        the rows whose multipliers are returned (``None``: no such rows, no multipliers)."""
        import daqp

        n_x, n = fixed.size, self.H.shape[0]
        f = np.asarray(f, float).reshape(-1)
        shift = A[:, :n_x] @ fixed
        lo_r, hi_r = bl - shift, bu - shift
        A_f = A[:, n_x:]
        free = np.any(A_f != 0.0, axis=1)
        if np.any(lo_r[~free] > FEAS_TOL) or np.any(hi_r[~free] < -FEAS_TOL):
            return None, np.inf, -1, None
        lam = None if n_G is None else np.zeros(n_G)
        if n_x == n:  # nothing left to choose: the plan is the held one
            x, flag = fixed.copy(), 1
        else:
            # contiguous copies: daqp.solve misreads a strided H or A (a slice), it does not refuse it
            x_f, _, flag, info = daqp.solve(np.ascontiguousarray(self.H[n_x:, n_x:]),
                                            f[n_x:] + self.H[n_x:, :n_x] @ fixed, np.ascontiguousarray(A_f[free]),
                                            np.concatenate([v_hi, np.minimum(hi_r[free], 1e30)]),
                                            np.concatenate([v_lo, np.maximum(lo_r[free], -1e30)]),
                                            np.zeros(n - n_x + int(free.sum()), dtype=np.int32))
            if flag not in (1, 2):
                return None, np.inf, int(flag), None
            x, flag = np.concatenate([fixed, np.asarray(x_f, float)]), int(flag)
            if n_G is not None:
                lam_rows = np.zeros(len(A))
                lam_rows[free] = np.asarray(info["lam"], float)[n - n_x:]
                lam = lam_rows[len(A) - n_G:]
        return x, float(0.5 * x @ (self.H @ x) + f @ x), flag, lam

    # ------------------------------------------------------------------ boxes for the node bounds
    def boxes(self, z0: Array, first: Optional[tuple[Array, Array]] = None) -> tuple[Array, Array]:
        """Boxes of ``[z(k); v(k)]``, k = 0..N_p-1, over every admissible plan (:func:`flnotes.horizon_boxes`; ``first``:
        the first input's exact range, :meth:`first_range`)."""
        return horizon_boxes(self.Ad, self.Bd, z0, self.z_lo, self.z_hi, self.v_lo, self.v_hi, self.N, first)

    def level_boxes(self, z0: Array, V_c: Array, delta: float, lo: Array, hi: Array) -> tuple[Array, Array]:
        """``lo, hi`` cut by the ellipsoid ``0.5 ||V - V_c||_H^2 <= delta`` projected on each ``[z(k); v(k)]``, then,
        with an :attr:`enclosure`, by its slab (:func:`flnotes.enclosure.contract`; step 0 only when ``z0`` lies in
        the enclosure's box). Each box still holds every admissible point of its step within the ellipsoid;
        ``delta = inf``: the slab's cut alone (the boxes a level set must contain to cut nothing)."""
        off = np.zeros(self.nz + self.m)
        lo2, hi2 = lo.copy(), hi.copy()
        Zf = self.Sx @ z0
        for k in range(self.N if np.isfinite(delta) else 0):
            off[: self.nz] = Zf[k]
            a, b = ellipsoid_box(self.T[k], self.H_inv, V_c, off, delta)
            lo2[k], hi2[k] = np.maximum(lo2[k], a - 1e-9), np.minimum(hi2[k], b + 1e-9)
        enc = self.enclosure
        if enc is not None:
            k0 = 0 if self._inside(z0) else 1
            lo2[k0:], hi2[k0:] = contract(enc, lo2[k0:], hi2[k0:], self.u_eps + BOUND_TOL)
        return lo2, hi2

    def _inside(self, z0: Array) -> bool:
        """Does ``z0`` lie in the enclosure's box (where its slab holds at step 0)?"""
        enc = self.enclosure
        return bool(np.all(enc.lo[: self.nz] <= z0) and np.all(z0 <= enc.hi[: self.nz]))
