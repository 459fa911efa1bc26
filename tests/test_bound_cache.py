"""LP bounds kept along the closed loop (``MPCOptions.bound_cache``): valid on every box they are reused for, and
the lever changes no optimum."""
from __future__ import annotations

import numpy as np
import pytest

import flnotes as fl
from flnotes.mpc import MPC, BoundCache, MPCOptions, sine_reference
from flnotes.tightening import lp_bounds

from _nets import test_net

U_EPS = 0.1745 - 0.0322


@pytest.fixture(scope="module")
def small_net():
    net, _ = test_net("quad1d-8x8")
    return fl.quad1d(), net


def _lp(net, lo, hi, prior=None):
    c = np.array([U_EPS])
    return lp_bounds(net, lo[None], hi[None], out_bounds=(-c, c), prior=prior, skip_stable=True)


def _feasible_preactivations(net, lo, hi, n=100_000, seed=0):
    X = np.random.default_rng(seed).uniform(lo, hi, (n, net.n_in))
    out, pre = net.forward(X)
    ok = np.all(np.abs(out) <= U_EPS, axis=1)
    return [a[ok] for a in pre], int(ok.sum())


def test_kept_bounds_hold_on_every_box_they_serve(small_net):
    """Bounds of a box B, reused on B' inside B, contain every sampled pre-activation of B' whose output meets the
    bound; they are at least as tight as FBBT on B', and the LPs started from them stay valid and not looser."""
    s, net = small_net
    lo, hi = s.lo * 0.8, s.hi * 0.8
    cache = BoundCache()
    cache.add(lo[None], hi[None], _lp(net, lo, hi))
    lo2, hi2 = lo + 0.25 * (hi - lo), hi - 0.35 * (hi - lo)  # inside
    fb = fl.fbbt(net, lo2[None], hi2[None])
    prior = cache.prior(lo2[None], hi2[None], fb)
    assert (cache.served, cache.asked) == (1, 1)
    pre, n_ok = _feasible_preactivations(net, lo2, hi2)
    assert n_ok > 1000, "premise: many sampled points meet the output bound"
    for a, L, U, Lf, Uf in zip(pre, prior.L, prior.U, fb.L, fb.U):
        assert np.all(a >= L[0] - 1e-7) and np.all(a <= U[0] + 1e-7)
        assert np.all(L >= Lf - 1e-12) and np.all(U <= Uf + 1e-12)
    assert any(np.any(L > Lf + 1e-9) or np.any(U < Uf - 1e-9) for L, U, Lf, Uf in zip(prior.L, prior.U, fb.L, fb.U)), \
        "premise: the kept bounds are tighter than FBBT on the smaller box"
    started = _lp(net, lo2, hi2, prior=prior)
    for a, L, U in zip(pre, started.L, started.U):
        assert np.all(a >= L[0] - 1e-7) and np.all(a <= U[0] + 1e-7)
    assert started.n_unstable <= _lp(net, lo2, hi2).n_unstable


def test_a_box_not_inside_a_kept_one_is_not_served(small_net):
    s, net = small_net
    lo, hi = s.lo * 0.5, s.hi * 0.5
    cache = BoundCache()
    cache.add(lo[None], hi[None], _lp(net, lo, hi))
    lo2 = lo.copy()
    lo2[0] = lo[0] - 0.1  # sticks out on one side
    fb = fl.fbbt(net, lo2[None], hi[None])
    prior = cache.prior(lo2[None], hi[None], fb)
    assert (cache.served, cache.asked) == (0, 1)
    assert all(np.array_equal(a, b) for a, b in zip(prior.L + prior.U, fb.L + fb.U))


def test_the_cache_keeps_its_capacity_and_checks_shapes(small_net):
    s, net = small_net
    cache = BoundCache(capacity=3)
    rng = np.random.default_rng(4)
    for _ in range(5):
        c = rng.uniform(s.lo * 0.5, s.hi * 0.5)
        cache.add((c - 0.1)[None], (c + 0.1)[None], _lp(net, c - 0.1, c + 0.1))
    assert len(cache) == 3 and cache.L[0].shape[0] == 3
    with pytest.raises(ValueError, match="one row per box"):
        cache.prior(np.zeros((2, net.n_in)), np.ones((2, net.n_in)), fl.fbbt(net, s.lo, s.hi))
    with pytest.raises(ValueError, match="positive integer"):
        BoundCache(capacity=0)
    cache.clear()
    assert len(cache) == 0 and cache.served == cache.asked == 0


def test_bound_cache_changes_no_optimum_along_a_closed_loop():
    """The closed loop with LP bounds in every level-set round, with and without the kept bounds: the same optimum at
    every step, and the kept bounds served boxes (premise); ``reset`` forgets them."""
    sysm = fl.quad1d()
    net, _ = test_net("quad1d-8x8")
    S = fl.paper.QUAD_SETTING
    runs = {}
    for keep in (True, False):
        mpc = MPC(sysm, net, 0.03, horizon=10, ts=S["ts"], Q=S["Q"], R=S["R"],
                  options=MPCOptions(lp=True, bound_cache=keep))
        fl.simulate(sysm, mpc, t_final=3.0, ts=S["ts"], z0=S["z0"], reference=sine_reference(1.5),
                    net=net, progress=False)
        assert all(h.status == "optimal" and not h.fallback for h in mpc.history)
        runs[keep] = (mpc, [h.objective for h in mpc.history])
    mpc, J = runs[True]
    assert mpc.solver.cache.served > 0, "premise: a later box lay inside a kept one"
    assert runs[False][0].solver.cache is None
    J0 = runs[False][1]
    assert len(J) == len(J0)
    for a, b in zip(J, J0):
        assert abs(a - b) <= 1e-6 * max(1.0, abs(b)), (a, b)
    mpc.reset()
    assert len(mpc.solver.cache) == 0


def test_the_chapters_numbers_pair_each_loop_with_and_without():
    from flnotes.bench import mpc as rt

    row = lambda system, N, cpu, served=None, asked=None: dict(system=system, N_p=N, cpu_s_total=cpu,  # noqa: E731
                                                               boxes_served=served, boxes_asked=asked)
    rows = [row("Quad-1D", 15, 3.0, 30, 100), row("Quad-1D", 15, 3.5), row("Quad-1D", 20, 6.0, 190, 200),
            row("Quad-1D", 20, 8.0), row("A", 8, 1.0, 5, 10), row("A", 8, 1.5), row("B", 6, 2.0, 0, 0),
            row("B", 6, 2.0)]
    n = rt.cache_lever_numbers(rows)
    assert (n["served"], n["asked"], n["q_N_p"], n["q_served"], n["q_cpu_off"]) == (225, 310, 20, 190, 8.0)
    assert (n["n_lp_sys"], n["n_other"], n["ratio_min"], n["ratio_max"]) == (1, 1, 1.5, 1.5)
    with pytest.raises(ValueError, match="one row with the bounds kept and one without"):
        rt.cache_lever_numbers(rows[:-1])


def test_the_run_to_run_spread_is_measured_on_identical_runs_only():
    from flnotes.bench import mpc as rt

    def row(system, cpu, served=None, asked=None, nodes=10.0, **kw):
        return dict(system=system, N_p=8, config="kept" if served is not None else "not kept", states=5,
                    nodes_mean=nodes, binaries_max=30, programs_solved=6, non_optimal=0, infeasible=0,
                    cpu_s_total=cpu, cpu_ms_median=cpu * 100, cpu_ms_max=cpu * 300, boxes_served=served,
                    boxes_asked=asked, **kw)

    rows = [row("A", 1.0, 5, 10, nodes=12.0), row("A", 1.5), row("B", 0.8, 0, 0), row("B", 0.7),
            dict(row("C", 0.0, 0, 0), states=0), dict(row("C", 0.0), states=0)]
    pairs = rt.idle_cache_pairs(rows)  # A tightened boxes: not the same work; C replayed no state
    assert [(a["system"], b["system"]) for a, b in pairs] == [("B", "B")]
    s = rt.run_to_run_spread(pairs + [(row("D", 2.0), row("D", 2.1))])
    assert s["pairs"] == 2 and s["cpu_s_total"] == pytest.approx(0.8 / 0.7 - 1)
    assert s["cpu_ms_max"] == pytest.approx(0.8 / 0.7 - 1)
    with pytest.raises(ValueError, match="differ in \\['nodes_mean'\\]"):
        rt.run_to_run_spread([(rows[0], rows[1])])
    with pytest.raises(ValueError, match="at least one pair"):
        rt.run_to_run_spread([])


def test_a_lever_table_can_run_its_default_twice():
    from flnotes.bench import mpc as rt

    configs = rt.with_repeat(rt.SOLVER_LEVERS)
    names = list(configs)
    assert names[:-1] == list(rt.SOLVER_LEVERS) and names[-1] == names[0] + rt.REPEAT_SUFFIX
    assert configs[names[-1]] == configs[names[0]]
    rows = [dict(config=n) for n in names]
    assert rt.repeat_pairs(rows) == [(rows[0], rows[-1])] and rt.repeat_pairs(rows[:-1]) == []
    with pytest.raises(ValueError, match="at least one"):
        rt.with_repeat({})


@pytest.mark.parametrize("table, levers", [("daqp_lever_table", "DAQP_LEVERS"), ("level_lever_table", "LEVEL_LEVERS"),
                                           ("lp_lever_table", "LP_LEVERS"), ("solver_lever_table", "SOLVER_LEVERS")])
def test_every_lever_table_can_add_a_second_run_of_its_default(monkeypatch, table, levers):
    """More pairs of identical runs for the run-to-run spread: each lever table of the report can run its default
    once more, as its last row, interleaved with the others."""
    from flnotes.bench import mpc as rt

    seen = []
    monkeypatch.setattr(rt, "interleaved_table", lambda setup, rec, idx, configs, time_limit=30.0: seen.append(configs)
                        or [dict(config=k) for k in configs])
    once = getattr(rt, table)(None, None, [], repeat=False)
    twice = getattr(rt, table)(None, None, [], repeat=True)
    assert len(twice) == len(once) + 1 == len(getattr(rt, levers)) + 1
    assert rt.repeat_pairs(twice) == [(twice[0], twice[-1])] and rt.repeat_pairs(once) == []
    assert seen[1][twice[-1]["config"]] == seen[1][twice[0]["config"]], "the repeat runs the default's options"
