"""Studies of chapter 6: checks of a CLF-CBF run, Table 2's rows, the exact method against a back-end."""
from __future__ import annotations

from typing import Any, Optional

import numpy as np

from .. import paper
from ..control import ClfCbfController, _cbf_list
from ..simulate import SimLog
from ..systems import FLSystem
from ..tables import Table, time_stats

Array = np.ndarray

#: The back-ends of :class:`flnotes.ClfCbfController` that solve the program as a MILP/MIQP (screening first).
MIP_BACKENDS = ("scip", "highs")

__all__ = ["clf_cbf_checks", "chapter_eps", "cross_check_exact", "solve_time_table", "paper_mean_ms",
           "exponential_cbf_grid_check", "sampled_clf_decrease", "largest_change_within_sample",
           "cbf_failure_set_bounded", "highs_alone_check", "braking_scan"]


def clf_cbf_checks(log: SimLog, H: Any = None) -> dict:
    """The chapter's checks, computed from a closed-loop run.

    Parameters
    ----------
    log
        A run of :func:`flnotes.simulate`.
    H
        The CBF (or list of CBFs) whose minimum along the run is reported.

    Returns
    -------
    dict
        ``max_abs_u`` (true plant, at samples and between them) vs ``u_max``,
        ``max_abs_u_nn`` vs ``u_max^eps`` when logged, ``min_H`` at samples and
        along the integrated trajectory, the final ``||z||``, and the counts of
        non-optimal and fallback steps.
    """
    s = log.summary()
    out = dict(steps=s["steps"], u_max=s["u_max"][0] if len(s["u_max"]) == 1 else s["u_max"],
               max_abs_u=max(s["max_abs_u_samples"]) if s["steps"] else np.nan,
               max_abs_u_between=max(s["max_abs_u_between"]) if s["steps"] else np.nan,
               final_norm_z=s["final_norm_z"], non_optimal_steps=s["non_optimal_steps"],
               fallback_steps=s["fallback_steps"], left_domain_steps=s["left_domain_steps"], message=s["message"])
    if log.u_nn is not None and s["steps"]:
        out["max_abs_u_nn"] = float(np.abs(log.u_nn).max())
    if H is not None:
        Hs = _cbf_list(H)
        Z = log.z
        Zf = np.vstack([log.z_fine, log.z[-1:]]) if len(log.z_fine) else Z
        out["min_H"] = float(min(np.min(h(Z)) for h in Hs))
        out["min_H_between"] = float(min(np.min(h(Zf)) for h in Hs))
    return out


def _state_grid(system: FLSystem, kappa: float, n: int) -> Array:
    """The ``n x n`` grid of the z-box of a one-input, two-state ``system`` (rows), after checking ``kappa > 0``."""
    if system.m != 1 or system.n_z != 2:
        raise ValueError(f"the grid check is for one input and two states, got m = {system.m}, n_z = {system.n_z}")
    if not (np.isfinite(kappa) and kappa > 0):
        raise ValueError(f"kappa must be a positive gain, got {kappa!r}")
    lo, hi = system.lo, system.hi
    g1, g2 = np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n), indexing="ij")
    return np.column_stack([g1.ravel(), g2.ravel()])


def exponential_cbf_grid_check(system: Any, net: Any, eps: float, H2: Any, kappa: float, n: int = 201) -> dict:
    """Is the exponential CBF ``H2`` valid under the input bound at every state of a grid of the safe set?

    On an ``n`` by ``n`` grid of the domain box's ``z``-part, the states of the
    safe set ``{h >= 0, H_2 >= 0}`` (``h = H2.h``) are kept. At each, the CBF
    condition of eq. (CLF_CBF_d) for ``H_2``, ``a_H v + b_H >= 0`` with
    ``a_H = grad H_2^T B`` and ``b_H = grad H_2^T A z + kappa H_2(z)``, is
    maximized over the admissible ``v``; its largest value is the *margin* (a
    positive margin: some admissible ``v`` satisfies the condition with room to
    spare). Two input sets are checked, vectorized over the grid:

    - the true bound, ``|Phi(z, v)| <= u_max`` and ``v`` in the box;
    - the network's bound ``|Phi_NN(z, v)| <= u_max - eps`` (eq. Phi_NN_ep),
      through a witness: every ``v`` with ``|Phi(z, v)| <= u_max - 2 eps`` meets
      it, because ``|Phi - Phi_NN| <= eps`` on the box. The witness margin is
      therefore a lower bound of the network's margin; the network is also
      evaluated at the witnesses (the largest ``|Phi_NN|`` there is returned).

    ``Phi`` must be affine in the single input ``v`` with a positive slope
    (checked on the grid), as it is for the mass-spring-damper.

    Parameters
    ----------
    system
        The plant (:class:`flnotes.FLSystem`, one input).
    net
        The network ``Phi_NN`` (:class:`flnotes.ReLUNet`).
    eps
        The certified error bound of the network.
    H2
        An :class:`flnotes.ExponentialCBF` (constant gradient).
    kappa
        The CBF gain.
    n
        Grid points per axis.

    Returns
    -------
    dict
        ``states`` (grid states in the safe set), ``margin_true`` and
        ``margin_network`` (the smallest margins over them), ``argmin_true``
        (the state of the smallest true margin) and ``max_abs_u_nn_witness``
        (the largest ``|Phi_NN|`` at the network's witnesses, to compare with
        ``u_max - eps``).
    """
    from ..control import ExponentialCBF
    if not isinstance(H2, ExponentialCBF):
        raise TypeError(f"H2 must be an ExponentialCBF (constant gradient), got {type(H2).__name__}")
    Z = _state_grid(system, kappa, n)
    Z = Z[(H2.h.value(Z) >= 0) & (H2.value(Z) >= 0)]
    if len(Z) == 0:
        raise ValueError("no grid state lies in the safe set {h >= 0, H_2 >= 0}: refine the grid or check H2")
    g = H2.grad(Z[0])
    a_H = float(g @ system.B[:, 0])
    b_H = Z @ (system.A.T @ g) + kappa * H2.value(Z)
    v_lo, v_hi = float(system.lo[2]), float(system.hi[2])
    phi0 = system.Phi(Z, np.zeros((len(Z), 1)))[:, 0]
    slope = system.Phi(Z, np.ones((len(Z), 1)))[:, 0] - phi0
    at_hi = system.Phi(Z, np.full((len(Z), 1), v_hi))[:, 0]
    if not (np.all(slope > 0) and np.allclose(at_hi, phi0 + slope * v_hi, rtol=1e-9, atol=1e-9)):
        raise ValueError("Phi must be affine in v with a positive slope for this check")
    u_max = float(system.u_max[0])

    def margin(bound: float) -> tuple[Array, Array]:
        v_a = np.maximum(v_lo, (-bound - phi0) / slope)   # admissible interval [v_a, v_b] of v
        v_b = np.minimum(v_hi, (bound - phi0) / slope)
        best = v_b if a_H > 0 else v_a                     # the end that makes a_H v + b_H largest
        return np.where(v_a <= v_b, a_H * best + b_H, -np.inf), best

    (m_true, _), (m_net, v_w) = margin(u_max), margin(u_max - 2.0 * float(eps))
    u_nn = np.asarray(net(np.column_stack([Z, v_w])), float).reshape(len(Z), -1)
    i = int(np.argmin(m_true))
    return dict(states=int(len(Z)), margin_true=float(m_true.min()), margin_network=float(m_net.min()),
                argmin_true=Z[i], max_abs_u_nn_witness=float(np.abs(u_nn).max()))


def chapter_eps(name: str = "MSD") -> tuple[Array, str]:
    """The error bound ``eps`` of eq. (approx_err) that the controller uses, and where it comes from.

    The certified upper bound ``flnotes.paper.paper_eps(name).upper`` of the
    shipped network.
    """
    return np.atleast_1d(np.asarray(paper.paper_eps(name).upper, float)), "certified upper bound"


def cross_check_exact(controller: ClfCbfController, log: SimLog, ts: Optional[float] = None) -> dict:
    """Re-solve the program at every sampled state of a run with the exact 1-D method and compare.

    Parameters
    ----------
    controller
        The controller that produced ``log`` (single input).
    log
        Its run; ``log.steps[i].objective`` is compared with the exact
        optimum at ``log.z[i]`` (of the softened program at fallback steps,
        which both methods solve alike).
    ts
        The sampling time (s); if given, ``exact_over_ts`` counts the states at which the exact
        method's wall-clock time exceeded it (a machine-dependent count).

    Returns
    -------
    dict
        ``max_abs_diff`` and ``max_rel_diff`` (``|J - J_exact| / max(1, |J_exact|)``)
        of the optimal values, ``max_v_diff``, ``steps``, and the exact
        method's per-step times (ms) ``exact_ms_min/median/max/mean`` (and ``exact_over_ts``), and the state
        ``exact_argmax_z`` of its slowest step.
    """
    if ts is not None and not (np.isfinite(ts) and ts > 0):
        raise ValueError(f"ts must be a positive sampling time in seconds, got {ts!r}")
    ex = controller.with_backend("exact")
    J, Jx, v, vx, t, Zs = [], [], [], [], [], []
    for z, r in zip(log.z[:-1], log.steps):
        if not np.isfinite(r.objective):
            continue
        rx = ex.step(z)
        Zs.append(z), J.append(r.objective), Jx.append(rx.objective)
        v.append(r.v), vx.append(rx.v), t.append(rx.solve_time)
    J, Jx, t = np.array(J), np.array(Jx), np.array(t) * 1e3
    d = np.abs(J - Jx)
    over = {} if ts is None else dict(exact_over_ts=int(np.sum(t > 1e3 * ts)))
    return dict(over, steps=len(J), max_abs_diff=float(d.max()) if len(d) else np.nan,
                max_rel_diff=float((d / np.maximum(1.0, np.abs(Jx))).max()) if len(d) else np.nan,
                max_v_diff=float(np.abs(np.array(v) - np.array(vx)).max()) if len(d) else np.nan,
                exact_ms_min=float(t.min()), exact_ms_median=float(np.median(t)),
                exact_ms_max=float(t.max()), exact_ms_mean=float(t.mean()),
                exact_argmax_z=np.array(Zs[int(np.argmax(t))], float))


def solve_time_table(logs: dict, system: str = "MSD", ts: Optional[float] = None) -> Table:
    """Table 2's rows: min / median / max / mean solve time (ms) per controller, beside the paper's.

    Parameters
    ----------
    logs
        ``{controller name: SimLog}``, e.g. ``{"Lcost": ..., "Qcost": ..., "k(z)": ...}``.
    system
        The paper's system name for the reference rows of ``flnotes.paper.TABLE2_MS``.
    ts
        The sampling time (s); if given, the column ``over_ts`` counts the steps whose wall-clock
        time exceeded it (a machine-dependent count: :func:`flnotes.simulate` applies each input at
        its sample, as if it had been computed instantly).

    Returns
    -------
    Table
        Per controller: wall-clock ``min``, ``median``, ``max``, ``mean`` (ms), the controller's CPU
        time ``cpu_median`` and ``cpu_max`` (ms), ``over_ts`` when ``ts`` is given, and the paper's numbers.
        For a MIP back-end (``scip``, ``highs``, ``cvxpy``) also ``mip_steps`` (the steps that screening did not
        settle, so that the MIP solver ran) and ``mip_median`` (ms, the median wall-clock time over those steps:
        the time of a MILP/MIQP solve, comparable in kind with the paper's, where every step is one).
    """
    if ts is not None and not (np.isfinite(ts) and ts > 0):
        raise ValueError(f"ts must be a positive sampling time in seconds, got {ts!r}")
    rows = Table()
    for name, log in logs.items():
        st = time_stats(log.solve_time)
        cpu = np.array([r.info.get("cpu_time", np.nan) for r in log.steps], float) * 1e3
        ref = paper.TABLE2_MS.get((system, name), {})
        backend = (log.steps[0].backend or "numpy") if log.steps else ""
        has_cpu = bool(np.isfinite(cpu).any())
        row = dict(controller=name, backend=backend, steps=len(log.solve_time),
                   min=st["min_ms"], median=st["median_ms"], max=st["max_ms"], mean=st["mean_ms"],
                   cpu_median=float(np.nanmedian(cpu)) if has_cpu else None,
                   cpu_max=float(np.nanmax(cpu)) if has_cpu else None)
        if backend in MIP_BACKENDS or backend.startswith("cvxpy"):
            mip = np.array([not r.screened for r in log.steps], bool)
            row["mip_steps"] = int(mip.sum())
            row["mip_median"] = float(np.median(np.asarray(log.solve_time, float)[mip]) * 1e3) if mip.any() else None
        if ts is not None:
            row["over_ts"] = int(np.sum(np.asarray(log.solve_time, float) > ts))
        rows.append(dict(row, paper_min=ref.get("min"), paper_max=ref.get("max"), paper_mean=ref.get("mean")))
    return rows


def paper_mean_ms(system: str = "MSD") -> dict:
    """The paper's mean time per step (Table 2, ms) of each controller of ``system``, by name."""
    return {name: ref["mean"] for (sysname, name), ref in paper.TABLE2_MS.items() if sysname == system}


def sampled_clf_decrease(log: SimLog, V: Any) -> dict:
    """How the CLF ``V`` behaves from one sample to the next along a run (eq. CLF_CBF).

    The CLF row of eq. (CLF_CBF) is a continuous-time condition imposed at the
    samples; with the input held between them it does not make the *sampled*
    ``V(z_k)`` decrease. This reports whether it did.

    Parameters
    ----------
    log
        A run of :func:`flnotes.simulate` of a CLF-CBF controller.
    V
        The CLF (an object with ``value(Z)``).

    Returns
    -------
    dict
        ``steps`` (sample pairs), ``rise_fraction`` (share of ``k`` with
        ``V(z_{k+1}) > V(z_k)``), ``max_rise_ratio`` (largest ``V(z_{k+1}) / V(z_k)``),
        ``max_delta`` (largest CLF slack of the steps, ``nan`` if not logged),
        ``last_V`` and ``last_u`` (the last four samples, to read a cycle off).
    """
    Vz = np.asarray(V.value(log.z), float)
    if len(Vz) < 2:
        raise ValueError(f"the run has {len(Vz)} samples: need at least 2 to compare V from one to the next")
    ratio = Vz[1:] / np.maximum(Vz[:-1], np.finfo(float).tiny)
    deltas = [float(s.info["delta"]) for s in log.steps if s.info and s.info.get("delta") is not None]
    return dict(steps=int(len(ratio)), rise_fraction=float(np.mean(ratio > 1.0)), max_rise_ratio=float(ratio.max()),
                max_delta=float(max(deltas)) if deltas else np.nan, last_V=Vz[-4:].copy(),
                last_u=np.asarray(log.u, float)[-4:, 0].copy())


def largest_change_within_sample(log: SimLog, fn: Any) -> float:
    """The largest change ``max - min`` of ``fn(z(t))`` within one sampling interval of a run.

    Parameters
    ----------
    log
        A run of :func:`flnotes.simulate` (its fine trajectory ``t_fine``, ``z_fine``).
    fn
        A vectorized function of the states, ``fn(Z)`` with ``Z`` of shape (N, n_z).

    Returns
    -------
    float
        ``max_k (max - min)`` of ``fn`` over the fine points of interval ``k``.
    """
    if len(log.t_fine) == 0:
        raise ValueError("the run has no fine trajectory (t_fine is empty): simulate it with fl.simulate")
    f = np.asarray(fn(log.z_fine), float).reshape(len(log.t_fine))
    k = np.clip(np.searchsorted(log.t, log.t_fine, side="right") - 1, 0, None)
    hi = np.full(k.max() + 1, -np.inf)
    lo = np.full(k.max() + 1, np.inf)
    np.maximum.at(hi, k, f)
    np.minimum.at(lo, k, f)
    return float(np.max(hi - lo))


def cbf_failure_set_bounded(system: Any, H: Any, kappa: float, n: int = 801, h: float = 1e-6,
                            net: Any = None, eps: Optional[float] = None) -> dict:
    """Safe grid states at which no admissible ``v`` satisfies the CBF condition (CLF_CBF_d).

    On an ``n`` by ``n`` grid of the domain box's ``z``-part, the states with
    ``H(z) >= 0`` are kept; at each, ``a_H v + b_H`` with ``a_H = grad H^T B`` and
    ``b_H = grad H^T A z + kappa H(z)`` is maximized over the admissible ``v``
    (``Phi`` affine in the single input, checked). ``grad H`` is taken by central
    differences of step ``h`` (vectorized over the grid). Two input sets:

    - the true bound ``|Phi(z, v)| <= u_max`` (any ``v``);
    - with ``net`` and ``eps``: the controller's set, ``|Phi_NN(z, v)| <= u_max - eps`` with ``v`` in the
      domain box (eq. Phi_NN_ep). It lies inside the true set (``|Phi - Phi_NN| <= eps``), so every state that
      fails the true bound fails it too; it contains the witness set ``|Phi(z, v)| <= u_max - 2 eps`` (in the
      box), so a state that the witness set serves does not fail. The states between the two are decided
      exactly on the network's feasible intervals (:func:`flnotes.exact_1d_feasible_set`).

    Returns
    -------
    dict
        ``grid`` (states of the grid), ``safe`` (of them with ``H >= 0``), ``failing``
        (safe states with a negative best margin under the true bound), ``Z_fail`` (those states);
        with ``net``: ``failing_network`` and ``Z_fail_network`` (the same under the network's set),
        ``decided_exactly`` (states decided on the network's intervals).
    """
    if (net is None) != (eps is None):
        raise ValueError("give both net and eps (the network's set |Phi_NN| <= u_max - eps), or neither")
    Z = _state_grid(system, kappa, n)
    Hz = H.value(Z)
    Z, Hz = Z[Hz >= 0], Hz[Hz >= 0]
    G = np.column_stack([(H.value(Z + h * e) - H.value(Z - h * e)) / (2 * h) for e in np.eye(2)])
    a_H = G @ system.B[:, 0]
    b_H = np.einsum("ij,ij->i", G, Z @ system.A.T) + kappa * Hz
    phi0 = system.Phi(Z, np.zeros((len(Z), 1)))[:, 0]
    slope = system.Phi(Z, np.ones((len(Z), 1)))[:, 0] - phi0
    if not (np.all(slope > 0) and np.allclose(system.Phi(Z, np.full((len(Z), 1), 2.0))[:, 0], phi0 + 2 * slope)):
        raise ValueError("Phi must be affine in v with a positive slope for this check")
    u_max = float(system.u_max[0])
    v_a, v_b = (-u_max - phi0) / slope, (u_max - phi0) / slope
    best = np.maximum(a_H * v_a, a_H * v_b) + b_H
    fail = best < 0
    out = dict(grid=int(n * n), safe=int(len(Z)), failing=int(fail.sum()), Z_fail=Z[fail])
    if net is None:
        return out
    eps = float(np.asarray(eps, float).reshape(-1)[0])
    if not (np.isfinite(eps) and 0 <= eps < u_max / 2):
        raise ValueError(f"eps must lie in [0, u_max / 2) for the witness set, got {eps!r}")
    from ..control import exact_1d_feasible_set
    v_lo, v_hi = float(system.lo[2]), float(system.hi[2])
    w_a = np.maximum(v_lo, (-(u_max - 2 * eps) - phi0) / slope)   # the witness interval, in the box
    w_b = np.minimum(v_hi, ((u_max - 2 * eps) - phi0) / slope)
    served = (w_a <= w_b) & (np.maximum(a_H * w_a, a_H * w_b) + b_H >= 0)
    fail_net = fail.copy()
    undecided = np.flatnonzero(~served & ~fail)
    for i in undecided:
        iv = exact_1d_feasible_set(net, Z[i], v_lo, v_hi, u_max - eps)
        fail_net[i] = len(iv) == 0 or np.max(a_H[i] * iv.ravel()) + b_H[i] < 0
    return dict(out, failing_network=int(fail_net.sum()), Z_fail_network=Z[fail_net],
                decided_exactly=int(len(undecided)))


def highs_alone_check(controller: ClfCbfController, Z: Array, tol: float = 1e-6) -> dict:
    """HiGHS alone (one solve, no cross-check, no screening) against the exact 1-D method at the states ``Z``.

    The MILP of eq. (CLF_CBF) (the controller's program, linear cost) is solved at each state by
    ``controller.with_backend("highs", screening=False, solver_options=dict(cross_check=False))``:
    flnotes' HiGHS settings (presolve on, tolerances 1e-8) without the second solve that the
    back-end normally adds, and compared with ``backend="exact"``.

    Returns
    -------
    dict
        ``states``; ``wrong_value`` (states where both report ``"optimal"`` but the optimal values
        differ by more than ``tol`` relative, ``|J - J_exact| / max(1, |J_exact|)``);
        ``wrong_status`` (states where the statuses differ) and ``status_pairs`` (their
        ``(HiGHS, exact)`` status pairs, counted); ``min_gap`` (the smallest signed relative gap
        ``(J - J_exact) / max(1, |J_exact|)`` where both are optimal: negative would mean HiGHS beat
        the exact optimum); and at the largest gap, ``worst_z``, ``worst_highs``, ``worst_exact``
        (optimal values) and ``worst_gap`` (``None`` and NaN when no value is wrong).
    """
    if controller.cost != "linear":
        raise ValueError(f"HiGHS has no mixed-integer QP solver: give the linear-cost controller, got cost={controller.cost!r}")
    Z = np.atleast_2d(np.asarray(Z, float))
    hi = controller.with_backend("highs", screening=False, solver_options=dict(cross_check=False))
    ex = controller.with_backend("exact")
    gaps, pairs, worst = [], {}, (None, np.nan, np.nan, np.nan)
    for z in Z:
        r, rx = hi.step(z), ex.step(z)
        if r.status != rx.status:
            pairs[(r.status, rx.status)] = pairs.get((r.status, rx.status), 0) + 1
        elif r.status == "optimal":
            gap = (r.objective - rx.objective) / max(1.0, abs(rx.objective))
            gaps.append(gap)
            if gap > tol and not gap <= worst[3]:
                worst = (z.copy(), float(r.objective), float(rx.objective), float(gap))
    gaps = np.array(gaps)
    return dict(states=int(len(Z)), wrong_value=int(np.sum(np.abs(gaps) > tol)), wrong_status=int(sum(pairs.values())),
                status_pairs=pairs, min_gap=float(gaps.min()) if len(gaps) else np.nan,
                worst_z=worst[0], worst_highs=worst[1], worst_exact=worst[2], worst_gap=worst[3])


def braking_scan(system: FLSystem, H: Any, ts: float, z2: float = 1.0, coarse: Optional[Array] = None,
                 fine: Optional[Array] = None, t_final: float = 1.0, n_const: int = 21) -> dict:
    """Full braking ``u = -u_max`` from the states ``z = [z1, z2]`` of chapter 6's segment: the smallest ``H`` along
    each run (true plant, ``u`` held, ``t_final`` seconds), on a ``coarse`` scan of ``z1`` and a ``fine`` one near the
    segment's end, the crossover (the last ``z1`` of the fine scan that stays in ``H >= 0`` and the first that does
    not), and, from that first ``z1``, the best smallest ``H`` over ``n_const`` constant inputs in
    ``[-u_max, u_max]`` (the input enters as ``v = u - s(z2) - z1``, the MSD's linearizing input).

    Returns ``min_h`` and ``min_h_fine`` (arrays), ``coarse``, ``fine``, ``i_cross`` (index of the first fine point
    with ``H < 0``; 0 when none), ``z_safe``, ``z_lost``, ``best_const`` (the largest smallest-``H`` of the constant
    inputs from ``z_lost``) and ``brake_at_lost`` (full braking's smallest ``H`` there).
    """
    from ..simulate import FeedbackLaw, simulate
    from ..systems import stribeck

    u_max = float(np.asarray(system.u_max).reshape(-1)[0])
    coarse = np.arange(0.46, 0.695, 0.01) if coarse is None else np.asarray(coarse, float)
    fine = np.round(np.arange(0.690, 0.70001, 5e-4), 4) if fine is None else np.asarray(fine, float)

    def law(u: float) -> FeedbackLaw:
        return FeedbackLaw(lambda z: np.array([u - stribeck(z[1]) - z[0]]), name=f"u = {u:g}")

    def min_h(z1: float, u: float = -u_max) -> float:
        log = simulate(system, law(u), t_final=t_final, ts=ts, z0=np.array([z1, z2]), hold="u")
        return float(np.min(H(log.z_fine)))

    mh = np.array([min_h(z1) for z1 in coarse])
    mf = np.array([min_h(z1) for z1 in fine])
    i_cross = int(np.argmax(mf < 0)) if np.any(mf < 0) else 0
    z_lost = float(fine[i_cross])
    best = max(min_h(z_lost, u) for u in np.linspace(-u_max, u_max, n_const))
    return dict(coarse=coarse, fine=fine, min_h=mh, min_h_fine=mf, i_cross=i_cross,
                z_safe=float(fine[i_cross - 1]) if i_cross > 0 else float("nan"), z_lost=z_lost,
                best_const=float(best), brake_at_lost=float(mf[i_cross]))
