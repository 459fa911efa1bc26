"""One look for every figure of the book."""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import matplotlib as mpl
import matplotlib.pyplot as plt

from .._checks import check_count

#: Colours used consistently: the true input, the network, bounds, references, the three controllers.
COLORS = dict(
    true="#1f4e79", nn="#d95f02", u_max="#1f77b4", u_max_eps="#2ca02c", ref="0.6",
    lcost="#7570b3", qcost="#e7298a", nominal="#66a61e", unsafe="#d62728", grid="0.85",
)


def use_book_style() -> None:
    """Matplotlib defaults for the book: readable fonts, light grid, tight layout."""
    mpl.rcParams.update({
        "figure.figsize": (7.0, 3.6), "figure.dpi": 110, "savefig.dpi": 130, "figure.autolayout": True,
        "axes.grid": True, "grid.color": COLORS["grid"], "grid.linewidth": 0.6,
        "axes.spines.top": False, "axes.spines.right": False,
        "font.size": 10, "axes.titlesize": 10.5, "legend.fontsize": 8.5, "legend.frameon": False,
        "lines.linewidth": 1.6,
    })


def new_axes(nrows: int = 1, ncols: int = 1, figsize: Optional[Sequence[float]] = None, **kw):
    """``plt.subplots`` with the book's style; returns ``(fig, axes)``."""
    nrows = check_count(nrows, "nrows", 1, "rows of axes")
    ncols = check_count(ncols, "ncols", 1, "columns of axes")
    use_book_style()
    return plt.subplots(nrows, ncols, figsize=figsize, squeeze=False if (nrows * ncols > 1) else True, **kw)


def bound_lines(ax, u_max: float, eps: Optional[float] = None, label: bool = True) -> None:
    """Draw ``±u_max`` (blue) and ``±u_max^eps = ±(u_max - eps)`` (green) as in the paper's Fig. 6."""
    for s in (1, -1):
        ax.axhline(s * u_max, color=COLORS["u_max"], ls="--", lw=1,
                   label=r"$\pm u_{\max}$" if (label and s == 1) else None)
        if eps is not None:
            ax.axhline(s * (u_max - eps), color=COLORS["u_max_eps"], ls=":", lw=1.2,
                       label=r"$\pm u_{\max}^{\varepsilon}$" if (label and s == 1) else None)


def saved(fig, path=None):
    """``fig`` saved to ``path`` (returns the path), or ``fig`` itself when ``path`` is ``None``."""
    if path is None:
        return fig
    path = Path(path)
    fig.savefig(path, bbox_inches="tight")
    return path


def series_axes(data, what: str, ax=None):
    """Check that ``data`` is a non-empty mapping ``{label: values}`` and return ``(fig, ax)`` for drawing it."""
    from collections.abc import Mapping

    if not isinstance(data, Mapping) or not data:
        raise ValueError(f"{what} must be a non-empty mapping {{label: sequence}}")
    if ax is None:
        return new_axes(figsize=(6.4, 3.0))
    return ax.figure, ax
