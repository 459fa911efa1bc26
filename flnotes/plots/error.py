"""Figures of the book: the approximation error bound eps (chapter 5).

Each function draws one figure from results computed by :mod:`flnotes.error`
(estimates, certified brackets, sweeps), so a notebook cell is one call.
"""
from __future__ import annotations

from typing import Optional, Sequence

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import PatchCollection
from matplotlib.patches import Rectangle

from .._checks import check_count
from .style import COLORS, new_axes

__all__ = ["static_architecture", "error_slice", "pso_swarm",
           "estimator_convergence", "certification_progress", "partition_slice",
           "eps_sweep", "violation_line", "show_source", "explore_architecture"]

_METHOD_STYLE = {
    "pso": dict(color="#d95f02", marker="*", label="PSO"),
    "de": dict(color="#7570b3", marker="D", label="differential evolution"),
    "grid": dict(color="#1b9e77", marker="s", label="dense grid"),
    "sample": dict(color="#666666", marker="o", label="random samples"),
}


def _labels(system, n_in: int) -> list[str]:
    if system is not None:
        return list(system.state_names) + list(system.input_names)
    return [f"x{j + 1}" for j in range(n_in)]


def _slice_grid(lo, hi, dims, at, n):
    a = np.linspace(lo[dims[0]], hi[dims[0]], n)
    b = np.linspace(lo[dims[1]], hi[dims[1]], n)
    A, Bm = np.meshgrid(a, b, indexing="xy")
    X = np.tile(np.asarray(at, float), (A.size, 1))
    X[:, dims[0]], X[:, dims[1]] = A.ravel(), Bm.ravel()
    return A, Bm, X


def error_slice(system, net, dims: Sequence[int] = (1, 2), at: Optional[np.ndarray] = None, estimates: Sequence = (),
                n: int = 241, output: int = 0, ax=None, title: Optional[str] = None):
    """Heat map of ``|Phi - Phi_NN|`` (eq. epsilon_find's cost) on a 2-D slice of the domain.

    Parameters
    ----------
    system
        The :class:`flnotes.FLSystem` (its ``phi_stacked``, box and labels are used).
    net
        The network.
    dims
        The two stacked coordinates spanning the slice.
    at
        The point the slice goes through (other coordinates fixed there);
        default: the first estimate's maximizer, else the box centre.
    estimates
        :class:`flnotes.error.ErrorEstimate` / ``ErrorBracket`` objects whose maximizers are marked.
    """
    dims = tuple(dims)
    n = check_count(n, "n", 2, "grid points per axis")
    if at is None:
        at = estimates[0].argmax[output] if estimates else 0.5 * (system.lo + system.hi)
    A, Bm, X = _slice_grid(system.lo, system.hi, dims, at, n)
    E = np.abs(system.phi_stacked(X)[:, output] - net(X)[:, output]).reshape(A.shape)
    if ax is None:
        fig, ax = new_axes(figsize=(6.4, 4.4))
    im = ax.pcolormesh(A, Bm, E, shading="auto", cmap="magma")
    plt.colorbar(im, ax=ax, label=r"$|\Phi - \Phi_{NN}|$")
    for est in estimates:
        st = dict(_METHOD_STYLE.get(getattr(est, "method", ""), dict(color="c", marker="P", label="certified bracket")))
        label = st.pop("label")
        val = est.eps[output] if hasattr(est, "n_evals") else est.lower[output]
        ax.plot(est.argmax[output, dims[0]], est.argmax[output, dims[1]], ls="none", ms=12, mec="w",
                label=f"{label}: {val:.4f}", **st)
    names = _labels(system, net.n_in)
    ax.set_xlabel(names[dims[0]])
    ax.set_ylabel(names[dims[1]])
    fixed = [f"{names[j]} = {at[j]:.3g}" for j in range(net.n_in) if j not in dims]
    ax.set_title(title or f"{system.name}: error on the slice " + ", ".join(fixed))
    ax.grid(False)
    if estimates:
        ax.legend(loc="upper right", framealpha=0.9, frameon=True)
    return ax


def pso_swarm(system, net, est, dims: Sequence[int] = (1, 2), iterations: Sequence[int] = (0, 10, -1), n: int = 161):
    """The swarm of :func:`flnotes.error.pso_max_error` (run with ``record=True``) at a few iterations.

    The particles (projected on ``dims``) are drawn over the error slice
    through the final best point.
    """
    if est.swarm is None:
        raise ValueError("this estimate has no recorded swarm: run pso_max_error(..., record=True)")
    n = check_count(n, "n", 2, "grid points per axis")
    fig, axes = new_axes(1, len(iterations), figsize=(3.4 * len(iterations) + 0.8, 3.4), sharey=True,
                         layout="constrained")  # room for the shared colorbar
    axes = np.asarray(axes).ravel()
    at = est.argmax[0]
    A, Bm, X = _slice_grid(system.lo, system.hi, tuple(dims), at, n)
    E = np.abs(system.phi_stacked(X)[:, 0] - net(X)[:, 0]).reshape(A.shape)
    names = _labels(system, net.n_in)
    for ax, k in zip(axes, iterations):
        k = k if k >= 0 else len(est.swarm) + k
        mesh = ax.pcolormesh(A, Bm, E, shading="auto", cmap="Greys", vmin=0.0, vmax=float(E.max()))
        P = est.swarm[k]
        ax.plot(P[:, dims[0]], P[:, dims[1]], ".", color=COLORS["nn"], ms=5)
        ax.plot(*est.swarm_best[k][list(dims)], "*", color="#ffd92f", mec="k", ms=14)
        ax.set_title(f"iteration {k}: best {est.history[0, k]:.4f}")
        ax.set_xlabel(names[dims[0]])
        ax.grid(False)
    axes[0].set_ylabel(names[dims[1]])
    fig.colorbar(mesh, ax=axes.tolist(), label=r"$|\Phi - \Phi_{NN}|$ on the slice")
    return axes


def estimator_convergence(estimates: Sequence, bracket=None, output: int = 0, ax=None):
    """Best error found vs evaluations of ``Phi`` and the network, with the certified bracket.

    PSO and differential evolution are drawn against ``est.history_evals``
    (iterations of the two cost different numbers of evaluations); the other
    estimates (grid, samples, local searches) as a marker at their total
    number of evaluations and a dashed level.
    """
    if ax is None:
        fig, ax = new_axes(figsize=(7.0, 3.6))
    for est in estimates:
        st = dict(_METHOD_STYLE.get(est.method, {}))
        label = st.pop("label", est.method)
        marker = st.pop("marker", "o")
        if est.history is not None and est.history_evals is not None:
            ax.plot(est.history_evals[output], est.history[output], label=f"{label} ({est.eps[output]:.4f})", **st)
        else:  # one number for its whole budget
            ax.axhline(est.eps[output], ls="--", lw=1.0, **st)
            ax.plot([est.n_evals], [est.eps[output]], marker, ms=7, label=f"{label} ({est.eps[output]:.4f})", **st)
    if bracket is not None:
        ax.axhspan(bracket.lower[output], bracket.upper[output], color=COLORS["u_max_eps"], alpha=0.25,
                   label=f"certified [{bracket.lower[output]:.4f}, {bracket.upper[output]:.4f}]")
        ax.axhline(bracket.upper[output], color=COLORS["u_max_eps"], lw=1.2)
    ax.set_xscale("log")
    ax.set_xlabel(r"evaluations of $\Phi$ and $\Phi_{NN}$")
    ax.set_ylabel(r"largest $|\Phi - \Phi_{NN}|$ found")
    ax.legend(loc="lower right")
    return ax


def certification_progress(brackets: dict, output: int = 0, ax=None):
    """Lower and upper bound of the certified bracket vs sub-boxes evaluated, one colour per system.

    ``brackets`` maps a label to an :class:`flnotes.error.ErrorBracket`;
    values are divided by the final lower bound so systems share an axis.
    """
    if ax is None:
        fig, ax = new_axes(figsize=(7.0, 3.6))
    for (name, br), c in zip(brackets.items(), ["#1f4e79", "#d95f02", "#2ca02c", "#7570b3"]):
        h = br.history[output]
        ref = br.lower[output]
        ax.plot(h[:, 0], h[:, 2] / ref, color=c, label=f"{name}: upper / final lower")
        ax.plot(h[:, 0], h[:, 1] / ref, color=c, ls=":", label=f"{name}: lower / final lower")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("sub-boxes evaluated")
    ax.set_ylabel("bound / final lower bound")
    ax.legend(loc="upper right", ncol=2)
    return ax


def partition_slice(bracket, system, dims: Sequence[int] = (1, 2), at: Optional[np.ndarray] = None,
                    output: int = 0, ax=None, title: Optional[str] = None):
    """The final sub-boxes of a certification that cut a 2-D slice, coloured by their upper bound.

    Needs ``certify_error(..., keep_partition=True)``. The slice goes through
    ``at`` (default: the maximizer ``bracket.argmax``); small boxes show
    where the branch and bound had to work, i.e. near the maximizer and where
    the error comes close to it.
    """
    if bracket.partition is None:
        raise ValueError("this bracket kept no partition: run certify_error(..., keep_partition=True)")
    P = bracket.partition[output]
    dims = list(dims)
    at = bracket.argmax[output] if at is None else np.asarray(at, float)
    other = [j for j in range(P["lo"].shape[1]) if j not in dims]
    cut = np.all((P["lo"][:, other] <= at[other]) & (at[other] <= P["hi"][:, other]), axis=1)
    lo, hi, ub = P["lo"][cut], P["hi"][cut], P["ub"][cut]
    if ax is None:
        fig, ax = new_axes(figsize=(6.4, 4.6))
    rects = [Rectangle((l[dims[0]], l[dims[1]]), h[dims[0]] - l[dims[0]], h[dims[1]] - l[dims[1]]) for l, h in zip(lo, hi)]
    pc = PatchCollection(rects, cmap="viridis", edgecolor="k", linewidth=0.15)
    pc.set_array(ub / bracket.upper[output])
    pc.set_clim(0, 1)
    ax.add_collection(pc)
    plt.colorbar(pc, ax=ax, label="box upper bound / certified eps")
    ax.plot(at[dims[0]], at[dims[1]], "*", color="#ffd92f", mec="k", ms=14, label="maximizer (lower bound)")
    names = _labels(system, P["lo"].shape[1])
    ax.set_xlim(system.lo[dims[0]], system.hi[dims[0]])
    ax.set_ylim(system.lo[dims[1]], system.hi[dims[1]])
    ax.set_xlabel(names[dims[0]])
    ax.set_ylabel(names[dims[1]])
    fixed = ", ".join(f"{names[j]} = {at[j]:.3g}" for j in other)
    ax.set_title(title or f"{system.name}: {len(lo):,} of {len(P['ub']):,} final boxes cut the slice {fixed}")
    ax.grid(False)
    ax.legend(loc="upper right", framealpha=0.9, frameon=True)
    return ax


def eps_sweep(rows: Sequence[dict], key: str = "eps_certified", paper_eps: Optional[float] = None):
    """``eps`` against the hidden width, one panel per grid density ``n_s`` and one line per depth.

    ``rows`` come from :func:`flnotes.error.architecture_sweep`.
    """
    grids = sorted({r["n_s"] for r in rows})
    depths = sorted({r["depth"] for r in rows})
    fig, axes = new_axes(1, len(grids), figsize=(3.6 * len(grids), 3.4), sharey=True)
    axes = np.asarray(axes).ravel()
    colors = ["#1b9e77", "#d95f02", "#7570b3", "#e7298a"]
    for ax, n_s in zip(axes, grids):
        for depth, c in zip(depths, colors):
            rr = sorted([r for r in rows if (r["depth"], r["n_s"]) == (depth, n_s)], key=lambda r: r["width"])
            ax.plot([r["width"] for r in rr], [r[key] for r in rr], marker="o", color=c, label=f"{depth} hidden")
        if paper_eps is not None:
            ax.axhline(paper_eps, color="k", lw=1, ls="--", label=f"paper's eps ({paper_eps})")
        ax.set_title(f"grid $n_s$ = {n_s} per axis")
        ax.set_xlabel(r"hidden width $\bar n$")
        ax.set_yscale("log")
    axes[0].set_ylabel(key.replace("_", " "))
    axes[-1].legend(loc="upper right", fontsize=7.5)
    return axes


def violation_line(system, net, z: np.ndarray, eps: dict, v_focus: Optional[float] = None, half_window: float = 0.4,
                   n: int = 4001):
    """``Phi(z, v)`` and ``Phi_NN(z, v)`` along ``v`` at a fixed state ``z`` (single-input systems).

    ``eps`` maps a label to an error bound; for each, the level
    ``u_max - eps`` of eq. (Phi_NN_ep) is drawn and the inputs ``v`` it allows
    although the true input ``|Phi|`` exceeds ``u_max`` (a violation of eq.
    constraintU) are marked. With ``v_focus`` a second panel zooms on
    ``v_focus +- half_window``.
    """
    if system.m != 1:
        raise ValueError("violation_line draws single-input systems (m = 1)")
    n = check_count(n, "n", 2, "points along v")
    z = np.asarray(z, float)[: system.n_z]
    u_max = float(system.u_max[0])
    panels = [(system.lo[-1], system.hi[-1])]
    if v_focus is not None:
        panels.append((max(system.lo[-1], v_focus - half_window), min(system.hi[-1], v_focus + half_window)))
    fig, axes = new_axes(1, len(panels), figsize=(5.2 * len(panels), 3.8))
    axes = np.asarray(axes).ravel()
    for p, (ax, (a, b)) in enumerate(zip(axes, panels)):
        v = np.linspace(a, b, n)
        X = np.hstack([np.tile(z, (n, 1)), v[:, None]])
        phi, nn = system.phi_stacked(X)[:, 0], net(X)[:, 0]
        ax.plot(v, phi, color=COLORS["true"], label=r"$\Phi(z, v)$")
        ax.plot(v, nn, color=COLORS["nn"], ls="--", label=r"$\Phi_{NN}(z, v)$")
        for sgn in (1, -1):
            ax.axhline(sgn * u_max, color=COLORS["u_max"], lw=1, label=r"$\pm u_{\max}$" if sgn > 0 else None)
        for (label, e), c in zip(eps.items(), ["#d62728", COLORS["u_max_eps"], "#7570b3"]):
            e = float(np.atleast_1d(e)[0])
            for sgn in (1, -1):
                ax.axhline(sgn * (u_max - e), color=c, ls=":", lw=1.4,
                           label=f"$\\pm(u_{{\\max}} - \\varepsilon)$, {label}" if sgn > 0 else None)
            bad = (np.abs(nn) <= u_max - e) & (np.abs(phi) > u_max)
            if bad.any():
                ax.plot(v[bad], phi[bad], ".", color=c, ms=4, label=f"allowed by {label}, $|\\Phi| > u_{{\\max}}$")
        if p == 1:
            mid = np.concatenate([phi, nn])
            pad = 0.25 * (mid.max() - mid.min()) + 1e-9
            ax.set_ylim(mid.min() - pad, mid.max() + pad)
            ax.set_title(f"zoom on v = {v_focus:.3g}")
        else:
            ax.set_title(f"{system.name} at z = {np.array2string(z, precision=3)}")
            if v_focus is not None:
                ax.axvspan(*panels[1], color="0.85", zorder=0)
        ax.set_xlabel(system.input_names[0])
    axes[0].set_ylabel("input u")
    axes[-1].legend(loc="best", fontsize=7)
    return axes


def show_source(func, skip_docstring: bool = True):
    """The source code of a function as a rendered code block (for reading the algorithm in a chapter)."""
    import inspect

    from IPython.display import Markdown

    src = inspect.getsource(func)
    if skip_docstring and func.__doc__:
        i = src.find('"""')
        j = src.find('"""', i + 3)
        if i >= 0 and j > i:
            src = src[:i].rstrip() + "\n" + src[j + 3:].lstrip("\n")
    return Markdown("```python\n" + src.rstrip() + "\n```")


def _architecture_figure(rows: Sequence[dict], width: int, depth: int, n_s: int, title: str):
    """One frame of :func:`explore_architecture`: eps against width, and accuracy against MILP size."""
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10.5, 3.8))
    rr = sorted([r for r in rows if r["depth"] == depth and r["n_s"] == n_s], key=lambda r: r["width"])
    for key, st in (("eps_sample", dict(color="#666666", marker="o", label="max over samples")),
                    ("eps_pso", dict(color="#d95f02", marker="*", label="PSO")),
                    ("eps_certified", dict(color="#2ca02c", marker="s", label="certified upper"))):
        a1.plot([r["width"] for r in rr], [r[key] for r in rr], **st)
    sel = [r for r in rr if r["width"] == width]
    if sel:
        a1.axvline(width, color="k", lw=0.8)
        a1.set_title(f"width {width}, depth {depth}, $n_s$ = {n_s}: certified eps = {sel[0]['eps_certified']:.4f}, "
                     f"{sel[0]['n_binaries']} binaries", fontsize=9)
    a1.set_xlabel(r"hidden width $\bar n$")
    a1.set_ylabel("eps")
    a1.set_yscale("log")
    a1.legend(fontsize=8)
    a2.scatter([r["n_binaries"] for r in rows], [r["eps_certified"] for r in rows], c="0.75", s=18)
    if sel:
        a2.scatter([sel[0]["n_binaries"]], [sel[0]["eps_certified"]], c="#d62728", s=60, label="selected")
        a2.legend(fontsize=8)
    a2.set_xlabel("binaries per network copy")
    a2.set_ylabel("certified eps")
    a2.set_yscale("log")
    a2.set_title(f"{title}: accuracy vs MILP size, all nets", fontsize=9)
    fig.tight_layout()
    return fig


def static_architecture(rows: Sequence[dict], title: str = "MSD"):
    """Kernel-free version of :func:`explore_architecture`: every (width, depth, grid) frame precomputed.

    Returns
    -------
    flnotes.plots.static.FramePlayer
        Sliders for width, depth and grid density that run in the browser.
    """
    from .static import frame_player

    widths = sorted({r["width"] for r in rows})
    depths = sorted({r["depth"] for r in rows})
    grids = sorted({r["n_s"] for r in rows})
    return frame_player(lambda w, d, g: _architecture_figure(rows, w, d, g, title),
                        {"width": widths, "depth": depths, "grid n_s": grids}, name=f"architecture{title}".replace("-", ""),
                        start=[len(widths) // 2, len(depths) - 1, len(grids) - 1])


def explore_architecture(rows: Sequence[dict], title: str = "MSD"):
    """Sliders for width, depth and grid density over a precomputed sweep: eps and the number of binaries.

    ``rows`` come from :func:`flnotes.error.architecture_sweep`. The left
    panel shows eps (sampled maximum, PSO and certified) against the width
    for the chosen depth and grid density, the chosen net highlighted; the
    right panel its number of binaries ``sum_k n_k`` per copy of eq.
    (MIP_general) against its certified eps for all nets. The kernel-free
    player of :func:`static_architecture` is shown first (it moves in the
    built book); the ipywidgets sliders below it redraw in a running kernel.
    """
    import ipywidgets as W
    from IPython.display import display

    widths = sorted({r["width"] for r in rows})
    depths = sorted({r["depth"] for r in rows})
    grids = sorted({r["n_s"] for r in rows})
    out = W.Output()

    def draw(width: int, depth: int, n_s: int) -> None:
        fig = _architecture_figure(rows, width, depth, n_s, title)
        display(fig)
        plt.close(fig)

    sw = W.SelectionSlider(options=widths, value=widths[len(widths) // 2], description="width", continuous_update=False)
    sd = W.SelectionSlider(options=depths, value=depths[-1], description="depth", continuous_update=False)
    sg = W.SelectionSlider(options=grids, value=grids[-1], description="grid n_s", continuous_update=False)

    def update(_=None) -> None:
        out.clear_output(wait=True)
        with out:
            draw(sw.value, sd.value, sg.value)

    for s in (sw, sd, sg):
        s.observe(update, names="value")
    display(static_architecture(rows, title))  # works in the static book, without a kernel
    box = W.VBox([W.HBox([sw, sd, sg]), out])
    display(box)
    return box
