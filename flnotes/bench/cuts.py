"""Benchmark: how much of the MSD MIQP's root gap valid cuts close, and what they cost (:mod:`flnotes.studies.cuts`).

On chapter 11's MSD setting (the shipped (20, 20, 20) network, ``N_p = 10``), at the cold states of
:func:`flnotes.bench.msd_realtime.cold_states`: the default engine's CPU time on the state, then the program of its
level-set round at the optimum's cost (:func:`flnotes.studies.cuts.level_program`) with each family of
:data:`flnotes.studies.cuts.FAMILIES` (big-M alone, the ideal cuts of one neuron, the projection cuts of one step):
root bound, share of the root gap closed, cuts, their CPU time, and SCIP's time and nodes on the program with them
(warm-started at the optimum). Speed is measured here, never asserted in tests.
"""
from __future__ import annotations

from ..studies import cuts as study
from . import msd_realtime as msd

#: Cold states of the full run (:func:`flnotes.bench.msd_realtime.cold_states`), and the one of the fast run.
N_STATES = 8
FAST_STATE = 7

#: Cut rounds per family in the full run (the fast run: one).
ROUNDS = 5


def run(fast: bool = False) -> dict:
    """The section dict of :mod:`flnotes.bench`: one row per state and family; states where the default proves no
    optimum, or where no step needs the network in the level set, are named in the notes (nothing to cut there)."""
    s = msd.setting()
    states = msd.cold_states(s, N_STATES)
    pick = (FAST_STATE,) if fast else range(N_STATES)
    ctrl = msd.controller(s)
    rows, skipped = [], []
    for i in pick:
        kind, z, R = states[i]
        try:
            lp_rows = study.cut_rows(ctrl, [(f"{i} {kind}", z, R)], rounds=1 if fast else ROUNDS)
        except ValueError as exc:  # the state has nothing to cut: said in the notes, never dropped silently
            skipped.append(f"state {i} ({kind}): {exc}")
            continue
        rows += lp_rows
    notes = [f"MSD, N_p = {s['horizon']}, t_s = {s['ts']} s, Q = diag(10, 1), R = 0.01, eps = {s['eps']:.4f}, the "
             f"shipped (20, 20, 20) network; cold states {list(pick)} of msd_realtime.cold_states(setting, {N_STATES})",
             "engine cpu s: the default fl.MPC on the state, cold; the program: its level-set round at the optimum's "
             "cost (+1e-9 relative), LP node bounds on the level-set boxes ('LP bounds cpu s'), every step whose output "
             "can exceed u_max^eps encoded, the optimum as SCIP's warm start (gap 1e-6)",
             "big-M: the relaxation as written; ideal: plus the most violated ideal cut of every neuron over its "
             "inputs' box (Anderson et al. 2020), per round; projection: plus g'[z(k); v(k)] <= beta per step whose "
             "point exceeds the bound, g the network's gradient there, beta proven by SCIP on one network copy "
             f"(without SCIP's cutting planes, at most {study.PROJECTION_LIMIT:g} s each); up to "
             f"{1 if fast else ROUNDS} round(s), stopped when the bound gains less than 1e-5 (relative)",
             "gap closed %: (root bound with the cuts - without) / (J_opt - root bound without); cut cpu s: the "
             "relaxations (SCIP) and the separation; scip cpu s: SCIP on the program with the cuts, model build "
             "included; same optimum: SCIP's optimum equals J_opt within 1e-6 (relative)"]
    notes += [f"skipped {msg}" for msg in skipped]
    return dict(title="MSD: the root gap of the MIQP and what cuts close (ideal per neuron, projection per step)",
                rows=rows, notes=notes, figures=[])
