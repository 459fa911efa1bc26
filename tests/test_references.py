"""The references are exact: the MPC's cold ``cvxpy-scip`` program and the CLF-CBF's ``cvxpy`` back-end.

The MPC reference runs SCIP at the engine's feasibility tolerance (1e-9) and moves a plan that lies on the ``v``-box
face up to SCIP's tolerance onto it; its plan is then checked by the forward pass. The CLF-CBF ``cvxpy`` back-end
checks every answer against the exact method of one input (the linear pieces of ``Phi_NN(z, .)``). Both are compared
here with the engine (MPC) and the exact method (CLF-CBF) on states of the audited kinds: uniform, at and near the
faces of the domain box, and with the network bound active; the MPC also on states whose optimum lies on the
``v``-box face. No solver chatter reaches the C streams.
"""
import numpy as np
import pytest

import flnotes as fl
from flnotes.bench import exactness as ex
from flnotes.control import ClfCbfController, DistanceCBF, QuadraticCLF
from flnotes.mpc import MPC

from _nets import stored_integrator_case, test_net

S = fl.paper.QUAD_SETTING
EPS = 0.03  # above the small network's largest error on its training grid (0.028)
COMMON = dict(horizon=4, ts=S["ts"], Q=S["Q"], R=S["R"])


def rel(a, b):
    return abs(a - b) / max(1.0, abs(b))


@pytest.fixture(scope="module")
def quad_small():
    return fl.quad1d(), test_net("quad1d-8x8")[0]


def _agree(eng, ref, z, R):
    a, b = eng(z, R), ref(z, R)
    assert b.status == a.status, (z, a.message, b.message)
    if a.status == "optimal":
        assert not b.fallback and ref.plan_feasible(b.z_pred, b.v_pred), b.message
        assert rel(b.objective, a.objective) <= 1e-6, (z, a.objective, b.objective, b.message)
    return a, b


def test_the_mpc_reference_is_exact_on_the_v_box_face(quad_small, capfd):
    """States whose optimum puts an input on the face of a narrowed v-box: the reference returns that optimum (not
    an error), its plan on the box and through the forward pass, at the engine's cost to 1e-6; nothing on the C
    streams."""
    sysm, net = quad_small
    vb = (-2.0, 2.0)
    eng = MPC(sysm, net, EPS, v_box=vb, **COMMON)
    ref = MPC(sysm, net, EPS, v_box=vb, backend="cvxpy-scip", bounds="box", **COMMON)
    rng = np.random.default_rng(0)
    lo, hi = sysm.lo[:3], sysm.hi[:3]
    on_face = 0
    for _ in range(fl.scale(12, 8)):
        z = rng.uniform(0.8 * lo, 0.8 * hi)
        R = np.zeros((COMMON["horizon"] + 1, 3))
        R[:, 0] = rng.uniform(-4, 4)
        eng.reset(), ref.reset()
        a, b = _agree(eng, ref, z, R)
        if a.status == "optimal" and np.any(np.abs(np.abs(a.v_pred) - vb[1]) <= 1e-9):
            on_face += 1
            assert np.all(np.abs(b.v_pred) <= vb[1])
    assert on_face >= 2, "premise: optima on the v-box face"
    out = capfd.readouterr()
    assert "GMP" not in out.err and "GMP" not in out.out


def test_the_mpc_reference_is_exact_on_the_audited_states(quad_small):
    """Uniform states, states on and near the faces of the box, the input bound strongly active, sine and step
    references: the reference and the engine return the same status and the same optimum to 1e-6."""
    sysm, net = quad_small
    setup = dict(system=sysm, N=COMMON["horizon"], ts=COMMON["ts"])
    eng = MPC(sysm, net, EPS, **COMMON)
    ref = MPC(sysm, net, EPS, backend="cvxpy-scip", bounds="horizon", **COMMON)
    seen = set()
    for c in ex.mpc_cases(setup, fl.scale(18, 12), seed=4):
        eng.reset(), ref.reset()
        a, _ = _agree(eng, ref, c["z"], c["z_ref"])
        seen.add((c["category"], a.status))
    assert {cat for cat, st in seen if st == "optimal"} >= {"uniform", "edge"}, f"premise: optima of each kind {seen}"


def test_compare_to_reference_on_an_unseen_system():
    """fl.studies.compare_to_reference on the shipped VdP-gain network (a system not in the book): every optimum of
    the engine equals the cold reference's to 1e-6."""
    from flnotes.studies import unseen as us

    cases = us.diverse_cases("VdP-gain", fl.scale(8, 4), seed=0, horizon=4)  # a short horizon: the cold solves are
    # slow (10 to 170 s each at the case's N_p = 12 on a loaded machine; there 24 states gave at most 7.7e-7)
    rows = fl.studies.compare_to_reference(us.unseen_mpc("VdP-gain", horizon=4), [(c["z"], c["z_ref"]) for c in cases])
    opt = [r for r in rows if r["status"] == "optimal"]
    assert opt, "premise: optimal steps"
    for r in rows:
        assert r["scip_status"] == r["status"], r
    assert max(r["rel_diff"] for r in opt) <= 1e-6, rows


# ----------------------------------------------------------------------------- CLF-CBF
def _hand_case():
    """One integrator with the hand-made network ``1 + |v - 0.3| - 3 relu(v - 1)`` (3 neurons) and ``u_max = 1``."""
    net = fl.ReLUNet([np.array([[0.0, 1.0], [0.0, -1.0], [0.0, 1.0]]), np.array([[1.0, 1.0, -3.0]])],
                     [np.array([-0.3, 0.3, -1.0]), np.array([1.0])])
    sysm = fl.integrators([1], [-2.0, -2.0], [2.0, 2.0], [1.0])
    return sysm, net, np.array([0.0]), np.array([0.5]), dict(horizon=2, ts=0.2, Q=[1.0], R=0.1, P=[10.0])


def _cone_case(name: str):
    """``(system, network, z, z_ref, MPC keywords)`` of the program ``name`` ("hand" or "random")."""
    if name == "hand":
        return _hand_case()
    sysm, net, z, z_ref = stored_integrator_case("cone_stall_program.npz")
    return sysm, net, z, z_ref, dict(horizon=1, ts=0.2, Q=[1.0], R=0.1, P=[1.0])


@pytest.mark.parametrize("case, bounds, gap", [("random", "box", 1e-6), ("random", "box", 1e-9),
                                               ("random", "lp", 1e-9), ("hand", "box", 1e-9), ("hand", "lp", 1e-9)])
def test_the_reference_closes_its_gap_on_small_programs_with_a_quadratic_cost(case, bounds, gap):
    """Two small programs on which SCIP, given the cost's cones as cvxpy writes them (``sum x_i^2 <= t^2``),
    branched on continuous variables without closing the gap: a random 2-4-4-1 network, one step, 8 binaries
    (``bounds="box"``: no answer in 100 s), and a hand-made 3-neuron network, two steps ("error in LP solver").
    With each cone written as a norm the reference is optimal, and equal to the engine's SCIP back-end. The time
    limit turns a stall into a failure of this test rather than a hang."""
    sysm, net, z, z_ref, kw = _cone_case(case)
    eng = MPC(sysm, net, 0.0, backend="scip", **kw)(z, z_ref)
    mpc = MPC(sysm, net, 0.0, backend="cvxpy-scip", bounds=bounds, gap=gap, time_limit=60.0, **kw)
    ref = mpc(z, z_ref)
    assert eng.status == "optimal"
    assert ref.status == "optimal", ref.message
    assert mpc.plan_feasible(ref.z_pred, ref.v_pred)
    assert rel(ref.objective, eng.objective) <= 1e-6, (ref.objective, eng.objective)
    assert ref.bound <= eng.objective + 1e-9 * max(1.0, abs(eng.objective))


@pytest.fixture(scope="module")
def msd():
    net, _ = fl.paper_net("MSD")
    return fl.msd(), net


def _msd_states(sysm, n, seed):
    """Uniform states, states on a face of the box and near it (1 %), and states near the origin where the network
    bound is active on the Lcost optimum."""
    rng = np.random.default_rng(seed)
    lo, hi = sysm.lo[:2], sysm.hi[:2]
    out = []
    for j in range(n):
        z = rng.uniform(lo, hi)
        if j % 3 == 1:
            i = int(rng.integers(2))
            z[i] = (lo[i] if rng.integers(2) else hi[i]) * (1.0 - rng.uniform(0.0, 0.01))
        elif j % 3 == 2:
            z = rng.uniform(-0.5, 0.5, 2)
        out.append(z)
    return out


@pytest.mark.parametrize("cost", ["linear", "quadratic"])
def test_the_clf_cbf_cvxpy_backend_returns_the_exact_optimum(msd, cost, capfd):
    """The cvxpy back-end (SCIP through the solver layer, both costs) on uniform states, states at the box's faces and states
    where the bound is active: the same status as the exact 1-D method and its optimum to 1e-6, every message
    naming the check; nothing on the C streams."""
    sysm, net = msd
    P = fl.paper.MSD_SETTING
    ctrl = ClfCbfController(sysm, net, fl.paper.TABLE1["MSD"]["eps"], QuadraticCLF(P["P"]),
                            DistanceCBF(P["z_o"], P["r_o"]), lambda z: -P["K_nominal"] @ z, cost=cost,
                            backend="cvxpy", time_limit=5.0)
    exact = ctrl.with_backend("exact")
    active = 0
    for z in _msd_states(sysm, fl.scale(12, 6), seed=1):
        r, rx = ctrl.step(z), exact.step(z)
        assert r.status == rx.status and r.fallback == rx.fallback, (z, r.message, rx.message)
        if rx.status == "optimal":
            assert rel(r.objective, rx.objective) <= 1e-6, (z, r.objective, rx.objective, r.message)
            assert "exact 1-D method" in r.message, r.message
            active += bool(abs(abs(rx.info["phi_nn"][0]) - ctrl.u_eps[0]) <= 1e-6)
    assert active >= 1, "premise: states where the network bound is active"
    assert "GMP" not in capfd.readouterr().err


def test_a_cvxpy_failure_is_replaced_by_the_exact_optimum_and_said(msd, monkeypatch):
    """When cvxpy's solver fails (SolverError, as SCIP did near the domain edge), the step returns the exact
    method's optimum, and its message says first what was proven, then that the solver failed."""
    import cvxpy as cp

    sysm, net = msd
    P = fl.paper.MSD_SETTING
    ctrl = ClfCbfController(sysm, net, fl.paper.TABLE1["MSD"]["eps"], QuadraticCLF(P["P"]),
                            DistanceCBF(P["z_o"], P["r_o"]), cost="linear", backend="cvxpy")
    z = np.array([1.0, 0.3])
    rx = ctrl.with_backend("exact").step(z)
    assert rx.status == "optimal", "premise: a feasible state"

    def fails(*a, **k):
        raise cp.error.SolverError("Solver 'HIGHS' failed")

    monkeypatch.setattr(ctrl._impl.problem, "solve", fails)
    r = ctrl.step(z)
    assert r.status == "optimal" and not r.fallback
    assert r.objective == rx.objective and np.array_equal(r.v, rx.v)
    assert "failed" in r.message and "exact 1-D method" in r.message, r.message
    assert r.message.startswith("the optimum of the exact 1-D method"), "the message says first what was proven"


def test_the_qcost_cvxpy_backend_solves_through_the_solver_layer(msd):
    """Qcost through cvxpy: SCIP gets the program's QP form (flnotes.solvers.cvxpy_bridge.ScipQP), not cvxpy's cone
    form; at a state within 2 % of the box's face where the cone form once took 65 s, the answer is SCIP's own
    optimum (not replaced by the exact method) and equals the exact 1-D optimum to 1e-6; the message carries SCIP's
    status. Also at two states on the face z2 = -5 where SCIP wrote a numerical warning and proved the optimum."""
    sysm, net = msd
    P = fl.paper.MSD_SETTING
    ctrl = ClfCbfController(sysm, net, fl.paper.TABLE1["MSD"]["eps"], QuadraticCLF(P["P"]),
                            DistanceCBF(P["z_o"], P["r_o"]), lambda z: -P["K_nominal"] @ z, cost="quadratic",
                            backend="cvxpy")
    from flnotes.solvers.cvxpy_bridge import ScipQP

    assert isinstance(ctrl._impl._bridge, ScipQP)
    exact = ctrl.with_backend("exact")
    # the second and third: SCIP wrote "EMAISM: numerical violation ..." and still proved the optimum
    for z in ([4.942480204479921, -1.3465765358892146], [1.9392107619453363, -4.999999974365303],
              [1.9576894845731498, -4.999999971872964]):
        r, rx = ctrl.step(np.array(z)), exact.step(np.array(z))
        assert rx.status == "optimal", "premise: a feasible state"
        assert r.status == "optimal" and rel(r.objective, rx.objective) <= 1e-6, (r.message, r.objective, rx.objective)
        assert "SCIP status" in r.message and "equal to the optimum of the exact 1-D method" in r.message, r.message
        assert "failed" not in r.message and ctrl._impl._bridge.result.status == "optimal", r.message


def test_the_bridge_checks_its_options():
    """ScipQP takes time_limit, gap, feastol and miqp_params only: anything else is an error that names them."""
    import cvxpy as cp

    from flnotes.solvers.cvxpy_bridge import ScipQP

    x = cp.Variable(2)
    b = cp.Variable(boolean=True)
    prob = cp.Problem(cp.Minimize(cp.sum_squares(x - np.array([0.3, -2.0])) + b), [x >= -b, x <= 1])
    bridge = ScipQP()
    prob.solve(solver=bridge, time_limit=10.0)
    assert bridge.result.status == "optimal" and prob.status == "optimal"
    assert np.allclose(x.value, [0.3, -1.0], atol=1e-7) and abs(b.value - 1) <= 1e-9  # 1 + 1 = 2 < 4 with b = 0
    assert abs(prob.value - 2.0) <= 1e-7
    with pytest.raises(ValueError, match="time_limit"):
        prob.solve(solver=ScipQP(), limits_time=1.0)


def test_the_reference_rounds_share_its_time_limit(quad_small, monkeypatch):
    """The reference's time_limit bounds its whole step: when the rows must be tightened again (here every round
    counts as exceeding u_max^eps), each SCIP call gets the time the earlier rounds left, and a round that would
    start with nothing left is not run: the step says so and ends at the limit. Each round is a call that takes
    0.3 s and returns the optimum solved beforehand, so that what the test sees does not depend on SCIP's speed."""
    import copy
    import time

    from flnotes.mpc import controller as ctl

    sysm, net = quad_small
    ref = MPC(sysm, net, EPS, backend="cvxpy-scip", bounds="box", time_limit=0.8, **COMMON)
    z = np.array([0.5, 0.0, 0.0])
    R = np.zeros((COMMON["horizon"] + 1, 3))
    solved = ref.solver.solve(z, R, ref.u_eps)
    assert solved.status == "optimal", "premise: the program is solved to optimality"
    given = []

    def slow(z, R, u_in, time_limit=None, gap=1e-6):
        t_start = time.perf_counter()
        given.append((t_start, time_limit))
        time.sleep(0.3)
        return copy.deepcopy(solved)

    monkeypatch.setattr(ref.solver, "solve", slow)
    monkeypatch.setattr(ctl, "BOUND_TOL", -1.0)  # every optimal round "exceeds" u_max^eps: another round
    step = ref(z, R)
    assert 2 <= len(given) < 6, given
    t_first = given[0][0]
    for t_call, left in given:
        assert left is not None and 0 < left <= 0.8 - (t_call - t_first) + 2e-3, given  # the time left, not 0.8
    assert "the time limit came before round" in step.message, step.message
    assert step.status == "time_limit", (step.status, step.message)


def test_the_reference_reports_its_own_solve_after_an_infeasible_one(quad_small):
    """The reference keeps its program with ``bounds="box"``; when SCIP stops at the time limit without a point,
    cvxpy raises and keeps the previous solve's statistics. The status is this solve's (``"time_limit"``), not the
    previous solve's: it was "infeasible" after a proven infeasible state (a false proof)."""
    sysm, net = quad_small
    ref = MPC(sysm, net, EPS, backend="cvxpy-scip", bounds="box", **COMMON)
    R = np.zeros((COMMON["horizon"] + 1, 3))
    first = ref.solver.solve(np.array([1.369616873214543, -2.302132862361297, -4.590264760638053]), R, ref.u_eps)
    assert first.status == "infeasible", "premise: a state proven infeasible"
    second = ref.solver.solve(np.array([0.5, 0.0, 0.0]), R, ref.u_eps, time_limit=1e-6)
    assert second.status == "time_limit", second.message
    assert "timelimit" in second.message


@pytest.mark.parametrize("scip_status, status", [("time_limit", "time_limit"), ("optimal", "error")])
def test_a_reference_plan_that_fails_the_check_is_a_limit_hit_under_the_limit_else_an_error(quad_small, monkeypatch,
                                                                                           scip_status, status):
    """A plan of the reference that fails the forward-pass check is never applied. When SCIP returned it at the time
    limit, the limit came before a plan that passes (status ``"time_limit"``, as the engine's); when SCIP called it
    optimal, the step is an error. Both apply the fallback."""
    sysm, net = quad_small
    ref = MPC(sysm, net, EPS, backend="cvxpy-scip", bounds="box", time_limit=30.0, **COMMON)
    real, real_check, returned = ref.solver.solve, ref.plan_feasible, {}

    def solve(z, R, u_in, time_limit=None, gap=1e-6):
        out = real(z, R, u_in, time_limit=time_limit, gap=gap)
        assert out.v is not None, "premise: a plan"
        out.status = scip_status
        returned["v"] = out.v_pred
        return out

    monkeypatch.setattr(ref.solver, "solve", solve)
    monkeypatch.setattr(ref, "plan_feasible", lambda Z, V: False if V is returned.get("v") else real_check(Z, V))
    step = ref(np.array([0.5, 0.0, 0.0]), np.zeros((COMMON["horizon"] + 1, 3)))
    assert step.status == status and step.fallback, (step.status, step.message)
    assert "the returned plan fails the forward-pass check" in step.message


def _msd_ctrl(msd, cost, **kw):
    sysm, net = msd
    P = fl.paper.MSD_SETTING
    return ClfCbfController(sysm, net, fl.paper.TABLE1["MSD"]["eps"], QuadraticCLF(P["P"]),
                            DistanceCBF(P["z_o"], P["r_o"]), lambda z: -P["K_nominal"] @ z, cost=cost,
                            backend="cvxpy", **kw)


def test_the_lcost_cvxpy_backend_is_exact_on_its_own(msd):
    """Lcost through cvxpy uses SCIP by default: at the MSD states where HiGHS (the former default) labelled points of
    cost -166.2 and -1029.7 optimal, the program's own answer is the exact optimum (confirmed, not replaced)."""
    ctrl = _msd_ctrl(msd, "linear")
    exact = ctrl.with_backend("exact")
    assert ctrl._impl.solver == "SCIP"
    for z in ([-4.388405839673802, 2.909481120131087], [-3.7296355151117524, 3.916213231301512]):
        r, rx = ctrl.step(np.array(z)), exact.step(np.array(z))
        assert rx.status == "optimal", "premise: a feasible state"
        assert r.status == "optimal" and rel(r.objective, rx.objective) <= 1e-6, (r.message, r.objective, rx.objective)
        assert "equal to the optimum of the exact 1-D method" in r.message and "not the optimum" not in r.message


@pytest.mark.parametrize("solver", ["SCIP", "HIGHS"])
def test_a_point_under_a_tiny_time_limit_is_checked_against_the_program(msd, solver):
    """At 1 ms a solver may stop with a point that is no point of the program (HiGHS returned v = 0 with every slack
    0 where the CBF row needs slack): the step's status is still the exact method's (infeasible here, no crash), and
    a softened answer that is applied satisfies the softened program's rows with the slacks it reports."""
    ctrl = _msd_ctrl(msd, "linear", time_limit=0.001, solver=solver)
    z = np.array([0.8080457023762336, 1.3995000000000002])
    rx = ctrl.with_backend("exact").step(z)
    assert rx.status == "infeasible", "premise: an infeasible state"
    for _ in range(3):
        r = ctrl.step(z)
        assert r.status == "infeasible" and r.fallback, r.message
        if r.info["fallback_rule"] == "softened program":
            d = ctrl.program_data(z)
            assert np.all(d["aH"] @ r.v + d["bH"] + r.info["slack_H"] >= -1e-6), (r.v, r.info["slack_H"])
            assert np.all(np.abs(r.info["phi_nn"]) <= ctrl.u_eps + r.info["slack_u"] + 1e-6)


def test_cvxpy_backend_edge_cases_found_by_attack(msd):
    """States and settings where the cvxpy back-end once misbehaved: a state on the edge of feasibility (SCIP's point
    2.4e-13 over the network bound, the exact method finds none: the exact method's status, no error); a v-box of
    width 0.02 whose face holds the optimum (the applied v lies in the box, SCIP keeps it only to its tolerance); the
    softened program with a penalty far below SCIP's tolerance (the reported slacks are those v needs); zero and
    negative penalties are refused."""
    for cost, z in (("linear", [1.106423409007001, 0.8694218081841291]),
                    ("quadratic", [1.3646646318637754, 0.9339312949416831])):
        ctrl = _msd_ctrl(msd, cost)
        r, rx = ctrl.step(np.array(z)), ctrl.with_backend("exact").step(np.array(z))
        assert r.status == rx.status == "infeasible", (r.status, r.message)
    ctrl = _msd_ctrl(msd, "quadratic", v_lo=[-0.01], v_hi=[0.01])
    on_face = 0
    for z in ([3.8311843392541594, -4.858287071181678], [5.0, -5.0], [-1.1929976579951185, -1.9375792241126364]):
        r = ctrl.step(np.array(z))
        assert r.status == "optimal" and -0.01 <= r.v[0] <= 0.01, (r.v, r.message)
        on_face += bool(r.v[0] == 0.01)
    assert on_face >= 1, "premise: optima on the face of the v-box"
    ctrl = _msd_ctrl(msd, "linear", penalty=(1e-9, 1e-9))
    z = np.array([1.65, 1.2598076211353315])
    r = ctrl.step(z)
    assert r.fallback and r.info["fallback_rule"] == "softened program", "premise: the softened program"
    d = ctrl.program_data(z)
    need_u = np.maximum(0.0, np.abs(r.info["phi_nn"]) - ctrl.u_eps)
    need_H = np.maximum(0.0, -(d["aH"] @ r.v + d["bH"]))
    assert np.allclose(r.info["slack_u"], need_u, atol=1e-9) and np.allclose(r.info["slack_H"], need_H, atol=1e-9)
    for bad in ((0.0, 1.0), (1.0, -1.0), (np.nan, 1.0)):
        with pytest.raises(ValueError, match="penalty"):
            _msd_ctrl(msd, "linear", penalty=bad)


def test_the_bridge_reports_unbounded_programs_and_checks_its_numbers():
    """ScipQP: an unbounded program is cvxpy's 'unbounded' (not a SolverError), an infeasible one is infeasible (or
    SCIP's 'infeasible or unbounded'); a time_limit or feastol that means nothing is an error naming it."""
    import cvxpy as cp

    from flnotes.solvers.cvxpy_bridge import ScipQP

    x, n = cp.Variable(), cp.Variable(integer=True)
    unb = cp.Problem(cp.Minimize(x + n), [n >= 0, n <= 3])
    unb.solve(solver=ScipQP())
    assert unb.status == "unbounded" and unb.value == -np.inf
    inf = cp.Problem(cp.Minimize(x), [x >= 1, x <= 0, 2 * n == 1])
    inf.solve(solver=ScipQP())
    assert inf.status in ("infeasible", "infeasible_or_unbounded")
    ok = cp.Problem(cp.Minimize(cp.square(x - 0.3) + n), [n >= 0, n <= 3])
    for opts, word in (({"time_limit": "abc"}, "time_limit"), ({"time_limit": np.inf}, "time_limit"),
                       ({"feastol": 0.0}, "feastol"), ({"feastol": 1.0}, "feastol")):
        with pytest.raises(ValueError, match=word):
            ok.solve(solver=ScipQP(), **opts)
    ok.solve(solver=ScipQP(), time_limit=5.0, feastol=1e-9)
    assert ok.status == "optimal" and abs(x.value - 0.3) <= 1e-7 and abs(n.value) <= 1e-9
