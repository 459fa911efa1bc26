"""Figures of the book: time per MPC step and certified eps against the size of the network."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .style import COLORS, new_axes, saved

__all__ = ["size_plot"]


def size_plot(rows: Sequence[dict], t_s_ms: float = 100.0, path=None):
    """Per-step time (median to max, p99 marked) and certified ``eps / u_max`` against the hidden neurons.

    Parameters
    ----------
    rows
        Rows of :func:`flnotes.studies.size.size_rows` (``system``, ``network``, ``depth``, ``hidden``, ``N_p``,
        ``median ms``, ``p99 ms``, ``max ms``, ``eps/u_max``).
    t_s_ms
        The sampling time, drawn as a horizontal line on the time panel.
    path
        Where to save the figure (returns the path), or ``None`` (returns the figure).
    """
    if not rows:
        raise ValueError("rows must hold at least one row of flnotes.studies.size.size_rows")
    fig, axes = new_axes(1, 2, figsize=(10.0, 3.8))
    ax_t, ax_e = axes[0]
    series = sorted({(r["system"], r["N_p"]) for r in rows})
    markers = {2: "o", 3: "s", 4: "^"}
    for i, (s, N) in enumerate(series):
        rs = sorted((r for r in rows if r["system"] == s and r["N_p"] == N), key=lambda r: r["hidden"])
        x = np.array([r["hidden"] for r in rs], float) * (1.0 + 0.03 * (i - (len(series) - 1) / 2))
        med, p99, mx = (np.array([r[k] for r in rs], float) for k in ("median ms", "p99 ms", "max ms"))
        ax_t.vlines(x, med, mx, color=f"C{i}", lw=1.0, alpha=0.7)
        for r, xi, m in zip(rs, x, med):
            ax_t.plot(xi, m, markers.get(r["depth"], "o"), color=f"C{i}", ms=4, mfc="white")
        ax_t.plot(x, p99, "_", color=f"C{i}", ms=9, mew=2, label=f"{s}, N_p = {N}")
    ax_t.axhline(t_s_ms, color=COLORS["unsafe"], ls="--", lw=1, label=f"t_s = {t_s_ms:.0f} ms")
    ax_t.set_xscale("log")
    ax_t.set_yscale("log")
    ax_t.set_xlabel("hidden neurons")
    ax_t.set_ylabel("time per step [ms] (median o, p99 -, max)")
    ax_t.legend(fontsize=7.5, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3)
    color = {s: f"C{i}" for i, (s, N) in reversed(list(enumerate(series)))}   # each system's first series colour
    for s in sorted({r["system"] for r in rows}):
        for r in {r["network"]: r for r in rows if r["system"] == s}.values():     # one point per network
            ax_e.plot(r["hidden"], r["eps/u_max"], markers.get(r["depth"], "o"), color=color[s], ms=5)
            ax_e.annotate(r["network"], (r["hidden"], r["eps/u_max"]), fontsize=6.5, xytext=(3, 2),
                          textcoords="offset points")
        ax_e.plot([], [], "o", color=color[s], label=s)
    ax_e.set_xscale("log")
    ax_e.set_ylim(bottom=0.0)
    hidden = sorted({int(r["hidden"]) for r in rows})
    for ax in (ax_t, ax_e):
        ax.set_xticks(hidden, [str(h) for h in hidden])
        ax.minorticks_off()
    ax_e.set_xlabel("hidden neurons")
    ax_e.set_ylabel("certified eps / u_max")
    ax_e.legend(fontsize=7.5, title="o depth 2, s 3, ^ 4", title_fontsize=7)
    return saved(fig, path)
