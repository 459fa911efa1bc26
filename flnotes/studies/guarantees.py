"""Studies of chapter 9: closed loops with and without terminal ingredients, and the margin between samples.

``terminal_sweep``
    the MPC regulating to the origin for several horizons, without terminal ingredients (the paper's program) and
    with the terminal cost and set of :mod:`flnotes.terminal`, on the nominal model and on the true plant;
``nominal_loop``
    one closed loop on the nominal model ``z+ = A_d z + B_d v`` (eq. MPC_form_miqp_c);
``fallback_table``
    the steps of a run that had no admissible plan, as the MPC recorded them;
``margin_study``
    closed loops with ``u_max^eps`` and ``u_max^{eps+Delta}`` for several sampling times: the true input on a
    fine grid between the samples, the tracking and the feasibility;
``intersample_sample``
    sampled pairs ``(z, v)`` admissible at the sample: the share whose true input stays within ``u_max`` over the
    whole hold (what the uniform worst case ``Delta`` does not say);
``guaranteed_loop``
    the MPC with the terminal ingredients built for ``u_max^{eps+Delta}`` on the true plant: the network bound
    active or not at each step, and the true input checked densely along the exact flow between the samples;
``margin_study_numbers``
    the figures and the clause on late steps that chapter 9 quotes from ``margin_study``.
"""
from __future__ import annotations

import time
from typing import Callable, Optional, Sequence

import numpy as np

from ..intersample import flow, intersample_drift
from ..mpc import MPC
from ..network import ReLUNet
from ..simulate import simulate
from ..systems import FLSystem
from ..terminal import TerminalSet

Array = np.ndarray

__all__ = ["nominal_loop", "plan_costs", "terminal_sweep", "fallback_table", "margin_study", "intersample_sample",
           "guaranteed_loop", "margin_study_numbers", "power_text", "margin_numbers"]


def _stage_costs(Z: Array, V: Array, Q: Array, R: Array) -> Array:
    """``ell(z_k, v_k) = z_k'Q z_k + v_k'R v_k`` for the applied steps (regulation to the origin)."""
    Z, V = Z[: len(V)], np.asarray(V, float).reshape(len(V), -1)
    return np.einsum("ij,jk,ik->i", Z, Q, Z) + np.einsum("ij,jk,ik->i", V, R, V)


def nominal_loop(mpc: MPC, z0: Array, n_steps: int, Ad: Array, Bd: Array, z_box: tuple,
                 z_ref: Optional[Array] = None) -> dict:
    """The MPC in closed loop with its own prediction model ``z+ = A_d z + B_d v`` (eq. MPC_form_miqp_c).

    The run stops early, as :func:`flnotes.simulate` does, when a sampled state lies outside the state box
    ``z_box``: the controller is not defined there.
    The controller's previous plan is cleared first (``mpc.reset()``); every step's record is kept.

    Parameters
    ----------
    mpc
        The controller.
    z0
        Initial state, (n_z,).
    n_steps
        Number of sampling steps.
    Ad, Bd
        The MPC's discrete model, (n_z, n_z) and (n_z, m).
    z_box
        ``(z_lo, z_hi)``, the state box.
    z_ref
        Constant reference, (n_z,); default the origin.

    Returns
    -------
    dict
        ``t`` (n+1,), ``z`` (n+1, n_z), ``v`` (n, m), ``steps`` (the n step records), ``box_exit`` (bool) and
        ``time_s``, with ``n <= n_steps`` the steps applied.
    """
    Ad, Bd = np.asarray(Ad, float), np.asarray(Bd, float)
    n, m = Bd.shape
    z = np.asarray(z0, float).reshape(n)
    z_lo, z_hi = (np.asarray(b, float).reshape(n) for b in z_box)
    ref = np.zeros(n) if z_ref is None else np.asarray(z_ref, float).reshape(n)
    mpc.reset()
    Z, V, steps, box_exit = [z], [], [], False
    t0 = time.perf_counter()
    for _ in range(int(n_steps)):
        if np.any(z < z_lo) or np.any(z > z_hi):  # a measured state outside the box: the loop stops there
            box_exit = True
            break
        step = mpc(z, ref)
        steps.append(step)
        z = Ad @ z + Bd @ step.v
        Z.append(z), V.append(step.v)
    return dict(t=mpc.ts * np.arange(len(Z)), z=np.array(Z), v=np.array(V).reshape(len(V), m), steps=steps,
                box_exit=box_exit, time_s=time.perf_counter() - t0)


def plan_costs(steps: Sequence, Q: Array, R: Array, P: Optional[Array] = None) -> Array:
    """The cost of eq. (MPC_form_miqp_a) (plus ``V_f(z(N_p)) = z(N_p)' P_f z(N_p)``, ``P_f`` passed as ``P``) of each
    step's plan, regulation to the origin.

    Computed from the plan itself (``z_pred``, ``v_pred``); NaN for a step without a proven optimal plan of its own
    (status other than ``"optimal"``, or a fallback).
    """
    out = np.full(len(steps), np.nan)
    for k, s in enumerate(steps):
        if s.status == "optimal" and not s.fallback:
            Z, V = np.asarray(s.z_pred, float), np.asarray(s.v_pred, float)
            out[k] = _stage_costs(Z, V, Q, R).sum() + (0.0 if P is None else float(Z[-1] @ P @ Z[-1]))
    return out


def _summarize(run: dict, Q: Array, R: Array, P: Optional[Array], system: FLSystem, n_planned: int) -> dict:
    Z, V, steps = run["z"], run["v"], run["steps"]
    stage = _stage_costs(Z, V, Q, R)
    J = plan_costs(steps, Q, R, P)
    # the Lyapunov decrease of the proof: J(z_{k+1}) <= J(z_k) - ell(z_k, v_k) between consecutive optimal steps
    dec = J[1:] - J[:-1] + stage[: len(J) - 1]
    ok = np.isfinite(dec)
    u = system.Phi(Z[: len(V)], V) if len(V) else np.zeros((0, system.m))
    # the true plant's input between the samples (u(t) = Phi(z(t), v_k), not saturated by the simulator)
    log = run.get("log")
    ub = log.summary()["max_abs_u_between"] if log is not None else []
    u_between = float(np.max(ub)) if len(ub) else np.nan
    # the measured decay rate over the second half of a completed run: ||z|| ~ exp(-rate t) there
    k2, nz = len(V) // 2, np.linalg.norm(Z, axis=1)
    done = len(V) == n_planned and not run["box_exit"] and k2 > 0 and nz[k2] > 0 and nz[-1] > 0
    rate = float(np.log(nz[k2] / nz[-1]) / ((len(V) - k2) * run["t"][1])) if done else np.nan
    return dict(steps=len(V), completed=len(V) == n_planned and not run["box_exit"],
                optimal=int(sum(s.status == "optimal" and not s.fallback for s in steps[: len(V)])),
                infeasible=int(sum(s.status == "infeasible" for s in steps)),
                fallback=int(sum(bool(s.fallback) for s in steps)),
                not_admissible=int(sum(not s.input_admissible for s in steps)),
                box_exit=bool(run["box_exit"]), cost=float(stage.sum()),
                final_norm_z=float(np.linalg.norm(Z[-1])), decay_rate=rate,
                max_cost_increase=float(np.max(dec[ok] / (1.0 + J[:-1][ok]))) if ok.any() else np.nan,
                max_abs_u_samples=float(np.abs(u).max()) if len(u) else np.nan, max_abs_u_between=u_between,
                time_s=run["time_s"])


def terminal_sweep(system: FLSystem, net: ReLUNet, eps, terminal: TerminalSet, horizons: Sequence[int],
                   z0: Array, t_final: float, plants: Sequence[str] = ("nominal", "true"),
                   **mpc_kwargs) -> tuple[dict, list[dict]]:
    """Regulation to the origin for several ``N_p``, without and with the terminal ingredients.

    Without: the paper's program, eq. (MPC_form_miqp) (``P=None``, no terminal constraint). With: terminal cost
    ``P_f`` (``P=terminal.P``) and ``z(N_p) in Z_f``, ``F_inf z(N_p) <= psi f_inf``
    (``terminal=terminal``). Both use the terminal ingredients' ``t_s``,
    ``Q``, ``R``, discretization and v-box. ``"nominal"`` runs :func:`nominal_loop`, ``"true"`` runs
    :func:`flnotes.simulate` on the true plant with ``v`` held (which stops when the state leaves the domain box).

    Returns
    -------
    runs, rows
        ``runs[(N_p, with_terminal, plant)]``: dict with ``t``, ``z``, ``v``, ``steps``, ``objective`` (the optimal
        cost per step from its plan, :func:`plan_costs`); ``rows``: one dict per run with the number of steps applied,
        whether the run completed, ``optimal`` (the applied steps whose plan is a proven optimum, status
        ``"optimal"`` without fallback: the hypothesis of the stability theorem), the infeasible and fallback
        steps, the steps whose applied input was not admissible, whether the state left the box, the
        closed-loop cost ``sum_k ell(z_k, v_k)``, the final ``|z|``,
        ``max_cost_increase`` (largest ``(J_{k+1} - J_k + ell(z_k, v_k)) / (1 + J_k)`` over consecutive optimal
        steps: ``<= 0`` is the proof's Lyapunov decrease), ``decay_rate`` (``ln(|z(T/2)| / |z(T)|) / (T/2)``, per
        second, over the second half of a completed run; NaN if it stopped early), the largest true ``|u|`` at
        the samples and, on the true plant, ``max_abs_u_between`` (the largest ``|u(t)|`` between the samples,
        ``u(t) = Phi(z(t), v_k)`` as the simulator applies it: not saturated at ``u_max``; NaN on the nominal
        model), and the time.
    """
    for p in plants:
        if p not in ("nominal", "true"):
            raise ValueError(f"plants must contain 'nominal' and/or 'true', got {p!r}")
    n_steps = int(round(t_final / terminal.ts))
    common = dict(ts=terminal.ts, Q=terminal.Q, R=terminal.R, discretization=terminal.discretization,
                  v_box=(terminal.v_lo, terminal.v_hi), **mpc_kwargs)
    zero = lambda t: np.zeros((np.size(t), system.n_z))  # noqa: E731
    runs, rows = {}, []
    for N in horizons:
        for with_terminal in (False, True):
            extra = dict(P=terminal.P, terminal=terminal) if with_terminal else {}
            mpc = MPC(system, net, eps, horizon=int(N), **common, **extra)
            for plant in plants:
                if plant == "nominal":
                    run = nominal_loop(mpc, z0, n_steps, terminal.Ad, terminal.Bd, (terminal.z_lo, terminal.z_hi))
                else:
                    t0 = time.perf_counter()
                    log = simulate(system, mpc, t_final=n_steps * terminal.ts, ts=terminal.ts, z0=z0, reference=zero,
                                   net=net, progress=False)
                    run = dict(t=log.t, z=log.z, v=log.v, steps=list(mpc.history[-log.n_steps:]),
                               box_exit="left the domain box" in (log.message or ""),
                               time_s=time.perf_counter() - t0, log=log)
                row = dict(N_p=int(N), ingredients="P_f and Z_f" if with_terminal else "none", plant=plant,
                           **_summarize(run, terminal.Q, terminal.R, extra.get("P"), system, n_steps))
                run["objective"] = plan_costs(run["steps"], terminal.Q, terminal.R, extra.get("P"))
                runs[(int(N), with_terminal, plant)] = run
                rows.append(row)
    return runs, rows


def fallback_table(run: dict) -> list[dict]:
    """The steps of a run without a proven admissible plan, as the MPC recorded them.

    One row per step with ``fallback`` set: the step index, ``status``, ``input_admissible`` (does the applied
    ``v`` satisfy ``|Phi_NN(z_k, v)| <= u_max^eps`` at the measured state?), ``|Phi_NN(z_k, v_k)|`` and the
    MPC's ``message`` (which rule of the fallback gave the input).
    """
    rows = []
    for k, s in enumerate(run["steps"]):
        if s.fallback:
            rows.append(dict(k=k, z=np.round(run["z"][k], 3), status=s.status, input_admissible=bool(s.input_admissible),
                             abs_phi_nn=float(np.abs(s.u_nn_pred[0]).max()), message=s.message))
    return rows


def margin_study(system: FLSystem, net: ReLUNet, eps: float, ts_values: Sequence[float], t_final: float,
                 reference: Callable[[Array], Array], z0: Array, horizon: Optional[int] = None,
                 lookahead: Optional[float] = None, n_fine: int = 20, drift: Optional[dict] = None,
                 **mpc_kwargs) -> tuple[dict, list[dict]]:
    """Closed loops on the true plant (``v`` held) with ``u_max^eps`` and with ``u_max^{eps+Delta(t_s)}``.

    For each ``t_s`` the drift ``Delta(t_s)`` is certified (:func:`flnotes.intersample.intersample_drift`, or
    taken from ``drift[t_s]``), and the MPC (``mpc_kwargs`` as in :class:`flnotes.MPC`) is run with ``eps`` and with
    ``eps + Delta`` as its ``eps``. Give exactly one of ``horizon`` (the same ``N_p`` for every ``t_s``: a shorter
    ``t_s`` also shortens the look-ahead) and ``lookahead`` (seconds: ``N_p = round(lookahead / t_s)``).
    When ``eps + Delta >= u_max`` the margin leaves no input (the sufficient condition cannot be met) and that run
    is not made (``run = False`` in its row).

    Returns
    -------
    logs, rows
        ``logs[(t_s, margin)]`` the :class:`flnotes.SimLog` s (``margin`` is ``"eps"`` or ``"eps+Delta"``);
        ``rows``: ``t_s``, ``margin``, ``Delta``, the bound ``u_max - eps (- Delta)``, whether the run was made and
        completed, the largest true ``|u|`` at the samples and on the fine grid between them (``n_fine`` points per
        interval), whether ``|u(t)| <= u_max`` held everywhere, the RMS position error over the second half, and the
        infeasible, time-limit and fallback steps.
    """
    if (horizon is None) == (lookahead is None):
        raise ValueError("give exactly one of horizon (N_p, steps) and lookahead (seconds)")
    u_max = float(system.u_max[0])
    logs, rows = {}, []
    for ts in ts_values:
        ts = float(ts)
        delta = float(np.max(drift[ts].upper if drift and ts in drift else intersample_drift(system, ts).upper))
        for label, e in (("eps", eps), ("eps+Delta", eps + delta)):
            N = int(horizon) if horizon is not None else max(1, int(round(lookahead / ts)))
            row = dict(t_s=ts, N_p=N, margin=label, Delta=delta, bound=u_max - e, run=bool(e < u_max))
            if not row["run"]:
                rows.append(row)
                continue
            mpc = MPC(system, net, e, horizon=N, ts=ts, **mpc_kwargs)
            log = simulate(system, mpc, t_final=t_final, ts=ts, z0=z0, reference=reference, net=net, n_fine=n_fine,
                           progress=False)
            err = np.abs(log.z[:, 0] - np.asarray(reference(log.t), float)[:, 0])
            st = list(log.status)
            row.update(completed=log.message == "", max_abs_u_samples=float(np.abs(log.u).max()),
                       max_abs_u_between=float(np.abs(log.u_fine).max()),
                       within_u_max=bool(np.all(np.abs(log.u_fine) <= u_max + 1e-7)),
                       rms_x_error_second_half=float(np.sqrt(np.mean(err[len(err) // 2:] ** 2))),
                       infeasible=int(sum(s == "infeasible" for s in st)),
                       time_limit=int(sum(s == "time_limit" for s in st)), fallback=int(np.sum(log.fallback)),
                       mean_ms=float(1e3 * np.mean(log.solve_time)), max_ms=float(1e3 * np.max(log.solve_time)))
            logs[(ts, label)] = log
            rows.append(row)
    return logs, rows


def intersample_sample(system: FLSystem, net: ReLUNet, u_bound: float, ts: float, n_samples: int = 200_000,
                       n_tau: int = 41, seed: int = 0) -> dict:
    """Sampled pairs admissible at the sample: does the true input stay within ``u_max`` over the whole hold?

    ``n_samples`` uniform pairs ``(z, v)`` of the domain box are drawn (``seed``); those with
    ``|Phi_NN(z, v)| <= u_bound`` (e.g. ``u_max^eps``) are followed along the exact flow ``z(vartheta)`` with ``v``
    held (:func:`flnotes.intersample.flow`) on ``n_tau`` equally spaced ``vartheta in [0, ts]``, and a pair counts as
    kept when ``|Phi(z(vartheta), v)| <= u_max`` at every one of them (``Phi`` undefined along the flow counts as not
    kept). The certified ``Delta`` is a uniform worst case over the box; this is the share of pairs for which the bound holds
    over the interval anyway (a sample: a statement about these pairs, not a certificate).

    Returns
    -------
    dict
        ``n_admissible`` (pairs admissible at the sample), ``n_kept``, ``fraction_kept``, ``max_abs_u`` (largest
        ``|Phi|`` met along the flows, over the pairs where it is defined) and ``ts``, ``n_tau``.
    """
    if not (np.isfinite(ts) and ts > 0) or int(n_tau) < 2 or int(n_samples) < 1:
        raise ValueError(f"need ts > 0, n_tau >= 2 and n_samples >= 1, got ts={ts!r}, n_tau={n_tau!r}, "
                         f"n_samples={n_samples!r}")
    n, u_max = system.n_z, system.u_max
    rng = np.random.default_rng(seed)
    X = rng.uniform(system.lo, system.hi, (int(n_samples), system.n_in))
    X = X[np.all(np.abs(net(X)) <= u_bound, axis=1)]
    Z, V = X[:, :n], X[:, n:]
    kept, top = np.ones(len(X), bool), 0.0
    for tau in np.linspace(0.0, float(ts), int(n_tau)):
        with np.errstate(all="ignore"):
            U = system.Phi(flow(system, Z, V, np.full(len(X), tau)), V)
        ok = np.all(np.isfinite(U), axis=1)
        kept &= ok & np.all(np.abs(np.where(ok[:, None], U, 0.0)) <= u_max, axis=1)
        if ok.any():
            top = max(top, float(np.abs(U[ok]).max()))
    return dict(ts=float(ts), n_tau=int(n_tau), n_admissible=int(len(X)), n_kept=int(kept.sum()),
                fraction_kept=float(kept.mean()) if len(X) else np.nan, max_abs_u=top)


def guaranteed_loop(system: FLSystem, net: ReLUNet, eps: float, delta: float, terminal: TerminalSet, z0: Array,
                    t_final: float, horizon: int, n_fine: int = 40, n_dense: int = 201, active_tol: float = 1e-6,
                    **mpc_kwargs) -> tuple:
    """The MPC with ``u_max^{eps+Delta}`` and the terminal ingredients built for it, on the true plant (``v`` held).

    ``delta`` is the certified drift ``Delta(t_s)``. ``terminal`` must be :func:`flnotes.terminal_set` for
    ``eps + Delta`` (its ``u_eps`` is checked), so that the theorem's hypotheses hold with the margin: then, from a
    start in ``X_{N_p}``, every step has a plan, ``|Phi_NN(z_k, v_k)| <= u_max^{eps+Delta}`` at the samples, and
    ``|u(t)| <= u_max`` between them. The true input is checked twice
    between the samples: on the simulator's ``n_fine`` points per interval, and on ``n_dense`` points of the
    exact flow ``z(t_k + vartheta)`` from each sampled state with ``v_k`` held (:func:`flnotes.intersample.flow`).

    Returns
    -------
    log, row
        The :class:`flnotes.SimLog` and a dict: ``bound`` (``u_max^{eps+Delta}``), ``max_abs_phi_nn`` at the samples,
        ``active_steps`` (steps with ``|Phi_NN| >= bound - active_tol``: the network bound is active),
        ``statuses`` (count per status), ``fallback``, ``max_abs_u_between`` (the larger of the two checks),
        ``within_u_max``, ``final_norm_z``, ``mean_ms``, ``max_ms``.
    """
    if not isinstance(terminal, TerminalSet):
        raise TypeError(f"terminal must be a flnotes.terminal.TerminalSet, got {type(terminal).__name__}")
    u_max, e = system.u_max, eps + delta
    if not np.allclose(terminal.u_eps, u_max - e, rtol=0, atol=1e-12):
        raise ValueError(f"terminal was built for u_max^eps = {terminal.u_eps}, not for u_max - eps - Delta = "
                         f"{u_max - e}: pass the terminal_set built with eps + Delta (eps + delta)")
    mpc = MPC(system, net, e, horizon=int(horizon), ts=terminal.ts, Q=terminal.Q, R=terminal.R, P=terminal.P,
              terminal=terminal, discretization=terminal.discretization, v_box=(terminal.v_lo, terminal.v_hi),
              **mpc_kwargs)
    zero = lambda t: np.zeros((np.size(t), system.n_z))  # noqa: E731
    log = simulate(system, mpc, t_final=t_final, ts=terminal.ts, z0=z0, reference=zero, net=net, n_fine=n_fine,
                   progress=False)
    K = len(log.v)
    taus = np.linspace(0.0, terminal.ts, int(n_dense))
    Zk = np.repeat(log.z[:K], len(taus), 0)
    Vk = np.repeat(log.v, len(taus), 0)
    U_dense = system.Phi(flow(system, Zk, Vk, np.tile(taus, K)), Vk)
    top = max(float(np.abs(log.u_fine).max()), float(np.abs(U_dense).max()))
    bound = float(np.max(u_max - e))
    phi_nn = np.abs(np.asarray(log.u_nn, float)).max(axis=1)
    st = list(log.status)
    row = dict(t_s=terminal.ts, N_p=int(horizon), eps=float(eps), Delta=float(delta), bound=bound, steps=K,
               completed=log.message == "", max_abs_phi_nn=float(phi_nn.max()),
               active_steps=int(np.sum(phi_nn >= bound - active_tol)),
               statuses={s: st.count(s) for s in sorted(set(st))}, fallback=int(np.sum(log.fallback)),
               max_abs_u_between=top, within_u_max=bool(top <= float(np.min(u_max)) + 1e-9),
               final_norm_z=float(np.linalg.norm(log.z[-1])), mean_ms=float(1e3 * np.mean(log.solve_time)),
               max_ms=float(1e3 * np.max(log.solve_time)))
    return log, row


def margin_study_numbers(rows: Sequence[dict], t_s: float) -> dict:
    """The figures chapter 9 quotes from :func:`margin_study` run at one sampling time ``t_s`` (s).

    Returns
    -------
    dict
        ``{margin}_{column}`` for each row's margin (``eps``, ``eps_delta``: ``+`` as ``_``, lower case) and each of
        ``max_abs_u_between``, ``rms_x_error_second_half``, ``mean_ms`` and ``max_ms``; ``late``: when no row's
        slowest step took longer than ``t_s``, "no step of either run took longer than the sampling interval here,
        which a slower or busier machine can change"; else "the slowest step with ε (and with ε + Δ) took longer
        than the sampling interval, and an answer later than the sampling interval is not a real-time controller",
        naming the runs that did.
    """
    q = {r["margin"]: r for r in rows}
    out = {}
    for m, r in q.items():
        for col in ("max_abs_u_between", "rms_x_error_second_half", "mean_ms", "max_ms"):
            out[f"{m.replace('+', '_').lower()}_{col}"] = r[col]
    late = [{"eps": "with ε", "eps+Delta": "with ε + Δ"}[m] for m, r in q.items() if r["max_ms"] > 1e3 * t_s]
    out["late"] = ("no step of either run took longer than the sampling interval here, which a slower or busier machine "
                   "can change" if not late else f"the slowest step {' and '.join(late)} took longer than the sampling "
                   "interval, and an answer later than the sampling interval is not a real-time controller")
    return out


def power_text(x: float) -> str:
    """A tolerance as the book prints it: a power of ten as ``10⁻⁹`` (superscript exponent), any other value as
    ``f"{x:.1e}"`` (e.g. ``"2.5e-07"``)."""
    e = round(np.log10(x))
    sup = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")
    return f"10{str(e).translate(sup)}" if np.isclose(x, 10.0 ** e) else f"{x:.1e}"


def margin_numbers(margin: float, tolerances: dict, default: float, clause: bool = False) -> dict:
    """A certificate's margin to ``u_max^eps`` in units of the solvers' feasibility tolerances (chapter 9).

    Parameters
    ----------
    margin
        ``u_max^eps`` minus the largest proven maximum of ``|Phi_NN|`` on the terminal set.
    tolerances
        the tolerances the solvers run at (:data:`flnotes.terminal.FEASIBILITY_TOLERANCE`); the loosest counts.
    default
        HiGHS's default feasibility tolerance for a MIP's solutions.
    clause
        add ``default_clause``.

    Returns
    -------
    dict
        ``margin``; ``margin_tol`` (over the loosest tolerance); ``margin_tol_default`` (over ``default``); with
        ``clause``, ``default_clause``: when the margin is less than 10 times ``default``, "but only R times HiGHS's
        default tolerance for a MIP's solutions (D): at the default, HiGHS's certificate would sit within a few
        tolerances of failing, which is why the package sets the tolerances itself"; else "and R times HiGHS's
        default tolerance for a MIP's solutions (D)" (``D`` by :func:`power_text`).
    """
    ratio = margin / default
    out = dict(margin=margin, margin_tol=margin / max(tolerances.values()), margin_tol_default=ratio)
    if clause:
        out["default_clause"] = (
            f"but only {ratio:.1f} times HiGHS's default tolerance for a MIP's solutions ({power_text(default)}): at "
            "the default, HiGHS's certificate would sit within a few tolerances of failing, which is why the package "
            "sets the tolerances itself" if ratio < 10 else
            f"and {ratio:,.0f} times HiGHS's default tolerance for a MIP's solutions ({power_text(default)})")
    return out
