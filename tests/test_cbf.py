"""The exponential (second-order) CBF for a relative-degree-2 barrier: definition, validity, closed loop.

The closed loop uses a double integrator whose input map is Phi(z, v) = v, represented exactly by the
ReLU network sigma(v) - sigma(-v); its premise does not depend on trained weights.
"""
import numpy as np
import pytest

import flnotes as fl

U_MAX = 2.0
EPS = 0.05


def double_integrator():
    A, B = fl.brunovsky(2)
    sysm = fl.FLSystem("DI", A, B, phi=lambda z, v: np.asarray(v, float).reshape(-1, 1), lo=[-3, -3, -6],
                       hi=[3, 3, 6], u_max=U_MAX, f=lambda x, u: np.array([x[1], u[0]]),
                       to_z=lambda x: np.asarray(x, float), to_x=lambda z: np.asarray(z, float))
    net = fl.ReLUNet([np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]), np.array([[1.0, -1.0]])],
                     [np.zeros(2), np.zeros(1)])
    return sysm, net


def test_value_and_gradient_follow_the_definition():
    A, B = fl.brunovsky(2)
    h = fl.AffineCBF([-1.0, 0.0], 1.0)          # h = 1 - z1: a wall at z1 = 1
    H2 = fl.ExponentialCBF(h, A, B, k1=2.0)     # H2 = dh/dt + 2 h = -z2 + 2 (1 - z1)
    Z = np.random.default_rng(0).uniform(-3, 3, (50, 2))
    assert np.allclose(H2(Z), -Z[:, 1] + 2.0 * (1.0 - Z[:, 0]))
    for z in Z[:5]:
        g = np.array([(H2(z + d) - H2(z - d)) / 2e-6 for d in np.eye(2) * 1e-6])
        assert np.allclose(H2.grad(z), g, atol=1e-6)
        # dh/dt along z' = Az + Bv does not contain v; H2's derivative does, with a never-zero coefficient
        assert np.allclose(h.grad(z) @ B, 0.0) and abs(H2.grad(z) @ B[:, 0]) > 0


def test_bad_barriers_are_refused():
    A, B = fl.brunovsky(2)
    with pytest.raises(ValueError, match="relative degree one"):
        fl.ExponentialCBF(fl.AffineCBF([0.0, 1.0], 1.0), A, B, 1.0)
    A3, B3 = fl.brunovsky(3)
    with pytest.raises(ValueError, match="above two"):
        fl.ExponentialCBF(fl.AffineCBF([1.0, 0.0, 0.0], 1.0), A3, B3, 1.0)
    with pytest.raises(ValueError, match="k1"):
        fl.ExponentialCBF(fl.AffineCBF([-1.0, 0.0], 1.0), A, B, 0.0)
    with pytest.raises(TypeError, match="AffineCBF"):
        fl.ExponentialCBF(fl.DistanceCBF([0, 0], 1.0), A, B, 1.0)
    with pytest.raises(ValueError, match="nonzero"):
        fl.AffineCBF([0.0, 0.0], 1.0)


def test_closed_loop_keeps_the_wall_where_the_first_order_condition_cannot():
    sysm, net = double_integrator()
    V = fl.QuadraticCLF(np.array([[2.0, 0.5], [0.5, 1.0]]))
    k = lambda z: -np.array([1.0, 2.0]) @ (z - np.array([2.5, 0.0]))  # pushes the mass towards z1 = 2.5
    h = fl.AffineCBF([-1.0, 0.0], 1.0)                                   # the wall z1 <= 1
    H2 = fl.ExponentialCBF(h, sysm.A, sysm.B, k1=1.5)
    z0 = np.array([-2.0, 0.0])
    assert H2(z0) >= 0 and h(z0) >= 0
    logs = {}
    for name, H in (("first order", h), ("exponential", H2)):
        ctrl = fl.ClfCbfController(sysm, net, EPS, V, H, k, cost="quadratic", backend="exact", kappa=5.0)
        logs[name] = fl.simulate(sysm, ctrl, t_final=6.0, ts=0.02, z0=z0, hold="u", net=net, progress=False)
    first, expo = (fl.studies.clf_cbf_checks(logs[n], h) for n in ("first order", "exponential"))
    # the first-order condition -z2 >= -kappa h does not contain v: infeasible steps, and the wall is crossed
    assert first["fallback_steps"] > 0 and h(logs["first order"].z).min() < 0
    # the exponential CBF keeps h >= 0 and H2 >= 0 at every sample, with the true input within its bound
    assert expo["fallback_steps"] == 0
    assert h(logs["exponential"].z).min() >= 0 and H2(logs["exponential"].z).min() >= -1e-9
    assert expo["max_abs_u"] <= U_MAX + 1e-9 and np.abs(logs["exponential"].u).max() <= U_MAX + 1e-9


@pytest.mark.parametrize("k1, kappa, margin, corner", [(2.0, 4.0, U_MAX - 2.0 * 3.0, (-0.5, 3.0)),
                                                        (0.5, 4.0, 1.0, (-3.0, 2.0))])
def test_grid_check_finds_the_analytic_margin(k1, kappa, margin, corner):
    """With Phi = v the margin is u_max + kappa H2 - k1 z2, smallest on H2 = 0 at the largest reachable z2."""
    sysm, net = double_integrator()
    H2 = fl.ExponentialCBF(fl.AffineCBF([-1.0, 0.0], 1.0), sysm.A, sysm.B, k1=k1)
    g = fl.studies.exponential_cbf_grid_check(sysm, net, EPS, H2, kappa=kappa, n=61)
    assert g["margin_true"] == pytest.approx(margin, abs=1e-12)
    assert np.allclose(g["argmin_true"], corner)
    assert g["margin_network"] == pytest.approx(margin - 2 * EPS, abs=1e-12)   # the witness uses u_max - 2 eps
    assert g["max_abs_u_nn_witness"] <= U_MAX - EPS
    assert (g["margin_true"] > 0) == (k1 < 1.0)   # k1 = 2 asks for more braking than |v| <= 2 gives at z2 = 3


def test_grid_check_refuses_what_it_cannot_check():
    sysm, net = double_integrator()
    with pytest.raises(TypeError, match="ExponentialCBF"):
        fl.studies.exponential_cbf_grid_check(sysm, net, EPS, fl.AffineCBF([-1.0, 0.0], 1.0), kappa=1.0)
    H2 = fl.ExponentialCBF(fl.AffineCBF([-1.0, 0.0], 1.0), sysm.A, sysm.B, k1=1.0)
    with pytest.raises(ValueError, match="kappa"):
        fl.studies.exponential_cbf_grid_check(sysm, net, EPS, H2, kappa=0.0)


def test_failure_set_under_the_bound_matches_the_closed_form():
    """A wall h = 1 - z1 does not contain v: it fails exactly where z2 > kappa (1 - z1); h = 2 - z2 never fails."""
    sysm, _ = double_integrator()
    kappa, n = 2.0, 41
    g = np.linspace(-3, 3, n)
    Z = np.array(np.meshgrid(g, g, indexing="ij")).reshape(2, -1).T
    wall = fl.studies.cbf_failure_set_bounded(sysm, fl.AffineCBF([-1.0, 0.0], 1.0), kappa, n=n)
    safe = Z[:, 0] <= 1.0
    expected = safe & (Z[:, 1] > kappa * (1.0 - Z[:, 0]) + 1e-9)
    assert wall["safe"] == safe.sum() and wall["failing"] == expected.sum() > 0
    assert np.allclose(np.sort(wall["Z_fail"], axis=0), np.sort(Z[expected], axis=0))
    # h = 2 - z2: the condition -v + kappa (2 - z2) >= 0 holds with v = -2 on the whole safe set
    assert fl.studies.cbf_failure_set_bounded(sysm, fl.AffineCBF([0.0, -1.0], 2.0), kappa, n=n)["failing"] == 0
    with pytest.raises(ValueError, match="kappa"):
        fl.studies.cbf_failure_set_bounded(sysm, fl.AffineCBF([0.0, -1.0], 2.0), 0.0, n=n)


def test_failure_set_under_the_network_bound_is_the_one_of_the_smaller_bound():
    """Phi_NN = v = Phi here: the network's set |Phi_NN| <= u_max - eps is the true set of the bound u_max - eps (in
    the box), so its failing states are exactly those of the true check with that bound, and include the true ones."""
    sysm, net = double_integrator()
    A, B, eps = *fl.brunovsky(2), 0.4  # a large eps: some states lie between the two bounds
    smaller = fl.FLSystem("DI", A, B, phi=lambda z, v: np.asarray(v, float).reshape(-1, 1), lo=sysm.lo, hi=sysm.hi,
                          u_max=U_MAX - eps, f=sysm.f, to_z=sysm.to_z, to_x=sysm.to_x)
    kappa, n, H = 0.5, 41, fl.DistanceCBF([1.0, 0.5], 0.4)
    got = fl.studies.cbf_failure_set_bounded(sysm, H, kappa, n=n, net=net, eps=eps)
    ref = fl.studies.cbf_failure_set_bounded(smaller, H, kappa, n=n)
    assert got["failing_network"] == ref["failing"] > got["failing"] > 0 and got["decided_exactly"] > 0
    assert np.array_equal(got["Z_fail_network"], ref["Z_fail"])
    assert {tuple(z) for z in got["Z_fail"]} <= {tuple(z) for z in got["Z_fail_network"]}
    with pytest.raises(ValueError, match="both net and eps"):
        fl.studies.cbf_failure_set_bounded(sysm, H, kappa, n=n, net=net)


def test_sampled_decrease_and_change_within_a_sample():
    """With v = 0 from z0 = [0, 1], z1 grows by ts per sample: V = ||z||^2 rises at every sample."""
    sysm, _ = double_integrator()
    ts = 0.1
    log = fl.simulate(sysm, lambda z: np.zeros(1), t_final=1.0, ts=ts, z0=np.array([0.0, 1.0]), progress=False)
    r = fl.studies.sampled_clf_decrease(log, fl.QuadraticCLF(np.eye(2)))
    assert r["rise_fraction"] == 1.0 and r["max_rise_ratio"] > 1.0 and np.isnan(r["max_delta"])
    change = fl.studies.largest_change_within_sample(log, lambda Z: Z[:, 0])
    assert 0.8 * ts <= change <= ts + 1e-9
