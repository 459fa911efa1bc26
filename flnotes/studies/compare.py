"""The comparative study: the network constraint against the methods used instead of it.

Five ways to keep ``|u| <= u_max`` in an MPC of a feedback-linearizable plant, all on the same
plant, cost, horizon, sampling time, references and initial states:

``"network"``
    the book's MIQP, eq. (MPC_form_miqp): ``|Phi_NN(z(k), v(k))| <= u_max - eps`` at every
    predicted step (``fl.MPC``, default options);
``"measured"``
    constant extension (Nevistic & Morari; Kandler et al.): the exact bound at the *measured*
    state turned into linear bounds on ``v``, applied at every predicted step (a QP);
``"previous"``
    previous prediction (Kurtz & Henson 1998): at predicted step ``k`` the exact bound evaluated
    along the plan of the previous sampling instant, shifted (a QP; ``iterations > 1`` re-solves
    with the new plan);
``"saturated"``
    unconstrained linear MPC on the Brunovsky model, then ``u`` clipped to ``+-u_max``
    (:class:`flnotes.nmpc.SaturatedInput`);
``"nmpc"``
    nonlinear MPC on the original plant with ``|u| <= u_max`` as a bound, CasADi + IPOPT
    (:class:`flnotes.nmpc.NonlinearMPC`), a local optimum.

The metrics of one closed-loop run are computed by :func:`run_metrics`; :func:`monte_carlo`
draws the scenarios of :func:`draw_scenarios` and runs every method on each.
"""
from __future__ import annotations

import dataclasses
import time
from functools import partial
from typing import Callable, Optional, Sequence

import numpy as np

from .. import paper
from ..mpc import MPC, sine_reference
from ..nmpc import NonlinearMPC, SaturatedInput
from ..parallel import task_key, using
from ..simulate import simulate
from ..systems import FLSystem
from ..tables import time_stats

Array = np.ndarray

__all__ = ["METHODS", "LABELS", "U_TOL", "setting", "make_controller", "Timed", "draw_scenarios", "scenario_reference",
           "run_methods", "run_metrics", "plan_violations", "settling_time", "monte_carlo", "method_table",
           "cost_vs_miqp", "step_field"]

#: The five methods, in the order of the chapter.
METHODS = ("network", "measured", "previous", "saturated", "nmpc")

#: Their names in tables and figures.
LABELS = {"network": "MIQP (network)", "measured": "constant extension", "previous": "previous prediction",
          "saturated": "saturated FL", "nmpc": "nonlinear MPC"}

#: Tolerance on ``|u| <= u_max`` (round-off of the input at the bound).
U_TOL = 1e-9


# ----------------------------------------------------------------------------------- setting
def setting(name: str, horizon: int = 10, ts: float = 0.1, time_limit: Optional[float] = 5.0) -> dict:
    """The common setting of every method for system ``name`` (``"Quad-1D"`` or ``"MSD"``).

    Quad-1D: the paper's Sec. IV-B (``t_s = 0.1`` s, ``Q = diag(10, 1, 1)``, ``R = 0.0175``).
    MSD: the book's choice ``Q = diag(10, 1)``, ``R = 0.01`` at the same ``t_s`` and ``N_p``
    (the paper runs no MPC on it). Both use the shipped network and its certified ``eps``.
    Returns a dict with ``system``, ``net``, ``eps``, ``horizon``, ``ts``, ``Q``, ``R``,
    ``time_limit``, ``rk4_steps`` (the NMPC's RK4 sub-steps per sample), ``to_z_sym`` (the
    coordinate change written for CasADi symbols, or ``None`` when the system's own works) and
    ``name``.
    """
    if name == "Quad-1D":
        S = paper.QUAD_SETTING
        Q, R, rk4, to_z = S["Q"], S["R"], 1, None
    elif name == "MSD":
        Q, R, rk4, to_z = np.diag([10.0, 1.0]), np.array([[0.01]]), 2, (lambda x: x)  # z = x
    else:
        raise ValueError(f"name must be 'Quad-1D' or 'MSD', got {name!r}")
    net, _ = paper.paper_net(name)
    eps = float(np.max(paper.paper_eps(name).upper))
    return dict(name=name, system=paper.system(name), net=net, eps=eps, horizon=int(horizon), ts=float(ts), Q=Q, R=R,
                time_limit=time_limit, rk4_steps=rk4, to_z_sym=to_z)


def make_controller(method: str, s: dict, iterations: int = 1):
    """The controller of ``method`` (one of :data:`METHODS`) for the setting ``s`` and the hold it assumes.

    Returns ``(controller, hold)``: the FL-based methods hold ``v`` over a sample (their
    prediction model is the Brunovsky chain, exact with ``hold="v"``); the nonlinear MPC holds
    ``u`` (its RK4 prediction holds ``u``).
    """
    common = dict(horizon=s["horizon"], ts=s["ts"], Q=s["Q"], R=s["R"])
    if method == "network":
        return MPC(s["system"], s["net"], s["eps"], time_limit=s["time_limit"], **common), "v"
    if method in ("measured", "previous"):
        kw = dict(iterations=int(iterations)) if method == "previous" else {}
        return MPC(s["system"], s["net"], s["eps"], constraint=method, time_limit=s["time_limit"], **kw, **common), "v"
    if method == "saturated":
        inner = MPC(s["system"], s["net"], s["eps"], constraint="none", time_limit=s["time_limit"], **common)
        return SaturatedInput(inner, s["system"]), "v"
    if method == "nmpc":
        return NonlinearMPC(s["system"], rk4_steps=s["rk4_steps"], to_z=s["to_z_sym"], time_limit=s["time_limit"],
                            **common), "u"
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")


class Timed:
    """One timing for every method: the wall time of ``controller.step`` (``time.perf_counter``).

    Wraps a controller; its ``step`` returns the inner record with ``solve_time`` replaced by
    the wall-clock time of the whole call (set-up, bounds, solves, checks, conversions).
    """

    def __init__(self, inner):
        if not hasattr(inner, "step"):
            raise TypeError(f"inner must be a controller with step(z, t, reference), got {type(inner).__name__}")
        self.inner = inner
        self.net = getattr(inner, "net", None)

    def reset(self) -> None:
        if hasattr(self.inner, "reset"):
            self.inner.reset()

    def step(self, z: Array, t: float, reference=None):
        t0 = time.perf_counter()
        res = self.inner.step(z, t, reference)
        return dataclasses.replace(res, solve_time=time.perf_counter() - t0)


def step_field(step, name: str):
    """Field ``name`` of a logged step record (an attribute, or an entry of its ``info`` dict), or ``None``."""
    if hasattr(step, name):
        return getattr(step, name)
    info = getattr(step, "info", None) or {}
    return info.get(name)


# ----------------------------------------------------------------------------------- scenarios
def draw_scenarios(name: str, n: int, seed: int = 0) -> list[dict]:
    """``n`` scenarios of the Monte Carlo: initial state and sine reference, from a seeded distribution.

    Quad-1D: ``z0 = [x, x', x'']`` with ``x ~ U(-1.5, 1.5)``, ``x', x'' ~ U(-1, 1)``; reference
    ``x_ref = A sin(w t + phi)`` with ``A ~ U(0.25, 2)``, ``w ~ U(0.5, 1.5)`` rad/s,
    ``phi ~ U(0, 2 pi)``. MSD: ``z0 ~ U(-2, 2)^2``; ``A ~ U(0.5, 4.5)``, ``w ~ U(0.3, 2)``,
    redrawn until ``A w <= 4`` and ``A w^2 <= 8`` (the reference and its ``v`` stay well
    inside the domain box). Each scenario also records ``u_ref_max``, the largest true input
    the reference itself needs, ``max_t |Phi(z_ref(t), v_ref(t))|``: above ``u_max`` the
    input bound must be active.
    """
    if isinstance(n, bool) or int(n) != n or n < 1:
        raise ValueError(f"n must be a positive number of scenarios, got {n!r}")
    if name not in ("Quad-1D", "MSD"):
        raise ValueError(f"name must be 'Quad-1D' or 'MSD', got {name!r}")
    rng = np.random.default_rng(seed)
    sysm = paper.system(name)
    out = []
    while len(out) < n:
        if name == "Quad-1D":
            z0 = np.r_[rng.uniform(-1.5, 1.5), rng.uniform(-1, 1, 2)]
            A, w, ph = rng.uniform(0.25, 2.0), rng.uniform(0.5, 1.5), rng.uniform(0, 2 * np.pi)
        elif name == "MSD":
            z0 = rng.uniform(-2, 2, 2)
            A, w, ph = rng.uniform(0.5, 4.5), rng.uniform(0.3, 2.0), rng.uniform(0, 2 * np.pi)
            if A * w > 4 or A * w**2 > 8:
                continue
        else:
            raise ValueError(f"name must be 'Quad-1D' or 'MSD', got {name!r}")
        sc = dict(index=len(out), z0=z0, amplitude=float(A), omega=float(w), phase=float(ph))
        t = np.linspace(0, 2 * np.pi / w, 200)
        Z = sine_reference(A, w, sysm.n_z + 1, ph)(t)
        sc["u_ref_max"] = float(np.abs(sysm.Phi(Z[:, :-1], Z[:, -1:])).max())
        sc["bound_active"] = bool(sc["u_ref_max"] > sysm.u_max[0])
        out.append(sc)
    return out


def scenario_reference(system: FLSystem, sc: dict) -> Callable[[Array], Array]:
    """The reference ``t -> z_ref(t)`` of a scenario (a sine and its derivatives)."""
    return sine_reference(sc["amplitude"], sc["omega"], system.n_z, sc["phase"])


# ----------------------------------------------------------------------------------- metrics
def plan_violations(log, system: FLSystem, tol: float = U_TOL, first: int = 1) -> dict:
    """How often the *predicted* plans violate the true bound ``|Phi(z(k), v(k))| <= u_max``.

    For every logged step with a plan ``(z_pred, v_pred)`` on the Brunovsky model, the true
    input of each predicted step ``k >= first`` (default: the later steps, after the one that is
    applied) is ``Phi(z_pred[k], v_pred[k])``. Returns the number of steps with a plan,
    the number whose plan violates the bound at some such step, that fraction, and the largest
    excess ``max |Phi| - u_max`` (0 when none).
    """
    n_plans = n_bad = 0
    excess = 0.0
    for s in log.steps:
        Z, V = step_field(s, "z_pred"), step_field(s, "v_pred")
        if Z is None or V is None:
            continue
        Z, V = np.asarray(Z, float), np.asarray(V, float)
        if not (np.all(np.isfinite(Z)) and np.all(np.isfinite(V))):
            continue  # no plan at this step (a solver failure's iterate)
        U = system.Phi(Z[first:len(V)], V[first:]) if len(V) > first else np.zeros((0, system.m))
        n_plans += 1
        ex = float(np.max(np.abs(U) - system.u_max)) if len(U) else -np.inf
        if ex > tol:
            n_bad += 1
            excess = max(excess, ex)
    return dict(plans=n_plans, plans_violating=n_bad, plan_violation_fraction=n_bad / n_plans if n_plans else np.nan,
                plan_excess_max=excess if n_plans else np.nan)


def settling_time(t: Array, error: Array, band: float) -> float:
    """The first time after which ``|error| <= band`` at every later sample (NaN if it never settles)."""
    t, e = np.asarray(t, float), np.abs(np.asarray(error, float))
    out = np.flatnonzero(e > band)
    if len(out) == 0:
        return float(t[0])
    if out[-1] == len(e) - 1:
        return np.nan
    return float(t[out[-1] + 1])


def run_metrics(log, reference: Callable[[Array], Array], Q: Array, R: Array, band: float = 0.1,
                tol: float = U_TOL) -> dict:
    """The metrics of one closed-loop run (one method, one scenario).

    Returns
    -------
    dict
        ``steps``, ``completed`` (the run reached its end), ``max_abs_u_samples`` and
        ``max_abs_u_between`` (the fine grid of :func:`flnotes.simulate`, samples included),
        ``violating_samples`` (steps with ``|u(t_k)| > u_max``) and ``violating_intervals``
        (sampling intervals where the true input exceeds ``u_max`` somewhere on the fine grid),
        the plan statistics of :func:`plan_violations`, ``infeasible_steps`` (status
        ``"infeasible"``), ``fallback_steps``, ``non_optimal_steps``, ``cost`` (the tracking cost
        ``t_s sum_k ||z_k - z_ref(t_k)||_Q^2 + ||v_k||_R^2`` over the run), ``rms_error`` (of the
        position ``z_1`` over the run), ``settling_s`` (:func:`settling_time` of ``z_1`` with
        ``band``), and the per-step wall times ``ms_min``, ``ms_median``, ``ms_max``.
    """
    sysm = log.system
    u_max = sysm.u_max
    K = log.n_steps
    Zr = np.asarray(reference(log.t), float).reshape(len(log.t), -1)
    E = log.z[:K] - Zr[:K]
    Q, R = np.atleast_2d(Q), np.atleast_2d(R)
    cost = float(log.ts * (np.einsum("ki,ij,kj->", E, Q, E) + np.einsum("ki,ij,kj->", log.v, R, log.v)))
    n_fine = len(log.u_fine) // K if K else 0
    fine_bad = (np.abs(log.u_fine) > u_max + tol).any(axis=1)
    st = time_stats(log.solve_time)
    pos = log.z[:, 0] - Zr[:, 0]
    out = dict(
        steps=K, completed=not log.message, message=log.message,
        max_abs_u_samples=float(np.abs(log.u).max()) if K else np.nan,
        max_abs_u_between=float(np.abs(log.u_fine).max()) if K else np.nan,
        violating_samples=int((np.abs(log.u) > u_max + tol).any(axis=1).sum()),
        violating_intervals=int(fine_bad.reshape(K, n_fine).any(axis=1).sum()) if K else 0,
        **plan_violations(log, sysm, tol),
        infeasible_steps=int(sum(str(s).startswith("infeasible") for s in log.status)),
        fallback_steps=int(np.sum(log.fallback)),
        non_optimal_steps=int(sum(s not in ("optimal", "nominal") for s in log.status)),
        cost=cost, rms_error=float(np.sqrt(np.mean(pos**2))),
        settling_s=settling_time(log.t, pos, band),
        ms_min=st["min_ms"], ms_median=st["median_ms"], ms_max=st["max_ms"],
    )
    return out


# ----------------------------------------------------------------------------------- runs
def run_methods(s: dict, z0: Array, reference: Callable[[Array], Array], t_final: float,
                methods: Optional[Sequence[str]] = None, iterations: int = 1) -> dict:
    """Run each method once in closed loop on the true plant; returns ``{method: log}``.

    Every controller is wrapped in :class:`Timed` (the same timing for all) and runs with the
    hold its prediction assumes (:func:`make_controller`); every run checks the domain box.
    ``methods`` defaults to :data:`METHODS`.
    """
    logs = {}
    for mth in (METHODS if methods is None else methods):
        ctrl, hold = make_controller(mth, s, iterations)
        logs[mth] = simulate(s["system"], Timed(ctrl), t_final, s["ts"], z0=z0, reference=reference, hold=hold,
                             net=s["net"] if mth != "nmpc" else None, check_domain=True, progress=False)
        logs[mth].controller = ctrl
    return logs


def _monte_carlo_run(s: dict, t_final: float, band: float, iterations: int, task: tuple) -> dict:
    """One task of :func:`monte_carlo`: one method on one scenario, its row."""
    sc, mth = task
    ref = scenario_reference(s["system"], sc)
    log = run_methods(s, sc["z0"], ref, t_final, (mth,), iterations)[mth]
    return dict(scenario=sc["index"], method=mth, amplitude=sc["amplitude"], omega=sc["omega"],
                u_ref_max=sc["u_ref_max"], bound_active=sc["bound_active"],
                **run_metrics(log, ref, s["Q"], s["R"], band))


def monte_carlo(s: dict, scenarios: Sequence[dict], t_final: float, methods: Optional[Sequence[str]] = None,
                band: float = 0.1, iterations: int = 1, workers: Optional[int] = None, client=None,
                progress: bool = False, resume: bool = False) -> list[dict]:
    """Every method on every scenario: one row of :func:`run_metrics` per (scenario, method).

    Rows also carry the scenario (``scenario``, ``amplitude``, ``omega``, ``u_ref_max``,
    ``bound_active``) and ``method``, in the order scenario by scenario, method by method.
    Each (scenario, method) run is one task of :class:`flnotes.parallel.Executor`: in this
    process by default, on ``workers`` local processes, or on a Dask ``client``; the rows come
    back in the same order whatever runs them. ``progress`` shows a bar; ``resume`` keeps each
    finished row in the cache folder and reuses it when the same run is asked again. Under a
    ``time_limit``, a run's plans depend on the time its solves take (rows with a late step can
    differ between runs); the timing columns (``ms_*``) always do.
    """
    mths = tuple(METHODS if methods is None else methods)
    tasks = [(sc, mth) for sc in scenarios for mth in mths]
    keys = None
    if resume:
        net_key = [np.asarray(a).tolist() for a in (*s["net"].W, *s["net"].b)]
        keys = [task_key("monte_carlo", s["name"], s["eps"], s["horizon"], s["ts"], np.asarray(s["Q"]).tolist(),
                         np.asarray(s["R"]).tolist(), s["time_limit"], net_key, t_final, band, iterations,
                         {k: v for k, v in sc.items()}, mth) for sc, mth in tasks]
    with using(workers, client) as ex:
        return ex.map(partial(_monte_carlo_run, s, t_final, band, iterations), tasks, keys=keys,
                      cache="monte_carlo" if resume else None, desc="Monte Carlo", progress=progress)


def method_table(rows: Sequence[dict], methods: Optional[Sequence[str]] = None, only_active: bool = False) -> list[dict]:
    """One line per method from the rows of :func:`monte_carlo` (or of single runs).

    Columns: scenarios, runs that completed, the largest ``|u|`` at the samples and between
    them over all runs, runs and steps violating the bound at the samples, intervals violating
    it between samples, the fraction of plans violating the true bound at a later predicted step,
    infeasible and fallback steps, the median tracking cost relative to the MIQP's on the same
    scenario, the fraction of runs settled, and the per-step wall times pooled over all runs
    (min of the minima, median of the medians, max of the maxima).
    """
    base = {r["scenario"]: r["cost"] for r in rows if r["method"] == "network"}
    out = []
    for mth in (METHODS if methods is None else methods):
        rr = [r for r in rows if r["method"] == mth and (r["bound_active"] or not only_active)]
        if not rr:
            continue
        plans = sum(r["plans"] for r in rr)
        ratio = [r["cost"] / base[r["scenario"]] for r in rr if r["scenario"] in base and base[r["scenario"]] > 0]
        out.append(dict(
            method=LABELS[mth], scenarios=len(rr), completed=int(sum(r["completed"] for r in rr)),
            max_u_samples=max(r["max_abs_u_samples"] for r in rr), max_u_between=max(r["max_abs_u_between"] for r in rr),
            runs_violating=int(sum(r["violating_samples"] > 0 for r in rr)),
            violating_samples=int(sum(r["violating_samples"] for r in rr)),
            violating_intervals=int(sum(r["violating_intervals"] for r in rr)),
            plans_violating=(sum(r["plans_violating"] for r in rr) / plans) if plans else np.nan,
            infeasible=int(sum(r["infeasible_steps"] for r in rr)), fallback=int(sum(r["fallback_steps"] for r in rr)),
            cost_vs_miqp=float(np.median(ratio)) if ratio else np.nan,
            settled=float(np.mean([np.isfinite(r["settling_s"]) for r in rr])),
            ms_min=float(np.nanmin([r["ms_min"] for r in rr])), ms_median=float(np.nanmedian([r["ms_median"] for r in rr])),
            ms_max=float(np.nanmax([r["ms_max"] for r in rr])),
        ))
    return out


def cost_vs_miqp(s: dict, log, indices: Sequence[int]) -> list[dict]:
    """The NMPC's local optimum against the MIQP's optimum on the same states.

    For each sampling instant ``k`` of a closed-loop run (``log`` from :func:`run_methods`, whose
    MPC steps record the horizon's reference ``z_ref``), the MIQP of eq. (MPC_form_miqp) is
    solved again at the logged state ``z_k`` and reference, *without a time limit*: its optimum
    and status do not depend on how fast the machine ran the loop. The NMPC is then solved at
    the same state and reference twice: cold (constant state, ``u = 0``) and started from the
    MIQP's plan turned into true inputs (``u_k = Phi(z_pred[k], v_pred[k])``). Both programs have
    the same cost function of the predicted ``z`` and ``v``; the MIQP holds ``v`` over a sample
    (its plan is exact for the plant under ``hold="v"``) and keeps ``eps`` of margin, the NMPC
    holds ``u``. Returns one row per instant: the MIQP's objective and status, the two NMPC
    objectives and statuses, and their relative differences to the MIQP (compare only where all
    three are ``"optimal"``).
    """
    sysm = s["system"]
    miqp, _ = make_controller("network", dict(s, time_limit=None))
    rows = []
    for k in indices:
        R = step_field(log.steps[int(k)], "z_ref")
        if R is None:
            raise ValueError(f"step {k} of the log has no reference z_ref: pass a run of run_methods with an MPC")
        x0 = np.asarray(sysm.to_x(log.z[int(k)]), float)
        exact = miqp(log.z[int(k)], R)
        obj = float(exact.objective)
        res = {}
        for start in ("cold", "miqp plan"):
            nm = NonlinearMPC(sysm, s["horizon"], s["ts"], s["Q"], s["R"], rk4_steps=s["rk4_steps"], to_z=s["to_z_sym"])
            guess = None
            if start == "miqp plan" and exact.v_pred is not None:
                guess = sysm.Phi(np.asarray(exact.z_pred)[:-1], np.asarray(exact.v_pred))
            res[start] = nm.solve(x0, R, u_guess=guess)
        rows.append(dict(step=int(k), t=float(log.t[int(k)]), miqp=obj, miqp_status=str(exact.status),
                         nmpc_cold=res["cold"]["objective"], nmpc_from_miqp=res["miqp plan"]["objective"],
                         status_cold=res["cold"]["status"], status_from_miqp=res["miqp plan"]["status"],
                         rel_cold=(res["cold"]["objective"] - obj) / max(abs(obj), 1e-12),
                         rel_from_miqp=(res["miqp plan"]["objective"] - obj) / max(abs(obj), 1e-12),
                         cold_vs_warm=abs(res["cold"]["objective"] - res["miqp plan"]["objective"])
                         / max(abs(res["miqp plan"]["objective"]), 1e-12)))
    return rows
