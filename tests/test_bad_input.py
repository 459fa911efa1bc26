"""Bad input is never swallowed: each call a new user might get wrong raises a clear error naming the argument.

Every network here has explicit weights (no training), so no premise depends on the machine.
"""
from __future__ import annotations

import collections
import dataclasses
import datetime
import importlib.util
import math
from decimal import Decimal
from fractions import Fraction
import re

import cvxpy as cp
import numpy as np
import pytest

import flnotes as fl
from flnotes import interval as iv


def _identity_net(system: fl.FLSystem) -> fl.ReLUNet:
    """A network with known weights: Phi_NN(z, v) = v + z_1 (relu(y) - relu(-y) for y = v + z_1)."""
    w = np.zeros(system.n_in)
    w[0], w[-1] = 1.0, 1.0
    return fl.ReLUNet([np.vstack([w, -w]), np.array([[1.0, -1.0]])], [np.zeros(2), np.zeros(1)])


def _random_net(n_in: int, widths=(6,), n_out: int = 1, seed: int = 0) -> fl.ReLUNet:
    rng = np.random.default_rng(seed)
    sizes = [n_in, *widths, n_out]
    return fl.ReLUNet([rng.normal(size=(b, a)) for a, b in zip(sizes[:-1], sizes[1:])],
                      [rng.normal(size=b) * 0.1 for b in sizes[1:]])


class _NetController:
    """A controller that carries a network (as ClfCbfController and MPC do): v = -z_1 - z_2."""

    def __init__(self, net, v=None):
        self.net, self.v = net, v

    def step(self, z, t, reference=None):
        v = np.array([-z[0] - z[1]]) if self.v is None else np.array([self.v])
        return fl.StepResult(v=v, status="optimal")


class _Spy(_NetController):
    """Records the times at which the simulation called the controller."""

    def __init__(self, net):
        super().__init__(net)
        self.calls = []

    def step(self, z, t, reference=None):
        self.calls.append(t)
        return super().step(z, t, reference)


@pytest.fixture(scope="module")
def msd():
    sysm = fl.msd()
    return sysm, _identity_net(sysm)


# --------------------------------------------------------------------------- item 1: start outside the box
@pytest.mark.parametrize("kw, name", [(dict(z0=[0.0, 6.0]), "z0"), (dict(x0=[-5.5, 0.0]), "x0")])
def test_simulate_start_outside_the_domain_box_raises_before_the_first_step(msd, kw, name):
    sysm, net = msd
    spy = _Spy(net)

    with pytest.raises(ValueError, match=rf"{name} = .* outside the domain box") as err:
        fl.simulate(sysm, spy, t_final=0.2, ts=0.1, **kw)
    assert "lo = [-5. -5.]" in str(err.value) and "hi = [5. 5.]" in str(err.value)
    assert spy.calls == []  # raised before the first step


def test_simulate_start_outside_the_box_with_a_real_controller(msd):
    sysm, net = msd
    S = fl.paper.MSD_SETTING
    ctrl = fl.ClfCbfController(sysm, net, 0.5, fl.QuadraticCLF(S["P"]), None, lambda z: -S["K_nominal"] @ z,
                               cost="quadratic", backend="exact")
    with pytest.raises(ValueError, match=r"z0 = \[0. 6.\] is outside the domain box"):
        fl.simulate(sysm, ctrl, t_final=0.2, ts=0.1, z0=[0.0, 6.0])


def test_a_plain_law_may_run_outside_the_box_and_the_check_can_be_switched(msd):
    """The box is where the network is trusted: a plain k(z) runs anywhere, a network controller with opt-out."""
    sysm, net = msd
    K = fl.paper.MSD_SETTING["K_nominal"]
    log = fl.simulate(sysm, lambda z: -K @ z, t_final=0.2, ts=0.1, z0=[0.0, 6.0])
    assert log.n_steps == 2 and not log.in_domain[0]
    log = fl.simulate(sysm, _NetController(net), t_final=0.2, ts=0.1, z0=[0.0, 6.0], check_domain=False)
    assert log.n_steps == 2
    with pytest.raises(ValueError, match="z0 = .* outside the domain box"):
        fl.simulate(sysm, lambda z: -K @ z, t_final=0.2, ts=0.1, z0=[0.0, 6.0], check_domain=True)


def test_leaving_the_box_during_the_run_stops_it_with_a_message(msd):
    sysm, net = msd
    log = fl.simulate(sysm, _NetController(net, v=30.0), t_final=2.0, ts=0.1, z0=[0.0, 4.0])
    assert "left the domain box" in log.message and log.message.startswith("stopped at t =")
    assert log.n_steps < 20
    assert log.in_domain[:-1].all() and not log.in_domain[-1]


# --------------------------------------------------------------------------- item 2: ClfCbfController.step outside
def test_clf_cbf_step_outside_the_domain_raises_like_mpc(msd):
    sysm, net = msd
    S = fl.paper.MSD_SETTING
    ctrl = fl.ClfCbfController(sysm, net, 0.5, fl.QuadraticCLF(S["P"]), None, lambda z: -S["K_nominal"] @ z,
                               cost="quadratic", backend="exact")
    mpc = fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1)
    z = np.array([0.0, 6.0])
    with pytest.raises(ValueError, match="z = .* is outside") as e_mpc:
        mpc(z, np.zeros(2))
    with pytest.raises(ValueError, match="z = .* is outside") as e_ctrl:
        ctrl.step(z)
    assert "trained domain" in str(e_mpc.value) and "trained domain" in str(e_ctrl.value)


@pytest.mark.parametrize("lo, hi, match", [
    (-1000.0, 1000.0, "leaves the network's domain"),
    (-10.0, 10.0 + 1e-6, "leaves the network's domain"),
    (-10.0 - 1e-6, 0.0, "leaves the network's domain"),
    (1.0, 1.0, "empty or a point"),
    (2.0, -2.0, "empty or a point"),
])
def test_a_v_box_outside_the_domain_or_empty_is_refused_by_both_controllers(msd, lo, hi, match):
    """eps holds on the domain box only (the MSD's |v| <= 10): a v-box that leaves it would let the controller use the
    network where it extrapolates, so both controllers refuse it; a box inside the domain, up to its faces, is kept."""
    sysm, net = msd
    S = fl.paper.MSD_SETTING
    assert np.array_equal(sysm.lo[2:], [-10.0]) and np.array_equal(sysm.hi[2:], [10.0])  # the premise
    kw = dict(cost="quadratic", backend="exact")
    with pytest.raises(ValueError, match=match):
        fl.ClfCbfController(sysm, net, 0.5, fl.QuadraticCLF(S["P"]), None, lambda z: -S["K_nominal"] @ z,
                            v_lo=[lo], v_hi=[hi], **kw)
    with pytest.raises(ValueError, match=match):
        fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1, v_box=([lo], [hi]))
    ctrl = fl.ClfCbfController(sysm, net, 0.5, fl.QuadraticCLF(S["P"]), None, lambda z: -S["K_nominal"] @ z,
                               v_lo=[-10.0], v_hi=[2.0], **kw)
    mpc = fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1, v_box=([-10.0], [2.0]))
    assert ctrl.v_hi[0] == 2.0 and mpc.v_hi[0] == 2.0
    assert ctrl.step(np.array([1.0, 0.0])).v[0] <= 2.0 and mpc(np.array([1.0, 0.0]), np.zeros(2)).v[0] <= 2.0


def test_a_v_box_just_outside_the_domain_is_named_with_its_excess(msd):
    """The message says which bound leaves the domain and by how much (the arrays alone print the same numbers)."""
    sysm, net = msd
    with pytest.raises(ValueError, match=r"v_box\[1\]\[0\] = 10.0000000001 lies 1e-10 beyond the domain's face 10.0"):
        fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1, v_box=([-10.0], [10.0 + 1e-10]))
    with pytest.raises(ValueError, match="must be numbers"):
        fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1, v_box=("-1", "1"))


def test_the_controllers_keep_their_own_copy_of_the_v_box(msd):
    """A box checked at construction stays the box: changing the caller's arrays afterwards changes nothing (the MPC
    kept them, and a later step applied v = -13.6 outside the domain |v| <= 10)."""
    sysm, net = msd
    S = fl.paper.MSD_SETTING
    lo, hi = np.array([-5.0]), np.array([5.0])
    mpc = fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1, v_box=(lo, hi))
    ctrl = fl.ClfCbfController(sysm, net, 0.5, fl.QuadraticCLF(S["P"]), None, lambda z: -S["K_nominal"] @ z,
                               cost="quadratic", backend="exact", v_lo=lo, v_hi=hi)
    lo[0], hi[0] = -50.0, 50.0
    assert mpc.v_lo[0] == ctrl.v_lo[0] == -5.0 and mpc.v_hi[0] == ctrl.v_hi[0] == 5.0
    res = mpc(np.array([4.0, 4.0]), np.zeros(2))
    assert res.v is not None and -5.0 - 1e-9 <= res.v[0] <= 5.0 + 1e-9, res.v  # the box to the solvers' round-off


@pytest.mark.parametrize("v_box", [(-5.0, 5.0, 7.0), (-5.0,), "ab", 3.0, {0: -1.0, 1: 1.0}, {-1.0, 1.0}])
def test_a_v_box_that_is_not_a_pair_is_refused(msd, v_box):
    sysm, net = msd
    with pytest.raises(ValueError, match="v_box must be a pair"):
        fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1, v_box=v_box)


@pytest.mark.parametrize("kw", [dict(v_box=(-20.0, 20.0)), dict(z_box=([-20.0, -20.0], [20.0, 20.0])),
                                dict(v_box=(-5.0, 5.0, 1.0))])
def test_a_terminal_set_box_outside_the_domain_is_refused(msd, kw):
    """The terminal set's boxes are the MPC's constraints near the origin: they must lie in the domain too."""
    sysm, net = msd
    with pytest.raises(ValueError, match="leaves the network's domain|must be a pair"):
        fl.terminal_set(sysm, net, 0.5, 0.1, np.diag([10.0, 1.0]), np.array([[0.1]]), **kw)


# --------------------------------------------------------------------------- item 3: MPC solver availability
@pytest.mark.skipif(importlib.util.find_spec("gurobipy") is not None, reason="gurobipy is installed here")
def test_mpc_with_a_missing_solver_fails_at_construction(msd):
    sysm, net = msd
    with pytest.raises((ImportError, ValueError), match="gurobi"):
        fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1, backend="gurobi")


# --------------------------------------------------------------------------- item 4: reference
@pytest.mark.parametrize("reference, exc, match", [
    (lambda t: np.zeros(3), ValueError, r"reference returned shape \(3,\)"),
    (lambda t: np.zeros((np.size(t), 3)), ValueError, r"reference returned shape \(1, 3\)"),
    (lambda t: np.zeros((2, np.size(t))), ValueError, "reference returned shape"),
    (lambda t: np.full((np.size(t), 2), np.nan), ValueError, "reference returned NaN"),
    (lambda t: np.array([math.sin(t), 0.0]), ValueError, "reference must accept .* array of times"),
    (np.zeros(2), TypeError, "reference must be a function"),
])
def test_simulate_rejects_a_bad_reference_before_the_first_step(msd, reference, exc, match):
    sysm, net = msd
    spy = _Spy(net)

    with pytest.raises(exc, match=match):
        fl.simulate(sysm, spy, t_final=0.3, ts=0.1, z0=[0.0, 1.0], reference=reference)
    assert spy.calls == []


def test_simulate_accepts_vectorized_and_constant_references(msd):
    sysm, net = msd
    for ref in (lambda t: np.zeros((np.size(t), 2)), lambda t: np.array([1.0, 0.0]),
                fl.sine_reference(n_z=2)):
        assert fl.simulate(sysm, _NetController(net), t_final=0.3, ts=0.1, z0=[0.0, 1.0], reference=ref).n_steps == 3


# --------------------------------------------------------------------------- item 5: controller errors
@pytest.mark.parametrize("exc", [ValueError("z has the wrong shape"), TypeError("unsupported operand"),
                                 ImportError("No module named 'gurobipy'"), AttributeError("no attribute 'L'")])
def test_simulate_raises_the_controllers_programming_errors(msd, exc):
    sysm, _ = msd

    class Broken:
        def step(self, z, t, reference=None):
            raise exc

    with pytest.raises(type(exc), match=str(exc).replace("(", r"\(").replace(")", r"\)")):
        fl.simulate(sysm, Broken(), t_final=0.3, ts=0.1, z0=[0.0, 1.0], fallback=lambda z: np.zeros(1))


def test_simulate_falls_back_only_on_a_solver_failure_and_says_so(msd):
    sysm, _ = msd

    class Infeasible:
        def step(self, z, t, reference=None):
            raise fl.SolverFailure(f"no admissible v at t = {t:.1f}", status="infeasible")

    log = fl.simulate(sysm, Infeasible(), t_final=0.3, ts=0.1, z0=[0.0, 1.0], fallback=lambda z: np.zeros(1))
    assert log.fallback.all() and all(s == "error" for s in log.status)
    assert all("SolverFailure: no admissible v" in st.message for st in log.steps)
    assert all(st.info["solver_status"] == "infeasible" for st in log.steps)


def test_simulate_checks_what_the_controller_returns(msd):
    sysm, _ = msd

    class ReturnsArray:
        def step(self, z, t, reference=None):
            return np.zeros(1)

    with pytest.raises(TypeError, match="must return a flnotes.StepResult"):
        fl.simulate(sysm, ReturnsArray(), t_final=0.3, ts=0.1, z0=[0.0, 1.0])
    with pytest.raises(ValueError, match=r"the controller's v at t = 0.000 s must have shape \(1,\)"):
        fl.simulate(sysm, lambda z: np.zeros(2), t_final=0.3, ts=0.1, z0=[0.0, 1.0])


# --------------------------------------------------------------------------- item 6: phi_interval is checked
def _typo(z, v):  # the MSD map with a typo: 2 z_1 instead of z_1
    return v + iv.stribeck(z[:, 1:2]) + 2.0 * z[:, 0:1]


def test_certify_error_refuses_a_phi_interval_that_does_not_enclose_phi(msd):
    sysm, net = msd
    bad = dataclasses.replace(sysm, phi_interval=_typo)
    with pytest.raises(ValueError, match="phi_interval of MSD does not enclose Phi"):
        fl.certify_error(bad, net, n_samples=500)
    with pytest.raises(ValueError, match="f_interval does not enclose Phi"):
        fl.certify_error(sysm, net, f_interval=lambda X: _typo(X[:, :2], X[:, 2:]), n_samples=500)


def test_certify_error_refuses_a_phi_interval_wrong_only_on_a_small_region():
    """Right at every sample point of a coarse look, wrong near one spot: the small random boxes see it."""
    net = _random_net(1, seed=1)

    def phi(X):
        return np.sin(3.0 * X)

    def wrong(X):  # sin(3x) everywhere, but its enclosure is shifted up by 0.5 on boxes right of 0.2
        y = iv.sin(3.0 * X)
        shift = np.where(X.lo > 0.2, 0.5, 0.0)
        return iv.Interval(y.lo + shift, y.hi + shift, y.dlo, y.dhi)

    with pytest.raises(ValueError, match="f_interval does not enclose Phi"):
        fl.certify_error(phi, net, [-1.0], [1.0], f_interval=wrong, n_samples=200)


def test_certify_error_refuses_too_small_lipschitz_constants():
    net = _random_net(1, seed=2)
    with pytest.raises(ValueError, match="lipschitz is too small"):
        fl.certify_error(lambda X: np.sin(3.0 * X), net, [-1.0], [1.0], lipschitz=1.0, n_samples=500)


# --------------------------------------------------------------------------- item 7: network of the wrong size
def test_certify_error_names_a_network_of_the_wrong_input_size():
    sysm = fl.quad1d()
    with pytest.raises(ValueError, match=r"net has 3 inputs .* the box of Quad-1D has 4 dimensions"):
        fl.certify_error(sysm, _random_net(3))
    with pytest.raises(ValueError, match=r"net has 3 inputs, the box .* has 4 dimensions"):
        fl.certify_error(lambda X: X[:, :1], _random_net(3), np.zeros(4), np.ones(4))
    with pytest.raises(ValueError,
                       match=r"net has 3 inputs but the box lo, hi has 4 dimensions: lo and hi must have shape \(3,\)"):
        fl.fbbt(_random_net(3), np.zeros(4), np.ones(4))


# --------------------------------------------------------------------------- item 8: encode's bounds
def test_encode_names_bounds_of_the_wrong_kind():
    net = _random_net(3)
    with pytest.raises(TypeError, match=r"bounds must be a flnotes.NodeBounds, e.g. bounds=fl.fbbt\(net, lo, hi\)"):
        fl.encode(net, cp.Variable(3), np.zeros(3))
    with pytest.raises(TypeError, match="x must be a cvxpy expression"):
        fl.encode(net, np.zeros(3), fl.fbbt(net, -np.ones(3), np.ones(3)))
    with pytest.raises(TypeError, match="bounds must be a flnotes.NodeBounds"):
        fl.bigm_form(net, (np.zeros(6), np.ones(6)))
    with pytest.raises(ValueError, match="either bounds= or L= and U="):
        fl.encode(net, cp.Variable(3), fl.fbbt(net, -np.ones(3), np.ones(3)), L=[np.zeros(6)], U=[np.ones(6)])
    with pytest.raises(ValueError, match="bounds hold 1 layers but the network has 2 hidden layers"):
        fl.encode(_random_net(3, (4, 4)), cp.Variable(3), fl.fbbt(net, -np.ones(3), np.ones(3)))


# --------------------------------------------------------------------------- item 9: R of the MPC
def test_mpc_says_r_must_be_positive_definite(msd):
    sysm, net = msd
    with pytest.raises(ValueError, match="R must be .*positive definite") as err:
        fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, Q=[10.0, 1.0], R=-0.1)
    assert "semidefinite" not in str(err.value)


# --------------------------------------------------------------------------- more: simulate, FLSystem, interval
@pytest.mark.parametrize("kw, exc, match", [
    (dict(controller=np.ones((1, 2))), TypeError, "controller must be"),
    (dict(system="msd"), TypeError, "system must be a flnotes.FLSystem"),
    (dict(net=np.ones(3)), TypeError, "net must be a flnotes.ReLUNet"),
    (dict(net="wrong size"), ValueError, r"net maps R\^4 -> R\^1"),
    (dict(n_fine=0), ValueError, "n_fine must be an integer >= 1"),
    (dict(n_fine=2.5), ValueError, "n_fine must be an integer >= 1"),
    (dict(fallback=0.0), TypeError, "fallback must be a function"),
    (dict(ts="0.1"), ValueError, "ts must be a finite number > 0"),
    (dict(ts=np.timedelta64(1)), ValueError, "ts must be a finite number > 0"),
    (dict(t_final=True), ValueError, "t_final must be a finite number > 0"),
    (dict(ts=0.5), ValueError, r"need 0 < ts <= t_final"),
    (dict(rtol=0.0), ValueError, "rtol must be a finite number > 0"),
    (dict(atol="1e-9"), ValueError, "atol must be a finite number > 0"),
    (dict(z0=[0.0, np.nan]), ValueError, "z0 contains NaN"),
    (dict(z0=None, x0=[0.0, np.inf]), ValueError, "x0 contains NaN or inf"),
])
def test_simulate_bad_arguments(msd, kw, exc, match):
    sysm, net = msd
    args = dict(system=sysm, controller=lambda z: np.zeros(1), t_final=0.3, ts=0.1, z0=[0.0, 1.0])
    if isinstance(kw.get("net"), str):
        kw = dict(net=_random_net(4))
    args.update(kw)
    with pytest.raises(exc, match=match):
        fl.simulate(**args)


@pytest.mark.parametrize("bad, what", [(True, "booleans"), ("5", "strings"), ([5.0, True], "booleans"),
                                       ((5.0, "1"), "strings"), (np.array(["5"]), "strings"), (5 + 0j, "complex"),
                                       ([5.0, 1j], "complex"), (np.datetime64("2020"), "dates"),
                                       ([np.str_("5")], "strings"), ([np.complex128(5)], "complex"),
                                       (bytearray(b"5"), "bytes"), (collections.deque([True, 5.0]), "booleans"),
                                       (np.array([np.complex64(5 + 1j)], dtype=object), "complex"),
                                       ([5.0, np.datetime64(1, "s")], "dates"), ([datetime.timedelta(1)], "time spans"),
                                       ([np.array(True)], "booleans"), ([bytearray(b"5")], "bytes"),
                                       (np.array([np.array("5")], dtype=object), "strings"),
                                       ([10 ** 400], "too large"), (np.longdouble("1e400"), "overflow"),
                                       ([Decimal("1e400")], "too large"), (np.ma.masked, "masked"),
                                       ([5.0, None], "None"), ([[[[[[[[[[[[True]]]]]]]]]]]], "booleans"),
                                       (np.array(["5"], dtype=np.dtypes.StringDType()), "strings"),
                                       (range(10 ** 12), "MemoryError")])
def test_numbers_are_never_read_from_booleans_strings_or_complex_numbers(msd, bad, what):
    """numpy turns ``True``, ``"5"``, ``[5.0, True]`` and ``5 + 0j`` into floats without a word; the package's
    checks refuse them and name the argument (here the bound of a system, the MPC's eps and a start state)."""
    sysm, net = msd
    with pytest.raises(ValueError, match=f"u_max must be numbers .*{what}"):
        fl.integrators([1], [-1.0, -1.0], [1.0, 1.0], bad)
    with pytest.raises(ValueError, match=f"eps must be numbers .*{what}"):
        fl.MPC(sysm, net, bad, horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1)
    with pytest.raises(ValueError, match=f"z0 must be numbers .*{what}"):
        fl.simulate(sysm, lambda z: np.zeros(1), t_final=0.3, ts=0.1, z0=bad)
    assert fl.integrators([1], [-1.0, -1.0], [1.0, 1.0], [np.float32(5)]).u_max[0] == 5.0  # numbers of any kind pass


@pytest.mark.parametrize("bad", [True, "1", 1j, [1.0, True]])
def test_every_numeric_entry_point_refuses_what_is_no_real_number(msd, bad):
    """The weights, the measured state and reference of a step, the CLF-CBF's gains, slack weights and limits, the
    start of a simulation and what a feedback law returns, the boxes of the bound computations and the network's
    weights: each refuses a boolean, a string or a complex number with a message that names it."""
    sysm, net = msd
    kw = dict(horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1)
    two = bad if np.ndim(bad) == 1 else [bad, 0.0]  # the value in a vector of two
    one = bad[-1] if np.ndim(bad) == 1 else bad  # a value on its own (True of [1.0, True])
    mpc = fl.MPC(sysm, net, 0.5, **kw)
    V, H = fl.QuadraticCLF(np.eye(2)), fl.DistanceCBF([3.0, 0.0], 0.5)
    calls = {"Q": lambda: fl.MPC(sysm, net, 0.5, **{**kw, "Q": bad}),
             "R": lambda: fl.MPC(sysm, net, 0.5, **{**kw, "R": bad}),
             "z": lambda: mpc(two, np.zeros(2)),
             "z_ref": lambda: mpc(np.zeros(2), two),
             "beta": lambda: fl.ClfCbfController(sysm, net, 0.5, V, H, beta=bad),
             "penalty": lambda: fl.ClfCbfController(sysm, net, 0.5, V, H, penalty=(1e6, bad)),
             "gap": lambda: fl.ClfCbfController(sysm, net, 0.5, V, H, gap=bad),
             "time_limit": lambda: fl.ClfCbfController(sysm, net, 0.5, V, H, time_limit=bad),
             "x0": lambda: fl.simulate(sysm, lambda z: np.zeros(1), t_final=0.2, ts=0.1, z0=None, x0=two),
             "the feedback law's v": lambda: fl.simulate(sysm, lambda z: bad, t_final=0.2, ts=0.1, z0=[0.0, 0.0]),
             "lo": lambda: fl.fbbt(net, [one, -1.0, -1.0], [1.0, 1.0, 1.0]),
             "W^1": lambda: fl.ReLUNet([[[one]], [[1.0]]], [[0.0], [0.0]])}
    for name, call in calls.items():
        with pytest.raises(ValueError, match=re.escape(name) + " must be"):
            call()


@pytest.mark.parametrize("bad", [10 ** 400, Fraction(1, 10 ** 400), Decimal("sNaN"), np.timedelta64(3), True, "1",
                                 np.array([1.0])])
def test_a_scalar_setting_is_a_finite_real_number_of_its_kind(msd, bad):
    """A positive setting refuses numbers beyond the float range, a positive number that is 0.0 as a float, a
    signalling NaN, a time span, a boolean, a string and an array, naming the setting; any finite real number of
    another type (a Fraction, a Decimal, a 0-d array) is that number."""
    sysm, net = msd
    V, H = fl.QuadraticCLF(np.eye(2)), fl.DistanceCBF([3.0, 0.0], 0.5)
    with pytest.raises(ValueError, match="beta must be a finite number > 0"):
        fl.ClfCbfController(sysm, net, 0.5, V, H, beta=bad)
    for good in (Fraction(1, 1000), Decimal("0.001"), np.array(0.001), np.float32(0.001)):
        assert fl.ClfCbfController(sysm, net, 0.5, V, H, beta=good).beta == float(good)


def test_numbers_in_any_container_numpy_reads_are_taken_as_they_are(msd):
    """The check of numbers changes no real input: a buffer of floats, an array.array, an object with ``__array__``,
    Fractions and Decimals, numpy scalars in a tuple give the network's and the bounds' results of the plain array."""
    import array

    class Wrapped:
        def __init__(self, a):
            self.a = a

        def __array__(self, dtype=None, copy=None):
            return np.asarray(self.a, dtype)

    sysm, net = msd
    X = np.array([0.3, -0.2, 1.5])
    for x in (memoryview(X.copy()), Wrapped(X), array.array("d", X), [Fraction(3, 10), Decimal("-0.2"), 1.5],
              tuple(np.float32(v) for v in (0.5, -0.25, 1.5)), np.asfortranarray(X[None])):
        assert np.array_equal(net(x), net(np.asarray(x, float))), type(x)
    lo, hi = np.array([-1.0, -1.0, -2.0]), np.array([1.0, 1.0, 2.0])
    b = fl.fbbt(net, memoryview(lo.copy()), Wrapped(hi))
    assert np.array_equal(b.out_L, fl.fbbt(net, lo, hi).out_L)


class _ArrayOf:
    """An object whose ``__array__`` gives ``a`` as it is (a masked array, booleans, or no array at all)."""

    def __init__(self, a):
        self.a = a

    def __array__(self, dtype=None, copy=None):
        return self.a


def test_bytes_and_masks_behind_a_protocol_are_refused(msd):
    """numpy reads a memoryview of bytes as its characters' codes and drops the mask of a masked array given by an
    object's ``__array__``: both are refused by name, while a memoryview of a uint8 array and an ``__array__`` that
    gives a plain (or unmasked) array are their numbers."""
    sysm, net = msd
    X = np.array([0.3, -0.2, 1.5])
    with pytest.raises(ValueError, match="x must be numbers .*memory.*bytes"):
        net(memoryview(b"123"))
    with pytest.raises(ValueError, match="x must be numbers .*bytes"):
        net(memoryview(bytearray(b"123")))
    with pytest.raises(ValueError, match="x must be numbers .*masked"):
        net(_ArrayOf(np.ma.masked_array(X, [False, True, False])))
    assert np.array_equal(net(_ArrayOf(np.ma.masked_array(X, [False, False, False]))), net(X))
    u8 = np.array([1, 2, 3], np.uint8)
    assert np.array_equal(net(memoryview(u8)), net(u8.astype(float)))


def test_what_hides_inside_a_list_is_judged_as_an_argument_of_its_own(msd):
    """Inside a list, a memoryview of bytes, an ``__array__`` object giving a masked array or booleans, and another
    kind of sequence holding a boolean are refused as they are on their own; an ``__array__`` that gives no array
    and a memory map of text are refused; the same containers of real numbers are their numbers."""
    import collections
    import mmap

    sysm, net = msd
    mm = mmap.mmap(-1, 3)
    mm.write(b"123")
    bad = [([memoryview(b"123")], "bytes"), ([_ArrayOf(np.ma.masked_array([0.3, -0.2, 1.5], [0, 1, 0]))], "masked"),
           ([collections.UserList([0.3, True, 1.5])], "booleans"), ([_ArrayOf(np.array([True, False, True]))], "booleans"),
           (_ArrayOf([0.3, -0.2, 1.5]), "gives no array"), (_ArrayOf(_ArrayOf(np.zeros(3))), "gives no array"),
           (mm, "bytes"), (memoryview(mm), "bytes"), ([mm], "bytes")]
    for x, what in bad:
        with pytest.raises(ValueError, match=f"x must be numbers .*{what}"):
            net(x)
    X = np.array([[0.3, -0.2, 1.5]])
    for x in ([_ArrayOf(X[0])], [collections.UserList(X[0].tolist())], [memoryview(X[0].copy())]):
        assert np.array_equal(net(x), net(X)), x


def test_a_number_like_object_is_read_once_and_a_missing_pandas_value_is_refused(msd):
    """An object numpy reads as one element (``__float__`` or ``__index__`` only) is its number, at the top and in
    a list (it used to send the check into a loop); a set, a dict or a generator is refused by numpy's own reason; a
    memoryview of bytes cast to doubles is its floats; a pandas NA (which numpy reads as NaN) is refused."""
    class FloatLike:
        def __float__(self):
            return 0.3

    class IndexLike:
        def __index__(self):
            return 2

    sysm, net = msd
    X = np.array([[0.3, 2.0, 0.3]])
    assert np.array_equal(net([FloatLike(), IndexLike(), FloatLike()]), net(X[0]))
    for bad in ({0.3, 2.0, 1.0}, {0: 0.3}, (v for v in X[0])):
        with pytest.raises(ValueError, match=f"x must be numbers .*TypeError: float.*{type(bad).__name__}"):
            net(bad)
    doubles = memoryview(bytearray(X[0].tobytes())).cast("d")
    assert np.array_equal(net(doubles), net(X[0]))
    pd = pytest.importorskip("pandas")
    with pytest.raises(ValueError, match="x must be numbers .*pandas NA"):
        net(pd.Series([0.3, None, 0.3], dtype="Float64"))
    with pytest.raises(ValueError, match="x must be numbers .*pandas NA"):
        net([pd.array([0.3, 2.0, None], dtype="Float64")])
    assert np.array_equal(net(pd.Series(X[0], dtype="Float64")), net(X[0]))


def test_a_number_is_no_state_of_several_coordinates(msd_mpc):
    """Where a state is expected, a single number is refused (it used to be read as the same value in every
    coordinate); a one-state system still takes a number."""
    mpc = msd_mpc
    sysm = mpc.system
    for call in (lambda: mpc.fallback_plan(1.0), lambda: mpc.safe_input(1.0, 0.0),
                 lambda: mpc.predict(1.0, np.zeros((mpc.N, 1))),
                 lambda: fl.simulate(sysm, lambda z: np.zeros(1), t_final=0.1, ts=0.1, z0=0.5),
                 lambda: sysm.linearized_rhs(0.5, 0.0)):
        with pytest.raises(ValueError, match=r"must have shape \(2,\) \(one state"):
            call()
    assert np.array_equal(mpc.predict([0.5, 0.5], np.zeros((mpc.N, 1))), mpc.predict(np.full(2, 0.5),
                                                                                   np.zeros(mpc.N)))
    one = fl.integrators([1], [-1.0, -1.0], [1.0, 1.0], [1.0])
    assert np.array_equal(one.linearized_rhs(0.5, 0.0), one.linearized_rhs([0.5], [0.0]))


def test_a_bad_box_of_a_batch_is_named_by_its_row(msd):
    """In a batch of boxes, the first empty or non-finite box is named by its row."""
    sysm, net = msd
    lo, hi = -np.ones((3, 3)), np.ones((3, 3))
    lo[2, 1] = 2.0
    with pytest.raises(ValueError, match=r"box is empty: lo\[2\]\[1\] = 2.0 > hi\[2\]\[1\]"):
        fl.fbbt(net, lo, hi)
    lo[2, 1], hi[1, 0] = -1.0, np.inf
    with pytest.raises(ValueError, match=r"hi\[1\] contains NaN or inf"):
        fl.fbbt(net, lo, hi)


@pytest.mark.parametrize("key, match", [("ts", "ts must be"), ("time_limit", "time_limit must be"),
                                        ("horizon", "horizon"), ("gap", "gap must be")])
def test_the_mpc_settings_refuse_a_time_span(msd, key, match):
    """numpy counts a time span as an integer: the MPC's sampling time, time limit, horizon and gap refuse it."""
    sysm, net = msd
    kw = dict(horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1)
    with pytest.raises(ValueError, match=match):
        fl.MPC(sysm, net, 0.5, **{**kw, key: np.timedelta64(1)})
    assert fl.MPC(sysm, net, 0.5, **{**kw, "ts": Fraction(1, 10)}).ts == 0.1  # a Fraction is a number


def test_the_mpc_and_simulate_take_any_real_number_for_their_settings(msd):
    """A Fraction, a Decimal, a 0-d array or an integral float is the number it holds, in the MPC's horizon, sampling
    time, time limit and gap and in simulate's times; a horizon that is no integer is refused, naming it."""
    sysm, net = msd
    kw = dict(ts=0.1, Q=[10.0, 1.0], R=0.1)
    for h in (Decimal(3), np.array(3), 3.0, Fraction(3), np.int64(3)):
        mpc = fl.MPC(sysm, net, 0.5, horizon=h, time_limit=Decimal("0.5"), gap=Fraction(1, 10 ** 6), **kw)
        assert (mpc.N, mpc.time_limit, mpc.gap) == (3, 0.5, 1e-6) and type(mpc.N) is int
    for bad in (2.5, Fraction(5, 2), np.array(2.5), 0, True):
        with pytest.raises(ValueError, match=r"horizon \(N_p\) must be"):
            fl.MPC(sysm, net, 0.5, horizon=bad, **kw)
    with pytest.raises(ValueError, match=r"gap must be a relative optimality gap in \[0, 1\)"):
        fl.MPC(sysm, net, 0.5, horizon=3, gap=Decimal(1), **kw)
    law = lambda z: np.zeros(1)  # noqa: E731
    plain = fl.simulate(sysm, law, t_final=0.3, ts=0.1, z0=[0.0, 1.0])
    for ts, tf in ((Fraction(1, 10), Decimal("0.3")), (np.array(0.1), np.float32(0.3))):
        run = fl.simulate(sysm, law, t_final=tf, ts=ts, z0=[0.0, 1.0])
        assert np.allclose(run.t, plain.t) and np.allclose(run.z, plain.z, atol=1e-6)


@pytest.mark.parametrize("field, match", [("phi", "phi must be a function"), ("f", "f must be a function"),
                                          ("to_z", "to_z must be a function"),
                                          ("phi_interval", "phi_interval must be a function")])
def test_flsystem_names_a_field_that_is_not_a_function(field, match):
    with pytest.raises(TypeError, match=match):
        dataclasses.replace(fl.msd(), **{field: np.zeros(3)})


@pytest.mark.parametrize("call, exc, match", [
    (lambda: iv.sqrt(iv.Interval(-1.0, 4.0)), iv.NotCertifiable, "sqrt of an interval reaching below 0"),
    (lambda: iv.log(iv.Interval(0.0, 4.0)), iv.NotCertifiable, "log of an interval reaching 0 or below"),
    (lambda: 1.0 / iv.Interval(-1.0, 2.0), iv.NotCertifiable, "division by an interval that contains 0"),
    (lambda: iv.tan(iv.Interval(1.0, 2.0)), iv.NotCertifiable, r"tan .* pole"),
    (lambda: iv.Interval(2.0, 1.0), ValueError, "lower bound must be <= its upper bound"),
    (lambda: iv.Interval(0.0, 1.0) ** 0.5, iv.NotCertifiable, "integer powers"),
])
def test_interval_domain_errors_are_clear(call, exc, match):
    with pytest.raises(exc, match=match):
        call()


def test_fit_relu_with_a_system_instead_of_a_function_names_f():
    s = fl.msd()
    with pytest.raises(TypeError, match=r"f must be a function.*phi_stacked"):
        fl.fit_relu(s, s.lo, s.hi, widths=(3,), n_per_axis=3)


@pytest.mark.parametrize("kw, match", [
    (dict(widths=(20.5, 20)), "each of widths must be an integer >= 1"),
    (dict(widths=(True, 3)), "each of widths must be an integer >= 1"),
    (dict(widths=20), "widths must list the hidden widths"),
    (dict(widths="20"), "widths must list the hidden widths"),
    (dict(widths=()), "at least one hidden width"),
    (dict(n_per_axis=2.5), "n_per_axis must be an integer >= 2"),
    (dict(n_per_axis=[3, 3]), "n_per_axis must be an integer >= 2, or one per axis"),
    (dict(max_iter=0), "max_iter must be an integer >= 1"),
    (dict(threads=1.5), "threads must be an integer >= 1"),
    (dict(alpha=-1.0), "alpha must be a finite number >= 0"),
    (dict(f=lambda X: X[:5, :1]), r"f must map the grid .* got shape \(5, 1\)"),
    (dict(f=lambda X: X[:, :1] > 0), "f\\(X\\) on the training grid must be numbers .*booleans"),
])
def test_fit_relu_names_a_setting_that_means_nothing(kw, match):
    """``int(20.5)`` is 20 and ``int(True)`` is 1: a width, a grid size or a training setting that is no count of its
    kind is refused with its name, before any training; so is an ``f`` whose values are not one per grid point."""
    args = dict(f=lambda X: np.sin(X[:, :1]), lo=[-1.0, -1.0, -1.0], hi=[1.0, 1.0, 1.0], widths=(3,), n_per_axis=3)
    args.update(kw)
    with pytest.raises(ValueError, match=match):
        fl.fit_relu(**args)


@pytest.mark.parametrize("call, match", [
    (lambda: fl.DistanceCBF([3.0, 0.0], True), "r_o must be a finite number > 0"),
    (lambda: fl.DistanceCBF([3.0, 0.0], "0.5"), "r_o must be a finite number > 0"),
    (lambda: fl.DistanceCBF([3.0, 0.0], 0.0), "r_o must be a finite number > 0"),
    (lambda: fl.DistanceCBF([3.0, np.nan], 0.5), "z_o must be the centre"),
    (lambda: fl.DistanceCBF(["3", 0.0], 0.5), "z_o must be numbers .*strings"),
    (lambda: fl.AffineCBF([1.0, 0.0], np.nan), "d must be a finite number"),
    (lambda: fl.AffineCBF([1.0, True], 1.0), "c must be numbers .*booleans"),
    (lambda: fl.QuadraticCLF([[1.0, 0.0], [0.0, np.inf]]), "P contains NaN or inf"),
    (lambda: fl.QuadraticCLF(np.eye(2) + 0j), "P must be numbers .*complex"),
])
def test_certificates_name_their_bad_parameters(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_a_masked_entry_is_refused_not_read_as_the_value_it_hides(msd):
    """numpy reads a masked array without its mask: a masked entry would enter as the value it hides. Refused, named;
    a masked array without masked entries is its values."""
    sysm, net = msd
    z = np.ma.array([0.5, 9.0], mask=[False, True])
    with pytest.raises(ValueError, match="z0 must be numbers .*masked"):
        fl.simulate(sysm, lambda z: np.zeros(1), t_final=0.2, ts=0.1, z0=z)
    with pytest.raises(ValueError, match="beta must be a finite number"):
        fl.ClfCbfController(sysm, net, 0.5, fl.QuadraticCLF(np.eye(2)), fl.DistanceCBF([3.0, 0.0], 0.5),
                            beta=np.ma.array(0.1, mask=True))
    with pytest.raises(ValueError, match="lo must be numbers .*masked"):
        fl.fbbt(net, [np.ma.masked, -1.0, -1.0], [1.0, 1.0, 1.0])
    X = np.array([[0.3, -0.2, 1.5]])
    assert np.array_equal(net(np.ma.array(X, mask=False)), net(X))


def test_lipschitz_constants_are_numbers(msd):
    sysm, net = msd
    with pytest.raises(ValueError, match="lipschitz must be numbers .*strings"):
        fl.certify_error(sysm.phi_stacked, net, sysm.lo, sysm.hi, lipschitz=["1", 1.0, 1.0])


@pytest.mark.parametrize("bad", [True, "0.1", np.timedelta64(1), 0.0, np.nan])
def test_every_sampling_time_is_a_positive_real_number(msd, bad):
    """``np.isfinite(True) and True > 0`` holds: a boolean sampling time would be read as 1 s. Every function with a
    sampling or hold time refuses it, and a string or a time span, naming ``ts``."""
    sysm, net = msd
    calls = [lambda: sysm.discretize(bad), lambda: fl.intersample_drift(sysm, bad),
             lambda: fl.NonlinearMPC(sysm, horizon=3, ts=bad),
             lambda: fl.simulate(sysm, lambda z: np.zeros(1), t_final=0.3, ts=bad, z0=[0.0, 1.0]),
             lambda: fl.MPC(sysm, net, 0.5, horizon=3, ts=bad, Q=[10.0, 1.0], R=0.1)]
    for call in calls:
        with pytest.raises(ValueError, match="ts must be a finite number > 0"):
            call()


@pytest.mark.parametrize("key", ["horizon", "rk4_steps", "max_iter"])
def test_the_nonlinear_mpc_counts_are_integers(msd, key):
    sysm, _ = msd
    for bad in (2.5, True, "3", 0):
        with pytest.raises(ValueError, match=f"{re.escape(key)}.* must be"):
            fl.NonlinearMPC(sysm, **{"horizon": 3, "ts": 0.1, key: bad})


def _cases_that_gave_wrong_answers(sysm, net):
    """Calls that once ran on bad input and answered wrongly (unsound bounds, -inf, a hidden value, a truncated count):
    each is refused now, with the argument's name."""
    lo, hi = sysm.lo, sysm.hi
    mpc = fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, Q=[10.0, 1.0], R=0.1)
    Ad, Bd = sysm.discretize(0.1)
    nmpc = fl.NonlinearMPC(fl.quad1d(), horizon=3, ts=0.1)  # the MSD's to_z is not CasADi-ready
    hidden = np.ma.array(np.ones((4, 2)), mask=True)
    return [
        (lambda: fl.lp_bounds(net, lo, hi, tol=-0.5), "tol must be a finite number >= 0"),
        (lambda: fl.lp_bounds(net, lo, hi, tol=True), "tol must be"),
        (lambda: fl.lp_bounds(net, lo, hi, out_bounds=([-1.0], [True])), "out_bounds\\[1\\] must be numbers"),
        (lambda: fl.lp_bounds(net, lo, hi, out_bounds=([-1.0], [np.nan])), "out_bounds must be numbers"),
        (lambda: fl.lp_bounds(net, lo, hi, out_bounds=(["-1"], [1.0])), "out_bounds\\[0\\] must be numbers"),
        (lambda: fl.lp_bounds(net, lo, hi, out_bounds=([1.0], [-1.0])), "out_bounds is empty"),
        (lambda: fl.worst_violation(sysm, net, None, n_z=5, n_v=3), "eps must be"),
        (lambda: fl.worst_violation(sysm, net, np.nan, n_z=5, n_v=3), "eps must be a finite error bound"),
        (lambda: fl.worst_violation(sysm, net, -1.0, n_z=5, n_v=3), "eps must be a finite error bound"),
        (lambda: fl.worst_violation(sysm, net, True, n_z=5, n_v=3), "eps must be numbers .*booleans"),
        (lambda: fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, terminal=(np.array([["1", "0"]]), np.array(["1"]))),
         "terminal F must be numbers .*strings"),
        (lambda: fl.MPC(sysm, net, 0.5, horizon=3, ts=0.1, terminal=([[1.0, 0.0]], [True])),
         "terminal g must be numbers .*booleans"),
        (lambda: fl.horizon_boxes(Ad, Bd, [0, 0], [-5, -5], [5, 5], [-10], [10], True), "horizon must be"),
        (lambda: fl.horizon_boxes(Ad, Bd, [0, 0], [-5, -5], [5, 5], [-10], [10], 2.5), "horizon must be"),
        (lambda: sysm.grid(2.5), "n_per_axis must be an integer >= 2"),
        (lambda: sysm.grid("3"), "n_per_axis must be numbers .*strings"),
        (lambda: fl.MPC(sysm, net, 0.5, horizon=Decimal("2.99999999999999999999"), ts=0.1), "horizon \\(N_p\\) must"),
        (lambda: mpc.step(np.zeros(2), 0.0, reference=lambda t: hidden), "reference\\(t\\) must be numbers .*masked"),
        (lambda: fl.time_stats(np.ma.array([0.1, 99.0], mask=[0, 1])), "times_s must be numbers .*masked"),
        (lambda: fl.drift_curve(sysm, np.ma.array([0.1, 5.0], mask=[0, 1])), "ts_values must be numbers .*masked"),
        (lambda: fl.sine_reference(phase=1j), "phase must be a finite number"),
        (lambda: fl.sine_reference(n_z=True), "n_z must be an integer >= 1"),
        (lambda: nmpc.solve(np.zeros(3), np.zeros(3), u_guess=np.full(3, np.nan)), "u_guess must be finite"),
        (lambda: sysm.Phi(["1", "2"], "3"), "z must be numbers .*strings"),
        (lambda: sysm.Phi([0.0, 0.0], True), "v must be numbers .*booleans"),
        (lambda: fl.discretize([["0", "1"], ["0", "0"]], [[0.0], [1.0]], 0.1), "A must be numbers .*strings"),
        (lambda: fl.discretize(sysm.A, sysm.B, 1e300), "the discretized model overflows"),
        (lambda: fl.quad1d(Gamma=True), "Gamma must be a finite number > 0"),
        (lambda: fl.quad1d(tau=None), "tau must be a finite number > 0"),
        (lambda: fl.two_link_arm(m1=True), "m1 must be a finite number > 0"),
        (lambda: fl.two_link_arm(q1_box=True), "q1_box must be a finite number > 0"),
        (lambda: fl.arm.ArmPointCBF([0.5, 0.5], radius=True), "radius must be a finite number > 0"),
        (lambda: fl.interval_affine(np.eye(2), np.zeros(2), np.ones(2), np.zeros(2)), "l <= u"),
        (lambda: fl.forward_milp(net, [np.nan, 0.0, 0.0]), "x contains NaN"),
        (lambda: fl.sample_max_error(sysm, net, n=-5), "n must be an integer >= 1"),
        (lambda: fl.sample_max_error(sysm, net, n=True), "n must be an integer >= 1"),
        (lambda: fl.local_max_error(sysm, net, output=1, n_starts=1), "output must be an output of Phi"),
        (lambda: fl.local_max_error(sysm, net, output=-1, n_starts=1), "output must be an integer >= 0"),
        (lambda: fl.pso_max_error(sysm, net, n_iter=True), "n_iter must be an integer >= 1"),
        (lambda: fl.ClfCbfController(sysm, net, 0.5, fl.QuadraticCLF(np.eye(2)), fl.DistanceCBF([3.0, 0.0], 0.5),
                                     gap=5.0), "gap must be a relative optimality gap in \\[0, 1\\)"),
        (lambda: fl.simulate(sysm, lambda z: np.zeros(1), t_final=0.3, ts=1e-300, z0=[0.0, 1.0]), "MAX_STEPS"),
        (lambda: fl.fbbt(net, lo, hi, outward="no"), "outward must be True or False"),
        (lambda: fl.simulate(sysm, lambda z: np.zeros(1), t_final=0.3, ts=0.1, z0=[0.0, 1.0], progress="no"),
         "progress must be True or False"),
        (lambda: fl.NonlinearMPC(sysm, horizon=3, ts=0.1, warm_start="no"), "warm_start must be True or False"),
        (lambda: fl.intersample_drift(sysm, 0.1, admissible="no"), "admissible must be True or False"),
        (lambda: net.forward(np.array([["1", "2", "3"]])), "X must be numbers .*strings"),
        (lambda: fl.QuadraticCLF(np.eye(2))(["1", "2"]), "z must be numbers .*strings"),
    ]


def test_bad_input_that_once_gave_a_wrong_answer_is_refused_by_name(msd):
    sysm, net = msd
    for call, match in _cases_that_gave_wrong_answers(sysm, net):
        with pytest.raises(ValueError, match=match):
            call()


def test_a_masked_array_without_masked_entries_and_real_numbers_of_any_kind_still_pass(msd):
    sysm, net = msd
    lo, hi = sysm.lo, sysm.hi
    ref = fl.lp_bounds(net, lo, hi, out_bounds=(-np.array([4.5]), np.array([4.5])))
    for ob in ((Fraction(-9, 2), Decimal("4.5")), ([-4.5], np.ma.array([4.5], mask=False)), ([-4.5], (4.5,))):
        b = fl.lp_bounds(net, lo, hi, out_bounds=ob)
        assert all(np.array_equal(x, y) for x, y in zip(b.L + b.U, ref.L + ref.U))
    assert np.array_equal(sysm.grid(np.int64(3)), sysm.grid(3)) and sysm.grid(3).shape == (27, 3)
    assert fl.time_stats(np.ma.array([0.1, 0.2], mask=False))["n"] == 2
    assert fl.quad1d(Gamma=Fraction(10), tau=Decimal("0.2")).params == fl.quad1d().params


def test_a_certificate_that_is_nan_or_no_number_stops_the_clf_cbf_step(msd):
    """A NaN barrier value or gradient would drop its row from eq. (CLF_CBF), and the step would be reported optimal
    without it: refused, naming the certificate."""
    sysm, net = msd
    K, P = np.array([4.0, 3.0]), [[2.0, 0.5], [0.5, 1.0]]
    kw = dict(k=lambda z: -K @ z, cost="quadratic")
    ok = fl.ClfCbfController(sysm, net, 0.5, fl.QuadraticCLF(P), H=fl.DistanceCBF([3.0, 0.0], 1.0), **kw)
    assert ok.step([1.5, 1.5]).status == "optimal"
    for H, match in [((lambda z: np.nan, lambda z: np.array([1.0, 0.0])), r"H\(z\) must be a finite number"),
                     ((lambda z: 1.0, lambda z: np.array([np.nan, np.nan])), r"H.grad\(z\) must be a finite vector"),
                     ((lambda z: "1.5", lambda z: np.array([1.0, 0.0])), r"H\(z\) must be numbers .*strings"),
                     ((lambda z: 1.0, lambda z: [True, False]), r"H.grad\(z\) must be numbers .*booleans"),
                     ((lambda z: 1.0, lambda z: np.ones(3)), r"H.grad\(z\) must be a finite vector of shape \(2,\)")]:
        c = fl.ClfCbfController(sysm, net, 0.5, fl.QuadraticCLF(P), H=H, **kw)
        with pytest.raises(ValueError, match=match):
            c.step([1.5, 1.5])
    V = (lambda z: np.nan, lambda z: np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match=r"V\(z\) must be a finite number"):
        fl.ClfCbfController(sysm, net, 0.5, V, H=fl.DistanceCBF([3.0, 0.0], 1.0), **kw).step([1.5, 1.5])


def test_an_error_estimate_refuses_a_phi_that_is_nan_somewhere(msd):
    """NaN drops out of every max: the estimators would return -inf or NaN as eps, or skip the point."""
    sysm, net = msd

    def f(X):
        Y = sysm.phi_stacked(X).copy()
        Y[X[:, 0] > 0] = np.nan  # half the box: every estimator meets it
        return Y

    for call in (lambda: fl.sample_max_error(f, net, sysm.lo, sysm.hi, n=2000),
                 lambda: fl.grid_max_error(f, net, sysm.lo, sysm.hi, n_per_axis=7),
                 lambda: fl.pso_max_error(f, net, sysm.lo, sysm.hi, n_particles=10, n_iter=3),
                 lambda: fl.local_max_error(f, net, sysm.lo, sysm.hi, n_starts=3)):
        with pytest.raises(ValueError, match="Phi returned NaN or inf on the box"):
            call()
    with pytest.raises(ValueError, match=r"\(X\) must be numbers .*booleans"):
        fl.certify_error(lambda X: X[:, :1] > 0, net, sysm.lo, sysm.hi, lipschitz=100.0)


def test_checks_that_once_answered_yes_to_nan_or_an_infinite_tolerance(msd):
    import scipy.sparse as sp

    from flnotes import terminal as tm

    sysm, net = msd
    P = fl.MIQP(None, [1.0, 1.0], 0.0, sp.csr_matrix([[1.0, 1.0]]), [1.0], [np.inf], [0, 0], [5, 5], [0, 1])
    assert P.violation([np.nan, np.nan]) == np.inf and P.violation([np.nan, 7.5]) == np.inf
    assert P.violation([0.5, 1.0]) == 0.0
    C, d = np.vstack([np.eye(2), -np.eye(2)]), np.ones(4)
    with pytest.raises(ValueError, match="tol must be a finite number"):
        tm.max_admissible_set([[0.9, 0.1], [0.0, 0.8]], C, d, tol=np.inf)
    with pytest.raises(ValueError, match="tol must be a finite number"):
        tm.remove_redundant(C, d, tol=np.nan)
    h = fl.AffineCBF([1.0, 0.0], 2.0)
    assert fl.cbf_condition_fails(h, [[-5.0, -3.0]], sysm.A, sysm.B, 4.0).tolist() == [True]
    for kw, match in [(dict(tol=-1), "tol must be a finite number >= 0"), (dict(tol=np.nan), "tol must be"),
                      (dict(kappa=True), "kappa must be a finite number > 0")]:
        args = {**dict(H=h, Z=[[-5.0, -3.0]], A=sysm.A, B=sysm.B, kappa=4.0), **kw}
        with pytest.raises(ValueError, match=match):
            fl.cbf_condition_fails(**args)
    with pytest.raises(ValueError, match="Z must be finite"):
        fl.cbf_condition_fails(h, [[np.nan, -3.0]], sysm.A, sysm.B, 4.0)
    z = np.array([1.0, 0.0])
    with pytest.raises(ValueError, match="z contains NaN"):
        fl.exact_1d_feasible_set(net, [np.nan, 0.0], -10, 10, 4.0)
    with pytest.raises(ValueError, match="bound must be a finite number > 0"):
        fl.exact_1d_feasible_set(net, z, -10, 10, np.nan)
    pw = fl.network_pieces_1d(net, z, -10, 10)
    with pytest.raises(ValueError, match="v must lie in the segment"):
        pw(1000.0)
    assert np.isclose(pw(3.0), net([1.0, 0.0, 3.0])[0])
    with pytest.raises(ValueError, match="eps = .* must lie below u_max"):
        fl.worst_violation(sysm, net, 10.0, n_z=5, n_v=3)
    with pytest.raises(ValueError, match="rtol must be a finite number > 0"):
        sysm.input_map([0.0, 0.0], rtol=np.nan)
    nb = fl.fbbt(net, sysm.lo, sysm.hi)
    with pytest.raises(ValueError, match="bounds .* contain NaN"):
        fl.lp_bounds(net, [0, 0, 0], [1, 1, 1], prior=fl.NodeBounds([a * np.nan for a in nb.L], nb.U, nb.out_L,
                                                                    nb.out_U))
    with pytest.raises(TypeError, match="must be a flnotes.NodeBounds"):
        fl.lp_bounds(net, [0, 0, 0], [1, 1, 1], prior=(nb.L, nb.U))
    with pytest.raises(ValueError, match="L\\^1 <= U\\^1 must hold"):
        fl.propagate(net, [a * np.nan for a in nb.L], nb.U)
    with pytest.raises(ValueError, match=f"pre must hold {len(nb.L)} arrays"):
        nb.contains([])
    with pytest.raises(ValueError, match="delta = J_up - J_c must be a number >= 0"):
        fl.ellipsoid_box(np.eye(2), np.eye(2), np.zeros(2), np.zeros(2), np.nan)


def test_the_mpc_methods_check_the_plans_they_are_given(msd):
    sysm, net = msd
    mpc = fl.MPC(sysm, net, 0.5, horizon=5, ts=0.1, Q=[10.0, 1.0], R=0.01)
    V = np.zeros((5, 1))
    Z = mpc.predict([1.0, 0.5], V)
    assert mpc.plan_feasible(Z, V) in (True, False)
    Zbad = Z.copy()
    Zbad[2:] = 1e6  # the documented rule: the model's prediction from z_pred[0] is what is checked
    assert mpc.plan_feasible(Zbad, V) == mpc.plan_feasible(Z, V)
    with pytest.raises(ValueError, match="a plan is \\(z_pred, v_pred\\) of shapes"):
        mpc.plan_feasible(Z[:3], V)
    with pytest.raises(ValueError, match="a plan is \\(z_pred, v_pred\\) of shapes"):
        mpc.cost(np.vstack([Z, np.ones((3, 2))]), V, np.zeros(2))
    with pytest.raises(ValueError, match="must be finite"):
        mpc.set_previous_plan((np.zeros((6, 2)), np.full((5, 1), np.nan)))
    with pytest.raises(ValueError, match="v_pred must be numbers .*strings"):
        mpc.predict([1.0, 0.5], [["0"]] * 5)
    with pytest.raises(ValueError, match="t must be a finite number"):
        mpc.step([1.0, 0.5], True)
    with pytest.raises(TypeError, match="net must be a flnotes.ReLUNet"):
        fl.MPC(sysm, "net", 0.5)
    with pytest.raises(TypeError, match="system must be a flnotes.FLSystem"):
        fl.ClfCbfController(None, net, 0.5, fl.QuadraticCLF(np.eye(2)))
    assert np.isfinite(mpc.cost(Z, V, np.zeros(2)))


def test_the_lower_layers_read_no_booleans_or_strings_as_numbers(msd):
    """The solver layer, the atlas, the terminal set's settings, the network's transforms and the time table."""
    import scipy.sparse as sp

    sysm, net = msd
    A = sp.csr_matrix([[1.0, 1.0]])
    good = dict(H=None, c=[1.0, 1.0], c0=0.0, A=A, rl=[1.0], ru=[np.inf], lb=[0, 0], ub=[5, 5], integrality=[0, 1])
    assert fl.MIQP(**good).n == 2
    for kw, match in [(dict(c0="1"), "c0 must be a finite number"), (dict(c=["1", 1.0]), "c must be numbers"),
                      (dict(lb=[True, 0]), "lb must be numbers .*booleans"),
                      (dict(lb=[np.inf, 0], ub=[np.inf, 5]), "lb must be < \\+inf")]:
        with pytest.raises(ValueError, match=match):
            fl.MIQP(**{**good, **kw})
    solver = fl.solvers.make_solver(fl.MIQP(**good), "highs")
    for kw, match in [(dict(time_limit=True), "time_limit must be"), (dict(gap=True), "gap must be"),
                      (dict(warm_start=["1", "0"]), "warm_start must be numbers")]:
        with pytest.raises(ValueError, match=match):
            solver.solve(**kw)
    assert solver.solve().status == "optimal"
    with pytest.raises(ValueError, match="u must be numbers .*strings"):
        fl.bound_atlas(net, sysm.lo, sysm.hi, "4.79", (2, 2, 2))
    with pytest.raises(ValueError, match="each of cells must be an integer >= 1"):
        fl.bound_atlas(net, sysm.lo, sysm.hi, 4.5, (2, 2, 2.5))
    with pytest.raises(ValueError, match="x_scale must be numbers .*strings"):
        net.affine_wrapped(np.zeros(3), ["1", "1", "1"], 0.0, 1.0)
    with pytest.raises(ValueError, match="x_scale must be nonzero"):
        net.affine_wrapped(np.zeros(3), np.zeros(3), 0.0, 1.0)
    X = np.array([[0.3, -0.2, 1.5]])
    assert np.allclose(net.affine_wrapped(1.0, 2.0, 0.5, 3.0)(X), 0.5 + 3.0 * net((X - 1.0) / 2.0))
    for kw, match in [(dict(percentiles=(150,)), "percentiles must lie in \\[0, 100\\]"),
                      (dict(percentiles=(True,)), "percentiles must be numbers .*booleans")]:
        with pytest.raises(ValueError, match=match):
            fl.time_stats([0.1, 0.2], **kw)


def test_legitimate_input_of_other_forms_is_still_taken(msd):
    """Counts as integral reals, sequences as arrays or ranges, a flat plan of one input, one point through forward,
    a seed of None, one-element arrays where one number is meant, None times in a table."""
    sysm, net = msd
    mpc = fl.MPC(sysm, net, 0.5, horizon=4, ts=0.1, Q=[10.0, 1.0], R=0.01)
    V = np.full((4, 1), 0.01)
    Z = mpc.predict([0.5, 0.0], V)
    assert np.array_equal(mpc.predict([0.5, 0.0], V.ravel()), Z)
    assert mpc.cost(Z, V.ravel(), np.zeros(2)) == mpc.cost(Z, V, np.zeros(2))
    assert mpc.plan_feasible(Z, V.ravel()) == mpc.plan_feasible(Z, V)
    out, pre = net.forward(np.array([0.5, -1.0, 2.0]))
    assert out.shape == (1,) and pre[0].shape == (net.widths[0],)
    assert np.allclose(out, net([0.5, -1.0, 2.0]))
    a = fl.bound_atlas(net, sysm.lo, sysm.hi, 4.5, np.array([1, 2, 3]))
    b = fl.bound_atlas(net, sysm.lo, sysm.hi, 4.5, range(1, 4))
    assert all(np.array_equal(x, y) for x, y in zip(a.L, b.L))
    assert np.isfinite(fl.sample_max_error(sysm, net, n=50, seed=None).eps).all()
    assert fl.msd(u_max=np.array([5.0])).u_max.tolist() == [5.0]
    assert fl.QuadraticCLF([[2.0]])(3.0) == 18.0
    assert fl.time_stats([0.001, None, 0.002])["n"] == 2
    with pytest.raises(ValueError, match="times_s must be times >= 0"):
        fl.time_stats([-1.0, 0.001])


def test_a_certificate_of_several_values_and_bad_matrices_are_refused(msd):
    sysm, net = msd
    H1, H2 = fl.DistanceCBF([3.0, 0.0], 1.0), fl.DistanceCBF([2.8, 0.2], 0.5)
    both = (lambda z: np.array([H2(z), H1(z)]), H2.grad)
    c = fl.ClfCbfController(sysm, net, 0.5, fl.QuadraticCLF(np.eye(2)), both, lambda z: -z, cost="quadratic")
    with pytest.raises(ValueError, match=r"H\(z\) must be one number per state"):
        c.step([2.0, 0.9])
    A = sysm.A.copy()
    A[0, 1] = np.nan
    with pytest.raises(ValueError, match="A must be finite"):
        fl.cbf_condition_fails(H1, [[2.0, 1.0]], A, sysm.B, 4.0)
    with pytest.raises(ValueError, match="W, b and the box must be finite"):
        fl.interval_affine([[1.0, 0.0]], [0.0], [-np.inf, 0.0], [0.0, 1.0])
    with pytest.raises(ValueError, match="need W \\(p, n\\), b \\(p,\\)"):
        fl.interval_affine(np.eye(2), [5.0], [0.0, 0.0], [1.0, 1.0])
    lo, hi = sysm.lo, sysm.hi
    with pytest.raises(ValueError, match="prior holds bounds of 3 boxes"):
        fl.lp_bounds(net, np.stack([lo / 4, lo / 3]), np.stack([hi / 4, hi / 3]),
                     prior=fl.fbbt(net, np.stack([lo / 10, lo / 10, lo]), np.stack([hi / 10, hi / 10, hi])))
    pw = fl.network_pieces_1d(net, [0.3, -0.2], -10.0, 10.0)
    with pytest.raises(ValueError, match="pieces cover"):
        fl.exact_1d_feasible_set(net, [0.3, -0.2], -1.0, 1.0, 4.8, pieces=pw)


def test_the_last_review_s_forms(msd):
    sysm, net = msd
    assert fl.time_stats([0.1, 0.2], 50)["median_ms"] == fl.time_stats([0.1, 0.2], (50,))["median_ms"]
    lo, hi = fl.ellipsoid_box(np.array([[1.0, 0.0], [0.0, 0.0]]), np.eye(2), np.zeros(2), np.zeros(2), np.inf)
    assert lo.tolist() == [-np.inf, 0.0] and hi.tolist() == [np.inf, 0.0]
    with pytest.raises(ValueError, match="in order"):
        fl.bound_atlas(net, sysm.lo, sysm.hi, 4.5, {2: 1, 3: 1, 4: 1})
    c1 = fl.control.as_certificate((lambda z: float(z[0] ** 2), lambda z: 2 * z))
    assert c1(0.5) == 0.25 and c1(np.array([0.5])) == 0.25


def test_the_program_s_matrices_and_node_bounds_are_numbers_and_finite(msd):
    import cvxpy as cp
    import scipy.sparse as sp

    sysm, net = msd
    good = dict(H=None, c=[1.0, 1.0], c0=0.0, A=sp.csr_matrix([[1.0, 1.0]]), rl=[1.0], ru=[np.inf], lb=[0, 0],
                ub=[5, 5], integrality=[0, 1])
    assert fl.MIQP(**{**good, "H": np.eye(2), "A": [[1.0, 1.0]]}).n == 2
    for kw, match in [(dict(H=np.eye(2, dtype=bool)), "H must be numbers .*booleans"),
                      (dict(A=[["1", "1"]]), "A must be numbers .*strings"),
                      (dict(A=np.ma.array([[1.0, 1.0]], mask=[[0, 1]])), "A must be numbers .*masked"),
                      (dict(A=sp.csr_matrix(np.array([[True, True]]))), "A must hold real numbers")]:
        with pytest.raises(ValueError, match=match):
            fl.MIQP(**{**good, **kw})
    nb = fl.fbbt(net, sysm.lo, sysm.hi)
    x = cp.Variable(3)
    with pytest.raises(ValueError, match="L\\^1 must be finite node bounds"):
        fl.encode(net, x, L=[np.full_like(a, -np.inf) for a in nb.L], U=list(nb.U))


# --------------------------------------------------------------------------- inputs read without checks before
@pytest.fixture(scope="module")
def msd_mpc(msd):
    sysm, net = msd
    return fl.MPC(sysm, net, 0.5, horizon=4, ts=0.1, Q=[10.0, 1.0], R=0.01)


@pytest.mark.parametrize("call, match", [
    (lambda m, fb: m.repair_plan([1.0, np.nan], np.zeros((4, 1))), "z contains NaN"),
    (lambda m, fb: m.repair_plan([1.0, 0.5], np.zeros((3, 1))), r"v_guess must be inputs of shape \(N_p, m\)"),
    (lambda m, fb: m.repair_plan([1.0, 0.5], [["0"]] * 4), "v_guess must be numbers .*strings"),
    (lambda m, fb: m.repair_plan([1.0, 0.5], np.full((4, 1), np.inf)), "v_guess must be finite"),
    (lambda m, fb: m.repair_plan([1.0, 0.5], np.zeros((4, 1)), first="yes"), "first must be True or False"),
    (lambda m, fb: m.repair_plan([1.0, 0.5], np.zeros((4, 1)), first=1), "first must be True or False"),
    (lambda m, fb: m.feasible_tail([1.0, 0.5], [True]), "v_guess must be numbers .*booleans"),
    (lambda m, fb: m.feasible_tail([1.0, 0.5, 0.0], 0.0), r"z must have shape \(2,\)"),
    (lambda m, fb: m.feasible_tail([1.0, 0.5], np.nan), "v_guess contains NaN"),
    (lambda m, fb: m.feasible_tail([1.0, 0.5], 0.0, last=None), "last must be True or False"),
    (lambda m, fb: fb.feasible_tail(m.pred, [1.0, 0.5], 0.0, n_grid=2.5), "n_grid must be an integer >= 1"),
    (lambda m, fb: fb.feasible_tail(m.pred, [1.0, 0.5], 0.0, n_grid=0), "n_grid must be"),
    (lambda m, fb: fb.feasible_tail(m.pred, [1.0, 0.5], 0.0, n_grid=True), "n_grid must be"),
    (lambda m, fb: fb.repair_plan(m.pred, [1.0, 0.5], np.zeros(4), deadline="now"), "deadline must be a finite number"),
])
def test_the_repairs_check_what_they_are_given(msd_mpc, call, match):
    from flnotes.mpc import fallback as fb

    with pytest.raises(ValueError, match=match):
        call(msd_mpc, fb)


def test_the_repairs_take_other_forms_and_name_a_model_of_the_wrong_kind(msd_mpc):
    from flnotes.mpc import fallback as fb

    mpc = msd_mpc
    Z, V = mpc.repair_plan([1.0, 0.5], np.zeros((4, 1)))
    Z2, V2 = mpc.repair_plan(np.array([Fraction(1), Decimal("0.5")], dtype=object), [0, 0, 0, 0])
    assert np.array_equal(Z, Z2) and np.array_equal(V, V2) and V2.dtype == float
    v = mpc.feasible_tail([1.0, 0.5], 0.0)
    assert np.array_equal(mpc.feasible_tail([1.0, 0.5], [Fraction(0)]), v)
    assert np.array_equal(fb.feasible_tail(mpc.pred, [1.0, 0.5], np.array(0.0), n_grid=np.array(2001.0)), v)
    with pytest.raises(TypeError, match="pred must be a flnotes.mpc.prediction.Prediction"):
        fb.repair_plan(mpc, [1.0, 0.5], np.zeros((4, 1)))


@pytest.fixture(scope="module")
def tightener():
    from flnotes.tightening import LPTightener

    return LPTightener(_random_net(3, (4, 3)))


@pytest.mark.parametrize("call, match", [
    (lambda T: T.set_box([1.0, -1.0, -1.0], [-1.0, 1.0, 1.0]), r"box is empty: lo\[0\]"),
    (lambda T: T.set_box([np.nan, -1.0, -1.0], [1.0, 1.0, 1.0]), "lo contains NaN or inf"),
    (lambda T: T.set_box([-1.0, -1.0, -1.0], [1.0, 1.0, np.inf]), "hi contains NaN or inf"),
    (lambda T: T.set_box([-1.0, -1.0], [1.0, 1.0]), r"lo must have shape \(3,\)"),
    (lambda T: T.set_box([-1.0, -1.0, -1.0], [1.0, True, 1.0]), "hi must be numbers .*booleans"),
    (lambda T: T.set_neuron(2, 0, -1.0, 1.0), "k must be the index .* 2 hidden layers"),
    (lambda T: T.set_neuron(-1, 0, -1.0, 1.0), "k must be an integer >= 0"),
    (lambda T: T.set_neuron(True, 0, -1.0, 1.0), "k must be an integer"),
    (lambda T: T.set_neuron(0, 4, -1.0, 1.0), "j must be the index .* 4 neurons of layer k = 0"),
    (lambda T: T.set_neuron(0, 1.0, -1.0, 1.0), "j must be an integer"),
    (lambda T: T.set_neuron(0, 0, 1.0, -1.0), "L must be <= U"),
    (lambda T: T.set_neuron(0, 0, -np.inf, 1.0), "L must be a finite number"),
    (lambda T: T.set_neuron(0, 0, -1.0, np.nan), "U must be a finite number"),
    (lambda T: T.set_neuron(0, 0, "-1", 1.0), "L must be a finite number"),
    (lambda T: T.set_layer(0, [-1.0] * 3, [1.0] * 4), r"L must have shape \(4,\)"),
    (lambda T: T.set_layer(1, [-1.0] * 3, [-2.0] * 3), r"L must be <= U .* L\[0\]"),
    (lambda T: T.preactivation_range(3, 0), "k must be the index .* 3 layers"),
    (lambda T: T.preactivation_range(2, 1), "j must be the index .* 1 neurons of layer k = 2"),
])
def test_the_lp_tightener_checks_its_box_and_its_neurons(tightener, call, match):
    with pytest.raises(ValueError, match=match):
        call(tightener)


def test_the_lp_tightener_takes_numbers_of_any_real_type(tightener):
    T = tightener
    T.restart()
    T.set_box(-1, [Fraction(1)] * 3)
    assert T._lb[T.x].tolist() == [-1.0] * 3 and T._ub[T.x].tolist() == [1.0] * 3
    nb = fl.fbbt(T.net, -np.ones(3), np.ones(3))
    for k in range(2):
        T.set_layer(k, nb.L[k].tolist(), nb.U[k])
    lo, hi = T.preactivation_range(np.int64(0), 0)
    assert isinstance(lo, float) and nb.L[0][0] - 1e-6 <= lo <= hi <= nb.U[0][0] + 1e-6
    T.set_neuron(np.int64(1), np.array(2), Fraction(-1, 2), np.array([1.5]))
    ia = int(T.alpha[1][2])
    assert T._A[int(T.row_U[1][2]), ia] == -1.5 and T._A[int(T.row_L[1][2]), ia] == 0.5
    T.restart()


def test_the_lp_tightener_answers_only_once_its_lp_relaxes_the_network(tightener):
    """Before the input box and the node bounds of every hidden neuron are set, the LP is no relaxation of the
    network (its big-M entries are zero): a pre-activation range then is refused, never answered "infeasible"."""
    T = tightener
    T.restart()
    with pytest.raises(ValueError, match="set the input box first"):
        T.preactivation_range(0, 0)
    T.set_box(-1.0, 1.0)
    with pytest.raises(ValueError, match="neuron j = 0 of layer 0 has none"):
        T.preactivation_range(0, 0)
    nb = fl.fbbt(T.net, -np.ones(3), np.ones(3))
    T.set_layer(0, nb.L[0], nb.U[0])
    with pytest.raises(ValueError, match="of layer 1 has none"):
        T.preactivation_range(0, 0)
    T.set_layer(1, nb.L[1], nb.U[1])
    X = np.random.default_rng(0).uniform(-1.0, 1.0, (2000, 3))
    a = np.maximum(np.maximum(X @ T.net.W[0].T + T.net.b[0], 0.0) @ T.net.W[1].T + T.net.b[1], 0.0) @ T.net.W[2].T \
        + T.net.b[2]
    lo, hi = T.preactivation_range(2, 0)
    assert lo <= a[:, 0].min() and a[:, 0].max() <= hi  # a sound range of the output's pre-activation
    lo_s, hi_s = T.preactivation_range(2, 0)
    T.set_box(-0.5, 0.5)  # bounds of a box hold on the boxes inside it: kept, and the range is sound and tighter
    X = np.random.default_rng(1).uniform(-0.5, 0.5, (2000, 3))
    a = np.maximum(np.maximum(X @ T.net.W[0].T + T.net.b[0], 0.0) @ T.net.W[1].T + T.net.b[1], 0.0) @ T.net.W[2].T \
        + T.net.b[2]
    lo_i, hi_i = T.preactivation_range(2, 0)
    assert lo_s <= lo_i <= a[:, 0].min() and a[:, 0].max() <= hi_i <= hi_s
    T.set_box(-2.0, 2.0)  # bounds of a smaller box do not hold on a larger one: forgotten
    with pytest.raises(ValueError, match="neuron j = 0 of layer 0 has none"):
        T.preactivation_range(2, 0)
    T.restart()  # node bounds set before the first box are the caller's for that box
    T.set_layer(0, nb.L[0], nb.U[0])
    T.set_layer(1, nb.L[1], nb.U[1])
    T.set_box(-1.0, 1.0)
    assert T.preactivation_range(2, 0) == (lo, hi)
    T.restart()
    with pytest.raises(ValueError, match="set the input box first"):  # a restart forgets what was set
        T.preactivation_range(0, 0)


def test_the_repairs_take_a_state_of_its_shape_and_plans_of_theirs(msd_mpc):
    """A number is no state (it used to be taken for every coordinate); a plan with axes of length 1, or flat, is
    the plan of (N_p, m)."""
    mpc = msd_mpc
    z = np.array([0.5, -0.2])
    for call in (lambda: mpc.repair_plan(1.0, np.zeros((mpc.N, 1))), lambda: mpc.feasible_tail(1.0, 0.0),
                 lambda: mpc.repair_plan([0.5, -0.2, 0.0], np.zeros((mpc.N, 1)))):
        with pytest.raises(ValueError, match=r"z must have shape \(2,\)"):
            call()
    Z, V = mpc.repair_plan(z, np.zeros((mpc.N, 1)))
    for guess in (np.zeros(mpc.N), np.zeros((1, mpc.N)), np.zeros((mpc.N, 1, 1))):
        Z2, V2 = mpc.repair_plan(z, guess)
        assert np.array_equal(V2, V) and np.array_equal(Z2, Z)
    with pytest.raises(ValueError, match="v_guess must be inputs of shape"):
        mpc.repair_plan(z, np.zeros((mpc.N + 1, 1)))
    with pytest.raises(ValueError, match="v_guess must be one input"):
        mpc.feasible_tail(z, [0.0, 0.0])
    assert np.array_equal(mpc.feasible_tail(z, [0.0]), mpc.feasible_tail(z, 0.0))


def test_the_enclosure_reads_only_its_own_network(small_enclosure):
    """residual and contains refuse a network of the same shape but other parameters; covers takes a number for
    every input."""
    net, enc = small_enclosure
    other = _random_net(3, (4, 3), seed=7)
    X = np.zeros((2, 3))
    for call in (lambda: enc.contains(other, X), lambda: enc.residual(other, X)):
        with pytest.raises(ValueError, match="net must be the network the enclosure was computed for"):
            call()
    assert enc.contains(net, X)
    assert enc.covers(-0.5, 0.5) == enc.covers([-0.5] * 3, [0.5] * 3) is True
    assert enc.covers(-2.0, 0.5) is False


def test_worst_violation_scans_only_states_of_the_domain(msd):
    """Extra states ``at`` outside the domain box, where eps is not certified, are refused."""
    sysm, net = msd
    with pytest.raises(ValueError, match="outside the network's trained domain"):
        fl.worst_violation(sysm, net, 0.1, n_z=3, n_v=3, at=[[-3.0, 1000.0, 0.0]])
    inside = np.r_[0.5 * (sysm.lo + sysm.hi)]
    r = fl.worst_violation(sysm, net, 0.1, n_z=3, n_v=3, at=[inside])
    assert r["n_points"] == 4 * 3


@pytest.fixture(scope="module")
def small_enclosure():
    net = _random_net(3, (4, 3))
    return net, fl.affine_enclosure(net, -np.ones(3), np.ones(3))


@pytest.mark.parametrize("call, exc, match", [
    (lambda e, n: e.covers([-0.5] * 3, [0.5, 0.5, np.nan]), ValueError, "hi contains NaN"),
    (lambda e, n: e.covers([-0.5] * 3, [True] * 3), ValueError, "hi must be numbers .*booleans"),
    (lambda e, n: e.covers([0.5] * 3, [-0.5] * 3), ValueError, "box is empty"),
    (lambda e, n: e.covers([-0.5] * 2, [0.5] * 2), ValueError, "lo and hi must have shape"),
    (lambda e, n: e.slab(np.nan), ValueError, "u must be finite output bounds >= 0"),
    (lambda e, n: e.slab(-1.0), ValueError, "u must be finite output bounds >= 0"),
    (lambda e, n: e.slab("1"), ValueError, "u must be numbers .*strings"),
    (lambda e, n: e.residual(n, [0.1, 0.2]), ValueError, r"X must have shape \(N, 3\)"),
    (lambda e, n: e.residual(n, [[0.1, 0.2, np.nan]]), ValueError, "X contains NaN"),
    (lambda e, n: e.residual("net", [0.1, 0.2, 0.3]), TypeError, "net must be a flnotes.ReLUNet"),
    (lambda e, n: e.contains(_random_net(2), [0.1, 0.2]), ValueError, "net must have 3 inputs"),
    (lambda e, n: e.contains(n, [0.1, 0.2, 0.3], tol=np.nan), ValueError, "tol must be a finite number >= 0"),
    (lambda e, n: e.contains(n, [0.1, 0.2, 0.3], tol=True), ValueError, "tol must be a finite number >= 0"),
])
def test_the_enclosure_s_methods_check_their_arguments(small_enclosure, call, exc, match):
    net, enc = small_enclosure
    with pytest.raises(exc, match=match):
        call(enc, net)


def test_the_enclosure_s_methods_take_other_forms(small_enclosure):
    net, enc = small_enclosure
    assert enc.covers([-0.5] * 3, np.array([Fraction(1, 2)] * 3, dtype=object)) is True
    assert enc.covers(np.array([[-0.5] * 3, [-2.0] * 3]), [[0.5] * 3, [0.0] * 3]) is False
    s_lo, s_hi = enc.slab([Fraction(1)])
    assert s_lo.dtype == float and np.array_equal((s_lo, s_hi), enc.slab(np.array(1.0)))
    assert np.array_equal(enc.residual(net, [0.1, 0.2, 0.3]), enc.residual(net, np.array([[0.1, 0.2, 0.3]])))
    assert enc.contains(net, [[0.1, 0.2, 0.3]], tol=Decimal("0.1")) is True


@pytest.fixture(scope="module")
def small_atlas():
    net = _random_net(3, (4, 3))
    return net, fl.bound_atlas(net, -np.ones(3), np.ones(3), 5.0, (2, 1, 1))


@pytest.mark.parametrize("call, exc, match", [
    (lambda a, n: a.covers([-0.5] * 3, [0.5, 0.5, np.nan]), ValueError, "hi contains NaN"),
    (lambda a, n: a.covers([-0.5] * 3, ["0.5"] * 3), ValueError, "hi must be numbers .*strings"),
    (lambda a, n: a.covers([0.5] * 3, [-0.5] * 3), ValueError, "box is empty"),
    (lambda a, n: a.cover([-0.5] * 3, [0.5, True, 0.5]), ValueError, "hi must be numbers .*booleans"),
    (lambda a, n: a.cover([np.nan] * 3, [0.5] * 3), ValueError, "lo contains NaN"),
    (lambda a, n: fl.atlas.shipped_atlas(n, -np.ones(3), np.ones(3), "5"), ValueError, "u must be numbers .*strings"),
    (lambda a, n: fl.atlas.shipped_atlas(n, np.ones(3), -np.ones(3), 5.0), ValueError, "box is empty"),
    (lambda a, n: fl.atlas.shipped_atlas("net", -np.ones(3), np.ones(3), 5.0), TypeError, "net must be"),
    (lambda a, n: fl.check_atlas(n, a, seed=1.5), ValueError, "seed must be an integer"),
])
def test_the_atlas_s_methods_check_their_arguments(small_atlas, call, exc, match):
    net, atlas = small_atlas
    with pytest.raises(exc, match=match):
        call(atlas, net)


def test_the_atlas_s_methods_take_other_forms(small_atlas):
    net, atlas = small_atlas
    assert atlas.covers([-0.5] * 3, [Fraction(1, 2)] * 3).tolist() == [True]
    assert atlas.covers(np.array([[-0.5] * 3, [-2.0] * 3]), [[0.5] * 3, [0.0] * 3]).tolist() == [True, False]
    L, U = atlas.cover([-0.5] * 3, [0.5] * 3)
    L2, U2 = atlas.cover(np.array([[-0.5] * 3]), np.array([[Decimal("0.5")] * 3], dtype=object))
    assert all(np.array_equal(a, b) and a.dtype == float for a, b in zip(L + U, L2 + U2))
    assert fl.atlas.shipped_atlas(net, [-1] * 3, [1] * 3, 5) is None


@pytest.mark.parametrize("kw, match", [
    (dict(input_map=[2, True, 0]), "input_map must be numbers .*booleans"),
    (dict(input_map=(np.eye(3, dtype=bool), np.zeros(3))), "input_map's M must be numbers .*booleans"),
    (dict(input_map=([["1", "0", "0"], ["0", "1", "0"], ["0", "0", "1"]], np.zeros(3))),
     "input_map's M must be numbers .*strings"),
    (dict(input_map=(np.eye(3), ["0", 0, 0])), "input_map's c must be numbers .*strings"),
    (dict(input_map=(np.eye(3), np.ma.array([0.0, 0.0, 0.0], mask=[0, 1, 0]))), "input_map's c must be numbers .*masked"),
    (dict(output_map=([True], [0.0])), "output_map's D must be numbers .*booleans"),
    (dict(output_map=([[2.0]], ["1"])), "output_map's d must be numbers .*strings"),
])
def test_mapped_reads_its_maps_as_numbers(kw, match):
    net = _random_net(3, (4,))
    with pytest.raises(ValueError, match=match):
        net.mapped(**kw)


def test_mapped_takes_maps_of_other_forms():
    net = _random_net(3, (4,))
    X = np.array([[0.3, -0.2, 1.5]])
    a = net.mapped(input_map=(np.eye(3)[[2, 0, 1]], np.zeros(3)), output_map=(np.array([2.0]), np.array([1.0])))
    b = net.mapped(input_map=[2, 0, 1], output_map=([Fraction(2)], Decimal(1)))
    c = net.mapped(input_map=np.array([2, 0, 1]), output_map=([[2]], [1]))
    assert np.allclose(a(X), b(X)) and np.allclose(a(X), c(X)) and b.W[0].dtype == float


@pytest.mark.parametrize("call, match", [
    (lambda r: r.spread([1.0, True]), "times must be numbers .*booleans"),
    (lambda r: r.spread(["1.0", "1.1"]), "times must be numbers .*strings"),
    (lambda r: r.spread([1.0, np.nan]), "times must hold at least two positive finite times"),
    (lambda r: r.against_spread(1.0, 1.1, True), "spread_ must be a finite number >= 0"),
    (lambda r: r.against_spread(1.0, "1.1", 0.1), "b must be a finite number > 0"),
    (lambda r: r.against_spread(True, 1.1, 0.1), "a must be a finite number > 0"),
    (lambda r: r.separation([1.0, np.nan], [2.0]), "a must be the values of runs, without NaN"),
    (lambda r: r.separation([1.0], ["2"]), "b must be numbers .*strings"),
    (lambda r: r.separation([], [2.0]), "a and b must hold at least one value each"),
])
def test_the_repeats_helpers_read_numbers_only(call, match):
    from flnotes import repeats

    with pytest.raises(ValueError, match=match):
        call(repeats)


def test_the_repeats_helpers_take_numbers_of_any_real_type():
    from flnotes import repeats

    assert repeats.spread([Fraction(1), Decimal("1.1")]) == repeats.spread([1.0, 1.1])
    assert repeats.against_spread(np.array([1.0]), Fraction(11, 10), np.array(0.2)) == repeats.VERDICTS[0]
    assert repeats.separation([1.0], (Fraction(2),)) == "higher"


@pytest.mark.parametrize("call, match", [
    (lambda a: a.arm_link_points([[0.1, 0.2]], [0.5, np.nan]), "fractions must lie in \\[0, 1\\]"),
    (lambda a: a.arm_link_points([[0.1, 0.2]], [True]), "fractions must be numbers .*booleans"),
    (lambda a: a.arm_obstacle_cbfs([0.0, -0.9], 0.1, n_points=True), "n_points must be"),
    (lambda a: a.arm_obstacle_cbfs([0.0, -0.9], 0.1, n_points=2.5), "n_points must be an integer >= 2"),
    (lambda a: a.arm_obstacle_cbfs([0.0, -0.9], "0.1"), "radius must be a finite number > 0"),
    (lambda a: a.arm_obstacle_cbfs([0.0, -0.9], True), "radius must be a finite number > 0"),
    (lambda a: a.arm_obstacle_cbfs([0.0, -0.9], np.nan), "radius must be a finite number > 0"),
])
def test_the_arm_helpers_check_their_numbers_and_counts(call, match):
    from flnotes import arm

    with pytest.raises(ValueError, match=match):
        call(arm)


def test_the_arm_helpers_take_counts_and_numbers_of_any_real_type():
    from flnotes import arm

    H = arm.arm_obstacle_cbfs([0.0, -0.9], 0.1, n_points=3)
    H2 = arm.arm_obstacle_cbfs([0.0, -0.9], Fraction(1, 10), n_points=np.array(3.0))
    assert [(h.R, h.s) for h in H] == [(h.R, h.s) for h in H2]
    assert np.array_equal(arm.arm_link_points([[0.1, 0.2]], Fraction(1, 2)), arm.arm_link_points([[0.1, 0.2]], [0.5]))


@pytest.mark.parametrize("call, match", [
    (lambda P, s: P.deadline.gap_histogram({"a": [0.1, 0.2]}, bins=2.5), "bins must be an integer >= 1"),
    (lambda P, s: P.deadline.gap_histogram({"a": [0.1, 0.2]}, bins=True), "bins must be"),
    (lambda P, s: P.foundations.fl_identity_residual(s, n=True), "n must be"),
    (lambda P, s: P.foundations.plot_feasible_v(s, n="801"), "n must be"),
    (lambda P, s: P.foundations.plot_feasible_set(s, n=1), "n must be a finite number >= 2"),
    (lambda P, s: P.foundations.plot_line_cut(s, _identity_net(s), n=10.5), "n must be an integer >= 2"),
    (lambda P, s: P.foundations.plot_error_slice(s, _identity_net(s), n=0), "n must be"),
    (lambda P, s: P.foundations.unstable_fixed_z(s, _identity_net(s), n=2.5), "n must be an integer >= 1"),
    (lambda P, s: P.foundations.unstable_vs_box_size(s, _identity_net(s), n_centers=True), "n_centers must be"),
    (lambda P, s: P.foundations.bounds_looseness(_identity_net(s), s.lo, s.hi, n=0), "n must be"),
    (lambda P, s: P.foundations.static_feasible_set(s, n_frames=4.5), "n_frames must be an integer >= 2"),
    (lambda P, s: P.error.violation_line(s, _identity_net(s), [0.0, 0.0], {}, n=1), "n must be"),
    (lambda P, s: P.static.frame_player(lambda x: None, {"a": [1]}, "x", dpi=0.5), "dpi must be"),
    (lambda P, s: P.style.new_axes(0, 1), "nrows must be"),
    (lambda P, s: P.style.new_axes(1, 1.5), "ncols must be an integer >= 1"),
])
def test_the_plotting_helpers_check_their_counts(call, match):
    import matplotlib.pyplot as plt
    from flnotes import plots as P
    from flnotes.plots import deadline, error, foundations, static, style  # noqa: F401 - the submodules, as P's attributes

    try:
        with pytest.raises(ValueError, match=match):
            call(P, fl.msd())
    finally:
        plt.close("all")


def test_the_plotting_helpers_take_counts_of_any_real_type():
    import matplotlib.pyplot as plt
    from flnotes.plots import deadline, foundations, style

    sysm = fl.msd()
    try:
        a = foundations.fl_identity_residual(sysm, n=np.array(5.0), seed=1)
        b = foundations.fl_identity_residual(sysm, n=Fraction(5), seed=1)
        assert np.array_equal(a, b) and a.dtype == float
        deadline.gap_histogram({"a": [0.1, 0.2]}, bins=Decimal(4))
        fig, axes = style.new_axes(2.0, np.int64(1))
        assert len(axes) == 2
        assert foundations.unstable_fixed_z(sysm, _identity_net(sysm), n=np.array(4)).shape == (4,)
    finally:
        plt.close("all")


def test_worst_violation_refuses_to_answer_when_no_sampled_point_was_feasible(msd):
    sysm, net = msd
    with pytest.raises(ValueError, match=r"no sampled point satisfies \|Phi_NN\| <= u_max - eps .*nothing was "
                                         r"checked.*n_z.*n_v.*smaller eps"):
        fl.worst_violation(sysm, net, 4.999, n_z=3, n_v=3)
    res = fl.worst_violation(sysm, net, 0.5, n_z=3, n_v=3)
    assert res["n_feasible"] > 0 and np.all(np.isfinite(res["violation"]))
    res2 = fl.worst_violation(sysm, net, np.array([Fraction(1, 2)], dtype=object), n_z=3, n_v=3)
    assert np.array_equal(res["violation"], res2["violation"])


# --------------------------------------------------------------------------- the plotting, atlas, arm and repeats
# helpers: values read as numbers, settings as numbers > 0, indices as integers in range, points of exact shape
@pytest.fixture(scope="module")
def book_msd_net():
    """The book's MSD network, of which an atlas is shipped."""
    net, _ = fl.paper.paper_net("MSD")
    return net, fl.paper.system("MSD")


def _other_net():
    """A network of the MSD's shape (3 inputs, 1 output) with known weights."""
    return fl.ReLUNet([np.ones((2, 3)), np.ones((1, 2))], [np.zeros(2), np.zeros(1)])


@pytest.mark.parametrize("call, exc, match", [
    # the gaps and times of the deadline figures are numbers
    (lambda P, s: P.deadline.gap_histogram({"a": ["0.1", "0.2"]}), ValueError, r"gaps\['a'\] must be numbers .*strings"),
    (lambda P, s: P.deadline.gap_histogram({"a": [0.1, True]}), ValueError, r"gaps\['a'\] must be numbers .*booleans"),
    (lambda P, s: P.deadline.answer_times({"a": ["1.0"]}, 100.0), ValueError, r"times_ms\['a'\] must be numbers"),
    (lambda P, s: P.deadline.answer_times({"a": [1.0]}, True), ValueError, "t_s_ms must be a finite number > 0"),
    # the step and the seed of the identity check
    (lambda P, s: P.foundations.fl_identity_residual(s, n=3, h=0.0), ValueError, "h must be a finite number > 0"),
    (lambda P, s: P.foundations.fl_identity_residual(s, n=3, h=-1), ValueError, "h must be a finite number > 0"),
    (lambda P, s: P.foundations.fl_identity_residual(s, n=3, h=True), ValueError, "h must be a finite number > 0"),
    (lambda P, s: P.foundations.fl_identity_residual(s, n=3, h=np.array([1e-6])), ValueError, "h must be a finite"),
    (lambda P, s: P.foundations.fl_identity_residual(s, n=3, seed=1.0), ValueError, "seed must be an integer >= 0"),
    (lambda P, s: P.foundations.fl_identity_residual(s, n=3, seed=True), ValueError, "seed must be an integer >= 0"),
    (lambda P, s: P.foundations.fl_identity_residual(s, n=3, seed=-1), ValueError, "seed must be an integer >= 0"),
    (lambda P, s: P.foundations.unstable_fixed_z(s, _other_net(), n=3, seed=0.5), ValueError, "seed must be"),
    (lambda P, s: P.foundations.bounds_looseness(_other_net(), s.lo, s.hi, n=3, seed=True), ValueError,
     "seed must be"),
    # the extent of the zeta figure
    (lambda P, s: P.foundations.plot_zeta(fl.quad1d(), extent=-5, n=5), ValueError, "extent must be a finite number > 0"),
    (lambda P, s: P.foundations.plot_zeta(fl.quad1d(), extent=0, n=5), ValueError, "extent must be a finite number > 0"),
    (lambda P, s: P.foundations.plot_zeta(fl.quad1d(), extent=True, n=5), ValueError, "extent must be"),
    # indices: integers (no booleans, no floats) in range
    (lambda P, s: P.foundations.plot_line_cut(s, _other_net(), axis=True, n=5), ValueError, "axis must be an integer"),
    (lambda P, s: P.foundations.plot_line_cut(s, _other_net(), output=True, n=5), ValueError,
     "output must be an integer"),
    (lambda P, s: P.foundations.plot_line_cut(s, _other_net(), axis=3, n=5), ValueError, r"axis must index .*0\.\.2"),
    (lambda P, s: P.foundations.plot_line_cut(s, _other_net(), output=1, n=5), ValueError, r"output must index .*0\.\.0"),
    (lambda P, s: P.foundations.plot_feasible_set(s, axis=True, n=5), ValueError, "axis must be an integer"),
    (lambda P, s: P.foundations.plot_feasible_set(s, axis=1.0, n=5), ValueError, "axis must be an integer"),
    (lambda P, s: P.foundations.plot_feasible_set(s, axis=1, n=5, family=(0.5, [0.0])), ValueError,
     r"family\[0\] must be an integer"),
    (lambda P, s: P.foundations.plot_feasible_set(s, axis=1, n=5, family=(1, [0.0])), ValueError,
     r"family\[0\] must index another component"),
    (lambda P, s: P.foundations.plot_feasible_set(s, axis=1, n=5, family=(0, ["1"])), ValueError,
     r"family\[1\] must be numbers"),
    (lambda P, s: P.foundations.plot_error_slice(s, _other_net(), axes=(1, 1), n=5), ValueError,
     "axes must be two different coordinates"),
    (lambda P, s: P.foundations.plot_error_slice(s, _other_net(), axes=(1, 2.0), n=5), ValueError,
     r"axes\[1\] must be an integer"),
    (lambda P, s: P.foundations.plot_error_slice(s, _other_net(), output=True, n=5), ValueError,
     "output must be an integer"),
])
def test_the_plotting_helpers_check_their_values_settings_and_indices(call, exc, match):
    import matplotlib.pyplot as plt
    from flnotes import plots as P
    from flnotes.plots import deadline, foundations  # noqa: F401 - the submodules, as P's attributes

    try:
        with pytest.raises(exc, match=match):
            call(P, fl.msd())
    finally:
        plt.close("all")


def _hist_steps(fig):
    """The outlines of the histograms drawn by gap_histogram."""
    return [p.get_xy().tolist() for p in fig.axes[0].patches]


def test_the_plotting_helpers_take_numbers_of_any_real_type():
    import matplotlib.pyplot as plt
    from flnotes.plots import deadline, foundations, static

    sysm = fl.msd()
    try:
        a = _hist_steps(deadline.gap_histogram({"a": [0.1, 0.2, np.inf]}, bins=3))
        b = _hist_steps(deadline.gap_histogram({"a": np.array([Fraction(1, 10), Decimal("0.2"), np.inf], dtype=object)},
                                               bins=3))
        c = _hist_steps(deadline.gap_histogram({"a": (np.float32(0.1), 0.2)}, bins=3))
        assert a == b and len(a) == 1 and np.allclose(a, c)
        r = foundations.fl_identity_residual(sysm, n=5, seed=1, h=1e-6)
        assert np.array_equal(r, foundations.fl_identity_residual(sysm, n=5, seed=np.int64(1), h=Decimal("1e-6")))
        assert np.array_equal(r, foundations.fl_identity_residual(sysm, n=5, seed=1, h=np.array(1e-6)))
        assert foundations.fl_identity_residual(sysm, n=5, seed=None).shape == (2,)
        fig = foundations.plot_line_cut(sysm, _other_net(), axis=np.int64(1), output=np.array(0), n=5)
        assert np.array_equal(fig.axes[0].lines[0].get_xdata(),
                              foundations.plot_line_cut(sysm, _other_net(), axis=1, n=5).axes[0].lines[0].get_xdata())
        foundations.plot_feasible_set(sysm, axis=np.int32(1), n=5, family=(0, np.array([Fraction(0), 1.0], dtype=object)))
        foundations.plot_zeta(fl.quad1d(), extent=Fraction(15), n=5)
        player = static.frame_player(lambda x: plt.figure(figsize=(1, 1)), {"a": [1]}, "x", dpi=72.5)
        assert len(player.frames) == 1
    finally:
        plt.close("all")


@pytest.mark.parametrize("times", [[5e-324, 1.0], [1.0, 2.0, 1e-310], np.array([[4.0], [1e-309]])])
def test_spread_refuses_times_whose_ratio_overflows(times):
    from flnotes import repeats

    with pytest.raises(ValueError, match=r"times must be times of the same work: max / min = .* overflows"):
        repeats.spread(times)


def test_spread_of_tiny_times_and_a_verdict_on_an_overflowing_ratio():
    import warnings

    from flnotes import repeats

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert repeats.spread([5e-324, 1e-323]) == 1.0  # the ratio of two tiny times is a number
        assert repeats.against_spread(5e-324, 1.0, 0.1) == repeats.VERDICTS[2]  # beyond any finite spread


@pytest.mark.parametrize("u", [-1.0, 0, 0.0, [0.0], np.array([-4.0])])
def test_shipped_atlas_refuses_a_bound_that_is_not_positive(book_msd_net, u):
    net, s = book_msd_net
    a = fl.atlas.shipped_atlas(net, s.lo, s.hi, 1.0)  # premise: a positive bound is served, in any real form
    assert a is not None and all(fl.atlas.shipped_atlas(net, s.lo, s.hi, x).digest == a.digest
                                 for x in (np.array([1.0]), Fraction(1), [Decimal(1)]))
    with pytest.raises(ValueError, match="u must be positive"):
        fl.atlas.shipped_atlas(net, s.lo, s.hi, u)


def test_check_atlas_takes_a_seed_of_none_as_numpy_does(small_atlas):
    net, atlas = small_atlas
    for seed in (None, 0, np.int64(3)):
        fl.check_atlas(net, atlas, seed=seed)


@pytest.mark.parametrize("seed", [True, 1.0, -1, "0"])
def test_check_atlas_refuses_other_seeds(small_atlas, seed):
    net, atlas = small_atlas
    with pytest.raises(ValueError, match="seed must be an integer >= 0 .*or None"):
        fl.check_atlas(net, atlas, seed=seed)


def test_the_atlas_takes_a_number_for_every_input(small_atlas):
    net, atlas = small_atlas
    assert atlas.covers(-0.5, 0.5).tolist() == atlas.covers([-0.5] * 3, [0.5] * 3).tolist() == [True]
    assert atlas.covers(-2.0, [0.5] * 3).tolist() == [False]
    assert atlas.covers(-0.5, np.array([[0.5] * 3, [2.0] * 3])).tolist() == [True, False]
    L, U = atlas.cover(-0.5, Fraction(1, 2))
    L2, U2 = atlas.cover([-0.5] * 3, [0.5] * 3)
    assert all(np.array_equal(a, b) for a, b in zip(L + U, L2 + U2))
    L, U = atlas.cover(np.array(-0.5), [0.25, 0.5, 0.5])
    L2, U2 = atlas.cover([-0.5] * 3, [0.25, 0.5, 0.5])
    assert all(np.array_equal(a, b) for a, b in zip(L + U, L2 + U2))
    # a number is checked as the vector is; a column (3, 1) stays refused (a batch of boxes of one input each)
    for lo, hi, match in [(True, 0.5, "lo must be numbers .*booleans"), (-0.5, "0.5", "hi must be numbers .*strings"),
                          (np.nan, 0.5, "lo contains NaN"), (0.5, -0.5, "box is empty"),
                          (np.full((3, 1), -0.5), np.full((3, 1), 0.5), r"lo and hi must have shape \(3,\) or \(T, 3\)")]:
        for method in (atlas.covers, atlas.cover):
            with pytest.raises(ValueError, match=match):
                method(lo, hi)


@pytest.mark.parametrize("call, exc, match", [
    (lambda a: a.arm_obstacle_cbfs(-0.9, 0.1), ValueError, r"center must be a point \(x, y\) .*shape \(2,\)"),
    (lambda a: a.arm_obstacle_cbfs([[0.0, -0.9], [0.1, 0.2]], 0.1), ValueError, r"center must be a point .*shape \(2, 2\)"),
    (lambda a: a.arm_obstacle_cbfs([0.0, -0.9, 0.0], 0.1), ValueError, "center must be a point"),
    (lambda a: a.ArmPointCBF(0.5, 0.1), ValueError, "center must be a point"),
    (lambda a: a.links_distance([[0.1, 0.2]], -0.9), ValueError, "center must be a point"),
    (lambda a: a.links_distance([[0.1, 0.2]], [0.0, np.inf]), ValueError, "center contains NaN or inf"),
    (lambda a: a.arm_link_points([[0.1, 0.2]], 0.5, p={"l1": "1"}), ValueError,
     r"p\['l1'\] must be a finite number > 0"),
    (lambda a: a.arm_link_points([[0.1, 0.2]], 0.5, p={"l1": True}), ValueError, r"p\['l1'\] must be"),
    (lambda a: a.arm_link_points([[0.1, 0.2]], 0.5, p={"l1": -0.5}), ValueError, r"p\['l1'\] must be"),
    (lambda a: a.arm_link_points([[0.1, 0.2]], 0.5, p={"L1": 0.5}), ValueError, r"p holds unknown keys \['L1'\]"),
    (lambda a: a.arm_link_points([[0.1, 0.2]], 0.5, p=[0.5, 0.5]), TypeError, "p must be a dict"),
    (lambda a: a.arm_joint_positions([[0.1, 0.2]], p={"l2": np.array([0.5])}), ValueError, r"p\['l2'\] must be"),
    (lambda a: a.arm_mass_matrix(np.zeros((1, 4)), p={"a1": "1"}), ValueError, r"p\['a1'\] must be a finite number"),
    (lambda a: a.arm_bias(np.zeros((1, 4)), p={"b1": np.nan}), ValueError, r"p\['b1'\] must be a finite number"),
    (lambda a: a.arm_obstacle_cbfs([0.0, -0.9], 0.1, params={"g": "9.81"}), ValueError,
     r"params\['g'\] must be a finite number > 0"),
    (lambda a: a.ArmPointCBF([0.0, -0.9], 0.1, params={"m": 1.0}), ValueError, r"params holds unknown keys"),
])
def test_the_arm_helpers_check_their_points_and_constants(call, exc, match):
    from flnotes import arm

    with pytest.raises(exc, match=match):
        call(arm)


def test_the_arm_helpers_take_their_constants_as_dicts_of_numbers():
    from flnotes import arm

    q = [[0.1, 0.2], [-0.3, 0.5]]
    base = arm.arm_link_points(q, [0.0, 1.0])
    p = arm.arm_parameters()
    assert np.array_equal(arm.arm_link_points(q, [0.0, 1.0], p=p), base)
    assert np.array_equal(arm.arm_link_points(q, [0.0, 1.0], p=arm.two_link_arm().params), base)
    assert np.array_equal(arm.arm_link_points(q, [0.0, 1.0], p={"l1": Fraction(1, 2), "l2": np.float32(0.5)}), base)
    assert np.array_equal(arm.arm_link_points(q, [0.0, 1.0], p={"l1": 1.0}),
                          arm.arm_link_points(q, [0.0, 1.0], p=arm.arm_parameters(l1=1.0)))
    Z = np.array([[0.1, 0.2, 0.3, -0.4]])
    assert np.array_equal(arm.arm_mass_matrix(Z, {k: Decimal(repr(v)) for k, v in p.items()}), arm.arm_mass_matrix(Z))
    assert np.array_equal(arm.arm_bias(Z, p), arm.arm_bias(Z))
    c = np.array([0.31, -0.95])
    assert np.array_equal(arm.links_distance(q, (0.31, -0.95)), arm.links_distance(q, c))
    H = arm.arm_obstacle_cbfs(c, 0.06, params=p)
    H2 = arm.arm_obstacle_cbfs([Fraction(31, 100), -0.95], 0.06)
    assert [(h.c.tolist(), h.R, h.s) for h in H] == [(h.c.tolist(), h.R, h.s) for h in H2]
    with pytest.raises(ValueError, match="center must be a point"):  # a number is no centre (not both coordinates)
        arm.links_distance(q, 0.31)


# --------------------------------------------------------------------------- the drawn range of v, the frame
# player's start, sliders and draw, the atlas's fields, gaps and times that a figure would drop, one-element settings
def _player(**kw):
    import matplotlib.pyplot as plt
    from flnotes.plots import static

    args = dict(draw=lambda a, b: plt.figure(figsize=(0.5, 0.5)), sliders={"a": [1, 2, 3], "b": [0.5, 1.5]},
                name="p", dpi=10)
    args.update(kw)
    return static.frame_player(**args)


@pytest.mark.parametrize("call, exc, match", [
    (lambda s: fl.plots.plot_feasible_set(s, n=5, v_lim=("-3", "3")), ValueError, r"v_lim\[0\] must be a finite number"),
    (lambda s: fl.plots.plot_feasible_set(s, n=5, v_lim=(False, True)), ValueError, r"v_lim\[0\] must be a finite"),
    (lambda s: fl.plots.plot_feasible_set(s, n=5, v_lim=(-3, 3, 99)), ValueError, r"v_lim must be a pair"),
    (lambda s: fl.plots.plot_feasible_set(s, n=5, v_lim=3), ValueError, r"v_lim must be a pair"),
    (lambda s: fl.plots.plot_feasible_set(s, n=5, v_lim=(3, -3)), ValueError, r"v_lim must be a range .*lo < hi"),
    (lambda s: fl.plots.plot_feasible_set(s, n=5, v_lim=(-3, np.nan)), ValueError, r"v_lim\[1\] must be a finite"),
    (lambda s: _player(start=[1.7, 0]), ValueError, r"start\[0\] must be an integer >= 0"),
    (lambda s: _player(start=[True, 0]), ValueError, r"start\[0\] must be an integer >= 0"),
    (lambda s: _player(start=[0, "1"]), ValueError, r"start\[1\] must be an integer >= 0"),
    (lambda s: _player(start=[np.nan, 0]), ValueError, r"start\[0\] must be an integer >= 0"),
    (lambda s: _player(start=1), ValueError, r"start must be a list of 2 indices"),
    (lambda s: _player(start=[0]), ValueError, r"start must hold one index per slider \(2"),
    (lambda s: _player(start=[0, 2]), ValueError, r"start\[1\] must index the values of slider 'b': 0\.\.1"),
    (lambda s: _player(sliders={"a": 3}), ValueError, r"sliders\['a'\] must be a non-empty ordered"),
    (lambda s: _player(sliders={"a": "abc", "b": [1]}), ValueError, r"sliders\['a'\] must be a non-empty ordered"),
    (lambda s: _player(sliders={"a": [1], "b": {1, 2}}), ValueError, r"sliders\['b'\] must be a non-empty ordered"),
    (lambda s: _player(sliders={"a": [1], "b": []}), ValueError, r"sliders\['b'\] must be a non-empty ordered"),
    (lambda s: _player(sliders=[("a", [1]), ("b", [2])]), TypeError, r"sliders must be a dict"),
    (lambda s: _player(draw=lambda a, b: None), TypeError, r"draw must return a matplotlib figure"),
    (lambda s: _player(draw=None), TypeError, r"draw must be a function"),
])
def test_the_drawn_range_and_the_frame_player_check_their_arguments(call, exc, match):
    import matplotlib.pyplot as plt

    try:
        with pytest.raises(exc, match=match):
            call(fl.msd())
    finally:
        plt.close("all")


def test_the_drawn_range_and_the_frame_player_take_other_forms():
    import matplotlib.pyplot as plt
    from flnotes.plots import foundations

    s = fl.msd()
    try:
        vs = foundations._v_axis(s, (-20, 20), 7)
        for v_lim in ([-20.0, 20.0], np.array([-20, 20]), (Fraction(-20), np.float32(20)), (np.array(-20), Decimal(20))):
            assert np.array_equal(foundations._v_axis(s, v_lim, 7), vs)
        fig = fl.plots.plot_feasible_set(s, n=5, v_lim=(Fraction(-20), 20.0))
        assert fig.axes[0].get_ylim() == fl.plots.plot_feasible_set(s, n=5, v_lim=(-20, 20)).axes[0].get_ylim()
        base = _player(start=[2, 0])
        for kw in (dict(start=(np.int64(2), np.array(0))), dict(start=np.array([2, 0])),
                   dict(sliders={"a": range(1, 4), "b": np.array([0.5, 1.5])}, start=[2, 0])):
            p = _player(**kw)
            assert p.start == base.start and p.frames.keys() == base.frames.keys() and len(p) == 6
        assert _player().start == [1, 1]
    finally:
        plt.close("all")


def _atlas_fields(atlas, **kw):
    fields = dict(edges=atlas.edges, L=atlas.L, U=atlas.U, u=atlas.u, net_id=atlas.net_id)
    fields.update(kw)
    return fields


def _with_cell(arrays, k, value):
    out = [np.array(a) for a in arrays]
    out[k][(0,) * out[k].ndim] = value
    return tuple(out)


@pytest.mark.parametrize("change, match", [
    (lambda a: dict(edges=(["-1", "0", "1"],) + a.edges[1:]), r"BoundAtlas\.edges\[0\] must be numbers .*strings"),
    (lambda a: dict(edges=(a.edges[0], [False, True]) + a.edges[2:]), r"BoundAtlas\.edges\[1\] must be numbers .*booleans"),
    (lambda a: dict(u=[True]), r"BoundAtlas\.u must be numbers .*booleans"),
    (lambda a: dict(L=tuple(np.zeros(x.shape, bool) for x in a.L)), r"BoundAtlas\.L\[0\] must be numbers .*booleans"),
    (lambda a: dict(U=tuple(x.astype(str) for x in a.U)), r"BoundAtlas\.U\[0\] must be numbers .*strings"),
    (lambda a: dict(L=_with_cell(a.L, 1, -np.inf)), r"L\[1\] and U\[1\] at cell \(0, 0, 0\), neuron 0: .*finite"),
    (lambda a: dict(U=_with_cell(a.U, 0, np.inf)), r"L\[0\] and U\[0\] at cell \(0, 0, 0\), neuron 0: .*finite"),
    (lambda a: dict(edges="abc"), r"BoundAtlas\.edges must be a tuple"),
    (lambda a: dict(L=5.0), r"BoundAtlas\.L must be a tuple"),
])
def test_a_bound_atlas_checks_its_fields(small_atlas, change, match):
    net, atlas = small_atlas
    with pytest.raises(ValueError, match=match):
        fl.BoundAtlas(**_atlas_fields(atlas, **change(atlas)))


def test_an_atlas_with_crossed_bounds_is_refused_by_check_atlas(small_atlas):
    net, atlas = small_atlas
    L = _with_cell(atlas.L, 0, float(atlas.U[0][0, 0, 0, 0]) + 1.0)
    crossed = fl.BoundAtlas(**_atlas_fields(atlas, L=L))
    with pytest.raises(ValueError, match=r"does not hold: at cell \(0, 0, 0\), neuron 0 of hidden layer 1: L = .* > U"):
        fl.check_atlas(net, crossed, seed=1)


def test_a_bound_atlas_takes_its_fields_in_other_forms(small_atlas):
    net, atlas = small_atlas
    same = fl.BoundAtlas(edges=[e.tolist() for e in atlas.edges], L=list(atlas.L),
                         U=tuple(np.array(a, dtype=object) for a in atlas.U), u=[Fraction(5)], net_id=atlas.net_id)
    assert same.digest == atlas.digest
    fl.check_atlas(net, same)


@pytest.mark.parametrize("call, match", [
    (lambda P: P.gap_histogram({"a": [-0.5, 0.1]}), r"gaps\['a'\] must be gaps >= 0 .*-0\.5 at position 0"),
    (lambda P: P.gap_histogram({"a": [0.1, 0.2], "b": [0.1, -np.inf]}), r"gaps\['b'\] must be gaps >= 0 .*-inf"),
    (lambda P: P.answer_times({"a": [-1.0, 5.0]}, 100), r"times_ms\['a'\] must be answer times .*-1\.0 at position 0"),
    (lambda P: P.answer_times({"a": [1.0], "b": [5.0, np.nan]}, 100), r"times_ms\['b'\] must be answer times .*nan"),
    (lambda P: P.answer_times({"a": [np.inf]}, 100), r"times_ms\['a'\] must be answer times .*inf"),
])
def test_the_deadline_figures_refuse_gaps_and_times_they_would_drop(call, match):
    import matplotlib.pyplot as plt
    from flnotes.plots import deadline

    try:
        with pytest.raises(ValueError, match=match):
            call(deadline)
    finally:
        plt.close("all")


def test_the_deadline_figures_leave_out_steps_without_a_plan_and_take_times_of_any_real_type():
    import matplotlib.pyplot as plt
    from flnotes.plots import deadline

    try:
        a = _hist_steps(deadline.gap_histogram({"a": [0.1, 0.2, np.nan, np.inf]}, bins=3))
        assert a == _hist_steps(deadline.gap_histogram({"a": [0.1, 0.2]}, bins=3))
        t = deadline.answer_times({"a": [5.0, 1.0, 0.0]}, 100).axes[0].lines[0].get_ydata()
        t2 = deadline.answer_times({"a": (Decimal(5), Fraction(1), 0)}, 100).axes[0].lines[0].get_ydata()
        assert np.array_equal(t, t2) and t.tolist() == [0.0, 1.0, 5.0]
    finally:
        plt.close("all")


@pytest.mark.parametrize("call, match", [
    (lambda: fl.repeats.against_spread(1.0, 1.05, [0.1]), r"spread_ must be a finite number >= 0"),
    (lambda: fl.repeats.against_spread(1.0, 1.05, np.array([0.1])), r"spread_ must be a finite number >= 0"),
    (lambda: fl.arm.arm_obstacle_cbfs([0.0, -0.9], [0.1]), r"radius must be a finite number > 0"),
    (lambda: fl.arm.arm_obstacle_cbfs([0.0, -0.9], np.array([0.1])), r"radius must be a finite number > 0"),
])
def test_scalar_settings_are_single_numbers_everywhere(call, match):
    from flnotes import arm, repeats  # noqa: F401 - the submodules, as fl's attributes

    with pytest.raises((ValueError, TypeError), match=match):
        call()


def test_a_number_for_every_input_of_a_batch_is_read_alike_by_the_enclosure_and_the_atlas(small_enclosure, small_atlas):
    net, enc = small_enclosure
    lo, hi = np.full((2, 3), -0.5), np.array([[0.5] * 3, [0.4] * 3])
    assert enc.covers(-0.5, hi) == enc.covers(lo, hi) is True
    assert enc.covers(lo, 0.5) == enc.covers(lo, np.full((2, 3), 0.5)) is True
    assert enc.covers(-2.0, hi) == enc.covers(np.full((2, 3), -2.0), hi) is False
    with pytest.raises(ValueError, match="box is empty"):
        enc.covers(0.45, hi)
    _, atlas = small_atlas
    assert atlas.covers(-0.5, hi).tolist() == atlas.covers(lo, hi).tolist() == [True, True]


@pytest.mark.parametrize("seed", [np.random.default_rng(0), np.random.SeedSequence(3), np.random.PCG64(2)])
def test_check_atlas_takes_numpy_s_seed_objects_as_the_plotting_helpers_do(small_atlas, seed):
    """One rule for a seed: what np.random.default_rng takes, without booleans, floats and negative integers."""
    from flnotes.plots import foundations

    net, atlas = small_atlas
    fl.check_atlas(net, atlas, seed=seed)
    fl.check_atlas(net, atlas, seed=np.int64(4))
    for bad in (True, 1.0, -1):
        with pytest.raises(ValueError, match="seed must be an integer >= 0"):
            fl.check_atlas(net, atlas, seed=bad)
    assert foundations.fl_identity_residual(fl.msd(), n=3, seed=seed).shape == (2,)


def test_what_numpy_and_python_take_legitimately_is_taken_again(msd):
    """Forms a third review found refused although they are legitimate: a seed as a sequence of integers (numpy's
    entropy), negative axes and outputs of the plots (counted from the end), a one-state system's state as a number
    in the repairs, an integral float or a range as the frame player's start, a Series or a dict's keys as a
    slider's values, a box without end in ``covers`` (no domain holds it: False), and a gap below 0 by round-off."""
    import matplotlib.pyplot as plt
    from flnotes.plots import deadline as D
    from flnotes.plots import foundations as F

    sysm, net = msd
    a = F.fl_identity_residual(sysm, n=20, seed=[1, 2])
    assert np.array_equal(a, F.fl_identity_residual(sysm, n=20, seed=np.array([1, 2])))
    with pytest.raises(ValueError, match=r"seed\[1\] must be an integer >= 0"):
        F.fl_identity_residual(sysm, n=20, seed=[1, True])
    f1, f2 = F.plot_line_cut(sysm, net, axis=-1, n=11), F.plot_line_cut(sysm, net, axis=sysm.n_in - 1, n=11)
    assert np.array_equal(f1.axes[0].lines[0].get_xdata(), f2.axes[0].lines[0].get_xdata())
    with pytest.raises(ValueError, match=r"axis must be an integer >= -3"):
        F.plot_line_cut(sysm, net, axis=-sysm.n_in - 1, n=11)
    plt.close("all")
    one = fl.integrators(1, [-2.0, -3.0], [2.0, 3.0], 2.5)
    m1 = fl.MPC(one, _identity_net(one), 0.1, horizon=4, ts=0.1, Q=[1.0], R=0.1)
    assert np.array_equal(m1.feasible_tail(0.5, 0.0), m1.feasible_tail([0.5], [0.0]))
    assert np.array_equal(m1.repair_plan(0.5, np.zeros(4))[1], m1.repair_plan([[0.5]], np.zeros(4))[1])
    assert _player(start=[1.0, 0]).start == _player(start=np.array([1, 0])).start == [1, 0]
    assert _player(start=range(1, -1, -1)).start == [1, 0]
    pd = pytest.importorskip("pandas")
    p = _player(sliders={"a": pd.Series([1.0, 2.0]), "b": {0.5: None, 1.5: None}.keys()})
    assert list(p.sliders["a"]) == [1.0, 2.0] and list(p.sliders["b"]) == [0.5, 1.5]
    enc = fl.affine_enclosure(net, sysm.lo, sysm.hi)
    assert enc.covers(sysm.lo - np.inf, sysm.hi) is False and enc.covers(sysm.lo, sysm.hi) is True
    with pytest.raises(ValueError, match="lo contains NaN"):
        enc.covers(np.full(sysm.n_in, np.nan), sysm.hi)
    assert np.array_equal(D._gaps([0.1, -1e-15, np.nan, np.inf], "gaps['a']"), [0.1, 0.0])
    with pytest.raises(ValueError, match=r"gaps\['a'\] must be gaps >= 0"):
        D._gaps([0.1, -1e-6], "gaps['a']")
