"""The bound atlas: its covers hold at every sampled admissible point, the MPC reads them instead of LPs and finds
the same optimum, and a wrong atlas is refused."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import flnotes as fl
from flnotes import paper
from flnotes.atlas import BoundAtlas, shipped_atlas
from flnotes.bench import msd_realtime as M

from _nets import two_msd


@pytest.fixture(scope="module")
def small():
    """A random 3-12-10-1 network, its domain box, a bound u met on part of it, and its atlas."""
    rng = np.random.default_rng(7)
    net = fl.ReLUNet([rng.normal(size=(12, 3)), rng.normal(size=(10, 12)) * 0.4, rng.normal(size=(1, 10))],
                     [rng.normal(size=12) * 0.3, rng.normal(size=10) * 0.3, np.zeros(1)])
    lo, hi = np.array([-2.0, -1.0, -3.0]), np.array([2.0, 1.0, 3.0])
    u = 0.5
    return net, lo, hi, u, fl.bound_atlas(net, lo, hi, u, (4, 3, 5))


def _admissible_preactivations(net, X, u):
    y, pre = net.forward(X)
    ok = np.all(np.abs(y) <= u, axis=1)
    return [a[ok] for a in pre], int(ok.sum())


def test_the_cover_of_a_box_holds_at_every_sampled_admissible_point(small):
    net, lo, hi, u, atlas = small
    rng = np.random.default_rng(0)
    boxes = []
    for _ in range(60):  # random boxes, some on the grid's edges or of zero width in some inputs
        a, b = rng.uniform(lo, hi), rng.uniform(lo, hi)
        blo, bhi = np.minimum(a, b), np.maximum(a, b)
        if rng.random() < 0.3:
            i = rng.integers(3)
            blo[i] = bhi[i] = atlas.edges[i][rng.integers(len(atlas.edges[i]))]
        boxes.append((blo, bhi))
    boxes.append((lo, hi))
    L, U = atlas.cover(np.array([b[0] for b in boxes]), np.array([b[1] for b in boxes]))
    n_checked = 0
    for t, (blo, bhi) in enumerate(boxes):
        X = rng.uniform(blo, bhi, size=(4000, 3))
        pre, n = _admissible_preactivations(net, X, u)
        n_checked += n
        for k, a in enumerate(pre):
            assert np.all(a >= L[k][t] - 1e-9) and np.all(a <= U[k][t] + 1e-9), (t, k)
    assert n_checked > 10_000  # the premise: the bound is met on a good part of the boxes


def test_the_cover_is_at_least_as_tight_as_fbbt_where_it_says_something(small):
    net, lo, hi, u, atlas = small
    L, U = atlas.cover(lo[None], hi[None])
    nb = fl.fbbt(net, lo, hi)
    assert any(np.any(a[0] > b + 1e-6) for a, b in zip(L, nb.L)) or any(np.any(a[0] < b - 1e-6) for a, b in zip(U, nb.U))


def test_empty_cells_hold_no_admissible_sample(small):
    net, lo, hi, u, atlas = small
    empty = np.argwhere(atlas.empty)
    assert 0 < len(empty) < atlas.empty.size  # the premise: the bound leaves some cells without admissible input
    rng = np.random.default_rng(1)
    for idx in empty:
        clo = np.array([atlas.edges[i][j] for i, j in enumerate(idx)])
        chi = np.array([atlas.edges[i][j + 1] for i, j in enumerate(idx)])
        assert _admissible_preactivations(net, rng.uniform(clo, chi, size=(2000, 3)), u)[1] == 0


def test_an_atlas_survives_a_save_and_load(small, tmp_path):
    net, lo, hi, u, atlas = small
    atlas.save(tmp_path / "a.npz")
    back = fl.load_atlas(tmp_path / "a.npz")
    assert back.net_id == atlas.net_id and np.array_equal(back.u, atlas.u)
    assert all(np.array_equal(a, b) for a, b in zip(back.edges + back.L + back.U, atlas.edges + atlas.L + atlas.U))
    fl.check_atlas(net, back)


def test_a_wrong_atlas_or_a_wrong_request_is_refused(small):
    net, lo, hi, u, atlas = small
    other = fl.ReLUNet([w.copy() for w in net.W], [b.copy() for b in net.b])
    other.W[1][0, 0] += 1.0
    with pytest.raises(ValueError, match="another network"):
        fl.check_atlas(other, atlas)
    shifted = dataclasses.replace(atlas, U=tuple(a - 1.0 for a in atlas.U))  # bounds that no longer hold
    with pytest.raises(ValueError, match="does not hold"):
        fl.check_atlas(net, shifted)
    with pytest.raises(ValueError, match="outside the atlas's domain"):
        atlas.cover(lo[None] - 1.0, hi[None])
    with pytest.raises(ValueError, match="cells must be"):
        fl.bound_atlas(net, lo, hi, u, (2, 2))
    with pytest.raises(ValueError, match="u must be positive"):
        fl.bound_atlas(net, lo, hi, -1.0, (2, 2, 2))
    with pytest.raises(ValueError, match="hi > lo"):
        fl.bound_atlas(net, lo, lo, u, (2, 2, 2))
    with pytest.raises(ValueError, match="no hidden layer"):
        fl.bound_atlas(fl.ReLUNet([np.ones((1, 3))], [np.zeros(1)]), lo, hi, u, (2, 2, 2))
    with pytest.raises(TypeError):
        fl.check_atlas(net, "atlas")


def test_the_shipped_atlas_serves_the_books_msd_and_nothing_else():
    s = M.setting()
    ctrl = M.controller(s)
    assert isinstance(ctrl.atlas, BoundAtlas)
    fl.check_atlas(s["net"], ctrl.atlas)
    assert np.all(ctrl.u_eps <= ctrl.atlas.u)
    quad_net, _ = paper.paper_net("Quad-1D")
    quad = paper.system("Quad-1D")
    assert shipped_atlas(quad_net, quad.lo, quad.hi, 1.0) is None
    # the MSD's network with a larger bound than the atlas was tightened with: not served
    assert shipped_atlas(s["net"], ctrl.atlas.lo, ctrl.atlas.hi, ctrl.atlas.u + 0.1) is None
    assert M.controller(s, atlas=False).atlas is None
    assert M.controller(s, backend="cvxpy-scip").atlas is None  # the reference computes no LP bounds of its own


def test_the_mpc_refuses_an_atlas_it_cannot_use(small):
    s = M.setting()
    atlas = M.controller(s).atlas
    with pytest.raises(ValueError, match="compute none"):
        M.controller(s, atlas=atlas, bounds="horizon")
    with pytest.raises(ValueError, match="compute none"):
        M.controller(s, atlas=atlas, lp=False)
    with pytest.raises(ValueError, match="another network"):
        M.controller(s, atlas=small[4])
    with pytest.raises(TypeError, match="atlas must be"):
        M.controller(s, atlas="yes")
    with pytest.raises(ValueError, match="u_max\\^eps"):
        M.controller(s, atlas=dataclasses.replace(atlas, u=atlas.u * 0.5))
    narrow = dataclasses.replace(atlas, edges=tuple(e * 0.5 for e in atlas.edges))
    with pytest.raises(ValueError):  # a smaller domain (its bounds no longer hold either)
        M.controller(s, atlas=narrow)


def _counting_cover(monkeypatch):
    calls = []
    orig = BoundAtlas.cover

    def cover(self, lo, hi):
        calls.append(len(np.atleast_2d(lo)))
        return orig(self, lo, hi)

    monkeypatch.setattr(BoundAtlas, "cover", cover)
    return calls


@pytest.mark.parametrize("index", [2, 3, 5])
def test_the_msd_mpc_with_the_atlas_finds_the_optimum_without_it(index, monkeypatch):
    """Hard cold states of the MSD's MIQP (the input bound active, a sine reference, a box face): the same status
    and optimum with the atlas's covers as with the LP bounds, and the covers were read."""
    s = M.setting()
    kind, z, R = M.cold_states(s, 6, seed=1)[index]
    plain = M.controller(s, atlas=False)(z, R)
    calls = _counting_cover(monkeypatch)
    with_atlas = M.controller(s)(z, R)
    assert sum(calls) > 0
    assert with_atlas.status == plain.status == "optimal"
    assert with_atlas.objective == pytest.approx(plain.objective, rel=1e-6, abs=1e-6)
    assert with_atlas.info["plan_feasible"]


@pytest.mark.parametrize("levers", [dict(bounds="lp", screening=False),
                                    dict(bounds="levelset", lp=True, screening=False)])
def test_a_computed_atlas_serves_a_two_input_mpc_with_the_same_optimum(levers, monkeypatch):
    sysm, net = two_msd()
    net = fl.ReLUNet(list(net.W[:-1]) + [4.0 * net.W[-1]], list(net.b))  # outputs 4 times larger: the bound binds
    lo, hi = sysm.lo, sysm.hi
    atlas = fl.bound_atlas(net, lo, hi, np.asarray(sysm.u_max, float), (2,) * 6)
    rng = np.random.default_rng(4)
    served = 0
    for _ in range(3):
        z = rng.uniform(lo[:4], hi[:4]) * 0.9
        R = np.zeros((6, 4))
        R[:, 0], R[:, 2] = -4.5 * np.sign(z[0]), -4.5 * np.sign(z[2])
        plain = fl.MPC(sysm, net, 0.0, horizon=5, ts=0.1, atlas=False, **levers)(z, R)
        calls = _counting_cover(monkeypatch)
        ctrl = fl.MPC(sysm, net, 0.0, horizon=5, ts=0.1, atlas=atlas, **levers)
        res = ctrl(z, R)
        monkeypatch.undo()
        assert res.status == plain.status
        if plain.status == "optimal":
            assert res.objective == pytest.approx(plain.objective, rel=1e-6, abs=1e-6)
        served += sum(calls)
    assert served > 0  # the covers were read (where the level set leaves a step to bound)


def test_the_reports_rows_give_the_same_verdict_with_and_without_the_atlas():
    s = M.setting()
    rows = M.atlas_rows(s, M.cold_states(s, 3, seed=2)[1:3])
    assert len(rows) == 2 and all(r["same optimum"] for r in rows)
    assert {"binaries without", "binaries with", "cpu s without", "cpu s with"} <= set(rows[0])


def test_an_atlas_cannot_be_changed_in_place_and_a_changed_shipped_file_is_refused(small, tmp_path, monkeypatch):
    net, lo, hi, u, atlas = small
    with pytest.raises(ValueError):
        atlas.U[0][0, 0, 0, 0] = -1e9
    with pytest.raises(ValueError):
        atlas.U[0].setflags(write=True)  # backed by bytes: read-only for good
    src = np.array(atlas.L[0])  # an atlas built from a writable array keeps a copy of its own
    built = BoundAtlas(atlas.edges, (src,) + atlas.L[1:], atlas.U, atlas.u, atlas.net_id)
    src[...] = 0.0
    assert np.array_equal(built.L[0], atlas.L[0])
    # the shipped file with one bound lowered (within what a sample of the domain sees): refused by its digest
    import flnotes.atlas as A

    s = M.setting()
    shipped = M.controller(s).atlas
    U = [np.array(a) for a in shipped.U]
    U[1][..., 1] -= 1e-3
    tampered = BoundAtlas(shipped.edges, shipped.L, tuple(U), shipped.u, shipped.net_id)
    tampered.save(tmp_path / "MSD.atlas.npz")
    monkeypatch.setattr(A, "_SHIPPED_CACHE", {})
    monkeypatch.setattr(A, "DATA", tmp_path)
    with pytest.raises(ValueError, match="contents changed"):
        M.controller(s)
    (tmp_path / "MSD.atlas.npz").unlink()  # missing, or not an atlas: refused too, never run without it silently
    monkeypatch.setattr(A, "_SHIPPED_CACHE", {})
    with pytest.raises(ValueError, match="cannot be read"):
        M.controller(s)
    (tmp_path / "MSD.atlas.npz").write_bytes(b"not an atlas")
    monkeypatch.setattr(A, "_SHIPPED_CACHE", {})
    with pytest.raises(ValueError, match="cannot be read"):
        M.controller(s)
    assert M.controller(s, atlas=False).atlas is None  # the way out the message names


def test_bad_atlas_arguments_get_short_clear_errors(small):
    net, lo, hi, u, atlas = small
    s = M.setting()
    with pytest.raises(ValueError) as err:
        M.controller(s, atlas=M.controller(s).atlas, bounds="box")
    assert len(str(err.value)) < 400 and "compute none" in str(err.value)
    for cells in ((2.0, 2, 2), (np.nan, 2, 2), (2, 2, 0), (True, 2, 2)):
        with pytest.raises(ValueError, match="cells must be"):
            fl.bound_atlas(net, lo, hi, u, cells)
    with pytest.raises(ValueError, match="same shape"):
        BoundAtlas(atlas.edges, atlas.L, tuple(a[..., :-1] for a in atlas.U), atlas.u, atlas.net_id)
    with pytest.raises(ValueError, match="cells"):
        BoundAtlas(atlas.edges[:-1] + (atlas.edges[-1][:-1],), atlas.L, atlas.U, atlas.u, atlas.net_id)
    with pytest.raises(ValueError, match="NaN"):
        BoundAtlas(atlas.edges, (np.full_like(atlas.L[0], np.nan),) + atlas.L[1:], atlas.U, atlas.u, atlas.net_id)
    with pytest.raises(ValueError, match="shape"):
        atlas.covers(lo[:2], hi[:2])


def test_the_msd_mpc_near_the_domain_corner_with_lp_true_is_optimal():
    """Found by an independent attack: with the atlas and ``lp=True`` DAQP's point failed the check on a QP and
    HiGHS ended in "Solve error" (status "error"); SCIP now decides such a QP."""
    s = M.setting()
    z, R = np.array([-4.999995, 4.999995]), np.tile([4.5, 0.0], (s["horizon"] + 1, 1))
    plain = M.controller(s, atlas=False)(z, R)
    res = M.controller(s, lp=True)(z, R)
    assert plain.status == res.status == "optimal"
    assert res.objective == pytest.approx(plain.objective, rel=1e-6)
