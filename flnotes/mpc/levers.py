"""The MPC's exact levers on the node bounds and the encoded steps (see :class:`flnotes.MPCOptions`).

* Node bounds of eq. (MIP_general_c) per predicted step (:func:`node_bounds`): the domain box (the
  paper's setting), the reachable boxes, LP-tightened ones, or the level-set boxes.
* Which steps need the network at all (:func:`needed_steps`): a step whose output bounds already lie
  within ``[-u_max^eps, u_max^eps]`` over its box is never encoded.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from ..bounds import NodeBounds, fbbt
from ..tightening import EmptyBoxError, lp_bounds
from ..atlas import BoundAtlas
from .bound_cache import BoundCache
from .options import MPCOptions
from .prediction import Prediction

Array = np.ndarray


def repeat_bounds(b: NodeBounds, N: int) -> NodeBounds:
    """The domain-box bounds ``b`` repeated for every predicted step (arrays of shape (N_p, n_k))."""
    rep = lambda a: np.repeat(np.asarray(a)[None], N, axis=0)  # noqa: E731
    return NodeBounds([rep(L) for L in b.L], [rep(U) for U in b.U], rep(b.out_L), rep(b.out_U), method="box")


def node_bounds(pred: Prediction, opts: MPCOptions, box: NodeBounds, lo: Array, hi: Array,
                steps: Optional[Sequence[int]] = None, use_lp: Optional[bool] = None,
                deadline: Optional[float] = None, cache: Optional[BoundCache] = None,
                atlas: Optional[BoundAtlas] = None) -> Optional[NodeBounds]:
    """Per-step node bounds for the boxes ``lo, hi`` (N_p, n_z + m) under ``opts.bounds``.

    ``"box"``: ``box`` (FBBT on the domain box) at every step. Otherwise FBBT on the boxes; with ``use_lp``
    (default: ``bounds="lp"``, or ``bounds="levelset"`` and ``lp=True``; the engine decides ``lp="auto"``), the
    steps in ``steps``
    (default all) whose outputs can leave ``[-u_max^eps, u_max^eps]`` are LP-tightened with that output
    bound (:func:`flnotes.lp_bounds`): valid for every point the program can select there. Returns
    ``None`` when some step's box holds no input meeting the output bound (the program is infeasible there).
    ``deadline`` (a ``time.perf_counter()`` value) stops the LPs: :class:`flnotes.tightening.DeadlineReached`.
    With a ``cache`` (``opts.bound_cache``) the LPs start from the bounds kept for boxes containing a step's box, and
    their results are kept (:class:`flnotes.mpc.bound_cache.BoundCache`). With an ``atlas``
    (:class:`flnotes.BoundAtlas`, ``fl.MPC(..., atlas=...)``) the steps whose box lies in its domain take its cover
    intersected with FBBT instead of LPs (valid there, so exact); a step where that intersection is empty (only by
    round-off, or a box without admissible input) is LP-tightened as without it, and so are the steps outside.
    """
    N = pred.N
    if opts.bounds == "box":
        return repeat_bounds(box, N)
    nb = fbbt(pred.net, lo, hi)
    if use_lp is None:
        use_lp = opts.bounds == "lp" or opts.lp is True
    if use_lp:
        c = pred.u_eps
        todo = range(N) if steps is None else sorted(steps)
        todo = [k for k in todo if np.any(nb.out_L[k] < -c) or np.any(nb.out_U[k] > c)]
        if todo and atlas is not None:
            todo = _atlas_steps(atlas, nb, lo, hi, todo)
        if todo:
            prior = NodeBounds([L[todo] for L in nb.L], [U[todo] for U in nb.U], nb.out_L[todo], nb.out_U[todo])
            if cache is not None:
                prior = cache.prior(lo[todo], hi[todo], prior)
            try:
                t = lp_bounds(pred.net, lo[todo], hi[todo], out_bounds=(-c, c), prior=prior, skip_stable=True,
                              deadline=deadline)
            except EmptyBoxError:
                return None
            if cache is not None:
                cache.add(lo[todo], hi[todo], t)
            for layer in range(len(nb.L)):
                nb.L[layer][todo], nb.U[layer][todo] = t.L[layer], t.U[layer]
            nb.method = "lp"
    return nb


def _atlas_steps(atlas: BoundAtlas, nb: NodeBounds, lo: Array, hi: Array, todo: list) -> list:
    """Write the atlas's cover (intersected with ``nb``) into ``nb`` at the steps of ``todo`` it serves; returns the
    steps left for the LPs (outside its domain, or an empty intersection)."""
    inside = [k for k, ok in zip(todo, atlas._covers(lo[todo], hi[todo])) if ok]
    if not inside:
        return todo
    cL, cU = atlas.cover(lo[inside], hi[inside])
    L = [np.maximum(nb.L[layer][inside], cL[layer]) for layer in range(len(nb.L))]
    U = [np.minimum(nb.U[layer][inside], cU[layer]) for layer in range(len(nb.U))]
    ok = np.all([np.all(a <= b, axis=1) for a, b in zip(L, U)], axis=0)
    served = [k for k, good in zip(inside, ok) if good]
    for layer in range(len(nb.L)):
        nb.L[layer][served], nb.U[layer][served] = L[layer][ok], U[layer][ok]
    if served:
        nb.method = "atlas"
    return [k for k in todo if k not in served]


#: ``lp="auto"``: a level-set round is LP-tightened when FBBT leaves more unstable neurons than this in the steps
#: it encodes. Measured on the book's Quad-1D programs (chapter "Making it real-time"): with at most ~40 the
#: branch and bound took a few ms, less than the LPs (0.2 ms each, two per unstable neuron and step); with 60 or
#: more it took 0.1 to 5 s, and the LP bounds cut it 4 to 10 times.
LP_AUTO_BINARIES = 48


#: ``backend="auto"``: a program with more binaries than this goes to SCIP, one with at most this many to DAQP.
#: First chosen (50) on the programs of the book's Quad-1D loops at N_p = 15 and 20, where DAQP was faster up to 49
#: binaries. Measured again on a wider set (``python -m flnotes.bench routing``): 499 warm-started programs of at most
#: 60 binaries that the engine handed to a solver along the Quad-1D loops (N_p = 10, 15, 20), the five systems not in
#: the book, cold MSD states and random networks of one integrator, each solved by both back-ends in one process.
#: DAQP's time per node differs from system to system (0.2 ms on the Quad-1D, 1 to 2 ms on the Van der Pol and MSD
#: programs). Up to 30 binaries DAQP took less time in sum than SCIP in every group (5.2 s against 14.4 s in all);
#: from 31 to 50, SCIP took 8.6 s against DAQP's 16.2 s in all: much less on the Van der Pol, the MSD, the other
#: Quad-1D and the random networks (DAQP took up to 0.5 s on programs SCIP proved in 40 to 70 ms), about as much or
#: more on the book's Quad-1D, the pendulum and the cubic chain. With 30 instead of 50 the rule spent 15.1 s instead
#: of 22.7 s on these programs, and the 95th percentile of one program was 127 ms instead of 261 ms; a second full run
#: of the section (555 programs) gave 10.0 s against 12.2 s, and 9.9 to 10.0 s for every threshold from 30 to 40.
#: The closed loops of that run (CPU time in all, two interleaved runs each, 50 -> 30) show the trade: the Van der Pol
#: 5.8, 6.1 -> 5.0, 5.2 s (slowest step 678, 684 -> 368, 503 ms) and the other Quad-1D 2.9, 3.4 -> 2.3, 3.1 s (slowest
#: step 234, 327 -> 111, 140 ms) gained; the book's Quad-1D at N_p = 15 (4.7, 4.5 -> 5.6, 5.8 s) and the pendulum
#: (1.5, 1.4 -> 2.0, 1.7 s) lost more than the run-to-run spread the benchmark report measures (14 %); the Quad-1D at
#: N_p = 10 and 20, the chain, the cubic system and the MSD's cold states moved within it. Which loops gain depends on
#: what a DAQP node costs on their programs, not on the network's size alone; 30 favours the loops where DAQP's nodes
#: are costly, whose steps were the slowest. Under ``time_limit = t_s`` (the Van der Pol and the
#: pendulum, t_s = 50 ms, two interleaved runs each) the limit hits (25, 25 against 25, 24; 8, 10 against 10, 7), the
#: plans at the limit (at most 2.5e-11 above the optimum) and the answers after t_s (none) stayed as they were.
AUTO_DAQP_BINARIES = 30


#: ``backend="auto"`` on a round without an incumbent (no warm start: DAQP's depth-first search cannot prune on a
#: known plan's cost, and its "infeasible", the usual verdict there, is verified by SCIP or HiGHS anyway): a program
#: with more binaries than this goes to SCIP. Measured on 42 such programs captured from closed loops of one integrator
#: with random networks (N_p = 5; all infeasible), each solved by both: from 20 to 34 binaries SCIP took a median
#: 10 ms against DAQP's 15 ms, from 35 on 26 ms against 106 ms; on a stored one of 40 binaries the step took 1.6 s
#: with DAQP and 0.1 s with SCIP. On 60 cold states of the book's Quad-1D (N_p = 10) the rule changed the total time
#: by less than 1 % (such programs there are small or caught earlier, by the relaxation or the node bounds).
AUTO_DAQP_COLD_BINARIES = 20


def pick_backend(backend: str, n_binaries: int, incumbent: bool = True) -> str:
    """The solver of one assembled program: ``backend``, or for ``"auto"`` DAQP up to :data:`AUTO_DAQP_BINARIES`
    binaries (:data:`AUTO_DAQP_COLD_BINARIES` without an ``incumbent``) and SCIP above."""
    if backend != "auto":
        return backend
    limit = AUTO_DAQP_BINARIES if incumbent else min(AUTO_DAQP_BINARIES, AUTO_DAQP_COLD_BINARIES)
    return "daqp" if n_binaries <= limit else "scip"


def unstable_count(nb: NodeBounds, steps: Sequence[int]) -> int:
    """Unstable neurons (``L < 0 < U``, one binary each) of the node bounds ``nb`` at the predicted ``steps``."""
    steps = list(steps)
    return int(sum(np.count_nonzero((np.asarray(L)[steps] < 0) & (np.asarray(U)[steps] > 0))
                   for L, U in zip(nb.L, nb.U))) if steps else 0


def needed_steps(nb: NodeBounds, u_eps: Array, encode: str) -> Optional[list]:
    """Steps whose network constraint must be encoded; ``None`` when a step cannot meet it at all.

    With ``encode="all"`` every step; with ``"needed"`` only steps whose output bounds are not already
    within ``[-u_max^eps, u_max^eps]``.
    """
    oL, oU = np.asarray(nb.out_L), np.asarray(nb.out_U)
    if np.any(np.any(oL > u_eps, axis=1) | np.any(oU < -u_eps, axis=1)):
        return None
    if encode == "all":
        return list(range(oL.shape[0]))
    return [k for k in range(oL.shape[0]) if np.any(oL[k] < -u_eps) or np.any(oU[k] > u_eps)]
