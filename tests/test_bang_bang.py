"""One-switch plans at the input bounds as the MPC's first incumbent (``MPCOptions.bang_bang``).

Properties: the coarse-to-fine search returns only admissible inputs (forward pass), keeps admissible guesses and
finds the nearest admissible grid point; the batched plans equal the same plans repaired one by one; a plan flagged
alive passes the program's check; the option never changes the optimum, and on the cold states of Cubic3 where the
repaired relaxation fails it gives the engine an incumbent; meaningless uses raise.
"""
import time

import numpy as np
import pytest

import flnotes as fl
from flnotes.mpc import MPC, MPCOptions
from flnotes.mpc import bang_bang as bb
from flnotes.mpc import fallback as fb
from flnotes.studies import unseen as un

#: Cold states of Cubic3 (seed 0 of its diverse states) whose repaired relaxation fails the check while a plan
#: exists; at both the optimum is bang-bang with one switch.
CUBIC3_STATES = (10, 13)


@pytest.fixture(scope="module")
def cubic3():
    cases = un.diverse_cases("Cubic3", max(CUBIC3_STATES) + 1, seed=0)
    return un.unseen_mpc("Cubic3"), [cases[i] for i in CUBIC3_STATES]


@pytest.fixture(scope="module")
def vdp():
    return un.unseen_mpc("VdP-gain"), un.diverse_cases("VdP-gain", fl.scale(8, 4), seed=1)


def test_nearest_admissible_is_admissible_kept_and_coarse_to_fine(vdp):
    """An inadmissible guess moves to the nearest admissible coarse grid point, or nearer: to the nearest admissible
    fine point between it and the last inadmissible coarse point before it; with no admissible coarse point it stays
    (and is flagged)."""
    mpc, cases = vdp
    pred = mpc.pred
    rng = np.random.default_rng(0)
    Z = np.vstack([c["z"] for c in cases])
    Z = np.vstack([Z, rng.uniform(pred.z_lo, pred.z_hi, (40, pred.nz))])
    v = rng.uniform(pred.v_lo[0], pred.v_hi[0], len(Z))
    v[::3] = pred.v_hi[0]
    v[1::3] = pred.v_lo[0]
    grid = np.linspace(pred.v_lo[0], pred.v_hi[0], bb.GRID)
    coarse = np.zeros(bb.GRID, bool)
    coarse[::bb.COARSE_STRIDE] = coarse[-1] = True
    checked = 0
    for last in (False, True):
        out, ok = bb.nearest_admissible(pred, Z, v, last=last)
        adm = fb._admissible(pred, Z, out[:, None], last)
        assert np.array_equal(ok, adm), "ok must say exactly which returned inputs are admissible"
        was = fb._admissible(pred, Z, v[:, None], last)
        assert np.array_equal(out[was], v[was]), "an admissible guess is kept"
        for i in np.flatnonzero(~was):
            d = np.abs(grid - v[i])
            g_ok = fb._admissible(pred, Z[i], grid[:, None], last)  # brute force over the whole grid
            if not (g_ok & coarse).any():
                assert not ok[i] and out[i] == v[i]
                continue
            d_hit = d[g_ok & coarse].min()
            inner = d[coarse & (d < d_hit)]
            d_prev = inner.max() if inner.size else -1.0
            # the nearest admissible fine point beyond the last inadmissible coarse one (ties in grid order)
            j = np.flatnonzero(g_ok & (d > d_prev) & (d <= d_hit))
            assert ok[i] and out[i] == grid[j[np.argmin(d[j])]], (i, out[i])
            checked += 1
    assert checked >= 20, f"premise: inadmissible guesses that can be moved ({checked})"


def test_nearest_admissible_rejects_wrong_shapes(vdp):
    pred = vdp[0].pred
    with pytest.raises(ValueError, match="one state per guess"):
        bb.nearest_admissible(pred, np.zeros((3, pred.nz)), np.zeros(2))


def test_batched_plans_equal_the_plans_repaired_one_by_one(cubic3, vdp):
    for mpc, cases in (cubic3, vdp):
        pred, N = mpc.pred, mpc.pred.N
        alive_seen = 0
        for c in cases:
            V, alive = bb.one_switch_plans(pred, c["z"])
            assert V.shape == (2 * N, N) and alive.shape == (2 * N,)
            for r in range(2 * N):
                s, (a, b) = r % N + 1, ((pred.v_hi[0], pred.v_lo[0]) if r < N else (pred.v_lo[0], pred.v_hi[0]))
                guess = np.where(np.arange(N) < s, a, b)
                z, W, ok_all = np.asarray(c["z"], float), guess.astype(float), True
                for k in range(N):  # the same plan, one row at a time
                    W[k:k + 1], ok = bb.nearest_admissible(pred, z[None], W[k:k + 1], last=k == N - 1)
                    if not ok[0]:
                        ok_all = False
                        break
                    z = pred.Ad @ z + pred.Bd @ W[k:k + 1]
                assert alive[r] == ok_all, (r, alive[r])
                if ok_all:
                    np.testing.assert_array_equal(V[r], W)
                    # every step admissible and in the box, so only the terminal set can reject it
                    assert pred.feasible(c["z"], V[r]) or pred.F is not None
                    alive_seen += 1
        assert alive_seen >= 2, "premise: some plans are built to the end"


def test_a_passed_deadline_builds_nothing(cubic3):
    mpc, cases = cubic3
    assert bb.one_switch_plans(mpc.pred, cases[0]["z"], deadline=time.perf_counter() - 1.0) is None


def test_one_input_only():
    arm = fl.two_link_arm()
    net, eps, _ = fl.arm_net()
    mpc = MPC(arm, net, eps, horizon=3, ts=0.05)
    assert mpc.options.bang_bang is False  # the default for more than one input
    with pytest.raises(ValueError, match="one input"):
        bb.one_switch_plans(mpc.pred, np.zeros(arm.n_z))
    with pytest.raises(ValueError, match="drop bang_bang"):
        MPC(arm, net, eps, horizon=3, ts=0.05, bang_bang=True)


def test_the_incumbent_where_the_repaired_relaxation_fails_and_the_same_optimum(cubic3):
    """At both Cubic3 states the repaired relaxation fails the check; with bang_bang the engine starts from a
    one-switch plan that passes it, without it from no incumbent, and both solves (no time limit) prove the same
    optimum."""
    mpc, cases = cubic3
    assert mpc.options.bang_bang is True  # the default for one input
    off = mpc.clone(options=MPCOptions(bang_bang=False))
    for c in cases:
        mpc.reset()
        off.reset()
        on_s, off_s = mpc(c["z"], c["z_ref"]), off(c["z"], c["z_ref"])
        assert off_s.info["repair_failed"] and off_s.info["incumbent"] is None, "premise: no first incumbent"
        assert on_s.info["incumbent"] == "one-switch plan"
        for s in (on_s, off_s):
            assert s.status == "optimal" and not s.fallback and mpc.plan_feasible(s.z_pred, s.v_pred), s.message
        assert abs(on_s.objective - off_s.objective) <= 1e-6 * max(1.0, abs(off_s.objective))
        f, c0 = mpc.pred.linear(c["z"], c["z_ref"])
        found = bb.bang_bang_incumbent(mpc.pred, c["z"], f, c0)
        assert found is not None and mpc.pred.feasible(c["z"], found[0])
        assert found[1] >= on_s.objective - 1e-6 * max(1.0, abs(on_s.objective)), "no plan beats the optimum"


@pytest.mark.parametrize("kw, match", [
    (dict(repair=False, bang_bang=True), "repair=False"),
    (dict(repair=False, bang_bang=False), "repair=False"),
    (dict(backend="cvxpy-scip", bang_bang=True), "bang_bang"),
    (dict(constraint="measured", bang_bang=False), "only apply to constraint='network'"),
    (dict(bang_bang="yes"), "True or False"),
])
def test_meaningless_bang_bang_raises(kw, match):
    with pytest.raises((ValueError, TypeError), match=match):
        MPCOptions(**kw)


def test_the_study_row_counts_what_it_says():
    """``bang_bang_row`` on the first 14 cold states of Cubic3 (states 10 and 13 among them): its machine-independent
    counts, and every step whose first incumbent was a one-switch plan returned a plan passing the check."""
    r = un.bang_bang_row("Cubic3", n=max(CUBIC3_STATES) + 1, seed=0)
    assert r["states"] == max(CUBIC3_STATES) + 1
    assert r["qp_feasible"] >= r["screened"] + r["repair_failed"] and r["repair_failed"] >= r["one_switch_found"] >= 2
    assert r["one_switch_unplanned"] == 0 and r["one_switch_used"] <= r["repair_failed"]
    assert r["plans_with"] <= r["qp_feasible"] and r["plans_without"] <= r["qp_feasible"]
    assert r["plans_with"] - r["plans_without"] == r["recovered"] - r["lost"] and r["lost_searched"] <= r["lost"]
