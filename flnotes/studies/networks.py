"""Studies of chapters 2, 4 and 5: the book's networks against fresh ones, exact node ranges, Table 1, sweeps.

These functions produce the chapters' tables; they train and certify many
networks, so their results for the book's settings ship as reference data
(:mod:`flnotes.reference`) where training would make them machine-dependent.
"""
from __future__ import annotations

import hashlib
import json
import os
from functools import partial
from typing import Optional, Sequence

import numpy as np

from .. import paper
from ..config import cache_dir
from ..error import certify_error, pso_max_error, sample_max_error
from ..network import fit_relu
from ..parallel import task_key, using
from ..reference import DATA_DIR, load_reference, load_table, save_table, weights_sha256
from ..systems import FLSystem

Array = np.ndarray

__all__ = ["table1_rows", "architecture_sweep", "book_sweep", "write_sweep", "fresh_vs_shipped",
           "width_experiment", "estimates_table", "exact_preactivation_range", "slope_in_v"]


def table1_rows(names: Sequence[str] = ("MSD", "Quad-1D")) -> list[dict]:
    """The paper's Table 1 next to the book's networks: K, n_bar, eps, n_s, certified eps.

    The paper's training times are left out: they compare MATLAB on the paper's machine with
    scikit-learn on this one, and depend on the machine.

    For each system one row with the paper's numbers (``source = "paper"``)
    and one with the book's: the network of :func:`flnotes.paper_net`, its
    PSO estimate and its certified bracket (:func:`flnotes.paper.paper_eps`).
    The column ``PSO vs bracket`` says whether the PSO estimate lies below the
    certified lower bound, i.e. is not a valid ``eps`` (``"below: invalid"``),
    or inside the bracket; for the paper's networks nothing is certified (``""``).
    """
    rows = []
    for name in names:
        t = paper.TABLE1[name]
        rows.append({"system": name, "source": "paper", "K": t["K"], "n_bar": t["n_bar"], "n_s": str(t["n_s"]),
                     "eps (PSO)": t["eps"], "eps certified": "", "PSO vs bracket": ""})
        net, rep = paper.paper_net(name)
        sysm = paper.system(name)
        pso = pso_max_error(sysm, net, **paper.EPS_SETTINGS["pso"])
        br = paper.paper_eps(name)
        n_s = "x".join(str(k) for k in rep.n_per_axis) if len(set(rep.n_per_axis)) > 1 else str(rep.n_per_axis[0])
        if rep.n_train < rep.n_grid:  # trained on a fixed random subset of the grid (chapter 2)
            n_s += f" ({rep.n_train // 1000}k subset)" if rep.n_train % 1000 == 0 else f" ({rep.n_train:,} subset)"
        rows.append({"system": name, "source": "flnotes", "K": net.K, "n_bar": net.widths[0], "n_s": n_s,
                     "eps (PSO)": round(float(pso.eps[0]), 5),
                     "eps certified": f"[{br.lower[0]:.5f}, {br.upper[0]:.5f}]",
                     "PSO vs bracket": "below: invalid" if pso.eps[0] < br.lower[0] else "inside"})
    return rows


def architecture_sweep(system: FLSystem, widths: Sequence[int] = (5, 10, 20), depths: Sequence[int] = (1, 2, 3),
                       n_per_axis: Sequence[int] = (10, 20, 30), max_iter: int = 300, max_train: Optional[int] = None,
                       seed: int = 0,
                       rtol: float = 0.05, max_time: float = 20.0, n_samples: int = 20_000,
                       cache: bool = True, progress: bool = False, recompute: bool = False,
                       ship_to: Optional[str] = None, workers: Optional[int] = None, client=None,
                       resume: bool = False) -> list[dict]:
    """Train small networks over a grid of widths, depths and grid densities; estimate and certify each eps.

    One row per network with ``width``, ``depth``, ``n_s``, ``n_binaries``
    (``width * depth``, the binaries of one copy of eq. (MIP_general)),
    ``eps_sample`` (max over ``n_samples`` random points), ``eps_pso``,
    ``eps_certified`` (upper end of :func:`certify_error` with ``rtol``),
    ``eps_lower``, ``train_time_s`` and ``certify_time_s``. ``max_train``
    caps the training points per network (a random subset of the grid, as in
    :func:`flnotes.fit_relu`; ``None``: the whole grid).

    Training many networks takes minutes and its result depends on the
    machine (see :mod:`flnotes.reference`), so the table chapter 5 draws is
    shipped with the package and returned as it is when the arguments match
    it exactly; ``recompute=True`` trains everything anew on this machine.
    Other arguments are computed and cached on disk (keyed by all arguments,
    ``cache=False`` skips the disk). ``ship_to`` (a folder) writes the
    computed table there as the shipped one (see
    :func:`flnotes.paper.write_sweep`).

    Each network (train, estimate, certify) is one task of :class:`flnotes.parallel.Executor`:
    in this process by default, on ``workers`` local processes or on a Dask ``client``; the rows
    come back in the order of the grid (grid density, then depth, then width) whatever runs them,
    and each task trains with one BLAS thread, so the table is the same (except the two time
    columns, and ``max_time`` when a certification runs out of it). ``progress`` shows a bar;
    ``resume`` keeps each finished network's row in the cache folder for a rerun.
    """
    args = dict(system=system.name, lo=system.lo.tolist(), hi=system.hi.tolist(), widths=list(widths),
                depths=list(depths), n_per_axis=list(n_per_axis), max_iter=max_iter, max_train=max_train, seed=seed, rtol=rtol,
                max_time=max_time, n_samples=n_samples, version=1)
    shipped = None if recompute else load_table(f"sweep-{system.name}", args)
    if shipped is not None:
        return shipped
    path = cache_dir() / f"sweep-{system.name}-{hashlib.sha1(json.dumps(args, sort_keys=True).encode()).hexdigest()[:12]}.json"
    if cache and not recompute and path.exists():
        return json.loads(path.read_text())
    tasks = [(n_s, depth, width) for n_s in n_per_axis for depth in depths for width in widths]
    opts = dict(max_train=max_train, max_iter=max_iter, seed=seed, rtol=rtol, max_time=max_time, n_samples=n_samples)
    keys = [task_key("sweep", args, t) for t in tasks] if resume else None
    with using(workers, client) as ex:
        rows = ex.map(partial(_sweep_network, system, opts), tasks, keys=keys, cache="sweep" if resume else None,
                      desc=f"sweep {system.name}", progress=progress)
    if cache:
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp")  # one per process: parallel runs never share it
        tmp.write_text(json.dumps(rows))
        tmp.replace(path)
    if ship_to is not None:
        save_table(f"sweep-{system.name}", args, rows, folder=ship_to)
    return rows


def _sweep_network(system: FLSystem, opts: dict, task: tuple) -> dict:
    """One task of :func:`architecture_sweep`: train, estimate and certify one network, its row."""
    n_s, depth, width = task
    seed = opts["seed"]
    net, rep = fit_relu(system.phi_stacked, system.lo, system.hi, widths=(width,) * depth,
                        n_per_axis=n_s, max_train=opts["max_train"], max_iter=opts["max_iter"], seed=seed)
    smp = sample_max_error(system, net, n=opts["n_samples"], seed=seed)
    pso = pso_max_error(system, net, n_particles=50, n_iter=100, seed=seed)
    br = certify_error(system, net, rtol=opts["rtol"], seeds=pso, n_samples=1000, max_time=opts["max_time"])
    return dict(width=width, depth=depth, n_s=n_s, n_binaries=width * depth,
                eps_sample=float(smp.eps[0]), eps_pso=float(pso.eps[0]),
                eps_lower=float(br.lower[0]), eps_certified=float(br.upper[0]),
                converged=bool(br.converged[0]), train_time_s=rep.time_s,
                certify_time_s=float(br.time_s[0]))


def estimates_table(estimates: dict, brackets: Optional[dict] = None) -> list[dict]:
    """Rows comparing estimates of eq. (epsilon_find): system, method, eps found, evaluations.

    ``estimates`` maps a system name to a list of :class:`ErrorEstimate`;
    ``brackets`` optionally maps it to an :class:`ErrorBracket`, added as a
    last row and used to report each estimate relative to the certified lower bound.
    """
    names = {"pso": "particle swarm", "de": "differential evolution", "grid": "dense grid",
             "sample": "random samples", "local": "L-BFGS-B, best of several starts"}
    rows = []
    for system, ests in estimates.items():
        br = None if brackets is None else brackets.get(system)
        for e in ests:
            row = {"system": system, "method": names.get(e.method, e.method), "eps found": round(float(e.eps[0]), 5),
                   "evaluations": f"{e.n_evals:,}"}
            if br is not None:
                row["found / certified lower"] = round(float(e.eps[0] / br.lower[0]), 3)
            rows.append(row)
        if br is not None:
            rows.append({"system": system, "method": "certified bracket",
                         "eps found": f"[{br.lower[0]:.5f}, {br.upper[0]:.5f}]",
                         "evaluations": f"{int(br.n_boxes[0]):,} boxes",
                         "found / certified lower": 1.0})
    return rows


def book_sweep(name: str = "MSD", recompute: bool = False) -> list[dict]:
    """Chapter 5's sweep over widths, depths and grid densities with :data:`SWEEP_SETTINGS` (shipped table).

    ``recompute=True`` retrains its networks on this machine (minutes).
    """
    return architecture_sweep(paper.system(name), **paper.SWEEP_SETTINGS, recompute=recompute)


def write_sweep(name: str = "MSD", folder=None, workers: Optional[int] = None, client=None,
                progress: bool = False, resume: bool = False) -> None:
    """Recompute chapter 5's sweep on this machine and write it as the shipped table (``make reference``).

    ``workers``, ``client``, ``progress``, ``resume``: see :func:`architecture_sweep`.
    """
    architecture_sweep(paper.system(name), **paper.SWEEP_SETTINGS, cache=False, recompute=True,
                       ship_to=DATA_DIR if folder is None else folder, workers=workers, client=client,
                       progress=progress, resume=resume)


def fresh_vs_shipped(names: Sequence[str] = ("MSD", "Quad-1D"), **overrides) -> list[dict]:
    """Train the book's networks anew on this machine and compare them with the shipped ones (the benchmark report).

    For each system one row for the shipped reference and one for a network
    trained now with the same settings (``overrides`` change them, e.g. fewer
    iterations), each with its grid error, certified bracket of ``eps``
    (eq. approx_err, :data:`EPS_SETTINGS`), training time and weights
    checksum, and whether the two networks are identical.
    """
    rows = []
    for name in names:
        ref = load_reference(paper.shipped_name(name, paper.NET_SETTINGS[name]))
        sysm = paper.system(name)
        settings = {**paper.NET_SETTINGS[name], **overrides}
        net, rep = fit_relu(sysm.phi_stacked, sysm.lo, sysm.hi, **settings)
        br = paper.certify_book_eps(name, net)
        same = (net.widths == ref.net.widths and all(np.array_equal(a, b) for a, b in zip(net.W + net.b, ref.net.W + ref.net.b)))
        for source, n, r, lower, upper in (("shipped", ref.net, ref.report, ref.bracket["lower"][0], ref.bracket["upper"][0]),
                                           ("trained now", net, rep, br.lower[0], br.upper[0])):
            rows.append({"system": name, "network": source, "widths": str(n.widths), "L-BFGS iterations": r.n_iter,
                         "train time [s]": round(r.time_s, 1), "grid max error": float(r.grid_max_error[0]),
                         "eps certified": f"[{lower:.5f}, {upper:.5f}]", "eps": float(upper),
                         "weights sha256": weights_sha256(n)[:12],
                         "identical to shipped": bool(same) if source == "trained now" else None})
    return rows


def width_experiment(system: FLSystem, n_bars: Sequence[int] = (5, 10, 20, 30), depth: int = 3,
                     n_per_axis: int = 15, max_iter: int = 1000, n_test: int = 100_000,
                     seed: int = 0) -> list[dict]:
    """Train ``depth`` hidden layers of ``n_bar`` neurons each on a coarse grid, for several widths.

    Parameters
    ----------
    system
        The system whose ``Phi`` is fitted on its domain box.
    n_bars
        Hidden widths ``n_bar`` to try (the paper's K - 1 = ``depth`` layers each).
    depth
        Number of hidden layers.
    n_per_axis, max_iter, seed
        Passed to :func:`flnotes.fit_relu`.
    n_test
        Random test points for the off-grid error (:func:`flnotes.error.sample_max_error`).

    Returns
    -------
    list of dict
        One row per width: ``n_bar``, ``n_hidden``, ``params``, ``grid_max_error``,
        ``grid_rmse``, ``sample_max_error`` (first input), ``time_s``.
    """
    rows = []
    for nb in n_bars:
        net, rep = fit_relu(system.phi_stacked, system.lo, system.hi, widths=(int(nb),) * depth,
                            n_per_axis=n_per_axis, max_train=None, max_iter=max_iter, seed=seed)
        rows.append(dict(n_bar=int(nb), n_hidden=net.n_hidden,
                         params=int(sum(W.size + b.size for W, b in zip(net.W, net.b))),
                         grid_max_error=float(rep.grid_max_error[0]), grid_rmse=float(rep.grid_rmse[0]),
                         sample_max_error=float(sample_max_error(system, net, n=n_test, seed=seed + 1).eps[0]),
                         time_s=rep.time_s))
    return rows


def slope_in_v(net, z: Array, v: Array) -> Array:
    """``d Phi_NN / d v`` of a network with inputs ``[z, v]`` (single ``v``) at the points ``(z, v_i)`` (chapter 3).

    The network is piecewise affine; at each point the derivative is that of the affine piece the
    point lies in, ``W^K D^{K-1} W^{K-1} ... D^1 W^1 e_v`` with ``D^k`` the activation pattern
    (eq. (MIP_general_c)), exact at the point. A check on a grid of ``v`` is a sampled check: a piece
    narrower than the grid spacing can be missed.

    Parameters
    ----------
    net
        A ``ReLUNet`` whose last input is ``v``.
    z
        The state, shape (n_in - 1,).
    v
        Values of ``v``, shape (N,).

    Returns
    -------
    Array
        Shape (N, n_out): the slope of each output in ``v`` at each point.
    """
    z, v = np.asarray(z, float), np.asarray(v, float)
    if z.shape != (net.n_in - 1,) or v.ndim != 1:
        raise ValueError(f"z must have shape ({net.n_in - 1},) and v shape (N,), got {z.shape} and {v.shape}")
    X = np.column_stack([np.tile(z, (len(v), 1)), v])
    active = net.activation_pattern(X)
    d = np.tile(net.W[0][:, -1], (len(v), 1))  # d y^0 / d v pushed through layer 1: (N, n_1)
    for k, on in enumerate(active):
        d = (d * on) @ net.W[k + 1].T
    return d


#: Largest relative gap HiGHS may report for a range :func:`exact_preactivation_range` accepts as proven. Asked for a
#: zero gap, HiGHS stops when its primal and dual bounds meet, and may then report their round-off (1.65e-16 on a
#: random network of the tests, which a test keeps). The bound is far above round-off and far below the solver's
#: feasibility tolerance (1e-7), which limits the range's accuracy anyway; a real gap (HiGHS reported 3.7e-8 as
#: "optimal" on one of the MSD network's programs with LP-tightened bounds) is still an error.
ROUNDOFF_GAP = 1e-12


def exact_preactivation_range(net, lo: Array, hi: Array, layer: int = -1,
                              neurons: Optional[Sequence[int]] = None, solver: str = "HIGHS") -> tuple[Array, Array]:
    """The exact range of every pre-activation of one hidden layer over the box ``[lo, hi]`` (chapter 4).

    Minimizes and maximizes each pre-activation ``(W^k y^{k-1} + b^k)_j`` of hidden layer ``layer``
    over the big-M program of eq. (MIP_general) with FBBT bounds and the input box, with HiGHS:
    two mixed-integer programs per neuron, each solved to optimality with a zero relative and
    absolute gap (``mip_rel_gap = mip_abs_gap = 0``: the returned point's value equals HiGHS'
    dual bound up to round-off, a reported relative gap of at most :data:`ROUNDOFF_GAP`, so the range is exact up to
    the solver's feasibility tolerances), an error otherwise.
    ``neurons`` selects some neurons of the layer (all by default). ``solver="SCIP"`` solves the same programs with
    SCIP (its default gap limits are zero; a status other than optimal is an error): an independent check of the
    HiGHS ranges.

    Returns
    -------
    L, U
        The smallest and largest pre-activation of each selected neuron, shape (len(neurons),).
    """
    import cvxpy as cp

    from ..bounds import fbbt
    from ..encoding import encode
    from ..solvers.cvxpy_bridge import ScipConic

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    if lo.shape != (net.n_in,) or hi.shape != (net.n_in,):
        raise ValueError(f"lo and hi must have shape ({net.n_in},), got {lo.shape} and {hi.shape}")
    x = cp.Variable(net.n_in)
    enc = encode(net, x, fbbt(net, lo, hi))
    pre = enc.ybar[layer] - enc.yund[layer]
    n_k = pre.shape[0]
    neurons = list(range(n_k)) if neurons is None else [int(j) for j in neurons]
    if not neurons or min(neurons) < 0 or max(neurons) >= n_k:
        raise ValueError(f"neurons must be indices of the layer's {n_k} neurons, got {neurons}")
    c = cp.Parameter(n_k)
    prob = cp.Problem(cp.Maximize(c @ pre), enc.constraints + [x >= lo, x <= hi])
    if solver not in ("HIGHS", "SCIP"):
        raise ValueError(f"solver must be 'HIGHS' or 'SCIP', got {solver!r}")
    L, U = np.empty(len(neurons)), np.empty(len(neurons))
    for i, j in enumerate(neurons):
        for sign, out in ((1.0, U), (-1.0, L)):
            c.value = sign * np.eye(n_k)[j]
            if solver == "SCIP":
                prob.solve(solver=ScipConic())  # cvxpy's SCIP interface without its output relay (see the class)
                if prob.status != "optimal":
                    raise RuntimeError(f"neuron {j}: SCIP returned {prob.status!r}, not a proved optimum")
            else:
                prob.solve(solver="HIGHS", mip_rel_gap=0.0, mip_abs_gap=0.0)
                # every neuron stable on the box: no binary is left and the program is an LP, proven without a gap
                gap = prob.solver_stats.extra_stats.mip_gap if prob.is_mixed_integer() else 0.0
                if prob.status != "optimal" or gap is None or not 0 <= gap <= ROUNDOFF_GAP:
                    raise RuntimeError(f"neuron {j}: HiGHS returned {prob.status!r} with gap {gap}, not a proved "
                                       "optimum")
            out[i] = sign * prob.value
    return L, U
