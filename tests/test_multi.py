"""Two inputs through the pipeline: the two-link arm, its input sets as polygons, the exact region method."""
import numpy as np
import pytest
from matplotlib.path import Path

import flnotes as fl
from flnotes import interval as iv
from flnotes import pieces as pc
from flnotes.arm import arm_net, two_link_arm


@pytest.fixture(scope="module")
def arm():
    return two_link_arm()


@pytest.fixture(scope="module")
def shipped():
    net, eps, ref = arm_net()
    return net, eps, ref


def _states(sysm, n, seed):
    rng = np.random.default_rng(seed)
    return rng.uniform(sysm.lo[: sysm.n_z], sysm.hi[: sysm.n_z], (n, sysm.n_z))


# ------------------------------------------------------------------ the system
def test_feedback_linearization_identity(arm):
    """f(x, Phi(z, v)) read in z-coordinates is the Brunovsky chain A z + B v."""
    rng = np.random.default_rng(0)
    X = rng.uniform(arm.lo[:4], arm.hi[:4], (200, 4))[:, [0, 2, 1, 3]]    # plant order (q1, q2, q1', q2')
    V = rng.uniform(arm.lo[4:], arm.hi[4:], (200, 2))
    for x, v in zip(X, V):
        z = arm.to_z(x)
        np.testing.assert_allclose(arm.to_x(z), x, atol=0)
        xdot = arm.f(x, arm.Phi(z, v))
        zdot = arm.to_z(xdot)      # to_z is a permutation, hence linear: d/dt to_z(x) = to_z(x')
        np.testing.assert_allclose(zdot, arm.A @ z + arm.B @ v, rtol=1e-11, atol=1e-11)


def test_phi_is_mass_matrix_times_v_plus_bias(arm):
    rng = np.random.default_rng(1)
    Z = rng.uniform(arm.lo[:4], arm.hi[:4], (100, 4))
    V = rng.uniform(arm.lo[4:], arm.hi[4:], (100, 2))
    M, h = arm.mass_matrix(Z), arm.bias(Z)
    np.testing.assert_allclose(arm.Phi(Z, V), np.einsum("nij,nj->ni", M, V) + h, rtol=1e-12, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(M) > 0), "M(q) must be positive definite"
    assert np.all(np.abs(M[:, 0, 1]) > 0), "the inputs are coupled through M_12"


def test_torque_bound_is_active_on_part_of_the_box(arm):
    X = arm.grid(5)
    viol = np.any(np.abs(arm.phi_stacked(X)) > arm.u_max, axis=1)
    assert 0.1 < viol.mean() < 0.9, f"the torque bound should bind on a good part of the box, got {viol.mean():.2f}"


def test_phi_interval_encloses_phi(arm):
    rng = np.random.default_rng(2)
    c = rng.uniform(arm.lo, arm.hi, (300, 6))
    r = rng.uniform(0, 0.3, (300, 6)) * (arm.hi - arm.lo)
    lo, hi = c - r, c + r
    Y = arm.phi_interval(iv.Interval(lo[:, :4], hi[:, :4]), iv.Interval(lo[:, 4:], hi[:, 4:]))
    for t in range(8):
        P = rng.uniform(lo, hi)
        U = arm.phi_stacked(P)
        assert np.all(Y.lo <= U) and np.all(U <= Y.hi)


def test_bad_arguments(arm):
    with pytest.raises(ValueError, match="tau_max"):
        two_link_arm(tau_max=(1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match="v_box"):
        two_link_arm(v_box=-1.0)
    with pytest.raises(ValueError, match="m1"):
        two_link_arm(m1=0.0)


# ------------------------------------------------------------------ network and eps
def test_shipped_network_and_certified_eps(arm, shipped):
    net, eps, ref = shipped
    assert net.n_in == 6 and net.n_out == 2
    assert np.all(np.asarray(ref.bracket["lower"]) <= eps)
    assert np.all(ref.bracket["converged"])
    X = np.random.default_rng(3).uniform(arm.lo, arm.hi, (200_000, 6))
    X = np.vstack([X, arm.grid(5), np.asarray(ref.bracket["argmax"])])
    E = np.abs(arm.phi_stacked(X) - net(X)).max(0)
    assert np.all(E <= eps), f"sampled error {E} exceeds the certified eps {eps}"
    assert np.all(eps < arm.u_max)


def test_certify_on_a_sub_box_bounds_sampled_error(arm, shipped):
    """certify_error on a 6-D sub-box of the arm: the bracket contains the sampled maximum."""
    net, _, _ = shipped
    c = np.array([0.4, -0.5, 0.8, 0.3, 2.0, -3.0])
    lo, hi = c - 0.05 * (arm.hi - arm.lo), c + 0.05 * (arm.hi - arm.lo)
    br = fl.certify_error(arm, net, lo, hi, rtol=0.1, n_samples=2000)
    X = np.random.default_rng(4).uniform(lo, hi, (50_000, 6))
    E = np.abs(arm.phi_stacked(X) - net(X)).max(0)
    assert np.all(E <= br.upper) and np.all(br.lower <= br.upper)


# ------------------------------------------------------------------ polygons
def _inside(P, V):
    return Path(P).contains_points(V, radius=0.0) if len(P) else np.zeros(len(V), bool)


def test_admissible_polygon_is_the_admissible_set(arm):
    rng = np.random.default_rng(5)
    V = rng.uniform(arm.lo[4:], arm.hi[4:], (4000, 2))
    n_nonempty = 0
    for z in _states(arm, 12, 6):
        P = pc.admissible_polygon(arm, z)
        U = arm.Phi(np.repeat(z[None], len(V), 0), V)
        margin = np.abs(np.abs(U) - arm.u_max).min(1)
        ok = np.all(np.abs(U) <= arm.u_max, axis=1)
        far = margin > 1e-6
        assert np.array_equal(_inside(P, V)[far], ok[far])
        n_nonempty += len(P) > 0
        if len(P):
            Ub = arm.Phi(np.repeat(z[None], len(P), 0), P)
            assert np.all(np.abs(Ub) <= arm.u_max + 1e-9), "vertices of V(z) must be admissible"
    assert n_nonempty >= 6


def test_regions_reproduce_the_network(arm, shipped):
    net, eps, _ = shipped
    rng = np.random.default_rng(7)
    V = rng.uniform(arm.lo[4:], arm.hi[4:], (3000, 2))
    box_area = float(np.prod(arm.hi[4:] - arm.lo[4:]))
    for z in _states(arm, 5, 8):
        R = pc.network_regions(net, z, arm.lo[4:], arm.hi[4:])
        assert abs(sum(pc.polygon_area(Q) for Q in R.polygons) - box_area) < 1e-9 * box_area
        Y = net(np.hstack([np.repeat(z[None], len(V), 0), V]))
        hit = np.zeros(len(V), int)
        for Q, A, c in zip(R.polygons, R.A, R.c):
            m = _inside(Q, V)
            hit += m
            np.testing.assert_allclose(V[m] @ A.T + c, Y[m], atol=1e-9)
        assert np.all(hit >= 1)
        # the network's input set, eq. (Phi_NN_ep)
        bound = arm.u_max - eps
        polys = pc.network_polygons(net, z, arm.lo[4:], arm.hi[4:], bound, regions=R)
        inside = np.zeros(len(V), bool)
        for Q in polys:
            inside |= _inside(Q, V)
        far = np.abs(np.abs(Y) - bound).min(1) > 1e-6
        assert np.array_equal(inside[far], np.all(np.abs(Y) <= bound, axis=1)[far])


def test_regions_reject_wrong_sizes(arm, shipped):
    net, _, _ = shipped
    with pytest.raises(ValueError, match="two inputs"):
        pc.network_regions(net, np.zeros(3), arm.lo[4:], arm.hi[4:])
    with pytest.raises(ValueError, match="v_lo < v_hi"):
        pc.network_regions(net, np.zeros(4), [1.0, 1.0], [0.0, 2.0])
    d = dict(aV=np.zeros(2), bV=0.0, Jc=0.0, aH=np.zeros((0, 2)), bH=np.zeros(0), k=np.zeros(2))
    with pytest.raises(ValueError, match="cost"):
        pc.solve_exact_2d(net, np.zeros(4), d, "cubic", [1.0, 1.0], arm.lo[4:], arm.hi[4:])
    with pytest.raises(ValueError, match="two inputs"):
        pc.solve_exact_2d(net, np.zeros(5), d, "linear", [1.0, 1.0], arm.lo[4:], arm.hi[4:])


# ------------------------------------------------------------------ the exact method vs the MIP
P_CLF = np.diag([2.0, 0.5, 2.0, 0.5]) + np.diag([0.4, 0, 0.4], 1) + np.diag([0.4, 0, 0.4], -1)
K_NOM = np.array([[6.0, 4.0, 0.0, 0.0], [0.0, 0.0, 6.0, 4.0]])


def _controllers(arm, net, eps, cost):
    H = fl.DistanceCBF(np.array([0.8, 0.0, -0.6, 0.0]), 0.5)
    kw = dict(k=lambda z: -K_NOM @ z, cost=cost)
    ex = fl.ClfCbfController(arm, net, eps, fl.QuadraticCLF(P_CLF), H, **kw)
    assert ex.backend == "exact" and isinstance(ex._impl, fl.control._ExactPiecesBackend)
    return ex, ex.with_backend("scip")


@pytest.mark.parametrize("cost", ["linear", "quadratic"])
def test_exact_method_equals_mip(arm, shipped, cost):
    net, eps, _ = shipped
    ex, mip = _controllers(arm, net, eps, cost)
    u_eps = arm.u_max - eps
    on_boundary = 0
    # 12 states at random, 12 where the nominal k(z) violates the network's bound (the hard case) and
    # 6 where the CLF condition (CLF_CBF_c) is relaxed at the optimum (delta > 0)
    pool = _states(arm, 400, 9 if cost == "linear" else 10)
    vk = np.clip(-pool @ K_NOM.T, arm.lo[4:], arm.hi[4:])
    hard = np.any(np.abs(net(np.hstack([pool, vk]))) > u_eps, axis=1)
    relaxed = np.array([ex.step(z).info["delta"] > 1e-6 for z in pool])
    Z = np.vstack([pool[~hard & ~relaxed][:12], pool[hard & ~relaxed][:12], pool[relaxed][:6]])
    n_delta = 0
    for z in Z:
        a, b = ex.step(z), mip.step(z)
        assert a.status == b.status, (z, a.status, b.status)
        assert a.fallback == b.fallback
        oa, ob = a.objective, b.objective
        assert abs(oa - ob) <= 1e-6 * max(1.0, abs(ob)), (z, oa, ob, a.v, b.v)
        y = net(np.concatenate([z, a.v]))
        if not a.fallback:
            assert np.all(np.abs(y) <= u_eps + 1e-9)
            on_boundary += bool(np.any(np.abs(np.abs(y) - u_eps) <= 1e-7))
        n_delta += b.info["delta"] > 1e-6
    # the premises: some optima lie on the network's bound |Phi_NN| = u_max^eps (the hard case), and
    # some relax the CLF condition (by the MIP's own solution)
    assert on_boundary >= 8, f"only {on_boundary} boundary optima among {len(Z)} states"
    assert n_delta >= 3, f"only {n_delta} of {len(Z)} MIP optima have delta > 0"


def _soft_value(ctrl, z, v):
    """The softened objective J(v) + delta*(v) + rho_u sum s_u + rho_H sum s_H at (z, v), evaluated exactly."""
    d = ctrl.program_data(z)
    J = d["aV"] @ v + d["Jc"] if ctrl.cost == "linear" else (v - d["k"]) @ (v - d["k"])
    s_u = np.maximum(0.0, np.abs(ctrl.net(np.concatenate([z, v]))) - ctrl.u_eps)
    s_H = np.maximum(0.0, -(d["aH"] @ v + d["bH"]))
    return float(J + max(0.0, d["aV"] @ v + d["bV"]) + ctrl.penalty[0] * s_u.sum() + ctrl.penalty[1] * s_H.sum())


@pytest.mark.parametrize("cost", ["linear", "quadratic"])
def test_softened_program_equals_mip(arm, shipped, cost):
    """Where no v satisfies every constraint both fall back to the softened program: same optimum."""
    net, eps, _ = shipped
    ex, mip = _controllers(arm, net, eps, cost)
    # inside the unsafe ball of the CBF, almost at rest: grad H^T (A z + B v) cannot reach -kappa H(z) > 0
    rng = np.random.default_rng(11)
    r = rng.uniform(0.2, 0.45, 6)
    th = rng.uniform(0, 2 * np.pi, 6)
    Z = np.column_stack([0.8 + r * np.cos(th), rng.uniform(-0.01, 0.01, 6), -0.6 + r * np.sin(th),
                         rng.uniform(-0.01, 0.01, 6)])
    for z in Z:
        a, b = ex.step(z), mip.step(z)
        assert a.fallback and b.fallback, (z, a.status, b.status)
        assert a.info["fallback_rule"] == b.info["fallback_rule"] == "softened program"
        # SCIP meets the slack rows to its feasibility tolerance only, which the weights rho (1e6, 1e4)
        # magnify in its reported objective: compare the softened objective evaluated exactly at both points
        # (rho_u = 1e6 also magnifies the rounding of the network's output, ~1e-13, hence the absolute term)
        fa, fb = _soft_value(ex, z, a.v), _soft_value(ex, z, b.v)
        tol = 1e-9 * max(1.0, abs(fb)) + 1e-11 * sum(ex.penalty)
        assert abs(a.objective - fa) <= tol
        assert fa <= fb + tol, (z, fa, fb)
        assert abs(fa - fb) <= 1e-6 * max(1.0, abs(fb)), (z, fa, fb, a.v, b.v)
        # the input bound is given up last: the network's output still meets it
        assert np.all(np.abs(net(np.concatenate([z, a.v]))) <= arm.u_max - eps + 1e-9)


def test_exact_backend_rejects_more_than_two_inputs():
    A, B = fl.brunovsky((1, 1, 1))
    ident = lambda x: np.asarray(x, float)
    sysm = fl.FLSystem("three", A, B, phi=lambda z, v: v, lo=[-1] * 6, hi=[1] * 6, u_max=[1, 1, 1],
                       f=lambda x, u: u, to_z=ident, to_x=ident)
    net = fl.ReLUNet([np.ones((2, 6)), np.ones((3, 2))], [np.zeros(2), np.zeros(3)])
    with pytest.raises(ValueError, match="m = 3 inputs"):
        fl.ClfCbfController(sysm, net, 0.1, fl.QuadraticCLF(np.eye(3)), backend="exact")
    assert fl.ClfCbfController(sysm, net, 0.1, fl.QuadraticCLF(np.eye(3))).backend == "scip"


@pytest.mark.parametrize("cost", ["quadratic", "linear"])
def test_closed_loop_avoids_obstacle_with_true_torques_bounded(arm, shipped, cost):
    """On the true plant: every true |tau_i| <= tau_max,i, H(z) >= 0, and the exact method's run is SCIP's run."""
    net, eps, _ = shipped
    z0 = np.array([1.4, 0.0, -1.2, 0.0])
    H = fl.DistanceCBF(np.array([0.85, -1.44, -0.73, 1.23]), 0.3)   # on the nominal law's path
    nominal = fl.simulate(arm, lambda z: np.clip(-K_NOM @ z, arm.lo[4:], arm.hi[4:]), t_final=1.5, ts=0.02, z0=z0)
    assert H(nominal.z).min() < 0, "premise: without the CBF the nominal law enters the unsafe set"
    ex = fl.ClfCbfController(arm, net, eps, fl.QuadraticCLF(P_CLF), H, k=lambda z: -K_NOM @ z, cost=cost)
    t_final = 0.8 if fl.FAST else 1.5
    logs = [fl.simulate(arm, c, t_final=t_final, ts=0.02, z0=z0, net=net) for c in (ex, ex.with_backend("scip"))]
    for log in logs:
        s = log.summary()
        assert np.all(np.abs(log.u) <= arm.u_max + 1e-9), s["max_abs_u_samples"]
        assert s["u_within_bound_between"], s["max_abs_u_between"]
        assert s["fallback_steps"] == 0 and s["left_domain_steps"] == 0
        assert H(log.z).min() >= 0
    np.testing.assert_allclose(logs[0].z, logs[1].z, atol=1e-6)


def test_input_sets_figure_draws_every_polygon(arm, shipped):
    from flnotes.plots.multi import input_sets_plot

    net, eps, _ = shipped
    sets = pc.input_sets(arm, net, eps, _states(arm, 3, 12))
    fig, axes = input_sets_plot(sets, input_names=("v_1", "v_2"))
    for S, ax in zip(sets, axes):
        assert len(S["network"]) >= 1 and len(S["true"]) >= 3
        assert len(ax.patches) == S["regions"].n_regions + len(S["network"]) + 1
    with pytest.raises(ValueError, match="two inputs"):
        pc.input_sets(fl.msd(), net, eps, [np.zeros(2)])


def test_compare_exact_mip_reports_agreement(arm, shipped):
    net, eps, _ = shipped
    ex, mip = _controllers(arm, net, eps, "linear")
    r = pc.compare_exact_mip(ex, mip, _states(arm, 6, 13))
    assert r["states"] == 6 and r["same_status"] == 6
    assert r["max_rel_objective_gap_hard"] <= 1e-6
    assert r["exact_ms_min"] <= r["exact_ms_median"] <= r["exact_ms_max"]
    with pytest.raises(ValueError, match="shape"):
        pc.compare_exact_mip(ex, mip, np.zeros((2, 3)))


def test_mpc_safe_input_is_exact_for_two_inputs():
    """MPC.safe_input finds an admissible v for the arm wherever the network's admissible polygons are non-empty,
    the nearest one to the guess among the polygons' projections."""
    s = fl.two_link_arm()
    net, eps, _ = fl.arm_net()
    mpc = fl.MPC(s, net, eps, horizon=2, ts=0.05, Q=np.ones(4), R=0.01 * np.ones(2), backend="scip")
    rng = np.random.default_rng(3)
    n_ok = 0
    for z in rng.uniform(s.lo[:4], s.hi[:4], (15, 4)):
        guess = rng.uniform(s.lo[4:], s.hi[4:])
        polys = fl.pieces.network_polygons(net, z, s.lo[4:], s.hi[4:], s.u_max - eps)
        v, ok = mpc.safe_input(z, guess)
        assert ok == bool(polys), (z, ok, len(polys))
        if ok:
            n_ok += 1
            assert np.all(np.abs(net(np.r_[z, v])) <= s.u_max - eps + 1e-12)
            best = min(np.sum((fl.pieces._project(P, guess) - guess) ** 2) for P in polys)
            assert np.sum((v - guess) ** 2) <= best + 1e-9
    assert n_ok >= 5


@pytest.mark.parametrize("cost", ["linear", "quadratic"])
def test_softened_minimizer_on_a_region_equals_a_convex_solver(cost):
    """The candidate set of the softened objective on one region contains its minimizer.

    On random polygons (the v-box cut by random half-planes) with random affine maps ``A v + c``,
    CLF and CBF rows and large or small penalties (minimizers at kinks or inside cells), the value at
    the returned point equals the optimum of the same convex program written with slacks and solved by
    Clarabel, and the point lies in the polygon.
    """
    cp = pytest.importorskip("cvxpy")
    from flnotes.pieces import _best_soft, _hinged_values, _hinges

    rng = np.random.default_rng(3)
    for i in range(40):
        rho = (50.0, 5.0) if i % 2 else (0.3, 0.1)   # minimizers at kinks, and inside cells
        Vb = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * rng.uniform(0.5, 2.0, 2)
        G0, h0 = rng.standard_normal((2, 2)), rng.uniform(-0.3, 0.5, 2)
        V = fl.pieces._clip_all(Vb, G0, -h0)
        if len(V) < 3:
            continue
        A, c = rng.standard_normal((2, 2)), rng.standard_normal(2)
        d = dict(aV=rng.standard_normal(2), bV=rng.uniform(-1, 1), Jc=0.3, k=rng.standard_normal(2),
                 aH=rng.standard_normal((3, 2)), bH=rng.uniform(-1, 1, 3))
        bound = np.array([0.4, 0.6])
        v = _best_soft(V, A, c, d, cost, bound, rho)
        G, e, w = _hinges(A, c, d, bound, rho)
        f = float(_hinged_values(v[None], G, e, w, d, cost)[0])
        x = cp.Variable(2)
        s = cp.Variable(len(e), nonneg=True)
        E = np.roll(V, -1, axis=0) - V
        inside = [E[i, 0] * (x[1] - V[i, 1]) - E[i, 1] * (x[0] - V[i, 0]) >= 0 for i in range(len(V))]
        J = d["aV"] @ x + d["Jc"] if cost == "linear" else cp.sum_squares(x - d["k"])
        prob = cp.Problem(cp.Minimize(J + w @ s), [s >= G @ x + e] + inside)
        prob.solve(solver="CLARABEL")
        assert prob.status == "optimal"
        assert f <= prob.value + 1e-6 * max(1.0, abs(prob.value)), (f, prob.value)
        assert f >= prob.value - 1e-6 * max(1.0, abs(prob.value))
        Ev = np.roll(V, -1, axis=0) - V
        assert np.all(Ev[:, 0] * (v[1] - V[:, 1]) - Ev[:, 1] * (v[0] - V[:, 0]) >= -1e-9)


def _two_msd(cost: str):
    """The CLF-CBF controller of two MSDs side by side (tests/_nets.two_msd), its CBF an obstacle."""
    from flnotes.control import ClfCbfController, DistanceCBF, QuadraticCLF

    from _nets import two_msd

    S = fl.paper.MSD_SETTING
    sysm, net = two_msd()
    return ClfCbfController(sysm, net, 0.1, QuadraticCLF(np.kron(np.eye(2), S["P"])),
                            DistanceCBF([1.5, 1.0, 0.0, 0.0], 0.8),
                            lambda z: -np.kron(np.eye(2), S["K_nominal"]) @ z, cost=cost, backend="exact")


@pytest.mark.parametrize("z", [
    [-0.7061141361019025, -2.537840786533119, -1.864114567505458, 4.303937982432174],
    [-3.070141180333585, -2.1126553205244396, -2.5845339563115184, 0.9657158518722784],
])
def test_the_region_method_at_the_edge_of_feasibility_returns_a_point_that_passes_the_check_or_none(z):
    """States on the edge of feasibility (found by bisection): the region method's optimum was a polygon vertex whose
    forward pass exceeded u_max^eps by 1.0e-12, and the step ended in "error". Its answer now passes the forward-pass
    check with no tolerance, or the region counts as empty (the feasible sliver has no point that passes): the status
    is "optimal" or "infeasible", never "error", and an optimal v meets the bound exactly."""
    from flnotes.pieces import solve_exact_2d

    ctrl = _two_msd("linear")
    z = np.asarray(z)
    d = ctrl.program_data(z)
    out = solve_exact_2d(ctrl.net, z, d, "linear", ctrl.u_eps, ctrl.v_lo, ctrl.v_hi)
    if out is not None:
        assert np.all(np.abs(ctrl.net(np.concatenate([z, out[0]]))) <= ctrl.u_eps)
    res = ctrl.step(z)
    assert res.status in ("optimal", "infeasible"), res.message
    assert (res.status == "optimal") == (out is not None)
    if res.status == "optimal":
        assert res.input_admissible and np.all(np.abs(ctrl.net(np.concatenate([z, res.v]))) <= ctrl.u_eps)
