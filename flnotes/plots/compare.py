"""Figures of the comparative study: one run of every method, and the Monte Carlo distributions.

Plots only draw: the runs come from :func:`flnotes.studies.compare.run_methods`, the rows from
:func:`flnotes.studies.compare.monte_carlo`.
"""
from __future__ import annotations

from typing import Callable, Mapping, Optional, Sequence

import numpy as np

from .style import COLORS, bound_lines, new_axes

Array = np.ndarray

__all__ = ["METHOD_COLORS", "plot_methods_run", "plot_monte_carlo"]

#: One colour per method of the study.
METHOD_COLORS = {"network": COLORS["true"], "measured": "#e6ab02", "previous": "#7570b3", "saturated": "#d62728",
                 "nmpc": "#1b9e77"}


def _label(method: str, labels: Optional[Mapping[str, str]]) -> str:
    return (labels or {}).get(method, method)


def _color(key: str) -> Optional[str]:
    """The colour of a method, or of a variant of it (``"<method> hold u"``, ``"network eps+delta"``)."""
    return METHOD_COLORS.get(key.split(" ")[0])


def _own(key: str) -> bool:
    """Whether ``key`` is a method as it is (its own hold, ``eps``) rather than a variant of it."""
    return " " not in key


def plot_methods_run(logs: Mapping[str, object], reference: Callable[[Array], Array], u_max: float,
                     eps: Optional[float] = None, labels: Optional[Mapping[str, str]] = None,
                     t_max: Optional[float] = None, title: Optional[str] = None):
    """One scenario, every method: the position against the reference, and the true input ``u(t)``.

    Parameters
    ----------
    logs
        ``{method: SimLog}`` of the same scenario.
    reference
        ``t -> z_ref(t)``; its first component is drawn in grey.
    u_max, eps
        The bounds ``+-u_max`` (and ``+-u_max^eps``) drawn on the input panel.
    labels
        Names of the methods in the legend.
    t_max
        Only draw ``t <= t_max``.
    """
    fig, axes = new_axes(2, 1, figsize=(7.4, 5.4), sharex=True)
    ax_x, ax_u = np.ravel(axes)
    t_end = max(float(log.t[-1]) for log in logs.values())
    t_end = min(t_end, t_max) if t_max is not None else t_end
    tr = np.linspace(0.0, t_end, 400)
    ax_x.plot(tr, np.asarray(reference(tr), float)[:, 0], color=COLORS["ref"], lw=2.6, label="reference")
    for mth, log in logs.items():
        c = METHOD_COLORS.get(mth, None)
        keep = log.t <= t_end + 1e-12
        ax_x.plot(log.t[keep], log.z[keep, 0], color=c, lw=1.3, label=_label(mth, labels))
        kf = log.t_fine <= t_end + 1e-12
        ax_u.plot(log.t_fine[kf], log.u_fine[kf, 0], color=c, lw=1.0)
        ks = keep[:-1][: len(log.u)]
        ax_u.plot(log.t[:-1][ks], log.u[ks, 0], ".", color=c, ms=3)
    bound_lines(ax_u, u_max, eps)
    ax_x.set_ylabel(log.system.state_names[0] if log.system.state_names else "z1")
    ax_u.set_ylabel("true input u")
    ax_u.set_xlabel("t [s]  (dots: sampling instants, lines: between them)")
    ax_x.legend(loc="upper center", bbox_to_anchor=(0.5, 1.32), ncol=3)
    ax_u.legend(loc="upper right", ncol=2, fontsize=7.5)
    if title:
        fig.suptitle(title)
    return fig


def plot_monte_carlo(rows: Sequence[dict], methods: Sequence[str], u_max: float,
                     labels: Optional[Mapping[str, str]] = None, title: Optional[str] = None):
    """The Monte Carlo in four panels, one column per method (or variant: same colour, hatched bar).

    ``methods`` are the ``method`` keys of the rows (:func:`flnotes.studies.compare.run_scenario`).
    (a) largest true ``|u|`` per run at the samples (filled) and between them (hollow), against
    ``u_max``; (b) fraction of steps whose plan violates the true bound at a later predicted step;
    (c) tracking cost relative to the MIQP on the same scenario (the rows' ``cost_vs_miqp``: runs
    that both completed); (d) per-step wall time (median and maximum of each run), log scale.
    """
    fig, axes = new_axes(2, 2, figsize=(9.0 if len(methods) <= 5 else 11.0, 6.8))
    (a, b), (c, d) = axes
    pos = np.arange(len(methods))
    rng = np.random.default_rng(0)  # horizontal jitter of the dots, drawing only
    ratios: list = []
    for i, mth in enumerate(methods):
        rr = [r for r in rows if r["method"] == mth]
        col = _color(mth)
        jit = rng.uniform(-0.15, 0.15, len(rr))
        a.plot(i + jit - 0.18, [r["max_abs_u_samples"] for r in rr], "o", color=col, ms=3.5)
        a.plot(i + jit + 0.18, [r["max_abs_u_between"] for r in rr], "o", mfc="none", color=col, ms=3.5)
        frac = float(np.mean([r["plan_violation_fraction"] for r in rr if np.isfinite(r["plan_violation_fraction"])]
                             or [0.0]))
        b.bar(i, frac, color=col, hatch=None if _own(mth) else "//", edgecolor="white" if _own(mth) else "0.2")
        b.text(i, frac, f"{frac:.2f}", ha="center", va="bottom", fontsize=8)
        ratio = [r["cost_vs_miqp"] for r in rr if np.isfinite(r["cost_vs_miqp"])]
        ratios += ratio
        if ratio:
            c.boxplot(ratio, positions=[i], widths=0.5, showfliers=True,
                      medianprops=dict(color=col), boxprops=dict(color=col), whiskerprops=dict(color=col),
                      capprops=dict(color=col), flierprops=dict(markeredgecolor=col, markersize=3))
        med = np.array([r["ms_median"] for r in rr], float)
        mx = np.array([r["ms_max"] for r in rr], float)
        d.plot(i + jit - 0.15, med, "o", color=col, ms=3.5)
        d.plot(i + jit + 0.15, mx, "^", mfc="none", color=col, ms=4)
    a.axhline(u_max, color=COLORS["u_max"], ls="--", lw=1, label=r"$u_{\max}$")
    a.plot([], [], "o", color="0.3", ms=3.5, label="at the samples")
    a.plot([], [], "o", mfc="none", color="0.3", ms=3.5, label="between samples")
    a.set_ylabel("largest |u| in a run")
    a.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=3, fontsize=7)
    b.set_ylabel("plans violating the true bound\n(fraction of steps, mean over runs)")
    b.set_ylim(0.0, max(0.1, 1.15 * max([p.get_height() for p in b.patches] or [0.0])))
    c.axhline(1.0, color="0.5", lw=0.8)
    if ratios and max(ratios) / max(min(ratios), 1e-12) > 20:
        c.set_yscale("log")
    c.set_ylabel("tracking cost / MIQP's")
    d.set_yscale("log")
    d.plot([], [], "o", color="0.3", ms=3.5, label="median per run")
    d.plot([], [], "^", mfc="none", color="0.3", ms=4, label="max per run")
    d.set_ylabel("wall time per step [ms]")
    d.legend(loc="upper right", fontsize=7.5)
    names = [_label(m, labels) for m in methods]
    for ax, tag in ((a, "(a)"), (b, "(b)"), (c, "(c)"), (d, "(d)")):
        ax.set_xticks(pos)
        ax.set_xticklabels(names, rotation=25, ha="right", fontsize=8)
        ax.set_xlim(-0.6, len(methods) - 0.4)
        ax.set_title(tag, loc="left")
    if title:
        fig.suptitle(title)
    return fig
