"""Benchmark: time per MPC step against the size of the network (:mod:`flnotes.studies.size`).

For the Quad-1D and the MSD, each network of :data:`flnotes.studies.size.SIZES` (widths 10 to 40, depths 2
to 4, trained on its system with the book's settings and shipped with its certified ``eps``) runs the default
:class:`flnotes.MPC` at ``N_p = 10`` and ``20`` (``t_s = 0.1`` s) along the same seeded closed loops of
chapter 11's Monte Carlo and on the same cold states; each step is capped at 1 s (``time_limit``). Per row:
the network's size, certified ``eps`` (also as a share of ``u_max``), the binaries (``N_p`` times the neurons
unstable over the box, and the most the engine encoded at a step), how many steps were proven optimal and how
many stopped at the cap, and the time per step (median, p99, max; wall and CPU). A figure draws the times and
``eps`` against the hidden neurons, with the ``t_s`` line. Fast mode: the Quad-1D's two smallest networks at
``N_p = 10``, one short loop and two cold states. Speed is measured here, never asserted in tests.
"""
from __future__ import annotations

from ..studies import size as study

#: Per-step time limit (s): a step that reaches it answers with its incumbent and counts as a limit hit.
CAP_S = 1.0


def settings(fast: bool) -> dict:
    """The arguments of :func:`flnotes.studies.size.size_rows` in full and in fast mode."""
    if fast:
        return dict(systems=("Quad-1D",), sizes=((10, 10), (10, 10, 10)), horizons=(10,), n_loops=1, loop_steps=3,
                    n_cold=2, seed=0, time_limit=CAP_S)
    return dict(systems=study.SYSTEMS, sizes=None, horizons=(10, 20), n_loops=2, loop_steps=30, n_cold=10,
                seed=0, time_limit=CAP_S)


def run(fast: bool = False) -> dict:
    """The section dict of :mod:`flnotes.bench`: rows, notes and the figure ``size.png``."""
    from . import out_dir
    from ..plots import size_plot

    args = settings(fast)
    rows = study.size_rows(**args)
    nums = study.size_numbers(rows)
    notes = [f"default fl.MPC, t_s = {study.TS * 1e3:.0f} ms, Q, R of Sec. IV-B (Quad-1D) and chapter 11 (MSD); "
             f"{args['n_loops']} closed loop(s) of {args['loop_steps']} steps (chapter 11's Monte Carlo scenarios, "
             f"seed {args['seed']}) and {args['n_cold']} cold states per row; every step capped at "
             f"time_limit = {CAP_S:g} s ('limit': steps stopped there, answered with the incumbent)",
             "eps: the certified bracket's upper end shipped with each network (the book's EPS_SETTINGS); "
             "'binaries (box)' = N_p x neurons unstable over the box (FBBT), 'binaries max' = most encoded at a step"]
    for s in args["systems"]:
        for N in args["horizons"]:
            best, p90 = nums[f"largest within t_s, {s} N_p={N}"], nums[f"largest p90 within t_s, {s} N_p={N}"]
            notes.append(f"{s}, N_p = {N}: largest network with every step proven optimal within t_s of CPU time: "
                         f"{best or 'none'}; with the 90th percentile of CPU time per step within t_s: {p90 or 'none'}")
    hits, waited = sum(r["limit"] for r in rows), sum(r["limit, cpu < cap/2"] for r in rows)
    notes.append(f"wall time includes waiting for a shared core (this machine's load); CPU time (time.process_time) "
                 f"is what the process used, including a cut-off solve's worker thread; of the {hits} steps stopped at "
                 f"the limit, {waited} used less than half of it in CPU time (they waited for the machine more than "
                 "they computed)")
    figures = [str(size_plot(rows, t_s_ms=study.TS * 1e3, path=out_dir() / "size.png"))]
    return dict(title="Time per MPC step versus network size (Quad-1D, MSD; N_p = 10, 20)", rows=rows, notes=notes,
                figures=figures)
