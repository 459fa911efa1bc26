"""Benchmark: the MSD's MPC (chapter "A comparative study": ``N_p = 10``, ``t_s = 0.1`` s, the (20, 20, 20) network)
on hard states, per back-end, side by side on the same programs.

Two sets of states. *Loop*: the states of closed loops of the Monte Carlo of the comparative study
(:func:`flnotes.studies.compare.draw_scenarios`, MIQP with default options and no time limit), replayed in order so
that each controller warm-starts from its own previous answer as in closed loop. *Cold*: diverse states solved
cold (:func:`cold_states`: uniform in the domain box, on its faces, with the input bound strongly active, with
random references). Each configuration (:func:`configurations`) is asked for the optimum at every state (the
default without a time limit, the one-back-end rows with :data:`ROW_LIMIT` seconds per step); a step's CPU time
(``time.process_time``, this process) and wall time are recorded with its status. The cold reference
(``backend="cvxpy-scip"``, the whole program written with :func:`flnotes.encode`, LP node bounds, solved cold by
SCIP, :data:`REFERENCE_LIMIT` seconds per state) gives the gap of the optima at the :data:`REFERENCE_STATES` states of
each set where the default took longest. The SCIP settings for the mixed-integer QPs (:data:`SCIP_SETTINGS`: the
objective's formulation, presolving rounds, restarts) are then compared side by side on the cold states where the
default took longest and on the loop (:func:`scip_settings_runs`, :func:`scip_settings_table`). Speed is measured here, never
asserted in tests; the machine may be shared, so single timings are noisy (CPU time less so).
"""
from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator, Optional, Sequence

import numpy as np

from ..mpc import MPC
from ..mpc import engine as _engine
from ..solvers import available_backends
from ..studies import compare as C
from ..tables import time_stats

Array = np.ndarray

#: Seconds the cold reference gets per state (a state it does not prove within them has no gap).
REFERENCE_LIMIT = 120.0

#: States of each set solved by the cold reference: those where the default took the most CPU time (the reference
#: takes up to minutes per state on these programs).
REFERENCE_STATES = 10

#: Seconds per step given to the side-by-side rows (one back-end for every program): a row whose solver takes minutes on
#: some program still ends; a step stopped there counts as ``time_limit`` (never as optimal). The default rows have none.
ROW_LIMIT = 30.0

#: Cold states of the side-by-side table of SCIP settings (:func:`scip_settings_runs`): those where the default took
#: the most CPU time.
SCIP_COLD_STATES = 8

#: The kinds of :func:`cold_states`.
COLD_KINDS = ("uniform", "face", "active", "reference")


def setting() -> dict:
    """Chapter 11's MSD setting, no time limit (:func:`flnotes.studies.compare.setting`)."""
    return C.setting("MSD", time_limit=None)


def controller(s: dict, **options) -> MPC:
    """The MIQP of setting ``s`` with the given :class:`flnotes.MPCOptions` fields (none: the default)."""
    return MPC(s["system"], s["net"], s["eps"], horizon=s["horizon"], ts=s["ts"], Q=s["Q"], R=s["R"], **options)


def loop_states(s: dict, n_scenarios: int, t_final: float, seed: int = 0) -> list[list[tuple[Array, Array]]]:
    """The states ``(z, z_ref)`` of the Monte Carlo's closed loops with the default MIQP, one list per scenario."""
    out = []
    for sc in C.draw_scenarios(s["name"], n_scenarios, seed):
        log = C.run_methods(s, sc["z0"], C.scenario_reference(s["system"], sc), t_final, methods=("network",))["network"]
        out.append([(np.asarray(z, float), np.asarray(C.step_field(st, "z_ref"), float))
                    for z, st in zip(log.z[:-1], log.steps)])
    return out


def cold_states(s: dict, n: int, seed: int = 1) -> list[tuple[str, Array, Array]]:
    """``n`` diverse states ``(kind, z, z_ref)``, the kinds of :data:`COLD_KINDS` in turn.

    ``"uniform"``: ``z`` uniform in the domain box, reference zero; ``"face"``: one coordinate on a face of the box;
    ``"active"``: ``z`` uniform, a constant reference at the far side of the box (``-0.9 sign(z_1)`` times the box),
    so that the input bound is active over the horizon; ``"reference"``: ``z`` uniform and the sine reference of a
    Monte Carlo scenario, at a random time.
    """
    rng = np.random.default_rng(seed)
    sysm, N, ts = s["system"], s["horizon"], s["ts"]
    lo, hi = sysm.lo[: sysm.n_z], sysm.hi[: sysm.n_z]
    scen = C.draw_scenarios(s["name"], max(1, n), seed + 1)
    out = []
    for i in range(n):
        kind = COLD_KINDS[i % len(COLD_KINDS)]
        z = rng.uniform(lo, hi)
        R = np.zeros((N + 1, sysm.n_z))
        if kind == "face":
            j = rng.integers(sysm.n_z)
            z[j] = hi[j] if rng.random() < 0.5 else lo[j]
        elif kind == "active":
            target = np.zeros(sysm.n_z)
            target[0] = -0.9 * np.sign(z[0] if z[0] != 0 else 1.0) * (hi[0] if z[0] < 0 else -lo[0])
            R[:] = target
        elif kind == "reference":
            t = rng.uniform(0, 10)
            R = np.asarray(C.scenario_reference(sysm, scen[i])(t + ts * np.arange(N + 1)), float)
        out.append((kind, z, R))
    return out


def timed(ctrl: MPC, z: Array, R: Array) -> tuple[object, float, float]:
    """One step: ``(StepResult, CPU s of this process, wall s)``."""
    c0, t0 = time.process_time(), time.perf_counter()
    res = ctrl(z, R)
    return res, time.process_time() - c0, time.perf_counter() - t0


def replay(ctrl: MPC, groups: Sequence[Sequence[tuple[Array, Array]]]) -> list[dict]:
    """Every state of every group, in order, the controller reset at the start of each group (warm start within)."""
    out = []
    for g in groups:
        ctrl.reset()
        for z, R in g:
            res, cpu, wall = timed(ctrl, z, R)
            out.append(dict(status=res.status, objective=float(res.objective) if res.v is not None else np.nan,
                            cpu=cpu, wall=wall, backend=res.backend, n_bin=res.n_binaries, nodes=res.nodes,
                            scip=int(res.info.get("scip_programs", 0))))
    return out


#: Rows that differ from the default by a constant of the engine, not by an option: name -> ``{constant: value}``
#: (set in :mod:`flnotes.mpc.engine` while the row runs, :func:`engine_constants`).
ENGINE_CONSTANTS = {"default without the near steps": {"NEAR_ACTIVE": None},
                    "default without step 0's range": {"FIRST_RANGE": False}}


@contextmanager
def engine_constants(name: str) -> Iterator[None]:
    """The engine's constants of row ``name`` (:data:`ENGINE_CONSTANTS`; none for the other rows) while it runs."""
    new = ENGINE_CONSTANTS.get(name, {})
    saved = {k: getattr(_engine, k) for k in new}
    try:
        for k, v in new.items():
            setattr(_engine, k, v)
        yield
    finally:
        for k, v in saved.items():
            setattr(_engine, k, v)


def configurations() -> list[tuple[str, dict]]:
    """The rows: the default; the default without constraint generation (every needed step encoded at once: measured
    on hard MSD states, fewer rounds on cold states, more work along the loop, where the warm start and the steps active
    at the previous solve seed the rounds); the default without the steps near the bound in the first round of
    constraint generation (:data:`flnotes.mpc.engine.NEAR_ACTIVE` ``= None``, :data:`ENGINE_CONSTANTS`); the default
    with step 0 encoded by its neurons instead of its exact range of inputs (:data:`flnotes.mpc.engine.FIRST_RANGE`
    ``= False``); the default
    without the network's affine enclosure in its relaxation
    (``enclosure=False``: the QP without the network, as before the enclosure); the default without the shipped bound
    atlas (``atlas=False``: LP node bounds solved at each step, :mod:`flnotes.atlas`); then one back-end for every program
    (SCIP, DAQP, and Gurobi/CPLEX when importable), these with :data:`ROW_LIMIT` seconds per step.

    HiGHS solves MILPs and convex QPs, not the mixed-integer QP of eq. (MPC_form_miqp): it has no row of its own
    (the engine uses it for its LP bounds and QPs in every row).
    """
    one = lambda b: dict(backend=b, time_limit=ROW_LIMIT, cut_off=False)  # noqa: E731
    rows = [("default (auto)", {}), ("default, lazy=False", dict(lazy=False)), ("default without the near steps", {}),
            ("default without step 0's range", {}),
            ("default without the affine enclosure", dict(enclosure=False)),
            ("default without the bound atlas", dict(atlas=False)), ("SCIP only", one("scip")),
            ("DAQP only", one("daqp"))]
    have = available_backends()
    rows += [(f"{b.upper()} only", one(b)) for b in ("gurobi", "cplex") if b in have]
    return rows


#: The SCIP settings for the mixed-integer QPs compared side by side (:func:`scip_settings_runs`): name -> the
#: ``solver_options["scip"]`` of :class:`flnotes.MPC` (:class:`flnotes.solvers.ScipSolver`'s options). The first is
#: the profile before the current lean one (one presolving round with probing, SCIP's restarts), spelled out, the
#: base of every speed-up; the second the lean profile spelled out, so that both stay what they are whatever the
#: default; each other one spells out its presolving rounds, restarts and probing too; the last is the back-end's
#: default (:data:`flnotes.solvers.scip.LEAN_PRESOLVE_ROUNDS`, :data:`flnotes.solvers.scip.LEAN_RESTARTS`,
#: :data:`flnotes.solvers.scip.LEAN_PROBING_ROUNDS`; today the same settings as the second, so the pair is also a
#: same-work check of the table's spread).
SCIP_SETTINGS = {
    "separable, presolve 1, restarts, probing (before)": dict(
        objective="separable", miqp_params="lean", params={"presolving/maxrounds": 1, "presolving/maxrestarts": -1,
                                                           "propagating/probing/maxprerounds": -1}),
    "separable, presolve 1, no restarts, no probing (lean)": dict(
        objective="separable", miqp_params="lean", params={"presolving/maxrounds": 1, "presolving/maxrestarts": 0,
                                                           "propagating/probing/maxprerounds": 0}),
    "separable, presolve 1, no restarts, probing": dict(
        objective="separable", params={"presolving/maxrounds": 1, "presolving/maxrestarts": 0,
                                       "propagating/probing/maxprerounds": -1}),
    "separable, no presolve, no restarts": dict(
        objective="separable", params={"presolving/maxrounds": 0, "presolving/maxrestarts": 0,
                                       "propagating/probing/maxprerounds": 0}),
    "epigraph, presolve 1, no restarts, no probing": dict(
        objective="epigraph", params={"presolving/maxrounds": 1, "presolving/maxrestarts": 0,
                                      "propagating/probing/maxprerounds": 0}),
    "default (separable, presolve 1, no restarts, no probing)": {},
}


#: Largest relative difference ``|J - J_before| / max(1, |J_before|)`` of two optima that counts as the same optimum
#: in :func:`scip_settings_table` (the solves ask for a relative gap of 1e-6).
SAME_OPTIMUM = 1e-6


def scip_settings_runs(make, groups: Sequence[Sequence[tuple[Array, Array]]], settings: Optional[dict] = None,
                       passes: int = 2) -> dict:
    """Every SCIP setting of ``settings`` (default :data:`SCIP_SETTINGS`) on the same states, side by side.

    ``make(scip_options)`` returns a fresh :class:`flnotes.MPC` with those SCIP options. In each of ``passes`` passes
    every setting gets a new controller; the states of ``groups`` are solved in order (each controller reset at the
    start of a group, warm-started within it), every state by every setting before the next state, in the order of
    ``settings`` at one state and in the reverse order at the next (and the other way round in the next pass), so
    that the machine's load and the caches hit all alike. Returns name -> one list of records per pass (per state:
    ``status``, ``objective``, ``cpu`` and ``wall`` s of the whole step, ``scip``: the programs handed to SCIP,
    ``n_bin``: the binaries of the step's last program).
    """
    settings = SCIP_SETTINGS if settings is None else settings
    if not settings or isinstance(passes, bool) or int(passes) != passes or passes < 1:
        raise ValueError(f"scip_settings_runs needs at least one setting and passes >= 1 (an integer), got "
                         f"{len(settings)} settings and passes={passes!r}")
    names = list(settings)
    out: dict = {k: [] for k in names}
    for p in range(int(passes)):
        ctrls = {k: make(dict(v)) for k, v in settings.items()}
        recs: dict = {k: [] for k in names}
        i = 0
        for g in groups:
            for c in ctrls.values():
                c.reset()
            for z, R in g:
                for k in (names if (i + p) % 2 == 0 else names[::-1]):
                    res, cpu, wall = timed(ctrls[k], z, R)
                    recs[k].append(dict(status=res.status, objective=float(res.objective) if res.v is not None
                                        else np.nan, cpu=cpu, wall=wall, scip=int(res.info.get("scip_programs", 0)),
                                        n_bin=int(res.n_binaries)))
                i += 1
        for k in names:
            out[k].append(recs[k])
    return out


def _ratios(before: Sequence[dict], after: Sequence[dict], scip_only: bool = True) -> np.ndarray:
    """Per state ``cpu before / cpu after`` (the speed-up), over the states where either handed a program to SCIP
    (``scip_only``) or all."""
    return np.array([b["cpu"] / max(a["cpu"], 1e-9) for b, a in zip(before, after)
                     if not scip_only or b["scip"] or a["scip"]], float)


def scip_settings_table(runs: dict, states: str) -> list[dict]:
    """The rows of :func:`scip_settings_runs`: per setting and pass, CPU time per step (median, max, in all), the
    steps that handed a program to SCIP, the per-state speed-up against the first setting of the same pass on those
    steps (``cpu before / cpu``: median, min, max) and whether every optimum is the same (every status the same and
    the objectives within :data:`SAME_OPTIMUM`, relative). Then, per setting, a ``run to run`` row: the per-state
    ratio of its two passes (``cpu pass 1 / cpu pass 2``), the spread a speed-up must exceed to mean anything."""
    names = list(runs)
    base = runs[names[0]]
    rows = []
    for k in names:
        for p, recs in enumerate(runs[k]):
            b = base[p]
            sp_ = _ratios(b, recs)
            cpu = np.array([r["cpu"] for r in recs], float)
            diff = [abs(r["objective"] - q["objective"]) / max(1.0, abs(q["objective"])) for r, q in zip(recs, b)
                    if r["status"] == q["status"] == "optimal"]
            same = all(r["status"] == q["status"] for r, q in zip(recs, b)) and max(diff, default=0.0) <= SAME_OPTIMUM
            rows.append({"states": states, "setting": k, "pass": str(p + 1), "n": len(recs),
                         "scip_steps": int(sum(bool(r["scip"]) for r in recs)),
                         "cpu_median_ms": 1e3 * float(np.median(cpu)) if cpu.size else np.nan,
                         "cpu_max_ms": 1e3 * float(cpu.max()) if cpu.size else np.nan,
                         "cpu_total_s": float(cpu.sum()),
                         "speedup_median": float(np.median(sp_)) if sp_.size else np.nan,
                         "speedup_min": float(sp_.min()) if sp_.size else np.nan,
                         "speedup_max": float(sp_.max()) if sp_.size else np.nan,
                         "same_optimum": "yes" if same else "NO", "max_rel_diff": float(max(diff, default=0.0))})
    for k in names:
        if len(runs[k]) >= 2:
            r12 = _ratios(runs[k][0], runs[k][1])
            cpu = [r["cpu"] for r in runs[k][1]]
            rows.append({"states": states, "setting": k, "pass": "run to run (1 / 2)", "n": len(cpu),
                         "scip_steps": int(sum(bool(r["scip"]) for r in runs[k][1])),
                         "cpu_median_ms": np.nan, "cpu_max_ms": np.nan,
                         "cpu_total_s": float(sum(r["cpu"] for r in runs[k][0]) / max(sum(cpu), 1e-9)),
                         "speedup_median": float(np.median(r12)) if r12.size else np.nan,
                         "speedup_min": float(r12.min()) if r12.size else np.nan,
                         "speedup_max": float(r12.max()) if r12.size else np.nan,
                         "same_optimum": "", "max_rel_diff": np.nan})
    return rows


def summarize(name: str, states: str, recs: list[dict], ref: Optional[list], ts: float) -> dict:
    """One table row: CPU and wall time statistics, steps over ``ts``, statuses and the largest gap to ``ref``."""
    cpu, wall = time_stats([r["cpu"] for r in recs], (50, 99)), time_stats([r["wall"] for r in recs], (50, 99))
    statuses = {}
    for r in recs:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    gaps = [abs(r["objective"] - J) / max(1.0, abs(J)) for r, J in zip(recs, ref or [])
            if J is not None and np.isfinite(J) and r["status"] == "optimal"]
    return {"configuration": name, "states": states, "n": len(recs),
            "cpu_median_ms": cpu["median_ms"], "cpu_p99_ms": cpu["p99_ms"], "cpu_max_ms": cpu["max_ms"],
            "wall_median_ms": wall["median_ms"], "wall_p99_ms": wall["p99_ms"], "wall_max_ms": wall["max_ms"],
            "cpu_over_ts": int(sum(r["cpu"] > ts for r in recs)), "wall_over_ts": int(sum(r["wall"] > ts for r in recs)),
            "statuses": ", ".join(f"{k} {v}" for k, v in sorted(statuses.items())),
            "max_gap_ref": float(max(gaps)) if gaps else np.nan, "compared": len(gaps)}


def reference_optima(s: dict, flat: Sequence[tuple[Array, Array]], limit: float = REFERENCE_LIMIT) -> list:
    """The cold reference's optimum at each state (``None`` where it did not prove one within ``limit`` s)."""
    ref = controller(s, backend="cvxpy-scip", bounds="lp", time_limit=limit, gap=1e-9)
    out = []
    for z, R in flat:
        ref.reset()
        res = ref(z, R)
        out.append(float(res.objective) if res.status == "optimal" and res.v is not None else None)
    return out


def hardest(recs: list[dict], n: int) -> list[int]:
    """Indices of the ``n`` steps of ``recs`` that took the most CPU time."""
    return sorted(np.argsort([-r["cpu"] for r in recs], kind="stable")[:n].tolist())


def run(fast: bool) -> dict:
    """``run(fast) -> {"title", "rows", "notes", "figures"}`` of the ``msd_realtime`` section."""
    s = setting()
    n_sc, t_final, n_cold, n_ref, limit = (1, 0.5, 4, 2, 20.0) if fast else (5, 3.0, 100, REFERENCE_STATES,
                                                                          REFERENCE_LIMIT)
    loops = loop_states(s, n_sc, t_final)
    cold = cold_states(s, n_cold)
    sets = {"loop": loops, "cold": [[(z, R)] for _, z, R in cold]}
    recs = {}
    for name, opts in configurations():
        with engine_constants(name):
            recs[name] = {k: replay(controller(s, **opts), g) for k, g in sets.items()}
    refs, n_proven = {}, {}
    for k, g in sets.items():  # the cold reference at the states the default found hardest (fast mode: quickest)
        flat = [x for grp in g for x in grp]
        cpu = [r["cpu"] for r in recs["default (auto)"][k]]
        pick = sorted(np.argsort(cpu if fast else np.negative(cpu), kind="stable")[:n_ref].tolist())  # fast: quickest
        opt = reference_optima(s, [flat[i] for i in pick], limit)
        refs[k] = [None] * len(flat)
        for i, J in zip(pick, opt):
            refs[k][i] = J
        n_proven[k] = (sum(J is not None for J in opt), len(pick))
    rows = [summarize(name, k, recs[name][k], refs[k], s["ts"]) for name, _ in configurations() for k in sets]
    # SCIP's settings for the mixed-integer QPs side by side: the cold states where the default took longest (fast
    # mode: the quickest one that reached SCIP) and the loop (full mode only)
    cold_recs = recs["default (auto)"]["cold"]
    if fast:
        pool = [i for i, r in enumerate(cold_recs) if r["scip"]] or list(range(len(cold_recs)))
        pick = [min(pool, key=lambda i: cold_recs[i]["cpu"])]
    else:
        pick = hardest(cold_recs, SCIP_COLD_STATES)
    make = lambda o: controller(s, solver_options={"scip": o})  # noqa: E731
    flat_cold = [x for grp in sets["cold"] for x in grp]
    scip_sets = {f"cold, {len(pick)} hardest": [[flat_cold[i]] for i in pick]} if not fast else {
        "cold, 1 state": [[flat_cold[i]] for i in pick]}
    if not fast:
        scip_sets["loop"] = loops
    for k, g in scip_sets.items():
        rows += [{"configuration": f"SCIP setting: {r.pop('setting')}", **r}
                 for r in scip_settings_table(scip_settings_runs(make, g), k)]
    notes = [f"MSD, N_p = {s['horizon']}, t_s = {s['ts']} s, Q = diag(10, 1), R = 0.01, eps = {s['eps']:.4f}, the "
             f"shipped (20, 20, 20) network; loop: {n_sc} Monte Carlo scenarios x {t_final} s in closed loop with the "
             f"default MIQP ({len(recs['default (auto)']['loop'])} states), replayed in order (warm start); cold: "
             f"{n_cold} states ({', '.join(COLD_KINDS)}), reset before each; no time limit for the two default rows, "
             f"{ROW_LIMIT:g} s per step for the one-back-end rows.",
             "cpu: time.process_time of the step (this process); wall: time.perf_counter; over_ts: steps longer than "
             "t_s. max_gap_ref: largest |J - J_ref| / max(1, |J_ref|) over the optimal steps compared with the cold "
             f"reference (cvxpy-scip, LP node bounds, gap 1e-9, {limit:g} s per state), run at the {n_ref} states of "
             f"each set where the default took the {'least' if fast else 'most'} CPU time; it proved "
             + ", ".join(f"{p} of {n} {k} states" for k, (p, n) in n_proven.items()) + ".",
             "HiGHS solves no mixed-integer QP: no row of its own (the engine uses it for LP bounds and QPs).",
             "SCIP setting rows: the default MIQP with each SCIP setting of SCIP_SETTINGS (solver_options['scip']) on "
             "the same states, interleaved state by state (the order reversed at every other state and in the second "
             "pass), two passes with fresh controllers; cpu: whole step; scip_steps: steps that handed a program to "
             "SCIP; speedup: per state, cpu of the first setting (the profile before the lean one, spelled out) / "
             "cpu of the row's, same pass, "
             "over the scip steps (median, min, max); same_optimum: every status the same and every objective within "
             f"{SAME_OPTIMUM:g} (relative) of the first setting's; run to run: per-state cpu of pass 1 / pass 2 of the "
             "same setting, the spread a speed-up must exceed (its cpu_total_s column: the ratio of the totals)."]
    return dict(title="MSD real time: per-step time of the MIQP on hard states, per back-end", rows=rows, notes=notes,
                figures=[])


def enclosure_rows(s: dict, states: Sequence[tuple[str, Array, Array]]) -> list[dict]:
    """The default engine with and without the network's affine enclosure (``enclosure=False``) at each cold state
    ``(kind, z, z_ref)``: the relaxation's optimum ``J_c`` without and with the slab, the MIQP's optimum, the
    binaries of the last program and the CPU time (s) of each; ``same optimum``: both optimal and within 1e-6."""
    with_enc, without = controller(s), controller(s, enclosure=False)
    rows = []
    for kind, z, R in states:
        f, c0 = without.pred.linear(z, R)
        J_box = without.pred.relaxation(f, z)[1] + c0
        J_slab = with_enc.pred.relaxation(f, z)[1] + c0
        without.reset()
        a, cpu_a, _ = timed(without, z, R)
        with_enc.reset()
        b, cpu_b, _ = timed(with_enc, z, R)
        same = a.status == b.status == "optimal" and abs(a.objective - b.objective) <= SAME_OPTIMUM * max(
            1.0, abs(a.objective))
        rows.append({"state": kind, "J_c (boxes)": J_box, "J_c (slab)": J_slab,
                     "J_opt": a.objective if a.status == "optimal" else np.nan,
                     "binaries without": a.n_binaries, "binaries with": b.n_binaries,
                     "cpu s without": cpu_a, "cpu s with": cpu_b, "same optimum": same})
    return rows


def atlas_rows(s: dict, states: Sequence[tuple[str, Array, Array]]) -> list[dict]:
    """The default engine with and without the bound atlas (``atlas=False``: the LP node bounds solved at each step)
    at each cold state ``(kind, z, z_ref)``, in alternating order: the binaries of the last program and the CPU time
    (s) of each; ``same optimum``: both of the same status and, when optimal, within 1e-6."""
    with_atlas, without = controller(s), controller(s, atlas=False)
    if with_atlas.atlas is None:
        raise ValueError("no shipped atlas serves this setting's network (flnotes.atlas.SHIPPED)")
    rows = []
    for i, (kind, z, R) in enumerate(states):
        out = {}
        for name, ctrl in (("without", without), ("with", with_atlas))[:: 1 if i % 2 == 0 else -1]:
            ctrl.reset()
            out[name] = timed(ctrl, z, R)[:2]
        (a, cpu_a), (b, cpu_b) = out["without"], out["with"]
        same = a.status == b.status and (a.status != "optimal" or abs(a.objective - b.objective) <= SAME_OPTIMUM * max(
            1.0, abs(a.objective)))
        rows.append({"state": kind, "status": a.status, "binaries without": a.n_binaries,
                     "binaries with": b.n_binaries, "cpu s without": cpu_a, "cpu s with": cpu_b, "same optimum": same})
    return rows


def without_rows(s: dict, states: Sequence[tuple[str, Array, Array]], row: str) -> list[dict]:
    """The default engine with and without the engine constants of ``row`` (a row of :data:`ENGINE_CONSTANTS`) at each
    cold state ``(kind, z, z_ref)``, in alternating order: the programs solved (``StepResult.rounds``), the binaries
    of the last program (``StepResult.n_binaries``) and the CPU time (s) of each; ``same optimum``: both of the same
    status and, when optimal, within :data:`SAME_OPTIMUM`."""
    if row not in ENGINE_CONSTANTS:
        raise ValueError(f"row must be one of {sorted(ENGINE_CONSTANTS)}, got {row!r}")
    with_it, without = controller(s), controller(s)
    rows = []
    for i, (kind, z, R) in enumerate(states):
        out = {}
        for name, ctrl in (("without", without), ("with", with_it))[:: 1 if i % 2 == 0 else -1]:
            ctrl.reset()
            with engine_constants(row if name == "without" else "default (auto)"):
                out[name] = timed(ctrl, z, R)[:2]
        (a, cpu_a), (b, cpu_b) = out["without"], out["with"]
        same = a.status == b.status and (a.status != "optimal" or abs(a.objective - b.objective) <= SAME_OPTIMUM * max(
            1.0, abs(a.objective)))
        rows.append({"state": kind, "status": a.status, "programs without": a.rounds, "programs with": b.rounds,
                     "binaries without": a.n_binaries, "binaries with": b.n_binaries,
                     "cpu s without": cpu_a, "cpu s with": cpu_b, "same optimum": same})
    return rows


def near_rows(s: dict, states: Sequence[tuple[str, Array, Array]]) -> list[dict]:
    """The default engine with and without the steps near the bound in its first program
    (:data:`flnotes.mpc.engine.NEAR_ACTIVE`, ``None`` for the row without): :func:`without_rows`."""
    return without_rows(s, states, "default without the near steps")


def first_range_rows(s: dict, states: Sequence[tuple[str, Array, Array]]) -> list[dict]:
    """The default engine with and without step 0 written as its exact range of inputs
    (:data:`flnotes.mpc.engine.FIRST_RANGE`, ``False`` for the row without): :func:`without_rows`."""
    return without_rows(s, states, "default without step 0's range")
