"""Exact means exact: proven optima, no false infeasibility, |Phi_NN| <= u_max^eps in floating point, safe fallbacks.

A seeded subset of the randomized harness of ``make bench`` (:mod:`flnotes.bench.exactness`): states drawn all
over the domain box, not only along the book's closed loops, every back-end against the exact 1-D method (CLF-CBF)
or a cold SCIP solve with every step encoded (MPC), and the states where a back-end was once wrong.
"""
import numpy as np
import pytest

import flnotes as fl
from flnotes.bench import exactness as ex
from flnotes.control import ClfCbfController, DistanceCBF, QuadraticCLF, exact_1d_feasible_set
from flnotes.solvers import BOUND_TOL, BOX_TOL, MIQP, make_solver
from flnotes.mpc import MPC

S = fl.paper.MSD_SETTING
QS = fl.paper.QUAD_SETTING


@pytest.fixture(scope="module")
def msd():
    net, _ = fl.paper_net("MSD")
    eps = float(np.max(fl.paper.paper_eps("MSD").upper))
    return fl.msd(), net, eps


def controller(msd, cost, backend, **kw):
    sysm, net, eps = msd
    return ClfCbfController(sysm, net, eps, QuadraticCLF(S["P"]), DistanceCBF(S["z_o"], S["r_o"]),
                            lambda z: -S["K_nominal"] @ z, cost=cost, backend=backend, beta=S["beta"],
                            kappa=S["kappa"], **kw)


def rel(a, b):
    return abs(a - b) / max(1.0, abs(b))


def check_against_exact(ctrl, exact, states):
    """Every 'optimal' equals the exact optimum, no false infeasibility, the bound holds in floating point."""
    rows = ex.clf_rows(ctrl, [(z, "") for z in states], exact)
    for z, r in zip(states, rows):
        assert not r["wrong_optimum"] and not r["below_reference"], (z, r)
        assert not r["false_infeasible"], (z, r)
        assert r["excess"] <= BOUND_TOL, (z, r)
    return rows


# --------------------------------------------------------------------------- CLF-CBF, diverse states
@pytest.mark.parametrize("cost, backend", [("linear", "highs"), ("linear", "scip"), ("linear", "daqp"),
                                           ("quadratic", "scip"), ("quadratic", "daqp")])
def test_clf_cbf_backends_are_exact_on_diverse_states(msd, cost, backend):
    states = [z for z, _ in ex.clf_states(msd[0], 40, seed=4)]
    ctrl = controller(msd, cost, backend, screening=False)  # the branch and bound at every state
    rows = check_against_exact(ctrl, controller(msd, cost, "exact"), states)
    assert sum(r["status"] == "optimal" for r in rows) >= 10  # the comparison is not vacuous


def test_boundary_optima_are_reported_optimal(msd):
    """States where the Lcost optimum lies exactly on |Phi_NN| = u_max^eps (the HiGHS misclassification)."""
    exact = controller(msd, "linear", "exact")
    rng = np.random.default_rng(12)
    cand = rng.uniform(msd[0].lo[:2], msd[0].hi[:2], (400, 2))
    on_bound = []
    for z in cand:
        r = exact.step(z)
        if r.status == "optimal" and abs(abs(r.info["phi_nn"][0]) - exact.u_eps[0]) <= 1e-9:
            on_bound.append(z)
        if len(on_bound) == 12:
            break
    assert len(on_bound) >= 8, "too few states with the optimum on the network bound"
    for backend in ("highs", "scip", "daqp"):
        ctrl = controller(msd, "linear", backend, screening=False)
        rows = check_against_exact(ctrl, exact, on_bound)
        assert all(r["status"] == "optimal" for r in rows), backend


# States (book's MSD network, eps = 0.21868) where a back-end once returned a wrong "optimal": HiGHS with
# presolve off (the first two) and on (the third); DAQP's exit flag 4 on Qcost (the last two).
WRONG_ONCE = {"linear": [[-1.3642336744490144, 3.9327733021625093], [-3.6566633167137064, 0.3403245883470474],
                         [-0.13211926, 0.45102298]],
              "quadratic": [[2.9728323560432965, -0.7450474284879753], [4.925854048373906, -1.258157258491818]]}


@pytest.mark.parametrize("cost", ["linear", "quadratic"])
def test_states_where_a_solver_was_wrong(msd, cost):
    states = [np.array(z) for z in WRONG_ONCE[cost]]
    exact = controller(msd, cost, "exact")
    for backend in (("highs", "scip", "daqp") if cost == "linear" else ("scip", "daqp")):
        check_against_exact(controller(msd, cost, backend, screening=False), exact, states)
    # DAQP without the regularization (its proximal iterations, exit flag 4): verified, never trusted
    daqp = controller(msd, cost, "daqp", screening=False, solver_options=dict(reg=None))
    rows = check_against_exact(daqp, exact, states)
    assert all(r["status"] == "optimal" for r in rows)


def test_softened_program_is_exact(msd):
    """The softened Lcost program of the fallback (DAQP was 3.7x above its optimum at this state)."""
    z = np.array([1.205209986953884, 1.5324538782546444])
    exact = controller(msd, "linear", "exact")
    d = exact.program_data(z)
    ref = exact._impl.solve(z, d, soft=True)
    for backend in ("daqp", "scip", "highs"):
        c = controller(msd, "linear", backend)
        sol = c._impl.solve(z, c.program_data(z), soft=True)
        assert sol.status == "optimal" and rel(sol.objective, ref.objective) <= 1e-6, (backend, sol, ref)


def test_daqp_exit_flag_4_is_not_a_proof():
    """DAQP's proximal iterations end with flag 4: the result is verified (by SCIP), and says so."""
    rng = np.random.default_rng(0)
    n = 6
    H = np.diag(np.r_[np.ones(3), np.zeros(3)])  # singular: zero on the binaries' block
    A = np.hstack([rng.normal(size=(4, 3)), -3 * np.eye(4)[:, :3]])
    p = MIQP(H, rng.normal(size=n), 0.0, A, np.full(4, -np.inf), np.ones(4), np.r_[-2 * np.ones(3), np.zeros(3)],
             np.r_[2 * np.ones(3), np.ones(3)], np.r_[np.zeros(3), np.ones(3)].astype(int))
    ref = make_solver(p, "scip").solve(gap=1e-9)
    for opts in (dict(reg=None), {}):
        r = make_solver(p, "daqp", **opts).solve()
        assert r.status == "optimal" and rel(r.objective, ref.objective) <= 1e-6, (opts, r, ref)
        assert "exitflag 1" in r.message or r.message.startswith("optimal, proven by scip"), r.message


def test_clf_cbf_step_outside_the_box_raises_like_mpc(msd):
    ctrl = controller(msd, "linear", "exact")
    with pytest.raises(ValueError, match="outside the network's trained domain"):
        ctrl.step(np.array([0.0, 5.5]))
    z_face = np.array([0.0, 5.0 + 0.5 * BOX_TOL])  # on the face up to round-off: accepted
    assert ctrl.step(z_face).status in ("optimal", "infeasible")


# --------------------------------------------------------------------------- MPC
@pytest.fixture(scope="module")
def quad():
    from flnotes.bench.mpc import quad_setup

    return quad_setup()


@pytest.fixture(scope="module")
def quad5():
    """The book's MPC with a horizon of 5 (a cold reference solve in seconds)."""
    from flnotes.bench.mpc import quad_setup

    return quad_setup(horizon=5)


def book_mpc(setup, **kw):
    return MPC(setup["system"], setup["net"], setup["eps"], horizon=setup["N"], ts=setup["ts"], Q=QS["Q"],
               R=QS["R"], **kw)


def test_mpc_is_exact_on_diverse_states(quad5):
    """The default MPC (cold and warm-started) against cold SCIP with every step encoded, on seeded diverse states."""
    cases = ex.mpc_cases(quad5, 12, seed=3)
    refs = ex.mpc_reference(quad5, cases)
    assert sum(r.status == "optimal" for r in refs) >= 2
    for warm in (False, True):
        rows = ex.mpc_controller_rows(quad5, cases, refs, "default", warm)
        for c, r in zip(cases, rows):
            assert not r["wrong_optimum"] and not r["false_infeasible"], (c, r)
            assert r["excess"] <= BOUND_TOL or (r["fallback"] and r["status"] == "infeasible"), (c, r)


def test_state_on_the_face_of_the_box_is_not_infeasible(quad5):
    """z2 = -5 - 5e-10 is the state z2 = -5 (one tolerance for the box, flnotes.solvers.BOX_TOL)."""
    mpc = book_mpc(quad5)
    ref = np.array([4.443496973836615, 0.0, 0.0])
    z = np.array([1.95917156728804, -5.0, 4.761859723150327])
    a = mpc(z + np.array([0.0, -5e-10, 0.0]), ref)
    mpc.reset()
    b = mpc(z, ref)
    assert a.status == b.status and a.fallback == b.fallback
    assert rel(a.objective, b.objective) <= 1e-6  # the requested gap


def test_time_limit_fallback_applies_an_admissible_input(quad):
    """A perturbed successor under a tight time limit: the applied v meets the network bound whenever some v does."""
    mpc = book_mpc(quad)
    z0, ref = np.array(QS["z0"]), np.array([1.5, 0.0, 0.0])
    first = mpc(z0, ref)
    assert first.status == "optimal"
    mpc.time_limit = 1e-3
    checked = 0
    for dz3 in (0.6, -0.6, 1.2):
        z1 = np.clip(first.z_pred[1] + np.array([0.0, 0.0, dz3]), -5, 5)
        mpc.set_previous_plan((first.z_pred, first.v_pred))
        st = mpc(z1, ref)
        iv = exact_1d_feasible_set(mpc.net, z1, float(mpc.v_lo[0]), float(mpc.v_hi[0]), float(mpc.u_eps[0]))
        if len(iv):
            checked += 1
            assert st.input_admissible and abs(mpc.net(np.r_[z1, st.v])[0]) <= mpc.u_eps[0] + BOUND_TOL, st.message
        else:
            assert st.fallback and not st.input_admissible
    assert checked >= 1


def test_objection_clause_names_what_took_longer_than_t_s():
    from flnotes.bench.exactness import objection_clause

    quiet = objection_clause(dict(cpu_over_ts=0, steps=60), dict(cold_ms_max=80.0), ts_ms=100.0)
    assert quiet == dict(objection_clause="in this build even the report's longer horizon and the cold states drawn all "
                                          "over the box stayed within the sampling period, which a slower machine can change")
    loop = ("on the report's longer horizon, 2 of the 60 steps of the loop used more than the sampling period of CPU "
            "time")
    cold = "cold states drawn all over the box took up to 250 ms"
    assert objection_clause(dict(cpu_over_ts=2, steps=60), dict(cold_ms_max=80.0), 100.0)["objection_clause"] == (
        "not all of it: " + loop)
    assert objection_clause(dict(cpu_over_ts=0, steps=60), dict(cold_ms_max=250.4), 100.0)["objection_clause"] == (
        "not all of it: " + cold)
    assert objection_clause(dict(cpu_over_ts=2, steps=60), dict(cold_ms_max=250.4), 100.0)["objection_clause"] == (
        "not all of it: " + loop + ", and " + cold)
