"""Randomized exactness harness: every back-end and lever against a cold reference, on diverse states.

The closed-loop benchmarks replay states of one run of the book's loop; a solver
that is wrong elsewhere in the box goes unnoticed there. Here the states are
drawn all over the domain box, in categories chosen to reach the corners of the
programs:

* ``"uniform"``: uniform in the state box;
* ``"edge"``: one coordinate at a face of the box;
* ``"active"``: states where the network constraint is strongly active (MPC:
  far from the reference, so that the unconstrained plan wants large inputs;
  CLF-CBF: large ``|z|``, where the CLF's preferred input is large);
* ``"near limit"``: a coordinate within 2 % of the box's face;
* MPC only: a random sine or step reference instead of a constant one, and a
  previous plan (the reference's optimum at a nearby state, shifted) as warm
  start.

Every program is compared with the cold reference (SCIP, every step encoded,
gap 1e-8; for the single-input CLF-CBF program also the exact 1-D method) and
each result is classified:

* **wrong optimum**: status ``"optimal"`` but the objective is above the
  reference's by more than ``1e-6`` relative (or below it: then the reference is
  wrong, which is also reported);
* **false infeasibility**: status ``"infeasible"`` where the reference found a
  plan;
* **bound excess**: ``max(|Phi_NN| - u_max^eps, 0)`` of the applied input
  (forward pass), which the tolerance policy makes 0 up to round-off; a
  fallback's least-violation input (no admissible ``v`` exists) is flagged by
  the controller and counted apart (``flagged_violations``);
* the time per program (median, p90, p99, max).

:func:`run` is the ``make bench`` section; tests use the same functions on a
smaller seeded subset.
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np

from .. import paper
from ..tables import time_stats

REL_TOL = 1e-6  # relative objective difference that counts as a wrong optimum

MPC_CATEGORIES = ("uniform", "edge", "active", "near limit", "sine reference", "step reference")
CLF_CATEGORIES = ("uniform", "edge", "active", "near limit")


# ----------------------------------------------------------------------------------- states
def _edge(rng, lo, hi, n, inset=0.0):
    Z = rng.uniform(lo, hi, (n, lo.size))
    i = rng.integers(0, lo.size, n)
    side = rng.integers(0, 2, n)
    span = hi - lo
    Z[np.arange(n), i] = np.where(side == 1, hi[i] - inset * span[i], lo[i] + inset * span[i])
    return Z


def mpc_cases(setup: dict, n: int, seed: int = 0) -> list[dict]:
    """``n`` diverse MPC programs: dicts with ``z``, ``z_ref`` (N_p + 1, n_z), ``category``.

    The categories cycle through :data:`MPC_CATEGORIES`. The reference's position
    ``x_ref`` is uniform in ``[-4.5, 4.5]``, its derivatives zero, except for the sine
    references (random amplitude, frequency and phase, consistent derivatives) and the
    step references (a step of the position at a random predicted step).
    """
    from ..mpc import sine_reference

    rng = np.random.default_rng(seed)
    s = setup["system"]
    nz, N, ts = s.n_z, setup["N"], setup["ts"]
    lo, hi = s.lo[:nz], s.hi[:nz]
    out = []
    for j in range(n):
        cat = MPC_CATEGORIES[j % len(MPC_CATEGORIES)]
        R = np.zeros((N + 1, nz))
        R[:, 0] = rng.uniform(-4.5, 4.5)
        if cat == "uniform" or cat.endswith("reference"):
            z = rng.uniform(lo, hi)
        elif cat == "edge":
            z = _edge(rng, lo, hi, 1)[0]
        elif cat == "near limit":
            z = _edge(rng, lo, hi, 1, inset=rng.uniform(0.0, 0.02))[0]
        else:  # active: far from the reference, moving away from it
            z = rng.uniform(lo, hi)
            z[0] = -np.sign(R[0, 0]) * rng.uniform(2.0, 5.0)
            z[1] = -np.sign(R[0, 0]) * rng.uniform(0.0, 3.0)
        if cat == "sine reference":
            ref = sine_reference(rng.uniform(0.5, 2.0), rng.uniform(0.5, 1.5), nz, rng.uniform(0, 2 * np.pi))
            R = ref(rng.uniform(0, 10) + ts * np.arange(N + 1))
        elif cat == "step reference":
            k = int(rng.integers(0, N + 1))
            R[k:, 0] = rng.uniform(-4.5, 4.5)
        out.append(dict(z=z, z_ref=R, category=cat))
    return out


def clf_states(system, n: int, seed: int = 0) -> list[tuple[np.ndarray, str]]:
    """``n`` diverse CLF-CBF states ``(z, category)`` in the domain box, categories of :data:`CLF_CATEGORIES`."""
    rng = np.random.default_rng(seed)
    nz = system.n_z
    lo, hi = system.lo[:nz], system.hi[:nz]
    out = []
    for j in range(n):
        cat = CLF_CATEGORIES[j % len(CLF_CATEGORIES)]
        if cat == "uniform":
            z = rng.uniform(lo, hi)
        elif cat == "edge":
            z = _edge(rng, lo, hi, 1)[0]
        elif cat == "near limit":
            z = _edge(rng, lo, hi, 1, inset=rng.uniform(0.0, 0.02))[0]
        else:  # large |z|: the CLF asks for a large input
            z = rng.uniform(0.5, 1.0, nz) * np.where(rng.integers(0, 2, nz) == 1, hi, lo)
        out.append((z, cat))
    return out


# ----------------------------------------------------------------------------------- statistics
def classify(status: str, objective: float, ref_status: str, ref_objective: float, excess: float) -> dict:
    """One comparison with the reference (see the module docstring)."""
    feas_ref = ref_status in ("optimal",) and np.isfinite(ref_objective)
    rel = np.nan
    if status == "optimal" and feas_ref and np.isfinite(objective):
        rel = (objective - ref_objective) / max(1.0, abs(ref_objective))
    return dict(wrong_optimum=bool(np.isfinite(rel) and rel > REL_TOL),
                below_reference=bool(np.isfinite(rel) and rel < -REL_TOL),
                false_infeasible=bool(status == "infeasible" and feas_ref),
                excess=float(max(excess, 0.0)), rel=rel)


def summarize(name: str, rows: list[dict]) -> dict:
    """One table row from per-program comparisons (keys of :func:`classify` plus ``status`` and ``time``)."""
    t = [r["time"] for r in rows]
    ex = np.array([r["excess"] for r in rows], float)
    return dict(config=name, programs=len(rows),
                optimal=int(sum(r["status"] == "optimal" for r in rows)),
                wrong_optimum=int(sum(r["wrong_optimum"] for r in rows)),
                below_reference=int(sum(r["below_reference"] for r in rows)),
                false_infeasible=int(sum(r["false_infeasible"] for r in rows)),
                max_bound_excess=float(ex.max()) if ex.size else 0.0,
                fallbacks=int(sum(r.get("fallback", False) for r in rows)),
                flagged_violations=int(sum(r.get("flagged_violation", False) for r in rows)),
                **time_stats(t))


# ----------------------------------------------------------------------------------- MPC
def mpc_reference(setup: dict, cases: list[dict], time_limit: float = 120.0) -> list:
    """The cold reference at every case: SCIP, every step encoded on the reachable boxes, gap 1e-8."""
    from .mpc import make_mpc

    mpc = make_mpc(setup, backend="scip", bounds="horizon", encode="all", screening=False, warm_start=False,
                   lazy=False, time_limit=time_limit)
    mpc.gap = 1e-8
    mpc.fallback_deadline = False  # a yardstick, not an answer on time: its fallback repairs to the end
    out = []
    for c in cases:
        mpc.reset()
        out.append(mpc(c["z"], c["z_ref"]))
    return out


def add_previous_plans(setup: dict, cases: list[dict], refs: list) -> None:
    """A previous plan for every case: the reference's optimum shifted by one step (the warm start of a
    closed loop that followed the prediction), stored as ``case["ws"]`` (``None`` without a plan)."""
    for c, r in zip(cases, refs):
        c["ws"] = None if not r.ok else np.vstack([r.v_pred[1:], r.v_pred[-1:]])


def perturbed_plan(mpc, z, v_opt, rng: np.random.Generator, perturbation: float = 0.05) -> tuple:
    """A previous plan ``(z_pred, v_pred)`` whose shift is the optimum ``v_opt`` at ``z`` with every input
    perturbed by ``perturbation`` (relative, seeded by ``rng``): a near-optimal warm start that may or may not be
    admissible."""
    Vp = v_opt * (1.0 + perturbation * rng.standard_normal(np.shape(v_opt)))
    V = np.vstack([Vp[-1:], Vp[:-1]])  # its shift is the perturbed optimum
    return mpc.predict(z, V), V


def warm_record(setup: dict, cases: list[dict], refs: list, seed: int = 7) -> dict:
    """The cases with a reference optimum as a record for :func:`flnotes.bench.mpc.interleaved_table`, each with
    the previous plan of :func:`perturbed_plan` (5 %, seeded): the warm counterpart of ``cases_record``."""
    from .mpc import make_mpc

    mpc, rng = make_mpc(setup), np.random.default_rng(seed)
    ok = [(c, r) for c, r in zip(cases, refs) if r.ok]
    return dict(z=[c["z"] for c, _ in ok], R=[c["z_ref"] for c, _ in ok],
                prev=[perturbed_plan(mpc, c["z"], r.v_pred, rng) for c, r in ok])


def mpc_controller_rows(setup: dict, cases: list[dict], refs: list, name: str, warm: bool,
                        time_limit: Optional[float] = None, **mpc_kw) -> list[dict]:
    """Compare :class:`flnotes.MPC` (the whole step: solve, checks, fallback) with the reference.

    With ``warm`` the controller gets a previous plan: the reference's optimum at ``z`` with
    its inputs perturbed by 5 % (seeded), shifted back by one step, so that the controller's
    shifted plan is a near-optimal warm start that may or may not be admissible.
    """
    from ..mpc import MPC

    S = paper.QUAD_SETTING
    mpc = MPC(setup["system"], setup["net"], setup["eps"], horizon=setup["N"], ts=setup["ts"], Q=S["Q"], R=S["R"],
              time_limit=time_limit, **mpc_kw)
    u_eps = mpc.u_eps
    rows = []
    rng = np.random.default_rng(7)
    for c, r in zip(cases, refs):
        mpc.reset()
        if warm and r.ok:
            mpc.set_previous_plan(perturbed_plan(mpc, c["z"], r.v_pred, rng))
        t0 = time.perf_counter()
        s = mpc(c["z"], c["z_ref"])
        dt = time.perf_counter() - t0
        # a flagged least-violation input (no admissible v exists) is a documented violation, counted apart
        excess = float(np.max(np.abs(mpc.net(np.r_[c["z"], s.v])) - u_eps)) if s.input_admissible else 0.0
        row = classify(s.status, s.objective, r.status, r.objective, excess)
        row.update(status=s.status, time=dt, fallback=s.fallback, category=c["category"],
                   flagged_violation=not s.input_admissible)
        rows.append(row)
    return rows


# ----------------------------------------------------------------------------------- CLF-CBF
def clf_rows(ctrl, states, ref_ctrl, exact=None) -> list[dict]:
    """Compare a :class:`flnotes.control.ClfCbfController` with the reference controller (and the exact 1-D method)."""
    rows = []
    for z, cat in states:
        r = ctrl.step(z)
        rr = ref_ctrl.step(z)
        ref_status, ref_obj = rr.status, rr.objective
        if exact is not None:  # the exact method decides where SCIP and it disagree
            re = exact.step(z)
            if re.status == "optimal" and (ref_status != "optimal" or re.objective < ref_obj):
                ref_status, ref_obj = re.status, re.objective
        # the softened program's input may violate the bound only when no admissible v exists: flagged
        excess = 0.0 if r.fallback else float(np.max(np.abs(r.info["phi_nn"]) - ctrl.u_eps))
        row = classify(r.status, r.objective, ref_status, ref_obj, excess)
        row.update(status=r.status, time=r.solve_time, fallback=r.fallback, category=cat,
                   flagged_violation=not r.input_admissible)
        rows.append(row)
    return rows


# ----------------------------------------------------------------------------------- the section
def run(fast: bool) -> dict:
    """``make bench`` section: exactness and time per program on diverse states."""
    from ..control import ClfCbfController, DistanceCBF, QuadraticCLF
    from .mpc import quad_setup

    rows, notes = [], []
    # ---- CLF-CBF (MSD)
    S = paper.MSD_SETTING
    sysm = paper.system("MSD")
    net, _ = paper.paper_net("MSD")
    eps = float(np.max(paper.paper_eps("MSD").upper))
    n_clf = 24 if fast else 200
    states = clf_states(sysm, n_clf, seed=1)
    V, H = QuadraticCLF(S["P"]), DistanceCBF(S["z_o"], S["r_o"])
    k = lambda z: -S["K_nominal"] @ z
    for cost, backends in (("linear", ("exact", "highs", "scip", "daqp", "cvxpy")),
                           ("quadratic", ("exact", "scip", "daqp", "cvxpy"))):
        base = dict(system=sysm, net=net, eps=eps, V=V, H=H, k=k, cost=cost, beta=S["beta"], kappa=S["kappa"])
        ref = ClfCbfController(**base, backend="scip", gap=1e-8)
        ex = ClfCbfController(**base, backend="exact")
        for b in backends:
            for scr in ((True, False) if b in ("highs", "scip", "daqp") else (True,)):
                ctrl = ClfCbfController(**base, backend=b, screening=scr)
                res = clf_rows(ctrl, states, ref, ex)
                rows.append(dict(program=f"MSD CLF-CBF {'Lcost' if cost == 'linear' else 'Qcost'}",
                                 **summarize(f"{b}{'' if scr else ', no screening'}", res)))
    # ---- MPC (Quad-1D)
    setup = quad_setup()
    n_mpc = 6 if fast else 120
    cases = mpc_cases(setup, n_mpc, seed=2)
    t0 = time.perf_counter()
    refs = mpc_reference(setup, cases)
    t_ref = time.perf_counter() - t0
    rows.append(dict(program="Quad-1D MPC", config="reference: SCIP, every step encoded, gap 1e-8",
                     programs=len(cases), optimal=int(sum(r.status == "optimal" for r in refs)),
                     **time_stats([r.solve_time for r in refs])))
    from ..mpc import DAQP_OPTIONS

    trust = dict(solver_options={"daqp": dict(DAQP_OPTIONS, verify_infeasible=False)})
    before = dict(solver_options={"daqp": dict(DAQP_OPTIONS, reg_mode="upper", reg_retry=False,
                                               verify_feasibility="miqp")})
    for name, kw, warm in (("default, cold", {}, False), ("default, warm (previous plan)", {}, True),
                           ("default, cold, time limit 5 s", dict(time_limit=5.0), False),
                           ("default, warm, time limit 5 s", dict(time_limit=5.0), True),
                           ("default, cold, DAQP's infeasibility trusted", trust, False),
                           ("default, cold, without the DAQP levers (upper regularization, no retry, SCIP on the "
                            "MIQP for every claim of infeasibility)", before, False),
                           ("scip level set, cold", dict(backend="scip"), False),
                           ("default, no screening, no constraint generation, time limit 30 s",
                            dict(screening=False, lazy=False, time_limit=30.0), False)):
        tl = kw.pop("time_limit", None)
        res = mpc_controller_rows(setup, cases, refs, name, warm, time_limit=tl, **kw)
        rows.append(dict(program="Quad-1D MPC", **summarize(name, res)))
        if name.startswith("default, ") and "DAQP" not in name:
            split = {k: [r["time"] for r, ref in zip(res, refs) if (ref.status == "infeasible") == (k == "infeasible")]
                     for k in ("feasible", "infeasible")}
            notes.append(f"{name}: " + "; ".join(
                f"{len(t)} programs the reference finds {k}: p99 {np.percentile(t, 99) * 1e3:.0f} ms, "
                f"max {max(t) * 1e3:.0f} ms" for k, t in split.items() if t))
    from .mpc import cases_record, level_lever_table

    for start, rec in (("cold", cases_record(cases)), ("warm (5 % from the optimum)", warm_record(setup, cases, refs))):
        for r in level_lever_table(setup, rec, range(len(rec["z"])), time_limit=30.0):
            rows.append(dict(program="Quad-1D MPC", config=f"level lever, {start}: {r['config']}",
                             programs=r["states"], median_ms=r["ms_median"], p99_ms=r["ms_p99"], max_ms=r["ms_max"],
                             cpu_ms_p99=r["cpu_ms_p99"], cpu_s_total=r["cpu_s_total"], non_optimal=r["non_optimal"],
                             max_rel_diff_to_default=r["max_rel_diff_to_default"]))
    for r in rows:
        if r.get("program") == "Quad-1D MPC" and str(r.get("config", "")).startswith("default, "):
            notes.append(f"target p99 <= t_s = {1e3 * setup['ts']:.0f} ms at N_p = {setup['N']} on diverse states: "
                         f"{r['config']}: p99 {r['p99_ms']:.0f} ms, max {r['max_ms']:.0f} ms (wall clock)")
    notes.append(f"{n_clf} CLF-CBF states (categories {', '.join(CLF_CATEGORIES)}) and {n_mpc} MPC programs "
                 f"(categories {', '.join(MPC_CATEGORIES)}), seeded; reference computed in {t_ref:.0f} s. "
                 "wrong_optimum counts 'optimal' results above the reference by more than 1e-6 relative; "
                 "false_infeasible counts 'infeasible' where the reference found a plan; max_bound_excess is "
                 "max(|Phi_NN(z, v)| - u_max^eps) of the applied input (forward pass). Times are wall-clock per "
                 "program: these are the real-time numbers on diverse states, next to the closed-loop ones.")
    return dict(title="Exactness and time on diverse states", rows=rows, notes=notes, figures=[])


# ----------------------------------------------------------------------------------- the chapter's table
def diverse_time_table(setup: dict, n: int, n_checked: int, seed: int = 2, time_limit: Optional[float] = None
                       ) -> tuple[list[dict], dict]:
    """Per-step time of the default MPC on ``n`` diverse states, cold and warm, next to each other.

    Cold: no previous plan. Warm: the previous plan is the cold solution with its inputs perturbed
    by 5 % (seeded) and shifted back by one step, so that its shift is a near-optimal warm start.
    The first ``n_checked`` states are also solved by the cold reference (:func:`mpc_reference`)
    and both runs compared with it. Returns the table rows and a dict of the numbers the chapter
    quotes (``wrong`` and ``false_infeasible`` summed over both runs, ``max_excess``).
    """
    from ..mpc import MPC

    S = paper.QUAD_SETTING
    cases = mpc_cases(setup, n, seed)
    refs = mpc_reference(setup, cases[:n_checked]) if n_checked else []
    rng = np.random.default_rng(7)
    mpc = MPC(setup["system"], setup["net"], setup["eps"], horizon=setup["N"], ts=setup["ts"], Q=S["Q"], R=S["R"],
              time_limit=time_limit)
    rows, out = [], dict(wrong=0, false_infeasible=0, max_excess=0.0)
    cold_plans = []
    for name in ("cold", "warm"):
        res = []
        for j, c in enumerate(cases):
            mpc.reset()
            if name == "warm" and cold_plans[j] is not None:
                mpc.set_previous_plan(perturbed_plan(mpc, c["z"], cold_plans[j], rng))
            t0 = time.perf_counter()
            s = mpc(c["z"], c["z_ref"])
            dt = time.perf_counter() - t0
            if name == "cold":
                cold_plans.append(None if s.fallback else s.v_pred)
            excess = float(np.max(np.abs(mpc.net(np.r_[c["z"], s.v])) - mpc.u_eps)) if s.input_admissible else 0.0
            if j < len(refs):
                r = refs[j]
                row = classify(s.status, s.objective, r.status, r.objective, excess)
            else:
                row = classify(s.status, s.objective, "unknown", np.nan, excess)
            row.update(status=s.status, time=dt, fallback=s.fallback, flagged_violation=not s.input_admissible)
            res.append(row)
        sm = summarize(f"default MPC, {name}", res)
        sm["checked_against_reference"] = len(refs)
        rows.append(sm)
        out["wrong"] += sm["wrong_optimum"]
        out["false_infeasible"] += sm["false_infeasible"]
        out["max_excess"] = max(out["max_excess"], sm["max_bound_excess"])
        out[f"{name}_ms_median"], out[f"{name}_ms_p90"], out[f"{name}_ms_max"] = (sm["median_ms"], sm["p90_ms"],
                                                                                  sm["max_ms"])
        out[f"{name}_ms_p99"] = sm["p99_ms"]
    return rows, out


def objection_clause(horizon: dict, diverse: dict, ts_ms: float) -> dict:
    """Whether a step still took longer than the sampling period in this build, as the benchmark report words it.

    Parameters
    ----------
    horizon
        the report's loop at its longest horizon: ``cpu_over_ts`` (steps that used more than ``t_s`` of CPU time)
        and ``steps``.
    diverse
        the numbers of :func:`diverse_time_table` (``cold_ms_max``: the slowest cold step, ms).
    ts_ms
        the sampling period (ms).

    Returns
    -------
    dict
        ``objection_clause``: when neither the loop nor the cold states took longer than ``t_s``, "in this build
        even the report's longer horizon and the cold states drawn all over the box stayed within the sampling
        period, which a slower machine can change"; else "not all of it: " followed by the cases that did, joined by
        ", and ": "on the report's longer horizon, K of the S steps of the loop used more than the sampling period of
        CPU time" and/or "cold states drawn all over the box took up to M ms".
    """
    over = []
    if horizon["cpu_over_ts"] > 0:
        over.append(f"on the report's longer horizon, {horizon['cpu_over_ts']} of the {horizon['steps']} steps of the loop "
                    "used more than the sampling period of CPU time")
    if diverse["cold_ms_max"] > ts_ms:
        over.append(f"cold states drawn all over the box took up to {diverse['cold_ms_max']:.0f} ms")
    return dict(objection_clause="not all of it: " + ", and ".join(over) if over else
                "in this build even the report's longer horizon and the cold states drawn all over the box stayed within "
                "the sampling period, which a slower machine can change")
