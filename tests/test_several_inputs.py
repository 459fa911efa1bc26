"""Chapter 10 (several inputs): the arm's identity, eps, the exact two-input method, obstacle and MPC closed loops."""
import numpy as np
import pytest

import flnotes as fl
from flnotes import arm as fa
from flnotes.studies import multi as study


@pytest.fixture(scope="module")
def arm():
    return fl.two_link_arm()


@pytest.fixture(scope="module")
def shipped():
    net, eps, _ = fl.arm_net()
    return net, eps


# ------------------------------------------------------------------ the system and the network
def test_feedback_linearization_identity_on_the_plant(arm):
    assert study.identity_residual(arm, n=300, seed=5) < 1e-10


def test_identity_residual_sees_a_wrong_phi(arm):
    """The check can fail: a map with the wrong inertia leaves a residual of the order of the mistake."""
    wrong = fl.two_link_arm(m2=1.2)
    bad = fl.FLSystem("wrong", arm.A, arm.B, phi=wrong.phi, lo=arm.lo, hi=arm.hi, u_max=arm.u_max, f=arm.f,
                      to_z=arm.to_z, to_x=arm.to_x)
    assert study.identity_residual(bad, n=50) > 1e-2


def test_certified_eps_bounds_dense_sampled_error(arm, shipped):
    net, eps = shipped
    E = study.sampled_error(arm, net, fl.scale(2_000_000, 300_000), seed=3)
    assert E["max_error"].shape == (2,)
    assert np.all(E["max_error"] <= eps), (E["max_error"], eps)
    # the argmax points are in the box and reproduce the reported errors
    X = E["argmax"]
    assert np.all((arm.lo <= X) & (X <= arm.hi))
    np.testing.assert_allclose(np.abs(arm.phi_stacked(X) - net(X))[[0, 1], [0, 1]], E["max_error"], rtol=1e-12)


def test_shipped_report_is_quoted(shipped):
    info = study.shipped_network()
    net, eps = shipped
    np.testing.assert_array_equal(info["eps"], eps)
    np.testing.assert_array_equal(info["upper"], eps)
    assert info["converged"] and np.all(info["lower"] <= info["upper"]) and np.all(info["cert_s"] > 0)
    assert info["train_s"] > 0 and info["widths"] == tuple(w.shape[0] for w in net.W[:-1])


# ------------------------------------------------------------------ the exact method against the MIP
def test_exact_method_equals_mip_on_the_chapter_program(arm, shipped):
    """Both costs, random safe states, half of them with the optimum on the network's bound."""
    net, eps = shipped
    table, res = study.exact_vs_mip(arm, net, eps, n=fl.scale(40, 12), seed=4)
    assert len(table) == 4
    for cost, r in res.items():
        assert r["same_status"] == r["states"], cost
        assert r["max_rel_objective_gap_hard"] <= 1e-6, (cost, r["max_rel_objective_gap_hard"])
        # premise: the hard case is there (the optimum on |Phi_NN| = u_max^eps)
        assert r["boundary_states"] == r["states"] // 2 and r["boundary_optima"] >= r["boundary_states"], r


def test_comparison_states_are_safe_and_on_the_bound_as_claimed(arm, shipped):
    net, eps = shipped
    ctrl = study.arm_clf_cbf(arm, net, eps, cost="linear")
    Z, on = study.comparison_states(ctrl, 10, seed=7)
    assert Z.shape == (10, 4) and on.sum() == 5
    assert all(np.all(h.value(Z) >= 0) for h in ctrl.H)
    for z, b in zip(Z, on):
        r = ctrl.step(z)
        gap = np.min(np.abs(np.abs(r.info["phi_nn"]) - ctrl.u_eps))
        assert (not r.fallback and gap <= 1e-7) == b


def test_softened_states_count_witnesses_in_the_true_set(arm, shipped):
    """Every softened state is counted once; a witness in the true set meets the CBF rows alone too."""
    net, eps = shipped
    r = study.softened_states(arm, net, eps, 30, seed=0, cost="linear", n_samples=5000)
    ctrl = study.arm_clf_cbf(arm, net, eps, cost="linear")
    Z, _ = study.comparison_states(ctrl, 30, seed=0)
    assert r["states"] == 30 and r["softened"] == sum(ctrl.step(z).fallback for z in Z) > 0
    assert 0 < r["true_feasible"] <= r["cbf_feasible"] <= r["softened"], r
    with pytest.raises(ValueError, match="n_samples"):
        study.softened_states(arm, net, eps, 5, n_samples=0)


# ------------------------------------------------------------------ the obstacle in the workspace
def test_arm_point_cbf_gradient_matches_finite_differences():
    H = fa.ArmPointCBF([0.6, -0.3], 0.1, fraction=0.7, k1=2.0)
    rng = np.random.default_rng(0)
    for z in rng.uniform(-1.5, 1.5, (20, 4)):
        fd = np.array([(H(z + 1e-6 * e) - H(z - 1e-6 * e)) / 2e-6 for e in np.eye(4)])
        np.testing.assert_allclose(H.grad(z), fd, atol=1e-7)


def test_arm_point_cbf_is_dh_dt_plus_k1_h(arm):
    """H_2 = dh/dt + k_1 h along the chains, dh/dt by finite differences of h along z' = A z + B v."""
    H = fa.ArmPointCBF([0.4, -0.8], 0.1, fraction=0.5, k1=3.0)
    rng = np.random.default_rng(1)
    for z in rng.uniform(arm.lo[:4], arm.hi[:4], (20, 4)):
        zd = arm.A @ z
        dh = (H.h((z + 1e-6 * zd)[None])[0] - H.h((z - 1e-6 * zd)[None])[0]) / 2e-6
        assert abs(H(z) - (dh + 3.0 * H.h(z[None])[0])) < 1e-6


def test_inflated_points_keep_the_whole_link_out():
    """Where every point of arm_obstacle_cbfs has h >= 0, the links are at least r from the centre."""
    c, r = np.array([0.31, -0.95]), 0.06
    Hs = fa.arm_obstacle_cbfs(c, r, n_points=5)
    rng = np.random.default_rng(2)
    Z = np.column_stack([rng.uniform(-0.2, 1.2, 40_000), np.zeros(40_000), rng.uniform(-1.5, 1.0, 40_000),
                         np.zeros(40_000)])
    safe = np.all([h.h(Z) >= 0 for h in Hs], axis=0)
    d = fa.links_distance(Z[:, [0, 2]], c)
    assert safe.sum() > 1000 and (~safe).sum() > 100, "premise: both sides are sampled"
    assert np.all(d[safe] >= r - 1e-12)
    # and links_distance is the distance to the drawn segments
    q = Z[:50, [0, 2]]
    elbow, hand = fa.arm_joint_positions(q)
    t = np.linspace(0, 1, 2001)[:, None, None]
    pts = np.concatenate([t * elbow[None], elbow[None] + t * (hand - elbow)[None]])
    np.testing.assert_allclose(fa.links_distance(q, c), np.linalg.norm(pts - c, axis=2).min(0), atol=1e-6)


def test_obstacle_closed_loop_keeps_torques_and_avoids_the_obstacle(arm, shipped):
    net, eps = shipped
    t_final = fl.scale(study.ARM_CLF_CBF["t_final"], 2.0)
    nominal = study.nominal_run(arm, setting=dict(t_final=t_final))
    c, r = study.ARM_CLF_CBF["center"], study.ARM_CLF_CBF["radius"]
    assert fa.links_distance(nominal.z[:, [0, 2]], c).min() < r, "premise: without barriers the link hits the obstacle"
    for cost in ("quadratic", "linear"):
        log, ch = study.obstacle_run(arm, net, eps, cost=cost, t_final=t_final)
        assert np.all(np.abs(log.u) <= arm.u_max + 1e-9) and ch["within"], ch["ratio_between"]
        assert ch["fallback_steps"] == 0 and ch["left_domain_steps"] == 0
        assert ch["min_distance"] >= r, ch["min_distance"]
        assert np.all(fa.links_distance(log.z_fine[:, [0, 2]], c) >= r), "the link touches the obstacle between samples"
        # the checks along the integrated trajectory include the samples and agree with a direct evaluation
        d_fine = fa.links_distance(np.vstack([log.z_fine, log.z])[:, [0, 2]], c).min()
        assert ch["min_distance_between"] == pytest.approx(d_fine) and ch["min_distance_between"] <= ch["min_distance"]
        assert ch["min_h_between"] <= ch["min_h"] and ch["inflated_radius"] > r


def test_mpc_short_closed_loop_keeps_torques(arm, shipped):
    net, eps = shipped
    log, ch = study.mpc_run(arm, net, eps, t_final=0.6)
    assert np.any(np.abs(log.u_nn) >= arm.u_max - eps - 1e-6), "premise: the network's bound is active"
    assert np.all(np.abs(log.u) <= arm.u_max + 1e-9) and ch["within"], ch["ratio_between"]
    assert ch["fallback_steps"] == 0


# ------------------------------------------------------------------ bad input
def test_bad_arguments(arm, shipped):
    with pytest.raises(ValueError, match="first link"):
        fa.arm_obstacle_cbfs([0.3, -0.3], 0.1)
    with pytest.raises(ValueError, match="n_points"):
        fa.arm_obstacle_cbfs([0.31, -0.95], 0.06, n_points=1)
    with pytest.raises(ValueError, match="fraction"):
        fa.ArmPointCBF([0.3, -0.9], 0.1, fraction=1.5)
    with pytest.raises(ValueError, match="radius"):
        fa.ArmPointCBF([0.3, -0.9], -0.1)
    with pytest.raises(ValueError, match="setpoints"):
        study.setpoint_reference(np.zeros((2, 3)), 1.0)
    with pytest.raises(ValueError, match="n must be"):
        study.sampled_error(arm, shipped[0], 0)
    with pytest.raises(ValueError, match="fractions"):
        fa.arm_link_points(np.zeros((1, 2)), [0.5, 2.0])
