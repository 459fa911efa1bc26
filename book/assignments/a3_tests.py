"""Checks for assignment 3 (a3_tune_gain.ipynb): a linear law under the true input bound."""
import numpy as np

from flnotes.grading import points

U_MAX = 5.0
Z0 = np.array([0.0, 4.0])
T_FINAL = 15.0


def _s(x):
    return (0.8 + 0.2 * np.exp(-100.0 * np.abs(x))) * np.tanh(10.0 * x) + x


def _traj(lam, t):
    e = np.exp(-lam * t)
    return Z0[1] * t * e, Z0[1] * (1.0 - lam * t) * e


def _u(lam, t):
    z1, z2 = _traj(lam, t)
    return -(lam**2) * z1 - 2.0 * lam * z2 + _s(z2) + z1


_T_FINE = np.linspace(0.0, T_FINAL, 30001)


def _peak(lam):
    return float(np.max(np.abs(_u(lam, _T_FINE))))


def _bisect(ok_at, bad_at, tol=1e-6):
    while abs(bad_at - ok_at) > tol:
        mid = 0.5 * (ok_at + bad_at)
        ok_at, bad_at = (mid, bad_at) if _peak(mid) <= U_MAX else (ok_at, mid)
    return ok_at


def _need(ns, name, kind="function"):
    assert name in ns, f"`{name}` is not defined: write the {kind} `{name}` in the cell of this part"
    return ns[name]


def _data_unchanged(ns):
    assert float(ns.get("U_MAX", np.nan)) == U_MAX, "U_MAX was changed; restore 5.0"
    assert np.allclose(np.asarray(ns.get("Z0", np.nan), dtype=float), Z0), "Z0 was changed; restore (0, 4)"


@points(2)
def check_closed_loop(ns):
    _data_unchanged(ns)
    cl, ut = _need(ns, "closed_loop"), _need(ns, "u_true")
    tt = np.linspace(0.0, 6.0, 61)
    for lam in (0.4, 1.0):
        z1, z2 = (np.asarray(a, dtype=float) for a in cl(lam, tt))
        r1, r2 = _traj(lam, tt)
        assert z1.shape == tt.shape and z2.shape == tt.shape, "closed_loop(lam, t) must return two arrays shaped like t"
        err = max(np.max(np.abs(z1 - r1)), np.max(np.abs(z2 - r2)))
        assert err < 1e-4, f"closed_loop({lam}, t) is off by {err:.3g} (poles at -lam, z(0) = Z0?)"
        u = np.asarray(ut(lam, tt), dtype=float)
        err_u = np.max(np.abs(u - _u(lam, tt)))
        assert err_u < 1e-3, f"u_true({lam}, t) is off by {err_u:.3g}: u = v + s(z2) + z1 with v = -lam^2 z1 - 2 lam z2"


@points(2)
def check_max_abs_u(ns):
    _data_unchanged(ns)
    fn = _need(ns, "max_abs_u")
    for lam in (0.3, 0.8, 1.3):
        got, ref = float(fn(lam)), _peak(lam)
        assert abs(got - ref) < 1e-2, f"max_abs_u({lam}) = {got:.4g}, expected {ref:.4g}"


@points(3)
def check_gain_interval(ns):
    _data_unchanged(ns)
    lo, hi, best = (float(_need(ns, k, "number")) for k in ("lam_min", "lam_max", "lam_best"))
    ref_lo, ref_hi = _bisect(0.75, 0.1), _bisect(0.75, 2.0)
    assert abs(lo - ref_lo) <= 0.01, f"lam_min = {lo:.4f} is not within 0.01 of the smallest admissible gain"
    assert abs(hi - ref_hi) <= 0.01, f"lam_max = {hi:.4f} is not within 0.01 of the largest admissible gain"
    assert _peak(best) <= U_MAX + 1e-2, f"lam_best = {best:.4f} violates |u| <= 5 (peak {_peak(best):.3f})"
    assert abs(best - ref_hi) <= 0.01, "lam_best should be the fastest admissible gain"
