"""The MPC of eq. (MPC_form_miqp) on the 1-D quadrotor: closed loop, exactness against SCIP, errors."""
import dataclasses

import numpy as np
import pytest

import flnotes as fl
from flnotes.mpc import MPC, sine_reference
from flnotes.studies import closed_loop_checks, compare_to_reference, input_guarantee, recorded_problems

from _nets import stored_integrator_case

S = fl.paper.QUAD_SETTING
EPS = fl.paper.TABLE1["Quad-1D"]["eps"]


@pytest.fixture(scope="module")
def quad():
    net, _ = fl.paper_net("Quad-1D")
    return fl.quad1d(), net


@pytest.fixture(scope="module")
def run(quad):
    """A short closed loop with the book's default levers (fast mode of the chapter's run)."""
    sysm, net = quad
    ref = sine_reference(1.5, 1.0)
    mpc = MPC(sysm, net, EPS, horizon=S["horizon"], ts=S["ts"], Q=S["Q"], R=S["R"], time_limit=30.0)
    log = fl.simulate(sysm, mpc, t_final=6.0, ts=S["ts"], z0=S["z0"], reference=ref, net=net)
    return log, mpc, ref


def test_closed_loop_respects_the_input_bound_at_samples(run):
    log, mpc, ref = run
    assert log.message == ""
    assert log.n_steps == 60
    u_max = log.system.u_max[0]
    # the true input at every sampling instant: |Phi(z_k, v_k)| <= u_max (Proposition 1)
    assert np.all(np.abs(log.u) <= u_max + 1e-9)
    # and the network's output is within u_max^eps there (it is the constraint imposed)
    assert np.all(np.abs(log.u_nn) <= mpc.u_eps + 1e-6)
    # the constraint matters in this run (otherwise the test would be trivially true)
    assert np.max(np.abs(log.u_nn)) >= 0.99 * mpc.u_eps[0]


def test_input_guarantee_is_checked_at_every_step(run):
    log, mpc, _ = run
    g = input_guarantee(log, mpc)
    # an admissible v exists at every state of this loop, and every applied input keeps |Phi_NN| <= u_max^eps
    assert g["steps"] == log.n_steps and g["admissible_exists"] == g["steps"] and g["violations"] == 0
    # the check can fail: an applied output above u_max^eps at a step where an admissible v exists is counted
    u_nn = np.array(log.u_nn, float)
    u_nn[3] = 2.0 * mpc.u_eps
    assert input_guarantee(dataclasses.replace(log, u_nn=u_nn), mpc)["violations"] == 1


def test_every_predicted_step_satisfies_the_network_constraint(run):
    log, mpc, _ = run
    for k, st in enumerate(log.steps):
        pred = st.u_nn_pred
        assert pred.shape == (mpc.N, 1)
        assert np.all(np.abs(pred) <= mpc.u_eps + 1e-6), f"step {k}: predicted |Phi_NN| = {np.abs(pred).max()}"
        # the predicted states stay in the network's domain box (eq. MPC_form_miqp_d)
        assert np.all(mpc.system.in_domain(st.z_pred, tol=1e-6))
        # the prediction is the nominal model's (eq. MPC_form_miqp_c)
        Z, V = st.z_pred, st.v_pred
        assert np.allclose(Z[1:], Z[:-1] @ mpc.Ad.T + V @ mpc.Bd.T, atol=1e-7)


def test_tracking_error_shrinks(run):
    log, mpc, ref = run
    chk = closed_loop_checks(log, mpc, ref)
    e = np.abs(log.z[:, 0] - ref(log.t)[:, 0])
    first, last = e[: len(e) // 3], e[-len(e) // 3:]
    assert last.max() < 0.5 * first.max()
    assert chk["tracking_error_rms_second_half"] < chk["tracking_error_initial"]
    assert chk["non_optimal_steps"] == 0 and chk["fallback_steps"] == 0


def test_optimum_equals_a_cold_scip_solve(run, quad):
    """On recorded states that needed the MIQP, the optimal cost equals SCIP's on the full program."""
    log, mpc, _ = run
    hard = [k for k, h in enumerate(mpc.history) if not h.screened]
    assert len(hard) >= 3
    picks = [hard[0], hard[len(hard) // 2], hard[-1]]
    rows = compare_to_reference(mpc, recorded_problems(log, picks))
    for r in rows:
        assert r["status"] == "optimal" and r["scip_status"] == "optimal"
        assert r["rel_diff"] <= 1e-6, r


def test_screened_steps_are_exact(run):
    """A step returned by screening is the QP optimum and satisfies the constraint: the MIQP optimum."""
    log, mpc, _ = run
    scr = [k for k, h in enumerate(mpc.history) if h.screened]
    assert scr, "no step was screened in this run"
    h = mpc.history[scr[0]]
    assert h.nodes == 0 and np.all(np.abs(h.u_nn_pred) <= mpc.u_eps)


def test_time_limit_is_reported_never_silent(quad):
    sysm, net = quad
    ref = sine_reference(1.5, 1.0)
    mpc = MPC(sysm, net, EPS, horizon=S["horizon"], ts=S["ts"], Q=S["Q"], R=S["R"], screening=False)
    first = mpc(S["z0"], ref(S["ts"] * np.arange(11)))
    assert first.status == "optimal"
    mpc = mpc.clone(time_limit=1e-6, warm_start=False)
    mpc.set_previous_plan((first.z_pred, first.v_pred))
    z1 = first.z_pred[1]
    st = mpc(z1, ref(S["ts"] * (1 + np.arange(11))))
    assert st.status == "time_limit"
    assert st.v is not None
    # either the solver's incumbent (feasible for the whole program) or the shifted previous plan
    assert st.fallback or mpc.plan_feasible(st.z_pred, st.v_pred)
    if st.fallback:
        assert np.allclose(st.v, first.v_pred[1])
    assert mpc.summary()["time_limit_hits"] == 1


def test_bad_inputs_give_clear_errors(quad):
    sysm, net = quad
    mpc = MPC(sysm, net, EPS, horizon=5, ts=0.1, Q=S["Q"], R=S["R"])
    with pytest.raises(ValueError, match="outside the network's trained domain"):
        mpc(np.array([0.0, 6.0, 0.0]), np.zeros(3))
    with pytest.raises(ValueError, match="z_ref must have shape"):
        mpc(np.zeros(3), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="z must be the measured state"):
        mpc(np.zeros(4), np.zeros(3))
    with pytest.raises(ValueError, match="horizon"):
        MPC(sysm, net, EPS, horizon=0)
    with pytest.raises(ValueError, match="eps"):
        MPC(sysm, net, 0.2)  # eps > u_max: no admissible input
    with pytest.raises(ValueError, match="backend"):
        MPC(sysm, net, EPS, backend="cplexx")
    with pytest.raises(ValueError, match="R must be positive definite"):
        MPC(sysm, net, EPS, R=-0.1)
    with pytest.raises(ValueError, match="Q must be positive semidefinite"):
        MPC(sysm, net, EPS, Q=[-1.0, 1.0, 1.0])
    # a state 5e-10 outside the box is on its face (tolerance policy of flnotes.solvers); 1e-6 outside is not
    assert mpc._check_z(np.array([0.0, -5.0 - 5e-10, 0.0]))[1] == -5.0
    with pytest.raises(ValueError, match="outside"):
        mpc(np.array([0.0, -5.0 - 1e-6, 0.0]), np.zeros(3))


def test_missing_solver_package_fails_at_construction(quad, monkeypatch):
    """A back-end whose package is not installed is an ImportError when the controller is built, not at a solve."""
    import sys

    sysm, net = quad
    monkeypatch.setitem(sys.modules, "gurobipy", None)  # as if it were not installed
    with pytest.raises(ImportError, match="gurobipy"):
        MPC(sysm, net, EPS, horizon=3, backend="gurobi")


@pytest.mark.parametrize("backend", ["daqp", "cvxpy-scip"])
def test_infeasible_start_is_reported(quad, backend):
    """At z = [0, 0, 5] the pitch is ~0.52 rad: no v in the box brings |Phi_NN| down to u_max^eps."""
    sysm, net = quad
    mpc = MPC(sysm, net, EPS, horizon=3, ts=0.1, Q=S["Q"], R=S["R"], backend=backend)
    z = np.array([0.0, 0.0, 5.0])
    st = mpc(z, np.zeros(3))
    # reported and flagged: the least-violation input, since no v is admissible at z (checked on a fine grid)
    assert st.status == "infeasible" and st.fallback and not st.input_admissible
    grid = np.linspace(sysm.lo[3], sysm.hi[3], 20001)
    phi = np.abs(net(np.c_[np.repeat(z[None], grid.size, 0), grid]))[:, 0]
    assert phi.min() > mpc.u_eps[0]
    assert abs(net(np.r_[z, st.v])[0]) <= phi.min() + 1e-9
    r = mpc.step(z, 0.0, None)
    assert r.fallback and r.input_admissible is False and "least-violation" in r.message


def test_simulate_survives_an_infeasible_start(quad):
    sysm, net = quad
    mpc = MPC(sysm, net, EPS, horizon=3, ts=0.1, Q=S["Q"], R=S["R"])
    log = fl.simulate(sysm, mpc, t_final=0.2, ts=0.1, z0=[0.0, 4.0, 4.5], net=net)
    assert log.n_steps >= 1
    assert log.fallback[0] and log.status[0] == "infeasible"


def test_levers_do_not_change_the_optimum(run, quad):
    """Every lever is exact: bounds, warm start, constraint generation and back-end give the same optimum."""
    from flnotes.studies import lever_study

    log, mpc, _ = run
    sysm, net = quad
    hard = [k for k, h in enumerate(mpc.history) if not h.screened and k >= 1][:2]
    problems = recorded_problems(log, hard, with_plans=True)
    configs = {
        "daqp lp warm": dict(backend="daqp", bounds="lp"),
        "daqp horizon cold": dict(backend="daqp", bounds="horizon", warm_start=False),
        "daqp box lazy": dict(backend="daqp", bounds="box"),
        "scip horizon": dict(backend="scip", bounds="horizon"),
    }
    rows = lever_study(sysm, net, EPS, problems, configs, horizon=S["horizon"], ts=S["ts"], Q=S["Q"], R=S["R"])
    for r in rows:
        assert r["statuses"] == "optimal", r
        assert r["max_rel_diff"] <= 1e-6, r


def test_the_solver_libraries_are_loaded_when_the_mpc_is_built():
    """The first step under a time limit does not pay an import: HiGHS (the engine's LP bounds and QPs) took 60 ms
    to import inside the first step of a 50 ms loop. Checked in a fresh interpreter."""
    import subprocess
    import sys

    code = ("import sys, flnotes as fl\n"
            "from flnotes.bench import mpc as rt\n"
            "assert 'highspy' not in sys.modules, 'premise: importing flnotes does not load HiGHS'\n"
            "rt.make_mpc(rt.quad_setup(), time_limit=0.1)\n"
            "assert {'highspy', 'daqp', 'pyscipopt', 'threadpoolctl'} <= set(sys.modules), sorted(sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]


def test_shifted_plans_are_checked_against_the_network(run, quad):
    """shifted_plans counts what an independent forward pass of the shifted plan finds."""
    log, mpc, _ = run
    sysm, net = quad
    counts = fl.studies.shifted_plans(log, mpc)
    assert counts["plans"] == counts["admissible"] + counts["not_admissible"] > 0
    probe, found = mpc.clone(), 0
    for k in range(len(log.steps) - 1):
        st = log.steps[k]
        if log.fallback[k] or not st.info.get("plan_feasible"):
            continue
        probe.set_previous_plan((st.z_pred, st.v_pred))
        Z, V = probe.shifted_plan(log.z[k + 1])
        assert np.allclose(V[:-1], st.v_pred[1:]), "the shifted plan keeps the old inputs but the first"
        u_nn = net(np.column_stack([Z[:-1], V]))
        in_box = np.all((Z >= sysm.lo[:3] - 1e-9) & (Z <= sysm.hi[:3] + 1e-9))
        found += bool(np.all(np.abs(u_nn) <= mpc.u_eps + 1e-6) and in_box)
    assert found == counts["admissible"]


def test_horizon_sweep_reuses_the_first_seconds_of_a_known_run(run, quad):
    """A known, longer run is not rerun: the sweep's run is its first t_final seconds, step for step."""
    log, mpc, ref = run
    sysm, net = quad
    logs, rows = fl.studies.horizon_sweep(sysm, net, EPS, (mpc.N,), 2.0, ref, S["z0"], known={mpc.N: (log, mpc)})
    head = logs[mpc.N]
    assert head.n_steps == 20 and len(head.t) == 21 and np.allclose(head.t, log.t[:21])
    # wall-clock times cannot repeat in a rerun: equal arrays mean the known run's own steps
    assert np.array_equal(head.solve_time, log.solve_time[:20]) and head.steps == log.steps[:20]
    assert np.array_equal(head.u_fine, log.u_fine[:len(head.u_fine)]) and head.t_fine[-1] < 2.0 <= log.t_fine[-1]
    assert rows[0]["mean_ms"] == pytest.approx(1e3 * np.mean(log.solve_time[:20]))
    assert rows[0]["miqp_steps"] == sum(not s.screened for s in log.steps[:20])


def test_horizon_sweep_refuses_a_known_run_too_short_or_of_another_horizon(run, quad):
    log, mpc, ref = run
    sysm, net = quad
    with pytest.raises(ValueError, match="t_final <="):
        fl.studies.horizon_sweep(sysm, net, EPS, (mpc.N,), 7.0, ref, S["z0"], known={mpc.N: (log, mpc)})
    with pytest.raises(ValueError, match="key it by its own horizon"):
        fl.studies.horizon_sweep(sysm, net, EPS, (5,), 2.0, ref, S["z0"], known={5: (log, mpc)})


def test_separation_names_a_direction_only_without_overlap():
    sep = fl.repeats.separation
    assert sep([5.0, 6.0], [3.0, 4.0]) == "lower" and sep([5.0, 6.0], [7.0]) == "higher"
    assert sep([5.0, 6.0], [4.0, 5.5]) == "overlapping" and sep([5.0], [5.0]) == "overlapping"
    with pytest.raises(ValueError, match="at least one value"):
        sep([], [1.0])


@pytest.fixture(scope="module")
def lever_setup(run, quad):
    """Two recorded problems of the loop, the cold and warm configurations and their common settings."""
    log, _, _ = run
    sysm, net = quad
    problems = recorded_problems(log, range(15, 17))
    configs = {"cold": dict(warm_start=False), "warm": dict()}
    settings = dict(horizon=S["horizon"], ts=S["ts"], Q=S["Q"], R=S["R"], time_limit=30.0)
    return sysm, net, problems, configs, settings


def test_lever_repeats_keeps_the_optimum_and_spans_the_repeats(lever_setup):
    sysm, net, problems, configs, settings = lever_setup
    rows = fl.studies.lever_repeats(sysm, net, EPS, problems, configs, repeats=2, **settings)
    assert [r["configuration"] for r in rows] == ["cold", "warm"]
    for r in rows:
        assert len(r["mean_ms_runs"]) == 2 and r["mean_ms_min"] == min(r["mean_ms_runs"]) <= r["mean_ms_max"]
        assert r["nodes_min"] == r["nodes_max"], "no time limit hit: the node counts repeat exactly"
        assert r["max_rel_diff"] < 1e-6 and "time_limit" not in r["statuses"]
    # the order alternates: cold runs first in repeat 0, warm first in repeat 1
    assert rows[0]["run_positions"].tolist() == [0, 1] and rows[1]["run_positions"].tolist() == [1, 0]
    with pytest.raises(ValueError, match="repeats"):
        fl.studies.lever_repeats(sysm, net, EPS, problems, configs, repeats=1, **settings)


def test_lever_repeats_alternates_the_order_of_the_configurations(monkeypatch):
    """No configuration always runs first: the order of every other repeat is reversed, and the rows keep the order
    of the configurations whatever order they ran in."""
    from flnotes.studies import mpc as study

    ran = []

    def fake_study(system, net, eps, problems, configs, order=None, **common):
        order = list(configs) if order is None else list(order)
        ran.append(order)
        return [dict(configuration=k, mean_ms=10.0 * (1 + order.index(k)), nodes=1.0, max_rel_diff=0.0,
                     statuses="optimal") for k in configs]

    monkeypatch.setattr(study, "lever_study", fake_study)
    rows = study.lever_repeats(None, None, 0.0, [], {"a": {}, "b": {}, "c": {}}, repeats=4)
    assert ran == [["a", "b", "c"], ["c", "b", "a"], ["a", "b", "c"], ["c", "b", "a"]]
    assert [r["configuration"] for r in rows] == ["a", "b", "c"]
    assert rows[0]["run_positions"].tolist() == [0, 2, 0, 2] and rows[1]["run_positions"].tolist() == [1, 1, 1, 1]
    assert rows[0]["mean_ms_runs"].tolist() == [10.0, 30.0, 10.0, 30.0]


def test_lever_study_runs_in_the_order_given_and_reports_in_the_order_of_the_configurations(lever_setup):
    sysm, net, problems, configs, settings = lever_setup
    ahead = fl.studies.lever_study(sysm, net, EPS, problems, configs, **settings)
    reverse = fl.studies.lever_study(sysm, net, EPS, problems, configs, order=["warm", "cold"], **settings)
    assert [r["configuration"] for r in reverse] == ["cold", "warm"]
    for a, b in zip(ahead, reverse):  # the same work, whatever the order; the costs are relative to "cold"
        assert a["nodes"] == b["nodes"] and a["binaries"] == b["binaries"] and b["max_rel_diff"] < 1e-6
    with pytest.raises(ValueError, match="each configuration once"):
        fl.studies.lever_study(sysm, net, EPS, problems, configs, order=["warm"], **settings)


def test_prediction_mismatch_per_component_of_z(run):
    """With v held the sampled plant is the model: every component misses the prediction by the integration
    tolerance only; per component, the largest of them is the scalar mismatch."""
    log, mpc, _ = run
    per = fl.studies.prediction_mismatch(log, mpc, per_component=True)
    assert per.shape == (log.z.shape[1],)
    assert per.max() == fl.studies.prediction_mismatch(log, mpc) < 1e-5


def test_repeat_numbers_words_each_separation():
    from flnotes.studies import repeat_numbers
    from flnotes.studies.mpc import WARM_EFFECT_WORDS

    def rows(cold, warm):
        return [dict(repeats=3, mean_ms_runs=np.array(cold), mean_ms_min=min(cold), mean_ms_max=max(cold)),
                dict(repeats=3, mean_ms_runs=np.array(warm), mean_ms_min=min(warm), mean_ms_max=max(warm))]

    out = repeat_numbers(rows([5.0, 6.0, 7.0], [1.0, 2.0, 3.0]))
    assert (out["rep_n"], out["rep_orderings"], out["rep_one_in"]) == (3, 20, 10.0)
    assert (out["rep_cold_min"], out["rep_cold_max"], out["rep_warm_min"], out["rep_warm_max"]) == (5.0, 7.0, 1.0, 3.0)
    assert out["warm_effect"] == "every warm-started repeat was faster than every cold one"
    assert repeat_numbers(rows([1.0, 2.0, 3.0], [5.0, 6.0, 7.0]))["warm_effect"] == (
        "every warm-started repeat was slower than every cold one")
    assert repeat_numbers(rows([1.0, 4.0, 3.0], [2.0, 6.0, 7.0]))["warm_effect"] == (
        "the ranges overlap, so no time difference is shown")
    assert set(WARM_EFFECT_WORDS) == {"lower", "higher", "overlapping"}
    with pytest.raises(ValueError, match="two rows"):
        repeat_numbers(rows([1.0, 2.0], [3.0, 4.0])[:1])


def test_time_limit_numbers_says_whether_warm_start_fell_back_less():
    from flnotes.studies import time_limit_numbers

    def chk(fb, hits=7, steps=20):
        return dict(fallback_steps=fb, time_limit_steps=hits, steps=steps)

    g = dict(warm=dict(admissible_exists=19), cold=dict(admissible_exists=18))
    out = time_limit_numbers(dict(warm=chk(2, 5), cold=chk(4, 6, 21)), g)
    assert (out["tl_warm_exists"], out["tl_cold_exists"], out["tl_warm_hits"], out["tl_cold_hits"]) == (19, 18, 5, 6)
    assert (out["tl_warm_fb"], out["tl_cold_fb"], out["tl_steps"]) == (2, 4, 20)
    assert out["tl_clause"] == ("with a limit of 1 ms per step the loop fell back at 2 of its 20 steps with it and at 4 "
                                "without it, counts that depend on the machine's speed")
    for w, c in ((4, 4), (5, 0)):  # not fewer fallbacks with warm start: the value did not show
        assert time_limit_numbers(dict(warm=chk(w), cold=chk(c)), g)["tl_clause"] == (
            f"with a limit of 1 ms per step the loop fell back at {w} of its 20 steps with it and at {c} without it, so "
            "that value did not show in this build, counts that depend on the machine's speed")


def _ridge_case():
    """One integrator whose network ``Phi_NN(z, v) = |v - 0.7| + 1`` with ``u_max = 1`` admits ``v = 0.7`` only."""
    net = fl.ReLUNet([np.array([[0.0, 1.0], [0.0, -1.0]]), np.array([[1.0, 1.0]])],
                     [np.array([-0.7, 0.7]), np.array([1.0])])
    return fl.integrators([1], [-5.0, -2.0], [5.0, 2.0], [1.0]), net


class _PastTheRidge:
    """A solver whose plans come back 1e-7 past the ridge of :func:`_ridge_case` (a solver's tolerance), for the
    back-end ``only`` (every back-end when ``None``); ``calls`` records the back-ends that solved."""

    def __init__(self, solver, backend: str, calls: list, only=None):
        self.solver, self.backend, self.calls, self.only = solver, backend, calls, only

    def solve(self, *args, **kwargs):
        res = self.solver.solve(*args, **kwargs)
        self.calls.append(self.backend)
        if res.w is not None and self.only in (None, self.backend):
            res.w = res.w.copy()
            res.w[:3] += 1e-7
        return res


@pytest.mark.parametrize("options", [dict(), dict(backend="daqp"), dict(backend="scip"), dict(enclosure=False),
                                     dict(lp=False), dict(first_level="relaxation")])
def test_an_optimum_on_a_flat_piece_of_the_network_at_exactly_u_max(options):
    """A double integrator (N_p = 3) whose random network is flat (constant output) on a piece that lies at exactly
    ``u_max`` (``u_max`` a quantile of sampled outputs that many samples share). The optimum ends on that piece's
    face; a solver's point 3e-9 past the face lies in the neighbouring region, whose output exceeds ``u_max``. The
    engine once tightened ``u_max`` by 7e-9 there, which removed the whole piece, and called a plan 1.5e-5 above the
    optimum optimal. Now the point is made exact on the region its binaries name (no margin), and every variant
    returns the cold reference's optimum."""
    sysm, net, z, z_ref = stored_integrator_case("flat_piece_at_u_max_program.npz")
    kw = dict(horizon=3, ts=0.2, Q=[1.0, 1.0], R=0.1)
    r_ref = fl.MPC(sysm, net, 0.0, backend="cvxpy-scip", bounds="box", gap=1e-9, **kw)(z, z_ref)
    assert r_ref.status == "optimal"
    # the premise: the optimum's first two inputs sit on a flat piece at exactly u_max (output unchanged when v(k)
    # moves into the piece)
    X = np.c_[r_ref.z_pred[:2], r_ref.v_pred[:2]]
    assert np.all(np.abs(np.abs(net(X)) - sysm.u_max) <= 1e-12)
    X_in = X.copy()
    X_in[:, -1] -= 1e-3
    assert np.max(np.abs(net(X_in) - net(X))) <= 1e-12
    mpc = fl.MPC(sysm, net, 0.0, **kw, **options)
    r = mpc(z, z_ref)
    assert r.status == "optimal" and mpc.plan_feasible(r.z_pred, r.v_pred), r.message
    assert abs(r.objective - r_ref.objective) <= 1e-6 * abs(r_ref.objective), (r.objective, r_ref.objective, r.message)


@pytest.mark.parametrize("options", [dict(), dict(backend="scip"), dict(backend="daqp")])
def test_a_verdict_under_tightened_rows_is_not_called_proven_beyond_the_untightened_bound(monkeypatch, options):
    """A network whose admissible inputs are a ridge: ``Phi_NN(z, v) = |v - 0.7| + 1`` with ``u_max = 1`` admits
    ``v = 0.7`` only. Every solver here returns its plan 1e-7 past the ridge (a solver's tolerance), and the region
    QP that would make it exact is switched off, so the engine tightens ``u_max^eps``, and the tightened program has
    no plan. That proves nothing about the program (``v = 0.7`` is admissible): the step is an ``"error"`` that says
    so, where it used to be ``"infeasible"``."""
    import flnotes.mpc.engine as engine

    sysm, net = _ridge_case()
    kw = dict(horizon=3, ts=0.5, Q=[1.0], R=0.01, repair=False)
    z, z_ref = np.array([0.0]), np.array([-3.0])
    exact = fl.MPC(sysm, net, 0.0, **kw, **options)(z, z_ref)
    assert exact.status == "optimal" and np.allclose(exact.v_pred, 0.7), exact.message  # the premise
    make, calls = engine.make_solver, []
    monkeypatch.setattr(engine, "make_solver", lambda prob, backend, **o: _PastTheRidge(make(prob, backend, **o), backend,
                                                                                         calls))
    monkeypatch.setattr(engine, "region_exact", lambda *args, **kwargs: None)
    r = fl.MPC(sysm, net, 0.0, **kw, **options)(z, z_ref)
    assert r.status == "error" and r.info["tightened"] >= 1, r.message
    assert r.message.startswith("not proven: no plan with u_max^eps tightened by"), r.message


def _late_ridge_case():
    """One double integrator (N_p = 6) with a random (12, 10) network at a state where the optimum lies within the
    solvers' tolerance of ``u_max^eps``: a round's point is over the bound, the rows are tightened, and the verdict
    comes from a later, higher level."""
    rng = np.random.default_rng(21)
    sysm = fl.integrators([2], [-5.0, -5.0, -3.0], [5.0, 5.0, 3.0], [1.0])
    W = [rng.normal(size=(12, 3)) * 0.6, rng.normal(size=(10, 12)) * 0.4, rng.normal(size=(1, 10)) * 0.8]
    net = fl.ReLUNet(W, [rng.normal(size=12) * 0.3, rng.normal(size=10) * 0.3, np.array([0.1])])
    z = np.array([float.fromhex("0x1.d61b105234c23p+1"), float.fromhex("-0x1.d4959f5022148p-1")])
    z_ref = np.zeros((7, 2))
    z_ref[:, 0] = -4.75
    return sysm, net, z, z_ref


@pytest.mark.parametrize("options", [dict(bounds="lp"), dict(lp=True), dict(bounds="lp", screening=False)])
def test_a_tightened_verdict_of_a_later_round_is_backed_by_that_rounds_untightened_bound(monkeypatch, options):
    """A verdict under tightened rows counts where the untightened program's lower bound backs it. That bound used
    to come from the round where the rows were first tightened only: a level-set round whose level (410.17) lies
    below the optimum (410.3038), so the later round's optimum was "not proven" and the step an ``"error"`` (a
    plan 3e-5 above the optimum applied). Now SCIP bounds the deciding round's untightened program, and the step is
    the cold reference's optimum. Every SCIP point is polished here (HiGHS's QP with the binaries fixed, as the
    back-end did on every optimum when the case was found): the polished point lies over the bound by HiGHS's
    tolerance, which is what tightens the rows; SCIP's own point meets the bound, and the step is then optimal at
    once."""
    import flnotes.mpc.engine as engine
    from flnotes.solvers import scip as scip_backend

    monkeypatch.setattr(scip_backend, "_needs_polish", lambda p, status, w, bound, gap: status in ("optimal",
                                                                                                    "time_limit"))
    # the case as found: the step that decides is added by a later round (the steps near the bound, which the
    # first round now encodes too, would hold it from the start), and step 0 encoded by its neurons (its exact
    # range, imposed from the start, also changes the rounds)
    monkeypatch.setattr(engine, "NEAR_ACTIVE", None)
    monkeypatch.setattr(engine, "FIRST_RANGE", False)
    sysm, net, z, z_ref = _late_ridge_case()
    kw = dict(horizon=6, ts=0.1, atlas=False)
    r_ref = fl.MPC(sysm, net, 0.1, backend="cvxpy-scip", bounds="box", gap=1e-9, **kw)(z, z_ref)
    assert r_ref.status == "optimal", r_ref.message
    mpc = fl.MPC(sysm, net, 0.1, **kw, **options)
    r = mpc(z, z_ref)
    assert r.status == "optimal" and mpc.plan_feasible(r.z_pred, r.v_pred), r.message
    assert abs(r.objective - r_ref.objective) <= 1e-6 * abs(r_ref.objective), (r.objective, r_ref.objective)
    assert r.bound <= r.objective + 1e-9 * abs(r.objective)
    # the premise: the rows were tightened and the later round's untightened bound decided
    assert r.info["tightened"] >= 1 and "untightened round's" in r.message, r.message


class _FirstScipPointOver:
    """A solver wrapper: the first SCIP point of a step is checked against ``u_max^eps`` lowered by 1e-9 (as if
    SCIP's tolerance had let it through 1e-9 over the bound); every other check is the engine's own."""

    def __init__(self, state: dict, solver, backend: str):
        self.state, self.solver, self.backend = state, solver, backend

    def solve(self, *args, **kwargs):
        res = self.solver.solve(*args, **kwargs)
        if self.backend == "scip":
            self.state["scip"] += 1
            self.state["armed"] = self.state["scip"] == 1
        return res


@pytest.mark.parametrize("options", [dict(lp=True), dict()])
def test_the_untightened_rounds_own_plan_is_the_optimum_where_it_passes_the_check(monkeypatch, options):
    """The book's MSD (N_p = 10) at a state on the domain's face with a constant reference, where SCIP's point in
    a round lies over ``u_max^eps`` by its tolerance, so the rows are tightened (the region QP is off). Where that
    round was a level-set round below the optimum (``lp=True``, on the machine that found it), the step used to be
    an ``"error"`` ("not proven"). The deciding round's untightened program, solved by SCIP, has a plan that passes
    the forward-pass check within the gap of its bound: it is the optimum, the default's. Whether SCIP's own point lands over the
    bound by round-off depends on the machine, so the first SCIP point of the step is checked against the bound
    lowered by 1e-9 (its tolerance's size); every later check is the engine's own."""
    import flnotes.mpc.engine as engine
    from flnotes.bench import msd_realtime
    from flnotes.mpc import prediction

    monkeypatch.setattr(engine, "NEAR_ACTIVE", None)  # the case as found: its rounds without the near steps
    monkeypatch.setattr(engine, "FIRST_RANGE", False)  # and with step 0 encoded by its neurons
    s = msd_realtime.setting()
    z = np.array([5.0, float.fromhex("-0x1.d027312650e74p+0")])
    z_ref = np.zeros((s["horizon"] + 1, 2))
    z_ref[:, 0] = float.fromhex("-0x1.fa2b99dd902f3p-1")
    r_def = msd_realtime.controller(s)(z, z_ref)
    state = dict(armed=False, scip=0)
    violated, make = prediction.Prediction.violated, engine.make_solver

    def over_once(self, z0, V, tol=prediction.BOUND_TOL):
        armed, state["armed"] = state["armed"], False
        return violated(self, z0, V, tol=-1e-9 if armed else tol)

    monkeypatch.setattr(prediction.Prediction, "violated", over_once)
    monkeypatch.setattr(engine, "make_solver", lambda prob, backend, **o: _FirstScipPointOver(
        state, make(prob, backend, **o), backend))
    monkeypatch.setattr(engine, "region_exact", lambda *args, **kwargs: None)
    mpc = msd_realtime.controller(s, **options)
    r = mpc(z, z_ref)
    assert r_def.status == r.status == "optimal" and mpc.plan_feasible(r.z_pred, r.v_pred), r.message
    assert abs(r.objective - r_def.objective) <= 1e-6 * abs(r_def.objective), (r.objective, r_def.objective)
    assert r.bound <= r.objective + 1e-9 * abs(r.objective)
    assert state["scip"] >= 2 and r.info["tightened"] >= 1, (state, r.message)  # the premise
    assert "untightened round's plan (scip) passes the forward-pass check" in r.message, r.message


@pytest.mark.parametrize("options", [dict(), dict(backend="daqp")])
def test_a_daqp_point_over_the_bound_is_solved_again_by_scip_before_any_row_is_tightened(monkeypatch, options):
    """The ridge network above, with only DAQP's plans 1e-7 past the ridge (DAQP's primal tolerance is 1e-6) and
    the region QP switched off: SCIP (tolerance 1e-9) solves the untightened round again and its plan is the
    optimum, where tightening the rows used to make the program look infeasible."""
    import flnotes.mpc.engine as engine

    sysm, net = _ridge_case()
    kw = dict(horizon=3, ts=0.5, Q=[1.0], R=0.01, repair=False)
    z, z_ref = np.array([0.0]), np.array([-3.0])
    exact = fl.MPC(sysm, net, 0.0, backend="scip", **kw)(z, z_ref)
    assert exact.status == "optimal" and np.allclose(exact.v_pred, 0.7), exact.message  # the premise
    make, backends = engine.make_solver, []
    monkeypatch.setattr(engine, "make_solver", lambda prob, backend, **o: _PastTheRidge(make(prob, backend, **o), backend,
                                                                                         backends, only="daqp"))
    monkeypatch.setattr(engine, "region_exact", lambda *args, **kwargs: None)
    r = fl.MPC(sysm, net, 0.0, **kw, **options)(z, z_ref)
    assert backends[:2] == ["daqp", "scip"], backends
    assert r.status == "optimal" and r.info["tightened"] == 0 and r.backend == "scip", r.message
    assert "scip solved the round again: the daqp optimum" in r.message
    assert abs(r.objective - exact.objective) <= 1e-9 * abs(exact.objective)


@pytest.mark.parametrize("name, horizon, P, past", [("flat_piece_reference_program.npz", 5, None, True),
                                                    ("ridge_reference_program.npz", 4, None, False),
                                                    ("two_input_ridge_program.npz", 4, 1.0, True)])
def test_the_reference_makes_a_plan_past_a_flat_piece_or_a_ridge_exact(name, horizon, P, past):
    """The cold reference (``backend="cvxpy-scip"``, gap 1e-9) on random programs whose optimum lies on a flat piece
    or a ridge of the network at ``u_max``:

    - a double integrator (N_p = 5) whose optimum ends on a flat piece at exactly ``u_max``;
    - two inputs (N_p = 4), one output at ``u_max`` to round-off at every step;
    - two inputs (N_p = 4, terminal weight), both outputs at ``u_max`` at every step (asserted).

    Where SCIP's plan exceeds ``u_max^eps`` by its tolerance (``past``), tightening the rows removed the piece or
    the ridge: the reference called a plan 0.76 % above the optimum optimal, the second program infeasible, and
    the third "not proven" (its region's plan cost 2e-9 more than SCIP's, beyond the gap asked). Now SCIP's plan
    is made exact on its linear region, held to ``max(gap, TIGHTENED_GAP)``, and the reference and the engine
    agree. (SCIP's plan on the second program exceeded the bound only with the cone written as cvxpy writes it;
    it still checks the agreement.)"""
    sysm, net, z, z_ref = stored_integrator_case(name)
    kw = dict(horizon=horizon, ts=0.2, Q=[1.0] * len(z), R=0.1, P=None if P is None else [P] * len(z))
    ref = fl.MPC(sysm, net, 0.0, backend="cvxpy-scip", bounds="box", gap=1e-9, **kw)
    r_ref = ref(z, z_ref)
    mpc = fl.MPC(sysm, net, 0.0, **kw)
    r = mpc(z, z_ref)
    assert r.status == r_ref.status == "optimal", (r.message, r_ref.message)
    assert ref.plan_feasible(r_ref.z_pred, r_ref.v_pred) and mpc.plan_feasible(r.z_pred, r.v_pred)
    assert abs(r.objective - r_ref.objective) <= 1e-6 * abs(r_ref.objective), (r.objective, r_ref.objective)
    if past:  # the premise: SCIP's own plan was over the bound
        assert "made exact on its linear region" in r_ref.message
    if name.startswith("two_input"):  # the premise: a ridge, both outputs at u_max at every step
        out = np.abs(net(np.hstack([r.z_pred[:horizon], r.v_pred])))
        assert np.allclose(out, sysm.u_max, rtol=1e-7), out


def test_a_reference_verdict_under_tightened_rows_within_the_solvers_tolerance_is_proven(monkeypatch):
    """A double integrator (N_p = 1, a random (4, 3) network) where SCIP's plan lies over ``u_max^eps`` by its
    tolerance, with the region QP switched off, so the rows are tightened (the region QP makes this plan exact;
    it is off to reach the tightened verdict, which a plan on a face of no region would reach). The tightened
    optimum lies 5e-9 (relative) above the untightened lower bound: beyond the asked gap of 1e-9, within
    ``TIGHTENED_GAP``, which backs it: "optimal", the engine's optimum, and the bound the step reports is the
    untightened one."""
    from flnotes.mpc import reference
    from flnotes.solvers import TIGHTENED_GAP

    monkeypatch.setattr(reference, "region_exact", lambda *args, **kwargs: None)
    sysm, net, z, z_ref = stored_integrator_case("tightened_reference_program.npz")
    kw = dict(horizon=1, ts=0.2, Q=[1.0, 1.0], R=0.1, P=[1.0, 1.0])
    ref = fl.MPC(sysm, net, 0.0, backend="cvxpy-scip", bounds="box", gap=1e-9, **kw)
    r_ref = ref(z, z_ref)
    r = fl.MPC(sysm, net, 0.0, **kw)(z, z_ref)
    assert r_ref.status == r.status == "optimal" and ref.margin > 0.0, r_ref.message
    assert abs(r.objective - r_ref.objective) <= 1e-6 * abs(r.objective)
    assert r_ref.bound <= r_ref.objective <= r_ref.bound + TIGHTENED_GAP * abs(r_ref.objective)
    # the premise: the floor decided (the verdict is beyond the asked gap from the untightened bound)
    assert r_ref.objective - r_ref.bound > 1e-9 * abs(r_ref.objective), (r_ref.objective, r_ref.bound)


def test_a_reference_verdict_under_tightened_rows_is_not_called_proven_beyond_the_untightened_bound(monkeypatch):
    """The ridge network of the engine's test above, with the reference's plans moved 1e-7 past the ridge and its
    region QP switched off: the rows are tightened and the tightened program has no plan, which proves nothing (the
    step is an ``"error"`` that says so; it used to be ``"infeasible"``)."""
    from flnotes.mpc import reference
    from flnotes.mpc.reference import ReferenceProgram

    sysm, net = _ridge_case()
    kw = dict(horizon=3, ts=0.5, Q=[1.0], R=0.01, backend="cvxpy-scip", bounds="box")
    z, z_ref = np.array([0.0]), np.array([-3.0])
    exact = fl.MPC(sysm, net, 0.0, **kw)(z, z_ref)
    assert exact.status == "optimal" and np.allclose(exact.v_pred, 0.7), exact.message  # the premise
    solve = ReferenceProgram.solve

    def past_the_ridge(self, z0, R, u_in, **kwargs):
        step = solve(self, z0, R, u_in, **kwargs)
        if step.v_pred is not None:
            step.v_pred = step.v_pred + 1e-7
            step.z_pred, step.v = self.pred.predict(z0, step.v_pred), step.v_pred[0].copy()
        return step

    monkeypatch.setattr(ReferenceProgram, "solve", past_the_ridge)
    monkeypatch.setattr(reference, "region_exact", lambda *args, **kwargs: None)
    mpc = fl.MPC(sysm, net, 0.0, **kw)
    r = mpc(z, z_ref)
    assert r.status == "error" and mpc.margin > 0.0, r.message
    assert r.message.startswith("not proven: no plan with u_max^eps tightened by"), r.message


#: Programs where DAQP's branch and bound returned a sub-optimal plan as optimal: one integrator, N_p = 5, random
#: networks. (5, 4): 34 binaries, 6e-4 above the optimum after 4,504 nodes with a primal tolerance of 1e-7. (4, 5):
#: programs of 32 and 41 binaries, 2e-2 above after 27,543 nodes at every DAQP setting tried.
DAQP_WRONG = ("daqp_suboptimal_program.npz", "daqp_long_search_program.npz")
NO_HANDOVER = dict(solver_options={"daqp": {"handover": None}, "scip": {}})


@pytest.mark.parametrize("name", DAQP_WRONG)
@pytest.mark.parametrize("options", [dict(), dict(backend="daqp"), dict(enclosure=False), NO_HANDOVER])
def test_programs_where_daqp_claimed_a_suboptimal_plan_optimal(name, options):
    """The engine returns the optimum of the cold reference, by default, with DAQP for every program, without the
    enclosure, and without the hand-over to SCIP (so that DAQP's long search is verified, not cut)."""
    sysm, net, z, z_ref = stored_integrator_case(name)
    kw = dict(horizon=5, ts=0.2, Q=[1.0], R=0.1)
    ref = fl.MPC(sysm, net, 0.0, backend="cvxpy-scip", bounds="box", gap=1e-9, **kw)
    r_ref = ref(z, z_ref)
    assert r_ref.status == "optimal" and ref.plan_feasible(r_ref.z_pred, r_ref.v_pred)  # the premise
    mpc = fl.MPC(sysm, net, 0.0, **kw, **options)
    r = mpc(z, z_ref)
    assert r.status == "optimal"
    assert abs(r.objective - r_ref.objective) <= 1e-6 * max(1.0, abs(r_ref.objective)), (r.objective,
                                                                                        r_ref.objective)


@pytest.mark.parametrize("daqp", [dict(handover=0.0), dict(verify_nodes=-1), dict(reg_mode="lower")])
def test_bad_daqp_options_are_refused_when_the_controller_is_built(daqp):
    """Not at the first program DAQP gets (which may come many steps later)."""
    sysm, net, _, _ = stored_integrator_case("daqp_long_search_program.npz")
    with pytest.raises(ValueError, match=next(iter(daqp))):
        fl.MPC(sysm, net, 0.0, horizon=5, ts=0.2, Q=[1.0], R=0.1, solver_options={"daqp": daqp, "scip": {}})


@pytest.mark.parametrize("options", [dict(), dict(backend="scip"), dict(enclosure=False)])
def test_an_infeasible_program_ends_its_level_rounds_once_they_cut_nothing(options):
    """A stored infeasible program (one integrator, N_p = 5, a random (5, 4) network, a state a closed loop reached):
    the level set's boxes grow each round until they hold the whole program's boxes, as the network's affine enclosure
    cuts them, and that round is the whole program. Compared with the boxes before that cut, the rounds never ended
    (21 rounds, to a level 1e12 times the relaxation's cost). The verdict is the cold reference's."""
    sysm, net, z, z_ref = stored_integrator_case("infeasible_level_rounds_program.npz")
    kw = dict(horizon=5, ts=0.2, Q=[1.0], R=0.1)
    r_ref = fl.MPC(sysm, net, 0.0, backend="cvxpy-scip", bounds="box", gap=1e-9, **kw)(z, z_ref)
    assert r_ref.status == "infeasible"  # the premise
    r = fl.MPC(sysm, net, 0.0, **kw, **options)(z, z_ref)
    assert r.status == "infeasible", r.message
    assert r.rounds <= 4, (r.rounds, r.message)


@pytest.mark.parametrize("warm_threshold", [None, 50])
def test_auto_sends_a_program_without_an_incumbent_to_scip_above_its_threshold(monkeypatch, warm_threshold):
    """``backend="auto"``: DAQP up to ``AUTO_DAQP_BINARIES`` binaries when the round has an incumbent (a warm start
    to prune on), up to ``AUTO_DAQP_COLD_BINARIES`` without one; an explicit back-end is kept either way. On the
    stored infeasible program (31 binaries, 40 with step 0's neurons; no plan to warm-start from) the default hands
    every round to SCIP, and
    DAQP alone reaches the same verdict (its claim verified). With the threshold for warm-started rounds moved above
    40 (``warm_threshold=50``, the default before it was measured again), the cold rule alone sends it to SCIP."""
    import flnotes.mpc.engine as engine
    import flnotes.mpc.levers as levers
    from flnotes.mpc.levers import pick_backend

    if warm_threshold is not None:
        monkeypatch.setattr(levers, "AUTO_DAQP_BINARIES", warm_threshold)
    warm, cold = levers.AUTO_DAQP_BINARIES, levers.AUTO_DAQP_COLD_BINARIES
    assert cold < min(warm, 40)  # the premise of the stored program
    assert pick_backend("auto", warm, incumbent=True) == "daqp"
    assert pick_backend("auto", warm, incumbent=False) == ("daqp" if warm <= cold else "scip")
    assert pick_backend("auto", cold, incumbent=False) == "daqp"
    assert pick_backend("auto", cold + 1, incumbent=False) == "scip"
    assert pick_backend("daqp", 40, incumbent=False) == "daqp"
    assert pick_backend("scip", 1, incumbent=True) == "scip"
    assert pick_backend("auto", warm + 1, incumbent=True) == "scip"
    if warm_threshold is not None:
        assert pick_backend("auto", 40, incumbent=True) == "daqp"  # only the missing incumbent sends it to SCIP
    sysm, net, z, z_ref = stored_integrator_case("infeasible_level_rounds_program.npz")
    kw = dict(horizon=5, ts=0.2, Q=[1.0], R=0.1)
    r = fl.MPC(sysm, net, 0.0, **kw)(z, z_ref)
    # 31 binaries with step 0 written as its exact range (FIRST_RANGE), 40 with step 0's neurons: above the cold
    # threshold either way
    assert (r.status, r.backend, r.n_binaries) == ("infeasible", "scip", 31), r.message
    with monkeypatch.context() as m:
        m.setattr(engine, "FIRST_RANGE", False)
        r = fl.MPC(sysm, net, 0.0, **kw)(z, z_ref)
    assert (r.status, r.backend, r.n_binaries) == ("infeasible", "scip", 40), r.message
    r_daqp = fl.MPC(sysm, net, 0.0, backend="daqp", **kw)(z, z_ref)
    assert (r_daqp.status, r_daqp.backend) == ("infeasible", "daqp"), r_daqp.message
