"""Figures of the book: realtime part (per-step solve times and how they scale)."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from .style import COLORS, new_axes, saved

__all__ = ["step_times", "scaling", "lever_bars"]


def step_times(rec: dict, series: Optional[dict] = None, target_ms: float = 100.0, paper_max_ms: Optional[float] = None,
               path=None, ax=None):
    """Solve time per control step over the recorded run (log scale), with the sampling period.

    Parameters
    ----------
    rec
        A recorded run (``t`` and ``ms`` arrays, ``screened`` flags), as from
        :func:`flnotes.bench.mpc.record_run`.
    series
        Optional further ``{label: ms per step}`` on the same steps (other configurations).
    target_ms
        The sampling period drawn as a horizontal line.
    paper_max_ms
        The paper's worst step, drawn for scale.
    path
        Where to save the figure (returns the path), or ``None`` (returns the figure).
    """
    if ax is None:
        fig, ax = new_axes(figsize=(7.0, 3.2))
    else:
        fig = ax.figure
    t, ms = np.asarray(rec["t"]), np.asarray(rec["ms"])
    scr = np.asarray(rec.get("screened", np.zeros(len(t), bool)))
    ax.semilogy(t, ms, ".-", color=COLORS["nn"], lw=0.8, ms=3, label="level set (default), per step")
    if scr.any():
        ax.semilogy(t[scr], ms[scr], "o", mfc="none", color=COLORS["nominal"], ms=4, label="screened (QP was optimal)")
    for i, (lab, y) in enumerate((series or {}).items()):
        ax.semilogy(t[: len(y)], y, ".-", lw=0.8, ms=2, label=lab, color=f"C{i + 2}")
    ax.axhline(target_ms, color=COLORS["unsafe"], ls="--", lw=1, label=f"one sampling period ({target_ms:.0f} ms)")
    if paper_max_ms:
        ax.axhline(paper_max_ms, color="0.4", ls=":", lw=1, label=f"paper's worst step ({paper_max_ms:.3g} ms)")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("solve time per step [ms]")
    ax.legend(loc="upper right", fontsize=7.5)
    return saved(fig, path)


def scaling(rows_horizon: Sequence[dict], rows_width: Sequence[dict] = (), target_ms: float = 100.0, path=None):
    """Median and maximum time per step against ``N_p`` (left) and the network's width (right)."""
    ncols = 2 if rows_width else 1
    fig, axes = new_axes(1, ncols, figsize=(7.0 if ncols == 2 else 4.2, 3.0))
    axes = np.ravel(axes)
    for ax, rows, key, label in ((axes[0], rows_horizon, "N_p", r"horizon $N_p$"),
                                 *(((axes[1], rows_width, "width", r"neurons per hidden layer $\bar n$"),)
                                   if rows_width else ())):
        rows = [r for r in rows if "ms_median" in r]
        x = [r[key] for r in rows]
        ax.semilogy(x, [r["ms_median"] for r in rows], "o-", color=COLORS["nn"], label="median")
        ax.semilogy(x, [r["ms_max"] for r in rows], "s--", color=COLORS["true"], label="max")
        ax.axhline(target_ms, color=COLORS["unsafe"], ls="--", lw=1, label="sampling period")
        ax.set_xlabel(label)
        ax.set_ylabel("ms per step")
        ax.legend(fontsize=7.5)
    return saved(fig, path)


def lever_bars(rows: Sequence[dict], target_ms: float = 100.0, path=None):
    """Median and maximum time per step for each lever configuration (a row of :func:`lever_table`)."""
    rows = [r for r in rows if r.get("source") != "paper" and "ms_median" in r]
    fig, ax = new_axes(figsize=(7.0, 0.35 * len(rows) + 1.2))
    y = np.arange(len(rows))[::-1]
    ax.barh(y + 0.18, [r["ms_max"] for r in rows], height=0.36, color=COLORS["true"], label="max")
    ax.barh(y - 0.18, [r["ms_median"] for r in rows], height=0.36, color=COLORS["nn"], label="median")
    ax.set_yticks(y, [r["config"] for r in rows], fontsize=8)
    ax.set_xscale("log")
    ax.axvline(target_ms, color=COLORS["unsafe"], ls="--", lw=1, label="sampling period")
    ax.set_xlabel("ms per step")
    ax.legend(fontsize=7.5, loc="lower right")
    return saved(fig, path)
