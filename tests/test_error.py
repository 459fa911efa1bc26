"""The error bound eps of eq. (approx_err): PSO estimate and certified bracket (flnotes.error, flnotes.interval)."""
from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

import flnotes as fl
from flnotes import interval as iv
from flnotes.error import (ErrorBracket, NotCertifiable, certify_error, grid_max_error, pso_max_error,
                           worst_violation)
from flnotes.interval import Interval

N_DENSE = 100_000


def _dense_max(f, net, lo, hi, seed=123):
    X = np.random.default_rng(seed).uniform(lo, hi, (N_DENSE, len(lo)))
    Y = np.asarray(f(X), float).reshape(N_DENSE, -1)
    return np.abs(Y - net(X)).max(0)


# --------------------------------------------------------------------------- interval arithmetic
def test_rounding_is_outward_for_exact_rationals():
    rng = np.random.default_rng(0)
    a, b = rng.uniform(-3, 3, 200), rng.uniform(-3, 3, 200)
    A, B = Interval(a), Interval(b)
    for op, name in ((lambda x, y: x + y, "+"), (lambda x, y: x - y, "-"), (lambda x, y: x * y, "*"),
                     (lambda x, y: x / y, "/")):
        R = op(A, B)
        for k in range(len(a)):
            exact = op(Fraction(a[k]), Fraction(b[k]))
            assert Fraction(R.lo[k]) <= exact <= Fraction(R.hi[k]), name
    # a matrix product with many terms: the midpoint-radius bound must contain the exact rational result
    W, x, c = rng.normal(size=(7, 30)), rng.normal(size=(5, 30)), rng.normal(size=7)
    Y = iv.affine(W, c, Interval(x))
    for t in range(5):
        for j in range(7):
            exact = sum(Fraction(W[j, i]) * Fraction(x[t, i]) for i in range(30)) + Fraction(c[j])
            assert Fraction(Y.lo[t, j]) <= exact <= Fraction(Y.hi[t, j])


@pytest.mark.parametrize("fun, np_fun, lo_range", [
    (iv.exp, np.exp, (-3, 3)), (iv.tanh, np.tanh, (-3, 3)), (iv.sqrt, np.sqrt, (0.1, 4)),
    (iv.abs_, np.abs, (-2, 2)), (iv.arcsin, np.arcsin, (-0.9, 0.8)), (iv.sqr, np.square, (-2, 2)),
    (lambda x: 1.0 / (1.0 + iv.sqr(x)), lambda x: 1.0 / (1.0 + x**2), (-2, 2)),
    (lambda x: x**3 - 2.0 * x, lambda x: x**3 - 2 * x, (-2, 2)),
])
def test_value_and_gradient_enclosures(fun, np_fun, lo_range):
    rng = np.random.default_rng(1)
    lo = rng.uniform(*lo_range, (3000, 1))
    hi = np.minimum(lo + rng.uniform(0, 0.1, lo.shape), lo_range[1] + 0.09)
    Y = fun(Interval.variables(lo, hi))
    x = rng.uniform(lo, hi)
    h = 1e-6
    x_up, x_dn = np.minimum(x + h, hi), np.maximum(x - h, lo)
    y, d = np_fun(x), (np_fun(x_up) - np_fun(x_dn)) / (x_up - x_dn)
    assert np.all((Y.lo <= y) & (y <= Y.hi))
    assert np.all((Y.dlo[..., 0] - 1e-5 <= d) & (d <= Y.dhi[..., 0] + 1e-5))


def test_system_phi_intervals_enclose_phi_and_gradient():
    rng = np.random.default_rng(2)
    for s in (fl.msd(), fl.quad1d()):
        lo = rng.uniform(s.lo, s.hi, (5000, s.n_in))
        hi = np.minimum(lo + rng.uniform(0, 0.2, lo.shape), s.hi)
        X = Interval.variables(lo, hi)
        F = s.phi_interval(X[:, : s.n_z], X[:, s.n_z:])
        P = rng.uniform(lo, hi)
        y = s.phi_stacked(P)
        assert np.all((F.lo <= y) & (y <= F.hi))
        for j in range(s.n_in):
            e = np.zeros(s.n_in)
            e[j] = 1e-7
            d = (s.phi_stacked(np.minimum(P + e, hi)) - s.phi_stacked(np.maximum(P - e, lo))) / (
                np.minimum(P + e, hi) - np.maximum(P - e, lo))[:, j:j + 1]
            assert np.all((F.dlo[:, :, j] - 1e-5 <= d) & (d <= F.dhi[:, :, j] + 1e-5))


def _random_net(n_in, widths, n_out, seed):
    rng = np.random.default_rng(seed)
    sizes = [n_in, *widths, n_out]
    return fl.ReLUNet([rng.normal(size=(sizes[k + 1], sizes[k])) / np.sqrt(sizes[k]) for k in range(len(sizes) - 1)],
                      [0.3 * rng.normal(size=sizes[k + 1]) for k in range(len(sizes) - 1)])


def test_network_enclosures_are_sound():
    net = _random_net(3, (12, 12, 12), 2, seed=3)
    rng = np.random.default_rng(4)
    lo = rng.uniform(-2, 2, (400, 3))
    hi = lo + rng.uniform(0, 1.0, lo.shape)
    X = Interval.variables(lo, hi)
    N = iv.net_interval(net, X)
    pre = iv.net_preactivations(net, Interval(lo, hi))
    bounds = [iv.net_linear_bound(net, pre, Interval(lo, hi), i, s) for i in range(2) for s in (1.0, -1.0)]
    for t in range(0, 400, 40):
        P = rng.uniform(lo[t], hi[t], (2000, 3))
        Y = net(P)
        assert np.all((N.lo[t] <= Y) & (Y <= N.hi[t]))
        for (a, c), (i, s) in zip(bounds, [(i, s) for i in range(2) for s in (1.0, -1.0)]):
            assert np.all(s * Y[:, i] >= P @ a[t] + c[t] - 1e-12)
        # Clarke Jacobian enclosure: finite differences of the network inside the box
        h = 1e-6 * (hi[t] - lo[t])
        for j in range(3):
            Q = P.copy()
            Q[:, j] = np.clip(Q[:, j], lo[t, j], hi[t, j] - h[j])
            d = (net(Q + np.eye(3)[j] * h[j]) - net(Q)) / h[j]
            assert np.all((N.dlo[t, :, j] - 1e-6 <= d) & (d <= N.dhi[t, :, j] + 1e-6))


# --------------------------------------------------------------------------- the two systems
@pytest.mark.parametrize("name", ["MSD", "Quad-1D"])
def test_certified_eps_dominates_dense_sample_and_pso(name):
    s = fl.paper.system(name)
    net, _ = fl.paper_net(name)
    br = fl.paper.paper_eps(name)
    assert isinstance(br, ErrorBracket) and br.converged.all()
    dense = _dense_max(s.phi_stacked, net, s.lo, s.hi)
    pso = pso_max_error(s, net, seed=7)
    assert np.all(br.upper >= dense)
    assert np.all(br.upper >= pso.eps)
    assert np.all(br.lower <= br.upper)
    assert np.all(br.width <= br.rtol * br.lower + 1e-15)
    # the lower end is attained: the error at the reported maximizer is at least `lower`
    at = np.abs(s.phi_stacked(br.argmax) - net(br.argmax))[np.arange(s.m), np.arange(s.m)]
    assert np.all(at >= br.lower - 1e-12)


def test_certification_from_scratch_matches_cached_and_pso_is_deterministic():
    s = fl.msd()
    net, _ = fl.paper_net("MSD")
    br = certify_error(s, net, rtol=0.05)
    ref = fl.paper.paper_eps("MSD")
    assert br.lower[0] <= ref.upper[0] and ref.lower[0] <= br.upper[0]      # the two brackets overlap
    assert br.width[0] <= 0.05 * br.lower[0] + 1e-15
    a, b = pso_max_error(s, net, seed=3), pso_max_error(s, net, seed=3)
    assert np.array_equal(a.eps, b.eps) and np.array_equal(a.argmax, b.argmax)


def test_certified_eps_keeps_the_true_input_bound():
    """Proposition 1: with the certified eps no point satisfying |Phi_NN| <= u_max - eps has |Phi| > u_max."""
    s = fl.msd()
    net, _ = fl.paper_net("MSD")
    br = fl.paper.paper_eps("MSD")
    res = worst_violation(s, net, br.upper, at=br.argmax, n_z=300, n_v=1001)
    assert res["n_feasible"] > 0 and np.all(res["violation"] <= 0)
    # ... while an eps below the certified lower bound lets the network allow true inputs beyond u_max
    bad = worst_violation(s, net, 0.5 * br.lower, at=br.argmax, n_z=300, n_v=1001)
    assert np.any(bad["violation"] > 0)


# --------------------------------------------------------------------------- user-supplied Phi
def _smooth_f(X):
    return np.hstack([np.exp(-X[:, :1] ** 2) * np.tanh(2 * X[:, 1:2]) + np.sqrt(1 + X[:, 2:3] ** 2),
                      np.abs(X[:, :1] - 0.2) * X[:, 1:2] / (2.0 + X[:, 2:3] ** 2)])


def _smooth_f_interval(X):
    a = iv.exp(-iv.sqr(X[:, 0:1])) * iv.tanh(2.0 * X[:, 1:2]) + iv.sqrt(1.0 + iv.sqr(X[:, 2:3]))
    b = iv.abs(X[:, 0:1] - 0.2) * X[:, 1:2] / (2.0 + iv.sqr(X[:, 2:3]))
    return iv.hstack([a, b])


def test_random_network_against_smooth_user_function():
    net = _random_net(3, (16, 16), 2, seed=5)
    lo, hi = np.array([-1.5, -1.0, -2.0]), np.array([1.0, 1.5, 1.0])
    br = certify_error(_smooth_f, net, lo, hi, f_interval=_smooth_f_interval, rtol=0.01)
    dense = _dense_max(_smooth_f, net, lo, hi)
    pso = pso_max_error(_smooth_f, net, lo, hi, n_particles=40, n_iter=100)
    assert br.upper.shape == (2,) and br.converged.all()
    assert np.all(br.upper >= dense) and np.all(br.upper >= pso.eps)
    assert np.all(br.width <= 0.01 * br.lower + 1e-15)


# --------------------------------------------------------------------------- a known answer
@pytest.mark.parametrize("depth", [1, 4])
def test_bracket_contains_exact_max_for_piecewise_linear_f(depth):
    """1-D: f(x) = |x| - 0.5 |x - 0.3| and a one-hidden-layer net fitted to it. Both are piecewise linear, so
    |f - net| is maximal at a breakpoint of f (0, 0.3), of the net (-b_j / w_j) or an end of the interval."""
    def f(X):
        return np.abs(X) - 0.5 * np.abs(X - 0.3)

    def f_iv(X):
        return iv.abs(X) - 0.5 * iv.abs(X - 0.3)

    lo, hi = np.array([-1.0]), np.array([1.0])
    net, _ = fl.fit_relu(f, lo, hi, widths=(6,), n_per_axis=41, max_iter=200, seed=0)
    W, b = net.W[0][:, 0], net.b[0]
    kinks = -b[W != 0] / W[W != 0]
    cand = np.concatenate([[-1.0, 1.0, 0.0, 0.3], kinks[(kinks >= -1) & (kinks <= 1)]])[:, None]
    exact = np.abs(f(cand) - net(cand)).max()
    br = certify_error(f, net, lo, hi, f_interval=f_iv, rtol=1e-6, depth=depth)
    assert br.lower[0] <= exact <= br.upper[0] + 1e-12
    assert br.width[0] <= 1e-6 * exact + 1e-12
    # the same with only a Lipschitz constant of f (|f'| <= 1 + 0.5)
    lip = certify_error(f, net, lo, hi, lipschitz=1.5, rtol=1e-4, depth=depth)
    assert lip.method == "lipschitz" and lip.converged.all()
    assert lip.lower[0] <= exact <= lip.upper[0] + 1e-12
    assert pso_max_error(f, net, lo, hi).eps[0] <= exact + 1e-12
    assert grid_max_error(f, net, lo, hi, 2001).eps[0] <= exact + 1e-12


@pytest.mark.parametrize("depth", [1, 4])
def test_bracket_contains_known_bump_height_in_3d(depth):
    """f = net + a tent of height 0.3 centred at x0: the error |f - net| is the tent, whose max is exactly 0.3."""
    net = _random_net(3, (10, 10), 1, seed=8)
    x0, r = np.array([0.2, -0.4, 0.1]), 0.5

    def f(X):
        return net(X) + 0.3 * np.maximum(1.0 - np.abs(X - x0).sum(1, keepdims=True) / r, 0.0)

    def f_iv(X):
        d = iv.abs(X[:, 0:1] - x0[0]) + iv.abs(X[:, 1:2] - x0[1]) + iv.abs(X[:, 2:3] - x0[2])
        return iv.net_interval(net, X) + 0.3 * iv.relu(1.0 - d / r)

    lo, hi = -np.ones(3), np.ones(3)
    br = certify_error(f, net, lo, hi, f_interval=f_iv, rtol=1e-3, depth=depth)
    assert br.lower[0] <= 0.3 <= br.upper[0] and br.upper[0] <= 0.3 * 1.001 + 1e-12


@pytest.mark.parametrize("depth", [1, 3])
def test_kept_partition_tiles_the_box_and_bounds_the_error_on_every_leaf(depth):
    """The final sub-boxes (keep_partition) cover the box without overlap, each leaf's upper bound is at least the
    error at points inside it, and the largest of them is the bracket's upper end; also when boxes are pruned
    inside the tasks (depth > 1)."""
    s = fl.msd()
    net, _ = fl.paper_net("MSD")
    mid, half = 0.5 * (s.lo + s.hi), 0.5 * (s.hi - s.lo)
    box_lo, box_hi = mid - 0.2 * half, mid + 0.2 * half             # a sub-box: about a thousand leaves
    br = certify_error(s, net, box_lo, box_hi, rtol=0.02, batch=64, chunk=32, depth=depth, keep_partition=True)
    part = br.partition[0]
    lo, hi, ub = part["lo"], part["hi"], part["ub"]
    assert br.converged[0] and len(ub) == len(lo) == len(hi) > 100 and len(br.history[0]) > 5
    assert np.prod(hi - lo, axis=1).sum() == pytest.approx(np.prod(box_hi - box_lo), rel=1e-12)
    assert ub.max() == br.upper[0]
    rng = np.random.default_rng(1)
    X = rng.uniform(box_lo, box_hi, (20_000, 3))
    inside = np.all((X[:, None, :] >= lo[None]) & (X[:, None, :] <= hi[None]), axis=2)
    assert inside.any(1).all()                                          # every point lies in a leaf
    err = np.abs(s.phi_stacked(X) - net(X))[:, 0]
    worst = np.where(inside, err[:, None], -np.inf).max(0)              # the largest sampled error in each leaf
    assert np.all(worst <= ub + 1e-12)


def test_deeper_tasks_give_a_sound_bracket_in_fewer_rounds():
    s = fl.msd()
    net, _ = fl.paper_net("MSD")
    kw = dict(rtol=0.01, batch=512, chunk=256, n_samples=500)
    flat, deep = certify_error(s, net, **kw), certify_error(s, net, **kw, depth=4)
    assert flat.converged.all() and deep.converged.all()
    assert len(deep.history[0]) < len(flat.history[0])                 # fewer dependent rounds
    assert deep.lower[0] <= flat.upper[0] and flat.lower[0] <= deep.upper[0]   # the brackets overlap
    assert deep.width[0] <= 0.01 * deep.lower[0] + 1e-15
    dense = _dense_max(s.phi_stacked, net, s.lo, s.hi)
    assert deep.upper[0] >= dense[0]


# --------------------------------------------------------------------------- bad input
def test_bad_inputs_give_clear_errors():
    s = fl.msd()
    net, _ = fl.paper_net("MSD")
    with pytest.raises(ValueError, match="box is empty"):
        certify_error(s, net, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="box is empty"):
        pso_max_error(s, net, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match=r"shape \(1, 3\)|lo must have shape"):
        certify_error(s, net, np.zeros(2), np.ones(2))
    with pytest.raises(ValueError, match="returned shape"):
        certify_error(lambda X: X[:, :2], net, s.lo, s.hi, lipschitz=1.0)
    with pytest.raises(ValueError, match="returned shape"):
        pso_max_error(lambda X: X.sum(), net, s.lo, s.hi)
    with pytest.raises(NotCertifiable, match="cannot certify"):
        certify_error(s.phi_stacked, net, s.lo, s.hi)
    for bad in (0, 2.0, True):
        with pytest.raises(ValueError, match="depth must be an integer >= 1"):
            certify_error(s, net, depth=bad)
    # every option that shapes the search or its budget: a wrong type or value is named, never run with
    for kw, match in [(dict(batch=1.5), "batch must be an integer >= 1"), (dict(batch=None), "batch must be"),
                      (dict(batch=True), "batch must be"), (dict(initial_per_axis=1.5), "initial_per_axis must be"),
                      (dict(initial_per_axis=True), "initial_per_axis must be"), (dict(n_samples=1.5), "n_samples must"),
                      (dict(n_samples=-1), "n_samples must be an integer >= 1"), (dict(max_boxes=None), "max_boxes"),
                      (dict(max_boxes=0), "max_boxes must be an integer >= 1"), (dict(max_boxes=1.5), "max_boxes"),
                      (dict(max_time=float("nan")), "max_time must be a finite number > 0"),
                      (dict(max_time=-1.0), "max_time must be"), (dict(max_time=0), "max_time must be"),
                      (dict(rtol="x"), "rtol must be a finite number >= 0"), (dict(rtol=-0.1), "rtol must be"),
                      (dict(atol=float("inf")), "atol must be a finite number"), (dict(rtol=0.0, atol=0.0),
                                                                                 "rtol or atol must be positive"),
                      (dict(seed=-1), "seed must be an integer >= 0"), (dict(chunk=0), "chunk must be"),
                      (dict(n_samples=0), "n_samples must be an integer >= 1"),
                      (dict(keep_partition="no"), "keep_partition must be True or False"),
                      (dict(keep_partition=None), "keep_partition must be"), (dict(progress=7), "progress must be"),
                      (dict(resume="yes"), "resume must be True or False"),
                      (dict(seeds="abc"), "seeds must be numbers"),
                      (dict(lipschitz=1.0), "lipschitz was given for the system 'MSD', which has phi_interval")]:
        with pytest.raises(ValueError, match=match):
            certify_error(s, net, **kw)
    with pytest.raises(NotCertifiable, match="flnotes.interval"):
        certify_error(s.phi_stacked, net, s.lo, s.hi, f_interval=lambda X: np.exp(X.lo[:, :1]))


def test_singular_phi_is_not_certifiable():
    q = fl.quad1d()
    net, _ = fl.paper_net("Quad-1D")
    lo, hi = q.lo.copy(), q.hi.copy()
    lo[2], hi[2] = -12.0, 12.0  # |zeta| reaches 1 (90 degrees of pitch): Phi is undefined there
    with pytest.raises(NotCertifiable, match="arcsin|sqrt"):
        certify_error(q, net, lo, hi)


def test_pso_moves_respect_the_velocity_clip_and_the_box():
    """eq. (5.4) of the book: every move is at most nu_max (hi - lo) per axis and stays in the box."""
    lo, hi = np.array([-1.0, 0.0]), np.array([1.0, 4.0])
    trail: list = []
    w_best, c_best, history = fl.error.pso_moves(lambda W: -np.sum((W - [0.3, 3.9]) ** 2, axis=1), lo, hi, 12, 40,
                                                 np.random.default_rng(0), 0.7298, 1.49618, 1.49618, 0.05, trail)
    W = np.array([t[0] for t in trail])                                   # (n_iter + 1, particles, 2)
    assert W.shape == (41, 12, 2) and np.all((W >= lo) & (W <= hi))
    assert np.all(np.abs(np.diff(W, axis=0)) <= 0.05 * (hi - lo) + 1e-15), "a move is larger than the velocity clip"
    assert np.all(np.diff(history) >= 0) and history[-1] == c_best, "the swarm's best never gets worse"
    assert np.isclose(c_best, -np.sum((w_best - [0.3, 3.9]) ** 2))


def test_history_evals_count_the_evaluations_behind_each_best():
    """PSO and DE record how many evaluations each entry of their history cost (their iterations differ in cost)."""
    msd = fl.msd()
    net, _ = fl.paper_net("MSD")
    pso = pso_max_error(msd, net, n_particles=7, n_iter=5, seed=0)
    assert pso.history_evals.shape == pso.history.shape == (1, 6)
    assert np.array_equal(pso.history_evals[0], 7 * np.arange(1, 7)) and pso.history_evals[0, -1] == pso.n_evals
    de = fl.error.de_max_error(msd, net, seed=0, maxiter=4, popsize=5)
    assert de.history_evals.shape == de.history.shape
    assert np.all(np.diff(de.history_evals[0]) > 0) and 0 < de.history_evals[0, -1] <= de.n_evals
    assert de.history_evals[0, 0] == 2 * 5 * 3, "the first generation is recorded after the initial population and one trial"


def test_estimator_convergence_plots_against_evaluations_and_swarm_has_a_colorbar():
    import matplotlib
    matplotlib.use("Agg")
    import flnotes.plots  # noqa: F401  (registers fl.plots)
    msd = fl.msd()
    net, _ = fl.paper_net("MSD")
    pso = pso_max_error(msd, net, n_particles=10, n_iter=4, seed=0, record=True)
    grid = grid_max_error(msd, net, n_per_axis=5)
    ax = fl.plots.estimator_convergence([pso, grid])
    assert np.array_equal(ax.lines[0].get_xdata(), pso.history_evals[0]) and "evaluations" in ax.get_xlabel()
    assert any(np.array_equal(line.get_xdata(), [grid.n_evals]) for line in ax.lines), "grid drawn at its evaluations"
    axes = fl.plots.pso_swarm(msd, net, pso, iterations=(0, 4))
    assert len(axes[0].figure.axes) == 3, "two panels and one colorbar for the error background"
    matplotlib.pyplot.close("all")


def test_enclosure_widths_sample_the_box_vertices():
    """The sampled maximum of enclosure_widths covers the box's vertices, where an almost affine error peaks."""
    import itertools
    msd = fl.msd()
    net, _ = fl.paper_net("MSD")
    pt, r = np.array([1.8, 0.33, 5.0]), 0.01
    (row,) = fl.error.enclosure_widths(msd, net, pt, radii=(r,), n_samples=10)
    V = np.array(list(itertools.product(*zip(pt - r, pt + r))))
    assert row["sampled max error"] >= np.abs(msd.phi_stacked(V) - net(V))[:, 0].max()
    assert row["sampled max error"] <= row["certify_error's bound"] <= row["natural interval bound"] + 1e-12


def test_a_network_equal_to_phi_gets_a_converged_bracket_at_the_rounding_floor():
    """``Phi(z, v) = v`` and ``Phi_NN = relu(v) - relu(-v)``: the error is 0, so ``rtol * lower`` is 0 and only the
    default absolute width (rounding, relative to Phi's scale) can end the search; with ``atol=0`` it cannot."""
    net = fl.ReLUNet([np.array([[0.0, 1.0], [0.0, -1.0]]), np.array([[1.0, -1.0]])], [np.zeros(2), np.zeros(1)])
    f = lambda X: 3.0 * X[:, 1:2]  # noqa: E731
    net3 = fl.ReLUNet([net.W[0], 3.0 * net.W[1]], net.b)
    br = fl.certify_error(f, net3, [-1.0, -1.0], [1.0, 1.0], f_interval=f, n_samples=200)
    assert br.converged.all() and br.lower[0] == 0.0
    assert fl.error.ATOL_ROUNDING * 2.9 < br.atol <= fl.error.ATOL_ROUNDING * 3.0  # |Phi| <= 3, nearly attained
    assert 0.0 <= br.upper[0] <= br.atol
    stuck = fl.certify_error(f, net3, [-1.0, -1.0], [1.0, 1.0], f_interval=f, n_samples=200, atol=0, max_boxes=500)
    assert not stuck.converged.any() and stuck.upper[0] >= 0.0
    wrong = fl.ReLUNet([net.W[0], 2.0 * net.W[1]], net.b)  # error |v| <= 1, attained at v = +-1
    br = fl.certify_error(f, wrong, [-1.0, -1.0], [1.0, 1.0], f_interval=f, n_samples=200)
    assert br.converged.all() and br.lower[0] <= 1.0 <= br.upper[0] <= 1.0 * (1 + br.rtol)
