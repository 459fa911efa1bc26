"""Terminal ingredients (flnotes.terminal) and the MPC with them.

Properties checked: P solves the Riccati equation; the terminal set is positively invariant (by sampling and by
LPs) and inside the boxes; its MILP certificate is never below the dense-sampling maximum and is within
u_max^eps; the level psi is the largest within tolerance; the MPC with the terminal option is recursively
feasible in a nominal closed loop, its plans end in Z_f and its optimal cost decreases Lyapunov-wise; its
region of attraction is decided by the MPC itself; the shifted plan closes the loop on the true plant.
"""
import numpy as np
import pytest

import flnotes as fl
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
    # positively invariant, exactly: max over Z_f of each face of (Ad + Bd K) z, one LP per face
    F, g = T.constraint()
    for i in range(len(g)):
        assert term._lp_max(F[i] @ T.A_cl, F, g) <= g[i] + 1e-9 * (1 + abs(g[i])), f"{name}: face {i} not invariant"
    # inside the state box and K z inside the v-box: exactly, by LPs over the polytope
    lo, hi = term._bounding_box(F, g)
    assert np.all(lo >= T.z_lo - 1e-9) and np.all(hi <= T.z_hi + 1e-9)
    for i in range(system.m):
        assert term._lp_max(T.K[i], F, g) <= T.v_hi[i] + 1e-9
        assert -term._lp_max(-T.K[i], F, g) >= T.v_lo[i] - 1e-9
    # the irredundant description keeps the box and v-box rows' meaning: O_inf itself is invariant too
    Z1 = Z / T.psi
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


def test_psi_is_largest_within_tolerance(setup):
    name, system, net, eps, T = setup
    assert 0 < T.psi <= 1
    if T.psi == 1.0:
        return
    assert T.psi < T.psi_failed <= T.psi * (1 + T.tol) + 1e-12
    bigger = term.network_max(net, T.K, T.F, T.psi * (1 + T.tol) * T.g)
    assert np.any(bigger.upper > T.u_eps), f"{name}: psi (1 + tol) still passes the certificate"
    # the failure is real, not only an upper bound: a point of the larger set violates the constraint
    assert np.any(bigger.lower > T.u_eps)
    passed = [h for h in T.history if h[3]]
    assert max(h[0] for h in passed) == T.psi


def _plan_cost(T, Z, V):
    """The program's cost with the terminal cost: sum_k l(z(k), v(k)) + z(N)'P z(N) (regulation to 0)."""
    return float(np.einsum("ij,jk,ik->", Z[:-1], T.Q, Z[:-1]) + np.einsum("ij,jk,ik->", V, T.R, V)
                 + Z[-1] @ T.P @ Z[-1])


def _terminal_mpc(system, net, eps, T, N):
    return fl.MPC(system, net, eps, horizon=N, ts=T.ts, Q=T.Q, R=T.R, P=T.P, terminal=T, time_limit=60.0)


def test_recursive_feasibility_in_nominal_closed_loop(quad_terminal):
    # the theorem: from a feasible start every step of the nominal closed loop is feasible, the plan ends in Z_f,
    # the shifted plan (the proof's candidate) is feasible, and the optimal cost falls by at least l(z_k, v_k)
    system, net, eps, T = quad_terminal
    N = 5
    mpc = _terminal_mpc(system, net, eps, T, N)
    z = np.array([-1.0, 1.0, 1.0])
    assert not T.contains(z)[0], "premise: the start is outside Z_f"
    F, g = T.constraint()
    u_eps = system.u_max - eps
    J_prev, l_prev, cand, J_first = None, None, None, None
    for k in range(fl.scale(25, 12)):
        step = mpc(z, np.zeros(3))
        assert step.status == "optimal" and not step.fallback and step.input_admissible, \
            f"step {k} at z = {z}: {step.status}, fallback {step.fallback}: {step.message}"
        Zp, Vp = step.z_pred, step.v_pred
        assert np.allclose(Zp[0], z)
        assert np.all(F @ Zp[-1] <= g + 1e-6), f"step {k}: the plan's last state violates F z(N_p) <= g"
        assert np.all(np.abs(net(np.hstack([Zp[:-1], Vp]))) <= u_eps + 1e-6)
        assert np.all(Zp >= T.z_lo - 1e-6) and np.all(Zp <= T.z_hi + 1e-6)
        J = _plan_cost(T, Zp, Vp)
        if J_prev is not None:
            # the candidate of the proof is feasible here, so the optimum is at most its cost J_prev - l_prev
            Zc, Vc = cand
            assert np.allclose(Zc[0], z) and np.all(F @ Zc[-1] <= g + 1e-6)
            assert np.all(np.abs(net(np.hstack([Zc[:-1], Vc]))) <= u_eps + 1e-6)
            assert J <= J_prev - l_prev + 1e-5 * (1 + J_prev), f"step {k}: no Lyapunov decrease ({J} > {J_prev - l_prev})"
        cand = term.shifted_plan(T, Zp, Vp)
        J_first = J if J_first is None else J_first
        J_prev, l_prev = J, float(z @ T.Q @ z + step.v @ T.R @ step.v)
        z = T.Ad @ z + T.Bd @ step.v
    assert J_prev < 0.5 * J_first, "the optimal cost (a Lyapunov function) must have fallen along the run"


def test_region_of_attraction_decided_by_the_engine(quad_terminal):
    system, net, eps, T = quad_terminal
    N = 3
    roa = term.region_of_attraction(system, net, eps, T, horizon=N, n_grid=fl.scale(5, 3),
                                    limits=((-4.0, 4.0), (-4.0, 4.0)), time_limit=60.0)
    assert not np.isnan(roa.feasible).any() and not np.isnan(roa.feasible_terminal).any()
    # the terminal constraint only removes plans, and it does remove some here
    assert np.all(roa.feasible_terminal <= roa.feasible)
    assert roa.feasible_terminal.sum() >= 1 and roa.feasible_terminal.sum() < roa.feasible.sum()
    # each verdict is the engine's: re-solve a feasible and an infeasible grid state with the terminal option
    mpc = fl.MPC(system, net, eps, horizon=N, ts=T.ts, Q=T.Q, R=T.R, terminal=T, time_limit=60.0)
    Z = roa.points()
    for verdict in (1.0, 0.0):
        z = Z[roa.feasible_terminal == verdict][0]
        mpc.reset()
        step = mpc(z, np.zeros(3))
        assert (step.status == "optimal" and not step.fallback) == bool(verdict)
        if not verdict:
            assert step.status == "infeasible"
    # every state of Z_f is feasible with the terminal constraint (the terminal law is a feasible plan)
    for z in T.sample(3, seed=5):
        mpc.reset()
        step = mpc(z, np.zeros(3))
        assert step.status == "optimal" and not step.fallback


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
    z0 = np.array([-1.0, 1.0, 1.0])
    assert not T.contains(z0)[0], "premise: the start is outside Z_f"
    step = _terminal_mpc(system, net, eps, T, N)(z0, np.zeros(3))
    assert step.status == "optimal" and not step.fallback
    plan = (step.z_pred, step.v_pred)

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


def test_scip_confirms_the_highs_certificate(quad_terminal):
    """The same MILP at the certified level, solved by SCIP: the same maximum, within u_max^eps."""
    system, net, eps, T = quad_terminal
    scip = term.network_max(net, T.K, T.F, T.psi * T.g, backend="scip")
    assert np.all(scip.upper <= T.u_eps)
    assert np.allclose(scip.upper, T.certificate.upper, rtol=0, atol=1e-6)
    # the point SCIP returns attains its bound (forward pass), so the bound is tight, not merely valid
    assert np.all(scip.lower >= scip.upper - 1e-6)
    # and at the level that failed, SCIP also finds a violating point
    bad = term.network_max(net, T.K, T.F, T.psi_failed * T.g, backend="scip")
    assert np.any(bad.lower > T.u_eps)


def test_network_max_refuses_unknown_backend(quad_terminal):
    system, net, eps, T = quad_terminal
    with pytest.raises(ValueError, match="backend must be one of"):
        term.network_max(net, T.K, T.F, T.psi * T.g, backend="cplex-ish")


def test_network_max_runs_highs_at_its_stated_tolerances(quad_terminal, monkeypatch):
    """The HiGHS tolerances are set, not HiGHS's defaults (1e-6 for a MIP's solutions): the MILP goes to HiGHS with
    them, and a value HiGHS refuses stops the certificate instead of running at another tolerance."""
    from scipy.optimize import OptimizeWarning

    system, net, eps, T = quad_terminal
    assert term.FEASIBILITY_TOLERANCE == {"highs": term.HIGHS_TOLERANCES["mip_feasibility_tolerance"],
                                          "scip": term.SCIP_FEASTOL}
    assert max(term.HIGHS_TOLERANCES.values()) <= 1e-9 and term.SCIP_FEASTOL <= 1e-9
    seen = []
    real = term.milp

    def spy(*args, options=None, **kwargs):
        seen.append(dict(options))
        return real(*args, options=options, **kwargs)

    monkeypatch.setattr(term, "milp", spy)
    cert = term.network_max(net, T.K, T.F, T.psi * T.g)
    assert seen and all(o[k] == v for o in seen for k, v in term.HIGHS_TOLERANCES.items())
    assert np.allclose(cert.upper, T.certificate.upper, rtol=0, atol=1e-9)
    monkeypatch.setattr(term, "HIGHS_TOLERANCES", dict(mip_feasibility_tolerance=-1.0))  # not a valid value
    with pytest.raises(OptimizeWarning):
        term.network_max(net, T.K, T.F, T.psi * T.g)


def test_power_text_and_margin_numbers():
    from flnotes.studies.guarantees import margin_numbers, power_text

    assert (power_text(1e-9), power_text(1e-6), power_text(1e3), power_text(2.5e-7)) == ("10⁻⁹", "10⁻⁶", "10³", "2.5e-07")
    out = margin_numbers(1e-4, dict(highs=1e-9, scip=1e-8), 1e-6)
    assert out == dict(margin=1e-4, margin_tol=pytest.approx(1e4), margin_tol_default=pytest.approx(100.0))
    out = margin_numbers(1e-3, dict(highs=1e-9), 1e-6, clause=True)
    assert out["default_clause"] == "and 1,000 times HiGHS's default tolerance for a MIP's solutions (10⁻⁶)"
    out = margin_numbers(5e-6, dict(highs=1e-9), 1e-6, clause=True)
    assert out["default_clause"] == (
        "but only 5.0 times HiGHS's default tolerance for a MIP's solutions (10⁻⁶): at the default, HiGHS's certificate "
        "would sit within a few tolerances of failing, which is why the package sets the tolerances itself")
