"""Linear models of the exact input constraint, for the QP-based MPCs the network constraint is compared with.

The exact constraint ``|Phi(z, v)| <= u_max`` is, at a *fixed* state ``zbar``, a set of linear rows in
``v`` when ``Phi`` is affine in ``v`` (it is for every feedback-linearized system: ``u = (v - L_f^r h) /
(L_g L_f^{r-1} h)``, or ``Phi = M(q) v + n(q, qdot)`` with several inputs):

    |a(zbar) + B(zbar) v| <= u_max,    a = Phi(zbar, 0),  B = dPhi/dv (zbar).

What differs between the methods is the state ``zbar_k`` at which step ``k``'s rows are written:

* ``"measured"`` (constant extension; Nevistić & del Re 1994, Kandler et al. 2012, as the paper cites them):
  ``zbar_k = z(0)``, the measured state, at every predicted step;
* ``"previous"`` (Kurtz & Henson 1998): ``zbar_k`` the state predicted for that instant at the previous
  sampling instant (the previous plan shifted by one step; ``zbar_0 = z(0)``), optionally re-linearized
  along the new plan a few times within the period;
* ``"none"``: no input rows at all (what a naive implementation followed by saturation of ``u`` solves).

Each is a QP (DAQP); none of them claims ``|Phi(z(k), v(k))| <= u_max`` along the *predicted* trajectory,
which is the point of the comparison with the network constraint of eq. (MPC_form_miqp).
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np

from ..result import StepResult
from ..systems import FLSystem
from .options import MPCOptions
from .prediction import Prediction

Array = np.ndarray


class LinearModel:
    """The QP of eq. (MPC_form_miqp) with the network rows replaced by a linear model of the exact constraint.

    Parameters
    ----------
    pred
        The prediction model (cost, boxes, terminal rows).
    opts
        Validated options with ``constraint`` in ``("measured", "previous", "none")``.
    system
        The system: its exact map ``Phi`` (affine in ``v``, :meth:`flnotes.FLSystem.input_map`) and ``u_max``.
    """

    def __init__(self, pred: Prediction, opts: MPCOptions, system: FLSystem):
        self.pred, self.opts, self.system = pred, opts, system
        self.u_max = np.asarray(system.u_max, float)
        # the points of the v-box at which every map is checked to be affine (as FLSystem.input_map checks it)
        self._v_test = np.random.default_rng(0).uniform(system.lo[system.n_z:], system.hi[system.n_z:], (8, system.m))

    def input_maps(self, zbar: Array, rtol: float = 1e-9) -> tuple[Array, Array]:
        """``a`` (N, m) and ``B`` (N, m, m) with ``Phi(zbar_k, v) = a_k + B_k v`` at every state of ``zbar`` (N, n_z).

        The batched form of :meth:`flnotes.FLSystem.input_map` (eq. coor_Phi): two calls of ``Phi`` on all the
        states at once, not two per state. A map that is not affine in ``v`` (checked at eight seeded points of the
        ``v``-box per state) raises ``ValueError``.
        """
        sysm = self.system
        zbar = np.asarray(zbar, float)
        if zbar.ndim != 2 or zbar.shape[1] != sysm.n_z:
            raise ValueError(f"zbar must have shape (N, {sysm.n_z}), got {zbar.shape}")
        N, m = len(zbar), sysm.m
        E = np.vstack([np.zeros(m), np.eye(m)])                                   # v = 0, then each unit vector
        U = np.asarray(sysm.Phi(np.repeat(zbar, m + 1, axis=0), np.tile(E, (N, 1))), float).reshape(N, m + 1, m)
        a, B = U[:, 0], np.transpose(U[:, 1:] - U[:, :1], (0, 2, 1))             # B[k][i, j] = dPhi_i / dv_j
        Vt = self._v_test
        Ut = np.asarray(sysm.Phi(np.repeat(zbar, len(Vt), axis=0), np.tile(Vt, (N, 1))), float).reshape(N, len(Vt), m)
        err = np.abs(Ut - (a[:, None, :] + np.einsum("tj,kij->kti", Vt, B)))
        if np.any(err > rtol * (1.0 + np.abs(Ut))):
            k = int(np.argmax(err.max(axis=(1, 2))))
            raise ValueError(f"Phi of {sysm.name} is not affine in v at z = {np.array2string(zbar[k], precision=4)} "
                             f"(error {err[k].max():.2e}): the linear models need Phi(z, v) = a(z) + B(z) v")
        return a, B

    def rows(self, zbar: Array) -> tuple[Array, Array, Array]:
        """Rows ``g_lo <= G V <= g_hi`` of ``|Phi(zbar_k, v(k))| <= u_max`` for the states ``zbar`` (N_p, n_z)."""
        p = self.pred
        N, m = p.N, p.m
        a, B = self.input_maps(zbar[:N])
        G = np.zeros((N, m, N, m))
        G[np.arange(N), :, np.arange(N), :] = B                                  # block k of the diagonal: B_k
        return G.reshape(N * m, N * m), (-self.u_max - a).reshape(-1), (self.u_max - a).reshape(-1)

    def solve(self, z0: Array, z_ref: Array, previous: Optional[Array] = None) -> StepResult:
        """The QP at ``z0``; ``previous`` is the previous plan's predicted states (N_p + 1, n_z) or ``None``."""
        p, o = self.pred, self.opts
        t0 = time.perf_counter()
        f, c0 = p.linear(z0, z_ref)
        N = p.N
        rounds = 0
        if o.constraint == "none":
            V, fv, flag = p.qp(f, z0)
            rounds = 1
        else:
            if o.constraint == "measured" or previous is None:
                zbar = np.repeat(np.asarray(z0, float)[None], N, axis=0)
            else:  # the previous prediction, shifted by one step; its last state repeated
                zbar = np.vstack([z0[None], previous[2:N + 1]]) if N > 1 else z0[None]
            for _ in range(o.iterations or 1):
                V, fv, flag = p.qp(f, z0, *self.rows(zbar))
                rounds += 1
                if V is None or o.constraint != "previous":
                    break
                zbar = p.predict(z0, V)[:N]  # re-linearize along the new plan (iterations > 1)
        res = StepResult(None, "optimal" if V is not None else ("infeasible" if flag == -1 else "error"),
                         rounds=rounds, backend="daqp", message=f"QP ({o.constraint}), DAQP exit flag {flag}")
        if V is not None:
            V = V.reshape(N, p.m)
            res.v, res.v_pred, res.z_pred = V[0].copy(), V, p.predict(z0, V)
            res.objective = res.bound = fv + c0
            res.gap = 0.0
        res.solve_time = time.perf_counter() - t0
        return res
