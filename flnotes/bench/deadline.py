"""Benchmark: the MPC with a time limit of one sampling period, ``time_limit = t_s``.

What :class:`flnotes.MPC` guarantees under ``time_limit`` (see :meth:`flnotes.MPC.__call__`): every answer is a
plan checked by the forward pass (:meth:`flnotes.mpc.Prediction.feasible`) whenever the engine's incumbent, the
shifted previous plan or a repair of it, or the plan built along the QP without the network passes that check;
otherwise a plan whose first input is admissible, flagged ``input_admissible=False`` only when no admissible input
exists at the measured state. A step that hits the limit records the cost ``J`` of its plan, a valid lower bound
``J_lb`` of eq. (MPC_form_miqp) and the gap ``(J - J_lb) / max(1, |J|)``.

Measured here for the Quad-1D of Sec. IV-B at ``N_p = 10, 15, 20`` with ``time_limit = t_s = 0.1`` s, on the
recorded closed loop with the constraint-active reference (``x_ref = 1.5 sin t``, true plant) and on the
diverse states of :func:`flnotes.bench.exactness.mpc_cases` (solved cold): the answer time per step (p50, p99,
max, and the overrun past ``t_s``), the CPU time next to it (the machine is shared: wall clock is noisy), the
steps that hit the limit and the distribution of their gaps, the distance of their plans from the optimum (proven
by the MPC without the limit and, for the closed loops, by the cold reference), the forward-pass check of every
returned plan and of every applied input, and the true ``|u| <= u_max`` of the closed loop. Speed is measured here, never
asserted in tests (``tests/test_deadline.py`` asserts the properties).
"""
from __future__ import annotations

import time
from typing import Optional, Sequence

import numpy as np

from ..mpc import FALLBACK_POST_SHARE, RESERVE_DECAY, RESERVE_MAX_SHARE, RESERVE_SHARE
from ..simulate import simulate
from ..solvers import BOUND_TOL
from ..tables import time_stats
from .exactness import mpc_cases, mpc_reference
from .mpc import TARGET_GAP, make_mpc, quad_setup

#: The time limit per step, one sampling period of the Quad-1D (s).
T_S = 0.1

#: Seconds the cold reference gets per limit hit of the closed loops in the full benchmark (:func:`reference_gaps`).
#: On the N_p = 20 loop it took 1 to 298 s per state; with 60 s it left about a quarter of them undecided.
REFERENCE_LIMIT = 600.0


class _Timed:
    """An MPC for :func:`flnotes.simulate` whose CPU time (``time.process_time``) is recorded per step."""

    def __init__(self, mpc):
        self.mpc, self.cpu = mpc, []

    def reset(self) -> None:
        self.mpc.reset()
        self.cpu = []

    def step(self, z, t, reference=None):
        c0 = time.process_time()
        res = self.mpc.step(z, t, reference)
        self.cpu.append(time.process_time() - c0)
        return res


def step_record(mpc, res, cpu: float) -> dict:
    """One answer of ``mpc`` checked independently: the plan by the forward pass, the applied input at ``z``."""
    z = res.z_pred[0]
    u_nn = mpc.net(np.r_[z, res.v])
    return dict(ms=1e3 * res.solve_time, cpu_ms=1e3 * cpu, status=res.status, fallback=bool(res.fallback),
                gap=float(res.gap), objective=float(res.objective), bound=float(res.bound),
                plan_admissible=bool(mpc.pred.feasible(z, res.v_pred)),
                input_ok=bool(np.all(np.abs(u_nn) <= mpc.u_eps + BOUND_TOL)),
                input_flagged=not res.input_admissible, cut_off=bool(res.info.get("cut_off", False)))


def closed_loop(setup: dict, t_final: float, t_s: float = T_S, cut_off: Optional[bool] = None,
                reserve_share: Optional[float] = None) -> tuple[list[dict], dict]:
    """The recorded closed loop (true plant, sine reference) with ``time_limit = t_s`` (and the MPC's ``cut_off``
    and ``reserve_share`` when given).

    Returns the per-step records (:func:`step_record`) and the run's checks: ``u_within`` (true ``|u| <= u_max``
    at the samples, to 1e-9: what ``eps`` guarantees), ``u_within_between`` (the same between the samples, which
    takes the drift margin of the chapter "Guarantees") and ``cpu_over_wall`` (CPU time / wall time over the run).
    """
    mpc = make_mpc(setup, time_limit=t_s, cut_off=cut_off)
    if reserve_share is not None:
        mpc.reserve_share = reserve_share
    timed = _Timed(mpc)
    w0, c0 = time.perf_counter(), time.process_time()
    log = simulate(setup["system"], timed, t_final=t_final, ts=setup["ts"], z0=setup["z0"],
                   reference=setup["reference"], progress=False)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    s = log.summary()
    recs = [dict(step_record(mpc, r, c), case=dict(z=r.z_pred[0], z_ref=r.info["z_ref"]))
            for r, c in zip(mpc.history, timed.cpu)]
    return recs, dict(u_within=bool(s["u_within_bound_at_samples"]), u_within_between=bool(s["u_within_bound_between"]),
                      cpu_over_wall=cpu / max(wall, 1e-12))


def cut_off_study(setup: dict, t_final: float, t_s: float = T_S, reserve_share: float = 0.0) -> list[dict]:
    """The cut-off as a lever: the closed loop with ``time_limit = t_s`` and ``reserve_share`` (default none: the
    reserve is only what the controller has measured), without and with ``cut_off``, one run after the other.

    One :func:`summarize` row per setting (``run`` says which), with ``u_within`` of the loop. Without a share kept
    back, a solver call that overruns its limit makes the answer late unless the step answers at its cut-off.
    """
    rows = []
    for cut in (False, True):
        recs, chk = closed_loop(setup, t_final, t_s, cut_off=cut, reserve_share=reserve_share)
        rows.append(summarize(f"cut_off={cut}, reserve_share={reserve_share:g}", setup["N"], recs, t_s,
                              u_within=chk["u_within"]))
    return rows


def diverse(setup: dict, n: int, t_s: float = T_S, seed: int = 2, fallback_deadline: bool = True) -> list[dict]:
    """``n`` diverse states (:func:`flnotes.bench.exactness.mpc_cases`), each solved cold with ``time_limit = t_s``
    (``fallback_deadline``: :attr:`flnotes.MPC.fallback_deadline`)."""
    mpc = make_mpc(setup, time_limit=t_s)
    mpc.fallback_deadline = fallback_deadline
    out = []
    for c in mpc_cases(setup, n, seed=seed):
        mpc.reset()
        c0 = time.process_time()
        res = mpc(c["z"], c["z_ref"])
        out.append(dict(step_record(mpc, res, time.process_time() - c0), category=c["category"], case=c))
    return out


def decide_misses(setup: dict, recs: Sequence[dict], time_limit: float = 10.0) -> dict:
    """The limit hits whose plan fails the forward-pass check, solved again with ``time_limit`` seconds: was there an
    admissible plan to return? Returns counts ``infeasible`` (no: the program is proven infeasible), ``missed``
    (yes: an optimum exists) and ``undecided`` (the longer solve hit its limit too)."""
    mpc = make_mpc(setup, time_limit=time_limit)
    out = dict(infeasible=0, missed=0, undecided=0)
    for r in recs:
        if r["status"] == "time_limit" and not r["plan_admissible"]:
            mpc.reset()
            s = mpc(r["case"]["z"], r["case"]["z_ref"])
            key = ("infeasible" if s.status == "infeasible" else "missed" if s.status == "optimal" and not s.fallback
                   else "undecided")
            out[key] += 1
    return out


def optimum_gaps(setup: dict, recs: Sequence[dict], time_limit: float = 30.0) -> None:
    """How far the plans returned at the limit are from the optimum: each limit hit whose plan passes the forward
    pass is solved again without the step's limit (the default MPC, cold, with ``time_limit`` seconds; its optimum
    is checked against the cold reference in ``tests/test_exactness.py``), and ``opt_gap = (J - J*) / max(1, |J*|)``
    is written into the record (NaN when that solve proves no optimum in ``time_limit``)."""
    exact = make_mpc(setup, time_limit=time_limit)
    for r in recs:
        if r["status"] == "time_limit" and r["plan_admissible"]:
            exact.reset()
            s = exact(r["case"]["z"], r["case"]["z_ref"])
            ok = s.status == "optimal" and not s.fallback
            r["opt_gap"] = (r["objective"] - s.objective) / max(1.0, abs(s.objective)) if ok else np.nan


def reference_gaps(setup: dict, recs: Sequence[dict], time_limit: float = REFERENCE_LIMIT) -> None:
    """The plans returned at the limit against the cold reference itself: each limit hit whose plan passes the
    forward pass is solved by :func:`flnotes.bench.exactness.mpc_reference` (SCIP, every step encoded on the
    reachable boxes, no lever, gap 1e-8, ``time_limit`` seconds), and ``ref_gap = (J - J_ref) / max(1, |J_ref|)``
    is written into the record (NaN when the reference proves no optimum in ``time_limit``), and ``ref_bound_gap =
    (J - J_lb) / max(1, J_lb)`` with ``J_lb`` the reference's lower bound: an upper bound on ``ref_gap`` that holds
    also when the reference stops at its limit (``J* >= J_lb`` and ``max(1, |J*|) >= max(1, J_lb)``; NaN when the
    reference returns no bound)."""
    for r in recs:
        if r["status"] == "time_limit" and r["plan_admissible"]:
            s = mpc_reference(setup, [r["case"]], time_limit)[0]
            ok = s.status == "optimal"
            r["ref_gap"] = (r["objective"] - s.objective) / max(1.0, abs(s.objective)) if ok else np.nan
            lb = float(s.bound) if s.status in ("optimal", "time_limit") and s.bound is not None else np.nan
            r["ref_bound_gap"] = (r["objective"] - lb) / max(1.0, lb) if np.isfinite(lb) else np.nan


def incumbent_quality(setup: dict, cases: Sequence[dict], time_limit: float = 30.0) -> list[dict]:
    """The first incumbent of ``repair=True`` against the proven optimum, step by step of its construction.

    For each case (``z``, ``z_ref``, ``category``) whose relaxation violates the network bound and whose program the
    MPC without a time limit (cold, ``time_limit`` seconds) proves optimal with ``J*``: the relative distance
    ``(J - J*) / max(1, |J*|)`` of the relaxation's optimum repaired along the QP
    (:func:`flnotes.mpc.fallback.qp_repair`), of that plan optimized over its linear region
    (:func:`flnotes.mpc.region.region_qp` without moves) and with the moves to neighbouring regions
    (:data:`flnotes.mpc.region.REGION_MOVES`), NaN where a plan fails the forward-pass check; and ``certified``,
    the gap ``(J - J_c) / max(1, |J|)`` of the last plan against the relaxation's optimum ``J_c``, the bound a step
    stopped at once by its time limit can certify.
    """
    from ..mpc.fallback import qp_repair
    from ..mpc.region import REGION_MOVES, region_qp

    exact = make_mpc(setup, time_limit=time_limit)
    pred, rows = exact.pred, []
    for c in cases:
        z, R = np.asarray(c["z"], float), c["z_ref"]
        f, c0 = pred.linear(z, R)
        V_c, fq, _ = pred.qp(f, z)
        if V_c is None or pred.feasible(z, V_c):
            continue
        exact.reset()
        s = exact(z, R)
        if s.status != "optimal" or s.fallback:
            continue
        J_opt = s.objective
        dist = lambda V: (pred.cost(V, f, c0) - J_opt) / max(1.0, abs(J_opt))  # noqa: E731
        _, V_r = qp_repair(pred, z, f, V_c)
        ok_r = pred.feasible(z, V_r)
        row = dict(category=c.get("category", ""), repaired=dist(V_r) if ok_r else np.nan, region=np.nan,
                   region_moves=np.nan, certified=np.nan)
        last = V_r if ok_r else None
        for key, moves in (("region", 0), ("region_moves", REGION_MOVES)):
            V_p = region_qp(pred, z, f, V_r, moves) if ok_r else None
            if V_p is not None and pred.feasible(z, V_p):
                row[key] = dist(V_p)
                if key == "region_moves":
                    last = V_p
        if last is not None:
            J = pred.cost(last, f, c0)
            row["certified"] = (J - (fq + c0)) / max(1.0, abs(J))
        rows.append(row)
    return rows


def limit_gaps(recs: Sequence[dict]) -> np.ndarray:
    """The gaps of the steps that hit the time limit (NaN where the plan is not admissible: no gap)."""
    return np.array([r["gap"] if r["plan_admissible"] else np.nan for r in recs if r["status"] == "time_limit"])


def late_by_cpu(rec: dict, t_s: float = T_S) -> bool:
    """An answer after ``t_s`` whose step also used more than ``t_s`` of CPU time: late by its own work. A late answer
    whose CPU time stayed within ``t_s`` waited for the machine (the process was not running for part of the step:
    another process had the core), which no time limit inside the process can prevent."""
    return rec["ms"] > 1e3 * t_s and rec["cpu_ms"] > 1e3 * t_s


def summarize(name: str, N: int, recs: Sequence[dict], t_s: float = T_S, **extra) -> dict:
    """One table row: answer times (wall and CPU), overrun past ``t_s`` (``over_t_s`` answers after it, of which
    ``over_t_s_cpu`` late by their own CPU time: :func:`late_by_cpu`), limit hits (``cut_offs`` of them answered at
    the cut-off while the engine ran on), gaps, admissibility."""
    wall = time_stats([r["ms"] / 1e3 for r in recs], percentiles=(50, 99))
    cpu = time_stats([r["cpu_ms"] / 1e3 for r in recs], percentiles=(50, 99))
    g = limit_gaps(recs)
    gf = g[np.isfinite(g)]
    q = (lambda p: float(np.quantile(gf, p)) if gf.size else np.nan)
    no_plan = [r for r in recs if r["status"] == "time_limit" and not r["plan_admissible"]]
    og = np.array([r["opt_gap"] for r in recs if "opt_gap" in r], float)
    opt = dict(opt_gap_max=float(np.nanmax(og)) if np.isfinite(og).any() else np.nan,
               opt_gap_over=int(np.sum(og > TARGET_GAP)), opt_undecided=int(np.sum(np.isnan(og))))
    rg = np.array([r["ref_gap"] for r in recs if "ref_gap" in r], float)
    if rg.size:  # only where reference_gaps ran
        rb = np.array([r["ref_bound_gap"] for r in recs if "ref_gap" in r], float)
        opt.update(ref_gap_max=float(np.nanmax(rg)) if np.isfinite(rg).any() else np.nan,
                   ref_gap_over=int(np.sum(rg > TARGET_GAP)), ref_undecided=int(np.sum(np.isnan(rg))),
                   ref_bound_gap_max=float(np.nanmax(rb)) if np.isfinite(rb).any() else np.nan,
                   ref_unproven=int(np.sum(~((rg <= TARGET_GAP) | (rb <= TARGET_GAP)))))
    return dict(run=name, N_p=int(N), steps=len(recs), ms_p50=wall["median_ms"], ms_p99=wall["p99_ms"],
                ms_max=wall["max_ms"], overrun_ms=max(0.0, wall["max_ms"] - 1e3 * t_s),
                over_t_s=int(sum(r["ms"] > 1e3 * t_s for r in recs)), over_t_s_cpu=int(sum(late_by_cpu(r, t_s) for r in recs)),
                cpu_ms_p50=cpu["median_ms"],
                cpu_ms_max=cpu["max_ms"], limit_hits=int(sum(r["status"] == "time_limit" for r in recs)),
                cut_offs=int(sum(r.get("cut_off", False) for r in recs)), limit_without_plan=len(no_plan),
                gap_p50=q(0.5), gap_p90=q(0.9), gap_max=q(1.0),
                fallbacks=int(sum(r["fallback"] for r in recs)),
                plans_admissible=int(sum(r["plan_admissible"] for r in recs)),
                inputs_admissible=int(sum(r["input_ok"] for r in recs)),
                inputs_flagged=int(sum(r["input_flagged"] for r in recs)),
                infeasible=int(sum(r["status"] == "infeasible" for r in recs)),
                error=int(sum(r["status"] == "error" for r in recs)), **opt, **extra)


def deadline_study(horizons: Sequence[int] = (10, 15, 20), t_final: float = 20.0, n_states: int = 60,
                   t_s: float = T_S, seed: int = 2, check_limit: float = 10.0, optimum_limit: float = 30.0,
                   reference_limit: float = 0.0) -> dict:
    """The closed loop and the diverse states at each ``N_p`` with ``time_limit = t_s``.

    The diverse states whose limit hit returned no admissible plan are solved again with ``check_limit`` seconds
    (:func:`decide_misses`; ``0`` skips it), and every limit hit with an admissible plan with ``optimum_limit``
    seconds (:func:`optimum_gaps`; ``0`` skips it): the rows' ``opt_gap_max`` is the largest distance of such a
    plan from the optimum, ``opt_gap_over`` the hits above the target 1e-4 and ``opt_undecided`` those whose
    optimum was not proven in ``optimum_limit``. With ``reference_limit > 0`` the closed loops' limit hits are also
    solved by the cold reference itself (:func:`reference_gaps`, ``reference_limit`` seconds each: 1 to 298 s per
    state at N_p = 20, :data:`REFERENCE_LIMIT`): columns ``ref_gap_max``, ``ref_gap_over`` and ``ref_undecided``,
    ``ref_bound_gap_max`` (the largest distance bound from the reference's lower bound) and ``ref_unproven`` (hits
    whose distance from the optimum the reference proves neither by its optimum nor by its bound to be at most 1e-4).

    Returns ``rows`` (:func:`summarize`, one per run), ``gaps`` (``{label: gaps at the limit}``), ``times``
    (``{label: answer times in ms}``) and ``checks``: ``plans_not_admissible`` (returned plans failing the
    forward pass), ``inputs_not_admissible`` (applied inputs exceeding ``u_max^eps`` at the measured state
    without the flag), ``u_within`` and ``u_within_between`` (true ``|u| <= u_max`` at the samples and between
    them in every closed loop, :func:`closed_loop`), ``max_overrun_ms``, ``max_ms`` and ``max_ms_cpu`` (the slowest
    answer, and the CPU time of its step), ``answers``, ``over_t_s`` and ``over_t_s_cpu`` (how many answers in all,
    after ``t_s``, and of those late by their own CPU time: :func:`late_by_cpu`), ``cut_offs`` (answers given at
    the cut-off while the engine's solve ran on: :class:`flnotes.MPC` ``cut_off``),
    ``negative_gaps`` and ``inconsistent_gaps`` (a recorded gap that does not follow from the objective and
    the bound), ``limit_without_plan`` (limit hits whose plan fails the forward pass: only its first input is
    admissible, or none exists) and, of those on diverse states, ``without_plan_infeasible`` / ``_missed`` /
    ``_undecided`` (:func:`decide_misses`).
    """
    base = quad_setup()
    rows, gaps, times = [], {}, {}
    checks = dict(plans_not_admissible=0, inputs_not_admissible=0, u_within=True, u_within_between=True,
                  max_overrun_ms=0.0, max_ms=0.0, max_ms_cpu=0.0, answers=0, over_t_s=0, over_t_s_cpu=0, cut_offs=0,
                  negative_gaps=0, inconsistent_gaps=0,
                  limit_without_plan=0, infeasible_programs=0,
                  without_plan_infeasible=0, without_plan_missed=0, without_plan_undecided=0)
    for N in horizons:
        setup = quad_setup(horizon=int(N), net=base["net"], eps=base["eps"])
        loop, ck = closed_loop(setup, t_final, t_s)
        div = diverse(setup, n_states, t_s, seed) if n_states else []
        checks["u_within"] &= ck["u_within"]
        checks["u_within_between"] &= ck["u_within_between"]
        miss = decide_misses(setup, div, check_limit) if check_limit else {}
        if optimum_limit:
            optimum_gaps(setup, loop + div, optimum_limit)
        if reference_limit:
            reference_gaps(setup, loop, reference_limit)
        for name, recs, extra in (("closed loop", loop, dict(cpu_over_wall=ck["cpu_over_wall"])),
                                  ("diverse states, cold", div, {f"without_plan_{k}": v for k, v in miss.items()})):
            if not recs:
                continue
            row = summarize(name, int(N), recs, t_s, **extra)
            checks["limit_without_plan"] += row["limit_without_plan"]
            checks["infeasible_programs"] += int(sum(r["status"] == "infeasible" and not r["plan_admissible"]
                                                     for r in recs))
            for k in ("infeasible", "missed", "undecided"):
                checks[f"without_plan_{k}"] += row.get(f"without_plan_{k}", 0)
            rows.append(row)
            label = f"N_p = {N}, {name}"
            gaps[label], times[label] = limit_gaps(recs), np.array([r["ms"] for r in recs])
            checks["plans_not_admissible"] += row["steps"] - row["plans_admissible"]
            checks["inputs_not_admissible"] += int(sum(not r["input_ok"] and not r["input_flagged"] for r in recs))
            checks["max_overrun_ms"] = max(checks["max_overrun_ms"], row["overrun_ms"])
            slowest = max(recs, key=lambda r: r["ms"])
            if slowest["ms"] > checks["max_ms"]:
                checks["max_ms"], checks["max_ms_cpu"] = slowest["ms"], slowest["cpu_ms"]
            checks["answers"] += row["steps"]
            checks["over_t_s"] += row["over_t_s"]
            checks["over_t_s_cpu"] += row["over_t_s_cpu"]
            checks["cut_offs"] += row["cut_offs"]
            for r in recs:
                if np.isfinite(r["gap"]):
                    checks["negative_gaps"] += int(r["gap"] < 0)
                    want = (r["objective"] - r["bound"]) / max(1.0, abs(r["objective"]))
                    checks["inconsistent_gaps"] += int(abs(want - r["gap"]) > 1e-9 or r["bound"] > r["objective"])
    return dict(rows=rows, gaps=gaps, times=times, checks=checks)


def deadline_numbers(study: dict) -> dict:
    """The numbers chapter 8 quotes from :func:`deadline_study`, as Python numbers: the checks on misses and
    overrun, ``loop_<column>`` of the closed loop at the longest horizon, and ``loops_<...>`` over the closed loops
    of every horizon (limit hits, plans more than 1e-4 above the optimum, the largest distance and its ``N_p``)."""
    c = study["checks"]
    py = lambda x: x.item() if hasattr(x, "item") else x  # noqa: E731 - numpy scalars to Python numbers
    out = {k: py(c[k]) for k in ("max_overrun_ms", "max_ms", "max_ms_cpu", "answers", "over_t_s", "over_t_s_cpu",
                                 "cut_offs", "limit_without_plan",
                                 "without_plan_infeasible", "without_plan_missed", "without_plan_undecided")}
    loop = [r for r in study["rows"] if r["run"] == "closed loop"][-1]
    out.update({f"loop_{k}": py(loop[k]) for k in ("N_p", "steps", "limit_hits", "gap_p50", "gap_max", "cpu_ms_max",
                                                    "opt_gap_max", "opt_gap_over", "opt_undecided")})
    loops = [r for r in study["rows"] if r["run"] == "closed loop"]  # every horizon, not the longest only
    og = np.array([r["opt_gap_max"] for r in loops], float)
    out.update(loops_limit_hits=int(sum(r["limit_hits"] for r in loops)),
               loops_opt_gap_over=int(sum(r["opt_gap_over"] for r in loops)),
               loops_opt_gap_max=float(np.nanmax(og)) if np.isfinite(og).any() else float("nan"),
               loops_opt_gap_max_N_p=int(loops[int(np.nanargmax(og))]["N_p"]) if np.isfinite(og).any() else 0)
    return out


def run(fast: bool) -> dict:
    """``make bench`` section ``deadline``: answer times and gaps at ``time_limit = t_s``."""
    from ..plots.deadline import answer_times, gap_histogram
    from . import out_dir

    horizons = (10, 20) if fast else (10, 15, 20)
    res = deadline_study(horizons, t_final=3.0 if fast else 20.0, n_states=6 if fast else 60,
                         check_limit=2.0 if fast else 10.0, reference_limit=0.0 if fast else REFERENCE_LIMIT)
    figs = []
    hits = {k: v for k, v in res["gaps"].items() if np.isfinite(v).any()}
    if hits:
        figs.append(str(gap_histogram(hits, path=out_dir() / "deadline_gaps.png")))
    figs.append(str(answer_times(res["times"], 1e3 * T_S, path=out_dir() / "deadline_times.png")))
    c = res["checks"]
    notes = [f"time_limit = t_s = {T_S} s per step, default options; closed loop: true plant, x_ref = 1.5 sin t; "
             "diverse states: flnotes.bench.exactness.mpc_cases, cold (no previous plan).",
             f"returned plans failing the forward-pass check: {c['plans_not_admissible']}: {c['limit_without_plan']} at "
             f"limit hits, {c['infeasible_programs']} on programs proven infeasible, "
             f"{c['plans_not_admissible'] - c['limit_without_plan'] - c['infeasible_programs']} otherwise; of the "
             "diverse states' limit "
             f"hits without one, {c['without_plan_infeasible']} programs are proven infeasible, "
             f"{c['without_plan_missed']} have an optimum (a plan the fallback missed) and "
             f"{c['without_plan_undecided']} are undecided by a solve with a longer limit. Applied inputs above "
             f"u_max^eps without the flag: {c['inputs_not_admissible']}; true |u| <= u_max in every closed loop: "
             f"{c['u_within']} at the samples, {c['u_within_between']} between them (no drift margin here); "
             f"negative or inconsistent gaps: {c['negative_gaps']}, {c['inconsistent_gaps']}.",
             f"answers after t_s: {c['over_t_s']} of {c['answers']}, of which {c['over_t_s_cpu']} used more than t_s of "
             "CPU time (the others waited for the machine: their process was not running for part of the step); the "
             f"slowest took {c['max_ms']:.1f} ms of wall clock and {c['max_ms_cpu']:.1f} ms of CPU time (a shared "
             "machine). A solver call need not stop at its limit: DAQP reads its clock every 32 iterations of a "
             "node's active-set solve and every 32 nodes of its branch and bound (a search of short nodes runs on by "
             "up to 32 of them), SCIP at its own pace. The controller keeps back from the engine "
             f"{100 * RESERVE_SHARE:.0f} % of t_s, or the lateness and fallback time it has measured on its own CPU "
             f"time (MPC.reserve; decaying by {RESERVE_DECAY:g} per step, cleared by reset, at most "
             f"{100 * RESERVE_MAX_SHARE:.0f} % of t_s); the fallback's repairs stop at {100 * (1 - FALLBACK_POST_SHARE):.0f} "
             "% of t_s; no solver or round starts without time left, no SCIP model is built with less than 20 ms "
             "left, and the models a step built are freed at the next step. The engine solves in a worker thread: a "
             "solve that has not returned at the cut-off (t_s less the largest of half the reserve, the longest "
             "fallback, the longest time from a cut-off to its answer and CUT_OFF_MIN_S, at most "
             f"{100 * RESERVE_MAX_SHARE:.0f} % of t_s) is "
             f"answered with its best plan so far while it runs on (MPC(cut_off=True), the default): {c['cut_offs']} "
             "answers were given so.",
             "gap = (J - J_lb) / max(1, |J|) at the steps that hit the limit: J the cost of the returned plan, J_lb the "
             "largest valid lower bound known (the QP without the network, the levels proven empty, a solver's bound).",
             "opt_gap = (J - J*) / max(1, |J*|) at the same steps, J* the optimum proven by the MPC without the step's "
             "limit (cold); opt_gap_over counts the hits above 1e-4, opt_undecided those without a proven J*."]
    if not fast:
        notes.append("ref_gap (closed loops only) = (J - J_ref) / max(1, |J_ref|) at the same steps, J_ref the optimum of "
                     "the cold reference (SCIP, every step encoded on the reachable boxes, no lever, gap 1e-8, "
                     f"{REFERENCE_LIMIT:.0f} s "
                     "per state); ref_gap_over counts the hits above 1e-4, ref_undecided those it did not prove; "
                     "ref_bound_gap = (J - J_lb) / max(1, J_lb) with J_lb the reference's lower bound bounds ref_gap "
                     "from above also when it stopped at its limit; ref_unproven counts the hits that the reference "
                     "proves within 1e-4 of the optimum neither by its optimum nor by its bound.")
    cut = cut_off_study(quad_setup(horizon=20, net=(base := quad_setup())["net"], eps=base["eps"]),
                        t_final=3.0 if fast else 10.0)
    off, on = cut
    notes.append(f"cut-off as a lever (the last two rows): the closed loop at N_p = 20 with no share of t_s kept back "
                 f"(MPC.reserve_share = 0: the reserve is only what the controller has measured), without and with "
                 f"the cut-off: {off['over_t_s']} and {on['over_t_s']} of {on['steps']} answers after t_s, slowest "
                 f"{off['ms_max']:.1f} and {on['ms_max']:.1f} ms; {on['cut_offs']} answers at the cut-off.")
    late = []
    for wl in (None, "auto"):
        for loaded in (False, True):
            late += late_answers(steps=10 if fast else 100, n_states=3 if fast else 30, loaded=loaded, work_limit=wl)
    notes += late_answers_notes(late)
    floor = budget_floor(steps=10 if fast else 100, n_states=3 if fast else 30)
    notes += budget_floor_notes(floor)
    again = [r for loaded in (False, True)
             for r in repeat_loops(runs=2 if fast else 6, loaded=loaded, t_final=1.0 if fast else None)]
    # a horizon where a cold step finds no plan within t_s: with the clock, and with a work budget
    again += [r for wl in (None, "auto") for r in repeat_loops([LONG_SYSTEM], runs=2 if fast else 6,
                                                               t_final=1.0 if fast else None, horizon=LONG_HORIZON,
                                                               work_limit=wl)]
    notes += repeat_loops_notes(again)
    first = first_incumbent_times(repeats=2 if fast else 5)
    notes.append(f"A cold step's first incumbent (the relaxation repaired along the QP, exact per step) at "
                 f"{LONG_SYSTEM}'s z(0), t_s = {1e3 * SHORT_TS:g} ms: " + "; ".join(
                     f"N_p = {r['N_p']}: {r['ms_median']:.1f} ms (max {r['ms_max']:.1f}, "
                     f"{'passes' if r['passes'] else 'fails'} the check)" for r in first)
                 + f"; a fresh controller's cut-off {first[0]['cut_off_ms']:.1f} ms after the step's start.")
    return dict(title="A guaranteed answer time (time_limit = t_s)", rows=res["rows"] + cut, notes=notes, figures=figs,
                late_answers=late, budget_floor=floor, repeat_loops=again, first_incumbent=first)


def late_answers_notes(rows: Sequence[dict]) -> list[str]:
    """The rows of :func:`late_answers` as notes, one per system, condition and time model."""
    out = ["Late answers per system (time_limit = t_s, default options; the book's two systems and the five not in "
           "it): answers after t_s on the wall clock, of them late by the step's own CPU time (> t_s) and those whose "
           "thread resumed late after the cut-off while not waiting for a core (info['wake_lag'] and "
           "info['wake_runqueue']: without that lag they were on time), of those the answers whose engine thread "
           "waited for a core for at least the overrun (info['engine_runqueue']: the interpreter lock the answer "
           "waited for was held by a thread that waited for a core), the slowest answer and the most CPU time over "
           "t_s, the longest time after the engine at a fallback step (fallback and checks, wall clock) over t_s, "
           "and the 1-minute load average at the start and the end of the system's runs. 'busy process on a core': "
           "a second process runs a plain CPU loop meanwhile (busy_core). "
           "work_limit='auto': the budgeted MPC (NODES_PER_SECOND times t_s nodes, SCIP for every mixed-integer "
           "program), whose safety-net hits are steps the wall clock decided."]
    for r in rows:
        out.append(f"{r['system']}, {r['run']}, {r['condition']}, work_limit={r['work_limit']}: {r['late_wall']} of "
                   f"{r['answers']} answers after t_s = {r['t_s_ms']:g} ms ({r['late_cpu']} late by CPU, "
                   f"{r['late_resume']} resumed late after the cut-off, {r['late_engine_queued']} of them while the "
                   f"engine's thread waited for a core, {r['late_blocked']} blocked after resuming, {r['late_faults']} "
                   f"with pages read back from disk, {r['late_steal']} while the host took the machine's CPUs); slowest "
                   f"{r['wall_max_over_ts']:.2f} t_s wall, most CPU {r['cpu_max_over_ts']:.2f} t_s; after the engine at "
                   f"a fallback at most {r['post_max_over_ts']:.2f} t_s; {r['limit_hits']} limit hits, {r['fallbacks']} "
                   f"fallbacks ({r['previous_ran_on']} without a solve: the previous solve ran on past their "
                   f"cut-off), {r['safety_net']} safety-net hits; short scheduler slice granted at {r['short_slice']} of "
                   f"{r['answers']} (fl.config.answer_slice, Linux 6.12+); load {r['load_start']:.1f} -> "
                   f"{r['load_end']:.1f}")
    return out


# ----------------------------------------------------------------------------------- late answers, idle and loaded
#: The two systems of the book and the five not in it (:data:`flnotes.studies.unseen.CASES`), in this order.
BOOK_SYSTEMS = ("Quad-1D", "MSD")


class busy_core:
    """A second process that keeps one core busy (a plain CPU loop in a subprocess) inside a ``with`` block: the
    loaded condition of :func:`late_answers`, on a two-core machine the other core."""

    def __enter__(self):
        import subprocess
        import sys

        self.proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        return self

    def __exit__(self, *exc):
        self.proc.kill()
        self.proc.wait()
        return False


def _book_mpc(name: str, time_limit: Optional[float], work_limit=None):
    """The book system's MPC at ``time_limit`` (Quad-1D: Sec. IV-B; MSD: chapter 11's setting) with its reference
    ``x_ref = 1.5 sin t`` and start."""
    from ..mpc import MPC, sine_reference
    from ..studies.compare import setting

    s = setting(name)
    mpc = MPC(s["system"], s["net"], s["eps"], horizon=s["horizon"], ts=s["ts"], Q=s["Q"], R=s["R"],
              time_limit=time_limit, work_limit=work_limit)
    z0 = np.asarray(quad_setup()["z0"] if name == "Quad-1D" else np.zeros(mpc.n_z), float)
    return mpc, sine_reference(1.5, 1.0, mpc.n_z), z0


def _system_run(name: str, steps: int, n_states: int, work_limit=None, time_limit: Optional[float] = None) -> dict:
    """One system with ``time_limit = t_s`` (or ``time_limit``): its closed loop of ``steps`` steps (true plant) and
    ``n_states`` cold states; per answer the wall and CPU time (this process's, a cut-off solve running on included)
    and the time after the engine (``post_time``: the fallback and the checks)."""
    from ..studies import unseen as U

    if name in BOOK_SYSTEMS:
        mpc, ref, z0 = _book_mpc(name, None)
        ts = mpc.ts
        mpc = mpc.clone(time_limit=ts if time_limit is None else time_limit, work_limit=work_limit)
        cases = [dict(z=c["z"], z_ref=c["z_ref"]) for c in mpc_cases(dict(quad_setup(horizon=mpc.N), N=mpc.N), n_states)] \
            if name == "Quad-1D" else _msd_cases(mpc, n_states)
    else:
        c = U.case(name)
        mpc = U.unseen_mpc(name, time_limit=c.ts if time_limit is None else time_limit, work_limit=work_limit)
        ref, z0, ts = c.reference(), np.array(c.z0), c.ts
        cases = U.diverse_cases(name, n_states)
    timed = U.TimedController(mpc)
    simulate(mpc.system, timed, t_final=steps * ts, ts=ts, z0=z0, reference=ref, progress=False)
    loop = [(s, w, c) for s, w, c in zip(mpc.history, timed.wall, timed.cpu)]
    cold = []
    for cs in cases:
        mpc.reset()
        w0, c0 = time.perf_counter(), time.process_time()
        s = mpc(cs["z"], cs["z_ref"])
        cold.append((s, time.perf_counter() - w0, time.process_time() - c0))
    return dict(ts=ts, loop=loop, cold=cold, mpc=mpc)


def _msd_cases(mpc, n: int, seed: int = 0) -> list[dict]:
    """``n`` cold MSD states: uniform in 90 % of the box, constant position references in 80 % of its range."""
    rng = np.random.default_rng(seed)
    mid, half = (mpc.z_lo + mpc.z_hi) / 2, (mpc.z_hi - mpc.z_lo) / 2
    out = []
    for _ in range(n):
        R = np.zeros((mpc.N + 1, mpc.n_z))
        R[:, 0] = mid[0] + rng.uniform(-0.8, 0.8) * half[0]
        out.append(dict(z=mid + rng.uniform(-0.9, 0.9, mpc.n_z) * half, z_ref=R))
    return out


def _resumed_late(step, wall: float, ts: float) -> bool:
    """Whether an answer after ``ts`` (``wall`` seconds) is late because its thread resumed late after the cut-off
    (``info["wake_lag"]`` at least the overrun ``wall - ts``) while not waiting for a core (``info["wake_runqueue"]``
    below half that lag, or unknown): a timer that fired late on the machine, or the interpreter lock held by the
    engine's thread in a C call, not the answer's own work."""
    lag, queued = step.info.get("wake_lag", 0.0), step.info.get("wake_runqueue", float("nan"))
    return bool(wall > ts and lag >= wall - ts and not queued >= 0.5 * lag)


def _engine_queued(step, wall: float, ts: float) -> bool:
    """Whether an answer that resumed late (:func:`_resumed_late`) had the engine's thread wait for a core for at
    least its overrun during the step (``info["engine_runqueue"]``): the interpreter lock the answer waited for was
    held by the engine's thread while that thread waited for a core (more runnable threads than cores)."""
    return bool(_resumed_late(step, wall, ts) and step.info.get("engine_runqueue", float("nan")) >= wall - ts)


def late_answers(names: Optional[Sequence[str]] = None, steps: int = 100, n_states: int = 30,
                 loaded: bool = False, work_limit=None) -> list[dict]:
    """Answers after ``t_s`` per system (the book's two and the five not in it), closed loop and cold states, with
    ``time_limit = t_s`` and default options (``work_limit`` of :class:`flnotes.MPC` when given).

    ``loaded``: the runs are made with a second process keeping a core busy (:class:`busy_core`). Per system and
    kind of run: ``answers``, ``late_wall`` (answers after ``t_s`` on the wall clock), ``late_cpu`` (of those, the
    answers whose step also used more than ``t_s`` of CPU time: late by the controller's own work; the others waited
    for the machine), ``late_resume`` (the late answers whose thread resumed late after the cut-off without waiting
    for a core, :func:`_resumed_late`: without that lag they were on time), ``late_engine_queued`` (of those, the
    answers whose engine thread waited for a core for at least the overrun, :func:`_engine_queued`: the lock held by
    a thread that waited for a core), the slowest answer and the most CPU
    time over ``t_s``, ``post_max_over_ts`` (the longest time after the engine, the fallback and the checks, over
    ``t_s``) at the fallback steps, limit hits, fallbacks,
    safety-net hits (under a work budget), ``short_slice`` (the steps whose answering thread was granted the short
    scheduler slice of :func:`flnotes.config.answer_slice`), ``previous_ran_on`` (the steps that answered without a
    solve because the previous step's solve ran on past their cut-off), ``late_blocked`` (the late answers whose
    thread, after it resumed, waited for the interpreter lock or the system for at least the overrun:
    ``info["after_wake_blocked"]``), ``late_faults`` (the late answers during which the process read pages back from
    disk: ``info["major_faults"]``), ``late_steal`` (the late answers during which the host of a virtual machine took
    its CPUs: ``info["steal_time"]``), and the load average (1 min) at the start and the end of
    the system's run.
    """
    import os
    from contextlib import nullcontext

    from ..studies import unseen as U

    rows = []
    for name in names or (*BOOK_SYSTEMS, *U.CASES):
        with busy_core() if loaded else nullcontext():
            load0 = os.getloadavg()[0]
            run = _system_run(name, steps, n_states, work_limit)
            load1 = os.getloadavg()[0]
        ts = run["ts"]
        for kind in ("loop", "cold"):
            recs = run[kind]
            wall = np.array([w for _, w, _ in recs])
            cpu = np.array([c for _, _, c in recs])
            post = [s.info.get("post_time", 0.0) for s, _, _ in recs if s.fallback]
            rows.append(dict(system=name, run="closed loop" if kind == "loop" else "cold states",
                             condition="busy process on a core" if loaded else "as found",
                             t_s_ms=1e3 * ts, answers=len(recs), late_wall=int(np.sum(wall > ts)),
                             late_cpu=int(np.sum((wall > ts) & (cpu > ts))),
                             late_resume=int(sum(_resumed_late(s, w, ts) for s, w, _ in recs)),
                             late_engine_queued=int(sum(_engine_queued(s, w, ts) for s, w, _ in recs)),
                             wall_max_over_ts=float(wall.max() / ts), cpu_max_over_ts=float(cpu.max() / ts),
                             post_max_over_ts=float(max(post) / ts) if post else 0.0,
                             limit_hits=int(sum(s.status == "time_limit" for s, _, _ in recs)),
                             fallbacks=int(sum(s.fallback for s, _, _ in recs)),
                             safety_net=int(sum(bool(s.info.get("safety_net")) for s, _, _ in recs)),
                             short_slice=int(sum(bool(s.info.get("answer_slice")) for s, _, _ in recs)),
                             previous_ran_on=int(sum(bool(s.info.get("previous_ran_on")) for s, _, _ in recs)),
                             late_blocked=int(sum(w > ts and s.info.get("after_wake_blocked", 0.0) >= w - ts
                                                  for s, w, _ in recs)),
                             late_faults=int(sum(w > ts and s.info.get("major_faults", 0.0) > 0 for s, w, _ in recs)),
                             late_steal=int(sum(w > ts and s.info.get("steal_time", 0.0) > 0 for s, w, _ in recs)),
                             work_limit=work_limit,
                             load_start=float(load0), load_end=float(load1)))
    return rows


# ----------------------------------------------------------------------------------- what a work budget cannot decide
#: The time limit of :func:`budget_floor`'s runs: a safety net that a one-node budget never reaches, so that the
#: budget alone decides every step.
FLOOR_LIMIT = 30.0


def budget_floor(names: Optional[Sequence[str]] = None, steps: int = 100, n_states: int = 30) -> list[dict]:
    """The least work a budget can ask for, against ``t_s``: why ``work_limit`` cannot decide every step in time.

    Per system (the book's two and the five not in it), the closed loop and the cold states of :func:`late_answers`
    with ``work_limit=1`` (one branch-and-bound node per step, the smallest budget) and ``time_limit =``
    :data:`FLOOR_LIMIT` (the clock never decides). Such a step still does what a budget does not cut: the node
    bounds, the incumbent search, the root node and every level-set round's first node. ``over_t_s`` counts the
    steps whose CPU time (``info["cpu_time"]``: this thread and the engine's) exceeds ``t_s``: on those, any budget
    answers after ``t_s``, so a controller that must answer within ``t_s`` lets the wall clock decide there (the
    safety net of ``work_limit``) and its answer depends on timing. ``repeat_identical`` (closed loop): the loop run
    a second time gives the same statuses and plans bit for bit, since no decision read the clock (``safety_net``
    counts the steps where it did: 0 unless a step took longer than :data:`FLOOR_LIMIT`).
    """
    from ..studies import unseen as U

    rows = []
    for name in names or (*BOOK_SYSTEMS, *U.CASES):
        run = _system_run(name, steps, n_states, work_limit=1, time_limit=FLOOR_LIMIT)
        ts, mpc = run["ts"], run["mpc"]
        again = _system_run(name, steps, 0, work_limit=1, time_limit=FLOOR_LIMIT)["loop"]
        for kind in ("loop", "cold"):
            recs = run[kind]
            cpu = np.array([s.info.get("cpu_time", c) for s, _, c in recs])
            row = dict(system=name, run="closed loop" if kind == "loop" else "cold states", t_s_ms=1e3 * ts,
                       nodes=mpc.node_limit, steps=len(recs), over_t_s=int(np.sum(cpu > ts)),
                       cpu_median_over_ts=float(np.median(cpu) / ts), cpu_max_over_ts=float(cpu.max() / ts),
                       budget_hits=int(sum(s.status == "time_limit" for s, _, _ in recs)),
                       safety_net=int(sum(bool(s.info.get("safety_net")) for s, _, _ in recs)))
            if kind == "loop":
                row["repeat_identical"] = len(again) == len(recs) and all(
                    a.status == b.status and np.array_equal(a.v_pred, b.v_pred) for (a, _, _), (b, _, _) in zip(recs, again))
            rows.append(row)
    return rows


def budget_floor_notes(rows: Sequence[dict]) -> list[str]:
    """The rows of :func:`budget_floor` as notes, one per system and kind of run."""
    out = ["What a work budget cannot decide (work_limit = 1 node, the smallest budget, time limit "
           f"{FLOOR_LIMIT:g} s so that the clock never decides): a step still computes its node bounds, its incumbent "
           "and a first node per round. over_t_s counts the steps whose CPU time exceeds t_s: there any budget answers "
           "late, so a controller held to t_s lets the clock decide (work_limit's safety net) and the answer depends on "
           "timing. repeat_identical: the loop run twice gives the same statuses and plans bit for bit."]
    for r in rows:
        rep = f"; rerun identical: {r['repeat_identical']}" if "repeat_identical" in r else ""
        out.append(f"{r['system']}, {r['run']}: {r['over_t_s']} of {r['steps']} steps over t_s = {r['t_s_ms']:g} ms "
                   f"with one node (CPU median {r['cpu_median_over_ts']:.2f} t_s, max {r['cpu_max_over_ts']:.2f} t_s); "
                   f"{r['budget_hits']} stopped by the budget, {r['safety_net']} by the clock{rep}")
    return out


# ----------------------------------------------------------------------------------- the same loop, run again
#: The sampling period and time limit of :func:`repeat_loops`: shorter than any case's own (the shortest is 50 ms).
SHORT_TS = 0.02

#: The cases :func:`repeat_loops` runs at :data:`SHORT_TS`: the two second-order systems not in the book.
REPEAT_SYSTEMS = ("Pendulum-gain", "VdP-gain")

#: A case and horizon where a cold step at :data:`SHORT_TS` finds no plan within ``t_s`` (VdP-gain at N_p = 40
#: instead of 12): its first incumbent, the relaxation repaired step by step (:func:`first_incumbent_times`), takes
#: about as long as the controller leaves its engine, so whether a run's first steps have a plan, and how well the run
#: tracks, is the machine's timing (measured idle: tracking errors 0.045 to 0.149 in 6 runs against 0.042 without
#: the limit; at N_p = 26, 30 and 34 all 6 runs alike). On a machine where the same repair took about 1.5 times as
#: long, every run at N_p = 40 lost the reference alike (1.08 against 0.042, every step at the limit, the shifted plan
#: kept as incumbent), also with the repair's QPs solved over the free inputs (its time at z(0) 15.7 -> 12.6 ms); at
#: N_p = 34 every run lost it before that change (18 of 18 at 1.08, against 0.043); after it 2 of 18 tracked (0.057,
#: 0.062), 13 ended at 1.08 and 3 elsewhere (0.35, 0.95, 1.26): the horizon where timing decides moved, it did not go
#: away. At the case's N_p = 12 every run tracked.
#: A work budget of one node does not fit in t_s there either: the clock decides (safety-net hits on nearly every
#: step).
LONG_SYSTEM, LONG_HORIZON = "VdP-gain", 40


def tracking_rms(log, reference) -> float:
    """The RMS of :func:`flnotes.studies.mpc.tracking_error` (the position against a vectorized reference) over the
    second half of a closed loop (:class:`flnotes.SimLog`): how well a run tracks once past its start."""
    from ..studies.mpc import tracking_error

    e = tracking_error(log, reference)
    return float(np.sqrt(np.mean(e[len(e) // 2:] ** 2)))


def repeat_loops(names: Sequence[str] = REPEAT_SYSTEMS, ts: float = SHORT_TS, runs: int = 6, loaded: bool = False,
                 t_final: Optional[float] = None, horizon: Optional[int] = None, work_limit=None) -> list[dict]:
    """The same closed loop run ``runs`` times with ``time_limit = ts``: does a run flip between tracking and losing
    the reference by timing alone?

    Per case (:data:`flnotes.studies.unseen.CASES`, its network, weights, horizon, start and sine reference, sampled
    at ``ts`` on the true plant for ``t_final`` seconds, the case's own by default): the loop without a time limit once
    (``rms_free``: :func:`tracking_rms`), then one controller with ``time_limit = ts`` (default options) run
    ``runs`` times through :func:`flnotes.simulate` (which resets it before each run). Per row: the spread of the
    runs' tracking errors (``rms_min``, ``rms_max``, ``rms_off_free``: the largest distance from ``rms_free``), of
    their optimal steps and limit hits, the answers after ``ts`` on the wall clock and of them those late by their
    own CPU time, the slowest answer and the most CPU time over ``ts``, ``stopped_optimizing`` (runs with no optimal
    step in their second half), and ``u_within`` (the true ``|u| <= u_max`` at every sample of every run, to
    :data:`flnotes.solvers.BOUND_TOL`). ``loaded``: the limited runs are made with a second process keeping a core
    busy (:class:`busy_core`). ``horizon`` replaces the cases' ``N_p`` and ``work_limit`` is :class:`flnotes.MPC`'s
    (the limited controller's); ``rms_runs`` lists every run's tracking error, ``safety_net`` counts the steps a
    work budget left to the clock (:func:`budget_floor`).
    """
    from contextlib import nullcontext

    from ..studies import unseen as U

    if not (isinstance(runs, (int, np.integer)) and not isinstance(runs, bool) and runs >= 1):
        raise ValueError(f"runs must be an integer >= 1, got {runs!r}")
    if not (isinstance(ts, (int, float, np.integer, np.floating)) and not isinstance(ts, bool) and np.isfinite(ts)
            and ts > 0):
        raise ValueError(f"ts must be a positive number of seconds, got {ts!r}")
    if isinstance(names, str):
        raise ValueError(f"names must be a sequence of case names, not one string: give [{names!r}]")
    cases = [U.case(name) for name in names]  # an unknown name stops here, before any loop runs
    rows = []
    for name, c in zip(names, cases):
        ref, z0, tf = c.reference(), np.array(c.z0, float), c.t_final if t_final is None else float(t_final)
        free = U.unseen_mpc(name, ts=ts, horizon=horizon)
        mpc = free.clone(time_limit=ts, work_limit=work_limit)  # a bad work_limit stops here, before the loops
        timed_free = U.TimedController(free)
        rms_free = tracking_rms(simulate(free.system, timed_free, t_final=tf, ts=ts, z0=z0, reference=ref,
                                         progress=False), ref)
        u_max = np.asarray(mpc.system.u_max, float)
        rms, optimal, hits, late, late_cpu, wall_max, cpu_max, stopped, within, net = [], [], [], 0, 0, 0.0, 0.0, 0, True, 0
        with busy_core() if loaded else nullcontext():
            for _ in range(int(runs)):
                timed = U.TimedController(mpc)
                log = simulate(mpc.system, timed, t_final=tf, ts=ts, z0=z0, reference=ref, progress=False)
                wall, cpu, st = np.array(timed.wall), np.array(timed.cpu), [s.status for s in mpc.history]
                rms.append(tracking_rms(log, ref))
                optimal.append(st.count("optimal"))
                hits.append(st.count("time_limit"))
                late += int(np.sum(wall > ts))
                late_cpu += int(np.sum((wall > ts) & (cpu > ts)))
                wall_max, cpu_max = max(wall_max, float(wall.max())), max(cpu_max, float(cpu.max()))
                stopped += "optimal" not in st[len(st) // 2:]
                net += sum(bool(s.info.get("safety_net")) for s in mpc.history)
                within &= bool(np.all(np.abs(log.u) <= u_max + BOUND_TOL))
        rows.append(dict(system=name, condition="busy process on a core" if loaded else "as found", t_s_ms=1e3 * ts,
                         N_p=mpc.N, work_limit=work_limit, runs=int(runs), steps=len(st), rms_free=rms_free,
                         free_wall_max_over_ts=max(timed_free.wall) / ts, rms_runs=rms, rms_min=min(rms),
                         rms_max=max(rms), safety_net=net,
                         rms_off_free=max(abs(e - rms_free) for e in rms), optimal_min=min(optimal),
                         optimal_max=max(optimal), limit_hits_min=min(hits), limit_hits_max=max(hits),
                         late_wall=late, late_cpu=late_cpu, wall_max_over_ts=wall_max / ts,
                         cpu_max_over_ts=cpu_max / ts, stopped_optimizing=stopped, u_within=within))
    return rows


#: Absolute slack of :func:`spread_clause`: a run whose tracking error exceeds the loop's without the limit by less
#: than this is never counted as worse (round-off, also where that error is 0).
SPREAD_ATOL = 1e-9


def spread_clause(row: dict, factor: float = 3.0) -> str:
    """The runs of a :func:`repeat_loops` row in words: how many tracked worse than ``factor`` times the loop without
    the limit (tracking error above ``max(factor * rms_free, rms_free + SPREAD_ATOL)``), with every run's error.

    The runs of a row differ only in the machine's timing (one controller, the same start and reference; ``reset()``
    before each run), so where some runs track worse and others do not, timing decided; where all do, the limit
    did. Errors must be finite numbers and there must be at least one run (``ValueError`` otherwise)."""
    free, errs = row["rms_free"], list(row["rms_runs"])
    if not errs:
        raise ValueError("the row has no runs (rms_runs is empty)")
    if not np.all(np.isfinite(np.r_[free, errs])):
        raise ValueError(f"tracking errors must be finite numbers, got rms_free={free!r}, rms_runs={errs!r}")
    worse = sum(e > max(factor * free, free + SPREAD_ATOL) for e in errs)
    each = ", ".join(f"{e:.3g}" for e in errs)
    ref = f"{factor:g} times the {free:.3g} of the loop without the limit"
    n = len(errs)
    if worse == 0:
        return (f"{'the run' if n == 1 else f'each of the {n} runs'} tracked within {ref} (tracking "
                f"error{'' if n == 1 else 's'} {each})")
    if worse == n:
        return (f"{'the run' if n == 1 else f'all {n} runs'} tracked worse than {ref} (tracking "
                f"error{'' if n == 1 else 's'} {each}): the limit decided, alike in every run")
    return (f"{worse} of {n} runs tracked worse than {ref} and the others did not (tracking errors {each}): the runs "
            "differ only in the machine's timing")


def first_incumbent_times(name: str = LONG_SYSTEM, horizons: Sequence[int] = (12, 20, 26, 30, 34, 40),
                          ts: float = SHORT_TS, repeats: int = 5) -> list[dict]:
    """How long a cold step's first incumbent takes against the time a fresh controller leaves the engine.

    At the case's start ``z(0)`` (:data:`flnotes.studies.unseen.CASES`, no previous plan, the reference at ``t = 0``)
    and each horizon: the relaxation's optimum (:meth:`flnotes.mpc.prediction.Prediction.relaxation`, with ``v(0)`` in
    its exact range when it breaks the bound there, :meth:`~flnotes.mpc.prediction.Prediction.first_range`, as the
    engine does with :data:`flnotes.mpc.engine.FIRST_RANGE` on) repaired along the QP
    (:func:`flnotes.mpc.fallback.qp_repair`, what the engine's incumbent search runs first), timed ``repeats`` times
    in this thread, the relaxations not counted (``ms_median``, ``ms_max``; CPU ``cpu_ms_median``), and the cut-off of
    a fresh controller with ``time_limit = ts`` (``cut_off_ms``: what :meth:`flnotes.MPC.step` leaves the engine
    before it answers with what it has; ``fallback_deadline_ms``: when its fallback's repairs stop, the end of the
    time in which the fallback continues a repair the cut-off stopped). ``passes``: the repaired plan passes the
    forward-pass check (then it is the step's incumbent once it is built before the cut-off). Where ``ms_max`` comes
    near ``cut_off_ms`` less the engine's set-up (a few ms), whether a cold step has a plan, and so whether a loop
    that starts cold tracks, is the machine's timing (:func:`repeat_loops`).
    """
    from ..mpc import engine as E
    from ..mpc.fallback import qp_repair
    from ..studies import unseen as U

    if not (isinstance(repeats, (int, np.integer)) and not isinstance(repeats, bool) and repeats >= 1):
        raise ValueError(f"repeats must be an integer >= 1, got {repeats!r}")
    if isinstance(horizons, (str, bytes)) or not all(
            isinstance(N, (int, np.integer)) and not isinstance(N, bool) and N >= 1 for N in horizons):
        raise ValueError(f"horizons must be a sequence of integers >= 1, got {horizons!r}")
    if not (isinstance(ts, (int, float, np.integer, np.floating)) and not isinstance(ts, bool) and np.isfinite(ts)
            and ts > 0):
        raise ValueError(f"ts must be a positive number of seconds, got {ts!r}")
    c = U.case(name)
    ref, z0 = c.reference(), np.array(c.z0, float)
    rows = []
    for N in horizons:
        free = U.unseen_mpc(name, ts=ts, horizon=int(N))
        pred = free.pred
        f, _ = pred.linear(z0, np.asarray(ref(ts * np.arange(pred.N + 1)), float))
        V_c, _, _ = pred.relaxation(f, z0)
        fr = pred.first_range(z0, pred.u_eps) if E._first_range_on() else None
        if V_c is not None and fr is not None and (np.any(V_c[: pred.m] < fr[0]) or np.any(V_c[: pred.m] > fr[1])):
            V_c, _, _ = pred.relaxation(f, z0, fr)  # v(0) breaks the bound: the engine's tighter relaxation
        if V_c is None:
            raise ValueError(f"{name} at N_p = {N}: the relaxation has no plan at z(0); choose another horizon")
        qp_repair(pred, z0, f, V_c)  # once untimed: the first call's imports and caches are no step's work
        wall, cpu = [], []
        for _ in range(int(repeats)):
            t, p = time.perf_counter(), time.thread_time()
            _, V_r = qp_repair(pred, z0, f, V_c)
            wall.append(time.perf_counter() - t)
            cpu.append(time.thread_time() - p)
        limited = free.clone(time_limit=ts)
        cut, until = limited._cut_off(0.0), limited._fallback_until(0.0)
        rows.append(dict(system=name, t_s_ms=1e3 * ts, N_p=pred.N, ms_median=1e3 * float(np.median(wall)),
                         ms_max=1e3 * max(wall), cpu_ms_median=1e3 * float(np.median(cpu)), cut_off_ms=1e3 * cut,
                         fallback_deadline_ms=1e3 * until, passes=bool(pred.feasible(z0, V_r))))
    return rows


def repeat_loops_notes(rows: Sequence[dict]) -> list[str]:
    """The rows of :func:`repeat_loops` as notes, one per case and condition."""
    out = ["The same loop run again (time_limit = t_s, default options, one controller run several times; the two "
           "second-order cases not in the book sampled faster than their own period): the spread of the runs' "
           "tracking errors (RMS of the position over the second half) against the loop without a limit, optimal "
           "steps and limit hits per run, answers after t_s, runs that stopped optimizing, true |u| <= u_max."]
    for r in rows:
        out.append(f"{r['system']}, t_s = {r['t_s_ms']:g} ms, N_p = {r['N_p']}, work_limit={r['work_limit']}, "
                   f"{r['condition']}: {r['runs']} runs of {r['steps']} steps ({r['safety_net']} safety-net hits); "
                   f"tracking error {r['rms_min']:.4g} to {r['rms_max']:.4g} (without the limit {r['rms_free']:.4g}; "
                   f"farthest run {r['rms_off_free']:.2g} from it); optimal steps {r['optimal_min']}-{r['optimal_max']}, "
                   f"limit hits {r['limit_hits_min']}-{r['limit_hits_max']}; {r['late_wall']} answers after t_s "
                   f"({r['late_cpu']} late by CPU), slowest {r['wall_max_over_ts']:.2f} t_s wall, most CPU "
                   f"{r['cpu_max_over_ts']:.2f} t_s; runs that stopped optimizing {r['stopped_optimizing']}; true "
                   f"|u| <= u_max: {r['u_within']}; the loop without the limit at most {r['free_wall_max_over_ts']:.1f} "
                   f"t_s per step; {spread_clause(r)}")
    return out


def late_clause(late: int, late_cpu: int) -> str:
    """The answers that came after the sampling period, in words that fit their counts.

    Parameters
    ----------
    late
        the answers after ``t_s`` by the wall clock.
    late_cpu
        of them, those late by their own CPU time.

    Returns
    -------
    str
        with no late answer, "none came after the sampling period"; else "N came after the sampling period, C of
        them late by their own CPU time", followed, when some were late by the wall clock only (``C < N``), by "; the
        other N - C waited for the machine: the process did not run for part of the step, which no time limit inside
        the process can prevent".
    """
    from ..tables import counted

    if late == 0:
        return "none came after the sampling period"
    out = f"{counted(late, 'came', 'came')} after the sampling period, {late_cpu} of them late by their own CPU time"
    return out + ("" if late == late_cpu else f"; the other {late - late_cpu} waited for the machine: the process did "
                  "not run for part of the step, which no time limit inside the process can prevent")


def cut_clause(cut_offs: int) -> str:
    """The answers given at the cut-off, in words that fit their count.

    Returns
    -------
    str
        with none, "No answer was given at the cut-off: every answer came from the engine itself, at a proof or at its
        own check of the time"; else "1 answer was" / "N answers were" "given at the cut-off while the engine's solve
        ran on; the others came from the engine itself, at a proof or at its own check of the time".
    """
    from ..tables import counted

    if cut_offs == 0:
        return ("No answer was given at the cut-off: every answer came from the engine itself, at a proof or at its own "
                "check of the time")
    return (f"{counted(cut_offs, 'answer was', 'answers were')} given at the cut-off while the engine's solve ran on; the "
            "others came from the engine itself, at a proof or at its own check of the time")


def deadline_clauses(numbers: dict) -> dict:
    """The clauses the benchmark report words from :func:`deadline_numbers`.

    Returns
    -------
    dict
        ``late_clause``: :func:`late_clause` of the answers after ``t_s`` and of those late by their own CPU time.
        ``loop_clause``: when the closed loop at the longest horizon hit the limit, "H of the S closed-loop steps hit
        the limit; their recorded gaps have median ... and maximum ..., and K of those plans were more than 10⁻⁴
        above the optimum", with " (the farthest by X)" when that distance is known (finite); else "none of the S
        closed-loop steps hit the limit".
        ``loops_clause``: over every horizon, when some step hit the limit, "K of the H plans returned at the limit
        were more than 10⁻⁴ above the optimum", with ", the farthest by X" when known; else "no step hit the limit,
        so no plan was returned there".
        ``cut_clause``: :func:`cut_clause` of the answers given at the cut-off.
    """
    dn = numbers
    if dn["loop_limit_hits"]:
        loop_clause = (f"{dn['loop_limit_hits']} of the {dn['loop_steps']} closed-loop steps hit the limit; their recorded "
                       f"gaps have median {dn['loop_gap_p50']:.2f} and maximum {dn['loop_gap_max']:.2f}, and "
                       f"{dn['loop_opt_gap_over']} of those plans were more than 10⁻⁴ above the optimum"
                       + (f" (the farthest by {dn['loop_opt_gap_max']:.1e})" if np.isfinite(dn["loop_opt_gap_max"]) else ""))
    else:
        loop_clause = f"none of the {dn['loop_steps']} closed-loop steps hit the limit"
    if dn["loops_limit_hits"]:
        loops_clause = (f"{dn['loops_opt_gap_over']} of the {dn['loops_limit_hits']} plans returned at the limit were "
                        "more than 10⁻⁴ above the optimum"
                        + (f", the farthest by {dn['loops_opt_gap_max']:.1e}" if np.isfinite(dn["loops_opt_gap_max"]) else ""))
    else:
        loops_clause = "no step hit the limit, so no plan was returned there"
    return dict(late_clause=late_clause(dn["over_t_s"], dn["over_t_s_cpu"]), loop_clause=loop_clause,
                loops_clause=loops_clause, cut_clause=cut_clause(dn["cut_offs"]))
