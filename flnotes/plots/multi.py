"""Figures for systems with two inputs: the input sets ``V(z)`` in the ``v``-plane."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
from matplotlib.patches import Polygon as _Patch

from .style import COLORS, new_axes

__all__ = ["input_sets_plot"]


def input_sets_plot(system, net, eps, states: Sequence[np.ndarray], axes=None, regions: bool = True,
                    v_opt: Optional[Sequence[np.ndarray]] = None, titles: Optional[Sequence[str]] = None):
    """``V(z)`` (eq. contraint_new_set) and the network's set (eq. Phi_NN_ep) in the ``v``-plane, one panel per state.

    For each ``z``: the true ``{v : |Phi(z, v)| <= u_max}`` as a convex polygon
    (:func:`flnotes.pieces.admissible_polygon`, blue outline), the network's
    ``{v : |Phi_NN(z, v)| <= u_max - eps}`` as a union of convex polygons, one per
    linear region of ``Phi_NN(z, .)`` (:func:`flnotes.pieces.network_polygons`,
    orange), and, with ``regions=True``, the edges of all linear regions (thin grey).

    Parameters
    ----------
    system
        A two-input :class:`flnotes.FLSystem` whose ``Phi`` is affine in ``v``.
    net, eps
        ``Phi_NN`` and its error bound (scalar or shape (2,)).
    states
        The states ``z`` to draw, each of shape (n_z,).
    axes
        Axes to draw in (one per state); new ones otherwise.
    regions
        Draw the linear regions' edges.
    v_opt
        Optional points to mark (e.g. a controller's ``v*``), one per state.
    titles
        Optional panel titles; default the state.

    Returns
    -------
    (fig, axes)
    """
    from ..pieces import admissible_polygon, network_polygons, network_regions

    if system.m != 2:
        raise ValueError(f"input_sets_plot draws the plane of two inputs; {system.name} has m = {system.m}")
    states = [np.asarray(z, float).reshape(-1) for z in states]
    if axes is None:
        fig, axes = new_axes(1, len(states), figsize=(3.3 * len(states), 3.4))
        axes = np.atleast_1d(axes).ravel()
    else:
        axes = np.atleast_1d(axes).ravel()
        fig = axes[0].figure
    if len(axes) < len(states):
        raise ValueError(f"need one axis per state: got {len(axes)} axes for {len(states)} states")
    eps = np.broadcast_to(np.asarray(eps, float), (2,))
    n_z = system.n_z
    v_lo, v_hi = system.lo[n_z:], system.hi[n_z:]
    for i, (z, ax) in enumerate(zip(states, axes)):
        R = network_regions(net, z, v_lo, v_hi)
        if regions:
            for Q in R.polygons:
                ax.add_patch(_Patch(Q, closed=True, fill=False, ec="0.8", lw=0.4))
        for j, Q in enumerate(network_polygons(net, z, v_lo, v_hi, system.u_max - eps, regions=R)):
            ax.add_patch(_Patch(Q, closed=True, fc=COLORS["nn"], ec=COLORS["nn"], alpha=0.35, lw=0.3,
                                label=r"$|\Phi_{NN}| \leq u_{\max}^{\varepsilon}$" if j == 0 else None))
        P = admissible_polygon(system, z)
        if len(P):
            ax.add_patch(_Patch(P, closed=True, fill=False, ec=COLORS["true"], lw=1.8,
                                label=r"$V(z)$: $|\Phi| \leq u_{\max}$"))
        if v_opt is not None and v_opt[i] is not None:
            ax.plot(*np.asarray(v_opt[i], float).reshape(2), "k*", ms=9, label=r"$v^*$")
        ax.set_xlim(v_lo[0], v_hi[0])
        ax.set_ylim(v_lo[1], v_hi[1])
        ax.set_aspect("equal")
        ax.set_xlabel(f"${system.input_names[0].split(' ')[0]}$" if system.input_names else "$v_1$")
        if i == 0:
            ax.set_ylabel(f"${system.input_names[1].split(' ')[0]}$" if system.input_names else "$v_2$")
            ax.legend(loc="lower left", fontsize=7)
        ax.set_title(titles[i] if titles is not None else
                     "z = (" + ", ".join(f"{x:.2g}" for x in z) + ")" + f"\n{R.n_regions} regions", fontsize=8.5)
    return fig, axes
