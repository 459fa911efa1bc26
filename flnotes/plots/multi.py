"""Figures for systems with two inputs: the input sets ``V(z)`` in the ``v``-plane."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
from matplotlib.patches import Circle, Polygon as _Patch

from .._checks import check_count
from .style import COLORS, bound_lines, new_axes

__all__ = ["input_sets_plot", "arm_workspace_plot", "arm_torques_plot"]


def input_sets_plot(sets: Sequence[dict], axes=None, regions: bool = True,
                    v_opt: Optional[Sequence[np.ndarray]] = None, titles: Optional[Sequence[str]] = None,
                    input_names: Sequence[str] = ("v_1", "v_2")):
    """``V(z)`` (eq. contraint_new_set) and the network's set (eq. Phi_NN_ep) in the ``v``-plane, one panel per state.

    Draws what :func:`flnotes.pieces.input_sets` computed: the true
    ``{v : |Phi(z, v)| <= u_max}``, a convex polygon (blue outline), the
    network's ``{v : |Phi_NN(z, v)| <= u_max - eps}``, a union of convex
    polygons, one per linear region of ``Phi_NN(z, .)`` (orange), and, with
    ``regions=True``, the edges of all linear regions (thin grey).

    Parameters
    ----------
    sets
        The output of :func:`flnotes.pieces.input_sets`.
    axes
        Axes to draw in (one per state); new ones otherwise.
    regions
        Draw the linear regions' edges.
    v_opt
        Optional points to mark (e.g. a controller's ``v*``), one per state (or None).
    titles
        Optional panel titles; default the state and its number of regions.
    input_names
        Axis labels (LaTeX without dollars).

    Returns
    -------
    (fig, axes)
    """
    if axes is None:
        fig, axes = new_axes(1, len(sets), figsize=(3.3 * len(sets), 3.4))
        axes = np.atleast_1d(axes).ravel()
    else:
        axes = np.atleast_1d(axes).ravel()
        fig = axes[0].figure
    if len(axes) < len(sets):
        raise ValueError(f"need one axis per state: got {len(axes)} axes for {len(sets)} states")
    for i, (S, ax) in enumerate(zip(sets, axes)):
        if regions:
            for Q in S["regions"].polygons:
                ax.add_patch(_Patch(Q, closed=True, fill=False, ec="0.8", lw=0.4))
        for j, Q in enumerate(S["network"]):
            ax.add_patch(_Patch(Q, closed=True, fc=COLORS["nn"], ec=COLORS["nn"], alpha=0.35, lw=0.3,
                                label=r"$|\Phi_{NN}| \leq u_{\max}^{\varepsilon}$" if j == 0 else None))
        if len(S["true"]):
            ax.add_patch(_Patch(S["true"], closed=True, fill=False, ec=COLORS["true"], lw=1.8,
                                label=r"$\mathcal{V}(z)$: $|\Phi| \leq u_{\max}$"))
        if v_opt is not None and v_opt[i] is not None:
            ax.plot(*np.asarray(v_opt[i], float).reshape(2), "k*", ms=9, label=r"$v^*$")
        ax.set_xlim(S["v_lo"][0], S["v_hi"][0])
        ax.set_ylim(S["v_lo"][1], S["v_hi"][1])
        ax.set_aspect("equal")
        ax.set_xlabel(f"${input_names[0]}$")
        if i == 0:
            ax.set_ylabel(f"${input_names[1]}$")
            ax.legend(loc="lower left", fontsize=7)
        ax.set_title(titles[i] if titles is not None else
                     "z = (" + ", ".join(f"{x:.2g}" for x in S["z"]) + ")" + f"\n{S['regions'].n_regions} regions",
                     fontsize=8.5)
    return fig, axes


def arm_workspace_plot(logs: dict, center: Sequence[float], radius: float, frames: int = 6, ax=None,
                       inflated: Optional[float] = None, colors: Optional[dict] = None):
    """The arm in its workspace at a few instants of each run, the hand's path and the disc obstacle.

    Parameters
    ----------
    logs
        ``{label: SimLog}`` of runs of :func:`flnotes.two_link_arm` (``z = (q_1, q_1', q_2, q_2')``).
    center, radius
        The obstacle (m).
    frames
        Arm configurations drawn per run, equally spaced in time (the last one in full colour).
    inflated
        Optional radius of the inflated disc the barriers keep the link's points out of (dashed).
    colors
        Optional ``{label: colour}``.

    Returns
    -------
    (fig, ax)
    """
    from ..arm import arm_joint_positions

    frames = check_count(frames, "frames", 1, "arm configurations drawn per run")
    if ax is None:
        fig, ax = new_axes(figsize=(4.6, 4.4))
    else:
        fig = ax.figure
    ax.add_patch(Circle(center, radius, fc=COLORS["unsafe"], alpha=0.35, ec=COLORS["unsafe"], label="obstacle"))
    if inflated is not None:
        ax.add_patch(Circle(center, inflated, fill=False, ec=COLORS["unsafe"], ls="--", lw=0.8))
    palette = [COLORS["qcost"], COLORS["lcost"], COLORS["nominal"], COLORS["true"], COLORS["nn"]]
    for j, (name, log) in enumerate(logs.items()):
        col = (colors or {}).get(name, palette[j % len(palette)])
        q = np.asarray(log.z)[:, [0, 2]]
        elbow, hand = arm_joint_positions(q)
        ax.plot(hand[:, 0], hand[:, 1], color=col, lw=1.2, label=f"{name}: hand")
        idx = np.unique(np.linspace(0, len(q) - 1, frames).round().astype(int))
        for i, k in enumerate(idx):
            a = 0.15 + 0.85 * (i + 1) / len(idx)
            ax.plot([0, elbow[k, 0], hand[k, 0]], [0, elbow[k, 1], hand[k, 1]], "-o", color=col, alpha=a, lw=2.2,
                    ms=3)
    ax.plot(0, 0, "ks", ms=6)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="upper right", fontsize=7)
    return fig, ax


def arm_torques_plot(logs: dict, eps: Optional[Sequence[float]] = None, axes=None):
    """The true torques ``u_i(t)`` each run applied (held between samples), with ``±u_max,i`` and ``±(u_max,i - eps_i)``.

    Parameters
    ----------
    logs
        ``{label: SimLog}`` of runs of the arm.
    eps
        Optional certified ``eps`` per output, to draw ``u_max^eps``.

    Returns
    -------
    (fig, axes)
    """
    if axes is None:
        fig, axes = new_axes(1, 2, figsize=(8.0, 2.8))
        axes = np.atleast_1d(axes).ravel()
    else:
        axes = np.atleast_1d(axes).ravel()
        fig = axes[0].figure
    palette = [COLORS["qcost"], COLORS["lcost"], COLORS["nominal"], COLORS["true"], COLORS["nn"]]
    for i, ax in enumerate(axes[:2]):
        for j, (name, log) in enumerate(logs.items()):
            ax.plot(log.t_fine, log.u_fine[:, i], color=palette[j % len(palette)], lw=1.1, label=name)
        u_max = float(next(iter(logs.values())).system.u_max[i])
        bound_lines(ax, u_max, None if eps is None else float(eps[i]), label=(i == 0))
        ax.set_xlabel("t (s)")
        ax.set_ylabel(f"$u_{i + 1}$ (torque, N m)")
    axes[0].legend(loc="lower right", fontsize=7, ncol=2)
    return fig, axes
