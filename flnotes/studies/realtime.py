"""Chapter 8: the MPC under a time limit in a periodic loop, and where Python's cyclic garbage collector runs.

Under ``time_limit`` :class:`flnotes.MPC` answers each step with the collector paused
(:func:`flnotes.config.no_cyclic_gc`), so a collection never starts inside a step. The collection is not gone: it
runs after the step has returned, between two answers. In a periodic loop the next step starts at the next tick or when that
pause ends, whichever is later, so a pause longer than the slack of a period still makes an answer late. This study
runs the book's closed loop (true plant) under ``time_limit = t_s``, records every collection with
:data:`gc.callbacks` (its generation, its duration, whether it started inside a step) and replays the periodic
schedule with the measured step times and the measured pauses between answers. It runs the loop as set up
and after :func:`gc.freeze` once the controller is built, which moves every object alive then out of the
collector's reach, so that a full collection walks only what the loop allocates; the pair of loops can be repeated,
interleaved, to measure how far identical loops move from run to run. Counts of objects are the same on
every machine; times are this machine's.
"""
from __future__ import annotations

import gc
import time
from typing import Callable

import numpy as np

from ..mpc import MPC
from ..simulate import simulate
from ..solvers import BOUND_TOL
from ..repeats import separation

__all__ = ["periodic_schedule", "gc_loop_row", "gc_study", "gc_numbers", "gc_clauses", "EFFECT_WORDS"]


def periodic_schedule(step_s, pause_s, t_s: float) -> np.ndarray:
    """Answer times of a periodic loop: step ``k`` starts at its tick ``k t_s`` or when the pause after answer
    ``k - 1`` ends, whichever is later, and answers ``step_s[k]`` later.

    Parameters
    ----------
    step_s
        Wall time of each step (s), shape (n,).
    pause_s
        Pause after each answer before the next step can start (s), shape (n,): here the collector's time.
    t_s
        Sampling period (s).

    Returns
    -------
    The lateness of each answer past the end of its period, ``answer_k - (k + 1) t_s`` (s), shape (n,): positive
    means late.
    """
    step_s, pause_s = np.asarray(step_s, float), np.asarray(pause_s, float)
    if step_s.shape != pause_s.shape or step_s.ndim != 1:
        raise ValueError(f"step_s and pause_s must be 1-D of one length, got {step_s.shape} and {pause_s.shape}")
    if not t_s > 0:
        raise ValueError(f"t_s must be positive, got {t_s}")
    late = np.empty_like(step_s)
    free = 0.0  # when the loop can start the next step
    for k, (s, p) in enumerate(zip(step_s, pause_s)):
        answer = max(k * t_s, free) + s
        late[k] = answer - (k + 1) * t_s
        free = answer + p
    return late


class _Watched:
    """An :class:`flnotes.MPC` for :func:`flnotes.simulate` that timestamps each step and each collection."""

    def __init__(self, mpc: MPC):
        self.mpc, self.in_step = mpc, False
        self.steps: list[tuple[float, float]] = []  # (start, answer), perf_counter
        self.collections: list[dict] = []
        self._start, self._inside = 0.0, False

    def reset(self) -> None:
        self.mpc.reset()

    def step(self, z, t, reference=None):
        t0 = time.perf_counter()
        self.in_step = True
        try:
            res = self.mpc.step(z, t, reference)
        finally:
            self.in_step = False
        self.steps.append((t0, time.perf_counter()))
        return res

    def callback(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._start = time.perf_counter()
            self._inside = self.in_step
        else:
            self.collections.append(dict(generation=int(info["generation"]), start=self._start,
                                         seconds=time.perf_counter() - self._start, in_step=self._inside))


def _full_collection() -> tuple[int, float]:
    """The objects a full collection walks now (every tracked object not frozen) and the time it takes (s)."""
    n = len(gc.get_objects())
    t0 = time.perf_counter()
    gc.collect()
    return n, time.perf_counter() - t0


def gc_loop_row(make_mpc: Callable[[], MPC], setup: dict, t_final: float, freeze: bool) -> dict:
    """One closed loop under the MPC's time limit, every collection recorded; ``freeze``: :func:`gc.freeze` once
    the controller is built (undone before returning).

    Returns a row: steps, limit hits, answers late by their own step time (``late_step``: the time from the call to
    the return of :meth:`flnotes.MPC.step`), answers late in the periodic schedule (:func:`periodic_schedule` with
    the collector's pauses between two steps: ``late_periodic``), the collections that started inside a step
    (``gc_in_step``: none is expected, the collector is paused from before the step allocates anything to its last
    action) and between two steps (``gc_between``), of them full ones (generation 2: ``full``), the longest
    collection (``gc_max_ms``), the objects a full collection walks at the end of the loop and its time then
    (``walked``, ``full_ms``), plans failing the forward-pass check, inputs neither admissible nor flagged, and
    whether the true ``|u| <= u_max`` held at the samples.
    """
    mpc = make_mpc()
    if mpc.time_limit is None:
        raise ValueError("the study needs an MPC with a time limit (time_limit=t_s): only then is the collector paused")
    t_s = float(setup["ts"])
    w = _Watched(mpc)
    was_enabled = gc.isenabled()
    gc.enable()
    try:
        if freeze:
            gc.collect()
            gc.freeze()
        gc.callbacks.append(w.callback)
        try:
            log = simulate(setup["system"], w, t_final=t_final, ts=t_s, z0=setup["z0"], reference=setup["reference"],
                           progress=False)
        finally:
            gc.callbacks.remove(w.callback)
        walked, full_s = _full_collection()
    finally:
        if freeze:
            gc.unfreeze()
        if not was_enabled:
            gc.disable()
    starts, answers = np.array(w.steps).T
    pause = np.zeros(len(starts))  # collector time after step k returned, before step k + 1 started
    between = [c for c in w.collections if not c["in_step"]]
    for c in between:
        k = int(np.searchsorted(answers, c["start"])) - 1
        if 0 <= k < len(pause):
            pause[k] += c["seconds"]
    late = periodic_schedule(answers - starts, pause, t_s)
    h = mpc.history
    plans_bad = sum(not mpc.pred.feasible(s.z_pred[0], s.v_pred) for s in h)
    inputs_bad = sum(not (s.input_admissible is False or np.all(np.abs(mpc.net(np.r_[s.z_pred[0], s.v]))
                                                                 <= mpc.u_eps + BOUND_TOL)) for s in h)
    return dict(run="gc.freeze() after set-up" if freeze else "as set up", steps=len(h),
                limit_hits=int(sum(s.status == "time_limit" for s in h)),
                late_step=int(np.sum(answers - starts > t_s)), late_periodic=int(np.sum(late > 0)),
                step_max_ms=1e3 * float(np.max(answers - starts)),
                gc_in_step=sum(c["in_step"] for c in w.collections), gc_between=len(between),
                full=sum(c["generation"] == 2 for c in w.collections),
                gc_max_ms=1e3 * max((c["seconds"] for c in w.collections), default=0.0),
                walked=int(walked), full_ms=1e3 * full_s,
                plans_not_admissible=int(plans_bad), inputs_not_admissible=int(inputs_bad),
                u_within=bool(log.summary()["u_within_bound_at_samples"]))


def gc_study(setup: dict, t_final: float, time_limit: float | None = None, repeats: int = 1) -> list[dict]:
    """:func:`gc_loop_row` for the book's closed loop (``setup`` as :func:`flnotes.bench.mpc.quad_setup`), with
    ``time_limit`` (default ``t_s``), as set up and after :func:`gc.freeze`.

    The pair of loops is run ``repeats`` times, interleaved (as set up, frozen, as set up, ...), so that the spread
    of the timing-dependent counts between identical loops is measured next to the difference between the two
    settings. Returns ``2 * repeats`` rows, each with its ``repeat`` number.
    """
    if int(repeats) != repeats or repeats < 1:
        raise ValueError(f"repeats must be a positive integer, got {repeats!r}")
    limit = float(setup["ts"]) if time_limit is None else float(time_limit)

    def make() -> MPC:
        return MPC(setup["system"], setup["net"], setup["eps"], horizon=setup["N"], ts=setup["ts"], Q=setup["Q"],
                   R=setup["R"], time_limit=limit)

    return [dict(repeat=i, **gc_loop_row(make, setup, t_final, freeze=f)) for i in range(int(repeats))
            for f in (False, True)]


#: How :func:`gc_numbers` words the frozen loops' count against the loops as set up, over the repeats
#: (keyed by :func:`flnotes.repeats.separation`).
EFFECT_WORDS = {"lower": "lower after the freeze in every repeat", "higher": "higher after the freeze in every repeat",
                "overlapping": "overlapping ranges: no difference shown"}


def gc_numbers(rows) -> dict:
    """The figures chapter 8 quotes from :func:`gc_study` (``plain``: as set up, ``frozen``: after the freeze).

    ``{name}_{key}`` is the first repeat's value; for the timing-dependent counts (limit hits, late answers) and
    the slowest step, ``{name}_{key}_min`` and ``_max`` span the repeats, and ``{key}_effect`` words the frozen
    range against the plain one (:data:`EFFECT_WORDS`: a direction only when the ranges do not overlap).
    """
    plain, frozen = rows[0::2], rows[1::2]
    if len(rows) < 2 or len(plain) != len(frozen) or any(
            p["run"] != "as set up" or f["run"] != "gc.freeze() after set-up" for p, f in zip(plain, frozen)):
        raise ValueError("gc_numbers needs the rows of gc_study: pairs of a loop as set up and one after gc.freeze()")
    out = {"repeats": len(plain)}
    for name, rs in (("plain", plain), ("frozen", frozen)):
        for key in ("steps", "limit_hits", "late_step", "late_periodic", "step_max_ms", "gc_in_step", "gc_between",
                    "full", "gc_max_ms", "walked", "full_ms"):
            out[f"{name}_{key}"] = rs[0][key]
        for key in ("limit_hits", "late_step", "late_periodic", "step_max_ms"):
            out[f"{name}_{key}_min"] = min(r[key] for r in rs)
            out[f"{name}_{key}_max"] = max(r[key] for r in rs)
    for key in ("limit_hits", "late_step", "late_periodic", "step_max_ms"):
        out[f"{key}_effect"] = EFFECT_WORDS[separation([r[key] for r in plain], [r[key] for r in frozen])]
    out["walked_ratio"] = frozen[0]["walked"] / max(plain[0]["walked"], 1)
    return out


def gc_clauses(rows) -> dict:
    """The full collections of :func:`gc_study`'s loops, as chapter 8 quotes them.

    Returns
    -------
    dict
        ``plain_full_ms_min``, ``plain_full_ms_max``, ``frozen_full_ms_min``, ``frozen_full_ms_max``: the range over
        the repeats of the full collection run at the end of each loop (ms; ``plain``: as set up, ``frozen``: after
        the freeze); ``full_clause``: when no full collection fell due inside the loops as set up (column ``full``
        summed over the repeats), "no full collection fell due during the loops as set up (column full), so that
        cost did not land in them; a longer run, or one that allocates more, can meet it"; otherwise "N full
        collection(s) fell due during the loops as set up (column full), each a pause of that size between two
        answers".
    """
    from ..tables import counted

    plain, frozen = rows[0::2], rows[1::2]
    out = {}
    for name, rs in (("plain", plain), ("frozen", frozen)):
        out[f"{name}_full_ms_min"] = min(r["full_ms"] for r in rs)
        out[f"{name}_full_ms_max"] = max(r["full_ms"] for r in rs)
    n_full = sum(r["full"] for r in plain)
    out["full_clause"] = (
        "no full collection fell due during the loops as set up (column full), so that cost did not land in them; a "
        "longer run, or one that allocates more, can meet it" if n_full == 0 else
        f"{counted(n_full, 'full collection', 'full collections')} fell due during the loops as set up (column full), "
        "each a pause of that size between two answers")
    return out
