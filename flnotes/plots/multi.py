"""Figures for systems with two inputs: the input sets ``V(z)`` in the ``v``-plane."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
from matplotlib.patches import Polygon as _Patch

from .style import COLORS, new_axes

__all__ = ["input_sets_plot"]


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
                                label=r"$V(z)$: $|\Phi| \leq u_{\max}$"))
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
