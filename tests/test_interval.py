"""flnotes.interval covers the functions users' Phi need: sound, outward-rounded, reasonably tight.

For each function: many random boxes of several sizes and positions (seeded numpy sampling), many points
in each; every value at a point must lie in the box's enclosure (and every derivative in the gradient
enclosure); on a point interval [x, x] the enclosure must reach past the float result by at least one
ulp on each side (outward rounding); on small boxes its width must be close to the true range's.
"""
from __future__ import annotations

import numpy as np
import pytest

import flnotes as fl
from flnotes import interval as iv
from flnotes.interval import Interval, NotCertifiable

N_BOXES, PER_BOX = 2000, 50


def _boxes(rng, lo_range, n=N_BOXES):
    """Random boxes inside lo_range, with widths from 1e-9 to the whole range (log-uniform)."""
    a, b = lo_range
    w = (b - a) * 10.0 ** rng.uniform(-9, 0, n)
    lo = rng.uniform(a, b - w)
    return lo, lo + w


def _check_function(fun, np_fun, d_fun, lo_range, seed):
    rng = np.random.default_rng(seed)
    lo, hi = _boxes(rng, lo_range)
    Y = fun(Interval.variables(lo[:, None], hi[:, None]))
    x = rng.uniform(np.repeat(lo, PER_BOX), np.repeat(hi, PER_BOX))
    x[::PER_BOX], x[1::PER_BOX] = lo, hi                                  # the end points too
    ylo, yhi = np.repeat(Y.lo[:, 0], PER_BOX), np.repeat(Y.hi[:, 0], PER_BOX)
    y = np_fun(x)
    assert np.all((ylo <= y) & (y <= yhi)), "a value lies outside its box's enclosure"
    dlo, dhi = np.repeat(Y.dlo[:, 0, 0], PER_BOX), np.repeat(Y.dhi[:, 0, 0], PER_BOX)
    d = d_fun(x)
    tol = 1e-12 * (1.0 + np.abs(d))                                      # d_fun is itself rounded
    assert np.all((dlo - tol <= d) & (d <= dhi + tol)), "a derivative lies outside the gradient enclosure"
    return lo, hi, Y


def _check_outward(fun, np_fun, lo_range, seed):
    """On [x, x] the enclosure contains the float result and one more float on each side."""
    x = np.random.default_rng(seed).uniform(*lo_range, 5000)
    Y = fun(Interval(x, x))
    y = np_fun(x)
    assert np.all(Y.lo <= np.nextafter(y, -np.inf)) and np.all(Y.hi >= np.nextafter(y, np.inf))


def _check_tight(fun, np_fun, lo_range, seed, rel=1e-6):
    """On small boxes the enclosure's width is the true range's, up to rounding (monotone pieces: end points)."""
    rng = np.random.default_rng(seed)
    r = 1e-3 * (lo_range[1] - lo_range[0])
    c = rng.uniform(lo_range[0] + r, lo_range[1] - r, 500)
    Y = fun(Interval(c - r, c + r))
    t = np.linspace(-1.0, 1.0, 201)
    vals = np_fun(c[:, None] + r * t[None, :])
    true_w = vals.max(1) - vals.min(1)
    assert np.all(Y.hi - Y.lo <= true_w * (1 + rel) + 1e-12 + 2 * r * 1e-3), "enclosure much wider than the range"


FUNCTIONS = {
    # name: (interval function, numpy function, derivative, range of the boxes)
    "sin": (iv.sin, np.sin, np.cos, (-20.0, 20.0)),
    "cos": (iv.cos, np.cos, lambda x: -np.sin(x), (-20.0, 20.0)),
    "tan": (iv.tan, np.tan, lambda x: 1 + np.tan(x) ** 2, (-1.5, 1.5)),
    "arctan": (iv.arctan, np.arctan, lambda x: 1 / (1 + x**2), (-30.0, 30.0)),
    "sqrt": (iv.sqrt, np.sqrt, lambda x: 0.5 / np.sqrt(x), (1e-3, 50.0)),
    "exp": (iv.exp, np.exp, np.exp, (-20.0, 20.0)),
    "log": (iv.log, np.log, lambda x: 1 / x, (1e-3, 50.0)),
    "tanh": (iv.tanh, np.tanh, lambda x: 1 - np.tanh(x) ** 2, (-5.0, 5.0)),
    "x**2": (lambda x: x**2, np.square, lambda x: 2 * x, (-3.0, 3.0)),
    "x**3": (lambda x: x**3, lambda x: x**3, lambda x: 3 * x**2, (-3.0, 3.0)),
    "x**4": (lambda x: x**4, lambda x: x**4, lambda x: 4 * x**3, (-3.0, 3.0)),
    "x**5": (lambda x: iv.pow(x, 5), lambda x: x**5, lambda x: 5 * x**4, (-3.0, 3.0)),
    "x**-2": (lambda x: x**-2, lambda x: x**-2.0, lambda x: -2 * x**-3.0, (0.1, 3.0)),
    "x**-3 (x < 0)": (lambda x: x**-3, lambda x: x**-3.0, lambda x: -3 * x**-4.0, (-3.0, -0.1)),
    "1/x": (lambda x: 1.0 / x, lambda x: 1 / x, lambda x: -1 / x**2, (0.1, 3.0)),
}


@pytest.mark.parametrize("name", list(FUNCTIONS))
def test_enclosure_on_many_random_boxes(name):
    fun, np_fun, d_fun, rng_ = FUNCTIONS[name]
    _check_function(fun, np_fun, d_fun, rng_, seed=sum(map(ord, name)))


@pytest.mark.parametrize("name", list(FUNCTIONS))
def test_outward_rounding(name):
    fun, np_fun, _, rng_ = FUNCTIONS[name]
    _check_outward(fun, np_fun, rng_, seed=3)


@pytest.mark.parametrize("name", list(FUNCTIONS))
def test_tight_on_small_boxes(name):
    fun, np_fun, _, rng_ = FUNCTIONS[name]
    _check_tight(fun, np_fun, rng_, seed=4)


def test_sin_cos_extrema_inside_and_large_boxes():
    """A box around pi/2 reaches sin = 1, one around pi reaches cos = -1; a box of width >= 2 pi gives [-1, 1]."""
    s = iv.sin(Interval(np.pi / 2 - 0.1, np.pi / 2 + 0.1))
    assert s.hi == 1.0 and abs(s.lo - np.sin(np.pi / 2 - 0.1)) < 1e-12
    c = iv.cos(Interval(np.pi - 0.2, np.pi + 0.1))
    assert c.lo == -1.0 and abs(c.hi - np.cos(np.pi - 0.2)) < 1e-12
    for f in (iv.sin, iv.cos):
        w = f(Interval(-3.0, -3.0 + 2 * np.pi))
        assert w.lo == -1.0 and w.hi == 1.0
    # far from 0: still sound
    x = np.random.default_rng(5).uniform(1e5, 1e6, 1000)
    y = iv.sin(Interval(x, x + 1e-3))
    pts = x[:, None] + np.linspace(0, 1e-3, 11)[None]
    assert np.all((y.lo[:, None] <= np.sin(pts)) & (np.sin(pts) <= y.hi[:, None]))


def test_even_powers_have_no_dependency_problem():
    y = Interval(-1.0, 2.0) ** 4
    assert y.lo == 0.0 and 16.0 <= y.hi < 16.0 * (1 + 1e-12)
    y = Interval(-1.0, 2.0) ** 3
    assert y.lo <= -1.0 and y.lo > -1.0 - 1e-12 and 8.0 <= y.hi < 8.0 * (1 + 1e-12)
    assert (Interval(-1.0, 2.0) ** 2.0).hi == (Interval(-1.0, 2.0) ** 2).hi   # an integral float power is fine


@pytest.mark.parametrize("call, match", [
    (lambda: iv.tan(Interval(1.0, 2.0)), "pole"),
    (lambda: iv.tan(Interval(-5.0, -4.6)), "pole"),                         # -3 pi / 2 inside
    (lambda: iv.log(Interval(-1.0, 1.0)), "log of an interval reaching 0 or below"),
    (lambda: iv.sqrt(Interval(-0.5, 1.0)), "sqrt of an interval reaching below 0"),
    (lambda: Interval(-1.0, 1.0) ** -2, "contains 0"),
    (lambda: 2.0 / Interval(-1.0, 1.0), "division by an interval that contains 0"),
    (lambda: Interval(1.0, 2.0) ** 1.5, "only integer powers"),
    (lambda: iv.sin(Interval(0.0, np.inf, check=False)), "unbounded"),
])
def test_domain_errors(call, match):
    with pytest.raises(NotCertifiable, match=match):
        call()


def test_certify_a_pendulum_like_phi_written_with_sin_and_cos():
    """Phi(z, v) = (v + 9.81 sin z1 + 0.1 z2) / cos(z1 / 2): certified upper >= the dense-sampled maximum."""
    A, B = fl.brunovsky(2)

    def phi(z, v):
        return (v + 9.81 * np.sin(z[:, :1]) + 0.1 * z[:, 1:2]) / np.cos(0.5 * z[:, :1])

    def phi_interval(z, v):
        return (v + 9.81 * iv.sin(z[:, 0:1]) + 0.1 * z[:, 1:2]) / iv.cos(0.5 * z[:, 0:1])

    pend = fl.FLSystem("pendulum", A, B, phi=phi, lo=[-2.0, -2.0, -3.0], hi=[2.0, 2.0, 3.0], u_max=20.0,
                       f=lambda x, u: x, to_z=lambda x: x, to_x=lambda z: z, phi_interval=phi_interval)
    # a network with known weights (no training): a coarse piecewise-linear fit is enough to have an error
    rng = np.random.default_rng(0)
    W1 = rng.normal(size=(12, 3))
    b1 = rng.normal(size=12)
    H = np.maximum(pend.grid(9) @ W1.T + b1, 0.0)
    G = np.hstack([H, np.ones((len(H), 1))])
    coef = np.linalg.lstsq(G, pend.phi_stacked(pend.grid(9)), rcond=None)[0]
    net = fl.ReLUNet([W1, coef[:-1].T], [b1, coef[-1]])
    br = fl.certify_error(pend, net, rtol=0.02, n_samples=2000)
    X = np.random.default_rng(1).uniform(pend.lo, pend.hi, (200_000, 3))
    dense = np.abs(pend.phi_stacked(X) - net(X)).max()
    assert br.lower[0] <= br.upper[0]
    assert br.upper[0] >= dense, "the certified bound is below a sampled error"
    assert br.lower[0] >= 0.9 * dense, "the certified lower end is far below the sampled maximum"
    assert br.converged[0] and br.upper[0] <= 1.02 * br.lower[0] + 1e-12
