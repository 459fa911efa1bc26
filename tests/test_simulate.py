"""Closed-loop simulation: exact linearization under hold='v', bookkeeping, and graceful failures."""
import numpy as np
import pytest

import flnotes as fl


def test_hold_v_linearizes_the_true_plant_exactly():
    """With v held and u = Phi(z(t), v), the true plant follows z' = A z + B v: compare with Ad, Bd."""
    for sysm, z0 in [(fl.msd(), np.array([0.3, -1.0])), (fl.quad1d(), np.array([-0.5, -0.15, -0.2]))]:
        ts = 0.05
        Ad, Bd = sysm.discretize(ts)
        law = lambda z: np.array([0.5 * np.sin(3 * z[0])])  # any law: the identity must hold step by step
        log = fl.simulate(sysm, law, t_final=1.0, ts=ts, z0=z0)
        pred = log.z[:-1] @ Ad.T + log.v @ Bd.T
        assert np.abs(pred - log.z[1:]).max() < 1e-6


def test_hold_u_keeps_u_constant_between_samples():
    sysm = fl.quad1d()
    log = fl.simulate(sysm, lambda z: np.array([-2.0 * z[0] - 2 * z[1] - z[2]]), t_final=0.5, ts=0.1,
                      z0=[-0.5, -0.15, -0.2], hold="u")
    per_step = log.u_fine.reshape(log.n_steps, -1)
    assert np.allclose(per_step, log.u[:, :1])


def test_log_shapes_and_summary():
    sysm = fl.msd()
    K = fl.paper.MSD_SETTING["K_nominal"]
    log = fl.simulate(sysm, lambda z: -K @ z, t_final=0.5, ts=0.05, z0=[0.0, 4.0], n_fine=4)
    n = log.n_steps
    assert n == 10
    assert log.z.shape == (n + 1, 2) and log.v.shape == (n, 1) and log.u.shape == (n, 1)
    assert log.u_fine.shape == (4 * n, 1) and log.t_fine.shape == (4 * n,)
    s = log.summary()
    assert s["steps"] == n and s["fallback_steps"] == 0
    # the true u recorded at samples is Phi(z_k, v_k)
    assert np.allclose(log.u, sysm.Phi(log.z[:-1], log.v))
    # the nominal law alone violates |u| <= 5 from z(0) = [0, 4]: the reason for the course
    assert s["max_abs_u_samples"][0] > 5.0 and not s["u_within_bound_at_samples"]


def test_controller_failure_uses_fallback_and_is_counted():
    sysm = fl.msd()
    calls = {"n": 0}

    class Flaky:
        def step(self, z, t, reference=None):
            calls["n"] += 1
            if calls["n"] % 3 == 0:
                raise RuntimeError("solver crashed")
            return fl.StepResult(v=np.array([-z[0] - z[1]]), status="optimal", solve_time=1e-4)

    log = fl.simulate(sysm, Flaky(), t_final=0.9, ts=0.1, z0=[1.0, 0.0], fallback=lambda z: np.zeros(1))
    assert log.summary()["fallback_steps"] == 3
    assert all(s.startswith("error: RuntimeError") for s, f in zip(log.status, log.fallback) if f)
    assert np.all(log.v[log.fallback] == 0)


def test_run_stops_with_a_message_at_the_singularity():
    """Quad-1D driven towards |zeta| = 1: the run ends with a message, not a traceback."""
    sysm = fl.quad1d()
    log = fl.simulate(sysm, lambda z: np.array([400.0]), t_final=3.0, ts=0.1, z0=[0, 0, 0])
    assert log.message.startswith("stopped at t =")
    assert log.n_steps < 30


@pytest.mark.parametrize("kw, match", [
    (dict(hold="x"), "hold"),
    (dict(ts=-1.0), "ts"),
    (dict(z0=None), "initial condition"),
    (dict(z0=[0.0, 1.0, 2.0]), "z0"),
])
def test_bad_arguments_raise_clear_errors(kw, match):
    args = dict(t_final=1.0, ts=0.1, z0=[0.0, 1.0])
    args.update(kw)
    with pytest.raises(ValueError, match=match):
        fl.simulate(fl.msd(), lambda z: np.zeros(1), **args)
