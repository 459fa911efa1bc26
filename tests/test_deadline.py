"""A guaranteed answer: the MPC under a time limit returns a plan checked by the forward pass, an admissible input
and an honest optimality gap (the properties; speed is measured in ``python -m flnotes.bench deadline``).

With a limit far below any solve (``TINY``) and ``cut_off=False`` the engine returns at its first check of the time,
so which path each step takes depends on the states only, not on the machine's speed. With the cut-off (the default
under a time limit) the step answers while the engine runs on in its thread; the tests of the cut-off hold the
solver in a gate, so that what they check does not depend on thread timing either.
"""
import contextlib
import os
import sys
import threading
import time

import numpy as np
import pytest

import flnotes as fl
from flnotes.bench import exactness as ex
from flnotes.bench import mpc as rt
from flnotes.control import exact_1d_feasible_set
from flnotes.mpc import MPC, RESERVE_MAX_SHARE, RESERVE_SHARE
from flnotes.mpc import fallback as fb
from flnotes.solvers import BOUND_TOL
from flnotes.studies import multi as study

TINY = 1e-6


@pytest.fixture(scope="module")
def quad():
    return rt.quad_setup()


def check_step(mpc, s):
    """The properties of one answer: the plan passes the forward pass, the applied v meets the network bound at the
    measured state (or is flagged because no v does), the gap follows from the objective and a bound below it."""
    z = s.z_pred[0]
    assert s.v is not None and np.allclose(s.v, s.v_pred[0])
    feasible = mpc.pred.feasible(z, s.v_pred)
    assert feasible == s.info["plan_feasible"]
    if s.input_admissible:
        assert np.all(np.abs(mpc.net(np.r_[z, s.v])) <= mpc.u_eps + BOUND_TOL), s.message
    if s.status in ("optimal", "time_limit") and feasible:
        assert np.isfinite(s.bound) and np.isfinite(s.gap), s.message
        assert s.bound <= s.objective and s.gap >= 0.0
        assert abs(s.gap - (s.objective - s.bound) / max(1.0, abs(s.objective))) <= 1e-12
        assert abs(s.objective - mpc.cost(s.z_pred, s.v_pred, s.info["z_ref"])) <= 1e-9 * max(1.0, abs(s.objective))
    return feasible


@pytest.mark.parametrize("repair", [False, True])
def test_closed_loop_at_the_limit_returns_admissible_plans(quad, repair):
    """The book's closed loop with N_p = 20 and a limit far below any solve: every plan passes the forward pass,
    every input is admissible, the gaps are consistent, and the true |u| <= u_max holds on the plant at the samples.
    Without the repaired incumbent the first step has no plan (the fallback is exercised); with it (the default)
    that step returns the repaired relaxation."""
    setup = rt.quad_setup(horizon=20, net=quad["net"], eps=quad["eps"])
    mpc = rt.make_mpc(setup, time_limit=TINY, repair=repair, cut_off=False)
    log = fl.simulate(setup["system"], mpc, t_final=fl.scale(4.0, 1.5), ts=setup["ts"], z0=setup["z0"],
                      reference=setup["reference"], progress=False)
    hits = [s for s in mpc.history if s.status == "time_limit"]
    assert len(hits) >= 3, "premise: the limit is hit"
    if repair:
        assert any(s.info.get("incumbent") == "repaired relaxation" and not s.fallback for s in hits), \
            "premise: some step returns the repaired relaxation at the limit"
    else:
        assert any(s.fallback for s in hits), "premise: some step has no incumbent (the fallback is exercised)"
    for s in mpc.history:
        assert s.status in ("optimal", "time_limit")
        assert check_step(mpc, s), s.message
        assert s.input_admissible
    assert log.summary()["u_within_bound_at_samples"]  # between samples it takes the drift margin of chapter 9


def test_the_bound_at_the_limit_is_a_lower_bound(quad):
    """At the limit, bound <= the proven optimum (the MPC without a limit, exact against the cold reference in
    tests/test_exactness.py) <= the returned plan's cost, on diverse states; an input flagged not admissible only
    where no admissible v exists (the exact 1-D set is empty)."""
    cases = ex.mpc_cases(quad, fl.scale(10, 7), seed=5)
    mpc, exact = rt.make_mpc(quad, time_limit=TINY, cut_off=False), rt.make_mpc(quad)
    hits = 0
    for c in cases:
        mpc.reset()
        s = mpc(c["z"], c["z_ref"])
        feasible = check_step(mpc, s)
        if not s.input_admissible:
            z = s.z_pred[0]
            assert not len(exact_1d_feasible_set(mpc.net, z, float(mpc.v_lo[0]), float(mpc.v_hi[0]),
                                                 float(mpc.u_eps[0])))
        if s.status == "time_limit" and feasible:
            exact.reset()
            r = exact(c["z"], c["z_ref"])
            assert r.status == "optimal", "the returned plan is feasible, so the program has an optimum"
            hits += 1
            J = r.objective
            assert s.bound <= J + 1e-6 * max(1.0, abs(J)) and J <= s.objective + 1e-6 * max(1.0, abs(J))
    assert hits >= 1, "premise: a limit hit with an admissible plan"


def test_a_solver_interrupted_by_the_limit_keeps_an_honest_bound(quad):
    """Limits that stop the engine inside its rounds (which rounds depends on the machine; the property does not):
    every answer is checked, and every bound is below the proven optimum."""
    cases = ex.mpc_cases(quad, fl.scale(6, 3), seed=6)
    exact, refs = rt.make_mpc(quad), {}
    for tl in (0.003, 0.02):
        mpc = rt.make_mpc(quad, time_limit=tl)
        for j, c in enumerate(cases):
            mpc.reset()
            s = mpc(c["z"], c["z_ref"])
            if check_step(mpc, s) and s.status == "time_limit":
                exact.reset()
                r = refs[j] = refs.get(j) or exact(c["z"], c["z_ref"])
                assert r.status == "optimal" and s.bound <= r.objective + 1e-6 * max(1.0, abs(r.objective))


@pytest.fixture(scope="module")
def arm():
    net, eps, _ = fl.arm_net()
    return fl.two_link_arm(), net, eps


@pytest.mark.parametrize("repair", [False, True])
def test_two_inputs_under_the_limit(arm, repair):
    """The arm (m = 2) with a limit far below any solve: admissible inputs and plans, true torques within tau_max;
    without the repaired incumbent the fallback is exercised, with it some step returns the repaired relaxation."""
    system, net, eps = arm
    M = study.ARM_MPC
    mpc = MPC(system, net, eps, horizon=M["horizon"], ts=M["ts"], Q=M["Q"], R=M["R"], time_limit=TINY,
              repair=repair, cut_off=False)
    log = fl.simulate(system, mpc, t_final=fl.scale(4.0, 3.5), ts=M["ts"], z0=M["z0"],
                      reference=study.setpoint_reference(M["setpoints"], M["t_switch"]), hold="u", net=net,
                      progress=False)
    hits = [s for s in mpc.history if s.status == "time_limit"]
    if repair:
        assert any(s.info.get("incumbent") == "repaired relaxation" and not s.fallback for s in hits), \
            "premise: the limit is hit and some step returns the repaired relaxation"
    else:
        assert hits and any(s.fallback for s in hits), "premise: the limit is hit and the fallback is exercised"
    for s in mpc.history:
        assert check_step(mpc, s), s.message
        assert s.input_admissible
    assert study.torque_checks(log)["within"]


def test_feasible_tail_is_exact_for_two_inputs(arm):
    """feasible_tail for m = 2: an admissible input (network bound by the forward pass, next state in the box)
    wherever a dense grid finds one, and none of the grid's admissible points is nearer to the guess."""
    system, net, eps = arm
    mpc = MPC(system, net, eps, horizon=3, ts=0.1, Q=np.ones(4), R=0.01 * np.ones(2))
    rng = np.random.default_rng(11)
    g = np.linspace(0.0, 1.0, 121)
    G = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) * (mpc.v_hi - mpc.v_lo) + mpc.v_lo
    checked = 0
    for z in rng.uniform(system.lo[:4], system.hi[:4], (12, 4)):
        guess = rng.uniform(mpc.v_lo, mpc.v_hi)
        v = fb.feasible_tail(mpc.pred, z, guess)
        ok_grid = fb._admissible(mpc.pred, z, G, False)
        ok_v = fb._admissible(mpc.pred, z, v[None], False)[0]
        if ok_grid.any():
            assert ok_v, z
        if ok_v and not np.allclose(v, guess):
            checked += 1
            nearest = np.min(np.sum((G[ok_grid] - guess) ** 2, axis=1)) if ok_grid.any() else np.inf
            # v may be pulled inside its polygon by 1e-6 of the way to its centre (round-off at the edges)
            assert np.linalg.norm(v - guess) <= np.sqrt(nearest) + 1e-4
    assert checked >= 3, "premise: guesses that are not admissible"


def _nearest_grid_distance(pred, z, guess, last, n):
    """The distance from ``guess`` to the nearest admissible point of a grid of ``n`` points over the v box (inf when
    none is admissible): a brute force against which feasible_tail is held."""
    grid = np.linspace(pred.v_lo[0], pred.v_hi[0], n)[:, None]
    ok = fb._admissible(pred, z, grid, last)
    return float(np.min(np.abs(grid[ok, 0] - guess[0]))) if ok.any() else np.inf


def test_feasible_tail_for_one_input_is_the_nearest_admissible_point(quad):
    """feasible_tail for m = 1 (the exact set of the step, eq. Phi_NN_ep at z cut by the next state's box and terminal
    rows): the guess when it is admissible; otherwise an admissible input within the program's bound u_max^eps, at
    least as near to the guess as every admissible point of a grid 50 times finer than the fallback's own (10 under
    FLNOTES_FAST), wherever such a point exists, and the guess back only where no grid point is admissible. Checked
    by brute force at states all over the box and at its faces, with and without the terminal rows."""
    system, net, eps = quad["system"], quad["net"], quad["eps"]
    n_z = system.n_z
    F, g = np.vstack([np.eye(n_z), -np.eye(n_z)]), 0.5 * np.r_[system.hi[:n_z], -system.lo[:n_z]]
    mpc = MPC(system, net, eps, horizon=3, ts=0.1, terminal=(F, g))
    pred = mpc.pred
    rng = np.random.default_rng(5)
    fine = fl.scale(50, 10) * (fb.FEASIBLE_TAIL_GRID - 1) + 1
    lo, hi = system.lo[:n_z], system.hi[:n_z]
    states = np.vstack([rng.uniform(lo, hi, (40, n_z)), np.where(rng.random((40, n_z)) < 0.5, lo, hi)
                        * rng.uniform(0.97, 1.0, (40, n_z))])
    kinds = set()
    for z in states:
        for last in (False, True):
            guess = rng.uniform(mpc.v_lo, mpc.v_hi)
            v = fb.feasible_tail(pred, z, guess, last=last)
            ok_v = fb._admissible(pred, z, v[None], last)[0]
            d_fine = _nearest_grid_distance(pred, z, guess, last, fine)
            if fb._admissible(pred, z, guess[None], last)[0]:
                assert np.array_equal(v, guess)
                kinds.add("guess admissible")
            elif not np.isfinite(d_fine):
                assert np.array_equal(v, guess) or ok_v, (z, last, guess, v)
                kinds.add("none admissible")
            else:
                assert ok_v, (z, last, guess, v)
                assert abs(v[0] - guess[0]) <= d_fine + 1e-9, (z, last, guess, v, d_fine)
                # a moved input meets the program's bound, not only the check's u_max^eps + BOUND_TOL: at the check's
                # own bound a plan fails the check once its states are predicted again (round-off)
                assert np.all(np.abs(pred.net(np.r_[z, v])) <= pred.u_eps + 1e-13), (z, last, v)
                kinds.add("moved")
    assert kinds == {"guess admissible", "none admissible", "moved"}, f"premise: every case met, got {kinds}"


@pytest.mark.parametrize("scale", [1e-9, 1.0, 1e9])
def test_feasible_tail_for_one_input_at_every_scale(scale):
    """The same property at states of size 1e-9 to 1e9 (round-off of A_d z + B_d v is relative to its terms: an end of
    the step's interval on the face of a box of size 1e9 is pulled inside until the forward-pass check passes it)
    and with an input that does not move the state (no box row involves v), against the fallback's grid: an
    admissible input at least as near as its nearest admissible point."""
    from flnotes.mpc.prediction import Prediction

    net = fl.ReLUNet([np.array([[0.0, 1.0], [0.0, -1.0]]), np.array([[1.0, -1.0]])], [np.zeros(2), np.zeros(1)])
    grid = np.linspace(-1.0, 1.0, fb.FEASIBLE_TAIL_GRID)
    rng = np.random.default_rng(2)
    moved = 0
    for B in (1.0, 0.0):
        pred = Prediction(net, np.array([[1.0]]), np.array([[B]]), 2, np.eye(1), np.eye(1), np.eye(1),
                          z_lo=np.array([-scale]), z_hi=np.array([scale]), v_lo=np.array([-1.0]),
                          v_hi=np.array([1.0]), u_eps=np.array([0.5]))
        for k in rng.integers(0, len(grid), 300):
            z = np.array([scale - grid[k] * B])  # the next state meets the upper face at the grid point k
            guess = np.array([1.0])
            v = fb.feasible_tail(pred, z, guess)
            d = _nearest_grid_distance(pred, z, guess, False, fb.FEASIBLE_TAIL_GRID)
            ok_v = fb._admissible(pred, z, v[None], False)[0]
            if not np.isfinite(d):  # no grid point admissible: the guess back, or an admissible input the grid missed
                assert v[0] == 1.0 or ok_v, (scale, B, z, v)
                continue
            assert ok_v, (scale, B, z, v)
            # a grid point can pass the check by the round-off of z + v, about eps * scale beyond the exact face
            assert abs(v[0] - 1.0) <= d + 1e-12 + 4 * np.finfo(float).eps * scale, (scale, B, z, v, d)
            # and it is the exact nearest: Phi = v, so |v| <= 0.5 and, where v moves the state, v <= (scale - z) / B
            exact = min(0.5, (scale - z[0]) / B) if B else 0.5
            assert abs(v[0] - exact) <= 1e-12 + 4 * np.finfo(float).eps * scale, (scale, B, z, v, exact)
            moved += v[0] != 1.0
    assert moved >= 100, f"premise: guesses moved ({moved})"


def _one_input_pred(Ws, bs, Ad, Bd, v_lo, v_hi, u_eps, z_lo, z_hi, terminal=None, N=2):
    """A Prediction of one input built by hand (identity weights): for the edge cases of feasible_tail."""
    from flnotes.mpc.prediction import Prediction

    net = fl.ReLUNet([np.asarray(W, float) for W in Ws], [np.asarray(b, float) for b in bs])
    Ad = np.atleast_2d(np.asarray(Ad, float))
    n_z = Ad.shape[0]
    return Prediction(net, Ad, np.asarray(Bd, float).reshape(-1, 1), N, np.eye(n_z), np.eye(1), np.eye(n_z),
                      z_lo=np.asarray(z_lo, float).reshape(-1), z_hi=np.asarray(z_hi, float).reshape(-1),
                      v_lo=np.array([float(v_lo)]), v_hi=np.array([float(v_hi)]), u_eps=np.array([float(u_eps)]),
                      terminal=terminal)


_C, _HW = 0.2e-10, 4e-13  # a tent of height 2 and half-width 4e-13 at 2e-11, on a v range of 1e-10
_EDGE_CASES = {
    # Phi = v; the terminal set (last step) or an equality face of the box leaves the one input v = c
    "terminal set leaves one point": (
        _one_input_pred([[[0, 1], [0, -1]], [[1, -1]]], [[0, 0], [0]], [[1.0]], [1.0], -1, 1, 1.0, [-10], [10],
                        terminal=(np.array([[1.0], [-1.0]]), np.array([0.123456789, -0.123456789]))),
        [0.0], 0.9, True, [0.123456789]),
    "box face leaves one point": (
        _one_input_pred([[[0, 1], [0, -1]], [[1, -1]]], [[0, 0], [0]], [[1.0]], [1.0], -1, 1, 1.0, [0.123456789],
                        [0.123456789]), [0.0], 0.9, False, [0.123456789]),
    # Phi = 3e170 relu(1e-170 v) - 1: the product of the pre-activations at the knots underflows
    "pre-activations of 1e-170": (
        _one_input_pred([[[0, 1e-170]], [[3e170]]], [[0.0], [-1.0]], [[1.0]], [0.0], -1, 1, 1.0, [-10], [10]),
        [0.0], 0.9, False, [2 / 3]),
    # a flat piece at u_max^eps + BOUND_TOL / 2: within the check's tolerance, outside the program's bound (the
    # nearest input within the bound is 0.9, where the piece drops)
    "flat piece within the check's tolerance": (
        _one_input_pred([[[0, -1], [0, 1]], [[10, -10]]], [[0, -0.9], [1.0 + 0.5e-12]], [[1.0]], [0.0], -1, 1, 1.0,
                        [-10], [10]), [0.0], -0.5, False, [0.9, 0.9 + 1e-13]),
    # an inadmissible tent narrower than 1e-12 on a v range of 1e-10, the guess on its top
    "a gap of 8e-13 on a range of 1e-10": (
        _one_input_pred([[[0, 1], [0, 1], [0, 1]], [[2 / _HW, -4 / _HW, 2 / _HW]]], [[-(_C - _HW), -_C, -(_C + _HW)],
                        [0.0]], [[1.0]], [0.0], 0, 1e-10, 1.0, [-10], [10]),
        [0.0], _C, False, np.linspace(_C - 2 * _HW, _C + 2 * _HW, 4001)),
    # u_max^eps = 0: only Phi = 0 (to the check's tolerance) is admissible
    "u_max^eps = 0": (
        _one_input_pred([[[0, 1], [0, -1]], [[1, -1]]], [[0, 0], [-0.1234567]], [[1.0]], [0.0], -1, 1, 0.0, [-10],
                        [10]), [0.0], 0.9, False, [0.1234567]),
    # Phi = 0; the terminal row's face: a batch's matrix product rounds otherwise than one row's
    "a terminal face at round-off": (
        _one_input_pred([[[0, 0, 1]], [[0.0]]], [[0.0], [0.0]], [[0.513, -0.298], [-0.53, -0.236]], [1.816, -0.05],
                        -10, 10, 1.0, [-100, -100], [100, 100],
                        terminal=(np.array([[0.087, -1.487]]), np.array([0.1])), N=1),
        [1.647, 0.917], 10.0, True, []),
}


@pytest.mark.parametrize("case", list(_EDGE_CASES))
def test_feasible_tail_for_one_input_on_edge_cases(case):
    """feasible_tail for m = 1 where an exact set is easy to get wrong: the box or the terminal set leaves one input,
    pre-activations whose product underflows, a piece flat within the check's tolerance, a gap narrower than 1e-12 on
    a short v range, u_max^eps = 0, a face met at round-off. The answer passes the forward-pass check on its own, meets
    the program's bound |Phi_NN| <= u_max^eps (to round-off far below BOUND_TOL) and lies no farther from the guess
    than the nearest such point of a dense grid (plus the known points)."""
    pred, z, guess, last, extra = _EDGE_CASES[case]
    z, g = np.asarray(z, float), np.array([guess])
    v = fb.feasible_tail(pred, z, g, last=last)
    within = lambda V: np.abs(pred.net(np.column_stack([np.repeat(z[None], len(V), 0), V]))[:, 0]) <= pred.u_eps[0] + 1e-13  # noqa: E731
    assert fb._admissible(pred, z, v[None], last)[0] and within(v)[0], (case, v)
    cand = np.unique(np.r_[np.linspace(pred.v_lo[0], pred.v_hi[0], 200001), np.asarray(extra, float)])
    cand = cand[(cand >= pred.v_lo[0]) & (cand <= pred.v_hi[0])]
    ok = fb._admissible(pred, z, cand[:, None], last) & within(cand)
    assert ok.any(), "premise: an admissible input"
    nearest = float(np.min(np.abs(cand[ok] - guess)))
    assert abs(v[0] - guess) <= nearest + 1e-12 * (pred.v_hi[0] - pred.v_lo[0]), (case, v, nearest)


def test_the_one_input_step_interval_is_the_set_that_keeps_the_state_in_its_box(quad):
    """_step_interval (one input: the v that keep A_d z + B_d v in the state box, and in the terminal set for the
    last step), which safe_input prefers, equals the grid points that meet those rows by a direct check, at states
    all over the box and beyond it (an empty interval there)."""
    system, net, eps = quad["system"], quad["net"], quad["eps"]
    n_z = system.n_z
    F, g = np.vstack([np.eye(n_z), -np.eye(n_z)]), 0.5 * np.r_[system.hi[:n_z], -system.lo[:n_z]]
    pred = MPC(system, net, eps, horizon=3, ts=0.1, terminal=(F, g)).pred
    rng = np.random.default_rng(8)
    grid = np.linspace(pred.v_lo[0], pred.v_hi[0], 4001)
    lo, hi = system.lo[:n_z], system.hi[:n_z]
    kinds = set()
    for z in np.vstack([rng.uniform(lo, hi, (60, n_z)), rng.uniform(1.5 * lo, 1.5 * hi, (60, n_z))]):
        for last in (False, True):
            s_lo, s_hi = fb._step_interval(pred, z, last)
            nxt = z @ pred.Ad.T + grid[:, None] @ pred.Bd.T
            ok = np.all((nxt >= pred.z_lo - 1e-9) & (nxt <= pred.z_hi + 1e-9), axis=1)
            if last:
                ok &= np.all(nxt @ F.T <= g + 1e-9, axis=1)
            inside = (grid >= s_lo - 1e-9) & (grid <= s_hi + 1e-9)
            assert np.array_equal(ok, inside), (z, last, s_lo, s_hi)
            kinds.add("empty" if not ok.any() else "all" if ok.all() else "part")
    assert {"empty", "part"} <= kinds, f"premise: empty and partial intervals met, got {kinds}"


def test_qp_repair_from_the_relaxation_is_the_full_rebuild(quad):
    """qp_repair started from the relaxation's optimum (the QP solved again only after a moved step) gives the plan
    of the rebuild that solves the QP at every step, on diverse states."""
    pred, moved = rt.make_mpc(quad).pred, 0
    for c in ex.mpc_cases(quad, fl.scale(12, 6), seed=7):
        f, _ = pred.linear(c["z"], c["z_ref"])
        V_c, _, _ = pred.qp(f, c["z"])
        if V_c is None:
            continue
        _, V_fast = fb.qp_repair(pred, c["z"], f, V_c)
        _, V_all = fb.qp_repair(pred, c["z"], f)
        assert np.allclose(V_fast, V_all, atol=1e-7), np.max(np.abs(V_fast - V_all))
        moved += not np.allclose(V_fast.reshape(-1), V_c)
    assert moved >= 2, "premise: states where the repair moves some input"


def test_the_qp_with_fixed_steps_holds_them_and_refuses_what_means_nothing(quad):
    """Prediction.qp(fixed=...): the first steps held at their values (to round-off) and the rest the QP's optimum with
    them fixed (the same as with equality rows); values outside the v box, not finite, more than the plan holds, or
    given with first, are a ValueError."""
    pred = rt.make_mpc(quad).pred
    c = next(iter(ex.mpc_cases(quad, 1, seed=3)))
    f, _ = pred.linear(c["z"], c["z_ref"])
    held = np.clip(np.linspace(-1.0, 1.0, 3), pred.v_lo[0], pred.v_hi[0])
    x, _, flag = pred.qp(f, c["z"], fixed=held)
    G = np.eye(pred.N * pred.m)[:3]
    y, _, flag_rows = pred.qp(f, c["z"], G, held, held)
    assert flag == flag_rows == 1 and np.allclose(x[:3], held, atol=1e-12) and np.allclose(x, y, atol=1e-7)
    for bad in ([pred.v_hi[0] + 1.0], [np.nan], [np.inf], np.zeros(pred.N * pred.m + 1)):
        with pytest.raises(ValueError, match="fixed"):
            pred.qp(f, c["z"], fixed=bad)
    with pytest.raises(ValueError, match="not both"):
        pred.qp_multipliers(f, c["z"], first=(pred.v_lo, pred.v_hi), fixed=held[:1])


def _held_bounds_qp(pred, f, z, fixed, G=None, g_lo=None, g_hi=None):
    """The QP with the first entries held by setting their bounds to their values (Prediction.qp's formulation before
    it solved the free entries alone): (V or None, J, multipliers of G's rows)."""
    import daqp

    lo, hi = pred.state_bounds(z)
    A = pred.A_state if G is None else np.vstack([pred.A_state, G])
    if G is not None:
        lo, hi = np.r_[lo, np.broadcast_to(g_lo, len(G))], np.r_[hi, np.broadcast_to(g_hi, len(G))]
    bu = np.r_[np.tile(pred.v_hi, pred.N), np.minimum(hi, 1e30)]
    bl = np.r_[np.tile(pred.v_lo, pred.N), np.maximum(lo, -1e30)]
    bl[: fixed.size] = bu[: fixed.size] = fixed
    x, J, flag, info = daqp.solve(pred.H, np.array(f, float), A, bu, bl, np.zeros(len(bu), dtype=np.int32))
    if flag not in (1, 2):
        return None, np.inf, None
    return np.asarray(x), J, None if G is None else np.asarray(info["lam"])[len(bu) - len(G):]


def test_the_qp_over_the_free_inputs_is_the_qp_with_held_bounds():
    """Prediction.qp(fixed=...) solves the QP over the inputs left free (the held ones eliminated): on the states of
    repairs of the five systems not in the book at N_p = 10 and 40, at every step (and with every input held), its
    plan, cost and the multipliers of extra rows are those of the QP whose held entries' bounds are set to their
    values; held inputs that drive a state out of its box make both infeasible."""
    from flnotes.studies import unseen as U

    checked = infeasible = binding = whole = 0
    for name in U.CASES:
        for N in (10, 40):
            mpc = U.unseen_mpc(name, horizon=N)
            pred, c = mpc.pred, U.case(name)
            z = np.asarray(c.z0, float)
            f, _ = pred.linear(z, np.asarray(c.reference()(mpc.ts * np.arange(N + 1)), float))
            states = []
            fb.qp_repair(pred, z, f, publish=states.append)
            rng = np.random.default_rng(N)
            G = rng.normal(size=(1, N * pred.m))  # one row: its multiplier is unique where it binds
            lo, hi = pred.state_bounds(z)
            for st in states[1:]:
                fixed = st.V[: st.k].reshape(-1)
                x, J, flag = pred.qp(f, z, fixed=fixed)
                y, J_ref, _ = _held_bounds_qp(pred, f, z, fixed)
                assert (x is None) == (y is None)
                if x is None:
                    continue
                assert flag in (1, 2) and np.array_equal(x[: fixed.size], fixed)
                assert np.allclose(x, y, atol=1e-8, rtol=0) and abs(J - J_ref) <= 1e-9 * max(1.0, abs(J_ref))
                # extra rows that cut the optimum off (G x <= G x* - 1e-4 where the held inputs leave room for it)
                g = G @ x - 1e-4
                x2, _, _, lam = pred.qp_multipliers(f, z, G, -np.inf, g, fixed=fixed)
                y2, _, lam_ref = _held_bounds_qp(pred, f, z, fixed, G, -np.inf, g)
                assert (x2 is None) == (y2 is None)
                if x2 is not None:  # both to DAQP's primal tolerance (1e-6), where the two may differ
                    s2 = pred.A_state @ x2
                    assert np.all(s2 >= lo - 1e-6) and np.all(s2 <= hi + 1e-6) and np.all(G @ x2 <= g + 1e-6)
                    J2, J2_ref = pred.cost(x2, f, 0.0), pred.cost(y2, f, 0.0)
                    assert abs(J2 - J2_ref) <= 1e-6 * max(1.0, abs(J2_ref)) and np.allclose(x2, y2, atol=1e-4, rtol=0)
                    assert np.allclose(lam, lam_ref, atol=1e-4, rtol=1e-3)
                    binding += bool(np.any(lam != 0.0))
                checked += 1
            # every input held: the plan itself, or infeasible when it breaks a row
            V = states[-1].V.reshape(-1)
            x, J, flag = pred.qp(f, z, fixed=V)
            assert (x is None) == (_held_bounds_qp(pred, f, z, V)[0] is None)
            if x is not None:
                assert flag == 1 and np.array_equal(x, V) and np.isclose(J, pred.cost(V, f, 0.0), rtol=1e-12)
                whole += 1
            # inputs at the box's end for the whole horizon: the state leaves its box (the QP with held bounds says
            # infeasible too)
            for end in (pred.v_lo, pred.v_hi):
                held = np.tile(end, N)
                x, _, flag = pred.qp(f, z, fixed=held[: N * pred.m - pred.m])
                y, _, _ = _held_bounds_qp(pred, f, z, held[: N * pred.m - pred.m])
                assert (x is None) == (y is None)
                infeasible += x is None
    assert checked >= 100 and infeasible >= 1 and binding >= 50 and whole >= 5, (checked, infeasible, binding, whole)


def test_the_qp_and_the_repair_refuse_arguments_that_do_not_fit(quad):
    """Prediction.qp / qp_multipliers and qp_repair check what DAQP would read past its end or as numbers without a
    word: f of another size or with NaN/inf, a state with NaN, G not (r, N_p m) or with NaN, bounds of G missing,
    NaN or of another count, bounds without G; qp_repair also a missing f and a V_qp outside the v box. Each is a
    ValueError naming it, with or without held inputs; G of no rows gives no multipliers (an empty array)."""
    pred = rt.make_mpc(quad).pred
    c = next(iter(ex.mpc_cases(quad, 1, seed=3)))
    z, n = np.asarray(c["z"], float), pred.N * pred.m
    f, _ = pred.linear(z, c["z_ref"])
    G = np.ones((2, n))
    bad_f = f.copy()
    bad_f[1] = np.nan
    cases = [(dict(f=f[:-2]), "f .*got shape \\(\\d+,\\)$"), (dict(f=bad_f), "with NaN or inf"),
             (dict(f=np.r_[f, 0.0]), "f "), (dict(f=f.reshape(1, 1, -1)), "f .*got shape \\(1, 1, \\d+\\)$"),
             (dict(z0=np.r_[np.nan, z[1:]]), "z0"), (dict(z0=z[:-1]), "z0"),
             (dict(G=np.ones(n), g_lo=-1.0, g_hi=1.0), "G must"), (dict(G=np.ones((2, n - 1)), g_lo=-1.0, g_hi=1.0),
                                                                  "G must"),
             (dict(G=np.where(G > 0, np.nan, 0.0), g_lo=-1.0, g_hi=1.0), "G must"), (dict(G=G, g_hi=1.0), "needs both"),
             (dict(G=G, g_lo=-1.0, g_hi=[1.0, np.nan]), "g_hi"), (dict(G=G, g_lo=np.zeros(3), g_hi=1.0), "g_lo"),
             (dict(g_lo=-1.0, g_hi=1.0), "give them with G")]
    for fixed in (None, np.zeros(0), np.zeros(2)):
        for change, match in cases:
            kw = dict(dict(f=f, z0=z), **change)
            with pytest.raises(ValueError, match=match):
                pred.qp_multipliers(kw.pop("f"), kw.pop("z0"), fixed=fixed, **kw)
        lam = pred.qp_multipliers(f, z, np.zeros((0, n)), np.zeros(0), np.zeros(0), fixed=fixed)[3]
        assert isinstance(lam, np.ndarray) and lam.shape == (0,)
    _, V = fb.qp_repair(pred, z, f)
    assert V.shape == (pred.N, pred.m)
    V_out = np.asarray(pred.qp(f, z)[0], float)
    V_out[0] = pred.v_lo[0] - 1e-5
    for args, match in (((z, None), "linear part"), ((z, f[:-1]), "f "), ((z[:-1], f), "z"),
                        ((z, f, V_out), "V_qp"), ((z, f, np.full(n, np.nan)), "V_qp")):
        with pytest.raises(ValueError, match=match):
            fb.qp_repair(pred, *args)


def test_at_the_limit_the_first_incumbent_is_returned(quad):
    """A limit far below any solve: each step returns its first incumbent, the cheaper (both checked by the forward
    pass) of the shifted previous plan and the relaxation's optimum repaired along the QP, then optimized over the
    network's linear regions around it (flnotes.mpc.region); so a dear warm start is not carried from step to
    step."""
    from flnotes.mpc import region as rg

    setup = rt.quad_setup(horizon=15, net=quad["net"], eps=quad["eps"])
    mpc = rt.make_mpc(setup, time_limit=TINY, cut_off=False)
    pred, z = mpc.pred, np.asarray(setup["z0"], float)
    seen = {"warm start": 0, "repaired relaxation": 0, "region": 0}
    for k in range(30):  # 30 steps also under FLNOTES_FAST (under 2 s): the region QP improves few exact repairs
        R = setup["reference"](setup["ts"] * (k + np.arange(setup["N"] + 1)))
        shifted = mpc.shifted_plan(z)
        s = mpc(z, R)
        f, c0 = pred.linear(z, R)
        cands = []
        if shifted is not None and pred.feasible(z, shifted[1]):
            cands.append((pred.cost(shifted[1], f, c0), shifted[1].reshape(-1)))
        V_c, _, _ = pred.qp(f, z)
        if V_c is not None:
            _, V_r = fb.qp_repair(pred, z, f, V_c)
            if pred.feasible(z, V_r):
                cands.append((pred.cost(V_r, f, c0), V_r.reshape(-1)))
        assert check_step(mpc, s), s.message
        if s.status == "time_limit" and not s.fallback:
            assert cands
            J, V = min(cands, key=lambda jv: jv[0])
            V_p = rg.region_qp(pred, z, f, V, rg.REGION_MOVES)
            if V_p is not None and pred.feasible(z, V_p):
                J = min(J, pred.cost(V_p, f, c0))
            assert abs(s.objective - J) <= 1e-9 * max(1.0, abs(J)), (s.objective, J)
            seen[s.info["incumbent"]] += 1
            seen["region"] += bool(s.info["region_improved"])
        z = pred.Ad @ z + pred.Bd @ s.v  # the prediction model as the plant: the states depend on no timing
    assert seen["repaired relaxation"] >= 3 and seen["region"] >= 3, f"premise: repairs and region QPs ({seen})"


def test_the_fallback_skips_a_plan_along_the_qp_the_engine_saw_fail(quad):
    """Where the plan along the QP fails the forward-pass check, the fallback told so (qp_repair_failed) returns the
    same plan as the fallback that builds it again; and the controller then keeps back at least that fallback's
    time from the engine (reserve), at most half its limit."""
    pred, same = rt.make_mpc(quad).pred, 0
    for c in ex.mpc_cases(quad, fl.scale(16, 10), seed=2):
        f, _ = pred.linear(c["z"], c["z_ref"])
        if pred.feasible(c["z"], fb.qp_repair(pred, c["z"], f)[1]):
            continue
        a = fb.fallback_plan(pred, c["z"], None, f=f)
        b = fb.fallback_plan(pred, c["z"], None, f=f, qp_repair_failed=True)
        assert np.array_equal(a[1], b[1]) and a[2:] == b[2:]
        same += 1
    assert same >= 2, "premise: states where the plan along the QP fails the check"
    mpc = rt.make_mpc(quad, time_limit=0.2)
    for c in ex.mpc_cases(quad, fl.scale(16, 10), seed=2):
        mpc.reset()
        if mpc(c["z"], c["z_ref"]).fallback:
            break
    else:
        pytest.fail("premise: a state that needs the fallback")
    assert mpc._fallback_s > 0
    assert mpc.reserve == max(RESERVE_SHARE * 0.2, min(mpc._late_s + mpc._fallback_s, RESERVE_MAX_SHARE * 0.2))
    mpc.reset()
    assert mpc._fallback_s == mpc._late_s == 0.0 and mpc.reserve == RESERVE_SHARE * 0.2


def _easy_and_cold(quad, n_easy=2):
    """States of the book's Quad-1D that the MPC without a limit screens (an easy step: one QP) and one where it has
    no plan (the fallback runs)."""
    exact = rt.make_mpc(quad)
    easy, cold = [], None
    for c in ex.mpc_cases(quad, 40, seed=11):
        exact.reset()
        s = exact(c["z"], c["z_ref"])
        if s.screened and len(easy) < n_easy:
            easy.append(c)
        elif s.status == "infeasible" and cold is None:
            cold = c
    assert len(easy) == n_easy and cold is not None, "premise: screened states and an infeasible one"
    return easy, cold


def _burn(seconds):
    """Busy CPU work of this thread for ``seconds`` of its CPU time."""
    import time

    c0 = time.thread_time()
    while time.thread_time() - c0 < seconds:
        sum(range(1000))


def test_slow_fallbacks_never_stop_the_controller_from_optimizing(quad, monkeypatch):
    """Fallbacks that cost more CPU than the whole limit (a slow fallback injected, on cold states), then easy states:
    the measured reserve stays at most RESERVE_MAX_SHARE of the limit, the cut-off leaves the engine most of the
    limit, and the easy states are solved to optimality again, by the same controller, without a reset. A reset
    clears what was measured."""
    from flnotes.mpc import controller

    easy, cold = _easy_and_cold(quad)
    tl = 0.25
    mpc = rt.make_mpc(quad, time_limit=tl)
    real = controller.fallback.fallback_plan

    def slow(*a, **k):
        _burn(1.5 * tl)  # the controller's own CPU work, more than its whole limit
        return real(*a, **k)

    monkeypatch.setattr(controller.fallback, "fallback_plan", slow)
    for _ in range(3):
        mpc.reset()
        s = mpc(cold["z"], cold["z_ref"])
        assert s.fallback, s.message
    monkeypatch.setattr(controller.fallback, "fallback_plan", real)
    mpc.set_previous_plan(None)
    assert mpc._fallback_s >= 1.5 * tl, "premise: the controller measured a fallback longer than its limit"
    assert mpc.reserve <= RESERVE_MAX_SHARE * tl
    for c in easy:
        mpc.set_previous_plan(None)
        s = mpc(c["z"], c["z_ref"])
        assert s.status == "optimal" and not s.fallback and not s.info["cut_off"], s.message
    assert mpc._fallback_s < 1.5 * tl, "what was measured decays step by step"
    mpc.reset()
    assert mpc.measured == dict(late=0.0, fallback=0.0, answer=0.0)


def test_the_reserve_is_measured_on_cpu_not_on_waiting(quad, monkeypatch):
    """A fallback that waits (the machine busy elsewhere, here a sleep) without working: the controller keeps back
    only its CPU time, not the wait."""
    import time

    from flnotes.mpc import controller

    _, cold = _easy_and_cold(quad, n_easy=0)
    mpc = rt.make_mpc(quad, time_limit=0.25)
    real = controller.fallback.fallback_plan

    def waits(*a, **k):
        time.sleep(1.0)
        return real(*a, **k)

    monkeypatch.setattr(controller.fallback, "fallback_plan", waits)
    s = mpc(cold["z"], cold["z_ref"])
    assert s.fallback and s.solve_time >= 1.0
    assert mpc._fallback_s < 0.5, mpc.measured
    assert s.info["cpu_time"] < s.solve_time - 0.5


def test_the_fallback_stops_its_repairs_at_its_deadline(quad):
    """With a deadline already past, the fallback makes only the first input admissible (exact, whatever the time)
    and says that its repairs stopped; without one it repairs as before."""
    import time

    _, cold = _easy_and_cold(quad, n_easy=0)
    pred = rt.make_mpc(quad).pred
    z = cold["z"]
    f, _ = pred.linear(z, cold["z_ref"])
    Z, V, what, ok = fb.fallback_plan(pred, z, None, f=f, deadline=time.perf_counter() - 1.0)
    assert "stopped at the step's deadline" in what
    v_ok, adm = fb.safe_input(pred, z, np.zeros(pred.m))
    assert ok == adm and np.array_equal(V[0], v_ok)
    assert np.array_equal(V[1:], np.zeros((pred.N - 1, pred.m)))  # the rest as guessed, not repaired
    Z2, V2, what2, _ = fb.fallback_plan(pred, z, None, f=f)
    assert "deadline" not in what2


def test_the_warm_up_changes_no_answer(quad):
    """A time-limited controller solves once when it is built (the process's one-off costs): it keeps no history,
    no previous plan and no active steps, and its answers equal those of a controller built without the warm-up."""
    import weakref

    from flnotes.solvers import release_retired, retire

    mpc = rt.make_mpc(quad, time_limit=60.0)
    assert mpc.history == [] and mpc._plan is None and mpc.solver.active_prev == ()
    ref = rt.make_mpc(quad)
    for c in ex.mpc_cases(quad, fl.scale(6, 3), seed=5):
        mpc.reset(), ref.reset()
        a, b = mpc(c["z"], c["z_ref"]), ref(c["z"], c["z_ref"])
        assert a.status == b.status
        if b.status == "optimal":
            assert abs(a.objective - b.objective) <= 1e-6 * max(1.0, abs(b.objective))

    class Model:  # stands for a solver model a step kept alive
        pass

    m = Model()
    dead = weakref.ref(m)
    retire(m)
    del m
    mpc(ex.mpc_cases(quad, 1, seed=5)[0]["z"], np.zeros(quad["system"].n_z))
    assert dead() is None, "the next step frees the models the last one kept"
    release_retired()


def test_plans_at_the_limit_are_measured_against_the_cold_reference(quad):
    """The bench's two distances of a plan returned at the limit: from the optimum the MPC proves without the limit
    (``opt_gap``) and from the cold reference's optimum (``ref_gap``). A plan that passes the forward pass is never
    below the reference's optimum, and the two optima agree (the levers are exact)."""
    from flnotes.bench import deadline as dl

    recs = dl.diverse(quad, fl.scale(8, 4), t_s=TINY, seed=3, fallback_deadline=False)  # the repaired plans
    dl.optimum_gaps(quad, recs, 60.0)
    dl.reference_gaps(quad, recs, 60.0)
    both = [r for r in recs if "ref_gap" in r and np.isfinite(r["ref_gap"]) and np.isfinite(r.get("opt_gap", np.nan))]
    assert len(both) >= 2, "premise: limit hits with a plan, decided by both solves"
    for r in both:
        assert r["ref_gap"] >= -1e-6, r
        assert abs(r["ref_gap"] - r["opt_gap"]) <= 1e-6, r
    row = dl.summarize("diverse", quad["N"], recs, dl.T_S)
    assert row["ref_gap_max"] == max(r["ref_gap"] for r in both)
    # the reference's lower bound bounds the distance from above, also when the reference stops at its limit
    for r in both:
        assert r["ref_bound_gap"] >= r["ref_gap"] - 1e-9, r
    proven = [r for r in recs if "ref_gap" in r and (r["ref_gap"] <= dl.TARGET_GAP or r["ref_bound_gap"] <= dl.TARGET_GAP)]
    assert row["ref_unproven"] == sum("ref_gap" in r for r in recs) - len(proven)
    full = {id(r): r["ref_gap"] for r in both}
    dl.reference_gaps(quad, recs, TINY)
    stopped = [r for r in recs if id(r) in full and np.isnan(r["ref_gap"]) and np.isfinite(r["ref_bound_gap"])]
    assert stopped, "premise: a reference stopped by its limit that returns a lower bound"
    for r in stopped:
        assert r["ref_bound_gap"] >= full[id(r)] - 1e-9, r


def test_late_answers_are_told_apart_by_their_cpu_time():
    """An answer after t_s counts as late by its own work only when its step also used more than t_s of CPU time."""
    from flnotes.bench import deadline as dl

    t = 1e3 * dl.T_S
    recs = [dict(ms=t + 50.0, cpu_ms=t - 40.0), dict(ms=t + 50.0, cpu_ms=t + 10.0), dict(ms=t - 1.0, cpu_ms=t - 2.0)]
    assert [dl.late_by_cpu(r) for r in recs] == [False, True, False]
    base = dict(status="optimal", gap=0.0, fallback=False, plan_admissible=True, input_ok=True, input_flagged=False)
    row = dl.summarize("synthetic", 10, [dict(base, **r) for r in recs])
    assert (row["over_t_s"], row["over_t_s_cpu"]) == (2, 1)


class Gate:
    """Holds the engine's first solver call (``calls`` of them) until :meth:`release`: a solver that overruns its
    limit by as long as the test wants, without any timing in the test. ``then`` replaces the held call's result
    (e.g. an exception to raise); ``mute`` filters the C output while held, as a SCIP call does."""

    def __init__(self, monkeypatch, calls: int = 1, then=None, mute: bool = False, spin: float = 0.0):
        import threading
        import time

        from flnotes.mpc import engine
        from flnotes.solvers import scip

        self.entered, self.released, self.left, self.then = threading.Event(), threading.Event(), calls, then
        real = engine.make_solver

        def make_solver(prob, backend, **kw):
            solver = real(prob, backend, **kw)
            if self.left <= 0:
                return solver
            self.left -= 1
            solve = solver.solve

            def held(*a, **k):
                with scip._quiet_c_output() if mute else contextlib.nullcontext():  # as a SCIP call while it solves
                    c0 = time.thread_time()
                    while time.thread_time() - c0 < spin:   # the held call works first (``spin`` s of CPU)
                        pass
                    self.spun = time.thread_time() - c0
                    self.entered.set()
                    assert self.released.wait(120.0), "the test never released the gate"
                if self.then is not None:
                    raise self.then
                return solve(*a, **k)

            solver.solve = held
            return solver

        monkeypatch.setattr(engine, "make_solver", make_solver)

    def release(self):
        self.released.set()


def engine_state(quad, horizon=15):
    """A state of the book's loop where the engine reaches a solver call with an incumbent (not screened)."""
    setup = rt.quad_setup(horizon=horizon, net=quad["net"], eps=quad["eps"])
    probe = rt.make_mpc(setup)
    z = np.asarray(setup["z0"], float)
    for k in range(40):
        R = setup["reference"](setup["ts"] * (k + np.arange(setup["N"] + 1)))
        prev = probe._plan
        s = probe(z, R)
        if s.rounds >= 1 and s.info.get("incumbent") is not None:
            return setup, z, R, prev, s
        z = probe.pred.Ad @ z + probe.pred.Bd @ s.v
    pytest.fail("premise: a state of the loop that needs a solver call")


def test_a_step_answers_at_its_cut_off_while_the_solver_runs_on(quad, monkeypatch):
    """A solver call held past the limit: the step answers anyway, with the engine's incumbent (checked by the
    forward pass, honest gap, status time_limit, flagged cut_off), while the call is still held; reset waits for the
    held solve to end, and the controller then solves to the same optimum as one without a limit."""
    from flnotes.mpc import controller

    setup, z, R, prev, exact = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=5.0)
    assert mpc.cut_off, "the cut-off is on by default under a time limit"
    gate = Gate(monkeypatch, mute=True)
    mpc.set_previous_plan(prev)
    real_faults = controller.major_faults
    first = []

    def slow_set_up():  # the call's set-up, before the step's own work, takes 50 ms (enter_time)
        if not first:
            first.append(time.sleep(0.05))
        return real_faults()

    monkeypatch.setattr(controller, "major_faults", slow_set_up)
    window = mpc.time_limit - mpc._cut_off(0.0)  # the time kept for the answer (nothing measured yet: no decay)
    s = mpc(z, R)
    assert s.info["enter_time"] >= 0.05, s.info
    # the cut-off counts from the call's start: the set-up is part of the caller's wait, not added after the limit
    assert abs(s.info["enter_time"] + s.info["cut_off_s"] - (mpc.time_limit - window)) <= 1e-9, (s.info, window)
    assert gate.entered.is_set() and not gate.released.is_set(), "premise: the answer came while the solver was held"
    from flnotes.solvers import scip

    assert scip.c_output_filtered(), "the held call's filter of the C output stays while the call runs on"
    assert s.status == "time_limit" and s.info["cut_off"], s.message
    assert check_step(mpc, s) and not s.fallback and s.input_admissible, s.message
    # the record accounts for the whole wall time of the call, and the answer's time after it resumed is split into
    # its CPU, its wait for a core and the rest (never below zero: the three readings of each end are in order)
    parts = ("enter_time", "cut_off_s", "wake_lag", "after_wake", "exit_time")
    assert abs(sum(s.info[k] for k in parts) - s.solve_time) <= 1e-3, ({k: s.info[k] for k in parts}, s.solve_time)
    assert all(s.info[k] >= 0.0 for k in parts) and s.info["after_wake_blocked"] >= -1e-4, s.info
    assert s.objective >= exact.objective - 1e-6 * max(1.0, abs(exact.objective))  # never below the optimum
    assert s.bound <= exact.objective + 1e-6 * max(1.0, abs(exact.objective))
    assert mpc._running is not None, "the held solve is still running"
    gate.release()
    mpc.reset()  # waits for the held solve first (outside any step's budget: the held solve ran on a shared machine)
    assert mpc._running is None
    mpc.set_previous_plan(prev)
    again = mpc(z, R)
    assert mpc._running is None and not again.info["cut_off"]
    assert again.status == "optimal", again.message
    assert abs(again.objective - exact.objective) <= 1e-6 * max(1.0, abs(exact.objective))
    mpc.solver.go()  # what a step does before it starts a solve: an answer read then has no plan of an earlier state
    assert mpc.solver.answer_now().v is None


def test_the_record_of_a_cut_off_step_ends_after_the_held_solve_is_released(quad, monkeypatch):
    """At a cut-off the step releases the held solve (``answered``) as its last act; the released solve's thread may
    take the interpreter lock at once, and the answering thread's wait for it is the caller's wait: ``solve_time``
    (and ``exit_time``) include it, and the parts of the record still sum to ``solve_time``."""
    setup, z, R, prev, exact = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=2.0)
    gate = Gate(monkeypatch, mute=True)
    mpc.set_previous_plan(prev)
    real_answered = mpc.solver.answered

    def answered_then_held():  # as if the released solve's thread held the lock for 60 ms
        real_answered()
        time.sleep(0.06)

    monkeypatch.setattr(mpc.solver, "answered", answered_then_held)
    w0 = time.perf_counter()
    s = mpc(z, R)
    wall = time.perf_counter() - w0
    assert s.info["cut_off"] and gate.entered.is_set(), "premise: the answer came at the cut-off"
    assert s.info["exit_time"] >= 0.06 and wall - 0.005 <= s.solve_time <= wall, (s.info["exit_time"], s.solve_time, wall)
    parts = ("enter_time", "cut_off_s", "wake_lag", "after_wake", "exit_time")
    assert abs(sum(s.info[k] for k in parts) - s.solve_time) <= 1e-3, ({k: s.info[k] for k in parts}, s.solve_time)
    gate.release()
    mpc.reset()


def test_a_held_solve_released_by_the_answer_sleeps_before_it_builds_its_result(quad, monkeypatch):
    """A solve stopped with hold=True waits for answered(); once released it sleeps ANSWER_GRACE_S before it builds its
    result (the answering thread returns with the interpreter lock meanwhile); a solve that reaches its end after the
    answer was given builds it at once."""
    from flnotes.mpc import engine as E

    setup, z, R, prev, exact = engine_state(quad)
    eng = rt.make_mpc(setup).solver
    starts = []
    real = E._step_result

    def recorded(*a, **k):
        starts.append(time.perf_counter())
        return real(*a, **k)

    monkeypatch.setattr(E, "_step_result", recorded)
    eng.go()
    eng.stop(hold=True)  # this thread answers; the solve runs in another
    out = {}
    th = threading.Thread(target=lambda: out.update(r=eng.solve(z, R)))
    th.start()
    time.sleep(0.3)
    assert th.is_alive() and not starts, "premise: the stopped solve waits for the answer"
    t_answer = time.perf_counter()
    eng.answered()
    th.join(5.0)
    assert not th.is_alive() and len(starts) == 1 and starts[0] - t_answer >= E.ANSWER_GRACE_S, (starts, t_answer)
    assert out["r"].status == "time_limit"
    sleeps = []
    monkeypatch.setattr(E.time, "sleep", lambda s: sleeps.append(s))
    eng.go()
    eng.stop(hold=True)
    eng.answered()  # answered before the solve ends: no wait, no sleep
    th = threading.Thread(target=lambda: out.update(r=eng.solve(z, R)))
    th.start()
    th.join(5.0)
    assert len(starts) == 2 and not sleeps, sleeps


def test_a_step_waits_for_the_previous_solve_until_its_own_cut_off_only(quad, monkeypatch):
    """The solve a step answered at its cut-off runs on (held) through the next step: that step does not wait for it
    past its own cut-off. It answers while the held solve still runs, without a solve (status time_limit, the fallback
    flagged, ``previous_ran_on``), with an admissible input and a plan that passes the checks. Once the held solve
    has ended, the next step waits for it and solves to the optimum of a controller without a limit."""
    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=5.0)  # far above the solve on any machine: the last step is optimal
    gate = Gate(monkeypatch)
    mpc.set_previous_plan(prev)
    s = mpc(z, R)
    assert gate.entered.is_set() and s.info["cut_off"] and mpc._running is not None, "premise: held at the answer"
    assert not s.info["previous_ran_on"] and s.info["previous_wait"] >= 0.0
    z1 = mpc.pred.Ad @ z + mpc.pred.Bd @ s.v
    try:
        s1 = mpc(z1, R)
        assert not gate.released.is_set() and mpc._running is not None, "answered while the held solve ran on"
    finally:
        gate.release()
    assert s1.info["previous_ran_on"] and s1.info["cut_off"], s1.info
    assert s1.status == "time_limit" and s1.fallback and "ran on" in s1.message, s1.message
    assert s1.info["previous_wait"] < mpc.time_limit  # it stopped waiting at its cut-off, before the limit
    parts = ("enter_time", "cut_off_s", "wake_lag", "after_wake", "exit_time")  # the whole call, as at a cut-off
    assert abs(sum(s1.info[k] for k in parts) - s1.solve_time) <= 1e-3, ({k: s1.info[k] for k in parts}, s1.solve_time)
    assert all(s1.info[k] >= 0.0 for k in parts) and 0.0 <= s1.info["after_wake_blocked"] + 1e-4, s1.info
    assert check_step(mpc, s1) and s1.input_admissible and s1.info["plan_feasible"], s1.message
    assert s1.info["post_runqueue"] >= 0.0 or not np.isfinite(fl.config.thread_run_delay())
    exact = rt.make_mpc(setup)
    exact.set_previous_plan(mpc._plan)
    best = exact(z1, R)
    s2 = mpc(z1, R)  # the held solve has been released: this step waits for its end, then solves
    assert mpc._running is None and not s2.info["previous_ran_on"], s2.info
    assert s2.status == best.status == "optimal", (s2.message, best.message)
    assert abs(s2.objective - best.objective) <= 1e-6 * max(1.0, abs(best.objective))


@pytest.mark.skipif(not hasattr(__import__("signal"), "raise_signal"), reason="needs signal.raise_signal")
def test_ctrl_c_inside_a_time_limited_step_is_raised_once_every_setting_is_back(quad, monkeypatch):
    """Ctrl-C (SIGINT) that arrives while a time-limited step sets the process-wide settings back (here as the
    collector is resumed, and as finish() sets back the switch interval a held solve kept) is held back until they
    are back, then raised as KeyboardInterrupt: the collector runs again and the switch interval is what it was."""
    import gc
    import signal

    from flnotes import config

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=5.0, cut_off=False)
    real_resume = config.resume_gc

    def resume_with_ctrl_c():
        signal.raise_signal(signal.SIGINT)  # delivered by the handler at the next line of Python, unless held back
        real_resume()

    monkeypatch.setattr(config, "resume_gc", resume_with_ctrl_c)  # as the step's end calls it
    assert gc.isenabled(), "premise: the collector runs outside the step"
    mpc.set_previous_plan(prev)
    with pytest.raises(KeyboardInterrupt):
        mpc(z, R)
    assert gc.isenabled() and config._GC_USERS == 0 and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    monkeypatch.undo()
    real_pause = config.pause_gc

    def pause_with_ctrl_c():  # just after the collector is paused, in mpc(...) and in mpc.step inside a loop
        real_pause()
        signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(config, "pause_gc", pause_with_ctrl_c)  # as the step's start calls it
    for call in (lambda: mpc(z, R), lambda: mpc.step(z, 0.0)):
        with pytest.raises(KeyboardInterrupt):
            call()
        mpc.finish()
        assert gc.isenabled() and config._GC_USERS == 0 and config._GC_LOCK.acquire(blocking=False)
        config._GC_LOCK.release()
    monkeypatch.undo()

    before = sys.getswitchinterval()
    mpc = rt.make_mpc(setup, time_limit=5.0)
    gate = Gate(monkeypatch)
    mpc.set_previous_plan(prev)
    s = mpc(z, R)
    assert s.info["cut_off"] and mpc._held.stack is not None, "premise: the settings are kept for the held solve"
    gate.release()
    real_set = sys.setswitchinterval

    def set_with_ctrl_c(value):
        signal.raise_signal(signal.SIGINT)
        real_set(value)

    monkeypatch.setattr(sys, "setswitchinterval", set_with_ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        mpc.finish()
    monkeypatch.undo()
    assert sys.getswitchinterval() == before and mpc._held.stack is None and gc.isenabled()
    assert config._GC_USERS == 0 and signal.getsignal(signal.SIGINT) is signal.default_int_handler


class _Handlers:
    """Python handlers that record each call with what ``probe()`` says then: SIGALRM's raises ``TimeoutError`` (as a
    timeout does), SIGINT's ``KeyboardInterrupt`` (as Python's default does), SIGUSR1's and SIGUSR2's only count.
    :meth:`restore` puts the handlers before back."""

    def __init__(self, probe=lambda: None):
        import signal

        self.calls, self.probe = [], probe
        self.before = {s: signal.getsignal(s) for s in (signal.SIGALRM, signal.SIGUSR1, signal.SIGUSR2,
                                                        signal.SIGINT)}

        def alarm(signum, frame):
            self.calls.append(("alarm", self.probe()))
            raise TimeoutError("the caller's timeout")

        def ctrl_c(signum, frame):
            self.calls.append(("sigint", self.probe()))
            raise KeyboardInterrupt

        def usr1(signum, frame):
            self.calls.append(("usr1", self.probe()))

        def usr2(signum, frame):
            self.calls.append(("usr2", self.probe()))

        self.alarm, self.ctrl_c, self.usr1, self.usr2 = alarm, ctrl_c, usr1, usr2
        self.mine = {signal.SIGALRM: alarm, signal.SIGINT: ctrl_c, signal.SIGUSR1: usr1, signal.SIGUSR2: usr2}
        for sig, h in self.mine.items():
            signal.signal(sig, h)

    def all_back(self) -> bool:
        """Every handler is this object's own again, nothing is held or noted."""
        import signal

        from flnotes import config

        return (all(signal.getsignal(sig) is h for sig, h in self.mine.items()) and not config._HOLDING
                and not config._DEFERRED and all(o is None for o in config._OLD))

    def next_hold_leaves_all_back(self) -> bool:
        """A later step's hold and release (no signal meanwhile) work and leave every handler back."""
        from flnotes import config

        held = config.hold_signals()
        if held is None:
            return False
        config.release_signals(held)
        return self.all_back()

    def restore(self):
        import signal

        for sig, h in self.before.items():
            signal.signal(sig, h)


needs_signals = pytest.mark.skipif(not all(hasattr(__import__("signal"), n) for n in ("SIGALRM", "SIGUSR1",
                                                                                      "raise_signal")),
                                   reason="needs SIGALRM, SIGUSR1 and signal.raise_signal")


@needs_signals
def test_a_handlers_exception_inside_a_time_limited_step_is_raised_once_the_step_has_answered(quad, monkeypatch):
    """Other signals than Ctrl-C that Python handles (a timeout's SIGALRM whose handler raises, a SIGUSR1 that counts)
    arriving while a time-limited step waits for its solve's thread are held back too: the step answers at its
    cut-off and records its answer, then the handlers run and the timeout's exception is raised by the call. Nothing
    is left waiting: finish() ends the solve and the next step solves to the optimum. (Unheld, the handler ran inside
    the step, which never answered; inside a threading primitive such an exception once left the solve's thread, then
    finish(), waiting for good.)"""
    import signal

    from flnotes import config

    setup, z, R, prev, exact = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=5.0)  # far above the solve on any machine: the next step is optimal
    gate = Gate(monkeypatch, mute=True)
    h = _Handlers(probe=lambda: len(mpc.history))

    def fire():  # from another thread while the step waits for its solve: Python runs the handlers in the main thread
        assert gate.entered.wait(30.0), "the solve never reached its solver call"
        for s in (signal.SIGUSR1, signal.SIGALRM):
            signal.raise_signal(s)

    shooter = threading.Thread(target=fire)
    try:
        mpc.set_previous_plan(prev)
        shooter.start()
        with pytest.raises(TimeoutError, match="caller's timeout"):
            mpc(z, R)
        shooter.join()
        assert len(mpc.history) == 1 and mpc.history[0].info["cut_off"], "the step answered at its cut-off"
        check_step(mpc, mpc.history[0])
        assert sorted(h.calls) == [("alarm", 1), ("usr1", 1)], "each handler once, after the step had answered"
        assert signal.getsignal(signal.SIGALRM) is h.alarm and signal.getsignal(signal.SIGUSR1) is h.usr1
        gate.release()
        ender = threading.Thread(target=mpc.finish, daemon=True)
        ender.start()
        ender.join(60.0)
        assert not ender.is_alive(), "finish() waits for good"
        assert gc_running() and config._GC_USERS == 0
        s = mpc(z, R)
        assert s.status == "optimal" and abs(s.objective - exact.objective) <= 1e-6 * max(1.0, abs(exact.objective))
        mpc.finish()
    finally:
        gate.release()
        h.restore()


def gc_running() -> bool:
    import gc

    return gc.isenabled()


@needs_signals
def test_signals_held_back_are_all_delivered_in_order_even_when_a_handler_raises():
    """hold_signals/release_signals directly: while held, nothing runs; at the release every signal that came is
    delivered (each arrival), in the order they came, and a handler that raises does not keep a later signal from its
    handler.
    A nested hold and a hold from another thread change nothing; a handler set while held is kept, and a signal held
    before it is delivered to the handler in place when it came."""
    import signal

    from flnotes import config

    h = _Handlers(probe=lambda: config._HOLDING)
    try:
        held = config.hold_signals()
        assert held is not None and signal.getsignal(signal.SIGALRM) is not h.alarm, "premise: held"
        assert config.hold_signals() is None, "a nested hold changes nothing"
        other = []
        t = threading.Thread(target=lambda: other.append(config.hold_signals()))
        t.start()
        t.join()
        assert other == [None], "only the main thread holds"
        for sig in (signal.SIGALRM, signal.SIGUSR1, signal.SIGALRM, signal.SIGUSR2):
            signal.raise_signal(sig)
        assert h.calls == [], "nothing runs while held"
        signal.signal(signal.SIGUSR2, h.usr1)  # code inside the step sets a handler of its own
        with pytest.raises(TimeoutError):
            config.release_signals(held)
        assert h.calls == [("alarm", False), ("usr1", False), ("alarm", False), ("usr2", False)], \
            "in the order they came, each arrival, to the handler in place when it came, after the hold"
        assert signal.getsignal(signal.SIGUSR2) is h.usr1, "the handler set while held is kept"
        signal.signal(signal.SIGUSR2, h.usr2)
        assert h.all_back()
    finally:
        h.restore()


@needs_signals
def test_a_signal_that_comes_as_the_hold_begins_leaves_nothing_held(monkeypatch):
    """A handler not yet replaced that raises while hold_signals goes through the handlers (here SIGALRM's, raised
    when SIGUSR1's is already held): the exception comes out of hold_signals, every handler is back, the signal held
    meanwhile is delivered after it, and the next hold works."""
    import _signal
    import signal

    from flnotes import config

    h = _Handlers()
    real = _signal.getsignal
    fired = []

    def getsignal(s):
        if s == int(signal.SIGALRM) and not fired:  # SIGUSR1 (10) is already held when SIGALRM (14) is read
            fired.append(s)
            signal.raise_signal(signal.SIGUSR1)  # held back
            _signal.raise_signal(signal.SIGALRM)  # its own handler, not yet replaced: raises here
        return real(s)

    try:
        assert int(signal.SIGUSR1) < int(signal.SIGALRM), "premise: the hold reads SIGUSR1 first"
        monkeypatch.setattr(_signal, "getsignal", getsignal)
        with pytest.raises(TimeoutError):
            config.hold_signals()
        monkeypatch.undo()
        assert [c[0] for c in h.calls] == ["alarm", "usr1"], "the signal held meanwhile is delivered after"
        assert h.all_back()
        assert h.next_hold_leaves_all_back()
    finally:
        monkeypatch.undo()
        h.restore()


@needs_signals
@pytest.mark.parametrize("when", ["delivering", "restoring"])
def test_a_release_cut_short_by_a_handler_loses_no_signal_and_no_handler(when, monkeypatch):
    """Ctrl-C that comes while release_signals ends the hold ("delivering": inside the handler of a signal held before,
    SIGUSR1; "restoring": just after SIGINT's own handler is back, SIGALRM's not yet) raises KeyboardInterrupt out of
    the release, after the signal held before it; none is left noted, and every handler is back, also those after
    SIGINT's."""
    import _signal
    import signal

    from flnotes import config

    h = _Handlers(probe=lambda: config._HOLDING)
    real_signal = _signal.signal
    fired = []

    def usr1_then_ctrl_c(signum, frame):
        h.usr1(signum, frame)
        if when == "delivering" and not fired:
            fired.append(signum)
            signal.raise_signal(signal.SIGINT)

    def signal_then_ctrl_c(s, handler):  # Ctrl-C just after SIGINT's own handler is back
        out = real_signal(s, handler)
        if s == int(signal.SIGINT) and handler is h.ctrl_c and not fired:
            fired.append(s)
            signal.raise_signal(signal.SIGINT)
        return out

    h.mine[signal.SIGUSR1] = usr1_then_ctrl_c
    signal.signal(signal.SIGUSR1, usr1_then_ctrl_c)
    try:
        held = config.hold_signals()
        signal.raise_signal(signal.SIGUSR1)  # held
        if when == "restoring":
            monkeypatch.setattr(_signal, "signal", signal_then_ctrl_c)
        with pytest.raises(KeyboardInterrupt):
            config.release_signals(held)
        monkeypatch.undo()
        assert h.calls == [("usr1", False), ("sigint", False)], "the signal held first is delivered first"
        assert h.all_back(), "every handler is back, also those after the one whose handler raised"
        assert h.next_hold_leaves_all_back()
    finally:
        monkeypatch.undo()
        h.restore()


@needs_signals
def test_a_handler_left_by_a_release_cut_short_is_put_back_at_its_next_signal_or_by_the_next_hold(monkeypatch):
    """A release cut short before any handler is back (an exception escaping it at its start: two signals at once can
    do that): SIGALRM's next arrival puts its handler back and delivers to it at once; the next step (hold and
    release) never takes a handler the hold left in place for the caller's, and its end puts the others back."""
    import signal

    from flnotes import config

    h = _Handlers(probe=lambda: config._HOLDING)

    def cut_short():
        raise KeyboardInterrupt

    try:
        held = config.hold_signals()
        monkeypatch.setattr(config, "_restore", cut_short)
        with pytest.raises(KeyboardInterrupt):
            config.release_signals(held)
        monkeypatch.undo()
        assert signal.getsignal(signal.SIGALRM) is not h.alarm, "premise: no handler was put back"
        with pytest.raises(TimeoutError):
            signal.raise_signal(signal.SIGALRM)
        assert h.calls == [("alarm", False)] and signal.getsignal(signal.SIGALRM) is h.alarm
        assert signal.getsignal(signal.SIGUSR1) is not h.usr1, "premise: the others are still left"
        held = config.hold_signals()
        signal.raise_signal(signal.SIGUSR1)
        assert len(h.calls) == 1, "held by the next hold"
        config.release_signals(held)
        assert h.calls[-1] == ("usr1", False) and h.all_back()
    finally:
        monkeypatch.undo()
        h.restore()


@needs_signals
def test_a_handler_put_back_late_survives_another_handlers_exception_as_it_is_put_back(monkeypatch):
    """A handler the hold left in place (a release cut short) is put back at its signal's next arrival; when another
    signal's handler raises just then (inside that signal.signal call, before it changes anything), the saved handler
    is kept for a later try: the next arrival still reaches the caller's handler and puts it back."""
    import _signal
    import signal

    from flnotes import config

    h = _Handlers(probe=lambda: config._HOLDING)
    real_signal = _signal.signal
    fired = []

    def cut_short():
        raise KeyboardInterrupt

    def alarm_first(s, handler):  # SIGALRM's own handler (put back already) raises as SIGUSR1's is put back
        if s == int(signal.SIGUSR1) and handler is h.usr1 and not fired:
            fired.append(s)
            _signal.raise_signal(signal.SIGALRM)
        return real_signal(s, handler)

    try:
        held = config.hold_signals()
        monkeypatch.setattr(config, "_restore", cut_short)
        with pytest.raises(KeyboardInterrupt):
            config.release_signals(held)
        monkeypatch.undo()
        with pytest.raises(TimeoutError):
            signal.raise_signal(signal.SIGALRM)  # puts SIGALRM's back
        monkeypatch.setattr(_signal, "signal", alarm_first)
        with pytest.raises(TimeoutError):
            signal.raise_signal(signal.SIGUSR1)  # noted, and put back -- cut short by the alarm
        monkeypatch.undo()
        assert signal.getsignal(signal.SIGUSR1) is not h.usr1, "premise: SIGUSR1's handler was not put back"
        signal.raise_signal(signal.SIGUSR1)
        assert [c[0] for c in h.calls].count("usr1") == 2, "both arrivals reached the caller's handler"
        assert signal.getsignal(signal.SIGUSR1) is h.usr1 and h.next_hold_leaves_all_back()
    finally:
        monkeypatch.undo()
        h.restore()


@needs_signals
@pytest.mark.parametrize("where", ["hold", "release"])
def test_a_handler_that_a_signal_sets_as_the_hold_begins_or_ends_is_kept(where, monkeypatch):
    """A two-stage handler (the first SIGUSR1 sets a second handler) whose signal comes inside the signal.signal call
    that replaces or puts back its handler: the handler it set is the one held, and the one in place after the call."""
    import _signal
    import signal

    from flnotes import config

    h = _Handlers(probe=lambda: config._HOLDING)
    real_signal = _signal.signal
    fired, stages = [], []

    def second(signum, frame):
        stages.append("second")

    def first(signum, frame):
        stages.append("first")
        real_signal(signum, second)

    def signal_with_usr1(s, handler):  # SIGUSR1 comes just as its handler is replaced (hold) or put back (release)
        if s == int(signal.SIGUSR1) and (handler is config._hold) == (where == "hold") and not fired:
            fired.append(s)
            if where == "release":
                real_signal(s, first)  # its own handler again, as SIGUSR1 comes (the hold's end)
            _signal.raise_signal(signal.SIGUSR1)
        return real_signal(s, handler)

    signal.signal(signal.SIGUSR1, first)
    try:
        if where == "hold":
            monkeypatch.setattr(_signal, "signal", signal_with_usr1)
        held = config.hold_signals()
        monkeypatch.undo()
        if where == "release":
            monkeypatch.setattr(_signal, "signal", signal_with_usr1)
        config.release_signals(held)
        monkeypatch.undo()
        assert stages == ["first"] and signal.getsignal(signal.SIGUSR1) is second, "the handler it set is kept"
        assert not config._HOLDING and not config._DEFERRED and all(o is None for o in config._OLD)
    finally:
        monkeypatch.undo()
        h.restore()


@needs_signals
@pytest.mark.skipif(not hasattr(__import__("signal"), "pthread_kill"), reason="needs signal.pthread_sigmask, pthread_kill")
def test_a_held_signal_reaches_its_handler_also_when_the_main_thread_blocks_it():
    """A signal held while the main thread blocks it (it came to another thread) is delivered by a direct call to its
    handler, not raised again in the main thread, where it would stay pending."""
    import signal

    from flnotes import config

    h = _Handlers(probe=lambda: config._HOLDING)
    go = threading.Event()
    t = threading.Thread(target=go.wait)  # started before the block: it lets the signal in
    t.start()
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGUSR1})
    try:
        held = config.hold_signals()
        signal.pthread_kill(t.ident, signal.SIGUSR1)
        go.set()
        t.join()
        time.sleep(0.01)  # a line of Python after the signal: the main thread notes it (held)
        config.release_signals(held)
        assert h.calls == [("usr1", False)] and signal.SIGUSR1 not in signal.sigpending()
        assert h.all_back()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
        h.restore()


def _one_c_call(seconds: float) -> int:
    """``n`` such that ``sum(range(n))``, one C call that holds the interpreter lock until it returns, takes about
    ``seconds`` on this machine (timed on a call of 10^6)."""
    t = time.perf_counter()
    sum(range(10 ** 6))
    return int(1e6 * seconds / max(time.perf_counter() - t, 1e-6))


def _held_step(mpc, z, R, prev, holding, monkeypatch):
    """One step of ``mpc`` from ``prev`` with its engine's solve replaced by ``holding``; the held solve is waited for
    (and the settings the step kept for it come back). Returns the step and when it started."""
    monkeypatch.setattr(mpc.solver, "solve", holding)
    mpc.set_previous_plan(prev)
    t0 = time.perf_counter()
    try:
        s = mpc(z, R)
    finally:
        mpc.finish()
    return s, t0


def test_a_late_resume_of_the_answering_thread_is_recorded(quad, monkeypatch):
    """The engine's thread holds the interpreter lock in one C call (a long sum over a range) past the limit: the
    answering thread cannot resume at its cut-off, and the record says so. ``wake_lag`` covers at least the time from
    the limit to the end of that call, and ``wake_runqueue`` (Linux) is far below it: the thread was not waiting
    for a core, so the late answer is not the controller's work. A step without such a call records both too."""
    import time

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=0.2)
    mpc.set_previous_plan(prev)
    plain = mpc(z, R)
    assert plain.info["wake_lag"] >= 0.0 and "wake_runqueue" in plain.info, plain.info
    mpc.reset()
    n = _one_c_call(1.0)  # about 1 s in one call
    solve, held = mpc.solver.solve, {}

    def holding(*a, **k):
        sum(range(n))  # one C call: the lock is not released until it returns
        held["end"] = time.perf_counter()
        return solve(*a, **k)

    s, t0 = _held_step(mpc, z, R, prev, holding, monkeypatch)
    # the engine's thread notes the end just after the call returns, when the answer may already have resumed
    over = held["end"] - (t0 + mpc.time_limit)
    assert over > 0.1, "premise: the held call ran on past the limit"
    assert s.info["wake_lag"] >= 0.9 * over, (s.info, over)
    if np.isfinite(s.info["wake_runqueue"]):
        assert s.info["wake_runqueue"] < 0.5 * s.info["wake_lag"], s.info
    assert check_step(mpc, s) and s.input_admissible, s.message


def test_a_wait_for_the_lock_after_the_answer_resumed_is_recorded(quad, monkeypatch):
    """After the answering thread has resumed at its cut-off, the engine's thread (asked to stop) holds the interpreter
    lock in one C call: the answer waits for it. ``after_wake`` covers that call and ``after_wake_blocked`` (neither
    running nor waiting for a core) says that the time went to a wait, not to the answer's own work."""
    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=0.2)
    mpc.set_previous_plan(prev)
    plain = mpc(z, R)
    assert plain.info["after_wake"] >= 0.0 and "after_wake_blocked" in plain.info, plain.info
    mpc.reset()
    n = _one_c_call(0.3)  # about 0.3 s in one call
    solve, answer_now, held = mpc.solver.solve, mpc.solver.answer_now, {}

    def holding(*a, **k):
        while not mpc.solver._stop.is_set():  # the answer's cut-off: the step asks the engine to stop
            time.sleep(1e-3)
        held["start"] = time.perf_counter()
        sum(range(n))  # one C call: the lock is not released until it returns
        held["end"] = time.perf_counter()
        return solve(*a, **k)

    def late_answer():
        time.sleep(0.02)  # the engine's thread takes the lock meanwhile
        return answer_now()

    monkeypatch.setattr(mpc.solver, "answer_now", late_answer)
    s, t0 = _held_step(mpc, z, R, prev, holding, monkeypatch)
    assert s.info["cut_off"] and held["start"] < t0 + s.solve_time, "premise: the C call started before the answer"
    hold = held["end"] - held["start"]
    assert s.info["after_wake"] >= 0.9 * hold and s.info["after_wake_blocked"] >= 0.6 * hold or \
        not np.isfinite(fl.config.thread_run_delay()), (s.info, hold)
    assert check_step(mpc, s) and s.input_admissible, s.message


@pytest.mark.parametrize("reading, key, start, step", [("major_faults", "major_faults", 100.0, 3.0),
                                                          ("machine_steal", "steal_time", 7.0, 0.03)])
def test_the_machines_time_during_a_step_is_recorded(quad, monkeypatch, reading, key, start, step):
    """The machine's time during the call, not the controller's, is recorded as the difference of two readings taken
    around the step (here a counter that the engine's held solve advances by ``step``), with and without a limit:
    ``info["major_faults"]``, the process's major page faults (pages read back from disk,
    :func:`flnotes.config.major_faults`), and ``info["steal_time"]``, the seconds the host of a virtual machine took
    its CPUs (:func:`flnotes.config.machine_steal`)."""
    from flnotes.mpc import controller

    setup, z, R, prev, _ = engine_state(quad)
    for limit in (None, 0.5):
        mpc = rt.make_mpc(setup, time_limit=limit)
        counter = {"n": start}
        monkeypatch.setattr(controller, reading, lambda: counter["n"])
        solve = mpc.solver.solve

        def advancing(*a, **k):
            counter["n"] += step
            return solve(*a, **k)

        s, _ = _held_step(mpc, z, R, prev, advancing, monkeypatch)
        assert abs(s.info[key] - step) < 1e-12, (limit, s.info[key])
        monkeypatch.undo()
        mpc.set_previous_plan(prev)
        assert mpc(z, R).info[key] >= 0.0 or not np.isfinite(getattr(fl.config, reading)())


def test_machine_steal_reads_the_steal_column_in_seconds(tmp_path, monkeypatch):
    """:func:`flnotes.config.machine_steal` is the 8th number of ``/proc/stat``'s ``cpu`` line over the clock ticks
    per second; NaN for a file without that column, another first line, or no file (not Linux)."""
    from flnotes import config

    hz = config._TICKS_PER_SECOND
    stat = tmp_path / "stat"
    monkeypatch.setattr(config, "_PROC_STAT", str(stat))
    stat.write_bytes(b"cpu  5193880 49023 256132 2427607 5082 0 2580 6687 0 0\ncpu0 1 2 3 4 5 6 7 8 9 10\n")
    assert config.machine_steal() == 6687 / hz
    stat.write_bytes(b"cpu  5193880 49023 256132 2427607 5082 0 2580\n")  # an old kernel: no steal column
    assert np.isnan(config.machine_steal())
    stat.write_bytes(b"intr 1 2 3 4 5 6 7 8 9\n")
    assert np.isnan(config.machine_steal())
    stat.unlink()
    assert np.isnan(config.machine_steal())
    monkeypatch.undo()
    if sys.platform.startswith("linux"):  # the real file: a count that never decreases
        first = config.machine_steal()
        assert np.isfinite(first) and 0.0 <= first <= config.machine_steal()

def test_the_engine_threads_wait_for_a_core_is_recorded(quad, monkeypatch):
    """The engine's thread holds the interpreter lock in one C call past the limit while it shares one core with a
    busy process: the answering thread resumes late without waiting for a core itself, and ``engine_runqueue`` says
    that the engine's thread waited for a core meanwhile (a loaded machine, not the controller's work). A step
    without it records the figure too."""
    import os
    import subprocess
    import sys
    import time

    if not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2 \
            or not np.isfinite(fl.config.thread_run_delay()):
        pytest.skip("needs Linux's per-thread scheduler statistics and two cores")
    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=0.2)
    mpc.set_previous_plan(prev)
    plain = mpc(z, R)
    assert plain.info["engine_runqueue"] >= 0.0, plain.info
    mpc.reset()
    core = min(os.sched_getaffinity(0))
    n = _one_c_call(0.6)  # about 0.6 s of CPU in one call
    solve, held = mpc.solver.solve, {}

    def holding(*a, **k):
        os.sched_setaffinity(0, {core})  # this thread only: on the busy process's core
        sum(range(n))  # one C call: the lock is not released until it returns
        held["end"] = time.perf_counter()
        return solve(*a, **k)

    busy = subprocess.Popen([sys.executable, "-c", f"import os; os.sched_setaffinity(0, {{{core}}})\nwhile True: pass"])
    try:
        time.sleep(0.2)
        s, t0 = _held_step(mpc, z, R, prev, holding, monkeypatch)
    finally:
        busy.kill()
        busy.wait()
    over = held["end"] - (t0 + mpc.time_limit)
    assert over > 0.1, "premise: the held call ran on past the limit"
    assert s.info["wake_lag"] >= 0.9 * over and s.info["wake_runqueue"] < 0.5 * s.info["wake_lag"], s.info
    assert s.info["engine_runqueue"] >= 0.2, s.info  # it shared its core: about half of its 0.6 s call and more


def test_the_cpu_time_of_a_cut_off_step_counts_the_engine_thread(quad, monkeypatch):
    """A step answered at its cut-off while its solver call runs on: ``info["cpu_time"]`` counts the CPU time the
    engine's thread used before the answer (here 0.2 s of work in the held call), not only the answering thread's."""
    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=2.0)
    gate = Gate(monkeypatch, spin=0.2)
    mpc.set_previous_plan(prev)
    s = mpc(z, R)
    assert gate.entered.is_set() and s.info["cut_off"], "premise: the answer came while the held call waited"
    assert s.info["engine_cpu_time"] >= gate.spun >= 0.2, s.info
    assert s.info["cpu_time"] >= s.info["engine_cpu_time"], s.info
    assert s.info["cpu_time"] <= s.solve_time + 0.05, "no more CPU than two threads could use: one waited"
    gate.release()
    mpc.reset()
    mpc.set_previous_plan(prev)
    again = mpc(z, R)
    assert not again.info["cut_off"] and again.info["engine_cpu_time"] <= again.info["cpu_time"], again.info


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a thread's own nice value is Linux's")
def test_at_the_cut_off_the_engine_thread_yields_its_core_to_the_answer(quad, monkeypatch):
    """At the cut-off the engine's thread, held in its solver call, is lowered to nice CUT_OFF_NICE (it shares a
    core with the answer less); the answering thread keeps its priority, and the next step's engine thread starts
    at the process's own priority again."""
    from flnotes.config import CUT_OFF_NICE

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=2.0)
    gate = Gate(monkeypatch)
    mpc.set_previous_plan(prev)
    own = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    s = mpc(z, R)
    assert gate.entered.is_set() and s.info["cut_off"], "premise: the answer came while the held call waited"
    tid = mpc._running[1]["tid"]
    assert s.info["engine_yielded"] is True
    assert os.getpriority(os.PRIO_PROCESS, tid) == max(own, CUT_OFF_NICE)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == own      # the answering thread's is kept
    gate.release()
    mpc.reset()
    seen = {}
    real = mpc.solver.solve

    def spy(*a, **k):
        seen["nice"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        return real(*a, **k)

    monkeypatch.setattr(mpc.solver, "solve", spy)
    mpc.set_previous_plan(prev)
    again = mpc(z, R)
    assert not again.info["cut_off"] and "engine_yielded" not in again.info
    assert seen["nice"] == own                                                     # a new thread, not lowered


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a thread's own nice value is Linux's")
def test_yield_core_lowers_one_thread_only_and_says_when_it_cannot():
    from flnotes.config import yield_core

    go, ids = threading.Event(), {}

    def wait():
        ids["tid"] = threading.get_native_id()
        go.wait(30.0)

    t = threading.Thread(target=wait)
    t.start()
    while "tid" not in ids:
        time.sleep(0.001)
    own = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    assert yield_core(ids["tid"], nice=max(own, 7)) is True
    assert os.getpriority(os.PRIO_PROCESS, ids["tid"]) == max(own, 7)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == own
    assert yield_core(ids["tid"], nice=max(own, 3)) is True                         # never raised back
    assert os.getpriority(os.PRIO_PROCESS, ids["tid"]) == max(own, 7)
    go.set()
    t.join()
    assert yield_core(None) is False


def _custom_slices() -> bool:
    """Does this machine's kernel give a thread of the normal policy the slice it asks for (EEVDF, Linux 6.12+)?"""
    import platform
    import re

    m = re.match(r"(\d+)\.(\d+)", os.uname().release) if hasattr(os, "uname") else None
    if not (sys.platform.startswith("linux") and platform.machine() == "x86_64" and m is not None
            and (int(m.group(1)), int(m.group(2))) >= (6, 12)):
        return False
    return _raw_slice_probe()


def _raw_slice_probe() -> bool:
    """Premise, checked without flnotes: in a throwaway thread, does sched_setattr (x86_64: 314) with
    sched_runtime = 0.2 ms read back as 0.2 ms through sched_getattr (315)? (A sandbox may refuse the calls.)"""
    import ctypes

    out = {}

    class Attr(ctypes.Structure):
        _fields_ = [("size", ctypes.c_uint32), ("policy", ctypes.c_uint32), ("flags", ctypes.c_uint64),
                    ("nice", ctypes.c_int32), ("priority", ctypes.c_uint32), ("runtime", ctypes.c_uint64),
                    ("deadline", ctypes.c_uint64), ("period", ctypes.c_uint64)]

    def probe():
        libc = ctypes.CDLL(None, use_errno=True)
        a = Attr()
        if libc.syscall(315, 0, ctypes.byref(a), ctypes.sizeof(Attr), 0) != 0 or a.policy != 0:
            return
        b = Attr(48, 0, 0, a.nice, 0, 200_000, 0, 0)
        if libc.syscall(314, 0, ctypes.byref(b), 0) != 0:
            return
        c = Attr()
        libc.syscall(315, 0, ctypes.byref(c), ctypes.sizeof(Attr), 0)
        out["ok"] = c.runtime == 200_000

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return bool(out.get("ok"))


def test_answer_slice_is_short_inside_and_set_back_after_even_on_an_error():
    from flnotes import config

    before = config.thread_slice()
    with config.answer_slice() as got:
        inside = config.thread_slice()
    if _custom_slices():
        assert got is True, "premise: Linux 6.12+ grants a custom slice"
    if got:
        assert inside == round(config.ANSWER_SLICE_S * 1e9)
    else:
        assert inside == before                                   # not granted: nothing changed
    assert config.thread_slice() == before
    with pytest.raises(RuntimeError, match="inside"):
        with config.answer_slice(2e-4):
            raise RuntimeError("inside")
    assert config.thread_slice() == before
    for bad in (0.0, 5e-5, 0.2, float("nan"), "1e-4", None):
        with pytest.raises(ValueError, match="between 1e-4 and 0.1"):
            with config.answer_slice(bad):
                pass


@pytest.mark.skipif(not _custom_slices(), reason="custom scheduler slices are Linux 6.12+ (EEVDF)")
def test_answer_slice_gives_back_a_custom_slice_the_thread_had():
    from flnotes import config

    seen = {}

    def run():  # in its own thread: the test's thread keeps its default slice
        assert config._set_slice(5_000_000)
        seen["before"] = config.thread_slice()
        with config.answer_slice() as got:
            seen["inside"], seen["got"] = config.thread_slice(), got
        seen["after"] = config.thread_slice()

    t = threading.Thread(target=run)
    t.start()
    t.join()
    assert seen == dict(before=5_000_000, inside=100_000, got=True, after=5_000_000)


@pytest.mark.skipif(not _custom_slices(), reason="custom scheduler slices are Linux 6.12+ (EEVDF)")
def test_answer_slice_keeps_the_reset_on_fork_flag_a_nice_value_set_inside_and_takes_numpy_reals():
    from flnotes import config

    seen = {}

    def run():  # in its own thread: the flag and the nice value stay with it
        tid = threading.get_native_id()
        os.sched_setscheduler(0, os.SCHED_OTHER | os.SCHED_RESET_ON_FORK, os.sched_param(0))
        nice = os.getpriority(os.PRIO_PROCESS, tid)
        with config.answer_slice(np.float32(1e-3)) as got:
            seen["got"], seen["inside"] = got, config.thread_slice()
            os.setpriority(os.PRIO_PROCESS, tid, min(nice + 2, 19))  # raising the nice value needs no privilege
        a = config._get_attr()
        seen["flags"], seen["nice"], seen["after"] = int(a.sched_flags) & 1, a.sched_nice, config.thread_slice()
        seen["want_nice"] = min(nice + 2, 19)

    t = threading.Thread(target=run)
    t.start()
    t.join()
    assert seen["got"] is True and abs(seen["inside"] - 1_000_000) <= 1
    assert seen["flags"] == 1 and seen["nice"] == seen["want_nice"] and seen["after"] != seen["inside"]


def test_a_time_limited_step_answers_with_a_short_slice_and_sets_it_back(quad, monkeypatch):
    """Under a time limit the answering thread runs the step with the short slice of ``answer_slice`` where the
    kernel grants it (``info["answer_slice"]``), and has its own slice again after the step; without a limit the
    slice is left alone."""
    from flnotes import config

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=5.0)
    inside = []
    real = mpc._solve_step

    def recorded(*a, **k):
        inside.append(config.thread_slice())
        return real(*a, **k)

    monkeypatch.setattr(mpc, "_solve_step", recorded)
    engine = []
    solve = mpc.solver.solve

    def in_engine(*a, **k):
        engine.append((threading.current_thread() is not threading.main_thread(), config.thread_slice()))
        return solve(*a, **k)

    monkeypatch.setattr(mpc.solver, "solve", in_engine)
    before = config.thread_slice()
    mpc.set_previous_plan(prev)
    s = mpc(z, R)
    if _custom_slices():
        assert s.info["answer_slice"] is True, "premise: this kernel grants a custom slice"
    assert inside == [round(config.ANSWER_SLICE_S * 1e9) if s.info["answer_slice"] else before]
    assert engine == [(True, before)], "the engine's thread solves with its creator's own slice, not the short one"
    assert config.thread_slice() == before
    no_limit = mpc.clone(time_limit=None)
    monkeypatch.setattr(no_limit, "_solve_step", recorded)
    t = no_limit(z, R)
    assert "answer_slice" not in t.info and inside[-1] == before and config.thread_slice() == before


def test_an_error_in_a_cut_off_solve_is_raised_at_the_next_step(quad, monkeypatch):
    """The solve a step answered at its cut-off fails after the answer: the error is raised by the next call, with a
    note saying where it came from (never dropped)."""
    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=5.0)  # the engine reaches its held solver call before the cut-off (a limit
    # of 0.5 s was too short for that on a machine loaded 7 times over)
    gate = Gate(monkeypatch, then=RuntimeError("the solver broke"))
    mpc.set_previous_plan(prev)
    assert mpc(z, R).info["cut_off"]
    gate.release()
    with pytest.raises(RuntimeError, match="the solver broke") as err:
        mpc(z, R)
    assert any("cut-off" in n for n in getattr(err.value, "__notes__", []))


def test_cut_off_closed_loop_keeps_every_property(quad):
    """The book's loop at N_p = 20 with a limit far below any solve and the cut-off on: steps answer while the
    engine runs on (which answer depends on thread timing), and every answer still passes the checks: the plan's
    forward pass, an admissible input, an honest gap, and the true |u| <= u_max on the plant at the samples."""
    setup = rt.quad_setup(horizon=20, net=quad["net"], eps=quad["eps"])
    mpc = rt.make_mpc(setup, time_limit=TINY)
    log = fl.simulate(setup["system"], mpc, t_final=fl.scale(4.0, 1.5), ts=setup["ts"], z0=setup["z0"],
                      reference=setup["reference"], progress=False)
    assert sum(bool(s.info.get("cut_off")) for s in mpc.history) >= 3, "premise: steps answered at the cut-off"
    for s in mpc.history:
        assert s.status in ("optimal", "time_limit")
        assert check_step(mpc, s), s.message
        assert s.input_admissible
    assert log.summary()["u_within_bound_at_samples"]


def test_cut_off_is_validated(quad):
    """cut_off means something only with a time limit and the network engine; anything else is an error that says
    what to change; a clone without a time limit drops it."""
    with pytest.raises(ValueError, match="time_limit"):
        rt.make_mpc(quad, cut_off=True)
    with pytest.raises(ValueError, match="time_limit"):
        rt.make_mpc(quad, cut_off=False)
    with pytest.raises(TypeError, match="cut_off"):
        rt.make_mpc(quad, time_limit=1.0, cut_off=1)
    with pytest.raises(ValueError, match="network engine"):
        rt.make_mpc(quad, backend="cvxpy-scip", time_limit=1.0, cut_off=True)
    ref = rt.make_mpc(quad, backend="cvxpy-scip", time_limit=1.0)
    assert not ref.cut_off, "the cold reference waits for its solver"
    mpc = rt.make_mpc(quad, time_limit=1.0, cut_off=False)
    assert not mpc.cut_off and not mpc.clone(time_limit=None).cut_off
    assert mpc.clone(cut_off=None).cut_off


def test_cut_off_study_compares_the_two_settings(quad):
    """The bench's cut-off lever: the same loop with no share kept back, without and with the cut-off; every plan
    passes the forward pass, no answer is flagged as cut off without the cut-off, and a share outside [0, 0.5] is an
    error that says so."""
    from flnotes.bench import deadline as dl

    off, on = dl.cut_off_study(quad, t_final=fl.scale(2.0, 0.5))
    assert off["run"].startswith("cut_off=False") and on["run"].startswith("cut_off=True")
    assert off["cut_offs"] == 0 and off["steps"] == on["steps"]
    for r in (off, on):
        assert r["plans_admissible"] == r["steps"] and r["u_within"] and r["error"] == 0
    mpc = rt.make_mpc(quad, time_limit=0.1)
    mpc.reserve_share = 0.7
    with pytest.raises(ValueError, match="reserve_share"):
        mpc.reserve


def test_a_step_under_a_time_limit_runs_without_the_cyclic_garbage_collector(quad, monkeypatch):
    """A full collection (tens of ms) must not land inside an answer: under a time limit the step runs with the
    collector off and leaves it as it found it; without a limit the collector stays on."""
    import gc

    seen = []
    for limit in (0.5, None):
        mpc = rt.make_mpc(quad, time_limit=limit, cut_off=False if limit else None)
        orig = mpc.solver.solve

        def spy(*a, _orig=orig, **k):
            seen.append(gc.isenabled())
            return _orig(*a, **k)

        monkeypatch.setattr(mpc.solver, "solve", spy)
        z = np.asarray(quad["z0"], float)
        R = quad["reference"](quad["ts"] * np.arange(quad["N"] + 1))
        assert gc.isenabled()
        mpc(z, R)
        assert gc.isenabled(), "the step restores the collector"
    assert seen == [False, True]


def test_a_slow_answer_after_a_cut_off_moves_the_next_cut_off_by_a_bounded_share(quad, monkeypatch):
    """An answer that took long after its cut-off (the machine busy: here a sleep) moves the following cut-offs
    earlier, by at most RESERVE_MAX_SHARE of the limit: the next easy state is still solved to optimality."""
    import time

    from flnotes.mpc import engine

    setup, z, R, prev, _ = engine_state(quad)
    easy, _ = _easy_and_cold(setup, n_easy=1)
    tl = 5.0  # long enough for the engine to reach its (held) solver call on a loaded machine
    mpc = rt.make_mpc(setup, time_limit=tl)
    gate = Gate(monkeypatch)
    real = engine.NetworkEngine.answer_now

    def slow(self):
        time.sleep(0.5 * tl)  # more than RESERVE_MAX_SHARE of the limit
        return real(self)

    monkeypatch.setattr(engine.NetworkEngine, "answer_now", slow)
    mpc.set_previous_plan(prev)
    s = mpc(z, R)
    assert s.info["cut_off"] and s.solve_time >= 0.5 * tl
    monkeypatch.setattr(engine.NetworkEngine, "answer_now", real)
    gate.release()
    assert mpc.measured["answer"] >= 0.5 * tl > RESERVE_MAX_SHARE * tl, mpc.measured
    # the released call runs on until its own limit (DAQP's long search there is verified by SCIP): wait for it, so
    # that what the next step meets is the reserve alone (finish keeps the measures)
    mpc.finish()
    assert mpc.measured["answer"] >= 0.5 * tl, mpc.measured
    mpc.set_previous_plan(None)
    s = mpc(easy[0]["z"], easy[0]["z_ref"])
    assert s.status == "optimal" and not s.info["cut_off"], s.message


def test_no_solver_notice_reaches_the_c_streams_across_a_cut_off(quad, monkeypatch, capfd):
    """SoPlex's tolerance notice (forced at every SCIP model by an LP tolerance below what it accepts) never reaches
    file descriptors 1 or 2: not from a step's SCIP calls, nor from one that runs on after its step answered at the
    cut-off; what the caller writes meanwhile comes out."""
    from flnotes.solvers import scip

    params = {"params": {"numerics/lpfeastolfactor": 1e-3}}  # LP tolerance 1e-12 with SCIP's 1e-9: the notice
    setup, z, R, prev, _ = engine_state(quad)
    probe = rt.make_mpc(setup, backend="scip", solver_options=params)
    monkeypatch.setattr(scip, "_quiet_c_output", contextlib.nullcontext)
    probe.set_previous_plan(prev)
    probe(z, R)
    assert "Cannot set feasibility tolerance" in capfd.readouterr().err, "premise: these settings print the notice"
    monkeypatch.undo()
    mpc = rt.make_mpc(setup, backend="scip", solver_options=params, time_limit=5.0)
    gate = Gate(monkeypatch)
    mpc.set_previous_plan(prev)
    s = mpc(z, R)
    assert s.info["cut_off"] and gate.entered.is_set(), "premise: the step answered while its SCIP call was held"
    gate.release()  # the held call now solves, in its thread, after its step answered
    os.write(2, b"written by the caller\n")
    mpc.reset()  # waits for it
    mpc.set_previous_plan(prev)
    mpc(z, R)  # and a whole step with SCIP calls
    out = capfd.readouterr()
    assert "written by the caller" in out.err
    assert "GMP" not in out.err and "GMP" not in out.out, out.err
    assert not scip.c_output_filtered()


def test_late_answers_are_counted_per_system_with_the_load_recorded():
    """bench deadline's late answers: per system and kind of run, the answers counted, those after t_s on the wall
    clock and of them those late by their own CPU time, the load average at start and end; the busy process of the
    loaded condition runs during the runs and is gone after them."""
    from flnotes.bench import deadline as dl

    with dl.busy_core() as busy:
        assert busy.proc.poll() is None, "the busy process runs"
    assert busy.proc.poll() is not None, "and is stopped at the end"
    rows = dl.late_answers(["Cubic3"], steps=3, n_states=1, loaded=True)
    assert [(r["run"], r["answers"]) for r in rows] == [("closed loop", 3), ("cold states", 1)]
    for r in rows:
        assert r["condition"] == "busy process on a core" and r["t_s_ms"] == 200.0
        assert 0 <= r["late_cpu"] <= r["late_wall"] <= r["answers"]
        assert 0 <= r["late_engine_queued"] <= r["late_resume"] <= r["late_wall"]
        assert 0 <= r["late_blocked"] <= r["late_wall"] and 0 <= r["late_faults"] <= r["late_wall"]
        assert 0 <= r["late_steal"] <= r["late_wall"]
        assert 0 <= r["previous_ran_on"] <= r["fallbacks"]
        assert np.isfinite(r["load_start"]) and np.isfinite(r["load_end"]) and r["work_limit"] is None
        assert r["short_slice"] == (r["answers"] if _custom_slices() else r["short_slice"]) <= r["answers"]
    assert len(dl.late_answers_notes(rows)) == 3


def test_repeat_loops_runs_one_controller_again_and_keeps_the_input_bound():
    """bench deadline's repeat_loops: the loop without a limit is the one fl.simulate gives; the limited controller
    runs the number of runs asked, each of the loop's steps, and keeps the true |u| <= u_max; counts are consistent."""
    from flnotes.bench import deadline as dl
    from flnotes.studies import unseen as U

    (r,) = dl.repeat_loops(["Pendulum-gain"], runs=2, t_final=0.4)
    assert (r["system"], r["condition"], r["t_s_ms"], r["runs"], r["steps"]) == ("Pendulum-gain", "as found", 20.0, 2, 20)
    c = U.case("Pendulum-gain")
    free = U.unseen_mpc("Pendulum-gain", ts=0.02)
    log = fl.simulate(free.system, free, t_final=0.4, ts=0.02, z0=np.array(c.z0, float), reference=c.reference(),
                      progress=False)
    assert r["rms_free"] == dl.tracking_rms(log, c.reference())
    assert r["u_within"] and r["rms_min"] <= r["rms_max"]
    assert r["rms_off_free"] >= max(abs(r["rms_min"] - r["rms_free"]), abs(r["rms_max"] - r["rms_free"])) - 1e-15
    assert 0 <= r["optimal_min"] <= r["optimal_max"] <= r["steps"]
    assert 0 <= r["limit_hits_min"] <= r["limit_hits_max"] <= r["steps"]
    assert r["optimal_min"] + r["limit_hits_min"] <= r["steps"]
    assert 0 <= r["late_cpu"] <= r["late_wall"] <= r["runs"] * r["steps"] and 0 <= r["stopped_optimizing"] <= r["runs"]
    assert len(dl.repeat_loops_notes([r])) == 2
    assert len(r["rms_runs"]) == 2 and (r["rms_min"], r["rms_max"]) == (min(r["rms_runs"]), max(r["rms_runs"]))
    assert r["N_p"] == c.horizon and r["work_limit"] is None and r["safety_net"] == 0  # no budget: no safety net
    assert r["free_wall_max_over_ts"] > 0
    (b,) = dl.repeat_loops(["Pendulum-gain"], runs=1, t_final=0.1, horizon=4, work_limit="auto")
    assert (b["N_p"], b["work_limit"], b["steps"], b["runs"]) == (4, "auto", 5, 1) and b["u_within"]
    assert 0 <= b["safety_net"] <= b["steps"]
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="runs must be"):
            dl.repeat_loops(["Pendulum-gain"], runs=bad)
    with pytest.raises(ValueError, match="ts must be"):
        dl.repeat_loops(["Pendulum-gain"], ts=-0.02)


def test_spread_clause_says_whether_every_run_tracked():
    """bench deadline's spread_clause: runs within 3 times the error of the loop without the limit tracked alike; some
    above it and some not is timing's doing; all above it is the limit's; round-off above an error of 0 is not worse;
    no run, or an error that is not finite, is refused."""
    from flnotes.bench import deadline as dl

    row = dict(rms_free=0.05, rms_runs=[0.05, 0.12, 0.0501])
    assert dl.spread_clause(row).startswith("each of the 3 runs tracked within 3 times") and "0.12" in dl.spread_clause(row)
    row["rms_runs"] = [0.05, 1.2, 0.16]
    out = dl.spread_clause(row)
    assert out.startswith("2 of 3 runs tracked worse") and "1.2" in out and "timing" in out, out
    row["rms_runs"] = [1.1, 1.1, 1.1]
    out = dl.spread_clause(row)
    assert out.startswith("all 3 runs tracked worse") and "the limit decided" in out and "timing" not in out, out
    assert dl.spread_clause(dict(rms_free=0.05, rms_runs=[1.0])).startswith("the run tracked worse")
    assert dl.spread_clause(dict(rms_free=0.0, rms_runs=[0.0, 1e-15])).startswith("each of the 2 runs tracked within")
    for bad in (dict(rms_free=0.05, rms_runs=[]), dict(rms_free=float("nan"), rms_runs=[0.05, 5.0]),
                dict(rms_free=0.05, rms_runs=[0.05, float("nan")])):
        with pytest.raises(ValueError):
            dl.spread_clause(bad)


def test_first_incumbent_times_time_the_engines_first_repair_against_a_fresh_cut_off():
    """bench deadline's first_incumbent_times: per horizon, the repaired relaxation at the case's z(0) is the plan the
    engine's incumbent search builds (its check as the row says), the times are positive and ordered, and the cut-off
    is a fresh controller's (t_s less the time kept for the answer, at most RESERVE_MAX_SHARE of t_s)."""
    from flnotes.bench import deadline as dl
    from flnotes.mpc import controller as ctl
    from flnotes.studies import unseen as U

    rows = dl.first_incumbent_times("VdP-gain", horizons=(8, 12), repeats=2)
    assert [r["N_p"] for r in rows] == [8, 12]
    c = U.case("VdP-gain")
    ts = dl.SHORT_TS
    keep = min(max(0.5 * ctl.RESERVE_SHARE * ts, ctl.CUT_OFF_MIN_S), ctl.RESERVE_MAX_SHARE * ts)
    incumbents = set()
    for r in rows:
        # the engine's own cold step at z(0) (no limit): its first incumbent is the repaired relaxation exactly when
        # the row says the repair passes (else the one-switch plans; none when the QP's optimum is screened)
        z0 = np.array(c.z0, float)
        R = np.asarray(c.reference()(ts * np.arange(r["N_p"] + 1)), float)
        s = U.unseen_mpc("VdP-gain", ts=ts, horizon=r["N_p"])(z0, R)
        if s.info.get("incumbent") is not None:
            incumbents.add(s.info["incumbent"])
            assert (s.info["incumbent"] == "repaired relaxation") == r["passes"], (r, s.info["incumbent"])
        assert 0 < r["ms_median"] <= r["ms_max"] and r["cpu_ms_median"] > 0
        assert r["cut_off_ms"] == pytest.approx(1e3 * (ts - keep))
        assert r["fallback_deadline_ms"] == pytest.approx(
            1e3 * (ts - max(ctl.FALLBACK_POST_SHARE * ts, ctl.FALLBACK_POST_MIN_S)))
    assert any(r["passes"] for r in rows), "premise: a repaired plan that passes the check"
    assert "repaired relaxation" in incumbents, "premise: the engine's first incumbent compared"
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="repeats must be"):
            dl.first_incumbent_times("VdP-gain", horizons=(8,), repeats=bad)
    for bad in ((8.5,), (0,), "12", (True,)):
        with pytest.raises(ValueError, match="horizons must be"):
            dl.first_incumbent_times("VdP-gain", horizons=bad)
    with pytest.raises(ValueError, match="ts must be"):
        dl.first_incumbent_times("VdP-gain", horizons=(8,), ts=-0.02)


def test_repeat_loops_refuses_bad_arguments_before_any_loop_runs(monkeypatch):
    """bench deadline's repeat_loops: a name given as one string, an unknown name after a good one, a bad work_limit
    and a ts that is no number are refused before any loop is simulated."""
    from flnotes.bench import deadline as dl

    def no_loop(*a, **k):
        raise AssertionError("a loop ran before the arguments were checked")

    monkeypatch.setattr(dl, "simulate", no_loop)
    with pytest.raises(ValueError, match="not one string"):
        dl.repeat_loops("Pendulum-gain", runs=1)
    with pytest.raises(ValueError, match="unknown system"):
        dl.repeat_loops(["Pendulum-gain", "nope"], runs=1)
    with pytest.raises(ValueError, match="work_limit"):
        dl.repeat_loops(["Pendulum-gain"], runs=1, work_limit="bogus")
    with pytest.raises(ValueError, match="ts must be"):
        dl.repeat_loops(["Pendulum-gain"], ts="abc")


def test_tracking_rms_is_the_position_error_over_the_second_half():
    """bench deadline's tracking_rms on a hand-made log and a vectorized reference: the last two of four samples,
    errors -1 and 0."""
    from types import SimpleNamespace

    from flnotes.bench import deadline as dl

    log = SimpleNamespace(t=np.arange(4.0), z=np.array([[5.0, 0.0], [5.0, 0.0], [1.0, 0.0], [3.0, 0.0]]))
    assert dl.tracking_rms(log, lambda t: np.c_[t, np.ones_like(t)]) == pytest.approx(np.sqrt(0.5))


def test_a_late_answer_counts_as_resumed_late_only_when_the_lag_covers_its_overrun():
    """bench deadline's _resumed_late: an answer after t_s counts only when its thread's lag after the cut-off covers
    the whole overrun and it was not waiting for a core (or the platform does not say); an answer on time never."""
    from flnotes.bench import deadline as dl

    def step(lag, queued):
        return fl.StepResult(v=np.zeros(1), info=dict(wake_lag=lag, wake_runqueue=queued))

    ts = 0.02
    assert dl._resumed_late(step(0.015, 0.0), 0.03, ts)  # overrun 10 ms, lag 15 ms, no wait for a core
    assert dl._resumed_late(step(0.015, float("nan")), 0.03, ts)  # the platform does not say
    assert not dl._resumed_late(step(0.005, 0.0), 0.03, ts)  # the lag does not cover the overrun
    assert not dl._resumed_late(step(0.015, 0.012), 0.03, ts)  # it waited for a core most of the lag
    assert not dl._resumed_late(step(0.015, 0.0), 0.019, ts)  # on time
    assert not dl._resumed_late(fl.StepResult(v=np.zeros(1)), 0.03, ts)  # no record of it (no cut-off)


def test_a_resumed_late_answer_counts_as_engine_queued_only_when_the_engines_wait_covers_its_overrun():
    """bench deadline's _engine_queued: a late resume whose engine thread waited for a core for at least the
    overrun; not when the engine's wait is shorter or unknown, nor for an answer that did not resume late."""
    from flnotes.bench import deadline as dl

    def step(lag, queued, engine):
        return fl.StepResult(v=np.zeros(1), info=dict(wake_lag=lag, wake_runqueue=queued, engine_runqueue=engine))

    ts = 0.02
    assert dl._engine_queued(step(0.015, 0.0, 0.012), 0.03, ts)  # overrun 10 ms, the engine waited 12 ms
    assert not dl._engine_queued(step(0.015, 0.0, 0.004), 0.03, ts)  # it waited less than the overrun
    assert not dl._engine_queued(step(0.015, 0.0, float("nan")), 0.03, ts)  # the platform does not say
    assert not dl._engine_queued(step(0.015, 0.012, 0.05), 0.03, ts)  # the answer itself waited for a core
    assert not dl._engine_queued(step(0.015, 0.0, 0.05), 0.019, ts)  # on time


def test_budget_floor_runs_on_the_budget_alone_and_repeats_bit_for_bit():
    """bench deadline's budget floor: one node per step, a time limit the steps never reach; the loop run twice gives
    the same statuses and plans (no decision read the clock), the steps over t_s counted among those run."""
    from flnotes.bench import deadline as dl

    rows = dl.budget_floor(["Cubic3"], steps=4, n_states=2)
    assert [(r["run"], r["steps"]) for r in rows] == [("closed loop", 4), ("cold states", 2)]
    for r in rows:
        assert r["nodes"] == 1 and r["safety_net"] == 0 and r["t_s_ms"] == 200.0
        assert 0 <= r["over_t_s"] <= r["steps"] and 0 <= r["budget_hits"] <= r["steps"]
        assert 0 < r["cpu_median_over_ts"] <= r["cpu_max_over_ts"]
    assert rows[0]["repeat_identical"] is True
    assert len(dl.budget_floor_notes(rows)) == 3


def test_the_engine_limit_ends_at_the_cut_off_even_when_its_thread_starts_late(quad, monkeypatch):
    """The engine's own time limit never runs past the step's cut-off, counted from when its thread starts: a thread
    that waits for a core (here held 0.2 s before it runs) gets only what is left until the cut-off, so that after
    the cut-off it does not compete with the answer. The step still answers with a checked plan."""
    import threading
    import time

    from flnotes.mpc import controller

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=0.5)
    seen = []
    solve = mpc.solver.solve

    def recorded(*a, **k):
        seen.append((time.perf_counter(), k["time_limit"]))
        return solve(*a, **k)

    monkeypatch.setattr(mpc.solver, "solve", recorded)

    class LateThread(threading.Thread):
        def run(self):
            time.sleep(0.2)
            super().run()

    monkeypatch.setattr(controller.threading, "Thread", LateThread)
    mpc.set_previous_plan(prev)
    t0 = time.perf_counter()
    s = mpc(z, R)
    mpc.reset()
    (entered, limit), = seen
    cut = t0 + mpc.time_limit - controller.CUT_OFF_MIN_S  # the latest cut-off: it leaves at least CUT_OFF_MIN_S
    assert entered >= t0 + 0.2, "premise: the engine's thread started late"
    assert entered + limit <= cut + 1e-3, (entered - t0, limit)
    assert limit < mpc.time_limit - mpc.reserve - 0.15, "the limit was cut by the late start"
    assert check_step(mpc, s), s.message


def test_a_step_under_a_time_limit_switches_threads_quickly_and_restores_the_interval(quad, monkeypatch):
    """Inside a step under a time limit a thread waiting for the interpreter lock gets it within
    ``SWITCH_INTERVAL_S`` (the answer at a cut-off does not wait 5 ms for the engine's thread); the interval the
    caller had is restored after the step, also when the step raises; a non-positive interval is refused."""
    import sys

    from flnotes import config

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=5.0)
    inside = []
    solve = mpc.solver.solve

    def recorded(*a, **k):
        inside.append(sys.getswitchinterval())
        return solve(*a, **k)

    monkeypatch.setattr(mpc.solver, "solve", recorded)
    before = sys.getswitchinterval()
    assert before > config.SWITCH_INTERVAL_S, "premise: Python's default interval is longer"
    mpc.set_previous_plan(prev)
    mpc(z, R)
    mpc.reset()
    assert inside and max(inside) <= config.SWITCH_INTERVAL_S
    assert sys.getswitchinterval() == before
    with pytest.raises(ValueError, match="z must"):
        mpc(np.zeros(7), R)
    assert sys.getswitchinterval() == before
    no_limit = mpc.clone(time_limit=None)
    no_limit(z, R)  # no limit: Python's interval is left alone
    assert sys.getswitchinterval() == before
    with pytest.raises(ValueError, match="positive"):
        with config.quick_thread_switch(0.0):
            pass


def test_the_fallback_deadline_leaves_a_floor_for_the_checks_after_it(quad, monkeypatch):
    """The fallback's repairs stop at ``t0 + time_limit`` less the larger of ``FALLBACK_POST_SHARE`` of the limit and
    ``FALLBACK_POST_MIN_S``: at a short limit the floor decides."""
    import time

    from flnotes.mpc import FALLBACK_POST_MIN_S, FALLBACK_POST_SHARE, controller

    setup, z, R, prev, _ = engine_state(quad)
    seen = []
    real = fb.fallback_plan

    def recorded(*a, **k):
        seen.append(k["deadline"])
        return real(*a, **k)

    monkeypatch.setattr(controller.fallback, "fallback_plan", recorded)
    for tl in (0.01, 2.0):
        mpc = rt.make_mpc(setup, time_limit=tl, cut_off=False)
        seen.clear()
        t0 = time.perf_counter()
        s = mpc._fallback(z, R, fl.StepResult(None, "time_limit"), None, t0)
        assert s.fallback and len(seen) == 1
        assert seen[0] == pytest.approx(t0 + tl - max(FALLBACK_POST_SHARE * tl, FALLBACK_POST_MIN_S), abs=1e-12)
    assert FALLBACK_POST_SHARE * 0.01 < FALLBACK_POST_MIN_S < FALLBACK_POST_SHARE * 2.0, "premise: both cases"


def test_region_qp_and_the_repair_stop_when_asked(quad):
    """``region_qp`` with its ``stop`` event set solves the first region only (no move), the same point as with no
    moves; ``qp_repair`` with ``stop`` set keeps the QP's plan unrepaired (what the engine's incumbent search does
    once the controller has answered at its cut-off)."""
    import threading

    from flnotes.mpc import region_qp

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup)
    f, _ = mpc.pred.linear(z, R)
    V_q, _, _ = mpc.pred.qp(f, z)
    assert V_q is not None and not mpc.pred.feasible(z, V_q), "premise: the QP's plan needs a repair"
    stop = threading.Event()
    stop.set()
    first = region_qp(mpc.pred, z, f, V_q, 0)
    stopped = region_qp(mpc.pred, z, f, V_q, 20, stop=stop)
    assert (first is None) == (stopped is None)
    if first is not None:
        assert np.array_equal(first, stopped)
    _, V_r = fb.qp_repair(mpc.pred, z, f, V_q, stop=stop)
    assert np.array_equal(V_r.reshape(-1), np.asarray(V_q).reshape(-1)), "nothing repaired after stop"
    _, V_full = fb.qp_repair(mpc.pred, z, f, V_q)
    assert not np.array_equal(V_full.reshape(-1), np.asarray(V_q).reshape(-1)), "without stop the plan is repaired"



def test_a_solve_stopped_with_hold_waits_for_the_answer_before_its_result(quad):
    """``NetworkEngine.stop(hold=True)``: the solve stops at its next check and then waits for ``answered()`` before
    it builds its result (it competes no longer with the caller's answer); ``stop()`` alone lets it return at once,
    and ``go()`` clears both. The held solve's result is the one of a stop: status time_limit, the incumbent as
    published, nothing beyond it."""
    import threading

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup)
    engine = mpc.solver
    for hold in (True, False):
        engine.go()
        engine.stop(hold=hold)
        out = {}
        worker = threading.Thread(target=lambda: out.setdefault("step", engine.solve(z, R, time_limit=5.0)))
        worker.start()
        worker.join(0.5 if hold else 30.0)
        assert worker.is_alive() == hold, (hold, out)
        if hold:
            assert engine.progress is not None, "premise: it ran up to its first check and published"
            engine.answered()
            worker.join(30.0)
            assert not worker.is_alive()
        s = out["step"]
        assert s.status == "time_limit" and s.message.startswith("time limit"), s.message
        assert s.v is None or mpc.plan_feasible(s.z_pred, s.v_pred)
    engine.go()
    assert engine._answered.is_set() and not engine._stop.is_set()
    assert engine.solve(z, R).status == "optimal", "after go() the same engine solves to the end"



def test_a_hold_never_stops_a_solve_for_good(quad, monkeypatch):
    """``stop(hold=True)`` never hangs: a solve in the thread that asked for the hold is not held (nothing could
    release it: the engine's own ``solve`` and ``warm_up``, and controllers without the cut-off, whose solve runs in
    the caller's thread), a held solve that is never released ends after ``HOLD_MAX_S``, and a controller's step
    clears a stop asked before it (``go()``): it solves to the optimum, not to a time limit."""
    import threading

    from flnotes.mpc import engine as eng

    setup, z, R, prev, exact = engine_state(quad)
    mpc = rt.make_mpc(setup)
    engine = mpc.solver
    engine.go()
    engine.stop(hold=True)
    s = engine.solve(z, R, time_limit=5.0)  # this thread asked for the hold: not held
    assert s.status == "time_limit", s.message
    engine.warm_up()
    monkeypatch.setattr(eng, "HOLD_MAX_S", 0.3)
    engine.go()
    engine.stop(hold=True)
    out = {}
    worker = threading.Thread(target=lambda: out.setdefault("step", engine.solve(z, R, time_limit=5.0)))
    t_start = time.perf_counter()
    worker.start()
    worker.join(0.1)
    assert worker.is_alive(), "premise: the solve in another thread is held"
    worker.join(30.0)
    assert not worker.is_alive() and time.perf_counter() - t_start >= 0.3 and out["step"].status == "time_limit"
    for limit, cut_off in ((None, None), (5.0, False), (5.0, True)):
        mpc = rt.make_mpc(setup, time_limit=limit, cut_off=cut_off)
        mpc.solver.stop(hold=True)  # asked before the step, from the caller's thread
        mpc.set_previous_plan(prev)
        step = mpc(z, R)
        mpc.finish()
        assert step.status == "optimal", (limit, cut_off, step.message)
        assert abs(step.objective - exact.objective) <= 1e-6 * max(1.0, abs(exact.objective))

def test_the_engine_builds_its_result_after_the_answer_at_its_cut_off(quad, monkeypatch):
    """At its cut-off a step stops its engine with ``hold=True`` and releases it once the answer is out: the solve's
    result is built after the step has returned (the answer is made slow here, 0.2 s, so that a solve that did not
    wait would build its result during it), and the next step and ``finish()`` still wait for it and end."""
    import threading

    from flnotes.mpc import engine as eng

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=0.3)
    stopped, built = {}, []
    real_stop, real_answer, real_result = mpc.solver.stop, mpc.solver.answer_now, eng._step_result
    real_solve = mpc.solver.solve

    def stop(*a, **k):
        real_stop(*a, **k)
        stopped["hold"] = k.get("hold", a[0] if a else False)
        stopped["event"].set()

    def solve_after_stop(*a, **k):  # the engine's solve starts only once the step has asked it to stop
        stopped["event"].wait(30.0)
        return real_solve(*a, **k)

    def slow_answer():
        time.sleep(0.2)  # releases the interpreter lock: a solve that does not wait would build its result now
        return real_answer()

    def result(*a, **k):  # the engine's own result (answer_now builds the answer with it too, in the step's thread)
        if threading.current_thread().name == "flnotes-mpc-solve":
            built.append(time.perf_counter())
        return real_result(*a, **k)

    stopped["event"] = threading.Event()
    monkeypatch.setattr(mpc.solver, "stop", stop)
    monkeypatch.setattr(mpc.solver, "answer_now", slow_answer)
    monkeypatch.setattr(eng, "_step_result", result)
    monkeypatch.setattr(mpc.solver, "solve", solve_after_stop)
    mpc.set_previous_plan(prev)
    s = mpc(z, R)
    answered = time.perf_counter()
    assert s.info["cut_off"] and stopped["hold"] is True, (s.info, stopped)
    assert s.v is not None and mpc.plan_feasible(s.z_pred, s.v_pred), s.message
    mpc.finish()
    assert len(built) == 1 and built[0] >= answered - 1e-3, (built, answered)
    assert mpc._running is None and mpc.solver._answered.is_set()

def test_a_proven_infeasible_program_skips_the_repairs(quad, monkeypatch):
    """When the step has proven the program infeasible, no repair can pass the check: the fallback goes straight to
    an admissible first input (the repair of a whole plan is not tried), so that this path costs little time. The
    same state without the flag tries the repairs first."""
    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup)
    f, _ = mpc.pred.linear(z, R)
    calls = []
    real_qp, real_rep = fb.qp_repair, fb.repair_plan
    monkeypatch.setattr(fb, "qp_repair", lambda *a, **k: calls.append("qp") or real_qp(*a, **k))
    monkeypatch.setattr(fb, "repair_plan", lambda *a, **k: calls.append(("plan", k.get("first", True))) or
                        real_rep(*a, **k))
    Z, V, what, ok = fb.fallback_plan(mpc.pred, z, None, f=f, infeasible=True)
    assert "qp" not in calls and ("plan", True) not in calls, calls
    assert ok and np.all(np.abs(mpc.net(np.r_[z, V[0]])) <= mpc.u_eps + BOUND_TOL), what
    calls.clear()
    fb.fallback_plan(mpc.pred, z, None, f=f)
    assert "qp" in calls, "premise: without the flag the repairs are tried"


def test_late_and_cut_clauses_fit_their_counts():
    from flnotes.bench import deadline as dl

    assert dl.late_clause(0, 0) == "none came after the sampling period"
    assert dl.late_clause(3, 3) == "3 came after the sampling period, 3 of them late by their own CPU time"
    assert dl.late_clause(3, 1) == ("3 came after the sampling period, 1 of them late by their own CPU time; the other 2 "
                                    "waited for the machine: the process did not run for part of the step, which no time "
                                    "limit inside the process can prevent")
    assert dl.cut_clause(0) == ("No answer was given at the cut-off: every answer came from the engine itself, at a proof "
                                "or at its own check of the time")
    assert dl.cut_clause(1).startswith("1 answer was given at the cut-off while the engine's solve ran on; the others")
    assert dl.cut_clause(2).startswith("2 answers were given at the cut-off")


def test_deadline_clauses_every_branch():
    from flnotes.bench import deadline as dl

    dn = dict(over_t_s=0, over_t_s_cpu=0, cut_offs=0, loop_limit_hits=0, loop_steps=40, loop_gap_p50=0.0,
              loop_gap_max=0.0, loop_opt_gap_over=0, loop_opt_gap_max=float("nan"), loops_limit_hits=0,
              loops_opt_gap_over=0, loops_opt_gap_max=float("nan"))
    out = dl.deadline_clauses(dn)
    assert out == dict(late_clause=dl.late_clause(0, 0), loop_clause="none of the 40 closed-loop steps hit the limit",
                       loops_clause="no step hit the limit, so no plan was returned there", cut_clause=dl.cut_clause(0))
    dn.update(over_t_s=2, over_t_s_cpu=1, cut_offs=3, loop_limit_hits=5, loop_gap_p50=0.123, loop_gap_max=0.5,
              loop_opt_gap_over=1, loops_limit_hits=9, loops_opt_gap_over=2)
    out = dl.deadline_clauses(dn)  # limit hits, the distance to the optimum not known
    assert out["late_clause"] == dl.late_clause(2, 1) and out["cut_clause"] == dl.cut_clause(3)
    assert out["loop_clause"] == ("5 of the 40 closed-loop steps hit the limit; their recorded gaps have median 0.12 and "
                                  "maximum 0.50, and 1 of those plans were more than 10⁻⁴ above the optimum")
    assert out["loops_clause"] == "2 of the 9 plans returned at the limit were more than 10⁻⁴ above the optimum"
    dn.update(loop_opt_gap_max=2.5e-3, loops_opt_gap_max=4e-3)
    out = dl.deadline_clauses(dn)
    assert out["loop_clause"].endswith("above the optimum (the farthest by 2.5e-03)")
    assert out["loops_clause"].endswith("above the optimum, the farthest by 4.0e-03")


def _blas_threads(libs: set) -> set:
    """The thread counts of the BLAS libraries ``libs`` (file paths) loaded in this process."""
    from threadpoolctl import threadpool_info

    return {p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas" and p["filepath"] in libs}


def _two_thread_blas() -> set:
    """The BLAS libraries that run two threads (inside ``threadpool_limits(limits=2)``): the premise of a test."""
    from threadpoolctl import threadpool_info

    libs = {p["filepath"] for p in threadpool_info() if p["user_api"] == "blas" and p["num_threads"] == 2}
    assert libs, "premise: a BLAS library runs two threads"
    return libs


def test_one_blas_thread_and_the_quick_switch_are_shared():
    """Both settings are process-wide: two contexts that end out of order (a step, then what its engine's solve
    kept) keep them until the last one ends, and the settings the first one found come back then."""
    from threadpoolctl import threadpool_limits

    from flnotes import config

    with threadpool_limits(limits=2, user_api="blas"):
        libs = _two_thread_blas()
        before = sys.getswitchinterval()
        assert before > config.SWITCH_INTERVAL_S, "premise: Python's default interval is longer"
        step, kept = config.one_blas_thread(), config.one_blas_thread()
        fast_step, fast_kept = config.quick_thread_switch(), config.quick_thread_switch()
        step.__enter__(), fast_step.__enter__()
        kept.__enter__(), fast_kept.__enter__()
        step.__exit__(None, None, None), fast_step.__exit__(None, None, None)  # the first one ends first
        assert _blas_threads(libs) == {1} and sys.getswitchinterval() <= config.SWITCH_INTERVAL_S
        kept.__exit__(None, None, None), fast_kept.__exit__(None, None, None)
        assert _blas_threads(libs) == {2} and sys.getswitchinterval() == before
        with config.one_blas_thread(), config.quick_thread_switch():  # nested
            with config.one_blas_thread(), config.quick_thread_switch(1e-3):
                assert _blas_threads(libs) == {1} and sys.getswitchinterval() <= config.SWITCH_INTERVAL_S
            assert _blas_threads(libs) == {1}
        assert _blas_threads(libs) == {2} and sys.getswitchinterval() == before


def _interrupting(real, calls: list, where: str):
    """``real`` wrapped to note each value it sets in ``calls`` and raise KeyboardInterrupt (a Ctrl-C) right after
    the setting on the way in (``where="entry"``, the first call) or on the way out (``"exit"``, the second)."""
    def interrupted(x):
        real(x)
        calls.append(x)
        if len(calls) == (1 if where == "entry" else 2):
            raise KeyboardInterrupt

    return interrupted


@pytest.mark.parametrize("where", ["entry", "exit"])
def test_an_interrupt_inside_one_blas_thread_never_leaves_the_limit(where, monkeypatch):
    """A Ctrl-C that lands after the BLAS libraries' count was changed, on the way in (the limit set, the context
    not yet entered) or on the way out (the setting back stopped half-way): the process's own count comes back, at
    once or at the next context's end, and is never taken for one."""
    from threadpoolctl import threadpool_limits

    from flnotes import config

    with threadpool_limits(limits=2, user_api="blas"):
        libs = _two_thread_blas()
        with config.one_blas_thread():  # the libraries are found
            pass
        lib = next(c for c in config._POOLS.lib_controllers if c.user_api == "blas" and c.filepath in libs)
        real, calls = lib.set_num_threads, []
        monkeypatch.setattr(lib, "set_num_threads", _interrupting(real, calls, where))
        with pytest.raises(KeyboardInterrupt):
            with config.one_blas_thread():
                assert where == "exit", "the entry was interrupted: the body never runs"
        assert calls[:2] == [1, 2] if where == "exit" else calls == [1, 2], calls
        monkeypatch.setattr(lib, "set_num_threads", real)
        assert not config._BLAS_HOLDERS
        with config.one_blas_thread():
            assert _blas_threads(libs) == {1}
        assert _blas_threads(libs) == {2}, "the process's own count, never the limit taken for it"


@pytest.mark.parametrize("where", ["entry", "exit"])
def test_an_interrupt_inside_the_quick_switch_never_leaves_the_short_interval(where, monkeypatch):
    """A Ctrl-C right after the interval was changed, on the way in or on the way out: Python's own interval is
    back after the context (or the next one), never taken for the process's own."""
    from flnotes import config

    before = sys.getswitchinterval()
    assert before > config.SWITCH_INTERVAL_S, "premise: Python's default interval is longer"
    real, calls = sys.setswitchinterval, []
    monkeypatch.setattr(config.sys, "setswitchinterval", _interrupting(real, calls, where))
    with pytest.raises(KeyboardInterrupt):
        with config.quick_thread_switch():
            assert where == "exit", "the entry was interrupted: the body never runs"
    monkeypatch.setattr(config.sys, "setswitchinterval", real)
    assert sys.getswitchinterval() == before and not config._SWITCH_HOLDERS
    with config.quick_thread_switch():
        assert sys.getswitchinterval() <= config.SWITCH_INTERVAL_S
    assert sys.getswitchinterval() == before


def test_an_exit_interrupted_before_the_setting_back_completes_it_later(monkeypatch):
    """The setting back of the last exit stopped before any library was set back: the limit stays until the next
    context ends, which sets back the counts from before the first entry (not the limit it finds)."""
    from threadpoolctl import threadpool_limits

    from flnotes import config

    with threadpool_limits(limits=2, user_api="blas"):
        libs = _two_thread_blas()
        with config.one_blas_thread():
            pass
        lib = next(c for c in config._POOLS.lib_controllers if c.user_api == "blas" and c.filepath in libs)
        real, calls = lib.set_num_threads, []

        def interrupted(n):
            calls.append(n)
            if n != 1:
                raise KeyboardInterrupt  # before the count is set back
            real(n)

        monkeypatch.setattr(lib, "set_num_threads", interrupted)
        with pytest.raises(KeyboardInterrupt):
            with config.one_blas_thread():
                pass
        monkeypatch.setattr(lib, "set_num_threads", real)
        assert _blas_threads(libs) == {1} and config._BLAS_ORIGINAL is not None, "premise: the limit was left"
        with config.one_blas_thread():
            assert _blas_threads(libs) == {1}
        assert _blas_threads(libs) == {2} and config._BLAS_ORIGINAL is None


def test_a_solve_running_on_after_the_cut_off_keeps_one_blas_thread_and_the_quick_switch(quad, monkeypatch):
    """A step answered at its cut-off returns while its engine's solve runs on: until that solve ends BLAS keeps one
    thread (a spinning second BLAS thread took the next answer's core: answers at up to 3.7 t_s) and the interval
    stays short (the caller's code gets the interpreter lock from the solve's thread); reset() (or the next step)
    waits for the solve and sets both back. The record's ``solve_time`` is the whole call and
    ``process_cpu_time`` the CPU time of every thread of the process meanwhile."""
    from threadpoolctl import threadpool_limits

    from flnotes import config

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=2.0)
    with threadpool_limits(limits=2, user_api="blas"):
        libs = _two_thread_blas()
        before = sys.getswitchinterval()
        gate = Gate(monkeypatch, spin=0.05)
        mpc.set_previous_plan(prev)
        t0 = time.perf_counter()
        s = mpc(z, R)
        wall = time.perf_counter() - t0
        assert gate.entered.is_set() and not gate.released.is_set() and s.info["cut_off"], "premise: held at the answer"
        assert _blas_threads(libs) == {1} and sys.getswitchinterval() <= config.SWITCH_INTERVAL_S
        assert s.solve_time <= wall and s.info["process_cpu_time"] + 2e-3 >= s.info["cpu_time"], s.info
        gate.release()
        mpc.reset()  # waits for the held solve, then sets the settings back in this thread
        assert _blas_threads(libs) == {2} and sys.getswitchinterval() == before
        mpc.set_previous_plan(prev)
        again = mpc(z, R)  # a step that ends with its solve sets them back at once
        assert not again.info["cut_off"] and mpc._running is None
        assert _blas_threads(libs) == {2} and sys.getswitchinterval() == before


def test_the_collector_stays_paused_until_the_time_limited_step_returns(quad, monkeypatch):
    """Everything a time-limited step does after its solve (setting back the BLAS threads and the switch interval,
    the record's times) runs with the cyclic collector paused, so that a collection of the caller's garbage cannot
    start inside the call (one did, 80 ms on a 20 ms controller, when the settings were set back after it resumed)."""
    import gc

    from flnotes.mpc import controller

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=5.0)
    seen = []
    real = controller.MPC._timed

    def spy(step, *readings):
        seen.append(gc.isenabled())
        real(step, *readings)

    monkeypatch.setattr(controller.MPC, "_timed", staticmethod(spy))
    assert gc.isenabled(), "premise: the collector runs outside the step"
    mpc.set_previous_plan(prev)
    s = mpc(z, R)
    assert seen == [False] and gc.isenabled() and s.solve_time > 0 and "process_cpu_time" in s.info


def test_finish_and_a_dropped_controller_set_back_what_a_running_solve_kept(quad, monkeypatch):
    """A step answered at its cut-off keeps one BLAS thread, the short switch interval and the paused collector while
    its solve runs on: ``finish()`` waits for the solve and sets them back (plan and history kept); a controller
    dropped while its solve still runs is freed at once in the thread that drops it (nothing refers to it from the
    solve's thread, and no collection is needed), waits for the solve and sets them back there: from the solve's
    thread OpenBLAS would ignore the thread count, and the process would keep one BLAS thread for good."""
    import gc

    from threadpoolctl import threadpool_limits

    from flnotes import config

    setup, z, R, prev, _ = engine_state(quad)
    with threadpool_limits(limits=2, user_api="blas"):
        libs = _two_thread_blas()
        before = sys.getswitchinterval()
        assert gc.isenabled(), "premise: the collector runs outside the steps"
        for how in ("finish", "drop"):
            mpc = rt.make_mpc(setup, time_limit=2.0)
            gate = Gate(monkeypatch)
            mpc.set_previous_plan(prev)
            s = mpc(z, R)
            assert gate.entered.is_set() and s.info["cut_off"], "premise: the answer came while the solver was held"
            assert _blas_threads(libs) == {1} and sys.getswitchinterval() <= config.SWITCH_INTERVAL_S
            assert not gc.isenabled(), "the collector stays paused while the solve runs on"
            if how == "finish":
                gate.release()
                mpc.finish()
                assert mpc._running is None and mpc.history == [s] and mpc._plan is not None
                mpc.finish()  # nothing running: nothing to do
            else:
                worker = mpc._running[0]
                releaser = threading.Timer(0.3, gate.release)  # the solve ends while the drop waits for it
                releaser.start()
                del mpc, s  # no gc.collect(): freed by its last reference, here
                assert not worker.is_alive(), "the drop waited for the solve"
                releaser.join()
            assert _blas_threads(libs) == {2} and sys.getswitchinterval() == before and gc.isenabled(), how


def test_no_collection_starts_inside_a_time_limited_call(quad):
    """A collection that falls due while a time-limited step runs starts after the call has returned: the
    collector is paused before the step allocates and resumed as its last action (one started by the first
    allocation after an earlier resume, still inside the call, made answers 2 to 4 times late while their record
    said on time). A threshold of one allocation makes a collection due at once."""
    import gc

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=5.0)
    inside, seen = [False], []
    callback = lambda phase, info: seen.append(inside[0]) if phase == "start" else None  # noqa: E731
    mpc.set_previous_plan(prev)
    mpc(z, R)  # a first step: whatever it builds once is built
    old = gc.get_threshold()
    gc.callbacks.append(callback)
    try:
        gc.set_threshold(1)
        for _ in range(3):
            mpc.set_previous_plan(prev)
            inside[0] = True
            s = mpc(z, R)
            inside[0] = False
            assert not s.info["cut_off"], "premise: the solve ended in the step"
            [object() for _ in range(3)]  # the caller's next allocations: the due collection starts here
    finally:
        gc.set_threshold(*old)
        gc.callbacks.remove(callback)
    assert seen and not any(seen), f"{sum(seen)} of {len(seen)} collections started inside the call"


def test_the_collector_pause_is_shared():
    """The collector is process-wide: two pauses that end out of order keep it paused until the last one ends, and
    it runs again only when the first found it running."""
    import gc

    from flnotes import config

    assert gc.isenabled(), "premise: the collector runs"
    first, second = config.no_cyclic_gc(), config.no_cyclic_gc()
    first.__enter__(), second.__enter__()
    first.__exit__(None, None, None)
    assert not gc.isenabled()
    second.__exit__(None, None, None)
    assert gc.isenabled()
    gc.disable()
    try:
        with config.no_cyclic_gc():
            pass
        assert not gc.isenabled(), "a collector the user had paused stays paused"
    finally:
        gc.enable()


@pytest.mark.parametrize("end", ["run", "interrupt"])
def test_simulate_ends_with_nothing_held(quad, monkeypatch, end):
    """A closed loop whose last step is answered at its cut-off: ``simulate`` finishes the controller when the run
    ends, also when an exception ends it (here an interrupt raised by the reference at the next step), so the
    caller's code after it runs with the process's own BLAS threads, switch interval and collector."""
    import gc

    from threadpoolctl import threadpool_limits

    setup, z, R, _, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=2.0)
    calls, refs = [], []
    real = mpc.finish

    def reference(t):
        refs.append(np.size(t))
        if end == "interrupt" and len(refs) == 4:  # two calls check it, the first step makes the third
            raise KeyboardInterrupt
        return R[np.minimum(np.arange(np.size(t)), len(R) - 1)].reshape(np.shape(t) + (-1,))

    with threadpool_limits(limits=2, user_api="blas"):
        libs = _two_thread_blas()
        before = sys.getswitchinterval()
        gate = Gate(monkeypatch)

        def spy():  # the run is at its end: the held solve may end now
            calls.append((mpc._running is not None, _blas_threads(libs)))
            gate.release()
            real()

        monkeypatch.setattr(mpc, "finish", spy)
        t_final = setup["ts"] * (1 if end == "run" else 3)
        try:
            with pytest.raises(KeyboardInterrupt) if end == "interrupt" else contextlib.nullcontext():
                fl.simulate(setup["system"], mpc, t_final=t_final, ts=setup["ts"], z0=z, reference=reference,
                            progress=False)
        finally:
            gate.release()
        assert gate.entered.is_set() and mpc.history[-1].info["cut_off"], "premise: the last step was cut off"
        assert calls == [(True, {1})] and mpc._running is None
        assert _blas_threads(libs) == {2} and sys.getswitchinterval() == before and gc.isenabled()


def test_an_interrupt_in_a_steps_set_up_leaves_nothing_paused(quad, monkeypatch):
    """An interrupt that lands while a time-limited step sets up its process settings (here in entering the BLAS
    limit, where a random Ctrl-C landed most often) leaves the collector running and nothing kept; the next step
    works. (It once left the collector paused for good, with the user's garbage never collected.)"""
    import gc

    from flnotes import config
    from flnotes.mpc import controller

    setup, z, R, prev, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=5.0)
    real = controller.one_blas_thread

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(controller, "one_blas_thread", interrupted)
    with pytest.raises(KeyboardInterrupt):
        mpc(z, R)
    assert gc.isenabled() and config._GC_USERS == 0 and mpc._held.stack is None
    monkeypatch.setattr(controller, "one_blas_thread", real)
    mpc.set_previous_plan(prev)
    assert mpc(z, R).v is not None and gc.isenabled() and config._GC_USERS == 0


def test_the_shared_pause_holds_across_threads_and_is_checked():
    """Two threads pausing and resuming the collector at once: it is never running while either holds a pause,
    and it runs again at the end (the state the first pause found was once read outside the lock, and the
    collector stayed off for good); a resume without its pause is an error."""
    import gc

    from flnotes import config

    assert gc.isenabled(), "premise: the collector runs"
    seen_running = []

    def work():
        for _ in range(20000):
            config.pause_gc()
            try:
                if gc.isenabled():
                    seen_running.append(1)
            finally:
                config.resume_gc()

    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as possible
    try:
        threads = [threading.Thread(target=work) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(old)
    assert not seen_running and gc.isenabled() and config._GC_USERS == 0
    with pytest.raises(RuntimeError, match="without a pause_gc"):
        config.resume_gc()


def test_a_gone_controllers_settings_come_back_even_when_its_wait_is_interrupted():
    """The finalizer of a dropped controller waits for its solve; an interrupt during that wait is raised only once
    the settings are back (nobody can set them back later)."""
    from contextlib import ExitStack

    from flnotes.mpc.controller import _HeldSettings

    closed = []

    class Done(threading.Event):
        calls = 0

        def wait(self, timeout=None):
            Done.calls += 1
            if Done.calls == 1:
                raise KeyboardInterrupt
            return super().wait(timeout)

    done = Done()
    worker = threading.Thread(target=done.set)
    worker.start()
    held = _HeldSettings()
    stack = ExitStack()
    stack.callback(lambda: closed.append(True))
    held.keep(stack, worker, done)
    with pytest.raises(KeyboardInterrupt):
        held.finalize()
    assert closed == [True] and held.stack is None and Done.calls == 2


def test_qp_repair_resumed_at_any_step_gives_the_uninterrupted_plan(quad):
    """qp_repair publishes its state at its start and after each step; continued from any of them (``resume``) it
    gives the plan of the build that was never stopped, to the last bit, and publishing changes nothing."""
    pred, moved = rt.make_mpc(quad).pred, 0
    for c in ex.mpc_cases(quad, fl.scale(10, 5), seed=11):
        f, _ = pred.linear(c["z"], c["z_ref"])
        V_c, _, _ = pred.qp(f, c["z"])
        for start in ((V_c, None) if V_c is not None else (None,)):
            states = []
            Z_full, V_full = fb.qp_repair(pred, c["z"], f, start, publish=states.append)
            assert np.array_equal(V_full, fb.qp_repair(pred, c["z"], f, start)[1])
            assert [s.k for s in states] == list(range(pred.N + 1))
            for s in states:
                Z_r, V_r = fb.qp_repair(pred, c["z"], f, resume=s)
                assert np.array_equal(V_r, V_full) and np.array_equal(Z_r, Z_full), s.k
            moved += any(s.resolve for s in states[1:])
    assert moved >= 2, "premise: builds that moved an input (the QP solved again after a resume)"


class _NotAnArray(np.ndarray):
    """A subclass of numpy's array (a resume's arrays must be plain float arrays)."""


def test_qp_repair_refuses_a_resume_that_means_nothing(quad):
    """A resume of another kind, with a new start, for another state, cost or horizon, or without the cost's linear
    part is refused with a message, never continued as if it fitted."""
    import dataclasses

    setup, z, R, _, _ = engine_state(quad)
    pred = rt.make_mpc(setup).pred
    f, _ = pred.linear(z, R)
    states = []
    fb.qp_repair(pred, z, f, publish=states.append)
    s = states[3]
    with pytest.raises(TypeError, match="RepairState"):
        fb.qp_repair(pred, z, f, resume=(s.k, s.V))
    with pytest.raises(ValueError, match="not both"):
        fb.qp_repair(pred, z, f, s.guess, resume=s)
    with pytest.raises(ValueError, match="another state"):
        fb.qp_repair(pred, z + 1e-3, f, resume=s)
    with pytest.raises(ValueError, match="another state"):
        fb.qp_repair(pred, z, 2.0 * f, resume=s)
    for bad in (dataclasses.replace(s, k=pred.N + 1), dataclasses.replace(s, V=s.V[:-1]),
                dataclasses.replace(s, guess=np.zeros((pred.N + 1, pred.m)))):
        with pytest.raises(ValueError, match="not a build of this horizon"):
            fb.qp_repair(pred, z, f, resume=bad)
    with pytest.raises(ValueError, match="needs the cost's linear part"):
        fb.fallback_plan(pred, z, None, resume=s)
    for bad in (dataclasses.replace(s, k=3.0), dataclasses.replace(s, k=True), dataclasses.replace(s, V=s.V.tolist()),
                dataclasses.replace(s, V=np.full_like(s.V, np.nan)), dataclasses.replace(s, V=s.V.astype(int)),
                dataclasses.replace(s, V=s.V.astype(complex)), dataclasses.replace(s, V=s.V.view(_NotAnArray))):
        with pytest.raises(ValueError, match="resume is not a build of this horizon"):
            fb.qp_repair(pred, z, f, resume=bad)
    out = np.array(s.V)
    out[0] = pred.v_hi + 1.0
    with pytest.raises(ValueError, match="leave the v box"):
        fb.qp_repair(pred, z, f, resume=dataclasses.replace(s, V=out))
    for resolve in (not s.resolve, "False", np.array([s.resolve])):
        with pytest.raises(ValueError, match="resolve must be a bool"):
            fb.qp_repair(pred, z, f, resume=dataclasses.replace(s, resolve=resolve))
    # a model with the same dynamics, weights and horizon (the same f) but another eps: not its build
    other = rt.make_mpc(dict(setup, eps=0.5 * np.asarray(setup["eps"], float))).pred
    assert np.array_equal(other.linear(z, R)[0], f), "premise: the same f"
    with pytest.raises(ValueError, match="another prediction model"):
        fb.qp_repair(other, z, f, resume=s)
    # refused by the fallback whether or not it would use it: the shifted plan passes, the program is infeasible,
    # the build failed, the deadline has passed
    full = states[-1].V
    assert pred.feasible(z, full), "premise: a shifted plan that passes the check"
    for kw in (dict(shifted=(pred.predict(z, full), full), f=None), dict(shifted=None, f=f, infeasible=True),
               dict(shifted=None, f=f, qp_repair_failed=True), dict(shifted=None, f=f, deadline=time.perf_counter() - 1)):
        with pytest.raises(TypeError, match="RepairState"):
            fb.fallback_plan(pred, z, resume=(s.k, s.V), **kw)
        if kw["f"] is None:
            with pytest.raises(ValueError, match="linear part"):
                fb.fallback_plan(pred, z, resume=s, **kw)
        else:
            with pytest.raises(ValueError, match="another state"):
                fb.fallback_plan(pred, z + 1e-3, resume=s, **kw)


def test_a_published_repair_state_cannot_be_changed_by_its_build_or_its_caller(quad):
    """The arrays of a published RepairState are read-only copies: the build's later steps and a caller that changes
    its own z or f afterwards leave it as it was."""
    setup, z, R, _, _ = engine_state(quad)
    pred = rt.make_mpc(setup).pred
    z = np.array(z, float)
    f = np.array(pred.linear(z, R)[0], float)
    states = []
    _, V_full = fb.qp_repair(pred, z, f, publish=states.append)
    s = states[2]
    V_at_2 = s.V.copy()
    z[:] += 1.0
    f[:] *= 2.0
    for a in (s.z, s.f, s.V, s.guess):
        assert not a.flags.writeable
        with pytest.raises(ValueError):
            a[...] = 0.0
        with pytest.raises(ValueError):
            a.setflags(write=True)  # a view of a read-only copy cannot be made writable again
    assert np.array_equal(s.V, V_at_2) and not np.array_equal(s.z, z) and not np.array_equal(s.f, f)
    with pytest.raises(ValueError, match="another state"):
        fb.qp_repair(pred, z, f, resume=s)
    assert np.array_equal(fb.qp_repair(pred, s.z, s.f, resume=s)[1], V_full)


def test_the_fallback_says_whether_its_plan_satisfies_the_program():
    """Step 3 of the fallback (the repairs' deadline past: an admissible first input, the rest as far as repaired)
    says "violates the program" only for a plan that fails the check, and says it satisfies the program otherwise."""
    from flnotes.studies import unseen as U

    kinds = set()
    for name, N in (("VdP-gain", 40), ("VdP-gain", 8)):
        mpc = U.unseen_mpc(name, ts=0.02, horizon=N)
        c, pred = U.case(name), mpc.pred
        rng = np.random.default_rng(3)
        lo, hi = mpc.system.lo[: pred.nz], mpc.system.hi[: pred.nz]
        for z in np.vstack([np.asarray(c.z0, float)[None, :], rng.uniform(0.8 * lo, 0.8 * hi, (8, pred.nz))]):
            R = c.reference()(0.02 * np.arange(N + 1))
            f, _ = pred.linear(z, R)
            _, V, what, ok = fb.fallback_plan(pred, z, None, f=f, deadline=time.perf_counter() - 1.0)
            if not ok:
                continue
            passes = pred.feasible(z, V)
            assert ("satisfies the program" in what) == passes and ("violates the program" in what) == (not passes)
            kinds.add(passes)
    assert kinds == {True, False}, f"premise: plans that pass and plans that fail, got {kinds}"


def test_a_cut_off_answer_continues_the_first_incumbent_its_engine_had_begun(quad, monkeypatch):
    """The cut-off comes while the engine builds its first incumbent (the relaxation repaired along the QP; here its
    thread is held after step 3 until past the cut-off): the answer hands the build on and the fallback continues it,
    so the plan applied is the one of the uninterrupted build, it passes the check, and the step says where the build
    went on from. Without the hand-over the fallback would start the build again."""
    setup, z, R, _, _ = engine_state(quad)
    mpc = rt.make_mpc(setup, time_limit=0.5, bang_bang=False)
    mpc.fallback_deadline = False  # the continued build is not cut by the fallback's clock on a slow machine
    engine, states = mpc.solver, []
    real = engine._publish_repair

    def held(state):
        real(state)
        states.append(state)
        if state.k == 3:
            time.sleep(0.6)  # past the cut-off (at most the 0.5 s limit after the call's start)

    monkeypatch.setattr(engine, "_publish_repair", held)
    mpc.reset()
    s = mpc(z, R)
    assert s.info["cut_off"] and s.fallback and s.status == "time_limit"
    assert s.info["repair_resumed_at"] == 3 and "continued from its step 3" in s.message
    assert "repair_state" not in s.info, "the build is handed on, not kept in the record"
    f, _ = mpc.pred.linear(z, R)
    _, V_full = fb.qp_repair(mpc.pred, z, f, states[0].guess)
    assert not np.array_equal(V_full[3:], states[3].guess[3:]), "premise: the rest of the build moves inputs"
    assert np.array_equal(s.v_pred, V_full) and s.info["plan_feasible"] and s.input_admissible
    mpc.finish()
    # the fallback's own deadline passed while the engine was held: the build is not continued, and no record says so
    mpc.fallback_deadline = True
    states.clear()
    mpc.reset()
    s = mpc(z, R)
    assert s.info["cut_off"] and s.fallback and states and states[-1].k == 3
    assert s.info["repair_resumed_at"] is None and "continued" not in s.message
    mpc.finish()


def test_the_repaired_relaxation_is_published_before_the_region_moves(quad, monkeypatch):
    """An answer at a cut-off during the region QP (the moves after the first incumbent) has the repaired plan: it is
    published as soon as it passes the check, not after the moves."""
    import flnotes.mpc.engine as E

    setup, z, R, _, _ = engine_state(quad)
    mpc = rt.make_mpc(setup)
    engine, seen = mpc.solver, []
    real = E.region_qp

    def spy(*a, **k):
        seen.append(engine.answer_now())
        return real(*a, **k)

    monkeypatch.setattr(E, "region_qp", spy)
    mpc.reset()
    s = mpc(z, R)
    assert seen, "premise: the region QP ran"
    a = seen[0]
    assert s.info["incumbent"] == "repaired relaxation", "premise: the first incumbent is the repaired relaxation"
    assert a.v is not None and "repaired relaxation" in a.message and a.info["incumbent"] == "repaired relaxation"
    assert mpc.pred.feasible(z, a.v_pred) and a.objective >= s.objective - 1e-9
