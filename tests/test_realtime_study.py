"""The periodic-loop study of chapter 8 (:mod:`flnotes.studies.realtime`): the schedule, the collector's state."""
import gc

import numpy as np
import pytest

from flnotes.bench.mpc import make_mpc, quad_setup
from flnotes.studies import realtime


def test_schedule_on_time_without_pauses():
    late = realtime.periodic_schedule([0.02, 0.05, 0.09], [0.0, 0.0, 0.0], t_s=0.1)
    np.testing.assert_allclose(late, [-0.08, -0.05, -0.01])


def test_a_pause_longer_than_the_slack_makes_the_next_answer_late():
    # step 0 answers at 0.02 and the collector then runs 0.15 s: step 1 starts at 0.17, not at its tick 0.1
    late = realtime.periodic_schedule([0.02, 0.02, 0.02], [0.15, 0.0, 0.0], t_s=0.1)
    np.testing.assert_allclose(late, [-0.08, -0.01, -0.08])
    late = realtime.periodic_schedule([0.02, 0.05, 0.02], [0.15, 0.0, 0.0], t_s=0.1)
    assert late[1] == pytest.approx(0.02) and late[2] < 0  # late once, then back on its tick


def test_schedule_rejects_bad_input():
    with pytest.raises(ValueError, match="one length"):
        realtime.periodic_schedule([0.1, 0.1], [0.0], t_s=0.1)
    with pytest.raises(ValueError, match="t_s"):
        realtime.periodic_schedule([0.1], [0.0], t_s=0.0)


def test_the_study_needs_a_time_limit():
    setup = quad_setup(horizon=3)
    with pytest.raises(ValueError, match="time limit"):
        realtime.gc_loop_row(lambda: make_mpc(setup), setup, t_final=0.2, freeze=False)


def test_gc_study_freezes_and_restores_the_collector():
    setup = quad_setup(horizon=3)
    enabled, frozen = gc.isenabled(), gc.get_freeze_count()
    plain, after = realtime.gc_study(setup, t_final=0.3)
    assert gc.isenabled() == enabled and gc.get_freeze_count() == frozen, "the study left the collector changed"
    assert plain["steps"] == after["steps"] == 3
    assert after["walked"] < plain["walked"] / 10, "after gc.freeze() a full collection walks the set-up objects"
    for r in (plain, after):
        assert r["plans_not_admissible"] == 0 and r["inputs_not_admissible"] == 0 and r["u_within"]
    n = realtime.gc_numbers([plain, after])
    assert n["walked_ratio"] == pytest.approx(after["walked"] / plain["walked"])


def test_gc_numbers_span_the_repeats_and_word_a_direction_only_without_overlap():
    def row(run, hits, late):
        return dict(run=run, steps=10, limit_hits=hits, late_step=late, late_periodic=late, step_max_ms=50.0 + late,
                    gc_in_step=0, gc_between=0, full=0, gc_max_ms=0.0, walked=100, full_ms=1.0)
    plain, frozen = "as set up", "gc.freeze() after set-up"
    rows = [row(plain, 0, 1), row(frozen, 13, 4), row(plain, 2, 0), row(frozen, 9, 1)]
    n = realtime.gc_numbers(rows)
    assert n["repeats"] == 2 and n["plain_limit_hits"] == 0 and n["frozen_limit_hits"] == 13
    assert (n["plain_limit_hits_min"], n["plain_limit_hits_max"]) == (0, 2)
    assert (n["frozen_limit_hits_min"], n["frozen_limit_hits_max"]) == (9, 13)
    assert n["limit_hits_effect"] == realtime.EFFECT_WORDS["higher"]
    assert n["late_step_effect"] == realtime.EFFECT_WORDS["overlapping"]  # 0..1 against 1..4: they share 1
    lower = realtime.gc_numbers([row(plain, 5, 3), row(frozen, 1, 0)])
    assert lower["limit_hits_effect"] == lower["late_step_effect"] == realtime.EFFECT_WORDS["lower"]
    with pytest.raises(ValueError, match="pairs"):
        realtime.gc_numbers(rows[:3])
    with pytest.raises(ValueError, match="pairs"):
        realtime.gc_numbers([rows[1], rows[0]])


def test_gc_study_repeats_the_pair_interleaved():
    setup = quad_setup(horizon=3)
    rows = realtime.gc_study(setup, t_final=0.2, repeats=2)
    assert [(r["repeat"], r["run"]) for r in rows] == [(0, "as set up"), (0, "gc.freeze() after set-up"),
                                                       (1, "as set up"), (1, "gc.freeze() after set-up")]
    with pytest.raises(ValueError, match="repeats"):
        realtime.gc_study(setup, t_final=0.2, repeats=0)


def _gc_row(run, full, full_ms):
    return dict(run=run, full=full, full_ms=full_ms)


def test_gc_clauses_span_the_repeats_and_count_the_full_collections():
    rows = [_gc_row("as set up", 0, 3.0), _gc_row("gc.freeze() after set-up", 0, 1.0),
            _gc_row("as set up", 0, 5.0), _gc_row("gc.freeze() after set-up", 0, 2.0)]
    out = realtime.gc_clauses(rows)
    assert (out["plain_full_ms_min"], out["plain_full_ms_max"]) == (3.0, 5.0)
    assert (out["frozen_full_ms_min"], out["frozen_full_ms_max"]) == (1.0, 2.0)
    assert out["full_clause"] == ("no full collection fell due during the loops as set up (column full), so that cost "
                                  "did not land in them; a longer run, or one that allocates more, can meet it")
    rows[0]["full"] = 1
    assert realtime.gc_clauses(rows)["full_clause"] == (
        "1 full collection fell due during the loops as set up (column full), each a pause of that size between two "
        "answers")
    rows[2]["full"] = 2
    rows[1]["full"] = 5  # the frozen loops do not count
    assert realtime.gc_clauses(rows)["full_clause"].startswith("3 full collections fell due")
