"""Figures of the MPC's guarantees: the terminal set's certificate, the region of attraction, the margin between samples."""
from __future__ import annotations

from typing import Optional

import numpy as np

from .style import COLORS, new_axes

__all__ = ["plot_terminal_bisection", "plot_region_of_attraction", "plot_drift_curve", "plot_terminal_sweep",
           "plot_guaranteed_loop"]


def plot_terminal_bisection(term, ax=None):
    """The bisection on the level ``psi`` (``TerminalSet.psi``): the MILP's ``max |Phi_NN(z, K_f z)|`` over ``psi O_inf``
    against ``u_max^eps``.

    Parameters
    ----------
    term
        A :class:`flnotes.terminal.TerminalSet`.
    """
    if ax is None:
        _, ax = new_axes(figsize=(5.0, 3.4))
    H = np.array([(a, up, lo) for a, up, lo, _ in term.history])
    ok = np.array([h[3] for h in term.history], bool)
    order = np.argsort(H[:, 0])
    ax.plot(H[order, 0], H[order, 1], color="0.6", lw=1, zorder=1)
    ax.scatter(H[ok, 0], H[ok, 1], color=COLORS["nominal"], zorder=2, label="certified (MILP upper bound)")
    ax.scatter(H[~ok, 0], H[~ok, 1], color=COLORS["unsafe"], marker="x", zorder=2, label="fails")
    ax.axhline(float(np.max(term.u_eps)), color=COLORS["u_max_eps"], ls=":", label=r"$u_{\max}^{\varepsilon}$")
    ax.axvline(term.psi, color=COLORS["true"], ls="--", lw=1, label=rf"$\psi = {term.psi:.3g}$")
    ax.set(xlabel=r"level $\psi$", ylabel=r"$\max_{z \in \psi O_\infty} |\Phi_{NN}(z, K_f z)|$")
    ax.legend(loc="upper left")
    return ax


def _slice_mask(term, roa, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    Z = np.broadcast_to(roa.z_fixed, X.shape + (len(roa.z_fixed),)).copy()
    Z[..., roa.axes[0]], Z[..., roa.axes[1]] = X, Y
    return term.contains(Z.reshape(-1, Z.shape[-1]), tol=0.0).reshape(X.shape)


def plot_region_of_attraction(roa, ax=None, title: Optional[str] = None, mark=None, mark_label: str = "start"):
    """Initial states (a 2-D slice) from which the horizon program is feasible, without and with ``z(N_p) in Z_f``.

    Only the second set, ``X_{N_p}``, is a region of attraction (with the terminal cost, by the stability theorem);
    the first is a feasible set that the closed loop may leave, so the default title says "feasible sets".
    Each grid state is a cell: light grey feasible without the terminal constraint only, green feasible with it,
    white infeasible, a red cross undecided (time limit); the terminal set's slice is outlined.

    Parameters
    ----------
    roa
        A :class:`flnotes.terminal.RegionOfAttraction`.
    mark
        Optional state (n_z,) drawn as a star at its two sliced coordinates (e.g. a run's start on the slice).
    mark_label
        Its legend entry.
    """
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    if ax is None:
        _, ax = new_axes(figsize=(5.0, 4.2))
    x, y = roa.x, roa.y
    level = np.where(roa.feasible_terminal == 1, 2.0, np.where(roa.feasible == 1, 1.0, 0.0))
    level = np.ma.masked_invalid(np.where(np.isnan(roa.feasible) | np.isnan(roa.feasible_terminal), np.nan, level))
    cmap = ListedColormap(["white", "0.82", COLORS["nominal"]])
    ax.pcolormesh(x, y, level, cmap=cmap, vmin=-0.5, vmax=2.5, shading="nearest", zorder=1)
    handles = [Patch(color="0.82", label="feasible, no terminal set"),
               Patch(color=COLORS["nominal"], label=r"$X_{N_p}$: feasible with $z(N_p) \in Z_f$")]
    X, Y = np.meshgrid(x, y)
    bad = np.ma.getmaskarray(level)
    if bad.any():
        handles.append(ax.scatter(X[bad], Y[bad], s=30, marker="x", color=COLORS["unsafe"],
                                  label="undecided (time limit)", zorder=3))
    xf, yf = np.linspace(x[0], x[-1], 300), np.linspace(y[0], y[-1], 300)
    Xf, Yf = np.meshgrid(xf, yf)
    M = _slice_mask(roa.terminal, roa, Xf, Yf)
    if M.any():
        ax.contour(Xf, Yf, M.astype(float), levels=[0.5], colors=[COLORS["true"]], linewidths=1.4, zorder=2)
        handles.append(_line(COLORS["true"], r"terminal set $Z_f$ (slice)"))
    if mark is not None:
        mk = np.asarray(mark, float).reshape(-1)
        if mk.shape != np.shape(roa.z_fixed):
            raise ValueError(f"mark must be a state of shape {np.shape(roa.z_fixed)}, got {mk.shape}")
        handles.append(ax.scatter([mk[roa.axes[0]]], [mk[roa.axes[1]]], marker="*", s=140, color="k", zorder=4,
                                  label=mark_label))
    ax.set(xlabel=f"$z_{roa.axes[0] + 1}$", ylabel=f"$z_{roa.axes[1] + 1}$",
           title=title or rf"feasible sets, $N_p = {roa.horizon}$, $t_s = {roa.ts:g}$ s")
    ax.legend(handles=handles, loc="upper right", fontsize=7.5, framealpha=0.9, frameon=True)
    return ax


def _line(color, label):
    """A legend handle for a line."""
    from matplotlib.lines import Line2D

    return Line2D([], [], color=color, label=label)


def plot_drift_curve(curve: dict, u_max: float, eps: float, ax=None, title: Optional[str] = None):
    """Certified ``Delta(t_s)`` (bracket) against the budget ``u_max - eps`` it must stay under.

    Parameters
    ----------
    curve
        The dict of :func:`flnotes.intersample.drift_curve`.
    u_max, eps
        The input bound and the certified approximation error.
    """
    if ax is None:
        _, ax = new_axes(figsize=(5.0, 3.4))
    ts = curve["ts"]
    ax.plot(ts, curve["upper"][:, 0], "o-", color=COLORS["nn"], label=r"$\Delta(t_s)$, certified upper bound")
    ax.plot(ts, curve["lower"][:, 0], "v", color=COLORS["true"], ms=4, label="attained (lower end)")
    ax.axhline(u_max - eps, color=COLORS["u_max_eps"], ls=":", label=r"$u_{\max} - \varepsilon$")
    ax.set(xlabel=r"hold time $t_s$ [s]", ylabel=r"$\Delta(t_s)$", title=title)
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper left")
    return ax


def plot_terminal_sweep(runs: dict, plant: str = "true", box: Optional[float] = None, title: Optional[str] = None):
    """``|z(t)|`` (left) and the optimal cost ``J(z_k)`` per step (right), without (dashed) and with (solid)
    the terminal ingredients, one colour per horizon.

    Parameters
    ----------
    runs
        The first output of :func:`flnotes.studies.guarantees.terminal_sweep`.
    plant
        ``"nominal"`` or ``"true"``: which runs to draw.
    box
        Optional value of ``|z|`` to mark (e.g. the state box's half-width); a run that stops early left the box.
    """
    fig, axes = new_axes(1, 2, figsize=(9.0, 3.4))
    a1, a2 = axes[0]
    horizons = sorted({k[0] for k in runs if k[2] == plant})
    cmap = [COLORS["nn"], COLORS["true"], COLORS["lcost"], COLORS["qcost"], COLORS["nominal"]]
    for i, N in enumerate(horizons):
        c = cmap[i % len(cmap)]
        for with_t, ls in ((False, "--"), (True, "-")):
            r = runs.get((N, with_t, plant))
            if r is None:
                continue
            lab = rf"$N_p = {N}$, " + ("with $P$, $Z_f$" if with_t else "none")
            a1.plot(r["t"], np.linalg.norm(r["z"], axis=1), ls=ls, color=c, label=lab)
            if r["box_exit"]:
                a1.plot(r["t"][-1], np.linalg.norm(r["z"][-1]), "x", color=COLORS["unsafe"], ms=8)
            J = r["objective"]
            a2.semilogy(r["t"][: len(J)], np.where(J > 0, J, np.nan), ls=ls, color=c)
    if box is not None:
        a1.axhline(box, color=COLORS["unsafe"], ls=":", lw=1)
    a1.set(xlabel="t [s]", ylabel=r"$\|z(t)\|$", title=title or f"closed loop ({plant} plant); x: left the box")
    a2.set(xlabel="t [s]", ylabel=r"optimal cost $J(z_k)$", title="cost per step (solid: decreasing by the theorem)")
    a1.legend(loc="upper right", fontsize=7)
    return fig



def plot_guaranteed_loop(logs: dict, u_max: float, bounds: dict, t_window: Optional[tuple] = None,
                         title: Optional[str] = None, unit: str = ""):
    """The true input ``u(t)`` between the samples (lines) and ``Phi_NN(z_k, v_k)`` at the samples (dots) of one or
    more runs, against ``u_max`` and the bounds imposed on ``|Phi_NN|`` at the samples (e.g. the loop of
    :func:`flnotes.studies.guarantees.guaranteed_loop`, or the two runs of ``margin_study`` at one ``t_s``).

    Parameters
    ----------
    logs
        ``{label: SimLog}``, each recorded with ``net`` (for ``u_nn``).
    u_max
        The input bound.
    bounds
        ``{label: value}``: the bounds at the samples, drawn as dotted lines ``+-value`` (e.g.
        ``{"u_max^eps": ..., "u_max^{eps+Delta}": ...}``, labels in LaTeX without dollars).
    t_window
        ``(t0, t1)`` to zoom on.
    unit
        Unit of ``u`` for the axis label (e.g. ``"rad"``), empty for none.
    """
    if not logs:
        raise ValueError("logs must map at least one label to a SimLog")
    fig, ax = new_axes(figsize=(8.0, 3.4))
    colors = (COLORS["true"], COLORS["nn"], COLORS["lcost"], COLORS["qcost"])
    for i, (label, log) in enumerate(logs.items()):
        col = colors[i % len(colors)]
        tf, uf = log.t_fine, log.u_fine[:, 0]
        tk, nn = log.t[:-1], np.asarray(log.u_nn, float)[:, 0]
        sf = np.ones(len(tf), bool) if t_window is None else (tf >= t_window[0]) & (tf <= t_window[1])
        sk = np.ones(len(tk), bool) if t_window is None else (tk >= t_window[0]) & (tk <= t_window[1])
        ax.plot(tf[sf], uf[sf], color=col, lw=1.3, label=f"{label}: true $u(t)$")
        ax.plot(tk[sk], nn[sk], "o", color=col, ms=3.5, label=rf"{label}: $\Phi_{{NN}}(z_k, v_k)$")
    ax.axhline(u_max, color=COLORS["u_max"], ls="--", lw=1, label=r"$\pm u_{\max}$")
    ax.axhline(-u_max, color=COLORS["u_max"], ls="--", lw=1)
    styles = (":", "-.", (0, (1, 3)))
    for j, (label, b) in enumerate(bounds.items()):
        for sgn in (1, -1):
            ax.axhline(sgn * b, color=COLORS["u_max_eps"], ls=styles[j % len(styles)], lw=1.2,
                       label=rf"$\pm {label}$" if sgn > 0 else None)
    ax.set(xlabel="t [s]", ylabel="u" + (f" [{unit}]" if unit else ""), title=title)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7.5, frameon=False)
    return ax
