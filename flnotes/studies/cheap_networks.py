"""Chapter 8: is a network cheaper to encode a faster MPC? Architecture, regularization and seed against the work.

The MPC's mixed-integer program has one binary per unstable neuron of each encoded predicted step
(eq. MIP_general_c); a narrower network, or one trained with a weight penalty, has fewer neurons and
perhaps fewer unstable ones. But the network also sets ``eps`` of eq. (approx_err), hence the bound
``u_max^eps = u_max - eps`` of eq. (Phi_NN_ep) the program must respect: a worse fit tightens it, the
bound binds at more steps, and more steps need the branch and bound. This study measures both sides on
variants of the Quad-1D network, each trained on the book's grid with one setting changed and shipped
with its certified ``eps`` (:data:`flnotes.paper.REFERENCES`), along the book's closed loop with the
default options of :class:`flnotes.MPC`.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from .. import paper
from ..bounds import fbbt
from ..mpc import MPC, sine_reference
from ..simulate import simulate
from ..tables import time_stats

__all__ = ["VARIANTS", "variant_network", "network_rows", "network_numbers"]

#: The Quad-1D networks compared: label -> the settings changed from :data:`flnotes.paper.NET_SETTINGS`.
#: Each is a shipped reference (same weights and certified ``eps`` on every machine).
VARIANTS: dict[str, dict] = {
    "book (10, 10, 10)": {},
    "(10, 10, 10), seed 1": dict(seed=1),
    "(10, 10, 10), seed 2": dict(seed=2),
    "(10, 10, 10), L2 3e-3": dict(alpha=3e-3),
    "(8, 8, 8)": dict(widths=(8, 8, 8)),
    "(6, 6, 6)": dict(widths=(6, 6, 6)),
    "(16, 16)": dict(widths=(16, 16)),
}


def variant_network(label: str):
    """The shipped network of :data:`VARIANTS` ``[label]`` and its certified ``eps`` (the bracket's upper end)."""
    if label not in VARIANTS:
        raise ValueError(f"unknown variant {label!r}; choose one of {list(VARIANTS)}")
    ov = VARIANTS[label]
    if paper.shipped_name("Quad-1D", {**paper.NET_SETTINGS["Quad-1D"], **ov}) is None:
        raise ValueError(f"variant {label!r} has no shipped reference: add it to flnotes.paper.REFERENCES and run "
                         "make reference")
    net, _ = paper.paper_net("Quad-1D", **ov)
    return net, float(np.max(paper.paper_eps("Quad-1D", **ov).upper))


def network_rows(t_final: float, labels: Optional[Sequence[str]] = None) -> list[dict]:
    """One row per network: its size, ``eps``, and the work of the default MPC along the book's closed loop.

    The loop is Sec. IV-B's (``N_p = 10``, ``t_s = 0.1`` s, ``x_ref = 1.5 sin t``) on the true plant for
    ``t_final`` seconds. Columns: hidden neurons; neurons unstable over the domain box (FBBT: the paper's
    binaries per encoded step); certified ``eps``; steps whose screening QP already met the network's
    bound; free binaries per step (mean and max over the steps that needed the branch and bound);
    branch-and-bound nodes in all; time per step (median and max, ms); the largest true ``|u| / u_max`` at
    the samples (at most 1: checked by the chapter).
    """
    S = paper.QUAD_SETTING
    sysm = paper.system("Quad-1D")
    rows = []
    for label in (labels or list(VARIANTS)):
        net, eps = variant_network(label)
        box = fbbt(net, sysm.lo, sysm.hi)
        mpc = MPC(sysm, net, eps, horizon=S["horizon"], ts=S["ts"], Q=S["Q"], R=S["R"])
        log = simulate(sysm, mpc, t_final=t_final, ts=S["ts"], z0=S["z0"], reference=sine_reference(1.5),
                       progress=False)
        h = mpc.history
        mi = [s for s in h if not s.screened and not s.fallback]
        nb = np.array([s.n_binaries for s in mi]) if mi else np.zeros(1)
        st = time_stats([s.solve_time for s in h])
        rows.append({"network": label, "hidden": int(net.n_hidden),
                     "unstable on box": box.n_unstable, "eps": eps,
                     "steps": len(h), "screened": int(sum(s.screened for s in h)),
                     "binaries mean": float(nb.mean()), "binaries max": int(nb.max()),
                     "nodes": int(sum(s.nodes for s in h)), "median ms": st["median_ms"], "max ms": st["max_ms"],
                     "max |u|/u_max": float(np.abs(log.u).max() / sysm.u_max[0])})
    return rows


def network_numbers(rows: Sequence[dict]) -> dict:
    """What chapter 8 quotes from :func:`network_rows`, as Python numbers.

    ``rank``: Spearman's rank correlation of ``eps`` and the screened steps (ties averaged); ``seed_lo`` and
    ``seed_hi``: the range of ``eps`` over the book's network and the other seeds; ``small_<column>`` and
    ``book_<column>`` for the network with the fewest hidden neurons and the book's (the first row).
    """
    from scipy.stats import spearmanr

    eps = np.array([r["eps"] for r in rows], float)
    screened = np.array([r["screened"] for r in rows], float)
    seeds = [float(r["eps"]) for r in rows if r["network"].startswith("book") or "seed" in r["network"]]
    small = min(rows, key=lambda r: r["hidden"])
    out = dict(rank=float(spearmanr(eps, screened).statistic), seed_lo=min(seeds), seed_hi=max(seeds))
    for key, r in (("small", small), ("book", rows[0])):
        for col in ("hidden", "unstable on box", "eps", "screened", "nodes"):
            v = r[col]
            out[f"{key}_{col.replace(' ', '_')}"] = v.item() if hasattr(v, "item") else v
    return out
