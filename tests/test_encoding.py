"""The big-M formulation of eq. (MIP_general) is exact: solved with HiGHS it reproduces the forward pass."""
import cvxpy as cp
import numpy as np
import pytest
from scipy.optimize import Bounds, LinearConstraint, milp

import flnotes as fl

TOL = 1e-6
NETS = [(2, (4,), 0), (3, (8, 8), 1), (3, (12, 6, 9), 2), (4, (10, 10, 10), 3), (2, (5, 5, 5, 5), 4)]


def _random_net(n_in, widths, seed, n_out=1):
    rng = np.random.default_rng(seed)
    sizes = (n_in, *widths, n_out)
    return fl.ReLUNet([rng.normal(size=(b, a)) / np.sqrt(a) for a, b in zip(sizes[:-1], sizes[1:])],
                      [0.3 * rng.normal(size=b) for b in sizes[1:]])


def _box(n_in, seed):
    rng = np.random.default_rng(1000 + seed)
    lo = rng.uniform(-2, 0, n_in)
    return lo, lo + rng.uniform(0.5, 3, n_in)


def _extremes_cvxpy(net, bounds, x_value, out_index=0):
    """Min and max of output ``out_index`` of the big-M program with the input fixed to ``x_value``."""
    x = cp.Variable(np.shape(x_value))
    enc = fl.encode(net, x, bounds)
    obj = cp.sum(enc.output[out_index]) if enc.output.ndim == 2 else enc.output[out_index]
    vals = []
    for sense in (cp.Minimize, cp.Maximize):
        prob = cp.Problem(sense(obj), enc.constraints + [x == x_value])
        prob.solve(solver="HIGHS")
        assert prob.status == "optimal", prob.status
        vals.append(prob.value)
        out = np.asarray(enc.output.value)
    return vals, out, enc


def _extremes_form(form, net, x_value, A_ub=None, b_ub=None, lb=None, ub=None):
    A_ub = form.A_ub if A_ub is None else A_ub
    b_ub = form.b_ub if b_ub is None else b_ub
    lb = (form.lb if lb is None else lb).copy()
    ub = (form.ub if ub is None else ub).copy()
    lb[form.x], ub[form.x] = x_value, x_value
    vals = []
    for sign in (1.0, -1.0):
        c = np.zeros(form.n)
        c[form.out[0]] = sign
        res = milp(c, integrality=form.integrality, bounds=Bounds(lb, ub),
                   constraints=[LinearConstraint(form.A_eq, form.b_eq, form.b_eq),
                                LinearConstraint(A_ub, -np.inf, b_ub)])
        assert res.status == 0, res.message
        vals.append(res.x[form.out[0]])
    return vals


@pytest.mark.parametrize("n_in,widths,seed", NETS)
def test_fixed_input_reproduces_forward_pass(n_in, widths, seed):
    """With x fixed, both the minimum and the maximum of the output equal Phi_NN(x): the MILP is exact."""
    net = _random_net(n_in, widths, seed)
    lo, hi = _box(n_in, seed)
    bounds = fl.fbbt(net, lo, hi)
    form = fl.bigm_form(net, bounds)
    X = np.random.default_rng(seed).uniform(lo, hi, (4, n_in))
    for x in X:
        y = net(x)[0]
        (vmin, vmax), _, enc = _extremes_cvxpy(net, bounds, x)
        assert abs(vmin - y) < TOL and abs(vmax - y) < TOL
        assert enc.n_binaries == bounds.n_unstable
        fmin, fmax = _extremes_form(form, net, x)
        assert abs(fmin - y) < TOL and abs(fmax - y) < TOL
        assert abs(fl.forward_milp(net, x)[0] - y) < TOL
        assert abs(fl.forward_milp(net, x, bounds)[0] - y) < TOL


def test_multi_output_network():
    net = _random_net(3, (7, 7), seed=5, n_out=2)
    lo, hi = _box(3, 5)
    bounds = fl.fbbt(net, lo, hi)
    x = np.random.default_rng(0).uniform(lo, hi)
    for i in range(2):
        (vmin, vmax), _, _ = _extremes_cvxpy(net, bounds, x, out_index=i)
        assert abs(vmin - net(x)[i]) < TOL and abs(vmax - net(x)[i]) < TOL
    np.testing.assert_allclose(fl.forward_milp(net, x, bounds), net(x), atol=TOL)


@pytest.mark.parametrize("batch_bounds", [False, True])
def test_horizon_encoding_per_column(batch_bounds):
    """x of shape (n_in, T): every column is encoded, with one set of bounds or one per column."""
    net = _random_net(4, (10, 10, 10), seed=6)
    T = 10  # equal to the widths on purpose
    rng = np.random.default_rng(7)
    if batch_bounds:
        c = rng.uniform(-1, 1, (T, 4))
        lo, hi = c - rng.uniform(0.05, 0.5, (T, 4)), c + rng.uniform(0.05, 0.5, (T, 4))
        X = rng.uniform(lo, hi)
    else:
        lo, hi = -np.ones(4), np.ones(4)
        X = rng.uniform(lo, hi, (T, 4))
    bounds = fl.fbbt(net, lo, hi)
    x = cp.Variable((4, T))
    enc = fl.encode(net, x, bounds)
    assert enc.output.shape == (1, T)
    assert enc.n_binaries == bounds.n_unstable * (1 if batch_bounds else T)
    for sense in (cp.Minimize, cp.Maximize):
        prob = cp.Problem(sense(cp.sum(enc.output)), enc.constraints + [x == X.T])
        prob.solve(solver="HIGHS")
        assert prob.status == "optimal"
        np.testing.assert_allclose(enc.output.value[0], net(X)[:, 0], atol=TOL)


def test_horizon_with_parameter_bounds_keeps_all_binaries():
    net = _random_net(3, (6, 6), seed=8)
    T = 3
    L = [cp.Parameter((6, T)) for _ in range(2)]
    U = [cp.Parameter((6, T)) for _ in range(2)]
    x = cp.Variable((3, T))
    enc = fl.encode(net, x, L=L, U=U)
    assert enc.n_binaries == net.n_hidden * T
    rng = np.random.default_rng(9)
    X = rng.uniform(-1, 1, (T, 3))
    b = fl.fbbt(net, -np.ones(3), np.ones(3))
    for k in range(2):
        L[k].value, U[k].value = np.repeat(b.L[k][:, None], T, 1), np.repeat(b.U[k][:, None], T, 1)
    for sense in (cp.Minimize, cp.Maximize):
        prob = cp.Problem(sense(cp.sum(enc.output)), enc.constraints + [x == X.T])
        prob.solve(solver="HIGHS")
        np.testing.assert_allclose(enc.output.value[0], net(X)[:, 0], atol=TOL)


@pytest.mark.parametrize("n_in,widths,seed", NETS[1:4])
def test_maximum_over_box_beats_dense_sampling(n_in, widths, seed):
    net = _random_net(n_in, widths, seed)
    lo, hi = _box(n_in, seed)
    x = cp.Variable(n_in)
    enc = fl.encode(net, x, fl.fbbt(net, lo, hi))
    prob = cp.Problem(cp.Maximize(enc.output[0]), enc.constraints + [x >= lo, x <= hi])
    prob.solve(solver="HIGHS")
    assert prob.status == "optimal"
    S = np.random.default_rng(seed).uniform(lo, hi, (100_000, n_in))
    S = np.vstack([S, fl.uniform_grid(lo, hi, 2)])  # and the corners
    assert prob.value >= net(S).max() - TOL
    x_star = np.clip(x.value, lo, hi)
    assert abs(net(x_star)[0] - prob.value) < TOL  # the maximizer is a real input with that output


def test_maximum_on_paper_net_matches_sampling():
    system, (net, _) = fl.msd(), fl.paper_net("MSD")
    x = cp.Variable(3)
    enc = fl.encode(net, x, fl.fbbt(net, system.lo, system.hi))
    prob = cp.Problem(cp.Maximize(enc.output[0]), enc.constraints + [x >= system.lo, x <= system.hi])
    prob.solve(solver="HIGHS")
    S = np.random.default_rng(0).uniform(system.lo, system.hi, (100_000, 3))
    assert prob.value >= net(np.vstack([S, system.grid(2)])).max() - TOL
    assert abs(net(x.value)[0] - prob.value) < 1e-5


def test_stable_neurons_create_no_binaries():
    net = _random_net(3, (15, 15), seed=10)
    for lo, hi in [(-np.ones(3), np.ones(3)), (np.array([0.2, 0.3, -1.0]), np.array([0.2, 0.3, 1.0])),
                   (np.full(3, 0.5), np.full(3, 0.5))]:
        bounds = fl.fbbt(net, lo, hi)
        enc = fl.encode(net, cp.Variable(3), bounds)
        assert enc.n_binaries == bounds.n_unstable
        n_alpha = sum(0 if a is None else a.size for a in enc.alpha)
        assert n_alpha == bounds.n_unstable
        assert fl.bigm_form(net, bounds).n_binaries == bounds.n_unstable
    assert fl.fbbt(net, np.full(3, 0.5), np.full(3, 0.5)).n_unstable == 0


def test_bigm_form_update_reproduces_forward_passes():
    """One persistent model, new bounds written by update(): still exact, both ways round."""
    net = _random_net(3, (10, 8), seed=11)
    rng = np.random.default_rng(12)
    box = fl.fbbt(net, -np.ones(3), np.ones(3))
    for x in rng.uniform(-0.9, 0.9, (3, 3)):
        y = net(x)[0]
        point = fl.fbbt(net, x, x)
        near = fl.fbbt(net, x - 0.1, x + 0.1)
        # built on the big box, updated to tight bounds
        form = fl.bigm_form(net, box)
        for new in (point, near):
            A_ub, b_ub, lb, ub = form.update(new)
            assert A_ub.shape == form.A_ub.shape
            vmin, vmax = _extremes_form(form, net, x, A_ub, b_ub, lb, ub)
            assert abs(vmin - y) < TOL and abs(vmax - y) < TOL
        # built on a single point (no unstable neuron), updated to the big box
        form = fl.bigm_form(net, point)
        assert form.n_binaries == 0
        A_ub, b_ub, lb, ub = form.update(box)
        vmin, vmax = _extremes_form(form, net, x, A_ub, b_ub, lb, ub)
        assert abs(vmin - y) < TOL and abs(vmax - y) < TOL


def test_encode_rejects_bad_shapes():
    net = _random_net(3, (4,), seed=0)
    b = fl.fbbt(net, -np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match=r"x must have shape \(3,\) or \(3, T\)"):
        fl.encode(net, cp.Variable(4), b)
    with pytest.raises(ValueError, match="needs node bounds"):
        fl.encode(net, cp.Variable(3))
    with pytest.raises(ValueError, match="one L and one U per hidden layer"):
        fl.encode(net, cp.Variable(3), L=[], U=[])
    with pytest.raises(ValueError, match=r"L\^1 of a layer with 4 neurons"):
        fl.encode(net, cp.Variable(3), L=[np.zeros(5)], U=[np.ones(5)])
    batch = fl.fbbt(net, -np.ones((2, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError, match="batch"):
        fl.encode(net, cp.Variable(3), batch)
    with pytest.raises(ValueError, match="batch of 2 boxes but x has 5 columns"):
        fl.encode(net, cp.Variable((3, 5)), batch)
    with pytest.raises(ValueError, match="one input box"):
        fl.bigm_form(net, batch)
    with pytest.raises(ValueError, match=r"x must have shape \(3,\)"):
        fl.forward_milp(net, np.zeros(2))
