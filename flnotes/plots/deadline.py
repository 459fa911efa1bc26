"""Figures of the book: the MPC under a time limit (answer times and the optimality gaps at the limit)."""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from .._checks import as_floats, check_count, check_number
from .style import COLORS, saved, series_axes

__all__ = ["gap_histogram", "answer_times"]


#: Relative gaps down to this far below 0 are round-off (a lower bound a rounding error above the cost): drawn as 0.
GAP_ROUNDING = 1e-9


def _gaps(values, name: str) -> np.ndarray:
    """The gaps of one series without those of steps without a plan (NaN, ``+inf``); a gap below 0 by round-off
    (:data:`GAP_ROUNDING`: a lower bound a rounding error above the cost) counts as 0; a negative gap beyond it is a
    ``ValueError`` naming ``name``."""
    d = as_floats(values, name).reshape(-1)
    bad = d < -GAP_ROUNDING  # NaN compares False: a step without a plan
    if np.any(bad):
        raise ValueError(f"{name} must be gaps >= 0 ((J - J_lb) / max(1, |J|) with a lower bound J_lb <= J; NaN or "
                         f"inf for a step without a plan), got {float(d[bad][0])!r} at position "
                         f"{int(np.flatnonzero(bad)[0])}")
    d = d[np.isfinite(d)]
    return np.maximum(d, 0.0)


def _times(values, name: str) -> np.ndarray:
    """The answer times of one series: finite numbers >= 0, else ``ValueError`` naming ``name``."""
    t = as_floats(values, name).reshape(-1)
    bad = ~(np.isfinite(t) & (t >= 0))
    if np.any(bad):
        raise ValueError(f"{name} must be answer times in ms, finite numbers >= 0, got {float(t[bad][0])!r} at "
                         f"position {int(np.flatnonzero(bad)[0])}")
    return t


def gap_histogram(gaps: Mapping[str, Sequence[float]], bins: int = 20, path=None, ax=None):
    """Histogram of the relative optimality gaps of the steps that hit the time limit, one series per run.

    Parameters
    ----------
    gaps
        ``{label: gaps}``: the gap ``(J - J_lb) / max(1, |J|)`` of each step that hit the limit, where ``J``
        is the cost of the returned plan and ``J_lb`` a valid lower bound of eq. (MPC_form_miqp) (see
        :func:`flnotes.bench.deadline.limit_gaps`). A gap is a number >= 0; NaN or ``+inf`` (no admissible plan,
        no gap: what ``limit_gaps`` records) are left out. A negative gap or ``-inf`` (a bound above the cost: no
        gap of eq. (MPC_form_miqp)), a boolean or a string is a ``ValueError`` naming its series.
    bins
        Number of bins over ``[0, max gap]``.
    path
        Where to save the figure (returns the path), or ``None`` (returns the figure).
    """
    bins = check_count(bins, "bins", 1, "bins of the histogram")
    if isinstance(gaps, Mapping):  # the values are read before a figure is made (series_axes refuses the rest)
        data = {k: _gaps(v, f"gaps[{k!r}]") for k, v in gaps.items()}
    fig, ax = series_axes(gaps, "gaps", ax)
    top = max([float(d.max()) for d in data.values() if d.size] + [1e-12])
    edges = np.linspace(0.0, top * 1.0001, bins + 1)
    for i, (lab, d) in enumerate(data.items()):
        ax.hist(d, bins=edges, histtype="step", lw=1.4, color=f"C{i}", label=f"{lab} ({d.size} steps)")
    ax.set_xlabel("optimality gap at the time limit, (J - J_lb) / max(1, |J|)")
    ax.set_ylabel("steps")
    ax.legend(loc="upper right", fontsize=7.5)
    return saved(fig, path)


def answer_times(times_ms: Mapping[str, Sequence[float]], t_s_ms: float, path=None, ax=None):
    """Sorted answer times per step (one curve per run) against the time limit ``t_s``.

    Parameters
    ----------
    times_ms
        ``{label: answer time of each step in ms}``: finite numbers >= 0 (``ValueError`` naming the series
        otherwise: a negative or NaN time would vanish from the logarithmic axis).
    t_s_ms
        The time limit, drawn as a horizontal line: a finite number > 0.
    path
        Where to save the figure (returns the path), or ``None`` (returns the figure).
    """
    t_s_ms = check_number(t_s_ms, "t_s_ms", "the time limit in ms", strict=True)
    if isinstance(times_ms, Mapping):  # the values are read before a figure is made (series_axes refuses the rest)
        times_ms = {k: _times(v, f"times_ms[{k!r}]") for k, v in times_ms.items()}
    fig, ax = series_axes(times_ms, "times_ms", ax)
    for i, (lab, t) in enumerate(times_ms.items()):
        t = np.sort(t)
        ax.semilogy(100.0 * np.arange(1, t.size + 1) / max(t.size, 1), t, lw=1.2, color=f"C{i}", label=lab)
    ax.axhline(t_s_ms, color=COLORS["unsafe"], ls="--", lw=1, label=f"time limit ({t_s_ms:.0f} ms)")
    ax.set_xlabel("steps [%] (sorted)")
    ax.set_ylabel("answer time [ms]")
    ax.legend(loc="upper left", fontsize=7.5)
    return saved(fig, path)
