"""Benchmark: the two-input arm (chapter 10): training and certification, CLF-CBF and MPC per-step times.

* training time, architecture and the certified ``eps`` bracket per output with its
  certification time: quoted from the shipped report (``flnotes/data/Arm2.json``),
  labelled ``source = "shipped report"`` (re-certifying takes about three minutes
  per output; ``flnotes.arm.make_arm_reference()`` redoes both);
* the CLF-CBF program (eq. CLF_CBF) of the chapter, with the obstacle's barriers,
  for Lcost and Qcost at the same random safe states (half of them with the optimum
  on the network's bound): the exact two-input method against SCIP and DAQP, the
  time per step (min / median / p99 / max) and the largest relative difference of
  the optimum to SCIP's;
* the chapter's closed loops: the CLF-CBF (exact) run around the obstacle and the
  MPC run (``fl.MPC`` with its default options) on the true plant, time per step.
"""
from __future__ import annotations

import numpy as np

from ..pieces import compare_exact_mip
from ..studies import multi as study
from ..systems import FLSystem
from ..tables import time_stats
from ..arm import two_link_arm

TARGET_MS = 5.0


def _row(**kw) -> dict:
    return dict(system="Arm", **kw)


def _clf_cbf_rows(sysm: FLSystem, net, eps, n: int, notes: list) -> list:
    rows = []
    for cost in ("linear", "quadratic"):
        name = "Lcost" if cost == "linear" else "Qcost"
        ex = study.arm_clf_cbf(sysm, net, eps, cost=cost, backend="exact")
        Z, on = study.comparison_states(ex, n, seed=0)
        ref = compare_exact_mip(ex, ex.with_backend("scip"), Z, fresh=True)
        for be, key in (("exact", "exact"), ("scip", "mip")):
            st = time_stats(ref["times_s"][key], percentiles=(50, 99))
            rows.append(_row(what=f"CLF-CBF {name}", backend=be, states=len(Z), boundary_states=int(on.sum()),
                             min_ms=st["min_ms"], median_ms=st["median_ms"], p99_ms=st["p99_ms"], max_ms=st["max_ms"],
                             max_rel_diff=None if be == "scip" else ref["max_rel_objective_gap_hard"],
                             fallback=ref["fallback"], source="flnotes"))
        notes.append(f"CLF-CBF {name}: {ref['states']} states, {ref['boundary_optima']} optima on the network's bound, "
                     f"{ref['fallback']} softened (no v meets every constraint), largest relative difference of the "
                     f"exact optimum to SCIP's {ref['max_rel_objective_gap_hard']:.2g} (both solved) and "
                     f"{ref['max_rel_objective_gap']:.2g} (all); exact max {ref['exact_ms_max']:.2f} ms "
                     f"(target {TARGET_MS:g} ms), CPU max {ref['exact_cpu_ms_max']:.2f} ms")
        try:
            daqp = ex.with_backend("daqp")
        except Exception as exc:  # a back-end that cannot be built is reported, the others still run
            notes.append(f"CLF-CBF {name}/daqp: not run ({type(exc).__name__}: {exc})")
            continue
        idx = np.unique(np.linspace(0, len(Z) - 1, min(len(Z), 100)).round().astype(int))   # both kinds of states
        m = len(idx)
        r = compare_exact_mip(ex, daqp, Z[idx], fresh=True)
        st = time_stats(r["times_s"]["mip"], percentiles=(50, 99))
        rows.append(_row(what=f"CLF-CBF {name}", backend="daqp", states=m, boundary_states=int(on[idx].sum()),
                         min_ms=st["min_ms"], median_ms=st["median_ms"], p99_ms=st["p99_ms"], max_ms=st["max_ms"],
                         max_rel_diff=r["max_rel_objective_gap_hard"], fallback=r["fallback"],
                         source="flnotes"))
        notes.append(f"CLF-CBF {name}/daqp: {m} of the states only; its difference is to the exact method "
                     f"(itself equal to SCIP's optimum as above)")
    return rows


def run(fast: bool) -> dict:
    sysm = two_link_arm()
    info = study.shipped_network()
    net, eps = info["net"], info["eps"]
    rows, notes = [], []
    rows.append(_row(what="training", backend="fit_relu (L-BFGS)", widths="x".join(map(str, info["widths"])),
                     n_train=info["n_train"], seconds=info["train_s"], source="shipped report"))
    for i in range(2):
        rows.append(_row(what=f"certification eps_{i + 1}", backend=info["method"], lower=float(info["lower"][i]),
                         upper=float(info["upper"][i]), seconds=float(info["cert_s"][i]), boxes=int(info["n_boxes"][i]),
                         rtol=info["rtol"], source="shipped report"))
    notes.append("max_rel_diff: |J_exact - J_scip| / max(1, |J_scip|) at the states where neither fell back (the daqp "
                 "row: to the exact method)")
    notes.append("training and certification rows are quoted from the shipped report (flnotes/data/Arm2.json), "
                 "not re-run; flnotes.arm.make_arm_reference() redoes both")
    rows += _clf_cbf_rows(sysm, net, eps, 30 if fast else 1000, notes)

    log, ch = study.obstacle_run(sysm, net, eps, cost="quadratic", t_final=2.0 if fast else None)
    st = ch["times"]
    rows.append(_row(what="CLF-CBF Qcost closed loop (obstacle)", backend="exact", states=st["n"], min_ms=st["min_ms"],
                     median_ms=st["median_ms"], p99_ms=st["p99_ms"], max_ms=st["max_ms"], fallback=ch["fallback_steps"],
                     source="flnotes"))
    notes.append(f"CLF-CBF closed loop: true |tau_i| / tau_max,i <= {np.round(ch['ratio_between'], 3).tolist()}, "
                 f"min distance of the links to the obstacle {ch['min_distance']:.3f} m (radius {ch['radius']} m)")
    log, ch = study.mpc_run(sysm, net, eps, t_final=3.0 if fast else None)
    st = ch["times"]
    rows.append(_row(what=f"MPC closed loop (N_p = {study.ARM_MPC['horizon']})", backend="fl.MPC defaults",
                     states=st["n"], min_ms=st["min_ms"], median_ms=st["median_ms"], p99_ms=st["p99_ms"],
                     max_ms=st["max_ms"], fallback=ch["fallback_steps"], source="flnotes"))
    notes.append(f"MPC closed loop: true |tau_i| / tau_max,i <= {np.round(ch['ratio_between'], 3).tolist()}, "
                 f"final tracking error {ch['final_error']:.2g}")
    return dict(title="Two inputs: the two-link arm", rows=rows, notes=notes, figures=[])
