"""A work budget per step (``fl.MPC(..., work_limit=...)``): the same state gives the same status and plan on every
run and at any machine load, because no decision of the engine reads the clock; the wall clock stays as a safety net
whose hits are recorded. Speed is measured by ``python -m flnotes.bench deadline``, never here."""
import subprocess
import sys
import time

import numpy as np
import pytest

import flnotes as fl
from flnotes.bench import mpc as rt
from flnotes.mpc import NODES_PER_SECOND
from flnotes.mpc import bang_bang, engine, fallback
from flnotes import tightening

#: A time limit that a budget of one node never reaches, even on a loaded machine: the safety net stays idle, and
#: the tests check that premise on every step.
SAFE_LIMIT = 30.0


@pytest.fixture(scope="module")
def quad():
    return rt.quad_setup(horizon=10)


@pytest.fixture(scope="module")
def quad15():
    """N_p = 15: a loop where one node is not enough at some steps (7 of 16 where this was written; at N_p = 10 SCIP
    proves every step of this loop at its root)."""
    return rt.quad_setup(horizon=15)


def loop(mpc, setup, t_final=1.6):
    """The book's closed loop (true plant, sine reference); returns (statuses, plans, messages)."""
    fl.simulate(setup["system"], mpc, t_final=t_final, ts=setup["ts"], z0=setup["z0"],
                reference=setup["reference"], progress=False)
    h = mpc.history
    assert not any(s.info["safety_net"] for s in h), "premise: the wall-clock safety net never decided a step"
    return [s.status for s in h], [s.v_pred.copy() for s in h], [s.message for s in h]


def test_the_same_loop_gives_the_same_answers_on_every_run_and_under_load(quad15):
    """A budget of one node: the loop run twice, then once with a busy process on the other core, gives identical
    statuses and plans (bit for bit); the loop has steps stopped by the budget and steps solved to optimality."""
    quad = quad15
    mpc = rt.make_mpc(quad, time_limit=SAFE_LIMIT).clone(work_limit=1)
    assert mpc.node_limit == 1
    first = loop(mpc, quad)
    assert "time_limit" in first[0] and "optimal" in first[0], "premise: the budget stops some steps, not all"
    assert any(m.startswith("work limit (1 nodes)") for m in first[2])
    second = loop(mpc, quad)
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        loaded = loop(mpc, quad)
    finally:
        busy.kill()
        busy.wait()
    for other in (second, loaded):
        assert other[0] == first[0]
        assert all(np.array_equal(a, b) for a, b in zip(first[1], other[1]))


def test_under_a_budget_the_incumbent_search_is_not_stopped_by_the_cut_off(quad, monkeypatch):
    """The engine's incumbent search stops at the cut-off (``go(stop_at=...)``) under a time limit only; under a work
    budget it runs to its end (the caller's stop() at the cut-off is the safety net, flagged as such)."""
    seen = {}
    for name, kw in (("clock", dict()), ("budget", dict(work_limit=1))):
        mpc = rt.make_mpc(quad, time_limit=SAFE_LIMIT).clone(**kw)
        real, calls = mpc.solver.go, seen.setdefault(name, [])
        monkeypatch.setattr(mpc.solver, "go", lambda stop_at=None, _r=real, _c=calls: (_c.append(stop_at), _r(stop_at))[1])
        R = quad["reference"](quad["ts"] * np.arange(mpc.N + 1))
        mpc(quad["z0"], R)
        mpc.finish()
    assert any(isinstance(t, float) for t in seen["clock"]), seen
    assert seen["budget"] and all(t is None for t in seen["budget"]), seen


class _SlowClock:
    """``time`` as a machine a million times slower would show it to the engine: ``perf_counter`` runs 1e6x fast
    (``SAFE_LIMIT`` is then 30 us of real time: the step outlasts it on any machine)."""

    def __init__(self):
        self._t0 = time.perf_counter()

    def perf_counter(self):
        return self._t0 + 1e6 * (time.perf_counter() - self._t0)

    def __getattr__(self, name):
        return getattr(time, name)


def _first_step(mpc, quad):
    mpc.reset()
    R = quad["reference"](quad["ts"] * np.arange(mpc.N + 1))
    return mpc(quad["z0"], R)


def test_a_slower_machine_changes_the_wall_clock_answer_not_the_budgeted_one(quad, monkeypatch):
    """The engine's modules see a clock 1e6x fast (a machine 1e6x slower for every decision that reads the
    clock): under the wall-clock limit the first step of the loop stops early with another answer; under a budget
    (without the cut-off, whose safety net is the one place that reads the clock) its status and plan are those of
    the normal clock, bit for bit."""
    wall = rt.make_mpc(quad, time_limit=SAFE_LIMIT, cut_off=False)
    work = wall.clone(work_limit=1)  # without the cut-off: no safety net either, the budget alone decides
    ref_wall, ref_work = _first_step(wall, quad), _first_step(work, quad)
    assert ref_wall.status == "optimal", "premise: without the slow clock the wall-clock step solves to the end"
    slow = _SlowClock()
    for mod in (engine, fallback, bang_bang, tightening):
        monkeypatch.setattr(mod, "time", slow)
    slow_wall, slow_work = _first_step(wall, quad), _first_step(work, quad)
    assert slow_wall.status == "time_limit", "the wall-clock answer depends on the machine's speed"
    assert not slow_work.info["safety_net"]
    assert slow_work.status == ref_work.status and slow_work.message == ref_work.message
    assert np.array_equal(slow_work.v_pred, ref_work.v_pred)


def test_a_budget_that_outlasts_the_limit_is_answered_by_the_safety_net_and_recorded(quad):
    """A limit far below any solve with a budget: the step answers at the cut-off, flagged as decided by the wall
    clock, and the summary counts it."""
    mpc = rt.make_mpc(quad, time_limit=1e-3).clone(work_limit=5)
    s = _first_step(mpc, quad)
    assert s.info["cut_off"] and s.info["safety_net"] and s.status == "time_limit"
    assert "wall-clock safety net" in s.message
    assert mpc.summary()["safety_net_hits"] == 1
    assert s.v is not None


def test_work_limit_is_validated_and_every_kept_combination_runs(quad):
    """Meaningless combinations raise with what to change; 'auto' is NODES_PER_SECOND times the limit (one node at
    least); each kept combination (back-end auto or scip, cut-off on or off, a number or 'auto') solves a step with
    the budget and records it."""
    for bad in (0, -1, 1.5, True, "fast", "1"):
        with pytest.raises(ValueError, match="work_limit must be"):
            rt.make_mpc(quad, time_limit=1.0).clone(work_limit=bad)
    with pytest.raises(ValueError, match="give time_limit"):
        rt.make_mpc(quad).clone(work_limit=3)
    with pytest.raises(ValueError, match="at most"):
        rt.make_mpc(quad, time_limit=1.0).clone(work_limit=10**30)
    for bad in ("0.1", True, -1.0, float("nan")):
        with pytest.raises(ValueError, match="time_limit must be"):
            rt.make_mpc(quad).clone(time_limit=bad)
    for bad in (-1.0, float("nan"), 2.0, "1e-6"):
        with pytest.raises(ValueError, match="gap must be"):
            rt.make_mpc(quad).clone(gap=bad)
    with pytest.raises(ValueError, match="node limit"):
        rt.make_mpc(quad, backend="daqp", time_limit=1.0).clone(work_limit=3)
    with pytest.raises(ValueError, match="network engine"):
        rt.make_mpc(quad, backend="cvxpy-scip", time_limit=1.0).clone(work_limit=3)
    with pytest.raises(ValueError, match="network engine"):
        rt.make_mpc(quad, backend="daqp", time_limit=1.0, constraint="measured").clone(work_limit=3)
    assert rt.make_mpc(quad, time_limit=0.5).clone(work_limit="auto").node_limit == max(1, int(NODES_PER_SECOND * 0.5))
    assert rt.make_mpc(quad, time_limit=1e-3).clone(work_limit="auto").node_limit == 1
    assert rt.make_mpc(quad, time_limit=1.0).node_limit is None, "the default reads the clock"
    assert rt.make_mpc(quad, time_limit=1.0).clone(work_limit=2).clone(time_limit=None).node_limit is None
    for backend in ("auto", "scip"):
        for cut_off in (None, False):
            for wl in (2, "auto"):
                mpc = rt.make_mpc(quad, backend=backend, time_limit=SAFE_LIMIT, cut_off=cut_off).clone(work_limit=wl)
                s = _first_step(mpc, quad)
                assert s.info["work_limit"] == mpc.node_limit and not s.info["safety_net"]
                assert s.nodes <= mpc.node_limit and s.status in ("optimal", "time_limit"), s.message
                assert s.backend == "scip", "under a budget every mixed-integer program goes to SCIP"


def test_a_solver_without_a_node_limit_refuses_one():
    """DAQP's branch and bound takes no node limit: asked for one on a mixed-integer program it says so; SCIP stops at
    its node limit with its incumbent as a time-limit result."""
    from flnotes.solvers import MIQP, make_solver
    import scipy.sparse as sp
    n = 6
    prob = MIQP(np.eye(n), -np.linspace(0.2, 0.8, n), 0.0, sp.csr_matrix(np.ones((1, n))), np.array([-np.inf]),
                np.array([2.5]), np.zeros(n), np.ones(n), np.ones(n, int))
    with pytest.raises(ValueError, match="no node limit"):
        make_solver(prob, "daqp").solve(node_limit=3)
    with pytest.raises(ValueError, match="node_limit must be"):
        make_solver(prob, "scip").solve(node_limit=0)
    r = make_solver(prob, "scip").solve(node_limit=1)
    assert r.status in ("optimal", "time_limit") and r.nodes <= 1
