"""Time versus network size: the default MPC with wider and deeper networks on the Quad-1D and the MSD.

A network accurate enough to matter is larger than the book's: a smaller certified ``eps`` of eq. (approx_err)
leaves more of ``u_max`` to the controller (``u_max^eps = u_max - eps``, eq. Phi_NN_ep), but every hidden
neuron that is unstable over the domain box is one more binary per encoded step of eq. (MIP_general_c). This
study measures both sides on a grid of ReLU networks, each trained on its system with the book's training
settings (:data:`flnotes.paper.NET_SETTINGS`) and only the widths changed, and each shipped with its certified
``eps`` (:data:`flnotes.paper.EPS_SETTINGS`) in ``flnotes/data/size/`` (the book's own two networks are the
shipped references of :data:`flnotes.paper.REFERENCES` and are not duplicated).

``python -m flnotes.studies.shipped size`` (part of ``make reference``) writes the files; :func:`size_net`
loads one and checks its premise (checksum, widths, system, training and certification settings).
:func:`size_rows` runs the default :class:`flnotes.MPC` at ``N_p`` in ``{10, 20}`` along a fixed set of seeded
closed loops and cold states, per network, and reports the per-step time distribution (median, p99, max; CPU
and wall), the statuses (proven optimal, stopped at the per-step limit), ``eps`` and the binaries.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from .. import paper
from ..bounds import fbbt
from ..network import ReLUNet, fit_relu
from ..parallel import task_key, task_seeds, using
from ..reference import DATA_DIR, load_reference, save_reference
from ..tables import time_stats

Array = np.ndarray

__all__ = ["SYSTEMS", "SIZES", "SIZE_DIR", "TS", "size_label", "size_reference_name", "size_net", "size_settings",
           "write_size_references", "network_table", "size_cases", "size_run", "size_row", "size_rows", "size_numbers"]

#: The two systems of the study (:func:`flnotes.paper.system`).
SYSTEMS: tuple[str, ...] = ("Quad-1D", "MSD")

#: The hidden widths of the study per system: widths 10 to 40, depths 2 to 4. A subset of the full grid that keeps
#: the trend along each axis and includes the (20, 20, 20) and (30, 30) class. The Quad-1D's (30, 30, 30) and
#: (10, 10, 10, 10) are not shipped yet: their training (60 000 points) did not finish on the loaded machine that
#: wrote the files; ``write_size_references(["Quad-1D"], [(30, 30, 30), (10, 10, 10, 10)])`` after adding them here.
SIZES: dict[str, tuple[tuple[int, ...], ...]] = {
    "Quad-1D": ((10, 10), (20, 20), (30, 30), (40, 40), (10, 10, 10), (20, 20, 20)),
    "MSD": ((10, 10), (20, 20), (30, 30), (40, 40), (10, 10, 10), (20, 20, 20), (30, 30, 30), (10, 10, 10, 10)),
}

#: Folder of the study's shipped networks (package data).
SIZE_DIR: Path = DATA_DIR / "size"


def size_label(widths: Sequence[int]) -> str:
    """``(20, 20, 20) -> "20x3"`` (equal widths) or ``"10-20"`` (otherwise)."""
    w = tuple(int(x) for x in widths)
    return f"{w[0]}x{len(w)}" if len(set(w)) == 1 else "-".join(str(x) for x in w)


def _check_system(system: str) -> None:
    if system not in SYSTEMS:
        raise ValueError(f"unknown system {system!r}; choose one of {list(SYSTEMS)}")


def _check(system: str, widths: Sequence[int]) -> tuple[int, ...]:
    _check_system(system)
    w = tuple(int(x) for x in widths)
    if w not in SIZES[system]:
        raise ValueError(f"widths {w} are not in the study of {system}; choose one of {[list(s) for s in SIZES[system]]}")
    return w


def size_settings(system: str, widths: Sequence[int]) -> dict:
    """The training settings of the network: the book's :data:`flnotes.paper.NET_SETTINGS` with ``widths``."""
    w = _check(system, widths)
    return {**paper.NET_SETTINGS[system], "widths": w}


def size_reference_name(system: str, widths: Sequence[int]) -> tuple[str, Optional[Path]]:
    """``(name, folder)`` of the shipped reference: the book's own (folder ``None``) or ``size_<system>-<label>``."""
    settings = size_settings(system, widths)
    book = paper.shipped_name(system, settings)
    if book is not None:
        return book, None
    return f"size_{system}-{size_label(settings['widths'])}", SIZE_DIR


def size_net(system: str, widths: Sequence[int], folder: Optional[Path] = None) -> tuple[ReLUNet, float, dict]:
    """The shipped network of the study, its certified ``eps`` (the bracket's upper end) and the bracket.

    The premise is checked on load: the weights match their SHA-256 checksum
    (:func:`flnotes.reference.load_reference`), the network has the requested widths and the system's input and
    output sizes, it was trained on ``system`` with :func:`size_settings`, and its bracket was certified with the
    book's :data:`flnotes.paper.EPS_SETTINGS`. Anything else is an error that says how to rewrite the file.
    ``folder`` overrides :data:`SIZE_DIR` (tests).
    """
    name, where = size_reference_name(system, widths)
    ref = load_reference(name, folder=where if folder is None or where is None else folder)
    sysm = paper.system(system)
    settings = paper._normalized(dict(system=system, **size_settings(system, widths)))
    eps_settings = paper._normalized(dict(paper.EPS_SETTINGS, version=paper._EPS_VERSION))
    fix = "rewrite it with `python -m flnotes.studies.shipped size`"
    if tuple(ref.net.widths) != tuple(widths) or ref.net.n_in != sysm.n_in or ref.net.n_out != sysm.B.shape[1]:
        raise ValueError(f"the shipped network {name!r} has widths {ref.net.widths} and {ref.net.n_in} inputs, "
                         f"{ref.net.n_out} outputs; expected {tuple(widths)}, {sysm.n_in}, {sysm.B.shape[1]}: {fix}")
    if paper._normalized(ref.meta.get("settings")) != settings:
        raise ValueError(f"the shipped network {name!r} was trained with {ref.meta.get('settings')}, not with the "
                         f"study's settings {settings}: {fix}")
    if ref.bracket is None or ref.meta.get("eps_settings") != eps_settings:
        raise ValueError(f"the shipped network {name!r} has no bracket certified with the book's EPS_SETTINGS: {fix}")
    if not all(ref.bracket["converged"]):
        raise ValueError(f"the certification of the shipped network {name!r} did not converge: {fix}")
    return ref.net, float(np.max(ref.bracket["upper"])), ref.bracket


def _size_task(task: tuple) -> tuple:
    """One task of :func:`write_size_references`: train and certify; ``(net, report, bracket)``."""
    system, widths = task
    sysm = paper.system(system)
    net, rep = fit_relu(sysm.phi_stacked, sysm.lo, sysm.hi, **size_settings(system, widths))
    return net, rep, paper.certify_book_eps(system, net)


def write_size_references(systems: Sequence[str] = SYSTEMS, sizes: Optional[Sequence[Sequence[int]]] = None, folder=None,
                          workers: Optional[int] = None, client=None, progress: bool = False,
                          resume: bool = False) -> list[str]:
    """Train (:func:`flnotes.fit_relu`) and certify (:func:`flnotes.paper.certify_book_eps`) the study's networks.

    ``sizes`` (default: :data:`SIZES` of each system) selects networks of the study.
    Every (system, widths) pair not already shipped as one of the book's networks is one task of
    :class:`flnotes.parallel.Executor` (``workers`` local processes or a Dask ``client``; training with one
    BLAS thread either way); the files are written here, into ``folder`` (default :data:`SIZE_DIR`), in the order
    of ``systems`` then ``sizes``. ``resume`` keeps each finished network in the cache folder. Minutes of CPU:
    only to change the shipped networks on purpose. Returns the JSON files written.
    """
    tasks = [(s, _check(s, w)) for s in systems for w in (SIZES[s] if sizes is None else sizes)
             if size_reference_name(s, w)[1] is not None]
    keys = ([task_key("size", s, paper._normalized(size_settings(s, w)), paper._normalized(paper.EPS_SETTINGS),
                      paper._EPS_VERSION, paper.library_versions()) for s, w in tasks] if resume else None)
    with using(workers, client) as ex:
        done = ex.map(_size_task, tasks, keys=keys, cache="size" if resume else None, desc="size networks",
                      progress=progress)
    out = []
    for (s, w), (net, rep, br) in zip(tasks, done):
        name, _ = size_reference_name(s, w)
        out.append(str(save_reference(name, net, rep, dict(system=s, **size_settings(s, w)), bracket=br,
                                      eps_settings=dict(paper.EPS_SETTINGS, version=paper._EPS_VERSION),
                                      folder=SIZE_DIR if folder is None else folder)))
    return out


def network_table(systems: Sequence[str] = SYSTEMS, sizes: Optional[Sequence[Sequence[int]]] = None) -> list[dict]:
    """One row per shipped network of the study: its size, the neurons unstable over the box and its certified bracket.

    Columns: ``system``, ``network``, ``depth``, ``hidden``, ``unstable`` (FBBT over the domain box: the binaries
    of one encoded step of eq. MIP_general_c), ``eps lower`` and ``eps`` (the certified bracket), ``eps/u_max``,
    ``grid max error`` (of the training report) and ``training iterations``. The same on every machine: it
    reads the shipped files only. ``sizes`` defaults to :data:`SIZES` of each system.
    """
    rows = []
    for s in systems:
        sysm = paper.system(s)
        for w in (SIZES[s] if sizes is None else sizes):
            net, eps, br = size_net(s, w)
            name, where = size_reference_name(s, w)
            rep = load_reference(name, folder=where).report
            rows.append({"system": s, "network": size_label(w), "depth": len(w), "hidden": int(net.n_hidden),
                         "unstable": int(fbbt(net, sysm.lo, sysm.hi).n_unstable),
                         "eps lower": float(np.max(br["lower"])), "eps": eps, "eps/u_max": eps / float(sysm.u_max[0]),
                         "grid max error": float(np.max(rep.grid_max_error)), "training iterations": int(rep.n_iter)})
    return rows


# ----------------------------------------------------------------------------------- the MPC along fixed states
#: The MPC of the study per system: Sec. IV-B's setting for the Quad-1D, chapter 11's for the MSD
#: (:func:`flnotes.studies.compare.setting`), both at ``t_s = 0.1`` s.
TS: float = 0.1


def _weights(system: str) -> tuple[Array, Array]:
    if system == "Quad-1D":
        return np.diag(paper.QUAD_SETTING["Q"]).copy(), np.atleast_2d(paper.QUAD_SETTING["R"])
    return np.array([10.0, 1.0]), np.array([[0.01]])


def size_cases(system: str, horizon: int, n_loops: int = 2, n_cold: int = 10, seed: int = 0) -> dict:
    """The fixed programs every network of ``system`` is timed on, from ``seed``.

    ``loops``: ``n_loops`` scenarios of chapter 11's Monte Carlo (:func:`flnotes.studies.compare.draw_scenarios`:
    a start and a sine reference), each run as a closed loop on the true plant. ``cold``: ``n_cold`` states
    solved cold (no previous plan): the position uniform in 90 % of its range, the derivatives in 50 % of
    theirs, and a reference of the same distribution as the loops' from a random time (``z_ref`` of shape
    ``(N_p + 1, n_z)``). The same for every network, so the rows differ by the network only.
    """
    from .compare import draw_scenarios, scenario_reference

    _check_system(system)
    sysm = paper.system(system)
    loops = draw_scenarios(system, n_loops, seed=seed) if n_loops else []
    rng = np.random.default_rng(task_seeds(seed, 2)[1])
    nz = sysm.n_z
    mid, half = (sysm.lo[:nz] + sysm.hi[:nz]) / 2, (sysm.hi[:nz] - sysm.lo[:nz]) / 2
    spread = np.r_[0.9, np.full(nz - 1, 0.5)]
    refs = draw_scenarios(system, max(n_cold, 1), seed=seed + 1)
    cold = []
    for j in range(n_cold):
        sc = refs[j]
        t0 = rng.uniform(0.0, 2 * np.pi / sc["omega"])
        z = mid + rng.uniform(-1.0, 1.0, nz) * spread * half
        cold.append(dict(z=z, z_ref=scenario_reference(sysm, sc)(t0 + TS * np.arange(int(horizon) + 1))))
    return dict(system=system, horizon=int(horizon), loops=loops, cold=cold)


def size_run(system: str, widths: Sequence[int], cases: dict, loop_steps: int = 30,
             time_limit: Optional[float] = 1.0) -> dict:
    """Time the default :class:`flnotes.MPC` with the study's network ``widths`` on ``cases`` (:func:`size_cases`).

    Every closed loop runs ``loop_steps`` sampling instants on the true plant (:func:`flnotes.simulate`, warm
    started from step to step as the controller does), then every cold state is solved once after
    :meth:`flnotes.MPC.reset`. ``time_limit`` (s per step, default 1 s = 10 ``t_s``) caps each step: a step that
    reaches it answers with its incumbent (status ``"time_limit"``), so a large network cannot stall the
    benchmark; ``None`` solves every step to the end. Returns the network's ``eps``, its unstable neurons over
    the domain box (FBBT) and per step: ``wall`` and ``cpu`` (s), the :class:`flnotes.StepResult` ``status``,
    ``n_binaries``, ``screened`` and ``kind`` (``"loop"`` or ``"cold"``).
    """
    from ..mpc import MPC
    from ..simulate import simulate
    from .compare import scenario_reference
    from .unseen import TimedController

    sysm = paper.system(system)
    net, eps, _ = size_net(system, widths)
    Q, R = _weights(system)
    N = cases["horizon"]
    mpc = MPC(sysm, net, eps, horizon=N, ts=TS, Q=Q, R=R, time_limit=time_limit)
    timed = TimedController(mpc)
    steps, kinds, wall, cpu = [], [], [], []
    for sc in cases["loops"]:
        simulate(sysm, timed, t_final=loop_steps * TS, ts=TS, z0=sc["z0"], reference=scenario_reference(sysm, sc),
                 net=net, progress=False)                       # resets the controller and its timer first
        steps += list(mpc.history)
        kinds += ["loop"] * len(mpc.history)
        wall += timed.wall
        cpu += timed.cpu
    for cs in cases["cold"]:
        mpc.reset()
        w0, c0 = time.perf_counter(), time.process_time()
        steps.append(mpc(cs["z"], cs["z_ref"]))
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
        kinds.append("cold")
    if len(wall) != len(steps):
        raise RuntimeError(f"{len(wall)} timed steps for {len(steps)} step results: the controller's history and "
                           "the timer disagree")
    return dict(system=system, widths=tuple(int(w) for w in widths), horizon=N, eps=eps, u_max=float(sysm.u_max[0]),
                unstable=int(fbbt(net, sysm.lo, sysm.hi).n_unstable), hidden=int(net.n_hidden),
                wall=np.array(wall), cpu=np.array(cpu), status=[s.status for s in steps],
                n_binaries=np.array([s.n_binaries for s in steps]), screened=np.array([s.screened for s in steps]),
                kind=kinds, time_limit=time_limit)


def size_row(run: dict) -> dict:
    """The table row of one :func:`size_run`: size, ``eps``, binaries, statuses and the time per step.

    ``binaries (box)``: ``N_p`` times the neurons unstable over the domain box (FBBT), the free binaries of
    eq. (MIP_general_c) with every predicted step encoded (the paper's count, every neuron, is larger);
    ``binaries max``: the most the engine encoded at a step. ``optimal``:
    steps proven optimal; ``limit``: steps stopped at the time limit, and ``limit, cpu < cap/2`` those of them that
    used less than half the limit in CPU time (they waited for a shared core more than they computed); ``other``:
    any other status (infeasible, error). Times in ms, wall (:func:`time.perf_counter`, waits for a shared core included) and CPU
    (:func:`time.process_time`); ``over t_s`` and ``cpu over t_s`` count the steps whose wall or CPU time exceeds
    ``t_s``.
    """
    sw, sc = time_stats(run["wall"], (50, 99)), time_stats(run["cpu"], (50, 90, 99))
    st = run["status"]
    n_opt, n_lim = sum(s == "optimal" for s in st), sum(s == "time_limit" for s in st)
    cap = run["time_limit"]
    waited = 0 if cap is None else int(sum(s == "time_limit" and c < 0.5 * cap for s, c in zip(st, run["cpu"])))
    return {"system": run["system"], "network": size_label(run["widths"]), "depth": len(run["widths"]),
            "hidden": run["hidden"],
            "unstable": run["unstable"], "eps": run["eps"], "eps/u_max": run["eps"] / run["u_max"],
            "N_p": run["horizon"], "binaries (box)": run["horizon"] * run["unstable"],
            "binaries max": int(run["n_binaries"].max()), "steps": len(st), "screened": int(run["screened"].sum()),
            "optimal": int(n_opt), "limit": int(n_lim), "limit, cpu < cap/2": waited,
            "other": int(len(st) - n_opt - n_lim),
            "median ms": sw["median_ms"], "p99 ms": sw["p99_ms"], "max ms": sw["max_ms"],
            "cpu median ms": sc["median_ms"], "cpu p90 ms": sc["p90_ms"], "cpu p99 ms": sc["p99_ms"], "cpu max ms": sc["max_ms"],
            "over t_s": int(np.sum(run["wall"] > TS)), "cpu over t_s": int(np.sum(run["cpu"] > TS))}


def _row_task(task: tuple) -> dict:
    system, widths, cases, loop_steps, time_limit = task
    return size_row(size_run(system, widths, cases, loop_steps=loop_steps, time_limit=time_limit))


def size_rows(systems: Sequence[str] = SYSTEMS, sizes: Optional[Sequence[Sequence[int]]] = None,
              horizons: Sequence[int] = (10, 20), n_loops: int = 2, loop_steps: int = 30, n_cold: int = 10,
              seed: int = 0, time_limit: Optional[float] = 1.0, workers: Optional[int] = None, client=None,
              progress: bool = False) -> list[dict]:
    """:func:`size_row` for every system, network and ``N_p`` of the grid, on the same seeded programs.

    ``sizes`` defaults to :data:`SIZES` of each system. One task of :class:`flnotes.parallel.Executor` per
    (system, ``N_p``, network); the rows in that order.
    Tasks side by side share the machine: their wall times include the competition (the CPU times less so).
    """
    tasks = []
    for s in systems:
        for N in horizons:
            cases = size_cases(s, N, n_loops=n_loops, n_cold=n_cold, seed=seed)
            tasks += [(s, _check(s, w), cases, int(loop_steps), time_limit) for w in (SIZES[s] if sizes is None else sizes)]
    with using(workers, client) as ex:
        return ex.map(_row_task, tasks, desc="size study", progress=progress)


def size_numbers(rows: Sequence[dict]) -> dict:
    """What a page quotes from :func:`size_rows`.

    Per row ``<system> <network> N_p=<N>``: its wall p99 and max over ``t_s``, ``within`` (every step proven optimal
    and none used more than ``t_s`` of CPU time) and ``p90_within`` (the 90th percentile of the CPU time per step
    at most ``t_s``). The verdicts rest on CPU time, not on the wall clock: on a shared machine a single step that
    waited for a core would otherwise decide them. Per system and ``N_p``: ``largest within t_s, <system>
    N_p=<N>`` and ``largest p90 within t_s, <system> N_p=<N>``, the largest network that meets each (``None`` when
    none does): the most neurons, and among networks with as many neurons the most binaries on the domain box
    (``binaries (box)``, the size of the program); networks tied on both are all named (``"30x2 and 20x3"``).
    """
    out: dict = {}
    for r in rows:
        key = f"{r['system']} {r['network']} N_p={r['N_p']}"
        out[key] = dict(p99_over_ts=r["p99 ms"] / (TS * 1e3), max_over_ts=r["max ms"] / (TS * 1e3), eps=r["eps"],
                        within=bool(r["optimal"] == r["steps"] and r["cpu over t_s"] == 0),
                        p90_within=bool(r["cpu p90 ms"] <= TS * 1e3))
    for s in {r["system"] for r in rows}:
        for N in {r["N_p"] for r in rows}:
            mine = [r for r in rows if r["system"] == s and r["N_p"] == N]
            for name, flag in (("largest within t_s", "within"), ("largest p90 within t_s", "p90_within")):
                ok = [r for r in mine if out[f"{s} {r['network']} N_p={N}"][flag]]
                out[f"{name}, {s} N_p={N}"] = _largest(ok)
    return out


def _size_key(r: dict) -> tuple:
    """How :func:`size_numbers` orders networks by size: neurons, then the binaries of the program on the box."""
    return (r["hidden"], r["binaries (box)"])


def _largest(rows: Sequence[dict]) -> Optional[str]:
    """The largest network of ``rows`` by :func:`_size_key`, or all of them that tie (``"a and b"``); ``None`` if
    ``rows`` is empty."""
    if not rows:
        return None
    top = max(_size_key(r) for r in rows)
    names = [r["network"] for r in rows if _size_key(r) == top]
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]
