"""What the MPC applies when a solve gives no plan, and the step-by-step repairs it is built from.

Safety first: a plan is accepted only when :meth:`flnotes.mpc.prediction.Prediction.feasible` passes it
(boxes, terminal rows, and the network bound by the forward pass); otherwise only the first input is
made admissible, and when no admissible input exists at the measured state the least-violation input is
returned and flagged. See :func:`fallback_plan`.

The repairs (:func:`repair_plan`, :func:`qp_repair`) move one input at a time to an admissible one
(:func:`feasible_tail`): exact for one and two inputs; with three or more inputs an input is kept as it
is, so a repair succeeds there only where the guess already satisfies the program, and :func:`safe_input`
samples (its flag then means "none found", not "none exists").
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from .._checks import as_floats, as_state, check_bool, check_count, check_number
from ..solvers import BOUND_TOL, FEAS_TOL
from .prediction import Prediction

Array = np.ndarray



def _past(deadline: Optional[float]) -> bool:
    """Has ``deadline`` (a :func:`time.perf_counter` value, ``None``: none) passed?"""
    return deadline is not None and time.perf_counter() >= deadline


def _check_pred(pred) -> None:
    """``TypeError`` unless ``pred`` is a :class:`Prediction` (the model the repairs read)."""
    if not isinstance(pred, Prediction):
        raise TypeError(f"pred must be a flnotes.mpc.prediction.Prediction (an MPC's model, MPC.pred), got "
                        f"{type(pred).__name__}")


def _check_state(pred: Prediction, z) -> Array:
    """The state ``z`` as a finite float vector (n_z,) (:func:`flnotes._checks.as_state`: a number is a state of one
    coordinate only; ``ValueError`` naming it otherwise)."""
    return as_state(z, pred.nz, "z")


def _check_guess(pred: Prediction, v_guess, name: str = "v_guess") -> Array:
    """A plan's inputs ``v_guess`` as finite floats of shape (N_p, m) (a flat (N_p m,) array too); ``name``: what
    the errors call it."""
    V = as_floats(v_guess, name)
    if V.shape != (pred.N, pred.m) and np.squeeze(V).shape in {np.squeeze(np.empty((pred.N, pred.m))).shape,
                                                               (pred.N * pred.m,)}:
        V = V.reshape(pred.N, pred.m)  # flat as Prediction takes it, or with axes of length 1 (e.g. (1, N_p) for m = 1)
    if V.shape != (pred.N, pred.m):
        raise ValueError(f"{name} must be inputs of shape (N_p, m) = ({pred.N}, {pred.m}) or ({pred.N * pred.m},), "
                         f"got shape {np.shape(v_guess)}")
    if not np.all(np.isfinite(V)):
        raise ValueError(f"{name} must be finite inputs: it contains NaN or inf")
    return V


def _check_deadline(deadline) -> Optional[float]:
    """``deadline`` as a float (a :func:`time.perf_counter` value) or ``None``."""
    return check_number(deadline, "deadline", "a time.perf_counter() value", low=-np.inf, none=True)


def repair_plan(pred: Prediction, z: Array, v_guess: Array, first: bool = True,
                deadline: Optional[float] = None) -> tuple[Array, Array]:
    """A plan built step by step from ``v_guess`` (N_p, m), each input replaced by :meth:`feasible_tail`.

    With ``first=False`` the first input is kept as given. The repair stops at ``deadline`` (a
    :func:`time.perf_counter` value; the later inputs are then kept as guessed). Check the result with
    :meth:`plan_feasible`.

    ``z`` (n_z,) and ``v_guess`` ((N_p, m) or flat) must be finite numbers, ``first`` True or False; anything else
    is a ``ValueError`` naming it.
    """
    _check_pred(pred)
    z = _check_state(pred, z)
    V = _check_guess(pred, v_guess)
    first = check_bool(first, "first", "whether the first input is repaired too")
    return _repair_plan(pred, z, V, first, _check_deadline(deadline))


def _repair_plan(pred: Prediction, z: Array, v_guess: Array, first: bool = True,
                 deadline: Optional[float] = None) -> tuple[Array, Array]:
    """:func:`repair_plan` without its checks (the callers here pass checked arrays)."""
    V = np.array(v_guess, float).reshape(pred.N, pred.m)
    zk = np.asarray(z, float)
    for k in range(pred.N):
        if _past(deadline):
            break
        if first or k:
            V[k] = _feasible_tail(pred, zk, V[k], last=k == pred.N - 1)
        zk = pred.Ad @ zk + pred.Bd @ V[k]
    return pred.predict(z, V), V


def _admissible(pred: Prediction, z: Array, cand: Array, last: bool) -> Array:
    """Which rows of ``cand`` (n, m) meet ``|Phi_NN(z, v)| <= u_max^eps`` (forward pass) and keep
    ``A_d z + B_d v`` in the state box (and, for the ``last`` step, in the terminal set). ``z`` is one state (n_z,)
    or one per row of ``cand`` (n, n_z)."""
    X = np.empty((len(cand), pred.nz + pred.m))  # [z, v] per row
    X[:, :pred.nz], X[:, pred.nz:] = z, cand
    u = pred.net._forward(X)[0]  # checked floats: the forward pass without its checks
    nxt = X[:, :pred.nz] @ pred.Ad.T + cand @ pred.Bd.T
    ok = ((np.abs(u) <= pred.u_eps + BOUND_TOL).all(axis=1) & (nxt >= pred.z_lo).all(axis=1)
          & (nxt <= pred.z_hi).all(axis=1))
    if last and pred.F is not None:
        ok &= np.all(nxt @ pred.F.T <= pred.g, axis=1)
    return ok


def _step_rows(pred: Prediction, z: Array, last: bool) -> Optional[tuple[Array, Array]]:
    """The rows ``G v + h <= 0`` that keep ``A_d z + B_d v`` in the state box (and the terminal set when ``last``).

    Rows that do not involve ``v`` are dropped when they hold and make the result ``None`` when they do not.
    """
    Az = pred.Ad @ z
    G = np.vstack([pred.Bd, -pred.Bd])
    h = np.concatenate([Az - pred.z_hi, pred.z_lo - Az])
    if last and pred.F is not None:
        G, h = np.vstack([G, pred.F @ pred.Bd]), np.concatenate([h, pred.F @ Az - pred.g])
    free = np.any(G != 0.0, axis=1)
    if np.any(h[~free] > 0.0):
        return None
    return G[free], h[free]


def _step_interval(pred: Prediction, z: Array, last: bool = False) -> tuple[float, float]:
    """One input: the interval ``[lo, hi]`` of ``v`` that meets :func:`_step_rows` (the next state in its box, and in
    the terminal set when ``last``); empty (``lo > hi``) when no ``v`` does."""
    rows = _step_rows(pred, z, last)
    if rows is None:
        return np.inf, -np.inf
    g, h = rows[0][:, 0], rows[1]
    up, down = g > 0, g < 0  # g v + h <= 0: v <= -h/g where g > 0, v >= -h/g where g < 0
    return (float(np.max(-h[down] / g[down], initial=-np.inf)), float(np.min(-h[up] / g[up], initial=np.inf)))


def _in_step_rows(pred: Prediction, z: Array, v: Array, last: bool) -> Array:
    """Which of the one-input values ``v`` (n,) can meet :func:`_step_rows` (the next state in its box, and in the
    terminal set when ``last``), with a margin for round-off: a value outside is never admissible
    (:func:`_admissible` checks the same rows on the next state), so it need not be passed through the network."""
    rows = _step_rows(pred, z, last)
    if rows is None:
        return np.zeros(v.shape, bool)
    G, h = rows
    if not len(h):  # no row involves v (B_d = 0): every value keeps the next state where it is
        return np.ones(v.shape, bool)
    # the round-off of A_d z + B_d v in _admissible is relative to the size of its terms, not to their difference
    # from the box's face (a state of size 1e9 near its face): the margin is relative to the largest of them
    scale = 1.0 + max(float(np.max(np.abs(pred.Ad @ z))), float(np.max(np.abs(np.r_[pred.z_lo, pred.z_hi]))),
                      float(np.max(np.abs(h))), float(np.max(np.abs(G))) * float(np.max(np.abs(v))))
    return np.all(np.outer(v, G[:, 0]) + h <= 1e-6 * scale, axis=1)


#: Grid points of a one-input search (:func:`feasible_tail`) checked first, the nearest to the guess; the rest only
#: when none of them is admissible.
_NEAR = 128

#: Grid points of a one-input search (:func:`feasible_tail`) over ``[v_lo, v_hi]``, where the exact set gives no
#: candidate that passes the forward pass.
FEASIBLE_TAIL_GRID = 2001


def feasible_tail(pred: Prediction, z: Array, v_guess: Array, n_grid: int = FEASIBLE_TAIL_GRID,
                  last: bool = False) -> Array:
    """An input ``v`` with ``|Phi_NN(z, v)| <= u_max^eps`` and ``A_d z + B_d v`` in the state box (and, for the
    ``last`` step, in the terminal set), closest to ``v_guess``.

    One input: exact, over the intervals where ``|Phi_NN(z, v)| <= u_max^eps`` (chapter 6's exact 1-D method,
    :func:`flnotes.exact_1d_feasible_set`) cut by the rows of the state box and the terminal set: the nearest point
    of each interval, pulled inside only as far as the forward pass needs (:func:`_nearest_exact_1d`); a grid of the
    ``v``-range (``n_grid`` points) only where none of those passes the forward pass (round-off) or the network has
    more than one output (an admissible sliver narrower than 1e-12 of the ``v``-range can be missed: knots of the
    pieces closer than that are one). The exact path aims at the program's bound ``u_max^eps``; the guess and the
    grid's points are judged by the check itself, to its :data:`flnotes.solvers.BOUND_TOL`. Two inputs: exact, over the convex
    polygons where the network is affine in ``v`` (:func:`flnotes.pieces.network_regions`, cut by the rows of
    the state box and the terminal set, then by the output bound): the point of each polygon nearest to
    ``v_guess``. Every candidate is checked with the forward pass. ``v_guess`` is returned unchanged when it is
    admissible, when no candidate is, and for three or more inputs (no search there: a repair built from such a
    step is rejected by :meth:`Prediction.feasible`, and :func:`safe_input` handles the first input).

    ``z`` (n_z,) and ``v_guess`` (m,) must be finite numbers, ``n_grid`` a count >= 1 and ``last`` True or False;
    anything else is a ``ValueError`` naming it.
    """
    _check_pred(pred)
    z = _check_state(pred, z)
    v_guess = as_floats(v_guess, "v_guess")
    if v_guess.size != pred.m or (v_guess.ndim > 1 and np.squeeze(v_guess).ndim > 1):
        raise ValueError(f"v_guess must be one input of shape ({pred.m},), got shape {v_guess.shape}")
    v_guess = v_guess.reshape(pred.m)
    if not np.all(np.isfinite(v_guess)):
        raise ValueError(f"v_guess contains NaN or inf: {v_guess}")
    n_grid = check_count(n_grid, "n_grid", 1, "grid points of the one-input search")
    last = check_bool(last, "last", "whether the step is the plan's last (its next state in the terminal set)")
    return _feasible_tail(pred, z, v_guess, n_grid, last)


def _feasible_tail(pred: Prediction, z: Array, v_guess: Array, n_grid: int = FEASIBLE_TAIL_GRID,
                   last: bool = False) -> Array:
    """:func:`feasible_tail` without its checks (the callers here pass checked arrays)."""
    v_guess = np.asarray(v_guess, float).reshape(pred.m)
    z = np.asarray(z, float)
    if pred.m > 2 or _admissible(pred, z, v_guess[None], last)[0]:
        return v_guess
    if pred.m == 1:
        v = _nearest_exact_1d(pred, z, v_guess, last)
        if v is not None:
            return v
        # the grid (where no candidate of the exact set passes the forward pass, or the network has more outputs)
        # in order of distance from the guess (ties in grid order), the nearest _NEAR points first: the first
        # admissible point in that order is the nearest admissible one, as over the whole grid
        cand = np.linspace(pred.v_lo[0], pred.v_hi[0], n_grid)[:, None]
        keep = _in_step_rows(pred, z, cand[:, 0], last)  # only these can keep the next state in its box
        if not keep.any():
            return v_guess
        order = np.argsort(np.abs(cand[:, 0] - v_guess[0]), kind="stable")
        order = order[keep[order]]
        for part in (order[:_NEAR], order[_NEAR:]):
            ok = _admissible(pred, z, cand[part], last)
            if ok.any():
                return cand[part[int(np.argmax(ok))]].copy()
        return v_guess
    from ..pieces import _project, network_polygons, network_regions

    rows = _step_rows(pred, z, last)
    if rows is None:
        return v_guess
    regions = network_regions(pred.net, z, pred.v_lo, pred.v_hi, rows[0], rows[1])
    polys = network_polygons(pred.net, z, pred.v_lo, pred.v_hi, pred.u_eps, regions=regions)
    if not polys:
        return v_guess
    # the nearest point of each polygon, and the same pulled slightly inside (round-off at its edges)
    near = np.array([_project(P, v_guess) for P in polys])
    mid = np.array([P.mean(axis=0) for P in polys])
    cand = np.vstack([near, near + 1e-9 * (mid - near), near + 1e-6 * (mid - near), mid])
    i = np.flatnonzero(_admissible(pred, z, cand, last))
    if not i.size:
        return v_guess
    return cand[i[np.argmin(np.sum((cand[i] - v_guess) ** 2, axis=1))]].copy()


#: How far (a share of the distance to its midpoint) the exact method's candidates are pulled from an end of an
#: admissible interval towards its inside (round-off at the ends; :func:`_nearest_exact_1d`), the nearest first.
_PULLS = (0.0, 1e-12, 1e-9, 1e-6, 1e-3)


def _nearest_exact_1d(pred: Prediction, z: Array, v_guess: Array, last: bool) -> Optional[Array]:
    """One input: the admissible input nearest to ``v_guess`` over the exact set (eq. Phi_NN_ep at ``z``, piece by
    piece of ``Phi_NN(z, .)``, :func:`flnotes.network_pieces_1d`) cut by the step's rows (:func:`_step_interval`), or
    ``None`` when that set is empty or none of its candidates passes the forward pass (:func:`_admissible`).

    The set is the program's, ``|Phi_NN| <= u_max^eps``, not the check's ``u_max^eps +``
    :data:`flnotes.solvers.BOUND_TOL`: an input at the check's own bound would fail it once the plan's states are
    predicted again (:meth:`Prediction.feasible`), by their round-off; the check's tolerance stays that margin.

    The candidates of each piece's interval ``[a, b]``: the guess clipped to it, pulled towards its midpoint by
    :data:`_PULLS` of the distance to it, and the midpoint (intervals are not merged, so that a gap of round-off between two
    of them costs no candidate). The nearest that passes :func:`_admissible`, checked again alone (a batch's matrix
    product rounds otherwise than one row's), is returned. No admissible input is nearer than the clipped guesses, so
    the answer is the exact nearest to within the pull the forward pass needed.
    """
    from ..control import _pieces_1d, _pieces_within

    net = pred.net
    if net.n_out != 1 or net.n_in != pred.nz + 1:
        return None
    bound = float(pred.u_eps[0])  # the program's bound (see above)
    s_lo, s_hi = _step_interval(pred, z, last)
    lo, hi = max(float(pred.v_lo[0]), s_lo), min(float(pred.v_hi[0]), s_hi)
    if not (lo <= hi and bound >= 0.0):
        return None
    if lo == hi:  # the box or the terminal set leaves one input
        cand = np.array([lo])
    else:
        iv = _pieces_within(_pieces_1d(net, z, lo, hi), bound)  # exact_1d_feasible_set, piece by piece
        iv = iv[iv[:, 0] <= iv[:, 1]]
        if not len(iv):
            return None
        a, b = iv[:, 0], iv[:, 1]
        near = np.clip(float(v_guess[0]), a, b)
        inward = 0.5 * (a + b) - near  # towards the middle of its interval
        cand = np.concatenate([(near[:, None] + np.asarray(_PULLS)[None, :] * inward[:, None]).reshape(-1),
                               0.5 * (a + b)])
        cand = cand[np.argsort(np.abs(cand - v_guess[0]), kind="stable")]
    for i in np.flatnonzero(_admissible(pred, z, cand[:, None], last)):
        if _admissible(pred, z, cand[i:i + 1, None], last)[0]:
            return cand[i:i + 1].copy()
    return None


@dataclass(frozen=True, eq=False)
class RepairState:
    """How far a build of :func:`qp_repair` got at ``z`` with the cost's linear part ``f``.

    ``V[:k]`` are final (each moved to an admissible input at its predicted state), ``guess`` is the last QP's plan
    (the build goes on from its step ``k``) and ``resolve`` says whether the QP must be solved again first (the input
    before was moved). Published whole after each step and never changed in place, so another thread can read it
    while the build goes on: the MPC's fallback continues the engine's build that its cut-off stopped
    (``qp_repair(..., resume=state)``), which gives the plan the uninterrupted build gives. Its arrays are read-only
    copies, and ``pred`` is the prediction model it was built with (a build continues only with that model).
    """

    z: Array
    f: Array
    k: int
    V: Array
    guess: Array
    resolve: bool
    pred: Prediction = field(repr=False)


def _check_resume(pred: Prediction, z: Array, f, resume, V_qp=None) -> None:
    """A :class:`RepairState` that continues a build of :func:`qp_repair` with this model, ``z`` and ``f``, else an
    error that says what does not fit."""
    if not isinstance(resume, RepairState):
        raise TypeError(f"resume must be a RepairState (the state qp_repair publishes), got {type(resume).__name__}")
    if V_qp is not None:
        raise ValueError("give V_qp (a new build's start) or resume (a build to continue), not both")
    if f is None:
        raise ValueError("resume continues the build along the QP, which needs the cost's linear part f")
    if resume.pred is not pred:
        raise ValueError("resume is a build of another prediction model (another network, eps, weights or "
                         "horizon): continue it only with the model it was built with")
    shape = (pred.N, pred.m)
    arrays = all(type(a) is np.ndarray and a.dtype == np.float64 and a.shape == shape and np.all(np.isfinite(a))
                 for a in (resume.V, resume.guess))
    k = resume.k
    if not (arrays and isinstance(k, (int, np.integer)) and not isinstance(k, bool) and 0 <= k <= pred.N):
        raise ValueError(f"resume is not a build of this horizon: V and guess must be finite float arrays of shape "
                         f"{shape} and k an integer in [0, {pred.N}], got k = {k!r}, V {np.shape(resume.V)}, guess "
                         f"{np.shape(resume.guess)}")
    done = resume.V[:k]
    if np.any(done < pred.v_lo - FEAS_TOL) or np.any(done > pred.v_hi + FEAS_TOL):
        raise ValueError(f"resume is not a build of this model: its inputs v(0..k-1) leave the v box [{pred.v_lo}, "
                         f"{pred.v_hi}]")
    # a build solves the QP again exactly after a moved input (at k = 0: when it was given no start)
    if not isinstance(resume.resolve, (bool, np.bool_)) or (
            k > 0 and bool(resume.resolve) != (not np.array_equal(resume.V[k - 1], resume.guess[k - 1]))):
        raise ValueError(f"resume is not a build's state: resolve must be a bool, True exactly when its input "
                         f"v({k - 1}) was moved from the QP's, got {resume.resolve!r}")
    if not (np.array_equal(resume.z, z) and np.array_equal(resume.f, np.asarray(f, float))):
        raise ValueError("resume is a build for another state z or cost f: continue it only with the z and f it was "
                         "started with")


#: The QP solver's feasibility tolerance (DAQP's default primal tolerance): a QP's optimum given to :func:`qp_repair`
#: (``V_qp``) may leave the v box by this much (its round-off); the plan built from it is judged by
#: :meth:`Prediction.feasible` as every plan is.
QP_TOL = 1e-6

#: How the message of :func:`fallback_plan` starts when its plan is a build of :func:`qp_repair` that it continued
#: (``resume``) to the end: the plan the uninterrupted build gives.
_ALONG_QP = "the plan built along the QP without the network"
CONTINUED = f"{_ALONG_QP}, repaired step by step (the build continued from its step"


def _frozen(a: Array) -> Array:
    """A read-only view of a read-only copy of ``a`` (numpy refuses to make such a view writable again)."""
    a = np.array(a, float)
    a.setflags(write=False)
    return a.view()


def qp_repair(pred: Prediction, z: Array, f: Array, V_qp: Optional[Array] = None,
              deadline: Optional[float] = None, stop: Optional[threading.Event] = None,
              resume: Optional[RepairState] = None,
              publish: Optional[Callable[[RepairState], None]] = None) -> tuple[Array, Array]:
    """A plan built step by step along the QP without the network (eq. MPC_form_miqp without (MPC_form_miqp_b)).

    At step ``k`` the QP ``min J(V)`` over the boxes and terminal rows is solved with ``v(0..k-1)`` fixed
    (:meth:`Prediction.qp` with ``fixed``: over ``v(k..N_p-1)`` alone); its ``v(k)`` is made admissible at ``z(k)`` by
    :func:`feasible_tail`. The QP keeps the later steps' boxes in view, which a repair of a fixed guess does not.
    ``f`` is the cost's linear part (:meth:`Prediction.linear`); ``V_qp`` the QP's optimum without fixed steps when
    the caller has it. The QP is solved again only after a step whose ``v(k)`` was moved: fixing ``v(k)`` at the QP's
    own value leaves its (unique: ``H`` is positive definite) optimum where it is. The build stops at ``deadline`` (a
    :func:`time.perf_counter` value) or once ``stop`` is set (a controller answering at its cut-off); the later
    inputs are then the last QP's. Check the result with :meth:`Prediction.feasible`.

    ``publish`` is called with the build's :class:`RepairState` at its start and after each step; ``resume`` (such a
    state, for the same ``z`` and ``f``; not with ``V_qp``) continues that build where it stopped: the plan is then the
    one the build would have given without the stop, to the last bit.

    ``z`` must be one finite state, ``f`` ``N_p m`` finite numbers and ``V_qp`` finite inputs of shape ``(N_p, m)``
    (or flat) inside the v box to the QP solver's tolerance (:data:`QP_TOL`), else a ``ValueError`` that names it.
    """
    N, m = pred.N, pred.m
    _check_pred(pred)
    if f is None:
        raise ValueError("qp_repair builds along the QP, which needs the cost's linear part f (Prediction.linear)")
    f, z = pred._qp_arguments(f, _check_state(pred, z), None, None, None)[:2]
    if V_qp is not None:
        V_qp = _check_guess(pred, V_qp, "V_qp")
        if np.any(V_qp < pred.v_lo - QP_TOL) or np.any(V_qp > pred.v_hi + QP_TOL):
            raise ValueError(f"V_qp (the QP's optimum) must lie inside the v box [{pred.v_lo}, {pred.v_hi}] (to "
                             f"{QP_TOL:g}), got inputs from {V_qp.min(axis=0)} to {V_qp.max(axis=0)}")
    if resume is not None:
        _check_resume(pred, z, f, resume, V_qp)
        k0, V, guess, resolve = int(resume.k), resume.V.copy(), resume.guess.copy(), bool(resume.resolve)
        zk = z
        for j in range(k0):  # the same products as the build's own, so the same state to the last bit
            zk = pred.Ad @ zk + pred.Bd @ V[j]
    else:
        k0, V = 0, np.zeros((N, m))
        # without the QP's optimum, zero inputs (in the v box) until the first QP gives one
        guess = (np.clip(np.zeros((N, m)), pred.v_lo, pred.v_hi) if V_qp is None
                 else np.asarray(V_qp, float).reshape(N, m))
        resolve = V_qp is None
        zk = z
    if publish is not None:
        z_s, f_s = _frozen(z), _frozen(f)  # the states' own: a caller's array changed later does not change them
        publish(RepairState(z_s, f_s, k0, _frozen(V), _frozen(guess), resolve, pred))
    # the QP with v(0..k-1) held is solved over the later inputs alone (Prediction._qp_fixed); its rows and boxes
    # do not change along the build
    lo, hi = pred.state_bounds(z)
    v_lo, v_hi = np.tile(pred.v_lo, N), np.tile(pred.v_hi, N)
    for k in range(k0, N):
        if _past(deadline) or (stop is not None and stop.is_set()):
            V[k:] = guess[k:]
            break
        if resolve:
            if k:  # v(0..k-1) held where they are
                x = pred._qp_fixed(f, pred.A_state, lo, hi, v_lo[k * m:], v_hi[k * m:], V[:k].reshape(-1))[0]
            else:
                x = pred.qp(f, z)[0]
            if x is not None:
                guess = np.asarray(x, float).reshape(N, m)
        V[k] = _feasible_tail(pred, zk, guess[k], last=k == N - 1)
        resolve = not np.array_equal(V[k], guess[k])
        zk = pred.Ad @ zk + pred.Bd @ V[k]
        if publish is not None:
            publish(RepairState(z_s, f_s, k + 1, _frozen(V), _frozen(guess), resolve, pred))
    return pred.predict(z, V), V


def fallback_plan(pred: Prediction, z: Array, shifted: Optional[tuple[Array, Array]],
                  f: Optional[Array] = None, qp_repair_failed: bool = False,
                  deadline: Optional[float] = None, infeasible: bool = False,
                  resume: Optional[RepairState] = None) -> tuple[Array, Array, str, bool]:
    """The plan applied when a solve gives no plan (infeasible, time limit without one, solver failure).

    Safety first, in this order:

    1. the previous plan shifted by one step (``shifted``, from :meth:`flnotes.MPC.shifted_plan`), if it
       satisfies the whole program from the measured ``z``;
    2. a plan repaired step by step that satisfies the whole program: the shifted plan repaired
       (:func:`repair_plan`) and, when the cost's linear part ``f`` is given, the plan built along the QP
       without the network (:func:`qp_repair`), the cheaper of those that pass :meth:`Prediction.feasible`;
       then zero inputs repaired;
    3. otherwise only the first input is made safe: if any ``v`` with ``|Phi_NN(z, v)| <= u_max^eps``
       exists at ``z`` (:func:`safe_input`), the closest to the plan's is applied, the rest repaired while the
       deadline allows (``what`` says whether the plan then satisfies the program);
    4. when none exists, the least-violation input (``input_admissible=False``).

    ``qp_repair_failed``: the caller has already built the plan along the QP for this ``z`` and ``f`` and seen it
    fail the check (the MPC engine's first incumbent), so it is not built again. ``infeasible``: the caller has
    proven the program infeasible at ``z`` (e.g. its QP without the network has no point): no plan can pass the
    check, so the repairs of 2. are skipped and step 3. starts at once.

    ``resume``: the caller's own build of that plan, cut short (:class:`RepairState`: the MPC engine's at its cut-off,
    for this ``z`` and ``f``): it is continued first, before any other repair, instead of built again, so the plan is
    the one the uninterrupted build gives wherever the rest fits before ``deadline``.

    ``deadline`` (a :func:`time.perf_counter` value; ``None``: none) bounds the repairs of 2. and of the plan's rest in
    3.: none starts after it and each stops at it (a plan cut short is rejected by the check like any other). The
    shifted plan's check and step 3.'s first input (exact for one and two inputs) are made whatever the time: safety
    does not wait for the clock. ``what`` then says that the repairs were stopped.

    For the QP-based constraint models (``constraint`` other than ``"network"``) the same order applies
    with the network as the judge of admissibility: the fallback never claims more than it checks.
    Returns ``(z_pred, v_pred, what, admissible)``.
    """
    z = np.asarray(z, float)
    if resume is not None:  # refused whether or not it is used below
        _check_resume(pred, z, f, resume)
    if shifted is not None and pred.feasible(z, shifted[1]):
        return shifted[0], shifted[1], "the previous plan shifted by one step", True
    found = []
    if resume is not None and not infeasible and not qp_repair_failed and not _past(deadline):
        states: list = []  # how far the continued build gets (its last state)
        plan = qp_repair(pred, z, f, deadline=deadline, resume=resume, publish=states.append)
        reached = states[-1].k
        found.append((plan, f"{CONTINUED} {resume.k} of {pred.N}, where the solve's cut-off stopped it)"
                      if reached == pred.N else
                      f"{_ALONG_QP}, partly repaired (the build went on from its step {resume.k} to {reached} of "
                      f"{pred.N} and stopped at the step's deadline)"))
    # infeasible (proven by the caller): no plan satisfies the program, so no repair of 2. can pass the check
    if shifted is not None and not infeasible and not _past(deadline):
        found.append((repair_plan(pred, z, shifted[1], deadline=deadline),
                      "the shifted previous plan repaired step by step"))
    if f is not None and resume is None and not infeasible and not qp_repair_failed and not _past(deadline):
        found.append((qp_repair(pred, z, f, deadline=deadline), f"{_ALONG_QP}, repaired step by step"))
    found = [(plan, what) for plan, what in found if pred.feasible(z, plan[1])]
    if not found and not infeasible and not _past(deadline):
        plan = repair_plan(pred, z, np.zeros((pred.N, pred.m)), deadline=deadline)
        if pred.feasible(z, plan[1]):
            found.append((plan, "zero inputs repaired step by step"))
    if found:
        if f is not None:
            found.sort(key=lambda pw: pred.cost(pw[0][1], f, 0.0))
        (Zr, Vr), what = found[0]
        return Zr, Vr, what, True
    stopped = "; the repairs stopped at the step's deadline" if _past(deadline) else ""
    V = np.array(shifted[1] if shifted is not None else np.zeros((pred.N, pred.m)), float)
    V[0], ok = safe_input(pred, z, V[0])
    Zr, Vr = repair_plan(pred, z, V, first=False, deadline=deadline)
    if not stopped and _past(deadline):
        stopped = "; the repairs stopped at the step's deadline"
    if ok:
        rest = ("the rest of the plan repaired step by step (the plan satisfies the program)" if pred.feasible(z, Vr)
                else "the rest of the plan violates the program")
        return Zr, Vr, ("an admissible first input (|Phi_NN(z, v)| <= u_max^eps at the measured state); " + rest
                        + stopped), True
    return Zr, Vr, ("the least-violation input: no v satisfies |Phi_NN(z, v)| <= u_max^eps at the measured "
                    "state (input bound violated, flagged)" + stopped), False


def safe_input(pred: Prediction, z: Array, v_guess: Array) -> tuple[Array, bool]:
    """An input ``v`` with ``|Phi_NN(z, v)| <= u_max^eps`` closest to ``v_guess``, or the least-violation one.

    Exact for one input (:func:`flnotes.exact_1d_feasible_set`, inputs keeping ``A_d z + B_d v`` in the
    state box preferred) and for two (convex polygons over the network's linear regions,
    :func:`flnotes.pieces.network_polygons`); for more inputs, and for the least-violation input of two
    or more when nothing is admissible, a seeded sample of the ``v`` box (4096 points). Returns
    ``(v, admissible)``.
    """
    from ..control import exact_1d_feasible_set, network_pieces_1d

    z, v_guess = np.asarray(z, float), np.asarray(v_guess, float).reshape(pred.m)
    phi_ok = lambda v: bool(np.all(np.abs(pred.net(np.r_[z, v])) <= pred.u_eps + BOUND_TOL))  # noqa: E731
    if pred.m == 1:
        lo, hi = float(pred.v_lo[0]), float(pred.v_hi[0])
        iv = exact_1d_feasible_set(pred.net, z, lo, hi, float(pred.u_eps[0]))
        s_lo, s_hi = _step_interval(pred, z)  # the inputs that keep the next state in its box
        for keep_state in (True, False):
            cand = []
            for lo_i, hi_i in np.asarray(iv).reshape(-1, 2):
                if keep_state:
                    lo_i, hi_i = max(lo_i, s_lo), min(hi_i, s_hi)
                if lo_i <= hi_i:
                    cand += [np.clip(v_guess[0], lo_i, hi_i), 0.5 * (lo_i + hi_i)]
            for v in sorted(cand, key=lambda v: abs(v - v_guess[0])):
                if phi_ok([v]):
                    return np.array([v]), True
        pw = network_pieces_1d(pred.net, z, lo, hi)
        v0, y0, sl = pw.knots[:-1], pw.values[:-1], pw.slope
        with np.errstate(divide="ignore", invalid="ignore"):
            cross = np.where(sl != 0, v0 - y0 / sl, v0)
        cand = np.r_[pw.knots, np.clip(cross, pw.knots[:-1], pw.knots[1:])]
        v = float(cand[np.argmin(np.abs(pred.net(np.c_[np.repeat(z[None], cand.size, 0), cand])[:, 0]))])
        return np.array([v]), False
    if pred.m == 2:
        from ..pieces import _project, network_polygons, network_regions

        regions = network_regions(pred.net, z, pred.v_lo, pred.v_hi)
        polys = network_polygons(pred.net, z, pred.v_lo, pred.v_hi, pred.u_eps, regions=regions)
        cand = [_project(P, v_guess) for P in polys]
        cand = [v for v in sorted(cand, key=lambda v: float(np.sum((v - v_guess) ** 2))) if phi_ok(v)]
        if cand:
            return np.asarray(cand[0], float).copy(), True
    rng = np.random.default_rng(0)
    cand = np.vstack([v_guess, rng.uniform(pred.v_lo, pred.v_hi, (4096, pred.m))])
    excess = np.max(np.abs(pred.net(np.hstack([np.repeat(z[None], len(cand), 0), cand]))) - pred.u_eps, axis=1)
    ok = np.flatnonzero(excess <= BOUND_TOL)
    if ok.size:
        return cand[ok[np.argmin(np.abs(cand[ok] - v_guess).sum(axis=1))]].copy(), True
    return cand[int(np.argmin(excess))].copy(), False
