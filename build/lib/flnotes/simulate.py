"""Closed-loop simulation on the true plant: the one place that owns time.

At each sampling instant ``t_k = k t_s`` the controller sees ``z_k = to_z(x(t_k))``
and answers ``v_k``. Between samples the true plant ``x' = f(x, u)`` is
integrated accurately (``scipy.integrate.solve_ivp``) with either

* ``hold="v"`` (default): ``v`` is held and ``u(t) = Phi(z(t), v_k)`` is
  recomputed continuously, so the plant is exactly linearized, ``z' = A z + B v``;
  the bound ``|Phi_NN| <= u_max^eps`` is only imposed at ``t_k``, and ``u(t)``
  may leave ``[-u_max, u_max]`` between samples;
* ``hold="u"``: ``u_k = Phi(z_k, v_k)`` is held (a zero-order hold on the true
  input); ``|u| <= u_max`` then holds at all times, but the plant is no longer
  exactly linearized between samples.

Any controller plugs in through the :class:`Controller` protocol; a plain
function ``k(z) -> v`` is accepted too.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Protocol, Union, runtime_checkable

import numpy as np
from scipy.integrate import solve_ivp

from ._checks import as_vector
from .systems import FLSystem

Array = np.ndarray


@dataclass
class StepResult:
    """A controller's answer at one sampling instant.

    Attributes
    ----------
    v
        The virtual input to apply, shape (m,).
    status
        ``"optimal"`` when the program was solved to optimality, ``"nominal"``
        for a plain feedback law; anything else (``"infeasible"``,
        ``"time_limit"``, ``"error"``, ...) says why ``v`` is not an optimum.
    solve_time
        Wall-clock seconds spent by the controller.
    fallback
        True when ``v`` comes from the controller's documented fallback rather
        than from a solved program.
    info
        Anything else worth logging: objective, gap, nodes, predicted
        trajectories, ``Phi_NN`` at the solution, ...
    """

    v: Array
    status: str = "optimal"
    solve_time: float = 0.0
    fallback: bool = False
    info: dict = field(default_factory=dict)


@runtime_checkable
class Controller(Protocol):
    """What :func:`simulate` needs: ``step(z, t, reference) -> StepResult``."""

    def step(self, z: Array, t: float, reference: Optional[Callable[[Array], Array]] = None) -> StepResult:
        ...


class FeedbackLaw:
    """Wrap a plain law ``k(z) -> v`` (e.g. the nominal ``k(z) = -K z``) as a :class:`Controller`."""

    def __init__(self, k: Callable[[Array], Array], name: str = "k(z)"):
        self.k, self.name = k, name

    def __call__(self, z: Array) -> Array:
        return np.atleast_1d(np.asarray(self.k(np.asarray(z, float)), float))

    def step(self, z: Array, t: float, reference=None) -> StepResult:
        t0 = time.perf_counter()
        v = self(z)
        return StepResult(v=v, status="nominal", solve_time=time.perf_counter() - t0)


@dataclass
class SimLog:
    """Everything a closed-loop run recorded.

    Sample arrays have one row per sampling instant ``t_k`` (``t``, ``x``,
    ``z``: K+1 rows; ``v``, ``u``, ``u_nn``, ``solve_time``, ``status``: K rows).
    ``t_fine``, ``x_fine``, ``z_fine``, ``u_fine`` resolve the true input
    between samples.
    """

    system: FLSystem
    ts: float
    hold: str
    t: Array
    x: Array
    z: Array
    v: Array
    u: Array
    u_nn: Optional[Array]
    solve_time: Array
    status: list
    fallback: Array
    t_fine: Array
    x_fine: Array
    z_fine: Array
    u_fine: Array
    in_domain: Array
    steps: list = field(default_factory=list)
    message: str = ""

    @property
    def n_steps(self) -> int:
        return len(self.v)

    def summary(self) -> dict[str, Any]:
        """The checks a chapter prints: true |u| vs u_max, solve times, fallbacks, final ||z||."""
        st = self.solve_time * 1e3 if len(self.solve_time) else np.array([np.nan])
        out = dict(
            steps=self.n_steps,
            u_max=self.system.u_max.tolist(),
            max_abs_u_samples=np.abs(self.u).max(0).tolist() if self.n_steps else [],
            max_abs_u_between=np.abs(self.u_fine).max(0).tolist() if len(self.u_fine) else [],
            u_within_bound_at_samples=bool(np.all(np.abs(self.u) <= self.system.u_max + 1e-9)),
            u_within_bound_between=bool(np.all(np.abs(self.u_fine) <= self.system.u_max + 1e-9)),
            final_norm_z=float(np.linalg.norm(self.z[-1])),
            fallback_steps=int(self.fallback.sum()),
            non_optimal_steps=int(sum(s not in ("optimal", "nominal") for s in self.status)),
            left_domain_steps=int((~self.in_domain).sum()),
            solve_ms_min=float(np.min(st)), solve_ms_median=float(np.median(st)),
            solve_ms_max=float(np.max(st)), solve_ms_mean=float(np.mean(st)),
            message=self.message,
        )
        if self.u_nn is not None and self.n_steps:
            out["max_abs_u_nn"] = np.abs(self.u_nn).max(0).tolist()
        return out


def simulate(system: FLSystem, controller: Union[Controller, Callable[[Array], Array]], t_final: float, ts: float,
             x0: Optional[Array] = None, z0: Optional[Array] = None,
             reference: Optional[Callable[[Array], Array]] = None, hold: str = "v", net=None,
             n_fine: int = 10, fallback: Optional[Callable[[Array], Array]] = None,
             progress: Optional[bool] = None, rtol: float = 1e-8, atol: float = 1e-10) -> SimLog:
    """Run the sampled closed loop on the true plant ``x' = f(x, u)``, ``u = Phi(z, v)``.

    Parameters
    ----------
    system
        The plant and its linearizing map.
    controller
        A :class:`Controller` (``step(z, t, reference) -> StepResult``) or a
        plain function ``k(z) -> v``.
    t_final, ts
        Horizon of the run and sampling time ``t_s`` (seconds).
    x0, z0
        Initial plant state, or initial linearizing state (converted by
        ``system.to_x``). Give exactly one.
    reference
        Optional ``t -> z_ref(t)``, vectorized: an array of times (T,) gives
        (T, n_z). Passed on to the controller.
    hold
        ``"v"`` (hold v, recompute u continuously: exact linearization) or
        ``"u"`` (hold u between samples); see the module docstring.
    net
        Optional network, to log ``Phi_NN(z_k, v_k)`` next to the true ``u``.
    n_fine
        Points per sampling interval recorded for ``u(t)`` between samples.
    fallback
        ``z -> v`` applied when the controller raises; default: the previous
        ``v`` (zero at the first step). Such steps are flagged and counted.
    progress
        Print a one-line progress indicator. ``True``: every 5 % of the run;
        ``None`` (default): only on long runs, every 5 s of wall-clock time
        once the run has lasted that long (short runs print nothing);
        ``False``: never.

    Returns
    -------
    SimLog
        The run. It never ends with a bare traceback: if the plant leaves the
        region where ``Phi`` is defined, the run stops there and
        ``log.message`` says why.
    """
    if hold not in ("v", "u"):
        raise ValueError(f"hold must be 'v' (hold v, u = Phi(z(t), v)) or 'u' (hold u), got {hold!r}")
    if not (np.isfinite(ts) and ts > 0 and np.isfinite(t_final) and t_final >= ts):
        raise ValueError(f"need 0 < ts <= t_final, got ts={ts!r}, t_final={t_final!r}")
    if (x0 is None) == (z0 is None):
        raise ValueError("give exactly one initial condition: x0 (plant state) or z0 (linearizing state)")
    ctrl = controller if isinstance(controller, Controller) else FeedbackLaw(controller)
    if hasattr(ctrl, "reset"):
        ctrl.reset()
    x = np.asarray(system.to_x(as_vector(z0, system.n_z, "z0")) if z0 is not None else x0, float).copy()
    if not np.all(np.isfinite(x)):
        raise ValueError(f"x0 contains NaN or inf: {x}")
    K = int(round(t_final / ts))
    every_s = 5.0 if progress is None else 0.0  # progress=None: time-based, silent on short runs
    progress = True if progress is None else bool(progress)
    last_print, printed = time.perf_counter(), False
    m = system.m

    ts_list, xs, zs, vs, us, unn, times, stats, fbs, steps = [0.0], [x.copy()], [system.to_z(x)], [], [], [], [], [], [], []
    t_fine, x_fine, u_fine = [], [], []
    v_prev = np.zeros(m)
    message = ""
    t_start = time.perf_counter()
    for k in range(K):
        t = k * ts
        z = np.asarray(system.to_z(x), float)
        try:
            res = ctrl.step(z, t, reference)
            v = as_vector(res.v, m, "controller output v")
        except Exception as exc:  # the run goes on with the documented fallback
            v = as_vector(fallback(z), m, "fallback v") if fallback is not None else v_prev.copy()
            res = StepResult(v=v, status=f"error: {type(exc).__name__}: {exc}", solve_time=np.nan, fallback=True)
        try:
            u_k = system.Phi(z, v)
            if hold == "v":
                rhs = lambda _t, xx: system.f(xx, system.Phi(np.asarray(system.to_z(xx), float), v))
            else:
                rhs = lambda _t, xx, uu=u_k: system.f(xx, uu)
            grid = np.linspace(t, t + ts, n_fine + 1)
            sol = solve_ivp(rhs, (t, t + ts), x, t_eval=grid, rtol=rtol, atol=atol, method="RK45")
            if not sol.success:
                raise RuntimeError(sol.message)
        except Exception as exc:
            message = f"stopped at t = {t:.3f} s: {type(exc).__name__}: {exc}"
            break
        X = sol.y.T
        Zs = np.array([system.to_z(xx) for xx in X], float)
        if system.extra is not None:  # Remark 1: leaving phi(z, v) <= 0 voids the linearization
            phi_x = np.asarray(system.extra(Zs, np.repeat(v[None], len(Zs), axis=0)), float)
            if np.any(phi_x > 0):
                j = int(np.argmax(phi_x.max(axis=1) > 0))
                message = (f"stopped at t = {grid[j]:.3f} s: Remark 1's operating constraint is violated "
                           f"(max varphi(z, v) = {phi_x.max():.3g} > 0), the linearizing map is not valid there")
                break
        try:
            U = (system.Phi(Zs[:-1], np.repeat(v[None], len(Zs) - 1, axis=0)) if hold == "v"
                 else np.repeat(u_k[None], len(X) - 1, axis=0))
        except Exception as exc:
            message = f"stopped at t = {t:.3f} s: {type(exc).__name__}: {exc}"
            break
        t_fine.append(grid[:-1]), x_fine.append(X[:-1]), u_fine.append(U)
        vs.append(v), us.append(u_k), times.append(res.solve_time), stats.append(res.status), fbs.append(res.fallback)
        steps.append(res)
        if net is not None:
            unn.append(net(system.stack(z, v)))
        x = X[-1].copy()
        v_prev = v
        ts_list.append(t + ts), xs.append(x.copy()), zs.append(np.asarray(system.to_z(x), float))
        now = time.perf_counter()
        if progress and ((every_s and now - last_print >= every_s)
                         or (not every_s and (k + 1) % max(1, K // 20) == 0)):
            print(f"\rstep {k + 1}/{K} ({100 * (k + 1) // K}%), {now - t_start:.1f} s", end="", flush=True)
            last_print, printed = now, True
    if printed:
        print(flush=True)
    Z = np.array(zs)
    zf = np.vstack(x_fine) if x_fine else np.zeros((0, len(x)))
    return SimLog(
        system=system, ts=ts, hold=hold, t=np.array(ts_list), x=np.array(xs), z=Z,
        v=np.array(vs).reshape(-1, m), u=np.array(us).reshape(-1, m),
        u_nn=np.array(unn).reshape(-1, m) if net is not None else None,
        solve_time=np.array(times, float), status=stats, fallback=np.array(fbs, bool),
        t_fine=np.concatenate(t_fine) if t_fine else np.zeros(0), x_fine=zf,
        z_fine=np.array([system.to_z(xx) for xx in zf]).reshape(-1, system.n_z),
        u_fine=np.vstack(u_fine) if u_fine else np.zeros((0, m)),
        in_domain=system.in_domain(Z), steps=steps, message=message,
    )
