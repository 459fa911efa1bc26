"""The words :mod:`flnotes.bench.mpc` chooses for the glued sentences of chapter 8 and the benchmark report."""
import numpy as np
import pytest

from flnotes.bench import mpc as rt
from flnotes.repeats import VERDICTS

WITHIN, EDGE, BEYOND = VERDICTS


class _Boxes:
    """A stand-in for the prediction model: the box |V_j| <= 1."""

    def feasible(self, z, V, network=True):
        assert network is False
        return bool(np.all(np.abs(V) <= 1.0))


def test_box_samples_keeps_the_plans_in_the_boxes_in_the_order_drawn():
    V0 = np.zeros((2, 1))
    Vs = rt.box_samples(_Boxes(), None, V0, n=50, scale=0.8, seed=0)
    rng = np.random.default_rng(0)
    drawn = [rng.normal(scale=0.8, size=2) for _ in range(50)]
    expect = [V for V in drawn if np.all(np.abs(V) <= 1.0)]
    assert 0 < len(Vs) < 50 and np.array_equal(Vs, np.array(expect))
    assert rt.box_samples(_Boxes(), None, V0 + 5.0, n=5).shape == (0, 2)  # none in the boxes


def test_slack_numbers_on_the_boundary_and_inside():
    out = rt.slack_numbers([0.5, 0.25, 1.0], np.array([3.0, 4.0]), J_c=2.0)
    assert (out["ex1_slack_min"], out["ex1_grad"]) == (0.25, 5.0)
    assert out["ex1_clause"] == ("the QP's optimum sits on the boundary of the boxes (the gradient there has norm 5), "
                                 "and the smallest slack over the sampled plans is 0.25")
    out = rt.slack_numbers([0.0, 0.0], np.array([1e-9, 0.0]), J_c=10.0)
    assert out["ex1_clause"] == ("the QP's optimum lies inside the boxes (its gradient is zero), and the inequality "
                                 "holds with equality")
    with pytest.raises(ValueError, match="one sampled plan"):
        rt.slack_numbers([], np.zeros(2), 1.0)


def test_screening_numbers_each_case():
    scr = np.array([True, True, False, False, False])
    out = rt.screening_numbers([1.0, 3.0, 10.0, 12.0, 11.0], [9.0, 9.0, 10.5, 11.0, 10.0], scr)
    assert (out["scr_on"], out["not_on"], out["not_off"]) == (2.0, 11.0, 10.5)
    assert out["clause"] == ("The difference, +0.50 ms, is within what the QP and the forward pass cost, as the "
                             "argument expects")
    out = rt.screening_numbers([1.0, 1.0, 10.0, 12.0, 11.0], [9.0, 9.0, 5.0, 5.0, 5.0], scr)
    assert out["clause"].startswith("The difference, +6.00 ms, is larger than what the QP and the forward pass cost, so "
                                    "they do not explain it, and this chapter has not found its cause")
    out = rt.screening_numbers([1.0, 2.0], [3.0, 4.0], [False, False])  # no screened step
    assert np.isnan(out["scr_on"]) and out["not_on"] == 1.5
    assert out["clause"] == "This selection of steps lacks one of the two groups, so there is no difference to read"


def test_cache_lever_clauses_none_one_several():
    row = lambda s, n: dict(system=s, states=n)  # noqa: E731
    assert rt.cache_lever_clauses([row("Quad-1D", 3), row("A", 2)]) == dict(empty="")
    assert rt.cache_lever_clauses([row("Quad-1D", 3), row("A", 0), row("A", 0)]) == dict(
        empty=" The loop of A is not in the table: the screening QP settled every one of its steps, so no state was left "
              "to replay.")
    assert rt.cache_lever_clauses([row("B", 0), row("A", 0), row("B", 0)]) == dict(
        empty=" The loops of B and A are not in the table: the screening QP settled every one of their steps, so no "
              "state was left to replay.")


def test_lever_verdicts_and_their_table():
    spr = dict(cpu_s_total=0.1, cpu_ms_max=0.1)
    compared = [("a", "setting a", dict(cpu_s_total=1.05), dict(cpu_s_total=1.0), "cpu_s_total"),
                ("b", "setting b", dict(cpu_ms_max=1.15), dict(cpu_ms_max=1.0), "cpu_ms_max"),
                ("c", "setting c", dict(cpu_s_total=2.0), dict(cpu_s_total=1.0), "cpu_s_total")]
    assert rt.lever_verdicts(compared, spr) == dict(a=WITHIN, b=EDGE, c=BEYOND)
    rows = rt.lever_verdict_table(compared, spr)
    assert [r["verdict"] for r in rows] == [WITHIN, EDGE, BEYOND]
    assert rows[2] == dict(setting="setting c", figure="cpu_s_total", setting_value=2.0, default_value=1.0, ratio=2.0,
                           spread=0.1, verdict=BEYOND)


def _t(total, median=10.0, slowest=20.0):
    return dict(cpu_s_total=total, cpu_ms_median=median, cpu_ms_max=slowest)


def test_lever_clauses_every_verdict_and_direction():
    spr = dict(cpu_s_total=0.1, cpu_ms_median=0.1, cpu_ms_max=0.1)
    same = (_t(1.0), _t(1.0))
    clauses = lambda secant=same, daqp=same, repair=same: rt.lever_clauses(secant, daqp, repair, same, spr)  # noqa: E731
    # secant (setting = off, default = on) on the CPU time in all
    assert clauses()["secant_clause"] == "not a measured difference on this machine"
    assert clauses(secant=(_t(1.15), _t(1.0)))["secant_clause"] == "weak evidence that the secant regularization shortens it"
    assert clauses(secant=(_t(1.0), _t(1.15)))["secant_clause"] == "weak evidence that the secant regularization lengthens it"
    assert clauses(secant=(_t(2.0), _t(1.0)))["secant_clause"] == "the secant regularization shortens it on this machine"
    assert clauses(secant=(_t(1.0), _t(2.0)))["secant_clause"] == "the secant regularization lengthens it on this machine"
    # DAQP for every program against the default
    assert clauses()["auto_clause"] == ("neither the slowest step nor the CPU time in all differs measurably, so on these "
                                        "steps no measured gain in time supports sending the large programs to SCIP")
    assert clauses(daqp=(_t(1.0, slowest=40.0), _t(1.0)))["auto_clause"] == (
        "the slowest step is shorter with the default, and the CPU time in all does not differ measurably")
    assert clauses(daqp=(_t(1.0, slowest=17.5), _t(1.15)))["auto_clause"] == (
        "the slowest step is longer with the default, on weak evidence, and the CPU time in all is longer with the "
        "default, on weak evidence")
    # the repair: longer, shorter, the same
    out = clauses(repair=(_t(1.0, 10.0, 20.0), _t(2.0, 5.0, 20.0)))["repair_trade"]
    assert out == (f"with the repair, the loop's median step was shorter (10 → 5 ms, {BEYOND} of median steps), its "
                   f"slowest step the same (20 → 20 ms, {WITHIN} of slowest steps) and its CPU time in all longer "
                   f"(1.00 → 2.00 s, {BEYOND}); on the cold states the CPU time in all went 1.0 → 1.0 s ({WITHIN})")
