"""FBBT node bounds (Grimstad & Andersson 2019, Sec. 4.3): soundness, batches, fixed coordinates, stable neurons."""
import numpy as np
import pytest

import flnotes as fl


def _random_net(n_in, widths, seed, scale=1.0):
    rng = np.random.default_rng(seed)
    sizes = (n_in, *widths, 1)
    return fl.ReLUNet([scale * rng.normal(size=(b, a)) / np.sqrt(a) for a, b in zip(sizes[:-1], sizes[1:])],
                      [0.3 * rng.normal(size=b) for b in sizes[1:]])


def _assert_sound(net, lo, hi, n=100_000, seed=0):
    b = fl.fbbt(net, lo, hi)
    pre = fl.sample_preactivations(net, lo, hi, n=n, seed=seed)  # uniform samples plus every corner
    assert len(pre) == len(b.L) == net.K - 1
    for a, L, U in zip(pre, b.L, b.U):
        assert a.shape[1] == L.shape[0]
        assert np.all(L <= U)
        assert np.all(a >= L - 1e-9), (a.min(0) - L).min()
        assert np.all(a <= U + 1e-9), (U - a.max(0)).min()
    assert b.contains(pre)
    X = np.random.default_rng(seed + 1).uniform(lo, hi, (10_000, net.n_in))
    out = net(X)
    assert np.all(out >= b.out_L - 1e-9) and np.all(out <= b.out_U + 1e-9)
    return b, pre


@pytest.mark.parametrize("n_in,widths,seed", [(2, (5,), 0), (3, (10, 10), 1), (4, (8, 12, 6), 2), (3, (20, 20, 20), 3),
                                              (6, (16, 4, 16, 4), 4)])
def test_fbbt_sound_on_random_nets(n_in, widths, seed):
    rng = np.random.default_rng(100 + seed)
    lo = rng.uniform(-3, 0, n_in)
    hi = lo + rng.uniform(0.1, 4, n_in)
    _assert_sound(_random_net(n_in, widths, seed), lo, hi, seed=seed)


def test_fbbt_sound_on_paper_nets():
    for name in ("MSD", "Quad-1D"):
        system = fl.paper.system(name)
        net, _ = fl.paper_net(name)
        b, pre = _assert_sound(net, system.lo, system.hi)
        # first layer: interval arithmetic is exact on an affine map, so the corners attain L and U
        np.testing.assert_allclose(pre[0].min(0), b.L[0], atol=1e-9)
        np.testing.assert_allclose(pre[0].max(0), b.U[0], atol=1e-9)
        # and on a small box around a point of the domain
        c = np.random.default_rng(5).uniform(system.lo, system.hi)
        lo, hi = np.maximum(c - 0.2, system.lo), np.minimum(c + 0.2, system.hi)
        _assert_sound(net, lo, hi, n=20_000)


def test_first_layer_exact_and_deeper_layers_contain_samples():
    net = _random_net(3, (6, 6), seed=9)
    lo, hi = -np.ones(3), np.ones(3)
    b = fl.fbbt(net, lo, hi)
    L, U = fl.interval_affine(net.W[0], net.b[0], lo[None], hi[None])
    np.testing.assert_allclose(b.L[0], L[0])
    np.testing.assert_allclose(b.U[0], U[0])
    W = net.W[0]
    np.testing.assert_allclose(b.U[0], np.abs(W).sum(1) + net.b[0])  # box [-1, 1]^3: U = |W| 1 + b


def test_batch_boxes_agree_with_single_calls():
    net = _random_net(4, (10, 10, 10), seed=11)
    rng = np.random.default_rng(12)
    T = 10  # T == n_k on purpose: a transposition would go unnoticed by shapes
    lo = rng.uniform(-2, 0, (T, 4))
    hi = lo + rng.uniform(0, 2, (T, 4))
    hi[3] = lo[3]  # one degenerate box
    b = fl.fbbt(net, lo, hi)
    assert all(L.shape == (T, 10) for L in b.L) and b.out_L.shape == (T, 1)
    for t in range(T):
        bt = fl.fbbt(net, lo[t], hi[t])
        for k in range(net.K - 1):
            np.testing.assert_allclose(b.L[k][t], bt.L[k], rtol=0, atol=1e-12)
            np.testing.assert_allclose(b.U[k][t], bt.U[k], rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.out_U[t], bt.out_U, rtol=0, atol=1e-12)
    assert b.n_unstable == sum(fl.fbbt(net, lo[t], hi[t]).n_unstable for t in range(T))


def test_fixed_coordinates():
    net = _random_net(3, (12, 12), seed=13)
    z = np.array([0.4, -0.7])
    lo, hi = np.r_[z, -2.0], np.r_[z, 2.0]  # z measured, v free: what a controller sees
    _assert_sound(net, lo, hi, n=20_000)
    full = fl.fbbt(net, np.array([-1.0, -1.0, -2.0]), np.array([1.0, 1.0, 2.0]))
    fixed = fl.fbbt(net, lo, hi)
    for k in range(net.K - 1):  # a sub-box gives bounds inside the full box's ones
        assert np.all(fixed.L[k] >= full.L[k] - 1e-12) and np.all(fixed.U[k] <= full.U[k] + 1e-12)
    assert fixed.n_unstable <= full.n_unstable
    x = np.array([0.4, -0.7, 1.3])
    point = fl.fbbt(net, x, x)  # every coordinate fixed: the bounds are the pre-activations themselves
    for a, L, U in zip(net.preactivations(x), point.L, point.U):
        np.testing.assert_allclose(L, a[0], atol=1e-12)
        np.testing.assert_allclose(U, a[0], atol=1e-12)
    assert point.n_unstable == 0  # (almost surely: no pre-activation is exactly 0)


def test_stable_flags_are_consistent():
    net = _random_net(3, (15, 15, 15), seed=14)
    lo, hi = -np.ones(3), np.ones(3)
    b = fl.fbbt(net, lo, hi)
    pre = fl.sample_preactivations(net, lo, hi, n=20_000)
    total = 0
    for act, ina, uns, L, U, a in zip(b.active, b.inactive, b.unstable, b.L, b.U, pre):
        assert np.all(act.astype(int) + ina.astype(int) + uns.astype(int) == 1)  # a partition
        np.testing.assert_array_equal(act, L >= 0)
        np.testing.assert_array_equal(ina, U <= 0)
        assert np.all(a[:, act] >= 0) and np.all(a[:, ina] <= 0)  # stable neurons never switch
        total += uns.sum()
    assert b.n_unstable == total
    assert b.n_unstable + b.n_stable == net.n_hidden
    assert all(np.all(w >= 0) for w in b.width())
    assert "unstable" in b.summary()


def test_bad_boxes_raise():
    net = _random_net(3, (4,), seed=0)
    with pytest.raises(ValueError, match="box is empty"):
        fl.fbbt(net, np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match=r"lo and hi must have shape \(3,\)"):
        fl.fbbt(net, np.zeros(2), np.ones(2))
    with pytest.raises(ValueError, match="lo and hi must have shape"):
        fl.fbbt(net, np.zeros((2, 3)), np.ones((3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        fl.fbbt(net, np.array([0.0, np.nan, 0.0]), np.ones(3))


def test_exact_preactivation_range_is_the_true_range_and_within_fbbt():
    """Chapter 4's exact ranges: a hand network whose ranges are known, and a random one against samples and FBBT."""
    absnet = fl.ReLUNet([np.array([[1.0], [-1.0]]), np.array([[1.0, 1.0]])], [np.zeros(2), np.zeros(1)])
    L, U = fl.studies.exact_preactivation_range(absnet, np.array([-2.0]), np.array([3.0]))
    assert np.allclose(L, [-2.0, -3.0]) and np.allclose(U, [3.0, 2.0])
    net = _random_net(2, (6, 5), seed=4)
    lo, hi = np.array([-1.0, -2.0]), np.array([1.5, 1.0])
    L, U = fl.studies.exact_preactivation_range(net, lo, hi, layer=-1, neurons=[0, 2, 4])
    pre = fl.sample_preactivations(net, lo, hi, n=50_000)[-1][:, [0, 2, 4]]
    b = fl.fbbt(net, lo, hi)
    assert np.all(L <= pre.min(0) + 1e-7) and np.all(U >= pre.max(0) - 1e-7), "the exact range holds every sample"
    assert np.all(L >= b.L[-1][[0, 2, 4]] - 1e-7) and np.all(U <= b.U[-1][[0, 2, 4]] + 1e-7), "and lies within FBBT"
    # and no wider than the range on a dense grid plus what the pre-activation can change between grid points
    g1, g2 = np.linspace(lo[0], hi[0], 1201), np.linspace(lo[1], hi[1], 1201)
    X = np.stack(np.meshgrid(g1, g2), -1).reshape(-1, 2)
    grid = net.preactivations(X)[-1][:, [0, 2, 4]]
    lip = np.prod([np.linalg.norm(W_k, 2) for W_k in net.W[:-1]])  # of every pre-activation of the last hidden layer
    reach = lip * 0.5 * np.hypot(g1[1] - g1[0], g2[1] - g2[0])  # distance from any point of the box to the grid
    assert np.all(U <= grid.max(0) + reach + 1e-9) and np.all(L >= grid.min(0) - reach - 1e-9), "the range is attained"
    with pytest.raises(ValueError, match="neurons must be indices"):
        fl.studies.exact_preactivation_range(net, lo, hi, neurons=[5])
    # every neuron stable on the box: the program is an LP (HiGHS reports no gap for it), its range still exact
    stable = fl.ReLUNet([np.array([[1.0], [2.0]]), np.array([[1.0, 1.0]])], [np.zeros(2), np.zeros(1)])
    for solver in ("HIGHS", "SCIP"):
        L, U = fl.studies.exact_preactivation_range(stable, np.array([1.0]), np.array([3.0]), solver=solver)
        assert np.allclose(L, [1.0, 2.0]) and np.allclose(U, [3.0, 6.0])


def _knot_range(net, lo: float, hi: float):
    """The range of every pre-activation of the last hidden layer of a one-input network over ``[lo, hi]``, without a
    solver: it is piecewise affine in ``x``, with knots where a neuron of an earlier layer switches. Layer by layer,
    each pre-activation is affine between the knots found so far, so its zeros there are new knots; the extremes lie
    at the knots and the ends."""
    knots = np.array([lo, hi], float)
    for k in range(len(net.W) - 2):
        pre = net.preactivations(knots[:, None])[k]
        a, b = pre[:-1], pre[1:]
        i, j = np.nonzero(a * b < 0)
        knots = np.unique(np.r_[knots, knots[i] + (knots[i + 1] - knots[i]) * a[i, j] / (a[i, j] - b[i, j])])
    last = net.preactivations(knots[:, None])[-1]
    return last.min(0), last.max(0)


@pytest.mark.parametrize("seed", [0, 2])
def test_exact_preactivation_range_of_a_deep_one_input_network_is_the_range_at_its_knots(seed):
    """One input, three hidden layers: the range equals the one computed exactly at the knots (:func:`_knot_range`)
    to 1e-9. Checked against the data too: a grid of 4,000,001 points lies inside the knots' range but misses it by
    more than 1e-9, and so do the samples of ``fl.sample_preactivations``, so a range read off either would fail.
    Seed 2 has a program where HiGHS, asked for a zero gap, reports a round-off gap (1.65e-16) at its optimum."""
    net = _random_net(1, (6, 5, 4), seed=seed)
    lo, hi = -2.0, 3.0
    L, U = fl.studies.exact_preactivation_range(net, np.array([lo]), np.array([hi]))
    L_k, U_k = _knot_range(net, lo, hi)
    tol = 1e-9
    assert np.all(np.abs(U - U_k) <= tol) and np.all(np.abs(L - L_k) <= tol), (L - L_k, U - U_k)
    grid = net.preactivations(np.linspace(lo, hi, 4_000_001)[:, None])[-1]
    sampled = fl.sample_preactivations(net, np.array([lo]), np.array([hi]))[-1]
    for pts in (grid, sampled):
        assert np.all(pts.max(0) <= U_k + 1e-12) and np.all(pts.min(0) >= L_k - 1e-12), "the knots' range holds them"
        assert np.max(np.r_[U_k - pts.max(0), pts.min(0) - L_k]) > 10 * tol, "premise: they miss the range"


def test_slope_in_v_is_the_slope_of_the_piece():
    """Chapter 3's monotonicity check: Phi_NN = max(0, v) + 2 max(0, -v) + 0 z has slope 1 for v > 0, -2 for v < 0."""
    net = fl.ReLUNet([np.array([[0.0, 1.0], [0.0, -1.0]]), np.array([[1.0, 2.0]])], [np.zeros(2), np.zeros(1)])
    v = np.array([-3.0, -0.5, 0.25, 4.0])
    assert np.array_equal(fl.studies.slope_in_v(net, np.array([7.0]), v)[:, 0], [-2.0, -2.0, 1.0, 1.0])
    rnd = _random_net(3, (8, 6), seed=5)
    v = np.linspace(-2, 2, 2001)
    z = np.array([0.3, -0.7])
    f = lambda w: rnd(np.column_stack([np.tile(z, (len(w), 1)), w]))[:, 0]  # noqa: E731
    fd = (f(v + 1e-7) - f(v - 1e-7)) / 2e-7
    pattern = lambda w: np.hstack(rnd.activation_pattern(np.column_stack([np.tile(z, (len(w), 1)), w])))  # noqa: E731
    same_piece = np.all(pattern(v - 1e-7) == pattern(v + 1e-7), axis=1)
    assert same_piece.mean() > 0.9
    assert np.allclose(fl.studies.slope_in_v(rnd, z, v)[same_piece, 0], fd[same_piece], atol=1e-6)
    with pytest.raises(ValueError, match="z must have shape"):
        fl.studies.slope_in_v(rnd, np.zeros(3), v)


def test_bounds_figure_legend_covers_no_axes():
    """The legend of plot_bounds_vs_samples sits outside every panel."""
    import matplotlib
    matplotlib.use("Agg")
    import flnotes.plots  # noqa: F401  (registers fl.plots)
    net = _random_net(2, (5, 4), seed=1)
    fig = fl.plots.plot_bounds_vs_samples(net, -np.ones(2), np.ones(2), n=2000)
    fig.canvas.draw()
    leg = fig.axes[0].get_legend()
    assert leg is not None
    box = leg.get_window_extent()
    assert not any(box.overlaps(ax.get_window_extent()) for ax in fig.axes)
