"""Benchmark: the default MPC along the book's closed loop with each Quad-1D network of the study.

:func:`flnotes.studies.cheap_networks.network_rows` on the shipped variants (another seed, a weight
penalty, narrower or shallower networks): size, unstable neurons over the box, certified ``eps``, screened
steps, binaries and nodes of the branch and bound, time per step. Counts are the same on every machine; the
times are this machine's.
"""
from __future__ import annotations

from ..studies import cheap_networks as study


def run(fast: bool = False) -> dict:
    """The section dict of :mod:`flnotes.bench` (20 s closed loops; 3 s in fast mode)."""
    t_final = 3.0 if fast else 20.0
    rows = study.network_rows(t_final)
    book = rows[0]
    notes = [f"closed loop of Sec. IV-B, {t_final:g} s on the true plant, default options of fl.MPC; every row keeps "
             f"the true |u| <= u_max: {all(r['max |u|/u_max'] <= 1.0 for r in rows)}",
             f"the book's network: eps {book['eps']:.4f}, {book['screened']} of {book['steps']} steps screened, "
             f"{book['nodes']} nodes"]
    return dict(title="Networks cheaper to encode? (Quad-1D MPC, N_p = 10)", rows=rows, notes=notes, figures=[])
