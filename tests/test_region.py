"""The program on one activation region of the network (flnotes.mpc.region): the network is affine there, the
region QP returns a feasible plan no dearer than its start (that it changes no optimum of the MPC is checked in
tests/test_mpc_options.py)."""
import numpy as np
import pytest

import flnotes as fl
from flnotes.bench import exactness as ex
from flnotes.bench import mpc as rt
from flnotes.mpc import fallback as fb
from flnotes.mpc import region as rg


@pytest.fixture(scope="module")
def quad15():
    q = rt.quad_setup()
    setup = rt.quad_setup(horizon=15, net=q["net"], eps=q["eps"])
    return setup, rt.make_mpc(setup).pred


def _repaired(setup, pred, n, seed):
    """Diverse states whose relaxation violates the network bound and whose repaired plan passes the check."""
    out = []
    for c in ex.mpc_cases(setup, n, seed=seed):
        f, c0 = pred.linear(c["z"], c["z_ref"])
        V_c, _, _ = pred.qp(f, c["z"])
        if V_c is None or pred.feasible(c["z"], V_c):
            continue
        _, V_r = fb.qp_repair(pred, c["z"], f, V_c)
        if pred.feasible(c["z"], V_r):
            out.append((c, f, c0, V_r.reshape(-1)))
    return out


def test_the_network_is_affine_on_the_region(quad15):
    """Plans near a repaired plan that keep its activation pattern satisfy its sign rows, and the output rows give
    the forward pass there: u_max^eps - margin - (row value) equals u_max^eps - margin - Phi_NN(z(k), v(k))."""
    setup, pred = quad15
    rng = np.random.default_rng(3)
    checked = 0
    for c, f, c0, V in _repaired(setup, pred, fl.scale(10, 6), seed=2)[:3]:
        G, h, pat = rg.region_rows(pred, c["z"], V)
        n_sign = sum(p.size for p in pat)
        N = pred.N
        assert np.all(G[:n_sign] @ V <= h[:n_sign] + 1e-12), "V violates its own sign rows"
        for Vp in V + 1e-4 * rng.standard_normal((40, V.size)):
            X = np.hstack([pred.predict(c["z"], Vp)[:N], Vp.reshape(N, pred.m)])
            pre = pred.net.preactivations(X)
            if not all(np.array_equal(a > 0, p) for a, p in zip(pre, pat)):
                continue
            checked += 1
            assert np.all(G[:n_sign] @ Vp <= h[:n_sign] + 1e-12)
            u = pred.net(X).reshape(-1)
            upper = G[n_sign:n_sign + N * pred.m] @ Vp - h[n_sign:n_sign + N * pred.m]
            np.testing.assert_allclose(upper, u - (pred.u_eps[0] - rg.REGION_MARGIN), atol=1e-9)
    assert checked >= 10, "premise: perturbed plans inside the region"


def _one_switch(setup, pred, n, seed):
    """Diverse states and their one-switch plans (flnotes.mpc.bang_bang, on a coarse grid): the other first incumbent
    that the engine polishes with the region QP."""
    from flnotes.mpc.bang_bang import bang_bang_incumbent

    out = []
    for c in ex.mpc_cases(setup, n, seed=seed):
        f, c0 = pred.linear(c["z"], c["z_ref"])
        got = bang_bang_incumbent(pred, c["z"], f, c0)
        if got is not None:
            out.append((c, f, c0, got[0]))
    return out


def test_region_qp_is_feasible_and_no_dearer(quad15):
    """From the first incumbents (repaired relaxations and one-switch plans): the region QP's plan passes the
    forward-pass check and costs at most its start; the moves to neighbouring regions cost at most the first
    region's optimum."""
    setup, pred = quad15
    repaired = _repaired(setup, pred, fl.scale(16, 8), seed=4)
    cases = repaired + _one_switch(setup, pred, fl.scale(8, 4), seed=4)
    better = better_repaired = 0
    for i, (c, f, c0, V) in enumerate(cases):
        J = pred.cost(V, f, c0)
        V1 = rg.region_qp(pred, c["z"], f, V, max_moves=0)
        V2 = rg.region_qp(pred, c["z"], f, V, max_moves=rg.REGION_MOVES)
        for W in (V1, V2):
            assert W is not None and pred.feasible(c["z"], W)
        J1, J2 = pred.cost(V1, f, c0), pred.cost(V2, f, c0)
        assert J1 <= J + 1e-9 * max(1.0, abs(J)) and J2 <= J1 + 1e-9 * max(1.0, abs(J1))
        better += J1 < J - 1e-6 * max(1.0, abs(J))
        better_repaired += i < len(repaired) and J1 < J - 1e-6 * max(1.0, abs(J))
    assert len(cases) >= 3 and better >= 2, f"premise: states where the region QP improves ({len(cases)}, {better})"
    assert better_repaired >= 1, "premise: a repaired relaxation that the region QP improves"


def test_a_solver_point_over_the_bound_is_made_exact_on_its_region():
    """The book's loop at N_p = 10: where a solver's optimum exceeded u_max^eps by its tolerance, the engine took the
    QP of that point's linear region instead of tightening the rows (no margin), and that plan is the cold
    reference's optimum."""
    setup = rt.quad_setup()
    mpc = rt.make_mpc(setup)
    fl.simulate(setup["system"], mpc, t_final=fl.scale(6.0, 4.0), ts=setup["ts"], z0=setup["z0"],
                reference=setup["reference"], progress=False)
    made = [s for s in mpc.history if "made exact on its linear region" in s.message]
    assert made, "premise: a step whose solver point exceeded the bound by its tolerance"
    ref = rt.make_mpc(setup, backend="cvxpy-scip", bounds="lp")
    for s in made[:3]:
        assert s.status == "optimal" and s.info["plan_feasible"]
        assert s.info["tightened"] == 0
        r = ref(s.z_pred[0], s.info["z_ref"])
        assert r.status == "optimal"
        assert abs(s.objective - r.objective) <= 1e-6 * max(1.0, abs(r.objective)), (s.objective, r.objective)


def _flat_net_mpc(u_max: float = 1.0):
    """One integrator whose network is ``Phi_NN(z, v) = relu(v) - relu(v - 1)``: flat at exactly ``u_max = 1`` for
    ``v >= 1`` (both neurons active, output ``v - (v - 1)``), and a reference that pulls ``v`` up."""
    net = fl.ReLUNet([np.array([[0.0, 1.0], [0.0, 1.0]]), np.array([[1.0, -1.0]])], [np.array([0.0, -1.0]), np.zeros(1)])
    sysm = fl.integrators([1], lo=[-5.0, -2.0], hi=[5.0, 2.0], u_max=[u_max])
    return sysm, net, fl.MPC(sysm, net, 0.0, horizon=3, ts=0.5, Q=[1.0], R=0.01)


def test_a_flat_piece_at_exactly_u_max_keeps_its_region():
    """Where the output is constant on the region (its rows are zero), the row needs no margin: a margin would
    empty a region whose output is exactly ``u_max^eps``. Rows with a slope keep ``REGION_MARGIN``."""
    _, net, mpc = _flat_net_mpc()
    pred = mpc.pred
    z, z_ref = np.array([0.0]), np.array([4.0])
    f, _ = pred.linear(z, z_ref)
    V = np.full(pred.N, 1.5)  # every step on the flat piece
    assert np.all(net(np.c_[pred.predict(z, V.reshape(-1, 1))[: pred.N], V]) == 1.0)  # the premise
    G, h, pat = rg.region_rows(pred, z, V)
    n_sign = sum(p.size for p in pat)
    assert np.all(G[n_sign:] == 0.0) and np.all(h[n_sign: n_sign + pred.N] == 0.0)  # |1| <= 1 exactly, no margin
    W = rg.region_qp(pred, z, f, V)
    assert W is not None and pred.feasible(z, W) and np.all(W >= 1.0)
    # a region with a slope (0 < v < 1: the output is v) keeps the margin
    G, h, pat = rg.region_rows(pred, z, np.full(pred.N, 0.5))
    n_sign = sum(p.size for p in pat)
    assert np.all(np.abs(G[n_sign: n_sign + pred.N]).sum(axis=1) > 0)
    assert np.allclose(h[n_sign: n_sign + pred.N], pred.u_eps[0] - rg.REGION_MARGIN, rtol=0, atol=1e-15)
    # the controller's first input lies on the flat piece, pulled up by the reference
    r = mpc(z, z_ref)
    assert r.status == "optimal" and mpc.plan_feasible(r.z_pred, r.v_pred), r.message
    assert r.v_pred[0, 0] >= 1.0


def test_the_pattern_a_program_point_names_inverts_the_warm_start(quad15):
    """``program_pattern`` reads the activation pattern from a program's binaries: for the ``w`` that
    ``plan_vector`` builds from a plan it is the plan's forward-pass pattern, and a flipped binary flips it."""
    from flnotes.mpc.levers import node_bounds
    from flnotes.mpc.program import compact_program, plan_vector, program_pattern

    setup, pred = quad15
    mpc = rt.make_mpc(setup)
    checked = 0
    for c, f, c0, V in _repaired(setup, pred, 20, seed=11)[:4]:
        lo, hi = pred.boxes(c["z"])
        nb = node_bounds(pred, mpc.options, mpc.solver.box, lo, hi)
        steps = list(range(pred.N))
        for eliminate in (True, False):
            prob = compact_program(pred, c["z"], f, c0, nb, steps, pred.u_eps, eliminate_stable=eliminate)
            w = plan_vector(pred, c["z"], V, nb, steps, prob, eliminate)
            pat = program_pattern(pred, c["z"], w, nb, steps, prob, eliminate)
            _, pre = pred.net.forward(np.c_[pred.predict(c["z"], V.reshape(pred.N, -1))[: pred.N], V.reshape(pred.N, -1)])
            assert all(np.array_equal(p, a > 0) for p, a in zip(pat, pre))
            ib = np.flatnonzero(prob.integrality == 1)
            free = ib[prob.lb[ib] < prob.ub[ib]]
            if free.size:
                w2 = w.copy()
                w2[free[0]] = 1.0 - w2[free[0]]
                pat2 = program_pattern(pred, c["z"], w2, nb, steps, prob, eliminate)
                assert sum(int((p != q).sum()) for p, q in zip(pat, pat2)) == 1
                checked += 1
        with pytest.raises(ValueError, match="variables"):
            program_pattern(pred, c["z"], w[:-1], nb, steps, prob, True)
    assert checked >= 4, "premise: programs with a free binary"
