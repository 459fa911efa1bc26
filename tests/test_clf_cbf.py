"""The CLF-CBF controller of eq. (CLF_CBF): exact 1-D enumeration, MILP/MIQP backends, closed loop, infeasibility."""
import numpy as np
import pytest

import flnotes as fl
from flnotes.control import (ClfCbfController, DistanceCBF, QuadraticCLF, as_certificate, exact_1d_feasible_set,
                             network_pieces_1d)
from flnotes.studies import clf_cbf_checks, cross_check_exact

S = fl.paper.MSD_SETTING
EPS = fl.paper.TABLE1["MSD"]["eps"]


@pytest.fixture(scope="module")
def msd():
    net, _ = fl.paper_net("MSD")
    return fl.msd(), net


def parts():
    return QuadraticCLF(S["P"]), DistanceCBF(S["z_o"], S["r_o"]), (lambda z: -S["K_nominal"] @ z)


def rel(a, b):
    return abs(a - b) / max(1.0, abs(b))


# --------------------------------------------------------------------------- certificates
def test_clf_and_cbf_values_and_gradients():
    V, H, _ = parts()
    rng = np.random.default_rng(0)
    for z in rng.uniform(-3, 3, (5, 2)):
        for f in (V, H):
            g = np.array([(f(z + h) - f(z - h)) / 2e-6 for h in np.eye(2) * 1e-6])
            assert np.allclose(f.grad(z), g, atol=1e-6)
    assert np.isclose(V(np.array([1.0, 0.0])), S["P"][0, 0])
    assert np.isclose(H(S["z_o"]), -S["r_o"]) and np.allclose(H.grad(S["z_o"]), 0)
    Z = rng.uniform(-3, 3, (7, 2))
    assert np.allclose(H(Z), [H(z) for z in Z]) and np.allclose(V(Z), [V(z) for z in Z])
    # a user's own pair (fn, grad) is accepted
    c = as_certificate((lambda z: z @ z, lambda z: 2 * z), "W")
    assert c(np.array([1.0, 2.0])) == 5.0 and np.allclose(c.grad(np.array([1.0, 2.0])), [2, 4])
    with pytest.raises(ValueError, match="positive definite"):
        QuadraticCLF(-np.eye(2))
    with pytest.raises(ValueError, match="r_o"):
        DistanceCBF([0, 0], -1.0)


# --------------------------------------------------------------------------- exact 1-D method
@pytest.mark.parametrize("z", [S["z0"], np.array([1.0, 0.3]), np.array([-2.0, -4.5]), np.array([0.01, -0.02])])
def test_pieces_reproduce_the_network_and_its_activation_regions(msd, z):
    _, net = msd
    pw = network_pieces_1d(net, z, -10.0, 10.0)
    v = np.linspace(-10, 10, 40001)
    X = np.column_stack([np.repeat(z[None], len(v), 0), v])
    assert np.abs(pw(v) - net(X)[:, 0]).max() < 1e-9
    # inside every piece the activation pattern is constant (the knots are all the breakpoints)
    for a, b in zip(pw.knots[:-1], pw.knots[1:]):
        pts = np.linspace(a, b, 7)[1:-1]
        pats = net.activation_pattern(np.column_stack([np.repeat(z[None], len(pts), 0), pts]))
        assert all(np.all(p == p[0]) for p in pats)


def test_feasible_set_is_exact(msd):
    _, net = msd
    bound = 5.0 - EPS
    for z in [S["z0"], np.array([2.0, -1.0]), np.array([4.5, 4.5])]:
        iv = exact_1d_feasible_set(net, z, -10.0, 10.0, bound)
        v = np.linspace(-10, 10, 20001)
        inside = np.abs(net(np.column_stack([np.repeat(z[None], len(v), 0), v]))[:, 0]) <= bound
        in_iv = np.zeros_like(inside)
        for a, b in iv:
            in_iv |= (v >= a) & (v <= b)
        near = np.min(np.abs(v[:, None] - iv.ravel()[None, :]), axis=1) < 1e-9 if len(iv) else np.zeros_like(inside)
        assert np.all((inside == in_iv) | near)
        assert np.all(np.diff(iv.ravel()) >= 0), "intervals sorted and disjoint"


def test_exact_method_takes_one_or_two_inputs():
    A, B = fl.brunovsky([1, 1])
    rng = np.random.default_rng(1)
    net = fl.ReLUNet([rng.normal(size=(5, 4)), rng.normal(size=(2, 5))], [rng.normal(size=5), rng.normal(size=2)])
    sysm = fl.FLSystem("two", A, B, phi=lambda z, v: v, lo=[-1] * 4, hi=[1] * 4, u_max=[1, 1],
                       f=lambda x, u: u, to_z=lambda x: x, to_x=lambda z: z)
    with pytest.raises(ValueError, match="single input"):
        network_pieces_1d(net, np.zeros(3), -1, 1)
    ctrl = ClfCbfController(sysm, net, 0.1, QuadraticCLF(np.eye(2)), None, cost="linear", backend="exact")
    assert ctrl.backend == "exact" and ctrl.step(np.zeros(2)).v.shape == (2,)


# --------------------------------------------------------------------------- backends agree
STATES = [S["z0"], np.array([1.0, 0.3]), np.array([0.02, -0.01]), np.array([2.5, 0.9]), np.array([-1.5, 2.0]),
          np.array([0.5, 1.0])]  # the last one has z2 = 1: grad H^T B = 0 and the CBF condition fails


@pytest.mark.parametrize("cost, backend", [("linear", "highs"), ("linear", "scip"), ("linear", "cvxpy"),
                                           ("quadratic", "scip")])
def test_mip_backends_match_the_exact_enumeration(msd, cost, backend):
    sysm, net = msd
    V, H, k = parts()
    ctrl = ClfCbfController(sysm, net, EPS, V, H, k, cost=cost, backend=backend)
    ex = ctrl.with_backend("exact")
    states = STATES[:3] + STATES[-1:] if backend == "cvxpy" else STATES
    for z in states:
        r, rx = ctrl.step(z), ex.step(z)
        assert r.status == rx.status and r.fallback == rx.fallback
        assert rel(r.objective, rx.objective) <= 1e-6, (z, r.info, rx.info)
        # whenever the program is feasible the applied v satisfies (CLF_CBF_b)-(CLF_CBF_d) up to tolerances
        if not r.fallback:
            d = ctrl.program_data(z)
            assert abs(r.info["phi_nn"][0]) <= 5.0 - EPS + 1e-6
            assert d["aH"] @ r.v + d["bH"] >= -1e-6
            assert r.info["delta"] >= d["aV"] @ r.v + d["bV"] - 1e-6 and r.info["delta"] >= -1e-9


@pytest.mark.parametrize("backend, n", [("highs", 400), ("scip", 60)])
def test_mip_optimum_matches_the_exact_enumeration_on_many_states(msd, backend, n):
    """The MILP optimum is the global one: no state of a random sample where the exact 1-D method does better."""
    sysm, net = msd
    V, H, k = parts()
    ctrl = ClfCbfController(sysm, net, EPS, V, H, k, cost="linear", backend=backend)
    ex = ctrl.with_backend("exact")
    rng = np.random.default_rng(3)
    states = np.vstack([rng.uniform(-0.5, 0.5, (n // 2, 2)), rng.uniform(-3.0, 3.0, (n - n // 2, 2))])
    worst = 0.0
    for z in states:
        r, rx = ctrl.step(z), ex.step(z)
        assert r.status == rx.status, (z, r.status, rx.status)
        worst = max(worst, rel(r.objective, rx.objective))
        assert worst <= 1e-6, (z, r.v, rx.v, r.objective, rx.objective)


def test_persistent_model_matches_bigm_form_update(msd):
    """The fast in-place write of the big-M coefficients equals BigMForm.update on the same bounds."""
    sysm, net = msd
    V, H, k = parts()
    ctrl = ClfCbfController(sysm, net, EPS, V, H, k, cost="linear", backend="highs")
    impl = ctrl._impl
    z = np.array([1.0, -2.0])
    b = ctrl.node_bounds(z)
    kw = impl.write(z, ctrl.program_data(z), b, soft=False)
    A_ub, b_ub, lb, ub = impl.form.update(b)
    n_eq, n_ub, nf = impl.form.A_eq.shape[0], impl.form.A_ub.shape[0], impl.form.n
    assert np.allclose(kw["A"][n_eq:n_eq + n_ub, :nf].toarray(), A_ub.toarray())
    assert np.allclose(kw["ru"][n_eq:n_eq + n_ub], b_ub)
    keep = np.setdiff1d(np.arange(nf), impl.form.x)
    assert np.array_equal(kw["lb"][keep], lb[keep]) and np.array_equal(kw["ub"][keep], ub[keep])


@pytest.mark.parametrize("backend", ["scip", "highs"])
def test_a_margin_left_by_an_earlier_solve_does_not_shrink_the_next_program(msd, backend):
    """The margin that tightens u_max^eps after a point slipped through the solver's tolerance is per solve."""
    sysm, net = msd
    V, H, k = parts()
    ctrl = ClfCbfController(sysm, net, EPS, V, H, k, cost="linear", backend=backend, screening=False)
    z = np.array([1.0, -2.0])
    ref = ctrl.with_backend(backend).step(z)
    assert abs(abs(ref.info["phi_nn"][0]) - (5.0 - EPS)) <= 1e-6, "premise: the optimum lies on the network's bound"
    ctrl._impl.margin = 1e-2  # what an earlier state's solve may leave behind
    r = ctrl.step(z)
    assert r.status == ref.status == "optimal"
    assert rel(r.objective, ref.objective) <= 1e-9 and np.allclose(r.v, ref.v, rtol=0, atol=1e-9), (r.v, ref.v)


def test_the_same_state_gets_the_same_plan_after_hundreds_of_unrelated_states(msd):
    """The persistent SCIP model's answer at a state does not depend on the states solved before it."""
    sysm, net = msd
    V, H, k = parts()
    ctrl = ClfCbfController(sysm, net, EPS, V, H, k, cost="quadratic", backend="scip")
    rng = np.random.default_rng(7)
    probes = [S["z0"], np.array([1.0, -2.0]), np.array([0.257, 0.0156])]
    first = [ctrl.step(z) for z in probes]
    unscreened = sum(not ctrl.step(z).screened for z in rng.uniform(sysm.lo[:2], sysm.hi[:2], (200, 2)))
    assert unscreened >= 20, "premise: many of the unrelated states reach the MIQP"
    for z, a in zip(probes, first):
        b = ctrl.step(z)
        assert b.status == a.status and b.objective == a.objective and np.array_equal(b.v, a.v), (z, a.v, b.v)


# --------------------------------------------------------------------------- closed loop
# States of the book's closed loops where HiGHS once returned a sub-optimal point as "optimal" (with its MIP
# presolve on, resp. with feasibility tolerances of 1e-8), with the chapter's certified eps.
HARD_STATES = np.array([[0.257, 0.0156], [0.47109655, -0.12717008]])


@pytest.mark.parametrize("backend", ["highs", "scip", "cvxpy"])
def test_mip_optimum_at_states_where_a_solver_was_wrong(msd, backend):
    sysm, net = msd
    V, H, k = parts()
    eps = fl.paper.paper_eps("MSD").upper
    ctrl = ClfCbfController(sysm, net, eps, V, H, k, cost="linear", backend=backend, beta=S["beta"], kappa=S["kappa"])
    ex = ctrl.with_backend("exact")
    for z in HARD_STATES:
        r, rx = ctrl.step(z), ex.step(z)
        assert r.status == rx.status == "optimal", (z, r.status, rx.status)
        assert rel(r.objective, rx.objective) <= 1e-6, (z, r.v, rx.v, r.objective,
                                                                          rx.objective)


@pytest.mark.parametrize("cost", ["linear", "quadratic"])
def test_screening_is_exact(msd, cost):
    """Solving without the network constraint first never changes the optimum, and it is used both ways."""
    sysm, net = msd
    V, H, k = parts()
    ctrl = ClfCbfController(sysm, net, EPS, V, H, k, cost=cost, backend="scip", screening=True)
    ex = ctrl.with_backend("exact")
    rng = np.random.default_rng(11)
    states = np.vstack([rng.uniform(-0.5, 0.5, (15, 2)), rng.uniform(-3.0, 3.0, (15, 2)), [[0.5, 1.0]]])
    screened = 0
    for z in states:
        r, rx = ctrl.step(z), ex.step(z)
        assert r.status == rx.status, (z, r.status, rx.status)
        assert rel(r.objective, rx.objective) <= 1e-6, (z, r.v, rx.v)
        screened += r.screened
    assert 0 < screened < len(states)


@pytest.fixture(scope="module")
def runs(msd):
    sysm, net = msd
    V, H, k = parts()
    out = {}
    for cost, backend in [("linear", "highs"), ("quadratic", "scip")]:
        ctrl = ClfCbfController(sysm, net, EPS, V, H, k, cost=cost, backend=backend)
        log = fl.simulate(sysm, ctrl, t_final=10.0, ts=0.05, z0=S["z0"], hold="u", net=net)
        out[cost] = (ctrl, log)
    return out


@pytest.mark.parametrize("cost", ["linear", "quadratic"])
def test_closed_loop_on_the_true_plant(runs, cost):
    ctrl, log = runs[cost]
    _, H, _ = parts()
    chk = clf_cbf_checks(log, H)
    assert log.message == "" and chk["steps"] == 200
    assert chk["fallback_steps"] == 0 and chk["non_optimal_steps"] == 0
    # the true input never exceeds u_max (u is held between samples), the network output stays within u_max^eps
    assert chk["max_abs_u"] <= 5.0 and chk["max_abs_u_between"] <= 5.0
    assert chk["max_abs_u_nn"] <= 5.0 - EPS + 1e-6
    # safety: H(z) >= 0 at every sample and along the integrated trajectory
    assert chk["min_H"] > 0 and chk["min_H_between"] > 0
    # convergence: ||z|| decreases to a small value (Lcost slides slowly along grad V^T B = 0)
    nz = np.linalg.norm(log.z, axis=1)
    assert nz[-1] < 0.1 * nz[0]
    if cost == "quadratic":
        assert nz[-1] < 1e-3
    # the nominal law alone would have violated |u| <= 5 from the same start (see test_simulate)


@pytest.mark.parametrize("cost", ["linear", "quadratic"])
def test_closed_loop_optima_match_the_exact_method(runs, cost):
    ctrl, log = runs[cost]
    chk = cross_check_exact(ctrl, log)
    assert chk["steps"] == log.n_steps
    assert chk["max_rel_diff"] <= 1e-6
    assert "exact_over_ts" not in chk and any(np.array_equal(chk["exact_argmax_z"], z) for z in log.z)


def test_exact_cross_check_counts_the_steps_over_ts(runs):
    ctrl, log = runs["linear"]
    short = cross_check_exact(ctrl, log, ts=1e-9)
    assert short["exact_over_ts"] == short["steps"]
    assert cross_check_exact(ctrl, log, ts=1e3)["exact_over_ts"] == 0
    with pytest.raises(ValueError, match="ts must be"):
        cross_check_exact(ctrl, log, ts=0.0)


def test_solve_time_table_reports_the_mip_steps_apart(runs):
    """The median over the steps that screening did not settle is the MIP solver's, not the screening QP's."""
    logs = {cost: log for cost, (_, log) in runs.items()}
    table = fl.studies.solve_time_table(logs, ts=0.05)
    for row, (cost, log) in zip(table, logs.items()):
        mip = np.array([not r.screened for r in log.steps])
        assert row["mip_steps"] == mip.sum() > 0
        assert row["mip_median"] == pytest.approx(1e3 * np.median(np.asarray(log.solve_time)[mip]))
    law = fl.simulate(runs["linear"][1].system, fl.FeedbackLaw(lambda z: -S["K_nominal"] @ z), t_final=0.2, ts=0.05,
                      z0=S["z0"], hold="u")
    assert "mip_steps" not in fl.studies.solve_time_table({"k(z)": law})[0], "no MIP solver, no MIP column"


# --------------------------------------------------------------------------- infeasibility
@pytest.mark.parametrize("backend", ["exact", "highs", "cvxpy"])
def test_infeasible_cbf_reports_and_falls_back(msd, backend):
    sysm, net = msd
    V, H, k = parts()
    ctrl = ClfCbfController(sysm, net, EPS, V, H, k, cost="linear", backend=backend)
    r = ctrl.step(np.array([0.5, 1.0]))
    assert r.status == "infeasible" and r.fallback
    assert r.info["fallback_rule"] == "softened program"
    # the fallback keeps the network bound (its slack is zero) and gives up part of the CBF condition
    assert r.info["slack_u"][0] <= 1e-7 and r.info["slack_H"][0] > 0
    assert abs(r.info["phi_nn"][0]) <= 5.0 - EPS + 1e-6


def test_input_bound_too_small_gives_up_the_input_bound_last(msd):
    """u_max = 0.5: at z = [5, 5] no v in [-10, 10] gives |Phi_NN| <= u_max^eps; the fallback minimizes the excess.

    (The true map gives |Phi| = |v + 10.8| >= 0.8 there, so no admissible v exists for Phi either.)"""
    _, net = msd
    sysm = fl.msd(u_max=0.5)
    V, H, k = parts()
    z = np.array([5.0, 5.0])
    pw = network_pieces_1d(net, z, -10, 10)
    assert np.all(pw.values > 0.5 - EPS), "premise: no v in [-10, 10] is admissible at z = [5, 5] for this network"
    res = {}
    for backend in ("exact", "highs"):
        ctrl = ClfCbfController(sysm, net, EPS, V, H, k, cost="quadratic" if backend == "exact" else "linear",
                                backend=backend)
        r = ctrl.step(z)
        assert r.status == "infeasible" and r.fallback and r.info["slack_u"][0] > 0
        res[backend] = r.v[0]
    assert np.allclose([res["exact"], res["highs"]], -10.0)  # the smallest |Phi_NN| is at v_lo


def test_closed_loop_with_too_small_u_max_reports_infeasibility_and_never_crashes(msd):
    """u_max = 2: near the obstacle the input cannot brake enough for the CBF condition.

    Infeasible steps are reported and counted, the softened program is applied, the
    input bound is kept (it is given up last) and the run goes on to the end.
    """
    _, net = msd
    sysm = fl.msd(u_max=2.0)
    V, H, k = parts()
    ctrl = ClfCbfController(sysm, net, EPS, V, H, k, cost="quadratic", backend="exact")
    log = fl.simulate(sysm, ctrl, t_final=6.0, ts=0.05, z0=S["z0"], hold="u", net=net)
    s = log.summary()
    assert log.n_steps == 120 and log.message == ""
    n_inf = sum(st == "infeasible" for st in log.status)
    assert n_inf > 0 and s["fallback_steps"] == n_inf == s["non_optimal_steps"]
    assert all(r.info["fallback_rule"] == "softened program" for r in log.steps if r.fallback)
    assert all(r.info["slack_H"][0] > 0 and r.info["slack_u"][0] <= 1e-9 for r in log.steps if r.fallback)
    assert np.abs(log.u).max() <= 2.0 and np.abs(log.u_fine).max() <= 2.0
    # the same steps with the MIQP backend: same verdicts, same softened optimum
    ctrl_milp = ctrl.with_backend("scip")
    for i in np.flatnonzero(log.fallback)[:3]:
        r = ctrl_milp.step(log.z[i])
        assert r.status == "infeasible" and r.fallback
        assert rel(r.objective, log.steps[i].objective) <= 1e-6
    # a solver that raises is caught by the controller, not by the simulation
    ctrl_bad = ClfCbfController(sysm, net, EPS, V, H, k, cost="quadratic", backend="exact")
    ctrl_bad._impl.solve = lambda *a, **kw: (_ for _ in ()).throw(RuntimeError("boom"))
    r = ctrl_bad.step(np.array([1.0, 1.0]))
    assert r.fallback and r.status == "error" and r.message.startswith("RuntimeError")
    assert r.info["fallback_rule"].startswith("k(z)")


@pytest.mark.parametrize("cost, backend, screening", [("linear", "highs", True), ("linear", "auto", True),
                                                      ("linear", "scip", False), ("quadratic", "auto", True),
                                                      ("quadratic", "scip", False)])
def test_multi_input_system_works_with_the_milp(msd, cost, backend, screening):
    """Two decoupled double integrators with a random network: the persistent backends and the exact region
    method (the default for m = 2) handle m = 2 and agree with the cvxpy reference."""
    from _nets import two_msd

    sysm, net = two_msd()
    P = np.kron(np.eye(2), S["P"])
    ctrl = ClfCbfController(sysm, net, 0.1, QuadraticCLF(P), DistanceCBF([1.5, 1.0, 0.0, 0.0], 0.8),
                            lambda z: -np.kron(np.eye(2), S["K_nominal"]) @ z, cost=cost, backend=backend,
                            screening=screening)
    assert ctrl.backend == (backend if backend != "auto" else "exact")
    ref = ctrl.with_backend("cvxpy")
    states = np.vstack([[0.0, 4.0, 1.0, -1.0], [2.0, 0.0, 0.0, 2.0],
                        np.random.default_rng(4).uniform(-3.0, 3.0, (6, 4))])
    for z in states:
        r, rr = ctrl.step(z), ref.step(z)
        assert r.v.shape == (2,) and r.status == rr.status
        assert rel(r.objective, rr.objective) <= 1e-6
        assert np.all(np.abs(r.info["phi_nn"]) <= 5.0 - 0.1 + 1e-6) or r.fallback


def test_auto_backend_and_clear_errors(msd):
    sysm, net = msd
    V, H, k = parts()
    ctrl = ClfCbfController(sysm, net, EPS, V, H, k)
    assert ctrl.backend == "exact" and ctrl.cost == "linear" and "no model" in ctrl.describe()
    assert np.allclose(ctrl(S["z0"]), ctrl.history[-1].v) and ctrl.stats()["steps"] == 1
    with pytest.raises(ValueError, match="nominal law k"):
        ClfCbfController(sysm, net, EPS, V, H, None, cost="quadratic")
    with pytest.raises(ValueError, match="HiGHS has no mixed-integer QP"):
        ClfCbfController(sysm, net, EPS, V, H, k, cost="quadratic", backend="highs")
    with pytest.raises(ValueError, match="u_max - eps must stay positive"):
        ClfCbfController(sysm, net, 6.0, V, H, k)
    with pytest.raises(ValueError, match="cost must be"):
        ClfCbfController(sysm, net, EPS, V, H, k, cost="cubic")


def test_highs_alone_check_compares_one_highs_solve_with_the_exact_method(msd):
    """The chapter's check of a single HiGHS solve: never better than the exact optimum, MILP only."""
    sysm, net = msd
    V, H, k = parts()
    ctrl = ClfCbfController(sysm, net, EPS, V, H, k, cost="linear", backend="scip")
    Z = np.array([[1.0, -2.0], [0.257, 0.0156], [-1.0, 2.0]])
    r = fl.studies.highs_alone_check(ctrl, Z)
    assert r["states"] == 3 and r["wrong_value"] + r["wrong_status"] <= 3 and r["min_gap"] >= -1e-6
    with pytest.raises(ValueError, match="no mixed-integer QP"):
        fl.studies.highs_alone_check(ctrl.with_backend("scip", cost="quadratic"), Z)


def test_braking_scan_finds_the_crossover_of_full_braking_near_the_segment_end():
    """``braking_scan``: from z = [z1, 1] full braking keeps the MSD out of the disc at z1 = 0.5 and enters it from
    the segment's end point 0.7; the crossover lies between the two fine points, and no constant input does better
    than full braking from the first point lost."""
    import flnotes as fl
    from flnotes.studies import braking_scan

    S = fl.paper.MSD_SETTING
    msd, H = fl.msd(), fl.DistanceCBF(S["z_o"], S["r_o"])
    bs = braking_scan(msd, H, 0.01, coarse=[0.5], fine=[0.68, 0.7], n_const=5)
    assert bs["min_h"][0] > 0 and bs["min_h_fine"][0] > 0 > bs["min_h_fine"][1]
    assert bs["i_cross"] == 1 and bs["z_safe"] == 0.68 and bs["z_lost"] == 0.7
    assert bs["best_const"] == pytest.approx(bs["brake_at_lost"], abs=1e-9) and bs["best_const"] < 0


@pytest.mark.parametrize("backend, options, match", [
    ("exact", {"params": {}}, "does not read them"), ("cvxpy", {"threads": 1}, "does not read them"),
    ("scip", {"objectiv": "epigraph"}, "no option 'objectiv'"), ("highs", {"params": {"bogus_option": 1}}, "bogus"),
    ("daqp", {"reg": -1}, "reg")])
def test_clf_cbf_solver_options_are_checked_when_the_controller_is_built(msd, backend, options, match):
    sysm, net = msd
    V, H, k = parts()
    with pytest.raises(ValueError, match=match):
        ClfCbfController(sysm, net, EPS, V, H, k, cost="linear", backend=backend, solver_options=options)


def test_clf_cbf_highs_keeps_its_measured_params_under_given_options(msd):
    """Options given for HiGHS are merged with the two measured HiGHS settings (a given entry wins), not put in
    their place."""
    sysm, net = msd
    V, H, k = parts()
    c = ClfCbfController(sysm, net, EPS, V, H, k, cost="linear", backend="highs", solver_options={"threads": 1})
    assert c.solver_options["params"] == dict(mip_detect_symmetry=False, mip_heuristic_run_feasibility_jump=False)
    c = ClfCbfController(sysm, net, EPS, V, H, k, cost="linear", backend="highs",
                         solver_options={"params": {"mip_detect_symmetry": True}})
    assert c.solver_options["params"]["mip_detect_symmetry"] is True
    with pytest.raises(ValueError, match="solver_options must be a dict"):
        ClfCbfController(sysm, net, EPS, V, H, k, cost="linear", backend="highs", solver_options=[("threads", 1)])
