"""The solve of eq. (MPC_form_miqp) at one state, with the levers of :class:`flnotes.MPCOptions`.

:class:`NetworkEngine` is the one place where the MIQP is solved by the persistent back-ends: screening QP,
node bounds (box, reachable boxes, LP, level set), constraint generation, warm start, the solver-margin
policy. Every lever is exact: the plan returned as ``"optimal"`` is a global optimum of the program.

The level set (``bounds="levelset"``). With ``(V_c, J_c)`` the optimum of the relaxation (the convex QP
without the network, plus the slab of the network's affine enclosure when the model has one:
:meth:`flnotes.mpc.prediction.Prediction.relaxation`; a set containing every feasible plan), every feasible ``V`` has
``J(V) >= J_c + 0.5 ||V - V_c||_H^2`` (:func:`flnotes.ellipsoid_box`). A plan cheaper than a level ``J_up``
thus lies in an ellipsoid whose projection on each ``(z(k), v(k))`` is a small box; FBBT on these boxes
leaves few unstable neurons, and steps whose output provably meets the bound are not encoded. The program
restricted to these boxes contains every plan cheaper than ``J_up`` and nothing infeasible, so its optimum
is the global one whenever it is below ``J_up``; otherwise ``J_up`` is raised (or, when ``J_up`` is the
incumbent's cost, the incumbent is optimal). The incumbent is the cheaper of the warm start and the relaxation's
optimum repaired step by step along the QP without the network (or, when neither passes the check, the cheapest
one-switch plan at the input bounds: ``bang_bang``, :mod:`flnotes.mpc.bang_bang`), then optimized over the
network's linear region around it and its neighbours (``repair``; :mod:`flnotes.mpc.region`). ``J_up`` starts at
the incumbent's cost (``first_level="incumbent"``: one round holds the optimum; without an incumbent at
``J_c + max(1, |J_c|)``), or at ``J_c`` plus a small margin (``first_level="relaxation"``); the margin is
multiplied by 4 per round that finds nothing below it. A round whose boxes hold the whole program's (the boxes
the enclosure's slab alone leaves) is the whole program: its verdict is final. For one input, step 0's constraint is
the exact range of ``v(0)`` at the measured state, bounds instead of neurons (:data:`FIRST_RANGE`).
"""
from __future__ import annotations

import copy
import numbers
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np

from ..atlas import BoundAtlas
from ..bounds import NodeBounds, fbbt
from ..result import StepResult
from ..solvers import MIQP, TIGHTENED_GAP, available_backends, make_solver, next_margin, release_retired, retire
from ..solvers.base import VERIFY_MIN_LEFT
from ..tightening import DeadlineReached, EmptyBoxError, intersect
from .bang_bang import bang_bang_incumbent
from .bound_cache import BoundCache
from .fallback import RepairState, qp_repair
from .region import REGION_MOVES, region_exact, region_qp
from .levers import LP_AUTO_BINARIES, needed_steps, node_bounds, pick_backend, unstable_count
from .options import MPCOptions
from .prediction import Prediction
from .program import compact_program, plan_vector, program_pattern

Array = np.ndarray

#: ``first_level="incumbent"`` without an incumbent: the first level is ``J_c`` plus this times ``max(1, |J_c|)``.
#: Measured on 120 diverse cold states of the book's Quad-1D at N_p = 10 (42 infeasible, and one feasible program
#: whose repaired relaxation failed the check): factors from 0.25 to 4 took 3.8 to 4.0 s in all on the programs
#: without an incumbent, against 6.5 s with the relaxation's margin of 1e-3 and 4.2 s for the whole program at once.
FIRST_LEVEL_NO_INCUMBENT = 1.0

#: Lazy constraint generation (``lazy=True``) encodes from the first round, besides the steps where the QP's optimum
#: without the network breaks the bound, the steps where the incumbent plan (the repaired relaxation, or the warm
#: start) has ``|Phi_NN| >= (1 - NEAR_ACTIVE) u_max^eps``: the optimum is most often held there too, and a step found
#: violated only after a round costs a second program (built and solved again). Measured side by side on chapter 11's
#: MSD (N_p = 10): on 100 diverse cold states CPU -27% (p90 0.25 -> 0.17 s, 39 -> 29 steps over t_s = 0.1 s, SCIP
#: programs 108 -> 80), on the closed loops of 5 scenarios x 3 s CPU -17% (max 0.20 -> 0.13 s); the same optima. Any
#: value from 0.005 to 0.05 gave the same; 0 (the steps at the bound only) gained nothing. ``None``: none added (the
#: first round holds the QP's violated steps and the previous step's only).
NEAR_ACTIVE: Optional[float] = 0.02

#: One input (``m = 1``): at the measured state ``z(0) = z0`` is known, so step 0's admissible inputs are exact (chapter
#: 6's 1-D method); where they form one interval (:meth:`flnotes.mpc.prediction.Prediction.first_range`), step 0's
#: network constraint is written as the bounds ``a <= v(0) <= b`` in every program instead of step 0's neurons and
#: binaries, and the same bounds cut the relaxation (a second QP, when the first one's ``v(0)`` lies outside them) and
#: the reachable boxes of the later steps. Exact: the bounds are step 0's constraint. Where the set is empty or several
#: intervals, and for several inputs, step 0 is encoded like the others, as with ``False``. Measured side by side (one
#: process, alternating, the same states), the same statuses and optima (within 3.3e-10): chapter 11's MSD (N_p = 10),
#: 100 cold states: CPU -13 to -16% (p90 0.18 -> 0.15 s, binaries 7,838 -> 7,049), its closed loops (5 scenarios x
#: 3 s) -16 to -17% (max 0.19 -> 0.12 s); the book's Quad-1D, 80 cold states: -12 to -15% (median 29 -> 9 ms), at
#: N_p = 20 (30 states): -8 to -9%.
FIRST_RANGE: bool = True


def _near_active() -> float:
    """:data:`NEAR_ACTIVE` as a share in ``[0, 1)`` (``ValueError`` otherwise: 1 or more would encode every step, a
    negative share none, like ``None``)."""
    share = NEAR_ACTIVE
    if isinstance(share, (bool, np.bool_)) or not isinstance(share, numbers.Real) or not 0.0 <= share < 1.0:
        raise ValueError(f"flnotes.mpc.engine.NEAR_ACTIVE must be None or a share of u_max^eps in [0, 1), got "
                         f"{share!r}")
    return float(share)


def _first_range_on() -> bool:
    """:data:`FIRST_RANGE` as a flag (``ValueError`` for anything but ``True`` or ``False``)."""
    if not isinstance(FIRST_RANGE, (bool, np.bool_)):
        raise ValueError(f"flnotes.mpc.engine.FIRST_RANGE must be True or False, got {FIRST_RANGE!r}")
    return bool(FIRST_RANGE)


#: Seconds of the time limit that must be left to start a solver or a round: with less, the step returns its
#: incumbent (a solver started then answered after the limit by its start-up and its overrun).
SOLVE_MIN_LEFT = 0.002

#: The longest a solve stopped with ``hold=True`` waits for :meth:`NetworkEngine.answered` before it builds its result
#: (seconds): far longer than an answer at a cut-off takes, so that the hold is released by the answer, and finite,
#: so that a caller that never calls ``answered()`` delays the solve's end instead of stopping it for good.
HOLD_MAX_S = 2.0

#: Seconds a solve held by :meth:`NetworkEngine.stop` (``hold=True``) sleeps once the caller's
#: :meth:`NetworkEngine.answered` has released it, before it builds its result: the answering thread, which released
#: it as its last act, then returns to its caller with the interpreter lock instead of waiting for it while this
#: thread runs (on a loaded machine such a wait, with this thread off its core, held an answer 6 ms past t_s). Its
#: cost: a next step called at once (as :func:`flnotes.simulate` does) waits for this solve's end inside its own
#: budget, about 1 ms longer (measured: 0.2-1.0 -> 1.3-1.5 ms on average); a step called at its sampling tick
#: starts after it. Measured side by side with a busy core (20 ms, N_p = 10, 3 x 300 steps, two pairs): cut-off
#: answers p99 0.80 and 0.82 -> 0.76 and 0.73 t_s, the slowest 0.93 and 0.88 -> 0.88 and 0.76 t_s.
ANSWER_GRACE_S = 0.002

#: Seconds that must be left to polish a round's optimum under a tightened bound (:meth:`NetworkEngine._polish`: a
#: HiGHS model built and solved, 4 to 6 ms on the systems of the benchmark).
TIGHTENED_QP_MIN_LEFT = 0.008

#: Appended to the message of a verdict of tightened rows that an untightened SCIP bound of its round backs, and
#: of one that the untightened round's own plan replaces (it passed the forward-pass check, within the gap).
BACKED = "; backed by the untightened round's bound (scip)"
BACKED_PLAN = "; the untightened round's plan (scip) passes the forward-pass check and is optimal to the gap"

#: Solver of the convex QP with the binaries fixed (:meth:`NetworkEngine._polish`): it must be the exact optimum, so
#: HiGHS's active-set QP, not DAQP's regularized one.
_RELAX = "highs"


@dataclass(frozen=True, eq=False)
class Progress:
    """What a running :meth:`NetworkEngine.solve` has at one moment, published for an answer at a cut-off.

    ``V`` is the best plan found so far that passed the forward-pass check (``None``: none yet), ``J`` its cost
    and ``bound`` a valid lower bound of eq. (MPC_form_miqp) (``-inf``: none yet); ``f, c0`` the cost's linear
    part at ``z0`` and ``stats`` the solve's counters (nodes, rounds, binaries, encoded steps).
    """

    z0: Array
    f: Array
    c0: float
    V: Optional[Array] = None
    J: float = np.inf
    bound: float = -np.inf
    source: Optional[str] = None
    warm: bool = False
    stats: dict = field(default_factory=dict)


def _step_result(pred: Prediction, z0: Array, f: Array, c0: float, status: str, V: Optional[Array], bound: float,
                 msg: str, st: dict, warm: bool, screened: bool = False) -> StepResult:
    """The :class:`flnotes.StepResult` of a solve: the plan ``V`` (or none) with its cost, ``bound`` and gap."""
    N, m = pred.N, pred.m
    res = StepResult(None, status, nodes=st.get("nodes", 0), rounds=st.get("rounds", 0),
                     n_binaries=st.get("n_bin", 0), encoded_steps=tuple(int(k) for k in st.get("steps", ())),
                     screened=screened, backend="qp-screening" if screened else st.get("backend", ""),
                     message=msg, warm_started=warm)
    res.info["lp_rounds"] = st.get("lp_rounds", 0)  # level-set rounds whose node bounds were LP-tightened
    res.info["scip_programs"] = st.get("scip_programs", 0)  # programs of the rounds handed to SCIP
    res.info["incumbent"] = st.get("incumbent")  # where the first incumbent came from (None: none)
    res.info["region_improved"] = st.get("region", False)  # the region QP made it cheaper
    res.info["tightened"] = st.get("tightened", 0)  # times u_max^eps was tightened in the rows (solver tolerance)
    res.info["repair_failed"] = st.get("repair_failed", False)  # the plan along the QP failed the check
    res.info["bang_bang_s"] = st.get("bang_bang_s")  # time of the one-switch search (s; None: it did not run)
    if V is not None:
        V = np.asarray(V, float).reshape(N, m)
        obj = pred.cost(V, f, c0)
        bound = min(bound, obj)
        res.v, res.v_pred, res.z_pred = V[0].copy(), V, pred.predict(z0, V)
        res.objective, res.bound = obj, bound
        res.gap = abs(obj - bound) / max(1.0, abs(obj)) if np.isfinite(bound) else np.inf
    elif status == "time_limit":
        res.bound = bound  # a valid lower bound, for the gap of the caller's fallback plan
    return res


def _status(s: str) -> str:
    s = str(s).lower()
    if s in ("optimal", "time_limit", "infeasible"):
        return s
    if "time" in s or "limit" in s:
        return "time_limit"
    if "infeas" in s:
        return "infeasible"
    return "error"


class NetworkEngine:
    """Eq. (MPC_form_miqp) with the network constraint, solved to global optimality with the levers.

    Parameters
    ----------
    pred
        The prediction model (cost, boxes, terminal rows, checks).
    opts
        The validated options (``constraint="network"``, a persistent back-end).
    box
        FBBT node bounds on the domain box (``bounds="box"``).
    solver_options
        Per back-end, passed to :func:`flnotes.solvers.make_solver`: ``{"daqp": {...}, "scip": {...}}``.
    atlas
        A :class:`flnotes.BoundAtlas` of the network whose covers replace the LP bounds of the boxes in its domain
        (:func:`flnotes.mpc.levers.node_bounds`), or ``None``.

    Attributes
    ----------
    margin
        How much ``u_max^eps`` was tightened in the rows of the last solve (0 at the start of each solve; grows
        when a returned plan's forward pass exceeds ``u_max^eps`` beyond round-off; the tolerance policy of
        :mod:`flnotes.solvers`).
    cache
        The kept LP bounds (:class:`flnotes.mpc.bound_cache.BoundCache`) with ``opts.bound_cache``, else ``None``.
    progress
        The running (or last) solve's :class:`Progress`: its best plan and bound so far, replaced as they improve
        (``None`` before the first solve). :meth:`answer_now` reads it from another thread.
    repair
        The running (or last) solve's build of its first incumbent along the QP
        (:class:`flnotes.mpc.fallback.RepairState`, replaced after each step; ``None`` before it starts), which
        :meth:`answer_now` hands on where it has no plan yet, for the caller's fallback to continue.
    """

    def __init__(self, pred: Prediction, opts: MPCOptions, box: NodeBounds, solver_options: Optional[dict] = None,
                 atlas: Optional[BoundAtlas] = None):
        self.pred, self.opts, self.box, self.atlas = pred, opts, box, atlas
        self.solver_options = {k: dict(v) for k, v in (solver_options or {}).items()}
        self.margin = 0.0
        self.active_prev: tuple = ()
        self.order = opts.branching or "layers"  # the binaries' column order (DAQP's branching order)
        self.cache = BoundCache() if opts.bound_cache else None  # LP bounds kept for later boxes
        self.progress: Optional[Progress] = None
        self.repair: Optional[RepairState] = None
        self._stop = threading.Event()
        self._answered = threading.Event()  # cleared by stop(hold=True) until answered(): see stop
        self._answered.set()
        self._holder: Optional[int] = None  # the thread that asked for the hold (it is never held itself)
        self.stop_at: Optional[float] = None

    def stop(self, hold: bool = False) -> None:
        """Ask the running :meth:`solve` to return at its next check of the time (a solver call already started
        runs to its own time limit first); cleared by :meth:`go`.

        ``hold=True`` (a caller that answers meanwhile from :meth:`answer_now`, as :class:`flnotes.MPC` does at its
        cut-off): once the solve has stopped, it waits for :meth:`answered` before it builds its result, so that what
        is left of it does not compete with the caller's answer for the interpreter lock and the core. Only a solve
        in another thread than the caller's waits (a solve in the caller's own thread could never be released), and
        at most :data:`HOLD_MAX_S` seconds: a caller that never calls :meth:`answered` delays the solve's end, never
        stops it for good. Call :meth:`answered` (or :meth:`go`) once the answer is out."""
        if hold:
            self._holder = threading.get_ident()
            self._answered.clear()
        self._stop.set()

    def answered(self) -> None:
        """The caller has answered: a solve held by :meth:`stop` (``hold=True``) goes on to its end."""
        self._answered.set()

    def go(self, stop_at: Optional[float] = None) -> None:
        """Clear :meth:`stop` and :attr:`progress` for the next solve (an answer read before it publishes anything
        then has no plan, never one of an earlier state). ``stop_at`` (a :func:`time.perf_counter` value: the
        caller's cut-off) also stops the incumbent search's repair and region moves at that time, without waiting
        for the caller's :meth:`stop` (on a busy machine the caller's thread can wake late)."""
        self._stop.clear()
        self._answered.set()
        self.stop_at = stop_at
        self.progress = None
        self.repair = None

    def _stopped(self) -> bool:
        """Has the caller asked this solve to stop (:meth:`stop`), or has its cut-off (``stop_at``) passed?"""
        return self._stop.is_set() or (self.stop_at is not None and time.perf_counter() >= self.stop_at)

    def answer_now(self) -> StepResult:
        """The answer of the running solve at this moment, from :attr:`progress`: status ``"time_limit"``, its best
        plan that passed the forward-pass check (or no plan) and its lower bound, ``info["cut_off"]`` True. Without a
        plan, ``info["repair_state"]`` is the first incumbent's build as far as it got (:attr:`repair`; ``None``: not
        started), which :class:`flnotes.MPC`'s fallback continues instead of starting it again.

        Reads only :attr:`progress` (replaced whole by the solve, never changed in place) and the prediction
        model, so it can run while the solve goes on in another thread (:class:`flnotes.MPC` with a time limit).
        """
        p, r = self.progress, self.repair
        if p is None:
            res = StepResult(None, "time_limit", message="time limit: cut off before the solve started")
            res.bound = -np.inf
        else:
            what = f"the incumbent ({p.source}) is returned" if p.V is not None else "no feasible plan yet"
            res = _step_result(self.pred, p.z0, p.f, p.c0, "time_limit", p.V, p.bound,
                               f"time limit: cut off while a solver ran on; {what}", p.stats, p.warm)
        res.info["cut_off"] = True
        if res.v is not None and res.info["incumbent"] is None:  # published before the search recorded it
            res.info["incumbent"] = p.source
        if res.v is None:
            res.info["repair_state"] = r if r is not None and p is not None and np.array_equal(r.z, p.z0) else None
        return res

    def reset(self) -> None:
        """Forget the steps encoded last and the kept LP bounds: the next solve is cold."""
        self.active_prev = ()
        if self.cache is not None:
            self.cache.clear()

    def warm_up(self, time_limit: float = 0.05) -> None:
        """Solve once at the centre of the domain box (reference zero, at most ``time_limit`` seconds per solve) and
        forget it.

        A process's first solve pays one-off costs that later ones do not: on the pendulum of the benchmark the first
        program assembly took 62 ms in Python's type checks of the sparse matrices alone (cached after it), and the
        first DAQP call 70 ms, more than its sampling time. So the whole step is solved once, then a program with
        the last predicted step encoded (at the centre the QP's optimum is often admissible: no branch and bound)
        by each solver a step may call. :class:`flnotes.MPC` calls this when it is given a time limit.
        """
        pred = self.pred
        z_c = 0.5 * (pred.z_lo + pred.z_hi)
        R = np.zeros((pred.N + 1, pred.nz))
        self.solve(z_c, R, time_limit=time_limit)
        try:
            prob = self.program(z_c, R, steps=[pred.N - 1])
        except EmptyBoxError:
            prob = None
        if prob is not None:
            relaxed = MIQP(prob.H, prob.c, prob.c0, prob.A, prob.rl, prob.ru, prob.lb, prob.ub,
                           np.zeros(prob.n, dtype=int))
            backends = [b for b in dict.fromkeys((pick_backend(self.opts.backend, int(prob.n_integer)), "daqp", "scip"))
                        if b in available_backends() and (b != "daqp" or prob.n_integer)]
            for backend in backends:
                make_solver(prob, backend, **self.solver_options.get(backend, {})).solve(time_limit=time_limit)
            make_solver(relaxed, _RELAX).solve(time_limit=time_limit)
        release_retired()
        self.reset()

    def program(self, z0: Array, z_ref: Array, steps=None, lo: Optional[Array] = None,
                hi: Optional[Array] = None) -> MIQP:
        """The assembled program at ``z0`` with the encoded ``steps`` (default: those the options need)."""
        pred = self.pred
        f, c0 = pred.linear(z0, z_ref)
        blo, bhi = pred.boxes(z0)
        nb = node_bounds(pred, self.opts, self.box, blo, bhi)
        if nb is None:
            raise EmptyBoxError("no input of some step's box meets |Phi_NN| <= u_max^eps")
        if steps is None:
            steps = needed_steps(nb, pred.u_eps, self.opts.encode) or []
        return compact_program(pred, z0, f, c0, nb, steps, pred.u_eps - self.margin,
                               eliminate_stable=self.opts.eliminate_stable, lo=lo, hi=hi, order=self.order)

    def solve(self, z0: Array, z_ref: Array, incumbent: Optional[Array] = None, time_limit: Optional[float] = None,
              gap: float = 1e-6, node_limit: Optional[int] = None,
              safety_deadline: Optional[float] = None) -> StepResult:
        """Solve at the measured ``z0`` for ``z_ref`` (N_p + 1, n_z); ``incumbent`` is a plan ``V`` known feasible.

        ``node_limit`` (a work budget, with ``time_limit=None``): branch-and-bound nodes in all of this solve's
        rounds (each solver call gets what is left, ``Solver.solve(node_limit=...)``); no decision of the solve then
        reads the clock, so the same state gives the same status and plan on every run, machine and load. The
        solve stops only at the budget, or when :meth:`stop` is called (the caller's wall-clock safety net); a solver
        call also stops at ``safety_deadline`` (a :func:`time.perf_counter` value, the caller's time limit), so that a
        call the caller no longer waits for does not run on: a result it decided is flagged ``info["safety_net"]``.

        Returns a :class:`flnotes.StepResult` with the plan (``v`` is ``None`` when there is none:
        infeasible, time limit without a plan, solver failure); the caller applies its fallback then. At a
        time limit the plan is the best feasible one found and ``bound`` is the optimum of the QP without
        the network (a lower bound on eq. MPC_form_miqp), so ``gap`` is an honest optimality gap.
        """
        pred, o = self.pred, self.opts
        t0 = time.perf_counter()
        N, m = pred.N, pred.m
        f, c0 = pred.linear(z0, z_ref)
        self.margin = 0.0  # per solve: a margin kept from another state would shrink this state's program
        ranges: dict = {}

        def first_at(u_in: Array) -> Optional[tuple[Array, Array]]:
            """Step 0's exact range of inputs at the bound ``u_in`` (:data:`FIRST_RANGE`), once per bound."""
            key = float(np.max(u_in))
            if key not in ranges:
                ranges[key] = pred.first_range(z0, u_in) if _first_range_on() else None
            return ranges[key]

        def build(nb_: NodeBounds, enc_, u_in: Array, lo_=None, hi_=None) -> tuple[MIQP, list]:
            """The program of a round and the steps whose neurons it encodes (step 0 as its exact range when
            :data:`FIRST_RANGE` and one input give one)."""
            fr = first_at(u_in)
            nn = [k for k in enc_ if k != 0] if fr is not None else list(enc_)
            st["first_range"] = fr is not None  # step 0's constraint is in the program as bounds
            return compact_program(pred, z0, f, c0, nb_, nn, u_in, eliminate_stable=o.eliminate_stable, lo=lo_,
                                   hi=hi_, order=self.order, first=fr), nn
        st = dict(nodes=0, rounds=0, tightened=0, n_bin=0, steps=(), lp_rounds=0, backend=o.backend)
        if node_limit is not None and time_limit is not None:
            raise ValueError("give the solve a node_limit (work budget) or a time_limit, not both")
        work = node_limit is not None

        def done(status: str, V: Optional[Array], bound: float, msg: str, screened: bool = False) -> StepResult:
            if self._stop.is_set() and threading.get_ident() != self._holder:  # stopped by a caller that answers
                if not self._answered.is_set():  # meanwhile in another thread: the result after its answer, and
                    self._answered.wait(HOLD_MAX_S)  # after its return (the answering thread takes the lock first)
                    time.sleep(ANSWER_GRACE_S)
            if work and status == "time_limit" and msg.startswith("time limit"):  # say which limit stopped it
                msg = ("wall-clock safety net" if self._stop.is_set() or st.get("safety") else
                       f"work limit ({node_limit} nodes)") + msg[len("time limit"):]
            res = _step_result(pred, z0, f, c0, status, V, bound, msg, st, inc_from_warm, screened)
            if work:
                res.info["safety_net"] = bool(st.get("safety")) or self._stop.is_set()
            res.solve_time = time.perf_counter() - t0
            return res

        def publish(V: Optional[Array], J: float, bound: float, source: Optional[str]) -> None:
            self.progress = Progress(z0, f, c0, V, J, bound, source, inc_from_warm, dict(st))

        inc_V, inc_J, inc_from_warm = None, np.inf, False
        self.progress = self.repair = None
        if o.warm_start and incumbent is not None and pred.feasible(z0, incumbent):
            inc_V, inc_J, inc_from_warm = np.asarray(incumbent, float).reshape(-1), pred.cost(incumbent, f, c0), True
        publish(inc_V, inc_J, -np.inf, "warm start" if inc_V is not None else None)
        # the QP without the network: screening, the first level-set center, the first active steps
        V_c, J_c = None, -np.inf
        if o.screening or o.bounds == "levelset" or o.lazy or o.repair:
            V_q, fq, flag = pred.relaxation(f, z0)
            if V_q is None:
                if flag == -1:
                    return done("infeasible", None, np.inf, "the QP without the network constraint is infeasible "
                                "(the state box or terminal set cannot be kept)" if pred.enclosure is None else
                                "the relaxation is infeasible: no plan keeps the state box and terminal set with every "
                                "step in the network's affine enclosure's slab (which holds every admissible input)")
            else:
                V_c, J_c = V_q, fq + c0
                if o.screening and pred.feasible(z0, V_q):
                    self.active_prev = ()
                    return done("optimal", V_q, J_c, "screened: the QP optimum meets the network constraint", True)
                fr = first_at(pred.u_eps)
                if fr is not None and (np.any(V_q[:m] < fr[0]) or np.any(V_q[:m] > fr[1])):
                    # its v(0) breaks the bound: the relaxation with v(0) in its exact range (a tighter one)
                    V_q, fq, flag = pred.relaxation(f, z0, fr)
                    if V_q is not None:
                        V_c, J_c = V_q, fq + c0
                    elif flag == -1:
                        return done("infeasible", None, np.inf, "the relaxation is infeasible with the first input in "
                                    f"its exact admissible range [{fr[0][0]:.9g}, {fr[1][0]:.9g}] (|Phi_NN(z0, v)| <= "
                                    "u_max^eps): no plan keeps the state box and terminal set")
        incumbent_from = "warm start" if inc_V is not None else None
        if o.repair and V_c is not None:
            inc_V, inc_J, incumbent_from, st["region"], st["repair_failed"] = self._improve(
                z0, f, c0, V_c, inc_V, inc_J, incumbent_from, None if time_limit is None else t0 + time_limit, st)
        st["incumbent"] = incumbent_from
        publish(inc_V, inc_J, J_c, incumbent_from)

        def stopped(bound: float) -> StepResult:  # out of time (or stopped) between rounds: the incumbent so far
            return done("time_limit", inc_V, bound, "time limit: " + (
                f"the incumbent ({incumbent_from}) is returned" if inc_V is not None else "no feasible plan"))

        if self._stop.is_set():  # the caller has answered from what is published: the node bounds would be wasted
            return stopped(J_c)
        try:
            lo_h, hi_h = pred.boxes(z0, first_at(pred.u_eps))
        except EmptyBoxError as exc:
            return done("infeasible", None, np.inf, f"infeasible: {exc}")
        active = set(pred.violated(z0, V_c).tolist()) if V_c is not None else set(range(N))
        active |= {k - 1 for k in self.active_prev if k >= 1}
        if inc_V is not None and NEAR_ACTIVE is not None:  # the steps where the incumbent is near the bound
            active |= set(pred.near_bound(z0, inc_V, _near_active()).tolist())
        level = o.bounds == "levelset" and V_c is not None

        def remaining() -> Optional[float]:
            return None if time_limit is None else max(time_limit - (time.perf_counter() - t0), 1e-3)

        def nodes_left() -> Optional[int]:  # of the work budget (None: no budget)
            return None if node_limit is None else int(node_limit) - int(st["nodes"])

        def out_of_time(need: float = SOLVE_MIN_LEFT) -> bool:  # less than ``need`` seconds of the time limit left,
            # or the work budget spent (or the caller answered at a cut-off and asked this solve to stop: :meth:`stop`)
            if work:
                return nodes_left() <= 0 or self._stop.is_set()
            return time_limit is not None and (time_limit - (time.perf_counter() - t0) < need or self._stop.is_set())

        deadline = None if time_limit is None else t0 + time_limit  # no LP of the node bounds starts after it
        if work:
            deadline = safety_deadline  # under a budget only the safety net stops the LPs (flagged where it does)

        delta = max(1e-3 * max(1.0, abs(J_c)), 1e-4) if level else np.inf
        if level and o.first_level == "incumbent":
            # the first level set holds the incumbent, hence the optimum; without an incumbent (no warm start, the
            # repaired relaxation rejected: most often an infeasible program) a level twice the relaxation's cost
            delta = max(delta, inc_J - J_c) if np.isfinite(inc_J) else FIRST_LEVEL_NO_INCUMBENT * max(1.0, abs(J_c))
        # time limit: a lower bound of eq. (MPC_form_miqp) for the gap (J_c; each round that ends without a plan
        # cheaper than its level J_up proves that nothing cheaper exists)
        lb, J_up, n_round = J_c, -np.inf, 0
        lo_f = hi_f = None
        # once the rows are tightened (self.margin > 0) a verdict holds for the tightened program only; lb_free is
        # the lower bound the untightened solve gave (on the plans cheaper than its round's level)
        lb_free = -np.inf

        def unproven(J: float) -> bool:  # a verdict of the tightened program that the untightened bound cannot back
            return self.margin > 0.0 and not J <= lb_free + max(gap, TIGHTENED_GAP) * max(1.0, abs(J))

        def back(J: float, V: Optional[Array], round_: tuple) -> Optional[tuple[Optional[Array], float]]:
            """A verdict of the tightened rows (a plan ``V`` of cost ``J``; ``J = inf``, ``V = None``: no plan),
            backed to the gap by the untightened program: the plan and cost to report, or ``None`` (not proven).

            The lower bound ``lb_free`` comes from the round where the rows were first tightened; a later round (a
            higher level, or the whole program) proves more. So where that bound falls short, SCIP (1e-9) solves
            the deciding round's program with the untightened bound (``round_ = (nb, enc, lo, hi, J_up)``, ``lo``
            and ``hi`` ``None`` for the whole program): a relaxation of the tightened one (``V`` is a warm start)
            that holds every plan cheaper than ``J_up``. Its bound, capped at ``J_up``, is a lower bound of eq.
            (MPC_form_miqp) (``J_up`` when it is infeasible). Where its own plan passes the forward-pass check, costs
            at most ``J_up`` and lies within the gap of its bound, that plan is the optimum and is returned."""
            nonlocal lb_free
            if np.isfinite(J) and not unproven(J):
                return V, J
            if out_of_time(VERIFY_MIN_LEFT) or (work and nodes_left() <= 0):
                return None
            nb_r, enc_r, lo_r, hi_r, J_up_r = round_
            free, nn_r = build(nb_r, enc_r, pred.u_eps, lo_r, hi_r)
            w0 = (plan_vector(pred, z0, V, nb_r, nn_r, free, o.eliminate_stable, self.order)
                  if V is not None else None)
            solver = make_solver(free, "scip", **self.solver_options.get("scip", {}))
            if not work:
                limit = remaining()
            else:  # under a work budget the caller's clock is a safety net only
                limit = None if safety_deadline is None else max(safety_deadline - time.perf_counter(), 1e-3)
            r = solver.solve(warm_start=w0, time_limit=limit, gap=gap, node_limit=nodes_left())
            if time_limit is not None or work:
                retire(solver)
            st["nodes"] += int(r.nodes)
            st["scip_programs"] = st.get("scip_programs", 0) + 1
            s = _status(r.status)
            if s == "infeasible":
                b = np.inf
            elif s in ("optimal", "time_limit") and r.bound is not None and np.isfinite(r.bound):
                b = float(r.bound)
            else:
                return None
            lb_free = max(lb_free, min(b, J_up_r))
            tol = max(gap, TIGHTENED_GAP)
            if s == "optimal" and r.w is not None:
                V2 = np.asarray(r.w[: N * m], float)
                J2 = pred.cost(V2, f, c0)
                if (pred.feasible(z0, V2) and J2 <= J and J2 <= J_up_r + 1e-9 * max(1.0, abs(J_up_r))
                        and J2 <= lb_free + tol * max(1.0, abs(J2))):
                    st["backed"] = BACKED_PLAN
                    return V2, J2
            if not np.isfinite(J):  # "no plan": only the untightened program's infeasibility backs it
                if s == "infeasible":
                    st["backed"] = BACKED
                    return None, np.inf
                return None
            if unproven(J):
                return None
            st["backed"] = BACKED
            return V, J

        def not_proven(what: str) -> StepResult:  # the step's plan is dropped (the controller's fallback applies)
            return done("error", None, -np.inf,
                        f"not proven: {what} with u_max^eps tightened by {self.margin:.1e} (a solver's tolerance let "
                        f"its point through), while the untightened program's lower bound is {lb_free:.9g}: its "
                        "optimum lies within the solvers' tolerance of the network bound (e.g. on a ridge of the "
                        "network)")
        while True:
            if time_limit is not None or work:
                if n_round and self.margin == 0.0:
                    lb = max(lb, J_up)
                n_round += 1
                publish(inc_V, inc_J, lb, incumbent_from)
                if out_of_time():
                    return stopped(lb)
            lo, hi, J_up, full, override = lo_h, hi_h, np.inf, True, None
            lp_done = None  # lp="auto" on a large round: the steps whose bounds are LP-tightened
            if level:
                J_up = min(inc_J, J_c + delta)
                full = not np.isfinite(J_up) or delta > 1e12 * max(1.0, abs(J_c))
                if full:  # the level set no longer restricts anything: the whole program
                    J_up, delta = np.inf, np.inf
                else:
                    lo, hi = pred.level_boxes(z0, V_c, max(J_up - J_c, 0.0), lo_h, hi_h)
                    empty = bool(np.any(lo > hi + 1e-12))
                    hi = np.maximum(hi, lo)
                    if lo_f is None:  # the boxes without the ellipsoid (the enclosure's slab cuts them too)
                        lo_f, hi_f = pred.level_boxes(z0, V_c, np.inf, lo_h, hi_h)
                    full = bool(np.all(lo <= lo_f) and np.all(hi >= hi_f))  # the level set cut nothing
                    if full:  # the round is the whole program: no level below the incumbent's cost is proven
                        J_up = inc_J
                    try:
                        if not empty and o.lp == "auto":  # FBBT first; LP only when it leaves a large program
                            override = node_bounds(pred, o, self.box, lo, hi, use_lp=False)
                            st_f = needed_steps(override, pred.u_eps, o.encode)
                            enc_f = (sorted(set(st_f) & active) if o.lazy else st_f) if st_f is not None else []
                            if st_f is not None and unstable_count(override, enc_f) > LP_AUTO_BINARIES:
                                empty, lo, hi, override = self._lp_level(lo, hi, enc_f, deadline)
                                lp_done = set(enc_f)
                                st["lp_rounds"] += 1
                        elif not empty and o.lp:
                            empty, lo, hi, override = self._lp_level(lo, hi, None, deadline)
                            st["lp_rounds"] += 1
                    except DeadlineReached:
                        st["safety"] = work
                        return done("time_limit", inc_V, lb, "time limit during the LP bounds of a level-set round")
                    if empty:  # nothing cheaper than J_up
                        if full and inc_V is None:  # the boxes of the whole program hold no admissible plan
                            return done("infeasible", None, np.inf, "no admissible plan in the whole program's "
                                        "boxes (their node bounds or their relaxation)")
                        if J_up >= inc_J:
                            return done("optimal", inc_V, inc_J,
                                        f"the incumbent is optimal ({incumbent_from}; level set empty)")
                        delta *= 4.0
                        continue
            try:
                nb = override if override is not None else node_bounds(pred, o, self.box, lo, hi, deadline=deadline,
                                                                        cache=self.cache, atlas=self.atlas)
            except DeadlineReached:
                st["safety"] = work
                return done("time_limit", inc_V, lb, "time limit during the LP bounds of a round")
            if out_of_time():  # the node bounds (an LP each under lp) took the rest of the time
                return done("time_limit", inc_V, lb, "time limit after the node bounds of a round")
            steps = needed_steps(nb, pred.u_eps, o.encode) if nb is not None else None
            if steps is None:
                if full and inc_V is None:
                    return done("infeasible", None, np.inf, "no admissible plan: the node bounds exclude "
                                "|Phi_NN| <= u_max^eps over a step's reachable box")
                if J_up >= inc_J or full:
                    return done("optimal", inc_V, inc_J,
                                f"the incumbent is optimal ({incumbent_from}; no admissible output)")
                delta *= 4.0
                continue
            restrict = level and not full
            enc = sorted(set(steps) & active) if o.lazy else list(steps)
            while True:  # constraint generation (one round without lazy)
                if out_of_time():  # before building anything (a tightened program comes back here)
                    return done("time_limit", inc_V, lb, "time limit before the round's program was built")
                prob, nn = build(nb, enc, pred.u_eps - self.margin, lo if restrict else None,
                                 hi if restrict else None)
                shown = set(enc) | ({0} if st["first_range"] else set())  # step 0 as bounds counts as encoded
                st["n_bin"], st["steps"] = int(prob.n_integer), tuple(sorted(shown))
                st["backend"] = backend = ("scip" if work and o.backend == "auto" and prob.n_integer else
                                           pick_backend(o.backend, int(prob.n_integer), inc_V is not None))  # DAQP: no node limit
                if backend == "scip" and out_of_time(VERIFY_MIN_LEFT):  # a SCIP model takes 10 ms and more to build
                    return done("time_limit", inc_V, lb, "time limit: too little time left to build a SCIP model")
                solver = make_solver(prob, backend, **self.solver_options.get(backend, {}))
                w0 = (plan_vector(pred, z0, inc_V, nb, nn, prob, o.eliminate_stable, self.order)
                      if inc_V is not None else None)
                if out_of_time():  # no solver starts without time left (it would answer after the limit)
                    return done("time_limit", inc_V, lb, "time limit before the round's solver started")
                safety = (None if not work or safety_deadline is None else
                          max(safety_deadline - time.perf_counter(), 1e-3))  # a safety net only (see above)
                res = solver.solve(warm_start=w0, time_limit=remaining() if not work else safety, gap=gap,
                                   node_limit=nodes_left())
                if work and safety is not None and _status(res.status) == "time_limit" and "timelimit" in res.message:
                    st["safety"] = True  # the clock stopped this call, not the budget
                if (time_limit is not None or work) and backend != "daqp":
                    retire(solver)  # a SCIP or HiGHS model is freed at the next step, not inside this one
                st["nodes"] += int(res.nodes)
                st["rounds"] += 1
                st["scip_programs"] = st.get("scip_programs", 0) + (backend == "scip")
                publish(inc_V, inc_J, lb, incumbent_from)
                status = _status(res.status)
                if status != "optimal":
                    break
                viol = set(pred.violated(z0, res.w[: N * m]).tolist())
                where = (nb, nn, prob, o.eliminate_stable, self.order)
                exact = (self._region_exact(z0, f, c0, res, gap, where)
                         if viol & set(enc) and self.margin == 0.0 else None)
                if exact is not None:  # the same plan's linear region holds a point within the gap that meets the bound
                    res = exact
                    viol = set(pred.violated(z0, res.w[: N * m]).tolist())
                elif viol & set(enc) and self.margin == 0.0 and backend != "scip":
                    # DAQP's point meets the rows to its tolerance (1e-6), which bounds the program's optimum from
                    # below only loosely: SCIP (1e-9) solves the same program before any row is tightened
                    if out_of_time(VERIFY_MIN_LEFT):
                        return done("time_limit", inc_V, lb, "time limit: too little time left to solve again with "
                                    f"scip a round whose {backend} optimum exceeds u_max^eps")
                    was = res.message
                    solver = make_solver(prob, "scip", **self.solver_options.get("scip", {}))
                    res = solver.solve(warm_start=w0, time_limit=remaining() if not work else safety, gap=gap,
                                       node_limit=nodes_left())
                    if time_limit is not None or work:
                        retire(solver)
                    res.message = (f"{res.message}; scip solved the round again: the {backend} optimum ({was}) "
                                   "exceeded u_max^eps")
                    backend = st["backend"] = "scip"
                    st["nodes"] += int(res.nodes)
                    st["scip_programs"] += 1
                    status = _status(res.status)
                    if status != "optimal":
                        break
                    viol = set(pred.violated(z0, res.w[: N * m]).tolist())
                    exact = self._region_exact(z0, f, c0, res, gap, where) if viol & set(enc) else None
                    if exact is not None:
                        res = exact
                        viol = set(pred.violated(z0, res.w[: N * m]).tolist())
                if viol & set(enc):
                    # an encoded step exceeds u_max^eps beyond round-off (the solver's tolerance let it through):
                    # tighten the bound in the rows and solve again
                    ex = pred.excess(z0, res.w[: N * m], enc)
                    if st["tightened"] >= 5:
                        return done("error", None, -np.inf, f"the optimum exceeds u_max^eps by {ex:.1e} after "
                                    f"tightening the rows by {self.margin:.1e}")
                    st["tightened"] += 1
                    if self.margin == 0.0:
                        b1 = float(res.bound) if res.bound is not None and np.isfinite(res.bound) else float(res.objective)
                        lb_free = min(b1, float(res.objective), J_up)
                    self.margin = next_margin(self.margin, ex, float(np.max(pred.u_eps)))
                    prob, nn = build(nb, enc, pred.u_eps - self.margin, lo if restrict else None,
                                     hi if restrict else None)
                    if out_of_time(TIGHTENED_QP_MIN_LEFT):
                        return done("time_limit", inc_V, lb, "time limit: too little time left to re-solve the "
                                    "round under the tightened bound")
                    polished = self._polish(prob, res, gap, remaining())
                    if polished is None or set(pred.violated(z0, polished.w[: N * m]).tolist()) & set(enc):
                        continue  # the tightened program solved from scratch
                    res = polished
                    viol = set(pred.violated(z0, res.w[: N * m]).tolist())
                new = sorted(viol - set(enc))
                if not new or not o.lazy:
                    break
                if (time_limit is not None and time.perf_counter() - t0 > time_limit) or (work and out_of_time()):
                    # out of time between constraint-generation rounds: this round's optimum is a lower bound
                    # of the program restricted to the level set (fewer steps encoded: a relaxation)
                    lb_r = max(lb, min(float(res.objective), J_up)) if self.margin == 0.0 else lb
                    return done("time_limit", inc_V, lb_r, "time limit between constraint-generation rounds")
                if lp_done is not None and set(new) - lp_done:
                    try:
                        nb = self._lp_steps(nb, lo, hi, sorted(set(new) - lp_done), deadline)
                    except DeadlineReached:
                        st["safety"] = work
                        return done("time_limit", inc_V, lb, "time limit during the LP bounds of added steps")
                    lp_done |= set(new)
                enc = sorted(set(enc) | set(new))
                active |= set(new)
            if status == "optimal":
                V = res.w[: N * m]
                J = pred.cost(V, f, c0)
                if not pred.feasible(z0, V):
                    return done("error", None, -np.inf, "the program's optimum fails the forward-pass check")
                self.active_prev = tuple(enc)
                if full or J <= J_up + 1e-9 * max(1.0, abs(J_up)):
                    got = back(J, V, (nb, enc, lo if restrict else None, hi if restrict else None, J_up))
                    if got is None:
                        return not_proven(f"an optimum of cost {J:.9g}")
                    if got[0] is not V:  # the untightened round's own plan
                        return done("optimal", got[0], lb_free, f"{res.backend}: {res.message}" + st["backed"])
                    bound = res.bound if np.isfinite(res.bound) else J
                    if self.margin > 0.0:
                        bound = min(bound, lb_free)
                    return done("optimal", V, bound, f"{res.backend}: {res.message}" + st.get("backed", ""))
                if J < inc_J:
                    inc_V, inc_J, incumbent_from = V, J, "an earlier round"
                    publish(inc_V, inc_J, lb, incumbent_from)
            elif status == "infeasible":
                if full and inc_V is None:
                    said = res.message if "proven by" in res.message else f"{res.backend}: {res.message}"
                    if self.margin > 0.0:
                        got = back(np.inf, None, (nb, enc, None, None, np.inf))
                        if got is None:
                            return not_proven("no plan")
                        if got[0] is not None:  # the untightened program's plan passes the check
                            return done("optimal", got[0], lb_free, f"the tightened program is infeasible ({said})"
                                        + st["backed"])
                    return done("infeasible", None, np.inf, f"the program is infeasible ({said})"
                                + st.get("backed", ""))
            elif status == "time_limit":
                # the solver's bound holds for the program it solved: a relaxation of eq. (MPC_form_miqp) restricted
                # to the plans cheaper than J_up (constraint generation encodes fewer steps), unless the rows were
                # tightened by a solver margin
                sb = float(res.bound) if res.bound is not None and np.isfinite(res.bound) else -np.inf
                lb_r = max(lb, min(sb, J_up)) if self.margin == 0.0 else lb
                cand = res.w[: N * m] if res.w is not None else None
                if cand is not None and pred.feasible(z0, cand) and pred.cost(cand, f, c0) < inc_J:
                    return done("time_limit", cand, lb_r, f"time limit: {res.message}")
                return done("time_limit", inc_V, lb_r, f"time limit: {res.message}")
            else:
                return done("error", None, -np.inf, f"{res.backend}: {res.status} {res.message}")
            if J_up >= inc_J or full:  # nothing below J_up in the restricted program
                if inc_V is not None and self.margin > 0.0:
                    got = back(inc_J, inc_V, (nb, enc, lo if restrict else None, hi if restrict else None, J_up))
                    if got is None:
                        return not_proven(f"nothing cheaper than the incumbent's {inc_J:.9g}")
                    if got[0] is not inc_V:
                        return done("optimal", got[0], lb_free, "the untightened round's plan is optimal"
                                    + st["backed"])
                return done("optimal", inc_V, inc_J,
                            f"the incumbent is optimal ({incumbent_from}; nothing cheaper)" + st.get("backed", ""))
            delta *= 4.0

    def _improve(self, z0: Array, f: Array, c0: float, V_c: Array, inc_V: Optional[Array], inc_J: float,
                 inc_from: Optional[str], deadline: Optional[float] = None, st: Optional[dict] = None
                 ) -> tuple[Optional[Array], float, Optional[str], bool, bool]:
        """The first incumbent of ``repair``: the cheaper of the warm start and the relaxation's optimum ``V_c``
        repaired along the QP (:func:`flnotes.mpc.fallback.qp_repair`, stopped by :meth:`stop` or at ``stop_at``); when neither
        passes and ``bang_bang`` is on, the cheapest one-switch plan at the input bounds
        (:func:`flnotes.mpc.bang_bang.bang_bang_incumbent`, given up at the ``deadline``, a ``time.perf_counter()``
        value); then optimized over its linear region and its neighbours (:func:`flnotes.mpc.region.region_qp`, no
        move after :meth:`stop` or ``stop_at``). Each candidate counts only if it passes the forward-pass check. Returns ``(V, J,
        where it came from, whether the region QP made it cheaper, whether the repaired plan failed the check, not
        cut short by :meth:`stop` or ``stop_at``)``;
        the one-switch search's time (s) goes to ``st["bang_bang_s"]``."""
        pred, o = self.pred, self.opts
        _, V_r = qp_repair(pred, z0, f, V_c, deadline=self.stop_at, stop=self._stop, publish=self._publish_repair)
        passed = pred.feasible(z0, V_r)
        failed = not passed and not self._stopped()  # not cut short by the caller's cut-off
        if passed:
            J_r = pred.cost(V_r, f, c0)
            if J_r < inc_J:
                inc_V, inc_J, inc_from = V_r.reshape(-1), J_r, "repaired relaxation"
                self._offer(inc_V, inc_J, inc_from)  # an answer at the cut-off has it before the moves below
        if inc_V is None and (o.bang_bang if o.bang_bang is not None else pred.m == 1):
            t_bb = time.perf_counter()
            found = bang_bang_incumbent(pred, z0, f, c0, deadline)
            if st is not None:
                st["bang_bang_s"] = time.perf_counter() - t_bb
            if found is not None:
                inc_V, inc_J, inc_from = found[0], found[1], "one-switch plan"
                self._offer(inc_V, inc_J, inc_from)
        if inc_V is None:
            return None, np.inf, inc_from, False, failed
        if self._stopped():
            return inc_V, inc_J, inc_from, False, failed
        V_p = region_qp(pred, z0, f, inc_V, REGION_MOVES, stop=self._stop)
        if V_p is not None and pred.feasible(z0, V_p):
            J_p = pred.cost(V_p, f, c0)
            if J_p < inc_J:
                return V_p, J_p, inc_from, True, failed
        return inc_V, inc_J, inc_from, False, failed

    def _offer(self, V: Array, J: float, source: str) -> None:
        """Publish ``V`` (cost ``J``, passed the forward-pass check) as the running solve's incumbent in
        :attr:`progress` when it is cheaper than the one there: an answer at the cut-off has it at once."""
        p = self.progress
        if p is not None and J < p.J:
            self.progress = replace(p, V=np.asarray(V, float).copy(), J=float(J), source=source,
                                    stats={**p.stats, "incumbent": source})

    def _publish_repair(self, state: RepairState) -> None:
        """Keep the first incumbent's build as far as it got (:attr:`repair`, replaced whole)."""
        self.repair = state

    def _lp_steps(self, nb: NodeBounds, lo: Array, hi: Array, steps: list,
                  deadline: Optional[float] = None) -> NodeBounds:
        """``nb`` with the bounds of ``steps`` LP-tightened on the boxes ``lo, hi`` (steps that constraint
        generation adds to an LP-tightened round). When the LP finds a step's box without an admissible
        input, ``nb`` is kept: its FBBT bounds are valid, and the branch and bound proves the same."""
        t = node_bounds(self.pred, self.opts, self.box, lo, hi, steps=steps, use_lp=True, deadline=deadline,
                        cache=self.cache, atlas=self.atlas)
        if t is None:
            return nb
        L = [a.copy() for a in nb.L]
        U = [a.copy() for a in nb.U]
        for layer in range(len(L)):
            L[layer][steps] = np.maximum(L[layer][steps], t.L[layer][steps])
            U[layer][steps] = np.minimum(U[layer][steps], t.U[layer][steps])
        return NodeBounds(L, U, nb.out_L, nb.out_U, method=nb.method)

    def _region_exact(self, z0: Array, f: Array, c0: float, res, gap: float, where: tuple):
        """A solver's optimum that exceeds ``u_max^eps`` by its tolerance, made exact on its own linear region.

        The solver solved the program with its tolerance, which only enlarges the feasible set, so its objective
        ``J1`` is a lower bound on the program's optimum. The QP of the plan's linear region
        (:func:`flnotes.mpc.region.region_qp`: the same activation pattern, the output bound met to
        :data:`flnotes.mpc.region.REGION_MARGIN`) gives a plan that satisfies the program; when its cost is
        within ``max(gap, TIGHTENED_GAP)`` of ``J1`` it is optimal to that, and no row has to be tightened (the
        tolerance policy of :mod:`flnotes.solvers` then solves the program with ``u_max^eps`` less a margin, whose
        optimum is the optimum of that tightened program: on the Quad-1D at N_p = 15 a margin of 1.3e-7 moved one
        optimum by 3.7e-6). The regions tried are those of :func:`flnotes.mpc.region.region_exact`, the solver's binaries read
        by :func:`flnotes.mpc.program.program_pattern` (``where = (nb, steps, prob, eliminate_stable, order)`` as
        the program was built). Returns the result with that plan, or ``None``.
        """
        pred = self.pred
        Nm = pred.N * pred.m
        J1 = float(res.objective)
        V = region_exact(pred, z0, f, c0, res.w[:Nm], program_pattern(pred, z0, res.w, *where), J1, gap)
        if V is None:
            return None
        J2 = pred.cost(V, f, c0)
        out = copy.copy(res)
        out.w = np.r_[V, res.w[Nm:]]  # only the plan is read from here on
        out.objective, out.bound = J2, min(J1, float(res.bound)) if np.isfinite(res.bound) else J1
        out.message = f"{res.message}; made exact on its linear region (QP)"
        return out

    @staticmethod
    def _polish(prob: MIQP, res, gap: float, time_limit: Optional[float] = None):
        """The tightened program with the binaries of ``res`` fixed: a convex QP (HiGHS, exact active set).

        ``res`` solved the program before tightening; its objective is a lower bound on that program's optimum
        (the solver's tolerance only enlarged the feasible set). A point of the tightened program with the same
        activation pattern whose cost is within ``gap`` of that bound is therefore optimal to ``gap`` for the
        untightened program too, and it satisfies the bound with the margin: it replaces a second branch and
        bound. Returns the polished result (status ``"optimal"``, ``bound`` the earlier objective), or ``None``
        when the pattern is infeasible under the tightened bound, the cost moved by more than ``gap`` or
        ``time_limit`` stopped the QP.
        """
        ib = np.flatnonzero(prob.integrality == 1)
        lb, ub = prob.lb.copy(), prob.ub.copy()
        lb[ib] = ub[ib] = np.round(res.w[ib])
        r = make_solver(MIQP(prob.H, prob.c, prob.c0, prob.A, prob.rl, prob.ru, lb, ub,
                             np.zeros(prob.n, dtype=int)), _RELAX).solve(time_limit=time_limit)
        J1 = float(res.objective)
        if r.status != "optimal" or r.w is None or not r.objective <= J1 + gap * max(1.0, abs(J1)):
            return None
        r.bound, r.nodes = min(J1, float(r.objective)), int(res.nodes)
        r.message = f"{res.message}; re-solved with the pattern fixed under the tightened bound (HiGHS QP)"
        return r

    def _lp_level(self, lo: Array, hi: Array, lp_steps=None, deadline: Optional[float] = None
                  ) -> tuple[bool, Array, Array, Optional[NodeBounds]]:
        """LP bounds on the level-set boxes ``lo``, ``hi``, and FBBT again.

        ``lp=True``: every needed step is LP-tightened; ``lp="auto"`` (a large round): ``lp_steps``, the steps
        encoded first (:meth:`_lp_steps` adds the ones constraint generation brings in). No LP starts after
        ``deadline`` (:class:`flnotes.tightening.DeadlineReached`).
        Returns ``(empty, lo, hi, node bounds to use or None)``.

        The round keeps its level-set boxes. Earlier versions first solved the round's convex relaxation (the big-M
        program with the LP node bounds, HiGHS's QP, at most 500 iterations) and, where it cost more than the first
        QP, centred the level set's ellipsoid there. Measured with and without it (whole MPC steps, CPU time, two
        passes in alternating order, the same verdicts and optima): the MSD's cold states
        (:func:`flnotes.bench.msd_realtime.cold_states`, 40 of each of the seeds 1 and 2, 24 of seed 3) took 18 % and
        17 % less time without it; there the relaxation (about 500 variables and 1,100 rows) took 65 to 85 ms and
        ran into its cap in 10 of 18 rounds (seed 1), while the LP node bounds, read from the network's atlas, took
        about 1 ms. The book's Quad-1D loop took 8 % less at N_p = 15 and 5 % more at N_p = 20; the closed loops and
        20 cold states each of the five systems not in the book (:mod:`flnotes.studies.unseen`) were within 6 %
        either way, less than a setting's own two passes differed.
        """
        pred, o = self.pred, self.opts
        nb_lp = node_bounds(pred, o, self.box, lo, hi, steps=lp_steps, use_lp=True, deadline=deadline,
                            cache=self.cache, atlas=self.atlas)
        if nb_lp is None or needed_steps(nb_lp, pred.u_eps, o.encode) is None:
            return True, lo, hi, None
        nb_f = fbbt(pred.net, lo, hi)
        both = intersect(nb_f, nb_lp, method="lp")
        both.out_L, both.out_U = nb_f.out_L, nb_f.out_U  # FBBT's: valid on the whole box
        return False, lo, hi, both
