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


def test_hardest_picks_the_longest_steps_in_order():
    recs = [dict(cpu=c) for c in (0.1, 3.0, 0.2, 5.0, 3.0)]
    assert B.hardest(recs, 2) == [1, 3]
    assert B.hardest(recs, 10) == [0, 1, 2, 3, 4]
