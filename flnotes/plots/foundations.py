"""Figures of the book: foundations part (feedback linearization, ReLU networks, big-M, node bounds).

Each ``plot_*`` function draws one figure of chapters 1-4 and returns it; the
few ``*_residual``/``*_experiment``/``*_counts`` helpers compute the numbers
those figures show, so a chapter can print or glue exactly what is drawn.
``explore_feasible_set`` is the interactive explorer of the constraint set
``V`` of eq. (contraint_new_set).
"""
from __future__ import annotations

import re
from typing import Optional, Sequence

import matplotlib.pyplot as plt
import numpy as np

from .._checks import (as_floats, as_pair, as_state, as_vector, brief, check_box, check_count, check_int,
                       check_number, check_seed)
from ..bounds import fbbt, sample_preactivations
from ..network import ReLUNet
from ..systems import FLSystem, brunovsky, discretize
from .style import COLORS, bound_lines, new_axes

Array = np.ndarray

__all__ = [
    "static_feasible_set",
    "fl_identity_residual", "affine_v_interval", "plot_feasible_set", "plot_feasible_v", "explore_feasible_set", "plot_zeta",
    "plot_input_violation", "discretization_gap", "plot_discretization_gap",
    "plot_error_slice", "plot_line_cut", "plot_width_experiment",
    "plot_relu_bigm", "bounds_looseness", "plot_bounds_vs_samples", "unstable_fixed_z", "plot_unstable_fixed_z",
    "unstable_vs_box_size", "plot_unstable_vs_box_size",
]


def _single_input(system: FLSystem, what: str) -> None:
    if system.m != 1:
        raise ValueError(f"{what} draws the admissible v of a single-input system; {system.name} has m = {system.m} "
                         f"inputs: fix all but one input and wrap Phi as a single-input system")


def _z_point(system: FLSystem, z: Optional[Array], name: str = "z_fixed") -> Array:
    return np.zeros(system.n_z) if z is None else as_state(z, system.n_z, name)


def _index(i, name: str, size: int, what: str) -> int:
    """``i`` as an index 0..size-1 of ``what`` (an integer, not a boolean; negative from the end, as Python counts),
    else ``ValueError`` naming ``name``."""
    i = check_int(i, name, -size, f"the index, 0-based (negative from the end), of {what}")
    if i >= size:
        raise ValueError(f"{name} must index {what}: 0..{size - 1} (or -{size}..-1), got {i}")
    return i % size


def _seed(seed, name: str = "seed"):
    """``seed`` for ``np.random.default_rng``: an integer >= 0, ``None`` (a fresh random sample) or numpy's own seed
    objects (a ``Generator``, ``BitGenerator`` or ``SeedSequence``); anything else (a boolean, a float, a negative
    integer) is a ``ValueError`` naming ``name`` (:func:`flnotes._checks.check_seed`, the rule of every seed)."""
    return check_seed(seed, name)


# --------------------------------------------------------------------------
# Chapter 1: feedback linearization and its constraint set
# --------------------------------------------------------------------------
def fl_identity_residual(system: FLSystem, n: int = 200, seed: int = 0, h: float = 1e-6) -> Array:
    """Check eq. (linearizedDyna) on the true plant at random points of the domain.

    For ``n`` uniform samples ``(z, v)`` of the domain box, the plant state is
    ``x = to_x(z)`` and the input ``u = Phi(z, v)`` (eq. coor_Phi). The time
    derivative of ``z = to_z(x)`` along the true plant is estimated by a
    central difference ``(to_z(x + h f) - to_z(x - h f)) / (2h)`` with
    ``f = f(x, u)``; feedback linearization says it equals ``A z + B v``.

    Parameters
    ----------
    system
        The system.
    n, seed
        Number of random points and the seed (an integer >= 0, or ``None`` for a fresh sample).
    h
        Step of the central difference: a finite number > 0.

    Returns
    -------
    Array
        Largest ``|dz/dt - (A z + B v)|`` per component of ``z``, shape (n_z,).
    """
    n = check_count(n, "n", 1, "random points of the domain")
    h = check_number(h, "h", "the step of the central difference, e.g. 1e-6", strict=True)
    X = np.random.default_rng(_seed(seed)).uniform(system.lo, system.hi, (n, system.n_in))
    Z, V = system.split(X)
    U = system.Phi(Z, V)
    res = np.zeros(system.n_z)
    for z, v, u in zip(Z, V, U):
        x = np.asarray(system.to_x(z), float)
        f = np.asarray(system.f(x, u), float)
        zdot = (np.asarray(system.to_z(x + h * f)) - np.asarray(system.to_z(x - h * f))) / (2 * h)
        res = np.maximum(res, np.abs(zdot - (system.A @ z + system.B @ v)))
    return res


def _v_axis(system: FLSystem, v_lim: Optional[Sequence[float]], n: int) -> Array:
    """``n`` points of ``v`` over ``v_lim`` (two finite numbers lo < hi), or over the domain box when it is None."""
    if v_lim is None:
        return np.linspace(system.lo[-1], system.hi[-1], int(n))
    lo, hi = as_pair(v_lim, "v_lim")
    lo, hi = (check_number(x, f"v_lim[{i}]", "an end of the drawn range of v", low=-np.inf)
              for i, x in enumerate((lo, hi)))
    if lo >= hi:
        raise ValueError(f"v_lim must be a range (lo, hi) with lo < hi, got {brief(v_lim)}: give the lower end first")
    return np.linspace(lo, hi, int(n))


def affine_v_interval(system: FLSystem, z: Array) -> tuple[Array, Array]:
    """The interval ``{v : |Phi(z, v)| <= u_max}`` of a single-input system whose ``Phi`` is affine in ``v``.

    With ``Phi(z, v) = Phi(z, 0) + g(z) v`` and ``g(z) != 0`` (eq. contraint_new_set; both systems of the
    course, eqs. (1.6) and (1.9)), the ends are ``(+-u_max - Phi(z, 0)) / g(z)``, ordered. The caller checks
    affinity; a zero slope is an error.

    Parameters
    ----------
    system
        A single-input system.
    z
        States, shape (N, n_z).

    Returns
    -------
    v_lo, v_hi
        The ends of the interval, each shape (N,).
    """
    _single_input(system, "affine_v_interval")
    z = np.asarray(z, float)
    if z.ndim != 2 or z.shape[1] != system.n_z:
        raise ValueError(f"z must have shape (N, {system.n_z}), got {z.shape}")
    p0 = system.Phi(z, np.zeros((len(z), 1)))[:, 0]
    g = system.Phi(z, np.ones((len(z), 1)))[:, 0] - p0
    if np.any(g == 0):
        raise ValueError("Phi does not depend on v at some state: the admissible v is not an interval")
    ends = np.stack([(-system.u_max[0] - p0) / g, (system.u_max[0] - p0) / g])
    return ends.min(0), ends.max(0)


def _affine_in_v(system: FLSystem, z: Array, vs: Array) -> bool:
    """Whether ``Phi(z, v)`` is affine in ``v`` at the states ``z`` over the values ``vs`` (to rounding)."""
    p0 = system.Phi(z, np.zeros((len(z), 1)))[:, 0]
    g = system.Phi(z, np.ones((len(z), 1)))[:, 0] - p0
    for v in (vs[0], vs[len(vs) // 3], vs[-1]):
        p = system.Phi(z, np.full((len(z), 1), v))[:, 0]
        if not np.allclose(p, p0 + g * v, rtol=1e-9, atol=1e-9 * (1 + abs(v))):
            return False
    return bool(np.all(g != 0))


def plot_feasible_set(system: FLSystem, axis: int = 1, z_fixed: Optional[Array] = None,
                      family: Optional[tuple[int, Sequence[float]]] = None, v_lim: Optional[Sequence[float]] = None,
                      n: int = 301):
    """A slice of ``V = {(z, v): |Phi(z, v)| <= u_max}`` (eq. contraint_new_set) over ``(z_axis, v)``.

    The box ``|u| <= u_max`` becomes, for each state, an interval of admissible
    ``v`` that moves with the state: the shaded band. When ``Phi`` is affine in
    ``v`` (both systems of the course), the band's edges are the exact lines of
    `affine_v_interval`; otherwise they are the level set of an ``n x n`` grid.

    Parameters
    ----------
    system
        A single-input system.
    axis
        Index of the component of ``z`` on the horizontal axis (0-based, an integer).
    z_fixed
        Values of the other components of ``z``, shape (n_z,) (the ``axis``
        entry is ignored); default zero.
    family
        Optional ``(index, values)``: draw one band per value of ``z[index]`` (an integer index other than
        ``axis``, and numbers).
    v_lim
        Range ``(lo, hi)`` of ``v`` drawn, two finite numbers with ``lo < hi``; default the domain box. The box's
        ``v`` limits are dashed.
    n
        Grid points per axis.

    Returns
    -------
    matplotlib.figure.Figure
    """
    _single_input(system, "plot_feasible_set")
    n = check_count(n, "n", 2, "grid points per axis")
    axis = _index(axis, "axis", system.n_z, "a component of z")
    z0 = _z_point(system, z_fixed)
    if family is not None:
        fam_i, fam_v = as_pair(family, "family")
        fam_i = _index(fam_i, "family[0]", system.n_z, "a component of z")
        if fam_i == axis:
            raise ValueError(f"family[0] must index another component of z than axis = {axis} (the horizontal "
                             f"axis), got {fam_i}")
        fam_v = as_floats(fam_v, "family[1]")
        if fam_v.ndim != 1 or fam_v.size == 0 or not np.all(np.isfinite(fam_v)):
            raise ValueError(f"family[1] must be a non-empty sequence of finite values of z[{fam_i}], got "
                             f"{brief(family[1])}")
        family = (fam_i, fam_v.tolist())
    zs = np.linspace(system.lo[axis], system.hi[axis], int(n))
    vs = _v_axis(system, v_lim, n)
    Zg, Vg = np.meshgrid(zs, vs, indexing="xy")
    zs_fine = np.linspace(zs[0], zs[-1], 20 * int(n))  # the exact edges are cheap: draw them finely
    fam_idx, fam_vals = (None, [None]) if family is None else (int(family[0]), list(family[1]))
    colors = plt.cm.viridis(np.linspace(0.1, 0.85, len(fam_vals))) if family is not None else [COLORS["u_max"]]
    fig, ax = new_axes(figsize=(6.4, 3.8))
    handles = []
    for val, c in zip(fam_vals, colors):
        z = np.tile(z0, (Zg.size, 1))
        z[:, axis] = Zg.ravel()
        if fam_idx is not None:
            z[:, fam_idx] = val
        z_line = np.tile(z[0], (len(zs_fine), 1))
        z_line[:, axis] = zs_fine
        edges = affine_v_interval(system, z_line) if _affine_in_v(system, z_line, vs) else None
        if edges is not None:  # the exact boundaries v = (+-u_max - Phi(z, 0)) / slope, clipped to the drawn range
            v_a, v_b = np.clip(edges[0], vs[0], vs[-1]), np.clip(edges[1], vs[0], vs[-1])
            ax.fill_between(zs_fine, v_a, v_b, where=v_a < v_b, color=c, alpha=0.30, lw=0)
            for e in edges:
                ax.plot(zs_fine, np.where((e >= vs[0]) & (e <= vs[-1]), e, np.nan), color=c, lw=1.2)
        else:  # Phi not affine in v: the level set of the grid
            ok = (np.abs(system.Phi(z, Vg.reshape(-1, 1))) <= system.u_max).all(1).reshape(Zg.shape)
            ax.contourf(Zg, Vg, ok.astype(float), levels=[0.5, 1.5], colors=[c], alpha=0.30)
            if ok.any() and not ok.all():
                ax.contour(Zg, Vg, ok.astype(float), levels=[0.5], colors=[c], linewidths=1.2)
        lab = r"$|\Phi(z, v)| \leq u_{\max}$" if fam_idx is None else f"$z_{fam_idx + 1} = {val:g}$"
        handles.append(plt.Rectangle((0, 0), 1, 1, color=c, alpha=0.45, label=lab))
    for s in (system.lo[-1], system.hi[-1]):
        if vs[0] <= s <= vs[-1]:
            ax.axhline(s, color="k", ls="--", lw=0.8)
    fixed = [f"$z_{i + 1} = {z0[i]:g}$" for i in range(system.n_z) if i != axis and i != fam_idx]
    ax.set(xlabel=f"$z_{axis + 1}$", ylabel="$v$",
           title=f"{system.name}: admissible $v$ over $z_{axis + 1}$" + (f" ({', '.join(fixed)})" if fixed else ""))
    ax.legend(handles=handles, loc="upper right")
    return fig


def plot_feasible_v(system: FLSystem, z: Optional[Array] = None, net: Optional[ReLUNet] = None,
                    eps: Optional[float] = None, n: int = 801, ax=None):
    """``Phi(z, .)`` (and ``Phi_NN(z, .)``) over ``v`` at one state, with the admissible ``v`` shaded.

    Blue band: ``{v: |Phi(z, v)| <= u_max}`` (eq. contraint_new_set). Green
    band (with ``net`` and ``eps``): ``{v: |Phi_NN(z, v)| <= u_max - eps}``
    (eq. Phi_NN_ep); by Proposition 1 it lies inside the blue one whenever
    ``eps`` bounds the approximation error.

    Parameters
    ----------
    system
        A single-input system.
    z
        The state, shape (n_z,); default zero.
    net, eps
        Optional network ``Phi_NN`` and error bound ``eps`` (scalar).
    n
        Points on the ``v`` axis (over the domain box).
    ax
        Axes to draw into (default: a new figure).

    Returns
    -------
    matplotlib.figure.Figure
    """
    _single_input(system, "plot_feasible_v")
    n = check_count(n, "n", 2, "points on the v axis")
    z = _z_point(system, z, "z")
    vs = _v_axis(system, None, n)
    Z = np.tile(z, (len(vs), 1))
    u = system.Phi(Z, vs[:, None])[:, 0]
    u_max = float(system.u_max[0])
    if ax is None:
        fig, ax = new_axes(figsize=(6.4, 3.6))
    else:
        fig = ax.figure
    _shade_runs(ax, vs, np.abs(u) <= u_max, COLORS["u_max"], 0.18, r"$|\Phi| \leq u_{\max}$")
    ax.plot(vs, u, color=COLORS["true"], label=r"$\Phi(z, v)$")
    title = f"{system.name} at z = {np.array2string(z, precision=2)}"
    if net is not None:
        unn = net(system.stack(Z, vs[:, None]))[:, 0]
        ax.plot(vs, unn, color=COLORS["nn"], ls="--", label=r"$\Phi_{NN}(z, v)$")
        if eps is not None:
            _shade_runs(ax, vs, np.abs(unn) <= u_max - float(eps), COLORS["u_max_eps"], 0.25,
                        r"$|\Phi_{NN}| \leq u_{\max}^{\varepsilon}$")
    bound_lines(ax, u_max, None if net is None else eps)
    ok = np.abs(u) <= u_max
    title += (f": admissible v in [{vs[ok].min():.2f}, {vs[ok].max():.2f}]" if ok.any()
              else ": no admissible v in the box")
    ax.set(xlabel="$v$", ylabel="$u$", title=title, ylim=(-3 * u_max, 3 * u_max))
    ax.legend(loc="upper left", ncols=2)
    return fig


def _shade_runs(ax, x: Array, mask: Array, color: str, alpha: float, label: str) -> None:
    """Shade the contiguous runs of ``mask`` along ``x`` (one legend entry)."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(int), 0]))
    for i, (a, b) in enumerate(zip(edges[::2], edges[1::2])):
        ax.axvspan(x[a], x[b - 1], color=color, alpha=alpha, lw=0, label=label if i == 0 else None)


def explore_feasible_set(system: FLSystem, net: Optional[ReLUNet] = None, eps: Optional[float] = None):
    """Interactive: move the state ``z`` and watch the admissible set of ``v`` move.

    Shows :func:`static_feasible_set` first (precomputed frames behind a
    slider that runs in the browser, so the built book moves without a
    kernel), then returns one ipywidgets slider per component of ``z``
    (``continuous_update=False``) and an output area that redraws the figure
    for the chosen state in a running kernel.

    Parameters
    ----------
    system
        A single-input system.
    net, eps
        Optional network and error bound, drawn as in :func:`plot_feasible_v`.

    Returns
    -------
    ipywidgets.VBox
    """
    import ipywidgets as widgets
    from IPython.display import display

    _single_input(system, "explore_feasible_set")
    display(static_feasible_set(system, net, eps))  # works in the static book, without a kernel
    sliders = [widgets.FloatSlider(value=0.0, min=float(system.lo[i]), max=float(system.hi[i]),
                                   step=float(system.hi[i] - system.lo[i]) / 100, description=f"z{i + 1}",
                                   continuous_update=False, readout_format=".2f")
               for i in range(system.n_z)]
    out = widgets.Output()

    def redraw(_change=None) -> None:
        with out:
            out.clear_output(wait=True)
            f = plot_feasible_v(system, np.array([s.value for s in sliders]), net, eps)
            display(f)
            plt.close(f)

    for s in sliders:
        s.observe(redraw, names="value")
    note = widgets.HTML("<i>Move a slider: the figure is redrawn below for the chosen state.</i>")
    return widgets.VBox([widgets.HBox(sliders), note, out])


def static_feasible_set(system: FLSystem, net: Optional[ReLUNet] = None, eps: Optional[float] = None,
                        n_frames: Optional[int] = None):
    """Kernel-free explorer: :func:`plot_feasible_v` precomputed along the last component of ``z``, the others zero.

    Parameters
    ----------
    system
        A single-input system.
    net, eps
        Optional network and error bound, drawn as in :func:`plot_feasible_v`.
    n_frames
        Number of values of ``z_{n_z}`` (odd, so that ``z = 0`` is one of them);
        default 9, 5 in fast mode.

    Returns
    -------
    flnotes.plots.static.FramePlayer
    """
    from ..config import FAST
    from .static import frame_player

    _single_input(system, "static_feasible_set")
    n = (5 if FAST else 9) if n_frames is None else check_count(n_frames, "n_frames", 2, "values of the last "
                                                                                         "component of z")
    i = system.n_z - 1
    values = np.round(np.linspace(system.lo[i], system.hi[i], n), 3)

    def draw(zi: float):
        z = np.zeros(system.n_z)
        z[i] = zi
        return plot_feasible_v(system, z, net, eps)

    name = re.sub(r"[^A-Za-z0-9]", "", f"feasible{system.name}") + ("-net" if net is not None else "")
    start = int(np.argmin(np.abs(values)))
    return frame_player(draw, {f"z{i + 1}": values}, name=name, start=[start])


def plot_zeta(system: FLSystem, extent: float = 15.0, n: int = 301):
    """Quad-1D: ``zeta(z) = (z_3 + gamma z_2) / Gamma`` over ``(z_2, z_3)`` and the singular set ``|zeta| = 1``.

    The linearizing map of eq. (quad1D_nonlinear) divides by
    ``sqrt(1 - zeta^2)`` (Remark 1); the training box is drawn as a rectangle.

    Parameters
    ----------
    system
        A system with a ``zeta(z)`` method (``fl.quad1d()``).
    extent
        Half-width of the drawn ``(z_2, z_3)`` square: a finite number > 0.
    n
        Grid points per axis.
    """
    if not hasattr(system, "zeta"):
        raise ValueError(f"system {system.name!r} has no zeta(z): plot_zeta is for the quadrotor (fl.quad1d())")
    n = check_count(n, "n", 2, "grid points per axis")
    extent = check_number(extent, "extent", "the half-width of the drawn square", strict=True)
    s = np.linspace(-extent, extent, n)
    Z2, Z3 = np.meshgrid(s, s, indexing="xy")
    Z = np.column_stack([np.zeros(Z2.size), Z2.ravel(), Z3.ravel()])
    zeta = system.zeta(Z).reshape(Z2.shape)
    fig, ax = new_axes(figsize=(5.4, 4.2))
    im = ax.contourf(Z2, Z3, np.abs(zeta), levels=np.linspace(0, max(1.6, np.abs(zeta).max()), 17), cmap="Blues")
    fig.colorbar(im, ax=ax, label=r"$|\zeta(z)|$")
    ax.grid(False)
    ax.contour(Z2, Z3, np.abs(zeta), levels=[1.0], colors=[COLORS["unsafe"]], linewidths=1.6)
    lo, hi = system.lo[1:3], system.hi[1:3]
    ax.add_patch(plt.Rectangle(lo, *(hi - lo), fill=False, ec="k", lw=1.4, ls="--"))
    ax.plot([], [], color=COLORS["unsafe"], label=r"$|\zeta| = 1$ (singular)")
    ax.plot([], [], color="k", ls="--", label="training box")
    ax.set(xlabel="$z_2$", ylabel="$z_3$", title=r"Quad-1D: $\zeta(z) = (z_3 + \gamma z_2)/\Gamma$")
    ax.legend(loc="lower left")
    return fig


def plot_input_violation(log, title: Optional[str] = None):
    """A closed-loop run: the phase portrait in ``z`` and the true input ``u(t)`` against ``±u_max``.

    Parameters
    ----------
    log
        A :class:`flnotes.SimLog` of a two-state, single-input system.
    title
        Optional title of the input panel.
    """
    fig, axs = new_axes(1, 2, figsize=(9.0, 3.4))
    a1, a2 = axs.ravel()
    a1.plot(log.z_fine[:, 0], log.z_fine[:, 1], color=COLORS["nominal"])
    a1.plot(*log.z[0, :2], "ko", ms=4, label="$z(0)$")
    a1.set(xlabel="$z_1$", ylabel="$z_2$", title="trajectory in $z$")
    a1.legend()
    a2.plot(log.t_fine, log.u_fine[:, 0], color=COLORS["nominal"], label="$u(t)$")
    bound_lines(a2, float(log.system.u_max[0]))
    viol = np.abs(log.u_fine[:, 0]) > log.system.u_max[0]
    if viol.any():
        a2.plot(log.t_fine[viol], log.u_fine[viol, 0], ".", color=COLORS["unsafe"], ms=3, label="violation")
    a2.set(xlabel="$t$ [s]", ylabel="$u$", title=title or "true input")
    a2.legend()
    return fig


def discretization_gap(ts: float, orders: Sequence[int] = (1, 2, 3, 4, 5, 6)) -> Array:
    """``max(|A_d^exact - A_d^rk4|, |B_d^exact - B_d^rk4|)`` for single chains of each length.

    Both discretize ``z' = A z + B v`` with ``v`` held over ``ts``; they agree
    (to rounding) as long as ``A^4 = 0``, i.e. chains of at most four integrators.
    """
    gaps = []
    for r in orders:
        A, B = brunovsky([int(r)])
        Ae, Be = discretize(A, B, ts, "exact")
        Ar, Br = discretize(A, B, ts, "rk4")
        gaps.append(max(np.abs(Ae - Ar).max(), np.abs(Be - Br).max()))
    return np.array(gaps)


def plot_discretization_gap(ts_values: Sequence[float] = (0.01, 0.1, 0.5),
                            orders: Sequence[int] = (1, 2, 3, 4, 5, 6)):
    """Gap between exact (zero-order hold) and RK4 discretization vs chain length, one line per ``ts``."""
    fig, ax = new_axes(figsize=(6.0, 3.4))
    for ts in ts_values:
        g = discretization_gap(ts, orders)
        ax.semilogy(list(orders), np.maximum(g, 1e-18), "o-", label=f"$t_s$ = {ts:g} s")
    ax.axvspan(0.5, 4.5, color=COLORS["grid"], alpha=0.5, lw=0, label="chain length $\\leq 4$")
    ax.set(xlabel="chain length $r$", ylabel="max |exact - RK4|", ylim=(1e-18, 1),
           title="ZOH vs one RK4 step (values below 1e-18 drawn at 1e-18)")
    ax.legend(loc="upper left")
    return fig


# --------------------------------------------------------------------------
# Chapter 2: ReLU networks
# --------------------------------------------------------------------------
def _slice_points(system: FLSystem, axes: tuple[int, int], x_fixed: Optional[Array], n: int):
    x0 = (system.lo + system.hi) / 2 if x_fixed is None else as_vector(x_fixed, system.n_in, "x_fixed")
    a = np.linspace(system.lo[axes[0]], system.hi[axes[0]], int(n))
    b = np.linspace(system.lo[axes[1]], system.hi[axes[1]], int(n))
    A_, B_ = np.meshgrid(a, b, indexing="xy")
    X = np.tile(x0, (A_.size, 1))
    X[:, axes[0]], X[:, axes[1]] = A_.ravel(), B_.ravel()
    return x0, A_, B_, X


def _name(system: FLSystem, i: int) -> str:
    return f"$z_{i + 1}$" if i < system.n_z else ("$v$" if system.m == 1 else f"$v_{i - system.n_z + 1}$")


def plot_error_slice(system: FLSystem, net: ReLUNet, axes: tuple[int, int] = (1, 2),
                     x_fixed: Optional[Array] = None, n: int = 201, output: int = 0):
    """``|Phi - Phi_NN|`` over a 2-D slice of the stacked input ``(z, v)``.

    Parameters
    ----------
    system, net
        The system and its network.
    axes
        The two stacked-input coordinates on the axes (two different integers, 0-based; ``n_z`` is ``v``).
    x_fixed
        The other coordinates, shape (n_in,); default the box centre.
    n
        Grid points per axis.
    output
        Which input ``u_i`` for multi-input systems (an integer, 0-based).
    """
    n = check_count(n, "n", 2, "grid points per axis")
    axes = tuple(_index(a, f"axes[{k}]", system.n_in, "a coordinate of the stacked input (z, v)")
                 for k, a in enumerate(as_pair(axes, "axes")))
    if axes[0] == axes[1]:
        raise ValueError(f"axes must be two different coordinates of the stacked input (z, v), got {axes}")
    output = _index(output, "output", min(system.m, net.n_out), "an output of Phi (an input u_i)")
    x0, A_, B_, X = _slice_points(system, axes, x_fixed, n)
    err = np.abs(net(X) - system.phi_stacked(X))[:, output].reshape(A_.shape)
    fig, ax = new_axes(figsize=(6.0, 4.2))
    im = ax.pcolormesh(A_, B_, err, shading="auto", cmap="magma_r")
    fig.colorbar(im, ax=ax, label=r"$|\Phi - \Phi_{NN}|$")
    ax.grid(False)
    i, j = np.unravel_index(np.argmax(err), err.shape)
    ax.plot(A_[i, j], B_[i, j], "c*", ms=11, label=f"max {err.max():.3f}")
    fixed = [f"{_name(system, k)[:-1]} = {x0[k]:g}$" for k in range(system.n_in) if k not in axes]
    ax.set(xlabel=_name(system, axes[0]), ylabel=_name(system, axes[1]),
           title=f"{system.name}: approximation error on the slice {', '.join(fixed)}")
    ax.legend(loc="upper right")
    return fig


def plot_line_cut(system: FLSystem, net: ReLUNet, axis: int = 1, x_fixed: Optional[Array] = None,
                  n: int = 2001, output: int = 0):
    """``Phi`` and ``Phi_NN`` along one coordinate of ``(z, v)`` (top) and their difference (bottom).

    ``axis`` indexes a coordinate of the stacked input ``(z, v)`` and ``output`` an output of ``Phi`` (integers,
    0-based); ``x_fixed`` holds the other coordinates, shape (n_in,), default the box centre.
    """
    n = check_count(n, "n", 2, "points along the axis")
    axis = _index(axis, "axis", system.n_in, "a coordinate of the stacked input (z, v)")
    output = _index(output, "output", min(system.m, net.n_out), "an output of Phi (an input u_i)")
    x0 = (system.lo + system.hi) / 2 if x_fixed is None else as_vector(x_fixed, system.n_in, "x_fixed")
    s = np.linspace(system.lo[axis], system.hi[axis], n)
    X = np.tile(x0, (len(s), 1))
    X[:, axis] = s
    u, unn = system.phi_stacked(X)[:, output], net(X)[:, output]
    fig, axs = new_axes(2, 1, figsize=(6.4, 4.4), sharex=True)
    a1, a2 = axs.ravel()
    a1.plot(s, u, color=COLORS["true"], label=r"$\Phi$")
    a1.plot(s, unn, color=COLORS["nn"], ls="--", label=r"$\Phi_{NN}$")
    fixed = [f"{_name(system, k)[:-1]} = {x0[k]:g}$" for k in range(system.n_in) if k != axis]
    a1.set(ylabel="$u$", title=f"{system.name}: cut along {_name(system, axis)} at {', '.join(fixed)}")
    a1.legend()
    a2.plot(s, unn - u, color=COLORS["nn"])
    a2.set(xlabel=_name(system, axis), ylabel=r"$\Phi_{NN} - \Phi$")
    return fig


def plot_width_experiment(rows: Sequence[dict], title: str = ""):
    """Grid max error, grid RMSE and random-sample max error against the width ``n_bar``."""
    nb = [r["n_bar"] for r in rows]
    fig, ax = new_axes(figsize=(6.0, 3.6))
    ax.semilogy(nb, [r["grid_max_error"] for r in rows], "o-", color=COLORS["nn"], label="grid max error")
    ax.semilogy(nb, [r["sample_max_error"] for r in rows], "s--", color=COLORS["true"], label="random-sample max error")
    ax.semilogy(nb, [r["grid_rmse"] for r in rows], "^:", color="0.4", label="grid RMSE")
    ax.set(xlabel=r"width $\bar n$ (3 hidden layers)", ylabel=r"$|\Phi - \Phi_{NN}|$", title=title)
    ax.legend()
    return fig


# --------------------------------------------------------------------------
# Chapter 3: big-M
# --------------------------------------------------------------------------
def plot_relu_bigm(L: float = -1.0, U: float = 2.0, alphas: Sequence[float] = (0.25, 0.5, 0.75)):
    """One neuron: the graph of ``y = max(0, a)`` over ``[L, U]`` and the big-M set of eq. (one_perceptron_MIP).

    With ``alpha`` in {0, 1} the constraints
    ``a = ybar - yund``, ``ybar, yund >= 0``, ``ybar <= U alpha``, ``yund <= -L (1 - alpha)``
    give exactly the graph; with ``alpha`` relaxed to [0, 1] the projection on
    ``(a, y = ybar)`` is the shaded triangle ``conv{(L, 0), (0, 0), (U, U)}``.
    The outlines show the slices at fixed fractional ``alpha``.
    """
    if not L < 0 < U:
        raise ValueError(f"draw an unstable neuron: need L < 0 < U, got L={L}, U={U}")
    a = np.linspace(L, U, 801)
    fig, ax = new_axes(figsize=(6.0, 4.0))
    ax.fill([L, 0, U], [0, 0, U], color=COLORS["u_max"], alpha=0.18, label=r"relaxation, $\alpha \in [0, 1]$")
    cmap = plt.cm.Greys(np.linspace(0.45, 0.8, len(alphas)))
    for al, c in zip(alphas, cmap):
        lower, upper = np.maximum(a, 0.0), np.minimum(U * al, a - L * (1 - al))
        ok = upper >= lower - 1e-12
        ax.plot(np.r_[a[ok], a[ok][::-1], a[ok][0]], np.r_[lower[ok], upper[ok][::-1], lower[ok][0]],
                color=c, lw=1, label=fr"$\alpha = {al:g}$")
    ax.plot(a, np.maximum(a, 0.0), color=COLORS["true"], lw=2.4, label=r"$y = \max(0, a)$ ($\alpha \in \{0,1\}$)")
    ax.plot([L, 0], [0, 0], color=COLORS["nn"], lw=2.4, label=r"$\alpha = 0$ piece")
    ax.plot([0, U], [0, U], color=COLORS["u_max_eps"], lw=2.4, ls="--", label=r"$\alpha = 1$ piece")
    ax.set(xlabel="pre-activation $a = W y^{in} + b$", ylabel=r"$y^\star = \bar y^\star$",
           title=f"one neuron with L = {L:g}, U = {U:g}")
    ax.legend(loc="upper left")
    return fig


# --------------------------------------------------------------------------
# Chapter 4: node bounds
# --------------------------------------------------------------------------
def bounds_looseness(net: ReLUNet, lo: Array, hi: Array, n: int = 100_000, seed: int = 0) -> Array:
    """Median over the neurons of ``(U - L) / (sampled max - sampled min)`` per hidden layer.

    1 means FBBT is as tight as the sampled range (which itself under-estimates
    the true range); larger means looser big-M constants.
    """
    n = check_count(n, "n", 1, "random samples of the box")
    seed = _seed(seed)
    b = fbbt(net, lo, hi)
    pre = sample_preactivations(net, lo, hi, n=n, seed=seed)
    return np.array([np.median((U - L) / np.maximum(a.max(0) - a.min(0), 1e-12)) for a, L, U in zip(pre, b.L, b.U)])


def plot_bounds_vs_samples(net: ReLUNet, lo: Array, hi: Array, n: int = 100_000, seed: int = 0,
                           max_neurons: int = 20):
    """Per layer: FBBT intervals ``[L, U]`` against the sampled range of each neuron's pre-activation.

    Parameters
    ----------
    net
        The network.
    lo, hi
        The input box, shape (n_in,).
    n, seed
        Uniform samples of the box (the corners are added).
    max_neurons
        Neurons drawn per layer (the first ones).
    """
    lo, hi = check_box(lo, hi, net.n_in)
    n = check_count(n, "n", 1, "random samples of the box")
    max_neurons = check_count(max_neurons, "max_neurons", 1, "neurons drawn per layer")
    seed = _seed(seed)
    b = fbbt(net, lo, hi)
    pre = sample_preactivations(net, lo, hi, n=n, seed=seed)
    fig, axs = new_axes(1, net.K - 1, figsize=(3.2 * (net.K - 1), 3.6), sharey=False)
    axs = np.atleast_1d(axs).ravel()
    for k, (ax, a, L, U) in enumerate(zip(axs, pre, b.L, b.U)):
        j = np.arange(min(len(L), max_neurons))
        ax.vlines(j, L[j], U[j], color=COLORS["u_max"], lw=6, alpha=0.35, label="FBBT $[L, U]$")
        ax.vlines(j, a.min(0)[j], a.max(0)[j], color=COLORS["nn"], lw=2, label="sampled range")
        ax.axhline(0, color="k", lw=0.7)
        ax.set(title=f"layer {k + 1}", xlabel="neuron $j$")
        if k == 0:
            ax.set_ylabel("pre-activation")
    # below the axes, so that it covers no neuron's interval
    axs[0].legend(*axs[0].get_legend_handles_labels(), loc="upper left", bbox_to_anchor=(0.0, -0.2), ncol=2,
                  frameon=False)
    return fig


def unstable_fixed_z(system: FLSystem, net: ReLUNet, n: int = 1000, seed: int = 0) -> Array:
    """Unstable neurons when ``z`` is measured: boxes ``{z} x [v_lo, v_hi]`` at ``n`` random states.

    A controller knows ``z`` and only decides ``v``, so its FBBT box fixes the
    ``z`` coordinates (``lo == hi``). All ``n`` boxes are propagated at once.

    Returns
    -------
    Array
        Number of unstable neurons (binaries) per sampled state, shape (n,).
    """
    rng = np.random.default_rng(_seed(seed))
    Z = rng.uniform(system.lo[: system.n_z], system.hi[: system.n_z], (check_count(n, "n", 1, "random states"),
                                                                           system.n_z))
    lo = np.hstack([Z, np.tile(system.lo[system.n_z:], (len(Z), 1))])
    hi = np.hstack([Z, np.tile(system.hi[system.n_z:], (len(Z), 1))])
    b = fbbt(net, lo, hi)
    return sum(u.sum(1) for u in b.unstable)


def plot_unstable_fixed_z(counts: Array, n_full_box: int, n_hidden: int, title: str = ""):
    """Histogram of the binaries needed with ``z`` fixed, against the full box and ``sum n_k``."""
    counts = np.asarray(counts)
    fig, ax = new_axes(figsize=(6.0, 3.4))
    ax.hist(counts, bins=np.arange(-0.5, n_hidden + 1.5, 1), color=COLORS["nn"], alpha=0.8,
            label="box $\\{z\\} \\times [v_{lo}, v_{hi}]$")
    ax.axvline(n_full_box, color=COLORS["u_max"], lw=2, label=f"full box: {n_full_box}")
    ax.axvline(n_hidden, color="k", ls="--", lw=1, label=f"all neurons: {n_hidden}")
    ax.set(xlabel="unstable neurons (binaries)", ylabel="states", title=title)
    ax.legend()
    return fig


def unstable_vs_box_size(system: FLSystem, net: ReLUNet, radii: Sequence[float] = tuple(np.logspace(-3, 0, 13)),
                         n_centers: int = 200, seed: int = 0) -> Array:
    """Mean fraction of unstable neurons for boxes of relative half-width ``r`` (the book's ``r_box``) at random centres.

    A box is ``w_c ± r (hi - lo)``, clipped to the domain, with centres ``w_c``
    uniform in the domain; ``r = 1`` gives the whole domain from any centre.

    Returns
    -------
    Array
        Shape (len(radii),): mean over centres of ``n_unstable / sum n_k``.
    """
    rng = np.random.default_rng(_seed(seed))
    C = rng.uniform(system.lo, system.hi, (check_count(n_centers, "n_centers", 1, "random centres"), system.n_in))
    half = system.hi - system.lo
    out = []
    for r in radii:
        lo, hi = np.maximum(C - r * half, system.lo), np.minimum(C + r * half, system.hi)
        b = fbbt(net, lo, hi)
        out.append(np.mean(sum(u.sum(1) for u in b.unstable)) / net.n_hidden)
    return np.array(out)


def plot_unstable_vs_box_size(radii: Sequence[float], fractions: dict):
    """Fraction of unstable neurons against the relative box size, one line per network."""
    fig, ax = new_axes(figsize=(6.0, 3.6))
    for name, fr in fractions.items():
        ax.semilogx(radii, fr, "o-", ms=4, label=name)
    ax.set(xlabel="relative half-width $r_{box}$ of the box", ylabel="unstable neurons / $\\Sigma_k n_k$", ylim=(0, 1.02),
           title="binaries needed vs size of the input box (FBBT)")
    ax.legend()
    return fig
