"""Systems not in the book: five feedback-linearizable plants defined as a new user would, and the default MPC on them.

The book's defaults (:class:`flnotes.MPCOptions`) were chosen on the book's Quad-1D. Here five other systems
are written through the public :class:`flnotes.FLSystem`, each with its own ReLU network trained by
:func:`flnotes.fit_relu`, its ``eps`` certified by :func:`flnotes.certify_error` and both shipped with the
package (:mod:`flnotes.reference`, files ``flnotes/data/unseen_<name>.{npz,json}``):

========================  =========  ============================================================
name                      role       plant
========================  =========  ============================================================
``Pendulum-gain``         tuning     pendulum whose input gain ``1 + 0.5 cos x_1`` depends on the angle
``Quad-1D-other``         tuning     the 1-D quadrotor with Gamma = 9.81, tau = 0.1, u_max = 0.3
``VdP-gain``              held out   Van der Pol oscillator with input gain ``1 + 0.3 sin x_1``
``Chain4-gain``           held out   4th-order chain, gravity-like drift, input gain ``1.5 + cos x_1``
``Cubic3``                held out   3rd-order chain with cubic drift, input gain ``1 + 0.2 x_2^2``
========================  =========  ============================================================

The *tuning* pair is the one the issue's trial used and may be looked at while the engine's levers are
chosen; the *held-out* three are run only with the default options, never to tune them. Each scenario
(sampling time, horizon, weights, reference) makes the input bound active on a good share of the steps.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np

from .. import interval as iv
from ..error import certify_error
from ..mpc import MPC, MPCOptions, sine_reference
from ..mpc.bang_bang import bang_bang_incumbent
from ..mpc.fallback import qp_repair
from ..network import ReLUNet, fit_relu
from ..parallel import task_key, using
from ..reference import load_reference, save_reference
from ..result import StepResult
from ..simulate import simulate
from ..solvers import BOUND_TOL
from ..systems import FLSystem, brunovsky, quad1d
from ..tables import time_stats
from .mpc import active_fraction

Array = np.ndarray

__all__ = ["UnseenCase", "CASES", "case", "unseen_system", "unseen_net", "unseen_mpc", "write_unseen_references",
           "definitions_table", "TimedController", "closed_loop", "diverse_cases", "diverse_run", "step_phase",
           "closed_loop_row", "diverse_row", "unseen_table", "unseen_numbers", "dense_error", "worst_step",
           "deadline_row", "deadline_table", "late_steps", "diverse_deadline_row", "diverse_deadline_table", "bang_bang_row",
           "bang_bang_table", "BANG_BANG_COUNTS", "bang_bang_numbers"]


def _identity(x: Array) -> Array:
    return np.asarray(x, float).copy()


# ----------------------------------------------------------------------------------- the systems
def pendulum_gain(u_max: float = 5.0) -> FLSystem:
    """Pendulum with an angle-dependent input gain.

    ``x_1' = x_2``, ``x_2' = -9.81 sin x_1 - 0.5 x_2 + (1 + 0.5 cos x_1) u``; ``z = x``,
    ``Phi(z, v) = (v + 9.81 sin z_1 + 0.5 z_2) / (1 + 0.5 cos z_1)``. Box ``|z_1| <= 1.5``, ``|z_2| <= 5``,
    ``|v| <= 15``.
    """
    A, B = brunovsky(2)

    def phi(z: Array, v: Array) -> Array:
        return (v + 9.81 * np.sin(z[:, :1]) + 0.5 * z[:, 1:2]) / (1.0 + 0.5 * np.cos(z[:, :1]))

    def phi_interval(z, v):
        return (v + 9.81 * iv.sin(z[:, 0:1]) + 0.5 * z[:, 1:2]) / (1.0 + 0.5 * iv.cos(z[:, 0:1]))

    def f(x: Array, u: Array) -> Array:
        return np.array([x[1], -9.81 * np.sin(x[0]) - 0.5 * x[1] + (1.0 + 0.5 * np.cos(x[0])) * u[0]])

    return FLSystem("Pendulum-gain", A, B, phi=phi, lo=[-1.5, -5, -15], hi=[1.5, 5, 15], u_max=u_max, f=f,
                    to_z=_identity, to_x=_identity, phi_interval=phi_interval, state_names=("angle", "rate"),
                    params=dict(g_over_l=9.81, damping=0.5, gain="1 + 0.5 cos x1", u_max=u_max))


def quad1d_other() -> FLSystem:
    """The 1-D quadrotor of :func:`flnotes.quad1d` with other parameters: Gamma = 9.81, tau = 0.1, u_max = 0.3."""
    s = quad1d(Gamma=9.81, tau=0.1, u_max=0.3)
    s.name = "Quad-1D-other"
    return s


def vdp_gain(mu: float = 0.5, a: float = 0.3, u_max: float = 3.0) -> FLSystem:
    """Van der Pol oscillator with input gain ``1 + a sin x_1``.

    ``x_1' = x_2``, ``x_2' = mu (1 - x_1^2) x_2 - x_1 + (1 + a sin x_1) u``; ``z = x``,
    ``Phi(z, v) = (v - mu (1 - z_1^2) z_2 + z_1) / (1 + a sin z_1)``. Box ``|z| <= 2``, ``|v| <= 6``.
    """
    A, B = brunovsky(2)

    def phi(z: Array, v: Array) -> Array:
        z1, z2 = z[:, :1], z[:, 1:2]
        return (v - mu * (1.0 - z1**2) * z2 + z1) / (1.0 + a * np.sin(z1))

    def phi_interval(z, v):
        z1, z2 = z[:, 0:1], z[:, 1:2]
        return (v - mu * (1.0 - iv.sqr(z1)) * z2 + z1) / (1.0 + a * iv.sin(z1))

    def f(x: Array, u: Array) -> Array:
        return np.array([x[1], mu * (1.0 - x[0]**2) * x[1] - x[0] + (1.0 + a * np.sin(x[0])) * u[0]])

    return FLSystem("VdP-gain", A, B, phi=phi, lo=[-2, -2, -6], hi=[2, 2, 6], u_max=u_max, f=f,
                    to_z=_identity, to_x=_identity, phi_interval=phi_interval, state_names=("x", "x'"),
                    params=dict(mu=mu, gain=f"1 + {a} sin x1", u_max=u_max))


def chain4_gain(u_max: float = 1.2) -> FLSystem:
    """A 4th-order chain with a gravity-like drift and the input gain ``1.5 + cos x_1``.

    ``x_1' = x_2``, ``x_2' = x_3``, ``x_3' = x_4``, ``x_4' = -2 sin x_1 - 0.5 x_4 + (1.5 + cos x_1) u``
    (a ball-and-beam-like chain); ``z = x``, ``Phi(z, v) = (v + 2 sin z_1 + 0.5 z_4) / (1.5 + cos z_1)``.
    Box ``|z| <= 2``, ``|v| <= 6``.
    """
    A, B = brunovsky(4)

    def phi(z: Array, v: Array) -> Array:
        return (v + 2.0 * np.sin(z[:, :1]) + 0.5 * z[:, 3:4]) / (1.5 + np.cos(z[:, :1]))

    def phi_interval(z, v):
        return (v + 2.0 * iv.sin(z[:, 0:1]) + 0.5 * z[:, 3:4]) / (1.5 + iv.cos(z[:, 0:1]))

    def f(x: Array, u: Array) -> Array:
        return np.array([x[1], x[2], x[3], -2.0 * np.sin(x[0]) - 0.5 * x[3] + (1.5 + np.cos(x[0])) * u[0]])

    return FLSystem("Chain4-gain", A, B, phi=phi, lo=[-2, -2, -2, -2, -6], hi=[2, 2, 2, 2, 6], u_max=u_max, f=f,
                    to_z=_identity, to_x=_identity, phi_interval=phi_interval,
                    params=dict(gain="1.5 + cos x1", u_max=u_max))


def cubic3(u_max: float = 1.4) -> FLSystem:
    """A 3rd-order chain with a cubic drift and the input gain ``1 + 0.2 x_2^2``.

    ``x_1' = x_2``, ``x_2' = x_3``, ``x_3' = -x_1^3 - x_2 + (1 + 0.2 x_2^2) u``; ``z = x``,
    ``Phi(z, v) = (v + z_1^3 + z_2) / (1 + 0.2 z_2^2)``. Box ``|z| <= 1.5``, ``|v| <= 6``.
    """
    A, B = brunovsky(3)

    def phi(z: Array, v: Array) -> Array:
        return (v + z[:, :1]**3 + z[:, 1:2]) / (1.0 + 0.2 * z[:, 1:2]**2)

    def phi_interval(z, v):
        return (v + iv.power(z[:, 0:1], 3) + z[:, 1:2]) / (1.0 + 0.2 * iv.sqr(z[:, 1:2]))

    def f(x: Array, u: Array) -> Array:
        return np.array([x[1], x[2], -x[0]**3 - x[1] + (1.0 + 0.2 * x[1]**2) * u[0]])

    return FLSystem("Cubic3", A, B, phi=phi, lo=[-1.5, -1.5, -1.5, -6], hi=[1.5, 1.5, 1.5, 6], u_max=u_max, f=f,
                    to_z=_identity, to_x=_identity, phi_interval=phi_interval,
                    params=dict(drift="-x1^3 - x2", gain="1 + 0.2 x2^2", u_max=u_max))


# ----------------------------------------------------------------------------------- the cases
@dataclass(frozen=True)
class UnseenCase:
    """A system not in the book with its network settings and its MPC scenario.

    Attributes
    ----------
    name, role
        The system's name and ``"tuning"`` or ``"held-out"``.
    make
        Builds the :class:`flnotes.FLSystem`.
    net_settings
        Arguments of :func:`flnotes.fit_relu` (widths, grid, iterations, seed).
    horizon, ts, Q, R
        ``N_p``, ``t_s`` and the weights of eq. (MPC_form_miqp_a).
    amplitude, omega
        The reference ``x_ref(t) = amplitude sin(omega t)`` (:func:`flnotes.mpc.sine_reference`).
    z0
        Start of the closed loop.
    t_final
        Length of the closed loop (s) in the benchmark (100 sampling instants); its fast mode runs a quarter.
    dynamics
        The plant's last equation, for tables.
    """

    name: str
    role: str
    make: Callable[[], FLSystem]
    net_settings: dict
    horizon: int
    ts: float
    Q: tuple
    R: float
    amplitude: float
    omega: float
    z0: tuple
    t_final: float
    dynamics: str = ""

    @property
    def reference_name(self) -> str:
        """Name of the shipped reference (:func:`flnotes.reference.load_reference`)."""
        return f"unseen_{self.name}"

    def reference(self) -> Callable[[Array], Array]:
        """``t -> z_ref(t)``: the sine ``amplitude sin(omega t)`` and its derivatives (:func:`flnotes.mpc.sine_reference`)."""
        return sine_reference(self.amplitude, self.omega, len(self.z0))


#: Certification settings of the shipped ``eps`` (:func:`flnotes.certify_error`).
EPS_SETTINGS = dict(rtol=0.02, atol=0.0, n_samples=10_000, seed=0)

CASES: dict[str, UnseenCase] = {c.name: c for c in (
    UnseenCase("Pendulum-gain", "tuning", pendulum_gain,
               dict(widths=(12, 12), n_per_axis=40, max_train=None, max_iter=3000, seed=0),
               horizon=8, ts=0.05, Q=(10.0, 1.0), R=0.001, amplitude=1.5, omega=2.0, z0=(0.0, 0.0), t_final=5.0,
               dynamics="x2' = -9.81 sin x1 - 0.5 x2 + (1 + 0.5 cos x1) u"),
    UnseenCase("Quad-1D-other", "tuning", quad1d_other,
               dict(widths=(8, 8, 8), n_per_axis=30, max_train=60_000, max_iter=3000, seed=0),
               horizon=8, ts=0.1, Q=(10.0, 1.0, 1.0), R=0.0175, amplitude=1.5, omega=1.6, z0=(-0.5, -0.15, -0.2),
               t_final=10.0, dynamics="x'' = 9.81 sin(theta) - 0.3 x', theta' = (u - theta) / 0.1"),
    UnseenCase("VdP-gain", "held-out", vdp_gain,
               dict(widths=(16, 16), n_per_axis=40, max_train=None, max_iter=3000, seed=0),
               horizon=12, ts=0.05, Q=(10.0, 1.0), R=0.001, amplitude=1.5, omega=1.5, z0=(0.0, 0.0), t_final=5.0,
               dynamics="x2' = 0.5 (1 - x1^2) x2 - x1 + (1 + 0.3 sin x1) u"),
    UnseenCase("Chain4-gain", "held-out", chain4_gain,
               dict(widths=(12, 12), n_per_axis=14, max_train=60_000, max_iter=3000, seed=0),
               horizon=10, ts=0.1, Q=(10.0, 1.0, 1.0, 1.0), R=0.01, amplitude=0.8, omega=1.0, z0=(0.0, 0.0, 0.0, 0.0),
               t_final=10.0, dynamics="x4' = -2 sin x1 - 0.5 x4 + (1.5 + cos x1) u"),
    UnseenCase("Cubic3", "held-out", cubic3,
               dict(widths=(10, 10, 10), n_per_axis=20, max_train=60_000, max_iter=3000, seed=0),
               horizon=6, ts=0.2, Q=(10.0, 1.0, 1.0), R=0.01, amplitude=1.0, omega=1.2, z0=(0.0, 0.0, 0.0),
               t_final=20.0, dynamics="x3' = -x1^3 - x2 + (1 + 0.2 x2^2) u"),
)}


def case(name: str) -> UnseenCase:
    """The case ``name`` of :data:`CASES`."""
    if name not in CASES:
        raise ValueError(f"unknown system {name!r}; choose one of {list(CASES)}")
    return CASES[name]


def unseen_system(name: str) -> FLSystem:
    """The :class:`flnotes.FLSystem` of the case ``name``."""
    return case(name).make()


def unseen_net(name: str) -> tuple[ReLUNet, float, object]:
    """The shipped network of the case ``name``, its certified ``eps`` (the bracket's upper end) and the reference.

    The weights are checked against their SHA-256 checksum on load (:func:`flnotes.reference.load_reference`).
    """
    c = case(name)
    ref = load_reference(c.reference_name)
    if ref.bracket is None:
        raise ValueError(f"the shipped reference {c.reference_name!r} has no certified bracket; rewrite it with "
                         f"write_unseen_references([{name!r}])")
    return ref.net, float(np.max(ref.bracket["upper"])), ref


def _unseen_task(name: str):
    """One task of :func:`write_unseen_references`: ``(net, report, bracket)`` of the case ``name``."""
    c = case(name)
    s = c.make()
    net, rep = fit_relu(s.phi_stacked, s.lo, s.hi, **c.net_settings)
    return net, rep, certify_error(s, net, **EPS_SETTINGS)


def write_unseen_references(names: Optional[Sequence[str]] = None, folder=None, workers: Optional[int] = None,
                            client=None, progress: bool = False, resume: bool = False) -> list[str]:
    """Train (:func:`flnotes.fit_relu`) and certify (:func:`flnotes.certify_error`) the cases' networks and ship them.

    Minutes of CPU: only to change the shipped networks on purpose. Returns the JSON files written.
    Each case is one task of :class:`flnotes.parallel.Executor` (``workers``, ``client``); the files
    are written here in the order of ``names``; ``resume`` keeps finished cases in the cache folder.
    """
    from ..paper import library_versions

    names = list(names or CASES)
    for name in names:
        case(name)                                   # an unknown name fails here, before any work
    keys = ([task_key("unseen", n, {k: list(v) if isinstance(v, tuple) else v for k, v in case(n).net_settings.items()},
                      EPS_SETTINGS, library_versions()) for n in names] if resume else None)
    with using(workers, client) as ex:
        done = ex.map(_unseen_task, names, keys=keys, cache="unseen" if resume else None, desc="unseen references",
                      progress=progress)
    out = []
    for name, (net, rep, br) in zip(names, done):
        c = case(name)
        out.append(str(save_reference(c.reference_name, net, rep, dict(system=name, **c.net_settings), bracket=br,
                                      eps_settings=EPS_SETTINGS, folder=folder)))
    return out


def unseen_mpc(name: str, options: Optional[MPCOptions] = None, horizon: Optional[int] = None,
                ts: Optional[float] = None, **kwargs) -> MPC:
    """:class:`flnotes.MPC` of the case ``name`` with its shipped network and ``eps`` (default options).

    ``horizon`` and ``ts`` override the case's ``N_p`` and sampling period; ``kwargs`` go to :class:`flnotes.MPC`
    (e.g. ``time_limit``).
    """
    c = case(name)
    net, eps, _ = unseen_net(name)
    return MPC(c.make(), net, eps, horizon=c.horizon if horizon is None else horizon, ts=c.ts if ts is None else ts,
               Q=list(c.Q), R=c.R, options=options, **kwargs)


def definitions_table() -> list[dict]:
    """One row per case: dynamics, sizes, network, certified ``eps``, horizon, sampling time, reference."""
    rows = []
    for c in CASES.values():
        s = c.make()
        net, eps, ref = unseen_net(c.name)
        br = ref.bracket
        rows.append(dict(system=c.name, role=c.role, dynamics=c.dynamics, n_z=s.n_z, u_max=float(s.u_max[0]),
                         widths="x".join(str(w) for w in net.widths), hidden=net.n_hidden,
                         eps=eps, eps_lower=float(np.max(br["lower"])), eps_over_u_max=eps / float(s.u_max[0]),
                         certify_s=float(np.sum(br["time_s"])), N_p=c.horizon, t_s=c.ts,
                         reference=f"{c.amplitude:g} sin({c.omega:g} t)"))
    return rows


def dense_error(name: str, n: int = 200_000, seed: int = 0) -> float:
    """Largest ``|Phi - Phi_NN|`` on ``n`` seeded uniform samples of the case's box (a lower value for ``eps``)."""
    s = unseen_system(name)
    net, _, _ = unseen_net(name)
    X = np.random.default_rng(seed).uniform(s.lo, s.hi, (n, s.n_in))
    return float(np.max(np.abs(s.phi_stacked(X) - net(X))))


# ----------------------------------------------------------------------------------- timing
class TimedController:
    """An :class:`flnotes.MPC` for :func:`flnotes.simulate` that also records wall and CPU time per step.

    ``wall`` from :func:`time.perf_counter`, ``cpu`` from :func:`time.process_time` around each step
    (seconds); CPU time is what this process used, wall time includes waiting for a shared core.
    """

    def __init__(self, mpc: MPC):
        self.mpc, self.net = mpc, mpc.net
        self.wall: list[float] = []
        self.cpu: list[float] = []

    def reset(self) -> None:
        self.mpc.reset()
        self.wall, self.cpu = [], []

    def step(self, z: Array, t: float, reference=None) -> StepResult:
        w0, c0 = time.perf_counter(), time.process_time()
        res = self.mpc.step(z, t, reference)
        self.cpu.append(time.process_time() - c0)
        self.wall.append(time.perf_counter() - w0)
        return res


def step_phase(s: StepResult) -> str:
    """Where a step's time went, from its :class:`flnotes.StepResult`.

    ``"screening"``: the QP without the network was optimal; ``"confirmation"``: the incumbent (warm start or
    repaired relaxation) was proven optimal without a better plan (an empty level set); ``"levels"``:
    mixed-integer programs on the level set were solved (``rounds`` of them, ``nodes`` in all); ``"fallback"``:
    no plan.
    """
    if s.fallback:
        return "fallback"
    if s.screened:
        return "screening"
    if "incumbent is optimal" in s.message:
        return "confirmation"
    return "levels"


def closed_loop(name: str, t_final: Optional[float] = None, options: Optional[MPCOptions] = None,
                time_limit: Optional[float] = None, horizon: Optional[int] = None) -> tuple:
    """The case's closed loop on the true plant with :class:`flnotes.MPC` (default options unless given).

    ``t_final`` and ``horizon`` override the case's length and ``N_p``.

    Returns ``(log, mpc, timed)``: the :class:`flnotes.simulate` log (with ``Phi_NN`` at the samples), the
    controller (its ``history`` holds every :class:`flnotes.StepResult`) and the wall/CPU times per step.
    """
    c = case(name)
    mpc = unseen_mpc(name, options=options, horizon=horizon, time_limit=time_limit)
    timed = TimedController(mpc)
    log = simulate(mpc.system, timed, t_final=c.t_final if t_final is None else t_final, ts=c.ts, z0=np.array(c.z0),
                   reference=c.reference(), net=mpc.net, progress=False)
    return log, mpc, timed


def worst_step(history: Sequence[StepResult], wall: Array) -> dict:
    """The slowest step: its index, wall time (ms), phase (:func:`step_phase`), binaries, nodes and rounds."""
    k = int(np.argmax(wall))
    s = history[k]
    return dict(worst_step=k, worst_ms=float(wall[k] * 1e3), worst_phase=step_phase(s), worst_binaries=int(s.n_binaries),
                worst_nodes=int(s.nodes), worst_rounds=int(s.rounds), worst_encoded_steps=len(s.encoded_steps),
                worst_warm_started=bool(s.warm_started))


def _miss(history: Sequence[StepResult], wall: Array, ts: float) -> str:
    """Why the steps over ``t_s`` took long: their binaries, nodes, rounds and phase."""
    wall = np.asarray(wall, float)
    over = np.flatnonzero(wall > ts)
    if not over.size:
        return ""
    w = worst_step(history, wall)
    phases = {}
    for j in over:
        p = step_phase(history[j])
        phases[p] = phases.get(p, 0) + 1
    return (f"{over.size} step(s) over t_s, by up to {w['worst_ms'] / 1e3 / ts:.1f} t_s; worst step {w['worst_step']}: "
            f"{w['worst_ms']:.0f} ms, phase {w['worst_phase']}, {w['worst_binaries']} binaries, {w['worst_nodes']} nodes, "
            f"{w['worst_rounds']} round(s), {w['worst_encoded_steps']} encoded step(s), warm start "
            f"{'used' if w['worst_warm_started'] else 'not used'}; phases of the steps over t_s: "
            + ", ".join(f"{p} {n}" for p, n in sorted(phases.items())))


def late_steps(history: Sequence[StepResult], wall: Array, cpu: Array, ts: float) -> str:
    """The answers after ``t_s`` told apart: per late step its wall and CPU time (the process's, a cut-off solve
    running on in its thread included), the CPU time the controller's threads used until the answer
    (``info["cpu_time"]`` of :class:`flnotes.MPC`, where recorded), the controller's own time (``solve_time``),
    its status and whether it was answered at the cut-off or by the fallback; the rest of the wall time was spent
    waiting for the machine."""
    wall, cpu = np.asarray(wall, float), np.asarray(cpu, float)
    out = []
    for k in np.flatnonzero(wall > ts):
        s = history[k]
        own = s.info.get("cpu_time")
        out.append(f"step {k}: {wall[k] * 1e3:.1f} ms wall, {cpu[k] * 1e3:.1f} ms CPU"
                   + (f" ({own * 1e3:.1f} ms of the controller's threads until the answer)" if own is not None else "")
                   + f", engine {s.solve_time * 1e3:.1f} ms, "
                   f"{s.status}" + (", at the cut-off" if s.info.get("cut_off") else "")
                   + (", fallback" if s.fallback else ""))
    return "; ".join(out)


def closed_loop_row(name: str, log, mpc: MPC, timed: TimedController) -> dict:
    """The benchmark's row of a closed loop: bound activity, wall/CPU time per step, |u|/u_max, misses."""
    c = case(name)
    wall, cpu = np.array(timed.wall), np.array(timed.cpu)
    sw, sc = time_stats(wall, (50, 99)), time_stats(cpu, (50, 99))
    h = mpc.history
    u_max = float(mpc.system.u_max[0])
    return dict(system=name, role=c.role, N_p=mpc.N, t_s_ms=c.ts * 1e3, steps=log.n_steps,
                active_share=active_fraction(log, mpc.u_eps),
                wall_min_ms=sw["min_ms"], wall_median_ms=sw["median_ms"], wall_p99_ms=sw["p99_ms"],
                wall_max_ms=sw["max_ms"], cpu_min_ms=sc["min_ms"], cpu_median_ms=sc["median_ms"],
                cpu_p99_ms=sc["p99_ms"], cpu_max_ms=sc["max_ms"],
                over_ts_wall=int(np.sum(wall > c.ts)), over_ts_cpu=int(np.sum(cpu > c.ts)),
                max_u_over_u_max=float(np.abs(log.u).max() / u_max),
                max_u_between_over_u_max=float(np.abs(log.u_fine).max() / u_max),
                screened=int(sum(s.screened for s in h)), miqp_steps=int(sum(not s.screened for s in h)),
                binaries_max=int(max(s.n_binaries for s in h)), nodes_max=int(max(s.nodes for s in h)),
                non_optimal=int(sum(s.status != "optimal" for s in h)), fallbacks=int(sum(s.fallback for s in h)),
                completed=not log.message, **worst_step(h, wall), miss=_miss(h, wall, c.ts), message=log.message)


# ----------------------------------------------------------------------------------- diverse states
DIVERSE_CATEGORIES = ("uniform", "edge", "active", "tracking")


def diverse_cases(name: str, n: int, seed: int = 0, horizon: Optional[int] = None) -> list[dict]:
    """``n`` diverse MPC programs of the case ``name``: dicts with ``z``, ``z_ref`` (N_p + 1, n_z), ``category``.

    Categories cycle through :data:`DIVERSE_CATEGORIES`: ``"uniform"`` (position uniform in 90 % of its range,
    the derivatives in 50 % of theirs, constant position reference uniform in 80 % of its range), ``"edge"``
    (one coordinate on a face of the box, sine reference with a random phase) and ``"active"`` (position far
    from the reference, its derivatives pointing away from it: the bound binds) and ``"tracking"`` (the case's
    sine reference from a random phase, the state on it with the position off by up to 20 % of its range, as
    in the closed loop). ``horizon`` defaults to the case's ``N_p``.
    """
    c = case(name)
    s = c.make()
    rng = np.random.default_rng(seed)
    nz, N = s.n_z, c.horizon if horizon is None else int(horizon)
    lo, hi = s.lo[:nz], s.hi[:nz]
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    spread = np.r_[0.9, np.full(nz - 1, 0.5)]
    out = []
    for j in range(n):
        cat = DIVERSE_CATEGORIES[j % len(DIVERSE_CATEGORIES)]
        R = np.zeros((N + 1, nz))
        R[:, 0] = mid[0] + rng.uniform(-0.8, 0.8) * half[0]
        z = mid + rng.uniform(-1.0, 1.0, nz) * spread * half
        if cat == "edge":
            i = int(rng.integers(nz))
            z[i] = lo[i] if rng.integers(2) else hi[i]
            ref = sine_reference(c.amplitude, c.omega, nz, rng.uniform(0, 2 * np.pi))
            R = ref(c.ts * np.arange(N + 1))
        elif cat == "active":
            sgn = -np.sign(R[0, 0]) or 1.0
            z[0] = mid[0] + sgn * rng.uniform(0.5, 0.9) * half[0]
            z[1:] = mid[1:] + sgn * rng.uniform(0.2, 0.6, nz - 1) * half[1:]
        elif cat == "tracking":
            t0 = rng.uniform(0, 2 * np.pi / c.omega)
            R = c.reference()(t0 + c.ts * np.arange(N + 1))
            z = np.clip(R[0] + np.r_[rng.uniform(-0.2, 0.2) * half[0], np.zeros(nz - 1)], lo, hi)
        out.append(dict(z=z, z_ref=R, category=cat))
    return out


def diverse_run(name: str, n: int, seed: int = 0, time_limit: Optional[float] = None,
                options: Optional[MPCOptions] = None) -> tuple[list[StepResult], Array, Array, list[dict]]:
    """Solve :func:`diverse_cases` cold (no previous plan) with the case's MPC; returns steps, wall, CPU (s), cases."""
    cases = diverse_cases(name, n, seed)
    mpc = unseen_mpc(name, options=options, time_limit=time_limit)
    steps, wall, cpu = [], [], []
    for cs in cases:
        mpc.reset()
        w0, c0 = time.perf_counter(), time.process_time()
        steps.append(mpc(cs["z"], cs["z_ref"]))
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return steps, np.array(wall), np.array(cpu), cases


def diverse_row(name: str, steps: Sequence[StepResult], wall: Array, cpu: Array) -> dict:
    """The benchmark's row on diverse states: p99 (wall and CPU) against ``t_s``, statuses, the misses."""
    c = case(name)
    sw, sc = time_stats(wall, (50, 99)), time_stats(cpu, (50, 99))
    return dict(system=name, role=c.role, N_p=c.horizon, t_s_ms=c.ts * 1e3, states=len(steps),
                bound_active=int(sum(not s.screened for s in steps)),
                wall_median_ms=sw["median_ms"], wall_p99_ms=sw["p99_ms"], wall_max_ms=sw["max_ms"],
                cpu_median_ms=sc["median_ms"], cpu_p99_ms=sc["p99_ms"], cpu_max_ms=sc["max_ms"],
                p99_over_ts_wall=sw["p99_ms"] / (c.ts * 1e3), over_ts_wall=int(np.sum(wall > c.ts)),
                optimal=int(sum(s.status == "optimal" for s in steps)),
                infeasible=int(sum(s.status == "infeasible" for s in steps)),
                time_limit=int(sum(s.status == "time_limit" for s in steps)),
                fallbacks=int(sum(s.fallback for s in steps)),
                binaries_max=int(max(s.n_binaries for s in steps)), nodes_max=int(max(s.nodes for s in steps)),
                miss=_miss(steps, np.asarray(wall), c.ts))


def diverse_deadline_row(name: str, steps: Sequence[StepResult], wall: Array, cpu: Array,
                         exact: Sequence[StepResult]) -> dict:
    """The diverse states under the time limit: ``steps``, ``wall``, ``cpu`` from :func:`diverse_run` with
    ``time_limit = t_s``, ``exact`` the same states (same ``n`` and ``seed``) solved without it.

    Answer time against ``t_s``: ``over_ts_wall`` answers after it, ``over_ts_cpu`` those of them whose step also
    used more than ``t_s`` of CPU time, ``wall_p99_over_ts``, ``wall_max_over_ts``, ``cpu_max_over_ts``. What was
    returned: ``plans_admissible`` (plans passing the forward-pass check), ``inputs_flagged`` (first inputs flagged
    ``input_admissible=False``), ``inputs_not_admissible`` (first inputs with ``|Phi_NN(z, v)| > u_max^eps`` by the
    network's forward pass and not flagged: must be 0), ``infeasible`` (states whose program the solve without
    the limit proves infeasible). At the ``limit_hits`` (``cut_offs`` of them answered at the cut-off): for a plan
    that passes the check, its distance to the optimum ``(J - J*) / max(1, |J*|)`` (``opt_gap_max``,
    ``opt_gap_over`` above 1e-4, ``opt_undecided`` without a proven ``J*``); for one that does not, whether the
    program has a plan (``without_plan_infeasible``, ``without_plan_missed``, ``without_plan_undecided``); ``late``
    describes each answer after ``t_s`` (:func:`late_steps`).
    """
    c = case(name)
    if len(steps) != len(exact) or len(steps) != len(wall) or len(steps) != len(cpu):
        raise ValueError(f"{len(steps)} steps, {len(wall)} wall and {len(cpu)} CPU times, {len(exact)} exact steps: "
                         "pass the same states solved with and without the limit")
    net, eps, _ = unseen_net(name)
    u_eps = c.make().u_max - eps
    wall, cpu = np.asarray(wall, float), np.asarray(cpu, float)
    og, without = [], dict(infeasible=0, missed=0, undecided=0)
    not_admissible = 0
    for s, e in zip(steps, exact):
        if not np.allclose(s.z_pred[0], e.z_pred[0]):
            raise ValueError(f"{name}: a state solved with the limit ({s.z_pred[0]}) differs from the one solved "
                             f"without it ({e.z_pred[0]}): pass the same states (same n and seed) in the same order")
        u = net(np.r_[s.z_pred[0], np.atleast_1d(s.v)])
        not_admissible += int(s.input_admissible and not np.all(np.abs(u) <= u_eps + BOUND_TOL))
        if s.status != "time_limit":
            continue
        proven = e.status == "optimal" and not e.fallback
        if s.info.get("plan_feasible"):
            og.append((s.objective - e.objective) / max(1.0, abs(e.objective)) if proven else np.nan)
        else:
            without["infeasible" if e.status == "infeasible" else "missed" if proven else "undecided"] += 1
    og = np.array(og, float)
    sw = time_stats(wall, (50, 99))
    return dict(system=name, role=c.role, N_p=c.horizon, t_s_ms=c.ts * 1e3, states=len(steps),
                limit_hits=int(sum(s.status == "time_limit" for s in steps)),
                cut_offs=int(sum(bool(s.info.get("cut_off")) for s in steps)),
                over_ts_wall=int(np.sum(wall > c.ts)), over_ts_cpu=int(np.sum((wall > c.ts) & (cpu > c.ts))),
                wall_p99_over_ts=sw["p99_ms"] / (c.ts * 1e3), wall_max_over_ts=float(wall.max() / c.ts),
                cpu_max_over_ts=float(cpu.max() / c.ts),
                plans_admissible=int(sum(bool(s.info.get("plan_feasible")) for s in steps)),
                inputs_flagged=int(sum(not s.input_admissible for s in steps)), inputs_not_admissible=not_admissible,
                infeasible=int(sum(e.status == "infeasible" for e in exact)),
                opt_gap_max=float(np.nanmax(og)) if np.isfinite(og).any() else np.nan,
                opt_gap_over=int(np.sum(og > 1e-4)), opt_undecided=int(np.sum(np.isnan(og))),
                **{f"without_plan_{k}": v for k, v in without.items()}, late=late_steps(steps, wall, cpu, c.ts))


def diverse_deadline_table(names: Optional[Sequence[str]] = None, n: int = 10, seed: int = 0,
                           optimum_limit: float = 60.0) -> list[dict]:
    """:func:`diverse_deadline_row` for each case (default: all): ``n`` cold diverse states solved without a time
    limit (``optimum_limit`` seconds each, for the optimum) and with ``time_limit = t_s``."""
    rows = []
    for name in (names or list(CASES)):
        exact, *_ = diverse_run(name, n, seed=seed, time_limit=optimum_limit)
        lim, wall, cpu, _ = diverse_run(name, n, seed=seed, time_limit=case(name).ts)
        rows.append(diverse_deadline_row(name, lim, wall, cpu, exact))
    return rows


def bang_bang_row(name: str, n: int = 30, seed: int = 0) -> dict:
    """The one-switch plans (``MPCOptions.bang_bang``) on ``n`` cold diverse states of the case ``name``.

    What does not depend on the machine: ``qp_feasible`` (states whose QP without the network has a plan),
    ``screened`` (its optimum meets the network bound), ``repair_failed`` (the relaxation repaired along the QP
    fails the forward-pass check, so a cold solve has no first incumbent without the one-switch plans), and of
    those ``one_switch_found`` (a one-switch plan passes the check, searched without a deadline; the largest search
    time ``search_ms_max``).

    Then the same states solved with ``time_limit = t_s``, without and with the option (interleaved state by state):
    ``plans_without``/``plans_with`` (answers whose plan passes the check), ``recovered`` (a plan with the option,
    none without: a plan existed and was missed), ``lost`` (the reverse; ``lost_searched`` of them at states where
    the one-switch search ran: elsewhere both runs take the same path, and a difference is the machine's timing),
    ``one_switch_used`` (steps whose first
    incumbent was a one-switch plan) and ``one_switch_unplanned`` (of those, steps that returned no plan passing the
    check: 0, since an incumbent is always returned), ``optimal_without``/``optimal_with``, the slowest answers
    ``wall_max_over_ts_without``/``_with``, the answers after ``t_s`` ``over_ts_without``/``_with`` and each of them
    described (``late_without``/``late_with``, :func:`late_steps`).
    """
    c = case(name)
    cases = diverse_cases(name, n, seed)
    mpc = {bb: unseen_mpc(name, options=MPCOptions(bang_bang=bb), time_limit=c.ts) for bb in (False, True)}
    pred = mpc[True].pred
    det = dict(qp_feasible=0, screened=0, repair_failed=0, one_switch_found=0)
    search, steps, wall, cpu = [], {False: [], True: []}, {False: [], True: []}, {False: [], True: []}
    for cs in cases:
        z = np.asarray(cs["z"], float)
        f, c0 = pred.linear(z, cs["z_ref"])
        V_q, _, _ = pred.qp(f, z)
        if V_q is not None:
            det["qp_feasible"] += 1
            if pred.feasible(z, V_q):
                det["screened"] += 1
            elif not pred.feasible(z, qp_repair(pred, z, f, V_q)[1]):
                det["repair_failed"] += 1
                t0 = time.perf_counter()
                det["one_switch_found"] += bang_bang_incumbent(pred, z, f, c0) is not None
                search.append(time.perf_counter() - t0)
        for bb in (False, True):
            mpc[bb].reset()
            t0, p0 = time.perf_counter(), time.process_time()
            steps[bb].append(mpc[bb](z, cs["z_ref"]))
            cpu[bb].append(time.process_time() - p0)
            wall[bb].append(time.perf_counter() - t0)
    planned = {bb: np.array([bool(s.info.get("plan_feasible")) and not s.fallback for s in steps[bb]]) for bb in wall}
    used = [s.info.get("incumbent") == "one-switch plan" for s in steps[True]]
    searched = np.array([s.info.get("bang_bang_s") is not None for s in steps[True]])
    return dict(system=name, role=c.role, N_p=c.horizon, t_s_ms=c.ts * 1e3, states=n, **det,
                search_ms_max=1e3 * max(search) if search else 0.0,
                plans_without=int(planned[False].sum()), plans_with=int(planned[True].sum()),
                recovered=int(np.sum(planned[True] & ~planned[False])),
                lost=int(np.sum(planned[False] & ~planned[True])),
                lost_searched=int(np.sum(planned[False] & ~planned[True] & searched)),
                one_switch_used=int(sum(used)),
                one_switch_unplanned=int(sum(u and not p for u, p in zip(used, planned[True]))),
                optimal_without=int(sum(s.status == "optimal" for s in steps[False])),
                optimal_with=int(sum(s.status == "optimal" for s in steps[True])),
                wall_max_over_ts_without=float(max(wall[False]) / c.ts),
                wall_max_over_ts_with=float(max(wall[True]) / c.ts),
                over_ts_without=int(np.sum(np.array(wall[False]) > c.ts)),
                over_ts_with=int(np.sum(np.array(wall[True]) > c.ts)),
                late_without=late_steps(steps[False], wall[False], cpu[False], c.ts),
                late_with=late_steps(steps[True], wall[True], cpu[True], c.ts))


def bang_bang_table(names: Optional[Sequence[str]] = None, n: int = 30, seed: int = 0) -> list[dict]:
    """:func:`bang_bang_row` for each case (default: all)."""
    return [bang_bang_row(name, n, seed) for name in (names or list(CASES))]


def unseen_table(names: Optional[Sequence[str]] = None, steps: Optional[int] = None,
                 horizon: Optional[int] = None) -> tuple[list[dict], dict]:
    """The chapter's table: each case's closed loop with the default MPC (no time limit), and the runs.

    Returns ``(rows, runs)`` with one :func:`closed_loop_row` per case and ``runs[name] = (log, mpc, timed)``.
    ``steps`` (sampling instants per case) and ``horizon`` (``N_p``) override the cases' own (the chapter's
    fast mode runs a few steps at a short horizon).
    """
    rows, runs = [], {}
    for name in (names or list(CASES)):
        c = case(name)
        log, mpc, timed = closed_loop(name, t_final=None if steps is None else steps * c.ts, horizon=horizon)
        runs[name] = (log, mpc, timed)
        rows.append(closed_loop_row(name, log, mpc, timed))
    return rows, runs


def deadline_row(name: str, steps: Optional[int] = None, horizon: Optional[int] = None,
                 optimum_limit: float = 30.0) -> dict:
    """The case's closed loop with ``time_limit = t_s``: answer time against ``t_s`` and the plans at the limit.

    Each step that hit the limit with a plan passing the forward-pass check is solved again without the limit
    (cold, ``optimum_limit`` seconds): ``opt_gap_max`` is the largest ``(J - J*) / max(1, |J*|)`` of those plans,
    ``opt_gap_over`` how many are above 1e-4, ``opt_undecided`` how many optima that solve did not prove.
    ``wall_max_over_ts`` is the slowest answer (wall clock) over ``t_s``, ``cpu_max_over_ts`` the most CPU time a
    step used over ``t_s``; ``over_ts_wall`` counts the answers after ``t_s`` and ``over_ts_cpu`` those of them whose
    step also used more than ``t_s`` of CPU time (late by their own work; the others waited for the machine);
    ``cut_offs`` counts the answers given at the cut-off while the engine's solve ran on (:class:`flnotes.MPC`
    ``cut_off``); ``late`` describes each answer after ``t_s`` (:func:`late_steps`).
    """
    c = case(name)
    log, mpc, timed = closed_loop(name, t_final=None if steps is None else steps * c.ts, time_limit=c.ts,
                                  horizon=horizon)
    wall, cpu, h = np.array(timed.wall), np.array(timed.cpu), mpc.history
    exact = unseen_mpc(name, horizon=horizon, time_limit=optimum_limit)
    og = []
    for s in h:
        if s.status == "time_limit" and s.info.get("plan_feasible"):
            exact.reset()
            r = exact(s.z_pred[0], s.info["z_ref"])
            ok = r.status == "optimal" and not r.fallback
            og.append((s.objective - r.objective) / max(1.0, abs(r.objective)) if ok else np.nan)
    og = np.array(og, float)
    return dict(system=name, role=c.role, N_p=mpc.N, t_s_ms=c.ts * 1e3, steps=log.n_steps,
                limit_hits=int(sum(s.status == "time_limit" for s in h)),
                cut_offs=int(sum(bool(s.info.get("cut_off")) for s in h)), over_ts_wall=int(np.sum(wall > c.ts)),
                over_ts_cpu=int(np.sum((wall > c.ts) & (cpu > c.ts))),
                wall_max_over_ts=float(wall.max() / c.ts), cpu_max_over_ts=float(cpu.max() / c.ts),
                opt_gap_max=float(np.nanmax(og)) if np.isfinite(og).any() else np.nan,
                opt_gap_over=int(np.sum(og > 1e-4)), opt_undecided=int(np.sum(np.isnan(og))),
                plans_admissible=int(sum(bool(s.info.get("plan_feasible")) for s in h)),
                fallbacks=int(sum(s.fallback for s in h)), max_u_over_u_max=float(np.abs(log.u).max() / float(
                    mpc.system.u_max[0])), late=late_steps(h, wall, cpu, c.ts))


def deadline_table(names: Optional[Sequence[str]] = None, steps: Optional[int] = None,
                   horizon: Optional[int] = None, optimum_limit: float = 30.0) -> list[dict]:
    """:func:`deadline_row` for each case (default: all)."""
    return [deadline_row(name, steps, horizon, optimum_limit) for name in (names or list(CASES))]


def unseen_numbers(rows: Sequence[dict]) -> dict:
    """What chapter 8 quotes from :func:`unseen_table`'s rows, as Python numbers (and the worst system's name).

    ``steps`` (all systems), ``max_u`` (largest true ``|u| / u_max`` at a sample), ``active_max`` (largest share
    of steps with the bound active, %), ``over`` and ``systems_over`` (steps and systems over ``t_s``, wall
    clock), and for the step slowest relative to its ``t_s``: ``worst_system``, ``worst_step``, ``worst_ms``,
    ``worst_phase``, ``worst_ratio``, ``worst_binaries``, ``worst_nodes``.
    """
    py = lambda x: x.item() if hasattr(x, "item") else x  # noqa: E731 - numpy scalars to Python numbers
    worst = max(rows, key=lambda r: r["wall_max_ms"] / r["t_s_ms"])
    return dict(steps=py(sum(r["steps"] for r in rows)), max_u=py(max(r["max_u_over_u_max"] for r in rows)),
                active_max=py(100 * max(r["active_share"] for r in rows)),
                over=py(sum(r["over_ts_wall"] for r in rows)), systems_over=int(sum(r["over_ts_wall"] > 0 for r in rows)),
                worst_system=worst["system"], worst_step=py(worst["worst_step"]), worst_ms=py(worst["worst_ms"]),
                worst_phase=worst["worst_phase"], worst_ratio=py(worst["wall_max_ms"] / worst["t_s_ms"]),
                worst_binaries=py(worst["worst_binaries"]), worst_nodes=py(worst["worst_nodes"]))


#: The counts of :func:`bang_bang_row` that :func:`bang_bang_numbers` sums over the systems.
BANG_BANG_COUNTS = ("states", "repair_failed", "one_switch_found", "one_switch_used", "plans_without", "plans_with",
                    "recovered", "lost", "lost_searched", "optimal_without", "optimal_with")


def bang_bang_numbers(rows) -> dict:
    """The figures the benchmark report quotes from :func:`bang_bang_table`, over all its systems.

    Returns
    -------
    dict
        each of :data:`BANG_BANG_COUNTS` summed (int); ``net`` (answers with a plan gained by the lever, with minus
        without); ``search_ms`` (the longest search, ms) and ``search_share`` (the largest search over ``t_s``);
        ``wall_max_with`` (the largest ``wall_max_over_ts_with``); ``verdict``: when a one-switch plan passed the
        check at some state where the repair failed, "where the repair fails, the one-switch plans gave a cold step a
        first incumbent at K of those F states, ... that is why the default keeps the lever on"; else "on these
        states the lever found no incumbent at the F states where the repair failed, so it is not shown to pay here;
        its search took at most P of the sampling period".
    """
    out = {key: int(sum(r[key] for r in rows)) for key in BANG_BANG_COUNTS}
    out["net"] = int(sum(r["plans_with"] - r["plans_without"] for r in rows))
    out["search_ms"] = max(r["search_ms_max"] for r in rows)
    out["search_share"] = share = max(r["search_ms_max"] / r["t_s_ms"] for r in rows)
    out["wall_max_with"] = max(r["wall_max_over_ts_with"] for r in rows)
    found, failed = out["one_switch_found"], out["repair_failed"]
    if found > 0:
        out["verdict"] = (f"where the repair fails, the one-switch plans gave a cold step a first incumbent at {found} of "
                          f"those {failed} states, one it had no other way to get (a count that does not depend on the "
                          f"machine), for a search of at most {share:.0%} of the sampling period; that is why the default "
                          "keeps the lever on")
    else:
        out["verdict"] = (f"on these states the lever found no incumbent at the {failed} states where the repair failed, "
                          f"so it is not shown to pay here; its search took at most {share:.0%} of the sampling period")
    return out
