"""Benchmark: parallel certification and Monte Carlo, 2 workers against 1, and a scaling model on paper.

Measured side by side in one run, after the workers are started and have imported the package
(their start-up is reported apart):

* the certification of ``eps`` (:func:`flnotes.certify_error`) on 1 worker (in process), on 2
  local joblib processes and on a 2-worker Dask ``LocalCluster`` (loopback only), with the same
  schedule, hence the same bracket (checked);
* chapter 11's Monte Carlo (:func:`flnotes.studies.compare.monte_carlo`) the same way, without a
  time limit on the steps (with one, a plan depends on how fast the machine answered), the table
  but its timing columns checked equal.

Then the scaling model (:func:`scaling_model`): the wall time of the two-link arm's certification
and of a 4-D system's (Quad-1D, ``n_z + m = 4``) on 8, 32 and 128 workers, from the per-box times
measured here (box evaluation, which runs in the tasks, and the serial part around it), the number
of boxes of their shipped certifications, and the per-task overhead of the engine measured here.
"""
from __future__ import annotations

import math
import os
import time
from typing import Optional, Sequence

import numpy as np

from .. import paper
from .._checks import check_int, check_number
from ..arm import arm_net, two_link_arm
from ..config import MALLOC_SETTINGS, keep_freed_memory
from ..error import MIN_CHUNK, certify_error, chunk_sizes
from ..parallel import Executor, measure_overhead, measure_round_trip
from ..reference import load_reference

WORKERS_MODEL = (1, 2, 8, 32, 128)
#: Levels of bisection per task in the benchmark's deep schedule (``certify_error(depth=DEPTH)``), beside the default 1.
DEPTH = 16


def scaling_model(n_boxes: int, t_box: float, t_serial_box: float, overhead: float,
                  workers: Sequence[int] = WORKERS_MODEL, batch: int = 4096, chunk: int = 1024,
                  scale_batch: bool = False, depth: int = 1, round_trip: float = 0.0,
                  first_boxes: Optional[int] = None, rounds: Optional[int] = None) -> list[dict]:
    """Predicted wall time of a certification of ``n_boxes`` boxes on ``W`` workers.

    Each branch-and-bound round bisects ``batch`` boxes, i.e. evaluates ``2 batch`` boxes in
    ``k = ceil(2 batch / chunk)`` chunks (rounded up to an even number, :func:`flnotes.error.chunk_sizes`) of
    ``c = 2 batch / k`` boxes, sent as ``min(k, W)`` tasks of consecutive chunks; a round takes

        ``2 batch t_serial_box + ceil(k / W) c t_box + o(W, k)``,
        ``o(W, k) = round_trip + max(min(k, W) - 2, 0) overhead``   (``o = 0`` for W = 1)

    (the serial part: bracket, pruning and choice of the next boxes in the caller; the chunks, ``W``
    at a time; the engine's latency for a dependent map of two tasks, :func:`flnotes.parallel.measure_round_trip`,
    and its cost per further task in flight, :func:`flnotes.parallel.measure_overhead`). The work is
    ``n_boxes / (2 batch)`` rounds' worth; every full round pays ``o(W, k)``, the last partial one ``o`` of its
    tasks, and the rounds that grow from the first partition's ``first_boxes`` boxes to ``2 batch`` (those of at
    least ``2 MIN_CHUNK`` boxes, which leave the caller's process) pay ``round_trip`` each; ``rounds`` instead gives
    the number of rounds that pay ``o(W, k)`` (e.g. counted on a run). With the schedule fixed, no more than ``k``
    workers can be busy; with ``scale_batch=True`` the batch grows to ``W chunk / 2`` so that every worker has a
    task (another schedule: a sound bracket, not bit for bit the same, and somewhat more boxes, which the model
    does not count). Then the time tends to ``n_boxes (t_serial_box + overhead / chunk)``: the workers beyond
    ``W_half = t_box / (t_serial_box + overhead / chunk)`` cut less than the serial part they leave.

    With ``depth = d > 1`` (``certify_error(depth=d)``) a task bisects its chunk ``d - 1`` more times before it
    returns, so a round evaluates up to ``d`` times as many boxes for the same serial part and the same
    overhead: the model counts ``n_boxes / (2 batch d)`` rounds of ``d ceil(k / W) c t_box`` in the tasks, i.e.
    ``t_serial_box`` and the overheads divided by ``d`` per box (an upper estimate of the gain: pruning inside a
    task leaves its last levels with fewer boxes, those evaluate in smaller batches, and the total number of
    boxes differs somewhat).

    Returns
    -------
    list of dict
        Per ``W``: ``workers``, ``batch``, ``depth``, ``chunks_per_round``, ``tasks_per_round``, ``rounds`` (that pay
        the engine's overhead), ``wall_s``, ``speedup`` (against W = 1 with the given ``batch``), ``W_half``.
    """
    for v, name in ((n_boxes, "n_boxes"), (batch, "batch"), (chunk, "chunk"), (depth, "depth"),
                    *((w, "every entry of workers") for w in workers)):
        check_int(v, name, 1, "a count")
    for v, name in ((t_box, "t_box"), (t_serial_box, "t_serial_box"), (overhead, "overhead"), (round_trip, "round_trip")):
        check_number(v, name, "seconds")
    from ..error import MIN_CHUNK

    def o(W: int, tasks: int) -> float:
        return round_trip + max(min(tasks, W) - 2, 0) * overhead if W > 1 else 0.0

    def wall(W: int, b: int) -> tuple[float, int, int]:
        sizes = chunk_sizes(2 * b, chunk)            # the tasks of a full round, as certify_error cuts it
        k = len(sizes)
        work = n_boxes / (2 * b * depth)            # rounds' worth of work (a fraction)
        t = work * (2 * b * t_serial_box + depth * math.ceil(k / W) * max(sizes) * t_box)
        if rounds is not None:
            return t + rounds * o(W, k), k, int(rounds)
        full, frac = int(work), work - int(work)
        ramp = 0
        if first_boxes:
            n = int(first_boxes)
            while n < 2 * b:
                ramp += n >= 2 * MIN_CHUNK
                n *= 2
        t += full * o(W, k) + (o(W, math.ceil(frac * k)) if frac > 0 else 0.0) + (ramp * round_trip if W > 1 else 0.0)
        return t, k, full + (frac > 0) + ramp

    base, _, _ = wall(1, batch)
    w_half = t_box / ((t_serial_box + overhead / chunk) / depth) if (t_serial_box + overhead) > 0 else math.inf
    out = []
    for W in workers:
        b = max(batch, math.ceil(W * chunk / 2)) if scale_batch else batch
        t, k, n_rounds = wall(int(W), b)
        out.append(dict(workers=int(W), batch=b, depth=int(depth), chunks_per_round=k,
                        tasks_per_round=min(k, int(W)) if W > 1 else 0, rounds=n_rounds, wall_s=t, speedup=base / t,
                        W_half=w_half))
    return out


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def _drop_times(rows):
    """The rows without their timing columns (step wall times, steps slower than t_s): those are the machine's."""
    return [{k: v for k, v in r.items() if not (k.startswith("ms_") or k == "over_ts")} for r in rows]


def _same_rows(a, b) -> bool:
    a, b = _drop_times(a), _drop_times(b)
    if [list(r) for r in a] != [list(r) for r in b]:
        return False
    for ra, rb in zip(a, b):
        for k in ra:
            x, y = np.asarray(ra[k]), np.asarray(rb[k])
            if not (np.array_equal(x, y, equal_nan=True) if x.dtype.kind == "f" else np.array_equal(x, y)):
                return False
    return True


def _same_bracket(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("lower", "upper", "argmax", "n_boxes"))


def _per_box(name: str, budget: int) -> dict:
    """Per-box times of a certification, measured on 1 worker under a budget of boxes."""
    if name == "Arm":
        sysm, (net, _, ref) = two_link_arm(), arm_net()
        kw = dict(rtol=ref.meta["eps_settings"]["rtol"])
        shipped = ref.bracket
    else:
        sysm, (net, _) = paper.system(name), paper.paper_net(name)
        kw = dict(rtol=paper.EPS_SETTINGS["rtol"])
        shipped = load_reference(paper.shipped_name(name, paper.NET_SETTINGS[name])).bracket
    br = certify_error(sysm, net, **kw, n_samples=2000, max_boxes=budget)
    n = int(br.n_boxes.sum())
    return dict(system=name, n_in=sysm.n_in, outputs=sysm.m, boxes_measured=n,
                t_box=float(br.eval_s.sum() / n), t_serial_box=float((br.time_s - br.eval_s).sum() / n),
                n_boxes_shipped=int(np.sum(shipped["n_boxes"])), shipped_time_s=float(np.sum(shipped["time_s"])))


def _side_by_side(engines: dict, job, same, repeats: int, rows: list, notes: list, name) -> object:
    """Run ``job(engine)`` on every engine in turn, ``repeats`` rounds (alternating), keep the best wall time of each.

    Appends one row per engine to ``rows`` (``job`` named by ``name(first result)``, wall time, speed-up against the
    first engine, ``same_result``: equal to the first result by ``same``) and a note per differing result; returns
    the first result.
    """
    best, ref, differs = {}, None, set()
    for _ in range(repeats):
        for label, ex in engines.items():
            out, w = _timed(lambda: job(ex))
            best[label] = min(best.get(label, math.inf), w)
            ref = out if ref is None else ref
            if not same(out, ref):
                differs.add(label)
                notes.append(f"DIFFERENT result of {name(ref)} on {label}")
    first = engines_first(engines)
    for label in engines:
        rows.append(dict(job=name(ref), engine=label, wall_s=best[label], speedup=best[first] / best[label],
                         same_result=label not in differs))
    return ref


#: Environment variables a ``LocalCluster`` writes into this process's ``os.environ`` (distributed's
#: ``nanny.pre-spawn-environ``), inherited by every process started after it, the local workers too.
_ALLOC = tuple(MALLOC_SETTINGS)


def _local_cluster(LocalCluster):
    """The benchmark's 2-worker ``LocalCluster``, its workers with the allocator settings of the local workers.

    distributed starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536`` (to give memory back to the system
    sooner) and also leaves it in this process's environment, where local workers started later inherit it. With
    it, glibc returns freed memory at once and every array of a certification round is mapped anew: measured
    here, the workers then spent about two thirds of their time in the kernel and the certification on 2 local
    workers took 9 s instead of 3.4 s. The benchmark compares the engines on equal terms: every engine, this
    process too (:func:`flnotes.config.keep_freed_memory`), runs with :data:`flnotes.config.MALLOC_SETTINGS`, and
    this process's environment is left as it was. The workers' statistical profiler (Dask's dashboard feature, a
    sample of every thread's stack every 10 ms, taken under the interpreter lock) is off, as for a batch job.
    """
    import dask

    had = {k: os.environ.get(k) for k in _ALLOC}
    config = {f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in MALLOC_SETTINGS.items()}
    config["distributed.worker.profile.enabled"] = False      # no stack sampling of the task thread every 10 ms
    with dask.config.set(config):
        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address=None, silence_logs=40)
    for k, v in had.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    return cluster


def run(fast: bool = False, scheduler: Optional[str] = None) -> dict:
    """Speed-ups of certification and Monte Carlo (1 vs 2 workers, joblib and LocalCluster) and the scaling model."""
    from distributed import Client, LocalCluster

    from ..studies import compare as C

    import os

    rows, notes = [], []
    t0 = time.perf_counter()
    load0 = os.getloadavg()
    tuned = keep_freed_memory()        # the in-process engine with the allocator settings of the workers
    cluster = _local_cluster(LocalCluster)
    client = Client(cluster)
    engines = {"1 worker (in process)": Executor(workers=1), "2 joblib workers": Executor(workers=2),
               "2-worker LocalCluster": Executor(client=client)}
    try:
        startup = {}
        for label, ex in engines.items():          # start the workers and import the package in them
            _, startup[label] = _timed(lambda: ex.map(_warm, range(4 * ex.workers)))
        # ---------------------------------------------------------------- a small run of both jobs, untimed: every
        # process pays its first solves, IPOPT's start and the first box evaluations before the timings
        s = C.setting("MSD", time_limit=None)     # no time limit: the plans do not depend on the machine's timing
        warm_sc = C.draw_scenarios("MSD", 2, seed=1)
        wsys, (wnet, _) = paper.system("Quad-1D"), paper.paper_net("Quad-1D")
        for label, ex in engines.items():
            _, w = _timed(lambda: (C.monte_carlo(s, warm_sc, 0.2, client=ex),
                                   certify_error(wsys, wnet, rtol=0.2, batch=512, chunk=256, client=ex)))
            startup[label] += w
        notes.append("allocator: every engine runs with glibc's settings of flnotes.config.MALLOC_SETTINGS (freed "
                     "memory kept for reuse; the local and Dask workers from their environment at start, this "
                     "process by mallopt" + ("" if tuned else ", which failed here: the in-process row runs with "
                                             "the C library's defaults") + ")")
        notes.append("worker start-up and warm-up runs (not in the times below): "
                     + ", ".join(f"{k} {v:.1f} s" for k, v in startup.items()))
        # ---------------------------------------------------------------- certification
        cname, crtol = ("Quad-1D", 0.01) if fast else ("MSD", paper.EPS_SETTINGS["rtol"])
        sysm, (net, _) = paper.system(cname), paper.paper_net(cname)
        repeats = 1 if fast else 2
        brs = {}
        for depth in (1, DEPTH):
            brs[depth] = _side_by_side(
                engines, lambda ex, d=depth: certify_error(sysm, net, rtol=crtol, client=ex, depth=d), _same_bracket,
                repeats, rows, notes, lambda ref, d=depth: f"certify eps of {cname} to rtol {crtol:g}, depth {d} "
                                                  f"({int(ref.n_boxes.sum()):,} boxes, {len(ref.history[0])} rounds)")
        base = next(r["wall_s"] for r in rows if r["job"].startswith("certify") and ", depth 1 " in r["job"])
        for r in rows:
            if r["job"].startswith("certify"):         # against the default schedule on 1 worker, too
                r["vs_depth_1_on_1"] = base / r["wall_s"]
        notes.append(_amdahl_note(brs[1]))
        notes.append(f"depth {DEPTH} against depth 1 (certify_error(depth=...), each task bisects its chunk {DEPTH - 1} "
                     f"more times): bracket [{brs[DEPTH].lower[0]:.8g}, {brs[DEPTH].upper[0]:.8g}] against "
                     f"[{brs[1].lower[0]:.8g}, {brs[1].upper[0]:.8g}], {int(brs[DEPTH].n_boxes.sum()):,} boxes against "
                     f"{int(brs[1].n_boxes.sum()):,}, {len(brs[DEPTH].history[0])} dependent rounds against "
                     f"{len(brs[1].history[0])}: each round pays the engine's round trip once per busy worker. speedup "
                     "is against the same depth on 1 worker, vs_depth_1_on_1 against the default depth 1 on 1 worker "
                     "(deeper tasks evaluate their last levels in smaller batches, and the order of bisection "
                     "changes the number of boxes)")
        # ---------------------------------------------------------------- Monte Carlo
        n_sc, t_final = (2, 0.6) if fast else (8, 2.0)
        scenarios = C.draw_scenarios("MSD", n_sc, seed=0)
        _side_by_side(engines, lambda ex: C.monte_carlo(s, scenarios, t_final, client=ex), _same_rows, repeats,
                      rows, notes, lambda _: f"Monte Carlo MSD, {n_sc} scenarios x {len(C.METHODS)} methods, "
                                             f"{t_final:g} s, no time limit")
        # ---------------------------------------------------------------- scaling model
        overhead, trip = {}, {}
        for label, ex in engines.items():
            if not label.startswith("1 "):
                overhead[label], trip[label] = measure_overhead(ex, 40 if fast else 400), measure_round_trip(ex)
        if scheduler is not None:
            with Executor(client=scheduler) as ex:
                label = f"Dask at {scheduler}"
                overhead[label], trip[label] = measure_overhead(ex, 40 if fast else 400), measure_round_trip(ex)
        notes.append("engine costs (trivial tasks): per task with all workers busy (throughput) "
                     + ", ".join(f"{k} {1e3 * v:.2f} ms" for k, v in overhead.items())
                     + "; a dependent map of one task per worker (the latency every round pays) "
                     + ", ".join(f"{k} {1e3 * v:.2f} ms" for k, v in trip.items()))
        # the model against the measured job: the same certification's per-box times and rounds, each engine's costs
        for depth, br in brs.items():
            n = int(br.n_boxes.sum())
            steps = np.diff(np.r_[0, br.history[0][:, 0]])
            paying = int(np.sum(steps >= 2 * MIN_CHUNK))        # rounds whose boxes left the caller's process
            for label in overhead:
                if label not in engines:
                    continue
                r = scaling_model(n, float(br.eval_s.sum()) / n, float((br.time_s - br.eval_s).sum()) / n,
                                  overhead[label], workers=(1, 2), depth=depth, round_trip=trip[label],
                                  rounds=paying)[1]
                measured = next(x["speedup"] for x in rows if x["job"].startswith("certify")
                                and f", depth {depth} " in x["job"] and x["engine"] == label)
                rows.append(dict(job=f"model check: certify {cname}, depth {depth} ({paying} rounds leave the process)",
                                 engine=label, wall_s=r["wall_s"], speedup=r["speedup"], measured_speedup=measured))
        o, rt = max(overhead.values()), max(trip.values())
        for name in ("Arm", "Quad-1D"):
            pb = _per_box(name, 10_000 if fast else 100_000)
            notes.append(f"{name} ({pb['n_in']}-D box, {pb['outputs']} output(s)): per box {1e6 * pb['t_box']:.1f} us "
                         f"evaluating (tasks) and {1e6 * pb['t_serial_box']:.1f} us serial, measured on "
                         f"{pb['boxes_measured']:,} boxes; the shipped certification took {pb['n_boxes_shipped']:,} boxes "
                         f"({pb['shipped_time_s']:.3g} s when it was written, on another machine or load)")
            for scale, depth in ((False, 1), (True, 1), (False, DEPTH), (True, DEPTH)):
                for r in scaling_model(pb["n_boxes_shipped"], pb["t_box"], pb["t_serial_box"], o, scale_batch=scale,
                                       depth=depth, round_trip=rt, first_boxes=4 ** pb["n_in"]):
                    rows.append(dict(job=f"model: certify {name} ({pb['n_boxes_shipped']:,} boxes)",
                                     engine=f"{r['workers']} worker{'s' if r['workers'] > 1 else ''}, batch {r['batch']}"
                                            + (" (scaled)" if scale else " (fixed)") + f", depth {depth}",
                                     wall_s=r["wall_s"], speedup=r["speedup"], same_result=r["batch"] == 4096,
                                     W_half=r["W_half"]))
    finally:
        client.close()
        cluster.close()
    load1 = os.getloadavg()
    notes += [
        f"machine load (1-minute load average, {os.cpu_count()} cores): {load0[0]:.1f} at the start, {load1[0]:.1f} "
        f"at the end; with more runnable processes than cores the workers share the cores with other work and "
        f"the speed-ups below say little about the code.",
        f"measured in {time.perf_counter() - t0:.0f} s; wall_s of the measured rows is the best of {repeats} "
        "alternating runs. On a loaded machine the speed-ups are lower than on an idle one: rerun this "
        "section alone (python -m flnotes.bench parallel) on an idle machine for the target (>= 1.7 on 2 cores).",
        "same_result: the bracket (lower, upper, argmax, boxes) or the Monte Carlo table (all but its timing "
        "columns) is identical to the first engine's; model rows: whether the batch is the default 4096 (then "
        "the bracket is the same bit for bit as on 1 worker with that depth).",
        "model: per round, 2 batch boxes of serial work, ceil(k/W) chunks of chunk = 1024 boxes one after the other "
        "on each worker, the engine's round-trip latency plus its per-task cost for each task beyond two (the largest "
        "measured); the rounds that grow from the first partition (4 slices per axis) pay the latency too. The model "
        "check rows put the measured job's own per-box times, rounds and each engine's costs in the model, next to the "
        "speed-up measured above: how far the model is from a measurement (it leaves out the data a task sends and "
        "receives, and counts the first rounds, evaluated in the caller's process, as shared by the workers). The "
        "scaled rows reuse the shipped certification's box count, though their larger batch evaluates somewhat more "
        "boxes, and the depth rows' gain is an upper estimate (pruning inside a task leaves its last levels smaller "
        "and slower per box). Fixed: batch 4096, k = 8 chunks, so no gain "
        "beyond 8 workers; scaled: batch = W chunk / 2. W_half = t_box / (t_serial_box + overhead / chunk): beyond "
        "it the serial part and the scheduler's overhead dominate and more workers stop paying. Depth d: d levels of "
        f"bisection per task, the serial part and the overhead per box divided by d (depth {DEPTH} rows).",
    ]
    return dict(title="Parallel runs: certification and Monte Carlo on 2 workers, scaling model", rows=rows,
                notes=notes, figures=[])


def _amdahl_note(br) -> str:
    """The serial fraction of a certification run on 1 worker and the speed-up it leaves to 2 workers (Amdahl).

    Serial: the time outside the box evaluations (``time_s - eval_s``) and the rounds evaluated whole in the caller
    (fewer than ``2 MIN_CHUNK`` boxes); the other rounds' chunks (:func:`flnotes.error.chunk_sizes`) are shared by
    2 workers, a round taking as long as its busier worker (time per box taken as constant).
    """
    total, ser = float(np.sum(br.time_s)), float(np.sum(br.time_s - br.eval_s))
    boxes = np.concatenate([np.diff(np.r_[0, h[:, 0]]) for h in br.history]).astype(int)
    ev = total - ser
    busy = 0.0
    for n in boxes:
        sizes = chunk_sizes(int(n), 1024)
        loads = [0, 0]
        for c in sizes:
            loads[loads.index(min(loads))] += c
        busy += n if len(sizes) <= 1 else max(loads)
    whole = float(sum(n for n in boxes if len(chunk_sizes(int(n), 1024)) <= 1))
    f = (ser + ev * whole / boxes.sum()) / total                 # serial fraction
    par = ev * (busy - whole) / boxes.sum() / total               # the parallel rounds, as 2 workers share them
    return (f"certification on 1 worker: serial fraction {f:.3f} (bracket, pruning and choice of boxes "
            f"{ser / total:.3f}, rounds evaluated whole in process {ev * whole / boxes.sum() / total:.3f}); "
            f"Amdahl bound of 2 workers, with the chunks as cut: {1.0 / (f + par):.2f} (no engine overhead counted)")


def engines_first(engines: dict) -> str:
    return next(iter(engines))


def _warm(k: int) -> int:
    """Import, in a worker, what the timed tasks use (the package, its solvers, CasADi), once, before the timings."""
    import casadi  # noqa: F401
    import daqp  # noqa: F401
    import highspy  # noqa: F401
    import pyscipopt  # noqa: F401

    import flnotes  # noqa: F401
    from flnotes.studies import compare  # noqa: F401

    return k
