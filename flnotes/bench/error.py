"""Benchmark: estimating (PSO) and certifying the error bound eps of eq. (approx_err) for both systems.

Reports, per system, the time of the paper's particle swarm estimate and the
time to certify eps to a bracket width of 5 % of eps (the benchmark's target)
and to 0.1 % (the setting of :func:`flnotes.paper.paper_eps` used by the
book), with wall-clock and CPU time (the machine may be shared).
"""
from __future__ import annotations

import time


from .. import paper
from ..error import certify_error, pso_max_error


def _timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def run(fast: bool = False) -> dict:
    """Time PSO and certification for MSD and Quad-1D; returns the section dict of :mod:`flnotes.bench`."""
    rows, notes, brackets = [], [], {}
    rtols = (0.05,) if fast else (0.05, 1e-3)
    for name in ("MSD", "Quad-1D"):
        sysm = paper.system(name)
        net, rep = paper.paper_net(name)
        t1 = paper.TABLE1[name]
        rows.append(dict(system=name, source="paper", task="PSO estimate (MATLAB)", eps=t1["eps"], lower=None,
                         upper=None, width_rel=None, boxes=None, wall_s=None, cpu_s=None))
        pso, w, c = _timed(lambda: pso_max_error(sysm, net, **paper.EPS_SETTINGS["pso"]))
        rows.append(dict(system=name, source="flnotes", task=f"PSO estimate ({pso.n_evals:,} evaluations)",
                         eps=float(pso.eps[0]), lower=None, upper=None, width_rel=None, boxes=None, wall_s=w, cpu_s=c))
        for rtol in rtols:
            br, w, c = _timed(lambda: certify_error(sysm, net, rtol=rtol, seeds=pso))
            brackets[name] = br
            rows.append(dict(system=name, source="flnotes", task=f"certify to width <= {rtol:g} eps",
                             eps=float(br.upper[0]), lower=float(br.lower[0]), upper=float(br.upper[0]),
                             width_rel=float(br.width[0] / br.lower[0]), boxes=int(br.n_boxes[0]), wall_s=w, cpu_s=c))
            if not br.converged.all():
                notes.append(f"{name}: certification to {rtol:g} did not converge within its budget")
    figures = []
    try:
        import matplotlib

        matplotlib.use("Agg")
        from .. import plots
        from . import out_dir

        ax = plots.certification_progress(brackets)
        path = out_dir() / "error_certification_progress.png"
        ax.figure.savefig(path)
        figures.append(str(path))
    except Exception as exc:  # a figure must not sink the timings
        notes.append(f"figure not written: {exc}")
    notes += [
        "eps: the PSO value is a lower bound on max |Phi - Phi_NN|; certified rows give the rigorous bracket "
        "[lower, upper] and use upper as eps.",
        f"networks: the shipped references of fl.paper_net (MSD trained in {paper.paper_net('MSD')[1].time_s:.0f} s, "
        f"Quad-1D in {paper.paper_net('Quad-1D')[1].time_s:.0f} s when they were written; see the training section).",
        "wall_s and cpu_s: wall-clock and process CPU time; on a shared machine wall time can be several times the CPU time.",
    ]
    return dict(title="Error bound eps: PSO estimate and certification", rows=rows, notes=notes, figures=figures)
