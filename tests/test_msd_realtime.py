"""The MSD real-time benchmark's parts: its states and its table (no timing is asserted)."""
import numpy as np
import pytest

from flnotes.bench import SECTIONS
from flnotes.bench import msd_realtime as B


@pytest.fixture(scope="module")
def s():
    return B.setting()


def test_setting_is_chapter_11s_msd_without_time_limit(s):
    assert s["name"] == "MSD" and s["horizon"] == 10 and s["ts"] == 0.1 and s["time_limit"] is None
    assert [W.shape[0] for W in s["net"].W[:-1]] == [20, 20, 20]
    assert "msd_realtime" in SECTIONS


def test_cold_states_cover_their_kinds_inside_the_box(s):
    states = B.cold_states(s, 12)
    sysm = s["system"]
    lo, hi = sysm.lo[: sysm.n_z], sysm.hi[: sysm.n_z]
    assert [k for k, _, _ in states] == list(B.COLD_KINDS) * 3
    for kind, z, R in states:
        assert R.shape == (s["horizon"] + 1, sysm.n_z)
        assert np.all(z >= lo) and np.all(z <= hi)
        if kind == "face":
            assert np.any(np.isclose(z, lo) | np.isclose(z, hi))
        if kind == "active":  # a constant reference on the far side of the box
            assert np.all(R == R[0]) and R[0, 0] * z[0] < 0
    again = B.cold_states(s, 12)
    assert all(np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2]) for a, b in zip(states, again))


def test_summary_counts_late_steps_and_gaps_only_against_proven_references():
    recs = [dict(status="optimal", objective=10.0, cpu=0.05, wall=0.2),
            dict(status="optimal", objective=5.0 + 1e-3, cpu=0.3, wall=0.31),
            dict(status="time_limit", objective=7.0, cpu=0.1, wall=0.1),
            dict(status="optimal", objective=1.0, cpu=0.01, wall=0.01)]
    row = B.summarize("x", "loop", recs, [10.0, 5.0, 1.0, None], ts=0.1)
    assert row["n"] == 4 and row["cpu_over_ts"] == 1 and row["wall_over_ts"] == 2
    assert row["statuses"] == "optimal 3, time_limit 1"
    assert row["compared"] == 2 and row["max_gap_ref"] == pytest.approx(1e-3 / 5.0)
    assert row["cpu_max_ms"] == pytest.approx(300.0)


def test_configurations_start_with_the_default_and_name_no_highs_row():
    rows = B.configurations()
    assert rows[0] == ("default (auto)", {})
    assert all(o["time_limit"] == B.ROW_LIMIT for n, o in rows if n.endswith(" only"))
    assert "time_limit" not in dict(rows)["default, lazy=False"]
    assert {"SCIP only", "DAQP only"} <= {n for n, _ in rows}
    assert not any("HIGHS" in n.upper() for n, _ in rows)


def test_a_row_of_engine_constants_sets_them_while_it_runs_only():
    """The row without the near steps runs with ``NEAR_ACTIVE = None`` and leaves the engine's value as it was."""
    from flnotes.mpc import engine

    before = engine.NEAR_ACTIVE
    assert "default without the near steps" in dict(B.configurations())
    with B.engine_constants("default without the near steps"):
        assert engine.NEAR_ACTIVE is None
    assert engine.NEAR_ACTIVE == before is not None
    with pytest.raises(RuntimeError):
        with B.engine_constants("default without the near steps"):
            raise RuntimeError("a row that fails")
    assert engine.NEAR_ACTIVE == before
    with B.engine_constants("default (auto)"):
        assert engine.NEAR_ACTIVE == before


def test_the_row_without_step_0s_range_sets_first_range_off_while_it_runs_only():
    from flnotes.mpc import engine

    assert "default without step 0's range" in dict(B.configurations())
    with B.engine_constants("default without step 0's range"):
        assert engine.FIRST_RANGE is False
    assert engine.FIRST_RANGE is True


def test_first_range_rows_compare_the_same_states_with_the_same_verdicts():
    """The rows with and without step 0's exact range: one per state, the same verdict and optimum (the lever is
    exact), fewer binaries in all on these states (the premise of the report's sentence), FIRST_RANGE as it was."""
    from flnotes.mpc import engine

    s = B.setting()
    rows = B.first_range_rows(s, B.cold_states(s, 4, seed=2))
    assert len(rows) == 4 and all(r["same optimum"] for r in rows)
    assert sum(r["binaries with"] for r in rows) < sum(r["binaries without"] for r in rows)
    assert engine.FIRST_RANGE is True
    with pytest.raises(ValueError, match="row must be one of"):
        B.without_rows(s, [], "default (auto)")


def test_hardest_picks_the_longest_steps_in_order():
    recs = [dict(cpu=c) for c in (0.1, 3.0, 0.2, 5.0, 3.0)]
    assert B.hardest(recs, 2) == [1, 3]
    assert B.hardest(recs, 10) == [0, 1, 2, 3, 4]


def test_scip_settings_table_runs_every_setting_side_by_side_with_the_same_optimum():
    """The side-by-side table of SCIP settings on a small program that goes to SCIP: every setting and pass gives a
    row, the first setting is the reference of its pass (speed-up 1), every optimum is the same, and a run-to-run row
    per setting compares its two passes (no timing is asserted)."""
    import flnotes as fl
    from _nets import test_net

    net, _ = test_net("quad1d-6x6")
    opts = fl.MPCOptions(backend="scip", screening=False, bounds="horizon", encode="all", lazy=False)
    make = lambda o: fl.MPC(fl.quad1d(), net, 0.0324, horizon=4, ts=0.1, Q=[10.0, 1.0, 1.0], R=0.0175,  # noqa: E731
                            options=opts, solver_options=o)
    rng = np.random.default_rng(0)
    states = []
    for _ in range(3):
        zr = np.zeros((5, 3))
        z0 = rng.uniform([-1, -2, -2], [1, 2, 2])
        zr[:, 0], zr[:, 1] = rng.uniform(-3, 3), rng.uniform(-2, 2)
        states.append((z0, zr))
    groups = [states[:2], states[2:]]
    runs = B.scip_settings_runs(make, groups, passes=2)
    assert list(runs) == list(B.SCIP_SETTINGS) and all(len(v) == 2 and len(v[0]) == 3 for v in runs.values())
    assert all(r["scip"] >= 1 and r["n_bin"] > 0 for v in runs.values() for p in v for r in p), \
        "the premise: every step hands a mixed-integer program to SCIP"
    rows = B.scip_settings_table(runs, "test")
    assert len(rows) == 3 * len(B.SCIP_SETTINGS)
    timed = [r for r in rows if r["pass"] in ("1", "2")]
    assert all(r["same_optimum"] == "yes" for r in timed), [(r["setting"], r["max_rel_diff"]) for r in timed]
    assert all(r["speedup_median"] == 1.0 for r in timed if r["setting"] == next(iter(B.SCIP_SETTINGS)))
    assert {r["setting"] for r in rows if r["pass"].startswith("run to run")} == set(B.SCIP_SETTINGS)
    for bad in (dict(passes=0), dict(passes=1.5), dict(settings={})):
        with pytest.raises(ValueError, match="scip_settings_runs"):
            B.scip_settings_runs(make, groups, **bad)


def test_near_rows_compare_the_same_states_with_the_same_verdicts():
    """The rows with and without the steps near the bound: one per state, the same verdict and optimum (the lever is
    exact), no more programs in all on these states, and NEAR_ACTIVE as it was afterwards."""
    from flnotes.mpc import engine

    before = engine.NEAR_ACTIVE
    s = B.setting()
    rows = B.near_rows(s, B.cold_states(s, 4, seed=2))
    assert len(rows) == 4 and all(r["same optimum"] for r in rows)
    assert sum(r["programs with"] for r in rows) <= sum(r["programs without"] for r in rows)
    assert engine.NEAR_ACTIVE == before
