"""Studies of chapters 7 and 8: checks of an MPC run, Table 2's MPC row, horizon sweeps, lever studies."""
from __future__ import annotations

import dataclasses
from typing import Callable, Mapping, Optional, Sequence

import numpy as np

from .. import paper
from ..mpc import MPC, MPCOptions
from ..mpc.levers import node_bounds
from ..network import ReLUNet
from ..simulate import SimLog, simulate
from ..systems import FLSystem
from ..tables import time_stats

Array = np.ndarray

__all__ = ["active_fraction", "tracking_error", "closed_loop_checks", "table2", "run_closed_loop", "log_head", "horizon_sweep",
           "shifted_plans", "binaries_per_step", "prediction_mismatch", "recorded_problems", "hardest_steps",
           "compare_to_reference", "lever_study", "lever_repeats", "input_guarantee", "repeat_numbers",
           "time_limit_numbers", "WARM_EFFECT_WORDS"]


def active_fraction(log, u_eps, rel: float = 0.02) -> float:
    """Fraction of sampling instants where the network constraint is active.

    Active means ``|Phi_NN(z_k, v_k)| >= (1 - rel) u_max^eps`` (within ``rel``
    of the bound), read from ``log.u_nn`` (run :func:`flnotes.simulate` with ``net=``).
    """
    if log.u_nn is None:
        raise ValueError("log.u_nn is missing: run flnotes.simulate(..., net=net) to log Phi_NN(z_k, v_k)")
    u_eps = np.asarray(u_eps, float).reshape(-1)
    return float(np.mean(np.any(np.abs(log.u_nn) >= (1 - rel) * u_eps, axis=1))) if len(log.u_nn) else 0.0


def tracking_error(log, reference: Callable[[Array], Array], component: int = 0) -> Array:
    """``|z_i(t_k) - z_ref,i(t_k)|`` at the sampling instants (default: the position ``x``)."""
    return np.abs(log.z[:, component] - np.asarray(reference(log.t), float)[:, component])


def closed_loop_checks(log, mpc: "MPC", reference: Optional[Callable[[Array], Array]] = None,
                       rel: float = 0.02) -> dict:
    """The checks the chapter prints from a closed-loop run.

    Returns a dict with the largest true ``|u|`` at the samples and between
    them against ``u_max``, the largest ``|Phi_NN|`` at the samples and along
    every predicted plan against ``u_max^eps``, the active fraction, the
    tracking error of ``x`` (at ``t = 0``, and max/RMS over the second half of
    the run), and the steps that hit the time limit, fell back or were not optimal.
    """
    u_max = float(log.system.u_max[0])
    pred = [np.abs(s.u_nn_pred).max() for s in log.steps if s.u_nn_pred is not None]
    out = dict(
        u_max=u_max, u_max_eps=float(mpc.u_eps[0]),
        max_abs_u_samples=float(np.abs(log.u).max()), max_abs_u_between=float(np.abs(log.u_fine).max()),
        max_abs_u_nn_samples=float(np.abs(log.u_nn).max()) if log.u_nn is not None else np.nan,
        max_abs_u_nn_predicted=float(max(pred)) if pred else np.nan,
        active_fraction=active_fraction(log, mpc.u_eps, rel) if log.u_nn is not None else np.nan,
        steps=log.n_steps,
        time_limit_steps=int(sum(s == "time_limit" for s in log.status)),
        fallback_steps=int(np.sum(log.fallback)),
        non_optimal_steps=int(sum(s != "optimal" for s in log.status)),
        message=log.message,
    )
    if reference is not None:
        e = tracking_error(log, reference)
        half = e[len(e) // 2:]
        out.update(tracking_error_initial=float(e[0]), tracking_error_max_second_half=float(half.max()),
                   tracking_error_rms_second_half=float(np.sqrt(np.mean(half**2))))
    return out


def table2(log, mpc: "MPC", system: str = "Quad-1D", label: str = "this book") -> list[dict]:
    """Table 2's MPC row for ``system`` from a run, next to the paper's, with the binaries before/after elimination.

    The binary count of eq. (MPC_form_miqp) is ``N_p sum_k n_k`` (the paper's footnote): for the paper's
    row ``N_p`` of its setting times the hidden neurons of its architecture (Table 1: ``K - 1`` layers of
    ``n_bar``); after elimination it is the number of binaries actually left free in the programs solved
    (mean and max over the steps that needed one; with constraint generation only the encoded steps count).
    """
    key = [k for k in paper.TABLE2_MS if k[0] == system and k[1].startswith("MPC")]
    if not key:
        raise ValueError(f"the paper's Table 2 has no MPC row for {system!r}; it has "
                         f"{sorted({k[0] for k in paper.TABLE2_MS if k[1].startswith('MPC')})}")
    ref, N_paper = paper.TABLE2_MS[key[0]], paper.QUAD_SETTING["horizon"]
    t1 = paper.TABLE1[system]
    st = time_stats(log.solve_time)
    mi = [s for s in mpc.history if not s.screened]
    nbin = np.array([s.n_binaries for s in mi]) if mi else np.zeros(1)
    return [
        dict(source="paper (CPLEX via YALMIP)", N_p=N_paper, min_ms=ref["min"], max_ms=ref["max"], mean_ms=ref["mean"],
             binaries=N_paper * (t1["K"] - 1) * t1["n_bar"], binaries_after_mean=None, binaries_after_max=None),
        dict(source=f"{label} ({mpc.options})",
             N_p=mpc.N, min_ms=st["min_ms"], max_ms=st["max_ms"], mean_ms=st["mean_ms"], binaries=mpc.n_binaries_full,
             binaries_after_mean=float(nbin.mean()), binaries_after_max=int(nbin.max())),
    ]


def run_closed_loop(system: FLSystem, net: ReLUNet, eps, t_final: float, reference: Callable[[Array], Array],
                    z0: Array, hold: str = "v", **mpc_kwargs):
    """Build an :class:`MPC` (``mpc_kwargs`` as in its signature) and run it on the true plant.

    Returns ``(log, mpc)``; ``log`` records ``Phi_NN`` at the samples (``net=``).
    """

    mpc = MPC(system, net, eps, **mpc_kwargs)
    log = simulate(system, mpc, t_final=t_final, ts=mpc.ts, z0=z0, reference=reference, hold=hold, net=net,
                   progress=False)
    return log, mpc


def log_head(log: SimLog, t_final: float) -> SimLog:
    """The first ``t_final`` seconds of a closed-loop run, as the run of that length would have logged them.

    The loop is causal (each step sees only the past), so the first
    ``K = round(t_final / ts)`` steps of a longer run are the steps of the
    shorter one: the sample arrays keep ``K`` steps (``K + 1`` instants), the
    fine arrays the same steps. Raises ``ValueError`` if the run has fewer
    than ``K`` steps.
    """
    K = int(round(t_final / log.ts))
    if K < 1 or K > log.n_steps:
        raise ValueError(f"log_head: t_final = {t_final} s asks for {K} steps of ts = {log.ts} s, the run has "
                         f"{log.n_steps}: pass 0 < t_final <= {log.n_steps * log.ts:.6g} s")
    n_fine = len(log.t_fine) // max(1, log.n_steps)
    f = K * n_fine
    return dataclasses.replace(
        log, t=log.t[:K + 1], x=log.x[:K + 1], z=log.z[:K + 1], v=log.v[:K], u=log.u[:K],
        u_nn=None if log.u_nn is None else log.u_nn[:K], solve_time=log.solve_time[:K], status=list(log.status[:K]),
        fallback=log.fallback[:K], t_fine=log.t_fine[:f], x_fine=log.x_fine[:f], z_fine=log.z_fine[:f],
        u_fine=log.u_fine[:f], in_domain=log.in_domain[:K + 1], steps=list(log.steps[:K]),
        message=log.message if K == log.n_steps else "")


def horizon_sweep(system: FLSystem, net: ReLUNet, eps, horizons: Sequence[int], t_final: float,
                  reference: Callable[[Array], Array], z0: Array, known: Optional[Mapping[int, tuple]] = None,
                  **mpc_kwargs) -> tuple[dict, list[dict]]:
    """Closed-loop runs for several prediction horizons ``N_p`` (the paper's Figure 7).

    ``known`` maps a horizon to an existing ``(log, mpc)`` run with that
    ``N_p`` and the same settings, at least ``t_final`` long: it is not rerun,
    its first ``t_final`` seconds (:func:`log_head`) are the sweep's run. Returns
    ``({N_p: log}, rows)`` where each row holds ``N_p``, the per-step time
    statistics (ms), the binaries ``N_p sum_k n_k`` and after elimination
    (over the steps of the row's run), and the tracking error over the second
    half of the run.
    """
    logs, rows = {}, []
    known = {int(k): v for k, v in (known or {}).items()}
    for Np in horizons:
        if int(Np) in known:
            log, mpc = known[int(Np)]
            if mpc.N != int(Np):
                raise ValueError(f"known[{int(Np)}] is a run with N_p = {mpc.N}: key it by its own horizon")
            log = log_head(log, t_final)
        else:
            log, mpc = run_closed_loop(system, net, eps, t_final, reference, z0, horizon=int(Np), **mpc_kwargs)
        logs[int(Np)] = log
        st = time_stats(log.solve_time)
        chk = closed_loop_checks(log, mpc, reference)
        mi = [s.n_binaries for s in log.steps if not s.screened]
        rows.append(dict(N_p=int(Np), min_ms=st["min_ms"], max_ms=st["max_ms"], mean_ms=st["mean_ms"], median_ms=st["median_ms"],
                         binaries=mpc.n_binaries_full, binaries_after_mean=float(np.mean(mi)) if mi else 0.0,
                         miqp_steps=len(mi), active_fraction=chk["active_fraction"],
                         rms_x_error_second_half=chk["tracking_error_rms_second_half"],
                         max_abs_u_samples=chk["max_abs_u_samples"], non_optimal=chk["non_optimal_steps"]))
    return logs, rows


def binaries_per_step(mpc: "MPC", z: Array, bounds: Sequence[str] = ("box", "horizon", "lp")) -> list[dict]:
    """Binaries needed at each predicted step for the measured ``z`` under several ``bounds`` switches.

    One row per switch: the free binaries (unstable neurons) at every step
    ``k = 0..N_p-1`` and their total, against ``sum_k n_k`` per step.
    """
    z = mpc._check_z(z)
    lo, hi = mpc.pred.boxes(z)
    rows = []
    for b in bounds:
        nb = node_bounds(mpc.pred, MPCOptions(bounds=b), mpc.box_bounds, lo, hi)
        per = np.sum([u.reshape(mpc.N, -1).sum(axis=1) for u in nb.unstable], axis=0).astype(int)
        rows.append(dict(bounds=b, per_step=per, total=int(per.sum()), full=mpc.n_binaries_full))
    return rows


def prediction_mismatch(log, mpc: "MPC", per_component: bool = False):
    """``max_k |z_{k+1} - (A_d z_k + B_d v_k)|`` on the true plant: 0 when the plant is exactly linearized.

    The components of ``z`` carry different units (for the Quad-1D: m, m/s, m/s^2), so the largest over all of them
    (the default, a float) is a norm without a unit; ``per_component=True`` returns the largest mismatch of each
    component of ``z``, shape ``(n_z,)``, each in its own unit.
    """
    pred = log.z[:-1] @ mpc.Ad.T + log.v @ mpc.Bd.T
    miss = np.abs(pred - log.z[1:])
    return miss.max(axis=0) if per_component else float(miss.max())


def shifted_plans(log, mpc: "MPC") -> dict:
    """Is the previous plan, shifted by one step, admissible at the next measured state? Counted over a run.

    At every step ``k`` whose own plan passed the check (``info["plan_feasible"]``,
    no fallback), a fresh clone of ``mpc`` is given that plan as its previous one
    and builds :meth:`flnotes.MPC.shifted_plan` at the measured ``z_{k+1}``
    (the last input extended: ``K_f z(N_p)`` with a terminal set, else
    :meth:`flnotes.MPC.feasible_tail`); :meth:`flnotes.MPC.plan_feasible` then checks
    it against eq. (MPC_form_miqp_b)-(d) (and the terminal rows, if any).

    Returns
    -------
    dict
        ``plans`` (shifted plans checked), ``admissible`` and ``not_admissible`` (counts).
    """
    probe = mpc.clone()
    n = ok = 0
    for k in range(len(log.steps) - 1):
        st = log.steps[k]
        if st.v_pred is None or bool(log.fallback[k]) or not (st.info or {}).get("plan_feasible", False):
            continue
        probe.set_previous_plan((st.z_pred, st.v_pred))
        shifted = probe.shifted_plan(log.z[k + 1])
        n += 1
        ok += bool(probe.plan_feasible(*shifted))
    return dict(plans=n, admissible=ok, not_admissible=n - ok)


def recorded_problems(log, indices: Sequence[int], with_plans: bool = False) -> list[tuple]:
    """``(z_k, z_ref over the horizon)`` at the sampling instants ``indices`` of an MPC run.

    With ``with_plans=True`` each problem also carries the plan ``(z_pred, v_pred)``
    the controller had computed at step ``k - 1`` (``None`` at ``k = 0``), so that
    :func:`lever_study` can replay it with the warm start it had in closed loop.
    """
    out = []
    for k in indices:
        k = int(k)
        info = log.steps[k].info or {}
        if "z_ref" not in info:
            raise ValueError(f"step {k} of the log has no recorded reference (was it run with flnotes.mpc.MPC?)")
        item = (log.z[k].copy(), np.asarray(info["z_ref"]).copy())
        if with_plans:
            prev = log.steps[k - 1] if k >= 1 else None
            plan = (np.asarray(prev.z_pred), np.asarray(prev.v_pred)) if prev is not None and prev.v_pred is not None else None
            item = item + (plan,)
        out.append(item)
    return out


def hardest_steps(log, n: int) -> list[int]:
    """Indices of the ``n`` sampling instants with the largest controller time in a run."""
    order = np.argsort(-np.nan_to_num(log.solve_time, nan=0.0))
    return sorted(int(k) for k in order[:n])


def compare_to_reference(mpc: "MPC", problems: Sequence[tuple[Array, Array]], **reference_kwargs) -> list[dict]:
    """Solve recorded problems with ``mpc`` and with a cold SCIP solve of the same program (cvxpy).

    Each problem is solved from scratch by both (a fresh copy of ``mpc`` with
    the same settings, so no warm start; ``mpc`` itself is left untouched),
    and the optimal costs are compared. Returns
    one row per problem: both objectives, the relative difference, both times
    (ms) and statuses. ``reference_kwargs`` change the reference controller
    (default ``bounds="horizon"``; any valid bounds give the same optimum).
    """
    opts = MPCOptions(backend="cvxpy-scip", **{"bounds": "horizon", **reference_kwargs})
    ref = mpc.clone(options=opts, gap=1e-6, time_limit=None, solver_options=None)
    rows = []
    for z, R in problems:
        fresh = mpc.clone()
        a = fresh(z, R)
        b = ref(z, R)
        rel = abs(a.objective - b.objective) / max(1.0, abs(b.objective))
        rows.append(dict(objective=a.objective, scip_objective=b.objective, rel_diff=float(rel),
                         ms=a.solve_time * 1e3, scip_ms=b.solve_time * 1e3, status=a.status, scip_status=b.status,
                         binaries=a.n_binaries, scip_binaries=b.n_binaries))
    return rows


def lever_study(system: FLSystem, net: ReLUNet, eps, problems: Sequence[tuple[Array, Array]],
                configs: Mapping[str, dict], order: Optional[Sequence[str]] = None, **common) -> list[dict]:
    """Solve the same sequence of recorded problems with several :class:`MPC` configurations.

    The problems are solved in order by one controller per configuration, so
    a warm start sees the previous problem's plan (as in closed loop when the
    problems are consecutive); problems from ``recorded_problems(...,
    with_plans=True)`` instead start from the plan recorded in closed loop. The configurations run one after the
    other, in the order of ``configs`` or in ``order`` (a permutation of its names). Returns one row per
    configuration, in the order of ``configs`` whatever order they ran in, with the
    per-solve times (ms, array ``ms`` and statistics), the mean binaries left
    free, the mean nodes, and the largest relative difference of the optimal
    cost from the first configuration of ``configs`` (every lever is exact, so it must be ~0).
    """
    names = list(configs)
    run_order = names if order is None else list(order)
    if sorted(run_order) != sorted(names):
        raise ValueError(f"order must list each configuration once, got {run_order} for {names}")
    results = {}
    for label in run_order:
        mpc = MPC(system, net, eps, **{**common, **configs[label]})
        steps = []
        for prob in problems:
            if len(prob) == 3:  # replay: the previous plan it had in closed loop
                mpc.set_previous_plan(prob[2])
            steps.append(mpc(prob[0], prob[1]))
        results[label] = steps
    base = np.array([s.objective for s in results[names[0]]])
    rows = []
    for label in names:
        steps = results[label]
        obj = np.array([s.objective for s in steps])
        ms = np.array([s.solve_time for s in steps]) * 1e3
        rows.append(dict(configuration=label, mean_ms=float(ms.mean()), max_ms=float(ms.max()),
                         binaries=float(np.mean([s.n_binaries for s in steps])),
                         nodes=float(np.mean([s.nodes for s in steps])),
                         max_rel_diff=float(np.max(np.abs(obj - base) / np.maximum(1.0, np.abs(base)))),
                         statuses=",".join(sorted(set(s.status for s in steps))), ms=ms))
    return rows


def lever_repeats(system: FLSystem, net: ReLUNet, eps, problems: Sequence[tuple[Array, Array]],
                  configs: Mapping[str, dict], repeats: int = 3, **common) -> list[dict]:
    """:func:`lever_study` run ``repeats`` times, interleaved (every configuration once per repeat, in turn), the
    order of the configurations alternating from repeat to repeat.

    Repeat 0 runs the configurations in the order of ``configs``, repeat 1 in the reverse order, repeat 2 as
    repeat 0, and so on, so that no configuration always runs first (or last) on a machine whose speed drifts
    during the study. Repeating identical runs measures how far the mean time of one configuration moves from run
    to run on this machine, next to the difference between configurations. Returns one row per configuration, in
    the order of ``configs``: the node counts (the same in every repeat unless a time limit cut a solve), the mean
    time (ms) of every repeat (``mean_ms_runs``) and their range, the position in which it ran in each repeat
    (``run_positions``, 0 = first), and the largest relative difference of the optimal cost from the first
    configuration over the repeats.
    """
    if int(repeats) != repeats or repeats < 2:
        raise ValueError(f"repeats must be an integer >= 2 (one run shows no spread), got {repeats!r}")
    names = list(configs)
    orders = [names if i % 2 == 0 else names[::-1] for i in range(int(repeats))]
    runs = [lever_study(system, net, eps, problems, configs, order=o, **common) for o in orders]
    rows = []
    for j, label in enumerate(names):
        rs = [run[j] for run in runs]
        means = [r["mean_ms"] for r in rs]
        rows.append(dict(configuration=label, repeats=int(repeats), nodes_min=min(r["nodes"] for r in rs),
                         nodes_max=max(r["nodes"] for r in rs), mean_ms_min=min(means), mean_ms_max=max(means),
                         mean_ms_runs=np.array(means), run_positions=np.array([o.index(label) for o in orders]),
                         max_rel_diff=max(r["max_rel_diff"] for r in rs),
                         statuses=",".join(sorted({st for r in rs for st in r["statuses"].split(",")}))))
    return rows


def input_guarantee(log, mpc: MPC) -> dict:
    """The guarantee on the applied input, checked at every step of a closed loop with one input.

    Wherever some ``v`` in the input box with ``|Phi_NN(z_k, v)| <= u_max^eps`` exists at the measured ``z_k``
    (eq. (Phi_NN_ep); decided exactly by :func:`flnotes.exact_1d_feasible_set`, independently of the controller),
    the applied ``v_k`` must satisfy that bound, fallback steps included.

    Returns
    -------
    dict
        ``steps``; ``admissible_exists`` (steps where such a ``v`` exists); ``violations`` (of them, the steps whose
        applied input breaks the bound); ``flagged`` (steps the controller flagged ``input_admissible=False``).
    """
    from ..control import exact_1d_feasible_set
    from ..solvers import BOUND_TOL

    p = mpc.pred
    if p.m != 1:
        raise ValueError(f"input_guarantee decides existence exactly for one input; this controller has {p.m}")
    n = log.n_steps
    exists = np.array([len(exact_1d_feasible_set(p.net, log.z[k], float(p.v_lo[0]), float(p.v_hi[0]),
                                                 float(p.u_eps[0]))) > 0 for k in range(n)], bool)
    within = np.abs(np.asarray(log.u_nn, float).reshape(n, -1)[:, 0]) <= float(p.u_eps[0]) + BOUND_TOL
    flagged = sum(getattr(s, "input_admissible", True) is False for s in log.steps[:n])
    return dict(steps=int(n), admissible_exists=int(exists.sum()), violations=int(np.sum(exists & ~within)),
                flagged=int(flagged))


#: How :func:`repeat_numbers` words the warm-started repeats against the cold ones (keyed by
#: :func:`flnotes.repeats.separation`).
WARM_EFFECT_WORDS = {"overlapping": "the ranges overlap, so no time difference is shown",
                     "lower": "every warm-started repeat was faster than every cold one",
                     "higher": "every warm-started repeat was slower than every cold one"}


def repeat_numbers(rows: Sequence[dict]) -> dict:
    """The figures chapter 7 quotes from :func:`lever_repeats` run on a cold and a warm-started configuration.

    Parameters
    ----------
    rows
        the two rows of :func:`lever_repeats`: the cold configuration first, the warm-started one second.

    Returns
    -------
    dict
        ``rep_n`` (repeats per configuration); ``rep_orderings`` (``comb(2 n, n)``: the equally likely orders of the
        ``2 n`` mean times when the two configurations do not differ); ``rep_one_in`` (half of that: two of the
        orders separate the ranges, one in each direction); ``warm_effect``, a clause: "the ranges overlap, so no
        time difference is shown" when the ranges overlap, "every warm-started repeat was faster than every cold
        one" when every warm time is below every cold one, "... slower ..." when every warm time is above
        (:data:`WARM_EFFECT_WORDS`); ``rep_cold_min``, ``rep_cold_max``, ``rep_warm_min``, ``rep_warm_max`` (the
        range of the mean times, ms).
    """
    import math

    from ..repeats import separation

    if len(rows) != 2:
        raise ValueError(f"repeat_numbers needs two rows (cold, warm) of lever_repeats, got {len(rows)}")
    n_rep = rows[0]["repeats"]
    orderings = math.comb(2 * n_rep, n_rep)
    out = dict(rep_n=n_rep, rep_orderings=orderings, rep_one_in=orderings / 2,
               warm_effect=WARM_EFFECT_WORDS[separation(rows[0]["mean_ms_runs"], rows[1]["mean_ms_runs"])])
    for key, r in (("cold", rows[0]), ("warm", rows[1])):
        out[f"rep_{key}_min"], out[f"rep_{key}_max"] = r["mean_ms_min"], r["mean_ms_max"]
    return out


def time_limit_numbers(checks: Mapping[str, dict], guarantees: Mapping[str, dict]) -> dict:
    """The figures chapter 7 quotes from two closed loops under a time limit of 1 ms, with and without warm start.

    Parameters
    ----------
    checks
        ``{"warm": ..., "cold": ...}``: :func:`closed_loop_checks` of each loop.
    guarantees
        the same keys: :func:`input_guarantee` of each loop.

    Returns
    -------
    dict
        ``tl_{key}_exists`` (steps where an admissible ``v`` existed), ``tl_{key}_hits`` (steps that hit the limit)
        and ``tl_{key}_fb`` (fallback steps) for ``key`` in ``warm``, ``cold``; ``tl_steps`` (the steps of the warm
        loop); ``tl_clause``: "with a limit of 1 ms per step the loop fell back at W of its N steps with it and at
        C without it", followed by ", so that value did not show in this build" when the warm loop did not fall
        back less often than the cold one (W >= C), and always ending ", counts that depend on the machine's speed".
    """
    out = {}
    for key in ("warm", "cold"):
        out[f"tl_{key}_exists"] = guarantees[key]["admissible_exists"]
        out[f"tl_{key}_hits"] = checks[key]["time_limit_steps"]
        out[f"tl_{key}_fb"] = checks[key]["fallback_steps"]
    out["tl_steps"] = n = checks["warm"]["steps"]
    w_fb, c_fb = checks["warm"]["fallback_steps"], checks["cold"]["fallback_steps"]
    clause = f"with a limit of 1 ms per step the loop fell back at {w_fb} of its {n} steps with it and at {c_fb} without it"
    clause += "" if w_fb < c_fb else ", so that value did not show in this build"
    out["tl_clause"] = clause + ", counts that depend on the machine's speed"
    return out
