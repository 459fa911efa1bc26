"""Benchmark: per-step time of the five methods of the comparative study on the same recorded states.

The book's Quad-1D run (Sec. IV-B: ``N_p = 10``, ``t_s = 0.1`` s, ``x_ref = 1.5 sin t``) is recorded once
with the MIQP (:func:`flnotes.studies.compare.run_methods`); then each method's controller is built
once and asked, in order, for the input at every recorded state with its reference, so that
each warm-starts from its own previous answer as in closed loop. The time is the wall time of
the call (``time.perf_counter``), the same for every method. Speed is measured here, never
asserted in tests; the machine is shared, so single timings are noisy.
"""
from __future__ import annotations

import time

import numpy as np

from .. import paper
from ..mpc import sine_reference
from ..nmpc import input_to_v
from ..studies import compare as C
from ..tables import time_stats


def _answer(method: str, ctrl, z: np.ndarray, R: np.ndarray):
    """One call of the method's controller at state ``z`` with reference ``R`` (N_p + 1, n_z)."""
    if method == "saturated":  # the unconstrained linear MPC, then the clipping of the true input
        s = ctrl.inner(z, R)
        u = np.clip(ctrl.system.Phi(z, s.v), -ctrl.system.u_max, ctrl.system.u_max)
        return input_to_v(ctrl.system, z, u)
    s = ctrl(z, R)
    return s["u"] if method == "nmpc" else s.v


def run(fast: bool) -> dict:
    """``run(fast) -> {"title", "rows", "notes", "figures"}`` of the ``compare`` section."""
    s = C.setting("Quad-1D", time_limit=None)
    t_final = 3.0 if fast else 20.0
    ref = sine_reference(1.5, 1.0)
    log = C.run_methods(s, paper.QUAD_SETTING["z0"], ref, t_final, methods=("network",))["network"]
    Z = log.z[:-1]
    R = np.array([C.step_field(st, "z_ref") for st in log.steps])
    rows, notes = [], []
    notes.append(f"Quad-1D, N_p = {s['horizon']}, t_s = {s['ts']} s, x_ref = 1.5 sin t, eps = {s['eps']:.4f}; "
                 f"{len(Z)} states recorded in closed loop with the MIQP over {t_final} s; no time limit.")
    for mth in C.METHODS:
        ctrl, _ = C.make_controller(mth, s)
        if hasattr(ctrl, "reset"):
            ctrl.reset()
        ms = []
        for z, Rk in zip(Z, R):
            t0 = time.perf_counter()
            _answer(mth, ctrl, z, Rk)
            ms.append(time.perf_counter() - t0)
        st = time_stats(ms)
        rows.append(dict(method=C.LABELS[mth], states=st["n"], min_ms=st["min_ms"], median_ms=st["median_ms"],
                         p90_ms=st["p90_ms"], max_ms=st["max_ms"], mean_ms=st["mean_ms"]))
    notes.append("saturated FL: the unconstrained linear MPC's solve plus the clipping; nonlinear MPC: CasADi + IPOPT "
                 "(exact Hessian, multiple shooting, warm start from its previous solution).")
    return dict(title="Comparative study: per-step time of the five methods on the same states", rows=rows,
                notes=notes, figures=[])

