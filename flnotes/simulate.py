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

What stops a run, and what does not
-----------------------------------
* Bad arguments raise before the first step: a start ``z0`` (or ``x0``)
  outside the domain box when the controller carries a network, a reference
  of the wrong shape, ``ts <= 0``, ...
* A controller that raises :class:`flnotes.SolverFailure` (its documented
  solver outcome: infeasible, time limit, solver failure) gets the fallback
  input; the step is flagged and the log says why. Any other exception of the
  controller is raised as it is: a programming error is never turned into a
  fallback.
* Where the plant cannot go on (``Phi`` singular, the integration fails, the
  state leaves the domain box of a network controller) the run stops and
  ``log.message`` says where and why.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Protocol, Union, runtime_checkable

import numpy as np
from scipy.integrate import solve_ivp

from ._checks import as_state, as_floats, as_vector, check_bool, check_int, check_number
from .errors import SolverFailure
from .network import ReLUNet
from .result import StepResult
from .systems import FLSystem

Array = np.ndarray

#: Exceptions that signal a mistake in the code or the call, never a place the plant cannot go: always raised.
#: The most sampling intervals of one run (``t_final / ts``): a sampling time given in the wrong unit is an error,
#: not a run that never ends.
MAX_STEPS = 10_000_000

_PROGRAMMING_ERRORS = (TypeError, AttributeError, NameError, ImportError, KeyError, IndexError, NotImplementedError)


@runtime_checkable
class Controller(Protocol):
    """What :func:`simulate` needs: ``step(z, t, reference) -> StepResult``."""

    def step(self, z: Array, t: float, reference: Optional[Callable[[Array], Array]] = None) -> StepResult:
        ...


class FeedbackLaw:
    """Wrap a plain law ``k(z) -> v`` (e.g. the nominal ``k(z) = -K_nominal z``) as a :class:`Controller`."""

    def __init__(self, k: Callable[[Array], Array], name: str = "k(z)"):
        self.k, self.name = k, name

    def __call__(self, z: Array) -> Array:
        return np.atleast_1d(as_floats(self.k(np.asarray(z, float)), "the feedback law's v"))

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
             progress: Optional[bool] = None, rtol: float = 1e-8, atol: float = 1e-10,
             check_domain: Optional[bool] = None) -> SimLog:
    """Run the sampled closed loop on the true plant ``x' = f(x, u)``, ``u = Phi(z, v)``.

    Parameters
    ----------
    system
        The plant and its linearizing map.
    controller
        A :class:`Controller` (``step(z, t, reference) -> StepResult``) or a
        plain function ``k(z) -> v``.
    t_final, ts
        Horizon of the run and sampling time ``t_s`` (seconds). The run has ``K = round(t_final / ts)``
        sampling intervals and ends at ``K ts`` (``t_final = 0.25, ts = 0.1`` ends at 0.2): the log's
        ``t`` holds the times.
    x0, z0
        Initial plant state, or initial linearizing state (converted by
        ``system.to_x``). Give exactly one.
    reference
        Optional ``t -> z_ref(t)``, vectorized: an array of times (T,) gives
        (T, n_z) (a constant reference may return (n_z,)). Passed on to the
        controller. It is called once before the first step, on ``t = 0`` and
        on a few times of the run, and a wrong shape or a NaN stops there.
    hold
        ``"v"`` (hold v, recompute u continuously: exact linearization) or
        ``"u"`` (hold u between samples); see the module docstring.
    net
        Optional network, to log ``Phi_NN(z_k, v_k)`` next to the true ``u``.
    n_fine
        Points per sampling interval recorded for ``u(t)`` between samples.
    fallback
        ``z -> v`` applied when the controller raises
        :class:`flnotes.SolverFailure` (infeasible program, time limit without
        an admissible incumbent, solver failure); default: the previous ``v``
        (zero at the first step). Such steps are flagged (``log.fallback``),
        their status reads ``"error"`` (the message ``"SolverFailure: <message>"``) and
        ``log.steps[k].info`` holds ``solver_status`` and ``fallback_rule``.
        Any other exception of the controller (``ValueError``, ``TypeError``,
        ``ImportError``, ...) is a mistake, not a solver outcome: it stops the
        run and is raised with its message.
    progress
        Print a one-line progress indicator. ``True``: every 5 % of the run;
        ``None`` (default): only on long runs, every 5 s of wall-clock time
        once the run has lasted that long (short runs print nothing);
        ``False``: never.
    rtol, atol
        Tolerances of the plant's integration (``solve_ivp``).
    check_domain
        Whether the state must stay in the domain box ``system.lo[:n_z] <= z <=
        system.hi[:n_z]``, the box where the network was trained and ``eps``
        certified. ``None`` (default): when the controller carries a network
        (an attribute ``net``, as :class:`flnotes.ClfCbfController` and
        :class:`flnotes.MPC` do); a plain law ``k(z)`` may run anywhere.
        ``True``/``False`` force it on or off. When on, a start outside the
        box raises ``ValueError`` before the first step, and a state that
        leaves the box later stops the run there (``log.message`` says so).

    Returns
    -------
    SimLog
        The run. It never ends with a bare traceback: if the plant leaves the
        region where ``Phi`` is defined (or, with ``check_domain``, the domain
        box), the run stops there and ``log.message`` says why.

    Raises
    ------
    ValueError
        For a bad argument (``z0``/``x0`` of the wrong shape or outside the
        domain box, a reference of the wrong shape, ``ts``, ``hold``, ...).
    TypeError
        For a ``system``, ``controller``, ``reference``, ``fallback`` or
        ``net`` of the wrong kind, or a controller whose ``step`` does not
        return a :class:`StepResult`.
    Exception
        Any exception of the controller other than
        :class:`flnotes.SolverFailure`, as it was raised.
    """
    t_final, ts, n_fine, rtol, atol = _check_args(system, controller, t_final, ts, x0, z0, hold, net, n_fine,
                                                  fallback, rtol, atol)
    ctrl = controller if isinstance(controller, Controller) else FeedbackLaw(controller)
    if progress is not None:
        progress = check_bool(progress, "progress", "True, False or None (only on long runs)")
    if check_domain is None:
        check_domain = isinstance(getattr(ctrl, "net", None), ReLUNet)
    check_domain = check_bool(check_domain, "check_domain", "whether to stop when z leaves the domain box")
    m = system.m
    if z0 is not None:
        z_start = as_state(z0, system.n_z, "z0")
        if check_domain:
            _check_start(system, z_start, "z0")
        x = np.asarray(system.to_x(z_start), float).reshape(-1).copy()
    else:
        x = as_floats(x0, "x0").reshape(-1).copy()
        if not np.all(np.isfinite(x)):
            raise ValueError(f"x0 contains NaN or inf: {x}")
        z_start = as_vector(system.to_z(x), system.n_z, f"to_z(x0) for x0 = {x}")
        if check_domain:
            _check_start(system, z_start, "x0", x)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"to_x(z0) contains NaN or inf: {x}")
    if reference is not None:
        _check_reference(reference, system.n_z, t_final, ts)
    if hasattr(ctrl, "reset"):
        ctrl.reset()
    K = int(round(t_final / ts))
    every_s = 5.0 if progress is None else 0.0  # progress=None: time-based, silent on short runs
    progress = True if progress is None else bool(progress)
    last_print, printed = time.perf_counter(), False

    ts_list, xs, zs, vs, us, unn, times, stats, fbs, steps = [0.0], [x.copy()], [system.to_z(x)], [], [], [], [], [], [], []
    t_fine, x_fine, u_fine = [], [], []
    v_prev = np.zeros(m)
    message = ""
    t_start = time.perf_counter()
    try:
        for k in range(K):
            t = k * ts
            z = np.asarray(system.to_z(x), float)
            if check_domain and not system.in_domain(z)[0]:
                message = (f"stopped at t = {t:.3f} s: z = {np.array2string(z, precision=4)} left the domain box "
                           f"lo = {np.array2string(system.lo[:system.n_z], precision=3)}, "
                           f"hi = {np.array2string(system.hi[:system.n_z], precision=3)} where the network and eps are "
                           f"valid (pass check_domain=False to run on without the guarantee)")
                break
            try:
                res = ctrl.step(z, t, reference)
            except SolverFailure as exc:  # the documented solver outcome: the documented fallback, flagged
                v = as_vector(fallback(z), m, "fallback(z)") if fallback is not None else v_prev.copy()
                rule = "fallback(z)" if fallback is not None else ("the previous v" if k else "v = 0 (first step)")
                res = StepResult(v=v, status="error", solve_time=np.nan, fallback=True, message=f"{type(exc).__name__}: {exc}",
                                 info=dict(solver_status=exc.status, fallback_rule=f"simulate applied {rule}"))
            if not isinstance(res, StepResult):
                raise TypeError(f"controller.step(z, t, reference) must return a flnotes.StepResult, got "
                                f"{type(res).__name__} at t = {t:.3f} s")
            v = as_vector(res.v, m, f"the controller's v at t = {t:.3f} s")
            try:
                u_k = system.Phi(z, v)
            except _PROGRAMMING_ERRORS:
                raise
            except Exception as exc:
                if k == 0:  # at the start, which the caller chose: a bad Phi or a bad start, not a place the plant went
                    raise
                message = f"stopped at t = {t:.3f} s: {type(exc).__name__}: {exc}"
                break
            try:
                if hold == "v":
                    rhs = lambda _t, xx: system.f(xx, system.Phi(np.asarray(system.to_z(xx), float), v))
                else:
                    rhs = lambda _t, xx, uu=u_k: system.f(xx, uu)
                grid = np.linspace(t, t + ts, n_fine + 1)
                sol = solve_ivp(rhs, (t, t + ts), x, t_eval=grid, rtol=rtol, atol=atol, method="RK45")
                if not sol.success:
                    raise RuntimeError(sol.message)
            except _PROGRAMMING_ERRORS:
                raise
            except Exception as exc:  # Phi or f undefined where the plant went (e.g. a singularity): stop there
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
            except _PROGRAMMING_ERRORS:
                raise
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
    finally:  # also when the run stops by an exception (an interrupt, an error in the reference or the plant)
        if hasattr(ctrl, "finish"):  # a solve the last step answered at its cut-off ends here, not in the caller's code
            ctrl.finish()
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


# ---------------------------------------------------------------------- argument checks
def _check_args(system, controller, t_final, ts, x0, z0, hold, net, n_fine, fallback, rtol,
                atol) -> tuple[float, float, int, float, float]:
    """Refuse bad arguments (naming them); return ``t_final``, ``ts``, ``n_fine``, ``rtol`` and ``atol`` as numbers."""
    if not isinstance(system, FLSystem):
        raise TypeError(f"system must be a flnotes.FLSystem (e.g. fl.msd()), got {type(system).__name__}")
    if not (isinstance(controller, Controller) or callable(controller)):
        raise TypeError(f"controller must be a controller with step(z, t, reference) (ClfCbfController, MPC, ...) "
                        f"or a function k(z) -> v, got {type(controller).__name__}; for a gain matrix K pass "
                        f"lambda z: -K @ z")
    if hold not in ("v", "u"):
        raise ValueError(f"hold must be 'v' (hold v, u = Phi(z(t), v)) or 'u' (hold u), got {hold!r}")
    ts_f = check_number(ts, "ts", "the sampling time in seconds", strict=True)
    tf_f = check_number(t_final, "t_final", "the simulated time in seconds", strict=True)
    if tf_f < ts_f:
        raise ValueError(f"need 0 < ts <= t_final, got ts={ts!r}, t_final={t_final!r}")
    if tf_f / ts_f > MAX_STEPS:
        raise ValueError(f"t_final / ts = {tf_f / ts_f:.3g} sampling intervals is more than MAX_STEPS = {MAX_STEPS:,}: "
                         f"give a larger ts or a shorter t_final (ts is in seconds)")
    if (x0 is None) == (z0 is None):
        raise ValueError("give exactly one initial condition: x0 (plant state) or z0 (linearizing state)")
    if net is not None:
        if not isinstance(net, ReLUNet):
            raise TypeError(f"net must be a flnotes.ReLUNet (to log Phi_NN), got {type(net).__name__}")
        if (net.n_in, net.n_out) != (system.n_in, system.m):
            raise ValueError(f"net maps R^{net.n_in} -> R^{net.n_out} but {system.name} needs (z, v) in "
                             f"R^{system.n_in} -> u in R^{system.m}: pass the network trained on this system")
    n_fine = check_int(n_fine, "n_fine", 1, "points per sampling interval")
    if fallback is not None and not callable(fallback):
        raise TypeError(f"fallback must be a function z -> v, got {type(fallback).__name__}")
    rtol = check_number(rtol, "rtol", "the integrator's relative tolerance", strict=True)
    atol = check_number(atol, "atol", "the integrator's absolute tolerance", strict=True)
    return tf_f, ts_f, n_fine, rtol, atol


def _check_start(system: FLSystem, z: Array, name: str, x: Optional[Array] = None) -> None:
    """``ValueError`` naming ``z0`` (or ``x0``) and the box when the start is outside the domain box."""
    if system.in_domain(z)[0]:
        return
    lo, hi = system.lo[:system.n_z], system.hi[:system.n_z]
    bad = np.flatnonzero((z < lo - 1e-9) | (z > hi + 1e-9))
    where = f"{name} = {np.array2string(np.asarray(x), precision=4)} (z = {np.array2string(z, precision=4)})" \
        if x is not None else f"{name} = {np.array2string(z, precision=4)}"
    raise ValueError(
        f"{where} is outside the domain box of the network, lo = {np.array2string(lo, precision=3)} <= z <= "
        f"hi = {np.array2string(hi, precision=3)} (component(s) {bad.tolist()}): the error bound eps, hence "
        f"|u| <= u_max, is only guaranteed inside it. Start inside the box, retrain on a larger box, or pass "
        f"check_domain=False to run without the guarantee.")


def _check_reference(reference, n_z: int, t_final: float, ts: float) -> None:
    """Call ``reference`` on ``t = 0`` and on a few times of the run; ``ValueError`` naming it on a bad answer."""
    if not callable(reference):
        raise TypeError(f"reference must be a function t -> z_ref(t) (times (T,) -> (T, {n_z})), got "
                        f"{type(reference).__name__}; for a constant reference r use lambda t: np.tile(r, (np.size(t), 1))")
    T = n_z + 2  # a number of times that cannot be mistaken for n_z
    times = np.linspace(0.0, float(t_final), T)
    for t, ok_shapes, what in ((0.0, [(n_z,), (1, n_z)], "t = 0.0"),
                               (times, [(T, n_z), (n_z,)], f"an array of {T} times")):
        try:
            r = as_floats(reference(t), "the reference's z_ref")
        except Exception as exc:
            raise ValueError(f"reference must accept a time t and an array of times (T,) and return z_ref of shape "
                             f"(T, {n_z}); called on {what} it raised {type(exc).__name__}: {exc}") from exc
        if r.shape not in ok_shapes:
            raise ValueError(f"reference returned shape {r.shape} on {what}; expected one of {ok_shapes} "
                             f"(one row of n_z = {n_z} reference states per time)")
        if not np.all(np.isfinite(r)):
            raise ValueError(f"reference returned NaN or inf on {what}: {r}")
