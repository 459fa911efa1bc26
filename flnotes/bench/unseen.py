"""Benchmark: the default MPC on systems not in the book (:mod:`flnotes.studies.unseen`).

Five feedback-linearizable systems defined through the public :class:`flnotes.FLSystem`, each with its own
shipped network and certified ``eps``: a *tuning* pair (the pendulum with an angle-dependent input gain and
the Quad-1D with other parameters, which anybody may look at while choosing the engine's levers) and three
*held-out* systems (Van der Pol with input gain ``1 + 0.3 sin x_1``, a 4th-order chain with input gain
``1.5 + cos x_1``, a 3rd-order chain with a cubic drift), run here only, with the default
:class:`flnotes.MPCOptions`, without a time limit and with ``time_limit = t_s``.

Per system: the closed loop on the true plant (share of steps with the network bound active at the applied
input, per-step wall and CPU time min/median/p99/max, steps over ``t_s``, largest true ``|u|/u_max`` at the
samples, and for the steps over ``t_s`` their phase, binaries, nodes and rounds from
:class:`flnotes.StepResult`); then ~30 diverse states per system (uniform in the box, on its faces, bound
strongly active), solved cold at the system's horizon: p99 against ``t_s``, then the same states with
``time_limit = t_s`` (answer times, limit hits, the plans and inputs returned checked by the forward pass, and
the plans at the limit against the optimum proven without it), and with the one-switch plans off and on
(``MPCOptions.bang_bang``). The held-out systems run after
the tuning pair. Speed is measured here, never asserted in tests.
"""
from __future__ import annotations

import os
import time

from ..studies import unseen as U

#: Wall-clock cap per diverse state (s): a state that reaches it is reported as a time-limit hit.
DIVERSE_CAP_S = 60.0


def run(fast: bool) -> dict:
    rows, notes = [], []
    names = [n for n, c in U.CASES.items() if c.role == "tuning"] + [n for n, c in U.CASES.items() if c.role != "tuning"]
    for d in U.definitions_table():
        notes.append(f"{d['system']} ({d['role']}): {d['dynamics']}; n_z = {d['n_z']}, u_max = {d['u_max']:g}, network "
                     f"{d['widths']}, certified eps in [{d['eps_lower']:.4f}, {d['eps']:.4f}] ({d['certify_s']:.1f} s), "
                     f"N_p = {d['N_p']}, t_s = {d['t_s']:g} s, x_ref = {d['reference']}")
    for name in names:
        c = U.case(name)
        t_final = c.t_final / 4 if fast else c.t_final
        t0 = time.perf_counter()
        log, mpc, timed = U.closed_loop(name, t_final=t_final)
        r = U.closed_loop_row(name, log, mpc, timed)
        rows.append(dict(kind="closed loop", **r))
        notes.append(f"{name}: closed loop of {t_final:g} s ({r['steps']} steps) in {time.perf_counter() - t0:.0f} s; "
                     f"bound active on {100 * r['active_share']:.0f} % of the steps; max true |u|/u_max = "
                     f"{r['max_u_over_u_max']:.3f} at the samples; "
                     + (r["miss"] or "every step <= t_s (wall)"))
    for name in names:
        t0 = time.perf_counter()
        c = U.case(name)
        load0 = os.getloadavg()[0]
        r = U.deadline_row(name, steps=int(round((c.t_final / 4 if fast else c.t_final) / c.ts)))
        r.update(load_start=load0, load_end=os.getloadavg()[0])
        rows.append(dict(kind="closed loop, time_limit = t_s", **r))
        notes.append(f"{name}: closed loop with time_limit = t_s in {time.perf_counter() - t0:.0f} s: "
                     f"{r['limit_hits']} of {r['steps']} steps hit the limit ({r['cut_offs']} answered at the cut-off "
                     f"while the solve ran on), {r['over_ts_wall']} answers after t_s ({r['over_ts_cpu']} of them used more "
                     f"than t_s of CPU time), slowest answer {r['wall_max_over_ts']:.2f} t_s (wall), most CPU time "
                     f"of a step {r['cpu_max_over_ts']:.2f} t_s; plans at the limit: largest distance to the optimum "
                     f"{r['opt_gap_max']:.1e}, {r['opt_gap_over']} above 1e-4, {r['opt_undecided']} without a proven "
                     f"optimum; load average {r['load_start']:.1f} -> {r['load_end']:.1f}"
                     + (f"; late answers: {r['late']}" if r["late"] else ""))
    n = 9 if fast else 30
    for name in names:
        t0 = time.perf_counter()
        steps, wall, cpu, cases = U.diverse_run(name, n, seed=0, time_limit=DIVERSE_CAP_S)
        r = U.diverse_row(name, steps, wall, cpu)
        rows.append(dict(kind="diverse states", **r))
        notes.append(f"{name}: {n} diverse states (cold) in {time.perf_counter() - t0:.0f} s; p99 = "
                     f"{r['wall_p99_ms']:.0f} ms = {r['p99_over_ts_wall']:.1f} t_s (wall); "
                     + (r["miss"] or "every state <= t_s (wall)"))
        load0 = os.getloadavg()[0]
        lim, lw, lc, _ = U.diverse_run(name, n, seed=0, time_limit=U.case(name).ts)
        d = U.diverse_deadline_row(name, lim, lw, lc, steps)
        d.update(load_start=load0, load_end=os.getloadavg()[0])
        rows.append(dict(kind="diverse states, time_limit = t_s", **d))
        notes.append(f"{name}: the same {n} states with time_limit = t_s: p99 = {d['wall_p99_over_ts']:.2f} t_s, "
                     f"slowest {d['wall_max_over_ts']:.2f} t_s (wall), most CPU time of a step "
                     f"{d['cpu_max_over_ts']:.2f} t_s; {d['over_ts_wall']} answers after t_s ({d['over_ts_cpu']} of "
                     f"them used more than t_s of CPU time); {d['limit_hits']} limit hits ({d['cut_offs']} at the "
                     f"cut-off); plans passing the forward pass {d['plans_admissible']} of {d['states']} "
                     f"({d['infeasible']} programs infeasible; limit hits without one: {d['without_plan_infeasible']} "
                     f"infeasible, {d['without_plan_missed']} with a plan the fallback missed, "
                     f"{d['without_plan_undecided']} undecided); first inputs flagged {d['inputs_flagged']}, above "
                     f"u_max^eps unflagged {d['inputs_not_admissible']}; plans at the limit: largest distance to the "
                     f"optimum {d['opt_gap_max']:.1e}, {d['opt_gap_over']} above 1e-4, {d['opt_undecided']} without "
                     f"a proven optimum; load average {d['load_start']:.1f} -> {d['load_end']:.1f}"
                     + (f"; late answers: {d['late']}" if d["late"] else ""))
        b = U.bang_bang_row(name, n, seed=0)
        rows.append(dict(kind="diverse states, time_limit = t_s, one-switch plans off and on", **b))
        notes.append(f"{name}: one-switch plans (MPCOptions.bang_bang) on the same {n} states: the repaired relaxation "
                     f"fails the check at {b['repair_failed']} of the {b['qp_feasible'] - b['screened']} states the "
                     f"screening QP does not settle, and a one-switch plan passes it at {b['one_switch_found']} of them "
                     f"(search at most {b['search_ms_max']:.1f} ms); with time_limit = t_s, plans passing the check "
                     f"{b['plans_without']} without and {b['plans_with']} with ({b['recovered']} recovered, {b['lost']} "
                     f"lost, {b['lost_searched']} of them where the search ran), proven optimal "
                     f"{b['optimal_without']} and {b['optimal_with']}, slowest answer "
                     f"{b['wall_max_over_ts_without']:.2f} and {b['wall_max_over_ts_with']:.2f} t_s"
                     + "".join(f"; late {w}: {b['late_' + w]}" for w in ("without", "with") if b["late_" + w]))
    notes.append("Default MPCOptions, time_limit=None in the closed loops (and time_limit = t_s in the rows that say so: "
                 "each limit hit solved again without the limit, 30 s cap, for its distance to the optimum); the diverse "
                 "states are solved cold with a "
                 f"{DIVERSE_CAP_S:g} s cap per state (a state at the cap counts with its time and status 'time_limit'). "
                 "'bound active' in a closed loop: |Phi_NN(z_k, v_k)| >= 0.98 u_max^eps at the applied input; on the "
                 "diverse states: the QP without the network violates it (not screened). Wall time waits for a shared "
                 "core; CPU time (time.process_time) is what the solve used.")
    return dict(title="Systems not in the book (default MPC)", rows=rows, notes=notes, figures=[])
