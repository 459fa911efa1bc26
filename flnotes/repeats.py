"""Reading repeated measurements of the same work: how far runs of one setting differ, and whether two settings
differ by more than that.

Timings on a shared machine move from run to run. A comparison of two settings is read against that movement,
never from one run each:

- :func:`spread`: the run-to-run spread ``max / min - 1`` of repeated runs of the same work;
- :func:`against_spread`: the times of two settings within that spread, at its edge (up to twice it) or beyond
  it (more than twice);
- :func:`separation`: the values of repeated runs of two settings, ``"lower"`` / ``"higher"`` only when the two
  ranges do not overlap.

The verdicts are words about one machine's runs, for prose next to the table they come from; a book cell glues them
and asserts nothing that depends on them.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = ["spread", "against_spread", "separation", "VERDICTS"]


def spread(times: Sequence[float]) -> float:
    """The run-to-run spread of repeated measurements of the same work: ``max / min - 1`` (0.1 for 10 %).

    ``times`` are two or more positive times (any unit) of runs that did the same work, e.g. the same controller on
    the same states; :func:`against_spread` reads a comparison of two settings against it.
    """
    t = np.asarray(times, float).ravel()
    if t.size < 2 or not np.all(np.isfinite(t) & (t > 0)):
        raise ValueError(f"spread needs at least two positive finite times of the same work, got {t.tolist()}")
    return float(t.max() / t.min() - 1.0)


#: The three verdicts of :func:`against_spread`, in order of the difference they describe.
VERDICTS = ("within the run-to-run spread", "at the edge of the run-to-run spread", "beyond the run-to-run spread")


def against_spread(a: float, b: float, spread_: float) -> str:
    """A verdict on the times ``a`` and ``b`` of two settings against a run-to-run spread ``spread_`` of
    :func:`spread`, with ``d = max(a, b) / min(a, b) - 1``:

    - ``"within the run-to-run spread"`` when ``d <= spread_``: not a measured difference on this machine;
    - ``"at the edge of the run-to-run spread"`` when ``spread_ < d <= 2 spread_``: a spread estimated from a few
      pairs of identical runs is itself rough, so a difference up to twice it is weak evidence;
    - ``"beyond the run-to-run spread"`` when ``d > 2 spread_``.

    The verdict is a phrase for prose that must read with each of the three (:data:`VERDICTS`), e.g. "the ratio is
    {verdict}" or "1.6 s, {verdict} of the CPU time in all".
    """
    if not (np.isfinite(spread_) and spread_ >= 0):
        raise ValueError(f"against_spread needs a spread >= 0, got {spread_}")
    d = spread((a, b))
    return VERDICTS[0] if d <= spread_ else VERDICTS[1] if d <= 2 * spread_ else VERDICTS[2]


def separation(a: Sequence[float], b: Sequence[float]) -> str:
    """How the values ``b`` of repeated runs stand against the values ``a``: ``"lower"`` if every ``b`` is below
    every ``a``, ``"higher"`` if every ``b`` is above every ``a``, else ``"overlapping"`` (no direction shown)."""
    a, b = np.asarray(a, float).reshape(-1), np.asarray(b, float).reshape(-1)
    if a.size == 0 or b.size == 0:
        raise ValueError("separation needs at least one value on each side")
    return "lower" if b.max() < a.min() else "higher" if b.min() > a.max() else "overlapping"
