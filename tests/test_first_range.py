"""Step 0's network constraint as the exact range of the first input (``flnotes.mpc.engine.FIRST_RANGE``).

At the measured state ``z(0) = z0`` is known, so for one input the set ``{v(0) : |Phi_NN(z0, v(0))| <= u_max^eps}`` is
exact (chapter 6's 1-D method); where it is one interval ``[a, b]`` the engine writes step 0 as the bounds
``a <= v(0) <= b`` (no neuron, no binary), cuts the relaxation and the reachable boxes by it, and must return the
same verdict and optimum as with step 0 encoded.
"""
import numpy as np
import pytest

import flnotes as fl
from flnotes.mpc import MPC
from flnotes.mpc import engine
from flnotes.mpc.prediction import Prediction
from flnotes.mpc.program import compact_program
from flnotes.solvers import BOUND_TOL
from flnotes.studies import compare as C
from flnotes.tightening import EmptyBoxError, horizon_boxes


@pytest.fixture(scope="module", params=["MSD", "Quad-1D"])
def setting(request):
    """A book system with its shipped network and certified eps (chapter 11's settings, no time limit)."""
    return C.setting(request.param, time_limit=None)


def _mpc(s, **kw):
    return MPC(s["system"], s["net"], s["eps"], horizon=s["horizon"], ts=s["ts"], Q=s["Q"], R=s["R"], **kw)


def _states(s, n, seed):
    sysm = s["system"]
    return np.random.default_rng(seed).uniform(sysm.lo[: sysm.n_z], sysm.hi[: sysm.n_z], (n, sysm.n_z))


def test_the_first_range_is_the_exact_admissible_set_of_the_first_input(setting):
    """Every v(0) of [a, b] meets |Phi_NN(z0, v)| <= u_max^eps by the forward pass (its ends included), every
    other input of the box breaks it (a dense grid and the points just outside the ends), and [a, b] is the one
    interval of :func:`flnotes.exact_1d_feasible_set`."""
    pred = _mpc(setting).pred
    u = float(pred.u_eps[0])
    lo, hi = float(pred.v_lo[0]), float(pred.v_hi[0])
    grid = np.linspace(lo, hi, 4001)
    found = 0
    for z in _states(setting, 60, 0):
        fr = pred.first_range(z, pred.u_eps)
        iv = fl.exact_1d_feasible_set(pred.net, z, lo, hi, u)
        if fr is None:
            assert iv.shape[0] != 1
            continue
        found += 1
        a, b = float(fr[0][0]), float(fr[1][0])
        assert lo <= a <= b <= hi
        assert np.allclose(iv, [[a, b]], rtol=0, atol=1e-9)
        out = np.abs(pred.net(np.c_[np.repeat(z[None], grid.size + 2, 0), np.r_[grid, a, b]])[:, 0])
        inside = (np.r_[grid, a, b] >= a) & (np.r_[grid, a, b] <= b)
        assert np.all(out[inside] <= u + BOUND_TOL)       # the ends included, to the forward pass's round-off
        assert np.all(out[~inside] > u)
        step = 1e-7 * (hi - lo)
        for v in (a - step, b + step):
            if lo <= v <= hi:
                assert abs(pred.net(np.r_[z, v])[0]) > u
    assert found >= 40, "the premise: the set is one interval at most states"


def test_the_first_range_is_none_for_several_inputs_several_intervals_or_no_admissible_input():
    """Two inputs: the admissible set is a union of polygons, no range (step 0 stays encoded). One input: a network
    with ``Phi_NN(z, v) = |v| - 1.5`` admits ``1 <= |v| <= 2`` at ``u_max^eps = 0.5``, two intervals: no range; and
    on the Quad-1D a state where no input is admissible: no range."""
    s = fl.two_link_arm()
    net, eps, _ = fl.arm_net()
    pred = MPC(s, net, eps, horizon=2, ts=0.05, Q=np.ones(4), R=0.01 * np.ones(2), backend="scip").pred
    assert pred.first_range(np.zeros(4), pred.u_eps) is None
    absv = fl.ReLUNet([[[0.0, 1.0], [0.0, -1.0]], [[1.0, 1.0]]], [[0.0, 0.0], [-1.5]])
    one = Prediction(absv, [[1.0]], [[0.1]], 3, [[1.0]], [[1.0]], [[1.0]], z_lo=np.array([-5.0]),
                     z_hi=np.array([5.0]), v_lo=np.array([-4.0]), v_hi=np.array([4.0]), u_eps=np.array([0.5]))
    assert np.allclose(fl.exact_1d_feasible_set(absv, np.zeros(1), -4.0, 4.0, 0.5), [[-2.0, -1.0], [1.0, 2.0]])
    assert one.first_range(np.zeros(1), one.u_eps) is None
    assert np.allclose(np.r_[one.first_range(np.zeros(1), [2.0])], [-3.5, 3.5])    # |v| <= 3.5: one interval
    q = C.setting("Quad-1D", time_limit=None)
    qp = _mpc(q).pred
    empty = 0
    for z in _states(q, 40, 3):
        if fl.exact_1d_feasible_set(qp.net, z, qp.v_lo[0], qp.v_hi[0], float(qp.u_eps[0])).shape[0] == 0:
            empty += 1
            assert qp.first_range(z, qp.u_eps) is None
    assert empty, "the premise: a state without an admissible input"


def test_horizon_boxes_with_a_first_range_contain_every_trajectory_that_starts_in_it():
    """``first=(a, b)``: row 0's input is [a, b], every simulated admissible trajectory with v(0) in [a, b] lies in
    the boxes, which lie within those without it; ``first`` = the input box gives the boxes without it exactly."""
    s = fl.quad1d()
    Ad, Bd = s.discretize(0.1, "rk4")
    z0 = np.array([-0.5, -0.15, -0.2])
    z_lo, z_hi, v_lo, v_hi = s.lo[:3], s.hi[:3], s.lo[3:], s.hi[3:]
    N = 10
    base = horizon_boxes(Ad, Bd, z0, z_lo, z_hi, v_lo, v_hi, N)
    same = horizon_boxes(Ad, Bd, z0, z_lo, z_hi, v_lo, v_hi, N, first=(v_lo, v_hi))
    assert np.array_equal(base[0], same[0]) and np.array_equal(base[1], same[1])
    a, b = v_lo + 0.6 * (v_hi - v_lo), v_lo + 0.8 * (v_hi - v_lo)
    lo, hi = horizon_boxes(Ad, Bd, z0, z_lo, z_hi, v_lo, v_hi, N, first=(a, b))
    assert np.allclose(lo[0, 3:], a) and np.allclose(hi[0, 3:], b)
    assert np.all(lo >= base[0] - 1e-12) and np.all(hi <= base[1] + 1e-12)
    assert np.any(hi[1:, :3] - lo[1:, :3] < base[1][1:, :3] - base[0][1:, :3] - 1e-9), "the range cuts later boxes"
    rng = np.random.default_rng(0)
    kept = 0
    for _ in range(3000):
        V = rng.uniform(v_lo, v_hi, (N, 1))
        V[0] = rng.uniform(a, b) if rng.random() < 0.8 else rng.choice([a[0], b[0]])
        Z = [z0]
        for k in range(N - 1):
            Z.append(Ad @ Z[-1] + Bd @ V[k])
        Z = np.array(Z)
        if np.any(Z < z_lo) or np.any(Z > z_hi):
            continue
        kept += 1
        X = np.hstack([Z, V])
        assert np.all(X >= lo - 1e-9) and np.all(X <= hi + 1e-9)
    assert kept > 500


def test_horizon_boxes_refuse_a_first_range_outside_the_input_box_or_of_the_wrong_shape():
    s = fl.quad1d()
    Ad, Bd = s.discretize(0.1, "rk4")
    args = (Ad, Bd, np.zeros(3), s.lo[:3], s.hi[:3], s.lo[3:], s.hi[3:], 5)
    with pytest.raises(EmptyBoxError, match="first input's range"):
        horizon_boxes(*args, first=(s.hi[3:] + 1.0, s.hi[3:] + 2.0))
    with pytest.raises(ValueError, match="first's a"):
        horizon_boxes(*args, first=(np.zeros(2), np.ones(2)))
    with pytest.raises(ValueError, match="first's b"):
        horizon_boxes(*args, first=(np.zeros(1), np.array([np.nan])))
    for not_a_pair in ((np.zeros(1), np.ones(1), "junk"), (np.zeros(1), np.ones(1), np.ones(1)), (np.zeros(1),), 0.5):
        with pytest.raises(ValueError, match="first must be a pair"):
            horizon_boxes(*args, first=not_a_pair)
    with pytest.raises(ValueError, match="needs a <= b"):
        horizon_boxes(*args, first=(np.ones(1), -np.ones(1)))


def test_the_first_range_ends_are_the_exact_methods_where_the_output_touches_the_bound():
    """A bound equal to ``|Phi_NN(z0, v*)|`` at many ``v*`` (the output touches the bound): the range's ends are those of
    :func:`flnotes.exact_1d_feasible_set` (not moved inward by the check's round-off), and each ``v*`` lies within
    round-off (1e-12 of the input box's scale) of ``[a, b]``."""
    net = fl.ReLUNet([np.array([[0.3, 0.7], [-0.2, 1.3]]), np.array([[0.9, -0.4]])],
                     [np.array([0.05, -0.11]), np.array([0.137])])
    z0 = np.array([0.41])
    pred = Prediction(net, np.eye(1), np.ones((1, 1)), 2, np.eye(1), np.eye(1), np.eye(1), z_lo=-3 * np.ones(1),
                      z_hi=3 * np.ones(1), v_lo=np.array([-2.0]), v_hi=np.array([2.0]), u_eps=np.array([1.0]))
    seen = 0
    for v_star in np.linspace(-2.0, 2.0, 801):
        u = float(abs(net(np.r_[z0, v_star])[0]))
        if u <= 0.0:
            continue
        fr = pred.first_range(z0, [u])
        iv = fl.exact_1d_feasible_set(net, z0, -2.0, 2.0, u)
        if iv.shape[0] != 1:
            assert fr is None
            continue
        seen += 1
        assert fr is not None and (fr[0][0], fr[1][0]) == (iv[0, 0], iv[0, 1])
        tol = 1e-12 * 2.0  # the round-off of a root (an affine piece's zero) on the input box [-2, 2]
        assert fr[0][0] - tol <= v_star <= fr[1][0] + tol
    assert seen > 100


def test_a_program_with_the_first_range_bounds_v0_and_refuses_step_0_among_the_encoded_steps(setting):
    mpc = _mpc(setting)
    pred, eng = mpc.pred, mpc.solver
    z = _states(setting, 1, 5)[0]
    zr = np.zeros((pred.N + 1, pred.nz))
    prob = eng.program(z, zr, steps=[1, 2])
    f, c0 = pred.linear(z, zr)
    a, b = np.array([-0.25]), np.array([0.5])
    nb = fl.fbbt(pred.net, *pred.boxes(z))
    with_range = compact_program(pred, z, f, c0, nb, [1, 2], pred.u_eps, first=(a, b))
    assert with_range.lb[0] == max(a[0], pred.v_lo[0]) and with_range.ub[0] == min(b[0], pred.v_hi[0])
    assert with_range.n == prob.n and with_range.n_integer == prob.n_integer
    with pytest.raises(ValueError, match="leave 0 out of steps"):
        compact_program(pred, z, f, c0, nb, [0, 1], pred.u_eps, first=(a, b))


def test_step_0_as_its_exact_range_leaves_every_verdict_and_optimum(setting, monkeypatch):
    """The default engine with and without the first range on random cold states: the same status at each (infeasible
    ones included), the same optimum within 1e-6, every optimal plan passes the forward-pass check; with it, no program
    encodes step 0's neurons where the range exists, and it exists in some program (the premise)."""
    n = fl.scale(40, 12)
    with_r, without = _mpc(setting), _mpc(setting)
    built = []
    real = engine.compact_program

    def spy(*args, **kw):
        built.append((list(args[5]), kw.get("first")))
        return real(*args, **kw)

    checked = 0
    sysm = setting["system"]
    rng = np.random.default_rng(7)
    for z in _states(setting, n, 1):
        zr = np.zeros((setting["horizon"] + 1, sysm.n_z))
        zr[:, 0] = rng.uniform(sysm.lo[0], sysm.hi[0])
        with_r.reset()
        without.reset()
        with monkeypatch.context() as m:
            m.setattr(engine, "compact_program", spy)
            s = with_r(z, zr)
        with monkeypatch.context() as m:
            m.setattr(engine, "FIRST_RANGE", False)
            r = without(z, zr)
        assert s.status == r.status, (s.message, r.message)
        if r.status == "optimal":
            assert abs(s.objective - r.objective) <= 1e-6 * max(1.0, abs(r.objective)), (s.objective, r.objective)
            assert with_r.plan_feasible(s.z_pred, s.v_pred)
            checked += not r.screened
    assert checked >= 3, "the premise: states where the network constraint is active"
    assert all(0 not in steps for steps, first in built if first is not None)
    assert any(first is not None for _, first in built), "the premise: step 0 written as its range"


@pytest.mark.parametrize("bad", [1, 0, None, "yes", 1.0])
def test_a_first_range_switch_that_is_not_a_flag_is_refused(monkeypatch, bad):
    q = C.setting("Quad-1D", time_limit=None)
    mpc = _mpc(q)
    monkeypatch.setattr(engine, "FIRST_RANGE", bad)
    with pytest.raises(ValueError, match="FIRST_RANGE must be True or False"):
        for z in _states(q, 40, 2):
            mpc.reset()
            mpc(z, np.zeros((q["horizon"] + 1, q["system"].n_z)))


def test_a_first_range_that_no_plan_can_keep_makes_the_step_infeasible_as_without_it(monkeypatch):
    """At the lower face of the state box, keeping ``z(1)`` in the box needs ``v(0) >= 0``, while the network
    ``Phi_NN(z, v) = v + u_max^eps + 1e-3`` admits only ``v(0) <= -1e-3``: the relaxation with the first range is
    infeasible, and the step says so, with the verdict found without the range (SCIP on the encoded program)."""
    u_max, eps = 1.0, 0.5
    net = fl.ReLUNet([np.array([[0.0, 1.0]]), np.array([[1.0]])],
                     [np.array([10.0]), np.array([(u_max - eps) + 1e-3 - 10.0])])
    sysm = fl.integrators([1], [-1.0, -2.0], [1.0, 2.0], u_max)
    z0, zr = np.array([-1.0]), np.full((4, 1), -1.0)
    # no affine enclosure: this network is affine there, so its slab alone would already make the relaxation infeasible
    kw = dict(horizon=3, ts=0.1, Q=[1.0], R=0.01, atlas=False, enclosure=False)
    r = MPC(sysm, net, eps, **kw)(z0, zr)
    assert r.status == "infeasible" and "exact admissible range" in r.message, r.message
    with monkeypatch.context() as m:
        m.setattr(engine, "FIRST_RANGE", False)
        r0 = MPC(sysm, net, eps, **kw)(z0, zr)
    assert r0.status == "infeasible" and "exact admissible range" not in r0.message, r0.message
