"""The MPC's options as one validated value, each accepted combination checked against the cold SCIP reference.

Properties: every combination of :class:`flnotes.MPCOptions` that the engine accepts returns, on recorded
closed-loop states with the warm start they had, the optimum of the cold reference (the paper's program
written with ``fl.encode`` and solved by SCIP); a meaningless combination raises with a message; the
terminal set is imposed on the plan; the QP-based constraint models satisfy the linear rows they claim.
"""
import numpy as np
import pytest

import flnotes as fl
from flnotes.mpc import DAQP_OPTIONS, MPC, MPCOptions, sine_reference
from flnotes.studies import recorded_problems

from _nets import test_net

S = fl.paper.QUAD_SETTING
EPS = 0.03  # above the small network's largest error on its training grid (0.028)
COMMON = dict(horizon=4, ts=S["ts"], Q=S["Q"], R=S["R"])
COMBOS = list(MPCOptions.combinations(backends=("auto", "daqp", "scip", "cvxpy-scip"), constraints=("network",)))


@pytest.fixture(scope="module")
def recorded():
    """States of a short closed loop where the screening QP breaks the network constraint, with the
    previous plans they had, and the cold reference optimum at each."""
    sysm = fl.quad1d()
    net, _ = test_net("quad1d-8x8")  # small (16 neurons): every combination, even the paper's program, is quick
    mpc = MPC(sysm, net, EPS, **COMMON)
    log = fl.simulate(sysm, mpc, t_final=3.0, ts=S["ts"], z0=S["z0"], reference=sine_reference(1.5), net=net)
    hard = [k for k, h in enumerate(mpc.history) if not h.screened and k >= 1]
    assert len(hard) >= 2, "the premise: the run has steps where the network constraint is active"
    problems = recorded_problems(log, hard[:2], with_plans=True)
    ref = MPC(sysm, net, EPS, backend="cvxpy-scip", bounds="box", gap=1e-9, **COMMON)
    J = []
    for z, R, _ in problems:
        r = ref(z, R)
        assert r.status == "optimal" and not r.fallback, r.message
        J.append(r.objective)
    return sysm, net, problems, J


def test_the_combinations_are_the_accepted_ones():
    assert len(COMBOS) == len(set(COMBOS)) > 200
    for o in COMBOS:  # each is a fixed point of the validation
        assert MPCOptions(**{k: getattr(o, k) for k in o.__dataclass_fields__}) == o


@pytest.mark.parametrize("opts", COMBOS, ids=str)
def test_every_combination_gives_the_reference_optimum(recorded, opts):
    sysm, net, problems, J = recorded
    mpc = MPC(sysm, net, EPS, options=opts, **COMMON)
    for (z, R, prev), J_ref in zip(problems, J):
        mpc.set_previous_plan(prev)
        s = mpc(z, R)
        assert s.status == "optimal" and not s.fallback, (opts, s.message)
        assert mpc.plan_feasible(s.z_pred, s.v_pred)
        assert abs(s.objective - J_ref) <= 1e-6 * max(1.0, abs(J_ref)), (opts, s.objective, J_ref)


@pytest.mark.parametrize("kw, match", [
    (dict(backend="highs"), "HiGHS"),
    (dict(backend="cplexx"), "backend must be one of"),
    (dict(backend="cvxpy-scip", screening=True), "cold reference"),
    (dict(backend="cvxpy-scip", bounds="levelset"), "levelset"),
    (dict(bounds="horizon", lp=True), "lp=True"),
    (dict(encode="all", lazy=True), "choose one"),
    (dict(bounds="boxes"), "bounds must be one of"),
    (dict(constraint="measured", bounds="lp"), "only apply to constraint='network'"),
    (dict(constraint="none", backend="scip"), "backend must be 'daqp'"),
    (dict(constraint="measured", iterations=2), "iterations only applies"),
    (dict(iterations=2), "iterations only applies"),
    (dict(constraint="previous", iterations=0), "positive integer"),
    (dict(constraint="nonlinear"), "constraint must be one of"),
    (dict(bounds="lp", first_level="incumbent"), "first_level"),
    (dict(first_level="warm"), "first_level must be one of"),
    (dict(backend="cvxpy-scip", first_level="relaxation"), "first_level"),
    (dict(backend="cvxpy-scip", repair=True), "cold reference"),
    (dict(constraint="measured", repair=True), "only apply to constraint='network'"),
    (dict(backend="scip", branching="layers"), "branching"),
    (dict(branching="depth"), "branching must be one of"),
    (dict(backend="cvxpy-scip", branching="steps"), "branching"),
    (dict(bounds="box", bound_cache=True), "no LP bound"),
    (dict(bounds="horizon", bound_cache=False), "no LP bound"),
    (dict(lp=False, bound_cache=True), "no LP bound"),
    (dict(backend="cvxpy-scip", bounds="lp", bound_cache=True), "bound_cache"),
])
def test_meaningless_combinations_are_errors(kw, match):
    with pytest.raises(ValueError, match=match):
        MPCOptions(**kw)


def test_options_and_keywords_do_not_mix():
    sysm, (net, _) = fl.quad1d(), test_net("quad1d-8x8")
    with pytest.raises(ValueError, match="not both"):
        MPC(sysm, net, EPS, options=MPCOptions(), bounds="box")
    with pytest.raises(TypeError, match="unexpected keyword"):
        MPC(sysm, net, EPS, formulation="sparse")
    with pytest.raises(TypeError, match="True or False"):
        MPCOptions(screening="yes")
    with pytest.raises(TypeError, match="True or False"):
        MPCOptions(bound_cache=1)


def test_terminal_rows_are_imposed(recorded):
    """A terminal box around the origin changes the optimum and the plan ends inside it; too small a set is
    reported as infeasible (with the fallback flagged), never a plan outside it."""
    sysm, net, problems, J = recorded
    z, R, _ = problems[0]
    F = np.vstack([np.eye(3), -np.eye(3)])
    for half in (2.0, 0.5):
        g = np.full(6, half)
        m = MPC(sysm, net, EPS, terminal=(F, g), **COMMON)
        ref = MPC(sysm, net, EPS, terminal=(F, g), backend="cvxpy-scip", bounds="lp", **COMMON)
        s, r = m(z, R), ref(z, R)
        assert s.status == r.status
        if r.status == "optimal":
            assert np.all(F @ s.z_pred[-1] <= g + 1e-7) and not s.fallback
            assert abs(s.objective - r.objective) <= 1e-6 * max(1.0, abs(r.objective))
            assert s.objective >= J[0] - 1e-6 * max(1.0, J[0])  # a restriction cannot lower the optimum
        else:
            assert s.fallback
    with pytest.raises(ValueError, match="terminal must be"):
        MPC(sysm, net, EPS, terminal=(np.eye(2), np.ones(2)), **COMMON)


@pytest.mark.parametrize("constraint, it", [("measured", None), ("previous", 1), ("previous", 3), ("none", None)])
def test_linear_models_keep_their_own_rows(recorded, constraint, it):
    """The QP-based models: the plan satisfies the linear rows of the exact constraint at the states they
    are written at (the measured state; the previous prediction), and ``"none"`` only the boxes."""
    sysm, net, problems, _ = recorded
    kw = dict(constraint=constraint) if it is None else dict(constraint=constraint, iterations=it)
    m = MPC(sysm, net, EPS, **kw, **COMMON)
    for z, R, prev in problems:
        m.set_previous_plan(prev)
        s = m(z, R)
        assert s.status == "optimal" and not s.fallback, s.message
        assert m.pred.feasible(z, s.v_pred, network=False)
        if constraint == "measured":
            u = np.array([sysm.Phi(z, v) for v in s.v_pred])
            assert np.all(np.abs(u) <= sysm.u_max + 1e-6)
        elif constraint == "previous" and it == 1:
            zbar = np.vstack([z[None], prev[0][2:]])
            u = np.array([sysm.Phi(zb, v) for zb, v in zip(zbar, s.v_pred)])
            assert np.all(np.abs(u) <= sysm.u_max + 1e-6)
        elif constraint == "previous":  # iterated: the rows along its own plan's prediction of the last round
            assert s.rounds == it
        # the applied input at the measured state satisfies the exact bound for both linear models
        if constraint != "none":
            assert np.all(np.abs(sysm.Phi(z, s.v)) <= sysm.u_max + 1e-6)


def _small_quad(horizon: int):
    """The Quad-1D with a small test network (6x6) and the book's weights: system, net, eps, MPC keywords."""
    net, _ = test_net("quad1d-6x6")
    eps = 0.0323 + 1e-4  # above this network's largest error on its training grid
    return fl.quad1d(), net, eps, dict(horizon=horizon, ts=0.1, Q=[10.0, 1.0, 1.0], R=0.0175)


def _random_problems(n: int, horizon: int, seed: int = 0):
    """``n`` random states in a part of the box and constant references ``(z0, z_ref)`` (seeded)."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        z0 = rng.uniform([-1, -2, -2], [1, 2, 2])
        zr = np.zeros((horizon + 1, 3))
        zr[:, 0], zr[:, 1] = rng.uniform(-3, 3), rng.uniform(-2, 2)
        yield z0, zr


def test_warm_starts_and_backends_agree_on_random_states():
    """On random states and references (not a closed loop): the default options cold, warm-started with the
    optimum itself and with a feasible but worse plan, and SCIP with the level set all give the optimum of the
    cold reference."""
    sysm, net, eps, kw = _small_quad(horizon=6)
    fast, scip = MPC(sysm, net, eps, **kw), MPC(sysm, net, eps, backend="scip", **kw)
    ref = MPC(sysm, net, eps, backend="cvxpy-scip", bounds="lp", **kw)
    checked = 0
    for z0, zr in _random_problems(40, horizon=6):
        fast.reset()
        cold = fast(z0, zr)
        if cold.status != "optimal" or cold.screened:
            continue
        checked += 1
        J = ref(z0, zr).objective
        assert abs(cold.objective - J) <= 1e-6 * max(1.0, abs(J))
        other = fast(z0, zr + np.array([1.0, 0.0, 0.0]))  # the optimum for another reference: feasible, worse
        for plan in ((cold.z_pred, cold.v_pred), (other.z_pred, other.v_pred)):
            V = np.vstack([plan[1][-1:], plan[1][:-1]])  # so that its shift is the plan itself
            fast.set_previous_plan((fast.predict(z0, V), V))
            w = fast(z0, zr)
            assert w.status == "optimal" and abs(w.objective - J) <= 1e-6 * max(1.0, abs(J))
        r = scip(z0, zr)
        assert r.status == "optimal" and abs(r.objective - J) <= 1e-6 * max(1.0, abs(J))
        if checked == 4:
            break
    assert checked >= 3, "the premise: random states where the network constraint is active"


@pytest.mark.parametrize("first_level", ["incumbent", "relaxation"])
def test_repaired_incumbent_and_first_level_give_the_reference_optimum(first_level):
    """Cold diverse states (no warm start; feasible and infeasible programs): the relaxation's optimum repaired
    step by step is the first incumbent only when it passes the forward-pass check, the level-set rounds start at
    its cost or at the relaxation's, and status and optimum are the cold reference's, with and without the
    repair (which includes the QP of the repaired plan's linear region, flnotes.mpc.region)."""
    from flnotes.bench.exactness import mpc_cases

    sysm, net, eps, kw = _small_quad(horizon=8)
    on = MPC(sysm, net, eps, first_level=first_level, **kw)
    off = MPC(sysm, net, eps, first_level=first_level, repair=False, **kw)
    ref = MPC(sysm, net, eps, backend="cvxpy-scip", bounds="lp", **kw)
    repaired = rejected = checked = improved = 0
    # 100 states: an exact repair leaves the region QP little to improve (the premise below met at the 82nd)
    for c in mpc_cases(dict(system=sysm, N=8, ts=kw["ts"]), 100, seed=5):
        on.reset()
        off.reset()
        s = on(c["z"], c["z_ref"])
        if s.screened:
            continue
        t, r = off(c["z"], c["z_ref"]), ref(c["z"], c["z_ref"])
        assert s.status == t.status == r.status, (s.message, t.message, r.message)
        assert t.info.get("incumbent") is None  # no warm start, no repair: no incumbent
        repaired += s.info.get("incumbent") == "repaired relaxation"
        improved += bool(s.info.get("region_improved"))
        rejected += r.status == "infeasible"  # no admissible plan exists: a repaired plan must be rejected
        if r.status == "optimal":
            checked += 1
            for x in (s, t):
                assert not x.fallback and on.plan_feasible(x.z_pred, x.v_pred)
                assert abs(x.objective - r.objective) <= 1e-6 * max(1.0, abs(r.objective)), (x.objective, r.objective)
    assert checked >= 3 and repaired >= 2, f"the premise: optimal states, admissible repairs ({checked}, {repaired})"
    assert rejected >= 2, f"the premise: infeasible programs whose repaired plan the check rejects ({rejected})"
    assert improved >= 1, "the premise: states where the region QP improved the incumbent"


def test_branching_orders_lay_out_the_same_program(recorded):
    """``branching="layers"`` and ``"steps"`` only permute the columns: the same size and binaries, the same
    relaxation optimum, and the warm start of a feasible plan (:func:`flnotes.mpc.program.plan_vector`, laid out in
    the program's order) satisfies each program with the plan's cost."""
    from flnotes.mpc.program import plan_vector
    from flnotes.solvers import MIQP, make_solver

    sysm, net, problems, J = recorded
    for z, R, _ in problems:
        ref = MPC(sysm, net, EPS, backend="cvxpy-scip", bounds="box", gap=1e-9, **COMMON)(z, R)
        out = {}
        for order in ("layers", "steps"):
            mpc = MPC(sysm, net, EPS, bounds="horizon", branching=order, **COMMON)
            eng = mpc.solver
            f, c0 = mpc.pred.linear(z, R)
            lo, hi = mpc.pred.boxes(z)
            nb = fl.mpc.levers.node_bounds(mpc.pred, mpc.options, eng.box, lo, hi)
            steps = list(range(mpc.N))
            p = eng.program(z, R, steps=steps)
            w = plan_vector(mpc.pred, z, ref.v_pred, nb, steps, p, True, order)
            assert p.violation(w) <= 1e-7, (order, p.violation(w))
            assert abs(p.objective(w) - ref.objective) <= 1e-9 * max(1.0, abs(ref.objective))
            rel = make_solver(MIQP(p.H, p.c, p.c0, p.A, p.rl, p.ru, p.lb, p.ub, np.zeros(p.n, int)), "highs").solve()
            out[order] = (p.n, p.n_integer, p.m, rel.objective)
        (n1, b1, m1, r1), (n2, b2, m2, r2) = out["layers"], out["steps"]
        assert (n1, b1, m1) == (n2, b2, m2) and b1 > 0
        assert abs(r1 - r2) <= 1e-7 * max(1.0, abs(r1))


def test_auto_lp_rounds_give_the_reference_optimum(monkeypatch):
    """``lp="auto"`` with every level-set round counted as large (threshold 0): the LP-tightened rounds, and the
    LP bounds of the steps that constraint generation adds to them, leave the optimum at the cold reference's on
    random states. (On the small programs of the other tests no round reaches the real threshold.)"""
    import flnotes.mpc.engine as engine

    monkeypatch.setattr(engine, "LP_AUTO_BINARIES", 0)
    # steps added by constraint generation (the path of _lp_steps): the first round without the near steps
    monkeypatch.setattr(engine, "NEAR_ACTIVE", None)
    monkeypatch.setattr(engine, "FIRST_RANGE", False)  # and step 0 encoded by its neurons, as when it was written
    calls = {"_lp_level": 0, "_lp_steps": 0}
    for name in calls:
        orig = getattr(engine.NetworkEngine, name)

        def spy(self, *a, _orig=orig, _name=name, **k):
            calls[_name] += 1
            return _orig(self, *a, **k)

        monkeypatch.setattr(engine.NetworkEngine, name, spy)
    sysm, net, eps, kw = _small_quad(horizon=10)
    auto = MPC(sysm, net, eps, lp="auto", **kw)
    ref = MPC(sysm, net, eps, backend="cvxpy-scip", bounds="lp", **kw)
    checked = 0
    for z0, zr in _random_problems(60, horizon=10):
        auto.reset()
        s = auto(z0, zr)
        if s.screened:
            continue
        r = ref(z0, zr)
        assert s.status == r.status, (s.message, r.message)
        if r.status == "optimal":
            checked += 1
            assert not s.fallback and auto.plan_feasible(s.z_pred, s.v_pred)
            assert abs(s.objective - r.objective) <= 1e-6 * max(1.0, abs(r.objective)), (s.objective, r.objective)
        if checked >= 4 and calls["_lp_steps"]:
            break
    assert checked >= 3, "the premise: random states where the network constraint is active"
    assert calls["_lp_level"] and calls["_lp_steps"], f"the premise: both LP paths ran ({calls})"


@pytest.mark.parametrize("threshold, expect", [(0, "scip"), (10_000, "daqp")])
def test_auto_backend_gives_the_reference_optimum(monkeypatch, threshold, expect):
    """``backend="auto"`` with the threshold moved so that every program goes to SCIP (0) or to DAQP: both
    branches return the cold reference's optimum on random states, and each step names the solver it used."""
    import flnotes.mpc.levers as levers

    monkeypatch.setattr(levers, "AUTO_DAQP_BINARIES", threshold)
    monkeypatch.setattr(levers, "AUTO_DAQP_COLD_BINARIES", threshold)
    sysm, net, eps, kw = _small_quad(horizon=10)
    auto = MPC(sysm, net, eps, **kw)
    assert auto.options.backend == "auto"
    ref = MPC(sysm, net, eps, backend="cvxpy-scip", bounds="lp", **kw)
    checked = 0
    for z0, zr in _random_problems(80, horizon=10):
        auto.reset()
        s = auto(z0, zr)
        if s.screened or s.n_binaries == 0:
            continue
        r = ref(z0, zr)
        assert s.status == r.status, (s.message, r.message)
        if r.status == "optimal":
            checked += 1
            assert s.backend == expect, (s.backend, s.message)
            assert not s.fallback and auto.plan_feasible(s.z_pred, s.v_pred)
            assert abs(s.objective - r.objective) <= 1e-6 * max(1.0, abs(r.objective)), (s.objective, r.objective)
        if checked >= 4:
            break
    assert checked >= 3, "the premise: random states where the network constraint is active"


def test_auto_backend_takes_options_per_backend():
    sysm, net, eps, kw = _small_quad(horizon=4)
    with pytest.raises(ValueError, match="per back-end"):
        MPC(sysm, net, eps, solver_options=dict(reg=1e-5), **kw)
    mpc = MPC(sysm, net, eps, solver_options={"daqp": dict(reg=1e-5), "scip": dict(miqp_params="default")}, **kw)
    assert mpc.solver_options["daqp"]["reg"] == 1e-5 and "params" in mpc.solver_options["daqp"]
    assert mpc.solver_options["scip"] == dict(miqp_params="default")
    mpc = MPC(sysm, net, eps, solver_options={"daqp": dict(params={"iter_limit": 5000})}, **kw)
    assert mpc.solver_options["daqp"]["params"] == dict(DAQP_OPTIONS["params"], iter_limit=5000)  # merged, not replaced


@pytest.mark.parametrize("kw, match", [
    (dict(backend="scip", solver_options={"feastol": "abc"}), "feastol"),
    (dict(backend="scip", solver_options={"param": {"limits/nodes": 1}}), "no option 'param'"),
    (dict(backend="scip", solver_options={"params": {"not/a/param": 1}}), "not/a/param"),
    (dict(solver_options={"scip": {"objective": "foo"}}), "objective"),  # auto: before any SCIP program comes
    (dict(backend="daqp", solver_options={"verify_node": 0}), "verify_node"),
    (dict(backend="daqp", solver_options={"params": {"bogus": 1}}), "bogus"),
    (dict(backend="daqp", solver_options={"scip_options": {"objective": "foo"}}), "scip_options"),
    (dict(solver_options=[1, 2]), "solver_options must be a dict"),
    (dict(backend="cvxpy-scip", solver_options={"scip": {}}), "leave solver_options unset"),
    (dict(constraint="none", solver_options={"daqp": {}}), "leave solver_options unset"),
])
def test_solver_options_are_checked_when_the_controller_is_built(kw, match):
    """Never silently ignored, never first at a step (the bad option may reach its back-end many steps later)."""
    sysm, net, eps, common = _small_quad(horizon=4)
    with pytest.raises(ValueError, match=match):
        MPC(sysm, net, eps, **common, **kw)


@pytest.mark.parametrize("field, value", [("horizon", True), ("horizon", "4"), ("ts", "0.1"), ("ts", True)])
def test_horizon_and_sampling_time_of_the_wrong_type_are_named(field, value):
    sysm, net, eps, common = _small_quad(horizon=4)
    with pytest.raises(ValueError, match=field if field == "ts" else "horizon"):
        MPC(sysm, net, eps, **dict(common, **{field: value}))


def test_time_limit_returns_an_admissible_plan_with_an_honest_gap(recorded):
    """With (almost) no time, the controller returns the warm start if it is feasible, never a plan that breaks
    the program, and its gap is measured against a true lower bound (the QP without the network)."""
    sysm, net, problems, J = recorded
    mpc = MPC(sysm, net, EPS, time_limit=1e-9, cut_off=False, **COMMON)
    kept = 0
    for (z, R, prev), J_ref in zip(problems, J):
        mpc.set_previous_plan(prev)
        s = mpc(z, R)
        assert s.status in ("time_limit", "optimal")
        if s.fallback:
            continue
        kept += 1
        assert mpc.plan_feasible(s.z_pred, s.v_pred)
        assert s.bound <= J_ref + 1e-9 * max(1.0, J_ref) <= s.objective + 2e-9 * max(1.0, J_ref)
        if s.status == "time_limit":
            assert np.isfinite(s.gap) and abs(s.gap - (s.objective - s.bound) / max(1.0, abs(s.objective))) < 1e-12
    assert kept >= 1, "the premise: the shifted closed-loop plan is feasible at a recorded state"


@pytest.mark.parametrize("daqp_options", [dict(reg_mode="upper"), dict(reg_retry=False),
                                          dict(verify_feasibility="milp"), dict(verify_feasibility="miqp"),
                                          dict(reg=1e-5)], ids=str)
def test_daqp_switches_give_the_reference_optimum(recorded, daqp_options):
    """The exact switches of the DAQP back-end (its regularization, the retry when it cycles, how a claim of
    infeasibility is checked), given to the MPC as solver options, leave the optimum at the reference's."""
    sysm, net, problems, J = recorded
    mpc = MPC(sysm, net, EPS, backend="daqp", solver_options=daqp_options, **COMMON)
    for (z, R, prev), J_ref in zip(problems, J):
        for warm in (prev, None):
            mpc.reset()
            mpc.set_previous_plan(warm)
            s = mpc(z, R)
            assert s.status == "optimal" and not s.fallback, (daqp_options, s.message)
            assert abs(s.objective - J_ref) <= 1e-6 * max(1.0, abs(J_ref)), (daqp_options, s.objective, J_ref)


def test_clone_keeps_or_refuses_to_drop_the_options():
    """A clone changes what it is given and keeps the rest: keywords on keywords merge; keywords on an MPC built with
    ``options=`` would drop those options, so they raise; ``options=`` replaces them."""
    sysm = fl.quad1d()
    net, _ = test_net("quad1d-8x8")
    kw = MPC(sysm, net, EPS, screening=False, **COMMON).clone(warm_start=False)
    assert kw.options.screening is False and kw.options.warm_start is False
    built = MPC(sysm, net, EPS, options=MPCOptions(bounds="lp"), **COMMON)
    with pytest.raises(ValueError, match="options=MPCOptions"):
        built.clone(warm_start=False)
    again = built.clone(options=MPCOptions(bounds="lp", warm_start=False))
    assert again.options.bounds == "lp" and again.options.warm_start is False
    assert built.clone(time_limit=0.5).options == built.options


def test_the_steps_near_the_bound_encoded_first_leave_the_optimum(monkeypatch):
    """Encoding from the first round the steps where the incumbent is near the bound (``NEAR_ACTIVE``) changes how
    many rounds a step takes, never its result: on random states of the Quad-1D (N_p = 10) the status and the
    optimum are those without it, and it saves rounds on some state (the premise)."""
    import flnotes.mpc.engine as engine

    sysm, net, eps, kw = _small_quad(horizon=10)
    near, plain = MPC(sysm, net, eps, **kw), MPC(sysm, net, eps, **kw)
    rounds = {"near": 0, "plain": 0}
    checked = 0
    for z0, zr in _random_problems(40, horizon=10):
        near.reset()
        plain.reset()
        s = near(z0, zr)
        with monkeypatch.context() as m:
            m.setattr(engine, "NEAR_ACTIVE", None)
            r = plain(z0, zr)
        assert s.status == r.status, (s.message, r.message)
        if r.status == "optimal" and not r.screened:
            checked += 1
            assert abs(s.objective - r.objective) <= 1e-6 * max(1.0, abs(r.objective)), (s.objective, r.objective)
            assert near.plan_feasible(s.z_pred, s.v_pred)
            rounds["near"] += s.rounds
            rounds["plain"] += r.rounds
    assert checked >= 5, "the premise: states where the network constraint is active"
    assert rounds["near"] < rounds["plain"], f"the premise: the near steps save rounds ({rounds})"


@pytest.mark.parametrize("bad", [-0.1, 1.0, float("nan"), True, "0.02"])
def test_a_near_share_outside_zero_one_is_refused(monkeypatch, bad):
    """``NEAR_ACTIVE`` is None or a share in [0, 1): anything else is refused by name at the first solve that uses
    it, never read as 'every step' or 'none'."""
    import flnotes.mpc.engine as engine

    sysm, net, eps, kw = _small_quad(horizon=10)
    mpc = MPC(sysm, net, eps, **kw)
    monkeypatch.setattr(engine, "NEAR_ACTIVE", bad)
    with pytest.raises(ValueError, match="NEAR_ACTIVE must be None or a share"):
        for z0, zr in _random_problems(40, horizon=10):
            mpc.reset()
            mpc(z0, zr)
