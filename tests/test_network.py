"""ReLU networks: forward pass of eq. (recur), scikit-learn import, scaling, save/load, training."""
import warnings

import numpy as np
import pytest
from sklearn.exceptions import ConvergenceWarning
from sklearn.neural_network import MLPRegressor

import flnotes as fl


def _random_net(n_in=3, widths=(7, 5), n_out=2, seed=0):
    rng = np.random.default_rng(seed)
    sizes = (n_in, *widths, n_out)
    return fl.ReLUNet([rng.normal(size=(b, a)) for a, b in zip(sizes[:-1], sizes[1:])],
                      [rng.normal(size=b) for b in sizes[1:]])


def _manual_forward(W, b, x):
    """Eq. (recur) written out for one point, loop by loop."""
    y = np.array(x, float)
    for k in range(len(W)):
        a = np.array([sum(W[k][j, i] * y[i] for i in range(len(y))) + b[k][j] for j in range(len(b[k]))])
        y = a if k == len(W) - 1 else np.array([max(0.0, aj) for aj in a])
    return y


@pytest.mark.parametrize("widths", [(), (4,), (7, 5), (3, 8, 2)])
def test_forward_matches_manual_recursion(widths):
    net = _random_net(widths=widths, seed=len(widths))
    X = np.random.default_rng(1).normal(size=(20, 3))
    out = net(X)
    assert out.shape == (20, 2)
    for x, y in zip(X, out):
        np.testing.assert_allclose(y, _manual_forward(net.W, net.b, x), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(net(X[0]), out[0])  # single point -> (n_out,)
    assert net.K == len(widths) + 1 and net.widths == widths and net.n_hidden == sum(widths)
    y, pre = net.forward(X)
    assert len(pre) == len(widths)
    for a, act in zip(pre, net.activation_pattern(X)):
        np.testing.assert_array_equal(act, a > 0)


def test_from_sklearn_equals_predict():
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (300, 2))
    Y = np.column_stack([np.sin(3 * X[:, 0]) * X[:, 1], X[:, 0] ** 2])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model = MLPRegressor(hidden_layer_sizes=(8, 6), activation="relu", solver="lbfgs", max_iter=50, random_state=0).fit(X, Y)
    net = fl.ReLUNet.from_sklearn(model)
    Xt = rng.uniform(-2, 2, (200, 2))
    np.testing.assert_allclose(net(Xt), model.predict(Xt), rtol=1e-12, atol=1e-12)
    # with the scaling folded into the first and last layer
    xo, xs, yo, ys = np.array([0.5, -1.0]), np.array([2.0, 0.25]), np.array([3.0, -2.0]), np.array([0.1, 5.0])
    wrapped = fl.ReLUNet.from_sklearn(model, xo, xs, yo, ys)
    np.testing.assert_allclose(wrapped(Xt), yo + ys * model.predict((Xt - xo) / xs), rtol=1e-10, atol=1e-10)
    assert wrapped.widths == net.widths  # folding adds no layer


def test_from_sklearn_rejects_other_activations_and_unfitted_models():
    with pytest.raises(ValueError, match="ReLU"):
        fl.ReLUNet.from_sklearn(MLPRegressor(activation="tanh"))
    with pytest.raises(ValueError, match="not fitted"):
        fl.ReLUNet.from_sklearn(MLPRegressor(activation="relu"))


@pytest.mark.parametrize("widths", [(), (6,), (6, 4)])
def test_affine_wrapped(widths):
    net = _random_net(n_in=3, widths=widths, n_out=2, seed=3)
    rng = np.random.default_rng(4)
    xo, xs, yo, ys = rng.normal(size=3), rng.uniform(0.5, 2, 3), rng.normal(size=2), rng.uniform(0.5, 2, 2)
    X = rng.normal(size=(50, 3))
    np.testing.assert_allclose(net.affine_wrapped(xo, xs, yo, ys)(X), yo + ys * net((X - xo) / xs), atol=1e-12)


def test_fit_relu_folds_its_scaling_exactly():
    """fit_relu's net equals y_off + y_sc * model((x - x_off) / x_sc) of the sklearn model it trains."""
    f = lambda X: np.sin(2 * X[:, :1]) + X[:, 1:2] ** 2
    lo, hi = np.array([-1.0, 0.0]), np.array([2.0, 1.0])
    net, rep = fl.fit_relu(f, lo, hi, widths=(8, 8), n_per_axis=12, max_train=None, max_iter=200, seed=3)
    X = fl.uniform_grid(lo, hi, 12)
    Y = f(X)
    xo, xs, yo, ys = (lo + hi) / 2, (hi - lo) / 2, Y.mean(0), Y.std(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model = MLPRegressor(hidden_layer_sizes=(8, 8), activation="relu", solver="lbfgs", alpha=0.0, max_iter=200, max_fun=2000,
                             tol=1e-10, random_state=3).fit((X - xo) / xs, ((Y - yo) / ys).ravel())
    Xt = np.random.default_rng(0).uniform(lo, hi, (100, 2))
    np.testing.assert_allclose(net(Xt)[:, 0], yo[0] + ys[0] * model.predict((Xt - xo) / xs), rtol=1e-8, atol=1e-8)


def test_save_load_round_trip(tmp_path):
    net = _random_net(widths=(5, 4, 3), seed=7)
    path = tmp_path / "net.npz"
    net.save(path)
    back = fl.ReLUNet.load(path)
    assert back.K == net.K and back.widths == net.widths
    for a, b in zip(net.W + net.b, back.W + back.b):
        np.testing.assert_array_equal(a, b)
    X = np.random.default_rng(0).normal(size=(10, 3))
    np.testing.assert_array_equal(back(X), net(X))


def test_wrong_shapes_raise():
    with pytest.raises(ValueError, match="rows but b"):
        fl.ReLUNet([np.ones((3, 2))], [np.ones(4)])
    with pytest.raises(ValueError, match="columns but layer 1 has 3 neurons"):
        fl.ReLUNet([np.ones((3, 2)), np.ones((1, 4))], [np.ones(3), np.ones(1)])
    with pytest.raises(ValueError, match="as many weight matrices"):
        fl.ReLUNet([np.ones((3, 2))], [])
    with pytest.raises(ValueError, match="NaN"):
        fl.ReLUNet([np.array([[np.nan, 1.0]])], [np.ones(1)])
    net = _random_net()
    with pytest.raises(ValueError, match=r"x must have shape \(N, 3\)"):
        net(np.ones((4, 2)))
    with pytest.raises(ValueError, match="x must have shape"):
        net(np.ones(5))
    with pytest.raises(ValueError, match="NaN"):
        net(np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match="widths"):
        fl.fit_relu(lambda X: X[:, :1], [0, 0], [1, 1], widths=())
    with pytest.raises(ValueError, match="box is empty"):
        fl.fit_relu(lambda X: X[:, :1], [0, 2], [1, 1])
    with pytest.raises(ValueError, match="n_per_axis"):
        fl.uniform_grid([0, 0], [1, 1], 1)


def test_fit_relu_small_smooth_function_and_report():
    f = lambda X: np.sin(np.pi * X[:, :1]) * np.cos(X[:, 1:2]) + 0.3 * X[:, 1:2]
    lo, hi = np.array([-1.0, -1.0]), np.array([1.0, 1.0])
    net, rep = fl.fit_relu(f, lo, hi, widths=(16, 16), n_per_axis=25, max_train=None, max_iter=1500, seed=0)
    X = fl.uniform_grid(lo, hi, 25)
    err = np.abs(net(X) - f(X))
    assert rep.grid_max_error.shape == (1,)
    np.testing.assert_allclose(rep.grid_max_error, err.max(0))
    np.testing.assert_allclose(rep.grid_rmse, np.sqrt((err**2).mean(0)))
    assert rep.grid_max_error[0] < 0.08 and rep.grid_rmse[0] < 0.02  # the function's range is about [-1.3, 1.3]
    assert rep.grid_rmse[0] <= rep.grid_max_error[0]
    assert (rep.n_grid, rep.n_train, rep.widths, rep.n_per_axis) == (625, 625, (16, 16), (25, 25))
    assert 0 < rep.n_iter <= 1500 and rep.time_s > 0
    assert net.n_in == 2 and net.n_out == 1 and net.widths == (16, 16)
    assert "grid max |error|" in str(rep)
    assert f"{rep.time_s:.1f} s" not in str(rep) and "iterations" in str(rep)  # no machine-dependent time printed
    # a random subset when the grid is larger than max_train
    _, rep2 = fl.fit_relu(f, lo, hi, widths=(4,), n_per_axis=(30, 20), max_train=100, max_iter=20, seed=1)
    assert (rep2.n_grid, rep2.n_train, rep2.n_per_axis) == (600, 100, (30, 20))
