"""A bound on the true input between samples: the margin ``Delta(t_s)`` of ``u_max^{eps+Delta}`` (eq-09-margin).

The controllers impose ``|Phi_NN(z_k, v_k)| <= u_max^eps`` (eq. Phi_NN_ep) at the
sampling instants ``t_k``. With ``v_k`` held over ``[t_k, t_k + t_s]`` the plant is
exactly linearized and ``z`` follows the chain of integrators (eq. linearizedDyna)
exactly,

    z(t_k + vartheta) = A_d(vartheta) z_k + B_d(vartheta) v_k,   A_d(vartheta) = e^{A vartheta},
    B_d(vartheta) = int_0^vartheta e^{A s} ds B,   0 <= vartheta <= t_s,

while the true input ``u(t) = Phi(z(t), v_k)`` moves with ``z``. Let

    Delta_i(t_s) = max { |Phi_i(z(vartheta), v) - Phi_i(z, v)| : (z, v) in Z, vartheta in [0, t_s] }   (eq-09-delta),

with ``Z`` the domain box over ``(z, v)`` where ``eps`` is certified and ``z(vartheta)``
the flow above from ``z`` with ``v`` held. Then for every ``t`` in the interval

    |u(t)| = |Phi(z(t), v_k)| <= |Phi(z_k, v_k)| + Delta
           <= |Phi_NN(z_k, v_k)| + eps + Delta,

so ``|Phi_NN(z_k, v_k)| <= u_max^{eps+Delta} = u_max - eps - Delta`` at the samples
gives ``|u(t)| <= u_max`` at **every instant**. The exact condition:

* ``(z_k, v_k)`` lies in ``Z`` (the box where ``eps`` holds; eq. approx_err is only
  used at the sample, never at ``z(t)``), and
* ``Phi`` is defined along the flow, ``z(vartheta)`` for ``vartheta in [0, t_s]``. The
  intermediate states ``z(vartheta)`` may leave ``Z``: ``Delta`` is a property of
  ``Phi`` alone, and its certificate evaluates ``Phi`` on the reachable set (an
  interval enclosure of ``A_d(vartheta) z + B_d(vartheta) v`` over each sub-box), so no
  network and no ``eps`` is needed there. Where ``Phi`` is undefined on the
  reachable set (Quad-1D's ``|zeta| >= 1``) the certificate refuses
  (:class:`flnotes.interval.NotCertifiable`).

Only admissible samples matter: a sample with ``|Phi_NN(z_k, v_k)| <= u_max^{eps+Delta}``
in ``Z`` has ``|Phi(z_k, v_k)| <= u_max - Delta <= u_max``. So the maximum may be taken
over ``S = {(z, v) in Z : |Phi(z, v)| <= u_max}`` only (``admissible=True``, the
default), which is smaller than the whole box where the map is steep far from
the admissible set (Quad-1D: about 0.16 instead of 0.41 at ``t_s = 0.1``).

``Delta`` is certified like ``eps``: branch and bound with rigorous interval
enclosures (:mod:`flnotes.interval`) of ``f(z, v, vartheta) = Phi(z(vartheta), v) - Phi(z, v)``
over sub-boxes of ``Z x [0, t_s]``. With ``admissible=False`` this is
:func:`flnotes.certify_error` against the zero network (so that it bounds
``max |f|``); with ``admissible=True`` a branch and bound of the same kind
(natural and mean-value enclosures, best-first bisection) also discards every
sub-box on which the enclosure of ``Phi(z, v)`` lies outside ``[-u_max, u_max]``,
and takes lower values only at points proved admissible. The result is a bracket
``lower <= Delta <= upper``; use ``upper``. Since ``z(0) = z``, ``Delta(t_s)``
grows with ``t_s`` and vanishes as ``t_s -> 0`` (for a locally Lipschitz
``Phi``, about linearly): :func:`drift_curve` computes it on a list of ``t_s``.

The code names ``Delta`` ``delta`` (``DriftBound.delta``, the ``delta`` arguments and table columns); it is the
book's ``Delta(t_s)``, not the CLF slack ``delta`` of eq. (CLF_CBF).

Use: ``delta = intersample_drift(system, ts).upper`` and ``flnotes.MPC(system, net, eps + delta, ...)``
(the MPC's bound is then ``u_max^{eps+Delta}``, :func:`margin`, which refuses ``eps + Delta >= u_max``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np

from . import interval as iv
from ._checks import as_state, as_floats, as_vector, check_bool, check_int, check_number
from .error import ErrorBracket, certify_error
from .interval import Interval
from .network import ReLUNet
from .result import StepResult
from .systems import FLSystem

Array = np.ndarray

__all__ = ["flow", "flow_interval", "DriftBound", "intersample_drift", "drift_curve", "margin", "AdmissibleLaw"]


def _nilpotent_powers(A: Array, B: Array) -> tuple[list, list]:
    """``[A^0, ..., A^{r-1}]`` and ``[A^0 B, ...]`` with ``A^r = 0`` (chains of integrators are nilpotent)."""
    n = A.shape[0]
    Ak, As, ABs = np.eye(n), [], []
    for _ in range(n + 1):
        if not np.any(Ak):
            return As, ABs
        As.append(Ak), ABs.append(Ak @ B)
        Ak = Ak @ A
    raise ValueError("A must be nilpotent (a Brunovsky chain of integrators, A^n = 0): the exact flow "
                     "A_d(t) z + B_d(t) v is then a polynomial in the time t since the sample")


def flow(system: FLSystem, z: Array, v: Array, tau: Array) -> Array:
    """``z(vartheta) = A_d(vartheta) z + B_d(vartheta) v`` of eq. (linearizedDyna) with ``v`` held, vectorized.

    For a chain of integrators ``A`` is nilpotent and ``A_d(vartheta) = e^{A vartheta} = sum_k A^k vartheta^k / k!``,
    ``B_d(vartheta) = sum_k A^k B vartheta^{k+1} / (k+1)!`` (eq-09-delta). The argument ``tau`` is the time
    ``vartheta`` since the sample.

    Parameters
    ----------
    z, v, tau
        Shapes (N, n_z), (N, m) and (N,) (or (N, 1)).

    Returns
    -------
    Array of shape (N, n_z).
    """
    Z, V = np.atleast_2d(np.asarray(z, float)), np.atleast_2d(np.asarray(v, float))
    t = np.asarray(tau, float).reshape(-1, 1)
    if Z.shape[1] != system.n_z or V.shape[1] != system.m or not (len(Z) == len(V) == len(t)):
        raise ValueError(f"z, v, tau must be (N, {system.n_z}), (N, {system.m}), (N,), got {Z.shape}, {V.shape}, "
                         f"{np.shape(tau)}")
    As, ABs = _nilpotent_powers(system.A, system.B)
    out = np.zeros_like(Z)
    for k, (Ak, ABk) in enumerate(zip(As, ABs)):
        out += t**k / math.factorial(k) * (Z @ Ak.T) + t ** (k + 1) / math.factorial(k + 1) * (V @ ABk.T)
    return out


def flow_interval(system: FLSystem, z: Interval, v: Interval, tau: Interval) -> Interval:
    """Rigorous enclosure of :func:`flow` over boxes: ``z`` (T, n_z), ``v`` (T, m), ``tau`` (T, 1) Intervals.

    Written with :mod:`flnotes.interval` operations (gradients are carried
    along), the factorials as exact divisions.
    """
    As, ABs = _nilpotent_powers(system.A, system.B)
    out = None
    for k, (Ak, ABk) in enumerate(zip(As, ABs)):
        term = iv.power(tau, k) * iv.affine(Ak, None, z) / float(math.factorial(k)) \
            + iv.power(tau, k + 1) * iv.affine(ABk, None, v) / float(math.factorial(k + 1))
        out = term if out is None else out + term
    return out


@dataclass
class DriftBound:
    """A certified bracket ``lower <= Delta(t_s) <= upper`` per output (see the module docstring).

    Attributes
    ----------
    ts
        The hold time ``t_s``.
    lower, upper
        Shape (m,). ``upper`` is the margin to use in ``u_max^{eps+Delta}``.
    argmax
        Where ``lower`` is attained: rows ``(z, v, vartheta)``, shape (m, n_z + m + 1).
    z_lo, z_hi, v_lo, v_hi
        The box of samples ``(z_k, v_k)`` it holds for.
    bracket
        The :class:`flnotes.error.ErrorBracket` of the branch and bound.
    time_s
        Wall-clock time.
    admissible
        Whether the maximum is over the admissible samples ``|Phi(z, v)| <= u_max`` only.
    """

    ts: float
    lower: Array
    upper: Array
    argmax: Array
    z_lo: Array
    z_hi: Array
    v_lo: Array
    v_hi: Array
    bracket: ErrorBracket
    time_s: float
    admissible: bool = True

    @property
    def delta(self) -> Array:
        """The certified margin ``Delta(t_s)``: ``upper``."""
        return self.upper

    def __str__(self) -> str:
        return (f"Delta(t_s = {self.ts:g}) in [{np.array2string(self.lower, precision=5)}, "
                f"{np.array2string(self.upper, precision=5)}] ({self.time_s:.1f} s)")


def _zero_net(n_in: int, m: int) -> ReLUNet:
    """The network with all weights zero: ``certify_error(f, zero)`` brackets ``max |f|``."""
    return ReLUNet([np.zeros((1, n_in)), np.zeros((m, 1))], [np.zeros(1), np.zeros(m)])


def intersample_drift(system: FLSystem, ts: float, *, z_box: Optional[tuple] = None, v_box: Optional[tuple] = None,
                      admissible: bool = True, rtol: float = 0.02, atol: float = 0.0, n_samples: int = 200_000,
                      seed: int = 0, max_time: Optional[float] = 30.0, max_boxes: int = 20_000_000,
                      batch: int = 4096) -> DriftBound:
    """Certify ``Delta(t_s) = max |Phi(z(vartheta), v) - Phi(z, v)|`` over ``(z, v) in Z``, ``vartheta in [0, t_s]``.

    Branch and bound over the box ``Z x [0, t_s]`` of ``(z, v, vartheta)``, with
    ``f(z, v, vartheta) = Phi(z(vartheta), v) - Phi(z, v)`` written with
    :func:`flow_interval` and ``system.phi_interval`` (rigorous,
    outward-rounded): first :func:`flnotes.certify_error` against the zero
    network over the whole box; with ``admissible=True`` its upper end then caps
    a second branch and bound restricted to the admissible samples
    ``|Phi(z, v)| <= u_max``. See the module docstring for what the bound
    guarantees and under which condition.

    Parameters
    ----------
    system
        An :class:`FLSystem` with ``phi_interval`` and a nilpotent ``A``.
    ts
        Hold time ``t_s`` > 0.
    z_box, v_box
        ``(lo, hi)`` of the samples ``z_k`` and ``v_k``; default the domain box
        (use the MPC's ``v_box`` if it is smaller: ``Delta`` shrinks with it).
        They must lie in the domain box, where ``eps`` holds.
    admissible
        ``True`` (default): maximize over the admissible samples
        ``|Phi(z, v)| <= u_max`` only (module docstring); ``False``: over the whole box.
    rtol, atol
        Requested width of the bracket (``upper - lower <= max(atol, rtol lower)``).
    n_samples, seed
        Random samples for the first lower bound.
    max_time, max_boxes
        Budget per branch and bound; if exhausted the bracket is still sound,
        only wider (``bracket.converged`` is False).
    batch
        Boxes bisected per vectorized round (``admissible=True``).

    Returns
    -------
    DriftBound
    """
    if not isinstance(system, FLSystem):
        raise TypeError(f"system must be a flnotes.FLSystem, got {type(system).__name__}")
    if system.phi_interval is None:
        raise ValueError(f"{system.name} has no phi_interval: certifying the drift Delta needs Phi written with flnotes.interval")
    ts = check_number(ts, "ts", "a positive hold time in seconds", strict=True)
    admissible = check_bool(admissible, "admissible", "whether to bound Delta over the admissible set only")
    batch, n_samples = check_int(batch, "batch", 1, "boxes per round"), check_int(n_samples, "n_samples", 1, "samples")
    seed, max_boxes = check_int(seed, "seed", 0, "seed of the samples"), check_int(max_boxes, "max_boxes", 1, "budget")
    max_time = check_number(max_time, "max_time", "budget in seconds", strict=True, none=True)
    n, m = system.n_z, system.m
    _nilpotent_powers(system.A, system.B)
    zb = (system.lo[:n], system.hi[:n]) if z_box is None else z_box
    vb = (system.lo[n:], system.hi[n:]) if v_box is None else v_box
    z_lo, z_hi = as_vector(zb[0], n, "z_box[0]"), as_vector(zb[1], n, "z_box[1]")
    v_lo, v_hi = as_vector(vb[0], m, "v_box[0]"), as_vector(vb[1], m, "v_box[1]")
    lo, hi = np.r_[z_lo, v_lo], np.r_[z_hi, v_hi]
    if np.any(lo > hi):
        raise ValueError("z_box and v_box must have lo <= hi")
    if np.any(lo < system.lo - 1e-12) or np.any(hi > system.hi + 1e-12):
        raise ValueError(f"z_box, v_box must lie in the domain box lo = {system.lo}, hi = {system.hi} where eps holds "
                         f"(the bound |Phi(z_k, v_k)| <= |Phi_NN(z_k, v_k)| + eps is used at the samples)")

    def f(X: Array) -> Array:
        Z, V, tau = X[:, :n], X[:, n:n + m], X[:, n + m]
        return system.Phi(flow(system, Z, V, tau), V) - system.Phi(Z, V)

    def f_interval(X: Interval) -> Interval:
        Z, V, tau = X[:, :n], X[:, n:n + m], X[:, n + m:n + m + 1]
        return system.phi_interval(flow_interval(system, Z, V, tau), V) - system.phi_interval(Z, V)

    t0 = time.perf_counter()
    blo, bhi = np.r_[lo, 0.0], np.r_[hi, float(ts)]
    br = certify_error(f, _zero_net(n + m + 1, m), blo, bhi, f_interval=f_interval, rtol=rtol, atol=atol,
                       n_samples=n_samples, seed=seed, max_time=max_time, max_boxes=max_boxes)
    if admissible:  # the whole-box bracket's upper end also bounds the admissible maximum: a cap, and its point a seed
        if not (rtol >= 0 and atol >= 0 and rtol + atol > 0):
            raise ValueError(f"need rtol >= 0, atol >= 0 and at least one positive, got rtol={rtol}, atol={atol}")

        def phi_interval(X: Interval) -> Interval:
            return system.phi_interval(X[:, :n], X[:, n:n + m])

        br = _admissible_bnb(f, f_interval, phi_interval, blo, bhi, system.u_max, m, rtol, atol, n_samples, seed,
                             max_time, max_boxes, batch, seeds=br.argmax, cap=br.upper)
    return DriftBound(ts=float(ts), lower=br.lower, upper=br.upper, argmax=br.argmax, z_lo=z_lo, z_hi=z_hi,
                      v_lo=v_lo, v_hi=v_hi, bracket=br, time_s=time.perf_counter() - t0, admissible=bool(admissible))


def _admissible_bnb(f, f_interval, phi_interval, lo: Array, hi: Array, u_max: Array, m: int, rtol: float, atol: float,
                    n_samples: int, seed: int, max_time: Optional[float], max_boxes: int, batch: int,
                    seeds: Optional[Array] = None, cap: Optional[Array] = None) -> ErrorBracket:
    """``max |f_i|`` over ``{x in [lo, hi] : |Phi(x)| <= u_max}``, certified: a best-first branch and bound.

    Per box ``B``: discarded if the enclosure of ``Phi`` over ``B`` misses
    ``[-u_max, u_max]`` (no admissible point); else upper bound
    ``min(natural enclosure of |f_i|(B), |f_i(c)| + sum_j r_j max|df_i/dx_j(B)|)``
    (mean-value form about the centre ``c``, half-widths ``r``), all outward-rounded.
    Lower values: ``|f_i|`` at centres (and ``seeds``) proved admissible (point enclosures).
    ``cap`` (m,): a known upper bound (the whole box's); the search stops once
    the lower value is within tolerance of it, and ``upper`` never exceeds it.
    """
    n = len(lo)
    scale = np.where(hi > lo, hi - lo, 1.0)

    def admissible_points(P: Array) -> Array:
        E = phi_interval(Interval(P, P, check=False))
        return np.all((E.lo >= -u_max) & (E.hi <= u_max), axis=1)

    def lower_at(P: Array, i: int) -> Array:
        E = f_interval(Interval(P, P, check=False))
        return np.maximum(np.maximum(E.lo[:, i], -E.hi[:, i]), 0.0)

    rng = np.random.default_rng(seed)
    X0 = rng.uniform(lo, hi, (max(n_samples, 1), n))
    X0[rng.random(len(X0)) < 0.5, -1] = hi[-1]  # half the samples at the end of the hold
    if seeds is not None:
        X0 = np.vstack([np.clip(np.atleast_2d(seeds), lo, hi), X0])
    cap = np.full(m, np.inf) if cap is None else np.asarray(cap, float).reshape(m)
    ok0 = admissible_points(X0)
    lower, upper, argmax = np.zeros(m), np.zeros(m), np.zeros((m, n))
    n_boxes, conv, times, hists = np.zeros(m, int), np.zeros(m, bool), np.zeros(m), []
    for i in range(m):
        t0 = time.perf_counter()
        LB, best = 0.0, np.r_[0.5 * (lo + hi)[:-1], 0.0]
        if ok0.any():
            Xa = X0[ok0]
            E0 = np.abs(f(Xa)[:, i])
            top = Xa[np.argsort(E0)[::-1][:16]]
            low = lower_at(top, i)
            LB, best = float(low.max()), top[low.argmax()].copy()
        olo, ohi = lo[None].copy(), hi[None].copy()
        pruned, n_eval, hist, done, ub = -np.inf, 0, [], False, np.zeros(0)
        while True:
            # evaluate the open boxes
            P = phi_interval(Interval(olo, ohi, check=False))
            keep = np.all((P.lo <= u_max) & (P.hi >= -u_max), axis=1)
            olo, ohi = olo[keep], ohi[keep]
            n_eval += len(keep)
            if not len(olo):
                done = True
                break
            F = f_interval(Interval.variables(olo, ohi))
            mid = 0.5 * (olo + ohi)
            r = iv.up(np.maximum(ohi - mid, mid - olo))
            Fm = f_interval(Interval(mid, mid, check=False))
            dmag = np.maximum(np.abs(F.dlo[:, i, :]), np.abs(F.dhi[:, i, :]))
            S = iv.up((r * dmag).sum(1) * (1.0 + 2.0 * iv.gamma(n + 2)) + iv.TINY)
            mv = iv.up(np.maximum(Fm.hi[:, i], -Fm.lo[:, i]) + S)
            nat = np.maximum(F.hi[:, i], -F.lo[:, i])
            ub = np.minimum(mv, nat)
            adm = admissible_points(mid)
            if adm.any():
                low = np.where(adm, np.maximum(np.maximum(Fm.lo[:, i], -Fm.hi[:, i]), 0.0), -np.inf)
                j = int(low.argmax())
                if low[j] > LB:
                    LB, best = float(low[j]), mid[j].copy()
            thr = LB + max(atol, rtol * LB)
            fin = ub <= thr
            if fin.any():
                pruned = max(pruned, float(ub[fin].max()))
            olo, ohi, ub, r, dmag = olo[~fin], ohi[~fin], ub[~fin], r[~fin], dmag[~fin]
            hist.append((n_eval, LB, min(cap[i], max(pruned, float(ub.max()) if len(ub) else -np.inf))))
            if not len(olo) or cap[i] <= thr:
                done = True
                break
            if n_eval >= max_boxes or (max_time is not None and time.perf_counter() - t0 > max_time):
                break
            # bisect the `batch` open boxes with the largest upper bounds (others wait, bound kept)
            order = np.argsort(-ub)
            sel, rest = order[:batch], order[batch:]
            score = r[sel] * dmag[sel]
            score = np.where(score.max(1, keepdims=True) > 0, score, r[sel] / scale)
            ax = score.argmax(1)
            slo, shi = olo[sel], ohi[sel]
            rows = np.arange(len(sel))
            cut = 0.5 * (slo[rows, ax] + shi[rows, ax])
            clo, chi = np.vstack([slo, slo]), np.vstack([shi, shi])
            chi[rows, ax] = cut
            clo[len(sel) + rows, ax] = cut
            if len(rest):  # the boxes not bisected this round wait, and are evaluated again with the next round
                clo, chi = np.vstack([olo[rest], clo]), np.vstack([ohi[rest], chi])
            olo, ohi = clo, chi
        up_i = max(pruned, float(ub.max()) if len(ub) else -np.inf)
        lower[i], upper[i], argmax[i] = LB, max(min(up_i, cap[i]), LB), best
        n_boxes[i], conv[i], times[i] = n_eval, done, time.perf_counter() - t0
        hists.append(np.array(hist))
    return ErrorBracket(lower, upper, argmax, n_boxes, conv, times, rtol, atol, "interval, admissible samples",
                        None, hists)


def drift_curve(system: FLSystem, ts_values: Sequence[float], **kwargs) -> dict:
    """``Delta(t_s)`` for several hold times: how the margin shrinks with ``t_s``.

    Returns
    -------
    dict
        ``ts``, ``lower``, ``upper`` (arrays of shape (len(ts_values), m)),
        ``time_s`` (len(ts_values),) and ``bounds`` (the :class:`DriftBound` s).
        ``kwargs`` go to :func:`intersample_drift`.
    """
    ts_values = as_floats(ts_values, "ts_values").reshape(-1)
    if not len(ts_values) or np.any(~np.isfinite(ts_values)) or np.any(ts_values <= 0):
        raise ValueError(f"ts_values must be positive hold times, got {ts_values}")
    bounds = [intersample_drift(system, t, **kwargs) for t in ts_values]
    return dict(ts=ts_values, lower=np.array([b.lower for b in bounds]), upper=np.array([b.upper for b in bounds]),
                time_s=np.array([b.time_s for b in bounds]), bounds=bounds)


def margin(system: FLSystem, eps, delta) -> Array:
    """``u_max^{eps+Delta} = u_max - eps - Delta`` (eq-09-margin): the bound on ``|Phi_NN|`` at the samples that
    keeps ``|u(t)| <= u_max`` at every instant (module docstring).

    Parameters
    ----------
    eps
        Certified approximation error (``ErrorBracket.upper``), scalar or (m,).
    delta
        Certified drift ``Delta(t_s)`` (``DriftBound.upper``), scalar or (m,).

    Raises
    ------
    ValueError
        If ``eps + Delta >= u_max``: the margin leaves no admissible input. The
        condition is sufficient, not necessary (``Delta`` is a worst case over the
        box), so this says only that the margin cannot certify this hold time;
        shorten ``t_s`` or the v-box.
    """
    m = system.m
    eps, delta = as_vector(eps, m, "eps"), as_vector(delta, m, "delta")
    if np.any(eps < 0) or np.any(delta < 0):
        raise ValueError(f"eps and delta (the drift Delta) must be >= 0, got {eps} and {delta}")
    u = system.u_max - eps - delta
    if np.any(u <= 0):
        raise ValueError(f"eps + Delta = {eps + delta} >= u_max = {system.u_max}: the margin u_max - eps - Delta "
                         f"leaves no input, so it cannot certify |u(t)| <= u_max between samples at this hold time; "
                         f"shorten t_s (Delta shrinks with it) or the v-box")
    return u


class AdmissibleLaw:
    """``v_k`` nearest to ``k(z_k)`` among the ``v`` with ``|Phi_NN(z_k, v)| <= u_bound`` (a simple sampled law).

    ``Phi_NN(z, .)`` is evaluated on ``n_v`` points of the v-box; of the
    admissible ones the closest to ``k(z)`` is applied (admissibility is checked
    by the network's forward pass at that very point, so the sample constraint
    holds exactly). If no grid point is admissible, :class:`flnotes.SolverFailure`
    is raised (the simulation then flags a fallback).

    Parameters
    ----------
    system, net
        The plant and ``Phi_NN``.
    u_bound
        The bound at the samples, e.g. :func:`margin` ``(system, eps, delta)``, shape (m,) or scalar.
    k
        The nominal law ``z -> v`` (e.g. ``lambda z: K_f @ z`` with a terminal gain ``K_f``).
    n_v
        Grid points on the v-box (single-input systems only).
    """

    def __init__(self, system: FLSystem, net: ReLUNet, u_bound, k: Callable[[Array], Array], n_v: int = 4001):
        if system.m != 1:
            raise ValueError("AdmissibleLaw searches a grid of v: single-input systems only (m = 1)")
        if not callable(k):
            raise TypeError(f"k must be a function z -> v, got {type(k).__name__}")
        self.system, self.net, self.k = system, net, k
        self.u_bound = as_vector(u_bound, 1, "u_bound")
        if np.any(self.u_bound <= 0):
            raise ValueError(f"u_bound must be > 0, got {self.u_bound}")
        self.v_grid = np.linspace(system.lo[-1], system.hi[-1], int(n_v))

    def __call__(self, z: Array) -> Array:
        from .errors import SolverFailure

        z = as_state(z, self.system.n_z, "z")
        X = np.hstack([np.repeat(z[None], len(self.v_grid), 0), self.v_grid[:, None]])
        ok = np.abs(self.net(X)[:, 0]) <= self.u_bound[0]
        if not ok.any():
            raise SolverFailure(f"no v in the grid satisfies |Phi_NN(z, v)| <= {self.u_bound[0]:.4g} at z = {z}",
                                status="infeasible")
        v_nom = float(np.asarray(self.k(z), float).reshape(-1)[0])
        cand = self.v_grid[ok]
        return np.array([cand[np.argmin(np.abs(cand - v_nom))]])

    def step(self, z: Array, t: float, reference=None) -> StepResult:
        t0 = time.perf_counter()
        v = self(z)
        return StepResult(v=v, status="nominal", solve_time=time.perf_counter() - t0)
