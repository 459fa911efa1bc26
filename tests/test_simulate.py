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


def _flaky(exc: Exception):
    calls = {"n": 0}

    class Flaky:
        def step(self, z, t, reference=None):
            calls["n"] += 1
            if calls["n"] % 3 == 0:
                raise exc
            return fl.StepResult(v=np.array([-z[0] - z[1]]), status="optimal", solve_time=1e-4)

    return Flaky()


def test_solver_failure_uses_fallback_and_is_counted():
    """Only the documented solver outcome (SolverFailure) triggers the fallback; the log says which rule gave v."""
    sysm = fl.msd()
    log = fl.simulate(sysm, _flaky(fl.SolverFailure("no admissible v", status="infeasible")), t_final=0.9, ts=0.1,
                      z0=[1.0, 0.0], fallback=lambda z: np.zeros(1))
    assert log.summary()["fallback_steps"] == 3
    assert all(s == "error" for s, f in zip(log.status, log.fallback) if f)
    assert all(st.message.startswith("SolverFailure: no admissible v") for st in log.steps if st.fallback)
    assert np.all(log.v[log.fallback] == 0)
    flagged = [st for st in log.steps if st.fallback]
    assert all(st.info["solver_status"] == "infeasible" and "fallback(z)" in st.info["fallback_rule"] for st in flagged)
    # without a fallback law the previous v is held
    log = fl.simulate(sysm, _flaky(fl.SolverFailure("time limit", status="time_limit")), t_final=0.9, ts=0.1,
                      z0=[1.0, 0.0])
    k = np.flatnonzero(log.fallback)
    assert len(k) == 3 and np.all(log.v[k] == log.v[k - 1])


@pytest.mark.parametrize("exc", [RuntimeError("solver crashed"), ValueError("bad shape"), TypeError("bad type"),
                                 ImportError("no module named gurobipy"), KeyError("x"), IndexError("i")])
def test_other_controller_errors_stop_the_run(exc):
    """A programming error of the controller is raised with its message, never turned into a fallback."""
    with pytest.raises(type(exc), match=str(exc.args[0])):
        fl.simulate(fl.msd(), _flaky(exc), t_final=0.9, ts=0.1, z0=[1.0, 0.0], fallback=lambda z: np.zeros(1))


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


def test_a_phi_of_the_wrong_shape_raises_at_the_start():
    """Phi is evaluated at the start the caller chose: a wrong shape is raised there, not logged as a stop."""
    import dataclasses

    sysm = dataclasses.replace(fl.msd(), phi=lambda z, v: np.hstack([v, v]))
    with pytest.raises(ValueError, match=r"phi returned shape \(1, 2\), expected \(1, 1\)"):
        fl.simulate(sysm, lambda z: np.zeros(1), t_final=0.3, ts=0.1, z0=[0.0, 1.0])
