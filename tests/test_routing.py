"""``backend="auto"`` sends each program to DAQP or SCIP by its binaries (:func:`flnotes.mpc.levers.pick_backend`);
the benchmark section ``routing`` (:mod:`flnotes.bench.routing`) measures the threshold. Asserted here: the recorder
sees the programs the rule routed, and leaves the engine as it found it; both back-ends prove the same optimum on
every recorded program; the threshold's context puts the old value back."""
import pytest

import flnotes.mpc.engine as engine
import flnotes.mpc.levers as levers
from flnotes.bench import SECTIONS
from flnotes.bench import routing as R


@pytest.fixture(scope="module")
def recorded():
    programs: list = []
    made = engine.make_solver
    with R.recorded_programs(programs, "random networks: integrator"):
        R.random_loops(8, seed=2)  # 8 cases: with step 0 written as its range (FIRST_RANGE) fewer steps need rounds
    assert engine.make_solver is made, "the recorder did not put the engine's make_solver back"
    return programs


def test_the_recorder_sees_the_programs_the_rule_routed(recorded):
    assert "routing" in SECTIONS
    assert len(recorded) >= 5, "the premise: random networks whose steps need mixed-integer rounds"
    for rec in recorded:
        p = rec["problem"]
        assert p.is_mip
        assert rec["warm_start"] is None or rec["warm_start"].shape == (p.n,)
        expect = levers.pick_backend("auto", int(p.n_integer), rec["warm_start"] is not None)
        # the rule, or SCIP solving a round again whose DAQP optimum exceeded the bound (the engine's check)
        assert rec["backend"] == expect or rec["backend"] == "scip", (rec["backend"], expect, p.n_integer)
    assert {r["backend"] for r in recorded} >= {"daqp"}


def test_daqp_and_scip_prove_the_same_optimum_on_every_recorded_program(recorded):
    rows = R.solve_both(recorded)
    assert all(R.agree(r) for r in rows), [r for r in rows if not R.agree(r)]
    decided = [r for r in rows if r["daqp_status"] == r["scip_status"] == "optimal"]
    assert len(decided) >= 3, "the premise: programs with an optimum"
    table = R.class_table(rows)
    assert sum(r["programs"] for r in table) == sum(r["warm"] for r in rows if r["binaries"] <= 60)
    th = R.threshold_table(rows, thresholds=(0, 10_000))
    warm = [r for r in rows if r["warm"] and r["binaries"] <= 60]
    assert th[0]["total_s"] == pytest.approx(sum(r["scip_cpu"] for r in warm))
    assert th[1]["total_s"] == pytest.approx(sum(r["daqp_cpu"] for r in warm))


def test_agree_tells_a_wrong_optimum_and_a_wrong_verdict():
    row = dict(daqp_status="optimal", scip_status="optimal", daqp_objective=1.0, scip_objective=1.0 + 1e-9)
    assert R.agree(row)
    assert not R.agree({**row, "daqp_objective": 1.001})
    assert not R.agree({**row, "scip_status": "infeasible"})


def test_the_threshold_context_puts_the_default_back():
    old = levers.AUTO_DAQP_BINARIES
    with R.threshold(7):
        assert levers.pick_backend("auto", 7) == "daqp"
        assert levers.pick_backend("auto", 8) == "scip"
    assert levers.AUTO_DAQP_BINARIES == old
    with pytest.raises(RuntimeError):
        with R.threshold(3):
            raise RuntimeError("inside")
    assert levers.AUTO_DAQP_BINARIES == old
    for bad in (30.9, "40", -1, True, None):
        with pytest.raises(ValueError, match="integer"):
            with R.threshold(bad):
                pass
        assert levers.AUTO_DAQP_BINARIES == old
