"""The network's affine enclosure and the slab it adds to the MPC's relaxation.

Properties: the enclosure holds at every sampled point of its box, and its MILPs' witnesses come within the solver's
gap of its bounds (it is tight); every admissible point lies in the slab; a solver's bound that does not hold is
refused; the relaxation with the slab is a lower bound of the MIQP, never below the one without it; the engine gives
the same optimum with and without it; bad input raises.
"""
import numpy as np
import pytest

import flnotes as fl
import flnotes.enclosure as E
from flnotes.bench import msd_realtime as B
from flnotes.mpc import MPC

from _nets import test_net, two_msd


@pytest.fixture(scope="module")
def msd():
    s = B.setting()
    return s, fl.affine_enclosure(s["net"], s["system"].lo, s["system"].hi)


def _points(lo, hi, n=100_000, seed=11):
    return np.random.default_rng(seed).uniform(lo, hi, size=(n, len(lo)))


def _witnesses_attain(enc, net):
    """The MILPs' points reach the bounds up to the widening and the gap."""
    tol = (E.PAD + 2 * E.GAP) * np.maximum(1.0, np.abs(enc.r_hi - enc.r_lo))
    r_hi = np.diag(enc.residual(net, enc.x_hi))
    r_lo = np.diag(enc.residual(net, enc.x_lo))
    return np.all(r_hi >= enc.r_hi - tol) and np.all(r_lo <= enc.r_lo + tol)


def test_the_msd_enclosure_holds_everywhere_and_is_tight(msd):
    s, enc = msd
    net, sysm = s["net"], s["system"]
    X = _points(sysm.lo, sysm.hi)
    assert enc.contains(net, X)
    r = enc.residual(net, X)
    assert np.all(r.min(axis=0) >= enc.r_lo) and np.all(r.max(axis=0) <= enc.r_hi)
    assert _witnesses_attain(enc, net)
    assert np.all(enc.contains(net, enc.x_lo)) and np.all(enc.contains(net, enc.x_hi))
    # the premise of the lever on the MSD: Phi = v + s(z_2) + z_1 is nearly affine, so the slab is narrow
    assert np.all(enc.r_hi - enc.r_lo < 2.0 * np.asarray(sysm.u_max))


def test_two_outputs_and_a_small_network():
    sysm, net = two_msd()
    enc = fl.affine_enclosure(net, sysm.lo, sysm.hi)
    assert enc.a.shape == (2, 6) and enc.r_lo.shape == enc.r_hi.shape == (2,)
    assert enc.contains(net, _points(sysm.lo, sysm.hi, 50_000)) and _witnesses_attain(enc, net)
    small, _ = test_net("quad1d-8x8")
    q = fl.quad1d()
    enc = fl.affine_enclosure(small, q.lo, q.hi)
    assert enc.contains(small, _points(q.lo, q.hi, 50_000)) and _witnesses_attain(enc, small)


def test_every_admissible_point_lies_in_the_slab(msd):
    s, enc = msd
    net, sysm = s["net"], s["system"]
    X = _points(sysm.lo, sysm.hi, seed=12)
    u = np.asarray(sysm.u_max) - s["eps"]
    ok = np.all(np.abs(net(X)) <= u, axis=1)
    assert ok.sum() > 1000
    s_lo, s_hi = enc.slab(u)
    ax = X[ok] @ enc.a.T
    assert np.all(ax >= s_lo) and np.all(ax <= s_hi)
    with pytest.raises(ValueError, match="one bound per output"):
        enc.slab([1.0, 2.0])


def test_a_bound_that_does_not_hold_is_refused(monkeypatch):
    sysm, net = two_msd()

    def too_tight(net, form, lo, hi, a_j, j, sense):  # a solver's bound inside the range of the residual
        return 0.0, 0.5 * (lo + hi)

    monkeypatch.setattr(E, "_extreme", too_tight)
    with pytest.raises(RuntimeError, match="do not hold"):
        fl.affine_enclosure(net, sysm.lo, sysm.hi, seed=5, cache=False)


def test_the_cache_tells_networks_apart_by_their_layers_too(monkeypatch):
    monkeypatch.setattr(E, "_CACHE", {})
    rng = np.random.default_rng(8)
    p = rng.normal(size=9)  # the same nine numbers as one layer of 2 neurons, or as three layers of 1
    A = fl.ReLUNet([p[0:4].reshape(2, 2), p[6:8].reshape(1, 2)], [p[4:6], p[8:9]])
    B = fl.ReLUNet([p[0:2].reshape(1, 2), p[3:4].reshape(1, 1), p[5:6].reshape(1, 1), p[7:8].reshape(1, 1)],
                   [p[2:3], p[4:5], p[6:7], p[8:9]])
    flat = lambda n: b"".join(a.tobytes() for W, c in zip(n.W, n.b) for a in (W, c))  # noqa: E731
    assert flat(A) == flat(B)  # the premise: the same parameters in the same order
    lo, hi = [-2.0, -2.0], [2.0, 2.0]
    eA = fl.affine_enclosure(A, lo, hi)
    eB = fl.affine_enclosure(B, lo, hi)
    assert eA.net_id != eB.net_id and eA is not eB
    assert fl.affine_enclosure(A, lo, hi) is eA  # the same network: kept
    X = _points(np.array(lo), np.array(hi), 20_000)
    assert eA.contains(A, X) and eB.contains(B, X)


def test_a_network_without_hidden_layer_is_its_own_enclosure():
    W, b = np.array([[1.0, -2.0, 0.5]]), np.array([0.3])
    net = fl.ReLUNet([W], [b])
    enc = fl.affine_enclosure(net, [-1, -1, -1], [1, 1, 1])
    assert np.array_equal(enc.a, W) and np.all(enc.r_lo <= b) and np.all(b <= enc.r_hi)
    assert np.all(enc.r_hi - enc.r_lo <= 1e-4)


@pytest.mark.parametrize("lo, hi, match", [
    ([-1, -1], [1, 1], "shape"),
    ([-1, -1, -1, -1, -1, -1], [1, 1, 1, 1, 1, -1], "positive width"),
    (np.zeros((2, 6)), np.ones((2, 6)), "one box"),
])
def test_bad_boxes_raise(lo, hi, match):
    _, net = two_msd()
    with pytest.raises(ValueError, match=match):
        fl.affine_enclosure(net, lo, hi)


def _controller(s, **kw):
    return MPC(s["system"], s["net"], s["eps"], horizon=s["horizon"], ts=s["ts"], Q=s["Q"], R=s["R"], **kw)


def test_the_slab_tightens_the_relaxation_and_keeps_the_optimum(msd):
    s, enc = msd
    with_slab, without = _controller(s), _controller(s, enclosure=False)
    assert with_slab.enclosure is enc and without.enclosure is None
    n = 4 if fl.FAST else 12
    tighter = 0
    for kind, z, R in B.cold_states(s, n):
        f, c0 = without.pred.linear(z, R)
        _, J_q, flag_q = without.pred.relaxation(f, z)
        _, J_s, flag_s = with_slab.pred.relaxation(f, z)
        a, b = with_slab(z, R), without(z, R)
        assert a.status == b.status, (kind, a.message, b.message)
        if b.status != "optimal":
            continue
        assert abs(a.objective - b.objective) <= 1e-6 * max(1.0, abs(b.objective)), (kind, a.objective, b.objective)
        tol = 1e-9 * max(1.0, abs(b.objective))
        assert J_q + c0 <= J_s + c0 + tol <= b.objective + 2 * tol, (kind, J_q + c0, J_s + c0, b.objective)
        tighter += J_s > J_q + 1e-6 * max(1.0, abs(J_q))
    assert tighter >= 1  # on states where the bound is active the slab moves the relaxation's optimum


def test_the_enclosure_argument_is_checked(msd):
    s, enc = msd
    other, _ = test_net("quad1d-8x8")
    q = fl.quad1d()
    with pytest.raises(ValueError, match="another network"):
        _controller(s, enclosure=fl.affine_enclosure(other, q.lo, q.hi))
    with pytest.raises(TypeError, match="enclosure must be"):
        _controller(s, enclosure="slab")
    with pytest.raises(ValueError, match="do not run it"):
        _controller(s, enclosure=enc, constraint="measured")
    with pytest.raises(ValueError, match="do not run it"):
        _controller(s, enclosure=False, backend="cvxpy-scip")
    assert _controller(s, constraint="measured").enclosure is None
    sysm = s["system"]
    narrow = fl.affine_enclosure(s["net"], sysm.lo * 0.5, sysm.hi * 0.5)
    with pytest.raises(ValueError, match="must contain the program's box"):
        _controller(s, enclosure=narrow)
    assert _controller(s, enclosure=enc).enclosure is enc


def test_contracted_boxes_keep_every_admissible_point_and_empty_the_others(msd):
    s, enc = msd
    net, sysm = s["net"], s["system"]
    u = np.asarray(sysm.u_max) - s["eps"]
    rng = np.random.default_rng(4)
    c = rng.uniform(sysm.lo, sysm.hi, size=(30, 3))
    w = rng.uniform(0.2, 3.0, size=(30, 3))
    lo, hi = np.maximum(c - w, sysm.lo), np.minimum(c + w, sysm.hi)
    lo2, hi2 = E.contract(enc, lo, hi, u)
    assert np.all(lo2 >= lo) and np.all(hi2 <= hi)
    cut = 0
    for b in range(len(lo)):
        X = rng.uniform(lo[b], hi[b], size=(20_000, 3))
        ok = np.all(np.abs(net(X)) <= u, axis=1)
        inside = np.all((X >= lo2[b]) & (X <= hi2[b]), axis=1)
        assert np.all(inside[ok]), b  # every admissible point stays
        cut += np.any(lo2[b] > lo[b] + 1e-9) or np.any(hi2[b] < hi[b] - 1e-9)
    assert cut >= 5  # the premise: the slab cuts boxes of this size
    # a box where every point has a x above the slab: emptied
    far = enc.hi.copy()
    far_lo = far - 0.2
    assert enc.slab(u)[1][0] < far_lo @ np.maximum(enc.a[0], 0) + far @ np.minimum(enc.a[0], 0)  # the premise
    l3, h3 = E.contract(enc, far_lo[None], far[None], u)
    assert np.any(l3 > h3)


def test_an_enclosure_cannot_be_changed_and_a_wrong_one_is_refused(msd):
    s, enc = msd
    with pytest.raises(ValueError, match="read-only"):
        enc.r_hi[:] -= 1.0  # the cached object stays the checked one
    fields = {k: getattr(enc, k) for k in ("a", "r_lo", "r_hi", "lo", "hi", "x_lo", "x_hi", "net_id")}
    with pytest.raises(ValueError, match="r_lo <= r_hi"):
        fl.AffineEnclosure(**{**fields, "r_lo": enc.r_hi, "r_hi": enc.r_lo})
    with pytest.raises(ValueError, match="finite"):
        fl.AffineEnclosure(**{**fields, "r_hi": [np.nan]})
    with pytest.raises(ValueError, match="n_out, n_in"):
        fl.AffineEnclosure(**{**fields, "a": enc.a[0]})
    shifted = fl.AffineEnclosure(**{**fields, "r_lo": enc.r_lo + 0.8, "r_hi": enc.r_hi + 0.8})
    with pytest.raises(ValueError, match="does not hold"):
        _controller(s, enclosure=shifted)
    flat = fl.AffineEnclosure(**{**fields, "a": np.zeros_like(enc.a)})
    with pytest.raises(ValueError, match="does not hold"):
        _controller(s, enclosure=flat)


@pytest.mark.parametrize("kw, match", [(dict(seed=1.7), "seed"), (dict(seed=True), "seed"), (dict(seed=-1), "seed"),
                                       (dict(cache="no"), "cache")])
def test_bad_seed_or_cache_raise(kw, match):
    sysm, net = two_msd()
    with pytest.raises(TypeError, match=match):
        fl.affine_enclosure(net, sysm.lo, sysm.hi, **kw)
