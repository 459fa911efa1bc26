"""Figures of the book: the MPC chapter (the paper's Figures 5, 6 and 7, and the inter-sample input).

Each function turns run logs of :func:`flnotes.simulate` driven by
:class:`flnotes.mpc.MPC` into one figure and returns it.
"""
from __future__ import annotations

from typing import Callable, Mapping, Optional, Sequence

import numpy as np

from .._checks import check_count
from .style import COLORS, bound_lines, new_axes

Array = np.ndarray

__all__ = ["plot_mpc_tracking", "plot_mpc_input", "plot_horizon_sweep", "plot_intersample", "plot_step_times",
           "explore_horizon"]

_SWEEP_COLORS = ("#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#66a61e", "#e6ab02")


def _ref_on(reference: Optional[Callable[[Array], Array]], t: Array) -> Optional[Array]:
    return None if reference is None else np.asarray(reference(t), float)


def plot_mpc_tracking(log, reference: Optional[Callable[[Array], Array]] = None, components: Sequence[int] = (0, 1, 2),
                      title: Optional[str] = None):
    """The paper's Figure 5: the states ``z = [x, x', x'']`` of the closed loop and the reference (grey).

    Parameters
    ----------
    log
        A :class:`flnotes.SimLog`; the fine samples ``z_fine`` between the
        sampling instants are drawn as the line, the samples as dots.
    reference
        ``t -> z_ref(t)`` (vectorized), drawn in grey.
    components
        Which components of ``z`` to draw, one panel each.
    """
    comps = list(components)
    fig, axes = new_axes(len(comps), 1, figsize=(7.0, 1.9 * len(comps) + 0.4), sharex=True)
    axes = np.atleast_1d(axes).ravel()
    names = list(log.system.state_names)
    t_line = np.r_[log.t_fine, log.t[-1]] if len(log.t_fine) else log.t
    z_line = np.vstack([log.z_fine, log.z[-1:]]) if len(log.z_fine) else log.z
    R = _ref_on(reference, t_line)
    for ax, i in zip(axes, comps):
        if R is not None:
            ax.plot(t_line, R[:, i], color=COLORS["ref"], lw=2.4, label="reference")
        ax.plot(t_line, z_line[:, i], color=COLORS["true"], lw=1.4, label="closed loop (true plant)")
        ax.plot(log.t, log.z[:, i], ".", color=COLORS["true"], ms=3)
        ax.set_ylabel(names[i] if i < len(names) else f"z{i + 1}")
    axes[-1].set_xlabel("t [s]")
    axes[-1].legend(loc="upper center", bbox_to_anchor=(0.5, -0.4), ncol=2)
    if title:
        axes[0].set_title(title)
    return fig


def plot_mpc_input(log, u_max: float, eps: float, predictions: bool = True, every: int = 1, between: bool = True,
                   t_max: Optional[float] = None, ax=None, title: Optional[str] = None):
    """The paper's Figure 6: the input ``u = Phi``, ``Phi_NN`` and the predicted input trajectories.

    Parameters
    ----------
    log
        Run of :func:`flnotes.simulate` with ``net=`` given (so that
        ``log.u_nn`` holds ``Phi_NN(z_k, v_k)``) and an MPC controller (whose
        ``StepResult.u_nn_pred`` holds ``Phi_NN`` along each plan).
    u_max, eps
        The bounds ``±u_max`` (blue) and ``±u_max^eps = ±(u_max - eps)`` (green).
    predictions
        Draw the predicted ``Phi_NN(z(k), v(k))``, ``k = 0..N_p-1``, of every
        ``every``-th plan as thin lines starting at its sampling instant.
    between
        Draw the true ``u(t)`` between the samples (``log.u_fine``) as well.
    t_max
        Only draw ``t <= t_max``.
    """
    every = check_count(every, "every", 1, "steps between the plans drawn")
    if ax is None:
        fig, ax = new_axes(figsize=(7.4, 3.8))
    else:
        fig = ax.figure
    t_end = log.t[-1] if t_max is None else float(t_max)
    ts = log.ts
    if predictions:
        drawn = False
        for k, st in enumerate(log.steps):
            if k % every or log.t[k] > t_end:
                continue
            pred = st.u_nn_pred
            if pred is None:
                continue
            tk = log.t[k] + ts * np.arange(len(pred))
            ax.plot(tk, np.asarray(pred)[:, 0], color=COLORS["nn"], lw=0.6, alpha=0.35,
                    label=None if drawn else r"predicted $\Phi_{NN}(z(k), v(k))$")
            drawn = True
    if between and len(log.t_fine):
        sel = log.t_fine <= t_end
        ax.plot(log.t_fine[sel], log.u_fine[sel, 0], color=COLORS["true"], lw=1.0, alpha=0.6,
                label=r"true $u(t)$ between samples")
    sel = log.t[:-1] <= t_end
    ax.step(log.t[:-1][sel], log.u[sel, 0], where="post", color=COLORS["true"], lw=1.6,
            label=r"$u = \Phi(z_k, v_k)$ at samples")
    if log.u_nn is not None:
        ax.plot(log.t[:-1][sel], log.u_nn[sel, 0], "o", color=COLORS["nn"], ms=2.5, label=r"$\Phi_{NN}(z_k, v_k)$")
    bound_lines(ax, u_max, eps)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("u [rad]")
    ax.set_xlim(0, t_end + (ts * len(log.steps[0].u_nn_pred) if predictions and log.steps
                              and log.steps[0].u_nn_pred is not None and t_max is None else 0))
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3, fontsize=8)
    if title:
        ax.set_title(title)
    return fig


def plot_horizon_sweep(runs: Mapping[int, object], reference: Optional[Callable[[Array], Array]] = None,
                       title: Optional[str] = None):
    """The paper's Figure 7: the displacement ``x(t)`` and the per-step computation time for several ``N_p``.

    Parameters
    ----------
    runs
        ``{N_p: log}`` with one :class:`flnotes.SimLog` per horizon; the
        computation time per step is ``log.solve_time`` (the controller's wall
        time at each sampling instant).
    reference
        ``t -> z_ref(t)``; its first component is drawn in grey.
    """
    fig, axes = new_axes(2, 1, figsize=(7.0, 5.2), sharex=True)
    ax1, ax2 = np.asarray(axes).ravel()
    t_any = None
    for i, (Np, log) in enumerate(sorted(runs.items())):
        c = _SWEEP_COLORS[i % len(_SWEEP_COLORS)]
        ax1.plot(log.t, log.z[:, 0], color=c, lw=1.3, label=fr"$N_p = {Np}$")
        ax2.semilogy(log.t[:-1], np.maximum(log.solve_time * 1e3, 1e-3), ".-", color=c, lw=0.7, ms=2.5,
                     label=fr"$N_p = {Np}$")
        t_any = log.t
    if reference is not None and t_any is not None:
        tt = np.linspace(t_any[0], t_any[-1], 400)
        ax1.plot(tt, _ref_on(reference, tt)[:, 0], color=COLORS["ref"], lw=2.4, zorder=0, label="reference")
    ax1.set_ylabel("x [m]")
    ax1.legend(loc="upper right", ncol=3)
    ax2.set_ylabel("time per step [ms]")
    ax2.set_xlabel("t [s]")
    ax2.legend(loc="upper right", ncol=4)
    if title:
        ax1.set_title(title)
    return fig


def plot_intersample(logs: Mapping[str, object], u_max: float, eps: Optional[float] = None,
                     t_window: Optional[Sequence[float]] = None, title: Optional[str] = None):
    """The true input ``u(t)`` between the samples for several runs (e.g. ``hold="v"`` and ``hold="u"``).

    Parameters
    ----------
    logs
        ``{label: SimLog}``.
    u_max, eps
        Bounds drawn as in Figure 6.
    t_window
        ``(t0, t1)`` to zoom on, e.g. around the largest violation.
    """
    fig, ax = new_axes(figsize=(7.0, 3.4))
    colors = (COLORS["true"], COLORS["nn"], COLORS["lcost"], COLORS["qcost"])
    for i, (label, log) in enumerate(logs.items()):
        sel = np.ones(len(log.t_fine), bool)
        if t_window is not None:
            sel = (log.t_fine >= t_window[0]) & (log.t_fine <= t_window[1])
        ax.plot(log.t_fine[sel], log.u_fine[sel, 0], color=colors[i % len(colors)], lw=1.3, label=label)
        ks = np.ones(len(log.u), bool) if t_window is None else (log.t[:-1] >= t_window[0]) & (log.t[:-1] <= t_window[1])
        ax.plot(log.t[:-1][ks], log.u[ks, 0], "o", color=colors[i % len(colors)], ms=3)
    bound_lines(ax, u_max, eps)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("true u(t) [rad]")
    ax.legend(loc="lower right", fontsize=8)
    if title:
        ax.set_title(title)
    return fig


def plot_step_times(rows: Sequence[Mapping], key: str = "ms", label_key: str = "configuration", ax=None,
                    title: Optional[str] = None):
    """Per-step solve times of several configurations as horizontal box plots (log scale).

    ``rows`` are dicts with a label (``label_key``) and an array of times in
    milliseconds (``key``), e.g. from :func:`flnotes.mpc.lever_study`.
    """
    if ax is None:
        fig, ax = new_axes(figsize=(7.0, 0.5 * len(rows) + 1.2))
    else:
        fig = ax.figure
    data = [np.maximum(np.asarray(r[key], float), 1e-3) for r in rows]
    ax.boxplot(data, orientation="horizontal", whis=(0, 100))
    ax.set_yticks(np.arange(1, len(rows) + 1), [str(r[label_key]) for r in rows])
    ax.set_xscale("log")
    ax.set_xlabel("time per solve [ms]")
    if title:
        ax.set_title(title)
    return fig


def explore_horizon(runs: Mapping[int, object], rows: Sequence[dict],
                    reference: Optional[Callable[[Array], Array]] = None, u_max: Optional[float] = None,
                    eps: Optional[float] = None):
    """A slider over the prediction horizon ``N_p`` of a precomputed sweep: tracking, input and time per step.

    Parameters
    ----------
    runs, rows
        What :func:`flnotes.mpc.horizon_sweep` returns: ``{N_p: SimLog}`` and one
        row of statistics per horizon.
    reference
        ``t -> z_ref(t)``; its first component is drawn in grey.
    u_max, eps
        Bounds drawn on the input panel (``+-u_max`` and ``+-u_max^eps``).

    The chosen horizon is drawn in color over the others in light grey: the
    displacement ``x(t)``, the true input ``u`` at the samples and the
    controller's time per step. A kernel-free player (one precomputed frame
    per horizon, :func:`flnotes.plots.static.frame_player`) is shown first
    and moves in the built book; the ipywidgets slider below it
    (``continuous_update=False``) redraws in a running kernel.
    """
    import ipywidgets as W
    import matplotlib.pyplot as plt
    from IPython.display import display

    from .static import frame_player

    horizons = sorted(int(n) for n in runs)
    by_n = {int(r["N_p"]): r for r in rows}
    out = W.Output()

    def figure(Np: int):
        fig, axes = new_axes(3, 1, figsize=(7.5, 6.4), sharex=True)
        ax1, ax2, ax3 = np.asarray(axes).ravel()
        for n in horizons:
            log = runs[n]
            sel = n == Np
            kw = dict(color=COLORS["nn"] if sel else "0.8", lw=1.5 if sel else 0.8, zorder=3 if sel else 1)
            ax1.plot(log.t, log.z[:, 0], label=fr"$N_p = {n}$" if sel else None, **kw)
            ax2.step(log.t[:-1], log.u[:, 0], where="post", **kw)
            ax3.semilogy(log.t[:-1], np.maximum(log.solve_time * 1e3, 1e-3), ".-" if sel else "-", ms=2.5, **kw)
        log = runs[Np]
        if reference is not None:
            tt = np.linspace(log.t[0], log.t[-1], 400)
            ax1.plot(tt, _ref_on(reference, tt)[:, 0], color=COLORS["ref"], lw=2.4, zorder=0, label="reference")
        if u_max is not None:
            bound_lines(ax2, u_max, eps)
        r = by_n.get(Np, {})
        ax1.set_title(fr"$N_p = {Np}$: RMS x-error (2nd half) {r.get('rms_x_error_second_half', np.nan):.3f} m, "
                      f"{r.get('binaries', 0)} binaries before elimination", fontsize=9)
        ax1.set_ylabel("x [m]")
        ax1.legend(loc="upper right", fontsize=8)
        ax2.set_ylabel("true u [rad]")
        ax3.set_ylabel("time per step [ms]")
        ax3.set_xlabel("t [s]")
        ax3.set_title(f"median {r.get('median_ms', np.nan):.1f} ms, max {r.get('max_ms', np.nan):.0f} ms per step",
                      fontsize=9)
        fig.tight_layout()
        return fig

    def draw(Np: int) -> None:
        fig = figure(Np)
        display(fig)
        plt.close(fig)

    slider = W.SelectionSlider(options=horizons, value=horizons[len(horizons) // 2], description="N_p",
                               continuous_update=False)

    def update(_=None) -> None:
        out.clear_output(wait=True)
        with out:
            draw(slider.value)

    slider.observe(update, names="value")
    # the kernel-free player first: precomputed frames behind a slider that runs in the built book
    display(frame_player(figure, {"N_p": horizons}, name="horizon", start=[horizons.index(slider.value)]))
    box = W.VBox([slider, out])
    display(box)
    return box
