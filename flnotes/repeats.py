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

from ._checks import as_floats, brief, check_number, one_number

__all__ = ["spread", "against_spread", "separation", "VERDICTS"]


def spread(times: Sequence[float]) -> float:
    """The run-to-run spread of repeated measurements of the same work: ``max / min - 1`` (0.1 for 10 %).

    ``times`` are two or more positive times (any unit) of runs that did the same work, e.g. the same controller on
    the same states; :func:`against_spread` reads a comparison of two settings against it. Anything else (a
    boolean, a string, NaN, a time <= 0) is a ``ValueError`` naming ``times``; so are times whose ratio
    ``max / min`` lies beyond the float range (e.g. ``[5e-324, 1.0]``: no runs of the same work differ that much,
    one of the times is in another unit or no time at all).
    """
    t = as_floats(times, "times").ravel()
    if t.size < 2 or not np.all(np.isfinite(t) & (t > 0)):
        raise ValueError(f"times must hold at least two positive finite times of the same work (for the spread), "
                         f"got {t.tolist()}")
    d = _ratio_minus_one(t)
    if not np.isfinite(d):
        raise ValueError(f"times must be times of the same work: max / min = {float(t.max())!r} / "
                         f"{float(t.min())!r} overflows the float range (the smallest time is next to zero), so the "
                         f"spread max / min - 1 has no value; give all times in one unit and leave out a run that "
                         f"measured no time")
    return d


def _ratio_minus_one(t: np.ndarray) -> float:
    """``max(t) / min(t) - 1`` of positive finite times, ``inf`` where the ratio overflows the float range."""
    with np.errstate(over="ignore"):
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
    {verdict}" or "1.6 s, {verdict} of the CPU time in all". A ratio ``max(a, b) / min(a, b)`` beyond the float range
    is beyond any spread. ``a`` and ``b`` must be positive finite numbers and
    ``spread_`` a single finite number >= 0, not an array of one (``ValueError`` naming the argument otherwise).
    """
    try:
        spread_ = check_number(spread_, "spread_", "a run-to-run spread of spread(), a single number, e.g. 0.1 for "
                                                   "10 %")
    except ValueError as exc:
        raise ValueError(f"against_spread needs a spread >= 0: {exc}") from None
    a = check_number(one_number(a, "a"), "a", "the time of the first setting", strict=True)
    b = check_number(one_number(b, "b"), "b", "the time of the second setting", strict=True)
    d = _ratio_minus_one(np.array([a, b]))  # inf when the ratio overflows: beyond any finite spread
    return VERDICTS[0] if d <= spread_ else VERDICTS[1] if d <= 2 * spread_ else VERDICTS[2]


def separation(a: Sequence[float], b: Sequence[float]) -> str:
    """How the values ``b`` of repeated runs stand against the values ``a``: ``"lower"`` if every ``b`` is below
    every ``a``, ``"higher"`` if every ``b`` is above every ``a``, else ``"overlapping"`` (no direction shown).
    Both must be numbers, at least one each, none NaN (``ValueError`` naming the argument otherwise)."""
    a_in, b_in = a, b
    a, b = as_floats(a, "a").reshape(-1), as_floats(b, "b").reshape(-1)
    if a.size == 0 or b.size == 0:
        raise ValueError(f"a and b must hold at least one value each (separation compares them), got {a.size} and "
                         f"{b.size} values")
    for name, x, given in (("a", a, a_in), ("b", b, b_in)):
        if np.any(np.isnan(x)):
            raise ValueError(f"{name} must be the values of runs, without NaN (leave out a run that has no value), "
                             f"got {brief(given)}")
    return "lower" if b.max() < a.min() else "higher" if b.min() > a.max() else "overlapping"
