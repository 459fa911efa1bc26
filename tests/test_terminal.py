"""Terminal ingredients (flnotes.terminal) and the bound between samples (flnotes.intersample).

Properties checked: P solves the Riccati equation; the terminal set is positively invariant and inside the
boxes; its MILP certificate is never below the dense-sampling maximum and is within u_max^eps; the level
alpha is the largest within tolerance; the shifted plan of the recursive-feasibility proof is feasible along
a closed loop; delta's certified upper bound is never below sampled drifts; and with the margin
u_max^{eps+delta} the true input stays within u_max at every instant of a closed loop on the true plant.
"""
import numpy as np
import pytest

import flnotes as fl
from flnotes import intersample as isb
from flnotes import terminal as term

SETTINGS = {"Quad-1D": dict(Q=[10.0, 1.0, 1.0], R=0.0175), "MSD": dict(Q=[10.0, 1.0], R=0.1)}
TS = 0.1


@pytest.fixture(scope="module")
def quad_terminal():
    """The Quad-1D system, its shipped network and eps, and its terminal ingredients."""
    system = fl.quad1d()
    net, _ = fl.paper_net("Quad-1D")
    eps = fl.paper_eps("Quad-1D").upper
    return system, net, eps, term.terminal_set(system, net, eps, TS, **SETTINGS["Quad-1D"])


@pytest.fixture(scope="module", params=["Quad-1D", "MSD"])
def setup(request):
    name = request.param
    system = fl.paper.system(name)
    net, _ = fl.paper_net(name)
    eps = fl.paper_eps(name).upper
    T = term.terminal_set(system, net, eps, TS, **SETTINGS[name])
    return name, system, net, eps, T


def test_lqr_solves_riccati_and_decreases_cost():
    system = fl.quad1d()
    Ad, Bd = system.discretize(TS)
    Q, R = np.diag([10.0, 1.0, 1.0]), np.array([[0.0175]])
    K, P = term.lqr(Ad, Bd, Q, R)
    res = Ad.T @ P @ Ad - Ad.T @ P @ Bd @ np.linalg.solve(R + Bd.T @ P @ Bd, Bd.T @ P @ Ad) + Q - P
    assert np.abs(res).max() <= 1e-8 * np.abs(P).max()
    assert np.all(np.linalg.eigvalsh(P) > 0)
    Acl = Ad + Bd @ K
    assert np.max(np.abs(np.linalg.eigvals(Acl))) < 1
    Z = np.random.default_rng(0).normal(size=(100, 3))
    Zn, V = Z @ Acl.T, Z @ K.T
    # axiom A4 with equality: V_f(z+) - V_f(z) + l(z, Kz) = 0
    dec = np.einsum("ij,jk,ik->i", Zn, P, Zn) - np.einsum("ij,jk,ik->i", Z, P, Z) \
        + np.einsum("ij,jk,ik->i", Z, Q, Z) + np.einsum("ij,jk,ik->i", V, R, V)
    assert np.abs(dec).max() <= 1e-8 * (1 + np.einsum("ij,jk,ik->i", Z, P, Z).max())


def test_terminal_set_invariant_and_in_boxes(setup):
    name, system, net, eps, T = setup
    Z = T.sample(20_000, seed=1)
    assert len(Z) == 20_000 and np.all(T.contains(Z))
    # positively invariant under z+ = (Ad + Bd K) z
    assert np.all(T.contains(Z @ T.A_cl.T, tol=1e-9)), f"{name}: a point of Z_f leaves it under Ad + Bd K"
    # inside the state box and K z inside the v-box: exactly, by LPs over the polytope
    F, g = T.constraint()
    lo, hi = term._bounding_box(F, g)
    assert np.all(lo >= T.z_lo - 1e-9) and np.all(hi <= T.z_hi + 1e-9)
    for i in range(system.m):
        assert term._lp_max(T.K[i], F, g) <= T.v_hi[i] + 1e-9
        assert -term._lp_max(-T.K[i], F, g) >= T.v_lo[i] - 1e-9
    # the irredundant description keeps the box and v-box rows' meaning: O_inf itself is invariant too
    Z1 = Z / T.alpha
    assert np.all(np.all(Z1 @ T.A_cl.T @ T.F.T <= T.g + 1e-9, axis=1))


def test_certificate_bounds_sampled_max(setup):
    name, system, net, eps, T = setup
    Z = T.sample(50_000, seed=2)
    sampled = np.abs(net(np.hstack([Z, Z @ T.K.T]))).max(0)
    cert = T.certificate
    # the MILP maximum is never below what samples find (up to the solver's feasibility tolerance) ...
    assert np.all(sampled <= cert.upper + 1e-7), f"{name}: sampled {sampled} > certificate {cert.upper}"
    assert np.all(cert.lower <= cert.upper + 1e-9)
    # ... its best point is a real point of Z_f, and the proof holds
    assert np.all(T.contains(cert.argmax, tol=1e-6))
    assert np.all(cert.upper <= T.u_eps), f"{name}: certificate {cert.upper} > u_max^eps {T.u_eps}"
    assert np.allclose(T.u_eps, system.u_max - eps)


def test_alpha_is_largest_within_tolerance(setup):
    name, system, net, eps, T = setup
    assert 0 < T.alpha <= 1
    if T.alpha == 1.0:
        return
    assert T.alpha < T.alpha_failed <= T.alpha * (1 + T.tol) + 1e-12
    bigger = term.network_max(net, T.K, T.F, T.alpha * (1 + T.tol) * T.g)
    assert np.any(bigger.upper > T.u_eps), f"{name}: alpha (1 + tol) still passes the certificate"
    # the failure is real, not only an upper bound: a point of the larger set violates the constraint
    assert np.any(bigger.lower > T.u_eps)
    passed = [h for h in T.history if h[3]]
    assert max(h[0] for h in passed) == T.alpha


def test_recursive_feasibility_by_shifted_plan(quad_terminal):
    system, net, eps, T = quad_terminal
    N = 5
    prog = term.HorizonFeasibility(system, net, eps, TS, N, T.constraint())
    free = term.HorizonFeasibility(system, net, eps, TS, N, None)
    roa = term.region_of_attraction(system, net, eps, T, horizon=N, n_grid=4, limits=((-1.0, 1.0), (-1.0, 1.0)))
    # the terminal constraint only removes plans
    assert np.all(roa.feasible_terminal <= roa.feasible)
    starts = roa.points()[roa.feasible_terminal == 1]
    assert len(starts) >= 1, "premise: some grid state must be feasible with the terminal constraint"
    u_eps = system.u_max - eps
    for z in starts[:2]:
        ok, plan = prog.solve(z)
        assert ok
        Zp, Vp = plan
        for _ in range(6):
            # the candidate of the proof is feasible: boxes, network constraint, dynamics, terminal set
            Zc, Vc = term.shifted_plan(T, Zp, Vp)
            assert np.all(Zc >= T.z_lo - 1e-7) and np.all(Zc <= T.z_hi + 1e-7)
            assert np.all(Vc >= T.v_lo - 1e-7) and np.all(Vc <= T.v_hi + 1e-7)
            assert np.all(np.abs(net(np.hstack([Zc[:-1], Vc]))) <= u_eps + 1e-6)
            assert np.allclose(Zc[1:], Zc[:-1] @ T.Ad.T + Vc @ T.Bd.T)
            assert T.contains(Zc[-1], tol=1e-7)[0]
            # and the program is feasible at the next state (with and without the terminal constraint)
            ok, plan = prog.solve(Zc[0])
            assert ok, f"infeasible at {Zc[0]} although the shifted plan is feasible"
            assert free.solve(Zc[0])[0]
            Zp, Vp = plan
    # every state of Z_f is feasible with the terminal constraint (the terminal law is a feasible plan)
    for z in T.sample(5, seed=5):
        assert prog.solve(z)[0]


def test_horizon_milp_agrees_with_candidates(quad_terminal):
    system, net, eps, T = quad_terminal
    N = 5
    for terminal in (None, T.constraint()):
        fast = term.HorizonFeasibility(system, net, eps, TS, N, terminal, gains=(T.K,))
        milp_only = term.HorizonFeasibility(system, net, eps, TS, N, terminal, candidates=False)
        for z in ([0.0, 0.0, 0.0], [0.5, -0.5, 0.0], [-4.0, -4.0, 0.0], [4.5, 4.5, 0.0], [1.0, 1.0, 0.0]):
            ok_fast, _ = fast.solve(z)
            ok_milp, plan = milp_only.solve(z)
            assert ok_milp is not None
            assert ok_fast == ok_milp, f"z0 = {z}: candidates/reach say {ok_fast}, the MILP says {ok_milp}"
            if ok_milp:
                # the MILP's plan meets every constraint (network by its forward pass), up to solver tolerances
                assert milp_only.feasible_plan(*plan, tol=1e-6)
                assert np.allclose(plan[0][0], z)


def test_flow_is_the_exact_discretization():
    for system in (fl.msd(), fl.quad1d()):
        rng = np.random.default_rng(3)
        Z, V = rng.normal(size=(50, system.n_z)), rng.normal(size=(50, system.m))
        for ts in (0.02, 0.1):
            Ad, Bd = fl.discretize(system.A, system.B, ts, "exact")
            assert np.allclose(isb.flow(system, Z, V, np.full(50, ts)), Z @ Ad.T + V @ Bd.T, atol=1e-12)


@pytest.mark.parametrize("name", ["MSD", "Quad-1D"])
def test_delta_bounds_sampled_drift(name):
    system = fl.paper.system(name)
    ts = 0.05
    d_all = isb.intersample_drift(system, ts, admissible=False)
    d_adm = isb.intersample_drift(system, ts)
    n, m = system.n_z, system.m
    rng = np.random.default_rng(4)
    X = rng.uniform(system.lo, system.hi, (400_000, n + m))
    X[:50_000] = np.where(rng.random((50_000, n + m)) < 0.5, system.lo, system.hi)  # corners of the box
    tau = rng.uniform(0, ts, len(X))
    tau[: len(X) // 2] = ts
    Z, V = X[:, :n], X[:, n:]
    drift = np.abs(system.Phi(isb.flow(system, Z, V, tau), V) - system.Phi(Z, V))
    admissible = np.all(np.abs(system.Phi(Z, V)) <= system.u_max, axis=1)
    assert admissible.sum() > 1000, "premise: many samples are admissible"
    # the certified upper ends are never below the sampled drifts (whole box, admissible samples)
    assert np.all(drift.max(0) <= d_all.upper), f"{name}: sampled drift {drift.max(0)} > certified {d_all.upper}"
    assert np.all(drift[admissible].max(0) <= d_adm.upper), (
        f"{name}: sampled admissible drift {drift[admissible].max(0)} > certified {d_adm.upper}")
    assert np.all(d_adm.upper <= d_all.upper)
    for d in (d_all, d_adm):
        assert np.all(d.lower <= d.upper) and np.all(d.lower > 0)
        # the lower end is attained at a point of the box (and of the admissible set when restricted)
        za, va, ta = d.argmax[0, :n], d.argmax[0, n:n + m], d.argmax[0, -1]
        assert np.all(za >= system.lo[:n]) and np.all(za <= system.hi[:n]) and 0 <= ta <= ts
        at = np.abs(system.Phi(isb.flow(system, za[None], va[None], [ta]), va[None]) - system.Phi(za[None], va[None]))
        assert at[0, 0] >= d.lower[0] * (1 - 1e-9)
    assert np.all(np.abs(system.Phi(d_adm.argmax[:, :n], d_adm.argmax[:, n:n + m])) <= system.u_max)
    # a shorter hold cannot drift more: the certified lower end at t_s / 2 stays below the upper end at t_s
    assert np.all(isb.intersample_drift(system, ts / 2).lower <= d_adm.upper)


def test_margin_refuses_an_empty_input_set():
    system = fl.quad1d()
    with pytest.raises(ValueError, match="shorten t_s"):
        isb.margin(system, 0.1, 0.1)


@pytest.mark.parametrize("name, ts, z0", [("MSD", 0.1, [2.0, 2.0]), ("Quad-1D", 0.05, [-0.5, -0.15, -0.2])])
def test_true_input_within_bound_between_samples(name, ts, z0):
    system = fl.paper.system(name)
    net, _ = fl.paper_net(name)
    eps = fl.paper_eps(name).upper
    delta = isb.intersample_drift(system, ts).upper
    bound = isb.margin(system, eps, delta)
    K, _ = term.lqr(*system.discretize(ts), SETTINGS[name]["Q"], SETTINGS[name]["R"])
    law = isb.AdmissibleLaw(system, net, bound, lambda z: K @ z)
    log = fl.simulate(system, law, t_final=2.0, ts=ts, z0=z0, net=net, n_fine=40, check_domain=True)
    # premise of the guarantee: every sample (z_k, v_k) in the domain box, the whole run done
    assert log.message == "" and log.n_steps == int(round(2.0 / ts))
    assert np.all(system.in_domain(log.z[:-1], log.v))
    assert np.all(np.abs(log.u_nn) <= bound + 1e-12)
    assert not log.fallback.any()
    # |u(t)| <= u_max at every instant of the fine grid (a tiny slack for the ODE solver's tolerance)
    assert np.all(np.abs(log.u_fine) <= system.u_max + 1e-7), (
        f"{name}: max |u| between samples {np.abs(log.u_fine).max()} > u_max {system.u_max}")


def test_max_admissible_set_small_cases_and_bad_input():
    # a contraction inside a symmetric interval: the constraint set itself is invariant (t* = 0)
    F, g, t = term.max_admissible_set(np.array([[0.5]]), np.array([[1.0], [-1.0]]), np.array([1.0, 1.0]))
    assert t == 0 and np.allclose(np.sort((g / F[:, 0]))[[0, -1]], [-1.0, 1.0])
    # a rotation-contraction with a constraint on one coordinate only: later steps add faces, and the set is invariant
    th, r = 0.6, 0.9
    A = r * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    C = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    F, g, t = term.max_admissible_set(A, C, np.array([1.0, 1.0, 2.0, 2.0]))
    assert t >= 1
    Z = np.random.default_rng(6).uniform(-2, 2, (20_000, 2))
    inside = np.all(Z @ F.T <= g, axis=1)
    assert inside.any() and np.all(np.all((Z[inside] @ A.T) @ F.T <= g + 1e-9, axis=1))
    # maximal: the points of the set meet the constraints for the next 50 steps, the points outside it fail within them
    Zk, ok = Z.copy(), np.ones(len(Z), bool)
    for _ in range(50):
        ok &= np.all(Zk @ C.T <= np.array([1.0, 1.0, 2.0, 2.0]) + 1e-9, axis=1)
        Zk = Zk @ A.T
    assert np.all(ok[inside])
    assert not np.any(ok[~np.all(Z @ F.T <= g + 1e-7, axis=1)])
    with pytest.raises(ValueError, match="Schur"):
        term.max_admissible_set(np.array([[1.1]]), np.array([[1.0], [-1.0]]), np.array([1.0, 1.0]))
    with pytest.raises(ValueError, match="eps"):
        term.terminal_set(fl.msd(), fl.paper_net("MSD")[0], 5.0, TS, [10.0, 1.0], 0.1)


def test_shifted_plan_closes_the_loop_on_the_true_plant(quad_terminal):
    # the proof's candidate used as the control law on the true plant (v held, exact linearization): it stays
    # admissible at every sample, enters Z_f after N_p steps and then converges under v = K z
    system, net, eps, T = quad_terminal
    N = 5
    prog = term.HorizonFeasibility(system, net, eps, TS, N, T.constraint(), gains=(T.K,))
    roa = term.region_of_attraction(system, net, eps, T, horizon=N, n_grid=5, limits=((-1.0, 1.0), (-1.0, 1.0)))
    pts = roa.points()[roa.feasible_terminal == 1]
    pts = pts[~T.contains(pts)]
    assert len(pts) >= 1, "premise: a grid state outside Z_f from which the program is feasible"
    z0 = pts[np.argmax(np.linalg.norm(pts, axis=1))]
    ok, plan = prog.solve(z0)
    assert ok

    class Tail:
        net = None

        def __init__(self, plan):
            self.plan = plan

        def step(self, z, t, reference=None):
            Zp, Vp = self.plan
            v = Vp[0].copy()
            self.plan = term.shifted_plan(T, Zp, Vp)
            return fl.StepResult(v=v, status="nominal", solve_time=0.0)

    n_steps = 30
    log = fl.simulate(system, Tail(plan), t_final=n_steps * TS, ts=TS, z0=z0, net=net, check_domain=True)
    assert log.message == "" and log.n_steps == n_steps and not log.fallback.any()
    u_eps = system.u_max - eps
    assert np.all(np.abs(log.u_nn) <= u_eps + 1e-6), "the shifted plan left the network constraint"
    assert np.all(np.abs(log.u) <= system.u_max), "Proposition 1: the true input at the samples"
    assert np.all(system.in_domain(log.z))
    assert np.all(T.contains(log.z[N:], tol=1e-6)), "z(k) must be in Z_f from step N_p on"
    Vf = T.terminal_cost(log.z[N:])
    assert np.all(np.diff(Vf) <= 1e-9 * (1 + Vf[:-1])), "the terminal cost must decrease inside Z_f (axiom A4)"
    assert Vf[-1] < 0.05 * Vf[0]
