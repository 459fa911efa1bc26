"""The cut study of the benchmark (:mod:`flnotes.studies.cuts`): every cut keeps every point of the program, the
relaxation's bound never passes the optimum, and the program's optimum is unchanged (no timing is asserted)."""
import numpy as np
import pytest

from flnotes.bench import msd_realtime as B
from flnotes.mpc.program import plan_vector
from flnotes.studies import compare as C
from flnotes.studies import cuts


@pytest.fixture(scope="module")
def lp():
    """The level program at the first of the Quad-1D's cold 'active' states (24 binaries when written)."""
    s = C.setting("Quad-1D", time_limit=None)
    ctrl = B.controller(s)
    kind, z, R = B.cold_states(s, 4)[2]
    assert kind == "active"
    prog = cuts.level_program(ctrl, z, R)
    assert prog.prob.n_integer > 0 and prog.steps  # the premise: a program with binaries to cut
    return prog


def _feasible_points(lp, n=400, seed=0):
    """Program points ``w`` (hidden values from the forward pass) of plans near the optimum that meet every row."""
    rng = np.random.default_rng(seed)
    pred = lp.pred
    pts = [plan_vector(pred, lp.z0, lp.V_opt, lp.nb, lp.steps, lp.prob)]
    for scale in (1e-3, 1e-2, 1e-1):
        for _ in range(n // 3):
            V = np.clip(lp.V_opt + scale * rng.standard_normal(lp.V_opt.shape), pred.v_lo, pred.v_hi)
            w = plan_vector(pred, lp.z0, V, lp.nb, lp.steps, lp.prob)
            if lp.prob.violation(w) <= 1e-9:
                pts.append(w)
    return pts


def test_ideal_cuts_keep_every_point_of_the_program(lp):
    pts = _feasible_points(lp)
    assert len(pts) > 20  # the premise: points to check the cuts on
    relaxed = cuts.relaxation(lp.prob)
    rows, rhs = cuts.ideal_cuts(lp, relaxed[0])
    # the relaxation's optimum violates some cut (else the test checks nothing) and no program point does
    assert rows
    A, b = np.array(rows), np.array(rhs)
    assert np.max(A @ relaxed[0] - b) > cuts.VIOLATION_TOL
    for w in pts:
        assert np.all(A @ w <= b + 1e-7 * np.maximum(1.0, np.abs(b))), "an ideal cut removes a point of the program"


def test_projection_cut_holds_for_every_sampled_input_meeting_the_bound(lp):
    rng = np.random.default_rng(1)
    net, k = lp.pred.net, lp.steps[len(lp.steps) // 2]
    lo, hi = lp.lo[k], lp.hi[k]
    X = lo + (hi - lo) * rng.random((20000, lo.size))
    ok = np.abs(net(X)[:, 0]) <= lp.u_in[0]
    assert ok.sum() > 100  # the premise: inputs in the box that meet the bound
    for _ in range(3):
        g = rng.standard_normal(lo.size)
        beta, x = cuts.projection_beta(net, lp.nb, k, lo, hi, lp.u_in, g)
        assert np.max(X[ok] @ g) <= beta
        # beta is the maximum: SCIP's point is an input of the box that meets the bound and reaches it
        assert np.all(x >= lo - 1e-9) and np.all(x <= hi + 1e-9)
        assert abs(net(x[None, :])[0, 0]) <= lp.u_in[0] + 1e-6
        assert g @ x <= beta and g @ x >= beta - 1e-6 * max(1.0, abs(beta))


@pytest.mark.parametrize("family", cuts.FAMILIES)
def test_cuts_raise_the_bound_up_to_the_optimum_and_keep_it(lp, family):
    out = cuts.with_cuts(lp, family, rounds=3)
    b = np.array(out["bounds"])
    tol = 1e-6 * max(1.0, abs(lp.J_opt))
    assert np.all(np.diff(b) >= -tol) and b[-1] <= lp.J_opt + tol
    if family != "big-M":
        assert out["cuts"] > 0
    else:
        assert out["cuts"] == 0 and out["prob"] is lp.prob
    from flnotes.solvers import make_solver
    w0 = plan_vector(lp.pred, lp.z0, lp.V_opt, lp.nb, lp.steps, out["prob"])
    res = make_solver(out["prob"], "scip").solve(warm_start=w0, gap=1e-9)
    assert res.status == "optimal" and res.objective == pytest.approx(lp.J_opt, rel=1e-6, abs=1e-6)


def test_cut_rows_report_the_same_optimum_and_the_gap_closed():
    s = C.setting("Quad-1D", time_limit=None)
    rows = cuts.cut_rows(B.controller(s), [B.cold_states(s, 4)[2]], rounds=2)
    assert [r["family"] for r in rows] == list(cuts.FAMILIES)
    assert all(r["same optimum"] for r in rows)
    assert rows[0]["gap closed %"] == 0.0 and rows[0]["cuts"] == 0
    assert all(r["root bound"] <= r["J_opt"] + 1e-6 * max(1, abs(r["J_opt"])) for r in rows)


def test_cut_numbers_quote_each_range_once_when_its_ends_agree():
    row = lambda fam, t, closed: {"family": fam, "engine cpu s": t, "LP bounds cpu s": 1.0, "scip cpu s": 0.85,  # noqa: E731
                                  "scip nodes": 3, "J_opt": 100.0, "root bound": 97.0, "gap closed %": closed,
                                  "cut cpu s": 1.25}
    rows = [row(f, t, c) for t, c in ((3.6, 4.0), (4.6, 61.0)) for f in cuts.FAMILIES]
    num = cuts.cut_numbers(rows)
    assert num["engine"] == "3.60 to 4.60" and num["scip"] == "0.85" and num["nodes"] == "3"
    assert num["rel"] == "3.0%" and num["ideal"] == "4% to 61%" and num["proj_cut"] == "1.2"
    with pytest.raises(ValueError, match="every family"):
        cuts.cut_numbers([r for r in rows if r["family"] != "projection"])


def test_bad_input_is_refused():
    s = C.setting("Quad-1D", time_limit=None)
    with pytest.raises(ValueError, match="time_limit"):
        cuts.level_program(B.controller(dict(s), time_limit=0.1), *B.cold_states(s, 1)[0][1:])
    kind, z, R = B.cold_states(s, 4)[3]  # the reference state: screened, nothing to encode in the level set
    with pytest.raises(ValueError, match="no step needs the network"):
        cuts.level_program(B.controller(s), z, R)
    with pytest.raises(ValueError, match="family must be one of"):
        cuts.with_cuts(None, "hull")


def test_fast_bench_section_produces_the_rows(tmp_path, monkeypatch):
    from flnotes.bench import SECTIONS
    from flnotes.bench import cuts as section

    monkeypatch.setenv("FLNOTES_BENCH_DIR", str(tmp_path))
    sec = section.run(fast=True)
    assert "cuts" in SECTIONS
    rows = sec["rows"]
    assert [r["family"] for r in rows] == list(cuts.FAMILIES)
    assert all(r["state"].startswith(f"{section.FAST_STATE} ") and r["same optimum"] for r in rows)
    assert not any(n.startswith("skipped") for n in sec["notes"])
