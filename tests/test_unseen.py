"""Systems not in the book (flnotes.studies.unseen): shipped networks, certified eps, exact MPC, true |u| <= u_max."""
import json

import numpy as np
import pytest

import flnotes as fl
from flnotes.mpc import MPCOptions
from flnotes.reference import DATA_DIR, load_reference, weights_sha256
from flnotes.studies import unseen as U

NAMES = list(U.CASES)


def test_cases_have_both_roles_and_three_held_out():
    roles = [c.role for c in U.CASES.values()]
    assert roles.count("tuning") == 2 and roles.count("held-out") >= 3
    assert len({(U.case(n).horizon, U.case(n).ts, U.unseen_system(n).n_z) for n in NAMES}) >= 4  # not one setting


@pytest.mark.parametrize("name", NAMES)
def test_shipped_network_loads_with_checksum(name, tmp_path):
    ref = load_reference(U.case(name).reference_name)
    assert weights_sha256(ref.net) == ref.meta["sha256"]
    s = U.unseen_system(name)
    assert (ref.net.n_in, ref.net.n_out) == (s.n_in, s.m)
    assert ref.meta["eps_settings"] == U.EPS_SETTINGS and ref.bracket["lower"] <= ref.bracket["upper"]
    # a damaged copy is refused
    stem = U.case(name).reference_name
    (tmp_path / f"{stem}.json").write_text((DATA_DIR / f"{stem}.json").read_text())
    W = [w.copy() for w in ref.net.W]
    W[0][0, 0] += 1e-9
    fl.ReLUNet(W, [b.copy() for b in ref.net.b]).save(tmp_path / f"{stem}.npz")
    with pytest.raises(ValueError, match="checksum"):
        load_reference(stem, folder=tmp_path)
    assert json.loads((DATA_DIR / f"{stem}.json").read_text())["name"] == stem


@pytest.mark.parametrize("name", NAMES)
def test_certified_eps_bounds_the_error_on_dense_samples(name):
    _, eps, ref = U.unseen_net(name)
    err = U.dense_error(name, n=fl.scale(400_000, 100_000), seed=1)
    assert 0.0 < err <= eps
    assert eps < U.unseen_system(name).u_max[0]  # an admissible input is left


@pytest.mark.parametrize("name", NAMES)
def test_mpc_optimum_equals_cold_reference(name):
    """Default options against the cold SCIP reference on diverse states (N_p = 4 keeps the reference quick)."""
    c = U.case(name)
    net, eps, _ = U.unseen_net(name)
    mk = lambda o: fl.MPC(c.make(), net, eps, horizon=4, ts=c.ts, Q=list(c.Q), R=c.R, options=o)
    mpc, ref = mk(None), mk(MPCOptions(backend="cvxpy-scip"))
    compared = 0
    for cs in U.diverse_cases(name, 4, seed=0, horizon=4):  # one state of each category
        mpc.reset()
        s, r = mpc(cs["z"], cs["z_ref"]), ref(cs["z"], cs["z_ref"])
        if s.status == "optimal":
            assert np.all(np.abs(net(np.hstack([s.z_pred[:4], s.v_pred]))) <= mpc.u_eps + 1e-6)  # forward pass
        if r.status == "optimal" and not r.fallback:
            assert s.status == "optimal" and not s.fallback, (name, cs["category"], s.message)
            assert s.objective == pytest.approx(r.objective, rel=1e-5, abs=1e-6), (name, cs["category"])
            compared += not s.screened
        elif r.status == "infeasible":
            assert s.status == "infeasible", (name, cs["category"], s.message)
    assert compared >= 1, f"{name}: no state where the network constraint mattered was compared"


@pytest.mark.parametrize("name", NAMES)
def test_short_closed_loop_keeps_true_input_within_bound(name):
    """The case's scenario on the true plant, N_p = 4 (the guarantee does not depend on the horizon)."""
    c = U.case(name)
    steps = 10
    log, mpc, timed = U.closed_loop(name, t_final=steps * c.ts, horizon=4)
    assert log.n_steps == steps and not log.message
    assert any(not s.screened for s in mpc.history), "premise: the network constraint binds at some step"
    u_max = U.unseen_system(name).u_max
    assert np.all(np.abs(log.u) <= u_max + 1e-9)
    assert np.all(np.abs(log.u_nn) <= mpc.u_eps + 1e-6)
    assert len(timed.wall) == len(timed.cpu) == steps
    row = U.closed_loop_row(name, log, mpc, timed)
    assert row["max_u_over_u_max"] <= 1.0


def test_unknown_case_is_refused():
    with pytest.raises(ValueError, match="unknown system"):
        U.case("Pendulum")


def test_step_phase_reads_the_step_record():
    v = np.zeros(1)
    assert U.step_phase(fl.StepResult(v, screened=True)) == "screening"
    assert U.step_phase(fl.StepResult(v, message="the incumbent is optimal (warm start; level set empty)")) == "confirmation"
    assert U.step_phase(fl.StepResult(v, rounds=2, nodes=10, message="daqp: optimal")) == "levels"
    assert U.step_phase(fl.StepResult(v, status="infeasible", fallback=True)) == "fallback"


def test_plans_at_the_time_limit_are_checked_and_never_below_the_optimum():
    """VdP-gain (held out) with time_limit = t_s: every plan passes the forward-pass check, the true input stays
    within u_max, and a plan returned at the limit is never cheaper than the optimum proven without the limit
    (its distance is >= 0: the heuristic plan is feasible, the optimum is the optimum)."""
    r = U.deadline_row("VdP-gain", steps=fl.scale(12, 8), horizon=6, optimum_limit=30.0)
    assert r["plans_admissible"] == r["steps"] and r["max_u_over_u_max"] <= 1.0
    assert r["opt_undecided"] == 0
    if r["limit_hits"]:
        assert r["opt_gap_max"] >= -1e-6


def test_diverse_states_under_the_time_limit_are_checked_against_the_optimum():
    """Cubic3 (held out): cold diverse states with time_limit = t_s against the same states solved without it.
    No first input exceeds u_max^eps by the network's forward pass unless flagged, every plan that fails the
    forward-pass check is explained (a limit hit without a plan, or a program proven infeasible), and no plan
    returned at the limit is cheaper than the optimum."""
    n = fl.scale(6, 4)
    exact, *_ = U.diverse_run("Cubic3", n, seed=0, time_limit=60.0)
    lim, wall, cpu, _ = U.diverse_run("Cubic3", n, seed=0, time_limit=U.case("Cubic3").ts)
    d = U.diverse_deadline_row("Cubic3", lim, wall, cpu, exact)
    assert d["states"] == n and d["inputs_not_admissible"] == 0
    infeasible_not_hit = sum(e.status == "infeasible" and s.status != "time_limit" for s, e in zip(lim, exact))
    without = d["without_plan_infeasible"] + d["without_plan_missed"] + d["without_plan_undecided"]
    assert d["plans_admissible"] + without + infeasible_not_hit == n, "a plan fails the check unexplained"
    # never below the optimum, which the solve without the limit proves to a relative gap of 1e-6 (NaN: none)
    assert not d["opt_gap_max"] < -2e-6


def test_diverse_deadline_row_refuses_other_states():
    """Rows of different states (another seed) are an error that says what to pass, not a silent comparison."""
    a, wall, cpu, _ = U.diverse_run("Chain4-gain", 2, seed=0, time_limit=1.0)
    b, *_ = U.diverse_run("Chain4-gain", 2, seed=1, time_limit=1.0)
    with pytest.raises(ValueError, match="same states"):
        U.diverse_deadline_row("Chain4-gain", a, wall, cpu, b)
    with pytest.raises(ValueError, match="same states"):
        U.diverse_deadline_row("Chain4-gain", a, wall, cpu, b[:1])


def test_late_steps_names_each_answer_after_ts_and_where_its_time_went():
    h = [fl.StepResult(np.zeros(1), solve_time=0.01),
         fl.StepResult(np.zeros(1), status="time_limit", solve_time=0.045, info={"cut_off": True}),
         fl.StepResult(np.zeros(1), status="time_limit", solve_time=0.02, fallback=True)]
    assert U.late_steps(h, [0.01, 0.049, 0.03], [0.01, 0.05, 0.03], ts=0.05) == ""
    text = U.late_steps(h, [0.01, 0.06, 0.07], [0.01, 0.03, 0.069], ts=0.05)
    assert text.startswith("step 1: 60.0 ms wall, 30.0 ms CPU, engine 45.0 ms, time_limit, at the cut-off; ")
    assert text.endswith("step 2: 70.0 ms wall, 69.0 ms CPU, engine 20.0 ms, time_limit, fallback")
    h[1].info["cpu_time"] = 0.004  # the controller's threads' CPU time until the answer, as fl.MPC records it
    text = U.late_steps(h, [0.01, 0.06, 0.07], [0.01, 0.03, 0.069], ts=0.05)
    assert text.startswith("step 1: 60.0 ms wall, 30.0 ms CPU (4.0 ms of the controller's threads until the answer), "
                           "engine 45.0 ms, ")


def test_bang_bang_numbers_sums_and_words_the_verdict():
    def row(found, failed, search_ms, t_s_ms):
        r = {key: 1 for key in U.BANG_BANG_COUNTS}
        r.update(one_switch_found=found, repair_failed=failed, plans_with=5, plans_without=3, search_ms_max=search_ms,
                 t_s_ms=t_s_ms, wall_max_over_ts_with=0.5 * search_ms)
        return r

    out = U.bang_bang_numbers([row(2, 4, 10.0, 100.0), row(1, 3, 30.0, 200.0)])
    assert (out["states"], out["one_switch_found"], out["repair_failed"], out["net"]) == (2, 3, 7, 4)
    assert (out["search_ms"], out["search_share"], out["wall_max_with"]) == (30.0, 0.15, 15.0)
    assert out["verdict"] == ("where the repair fails, the one-switch plans gave a cold step a first incumbent at 3 of "
                              "those 7 states, one it had no other way to get (a count that does not depend on the "
                              "machine), for a search of at most 15% of the sampling period; that is why the default "
                              "keeps the lever on")
    out = U.bang_bang_numbers([row(0, 4, 10.0, 100.0), row(0, 0, 2.0, 100.0)])
    assert out["verdict"] == ("on these states the lever found no incumbent at the 4 states where the repair failed, so "
                              "it is not shown to pay here; its search took at most 10% of the sampling period")
    assert all(isinstance(out[k], int) for k in U.BANG_BANG_COUNTS)
