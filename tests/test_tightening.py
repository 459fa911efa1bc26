"""Tightened node bounds stay valid: they contain every sampled feasible pre-activation."""
from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

import flnotes as fl
from flnotes.tightening import EmptyBoxError, ellipsoid_box, horizon_boxes, intersect, lp_bounds

from _nets import test_net


@pytest.fixture(scope="module")
def small_net():
    """A small ReLU network fitted to the Quad-1D map on a coarse grid, stored with the tests."""
    net, _ = test_net("quad1d-8x8")
    return fl.quad1d(), net


def _samples(net, lo, hi, n=40_000, seed=0):
    X = np.random.default_rng(seed).uniform(lo, hi, (n, net.n_in))
    out, pre = net.forward(X)
    return X, out, pre


def _contains(bounds, pre, tol=1e-7):
    return all(np.all(a >= L - tol) and np.all(a <= U + tol) for a, L, U in zip(pre, bounds.L, bounds.U))


def _not_looser(tight, loose, tol=1e-9):
    return all(np.all(Lt >= Ll - tol) and np.all(Ut <= Ul + tol)
               for Lt, Ll, Ut, Ul in zip(tight.L, loose.L, tight.U, loose.U))


def test_fbbt_and_lp_bounds_contain_every_sampled_preactivation(small_net):
    s, net = small_net
    lo, hi = s.lo.copy(), s.hi.copy()
    lo[0], hi[0] = -1.0, 2.0  # a smaller box, to exercise stable neurons
    _, _, pre = _samples(net, lo, hi)
    fb = fl.fbbt(net, lo, hi)
    lp = lp_bounds(net, lo, hi)
    assert _contains(fb, pre) and _contains(lp, pre)
    assert _not_looser(lp, fb)
    assert lp.n_unstable <= fb.n_unstable
    assert sum(float((U - L).sum()) for L, U in zip(lp.L, lp.U)) < sum(float((U - L).sum()) for L, U in zip(fb.L, fb.U))


def test_lp_bounds_with_output_bounds_contain_every_feasible_sample(small_net):
    s, net = small_net
    u_eps = 0.1745 - 0.0322
    X, out, pre = _samples(net, s.lo, s.hi, n=200_000, seed=1)
    ok = np.all(np.abs(out) <= u_eps, axis=1)
    assert ok.sum() > 1000  # the check below must see many feasible points
    b = lp_bounds(net, s.lo, s.hi, out_bounds=(-np.array([u_eps]), np.array([u_eps])))
    assert b.method == "lp+out"
    assert _contains(b, [a[ok] for a in pre])
    assert _not_looser(b, lp_bounds(net, s.lo, s.hi))
    assert np.all(b.out_L >= -u_eps - 1e-6) and np.all(b.out_U <= u_eps + 1e-6)


def test_skip_stable_gives_the_same_binaries_and_valid_bounds(small_net):
    s, net = small_net
    lo, hi = s.lo * 0.3, s.hi * 0.3
    full, fast = lp_bounds(net, lo, hi), lp_bounds(net, lo, hi, skip_stable=True)
    _, _, pre = _samples(net, lo, hi, seed=2)
    assert _contains(fast, pre)
    assert _not_looser(fast, fl.fbbt(net, lo, hi))
    assert fast.n_unstable >= full.n_unstable  # never fewer binaries than the full tightening


def test_batched_lp_bounds_match_box_by_box(small_net):
    s, net = small_net
    rng = np.random.default_rng(3)
    c = rng.uniform(s.lo * 0.5, s.hi * 0.5, (3, net.n_in))
    lo, hi = c - 0.5, c + 0.5
    batch = lp_bounds(net, lo, hi)
    for t in range(3):
        one = lp_bounds(net, lo[t], hi[t])
        for k in range(len(one.L)):
            assert np.allclose(batch.L[k][t], one.L[k]) and np.allclose(batch.U[k][t], one.U[k])
        _, _, pre = _samples(net, lo[t], hi[t], n=5_000, seed=t)
        assert _contains(one, pre)


def _flat(b):
    return np.concatenate([*b.L, *b.U, b.out_L, b.out_U])


def test_the_bounds_of_a_box_do_not_depend_on_the_boxes_tightened_before():
    # The LP is kept between calls (one per network and output bound) and warm-started; the bounds of a box must
    # still be those of a fresh LP to the last bit, or an MPC step's program, hence a closed loop, would depend on
    # the loops that ran before it in the same process. The paper's MSD network with the MPC's output bound.
    sysm, (net, _) = fl.paper.system("MSD"), fl.paper.paper_net("MSD")
    c = sysm.u_max - float(np.max(fl.paper.paper_eps("MSD").upper))
    rng = np.random.default_rng(0)
    mid = rng.uniform(sysm.lo, sysm.hi, (200, net.n_in))
    mid = mid[np.abs(net(mid)[:, 0]) < c[0]][:6]                 # each box holds an admissible input
    half = 0.3 * (sysm.hi - sysm.lo) * rng.uniform(0.1, 1.0, (6, net.n_in))
    lo, hi = np.maximum(mid - half, sysm.lo), np.minimum(mid + half, sysm.hi)
    fresh = [_flat(fl.LPTightener(net, out_bounds=(-c, c)).tighten(lo[t], hi[t], skip_stable=True)) for t in range(6)]
    used = fl.LPTightener(net, out_bounds=(-c, c))
    for t in (5, 4, 3, 2, 1, 0):                         # the other boxes first, in another order
        assert np.array_equal(_flat(used.tighten(lo[t], hi[t], skip_stable=True)), fresh[t]), t
    batch = lp_bounds(net, lo, hi, out_bounds=(-c, c), skip_stable=True)
    for t in range(6):
        one = lp_bounds(net, lo[t], hi[t], out_bounds=(-c, c), skip_stable=True)
        assert np.array_equal(_flat(one), fresh[t]) and np.array_equal(
            np.concatenate([*(a[t] for a in batch.L), *(a[t] for a in batch.U), batch.out_L[t], batch.out_U[t]]),
            fresh[t]), t


def test_output_bounds_that_no_input_meets_raise(small_net):
    s, net = small_net
    with pytest.raises(EmptyBoxError):
        lp_bounds(net, s.lo, s.hi, out_bounds=(np.array([50.0]), np.array([60.0])))


def test_horizon_boxes_contain_every_simulated_trajectory():
    s = fl.quad1d()
    Ad, Bd = s.discretize(0.1, "rk4")
    z0 = np.array([-0.5, -0.15, -0.2])
    z_lo, z_hi, v_lo, v_hi = s.lo[:3], s.hi[:3], s.lo[3:], s.hi[3:]
    N = 12
    lo, hi = horizon_boxes(Ad, Bd, z0, z_lo, z_hi, v_lo, v_hi, N)
    assert lo.shape == hi.shape == (N, 4)
    assert np.allclose(lo[0, :3], z0) and np.allclose(hi[0, :3], z0)
    rng = np.random.default_rng(0)
    n_kept = 0
    for _ in range(4000):
        V = rng.choice([v_lo[0], v_hi[0]], N)[:, None] * rng.uniform(0.3, 1.0) if rng.random() < 0.5 \
            else rng.uniform(v_lo, v_hi, (N, 1))
        Z = [z0]
        for k in range(N - 1):
            Z.append(Ad @ Z[-1] + Bd @ V[k])
        Z = np.array(Z)
        if np.any(Z < z_lo) or np.any(Z > z_hi):
            continue  # leaves the state box: not admissible in the MPC
        n_kept += 1
        X = np.hstack([Z, V])
        assert np.all(X >= lo - 1e-9) and np.all(X <= hi + 1e-9)
    assert n_kept > 1000
    # tighter than the state box after a few steps, never wider
    assert np.all(lo[:, :3] >= z_lo - 1e-12) and np.all(hi[:, :3] <= z_hi + 1e-12)
    assert np.all(hi[1:4, 2] - lo[1:4, 2] < z_hi[2] - z_lo[2])


def test_horizon_boxes_reject_a_state_outside_the_box():
    s = fl.quad1d()
    Ad, Bd = s.discretize(0.1, "rk4")
    with pytest.raises(EmptyBoxError):
        horizon_boxes(Ad, Bd, [9.0, 0, 0], s.lo[:3], s.hi[:3], s.lo[3:], s.hi[3:], 5)
    with pytest.raises(ValueError, match="horizon"):
        horizon_boxes(Ad, Bd, [0.0, 0, 0], s.lo[:3], s.hi[:3], s.lo[3:], s.hi[3:], 0)


def test_fbbt_on_horizon_boxes_contains_the_preactivations_along_trajectories(small_net):
    s, net = small_net
    Ad, Bd = s.discretize(0.1, "rk4")
    z0 = np.array([0.3, -0.2, 0.1])
    N = 6
    lo, hi = horizon_boxes(Ad, Bd, z0, s.lo[:3], s.hi[:3], s.lo[3:], s.hi[3:], N)
    nb = fl.fbbt(net, lo, hi)
    rng = np.random.default_rng(1)
    kept = 0
    for _ in range(1000):
        V = rng.uniform(s.lo[3:], s.hi[3:], (N, 1))
        Z = [z0]
        for k in range(N - 1):
            Z.append(Ad @ Z[-1] + Bd @ V[k])
        Z = np.array(Z)
        if np.any(Z < s.lo[:3]) or np.any(Z > s.hi[:3]):
            continue  # not admissible: the MPC keeps the predictions in the state box
        kept += 1
        pre = net.preactivations(np.hstack([Z, V]))
        for k in range(N):
            assert all(np.all(a[k] >= L[k] - 1e-9) and np.all(a[k] <= U[k] + 1e-9) for a, L, U in zip(pre, nb.L, nb.U))
    assert kept > 200


def test_ellipsoid_box_contains_the_level_set():
    rng = np.random.default_rng(0)
    F = rng.normal(size=(5, 5))
    H = F @ F.T + 0.5 * np.eye(5)
    V_c, delta = rng.normal(size=5), 0.7
    S, off = rng.normal(size=(3, 5)), rng.normal(size=3)
    lo, hi = ellipsoid_box(S, np.linalg.inv(H), V_c, off, delta)
    # points on and inside the ellipsoid 0.5 (V - V_c)' H (V - V_c) <= delta
    D = rng.normal(size=(20_000, 5))
    r = np.sqrt(np.einsum("ij,jk,ik->i", D, H, D) / (2 * delta))
    P = V_c + D / r[:, None] * rng.uniform(0, 1, (20_000, 1))
    Y = P @ S.T + off
    assert np.all(Y >= lo - 1e-9) and np.all(Y <= hi + 1e-9)
    # and the box is tight: the extremes are attained on the boundary
    for i in range(3):
        g = np.linalg.solve(H, S[i])
        v_max = V_c + g * np.sqrt(2 * delta / (S[i] @ g))
        assert np.isclose(S[i] @ v_max + off[i], hi[i])


def test_intersect_is_valid_and_tighter(small_net):
    s, net = small_net
    a = fl.fbbt(net, s.lo, s.hi)
    b = lp_bounds(net, s.lo, s.hi)
    c = intersect(a, b)
    assert _not_looser(c, a) and _not_looser(c, b)
    _, _, pre = _samples(net, s.lo, s.hi, n=20_000, seed=4)
    assert _contains(c, pre)


def test_lp_bounds_stop_at_the_deadline(small_net):
    """A deadline in the past stops LP tightening before its first LP (a controller's time limit); a deadline far
    ahead changes nothing beyond the LP solver's tolerance (the persistent LP is warm-started)."""
    import time

    from flnotes.tightening import DeadlineReached

    sysm, net = small_net
    lo, hi = sysm.lo, sysm.hi
    with pytest.raises(DeadlineReached):
        lp_bounds(net, lo, hi, deadline=time.perf_counter() - 1.0)
    a, b = lp_bounds(net, lo, hi), lp_bounds(net, lo, hi, deadline=time.perf_counter() + 1e6)
    for x, y in zip(a.L + a.U, b.L + b.U):
        assert np.allclose(x, y, rtol=1e-6, atol=1e-6)


def test_mpc_time_limit_during_lp_bounds_returns_an_admissible_answer():
    """With LP bounds on every level-set round and almost no time, the MPC stops in the LP bounds or before them and
    still answers: the warm start when it is feasible, or a flagged fallback; never an exception."""
    from flnotes.mpc import MPC, sine_reference

    sysm = fl.quad1d()
    net, _ = test_net("quad1d-6x6")
    kw = dict(horizon=10, ts=0.1, Q=[10.0, 1.0, 1.0], R=0.0175)
    mpc = MPC(sysm, net, 0.0324, lp=True, time_limit=1e-4, **kw)
    fl.simulate(sysm, mpc, t_final=1.0, ts=0.1, z0=[0.0, 0.0, 0.0], reference=sine_reference(1.5), net=net)
    assert all(s.status in ("optimal", "time_limit", "infeasible") for s in mpc.history)
    assert any(s.status == "time_limit" for s in mpc.history), "the premise: the limit stops some step"
    for s in mpc.history:
        assert (not s.info["plan_feasible"]) or mpc.plan_feasible(s.z_pred, s.v_pred)


def test_lp_bounds_from_two_threads_at_once_are_those_of_one_thread(small_net):
    """The LP of a network is shared by every caller (a controller answered at its cut-off can still be tightening
    in its thread while another controller solves): two threads tightening the same network at once get the bounds
    of one thread alone, and nothing crashes."""
    import threading

    s, net = small_net
    rng = np.random.default_rng(3)
    c = rng.uniform(s.lo * 0.5, s.hi * 0.5, (12, net.n_in))
    lo, hi = c - 0.5, c + 0.5
    alone = [lp_bounds(net, lo[t], hi[t]) for t in range(len(lo))]
    seen, errors = {0: [], 1: []}, []

    def run(w: int) -> None:
        try:
            for _ in range(5):
                for t in range(len(lo)):
                    seen[w].append((t, lp_bounds(net, lo[t], hi[t])))
        except BaseException as exc:                       # re-raised below, in the test's thread
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(w,)) for w in (0, 1)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors, errors
    for w in (0, 1):
        assert len(seen[w]) == 5 * len(lo)
        for t, b in seen[w]:
            for k in range(net.K - 1):
                assert np.array_equal(b.L[k], alone[t].L[k]) and np.array_equal(b.U[k], alone[t].U[k])


_BADLY_SCALED = json.loads((Path(__file__).parent / "data" / "badly_scaled_lp_cases.json").read_text())


@pytest.mark.parametrize("case", _BADLY_SCALED, ids=[c["name"] for c in _BADLY_SCALED])
def test_lp_bounds_hold_on_badly_scaled_networks_whatever_the_lp_solver_says(case):
    """Networks whose weights span 1e-9 to 1e6 (found by independent attacks): HiGHS called non-optimal points
    optimal (a bound 1e-3 too tight at a box corner, 18.7 on 2.5e7) and feasible LPs infeasible, and interval
    arithmetic without outward rounding cut a corner by 140 units in the last place (and, as the LP's rows, emptied a
    box 2e-12 wide). The bounds are now the dual's safe bounds on outward-rounded intervals, so each stored witness
    ``x`` (in the box, meeting ``out_bounds``) lies within them, in exact arithmetic where the case says so."""
    net = fl.ReLUNet([np.array(w, float) for w in case["W"]], [np.array(v, float) for v in case["b"]])
    lo, hi, x = (np.array(case[k], float) for k in ("lo", "hi", "x"))
    ob = None if case["out_bounds"] is None else tuple(np.array(v, float) for v in case["out_bounds"])
    y, pre = net.forward(x[None])
    assert np.all(lo <= x) and np.all(x <= hi)  # the premise: a point of the box ...
    assert ob is None or np.all((ob[0] <= y[0]) & (y[0] <= ob[1]))  # ... that meets the output bound
    nb = lp_bounds(net, lo, hi, out_bounds=ob, skip_stable=case["skip_stable"])  # no EmptyBoxError
    for a, L, U in list(zip(pre, nb.L, nb.U)) + [(y, nb.out_L, nb.out_U)]:
        tol = 1e-9 * (1.0 + np.abs(a[0]))
        assert np.all(a[0] >= L - tol) and np.all(a[0] <= U + tol)
    if case.get("exact"):  # the witness's pre-activations in exact arithmetic, against the bounds with no tolerance
        yk = [Fraction(float(v)) for v in x]
        for k, (W, b) in enumerate(zip(net.W, net.b)):
            a = [sum((Fraction(float(W[i, j])) * yk[j] for j in range(len(yk))), Fraction(float(b[i])))
                 for i in range(W.shape[0])]
            L, U = (nb.L[k], nb.U[k]) if k < net.K - 1 else (nb.out_L, nb.out_U)
            assert all(Fraction(float(lo_)) <= v <= Fraction(float(hi_)) for v, lo_, hi_ in zip(a, L, U)), k
            yk = [max(v, Fraction(0)) for v in a]


def test_lp_bounds_of_a_network_without_a_hidden_layer_are_its_exact_output_range():
    net = fl.ReLUNet([np.array([[1.0, -2.0]])], [np.array([0.5])])
    nb = lp_bounds(net, np.zeros(2), np.ones(2))
    assert nb.L == [] and np.allclose([nb.out_L[0], nb.out_U[0]], [-1.5, 1.5])
    nb = lp_bounds(net, np.zeros(2), np.ones(2), out_bounds=(np.array([-1.0]), np.array([1.0])))
    assert np.allclose([nb.out_L[0], nb.out_U[0]], [-1.0, 1.0])
    with pytest.raises(EmptyBoxError):
        lp_bounds(net, np.zeros(2), np.ones(2), out_bounds=(np.array([2.0]), np.array([3.0])))


def test_lp_bounds_follow_a_network_changed_in_place():
    net = fl.ReLUNet([np.array([[1.0]]), np.array([[1.0]]), np.array([[1.0]])], [np.zeros(1)] * 3)
    assert lp_bounds(net, np.zeros(1), np.ones(1)).U[1][0] == pytest.approx(1.0, rel=1e-6)
    net.W[0][0, 0] = 5.0  # the same object, other parameters: the LP built for the old ones must not be reused
    assert lp_bounds(net, np.zeros(1), np.ones(1)).U[1][0] == pytest.approx(5.0, rel=1e-6)


def _exact_preactivations(net, x) -> list:
    """The pre-activations of every layer at ``x`` in exact rational arithmetic (the output last)."""
    yk, out = [Fraction(float(v)) for v in x], []
    for W, b in zip(net.W, net.b):
        a = [sum((Fraction(float(W[i, j])) * yk[j] for j in range(len(yk))), Fraction(float(b[i])))
             for i in range(W.shape[0])]
        out.append(a)
        yk = [max(v, Fraction(0)) for v in a]
    return out


def test_fbbt_contains_every_preactivation_of_badly_scaled_networks_exactly_and_in_floating_point():
    """``fl.fbbt`` rounds every interval outward by the error bound of its sums: on the stored networks whose weights
    span 1e-9 to 1e6 its bounds contain each witness's pre-activations with no tolerance, computed exactly and by the
    floating-point forward pass. Without the rounding (``outward=False``) some are cut (the premise)."""
    cut = 0
    for case in _BADLY_SCALED:
        net = fl.ReLUNet([np.array(w, float) for w in case["W"]], [np.array(v, float) for v in case["b"]])
        lo, hi, x = (np.array(case[k], float) for k in ("lo", "hi", "x"))
        corners = np.array(np.meshgrid(*[[a, b] for a, b in zip(lo, hi)], indexing="ij")).reshape(len(lo), -1).T
        for nb_kw in (dict(), dict(outward=False)):
            nb = fl.fbbt(net, lo, hi, **nb_kw)
            Ls, Us = list(nb.L) + [nb.out_L], list(nb.U) + [nb.out_U]
            ok = True
            for p in np.vstack([x[None], corners[:16]]):
                y, pre = net.forward(p[None])
                for a, ex, L, U in zip(list(pre) + [y], _exact_preactivations(net, p), Ls, Us):
                    ok &= bool(np.all(a[0] >= L) and np.all(a[0] <= U))
                    ok &= all(Fraction(float(lo_)) <= v <= Fraction(float(hi_)) for v, lo_, hi_ in zip(ex, L, U))
            if nb_kw:
                cut += not ok
            else:
                assert ok, case["name"]
    assert cut >= 1, "the premise: the plain intervals cut a pre-activation of some stored network"


def test_a_box_whose_bounds_cross_the_prior_is_empty_not_bounded():
    """With out_bounds and a valid prior, a box where the network stays far outside out_bounds has no feasible point:
    the bounds cross and that is an EmptyBoxError, never crossed bounds returned as if valid."""
    net, _ = fl.paper_net("MSD")
    msd = fl.msd()
    lo, hi = msd.lo, msd.hi
    ob = (np.array([-2.0]), np.array([2.0]))
    P = lp_bounds(net, lo, hi, out_bounds=ob)
    rng = np.random.default_rng(0)
    X = rng.uniform(lo, hi, (20000, 3))
    far = X[np.argsort(-np.abs(net(X)[:, 0]))[:40]]
    assert np.all(np.abs(net(far)[:, 0]) > 10.0)  # premise: far outside out_bounds
    for p in far[:10]:
        blo, bhi = np.maximum(p - 0.05, lo), np.minimum(p + 0.05, hi)
        with pytest.raises(fl.tightening.EmptyBoxError):
            lp_bounds(net, blo, bhi, out_bounds=ob, prior=P, skip_stable=True)
