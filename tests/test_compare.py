"""The comparative study: nonlinear MPC (CasADi + IPOPT), saturation, the study's metrics."""
from types import SimpleNamespace

import numpy as np
import pytest

import flnotes as fl
from flnotes.nmpc import NonlinearMPC, SaturatedInput, input_to_v
from flnotes.studies import compare as C

S = fl.paper.QUAD_SETTING


@pytest.fixture(scope="module")
def quad():
    return fl.quad1d()


@pytest.fixture(scope="module")
def quad_setting():
    return C.setting("Quad-1D", horizon=6)


# ------------------------------------------------------------------ the input map
def test_input_to_v_inverts_phi(quad):
    rng = np.random.default_rng(1)
    for _ in range(20):
        z = rng.uniform(-3, 3, 3)
        u = rng.uniform(-0.2, 0.2, 1)
        v = input_to_v(quad, z, u)
        assert np.allclose(quad.Phi(z, v), u, atol=1e-12)
    a, b = fl.msd().input_map(np.array([1.0, 0.5]))
    assert np.allclose(b, [[1.0]]) and np.isclose(a[0], 1.0 + fl.systems.stribeck(np.array(0.5)))


def test_input_to_v_rejects_a_map_not_affine_in_v():
    A, B = fl.brunovsky(2)
    cubic = fl.FLSystem("cubic", A, B, phi=lambda z, v: v**3 + z[:, :1], lo=[-1, -1, -1], hi=[1, 1, 1], u_max=1.0,
                        f=lambda x, u: np.array([x[1], u[0]]), to_z=lambda x: x, to_x=lambda z: z)
    with pytest.raises(ValueError, match="not affine in v"):
        input_to_v(cubic, np.zeros(2), np.array([0.5]))


# ------------------------------------------------------------------ saturated feedback linearization
def test_saturated_input_clips_the_true_input(quad):
    big = SaturatedInput(fl.FeedbackLaw(lambda z: np.array([12.0])), quad)
    small = SaturatedInput(fl.FeedbackLaw(lambda z: np.array([0.1])), quad)
    z = np.array([0.2, -0.1, 0.3])
    assert quad.Phi(z, 12.0)[0] > quad.u_max[0]  # premise: the inner law asks for too much
    r = big.step(z, 0.0)
    assert np.isclose(quad.Phi(z, r.v)[0], quad.u_max[0], rtol=0, atol=1e-12)
    r = small.step(z, 0.0)
    assert abs(quad.Phi(z, 0.1)[0]) < quad.u_max[0] and np.array_equal(r.v, [0.1])  # within the bound: untouched
    log = fl.simulate(quad, big, 1.0, 0.1, z0=[0.0, 0.0, 0.0], progress=False)
    assert np.all(np.abs(log.u) <= quad.u_max + 1e-12)


# ------------------------------------------------------------------ nonlinear MPC
def test_nmpc_respects_the_bound_and_satisfies_kkt(quad):
    nm = NonlinearMPC(quad, horizon=8, ts=0.1, Q=S["Q"], R=S["R"])
    ref = fl.sine_reference(1.5, 1.0)
    s = nm(S["z0"], ref(0.1 * np.arange(9)))
    assert s["status"] == "optimal"
    assert np.all(np.abs(s["u_pred"]) <= quad.u_max + 1e-12)
    assert np.abs(s["u_pred"]).max() >= quad.u_max[0] - 1e-6, "premise: the bound is active in this plan"
    assert s["kkt"]["stationarity"] < 1e-6 and s["kkt"]["primal"] < 1e-6 and s["kkt"]["complementarity"] < 1e-5
    # the plan is the RK4 rollout of its inputs, and its cost is the NLP's objective
    assert np.allclose(nm.rollout(s["x_pred"][0], s["u_pred"]), s["x_pred"], atol=1e-6)
    assert np.isclose(nm.cost(s["x_pred"][0], s["u_pred"], ref(0.1 * np.arange(9))), s["objective"], rtol=1e-6)
    # v of the plan is the Brunovsky input: Phi(z_k, v_k) = u_k
    assert np.allclose(quad.Phi(s["z_pred"][:-1], s["v_pred"]), s["u_pred"], atol=1e-9)


def test_nmpc_closed_loop_tracks_and_applies_its_input(quad):
    ref = fl.sine_reference(1.5, 1.0)
    nm = NonlinearMPC(quad, horizon=8, ts=0.1, Q=S["Q"], R=S["R"])
    log = fl.simulate(quad, nm, 3.0, 0.1, z0=S["z0"], reference=ref, hold="u", check_domain=True, progress=False)
    assert not log.message and log.n_steps == 30
    assert np.all(np.abs(log.u) <= quad.u_max + 1e-9) and np.all(np.abs(log.u_fine) <= quad.u_max + 1e-9)
    applied = np.array([h["u"] for h in nm.history])
    assert np.allclose(log.u, applied, atol=1e-12), "simulate applies exactly the NMPC's u"
    e = np.abs(log.z[:, 0] - ref(log.t)[:, 0])
    assert e[-5:].max() < 0.5 * e[0], "the position error falls"


def test_nmpc_checks_its_symbolic_model():
    msd = fl.msd()
    with pytest.raises(ValueError, match="to_z"):
        NonlinearMPC(msd, horizon=3)  # the MSD's to_z converts with np.asarray(x, float)
    NonlinearMPC(msd, horizon=3, to_z=lambda x: x)
    with pytest.raises(ValueError, match="horizon"):
        NonlinearMPC(msd, horizon=0, to_z=lambda x: x)


# ------------------------------------------------------------------ the study's metrics
def _tiny_log():
    """A hand-made run of the MSD (Phi = v + s(z2) + z1, u_max = 5): 3 steps, 2 fine points per step."""
    msd = fl.msd()
    z = np.array([[1.0, 0.0], [0.5, 0.0], [0.0, 0.0], [0.0, 0.0]])
    v = np.array([[0.0], [1.0], [-2.0]])
    u = np.array([[1.0], [6.0], [-2.0]])          # step 1 violates at the sample
    u_fine = np.array([[1.0], [4.0], [6.0], [5.5], [-2.0], [-5.2]])  # steps 1 and 2 between samples
    plan_ok = SimpleNamespace(z_pred=np.array([[1.0, 0.0], [2.0, 0.0], [3.0, 0.0]]), v_pred=np.array([[0.0], [1.0]]))
    plan_bad = SimpleNamespace(z_pred=np.array([[0.5, 0.0], [4.0, 0.0], [0.0, 0.0]]), v_pred=np.array([[0.0], [1.5]]))
    # a fallback without an admissible input; its plan is the fallback's, not the method's: not counted
    fallback_plan = SimpleNamespace(z_pred=plan_bad.z_pred, v_pred=plan_bad.v_pred, input_admissible=False)
    return fl.SimLog(system=msd, ts=0.1, hold="v", t=np.array([0.0, 0.1, 0.2, 0.3]), x=z, z=z, v=v, u=u, u_nn=None,
                     solve_time=np.array([0.001, 0.003, 0.002]), status=["optimal", "optimal", "infeasible"],
                     fallback=np.array([False, False, True]), t_fine=np.arange(6) * 0.05, x_fine=np.zeros((6, 2)),
                     z_fine=np.zeros((6, 2)), u_fine=u_fine, in_domain=np.ones(4, bool),
                     steps=[plan_ok, plan_bad, fallback_plan], message="")


def test_run_metrics_on_a_constructed_run():
    log = _tiny_log()
    ref = lambda t: np.zeros((np.size(t), 2))
    Q, R = np.diag([2.0, 1.0]), np.array([[0.5]])
    m = C.run_metrics(log, ref, Q, R, band=0.6)
    assert m["steps"] == 3 and m["completed"]
    assert m["max_abs_u_samples"] == 6.0 and m["max_abs_u_between"] == 6.0
    assert m["violating_samples"] == 1 and m["violating_intervals"] == 2
    assert m["inadmissible_steps"] == 1 and m["violating_after_admissible"] == 1  # step 2's interval: flagged
    assert m["over_ts"] == 0
    log.solve_time = np.array([0.001, 0.25, 0.002])
    assert C.run_metrics(log, ref, Q, R, band=0.6)["over_ts"] == 1  # one step slower than t_s = 0.1
    # plans: the first stays within 5 (Phi(z(1), v(1)) = 2 + 1 = 3), the second reaches 4 + 1.5 = 5.5
    assert m["plans"] == 2 and m["plans_violating"] == 1 and np.isclose(m["plan_excess_max"], 0.5)
    assert m["infeasible_steps"] == 1 and m["fallback_steps"] == 1 and m["non_optimal_steps"] == 1
    assert m["time_limit_steps"] == 0
    log.status = ["optimal", "time_limit", "infeasible"]
    assert C.run_metrics(log, ref, Q, R, band=0.6)["time_limit_steps"] == 1  # limit hits, apart from late answers
    # cost: ts * sum_k (2 z1^2 + 0.5 v^2) over k = 0, 1, 2
    assert np.isclose(m["cost"], 0.1 * ((2 * 1.0 + 0) + (2 * 0.25 + 0.5) + (0 + 0.5 * 4)))
    assert np.isclose(m["rms_error"], np.sqrt((1 + 0.25) / 4))
    assert np.isclose(m["settling_s"], 0.1)  # |z1| <= 0.6 from t = 0.1 on
    assert np.isclose(m["ms_min"], 1.0) and np.isclose(m["ms_median"], 2.0) and np.isclose(m["ms_max"], 3.0)


def test_settling_time():
    t = np.arange(5.0)
    assert C.settling_time(t, [1.0, 0.5, 0.05, 0.2, 0.01], 0.1) == 4.0
    assert np.isnan(C.settling_time(t, [1.0, 0.0, 0.0, 0.0, 0.5], 0.1))
    assert C.settling_time(t, np.zeros(5), 0.1) == 0.0


def test_scenarios_are_seeded_and_include_active_bounds():
    a, b = C.draw_scenarios("Quad-1D", 20, seed=3), C.draw_scenarios("Quad-1D", 20, seed=3)
    assert all(np.array_equal(x["z0"], y["z0"]) and x["omega"] == y["omega"] for x, y in zip(a, b))
    assert any(s["bound_active"] for s in a) and not all(s["bound_active"] for s in a)
    quad = fl.quad1d()
    assert all(quad.in_domain(s["z0"])[0] for s in a)
    with pytest.raises(ValueError, match="name"):
        C.draw_scenarios("Arm2", 3)


def test_study_on_one_short_scenario(quad_setting):
    """The MIQP's plans satisfy the true bound at every predicted step; the NMPC keeps |u| <= u_max everywhere."""
    sc = C.draw_scenarios("Quad-1D", 2, seed=0)[1]
    assert sc["bound_active"], "premise: this scenario's reference needs more than u_max"
    rows = C.monte_carlo(quad_setting, [sc], 1.0, methods=("network", "nmpc"))
    by = {r["method"]: r for r in rows}
    assert by["network"]["steps"] == by["nmpc"]["steps"] == 10
    assert by["network"]["violating_samples"] == 0 and by["network"]["plans_violating"] == 0
    assert by["nmpc"]["violating_samples"] == 0 and by["nmpc"]["violating_intervals"] == 0
    table = C.method_table(rows, ("network", "nmpc"))
    assert [r["method"] for r in table] == [C.LABELS["network"], C.LABELS["nmpc"]]
    assert table[0]["cost_vs_miqp"] == 1.0
    assert table[0]["non_optimal"] == table[0]["time_limit"] == 0  # no time limit: every MIQP step solved to the end
    assert [r["solved"] for r in table] == ["to the end"] * 2
    marked = C.method_table(rows, ("network", "nmpc"), time_limit=0.1)  # a limit marks the MIQP's line only
    assert [r["method"] for r in marked] == [C.LABELS["network"] + " *", C.LABELS["nmpc"]]
    assert [r["solved"] for r in marked] == ["time limit", "to the end"]


# ------------------------------------------------------------------ the linear input models (one MPC engine)
@pytest.fixture(scope="module")
def quad_net():
    net, _ = fl.paper_net("Quad-1D")
    return net, float(fl.paper.paper_eps("Quad-1D").upper[0])


def test_constant_extension_plan_satisfies_its_own_bounds(quad, quad_net):
    net, eps = quad_net
    mpc = fl.MPC(quad, net, eps, horizon=6, ts=0.1, Q=S["Q"], R=S["R"], constraint="measured")
    z = np.asarray(S["z0"], float)
    st = mpc(z, np.array([4.0, 0.0, 0.0]))  # a far set point: the bound binds
    assert st.status == "optimal" and not st.fallback
    u_measured = quad.Phi(np.repeat(z[None], 6, axis=0), st.v_pred)  # the rows: Phi at the measured state
    assert np.all(np.abs(u_measured) <= quad.u_max + 1e-6)
    assert np.abs(u_measured).max() >= quad.u_max[0] - 1e-6, "premise: the bound is active in this plan"


def test_previous_prediction_plan_satisfies_its_own_bounds(quad, quad_net):
    net, eps = quad_net
    N = 6
    mpc = fl.MPC(quad, net, eps, horizon=N, ts=0.1, Q=S["Q"], R=S["R"], constraint="previous")
    target = np.array([4.0, 0.0, 0.0])  # a far set point: the bound binds
    first = mpc(np.asarray(S["z0"], float), target)
    z1 = first.z_pred[1]  # the nominal next state
    second = mpc(z1, target)
    assert second.status == "optimal" and not second.fallback
    zbar = np.vstack([z1[None], first.z_pred[2:N + 1]])  # the previous plan, shifted (Kurtz & Henson)
    u_rows = quad.Phi(zbar, second.v_pred)
    assert np.all(np.abs(u_rows) <= quad.u_max + 1e-6)
    assert np.abs(u_rows).max() >= quad.u_max[0] - 1e-6, "premise: the bound is active in this plan"


def test_saturated_linear_mpc_clips_in_closed_loop(quad, quad_net):
    net, eps = quad_net
    inner = fl.MPC(quad, net, eps, horizon=6, ts=0.1, Q=S["Q"], R=S["R"], constraint="none")
    far = lambda t: np.tile([4.0, 0.0, 0.0], (np.size(t), 1))  # a far set point: the bound binds
    log = fl.simulate(quad, SaturatedInput(inner, quad), 1.0, 0.1, z0=S["z0"], reference=far, net=net, progress=False)
    assert any(s.info["clipped"] for s in log.steps), "premise: the unconstrained MPC asks for more than u_max"
    assert np.all(np.abs(log.u) <= quad.u_max + 1e-12)


def test_all_five_methods_on_one_short_scenario(quad_setting):
    sc = C.draw_scenarios("Quad-1D", 2, seed=0)[1]
    rows = C.monte_carlo(quad_setting, [sc], 1.0)
    by = {r["method"]: r for r in rows}
    assert set(by) == set(C.METHODS) and all(r["steps"] == 10 for r in rows)
    for m in ("network", "measured", "previous", "saturated", "nmpc"):
        assert by[m]["fallback_steps"] > 0 or by[m]["violating_samples"] == 0, f"{m}: |u| <= u_max at the samples"
    assert by["network"]["plans_violating"] == 0
    assert len(C.method_table(rows)) == 5


def test_cost_vs_miqp_solves_the_miqp_without_the_runs_time_limit(quad_setting):
    """The comparison's MIQP optimum does not depend on how fast the run was: it is solved again, exactly."""
    s = dict(quad_setting, time_limit=1e-4)  # every step of the run stops at its limit
    sc = C.draw_scenarios("Quad-1D", 2, seed=0)[1]
    log = C.run_methods(s, sc["z0"], C.scenario_reference(s["system"], sc), 0.5, methods=("network",))["network"]
    assert any(st != "optimal" for st in log.status), "premise: the run's steps hit their time limit"
    rows = C.cost_vs_miqp(s, log, range(log.n_steps))
    assert [r["miqp_status"] for r in rows] == ["optimal"] * log.n_steps
    exact = fl.MPC(s["system"], s["net"], s["eps"], horizon=s["horizon"], ts=s["ts"], Q=s["Q"], R=s["R"],
                   backend="scip", warm_start=False)
    for r, k in zip(rows, range(log.n_steps)):
        ref = exact(log.z[k], C.step_field(log.steps[k], "z_ref"))
        assert ref.status == "optimal" and abs(r["miqp"] - ref.objective) <= 1e-5 * max(1.0, abs(ref.objective))
        assert r["status_cold"] == "optimal" and r["status_from_miqp"] == "optimal"
    with pytest.raises(ValueError, match="z_ref"):
        C.cost_vs_miqp(s, SimpleNamespace(steps=[SimpleNamespace(info={})], z=log.z, t=log.t), [0])


# ------------------------------------------------------------------ variants: the hold and the margin
def test_variants_are_validated_values():
    assert C.Variant("network").hold == "v" and C.Variant("nmpc").hold == "u"
    assert C.Variant("network").key == "network" and C.Variant("measured", hold="u").key == "measured hold u"
    assert C.Variant("network", margin="eps+delta").key == "network eps+delta"
    for v in (C.Variant("previous"), C.Variant("saturated", hold="u"), C.Variant("network", margin="eps+delta")):
        assert C._variant(v.key) == v  # a key names its variant
    assert C.label("measured hold u") == C.LABELS["measured"] + ", u held"
    with pytest.raises(ValueError, match="holds u"):
        C.Variant("nmpc", hold="v")
    with pytest.raises(ValueError, match="margin"):
        C.Variant("measured", margin="eps+delta")
    with pytest.raises(ValueError, match="margin"):
        C.Variant("network", hold="u", margin="eps+delta")
    with pytest.raises(ValueError, match="hold"):
        C.Variant("network", hold="z")
    with pytest.raises(ValueError, match="method"):
        C.Variant("lqr")
    with pytest.raises(ValueError, match="not a variant"):
        C._variant("network hold u now")


@pytest.fixture(scope="module")
def msd_drift_setting():
    return C.with_drift(C.setting("MSD", horizon=2))  # a short horizon: a fast MIQP without a time limit


def test_with_drift_and_the_rows_of_the_study(msd_drift_setting):
    s = msd_drift_setting
    d = s["drift"]
    assert d.ts == s["ts"] and np.all(d.bracket.converged) and s["delta"] == float(d.upper[0]) >= d.lower[0] > 0
    assert s["margin_fits"] and s["eps"] + s["delta"] < s["system"].u_max[0]
    keys = [v.key for v in C.study_variants(s)]
    assert keys[:5] == list(C.METHODS) and "network eps+delta" in keys
    assert {k for k in keys if k.endswith("hold u")} == {f"{m} hold u" for m in C.METHODS if m != "nmpc"}
    assert "network eps+delta" not in [v.key for v in C.study_variants(C.setting("MSD"))]  # no delta, no row
    mpc, hold = C.make_controller("network eps+delta", s)
    assert hold == "v" and np.isclose(mpc.eps[0], s["eps"] + s["delta"])
    with pytest.raises(ValueError, match="with_drift"):
        C.make_controller("network eps+delta", C.setting("MSD"))


def test_the_margin_that_does_not_fit_is_refused(quad_setting):
    s = dict(quad_setting, delta=0.16, margin_fits=False)  # Quad-1D at t_s = 0.1: delta > u_max - eps
    assert s["eps"] + s["delta"] >= s["system"].u_max[0]
    assert "network eps+delta" not in [v.key for v in C.study_variants(s)]
    with pytest.raises(ValueError, match="leaves no input"):
        C.make_controller("network eps+delta", s)


def test_time_limit_applies_to_the_miqp_only():
    s = C.setting("Quad-1D", horizon=4, time_limit=0.5)
    assert C.make_controller("network", s)[0].time_limit == 0.5
    assert C.make_controller("measured", s)[0].time_limit is None
    assert C.make_controller("saturated", s)[0].inner.time_limit is None
    assert C.make_controller("nmpc", s)[0].time_limit is None
    with pytest.raises(ValueError, match="time_limit"):
        C.setting("MSD", time_limit=0.0)


def test_holding_u_keeps_the_sample_bound_between_samples(quad_setting):
    sc = C.draw_scenarios("Quad-1D", 2, seed=0)[1]
    rows = C.run_scenario(quad_setting, sc, 1.0, ("measured", "measured hold u"))
    by = {r["method"]: r for r in rows}
    assert by["measured"]["violating_intervals"] > 0, "premise: with v held the true input leaves the bound"
    assert by["measured hold u"]["hold"] == "u" and by["measured hold u"]["violating_samples"] == 0
    assert by["measured hold u"]["violating_intervals"] == 0
    assert by["measured hold u"]["max_abs_u_between"] == by["measured hold u"]["max_abs_u_samples"]


def test_the_margin_keeps_the_true_input_within_between_samples(msd_drift_setting):
    """eq. (eq-09-margin): with eps + delta, every interval from an admissible sample keeps |u(t)| <= u_max."""
    s = msd_drift_setting
    far = lambda t: np.tile([3.0, 0.0], (np.size(t), 1))  # a far set point: the bound binds
    logs = C.run_methods(s, np.array([0.0, 0.0]), far, 0.3, ("network", "network eps+delta"))
    m = {k: C.run_metrics(log, far, s["Q"], s["R"]) for k, log in logs.items()}
    assert m["network"]["violating_intervals"] > 0, "premise: with eps alone the true input leaves the bound"
    bound = s["system"].u_max[0] - s["eps"] - s["delta"]
    assert np.abs(logs["network eps+delta"].u).max() >= 0.9 * bound, "premise: the margin's bound is reached"
    assert m["network eps+delta"]["violating_after_admissible"] == 0
    assert m["network eps+delta"]["inadmissible_steps"] == 0 and m["network eps+delta"]["violating_intervals"] == 0


def test_relative_costs_compare_completed_runs_only():
    rows = [dict(scenario=0, method="network", completed=True, cost=2.0),
            dict(scenario=0, method="measured", completed=True, cost=3.0),
            dict(scenario=0, method="previous", completed=False, cost=0.5)]  # stopped early: cheap, not compared
    out = {r["method"]: r["cost_vs_miqp"] for r in C.relative_costs(rows)}
    assert out["network"] == 1.0 and out["measured"] == 1.5 and np.isnan(out["previous"])
    stopped = [dict(rows[0], completed=False), rows[1]]
    assert all(np.isnan(r["cost_vs_miqp"]) for r in C.relative_costs(stopped))
    with pytest.raises(ValueError, match="one scenario"):
        C.relative_costs(rows + [dict(rows[0], scenario=1)])


def test_extremes_name_every_method_at_the_extreme():
    table = {"a": dict(method="A", n=3), "b": dict(method="B", n=1), "c": dict(method="C", n=3),
             "d": dict(method="D", n=3)}
    e = C.extremes(table, "n", ["a", "b", "c"])
    assert e == dict(min=1, max=3, at_min="B", at_max="A and C")
    assert C.extremes(table, "n", ["a", "b", "c", "d"])["at_max"] == "A, C and D"
    assert C.extremes(table, "n", ["a", "c"])["at_min"] == "A and C"
    with pytest.raises(ValueError, match="at least one"):
        C.extremes(table, "n", [])


def test_monte_carlo_figure_draws_the_variants():
    import matplotlib
    matplotlib.use("Agg")
    from flnotes.plots.compare import plot_monte_carlo
    keys = ["network", "measured", "measured hold u", "network eps+delta"]
    rows = [dict(scenario=s, method=k, max_abs_u_samples=0.1, max_abs_u_between=0.2, plan_violation_fraction=0.1 * i,
                 cost_vs_miqp=1.0 + 0.1 * i if s else np.nan, ms_median=1.0, ms_max=2.0)
            for s in range(2) for i, k in enumerate(keys)]
    fig = plot_monte_carlo(rows, keys, 0.1745, labels={k: C.label(k) for k in keys})
    bars = fig.axes[1].patches
    assert len(bars) == 4 and [b.get_hatch() for b in bars] == [None, None, "//", "//"]  # variants hatched
    assert [t.get_text() for t in fig.axes[0].get_xticklabels()] == [C.label(k) for k in keys]
    assert np.isclose(bars[2].get_height(), 0.2)


@pytest.mark.parametrize("name", ["Quad-1D", "MSD", "arm"])
def test_batched_input_maps_equal_input_map_per_state(name):
    from flnotes.mpc.linear import LinearModel
    sysm = fl.two_link_arm() if name == "arm" else fl.paper.system(name)
    n_z, m = sysm.n_z, sysm.m
    lm = LinearModel(SimpleNamespace(N=5, m=m), None, sysm)  # the rows need only the prediction's sizes
    Z = np.random.default_rng(3).uniform(sysm.lo[:n_z], sysm.hi[:n_z], (5, n_z))
    a, B = lm.input_maps(Z)
    G, g_lo, g_hi = lm.rows(Z)
    for k in range(5):
        a_k, B_k = sysm.input_map(Z[k])
        assert np.allclose(a[k], a_k, rtol=1e-12, atol=1e-12) and np.allclose(B[k], B_k, rtol=1e-12, atol=1e-12)
        blk = slice(k * m, (k + 1) * m)
        assert np.allclose(G[blk, blk], B_k) and np.allclose(g_hi[blk], sysm.u_max - a_k)
        assert np.allclose(g_lo[blk], -sysm.u_max - a_k)
    assert np.count_nonzero(G) <= 5 * m * m, "only the diagonal blocks"


def test_batched_input_maps_reject_a_map_not_affine_in_v():
    from flnotes.mpc.linear import LinearModel
    A, B = fl.brunovsky(2)
    cubic = fl.FLSystem("cubic", A, B, phi=lambda z, v: v**3 + z[:, :1], lo=[-1, -1, -1], hi=[1, 1, 1], u_max=1.0,
                        f=lambda x, u: np.array([x[1], u[0]]), to_z=lambda x: x, to_x=lambda z: z)
    lm = LinearModel(SimpleNamespace(N=3, m=1), None, cubic)
    with pytest.raises(ValueError, match="not affine in v"):
        lm.input_maps(np.zeros((3, 2)))


def test_cost_summary_gives_absolute_differences_next_to_the_ratios():
    rows = [dict(miqp=100.0, nmpc_from_miqp=102.0, rel_from_miqp=0.02),
            dict(miqp=0.04, nmpc_from_miqp=0.06, rel_from_miqp=0.5),     # a tiny cost: a large ratio, a small gap
            dict(miqp=10.0, nmpc_from_miqp=9.0, rel_from_miqp=-0.1)]
    s = C.cost_summary(rows)
    assert (s["n"], s["rel_min"], s["rel_max"], s["rel_median"]) == (3, -0.1, 0.5, 0.02)
    assert s["abs_min"] == pytest.approx(-1.0) and s["abs_max"] == pytest.approx(2.0)
    assert s["weighted"] == pytest.approx(111.06 / 110.04 - 1)
    with pytest.raises(ValueError, match="at least one row"):
        C.cost_summary([])


def test_spread_verdicts_and_counts_in_words():
    from flnotes.repeats import against_spread, spread
    from flnotes.tables import counted

    assert spread([0.6872, 0.7817]) == pytest.approx(0.7817 / 0.6872 - 1)
    assert against_spread(1.0, 1.1, 0.137) == "within the run-to-run spread"
    assert against_spread(1.0, 1.137, 0.137) == "within the run-to-run spread"  # at the spread itself: within
    # barely above the spread is not yet "beyond": up to twice the spread is its edge
    assert against_spread(1.0, 1.2, 0.137) == "at the edge of the run-to-run spread"
    assert against_spread(1.2, 1.0, 0.137) == "at the edge of the run-to-run spread"
    assert against_spread(1.0, 1.274, 0.137) == "at the edge of the run-to-run spread"
    assert against_spread(1.0, 1.28, 0.137) == "beyond the run-to-run spread"
    assert against_spread(1.28, 1.0, 0.137) == "beyond the run-to-run spread"
    assert against_spread(1.0, 1.0, 0.0) == "within the run-to-run spread"  # no spread: no edge either
    assert against_spread(1.0, 1.001, 0.0) == "beyond the run-to-run spread"
    from flnotes.repeats import VERDICTS
    assert len(set(VERDICTS)) == 3 and all(v.endswith("the run-to-run spread") for v in VERDICTS)
    with pytest.raises(ValueError, match="at least two positive"):
        spread([1.0])
    with pytest.raises(ValueError, match="at least two positive"):
        spread([1.0, 0.0])
    with pytest.raises(ValueError, match="spread >= 0"):
        against_spread(1.0, 1.1, float("nan"))
    assert [counted(n, "answer came", "answers came") for n in (0, 1, 2)] == \
        ["0 answers came", "1 answer came", "2 answers came"]
    with pytest.raises(ValueError, match="a count"):
        counted(1.5, "a", "b")
