"""Chapter 10 (several inputs): the two-link arm through the whole pipeline.

The settings of the chapter's runs (:data:`ARM_CLF_CBF`, :data:`ARM_MPC`) and the
functions behind its checks and tables: the shipped network's report, a dense
sampling of its error, the exact two-input CLF-CBF method against a MIP back-end
on many states, the CLF-CBF closed loop around an obstacle in the workspace and
the MPC closed loop, with the true torques checked at every sample.
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence

import numpy as np

from ..arm import arm_net, arm_obstacle_cbfs, links_distance
from ..control import ClfCbfController, QuadraticCLF
from ..mpc import MPC
from ..network import ReLUNet
from ..pieces import compare_exact_mip
from ..simulate import SimLog, simulate
from ..systems import FLSystem
from ..tables import Table, time_stats

Array = np.ndarray

__all__ = ["identity_residual", "ARM_CLF_CBF", "ARM_MPC", "shipped_network", "sampled_error", "error_at_states",
           "arm_clf_cbf", "comparison_states",
           "exact_vs_mip", "softened_states", "nominal_run", "obstacle_run", "torque_checks", "setpoint_reference", "mpc_run"]

#: The CLF-CBF setting of the chapter: CLF ``z^T P z``, nominal law ``k(z) = -K_nominal z``, a disc obstacle of radius
#: ``radius`` (m) at ``center`` in the workspace kept away from the second link (``n_points`` barriers, gain ``k1``),
#: the start ``z0``, sampling time ``ts`` and length ``t_final`` (s).
ARM_CLF_CBF = dict(
    P=np.diag([2.0, 0.5, 2.0, 0.5]) + np.diag([0.4, 0, 0.4], 1) + np.diag([0.4, 0, 0.4], -1),
    K=np.array([[6.0, 4.0, 0.0, 0.0], [0.0, 0.0, 6.0, 4.0]]),
    z0=np.array([0.8, 0.0, -0.3, 0.0]), center=np.array([0.31, -0.95]), radius=0.06, n_points=5, k1=3.0,
    beta=0.001, kappa=4.0, ts=0.02, t_final=5.0,
)

#: The MPC setting of the chapter: horizon, sampling time, weights, and a reference through two set points
#: of the joint angles (switching at ``t_switch``), from rest at ``z0``.
ARM_MPC = dict(horizon=5, ts=0.1, Q=np.array([100.0, 1.0, 100.0, 1.0]), R=np.array([1e-3, 1e-3]),
               setpoints=np.array([[0.6, 0.0], [-0.3, 0.8]]), t_switch=3.0, t_final=6.0, z0=np.zeros(4))


def identity_residual(system: FLSystem, n: int = 200, seed: int = 0) -> float:
    """Largest ``|to_z(f(x, Phi(z, v))) - (A z + B v)|`` at ``n`` random ``(x, v)`` of the box (eq. coor_Phi).

    The feedback-linearization identity checked on the true plant: with
    ``u = Phi(z, v)`` the plant's vector field read in ``z`` (a permutation of
    ``x`` for the arm, so ``d/dt to_z(x) = to_z(x')``) is the Brunovsky chain.
    """
    if not (isinstance(n, (int, np.integer)) and n > 0):
        raise ValueError(f"n must be a positive integer, got {n!r}")
    rng = np.random.default_rng(seed)
    Z = rng.uniform(system.lo[: system.n_z], system.hi[: system.n_z], (n, system.n_z))
    V = rng.uniform(system.lo[system.n_z:], system.hi[system.n_z:], (n, system.m))
    U = system.Phi(Z, V)
    res = [system.to_z(system.f(system.to_x(z), u)) - (system.A @ z + system.B @ v) for z, v, u in zip(Z, V, U)]
    return float(np.abs(res).max())


def shipped_network() -> dict:
    """What the shipped report says of the arm's network: architecture, training time, certified ``eps`` bracket.

    Quoted, not recomputed: the network was trained with
    :data:`flnotes.arm.ARM_SETTINGS` and ``eps`` certified per output by
    :func:`flnotes.certify_error` (interval branch and bound) when the
    reference was written (:func:`flnotes.arm.make_arm_reference`).

    Returns
    -------
    dict
        ``net``, ``eps`` (shape (2,)), ``widths``, ``n_train``, ``n_grid``, ``train_s``,
        ``grid_max_error``, ``lower``, ``upper`` (the bracket, shape (2,)), ``cert_s``
        (seconds per output), ``n_boxes``, ``rtol``, ``converged``, ``method``, and ``sha256``, the checksum of
        the weights the bracket was certified for, written with it (:func:`flnotes.reference.save_reference`).
    """
    net, eps, ref = arm_net()
    rep, br = ref.report, ref.bracket
    return dict(net=net, eps=eps, widths=tuple(rep.widths), n_train=int(rep.n_train), n_grid=int(rep.n_grid),
                train_s=float(rep.time_s), grid_max_error=np.asarray(rep.grid_max_error, float),
                lower=np.asarray(br["lower"], float), upper=np.asarray(br["upper"], float),
                cert_s=np.asarray(br["time_s"], float), n_boxes=np.asarray(br["n_boxes"], int),
                rtol=float(br["rtol"]), converged=bool(np.all(br["converged"])), method=str(br["method"]),
                sha256=str(ref.meta["sha256"]))


def error_at_states(system: FLSystem, net: ReLUNet, sets: Sequence[dict]) -> Array:
    """The largest ``|Phi_i(z, v) - Phi_NN,i(z, v)|`` over the whole ``v``-box, at each state of ``sets``.

    Exact for a ``Phi`` affine in ``v`` (checked): on each linear region of ``Phi_NN(z, .)`` the
    error of each output is the absolute value of an affine function of ``v``, convex, so its maximum over
    the region is attained at a vertex; the regions tile the ``v``-box, so the maximum over their vertices
    is the maximum over the box.

    Parameters
    ----------
    system
        A two-input :class:`flnotes.FLSystem` (the arm).
    net
        ``Phi_NN``.
    sets
        The output of :func:`flnotes.pieces.input_sets` (their ``regions``).

    Returns
    -------
    Array
        Shape (len(sets), m): per state and output, the error's maximum over the ``v``-box, to set against ``eps``
        (a bound over the whole ``(z, v)``-box).
    """
    out = []
    for S in sets:
        V = np.vstack(S["regions"].polygons)
        Zr = np.repeat(np.asarray(S["z"], float)[None], len(V), 0)
        phi = system.Phi(Zr, V)
        mid = 0.5 * (V[:-1] + V[1:])
        if not np.allclose(system.Phi(Zr[:-1], mid), 0.5 * (phi[:-1] + phi[1:]), rtol=1e-9, atol=1e-9):
            raise ValueError("Phi must be affine in v for the vertex maximum to be exact")
        out.append(np.abs(phi - np.asarray(net(np.column_stack([Zr, V])), float)).max(0))
    return np.array(out)


def sampled_error(system: FLSystem, net: ReLUNet, n: int, seed: int = 0, chunk: int = 200_000) -> dict:
    """Largest sampled ``|Phi - Phi_NN|`` per output at ``n`` uniform points of the domain box and a grid.

    A lower bound of the true maximum (eq. approx_err), to set against the
    certified ``eps``: the points are uniform in the box plus the box's grid of 5
    points per axis (its faces and corners).

    Returns
    -------
    dict
        ``n`` (points), ``max_error`` (per output) and ``argmax`` (the point of each, (m, n_in)).
    """
    if not (isinstance(n, (int, np.integer)) and n > 0):
        raise ValueError(f"n must be a positive integer, got {n!r}")
    rng = np.random.default_rng(seed)
    best, arg = np.full(system.m, -np.inf), np.zeros((system.m, system.n_in))
    batches = [system.grid(5)] + [None] * int(np.ceil(n / chunk))
    done = 0
    for X in batches:
        if X is None:
            k = min(chunk, n - done)
            X, done = rng.uniform(system.lo, system.hi, (k, system.n_in)), done + k
        E = np.abs(system.phi_stacked(X) - net(X))
        i = E.argmax(0)
        better = E[i, np.arange(system.m)] > best
        best = np.where(better, E[i, np.arange(system.m)], best)
        arg[better] = X[i[better]]
    return dict(n=int(n + len(batches[0])), max_error=best, argmax=arg)


def arm_clf_cbf(system: FLSystem, net: ReLUNet, eps, cost: str = "quadratic", backend: str = "exact",
                obstacle: bool = True, setting: Optional[dict] = None) -> ClfCbfController:
    """The chapter's CLF-CBF controller (eq. CLF_CBF) for the arm, with the obstacle's barriers.

    ``H`` is the list of :func:`flnotes.arm.arm_obstacle_cbfs` (one condition
    (CLF_CBF_d) per point of the second link); ``obstacle=False`` leaves them out.
    """
    S = dict(ARM_CLF_CBF, **(setting or {}))
    H = arm_obstacle_cbfs(S["center"], S["radius"], S["n_points"], S["k1"]) if obstacle else None
    K = S["K"]
    return ClfCbfController(system, net, eps, QuadraticCLF(S["P"]), H, k=lambda z: -K @ z, cost=cost,
                            backend=backend, beta=S["beta"], kappa=S["kappa"])


def comparison_states(ctrl: ClfCbfController, n: int, seed: int = 0, boundary_share: float = 0.5,
                      tol: float = 1e-7) -> tuple[Array, Array]:
    """Random safe states for comparing back-ends, a share of them with the optimum on the network's bound.

    States are drawn uniformly in the domain box among those where every
    barrier of ``ctrl`` is nonnegative (the states a safe closed loop visits).
    ``boundary_share`` of them are states where ``ctrl``'s optimum ``v*`` has
    ``| |Phi_NN,i(z, v*)| - u_max^eps_i | <= tol`` for some ``i``: the optimum lies on
    the boundary of the network's input set (the hard case, where screening does
    not decide); the rest are the first other states drawn.

    Returns
    -------
    Z, on_boundary
        States (n, n_z) and, per state, whether ``ctrl``'s optimum is on the bound.
    """
    if not (isinstance(n, (int, np.integer)) and n > 0):
        raise ValueError(f"n must be a positive integer, got {n!r}")
    if not 0.0 <= boundary_share <= 1.0:
        raise ValueError(f"boundary_share must lie in [0, 1], got {boundary_share!r}")
    s = ctrl.system
    rng = np.random.default_rng(seed)
    n_b = int(round(boundary_share * n))
    bnd, rest = [], []
    for _ in range(200):
        Z = rng.uniform(s.lo[: s.n_z], s.hi[: s.n_z], (max(4 * n, 200), s.n_z))
        for h in ctrl.H:
            Z = Z[h.value(Z) >= 0]
        for z in Z:
            if len(bnd) >= n_b and len(rest) >= n - n_b:
                break
            r = ctrl.step(z)
            on = (not r.fallback) and bool(np.min(np.abs(np.abs(r.info["phi_nn"]) - ctrl.u_eps)) <= tol)
            if on and len(bnd) < n_b:
                bnd.append(z)
            elif not on and len(rest) < n - n_b:
                rest.append(z)
        if len(bnd) >= n_b and len(rest) >= n - n_b:
            break
    else:
        raise ValueError(f"found {len(bnd)} of {n_b} boundary states: lower boundary_share")
    ctrl.reset()
    Z = np.array(bnd + rest).reshape(-1, s.n_z)
    return Z, np.r_[np.ones(len(bnd), bool), np.zeros(len(rest), bool)]


def exact_vs_mip(system: FLSystem, net: ReLUNet, eps, n: int, seed: int = 0, mip: str = "scip",
                 costs: Sequence[str] = ("linear", "quadratic")) -> tuple[Table, dict]:
    """The exact two-input method against a MIP back-end at the same states, for both costs.

    For each cost, the chapter's controller (:func:`arm_clf_cbf`, ``backend="exact"``)
    and its ``with_backend(mip)`` solve eq. (CLF_CBF) at the ``n`` states of
    :func:`comparison_states` (half with the optimum on the network's bound);
    :func:`flnotes.pieces.compare_exact_mip` compares the optima, with one persistent MIP
    model updated in place from state to state, as the controller runs (its tightening
    margin is reset at every solve, so the states before do not change a state's program).

    Returns
    -------
    table, results
        One row per (cost, back-end) with :func:`flnotes.time_stats` of the time
        per step; ``results[cost]`` is the dict of :func:`compare_exact_mip` plus
        ``boundary_states``.
    """
    rows, out = [], {}
    for cost in costs:
        ex = arm_clf_cbf(system, net, eps, cost=cost, backend="exact")
        Z, on = comparison_states(ex, n, seed=seed)
        other = ex.with_backend(mip)
        r = compare_exact_mip(ex, other, Z)
        r["boundary_states"] = int(on.sum())
        out[cost] = r
        name = "Lcost" if cost == "linear" else "Qcost"
        for be, key in (("exact", "exact"), (mip, "mip")):
            st = time_stats(r["times_s"][key], percentiles=(50, 99))
            rows.append({"cost": name, "backend": be, "states": r["states"], "min ms": st["min_ms"],
                         "median ms": st["median_ms"], "p99 ms": st["p99_ms"], "max ms": st["max_ms"],
                         "max rel. gap": r["max_rel_objective_gap_hard"] if key == "mip" else None})
    return Table(rows), out


def softened_states(system: FLSystem, net: ReLUNet, eps, n: int, seed: int = 0, cost: str = "linear",
                    n_samples: int = 20_000) -> dict:
    """Where the exact controller ran the softened program: would the true set have met the CBF rows?

    At the ``n`` states of :func:`comparison_states` (as in :func:`exact_vs_mip`), the
    states where ``backend="exact"`` fell back on the softened program (its hard program,
    eq. (CLF_CBF) with ``|Phi_NN| <= u_max^eps``, is infeasible) are checked on ``n_samples``
    seeded uniform inputs of the ``v``-box: is some ``v`` in the true set
    ``V(z) = {v : |Phi(z, v)| <= u_max}`` with every CBF row ``a_H v + b_H >= 0``? A sample
    that does is a witness; none found is no proof of infeasibility.

    Returns
    -------
    dict
        ``states``, ``softened`` (count), ``true_feasible`` (softened states with a witness),
        ``cbf_feasible`` (softened states where a sampled ``v`` meets the CBF rows alone).
    """
    if not (isinstance(n_samples, (int, np.integer)) and n_samples > 0):
        raise ValueError(f"n_samples must be a positive integer, got {n_samples!r}")
    ctrl = arm_clf_cbf(system, net, eps, cost=cost, backend="exact")
    Z, _ = comparison_states(ctrl, n, seed=seed)
    n_z = system.n_z
    Vs = np.random.default_rng(seed).uniform(system.lo[n_z:], system.hi[n_z:], (n_samples, system.m))
    soft = true_ok = cbf_ok = 0
    for z in Z:
        if not ctrl.step(z).fallback:
            continue
        soft += 1
        d = ctrl.program_data(z)
        cbf = np.all(Vs @ d["aH"].T + d["bH"] >= 0, axis=1)
        inside = np.all(np.abs(system.Phi(np.broadcast_to(z, (n_samples, n_z)), Vs)) <= system.u_max, axis=1)
        cbf_ok += bool(cbf.any())
        true_ok += bool(np.any(cbf & inside))
    return dict(states=len(Z), softened=soft, true_feasible=true_ok, cbf_feasible=cbf_ok)


def nominal_run(system: FLSystem, setting: Optional[dict] = None) -> SimLog:
    """The nominal law ``k(z) = -K_nominal z`` (clipped to the ``v``-box) alone on the true plant, from the chapter's start."""
    S = dict(ARM_CLF_CBF, **(setting or {}))
    K, lo, hi = S["K"], system.lo[system.n_z:], system.hi[system.n_z:]
    return simulate(system, lambda z: np.clip(-K @ z, lo, hi), t_final=S["t_final"], ts=S["ts"], z0=S["z0"],
                    hold="u", progress=False)


def torque_checks(log: SimLog) -> dict:
    """The true torques of a run against ``tau_max``: at the samples and between them.

    Returns ``ratio_samples`` and ``ratio_between`` (per joint, ``max_k |tau_i| / tau_max,i``),
    ``within`` (every sample and every recorded point between samples ``<= tau_max``, to 1e-9).
    """
    u_max = log.system.u_max
    rs = np.abs(log.u).max(0) / u_max
    rb = np.abs(log.u_fine).max(0) / u_max if len(log.u_fine) else rs
    return dict(ratio_samples=rs, ratio_between=rb,
                within=bool(np.all(np.abs(log.u) <= u_max + 1e-9) and np.all(np.abs(log.u_fine) <= u_max + 1e-9)))


def obstacle_run(system: FLSystem, net: ReLUNet, eps, cost: str = "quadratic", backend: str = "exact",
                 t_final: Optional[float] = None, setting: Optional[dict] = None) -> tuple[SimLog, dict]:
    """The CLF-CBF closed loop around the obstacle on the true plant (``u`` held between samples).

    Returns
    -------
    log, checks
        ``checks``: :func:`torque_checks`, ``min_distance`` (m, the links to the
        obstacle's centre, :func:`flnotes.arm.links_distance`, at the samples) and ``min_distance_between``
        (the same along the integrated trajectory, samples included), ``radius``, ``inflated_radius``
        (the barriers' ``R``), ``min_h`` (the barriers ``h`` at the samples) and ``min_h_between`` (along the
        integrated trajectory), ``final_h`` (the smallest
        ``h`` at the last state), ``final_delta`` (the CLF slack of the last step),
        ``fallback_steps``, ``left_domain_steps``, ``final_norm_z``, ``times`` (:func:`flnotes.time_stats`).
    """
    S = dict(ARM_CLF_CBF, **(setting or {}))
    ctrl = arm_clf_cbf(system, net, eps, cost=cost, backend=backend, setting=setting)
    log = simulate(system, ctrl, t_final=S["t_final"] if t_final is None else t_final, ts=S["ts"], z0=S["z0"],
                   hold="u", net=net, progress=False)
    s = log.summary()
    Zf = np.vstack([log.z_fine, log.z]) if len(log.z_fine) else log.z
    checks = dict(torque_checks(log), min_distance=float(links_distance(log.z[:, [0, 2]], S["center"]).min()),
                  min_distance_between=float(links_distance(Zf[:, [0, 2]], S["center"]).min()),
                  radius=float(S["radius"]), inflated_radius=float(ctrl.H[0].R),
                  min_h=float(min(h.h(log.z).min() for h in ctrl.H)),
                  min_h_between=float(min(h.h(Zf).min() for h in ctrl.H)),
                  final_h=float(min(h.h(log.z[-1:])[0] for h in ctrl.H)),
                  final_delta=float(log.steps[-1].info["delta"]) if log.steps else float("nan"),
                  fallback_steps=s["fallback_steps"], left_domain_steps=s["left_domain_steps"],
                  final_norm_z=s["final_norm_z"], times=time_stats(log.solve_time))
    return log, checks


def setpoint_reference(setpoints: Array, t_switch: float) -> Callable[[Array], Array]:
    """``t -> z_ref(t)``: joint angles at rest at ``setpoints[j]`` for ``j t_switch <= t < (j+1) t_switch``.

    ``setpoints`` (J, 2) are angles ``(q_1, q_2)``; the reference is vectorized,
    (T,) -> (T, 4) in the order ``z = (q_1, q_1', q_2, q_2')``; it stays at the last set point.
    """
    Sp = np.asarray(setpoints, float)
    if Sp.ndim != 2 or Sp.shape[1] != 2:
        raise ValueError(f"setpoints must have shape (J, 2) (joint angles), got {Sp.shape}")
    if not t_switch > 0:
        raise ValueError(f"t_switch must be positive, got {t_switch!r}")

    def ref(t):
        j = np.minimum((np.atleast_1d(np.asarray(t, float)) // t_switch).astype(int), len(Sp) - 1)
        q = Sp[np.maximum(j, 0)]
        return np.column_stack([q[:, 0], np.zeros(len(q)), q[:, 1], np.zeros(len(q))])

    return ref


def mpc_run(system: FLSystem, net: ReLUNet, eps, t_final: Optional[float] = None,
            setting: Optional[dict] = None, **mpc_options) -> tuple[SimLog, dict]:
    """The MPC closed loop (eq. MPC_form) tracking the set-point reference on the true plant (``u`` held).

    ``fl.MPC`` with its default options unless ``mpc_options`` change them.

    Returns
    -------
    log, checks
        ``checks``: :func:`torque_checks`, ``fallback_steps``, ``non_optimal_steps``,
        ``final_error`` (``max |z - z_ref|`` over the last second), ``settle_errors`` (the same over the
        last second at each set point: before the prediction horizon reaches the next one, and at the end), ``times``
        (:func:`flnotes.time_stats`).
    """
    S = dict(ARM_MPC, **(setting or {}))
    mpc = MPC(system, net, eps, horizon=S["horizon"], ts=S["ts"], Q=S["Q"], R=S["R"], **mpc_options)
    ref = setpoint_reference(S["setpoints"], S["t_switch"])
    log = simulate(system, mpc, t_final=S["t_final"] if t_final is None else t_final, ts=S["ts"], z0=S["z0"],
                   reference=ref, hold="u", net=net, progress=False)
    s = log.summary()
    err = np.abs(log.z - ref(log.t)).max(1)
    # the MPC sees the reference over its horizon and leaves a set point N_p t_s before the switch
    lead = S["horizon"] * S["ts"]
    ends = [t - lead for t in S["t_switch"] * np.arange(1, len(S["setpoints"])) if t <= log.t[-1] + 1e-9]
    settle = [float(err[(log.t >= t - 1.0) & (log.t < t - 1e-9)].max()) for t in ends]
    settle.append(float(err[log.t >= log.t[-1] - 1.0].max()))
    checks = dict(torque_checks(log), fallback_steps=s["fallback_steps"], non_optimal_steps=s["non_optimal_steps"],
                  final_error=float(err[log.t >= log.t[-1] - 1.0].max()), settle_errors=settle,
                  times=time_stats(log.solve_time))
    return log, checks
