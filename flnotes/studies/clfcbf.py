"""Studies of chapter 6: checks of a CLF-CBF run, Table 2's rows, the exact method against a back-end."""
from __future__ import annotations

from typing import Any

import numpy as np

from .. import paper
from ..control import ClfCbfController, _cbf_list
from ..simulate import SimLog
from ..tables import Table, time_stats

Array = np.ndarray

__all__ = ["clf_cbf_checks", "chapter_eps", "cross_check_exact", "solve_time_table", "paper_mean_ms"]


def clf_cbf_checks(log: SimLog, H: Any = None) -> dict:
    """The chapter's checks, computed from a closed-loop run.

    Parameters
    ----------
    log
        A run of :func:`flnotes.simulate`.
    H
        The CBF (or list of CBFs) whose minimum along the run is reported.

    Returns
    -------
    dict
        ``max_abs_u`` (true plant, at samples and between them) vs ``u_max``,
        ``max_abs_u_nn`` vs ``u_max^eps`` when logged, ``min_H`` at samples and
        along the integrated trajectory, the final ``||z||``, and the counts of
        non-optimal and fallback steps.
    """
    s = log.summary()
    out = dict(steps=s["steps"], u_max=s["u_max"][0] if len(s["u_max"]) == 1 else s["u_max"],
               max_abs_u=max(s["max_abs_u_samples"]) if s["steps"] else np.nan,
               max_abs_u_between=max(s["max_abs_u_between"]) if s["steps"] else np.nan,
               final_norm_z=s["final_norm_z"], non_optimal_steps=s["non_optimal_steps"],
               fallback_steps=s["fallback_steps"], left_domain_steps=s["left_domain_steps"], message=s["message"])
    if log.u_nn is not None and s["steps"]:
        out["max_abs_u_nn"] = float(np.abs(log.u_nn).max())
    if H is not None:
        Hs = _cbf_list(H)
        Z = log.z
        Zf = np.vstack([log.z_fine, log.z[-1:]]) if len(log.z_fine) else Z
        out["min_H"] = float(min(np.min(h(Z)) for h in Hs))
        out["min_H_between"] = float(min(np.min(h(Zf)) for h in Hs))
    return out


def chapter_eps(name: str = "MSD") -> tuple[Array, str]:
    """The error bound ``eps`` of eq. (approx_err) that the controller uses, and where it comes from.

    The certified upper bound ``flnotes.paper.paper_eps(name).upper`` of the
    shipped network.
    """
    return np.atleast_1d(np.asarray(paper.paper_eps(name).upper, float)), "certified upper bound"


def cross_check_exact(controller: ClfCbfController, log: SimLog) -> dict:
    """Re-solve the program at every sampled state of a run with the exact 1-D method and compare.

    Parameters
    ----------
    controller
        The controller that produced ``log`` (single input).
    log
        Its run; ``log.steps[i].objective`` is compared with the exact
        optimum at ``log.z[i]`` (of the softened program at fallback steps,
        which both methods solve alike).

    Returns
    -------
    dict
        ``max_abs_diff`` and ``max_rel_diff`` (``|J - J_exact| / max(1, |J_exact|)``)
        of the optimal values, ``max_v_diff``, ``steps``, and the exact
        method's per-step times (ms) ``exact_ms_min/median/max/mean``.
    """
    ex = controller.with_backend("exact")
    J, Jx, v, vx, t = [], [], [], [], []
    for z, r in zip(log.z[:-1], log.steps):
        if not np.isfinite(r.objective):
            continue
        rx = ex.step(z)
        J.append(r.objective), Jx.append(rx.objective)
        v.append(r.v), vx.append(rx.v), t.append(rx.solve_time)
    J, Jx, t = np.array(J), np.array(Jx), np.array(t) * 1e3
    d = np.abs(J - Jx)
    return dict(steps=len(J), max_abs_diff=float(d.max()) if len(d) else np.nan,
                max_rel_diff=float((d / np.maximum(1.0, np.abs(Jx))).max()) if len(d) else np.nan,
                max_v_diff=float(np.abs(np.array(v) - np.array(vx)).max()) if len(d) else np.nan,
                exact_ms_min=float(t.min()), exact_ms_median=float(np.median(t)),
                exact_ms_max=float(t.max()), exact_ms_mean=float(t.mean()))


def solve_time_table(logs: dict, system: str = "MSD") -> Table:
    """Table 2's rows: min / median / max / mean solve time (ms) per controller, beside the paper's.

    Parameters
    ----------
    logs
        ``{controller name: SimLog}``, e.g. ``{"Lcost": ..., "Qcost": ..., "k(z)": ...}``.
    system
        The paper's system name for the reference rows of ``flnotes.paper.TABLE2_MS``.
    """
    rows = Table()
    for name, log in logs.items():
        st = time_stats(log.solve_time)
        cpu = np.array([r.info.get("cpu_time", np.nan) for r in log.steps], float) * 1e3
        ref = paper.TABLE2_MS.get((system, name), {})
        backend = (log.steps[0].backend or "numpy") if log.steps else ""
        rows.append(dict(controller=name, backend=backend, steps=len(log.solve_time),
                         min=st["min_ms"], median=st["median_ms"], max=st["max_ms"], mean=st["mean_ms"],
                         cpu_median=float(np.nanmedian(cpu)) if np.isfinite(cpu).any() else None,
                         paper_min=ref.get("min"), paper_max=ref.get("max"), paper_mean=ref.get("mean")))
    return rows


def paper_mean_ms(system: str = "MSD") -> dict:
    """The paper's mean time per step (Table 2, ms) of each controller of ``system``, by name."""
    return {name: ref["mean"] for (sysname, name), ref in paper.TABLE2_MS.items() if sysname == system}
