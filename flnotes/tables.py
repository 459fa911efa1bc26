"""The one table renderer and the one time-statistics reducer of the package.

A :class:`Table` is a list of row dicts that shows itself as HTML in a
notebook, as aligned text in a terminal and as Markdown in a benchmark report;
chapters, studies and ``make bench`` all render through it.
:func:`time_stats` reduces a sample of solve times to the figures every table
of the book quotes (min, median, percentiles, max, mean), in milliseconds;
:func:`counted` writes a glued count with its noun in the right number (reading repeated timings is
:mod:`flnotes.repeats`).
"""
from __future__ import annotations

import html
from typing import Any, Iterable, Sequence

import numpy as np

from ._checks import as_floats

Array = np.ndarray


class Table(list):
    """Rows of dicts rendered as a table (HTML in a notebook, text in a terminal, Markdown on request).

    Parameters
    ----------
    rows
        One dict per row; the columns are the keys in first-seen order.
    floatfmt
        Format of float cells (default ``".4g"``).

    Examples
    --------
    >>> Table([{"system": "MSD", "eps": 0.2053}])
    system     eps
       MSD  0.2053
    """

    def __init__(self, rows: Iterable[dict] = (), floatfmt: str = ".4g"):
        rows = list(rows)
        for i, r in enumerate(rows):
            if not isinstance(r, dict):
                raise TypeError(f"Table rows must be dicts, row {i} is {type(r).__name__}")
        super().__init__(dict(r) for r in rows)
        self.floatfmt = floatfmt

    @property
    def columns(self) -> list[str]:
        """Column names in first-seen order."""
        cols: list[str] = []
        for r in self:
            cols += [c for c in r if c not in cols]
        return cols

    @property
    def rows(self) -> list[dict]:
        """The rows (the table itself, as a plain list)."""
        return list(self)

    def cell(self, v: Any) -> str:
        """One cell as text: floats with :attr:`floatfmt`, ``None`` as ``-``, arrays comma-separated."""
        if v is None:
            return "-"
        if isinstance(v, (bool, np.bool_)):
            return str(bool(v))
        if isinstance(v, (float, np.floating)):
            return format(float(v), self.floatfmt)
        if isinstance(v, np.ndarray):
            return ", ".join(self.cell(x) for x in v.ravel())
        return str(v)

    def _repr_html_(self) -> str:
        cols = self.columns
        head = "".join(f"<th>{html.escape(str(c))}</th>" for c in cols)
        body = "".join("<tr>" + "".join(f"<td>{html.escape(self.cell(r.get(c)))}</td>" for c in cols) + "</tr>"
                       for r in self)
        return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"

    def markdown(self) -> str:
        """The table in Markdown (``make bench`` writes its results this way)."""
        cols = self.columns
        if not cols:
            return "(no rows)\n"
        lines = ["| " + " | ".join(map(str, cols)) + " |", "|" + "---|" * len(cols)]
        lines += ["| " + " | ".join(self.cell(r.get(c)) for c in cols) + " |" for r in self]
        return "\n".join(lines) + "\n"

    def __repr__(self) -> str:
        cols = self.columns
        if not cols:
            return "(no rows)"
        cells = [[str(c) for c in cols]] + [[self.cell(r.get(c)) for c in cols] for r in self]
        w = [max(len(row[i]) for row in cells) for i in range(len(cols))]
        return "\n".join("  ".join(x.rjust(wi) for x, wi in zip(row, w)) for row in cells)


def time_stats(times_s: Sequence[float], percentiles: Sequence[float] = (50, 90, 99)) -> dict:
    """Min, percentiles, max and mean of solve times, in milliseconds.

    Parameters
    ----------
    times_s
        Times in seconds; NaN entries (steps without a solve) are left out.
    percentiles
        Percentiles to report as ``p<q>_ms``; the 50th is reported as ``median_ms``.

    Returns
    -------
    dict
        ``n``, ``min_ms``, ``median_ms`` / ``p<q>_ms``, ``max_ms``, ``mean_ms``
        (all NaN when there is no time).
    """
    if isinstance(times_s, (list, tuple)):  # None: a step without a solve, like NaN
        times_s = [np.nan if x is None else x for x in times_s]
    t = as_floats(times_s, "times_s").ravel()
    if np.any(t < 0) or np.any(np.isinf(t)):
        raise ValueError(f"times_s must be times >= 0 (NaN for a step without a solve), got {t[(t < 0) | np.isinf(t)]}")
    if hasattr(percentiles, "__iter__") and not hasattr(percentiles, "__len__"):  # a generator
        percentiles = list(percentiles)
    q = as_floats(percentiles, "percentiles").reshape(-1)  # one number: one percentile
    if not np.all((q >= 0) & (q <= 100)):
        raise ValueError(f"percentiles must lie in [0, 100], got {q}")
    percentiles = q.tolist()
    t = t[np.isfinite(t)] * 1e3
    keys = ["median_ms" if q == 50 else f"p{q:g}_ms" for q in percentiles]
    if t.size == 0:
        return dict(n=0, min_ms=np.nan, **{k: np.nan for k in keys}, max_ms=np.nan, mean_ms=np.nan)
    return dict(n=int(t.size), min_ms=float(t.min()), **{k: float(np.percentile(t, q)) for k, q in zip(keys, percentiles)},
                max_ms=float(t.max()), mean_ms=float(t.mean()))


def counted(n: int, one: str, many: str) -> str:
    """A count with its noun phrase in the right number: ``counted(1, "answer came", "answers came")`` gives
    ``"1 answer came"``, ``counted(3, ...)`` ``"3 answers came"`` and ``counted(0, ...)`` ``"0 answers came"``."""
    if int(n) != n or n < 0:
        raise ValueError(f"counted needs a count (an integer >= 0), got {n}")
    return f"{int(n)} {one if int(n) == 1 else many}"
