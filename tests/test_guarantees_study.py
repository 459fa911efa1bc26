"""The chapter-9 studies of flnotes.studies.guarantees that are not covered elsewhere.

Properties checked: the sampled share of pairs that keep |u| <= u_max over the hold is 1 when the bound at the
samples includes the certified margin (the theorem of flnotes.intersample, on a sample) and below 1 for the
quadrotor with eps alone at t_s = 0.1 s; the combined loop (terminal set for u_max^{eps+delta}) refuses a terminal
set built for another bound, and on the MSD it keeps every step optimal, drives the network bound active and keeps
|u(t)| <= u_max along the exact flow between the samples.
"""
import numpy as np
import pytest

import flnotes as fl
from flnotes.studies import guarantees as G

MSD_Q, MSD_R = np.diag([10.0, 1.0]), np.array([[0.01]])


@pytest.fixture(scope="module")
def msd_margin():
    system = fl.msd()
    net, _ = fl.paper_net("MSD")
    eps = float(fl.paper_eps("MSD").upper[0])
    delta = float(fl.intersample_drift(system, 0.1).upper[0])
    return system, net, eps, delta


def test_sampled_pairs_keep_the_bound_with_the_margin(msd_margin):
    system, net, eps, delta = msd_margin
    u_max = float(system.u_max[0])
    with_margin = G.intersample_sample(system, net, u_max - eps - delta, 0.1, n_samples=20_000, n_tau=21)
    assert with_margin["n_admissible"] > 100
    assert with_margin["fraction_kept"] == 1.0 and with_margin["max_abs_u"] <= u_max
    alone = G.intersample_sample(system, net, u_max - eps, 0.1, n_samples=20_000, n_tau=21)
    assert alone["n_admissible"] > with_margin["n_admissible"]
    assert alone["fraction_kept"] <= 1.0


def test_sampled_pairs_quad_eps_alone_violate_sometimes():
    quad = fl.quad1d()
    net, _ = fl.paper_net("Quad-1D")
    eps = float(fl.paper_eps("Quad-1D").upper[0])
    u_max = float(quad.u_max[0])
    s = G.intersample_sample(quad, net, u_max - eps, 0.1, n_samples=20_000, n_tau=21)
    assert 0.0 < s["fraction_kept"] < 1.0 and s["max_abs_u"] > u_max
    # a shorter hold keeps more pairs within the bound (the same pairs, a shorter flow)
    short = G.intersample_sample(quad, net, u_max - eps, 0.025, n_samples=20_000, n_tau=21)
    assert short["n_admissible"] == s["n_admissible"] and short["fraction_kept"] >= s["fraction_kept"]
    with pytest.raises(ValueError, match="ts > 0"):
        G.intersample_sample(quad, net, u_max - eps, 0.0)


def test_guaranteed_loop_on_the_msd(msd_margin):
    system, net, eps, delta = msd_margin
    T = fl.terminal_set(system, net, eps + delta, 0.1, MSD_Q, MSD_R)
    with pytest.raises(ValueError, match="terminal was built for"):
        G.guaranteed_loop(system, net, eps, 0.0, T, np.array([-1.0, 1.0]), 1.0, horizon=10)
    log, row = G.guaranteed_loop(system, net, eps, delta, T, np.array([-1.0, 1.0]), 1.0, horizon=10, n_dense=51,
                                 time_limit=30.0)
    assert row["completed"] and row["statuses"] == {"optimal": row["steps"]} and row["fallback"] == 0
    assert row["active_steps"] > 0 and abs(row["max_abs_phi_nn"] - row["bound"]) <= 1e-6
    assert row["within_u_max"] and row["max_abs_u_between"] <= float(system.u_max[0])
    # the dense check is the true map along the exact flow: it reproduces the simulator's samples
    assert np.allclose(np.abs(log.u).max(), np.abs(system.Phi(log.z[:-1], log.v)).max())
    # the figure draws each run and refuses an empty mapping
    import matplotlib

    matplotlib.use("Agg")
    from flnotes.plots.guarantees import plot_guaranteed_loop

    ax = plot_guaranteed_loop({"run": log}, float(system.u_max[0]), {"b": row["bound"]})
    assert len(ax.lines) >= 2
    with pytest.raises(ValueError, match="at least one"):
        plot_guaranteed_loop({}, 5.0, {})


def test_terminal_sweep_reports_the_input_between_samples(msd_margin):
    """On the true plant the row carries the largest |u(t)| between samples as the simulator applied it (not
    saturated), at least the largest at the samples; the nominal model has no input between samples (NaN)."""
    system, net, eps, _ = msd_margin
    T = fl.terminal_set(system, net, eps, 0.1, MSD_Q, MSD_R)
    runs, rows = G.terminal_sweep(system, net, eps, T, (2,), np.array([-1.0, 1.0]), 0.5, time_limit=30.0)
    for r in rows:
        if r["plant"] == "nominal":
            assert np.isnan(r["max_abs_u_between"])
        else:
            log = runs[(2, r["ingredients"] == "P_f and Z_f", "true")]["log"]
            assert r["max_abs_u_between"] == pytest.approx(np.abs(log.u_fine).max())
            assert r["max_abs_u_between"] >= r["max_abs_u_samples"] - 1e-9


def test_margin_study_numbers_names_the_late_runs():
    def row(margin, max_ms):
        return dict(margin=margin, max_abs_u_between=1.0, rms_x_error_second_half=0.1, mean_ms=5.0, max_ms=max_ms)

    out = G.margin_study_numbers([row("eps", 20.0), row("eps+Delta", 30.0)], t_s=0.05)
    assert (out["eps_max_ms"], out["eps_delta_max_ms"], out["eps_delta_mean_ms"]) == (20.0, 30.0, 5.0)
    assert {k for k in out if k != "late"} == {f"{m}_{c}" for m in ("eps", "eps_delta") for c in (
        "max_abs_u_between", "rms_x_error_second_half", "mean_ms", "max_ms")}
    assert out["late"] == ("no step of either run took longer than the sampling interval here, which a slower or busier "
                           "machine can change")
    tail = " took longer than the sampling interval, and an answer later than the sampling interval is not a real-time controller"
    late = G.margin_study_numbers([row("eps", 60.0), row("eps+Delta", 30.0)], t_s=0.05)["late"]
    assert late == "the slowest step with ε" + tail
    late = G.margin_study_numbers([row("eps", 60.0), row("eps+Delta", 70.0)], t_s=0.05)["late"]
    assert late == "the slowest step with ε and with ε + Δ" + tail
