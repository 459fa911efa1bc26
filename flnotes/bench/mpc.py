"""Benchmark: per-step solve time of the Quad-1D MPC, eq. (MPC_form_miqp), and what each lever buys.

The book's run (Sec. IV-B: ``N_p = 10``, ``t_s = 0.1`` s, ``x_ref = 1.5 sin t``, which makes the
input bound active at many steps) is recorded once with :class:`flnotes.MPC` and its default options
(the same controller and code the chapters run). Every configuration of :class:`flnotes.MPCOptions`
is then timed on the same recorded states (and the same warm starts: the recorded plan of the previous
step, shifted), and every returned optimum is compared with a slow reference solve by SCIP (every step
encoded, no screening, no level set, gap 1e-8). The exact switches of the DAQP back-end are then turned off
one at a time on the same states (:func:`daqp_lever_table`, wall-clock and CPU time), the loop is run with
``N_p = 15`` and ``20`` against the targets (every step within ``t_s``, proven optimal:
:func:`horizon_targets`) and its slowest states replayed with and without the LP bounds of the level-set rounds
(:func:`lp_lever_table`) and with each solver setting (:func:`solver_lever_table`: ``backend="auto"``, DAQP for
every program, SCIP's checks at SCIP's own settings), and scaling with ``N_p`` and with the width of the network
closes the section.
Speed is measured here, never asserted in tests; the machine is shared, so single timings are noisy: how noisy is
measured on pairs of runs that did the same work (:func:`run_to_run_spread`, :func:`idle_cache_pairs`).
"""
from __future__ import annotations

import time
from typing import Optional, Sequence

import numpy as np

from .. import paper
from ..mpc import MPC, MPCOptions
from ..mpc.levers import AUTO_DAQP_BINARIES, node_bounds
from ..simulate import simulate
from ..solvers import available_backends
from ..repeats import spread
from ..tables import time_stats

TARGET_MAX_MS, TARGET_MEDIAN_MS, TARGET_GAP = 100.0, 10.0, 1e-4

#: The lever configurations compared on the recorded states: name -> :class:`flnotes.MPCOptions` fields.
#: "paper program" is eq. (MPC_form_miqp) as written: domain-box bounds, every neuron a binary,
#: every step encoded, no screening, no warm start. Each next row adds one lever.
CONFIGS = {
    "paper program": dict(bounds="box", eliminate_stable=False, encode="all", screening=False, warm_start=False,
                          lazy=False),
    "+ stable neurons eliminated": dict(bounds="box", eliminate_stable=True, encode="all", screening=False,
                                        warm_start=False, lazy=False),
    "+ horizon boxes (FBBT)": dict(bounds="horizon", encode="all", screening=False, warm_start=False, lazy=False),
    "+ screening QP": dict(bounds="horizon", encode="all", screening=True, warm_start=False, lazy=False),
    "+ only needed steps": dict(bounds="horizon", encode="needed", screening=True, warm_start=False, lazy=False),
    "+ LP bounds (per step)": dict(bounds="lp", encode="needed", screening=True, warm_start=False, lazy=False),
    "+ warm start": dict(bounds="lp", encode="needed", screening=True, warm_start=True, lazy=False),
    "+ level set": dict(bounds="levelset", encode="needed", screening=True, warm_start=True, lazy=False),
    "level set (default)": dict(),
    "level set, cold": dict(warm_start=False),
}


# ----------------------------------------------------------------------------------- setup
def quad_setup(horizon: Optional[int] = None, net=None, eps: Optional[float] = None) -> dict:
    """The Quad-1D MPC of Sec. IV-B: system, network, eps, discrete model, weights, reference."""
    from ..mpc import sine_reference

    S = paper.QUAD_SETTING
    sysm = paper.system("Quad-1D")
    eps_note = ""
    if net is None:
        net, _ = paper.paper_net("Quad-1D")
        if eps is None:
            eps = float(np.max(paper.paper_eps("Quad-1D").upper))
            eps_note = "eps = certified upper bound of the book's network (paper_eps)"
    if eps is None:
        eps, eps_note = paper.TABLE1["Quad-1D"]["eps"], "eps = the paper's 0.0322"
    ts, N = S["ts"], int(horizon or S["horizon"])
    Ad, Bd = sysm.discretize(ts, "rk4")
    return dict(system=sysm, net=net, eps=float(eps), eps_note=eps_note, ts=ts, N=N, Ad=Ad, Bd=Bd,
                Q=S["Q"], R=S["R"], z0=S["z0"], u_eps=float(sysm.u_max[0] - eps), reference=sine_reference(1.5))


def make_mpc(setup: dict, backend: Optional[str] = None, time_limit: Optional[float] = None,
             solver_options: Optional[dict] = None, cut_off: Optional[bool] = None, **levers) -> MPC:
    """:class:`flnotes.MPC` for the setup with the given options (see :data:`CONFIGS`), back-end options and
    ``cut_off`` (see :class:`flnotes.MPC`)."""
    return MPC(setup["system"], setup["net"], setup["eps"], horizon=setup["N"], ts=setup["ts"], Q=setup["Q"],
               R=setup["R"], time_limit=time_limit, options=MPCOptions(backend=backend, **levers),
               solver_options=solver_options, cut_off=cut_off)


def record_run(setup: dict, t_final: float, mpc: Optional[MPC] = None, time_limit: Optional[float] = None) -> dict:
    """The closed loop on the true plant with an :class:`flnotes.MPC` (default options unless given).

    Returns per step the state, the reference over the horizon, the plan, the previous plan (the warm
    start a replay hands over), the time (ms, wall clock; ``cpu_ms`` the CPU time of the whole step), status,
    screened flag and the step records, and the log.
    """
    mpc = mpc or make_mpc(setup, time_limit=time_limit)
    cpu, step = [], mpc.step

    def timed(*a, **k):  # the CPU time of each step next to its wall-clock time
        c0 = time.process_time()
        out = step(*a, **k)
        cpu.append(time.process_time() - c0)
        return out

    mpc.step = timed
    try:
        log = simulate(setup["system"], mpc, t_final=t_final, ts=setup["ts"], z0=setup["z0"],
                       reference=setup["reference"], progress=False)
    finally:
        del mpc.step
    h = mpc.history
    return dict(t=log.t[: len(h)], z=log.z[: len(h)], R=np.array([s.info["z_ref"] for s in h]),
                V=np.array([s.v_pred for s in h]), prev=history_record(h)["prev"], ms=np.array([s.solve_time for s in h]) * 1e3,
                cpu_ms=np.array(cpu[: len(h)]) * 1e3,
                status=[s.status for s in h], screened=np.array([s.screened for s in h]),
                fallback=np.array([s.fallback for s in h]), results=list(h), log=log)


# ----------------------------------------------------------------------------------- timing
def replay(mpc: MPC, rec: dict, idx, time_limit: Optional[float] = None, gap: float = 1e-6) -> list:
    """Solve the recorded states ``idx`` with ``mpc`` (warm start: the recorded previous plan, shifted)."""
    mpc.time_limit, mpc.gap = time_limit, gap
    out = []
    for i in idx:
        mpc.set_previous_plan(rec["prev"][i])
        out.append(mpc(rec["z"][i], rec["R"][i]))
    return out


def pick_states(rec: dict, n_hard: int, n_easy: int) -> np.ndarray:
    """Recorded states for the comparisons: up to ``n_hard`` where the screening QP was not optimal
    (evenly spread over the run) and ``n_easy`` screened ones."""
    hard = np.flatnonzero(~rec["screened"])
    easy = np.flatnonzero(rec["screened"])
    pick = lambda a, k: a[np.unique(np.linspace(0, len(a) - 1, min(k, len(a))).round().astype(int))] if len(a) else a
    return np.sort(np.r_[pick(hard, n_hard), pick(easy, n_easy)]).astype(int)


def reference(setup: dict, rec: dict, idx, time_limit: float = 600.0, lazy: bool = False) -> tuple[np.ndarray, list]:
    """Slow reference optimum at the recorded states: SCIP, FBBT horizon bounds, no warm start, gap 1e-8.

    Every step is encoded at once, or with ``lazy=True`` (for long horizons, where that program is
    too large for SCIP within minutes) by constraint generation without the level set: the steps
    found violated are encoded and the program is solved again until the plan meets the network
    constraint at every step. Returns the optima (NaN where not proven optimal) and the step results.
    """
    enc = dict(encode="needed", lazy=True) if lazy else dict(encode="all", lazy=False)
    mpc = make_mpc(setup, backend="scip", bounds="horizon", screening=False, warm_start=False, **enc)
    res = replay(mpc, rec, idx, time_limit=time_limit, gap=1e-8)
    return np.array([r.objective if r.status == "optimal" else np.nan for r in res]), res


def summarize(name: str, backend: str, res: list, ref_obj: np.ndarray, **extra) -> dict:
    """One table row: min/median/max/mean ms per step, nodes, binaries, statuses and the gap to the reference."""
    st = time_stats([r.solve_time for r in res])
    obj = np.array([r.objective for r in res])
    opt = np.array([r.status == "optimal" and not r.fallback for r in res])
    ok = np.isfinite(ref_obj) & np.isfinite(obj) & opt  # the gap of the steps the solver calls optimal
    rel = np.abs(obj[ok] - ref_obj[ok]) / np.maximum(1.0, np.abs(ref_obj[ok]))
    below = np.isfinite(ref_obj) & np.isfinite(obj) & (obj < ref_obj - 1e-6 * np.maximum(1, np.abs(ref_obj)))
    return dict(config=name, backend=backend, states=len(res), ms_min=st["min_ms"], ms_median=st["median_ms"],
                ms_max=st["max_ms"], ms_mean=st["mean_ms"], nodes_mean=float(np.mean([r.nodes for r in res])),
                binaries_max=int(max(r.n_binaries for r in res)),
                non_optimal=int(sum(r.status != "optimal" or r.fallback for r in res)),
                max_rel_gap_vs_ref=float(rel.max()) if rel.size else np.nan,
                below_ref=int(below.sum()), source="flnotes", **extra)


def lever_table(setup: dict, rec: dict, idx, ref_obj: np.ndarray, configs: Optional[dict] = None,
                backend: str = "auto", time_limit: Optional[float] = 30.0, slow_idx=None) -> list:
    """Rows for each lever configuration on the recorded states ``idx``.

    Configurations without the bound levers are slow: they run on ``slow_idx`` (a subset,
    default ``idx``) with ``time_limit`` seconds per state; a state that hits the limit counts
    as not optimal and its time is the limit. Each row's ``state_set`` says which states it ran on
    (``"slow"``: ``slow_idx``, ``"all"``: ``idx``): only rows of one set compare.
    """
    rows = []
    configs = configs or CONFIGS
    pos = {int(i): j for j, i in enumerate(idx)}
    for name, lv in configs.items():
        slow = lv.get("bounds") in ("box",) or (lv.get("bounds") == "horizon" and lv.get("encode") == "all")
        use = list(slow_idx) if (slow and slow_idx is not None) else list(idx)
        res = replay(make_mpc(setup, backend=backend, **lv), rec, use, time_limit=time_limit)
        rows.append(summarize(name, backend, res, ref_obj[[pos[int(i)] for i in use]],
                              state_set="slow" if (slow and slow_idx is not None) else "all",
                              levers=str(MPCOptions(backend=backend, **lv))))
    return rows


def paper_row() -> dict:
    """The paper's MPC row of Table 2 as a row of :func:`lever_table`. The paper gives no state count and no median:
    those cells are ``None`` (a table shows them as ``-``), not a number."""
    t = paper.TABLE2_MS[("Quad-1D", "MPC (N_p=10)")]
    return dict(config="paper (CPLEX via YALMIP, Table 2)", backend="cplex", states=None, ms_min=t["min"],
                ms_median=None, ms_max=t["max"], ms_mean=t["mean"], source="paper")


# ----------------------------------------------------------------------------------- the DAQP levers
#: The exact switches of the DAQP back-end (options of :func:`flnotes.solvers.make_solver`, passed by
#: :class:`flnotes.MPC` as ``solver_options``): name -> options. The first row is the default; each next row
#: turns one of them off; the last turns all three off (the back-end before them).
DAQP_LEVERS = {
    "default (secant regularization, retry, relaxation and feasibility MILP)": {},
    "without the secant regularization": dict(reg_mode="upper"),
    "without the retry with a stronger regularization": dict(reg_retry=False),
    "without the relaxation check (the feasibility MILP by SCIP)": dict(verify_feasibility="milp"),
    "without the feasibility MILP (SCIP on the MIQP)": dict(verify_feasibility="miqp"),
    "none of the three": dict(reg_mode="upper", reg_retry=False, verify_feasibility="miqp"),
}


def daqp_lever_table(setup: dict, rec: dict, idx, time_limit: Optional[float] = 30.0,
                     levers: Optional[dict] = None, repeat: bool = False) -> list:
    """Per-lever effect of :data:`DAQP_LEVERS` (DAQP back-end options) on the recorded states ``idx``
    (warm starts as recorded); see :func:`interleaved_table` for the columns. ``repeat=True`` adds the default once
    more as the last row (:func:`with_repeat`)."""
    levers = levers or DAQP_LEVERS
    configs = {k: dict(solver_options={"daqp": dict(v)}) for k, v in levers.items()}
    return interleaved_table(setup, rec, idx, with_repeat(configs) if repeat else configs, time_limit)


#: ``MPCOptions.lp`` compared on the recorded states of a longer horizon (:func:`lp_lever_table`); the default
#: first (the others are compared with it).
LP_LEVERS = {
    "lp='auto' (default)": dict(),
    "lp=False (FBBT bounds only)": dict(lp=False),
    "lp=True (LP bounds every round)": dict(lp=True),
}


def lp_lever_table(setup: dict, rec: dict, idx, time_limit: Optional[float] = 30.0, repeat: bool = False) -> list:
    """The LP tightening of the level-set rounds (:data:`LP_LEVERS`) on the recorded states ``idx``; see
    :func:`interleaved_table` for the columns. ``repeat=True`` adds the default once more as the last row
    (:func:`with_repeat`)."""
    configs = {k: dict(levers=v) for k, v in LP_LEVERS.items()}
    return interleaved_table(setup, rec, idx, with_repeat(configs) if repeat else configs, time_limit)


#: Which solver takes a program (``MPCOptions.backend``) and how SCIP is set up, on the recorded states of a
#: longer horizon (:func:`solver_lever_table`); the default first.
SOLVER_LEVERS = {
    f"backend='auto' (default: DAQP up to {AUTO_DAQP_BINARIES} binaries, SCIP above)": dict(),
    "branching='steps' (DAQP branches step by step)": dict(levers=dict(branching="steps")),
    "backend='daqp' (DAQP for every program)": dict(levers=dict(backend="daqp")),
    "backend='daqp', SCIP's checks with SCIP's settings and one epigraph": dict(
        levers=dict(backend="daqp"), solver_options=dict(scip_options=dict(objective="epigraph",
                                                                           miqp_params="default"))),
    "backend='auto', SCIP lean but presolving until nothing changes": dict(
        solver_options=dict(scip=dict(params={"presolving/maxrounds": -1}),
                            daqp=dict(scip_options=dict(params={"presolving/maxrounds": -1})))),
}


def solver_lever_table(setup: dict, rec: dict, idx, time_limit: Optional[float] = 30.0, repeat: bool = False) -> list:
    """The solver levers (:data:`SOLVER_LEVERS`) on the recorded states ``idx``; see :func:`interleaved_table`.
    ``repeat=True`` adds the default once more as the last row (:func:`with_repeat`)."""
    return interleaved_table(setup, rec, idx, with_repeat(SOLVER_LEVERS) if repeat else SOLVER_LEVERS, time_limit)


#: The suffix of the name of a configuration run a second time by :func:`with_repeat`.
REPEAT_SUFFIX = ", run again"


def with_repeat(configs: dict) -> dict:
    """``configs`` with its first configuration once more at the end, named with :data:`REPEAT_SUFFIX`: a second,
    separate controller with the same options, interleaved state by state with the others, so that the table holds
    a pair of identical runs (:func:`repeat_pairs`) for :func:`run_to_run_spread`."""
    if not configs:
        raise ValueError("with_repeat needs at least one configuration")
    first = next(iter(configs))
    return {**configs, first + REPEAT_SUFFIX: configs[first]}


def repeat_pairs(rows: Sequence[dict]) -> list[tuple[dict, dict]]:
    """The pairs (first row, its repeat) of a table built with :func:`with_repeat` (none when it has no repeat)."""
    return [(rows[0], r) for r in rows[1:] if r["config"] == rows[0]["config"] + REPEAT_SUFFIX]


#: Where the level-set rounds start (``MPCOptions.first_level``) and the repaired relaxation as a first incumbent
#: (``MPCOptions.repair``), compared by :func:`level_lever_table`; the default first, the engine before them last.
LEVEL_LEVERS = {
    "first_level='incumbent', repair (default)": dict(),
    "first_level='relaxation'": dict(levers=dict(first_level="relaxation")),
    "repair=False": dict(levers=dict(repair=False)),
    "first_level='relaxation', repair=False (before)": dict(levers=dict(first_level="relaxation", repair=False)),
}


def level_lever_table(setup: dict, rec: dict, idx, time_limit: Optional[float] = 30.0, repeat: bool = False) -> list:
    """The first level and the repaired incumbent (:data:`LEVEL_LEVERS`) on the states ``idx`` of ``rec`` (a
    recorded loop, warm-started as recorded, or :func:`cases_record` of diverse states, cold); see
    :func:`interleaved_table` for the columns. ``repeat=True`` adds the default once more as the last row
    (:func:`with_repeat`)."""
    return interleaved_table(setup, rec, idx, with_repeat(LEVEL_LEVERS) if repeat else LEVEL_LEVERS, time_limit)


def cases_record(cases: list) -> dict:
    """Diverse states (:func:`flnotes.bench.exactness.mpc_cases`) as a record for :func:`interleaved_table`: solved
    cold (no previous plan)."""
    return dict(z=[c["z"] for c in cases], R=[c["z_ref"] for c in cases], prev=[None] * len(cases))


def interleaved_table(setup: dict, rec: dict, idx, configs: dict, time_limit: Optional[float] = 30.0) -> list:
    """Configurations of :func:`make_mpc` (name -> ``dict(levers=..., solver_options=...)``) on the recorded
    states ``idx``, warm-started as recorded (:func:`interleaved_rows`)."""
    mpcs = {k: make_mpc(setup, time_limit=time_limit, solver_options=v.get("solver_options"), **v.get("levers", {}))
            for k, v in configs.items()}
    return interleaved_rows(mpcs, rec, idx)


def interleaved_rows(mpcs: dict, rec: dict, idx) -> list:
    """The controllers ``mpcs`` (name -> :class:`flnotes.MPC`) on the recorded states ``idx`` in order, each
    warm-started with the recorded previous plan.

    The controllers are interleaved state by state (the machine's load hits all alike) and none is reset in
    between (the kept LP bounds of ``MPCOptions.bound_cache`` carry over as along the loop). Each row gives the
    wall-clock and CPU time per step (median, p99, max, and the CPU time in all), the mean nodes and the largest
    number of binaries, the mixed-integer programs solved in all (level-set and constraint-generation rounds), the
    steps not proven optimal (and those of them proven infeasible), the largest relative difference of the objective
    to the first controller's at the steps both prove optimal, and with kept LP bounds the boxes they served and the
    boxes asked for.
    """
    out = {k: dict(wall=[], cpu=[], obj=[], ok=[], nodes=[], nbin=[], rounds=[]) for k in mpcs}
    for i in idx:
        for k, m in mpcs.items():
            m.set_previous_plan(rec["prev"][i])
            c0 = time.process_time()
            r = m(rec["z"][i], rec["R"][i])
            o = out[k]
            o["cpu"].append(time.process_time() - c0)
            o["wall"].append(r.solve_time)
            o["obj"].append(r.objective)
            o["ok"].append(r.status == "optimal" and not r.fallback)
            o["nodes"].append(r.nodes)
            o["nbin"].append(r.n_binaries)
            o["rounds"].append(r.rounds)
            o.setdefault("infeasible", []).append(r.status == "infeasible")
    first = next(iter(out.values()))
    rows = []
    for k, o in out.items():
        w, c = time_stats(o["wall"], percentiles=(50, 99)), time_stats(o["cpu"], percentiles=(50, 99))
        both = np.array(o["ok"], bool) & np.array(first["ok"], bool)
        J, J0 = np.array(o["obj"], float)[both], np.array(first["obj"], float)[both]
        d = np.abs(J - J0) / np.maximum(1.0, np.abs(J0))
        cache = getattr(mpcs[k].solver, "cache", None)
        rows.append(dict(config=k, N_p=mpcs[k].N, states=len(o["wall"]), ms_median=w["median_ms"],
                         ms_p99=w["p99_ms"], ms_max=w["max_ms"], cpu_ms_median=c["median_ms"], cpu_ms_p99=c["p99_ms"],
                         cpu_ms_max=c["max_ms"], cpu_s_total=float(np.sum(o["cpu"])),
                         nodes_mean=float(np.mean(o["nodes"])) if o["nodes"] else np.nan,
                         binaries_max=int(max(o["nbin"], default=0)),
                         programs_solved=int(sum(o["rounds"])),
                         non_optimal=int(len(o["ok"]) - sum(o["ok"])),
                         infeasible=int(sum(o.get("infeasible", ()))),
                         max_rel_diff_to_default=float(d.max()) if d.size else np.nan,
                         boxes_served=None if cache is None else cache.served,
                         boxes_asked=None if cache is None else cache.asked))
    return rows


def history_record(history) -> dict:
    """What a replay needs of a recorded loop (:func:`record_run`'s ``z``, ``R``, ``prev``, ``screened``), from the
    :class:`flnotes.StepResult` history of any :class:`flnotes.MPC`."""
    h = list(history)
    return dict(z=np.array([s.z_pred[0] for s in h]), R=np.array([s.info["z_ref"] for s in h]),
                prev=[None] + [(s.z_pred, s.v_pred) for s in h[:-1]], screened=np.array([s.screened for s in h]))


#: The kept LP bounds (``MPCOptions.bound_cache``) on and off, compared by :func:`cache_lever_table`; the default
#: first.
CACHE_LEVERS = {"bound_cache=True (default)": dict(), "bound_cache=False": dict(bound_cache=False)}


def cache_lever_table(horizons: Sequence[int] = (15, 20), t_final: float = 6.0,
                      unseen: Optional[Sequence[str]] = None, steps: Optional[int] = None,
                      time_limit: Optional[float] = 30.0) -> list:
    """The kept LP bounds (:data:`CACHE_LEVERS`) along closed loops: the book's Quad-1D at each ``N_p`` of
    ``horizons`` (``t_final`` seconds) and the systems ``unseen`` of :mod:`flnotes.studies.unseen` (default all of
    them; ``steps`` steps each, default their own length), each recorded with the default options and replayed
    state by state in order (the states where the screening QP was not optimal) with the bounds kept and not kept
    (:func:`interleaved_rows`, ``time_limit`` seconds per solve). One row per loop and setting, with ``system``."""
    from ..studies import unseen as un

    rows = []
    base = quad_setup()
    for N in horizons:
        setup = quad_setup(horizon=int(N), net=base["net"], eps=base["eps"])
        rec = record_run(setup, t_final)
        mpcs = {k: make_mpc(setup, time_limit=time_limit, **v) for k, v in CACHE_LEVERS.items()}
        rows += [dict(system="Quad-1D", **r) for r in interleaved_rows(mpcs, rec, np.flatnonzero(~rec["screened"]))]
    for name in list(un.CASES) if unseen is None else unseen:
        c = un.case(name)
        _, mpc, _ = un.closed_loop(name, t_final=None if steps is None else steps * c.ts)
        rec = history_record(mpc.history)
        mpcs = {k: un.unseen_mpc(name, options=MPCOptions(**v), time_limit=time_limit) for k, v in CACHE_LEVERS.items()}
        rows += [dict(system=name, **r) for r in interleaved_rows(mpcs, rec, np.flatnonzero(~rec["screened"]))]
    return rows


def cache_lever_numbers(rows: Sequence[dict]) -> dict:
    """The numbers chapter 8 quotes from :func:`cache_lever_table`: boxes ``served`` from kept bounds of the ``asked``
    (all loops), the same and the CPU time in all with and without (``q_cpu_on``, ``q_cpu_off``) for the Quad-1D
    loop at the longest horizon (``q_N_p``), and of the systems not in the book ``n_lp_sys`` that LP-tightened
    boxes, ``n_other`` that did not, and the range of their CPU time without over with (``ratio_min``,
    ``ratio_max``; NaN when none)."""
    on = [r for r in rows if r["boxes_served"] is not None]
    off = {(r["system"], r["N_p"]): r for r in rows if r["boxes_served"] is None}
    if len(on) != len(off) or any((r["system"], r["N_p"]) not in off for r in on):
        raise ValueError("each loop needs one row with the bounds kept and one without (cache_lever_table's rows)")
    quad = [r for r in on if r["system"] == "Quad-1D"]
    q = max(quad, key=lambda r: r["N_p"]) if quad else None
    lp = [r for r in on if r["system"] != "Quad-1D" and r["boxes_asked"] > 0]
    ratio = [off[(r["system"], r["N_p"])]["cpu_s_total"] / r["cpu_s_total"] for r in lp]
    out = dict(served=int(sum(r["boxes_served"] for r in on)), asked=int(sum(r["boxes_asked"] for r in on)),
               n_lp_sys=len(lp), n_other=len(on) - len(quad) - len(lp),
               ratio_min=min(ratio) if ratio else np.nan, ratio_max=max(ratio) if ratio else np.nan)
    if q is not None:
        out.update(q_N_p=int(q["N_p"]), q_served=int(q["boxes_served"]), q_asked=int(q["boxes_asked"]),
                   q_cpu_on=q["cpu_s_total"], q_cpu_off=off[("Quad-1D", q["N_p"])]["cpu_s_total"])
    return out


#: The columns of :func:`interleaved_rows` that do not depend on the machine: two rows that agree on all of them did
#: the same work (the same steps, nodes, binaries and programs), and differ only in time.
WORK_COLUMNS = ("states", "nodes_mean", "binaries_max", "programs_solved", "non_optimal", "infeasible")

#: The time columns of :func:`interleaved_rows` whose run-to-run spread :func:`run_to_run_spread` measures.
SPREAD_COLUMNS = ("cpu_s_total", "cpu_ms_median", "cpu_ms_max")


def idle_cache_pairs(rows: Sequence[dict]) -> list[tuple[dict, dict]]:
    """The loops of :func:`cache_lever_table` on which the kept LP bounds had nothing to do: no box was LP-tightened
    (``boxes_asked == 0``) on a loop with at least one replayed state. Both settings then ran the same work,
    interleaved state by state, and their two rows (kept, not kept) are a pair of identical runs for
    :func:`run_to_run_spread`."""
    off = {(r["system"], r["N_p"]): r for r in rows if r["boxes_served"] is None}
    return [(r, off[(r["system"], r["N_p"])]) for r in rows
            if r["boxes_served"] is not None and r["boxes_asked"] == 0 and r["states"] > 0
            and (r["system"], r["N_p"]) in off]


def run_to_run_spread(pairs: Sequence[tuple[dict, dict]], columns: Sequence[str] = SPREAD_COLUMNS) -> dict:
    """How far two runs of the same work on the same states differ in time on this machine.

    Parameters
    ----------
    pairs
        Pairs of rows of :func:`interleaved_rows` that ran the same work: the same configuration twice, or a lever
        that had nothing to do (:func:`idle_cache_pairs`). Each pair must agree on every column of
        :data:`WORK_COLUMNS`, or it is not a pair of identical runs (``ValueError``).
    columns
        Time columns to compare.

    Returns
    -------
    dict
        ``pairs`` (their number) and, per column, the largest relative difference ``|a - b| / min(a, b)`` over the
        pairs: a difference between two settings within it is not measurable on this machine.
    """
    if not pairs:
        raise ValueError("run_to_run_spread needs at least one pair of identical runs")
    for a, b in pairs:
        differ = [c for c in WORK_COLUMNS if not (a[c] == b[c] or (np.isnan(a[c]) and np.isnan(b[c])))]
        if differ:
            raise ValueError(f"not a pair of identical runs: {a['config']!r} and {b['config']!r} differ in {differ}")
    out: dict = dict(pairs=len(pairs))
    for c in columns:
        out[c] = max(spread((a[c], b[c])) for a, b in pairs)
    return out


def _horizon_runs(horizons, t_final: float, time_limit: Optional[float]):
    """``(N_p, setup, recorded run)`` of the book's loop with the book's network for each ``N_p``."""
    base = quad_setup()
    for N in horizons:
        setup = quad_setup(horizon=N, net=base["net"], eps=base["eps"])
        yield N, setup, record_run(setup, t_final, time_limit=time_limit)


def horizon_targets(horizons=(15, 20), t_final: float = 6.0, time_limit: Optional[float] = 30.0) -> list:
    """The recorded loop of Sec. IV-B with longer horizons against the targets (every step <= t_s, proven optimal).

    One closed loop per ``N_p`` with the default options; one :func:`horizon_row` each.
    """
    return [horizon_row(setup, rec) for _, setup, rec in _horizon_runs(horizons, t_final, time_limit)]


def horizon_row(setup: dict, rec: dict) -> dict:
    """A recorded loop (:func:`record_run`) against the targets: wall-clock and CPU time per step, steps over
    ``t_s``, steps not proven optimal (gap above the requested 1e-6, time limit, fallback), binaries, nodes."""
    w = time_stats(rec["ms"] / 1e3, percentiles=(50, 99))
    c = time_stats(rec["cpu_ms"] / 1e3, percentiles=(50, 99))
    ts_ms = 1e3 * setup["ts"]
    return dict(N_p=int(setup["N"]), steps=w["n"], ms_median=w["median_ms"], ms_p99=w["p99_ms"], ms_max=w["max_ms"],
                cpu_ms_median=c["median_ms"], cpu_ms_p99=c["p99_ms"], cpu_ms_max=c["max_ms"],
                over_ts=int(np.sum(rec["ms"] > ts_ms)), cpu_over_ts=int(np.sum(rec["cpu_ms"] > ts_ms)),
                non_optimal=int(sum(s != "optimal" for s in rec["status"])),
                binaries_max=int(max(r.n_binaries for r in rec["results"])),
                nodes_max=int(max(r.nodes for r in rec["results"])), target_ms=ts_ms)


def horizon_gap_row(setup: dict, rec: dict, idx, time_limit: float = 600.0, lazy: bool = False) -> dict:
    """The optimality gap of a recorded loop's steps ``idx`` against the cold reference (:func:`reference`).

    The reference solves each recorded program again from nothing: SCIP, every step of the
    horizon encoded (or by constraint generation, ``lazy=True``), FBBT bounds along the horizon,
    no warm start, no screening, gap 1e-8. The row reports the largest relative gap
    ``|J - J_ref| / max(1, |J_ref|)`` of the loop's optima (the steps the loop proved optimal),
    the steps below the reference (which would mean the reference is not optimal), and the
    reference solves that did not finish within ``time_limit``.
    """
    ref_obj, ref_res = reference(setup, rec, idx, time_limit=time_limit, lazy=lazy)
    row = summarize(f"gap N_p = {int(setup['N'])} vs cold reference", "auto", [rec["results"][i] for i in idx], ref_obj)
    return dict(row, reference_not_optimal=int(sum(r.status != "optimal" for r in ref_res)), target_gap=TARGET_GAP,
                reference_wall_s=float(sum(r.solve_time for r in ref_res)))


# ----------------------------------------------------------------------------------- scaling
def scaling_horizon(horizons, t_final: float, time_limit: Optional[float] = 30.0) -> list:
    """Closed-loop per-step times of the default configuration for each ``N_p``, with the binaries of the paper's
    program (``binaries_full``, every neuron at every step) and the free binaries the engine branched on at the steps
    the screening QP did not settle (``binaries_free_mean``, ``binaries_free_max``)."""
    rows = []
    for N, setup, rec in _horizon_runs(horizons, t_final, time_limit):
        st = time_stats(rec["ms"] / 1e3, percentiles=(50, 95))
        nb = np.array([r.n_binaries for r, s in zip(rec["results"], rec["screened"]) if not s], int)
        rows.append(dict(N_p=int(N), binaries_full=int(N * setup["net"].n_hidden),
                         binaries_free_mean=float(nb.mean()) if nb.size else 0.0,
                         binaries_free_max=int(nb.max()) if nb.size else 0, steps=st["n"],
                         ms_median=st["median_ms"], ms_p95=st["p95_ms"], ms_max=st["max_ms"],
                         ms_mean=st["mean_ms"], screened=int(rec["screened"].sum()),
                         infeasible=int(sum(s == "infeasible" for s in rec["status"])),
                         fallbacks=int(rec["fallback"].sum()),
                         non_optimal=int(sum(s != "optimal" for s in rec["status"]))))
    return rows


def scaling_width(widths, t_final: float, n_per_axis: int = 12, max_iter: int = 600,
                  time_limit: Optional[float] = 30.0) -> list:
    """Closed-loop per-step times for networks of three hidden layers of each width (coarse training).

    ``eps`` for these networks is their largest error on the training grid (an estimate, not a
    certificate): enough to time the solver on a realistic constraint.
    """
    from ..network import fit_relu

    rows = []
    s = paper.system("Quad-1D")
    for w in widths:
        t0 = time.perf_counter()
        net, rep = fit_relu(s.phi_stacked, s.lo, s.hi, widths=(w, w, w), n_per_axis=n_per_axis,
                            max_train=20_000, max_iter=max_iter, seed=0)
        t_train = time.perf_counter() - t0
        eps = float(np.max(rep.grid_max_error))
        setup = quad_setup(net=net, eps=eps)
        if setup["u_eps"] <= 0.02:
            rows.append(dict(width=int(w), note=f"eps = {eps:.3f} leaves no admissible input"))
            continue
        rec = record_run(setup, t_final, time_limit=time_limit)
        st = time_stats(rec["ms"] / 1e3, percentiles=(50, 95))
        rows.append(dict(width=int(w), binaries_full=int(setup["N"] * net.n_hidden), eps_grid=eps,
                         train_s=t_train, steps=st["n"], ms_median=st["median_ms"],
                         ms_p95=st["p95_ms"], ms_max=st["max_ms"], ms_mean=st["mean_ms"],
                         non_optimal=int(sum(st != "optimal" for st in rec["status"]))))
    return rows


def growth_note(x, y, what: str) -> str:
    """A fitted power law ``y ~ x^p`` (least squares on logs), stated in words."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = (x > 0) & (y > 0) & np.isfinite(y)
    if ok.sum() < 2:
        return f"{what}: too few points to fit a growth law"
    p = np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)[0]
    return f"{what} grows roughly like x^{p:.2f} over the measured range"


# ----------------------------------------------------------------------------------- the section
def run(fast: bool) -> dict:
    from ..plots import realtime as rp
    from . import out_dir

    setup = quad_setup()
    t_final = 4.0 if fast else 20.0
    rows, notes, figures = [paper_row()], [], []
    notes.append(f"Quad-1D, N_p = {setup['N']}, t_s = {setup['ts']} s, x_ref = 1.5 sin t, {setup['eps_note']} "
                 f"(eps = {setup['eps']:.4f}); t_final = {t_final} s.")
    rec = record_run(setup, t_final)
    n = len(rec["z"])
    ref_idx = pick_states(rec, n_hard=12 if fast else 40, n_easy=2 if fast else 6)
    t0 = time.perf_counter()
    ref_obj, ref_res = reference(setup, rec, ref_idx)
    notes.append(f"reference: SCIP on {len(ref_idx)} recorded states in {time.perf_counter() - t0:.0f} s "
                 f"({sum(r.status != 'optimal' for r in ref_res)} not proven optimal)")
    rows.append(summarize("recorded closed loop (level set, default)", "auto", rec["results"], np.full(n, np.nan)))
    # lever table on the states with a reference
    hard = [i for i in ref_idx if not rec["screened"][i]]
    slow_idx = np.array(hard[:: max(1, len(hard) // (3 if fast else 6))])
    notes.append(f"lever rows: {len(ref_idx)} recorded states ({len(hard)} where the screening QP violates the "
                 f"network constraint); configurations without bound levers on {len(slow_idx)} of the hard ones, "
                 f"{5 if fast else 10} s limit per state")
    rows += lever_table(setup, rec, ref_idx, ref_obj, slow_idx=slow_idx, time_limit=5.0 if fast else 10.0)
    # other back-ends for the default configuration
    for be in ("daqp", "scip", "gurobi", "cplex"):
        if be in available_backends():
            sub = ref_idx[:: max(1, len(ref_idx) // 8)]
            try:
                res = replay(make_mpc(setup, backend=be), rec, sub, time_limit=30.0)
                rows.append(summarize("level set (default)", be, res, ref_obj[np.searchsorted(ref_idx, sub)]))
            except Exception as exc:  # an installed commercial solver without a license
                notes.append(f"backend {be} skipped: {type(exc).__name__}: {exc}")
    # targets
    default = [r for r in rows if r.get("config") == "level set (default)" and r.get("backend") == "auto"][0]
    notes.append(f"targets: max {TARGET_MAX_MS:.0f} ms, median {TARGET_MEDIAN_MS:.0f} ms, gap {TARGET_GAP:g}; "
                 f"default configuration on {default['states']} states: max {default['ms_max']:.1f} ms "
                 f"({default['ms_max'] / TARGET_MAX_MS:.2f} x target), median {default['ms_median']:.2f} ms, "
                 f"max rel. gap {default['max_rel_gap_vs_ref']:.1e}, not optimal {default['non_optimal']}.")
    figures.append(str(rp.step_times(rec, path=out_dir() / "mpc_step_times.png")))
    # the DAQP levers (per-lever effect) on the recorded loop's states where the screening QP was not optimal
    hard_all = np.flatnonzero(~rec["screened"])
    for r in daqp_lever_table(setup, rec, hard_all[:: 4 if fast else 1], time_limit=30.0):
        rows.append(dict(r, config=f"DAQP lever: {r['config']}", backend="auto"))
    # longer horizons against the targets, and the LP tightening of the level-set rounds on their hardest states
    for N, s_N, rec_N in _horizon_runs((15,) if fast else (15, 20), t_final=2.0 if fast else 6.0, time_limit=30.0):
        r = horizon_row(s_N, rec_N)
        rows.append(dict(config=f"targets N_p = {r['N_p']}", backend="auto", **{k: v for k, v in r.items() if k != "N_p"}))
        worst = np.argsort(-rec_N["cpu_ms"])[: 4 if fast else 12]
        for lr in lp_lever_table(s_N, rec_N, np.sort(worst), time_limit=30.0):
            rows.append(dict(lr, config=f"LP lever N_p = {N}: {lr['config']}", backend="auto"))
        for sr in solver_lever_table(s_N, rec_N, np.sort(worst), time_limit=30.0):
            rows.append(dict(sr, config=f"solver lever N_p = {N}: {sr['config']}"))
        for lr in level_lever_table(s_N, rec_N, np.sort(worst), time_limit=30.0):
            rows.append(dict(lr, config=f"level lever N_p = {N}: {lr['config']}", backend="auto"))
        gap_idx = np.union1d(worst, pick_states(rec_N, n_hard=4 if fast else 12, n_easy=2))
        g = horizon_gap_row(s_N, rec_N, gap_idx, lazy=N > 15)  # N_p = 20 encoded at once: SCIP > 5 min per state
        rows.append(g)
        notes.append(f"N_p = {N}: largest gap of the loop's optima against the cold reference on {g['states']} steps "
                     f"(the slowest and some spread over the run): {g['max_rel_gap_vs_ref']:.1e} (target {TARGET_GAP:g}); "
                     f"{g['below_ref']} below the reference; {g['reference_not_optimal']} reference solves not finished; "
                     f"reference {'by constraint generation' if N > 15 else 'with every step encoded'}")
        notes.append(f"N_p = {r['N_p']} (recorded loop, {r['steps']} steps, default options): max {r['ms_max']:.0f} ms "
                     f"wall / {r['cpu_ms_max']:.0f} ms CPU against t_s = {r['target_ms']:.0f} ms; {r['over_ts']} steps "
                     f"over t_s (wall), {r['cpu_over_ts']} (CPU); {r['non_optimal']} not proven optimal; up to "
                     f"{r['binaries_max']} binaries and {r['nodes_max']} nodes in one step")
    # the LP bounds kept along the loop, on the longer horizons and the systems not in the book
    for r in cache_lever_table(horizons=(15,) if fast else (15, 20), t_final=2.0 if fast else 6.0,
                               unseen=("VdP-gain",) if fast else None, steps=8 if fast else 40):
        rows.append(dict(r, config=f"kept LP bounds, {r['system']} N_p = {r['N_p']}: {r['config']}", backend="auto"))
    # scaling
    horizons = (2, 5, 10) if fast else (2, 4, 6, 8, 10, 15, 20)
    sh = scaling_horizon(horizons, t_final=2.0 if fast else 6.0)
    for r in sh:
        rows.append(dict(config=f"scaling N_p = {r['N_p']}", backend="auto", **{k: v for k, v in r.items() if k != "N_p"}))
    for r in sh:
        if r["infeasible"]:
            notes.append(f"N_p = {r['N_p']}: {r['infeasible']} of {r['steps']} steps infeasible: the closed loop left "
                         f"the state box (without a terminal cost this short horizon does not stabilize the loop), "
                         f"a property of the controller, not of the solver; they count as non_optimal")
        other = r["non_optimal"] - r["infeasible"]
        if other:
            notes.append(f"N_p = {r['N_p']}: {other} steps stopped at the 30 s limit (time_limit) or failed")
    notes.append(growth_note([r["N_p"] for r in sh], [r["ms_median"] for r in sh], "median time per step vs N_p"))
    notes.append(growth_note([r["N_p"] for r in sh], [r["ms_max"] for r in sh], "max time per step vs N_p"))
    widths = (5, 10) if fast else (5, 10, 15, 20)
    sw = scaling_width(widths, t_final=2.0 if fast else 6.0, n_per_axis=9 if fast else 12,
                       max_iter=300 if fast else 600)
    for r in sw:
        rows.append(dict(config=f"scaling width {r['width']}", backend="auto", **{k: v for k, v in r.items() if k != "width"}))
    ok = [r for r in sw if "ms_median" in r]
    notes.append(growth_note([r["width"] for r in ok], [r["ms_median"] for r in ok], "median time per step vs width"))
    figures.append(str(rp.scaling(sh, sw, path=out_dir() / "mpc_scaling.png")))
    notes.append("MSD CLF-CBF per-step times: see the clfcbf section.")
    return dict(title="Quad-1D MPC: real-time levers (eq. MPC_form_miqp)", rows=rows, notes=notes, figures=figures)


# ----------------------------------------------------------------------------------- for the chapter
def binary_counts(setup: dict, z0, z_ref, previous=None) -> dict:
    """Binaries of eq. (MPC_form_miqp) at one state under each bounds lever (every step encoded).

    ``"paper"`` is ``N_p * sum_k n_k``; the others count the neurons left unstable by FBBT on the
    domain box, FBBT on the reachable boxes, LP-tightened reachable boxes, and the level set of
    the default options (which also drops the steps that need no encoding); ``previous`` is the plan
    ``(z_pred, v_pred)`` of the previous step (the warm start).
    """
    net, N = setup["net"], setup["N"]
    out = {"paper: every neuron a binary": N * net.n_hidden}
    mpc = make_mpc(setup)
    z0 = np.asarray(z0, float)
    lo, hi = mpc.pred.boxes(z0)
    for name, b in (("domain box, FBBT", "box"), ("reachable boxes, FBBT", "horizon"),
                    ("reachable boxes, LP with |Phi_NN| <= u_max^eps", "lp")):
        nb = node_bounds(mpc.pred, MPCOptions(bounds=b), mpc.box_bounds, lo, hi)
        out[name] = int(nb.n_unstable) if nb is not None else 0
    mpc.set_previous_plan(previous)
    out["level set (default options)"] = int(mpc(z0, z_ref).n_binaries)
    return out


def backend_overheads(n_repeat: int = 20) -> list:
    """Per-call time of every installed back-end on one small mixed-binary QP and LP (data changed each time).

    The QP's Hessian is positive definite on the continuous variables and zero on the binaries, the shape
    DAQP certifies by itself (its secant regularization vanishes at both values of a binary). The LP has a
    zero Hessian everywhere: DAQP's regularized answer then certifies a gap only through the continuous
    variables' bounds (at most ``reg / 8`` per variable scaled to a unit range, the DAQP option ``scale``), and
    when that gap exceeds the one requested the back-end re-solves the program with SCIP (building a SCIP model
    inside the call). Column ``checked_by_other`` counts those calls, so a row's
    times say whether they are one solver's call or two solvers'. Times: the wall clock of
    :meth:`Solver.solve` and the process's CPU time around it (median and minimum over ``n_repeat`` calls).
    """
    import scipy.sparse as sp

    from ..solvers import MIQP, make_solver as _make

    rng = np.random.default_rng(0)
    n_c, n_b = 5, 4
    F = rng.normal(size=(n_c, n_c + n_b))
    F[:, n_c:] = 0.0  # positive definite on the continuous variables (almost surely), zero on the binaries
    A = rng.normal(size=(6, n_c + n_b))
    A[:, n_c] += 2.0
    w = np.r_[rng.uniform(-1, 1, n_c), rng.integers(0, 2, n_b)]
    rows = []
    for kind, H in (("MIQP", sp.csc_matrix(F.T @ F)), ("MILP", None)):
        p = MIQP(H, rng.normal(size=n_c + n_b), 0.0, sp.csr_matrix(A), A @ w - 1.0, A @ w + 1.0,
                 np.r_[-2 * np.ones(n_c), np.zeros(n_b)], np.r_[2 * np.ones(n_c), np.ones(n_b)],
                 np.r_[np.zeros(n_c, int), np.ones(n_b, int)])
        for be in available_backends():
            if be in ("gurobi", "cplex") or (be == "highs" and H is not None):
                continue
            s = _make(p, be)
            ts, cpu, other = [], [], 0
            for k in range(n_repeat):
                s.update(c=p.c * (1 + 0.05 * np.sin(k)))
                c0 = time.process_time()
                r = s.solve()
                cpu.append(time.process_time() - c0)
                ts.append(r.time)
                other += "proven by" in r.message  # the answer was certified by another solver's re-solve
            st, sc = time_stats(ts), time_stats(cpu)
            rows.append(dict(program=kind, backend=be, n=p.n, binaries=n_b, ms_median=st["median_ms"],
                             ms_min=st["min_ms"], cpu_ms_median=sc["median_ms"], cpu_ms_min=sc["min_ms"],
                             checked_by_other=int(other), calls=n_repeat))
    return rows


def box_samples(pred, z, V0, n: int = 300, scale: float = 0.5, seed: int = 0) -> np.ndarray:
    """Plans near ``V0`` in the boxes of the prediction model ``pred`` at the state ``z`` (the feasible set of the QP
    without the network constraint): ``n`` draws ``V0 + N(0, scale^2 I)`` from ``np.random.default_rng(seed)``, of
    which those with ``pred.feasible(z, V, network=False)`` are kept, in the order drawn (rows; possibly none)."""
    V0 = np.asarray(V0, float).reshape(-1)
    rng = np.random.default_rng(seed)
    kept = []
    for _ in range(int(n)):
        V = V0 + rng.normal(scale=scale, size=V0.size)
        if pred.feasible(z, V, network=False):
            kept.append(V)
    return np.array(kept).reshape(-1, V0.size)


def slack_numbers(slack, grad, J_c: float) -> dict:
    """The figures chapter 8's first exercise quotes on the slack of the level-set inequality (8.2).

    Parameters
    ----------
    slack
        ``J(v) - (J(v_c) + 0.5 (v - v_c)' H (v - v_c))`` at the sampled plans (at least one).
    grad
        ``grad J(v_c)``, the gradient of the cost at the QP's optimum ``v_c``.
    J_c
        ``J(v_c)``, which scales the test of a zero gradient.

    Returns
    -------
    dict
        ``ex1_slack_min`` (the smallest slack), ``ex1_grad`` (the norm of the gradient) and ``ex1_clause``: when the
        norm exceeds ``1e-6 max(1, |J_c|)`` (a box constraint active at ``v_c``), "the QP's optimum sits on the
        boundary of the boxes (the gradient there has norm G), and the smallest slack over the sampled plans is S";
        otherwise "the QP's optimum lies inside the boxes (its gradient is zero), and the inequality holds with
        equality".
    """
    slack = np.asarray(slack, float)
    if slack.size == 0:
        raise ValueError("slack_numbers needs the slack at one sampled plan at least")
    g = float(np.linalg.norm(grad))
    on_boundary = g > 1e-6 * max(1.0, abs(J_c))
    clause = (f"the QP's optimum sits on the boundary of the boxes (the gradient there has norm {g:.3g}), and the "
              f"smallest slack over the sampled plans is {slack.min():.3g}" if on_boundary else
              "the QP's optimum lies inside the boxes (its gradient is zero), and the inequality holds with equality")
    return dict(ex1_slack_min=float(slack.min()), ex1_grad=g, ex1_clause=clause)


def screening_numbers(ms_on, ms_off, screened) -> dict:
    """The medians chapter 8's second exercise quotes on replayed steps with and without screening, and its clause.

    Parameters
    ----------
    ms_on, ms_off
        the solve time (ms) of each replayed step with and without screening.
    screened
        for each step, whether the screening QP settled it in the recorded run.

    Returns
    -------
    dict
        ``scr_on`` (median with screening over the screened steps), ``not_on`` and ``not_off`` (medians with and
        without screening over the steps not screened; each NaN when its group is empty) and ``clause``: when a
        group is empty, "This selection of steps lacks one of the two groups, so there is no difference to read";
        when ``|not_on - not_off| <= scr_on`` (what a screened step, the QP and forward pass, costs), "The
        difference, D ms, is within what the QP and the forward pass cost, as the argument expects"; otherwise "The
        difference, D ms, is larger than what the QP and the forward pass cost, so they do not explain it, ..." (no
        cause found in the chapter, candidates named).
    """
    ms_on, ms_off, scr = np.asarray(ms_on, float), np.asarray(ms_off, float), np.asarray(screened, bool)
    out = {key: float(np.median(ms[g])) if g.any() else float("nan")
           for key, g, ms in (("scr_on", scr, ms_on), ("not_on", ~scr, ms_on), ("not_off", ~scr, ms_off))}
    d, qp_cost = out["not_on"] - out["not_off"], out["scr_on"]  # with screening minus without; what the QP costs
    if not (np.isfinite(d) and np.isfinite(qp_cost)):
        out["clause"] = "This selection of steps lacks one of the two groups, so there is no difference to read"
    elif abs(d) <= qp_cost:
        out["clause"] = f"The difference, {d:+.2f} ms, is within what the QP and the forward pass cost, as the argument expects"
    else:
        out["clause"] = (f"The difference, {d:+.2f} ms, is larger than what the QP and the forward pass cost, so they do "
                         "not explain it, and this chapter has not found its cause: one run of each on a shared machine "
                         "does not separate it from the run-to-run variation of the timings, and a different incumbent "
                         "or first level without screening is a candidate that is not checked here")
    return out


def cache_lever_clauses(rows: Sequence[dict]) -> dict:
    """The sentence the benchmark report adds under :func:`cache_lever_table` for loops with no state to replay.

    Returns
    -------
    dict
        ``empty``: "" when every loop left a state to replay; for one loop ``S`` with none (``states == 0``),
        " The loop of S is not in the table: the screening QP settled every one of its steps, so no state was left
        to replay."; for several, " The loops of S1 and S2 are not in the table: the screening QP settled every one
        of their steps, so no state was left to replay." (systems in the order of the rows, each once).
    """
    empty = list(dict.fromkeys(r["system"] for r in rows if r["states"] == 0))
    names = " and ".join(empty)
    if not empty:
        return dict(empty="")
    if len(empty) == 1:
        return dict(empty=f" The loop of {names} is not in the table: the screening QP settled every one of its steps, "
                          "so no state was left to replay.")
    return dict(empty=f" The loops of {names} are not in the table: the screening QP settled every one of their steps, "
                      "so no state was left to replay.")


def lever_verdicts(compared: Sequence[tuple], spread_: dict) -> dict:
    """Each setting against the default, on one time figure, judged against the run-to-run spread.

    Parameters
    ----------
    compared
        tuples ``(key, what, setting_row, default_row, column)``.
    spread_
        the run-to-run spread of each column (:func:`run_to_run_spread`).

    Returns
    -------
    dict
        ``key`` -> the verdict of :func:`flnotes.repeats.against_spread` on ``setting_row[column]`` against
        ``default_row[column]``: one of :data:`flnotes.repeats.VERDICTS` (within, at the edge of, beyond the spread).
    """
    from ..repeats import against_spread

    return {key: against_spread(x[col], y[col], spread_[col]) for key, _, x, y, col in compared}


def lever_verdict_table(compared: Sequence[tuple], spread_: dict) -> list[dict]:
    """The rows of the table behind :func:`lever_verdicts`: ``setting`` (``what``), ``figure`` (the column), the two
    values, their ``ratio`` (setting over default), the ``spread`` of the column and the ``verdict``."""
    from ..repeats import against_spread

    return [dict(setting=what, figure=col, setting_value=x[col], default_value=y[col], ratio=x[col] / y[col],
                 spread=spread_[col], verdict=against_spread(x[col], y[col], spread_[col]))
            for _, what, x, y, col in compared]


def lever_clauses(secant: tuple, daqp: tuple, repair: tuple, repair_cold: tuple, spread_: dict) -> dict:
    """The clauses the benchmark report words from the lever tables, each a pair ``(setting_row, default_row)``.

    Parameters
    ----------
    secant
        the secant regularization off, and the default (on).
    daqp
        DAQP for every program, and the default.
    repair, repair_cold
        no repair, and the default, in the closed loop and on the cold states.
    spread_
        the run-to-run spread of each time column (:func:`run_to_run_spread`).

    Returns
    -------
    dict
        ``secant_clause`` on the CPU time in all: within the spread, "not a measured difference on this machine"; at
        its edge, "weak evidence that the secant regularization shortens it" (or "lengthens", when the default is
        slower than the setting); beyond it, "the secant regularization shortens it on this machine" (or
        "lengthens").
        ``auto_clause``: when neither the slowest step nor the CPU time in all of DAQP for every program differs
        beyond the spread, "neither the slowest step nor the CPU time in all differs measurably, so on these steps
        no measured gain in time supports sending the large programs to SCIP"; else "the slowest step ..., and the
        CPU time in all ...", each "does not differ measurably" (within the spread) or "is shorter|longer with the
        default" (", on weak evidence" at the edge of the spread).
        ``repair_trade``: the loop's median step, slowest step and CPU time in all without → with the repair, each
        "longer", "shorter" or "the same" with its verdict, and the CPU time in all on the cold states with its
        verdict.
    """
    from ..repeats import VERDICTS, against_spread

    within, edge, beyond = VERDICTS
    verdict = lambda x, y, col: against_spread(x[col], y[col], spread_[col])  # noqa: E731 - setting x, default y

    def reading(v, without, with_, what):  # a lever that changes the time from without to with_
        d = "shortens" if with_ < without else "lengthens"
        return {within: "not a measured difference on this machine", edge: f"weak evidence that {what} {d} it",
                beyond: f"{what} {d} it on this machine"}[v]

    def figure(what, v, alt, default):  # one figure of the default against an alternative
        if v == within:
            return f"{what} does not differ measurably"
        return (f"{what} is {'shorter' if default < alt else 'longer'} with the default"
                + (", on weak evidence" if v == edge else ""))

    off, on = secant
    out = dict(secant_clause=reading(verdict(off, on, "cpu_s_total"), off["cpu_s_total"], on["cpu_s_total"],
                                     "the secant regularization"))
    dq, df = daqp
    v_max, v_tot = verdict(dq, df, "cpu_ms_max"), verdict(dq, df, "cpu_s_total")
    if v_max == v_tot == within:
        out["auto_clause"] = ("neither the slowest step nor the CPU time in all differs measurably, so on these steps no "
                              "measured gain in time supports sending the large programs to SCIP")
    else:
        out["auto_clause"] = (figure("the slowest step", v_max, dq["cpu_ms_max"], df["cpu_ms_max"]) + ", and "
                              + figure("the CPU time in all", v_tot, dq["cpu_s_total"], df["cpu_s_total"]))
    (lo, ld), (co, cd) = repair, repair_cold
    word = lambda a, b: "longer" if b > a else "shorter" if b < a else "the same"  # noqa: E731
    out["repair_trade"] = (
        f"with the repair, the loop's median step was {word(lo['cpu_ms_median'], ld['cpu_ms_median'])} "
        f"({lo['cpu_ms_median']:.0f} → {ld['cpu_ms_median']:.0f} ms, {verdict(lo, ld, 'cpu_ms_median')} of median steps), "
        f"its slowest step {word(lo['cpu_ms_max'], ld['cpu_ms_max'])} ({lo['cpu_ms_max']:.0f} → {ld['cpu_ms_max']:.0f} ms, "
        f"{verdict(lo, ld, 'cpu_ms_max')} of slowest steps) and its CPU time in all "
        f"{word(lo['cpu_s_total'], ld['cpu_s_total'])} ({lo['cpu_s_total']:.2f} → {ld['cpu_s_total']:.2f} s, "
        f"{verdict(lo, ld, 'cpu_s_total')}); on the cold states the CPU time in all went {co['cpu_s_total']:.1f} → "
        f"{cd['cpu_s_total']:.1f} s ({verdict(co, cd, 'cpu_s_total')})")
    return out
