"""Reading repeated measurements of the same work: how far runs of one setting differ, and whether two settings
differ by more than that.

Timings on a shared machine move from run to run. A comparison of two settings is read against that movement,
never from one run each:

- :func:`spread`: the run-to-run spread ``max / min - 1`` of repeated runs of the same work;
- :func:`against_spread`: the times of two settings within or beyond that spread;
- :func:`separation`: the values of repeated runs of two settings, ``"lower"`` / ``"higher"`` only when the two
  ranges do not overlap.

The verdicts are words about one machine's runs, for prose next to the table they come from; a book cell glues them
and asserts nothing that depends on them.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = ["spread", "against_spread", "separation"]


def spread(times: Sequence[float]) -> float:
    """The run-to-run spread of repeated measurements of the same work: ``max / min - 1`` (0.1 for 10 %).

    ``times`` are two or more positive times (any unit) of runs that did the same work, e.g. the same controller on
    the same states; :func:`against_spread` reads a comparison of two settings against it.
    """
    t = np.asarray(times, float).ravel()
    if t.size < 2 or not np.all(np.isfinite(t) & (t > 0)):
        raise ValueError(f"spread needs at least two positive finite times of the same work, got {t.tolist()}")
    return float(t.max() / t.min() - 1.0)


def against_spread(a: float, b: float, spread_: float) -> str:
    """A verdict on the times ``a`` and ``b`` of two settings against a run-to-run spread ``spread_`` of
    :func:`spread`: ``"within the run-to-run spread"`` when ``max / min - 1 <= spread_`` (not a measured
    difference on this machine), ``"beyond the run-to-run spread"`` otherwise."""
    if not (np.isfinite(spread_) and spread_ >= 0):
        raise ValueError(f"against_spread needs a spread >= 0, got {spread_}")
    return "within the run-to-run spread" if spread((a, b)) <= spread_ else "beyond the run-to-run spread"


def separation(a: Sequence[float], b: Sequence[float]) -> str:
    """How the values ``b`` of repeated runs stand against the values ``a``: ``"lower"`` if every ``b`` is below
    every ``a``, ``"higher"`` if every ``b`` is above every ``a``, else ``"overlapping"`` (no direction shown)."""
    a, b = np.asarray(a, float).reshape(-1), np.asarray(b, float).reshape(-1)
    if a.size == 0 or b.size == 0:
        raise ValueError("separation needs at least one value on each side")
    return "lower" if b.max() < a.min() else "higher" if b.min() > a.max() else "overlapping"
