"""Checks for assignment 1 (a1_derive_phi.ipynb): Φ for the inverted pendulum.

Each ``check_*`` receives the notebook's namespace and raises AssertionError with
a hint when the work is wrong. Points are given by ``@points``.
"""
import numpy as np

from flnotes.grading import points

# the instructor's own copy of the data, so that a changed parameter in the
# notebook is caught rather than silently graded against itself
M, L, G, B, U_MAX = 0.5, 0.6, 9.81, 0.1, 3.0


def _phi_ref(z, v):
    z = np.asarray(z, dtype=float)
    return M * L**2 * np.asarray(v, dtype=float) - M * G * L * np.sin(z[..., 0]) + B * z[..., 1]


def _need(ns, name, kind="function"):
    assert name in ns, f"`{name}` is not defined: write the {kind} `{name}` in the cell of this part"
    return ns[name]


def _data_unchanged(ns):
    got = tuple(float(ns.get(k, np.nan)) for k in ("m", "l", "g", "b", "u_max"))
    assert np.allclose(got, (M, L, G, B, U_MAX)), (
        "the pendulum data m, l, g, b, u_max were changed; restore the given values"
    )


@points(3)
def check_phi(ns):
    _data_unchanged(ns)
    phi = _need(ns, "phi")
    assert callable(phi), "`phi` must be a function phi(z, v)"
    rng = np.random.default_rng(11)
    z = rng.uniform([-np.pi, -4.0], [np.pi, 4.0], size=(64, 2))
    v = rng.uniform(-10.0, 10.0, size=64)
    got = np.asarray(phi(z, v), dtype=float)
    assert got.shape == (64,), f"phi(z, v) with z.shape == (64, 2), v.shape == (64,) must return shape (64,), got {got.shape}"
    ref = _phi_ref(z, v)
    err = float(np.max(np.abs(got - ref)))
    if err > 1e-8:
        # tell the student which term is off
        no_grav = np.max(np.abs(got - (ref + M * G * L * np.sin(z[:, 0]))))
        hint = " (the gravity term looks missing or of the wrong sign)" if no_grav < 1e-8 else ""
        raise AssertionError(f"phi differs from the input that gives theta_ddot = v by up to {err:.3g}{hint}")
    one = np.asarray(phi(z[0], v[0]), dtype=float)
    assert one.shape == (), f"phi on a single point (z.shape == (2,), scalar v) must return a scalar, got shape {one.shape}"
    assert abs(float(one) - ref[0]) < 1e-8, "phi on a single point disagrees with phi on an array"


@points(2)
def check_identity(ns):
    samples = np.asarray(_need(ns, "identity_samples", "array"), dtype=float)
    err = _need(ns, "identity_error", "float")
    assert samples.ndim == 2 and samples.shape[1] == 3, f"identity_samples must have shape (N, 3), got {samples.shape}"
    assert samples.shape[0] >= 1000, f"use at least 1000 samples, got {samples.shape[0]}"
    lo, hi = np.array([-np.pi, -4.0, -10.0]), np.array([np.pi, 4.0, 10.0])
    assert np.all(samples >= lo - 1e-12) and np.all(samples <= hi + 1e-12), "samples must lie in the given box"
    assert np.all(np.ptp(samples, axis=0) > 0.5 * (hi - lo)), "samples do not spread over the box: draw them at random"
    assert isinstance(err, (float, np.floating)) and np.isfinite(err), "identity_error must be a finite float"
    assert err < 1e-9, f"identity_error = {err:.3g}: with the right Φ the identity holds to rounding error"
    # recompute with the instructor's dynamics and the student's Φ
    phi = _need(ns, "phi")
    z, v = samples[:, :2], samples[:, 2]
    u = np.asarray(phi(z, v), dtype=float)
    theta_ddot = G / L * np.sin(z[:, 0]) - B / (M * L**2) * z[:, 1] + u / (M * L**2)
    ref = float(np.max(np.abs(theta_ddot - v)))
    assert abs(ref - float(err)) < 1e-9, f"identity_error = {float(err):.3g} but the samples give {ref:.3g}"


@points(3)
def check_v_interval(ns):
    _data_unchanged(ns)
    fn = _need(ns, "v_interval")
    rng = np.random.default_rng(12)
    z = rng.uniform([-np.pi, -4.0], [np.pi, 4.0], size=(50, 2))
    out = fn(z)
    assert isinstance(out, tuple) and len(out) == 2, "v_interval(z) must return a pair (v_min, v_max)"
    vmin, vmax = (np.asarray(a, dtype=float) for a in out)
    assert vmin.shape == (50,) and vmax.shape == (50,), f"expected two arrays of shape (50,), got {vmin.shape}, {vmax.shape}"
    drift = M * G * L * np.sin(z[:, 0]) - B * z[:, 1]
    ref_lo, ref_hi = (-U_MAX + drift) / (M * L**2), (U_MAX + drift) / (M * L**2)
    assert np.all(vmin <= vmax), "v_min must not exceed v_max"
    assert np.allclose(vmin, ref_lo, atol=1e-8) and np.allclose(vmax, ref_hi, atol=1e-8), (
        "the interval is wrong: at its ends |Φ(z, v)| must equal u_max exactly"
    )
