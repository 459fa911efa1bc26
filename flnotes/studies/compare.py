"""The comparative study: the network constraint against the methods used instead of it.

Five ways to keep ``|u| <= u_max`` in an MPC of a feedback-linearizable plant, all on the same
plant, cost, horizon, sampling time, references and initial states:

``"network"``
    the book's MIQP, eq. (MPC_form_miqp): ``|Phi_NN(z(k), v(k))| <= u_max - eps`` at every
    predicted step (``fl.MPC``, default options);
``"measured"``
    constant extension (Nevistic & del Re 1994; Kandler et al. 2012): the exact bound at the
    *measured* state turned into linear bounds on ``v``, applied at every predicted step (a QP);
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

Each method runs with the hold its prediction assumes (``v`` for the first four, ``u`` for the
NMPC); a :class:`Variant` runs a method with the other hold (the FL methods with ``u`` held), or the
MIQP with the margin ``u_max^{eps+Delta}`` of eq. (eq-09-margin), ``Delta`` the certified drift of
``Phi`` over one sampling interval (:func:`with_drift`; stored as ``delta``, the option's name is ``"eps+delta"``).
:func:`study_variants` lists the rows of the
chapter.

The metrics of one closed-loop run are computed by :func:`run_metrics`; :func:`monte_carlo`
draws the scenarios of :func:`draw_scenarios` and runs every variant on each, one closed loop per task
(:func:`run_row`; :func:`run_scenario` for one scenario).

Same result on every machine: with ``time_limit=None`` (the default of :func:`setting`) every program
is solved to its end and every count of a run is the machine's speed-independent answer; the wall
times are measured, never used. A ``time_limit`` applies to the MIQP (the network constraint) only.
"""
from __future__ import annotations

import dataclasses
import time
from functools import partial
from typing import Callable, Optional, Sequence

import numpy as np

from .. import paper
from ..intersample import intersample_drift
from ..mpc import MPC, sine_reference
from ..nmpc import NonlinearMPC, SaturatedInput
from ..parallel import task_key, using
from ..simulate import simulate
from ..systems import FLSystem
from ..tables import time_stats

Array = np.ndarray

__all__ = ["METHODS", "LABELS", "HOLDS", "MARGINS", "U_TOL", "Variant", "label", "setting", "with_drift",
           "study_variants", "make_controller", "Timed", "draw_scenarios", "scenario_reference", "run_methods",
           "run_metrics", "plan_violations", "settling_time", "run_scenario", "run_row", "relative_costs",
           "TASK_WEIGHT", "task_cost", "monte_carlo",
           "method_table", "extremes",
           "cost_vs_miqp", "cost_summary", "step_field"]

#: The five methods, in the order of the chapter.
METHODS = ("network", "measured", "previous", "saturated", "nmpc")

#: Their names in tables and figures.
LABELS = {"network": "MIQP (network)", "measured": "constant extension", "previous": "previous prediction",
          "saturated": "saturated FL", "nmpc": "nonlinear MPC"}

#: What the actuator holds over a sampling interval (see :func:`flnotes.simulate`).
HOLDS = ("v", "u")

#: The bounds the MIQP may impose at the samples: ``u_max^eps`` (``"eps"``) or ``u_max^{eps+Delta}`` (``"eps+delta"``,
#: eq-09-margin).
MARGINS = ("eps", "eps+delta")

#: The hold each method's prediction assumes: the Brunovsky chain is exact with ``v`` held, the NMPC's RK4
#: prediction holds ``u``.
OWN_HOLD = {"network": "v", "measured": "v", "previous": "v", "saturated": "v", "nmpc": "u"}

#: Tolerance on ``|u| <= u_max`` (round-off of the input at the bound).
U_TOL = 1e-9


@dataclasses.dataclass(frozen=True)
class Variant:
    """One row of the study: a method, the hold it runs with and (the MIQP only) the margin of its bound.

    Parameters
    ----------
    method
        One of :data:`METHODS`.
    hold
        ``"v"`` or ``"u"`` (:data:`HOLDS`); ``None``: the hold the method's prediction assumes
        (:data:`OWN_HOLD`). The NMPC runs with ``u`` held only: its prediction holds ``u``.
    margin
        ``"eps"`` (``u_max^eps``, every method's own bound) or ``"eps+delta"``: the MIQP imposes
        ``|Phi_NN| <= u_max - eps - Delta`` at every predicted step, ``Delta`` the certified drift of
        eq. (eq-09-delta), so that ``|u(t)| <= u_max`` at every instant with ``v`` held. Only for the
        MIQP with ``v`` held (with ``u`` held the bound holds between samples already).

    Attributes
    ----------
    key
        The method's name for its own hold and ``eps`` (so the five methods keep their names), else
        ``"<method> hold u"`` or ``"network eps+delta"``: the ``method`` field of the study's rows.
    """

    method: str
    hold: Optional[str] = None
    margin: str = "eps"

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.hold is None:
            object.__setattr__(self, "hold", OWN_HOLD[self.method])
        if self.hold not in HOLDS:
            raise ValueError(f"hold must be one of {HOLDS} or None (the method's own), got {self.hold!r}")
        if self.margin not in MARGINS:
            raise ValueError(f"margin must be one of {MARGINS}, got {self.margin!r}")
        if self.method == "nmpc" and self.hold != "u":
            raise ValueError("the nonlinear MPC's prediction holds u: run it with hold='u' (or None)")
        if self.margin == "eps+delta" and (self.method != "network" or self.hold != "v"):
            raise ValueError(f"margin='eps+delta' is the MIQP's bound with v held (method='network', hold='v'), got "
                             f"method={self.method!r}, hold={self.hold!r}")

    @property
    def key(self) -> str:
        if self.margin != "eps":
            return f"{self.method} {self.margin}"
        return self.method if self.hold == OWN_HOLD[self.method] else f"{self.method} hold {self.hold}"


def _variant(v) -> Variant:
    """A :class:`Variant` from a Variant, a method name or a key of one."""
    if isinstance(v, Variant):
        return v
    if not isinstance(v, str):
        raise TypeError(f"a variant is a Variant or a method name, got {type(v).__name__}")
    parts = v.split(" ")
    if len(parts) == 1:
        return Variant(v)
    if len(parts) == 3 and parts[1] == "hold":
        return Variant(parts[0], hold=parts[2])
    if len(parts) == 2:
        return Variant(parts[0], margin=parts[1])
    raise ValueError(f"not a variant of the study: {v!r} (a method of {METHODS}, '<method> hold u' or "
                     f"'network eps+delta')")


def label(variant) -> str:
    """The name of a variant (or of its key) in tables and figures: the method's label, with the hold or margin."""
    v = _variant(variant)
    base = LABELS[v.method]
    if v.margin != "eps":
        return f"{base}, eps+Delta"
    return base if v.hold == OWN_HOLD[v.method] else f"{base}, {v.hold} held"


# ----------------------------------------------------------------------------------- setting
def setting(name: str, horizon: int = 10, ts: float = 0.1, time_limit: Optional[float] = None) -> dict:
    """The common setting of every method for system ``name`` (``"Quad-1D"`` or ``"MSD"``).

    Quad-1D: the paper's Sec. IV-B (``t_s = 0.1`` s, ``Q = diag(10, 1, 1)``, ``R = 0.0175``).
    MSD: the book's choice ``Q = diag(10, 1)``, ``R = 0.01`` at the same ``t_s`` and ``N_p``
    (the paper runs no MPC on it). Both use the shipped network and its certified ``eps``.
    ``time_limit`` (seconds per step, or ``None``: solved to the end) applies to the MIQP only (the
    network constraint, plain or with a margin); the QPs and the NMPC are always solved to the end,
    so their runs do not depend on the machine's speed.
    Returns a dict with ``system``, ``net``, ``eps``, ``horizon``, ``ts``, ``Q``, ``R``,
    ``time_limit``, ``rk4_steps`` (the NMPC's RK4 sub-steps per sample), ``to_z_sym`` (the
    coordinate change written for CasADi symbols, or ``None`` when the system's own works) and
    ``name``; :func:`with_drift` adds the certified drift ``delta``.
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
    if time_limit is not None and not (np.isfinite(time_limit) and time_limit > 0):
        raise ValueError(f"time_limit must be a positive number of seconds or None, got {time_limit!r}")
    return dict(name=name, system=paper.system(name), net=net, eps=eps, horizon=int(horizon), ts=float(ts), Q=Q, R=R,
                time_limit=time_limit, rk4_steps=rk4, to_z_sym=to_z)


def with_drift(s: dict) -> dict:
    """The setting ``s`` with the certified drift of ``Phi`` over one sampling interval (eq. eq-09-delta).

    The drift ``Delta(t_s)`` is :func:`flnotes.intersample_drift` at ``s["ts"]`` over the domain box, without a time
    budget (so that the bracket, hence ``Delta``, is the same on every machine). Adds ``drift`` (the
    :class:`flnotes.intersample.DriftBound`), ``delta`` (its upper end: the margin ``Delta``) and ``margin_fits``
    (``eps + Delta < u_max``: only then does ``u_max^{eps+Delta}`` leave any input).
    """
    d = intersample_drift(s["system"], s["ts"], max_time=None)
    if not np.all(d.bracket.converged):
        raise RuntimeError(f"the drift bracket of {s['name']} did not converge within its box budget: {d}")
    delta = float(np.max(d.upper))
    return dict(s, drift=d, delta=delta, margin_fits=bool(s["eps"] + delta < float(s["system"].u_max[0])))


def study_variants(s: dict) -> list:
    """The rows of the chapter for setting ``s``: the five methods with their own hold, the four FL
    methods with ``u`` held, and the MIQP with ``u_max^{eps+Delta}`` where the margin fits
    (``s`` from :func:`with_drift`; without ``delta`` that row is left out)."""
    out = [Variant(m) for m in METHODS] + [Variant(m, hold="u") for m in METHODS if OWN_HOLD[m] == "v"]
    if s.get("margin_fits"):
        out.append(Variant("network", margin="eps+delta"))
    return out


def make_controller(method, s: dict, iterations: int = 1):
    """The controller of ``method`` (one of :data:`METHODS`, or a :class:`Variant`) for the setting ``s``.

    Returns ``(controller, hold)``: by default the FL-based methods hold ``v`` over a sample (their
    prediction model is the Brunovsky chain, exact with ``hold="v"``) and the nonlinear MPC holds
    ``u`` (its RK4 prediction holds ``u``); a :class:`Variant` sets the hold, or the MIQP's margin
    (``eps + s["delta"]`` as its ``eps``; ``s`` from :func:`with_drift`). ``s["time_limit"]`` applies
    to the MIQP only.
    """
    var = _variant(method)
    method = var.method
    common = dict(horizon=s["horizon"], ts=s["ts"], Q=s["Q"], R=s["R"])
    if method == "network":
        eps = s["eps"]
        if var.margin == "eps+delta":
            if "delta" not in s:
                raise ValueError("margin='eps+delta' needs the certified drift: pass compare.with_drift(setting)")
            if not s["margin_fits"]:
                raise ValueError(f"eps + Delta = {s['eps'] + s['delta']:.4g} >= u_max = {s['system'].u_max[0]:.4g} "
                                 f"for {s['name']} at t_s = {s['ts']}: the margin leaves no input; use a shorter t_s")
            eps = s["eps"] + s["delta"]
        return MPC(s["system"], s["net"], eps, time_limit=s["time_limit"], **common), var.hold
    if method in ("measured", "previous"):
        kw = dict(iterations=int(iterations)) if method == "previous" else {}
        return MPC(s["system"], s["net"], s["eps"], constraint=method, **kw, **common), var.hold
    if method == "saturated":
        inner = MPC(s["system"], s["net"], s["eps"], constraint="none", **common)
        return SaturatedInput(inner, s["system"]), var.hold
    return NonlinearMPC(s["system"], rk4_steps=s["rk4_steps"], to_z=s["to_z_sym"], **common), var.hold


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
    applied) is ``Phi(z_pred[k], v_pred[k])``. Only the plans of the method's program count: a
    fallback step's plan (``log.fallback``) is the fallback's, counted in ``fallback_steps`` of
    :func:`run_metrics`. Returns the number of steps with a plan, the number whose plan violates
    the bound at some such step, that fraction, and the largest excess ``max |Phi| - u_max`` (0 when
    none).
    """
    n_plans = n_bad = 0
    excess = 0.0
    fallback = np.asarray(getattr(log, "fallback", np.zeros(len(log.steps), bool)), bool)
    for s, fb in zip(log.steps, fallback):
        if fb:
            continue
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
        ``violating_after_admissible`` (those of them whose step's input passed the controller's own
        check at the sample, ``input_admissible``), ``inadmissible_steps`` (steps flagged not
        admissible), the plan statistics of :func:`plan_violations`, ``infeasible_steps`` (status
        ``"infeasible"``), ``fallback_steps``, ``non_optimal_steps``, ``time_limit_steps`` (status ``"time_limit"``: the
        solve reached its time limit), ``cost`` (the tracking cost
        ``t_s sum_k ||z_k - z_ref(t_k)||_Q^2 + ||v_k||_R^2`` over the steps run: compare it between
        runs of the same length only, see :func:`method_table`), ``rms_error`` (of the position
        ``z_1`` over the run), ``settling_s`` (:func:`settling_time` of ``z_1`` with ``band``), the
        per-step wall times ``ms_min``, ``ms_median``, ``ms_max`` and ``over_ts``, the steps whose
        wall time exceeded the sampling period (the machine's, like the times).
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
    bad_interval = fine_bad.reshape(K, n_fine).any(axis=1) if K else np.zeros(0, bool)
    admissible = np.array([step_field(s, "input_admissible") is not False for s in log.steps[:K]], bool)
    st = time_stats(log.solve_time)
    pos = log.z[:, 0] - Zr[:, 0]
    out = dict(
        steps=K, completed=not log.message, message=log.message,
        max_abs_u_samples=float(np.abs(log.u).max()) if K else np.nan,
        max_abs_u_between=float(np.abs(log.u_fine).max()) if K else np.nan,
        violating_samples=int((np.abs(log.u) > u_max + tol).any(axis=1).sum()),
        violating_intervals=int(bad_interval.sum()),
        violating_after_admissible=int((bad_interval & admissible).sum()),
        inadmissible_steps=int((~admissible).sum()),
        **plan_violations(log, sysm, tol),
        infeasible_steps=int(sum(str(s).startswith("infeasible") for s in log.status)),
        fallback_steps=int(np.sum(log.fallback)),
        non_optimal_steps=int(sum(s not in ("optimal", "nominal") for s in log.status)),
        time_limit_steps=int(sum(s == "time_limit" for s in log.status)),
        cost=cost, rms_error=float(np.sqrt(np.mean(pos**2))),
        settling_s=settling_time(log.t, pos, band),
        ms_min=st["min_ms"], ms_median=st["median_ms"], ms_max=st["max_ms"],
        over_ts=int(np.sum(np.asarray(log.solve_time, float) > log.ts)),
    )
    return out


# ----------------------------------------------------------------------------------- runs
def run_methods(s: dict, z0: Array, reference: Callable[[Array], Array], t_final: float,
                methods: Optional[Sequence] = None, iterations: int = 1) -> dict:
    """Run each method (or :class:`Variant`) once in closed loop on the true plant; returns ``{key: log}``.

    Every controller is wrapped in :class:`Timed` (the same timing for all) and runs with the
    hold of its variant (:func:`make_controller`: by default the hold its prediction assumes);
    every run checks the domain box. ``methods`` defaults to :data:`METHODS`; the keys are the
    variants' :attr:`Variant.key` (the method names for the five methods as they are).
    """
    logs = {}
    for var in map(_variant, METHODS if methods is None else methods):
        ctrl, hold = make_controller(var, s, iterations)
        log = simulate(s["system"], Timed(ctrl), t_final, s["ts"], z0=z0, reference=reference, hold=hold,
                       net=s["net"] if var.method != "nmpc" else None, check_domain=True, progress=False)
        log.controller = ctrl
        logs[var.key] = log
    return logs


def run_scenario(s: dict, sc: dict, t_final: float, methods: Optional[Sequence] = None, band: float = 0.1,
                 iterations: int = 1) -> list[dict]:
    """One scenario of the Monte Carlo: every method (or variant) on it, one row of :func:`run_metrics` each.

    Rows also carry the scenario (``scenario``, ``amplitude``, ``omega``, ``u_ref_max``,
    ``bound_active``), ``method`` (the variant's key), ``hold``, ``margin`` and ``cost_vs_miqp``: the
    run's tracking cost over the MIQP's (``"network"``, ``v`` held, ``eps``) on this scenario, NaN
    unless both runs completed. The cost sums over the steps run, so a run that stopped early would
    look cheap: only runs of the full length are compared. Each row is :func:`run_row` of one variant:
    a run depends on its scenario and variant only, not on the runs before it.
    """
    variants = [_variant(m) for m in (METHODS if methods is None else methods)]
    return relative_costs([run_row(s, sc, t_final, v, band, iterations) for v in variants])


def run_row(s: dict, sc: dict, t_final: float, method, band: float = 0.1, iterations: int = 1) -> dict:
    """One closed loop of the Monte Carlo: ``method`` (a method name, a key or a :class:`Variant`) on scenario
    ``sc``; the row of :func:`run_scenario` without ``cost_vs_miqp`` (which needs the scenario's other rows)."""
    var = _variant(method)
    ref = scenario_reference(s["system"], sc)
    log = run_methods(s, sc["z0"], ref, t_final, [var], iterations)[var.key]
    return dict(scenario=sc["index"], method=var.key, hold=var.hold, margin=var.margin,
                amplitude=sc["amplitude"], omega=sc["omega"], u_ref_max=sc["u_ref_max"],
                bound_active=sc["bound_active"], **run_metrics(log, ref, s["Q"], s["R"], band))


def relative_costs(rows: Sequence[dict]) -> list[dict]:
    """The rows of one scenario with ``cost_vs_miqp``: cost over the MIQP's (``"network"``), completed runs only.

    The tracking cost of :func:`run_metrics` sums over the steps run, so a run that stopped early
    would look cheap: a ratio is computed only when both this run and the MIQP's completed (else NaN).
    """
    if len({r["scenario"] for r in rows}) > 1:
        raise ValueError("relative_costs compares the runs of one scenario: pass the rows of one scenario")
    base = next((r for r in rows if r["method"] == "network" and r["completed"] and r["cost"] > 0), None)
    return [dict(r, cost_vs_miqp=r["cost"] / base["cost"] if base is not None and r["completed"] else np.nan)
            for r in rows]


def extremes(table: dict, column: str, keys: Sequence[str]) -> dict:
    """The smallest and largest ``column`` among the lines ``keys`` of a keyed :func:`method_table`.

    ``table`` maps variant keys to lines; returns ``min``, ``max`` and the methods at each, ``at_min``
    and ``at_max`` (their labels: "A", "A and B", "A, B and C").
    """
    if not keys:
        raise ValueError("keys must name at least one line of the table")
    vals = {k: table[k][column] for k in keys}
    lo, hi = min(vals.values()), max(vals.values())

    def names(at) -> str:
        n = [table[k]["method"] for k in keys if vals[k] == at]
        return n[0] if len(n) == 1 else ", ".join(n[:-1]) + " and " + n[-1]

    return dict(min=lo, max=hi, at_min=names(lo), at_max=names(hi))


#: Relative CPU time of one closed loop per method, to start the longest tasks of :func:`monte_carlo` first
#: (measured on the MSD's Monte Carlo of the benchmark, N_p = 10: the MIQP took most of a scenario; only the
#: order in which the tasks start depends on it, never a result).
TASK_WEIGHT = {"network": 8.0, "nmpc": 2.0, "previous": 1.0, "measured": 1.0, "saturated": 0.5}


def task_cost(s: dict, sc: dict, t_final: float, variant) -> float:
    """A guess of the relative run time of one task of :func:`monte_carlo` (``variant`` on scenario ``sc``).

    :data:`TASK_WEIGHT` of the method times the steps times ``N_p``, for the MIQP also times
    ``1 + min(u_ref_max / u_max, 1)``: the closer the reference's input comes to the bound, the more of its binaries
    are undecided, and a reference beyond the bound (``bound_active``) doubles it (on the benchmark's MSD
    scenarios the longest loops were those whose reference came closest to the bound). Used to start the
    longest tasks first, so that the last ones to end are short; the results do not depend on it.
    """
    var = _variant(variant)
    near = min(float(sc["u_ref_max"]) / float(np.max(s["system"].u_max)), 1.0)
    w = TASK_WEIGHT[var.method] * (1.0 + near if var.method == "network" else 1.0)
    return w * (t_final / s["ts"]) * s["horizon"]


def _row_task(s: dict, t_final: float, band: float, iterations: int, task: tuple) -> dict:
    """One task of :func:`monte_carlo`: :func:`run_row` of one (scenario, variant)."""
    sc, var = task
    return run_row(s, sc, t_final, var, band, iterations)


def monte_carlo(s: dict, scenarios: Sequence[dict], t_final: float, methods: Optional[Sequence] = None,
                band: float = 0.1, iterations: int = 1, workers: Optional[int] = None, client=None,
                progress: bool = False, resume: bool = False) -> list[dict]:
    """Every method (or variant) on every scenario: the rows of :func:`run_scenario`, scenario by scenario.

    Each closed loop (a scenario and a variant, :func:`run_row`) is one task of
    :class:`flnotes.parallel.Executor`: in this process by default, on ``workers`` local processes, or on a
    Dask ``client``. The tasks start longest first (:func:`task_cost`), so that the workers end together; the
    rows come back in the order of the scenarios and variants whatever runs them, and ``cost_vs_miqp`` is
    computed here, per scenario (:func:`relative_costs`). ``progress`` shows a bar; ``resume`` keeps each
    finished run's row in the cache folder and reuses it when the same run is asked again. Under a
    ``time_limit``, a run's plans depend on the time its solves take (rows with a late step can differ between
    runs); the timing columns (``ms_*``, ``over_ts``) always do. The methods (variants) and the scenarios
    (their ``index``) must be distinct (``ValueError`` naming the one repeated). A stored row is refused if its
    file holds another run's (:meth:`flnotes.parallel.Executor.map`).
    """
    variants = [_variant(m) for m in (METHODS if methods is None else methods)]
    for what, names in (("methods", [v.key for v in variants]), ("scenarios", [sc["index"] for sc in scenarios])):
        twice = sorted({n for n in names if names.count(n) > 1}, key=names.index)
        if twice:
            raise ValueError(f"{what} must be distinct; given more than once: {', '.join(map(repr, twice))} "
                             f"(each run would count twice in the table): give each once")
    tasks = [(sc, v) for sc in scenarios for v in variants]
    keys = None
    if resume:
        net_key = [np.asarray(a).tolist() for a in (*s["net"].W, *s["net"].b)]
        keys = [task_key("monte_carlo", s["name"], s["eps"], s.get("delta"), s["horizon"], s["ts"],
                         np.asarray(s["Q"]).tolist(), np.asarray(s["R"]).tolist(), s["time_limit"], net_key, t_final,
                         band, iterations, dict(sc), repr(v)) for sc, v in tasks]
    with using(workers, client) as ex:
        rows = ex.map(partial(_row_task, s, t_final, band, iterations), tasks, keys=keys,
                      cache="monte_carlo" if resume else None, desc="Monte Carlo", progress=progress,
                      cost=[task_cost(s, sc, t_final, v) for sc, v in tasks])
    n = len(variants)
    return [r for k in range(0, len(rows), n) for r in relative_costs(rows[k:k + n])]


def method_table(rows: Sequence[dict], methods: Optional[Sequence] = None, only_active: bool = False,
                 time_limit: Optional[float] = None) -> list[dict]:
    """One line per method (or variant) from the rows of :func:`monte_carlo` (or of single runs).

    ``time_limit`` is the setting's (``s["time_limit"]``): it applies to the MIQP only, so with a limit the
    MIQP's lines depend on the machine that ran them. Column ``solved`` says it (``"to the end"``, or
    ``"time limit"``) and the label of such a line ends with ``" *"``; no conclusion may rest on those lines.

    Columns: hold, scenarios, runs that completed, the largest ``|u|`` at the samples and between
    them over all runs, runs and steps violating the bound at the samples, intervals violating it
    between samples, the fraction of plans violating the true bound at a later predicted step,
    infeasible and fallback steps, the steps not solved to the end (``non_optimal``) and those that
    reached the time limit (``time_limit``), the median tracking cost relative to the MIQP's on the same
    scenario over the scenarios where both runs completed (``cost_vs_miqp`` of :func:`run_scenario`)
    and how many those are (``cost_runs``), ``settled``: the fraction of runs whose position error ``|z_1 - x_ref|``
    stays within the band of :func:`run_metrics` (0.1 by default) from some sampling instant to the end of the run
    (:func:`settling_time` finite), the per-step wall times pooled over all runs
    (min of the minima, median of the medians, max of the maxima) and the steps slower than ``t_s``.
    ``methods`` defaults to the variants present in ``rows``, in their order.
    """
    if methods is None:
        methods = list(dict.fromkeys(r["method"] for r in rows))
    out = []
    for var in map(_variant, methods):
        rr = [r for r in rows if r["method"] == var.key and (r["bound_active"] or not only_active)]
        if not rr:
            continue
        plans = sum(r["plans"] for r in rr)
        ratio = [r["cost_vs_miqp"] for r in rr if np.isfinite(r["cost_vs_miqp"])]
        limited = time_limit is not None and var.method == "network"
        out.append(dict(
            method=label(var) + (" *" if limited else ""), solved="time limit" if limited else "to the end",
            hold=var.hold, scenarios=len(rr), completed=int(sum(r["completed"] for r in rr)),
            max_u_samples=max(r["max_abs_u_samples"] for r in rr), max_u_between=max(r["max_abs_u_between"] for r in rr),
            runs_violating=int(sum(r["violating_samples"] > 0 for r in rr)),
            violating_samples=int(sum(r["violating_samples"] for r in rr)),
            violating_intervals=int(sum(r["violating_intervals"] for r in rr)),
            plans_violating=(sum(r["plans_violating"] for r in rr) / plans) if plans else np.nan,
            infeasible=int(sum(r["infeasible_steps"] for r in rr)), fallback=int(sum(r["fallback_steps"] for r in rr)),
            non_optimal=int(sum(r["non_optimal_steps"] for r in rr)),
            time_limit=int(sum(r["time_limit_steps"] for r in rr)),
            cost_vs_miqp=float(np.median(ratio)) if ratio else np.nan, cost_runs=len(ratio),
            settled=float(np.mean([np.isfinite(r["settling_s"]) for r in rr])),
            ms_min=float(np.nanmin([r["ms_min"] for r in rr])), ms_median=float(np.nanmedian([r["ms_median"] for r in rr])),
            ms_max=float(np.nanmax([r["ms_max"] for r in rr])), over_ts=int(sum(r["over_ts"] for r in rr)),
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


def cost_summary(rows: Sequence[dict]) -> dict:
    """The NMPC's cost against the MIQP's over the rows of :func:`cost_vs_miqp` to compare (those where all three
    solves are optimal), in relative and in absolute terms.

    A ratio on a tiny cost (late in a run, near the reference) is dominated by that smallness: 0.05 against 0.04 is
    +25 %. So next to the relative differences (``rel_median``, ``rel_min``, ``rel_max``, NMPC started from the MIQP's
    plan over the MIQP's optimum, minus 1) this gives the absolute ones, ``abs_min`` and ``abs_max``
    (NMPC minus MIQP), and the cost-weighted ratio ``weighted`` = sum of the NMPC's costs over the sum of the MIQP's,
    minus 1, which large costs dominate; ``n`` is the number of rows.
    """
    if not rows:
        raise ValueError("cost_summary needs at least one row of cost_vs_miqp to compare")
    J = np.array([r["miqp"] for r in rows], float)
    Jn = np.array([r["nmpc_from_miqp"] for r in rows], float)
    rel = np.array([r["rel_from_miqp"] for r in rows], float)
    d = Jn - J
    return dict(n=len(rows), rel_median=float(np.median(rel)), rel_min=float(rel.min()), rel_max=float(rel.max()),
                abs_min=float(d.min()), abs_max=float(d.max()), weighted=float(Jn.sum() / J.sum() - 1.0))
