"""Figures of the CLF-CBF chapter: the paper's Fig. 4, the exact 1-D picture, solve times."""
from __future__ import annotations

from typing import Any, Mapping, Optional, Sequence

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Circle

from .style import COLORS, bound_lines, new_axes

__all__ = ["clfcbf_phase_portrait", "clfcbf_signals", "clfcbf_figure4", "exact_1d_plot", "solve_time_plot",
           "cbf_failure_plot", "wall_runs_plot"]

_NAMED = {"lcost": COLORS["lcost"], "qcost": COLORS["qcost"], "k(z)": COLORS["nominal"], "nominal": COLORS["nominal"]}


def _color(name: str, i: int) -> str:
    return _NAMED.get(name.lower(), f"C{i}")


def _style(name: str) -> dict:
    return dict(ls="--", lw=1.3) if name.lower() in ("k(z)", "nominal") else dict(ls="-")


def clfcbf_phase_portrait(logs: Mapping[str, Any], H: Any = None, ax=None, lim: Optional[Sequence[float]] = None):
    """Phase portrait ``(z_1, z_2)``: the unsafe disc ``H(z) <= 0`` and each run's trajectory.

    Parameters
    ----------
    logs
        ``{name: SimLog}``; names ``"Lcost"``, ``"Qcost"``, ``"k(z)"`` get the book's colours.
    H
        A :class:`flnotes.control.DistanceCBF` (or a list of them) drawn as filled discs.
    ax
        Axes to draw on (a new figure otherwise).
    lim
        ``(z1_min, z1_max, z2_min, z2_max)``; default: fit the trajectories.
    """
    if ax is None:
        fig, ax = new_axes(figsize=(4.6, 4.2))
    Hs = [] if H is None else (list(H) if isinstance(H, (list, tuple)) else [H])
    for j, h in enumerate(Hs):
        ax.add_patch(Circle(h.z_o[:2], h.r_o, color=COLORS["unsafe"], alpha=0.25, lw=0,
                            label=r"unsafe set $H(z)\leq 0$" if j == 0 else None))
        ax.add_patch(Circle(h.z_o[:2], h.r_o, fill=False, color=COLORS["unsafe"], lw=1.2))
    for i, (name, log) in enumerate(logs.items()):
        Z = np.vstack([log.z_fine, log.z[-1:]]) if len(log.z_fine) else log.z
        ax.plot(Z[:, 0], Z[:, 1], color=_color(name, i), label=name, **_style(name))
    first = next(iter(logs.values()))
    ax.plot(*first.z[0, :2], "ko", ms=5, label=r"$z(0)$")
    ax.plot(0, 0, "k+", ms=9, mew=1.5)
    ax.set_xlabel(r"$z_1$ (position)")
    ax.set_ylabel(r"$z_2$ (velocity)")
    ax.set_aspect("equal", adjustable="datalim")
    if lim is not None:
        ax.set_xlim(lim[0], lim[1]), ax.set_ylim(lim[2], lim[3])
    ax.legend(loc="upper right")
    ax.set_title("phase portrait")
    return ax.figure


def clfcbf_signals(logs: Mapping[str, Any], eps: float, axes=None, t_max: Optional[float] = None):
    """States, ``v`` and the true ``u`` over time, with ``+-u_max`` and ``+-u_max^eps``.

    ``u`` is drawn from ``log.u_fine`` (the input the true plant received,
    resolved between samples); ``v`` as a staircase (it is held over each sample).
    """
    if axes is None:
        fig, axes = new_axes(3, 1, figsize=(7.0, 6.4), sharex=True)
        axes = np.ravel(axes)
    ax_z, ax_v, ax_u = axes
    u_max, lo, hi = None, 0.0, 0.0
    for i, (name, log) in enumerate(logs.items()):
        c, st = _color(name, i), _style(name)
        ax_z.plot(log.t, log.z[:, 0], color=c, label=name, **st)
        ax_z.plot(log.t, log.z[:, 1], color=c, alpha=0.6, lw=1.0, ls=":")
        ax_v.step(log.t[:-1], log.v[:, 0], where="post", color=c, label=name, **st)
        tf = np.append(log.t_fine, log.t[-1])
        uf = np.append(log.u_fine[:, 0], log.u_fine[-1, 0])
        ax_u.plot(tf, uf, color=c, **st)
        lo, hi = min(lo, uf.min()), max(hi, uf.max())
        u_max = float(log.system.u_max[0])
    bound_lines(ax_u, u_max, float(np.ravel([eps])[0]))
    ax_z.set_ylabel(r"$z_1$ (solid), $z_2$ (dotted)", fontsize=8.5)
    ax_v.set_ylabel(r"$v$")
    ax_u.set_ylabel(r"true $u$")
    ax_u.set_xlabel("time (s)")
    ax_z.legend(ncol=3, fontsize=7.5, loc="upper right")
    ax_u.legend(ncol=2, fontsize=7.5, loc="lower right")
    span = max(hi, u_max) - min(lo, -u_max)
    ax_u.set_ylim(min(lo, -u_max) - 0.08 * span, max(hi, u_max) + 0.08 * span)
    if t_max is not None:
        ax_u.set_xlim(0, t_max)
    return ax_z.figure


def clfcbf_figure4(logs: Mapping[str, Any], H: Any, eps: float, t_max: Optional[float] = None):
    """The paper's Fig. 4 reproduced: phase portrait (left), states, ``v`` and ``u`` over time (right)."""
    fig = plt.figure(figsize=(10.5, 6.2))
    gs = fig.add_gridspec(3, 2, width_ratios=[1.0, 1.35])
    ax_p = fig.add_subplot(gs[:, 0])
    axes = [fig.add_subplot(gs[0, 1])]
    axes += [fig.add_subplot(gs[r, 1], sharex=axes[0]) for r in (1, 2)]
    clfcbf_phase_portrait(logs, H, ax=ax_p)
    clfcbf_signals(logs, eps, axes=axes, t_max=t_max)
    for a in axes[:2]:
        plt.setp(a.get_xticklabels(), visible=False)
    return fig


def exact_1d_plot(pieces, intervals: np.ndarray, bound: float, optima: Optional[Mapping[str, Any]] = None,
                  cbf: Optional[tuple[float, float]] = None, z: Optional[np.ndarray] = None, ax=None):
    """``v -> Phi_NN(z, v)`` at one state: its affine pieces, the feasible intervals and the optima.

    Draws only; the data come from :func:`flnotes.network_pieces_1d`, :func:`flnotes.exact_1d_feasible_set`
    and the controllers' steps.

    Parameters
    ----------
    pieces
        :class:`flnotes.control.PiecewiseAffine1D` of ``Phi_NN(z, .)`` (its knots span the ``v`` shown).
    intervals
        The feasible intervals of ``v`` (k, 2), ``|Phi_NN(z, v)| <= u_max^eps``.
    bound
        ``u_max^eps``.
    optima
        Controller name -> its :class:`flnotes.StepResult` at ``z`` (``v`` and ``info["phi_nn"]`` are marked;
        a fallback is labelled).
    cbf
        ``(a_H, b_H)`` of a CBF condition ``a_H v + b_H >= 0`` (CLF_CBF_d): the excluded half-line is shaded.
    z
        The state, for the title.
    """
    if ax is None:
        fig, ax = new_axes(figsize=(7.0, 3.6))
    knots, values = np.asarray(pieces.knots, float), np.asarray(pieces.values, float)
    v_lo, v_hi = float(knots[0]), float(knots[-1])
    ax.plot(knots, values, color=COLORS["nn"], lw=1.8, label=r"$\Phi_{NN}(z, v)$")
    ax.plot(knots, values, "o", color=COLORS["nn"], ms=3.5, label=f"breakpoints ({len(knots) - 2} inside)")
    for s in (1, -1):
        ax.axhline(s * bound, color=COLORS["u_max_eps"], ls=":", lw=1.2,
                   label=r"$\pm u_{\max}^{\varepsilon}$" if s == 1 else None)
    for j, (a, b) in enumerate(np.asarray(intervals, float).reshape(-1, 2)):
        ax.axvspan(a, b, color=COLORS["u_max_eps"], alpha=0.15, lw=0,
                   label=r"$|\Phi_{NN}| \leq u_{\max}^{\varepsilon}$" if j == 0 else None)
    if cbf is not None:
        a, b = float(cbf[0]), float(cbf[1])
        if a != 0:
            r = -b / a
            lo, hi = (v_lo, min(r, v_hi)) if a > 0 else (max(r, v_lo), v_hi)
            if lo < hi:
                ax.axvspan(lo, hi, color=COLORS["unsafe"], alpha=0.12, lw=0, hatch="//", label="CBF condition violated")
        elif b < 0:
            ax.axvspan(v_lo, v_hi, color=COLORS["unsafe"], alpha=0.12, lw=0, label="CBF condition violated")
    for i, (name, r) in enumerate((optima or {}).items()):
        ax.plot(r.v[0], r.info["phi_nn"][0], "*", ms=17 - 5 * min(i, 1), color=_color(name, i), mec="k", mew=0.6,
                label=f"{name} optimum" + (" (fallback)" if r.fallback else ""), zorder=5)
    ax.set_xlim(v_lo, v_hi)
    ax.set_xlabel(r"$v$")
    ax.set_ylabel(r"$\Phi_{NN}(z, v)$")
    title = f"{pieces.n_pieces} affine pieces"
    if z is not None:
        title = f"z = [{', '.join(f'{x:.3g}' for x in np.asarray(z, float).ravel())}]: " + title
    ax.set_title(title)
    ax.legend(fontsize=7.5, loc="upper left")
    return ax.figure


def solve_time_plot(logs: Mapping[str, Any], reference_ms: Optional[Mapping[str, float]] = None, ax=None):
    """Per-step solve time (ms, log scale) over the run; ``reference_ms`` (name -> ms, e.g. the paper's Table 2
    means from :func:`flnotes.studies.paper_mean_ms`) drawn as dashed lines in the run's color."""
    reference_ms = dict(reference_ms or {})
    if ax is None:
        fig, ax = new_axes(figsize=(7.0, 3.2))
    for i, (name, log) in enumerate(logs.items()):
        c = _color(name, i)
        ax.semilogy(log.t[:-1], log.solve_time * 1e3, ".", ms=3, color=c, label=name)
        if name in reference_ms:
            ax.axhline(reference_ms[name], color=c, ls="--", lw=1, label=f"{name}, paper's mean")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("solve time per step (ms)")
    ax.legend(ncol=3, fontsize=7.5)
    return ax.figure


def cbf_failure_plot(H: Any, segment: np.ndarray, z_mark: Optional[np.ndarray] = None, ax=None,
                     lim: Sequence[float] = (-0.5, 3.0, -0.5, 2.5)):
    """The unsafe disc, the line where ``grad H^T B = 0`` and the safe states there where the CBF condition fails.

    Parameters
    ----------
    H
        A :class:`flnotes.control.DistanceCBF`; ``grad H^T B = 0`` on the line ``z_2 = z_o[1]``.
    segment
        States on that line where no ``v`` satisfies the condition (e.g. the
        ones flagged by :func:`flnotes.control.cbf_condition_fails`), shape (N, 2).
    z_mark
        A state to mark, shape (2,).
    """
    if ax is None:
        fig, ax = new_axes(figsize=(5.2, 3.8))
    ax.add_patch(Circle(H.z_o[:2], H.r_o, color=COLORS["unsafe"], alpha=0.2, lw=0, label=r"unsafe: $H(z) < 0$"))
    ax.axhline(H.z_o[1], color="0.4", lw=0.9, ls="--", label=r"$\nabla H(z)^\top B = 0$")
    segment = np.atleast_2d(segment)
    if len(segment):
        ax.plot(segment[:, 0], segment[:, 1], color=COLORS["unsafe"], lw=4, solid_capstyle="butt",
                label="safe, but no $v$ satisfies the CBF condition")
    if z_mark is not None:
        ax.plot(*np.asarray(z_mark)[:2], "ko", ms=5, label=f"$z = [{z_mark[0]:g}, {z_mark[1]:g}]$")
    for x0 in np.linspace(lim[0] + 0.2, H.z_o[0] - H.r_o - 0.5, 3):  # the flow on the line: z1' = z2 = z_o2 > 0
        ax.annotate("", xy=(x0 + 0.3, H.z_o[1]), xytext=(x0, H.z_o[1]), arrowprops=dict(arrowstyle="->", color="0.3"))
    ax.set_xlim(lim[0], lim[1]), ax.set_ylim(lim[2], lim[3])
    ax.set_aspect("equal")
    ax.set_xlabel(r"$z_1$ (position)"), ax.set_ylabel(r"$z_2$ (velocity)")
    ax.legend(loc="upper right", fontsize=7.5)
    ax.set_title("where the distance H is not a CBF")
    return ax.figure


def wall_runs_plot(logs: Mapping[str, Any], h: Any, u_max: float, eps: Optional[float] = None):
    """Runs against a wall ``h(z) = c^T z + d >= 0`` on the position: phase portrait, ``h(z(t))`` and the true ``u``.

    Parameters
    ----------
    logs
        ``{name: SimLog}``.
    h
        A :class:`flnotes.control.AffineCBF` on ``z_1`` (``c = [c_1, 0]``).
    u_max, eps
        Bounds drawn on the input panel.
    """
    fig, axes = new_axes(1, 3, figsize=(11.0, 3.4))
    a_ph, a_h, a_u = np.ravel(axes)
    wall = -h.d / h.c[0]
    a_ph.axvspan(wall, wall + 10 * (1 if h.c[0] < 0 else -1), color=COLORS["unsafe"], alpha=0.15, lw=0,
                 label=r"unsafe: $h(z) < 0$")
    for i, (name, log) in enumerate(logs.items()):
        c = f"C{i}"
        Z = np.vstack([log.z_fine, log.z[-1:]]) if len(log.z_fine) else log.z
        a_ph.plot(Z[:, 0], Z[:, 1], color=c, label=name)
        a_h.plot(log.t, h(log.z), color=c, label=name)
        tf = np.append(log.t_fine, log.t[-1])
        a_u.plot(tf, np.append(log.u_fine[:, 0], log.u_fine[-1, 0]), color=c, label=name)
    first = next(iter(logs.values()))
    z_all = np.vstack([log.z for log in logs.values()])
    a_ph.set_xlim(z_all[:, 0].min() - 0.3, max(z_all[:, 0].max(), wall) + 0.5)
    a_ph.plot(*first.z[0, :2], "ko", ms=5)
    a_ph.set_xlabel(r"$z_1$"), a_ph.set_ylabel(r"$z_2$"), a_ph.set_title("phase portrait")
    a_ph.legend(fontsize=7.5)
    a_h.axhline(0, color=COLORS["unsafe"], lw=1)
    a_h.set_xlabel("t [s]"), a_h.set_ylabel(r"$h(z)$ at the samples"), a_h.set_title("distance to the wall")
    bound_lines(a_u, u_max, eps)
    a_u.set_xlabel("t [s]"), a_u.set_ylabel("true u"), a_u.set_title("input on the plant")
    a_u.legend(fontsize=7.5)
    fig.tight_layout()
    return fig
