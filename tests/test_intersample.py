"""The bound between samples (flnotes.intersample).

Properties checked: the flow is the exact discretization; delta's certified upper bound is never below sampled
drifts (whole box and admissible samples); the margin refuses an empty input set; and with the margin
u_max^{eps+delta} the true input stays within u_max at every instant of the fine grid of a closed loop on the true
plant, for a simple admissible law and for the MPC given eps + delta as its eps.
"""
import numpy as np
import pytest

import flnotes as fl
from flnotes import intersample as isb
from flnotes import terminal as term

SETTINGS = {"Quad-1D": dict(Q=[10.0, 1.0, 1.0], R=0.0175), "MSD": dict(Q=[10.0, 1.0], R=0.1)}


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


def test_mpc_with_margin_keeps_u_within_bound_between_samples():
    # the MPC given eps + delta(t_s) as its eps: |Phi_NN| <= u_max^{eps+delta} at the samples, hence |u(t)| <= u_max
    # on the fine grid between them (v held, the true plant)
    system = fl.quad1d()
    net, _ = fl.paper_net("Quad-1D")
    eps = float(fl.paper_eps("Quad-1D").upper[0])
    ts = 0.05
    delta = float(isb.intersample_drift(system, ts).upper[0])
    bound = float(isb.margin(system, eps, delta)[0])
    mpc = fl.MPC(system, net, eps + delta, horizon=10, ts=ts, Q=SETTINGS["Quad-1D"]["Q"], R=SETTINGS["Quad-1D"]["R"],
                 time_limit=30.0)
    z0 = [0.0, 2.0, 0.0]
    t_final = fl.scale(2.0, 1.0)
    log = fl.simulate(system, mpc, t_final=t_final, ts=ts, z0=z0, reference=lambda t: np.zeros((np.size(t), 3)),
                      net=net, n_fine=40)
    assert log.message == "" and log.n_steps == int(round(t_final / ts))
    assert not log.fallback.any() and all(s.input_admissible for s in mpc.history)
    assert np.all(system.in_domain(log.z[:-1], log.v))
    assert np.all(np.abs(log.u_nn) <= bound + 1e-6)
    # premise: the margin matters, the bound at the samples is active somewhere
    assert np.abs(log.u_nn).max() >= 0.9 * bound, "premise: the input bound is active in this run"
    assert np.all(np.abs(log.u_fine) <= system.u_max + 1e-7), (
        f"max |u| between samples {np.abs(log.u_fine).max()} > u_max {system.u_max}")
