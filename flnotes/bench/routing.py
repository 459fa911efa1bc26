"""Benchmark: which solver gets a program under ``backend="auto"`` (:func:`flnotes.mpc.levers.pick_backend`).

The default MPC sends a mixed-integer program of a level-set round to DAQP when it has at most
:data:`flnotes.mpc.levers.AUTO_DAQP_BINARIES` binaries (with an incumbent to warm-start from) and to SCIP above.
This section measures that threshold two ways, side by side in one process:

- *Per program.* Every mixed-integer program the engine hands to a solver along closed loops (the book's Quad-1D
  at ``N_p = 10, 15, 20``, the five systems not in the book, cold states of the MSD) and on random networks of one
  integrator is recorded with its warm start (:func:`recorded_programs`), then solved once by DAQP and once by
  SCIP, each with the warm start the engine gave it (:func:`solve_both`). The two must agree on the status and on
  the optimum within the gap. Per class of binaries, the CPU time in all of each back-end
  (:func:`class_table`), and per threshold the CPU time the rule would have spent (:func:`threshold_table`).
- *End to end.* The same closed loops run with the rule at two thresholds, interleaved (old, new, old, new) so that
  the run-to-run spread shows (:func:`loop_table`).

Speed is measured here, never asserted in tests (``tests/test_routing.py`` asserts that both back-ends agree).
"""
from __future__ import annotations

import contextlib
import time
from typing import Callable, Iterator, Optional, Sequence

import numpy as np

from ..mpc import MPC, levers
from ..mpc import engine as _engine
from ..solvers import MIQP, make_solver

Array = np.ndarray

#: Classes of binaries of :func:`class_table` (inclusive bounds).
CLASSES = ((0, 10), (11, 20), (21, 25), (26, 30), (31, 35), (36, 40), (41, 45), (46, 50), (51, 60))

#: The threshold before it was measured here: the closed loops of :func:`run` compare it with the default.
PREVIOUS_THRESHOLD = 50

#: Thresholds compared in :func:`threshold_table`.
THRESHOLDS = (20, 25, 30, 35, 40, 45, 50)


@contextlib.contextmanager
def recorded_programs(out: list, tag: str) -> Iterator[list]:
    """Inside the block, every mixed-integer program the engine of :class:`flnotes.MPC` (:mod:`flnotes.mpc.engine`)
    hands to a solver is appended to ``out`` as a dict: ``tag``, ``backend`` (the one the rule chose), ``problem`` (a
    copy of the :class:`flnotes.solvers.MIQP`), ``warm_start`` (``None`` for a round without an incumbent) and ``gap``.
    A controller built inside the block adds its warm-up solves at construction, one per back-end, without a warm
    start: the tables of this section read the warm-started programs only."""
    made = _engine.make_solver

    def recording(problem, backend="auto", **options):
        solver = made(problem, backend, **options)
        if not problem.is_mip:
            return solver
        solve = solver.solve

        def solve_and_record(warm_start=None, time_limit=None, gap=1e-6, node_limit=None):
            p = solver.problem
            out.append(dict(tag=tag, backend=backend, gap=float(gap),
                            warm_start=None if warm_start is None else np.array(warm_start, float),
                            problem=MIQP(None if p.H is None else p.H.copy(), p.c.copy(), p.c0, p.A.copy(),
                                         p.rl.copy(), p.ru.copy(), p.lb.copy(), p.ub.copy(), p.integrality.copy())))
            return solve(warm_start=warm_start, time_limit=time_limit, gap=gap, node_limit=node_limit)

        solver.solve = solve_and_record
        return solver

    _engine.make_solver = recording
    try:
        yield out
    finally:
        _engine.make_solver = made


@contextlib.contextmanager
def threshold(n_binaries: int) -> Iterator[None]:
    """Inside the block, ``backend="auto"`` sends programs of at most ``n_binaries`` binaries (with an incumbent)
    to DAQP."""
    if isinstance(n_binaries, bool) or not isinstance(n_binaries, (int, np.integer)) or n_binaries < 0:
        raise ValueError(f"the threshold is a number of binaries, an integer >= 0; got {n_binaries!r}")
    old = levers.AUTO_DAQP_BINARIES
    levers.AUTO_DAQP_BINARIES = int(n_binaries)
    try:
        yield
    finally:
        levers.AUTO_DAQP_BINARIES = old


def loop_cases(fast: bool) -> list[tuple[str, Callable[[], Array]]]:
    """The closed loops and cold states measured: ``(name, run)``, ``run()`` returning the CPU seconds per step."""
    from ..studies import unseen as U
    from . import msd_realtime as M
    from .mpc import quad_setup, record_run

    def unseen(name):
        def run():
            c = U.case(name)
            _, _, timed = U.closed_loop(name, t_final=c.t_final / 4 if fast else c.t_final)
            return np.asarray(timed.cpu, float)
        return run

    def quad(N):
        def run():
            return np.asarray(record_run(quad_setup(N), 1.0 if fast else 10.0)["cpu_ms"], float) / 1e3
        return run

    def msd_cold():
        s = M.setting()
        ctrl = M.controller(s)
        cpu = []
        for _, z, R in M.cold_states(s, 4 if fast else 24):
            ctrl.reset()
            cpu.append(M.timed(ctrl, z, R)[1])
        return np.asarray(cpu, float)

    cases = [(f"Quad-1D, N_p = {N}", quad(N)) for N in ((10,) if fast else (10, 15, 20))]
    cases += [(name, unseen(name)) for name in U.CASES]
    cases.append(("MSD, cold states", msd_cold))
    return cases


def random_loops(n_cases: int, seed: int = 0) -> None:
    """MPC steps of one integrator (order 1 or 2) with random (3-8, 3-8) networks, ``N_p = 5``, at random states,
    three per network, default options: programs of networks no one trained, for :func:`recorded_programs`."""
    from ..network import ReLUNet
    from ..systems import integrators

    rng = np.random.default_rng(seed)
    for case in range(n_cases):
        order = int(rng.integers(1, 3))
        n1, n2 = int(rng.integers(3, 9)), int(rng.integers(3, 9))
        sysm = integrators(order, lo=[-5.0] * order + [-3.0], hi=[5.0] * order + [3.0], u_max=1.0)
        W = [rng.normal(size=(n1, order + 1)) * 0.6, rng.normal(size=(n2, n1)) * 0.4, rng.normal(size=(1, n2)) * 0.8]
        net = ReLUNet(W, [rng.normal(size=n1) * 0.3, rng.normal(size=n2) * 0.3, np.array([0.5])])
        mpc = MPC(sysm, net, 0.0, horizon=5, ts=0.2, Q=[1.0] * order, R=0.1)
        for _ in range(3):
            zr = np.zeros((6, order))
            zr[:, 0] = rng.uniform(-4, 4)
            mpc(rng.uniform(-4, 4, size=order), zr)


def solve_both(programs: Sequence[dict], time_limit: Optional[float] = None, max_binaries: int = 60) -> list[dict]:
    """Each recorded program of at most ``max_binaries`` binaries solved by DAQP and by SCIP (default back-end options,
    the recorded warm start and gap), one after the other in this process: per program its tag, binaries, rows, and
    per back-end status, objective, nodes and CPU seconds (``time.process_time``). Larger programs go to SCIP under
    any threshold measured here.

    Each back-end is called as the engine calls it without a time limit (``time_limit=None``): DAQP's column is the
    whole :class:`flnotes.solvers.DaqpSolver` call, its hand-over to SCIP after
    :data:`flnotes.solvers.HANDOVER_S` and its checks of a claim that is no proof (by SCIP or HiGHS) included, which
    is what the route through DAQP costs."""
    rows = []
    for rec in programs:
        p = rec["problem"]
        if p.n_integer > max_binaries:
            continue
        row = dict(tag=rec["tag"], chosen=rec["backend"], binaries=int(p.n_integer), rows=int(p.m),
                   warm=rec["warm_start"] is not None)
        for backend in ("daqp", "scip"):
            solver = make_solver(p, backend)
            c0 = time.process_time()
            res = solver.solve(warm_start=rec["warm_start"], gap=rec["gap"], time_limit=time_limit)
            row.update({f"{backend}_cpu": time.process_time() - c0, f"{backend}_status": res.status,
                        f"{backend}_objective": float(res.objective), f"{backend}_nodes": int(res.nodes)})
        rows.append(row)
    return rows


def agree(row: dict, gap: float = 1e-6) -> bool:
    """Whether DAQP and SCIP agree on a program: the same status, and optima within ``gap`` (relative) where both
    proved one. A program either left at a time limit (``solve_both`` with one) agrees by default (nothing to
    compare)."""
    st = row["daqp_status"], row["scip_status"]
    if "time_limit" in st:
        return True
    if st[0] != st[1]:
        return False
    if st[0] != "optimal":
        return True
    a, b = row["daqp_objective"], row["scip_objective"]
    return abs(a - b) <= 2 * gap * max(1.0, abs(a), abs(b))


def class_table(rows: Sequence[dict], classes=CLASSES) -> list[dict]:
    """Per class of binaries, the warm-started programs: how many, CPU time in all of each back-end, the programs on
    which SCIP was faster, and the median of DAQP's time over SCIP's."""
    out = []
    for lo, hi in classes:
        sel = [r for r in rows if r["warm"] and lo <= r["binaries"] <= hi]
        if not sel:
            continue
        d = np.array([r["daqp_cpu"] for r in sel])
        s = np.array([r["scip_cpu"] for r in sel])
        out.append(dict(binaries=f"{lo}-{hi}", programs=len(sel), daqp_s=float(d.sum()), scip_s=float(s.sum()),
                        scip_faster=int(np.sum(s < d)), median_daqp_over_scip=float(np.median(d / s))))
    return out


def threshold_table(rows: Sequence[dict], thresholds: Sequence[int] = THRESHOLDS, at_most: int = 60) -> list[dict]:
    """Per threshold, the CPU time the rule would spend on the warm-started programs of at most ``at_most``
    binaries (DAQP's time up to the threshold, SCIP's above), per group of programs (the tag before ``:``), and the
    95th percentile and largest time of one program."""
    sel = [r for r in rows if r["warm"] and r["binaries"] <= at_most]
    groups = sorted({r["tag"].split(":")[0] for r in sel})
    out = []
    for t in thresholds:
        cost = np.array([r["daqp_cpu"] if r["binaries"] <= t else r["scip_cpu"] for r in sel])
        row = dict(threshold=int(t), default=int(t) == levers.AUTO_DAQP_BINARIES)
        for g in groups:
            row[f"{g}_s"] = float(sum(c for c, r in zip(cost, sel) if r["tag"].split(":")[0] == g))
        row.update(total_s=float(cost.sum()), p95_ms=float(np.percentile(cost, 95) * 1e3) if cost.size else np.nan,
                   max_ms=float(cost.max() * 1e3) if cost.size else np.nan)
        out.append(row)
    return out


def loop_table(cases, thresholds: tuple[int, int], repeats: int = 2) -> list[dict]:
    """Each case run at both thresholds, interleaved ``repeats`` times (old, new, old, new): CPU time in all, the
    median and the slowest step of every run."""
    out = []
    for name, run in cases:
        for k in range(repeats):
            for t in thresholds:
                with threshold(t):
                    cpu = run()
                out.append(dict(case=name, threshold=int(t), run=k + 1, steps=int(cpu.size), cpu_s=float(cpu.sum()),
                                median_ms=float(np.median(cpu) * 1e3), max_ms=float(cpu.max() * 1e3)))
    return out


def run(fast: bool) -> dict:
    programs: list = []
    for name, run_case in loop_cases(fast):
        with recorded_programs(programs, f"{name.split(',')[0]}: {name}"):
            run_case()
    with recorded_programs(programs, "random networks: integrator"):
        random_loops(4 if fast else 40)
    rows = solve_both(programs)
    bad = [r for r in rows if not agree(r)]
    notes = [f"{len(programs)} programs recorded, {len(rows)} of at most 60 binaries solved by both back-ends "
             f"({sum(r['warm'] for r in rows)} with a warm start); DAQP and SCIP "
             f"disagree on {len(bad)}" + (": " + "; ".join(f"{r['tag']} ({r['binaries']} binaries): "
                                                          f"{r['daqp_status']} {r['daqp_objective']:.9g} against "
                                                          f"{r['scip_status']} {r['scip_objective']:.9g}" for r in bad)
                                          if bad else "")]
    out_rows = [dict(kind="per class of binaries", **r) for r in class_table(rows)]
    out_rows += [dict(kind="per threshold", **r) for r in threshold_table(rows)]
    out_rows += [dict(kind="closed loops", **r) for r in loop_table(
        loop_cases(fast), (PREVIOUS_THRESHOLD, levers.AUTO_DAQP_BINARIES), repeats=1 if fast else 2)]
    notes.append(f"default threshold: {levers.AUTO_DAQP_BINARIES} binaries (with an incumbent), "
                 f"{levers.AUTO_DAQP_COLD_BINARIES} without; CPU times of this machine, one run per program")
    return dict(title="Routing programs between DAQP and SCIP (backend='auto')", rows=out_rows, notes=notes,
                figures=[])
