"""Benchmark: training the book's two networks (Table 1's TT column) with limited and unlimited thread pools.

Each network is trained with :data:`flnotes.paper.NET_SETTINGS` several times,
alternating ``threads=1`` (the default of :func:`flnotes.fit_relu`) and
``threads=None`` (the BLAS library's own default, all cores), so that both
see the same machine load; the table gives min/median/max wall-clock and CPU
seconds and the ratio of the two pair by pair. The paper's MATLAB times are
in rows of their own. The target: each network in at most 30 s on two cores.
"""
from __future__ import annotations

import time

import numpy as np

from .. import paper
from ..network import fit_relu
from ..reference import load_reference, weights_sha256


def run(fast: bool = False) -> dict:
    """Time the training of MSD and Quad-1D; returns the section dict of :mod:`flnotes.bench`."""
    n_rep = 1 if fast else 3
    rows, notes = [], []
    for name in ("MSD", "Quad-1D"):
        sysm = paper.system(name)
        settings = dict(paper.NET_SETTINGS[name])
        if fast:
            settings["max_iter"] = 200
        shipped = weights_sha256(load_reference(name).net)
        times: dict = {1: [], None: []}
        same = []
        for _ in range(n_rep):
            for threads in (1, None):
                w, c = time.perf_counter(), time.process_time()
                net, rep = fit_relu(sysm.phi_stacked, sysm.lo, sysm.hi, **settings, threads=threads)
                times[threads].append((time.perf_counter() - w, time.process_time() - c))
                if threads == 1:
                    same.append(weights_sha256(net) == shipped)
        t1 = paper.TABLE1[name]
        rows.append(dict(system=name, source="paper", threads="MATLAB", runs=None, wall_min_s=None,
                         wall_median_s=t1["train_time_s"], wall_max_s=None, cpu_median_s=None, ratio_median=None))
        for threads in (1, None):
            wall = np.array([t[0] for t in times[threads]])
            cpu = np.array([t[1] for t in times[threads]])
            ratio = np.array([a[0] / b[0] for a, b in zip(times[None], times[1])])
            rows.append(dict(system=name, source="flnotes", threads="all (BLAS default)" if threads is None else str(threads),
                             runs=n_rep, wall_min_s=float(wall.min()), wall_median_s=float(np.median(wall)),
                             wall_max_s=float(wall.max()), cpu_median_s=float(np.median(cpu)),
                             ratio_median=float(np.median(ratio)) if threads is None else None))
        if not fast:
            notes.append(f"{name}: threads=1 reproduced the shipped weights in {sum(same)} of {len(same)} runs "
                         "(the same weights need the same BLAS kernels and thread count)")
    notes += ["ratio_median: wall time with all threads / with one thread, pair by pair (runs alternate, so both "
              "see the same load); > 1 means the thread limit pays.",
              "target: each network <= 30 s on two cores (the paper's MATLAB: 9.43 s and 2.19 s)."]
    if fast:
        notes.append("fast mode: 200 L-BFGS iterations instead of 3000")
    return dict(title="Training the book's networks (threads limited vs not)", rows=rows, notes=notes, figures=[])
