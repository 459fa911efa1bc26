"""Checks for assignment 2 (a2_encode_by_hand.ipynb): big-M encoding of a 2-2-1 ReLU network."""
import itertools

import numpy as np
from scipy.optimize import linprog

from flnotes.grading import points

W1 = np.array([[1.0, -1.0], [0.5, 1.0]])
B1 = np.array([0.2, -0.3])
W2 = np.array([[1.0, -2.0]])
B2 = np.array([0.1])
LO, HI = np.array([-1.0, -1.0]), np.array([1.0, 1.0])


def _forward(x):
    h = np.maximum(0.0, np.asarray(x, dtype=float) @ W1.T + B1)
    return (h @ W2.T + B2)[..., 0]


def _need(ns, name, kind="function"):
    assert name in ns, f"`{name}` is not defined: write the {kind} `{name}` in the cell of this part"
    return ns[name]


def _network_unchanged(ns):
    for name, ref in (("W1", W1), ("b1", B1), ("W2", W2), ("b2", B2), ("x_lo", LO), ("x_hi", HI)):
        got = np.asarray(ns.get(name, np.nan), dtype=float)
        assert got.shape == ref.shape and np.allclose(got, ref), f"`{name}` was changed; restore the given network"


def _exact_max():
    """Global max of the network over the box: one LP per activation pattern."""
    best = -np.inf
    for pattern in itertools.product((0.0, 1.0), repeat=2):
        p = np.array(pattern)
        # y = W2 diag(p) (W1 x + B1) + B2 on the region where the pattern holds
        c = -(W2[0] * p) @ W1
        const = (W2[0] * p) @ B1 + B2[0]
        # active: W1 x + B1 >= 0  ->  -W1 x <= B1 ; inactive: W1 x + B1 <= 0
        A = np.where(p[:, None] > 0, -W1, W1)
        ub = np.where(p > 0, B1, -B1)
        res = linprog(c, A_ub=A, b_ub=ub, bounds=list(zip(LO, HI)), method="highs")
        if res.status == 0:
            best = max(best, -res.fun + const)
    return best


@points(2)
def check_bounds(ns):
    _network_unchanged(ns)
    fn = _need(ns, "interval_bounds")
    L1, U1 = (np.asarray(a, dtype=float) for a in (_need(ns, "L1", "array"), _need(ns, "U1", "array")))
    Wp, Wn = np.maximum(W1, 0), np.minimum(W1, 0)
    ref_L, ref_U = Wp @ LO + Wn @ HI + B1, Wp @ HI + Wn @ LO + B1
    assert L1.shape == (2,) and U1.shape == (2,), f"L1 and U1 must have shape (2,), got {L1.shape}, {U1.shape}"
    assert np.all(L1 <= ref_L + 1e-9) and np.all(U1 >= ref_U - 1e-9), (
        f"L1 = {L1}, U1 = {U1} are not valid bounds: some pre-activation leaves [L1, U1] on the box"
    )
    assert np.allclose(L1, ref_L) and np.allclose(U1, ref_U), (
        f"L1 = {L1}, U1 = {U1} are valid but not the tightest interval bounds (a corner of the box reaches each bound)"
    )
    # the function must be general, not tuned to this network
    W = np.array([[2.0, -3.0, 0.5]])
    lo, hi = np.array([0.0, -1.0, -2.0]), np.array([1.0, 2.0, 2.0])
    L, U = (np.asarray(a, dtype=float) for a in fn(W, np.array([1.0]), lo, hi))
    assert np.allclose(L, [2 * 0 - 3 * 2 + 0.5 * -2 + 1]) and np.allclose(U, [2 * 1 - 3 * -1 + 0.5 * 2 + 1]), (
        "interval_bounds is wrong on another layer (W = [[2, -3, 0.5]], b = [1], box [0,1]x[-1,2]x[-2,2])"
    )


@points(3)
def check_forward(ns):
    _network_unchanged(ns)
    fn = _need(ns, "milp_forward")
    rng = np.random.default_rng(21)
    pts = np.vstack([rng.uniform(LO, HI, size=(12, 2)), [[-1, -1], [1, 1], [1, -1], [-1, 1], [0.0, 0.0]]])
    for p in pts:
        got = float(fn(p))
        ref = float(_forward(p))
        assert abs(got - ref) < 1e-6, f"milp_forward({p.tolist()}) = {got:.6g} but the network gives {ref:.6g}"


@points(3)
def check_max(ns):
    _network_unchanged(ns)
    fn = _need(ns, "milp_max")
    out = fn()
    assert isinstance(out, tuple) and len(out) == 2, "milp_max() must return a pair (y_max, x_star)"
    y_max, x_star = float(out[0]), np.asarray(out[1], dtype=float)
    ref = _exact_max()
    assert x_star.shape == (2,), f"x_star must have shape (2,), got {x_star.shape}"
    assert np.all(x_star >= LO - 1e-7) and np.all(x_star <= HI + 1e-7), f"x_star = {x_star} is outside the box"
    assert abs(float(_forward(x_star)) - y_max) < 1e-6, (
        f"the network at x_star gives {float(_forward(x_star)):.6g}, not y_max = {y_max:.6g}: is the encoding exact?"
    )
    assert abs(y_max - ref) < 1e-6, f"y_max = {y_max:.6g} but the global maximum is {ref:.6g}"
