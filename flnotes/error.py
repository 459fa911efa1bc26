"""The approximation error bound ``eps`` of eq. (approx_err): estimate it, then certify it.

Proposition 1 of the paper guarantees ``|Phi(z, v)| <= u_max`` from
``|Phi_NN(z, v)| <= u_max^eps = u_max - eps`` only if

    eps_i >= max_{(z, v) in Z} |Phi_i(z, v) - Phi_NN,i(z, v)|        (eq. epsilon_find)

holds over the whole domain ``Z``. Two kinds of tools live here:

* **estimates** (lower bounds on the maximum): the paper's particle swarm
  search :func:`pso_max_error`, and for comparison a dense grid
  (:func:`grid_max_error`), uniform random samples (:func:`sample_max_error`)
  and SciPy's differential evolution (:func:`de_max_error`). Each returns an
  :class:`ErrorEstimate`: a point where the error is large, hence a value the
  true maximum is *at least*;
* **a certificate** (an upper bound): :func:`certify_error` runs branch and
  bound over sub-boxes with rigorous, outward-rounded interval enclosures
  (:mod:`flnotes.interval`) and returns an :class:`ErrorBracket`
  ``lower <= max |Phi - Phi_NN| <= upper``. The book uses ``upper`` as ``eps``
  in ``u_max^eps = u_max - eps`` everywhere downstream.
"""
from __future__ import annotations

import hashlib
import itertools
import time
from dataclasses import dataclass, field
from functools import partial
from typing import Callable, Optional, Sequence, Union

import numpy as np

from . import interval as iv
from ._checks import as_batch, as_floats, check_bool, check_box, check_int, check_number
from .config import one_blas_thread
from .interval import Interval, NotCertifiable
from .network import ReLUNet, uniform_grid
from .parallel import load_checkpoint, save_checkpoint, task_key, task_seeds, using
from .systems import FLSystem

Array = np.ndarray

__all__ = ["ErrorEstimate", "ErrorBracket", "NotCertifiable", "pso_max_error", "pso_moves", "sample_max_error",
           "grid_max_error", "de_max_error", "certify_error", "error_function", "worst_violation", "local_max_error",
           "enclosure_widths", "chunk_sizes", "MIN_CHUNK"]


# ============================================================================ results
@dataclass
class ErrorEstimate:
    """A point estimate of ``eps_i = max |Phi_i - Phi_NN,i|`` (eq. epsilon_find): a lower bound.

    Attributes
    ----------
    method
        ``"pso"``, ``"grid"``, ``"sample"``, ``"de"`` or ``"local"``.
    eps
        Largest error found per output, shape (m,).
    argmax
        Where it was found, shape (m, n_in) (row i for output i).
    n_evals
        Number of evaluations of ``Phi`` and the network.
    time_s
        Wall-clock time.
    history
        Best error after each iteration, shape (m, n_iter) (PSO, DE), or ``None``.
    history_evals
        Evaluations of ``Phi`` and the network spent on output ``i`` when
        ``history[i, k]`` was recorded, same shape as ``history`` (PSO, DE), or
        ``None``: iterations of different methods cost different amounts, so
        convergence is compared against this count.
    settings
        The parameters used.
    swarm, swarm_best
        PSO with ``record=True``: particle positions per iteration for output
        0, shape (n_iter + 1, n_particles, n_in), and the swarm's best point
        per iteration, (n_iter + 1, n_in).
    """

    method: str
    eps: Array
    argmax: Array
    n_evals: int
    time_s: float
    history: Optional[Array] = None
    settings: dict = field(default_factory=dict)
    swarm: Optional[Array] = None
    swarm_best: Optional[Array] = None
    history_evals: Optional[Array] = None

    def __str__(self) -> str:
        return (f"{self.method}: max |Phi - Phi_NN| >= {np.array2string(self.eps, precision=4)} "
                f"({self.n_evals:,} evaluations)")


@dataclass
class ErrorBracket:
    """A certified bracket ``lower <= max_Z |Phi_i - Phi_NN,i| <= upper`` per output.

    Attributes
    ----------
    lower
        Rigorous lower bound, shape (m,): ``|Phi - Phi_NN|`` at ``argmax``
        (evaluated with interval arithmetic, so rounding cannot inflate it).
    upper
        Rigorous upper bound, shape (m,): use it as ``eps`` in
        ``u_max^eps = u_max - eps`` (eq. Phi_NN_ep).
    argmax
        Point attaining ``lower``, shape (m, n_in).
    n_boxes
        Sub-boxes evaluated per output, shape (m,).
    converged
        Whether ``upper - lower`` reached the requested width, shape (m,).
    time_s
        Wall-clock time per output, shape (m,) (for a resumed run, with the time of the runs it resumed up to
        their last saved state).
    rtol, atol
        Requested width: ``upper - lower <= max(atol, rtol * lower)``.
    method
        How ``Phi`` was enclosed (``"interval"`` or ``"lipschitz"``).
    partition
        Optional final partition per output: a dict of arrays ``lo``, ``hi``
        (n_leaves, n_in) and ``ub`` (the leaf's upper bound), kept with
        ``keep_partition=True`` for plots.
    history
        Per output, an array of rows ``(boxes evaluated, lower, upper)`` after
        each branch-and-bound round.
    eval_s
        Wall-clock time per output spent evaluating boxes (in this process or in the
        workers' tasks, as seen from the caller), shape (m,); ``time_s - eval_s`` is the
        serial part (bracket, pruning, choice of the next boxes).
    """

    lower: Array
    upper: Array
    argmax: Array
    n_boxes: Array
    converged: Array
    time_s: Array
    rtol: float
    atol: float
    method: str = "interval"
    partition: Optional[list] = None
    history: Optional[list] = None
    eval_s: Optional[Array] = None

    @property
    def eps(self) -> Array:
        """The certified error bound to use downstream: ``upper``."""
        return self.upper

    @property
    def width(self) -> Array:
        """``upper - lower``, shape (m,)."""
        return self.upper - self.lower

    def __str__(self) -> str:
        rows = [f"output {i}: {lo:.5f} <= max |Phi - Phi_NN| <= {up:.5f} (width {up - lo:.2g}, "
                f"{n:,} boxes{'' if c else ', NOT converged'})"
                for i, (lo, up, n, c) in enumerate(zip(self.lower, self.upper, self.n_boxes, self.converged))]
        return "certified bracket (" + self.method + "):\n  " + "\n  ".join(rows)


# ============================================================================ input handling
def _resolve(f, net: ReLUNet, lo, hi) -> tuple[Callable[[Array], Array], Array, Array]:
    """``f`` on stacked inputs with shape checks, and the checked box."""
    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    if isinstance(f, FLSystem):
        if (net.n_in, net.n_out) != (f.n_in, f.m):
            raise ValueError(f"net has {net.n_in} inputs and {net.n_out} outputs, but the box of {f.name} has "
                             f"{f.n_in} dimensions (z in R^{f.n_z}, v in R^{f.m}) and Phi has {f.m} outputs: pass the "
                             f"network trained on this system's stacked input (z, v)")
        lo = f.lo if lo is None else lo
        hi = f.hi if hi is None else hi
        raw = f.phi_stacked
        name = f"{f.name}.Phi"
    elif callable(f):
        raw, name = f, getattr(f, "__name__", "f")
    else:
        raise TypeError(f"f must be a callable (N, n_in) -> (N, m) or an FLSystem, got {type(f).__name__}")
    if lo is None or hi is None:
        raise ValueError("give the box lo, hi (shape (n_in,)) over which to bound the error")
    for b, bname in ((lo, "lo"), (hi, "hi")):
        if np.ndim(b) == 1 and np.shape(b)[0] != net.n_in:
            raise ValueError(f"net has {net.n_in} inputs, the box lo = {np.asarray(lo)}, hi = {np.asarray(hi)} has "
                             f"{np.shape(b)[0]} dimensions: {bname} must have shape ({net.n_in},), a box over the "
                             f"network's input")
    lo, hi = check_box(lo, hi, net.n_in, "lo", "hi")
    m = net.n_out

    def fun(X: Array) -> Array:
        Y = as_floats(raw(X), f"{name}(X)")
        if Y.ndim == 1 and m == 1 and Y.shape[0] == len(X):
            Y = Y[:, None]
        if Y.shape != (len(X), m):
            raise ValueError(f"{name} returned shape {Y.shape} for {len(X)} input points; expected ({len(X)}, {m}) "
                             f"(one row per point, one column per network output)")
        bad = ~np.isfinite(Y)
        if bad.any():  # a NaN would drop out of every max: an estimate of -inf, or a bound that misses it
            raise ValueError(f"Phi returned NaN or inf on the box ({name} at x = {X[bad.any(1)][0]}): bound the error "
                             f"on a box where Phi is defined")
        return Y

    return fun, lo, hi


def error_function(f, net: ReLUNet, lo=None, hi=None) -> Callable[[Array], Array]:
    """The cost of eq. (epsilon_find): ``X (N, n_in) -> |Phi(X) - Phi_NN(X)|`` of shape (N, m)."""
    fun, _, _ = _resolve(f, net, lo, hi)
    return lambda X: np.abs(fun(X) - net(X))


def _best(X: Array, E: Array) -> tuple[Array, Array]:
    k = E.argmax(0)
    return E[k, np.arange(E.shape[1])], X[k]


# ============================================================================ estimates
def pso_max_error(f, net: ReLUNet, lo: Optional[Array] = None, hi: Optional[Array] = None, n_particles: int = 100,
                  n_iter: int = 300, seed: int = 0, inertia: float = 0.7298, c_cognitive: float = 1.49618,
                  c_social: float = 1.49618, nu_max: float = 0.2, record: bool = False, restarts: int = 1,
                  workers: Optional[int] = None, client=None) -> ErrorEstimate:
    """Particle swarm search for ``max |Phi_i - Phi_NN,i|`` over a box (Sec. III-A.3, eq. epsilon_find).

    The paper's derivative-free estimator (Kennedy & Eberhart 1995): a swarm
    of candidate points moves through the box; each particle is pulled toward
    the best point it has seen itself and the best point any particle has
    seen, so the swarm explores first and then contracts around a large error.
    The result is a point where the error is large: a *lower* bound on the
    true maximum, not a guarantee (see :func:`certify_error`).

    Parameters
    ----------
    f
        ``Phi`` on stacked inputs, (N, n_in) -> (N, m), or an :class:`FLSystem`
        (then ``lo``, ``hi`` default to its domain box).
    net
        The network ``Phi_NN``.
    lo, hi
        The box ``Z``, shape (n_in,).
    n_particles, n_iter
        Swarm size and number of moves.
    seed
        Seed of the initial swarm and of the random pulls.
    inertia, c_cognitive, c_social
        ``c_nu, c_1, c_2`` of the velocity update of :func:`pso_moves` (eq. (5.4) of the book);
        the defaults are Clerc's constriction values, a standard stable choice.
    nu_max
        Largest velocity component per move, ``nu_max (hi - lo)``: a fraction of the box size.
    record
        Keep the particle positions of every iteration (for output 0), for
        :func:`flnotes.plots.pso_swarm`.
    restarts
        Independent swarms; the best per output is kept. ``1`` (default) runs one swarm
        seeded with ``seed``; ``R > 1`` runs ``R`` swarms seeded with
        :func:`flnotes.parallel.task_seeds` ``(seed, R)``, so the result does not depend on where
        they ran (ties go to the first restart).
    workers, client
        Where the restarts run (:class:`flnotes.parallel.Executor`): this process by default,
        ``workers=N`` local processes, or a Dask client / scheduler address.

    Returns
    -------
    ErrorEstimate
        ``eps`` (m,), ``argmax`` (m, n_in) and the best value per iteration in
        ``history`` (m, n_iter + 1) (of the winning restart, per output); ``n_evals`` and
        ``time_s`` count all restarts (``time_s`` is the wall time of the whole call).
    """
    fun, lo, hi = _resolve(f, net, lo, hi)
    n_particles = check_int(n_particles, "n_particles", 2, "particles of the swarm")
    n_iter = check_int(n_iter, "n_iter", 1, "iterations of the swarm")
    seed = None if seed is None else check_int(seed, "seed", 0, "seed of the swarm")
    restarts = check_int(restarts, "restarts", 1, "independent swarms")
    inertia = check_number(inertia, "inertia", "the weight of a particle's velocity", low=-np.inf)
    c_cognitive = check_number(c_cognitive, "c_cognitive", "the pull toward a particle's own best point")
    c_social = check_number(c_social, "c_social", "the pull toward the swarm's best point")
    nu_max = check_number(nu_max, "nu_max", "the largest step, a fraction of the box", strict=True)
    record = check_bool(record, "record", "whether to keep the particles' paths")
    if restarts > 1:
        t0 = time.perf_counter()
        opts = dict(n_particles=n_particles, n_iter=n_iter, inertia=inertia, c_cognitive=c_cognitive,
                    c_social=c_social, nu_max=nu_max, record=record)
        seeds = task_seeds(seed, restarts)
        with using(workers, client) as ex:
            runs = ex.map(partial(_pso_restart, f, net, lo, hi, opts), seeds)
        E = np.array([r.eps for r in runs])                             # (R, m)
        win = E.argmax(0)                                               # first best restart per output
        m_out = net.n_out
        best = ErrorEstimate("pso", E[win, np.arange(m_out)], np.array([runs[w].argmax[i] for i, w in enumerate(win)]),
                             int(sum(r.n_evals for r in runs)), time.perf_counter() - t0,
                             np.array([runs[w].history[i] for i, w in enumerate(win)]),
                             dict(runs[0].settings, seed=seed, restarts=int(restarts), restart_seeds=seeds,
                                  winner=win.tolist()),
                             runs[win[0]].swarm, runs[win[0]].swarm_best)
        return best
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    n, m = net.n_in, net.n_out
    eps, argmax, history = np.zeros(m), np.zeros((m, n)), np.zeros((m, n_iter + 1))
    swarm = swarm_best = None
    for i in range(m):  # one swarm per output: eq. (epsilon_find) is a separate maximization for each i

        def cost(X: Array, i: int = i) -> Array:
            return np.abs(fun(X)[:, i] - net(X)[:, i])

        trail = [] if (record and i == 0) else None
        argmax[i], eps[i], history[i] = pso_moves(cost, lo, hi, n_particles, n_iter, rng, inertia, c_cognitive,
                                                  c_social, nu_max, trail)
        if trail is not None:
            swarm, swarm_best = np.array([t[0] for t in trail]), np.array([t[1] for t in trail])
    return ErrorEstimate("pso", eps, argmax, m * n_particles * (n_iter + 1), time.perf_counter() - t0, history,
                         dict(n_particles=n_particles, n_iter=n_iter, seed=seed, inertia=inertia,
                              c_cognitive=c_cognitive, c_social=c_social, nu_max=nu_max),
                         swarm, swarm_best, history_evals=np.tile(n_particles * np.arange(1, n_iter + 2), (m, 1)))


def pso_moves(cost, lo: Array, hi: Array, n_particles: int, n_iter: int, rng: np.random.Generator,
              c_nu: float, c1: float, c2: float, nu_max: float, trail: Optional[list] = None):
    """The particle swarm of eq. (5.4): maximize ``cost`` over the box ``[lo, hi]``.

    ``c_nu`` is the inertia, ``c1, c2`` the attraction weights; each velocity
    component is clipped to ``nu_max`` times the box's width on its axis.

    Returns the best point, its cost and the best cost after each move (``n_iter + 1``,
    start included). ``trail``, if a list, receives ``(positions, best point)`` per move.
    """
    nu_bound = nu_max * (hi - lo)                                   # |nu| <= nu_max (hi - lo), per axis
    w = rng.uniform(lo, hi, (n_particles, len(lo)))                 # positions w_p
    nu = rng.uniform(-1.0, 1.0, w.shape) * nu_bound                 # velocities nu_p
    w_own, c_own = w.copy(), cost(w)                                # each particle's best point, hat w_p
    w_best, c_best = w_own[c_own.argmax()].copy(), c_own.max()      # the swarm's best point, hat w
    history = [c_best]
    if trail is not None:
        trail.append((w.copy(), w_best.copy()))
    for _ in range(n_iter):
        xi1, xi2 = rng.random((2, *w.shape))
        nu = np.clip(c_nu * nu + c1 * xi1 * (w_own - w) + c2 * xi2 * (w_best - w), -nu_bound, nu_bound)
        w = np.clip(w + nu, lo, hi)                                 # stay inside the box Z
        c = cost(w)
        better = c > c_own
        w_own[better], c_own[better] = w[better], c[better]
        if c_own.max() > c_best:
            w_best, c_best = w_own[c_own.argmax()].copy(), c_own.max()
        history.append(c_best)
        if trail is not None:
            trail.append((w.copy(), w_best.copy()))
    return w_best, c_best, np.array(history)


def _pso_restart(f, net: ReLUNet, lo: Array, hi: Array, opts: dict, seed: int) -> ErrorEstimate:
    """One restart of :func:`pso_max_error` (a task)."""
    return pso_max_error(f, net, lo, hi, seed=seed, **opts)


def sample_max_error(f, net: ReLUNet, lo: Optional[Array] = None, hi: Optional[Array] = None, n: int = 100_000,
                     seed: int = 0, chunk: int = 200_000) -> ErrorEstimate:
    """Largest error over ``n`` uniform random points of the box (a lower bound on eq. epsilon_find)."""
    fun, lo, hi = _resolve(f, net, lo, hi)
    n = check_int(n, "n", 1, "random points")
    seed = None if seed is None else check_int(seed, "seed", 0, "seed of the points")
    chunk = check_int(chunk, "chunk", 1, "points per batch")
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    eps, argmax = np.full(net.n_out, -np.inf), np.zeros((net.n_out, net.n_in))
    for start in range(0, n, chunk):
        X = rng.uniform(lo, hi, (min(chunk, n - start), net.n_in))
        e, a = _best(X, np.abs(fun(X) - net(X)))
        upd = e > eps
        eps[upd], argmax[upd] = e[upd], a[upd]
    return ErrorEstimate("sample", eps, argmax, n, time.perf_counter() - t0, settings=dict(n=n, seed=seed))


def grid_max_error(f, net: ReLUNet, lo: Optional[Array] = None, hi: Optional[Array] = None,
                   n_per_axis: Union[int, tuple] = 41, chunk: int = 200_000) -> ErrorEstimate:
    """Largest error on a uniform grid with ``n_per_axis`` points per axis (a lower bound on eq. epsilon_find)."""
    fun, lo, hi = _resolve(f, net, lo, hi)
    chunk = check_int(chunk, "chunk", 1, "points per batch")
    t0 = time.perf_counter()
    X = uniform_grid(lo, hi, n_per_axis)
    eps, argmax = np.full(net.n_out, -np.inf), np.zeros((net.n_out, net.n_in))
    for start in range(0, len(X), chunk):
        e, a = _best(X[start:start + chunk], np.abs(fun(X[start:start + chunk]) - net(X[start:start + chunk])))
        upd = e > eps
        eps[upd], argmax[upd] = e[upd], a[upd]
    return ErrorEstimate("grid", eps, argmax, len(X), time.perf_counter() - t0, settings=dict(n_per_axis=n_per_axis))


def de_max_error(f, net: ReLUNet, lo: Optional[Array] = None, hi: Optional[Array] = None, seed: int = 0,
                 maxiter: int = 300, popsize: int = 30, tol: float = 1e-10) -> ErrorEstimate:
    """SciPy's differential evolution on ``-|Phi_i - Phi_NN,i|`` (a cross-check of :func:`pso_max_error`).

    Vectorized population evaluation, no gradient polishing (the cost is not
    differentiable at the network's kinks).
    """
    from scipy.optimize import differential_evolution

    fun, lo, hi = _resolve(f, net, lo, hi)
    seed = None if seed is None else check_int(seed, "seed", 0, "seed of the population")
    maxiter = check_int(maxiter, "maxiter", 1, "generations")
    popsize = check_int(popsize, "popsize", 1, "population per input dimension")
    tol = check_number(tol, "tol", "the relative convergence tolerance")
    t0 = time.perf_counter()
    m = net.n_out
    eps, argmax, hist, hist_evals, count = np.zeros(m), np.zeros((m, net.n_in)), [], [], [0]
    for i in range(m):
        best, spent, start = [], [], count[0]

        def record(intermediate_result) -> None:
            best.append(-intermediate_result.fun)
            spent.append(count[0] - start)

        def neg(Xt: Array) -> Array:  # DE passes candidates as columns: (n_in, S)
            X = np.atleast_2d(Xt.T)
            count[0] += len(X)
            return -np.abs(fun(X)[:, i] - net(X)[:, i])

        res = differential_evolution(neg, list(zip(lo, hi)), seed=seed, maxiter=maxiter, popsize=popsize, tol=tol,
                                     polish=False, vectorized=True, updating="deferred",
                                     callback=record)
        eps[i], argmax[i] = -res.fun, res.x
        hist.append(best)
        hist_evals.append(spent)
    L = max(len(h) for h in hist)
    history = np.array([h + [h[-1]] * (L - len(h)) if h else [np.nan] * L for h in hist])
    history_evals = np.array([h + [h[-1]] * (L - len(h)) if h else [np.nan] * L for h in hist_evals])
    return ErrorEstimate("de", eps, argmax, count[0], time.perf_counter() - t0, history,
                         dict(seed=seed, maxiter=maxiter, popsize=popsize, tol=tol), history_evals=history_evals)


def local_max_error(f, net: ReLUNet, lo: Optional[Array] = None, hi: Optional[Array] = None, n_starts: int = 20,
                    seed: int = 0, output: int = 0) -> ErrorEstimate:
    """Gradient-based local ascent of ``|Phi_i - Phi_NN,i|`` (L-BFGS-B) from random starts.

    Shows why the paper avoids gradient methods for eq. (epsilon_find): the
    cost is not differentiable at the network's kinks and has many local
    maxima, so each start stops somewhere else. ``history`` holds the final
    value of every start (shape (1, n_starts), sorted, for ``output``).
    """
    from scipy.optimize import minimize

    fun, lo, hi = _resolve(f, net, lo, hi)
    n_starts = check_int(n_starts, "n_starts", 1, "random starts")
    seed = None if seed is None else check_int(seed, "seed", 0, "seed of the starts")
    output = check_int(output, "output", 0, f"the output of Phi, 0..{net.n_out - 1}")
    if output >= net.n_out:
        raise ValueError(f"output must be an output of Phi in 0..{net.n_out - 1}, got {output}")
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    n_evals, finals, points = 0, [], []

    def neg(x: Array) -> float:
        X = x[None, :]
        return -float(np.abs(fun(X)[0, output] - net(X)[0, output]))

    for x0 in rng.uniform(lo, hi, (n_starts, net.n_in)):
        res = minimize(neg, x0, method="L-BFGS-B", bounds=list(zip(lo, hi)))
        finals.append(-res.fun)
        points.append(res.x)
        n_evals += res.nfev
    k = int(np.argmax(finals))
    return ErrorEstimate("local", np.array([finals[k]]), np.array([points[k]]), n_evals, time.perf_counter() - t0,
                         np.sort(np.array(finals))[None, :], dict(n_starts=n_starts, seed=seed, output=output))


# ============================================================================ certification
def _interval_f(f, net: ReLUNet, f_interval, lipschitz, fun) -> tuple[Callable[[Interval], Interval], str]:
    """An enclosure of ``Phi`` on stacked Interval inputs (T, n_in) -> (T, m)."""
    n, m = net.n_in, net.n_out
    if f_interval is None and lipschitz is not None and isinstance(f, FLSystem) and f.phi_interval is not None:
        raise ValueError(f"lipschitz was given for the system {f.name!r}, which has phi_interval (used by default): "
                         f"drop lipschitz, or pass f={f.name}.phi_stacked with lo and hi to certify with the "
                         f"Lipschitz constants instead")
    if f_interval is None and isinstance(f, FLSystem) and f.phi_interval is not None:
        pz = f.phi_interval
        n_z = f.n_z

        def f_interval(X: Interval) -> Interval:  # noqa: F811
            return pz(X[:, :n_z], X[:, n_z:])
    if f_interval is not None:
        if lipschitz is not None:
            raise ValueError("give either f_interval or lipschitz, not both")

        def enc(X: Interval) -> Interval:
            try:
                Y = f_interval(X)
            except NotCertifiable:
                raise
            except (TypeError, AttributeError) as exc:
                raise NotCertifiable(
                    f"f_interval failed on Interval inputs ({type(exc).__name__}: {exc}); write it with the "
                    f"operations of flnotes.interval (+ - * / **, iv.sin, iv.cos, iv.tan, iv.arctan, iv.exp, iv.log, "
                    f"iv.sqrt, iv.tanh, iv.abs, iv.arcsin, ...), "
                    f"not numpy functions") from exc
            if not isinstance(Y, Interval):
                raise NotCertifiable(f"f_interval must return an flnotes.interval.Interval, got {type(Y).__name__}")
            if Y.shape != (len(X), m):
                raise ValueError(f"f_interval returned shape {Y.shape} for {len(X)} boxes; expected ({len(X)}, {m})")
            if X.has_grad and not Y.has_grad:
                raise NotCertifiable("f_interval dropped the gradient: build it only from flnotes.interval operations")
            return Y

        return enc, "interval"
    if lipschitz is None:
        name = f.name if isinstance(f, FLSystem) else getattr(f, "__name__", "f")
        raise NotCertifiable(
            f"cannot certify the error of {name!r}: a rigorous bound needs either f_interval (an interval version "
            f"of Phi written with flnotes.interval, e.g. FLSystem(phi_interval=...)) or lipschitz (constants L with "
            f"|Phi_i(x) - Phi_i(y)| <= sum_j L_ij |x_j - y_j| on the box). Sampling or PSO alone only give a lower bound.")
    L = as_floats(lipschitz, "lipschitz")
    if L.shape not in ((), (n,), (m, n)) or not np.all(np.isfinite(L)) or np.any(L < 0):
        raise ValueError(f"lipschitz must be a finite non-negative scalar, or of shape ({n},) (per input) or "
                         f"({m}, {n}) (per output and input); got shape {L.shape}")
    L = np.broadcast_to(L, (m, n)).copy()

    def enc_lip(X: Interval) -> Interval:
        # f(x) for x in the box lies in f(m) +- sum_j L_ij r_j; f(m) itself is trusted to FTOL relative accuracy
        mid = 0.5 * (X.lo + X.hi)
        y = fun(mid)
        tol = _FTOL * (1.0 + np.abs(y))
        r = iv.up(np.maximum(X.hi - mid, mid - X.lo))
        S = iv.up((r[:, None, :] * L[None]).sum(-1) * (1 + 2 * iv.gamma(n + 2)) + iv.TINY)
        lo_, hi_ = iv.down(y - tol - S), iv.up(y + tol + S)
        if X.has_grad:
            G = np.broadcast_to(L, (len(mid), m, n))
            return Interval(lo_, hi_, -G, G, check=False)
        return Interval(lo_, hi_, check=False)

    return enc_lip, "lipschitz"


#: Relative accuracy assumed for a plain floating-point evaluation of Phi (Lipschitz mode only).
_FTOL = 1e-12


class _Evaluator:
    """Bounds of ``|g_i|``, ``g = Phi - Phi_NN``, over batches of boxes."""

    def __init__(self, f_enc, net: ReLUNet, i: int, scale: Array):
        self.f_enc, self.net, self.i, self.scale = f_enc, net, i, scale

    def g(self, X: Interval) -> Interval:
        return self.f_enc(X) - iv.net_interval(self.net, X)

    def point_lower(self, P: Array) -> Array:
        """Rigorous lower bound of ``|g_i|`` at the points ``P`` (N, n)."""
        G = self.g(Interval(P, P, check=False))
        return np.maximum(np.maximum(G.lo[:, self.i], -G.hi[:, self.i]), 0.0)

    def boxes(self, lo: Array, hi: Array) -> tuple[Array, Array, Array, Array]:
        """For T boxes: upper bound of ``|g_i|``, best rigorous lower value, its point, and the split axis."""
        i, T, net = self.i, len(lo), self.net
        F = self.f_enc(Interval.variables(lo, hi))                  # Phi(B) and grad Phi(B)
        Xb = Interval(lo, hi, check=False)
        pre = iv.net_preactivations(net, Xb)                        # rigorous [L^k, U^k] on each box
        Nb = iv.affine(net.W[-1], net.b[-1], iv.relu(pre[-1]))      # natural enclosure of Phi_NN(B)
        mid = 0.5 * (lo + hi)
        r = iv.up(np.maximum(hi - mid, mid - lo))
        df = Interval(F.dlo[:, i, :], F.dhi[:, i, :], check=False)
        ups, guesses, spread = [], [], 0.0
        for s in (1.0, -1.0):
            # s Phi_NN,i(x) >= a.x + c on B, so  s g(x) <= h(x) - c  with  h(x) = s Phi_i(x) - a.x,
            # and by the mean-value theorem  h(x) <= h(m) + sum_j r_j max|s dPhi_i/dx_j(B) - a_j|
            a, c = iv.net_linear_bound(net, pre, Xb, i, s)
            dh = (df if s > 0 else -df) - a
            S = iv.up((r * dh.mag()).sum(1) * (1.0 + 2.0 * iv.gamma(lo.shape[1] + 2)) + iv.TINY)
            ups.append((a, c, S))
            guesses.append(np.clip(mid + r * np.sign(dh.lo + dh.hi), lo, hi))
            spread = spread + np.abs(a)
        P = np.vstack([mid] + guesses)
        GP = self.g(Interval(P, P, check=False))                    # g at the centre and two vertex guesses
        Fm = self.f_enc(Interval(mid, mid, check=False))
        ub = np.empty((2, T))
        for k, (s, (a, c, S)) in enumerate(zip((1.0, -1.0), ups)):
            hm = (Fm.hi[:, i] if s > 0 else -Fm.lo[:, i])
            _, am_lo = None, iv.dot_bounds(a, mid)[0]
            mv = iv.up(iv.up(iv.up(hm - am_lo) + S) - c)
            nat = iv.up(F.hi[:, i] - Nb.lo[:, i]) if s > 0 else iv.up(Nb.hi[:, i] - F.lo[:, i])
            ub[k] = np.minimum(mv, nat)
        ub = ub.max(0)
        low = np.maximum(np.maximum(GP.lo[:, i], -GP.hi[:, i]), 0.0).reshape(3, T)
        k = low.argmax(0)
        best = low[k, np.arange(T)]
        pts = P.reshape(3, T, -1)[k, np.arange(T)]
        # split where Phi's gradient is least known or, on boxes where the network is not affine, where it varies most
        affine = np.all([((p.lo >= 0) | (p.hi <= 0)).all(1) for p in pre], axis=0)
        score = r * ((df.hi - df.lo) + np.where(affine[:, None], 0.0, spread))
        score = np.where(score.max(1, keepdims=True) > 0, score, r / self.scale)
        return ub, best, pts, score.argmax(1)


#: Relative tolerance of the consistency checks of f_interval / lipschitz against Phi (rounding only).
_CHECK_RTOL = 1e-8

#: The default absolute width of a bracket, relative to ``max(1, max |Phi|)`` on the samples (:func:`certify_error`):
#: far below any useful ``eps``, far above what the outward rounding of the enclosures leaves.
ATOL_ROUNDING = 1e-9


def _check_enclosure(f_enc, fun, X0: Array, Y0: Array, whole: Interval, lo: Array, hi: Array, name: str,
                     seed: int, n_boxes: int = 64, per_box: int = 16) -> Interval:
    """Refuse an interval version of ``Phi`` that does not enclose ``Phi``.

    Checked where it is cheap: at the sample points ``X0`` (``Phi(x)`` in
    ``f_interval([x, x])``), on the whole box, and on ``n_boxes`` small random
    boxes of several sizes (``per_box`` samples each). A certificate computed
    with an interval function that misses ``Phi`` would bound the error of
    another function: ``ValueError`` naming the argument. Returns the enclosures on the small boxes.
    """

    def fail(x, y, ilo, ihi, where):
        raise ValueError(
            f"{name} does not enclose Phi: at x = {np.array2string(np.asarray(x), precision=4)}, Phi(x) = {y:.6g} "
            f"but {name} on {where} gives [{ilo:.6g}, {ihi:.6g}]. The interval version must compute the same "
            f"function as Phi with flnotes.interval operations (look for a typo or a missing term); "
            f"certify_error refuses to certify with it.")

    def check(P, Y, E, where):
        tol = _CHECK_RTOL * (1.0 + np.abs(Y))
        bad = (Y < E.lo - tol) | (Y > E.hi + tol)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            fail(P[r], Y[r, c], E.lo[r, c], E.hi[r, c], where(r))

    check(X0, Y0, f_enc(Interval(X0, X0, check=False)), lambda r: "the point [x, x]")
    W = Interval(np.broadcast_to(whole.lo, Y0.shape), np.broadcast_to(whole.hi, Y0.shape), check=False)
    check(X0, Y0, W, lambda r: "the whole box")
    rng = np.random.default_rng(seed + 1)
    n = len(lo)
    centre = rng.uniform(lo, hi, (n_boxes, n))
    half = (hi - lo) * 10.0 ** rng.uniform(-4.0, -0.5, (n_boxes, 1))
    blo, bhi = np.maximum(centre - half, lo), np.minimum(centre + half, hi)
    E = f_enc(Interval(blo, bhi, check=False))
    P = rng.uniform(np.repeat(blo, per_box, 0), np.repeat(bhi, per_box, 0))
    Y = fun(P)
    Eb = Interval(np.repeat(E.lo, per_box, 0), np.repeat(E.hi, per_box, 0), check=False)
    check(P, Y, Eb, lambda r: f"the box [{np.array2string(blo[r // per_box], precision=4)}, "
                              f"{np.array2string(bhi[r // per_box], precision=4)}]")
    return E


def _check_lipschitz(fun, X0: Array, Y0: Array, lipschitz, lo: Array, hi: Array, seed: int, n_pairs: int = 2000) -> None:
    """Refuse Lipschitz constants that pairs of nearby sample points contradict (``ValueError`` naming ``lipschitz``)."""
    m, n = Y0.shape[1], X0.shape[1]
    L = np.broadcast_to(np.asarray(lipschitz, float), (m, n))
    rng = np.random.default_rng(seed + 1)
    k = min(n_pairs, len(X0))
    step = (hi - lo) * 10.0 ** rng.uniform(-4.0, -1.0, (k, 1)) * rng.uniform(-1.0, 1.0, (k, n))
    X1 = np.clip(X0[:k] + step, lo, hi)
    dY = np.abs(fun(X1) - Y0[:k])
    bound = np.abs(X1 - X0[:k]) @ L.T
    bad = dY > bound * (1.0 + 1e-6) + _FTOL * (2.0 + np.abs(Y0[:k]))
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise ValueError(
            f"lipschitz is too small: between x = {np.array2string(X0[r], precision=4)} and "
            f"y = {np.array2string(X1[r], precision=4)}, |Phi_{c}(x) - Phi_{c}(y)| = {dY[r, c]:.6g} > "
            f"sum_j L_{c}j |x_j - y_j| = {bound[r, c]:.6g}; a certificate with it would not be sound.")


def certify_error(f, net: ReLUNet, lo: Optional[Array] = None, hi: Optional[Array] = None, *,
                  f_interval: Optional[Callable[[Interval], Interval]] = None,
                  lipschitz: Optional[Union[float, Array]] = None, rtol: float = 0.05, atol: Optional[float] = None,
                  seeds: Optional[Union[Array, ErrorEstimate]] = None, n_samples: int = 10_000, seed: int = 0,
                  batch: int = 4096, initial_per_axis: int = 4, max_boxes: int = 20_000_000,
                  max_time: Optional[float] = None, keep_partition: bool = False, chunk: int = 1024,
                  depth: int = 1, workers: Optional[int] = None, client=None, progress: bool = False,
                  resume: bool = False, checkpoint_s: Optional[float] = None) -> ErrorBracket:
    """A certified bracket ``lower <= max_Z |Phi_i - Phi_NN,i| <= upper`` (eq. epsilon_find), per output.

    Branch and bound over sub-boxes of ``Z = [lo, hi]``. For each box ``B`` an
    upper bound of ``|g_i|``, ``g = Phi - Phi_NN``, comes from two rigorous
    enclosures, whichever is tighter:

    * the natural interval extension ``Phi(B) - Phi_NN(B)``;
    * for each sign ``s = +-1``, a linear relaxation of the network,
      ``s Phi_NN,i(x) >= a_s . x + c_s`` on ``B``
      (:func:`flnotes.interval.net_linear_bound`; exact where all neurons
      are stable on ``B``, since the network is affine there), against the
      mean-value form of ``Phi``:
      ``max_B s g_i <= s Phi_i(m) - a_s . m - c_s + sum_j r_j max|s dPhi_i/dx_j(B) - a_s,j|``
      with ``m`` the centre and ``r`` the half-widths of ``B``; ``dPhi(B)``
      comes from forward-mode interval differentiation of ``f_interval``.

    The centre and two vertex guesses give rigorous lower values. Boxes whose
    upper bound cannot beat the best lower value by more than the tolerance
    are discarded; the others are bisected (best first, ``batch`` boxes per
    vectorized round) along the axis where the gradient is least known. All
    arithmetic is outward-rounded (:mod:`flnotes.interval`), so floating point
    cannot make ``upper`` too small.

    Parameters
    ----------
    f
        ``Phi`` on stacked inputs (N, n_in) -> (N, m), or an :class:`FLSystem`
        (then ``lo``, ``hi`` default to its box and ``f_interval`` to its
        ``phi_interval``).
    net
        The network ``Phi_NN``.
    lo, hi
        The box ``Z``, shape (n_in,).
    f_interval
        **What certification needs from Phi** (one of the two):
        an interval version of ``Phi``, a function of an
        :class:`flnotes.interval.Interval` ``X`` of shape (T, n_in) returning
        an Interval of shape (T, m), written with the operations of
        :mod:`flnotes.interval` (``+ - * /``, integer powers ``**``,
        ``iv.sin``, ``iv.cos``, ``iv.tan``, ``iv.arctan``, ``iv.exp``,
        ``iv.log``, ``iv.sqrt``, ``iv.tanh``, ``iv.abs``, ``iv.arcsin``,
        ``iv.sqr``, ``iv.hstack``, slicing ``X[:, j:j+1]``) so that it also
        carries gradients; for an :class:`FLSystem` it is
        ``phi_interval(z, v)``. It must be defined (no singularity) on the
        whole box, and it must enclose ``Phi``: before certifying, ``Phi`` at
        the sample points and on small random boxes is checked against it,
        and a mismatch (a typo) raises ``ValueError`` naming it.
    lipschitz
        ... or Lipschitz constants ``L`` with
        ``|Phi_i(x) - Phi_i(y)| <= sum_j L_ij |x_j - y_j|`` on the box (scalar,
        (n_in,) or (m, n_in)). Then ``Phi`` is only evaluated at points, and its
        floating-point value is trusted to a relative accuracy of 1e-12 (and
        constants that pairs of nearby samples contradict are refused). Much
        slower to converge than ``f_interval``: the enclosure is first order
        (it cannot see ``Phi`` and ``Phi_NN`` cancel), so sub-boxes must shrink
        to about ``tolerance / L``; practical in one or two dimensions or for
        coarse tolerances only.
    rtol, atol
        Stop when ``upper - lower <= max(atol, rtol * lower)``. The default ``atol=None`` is
        :data:`ATOL_ROUNDING` times ``max(1, max |Phi|)`` over the starting samples: the width below
        which the outward rounding of the enclosures, not the network, decides, so that a network equal
        to ``Phi`` (error 0, where ``rtol * lower`` is 0) gives a converged bracket instead of running to
        the budget; give ``atol=0`` for ``rtol`` alone (then a zero error is never converged).
    seeds
        Points (N, n_in) where the error is believed large, or an
        :class:`ErrorEstimate` (e.g. from :func:`pso_max_error`), used as first
        lower bounds.
    n_samples, seed
        Uniform random points evaluated first for a starting lower bound.
    batch
        Boxes bisected per vectorized round.
    initial_per_axis
        The box is first cut into this many slices per axis.
    max_boxes, max_time
        Budget per output; if exhausted the bracket is still sound but wider
        than requested (``converged`` is False).
    keep_partition
        Keep the final sub-boxes (for :func:`flnotes.plots.partition_slice`).
    chunk
        Most boxes per task: each round's boxes are evaluated in consecutive chunks of at most this
        many, one task each (:func:`chunk_sizes`: equal chunks, an even number of them, so that two
        workers get the same share). The chunks, their order and the merge (concatenation in chunk
        order, then the same selection as a single evaluation) do not depend on ``workers`` or
        ``client``: the bracket is bit-identical on 1 worker, N local workers or a Dask cluster.
    workers, client
        Where the chunks run (:class:`flnotes.parallel.Executor`): ``workers=1`` (default) in this
        process, ``workers=N`` in N local processes, ``client=`` a Dask client or scheduler address.
        Only the box evaluations are parallel; the bracket, the pruning and the choice of the next
        boxes stay in this process, and so does a round of fewer than ``2 MIN_CHUNK`` boxes (the first
        rounds). A round is cut into at most ``ceil(2 batch / chunk)`` chunks (rounded up to an even
        number), sent as one task per worker of consecutive chunks (an engine pays its round trip per
        task); more workers than chunks only help with a larger ``batch`` (a different schedule, the
        same soundness).
    depth
        Levels of bisection per chunk before a task returns (default 1: a task evaluates its chunk and
        the caller prunes and chooses the next boxes). With ``depth = d > 1`` a task then prunes its
        boxes against the larger of the round's lower bound and the best lower value found in the
        task (the same sound test as the caller's), and bisects its open boxes of largest upper bound,
        at most half its chunk per level, ``d - 1`` more times. Every dependent round then carries up to
        ``d`` times the work for one round trip of the engine: on a Dask cluster, whose round trip costs
        tens of milliseconds, ``depth=16`` is what makes 2 workers pay (``python -m flnotes.bench
        parallel``); in one process it changes the time little. The bracket is as sound for every
        ``depth`` and, for a given ``depth`` and ``chunk``, bit-identical on every engine; different
        ``depth`` (or, with ``depth > 1``, ``chunk``) values give different, equally valid brackets
        (another order of bisection), and the shipped brackets were certified with ``depth=1``.
        ``max_boxes`` and ``max_time`` are checked between rounds, so a run may evaluate up to
        ``2 batch depth`` boxes beyond ``max_boxes``.
    progress
        Show a :mod:`tqdm` bar of the boxes evaluated and the current bracket.
    resume, checkpoint_s
        With ``resume=True`` the run saves its state (open boxes, bounds, history) between rounds, at most every
        ``checkpoint_s`` seconds (default :data:`CHECKPOINT_S`) and when it ends, in the package's cache folder
        (``cache_dir()/tasks/certify``, one file per output), under a key made of everything its path depends on:
        the box, the network's weights, ``Phi``'s values at the starting samples, the enclosures its interval
        version gives on the whole box, on the 64 small random boxes of the enclosure check and on the first
        partition's boxes, and the options that shape the search (not ``max_boxes``, ``max_time``, ``workers`` or
        ``client``). A ``Phi`` changed only where none of these looks would not be noticed: after changing ``Phi``
        in place, delete that folder. With ``lipschitz`` only, ``Phi`` is seen at points alone, and ``resume=True``
        is refused (``ValueError``). The same
        certification run again with ``resume=True`` starts from the last saved state: after an interruption (a
        killed process, Ctrl-C) it does only the rounds that were not saved, and after a run stopped by
        ``max_boxes`` or ``max_time`` a larger budget goes on from where it stopped. The rounds are deterministic,
        so the bracket is bit-identical to an uninterrupted run's (tested). A damaged resume file (its contents
        are checked against their SHA-256), or one holding another run's state, is refused with an error naming
        it; delete it to start afresh.

    Returns
    -------
    ErrorBracket

    Raises
    ------
    NotCertifiable
        If neither ``f_interval`` nor ``lipschitz`` is available, or ``Phi``'s
        interval version is undefined somewhere on the box.
    ValueError
        For an empty box (``lo > hi``), a network whose input size is not the
        box's, a function returning the wrong shape, an ``f_interval`` (or
        ``phi_interval``) that does not enclose ``Phi``, or ``lipschitz``
        constants that samples of ``Phi`` contradict.
    """
    fun, lo, hi = _resolve(f, net, lo, hi)
    rtol = check_number(rtol, "rtol", "relative width of the bracket")
    atol = check_number(atol, "atol", "absolute width of the bracket", none=True)
    if atol is not None and rtol + atol <= 0:
        raise ValueError(f"rtol or atol must be positive (the bracket's requested width), got rtol={rtol}, atol={atol}")
    batch = check_int(batch, "batch", 1, "boxes bisected per round")
    initial_per_axis = check_int(initial_per_axis, "initial_per_axis", 1, "first slices per axis")
    n_samples = check_int(n_samples, "n_samples", 1, "random points for the first lower bound")
    seed = check_int(seed, "seed", 0, "seed of those points")
    max_boxes = check_int(max_boxes, "max_boxes", 1, "budget of boxes per output")
    max_time = check_number(max_time, "max_time", "budget in seconds per output", strict=True, none=True)
    chunk = check_int(chunk, "chunk", 1, "boxes per task")
    depth = check_int(depth, "depth", 1, "levels of bisection per task")
    keep_partition = check_bool(keep_partition, "keep_partition", "whether to keep the final sub-boxes")
    progress = check_bool(progress, "progress", "whether to show a progress bar")
    resume = check_bool(resume, "resume", "whether to save and resume the run's state")
    if checkpoint_s is not None and not resume:
        raise ValueError("checkpoint_s is how often a resumable run saves its state: it needs resume=True")
    checkpoint_s = check_number(CHECKPOINT_S if checkpoint_s is None else checkpoint_s, "checkpoint_s",
                                "seconds between two saves of the state")
    with using(workers, client) as executor:
        return _certify(f, net, fun, lo, hi, f_interval, lipschitz, rtol, atol, seeds, n_samples, seed, batch,
                        initial_per_axis, max_boxes, max_time, keep_partition, chunk, depth, executor, progress,
                        resume, checkpoint_s)


def _certify(f, net, fun, lo, hi, f_interval, lipschitz, rtol, atol, seeds, n_samples, seed, batch, initial_per_axis,
             max_boxes, max_time, keep_partition, chunk, depth, executor, progress, resume,
             checkpoint_s) -> ErrorBracket:
    """The body of :func:`certify_error` (arguments checked, executor open)."""
    f_enc, method = _interval_f(f, net, f_interval, lipschitz, fun)
    n, m = net.n_in, net.n_out
    whole = f_enc(Interval(lo[None], hi[None], check=False))  # fails early (NotCertifiable) if Phi is undefined somewhere
    if not (np.all(np.isfinite(whole.lo)) and np.all(np.isfinite(whole.hi))):
        raise NotCertifiable("the interval version of Phi is unbounded on the box")
    degenerate = hi <= lo
    # starting lower bounds: random samples plus the given seeds
    rng = np.random.default_rng(seed)
    X0 = rng.uniform(lo, hi, (max(n_samples, 1), n))
    if seeds is not None:
        S = seeds.argmax if isinstance(seeds, ErrorEstimate) else as_batch(seeds, n, "seeds")
        X0 = np.vstack([np.clip(S, lo, hi), X0])
    Y0 = fun(X0)
    if not np.all(np.isfinite(Y0)):
        raise ValueError("Phi returned NaN or inf on the box: certify on a box where it is defined")
    if method == "interval":
        name = "f_interval" if f_interval is not None else f"phi_interval of {f.name}"
        small = _check_enclosure(f_enc, fun, X0, Y0, whole, lo, hi, name, seed)
    else:
        _check_lipschitz(fun, X0, Y0, lipschitz, lo, hi, seed)
        if resume:
            raise ValueError("resume=True needs an interval version of Phi (f_interval, or an FLSystem's phi_interval): "
                             "with lipschitz only, Phi is seen at points, and a Phi changed between two runs could not "
                             "be told from the saved one; certify without resume, or give f_interval")
    if atol is None:  # the width that rounding alone leaves: a network equal to Phi converges at it
        atol = ATOL_ROUNDING * max(1.0, float(np.abs(Y0).max()))
    E0 = np.abs(Y0 - net(X0))
    # initial partition
    edges = [np.linspace(l, h, 1 if d else initial_per_axis + 1) for l, h, d in zip(lo, hi, degenerate)]
    cells = np.stack(np.meshgrid(*[np.arange(max(len(e) - 1, 1)) for e in edges], indexing="ij"), -1).reshape(-1, n)
    lo0 = np.stack([edges[j][np.minimum(cells[:, j], len(edges[j]) - 1)] for j in range(n)], 1)
    hi0 = np.stack([edges[j][np.minimum(cells[:, j] + 1, len(edges[j]) - 1)] for j in range(n)], 1)
    lo0[:, degenerate], hi0[:, degenerate] = lo[degenerate], hi[degenerate]

    lower, upper, argmax = np.zeros(m), np.zeros(m), np.zeros((m, n))
    n_boxes, conv, times, eval_s = np.zeros(m, int), np.zeros(m, bool), np.zeros(m), np.zeros(m)
    parts, hists = [], []
    key = None
    if resume:      # everything the path of the branch and bound depends on, Phi through its values and enclosures
        digest = [hashlib.sha1(np.ascontiguousarray(a, float).tobytes()).hexdigest()
                  for a in (X0, Y0, whole.lo, whole.hi, small.lo, small.hi, *net.W, *net.b)]
        key = task_key(_CHECKPOINT_FORMAT, digest, lo, hi, rtol, atol, batch, initial_per_axis, chunk, depth,
                       keep_partition, method, None if lipschitz is None else np.asarray(lipschitz, float))
    for i in range(m):
        ev = _Evaluator(f_enc, net, i, np.where(hi > lo, hi - lo, 1.0))
        top = np.argsort(E0[:, i])[::-1][:16]
        low0 = ev.point_lower(X0[top])
        k = low0.argmax()
        LB, best_x = low0[k], X0[top][k].copy()
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(desc=f"certify output {i}" if m > 1 else "certify", unit="box")
        try:
            rounds = _Rounds(ev, chunk, executor, depth, rtol, atol, keep_partition)
            cp = None if key is None else partial(_checkpoint_of, f"{key}-{i}", checkpoint_s)
            res = _branch_and_bound(ev, lo0, hi0, LB, best_x, rtol, atol, batch, max_boxes, max_time, keep_partition,
                                    rounds, bar, cp)
        finally:
            if bar is not None:
                bar.close()
        lower[i], upper[i], argmax[i], n_boxes[i], conv[i], part, hist, times[i], eval_s[i] = res
        parts.append(part)
        hists.append(hist)
    return ErrorBracket(lower, upper, argmax, n_boxes, conv, times, rtol, atol, method,
                        parts if keep_partition else None, hists, eval_s)


@dataclass
class _Leaves:
    """What a round (or one task of it) hands back: the open boxes, the best lower value and what was pruned."""

    lo: Array
    hi: Array
    ub: Array
    axis: Array
    best: float                     # largest rigorous lower value found (-inf if none)
    best_x: Optional[Array]         # its point
    n_eval: int                     # boxes evaluated
    pruned_max: float               # largest upper bound of the boxes pruned inside the task (-inf if none)
    pruned: Optional[tuple]         # (lo, hi, ub) of those boxes, with keep_partition


def _best_of(low: Array, pts: Array) -> tuple[float, Optional[Array]]:
    if not len(low):
        return -np.inf, None
    j = int(low.argmax())                           # the first of equal values: the same on every machine
    return float(low[j]), pts[j].copy()


def _bisect(lo: Array, hi: Array, axis: Array) -> tuple[Array, Array]:
    """Both halves of each box, cut at the middle of its ``axis``: the lower halves first, then the upper ones."""
    rows = np.arange(len(lo))
    cut = 0.5 * (lo[rows, axis] + hi[rows, axis])
    clo, chi = np.vstack([lo, lo]), np.vstack([hi, hi])
    chi[rows, axis] = cut
    clo[len(lo) + rows, axis] = cut
    return clo, chi


def _subtree(ev: _Evaluator, depth: int, LB: float, rtol: float, atol: float, keep: bool, lo: Array,
             hi: Array) -> _Leaves:
    """Evaluate the boxes ``lo, hi``, then ``depth - 1`` more levels of best-first bisection among them.

    Each further level prunes the boxes whose upper bound cannot beat ``max(LB, best lower value found
    here)`` by more than the tolerance (the same test as the caller's, against a lower bound at least
    as large: sound), then bisects at most ``ceil(len(lo) / 2)`` of the open boxes, those of largest upper
    bound (a stable sort: ties in index order), so that each level evaluates at most ``len(lo)`` boxes.
    The result depends on the boxes, ``LB`` and the options only, never on where it runs.
    """
    ub, low, pts, ax = ev.boxes(lo, hi)
    best, best_x = _best_of(low, pts)
    n_eval, pruned_max, kept = len(lo), -np.inf, []
    cap = max(1, -(-len(lo) // 2))
    for _ in range(depth - 1):
        L = max(LB, best)
        done = ub <= L + max(atol, rtol * L)
        if done.any():
            pruned_max = max(pruned_max, float(ub[done].max()))
            if keep:
                kept.append((lo[done], hi[done], ub[done]))
            lo, hi, ub, ax = lo[~done], hi[~done], ub[~done], ax[~done]
        if not len(ub):
            break
        order = np.argsort(-ub, kind="stable")
        sel, rest = order[:cap], np.sort(order[cap:])
        clo, chi = _bisect(lo[sel], hi[sel], ax[sel])
        cub, clow, cpts, cax = ev.boxes(clo, chi)
        n_eval += len(clo)
        b, bx = _best_of(clow, cpts)
        if b > best:
            best, best_x = b, bx
        lo, hi = np.vstack([lo[rest], clo]), np.vstack([hi[rest], chi])
        ub, ax = np.concatenate([ub[rest], cub]), np.concatenate([ax[rest], cax])
    pruned = tuple(np.concatenate([k[j] for k in kept]) for j in range(3)) if kept else None
    return _Leaves(lo, hi, ub, ax, best, best_x, n_eval, pruned_max, pruned)


def _boxes_task(ev: _Evaluator, opts: tuple, chunks: list[tuple[Array, Array]]) -> list[_Leaves]:
    """One task of a round: :func:`_subtree` on each of a few consecutive chunks of boxes, one call per chunk."""
    return [_subtree(ev, *opts, *box) for box in chunks]


def _merge(out: list[_Leaves]) -> _Leaves:
    """The leaves of a round's chunks in chunk order; the best lower value the first largest one."""
    if len(out) == 1:
        return out[0]
    cat = [np.concatenate([getattr(o, a) for o in out]) for a in ("lo", "hi", "ub", "axis")]
    k = int(np.argmax([o.best for o in out]))
    kept = [o.pruned for o in out if o.pruned is not None]
    pruned = tuple(np.concatenate([q[j] for q in kept]) for j in range(3)) if kept else None
    return _Leaves(*cat, out[k].best, out[k].best_x, sum(o.n_eval for o in out),
                   max(o.pruned_max for o in out), pruned)


#: Seconds between two saves of a resumable certification's state (``certify_error(resume=True)``).
CHECKPOINT_S = 30.0

#: Fewest boxes a round is cut into tasks for: a round of fewer than ``2 MIN_CHUNK`` boxes is evaluated whole, in the
#: caller's process (a task of fewer boxes would cost the engine's overhead more than it saves).
MIN_CHUNK = 128


def chunk_sizes(n: int, chunk: int) -> list[int]:
    """The sizes of the consecutive chunks, one task each, that a round of ``n`` boxes is cut into (:func:`certify_error`).

    ``k = ceil(n / chunk)`` chunks, rounded up to an even number, and at least two when ``n >= 2 min(MIN_CHUNK,
    chunk)`` (one whole chunk below), of equal sizes (the first ``n mod k`` one box larger): two workers get the same
    share of every round, also of the rounds that do not fill ``2 batch`` boxes (the first and the last ones).
    Depends on ``n`` and ``chunk`` only, never on the workers: so the chunks, hence the bracket, are the same
    wherever they run.
    """
    if n < 2 * min(MIN_CHUNK, chunk):
        return [n] if n else []
    k = max(2, -(-n // chunk))
    k += k % 2
    return [n // k + (1 if j < n % k else 0) for j in range(k)]


class _Rounds:
    """Evaluates a round's boxes in fixed chunks (:func:`chunk_sizes`) through an executor, merged in chunk order.

    Each chunk is one :func:`_subtree` of ``depth`` levels against the lower bound at the start of the round.
    """

    def __init__(self, ev: _Evaluator, chunk: int, executor, depth: int, rtol: float, atol: float, keep: bool):
        self.ev, self.chunk, self.executor = ev, chunk, executor
        self.depth, self.rtol, self.atol, self.keep = depth, rtol, atol, keep
        self.seconds = 0.0          # wall time spent evaluating boxes (in tasks, as seen from here)

    def __call__(self, lo: Array, hi: Array, LB: float) -> _Leaves:
        t0 = time.perf_counter()
        try:
            return self._evaluate(lo, hi, LB)
        finally:
            self.seconds += time.perf_counter() - t0

    def _evaluate(self, lo: Array, hi: Array, LB: float) -> _Leaves:
        ends = np.cumsum([0] + chunk_sizes(len(lo), self.chunk))
        parts = [(lo[a:b], hi[a:b]) for a, b in zip(ends[:-1], ends[1:])]
        opts = (self.depth, float(LB), self.rtol, self.atol, self.keep)
        if self.executor.engine == "serial" or len(parts) == 1:
            with one_blas_thread():                         # the same chunks, in this process, as on a worker
                return _merge(_boxes_task(self.ev, opts, parts))
        # one task per worker, each evaluating its consecutive chunks one by one (the chunks, hence the bits, as
        # in one process): an engine pays its round trip per task, and the chunks are of equal sizes
        w = min(len(parts), self.executor.workers)
        ends = [len(parts) * j // w for j in range(w + 1)]
        fn = partial(_boxes_task, self.ev, opts)
        return _merge([o for group in self.executor.map(fn, [parts[a:b] for a, b in zip(ends[:-1], ends[1:])])
                       for o in group])


class _Checkpoint:
    """The resume file of one output of a certification (:func:`flnotes.parallel.save_checkpoint`), written at most
    every ``every_s`` seconds between rounds and when the run ends."""

    def __init__(self, key: str, every_s: float):
        self.key, self.every_s, self.last = key, every_s, time.perf_counter()

    def load(self) -> Optional[dict]:
        return load_checkpoint(CHECKPOINTS, self.key, _STATE_FIELDS)

    def due(self) -> bool:
        return time.perf_counter() - self.last >= self.every_s

    def save(self, st: dict) -> None:
        save_checkpoint(CHECKPOINTS, self.key, st)
        self.last = time.perf_counter()


#: The cache folder of the certifications' resume files (``cache_dir()/tasks/certify``).
CHECKPOINTS = "certify"
_CHECKPOINT_FORMAT = "certify-checkpoint-2"
_STATE_FIELDS = ("LB", "best_x", "pruned_max", "n_eval", "hist", "kept", "elapsed", "eval_s", "olo", "ohi", "oub", "oax")


def _checkpoint_of(key: str, every_s: float, first: _Leaves) -> _Checkpoint:
    """The resume file of a certification whose other inputs give ``key`` and whose first partition's bounds are
    ``first`` (bounds of ``|Phi - Phi_NN|`` on every box of the first partition: an ``f_interval`` whose enclosure
    of one of those boxes differs changes them)."""
    digest = hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in (first.ub, first.axis, first.lo,
                                                                                first.hi))).hexdigest()
    return _Checkpoint(f"{key}-{digest[:12]}", every_s)


def _absorb(st: dict, leaves: _Leaves, rtol: float, atol: float, keep: bool) -> None:
    """Take a round's leaves into the state: the boxes evaluated, the lower bound, pruning, one row of history."""
    olo, ohi, oub, oax = leaves.lo, leaves.hi, leaves.ub, leaves.axis
    st["n_eval"] += leaves.n_eval
    st["pruned_max"] = max(st["pruned_max"], leaves.pruned_max)
    if keep and leaves.pruned is not None:
        st["kept"].append(leaves.pruned)
    if leaves.best > st["LB"]:
        st["LB"], st["best_x"] = leaves.best, leaves.best_x
    LB = st["LB"]
    done = oub <= LB + max(atol, rtol * LB)
    if done.any():
        st["pruned_max"] = max(st["pruned_max"], float(oub[done].max()))
        if keep:
            st["kept"].append((olo[done], ohi[done], oub[done]))
        olo, ohi, oub, oax = olo[~done], ohi[~done], oub[~done], oax[~done]
    st.update(olo=olo, ohi=ohi, oub=oub, oax=oax)
    st["hist"].append((st["n_eval"], LB, max(st["pruned_max"], float(oub.max()) if len(oub) else -np.inf)))


def _branch_and_bound(ev: _Evaluator, lo0: Array, hi0: Array, LB: float, best_x: Array, rtol: float, atol: float,
                      batch: int, max_boxes: int, max_time: Optional[float], keep: bool, evaluate: Callable,
                      bar=None, checkpoint: Optional[Callable[[_Leaves], _Checkpoint]] = None):
    t_start = time.perf_counter()
    first = evaluate(lo0, hi0, LB)        # the first partition's bounds: also part of a resume file's key
    checkpoint = checkpoint(first) if checkpoint is not None else None
    st = checkpoint.load() if checkpoint is not None else None
    if st is None:
        st = dict(LB=LB, best_x=best_x, pruned_max=-np.inf, n_eval=0, hist=[], kept=[], elapsed=0.0, eval_s=0.0)
        _absorb(st, first, rtol, atol, keep)
    prior_eval, t0 = st["eval_s"], t_start - st["elapsed"]

    def snapshot() -> dict:
        return {**st, "elapsed": time.perf_counter() - t0, "eval_s": prior_eval + evaluate.seconds}

    converged = False
    while True:
        olo, ohi, oub, oax = st["olo"], st["ohi"], st["oub"], st["oax"]
        if bar is not None:
            n_eval, low, up = st["hist"][-1]
            bar.update(int(n_eval) - bar.n)
            bar.set_postfix_str(f"{low:.6g} <= max error <= {up:.6g}, {len(oub):,} open", refresh=False)
        if not len(oub):
            converged = True
            break
        if st["n_eval"] >= max_boxes or (max_time is not None and time.perf_counter() - t0 > max_time):
            break
        if checkpoint is not None and checkpoint.due():
            checkpoint.save(snapshot())
        # bisect the `batch` open boxes with the largest upper bounds
        if len(oub) > batch:
            sel = np.argpartition(-oub, batch - 1)[:batch]
            rest = np.ones(len(oub), bool)
            rest[sel] = False
        else:
            sel, rest = np.arange(len(oub)), np.zeros(len(oub), bool)
        clo, chi = _bisect(olo[sel], ohi[sel], oax[sel])
        leaves = evaluate(clo, chi, st["LB"])
        _absorb(st, _Leaves(np.vstack([olo[rest], leaves.lo]), np.vstack([ohi[rest], leaves.hi]),
                            np.concatenate([oub[rest], leaves.ub]), np.concatenate([oax[rest], leaves.axis]),
                            leaves.best, leaves.best_x, leaves.n_eval, leaves.pruned_max, leaves.pruned),
                rtol, atol, keep)
    if checkpoint is not None:
        checkpoint.save(snapshot())
    oub = st["oub"]
    upper = max(st["pruned_max"], float(oub.max()) if len(oub) else -np.inf)
    part = None
    if keep:
        kept = st["kept"] + [(st["olo"], st["ohi"], oub)]
        part = dict(lo=np.vstack([k[0] for k in kept]), hi=np.vstack([k[1] for k in kept]),
                    ub=np.concatenate([k[2] for k in kept]))
    t_all, e_all = time.perf_counter() - t0, prior_eval + evaluate.seconds
    return st["LB"], upper, st["best_x"], st["n_eval"], converged, part, np.array(st["hist"]), t_all, e_all


# ============================================================================ what eps is for
def worst_violation(system: FLSystem, net: ReLUNet, eps: Union[float, Array], n_z: int = 3000, n_v: int = 2001,
                    at: Optional[Array] = None, seed: int = 0, chunk: int = 400_000) -> dict:
    """Search for a point that satisfies eq. (Phi_NN_ep) but violates the true input bound.

    Among points with ``|Phi_NN(z, v)| <= u_max - eps`` (the constraint the
    controllers impose), find the largest ``|Phi_i(z, v)| - u_max,i``. With a
    certified ``eps`` it is <= 0 by Proposition 1; with an under-estimated
    ``eps`` it can be positive: a feasible ``v`` that drives the real input
    beyond its bound.

    Parameters
    ----------
    system, net
        The system (its box and ``u_max``) and the network.
    eps
        The error bound to test, scalar or (m,).
    n_z, n_v
        ``n_z`` random states ``z`` of the box, each with ``n_v`` inputs ``v``
        (a uniform grid when m = 1, random otherwise): violations sit where
        ``Phi_NN`` reaches ``u_max - eps``, which a scan over ``v`` finds.
    at
        Optional extra points (N, n_in) whose ``z`` is scanned too; their ``z`` must lie in the domain box
        (``ValueError`` otherwise: eps is certified there only).
    seed, chunk
        Seed of the random states; evaluation chunk size.

    Returns
    -------
    dict
        ``violation`` (the largest ``|Phi| - u_max`` found among feasible
        points, per output), ``point`` (where), ``n_feasible``, ``n_points``.

    Raises
    ------
    ValueError
        When no sampled point satisfies ``|Phi_NN| <= u_max - eps`` (e.g.
        ``eps`` just below ``u_max``): nothing was checked, and no violation
        (not ``-inf``, a margin it never measured) is returned. Sample more
        states ``n_z`` or inputs ``n_v``, or test a smaller ``eps``.
    """
    eps = as_floats(eps, "eps")
    if eps.size not in (1, system.m) or eps.ndim > 1 or not np.all(np.isfinite(eps)) or np.any(eps < 0):
        raise ValueError(f"eps must be a finite error bound >= 0, a scalar or one per input (shape ({system.m},)), "
                         f"got {eps}")
    eps = np.broadcast_to(eps.reshape(-1), (system.m,))
    if np.any(eps >= system.u_max):
        raise ValueError(f"eps = {eps} must lie below u_max = {system.u_max}: with eps >= u_max no input is feasible "
                         f"(u_max - eps <= 0), and there is no point to search")
    n_z, n_v = check_int(n_z, "n_z", 1, "random states"), check_int(n_v, "n_v", 1, "inputs per state")
    seed = None if seed is None else check_int(seed, "seed", 0, "seed of the states")
    chunk = check_int(chunk, "chunk", 1, "points per batch")
    rng = np.random.default_rng(seed)
    n_z_dim = system.n_z
    Z = rng.uniform(system.lo[:n_z_dim], system.hi[:n_z_dim], (n_z, n_z_dim))
    if at is not None:
        At = as_batch(at, system.n_in, "at")
        system.check_domain(At[:, :n_z_dim], what="a state of at")  # eps holds inside the domain only
        Z = np.vstack([At[:, :n_z_dim], Z])
    vlo, vhi = system.lo[n_z_dim:], system.hi[n_z_dim:]
    V = (np.linspace(vlo, vhi, n_v) if system.m == 1 else rng.uniform(vlo, vhi, (n_v, system.m))).reshape(n_v, -1)
    best, point, n_feas = np.full(system.m, -np.inf), None, 0
    per = max(1, chunk // n_v)
    for k in range(0, len(Z), per):
        Zk = Z[k:k + per]
        X = np.hstack([np.repeat(Zk, n_v, 0), np.tile(V, (len(Zk), 1))])
        feasible = np.all(np.abs(net(X)) <= system.u_max - eps, axis=1)
        if not feasible.any():
            continue
        Xf = X[feasible]
        n_feas += len(Xf)
        viol = np.abs(system.phi_stacked(Xf)) - system.u_max
        j = viol.max(1).argmax()
        if viol[j].max() > best.max():
            point = Xf[j]
        best = np.maximum(best, viol.max(0))
    if n_feas == 0:
        raise ValueError(f"no sampled point satisfies |Phi_NN| <= u_max - eps = {system.u_max - eps} (of {len(Z) * n_v} "
                         f"points: {len(Z)} states, n_v = {n_v} inputs each), so nothing was checked: sample more states "
                         f"(n_z) or inputs (n_v), or test a smaller eps")
    return dict(violation=best, point=point, n_feasible=n_feas, n_points=len(Z) * n_v)


# ============================================================================ teaching helpers
def enclosure_widths(system: FLSystem, net: ReLUNet, x0: Array, radii: Sequence[float] = (1.0, 0.3, 0.1, 0.03, 0.01),
                     n_samples: int = 20_000, seed: int = 0) -> list[dict]:
    """How tight are the bounds of ``max |Phi - Phi_NN|`` on boxes ``x0 +- r``?

    For each radius: the largest error on the box estimated at ``n_samples``
    random points and the box's ``2^n`` vertices (a lower bound; near a vertex
    is where an almost affine error peaks, which random points approach only to
    first order in ``r``), the bound from the natural interval extension
    ``Phi(B) - Phi_NN(B)`` (it ignores that the two nearly cancel and
    overestimates by O(r)), and the bound :func:`certify_error` uses (mean-value
    form of ``Phi`` against a linear relaxation of ``Phi_NN``). The latter
    overestimates by O(r^2) where every neuron is stable on the box, but only by
    O(r), with a smaller constant, on boxes around a point where a neuron switches.
    """
    f_enc, _ = _interval_f(system, net, None, None, system.phi_stacked)
    ev = _Evaluator(f_enc, net, 0, system.hi - system.lo)
    x0 = np.asarray(x0, float)
    rng = np.random.default_rng(seed)
    rows = []
    for r in radii:
        lo, hi = np.maximum(x0 - r, system.lo)[None], np.minimum(x0 + r, system.hi)[None]
        X = Interval(lo, hi, check=False)
        G = f_enc(X) - iv.net_interval(net, X)
        ub = ev.boxes(lo, hi)[0][0]
        P = np.vstack([rng.uniform(lo[0], hi[0], (n_samples, system.n_in)),
                       np.array(list(itertools.product(*zip(lo[0], hi[0]))))])  # and the 2^n vertices
        rows.append({"radius r": r, "sampled max error": float(np.abs(system.phi_stacked(P) - net(P))[:, 0].max()),
                     "natural interval bound": float(max(G.hi[0, 0], -G.lo[0, 0])),
                     "certify_error's bound": float(ub)})
    return rows
