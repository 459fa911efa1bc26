"""The MPC of eq. (MPC_form_miqp) as a controller: :class:`MPC` validates, warm-starts, falls back, keeps history.

The solving is done below it: :class:`flnotes.mpc.engine.NetworkEngine` (the network constraint with the
levers), :class:`flnotes.mpc.reference.ReferenceProgram` (the cold SCIP reference) or
:class:`flnotes.mpc.linear.LinearModel` (the QP-based methods of the comparison), all on one
:class:`flnotes.mpc.prediction.Prediction`.
"""
from __future__ import annotations

import dataclasses
import threading
import time
import weakref
from contextlib import ExitStack
from typing import Callable, Optional

import numpy as np

from .._checks import (as_state, as_floats, as_pair, as_vector, box_in_domain, check_count, check_int, check_number,
                       horizon_reference, weight_matrix)
from ..bounds import fbbt
from ..atlas import BoundAtlas, check_atlas, shipped_atlas
from ..enclosure import AffineEnclosure, affine_enclosure, check_enclosure
from ..config import (answer_slice, hold_signals, machine_steal, major_faults, one_blas_thread, pause_for_step, pause_gc,
                      quick_thread_switch, release_signals, resume_after_step, resume_gc, set_back_slice,
                      slice_before_answer, thread_run_delay, yield_core)
from ..network import ReLUNet
from ..result import StepResult
from ..solvers import BOUND_TOL, TIGHTENED_GAP, next_margin, project_to_box, release_retired
from ..solvers.base import _require, check_options
from ..systems import FLSystem
from . import fallback
from .engine import NetworkEngine
from .linear import LinearModel
from .options import MPCOptions
from .prediction import DAQP_OPTIONS, Prediction
from .reference import ReferenceProgram

Array = np.ndarray


#: Share of :attr:`MPC.time_limit` that :attr:`MPC.reserve` keeps back from the engine at least.
RESERVE_SHARE = 0.2

#: Largest share of :attr:`MPC.time_limit` that what a controller has measured (its engine's lateness after its budget,
#: its longest fallback) may keep back from the engine or leave for the answer after the cut-off: whatever was
#: measured, the engine keeps at least ``1 - RESERVE_MAX_SHARE`` of the limit (less what the step spent before it).
RESERVE_MAX_SHARE = 0.4

#: Factor by which the measured lateness and fallback time shrink at every step (:attr:`MPC.reserve`): one slow
#: fallback (a cold state, a burst of load) is forgotten over tens of steps, not kept for good. :meth:`MPC.reset`
#: clears them.
RESERVE_DECAY = 0.9

#: Share of :attr:`MPC.time_limit` left after the fallback's deadline for the work after it (the checks of the plan,
#: the QP of its gap): the repairs of :func:`flnotes.mpc.fallback.fallback_plan` stop at ``time_limit`` less this.
FALLBACK_POST_SHARE = 0.1

#: Seconds left after the fallback's deadline at least, whatever the limit: the checks after the repairs (the
#: admissible first input, the plan's forward pass, the QP of its gap) take 1 to 3 ms on the systems of the benchmark,
#: twice that while the engine's thread still runs after a cut-off.
FALLBACK_POST_MIN_S = 0.006

#: Seconds the cut-off leaves for the answer at least (:meth:`MPC._engine_solve`): the thread that answers waits for
#: Python's interpreter lock up to one switch interval (5 ms by default) while the solve runs Python code, then
#: checks the plan (1 to 3 ms). Measured on the Quad-1D at N_p = 20 with no reserve share: the answers at a cut-off
#: 4 to 6 ms before t_s came up to 1.7 ms after it.
CUT_OFF_MIN_S = 0.01

#: Branch-and-bound nodes per second of ``time_limit`` that ``work_limit="auto"`` gives a step (at least one node):
#: ``node_limit = max(1, floor(NODES_PER_SECOND * time_limit))``, a constant, so that the budget is the same on every
#: machine. Measured (SCIP back-end without a limit, 12 cold states of the Quad-1D at N_p = 10 and at N_p = 20, on a
#: loaded two-core machine): 4 and 7 nodes per CPU second of the whole step, most programs closing at the root node;
#: the round 10 gives the root node alone at t_s = 0.1 s and two nodes at 0.2 s. ``python -m flnotes.bench deadline``
#: counts the steps where the budget outlasted the limit (the safety net's hits). Measured again on an idle machine
#: when SCIP's lean profile stopped restarting the root (:data:`flnotes.solvers.scip.LEAN_RESTARTS`; 12 cold states
#: of :func:`flnotes.bench.exactness.mpc_cases`, seed 2): 19 nodes per CPU second at both horizons with restarts,
#: 20 and 44 without (a restart's root counted as a node; without restarts SCIP branches more, on cheaper nodes).
#: The constant stays: a node of the budget now stands for less CPU time of a step (50 and 22 ms against 54 and 53 ms).
NODES_PER_SECOND = 10.0

#: The largest node budget a step takes (the solvers' node-limit parameters are C integers).
MAX_WORK_LIMIT = 2**31 - 1
#: The values of :class:`MPC`'s ``work_limit`` besides a positive number of nodes.
WORK_LIMITS = (None, "auto")


def sine_reference(amplitude: float = 1.5, omega: float = 1.0, n_z: int = 3, phase: float = 0.0
                   ) -> Callable[[Array], Array]:
    """A smooth reference ``x_ref(t) = amplitude sin(omega t + phase)`` with consistent derivatives.

    Returns a vectorized ``t -> z_ref(t)``: times of shape (T,) give (T, n_z)
    with column ``i`` the ``i``-th time derivative of ``x_ref``, as the
    Brunovsky state ``z = [x, x', x'', ...]`` requires (the book's reference, Sec. IV-B: ``1.5 sin t``).
    """
    n_z = check_int(n_z, "n_z", 1, "the state's dimension: x_ref and its derivatives")
    amplitude = check_number(amplitude, "amplitude", "of the sine", low=-np.inf)
    omega = check_number(omega, "omega", "the angular frequency in rad/s", low=-np.inf)
    phase = check_number(phase, "phase", "in rad", low=-np.inf)

    def z_ref(t: Array) -> Array:
        t = np.atleast_1d(as_floats(t, "t"))
        cols = [amplitude * omega**i * np.sin(omega * t + phase + i * np.pi / 2) for i in range(n_z)]
        return np.stack(cols, axis=-1)

    z_ref.__doc__ = f"x_ref(t) = {amplitude} sin({omega} t + {phase}) and its derivatives, shape (T, {n_z})"
    return z_ref


def _per_backend(backend: str, used: tuple, solver_options: Optional[dict]) -> dict:
    """``solver_options`` as ``{back-end: options}`` for the solvers the engine may call (DAQP gets
    :data:`DAQP_OPTIONS` under the given ones)."""
    if solver_options is not None and not isinstance(solver_options, dict):
        raise ValueError(f"solver_options must be a dict of back-end options (with backend='auto' one dict per "
                         f"back-end, e.g. {{'daqp': {{...}}, 'scip': {{...}}}}), got {solver_options!r}")
    given = dict(solver_options or {})
    if backend == "auto" and given:
        bad = sorted(k for k, v in given.items() if k not in used or not isinstance(v, dict))
        if bad:
            raise ValueError(f"backend='auto' calls DAQP or SCIP per program: give solver_options per back-end, "
                             f"e.g. {{'daqp': {{...}}, 'scip': {{...}}}} (got the keys {sorted(given)}), or choose "
                             f"backend='daqp' or 'scip' for flat options")
        per = {b: dict(given.get(b, {})) for b in used}
    else:
        per = {b: dict(given) for b in used}
    if "daqp" in per:  # DAQP_OPTIONS under the given ones (their params merged: a given setting wins)
        given_daqp = per["daqp"]
        per["daqp"] = dict(DAQP_OPTIONS, **given_daqp)
        if isinstance(given_daqp.get("params"), dict):
            per["daqp"]["params"] = dict(DAQP_OPTIONS["params"], **given_daqp["params"])
    for b, opts in per.items():  # now, not at the first program that reaches the back-end
        try:
            check_options(b, opts)
        except ValueError as exc:
            raise ValueError(f"solver_options for {b}: {exc}") from None
    return per


def _wait_for(worker: threading.Thread, done: threading.Event, timeout: Optional[float] = None) -> bool:
    """Wait for the solve of ``worker`` to end (its ``done`` is set as its last action): ``True`` when it has.

    Waits on the event, not with :meth:`threading.Thread.join`: an interrupt (Ctrl-C) during ``join`` on Python 3.11
    can mark a thread that still runs as stopped (its later ``join`` then returns at once, and a process leaving
    while the solver's C++ code runs was aborted). ``join`` only follows the event, for the few lines after it."""
    if worker.ident is None:  # never started (interrupted before): nothing to wait for
        return True
    if not done.wait(timeout):
        return False
    worker.join()
    return True


def _thread_cpu(worker: threading.Thread, box: dict) -> float:
    """The CPU time the engine's thread of :meth:`MPC._engine_solve` has used so far, read from the answering thread.

    A new thread's CPU clock starts at zero (:func:`time.pthread_getcpuclockid`). The thread's own final figure
    when it has ended; NaN where the platform cannot read another thread's clock.
    """
    if "cpu" in box:
        return float(box["cpu"])
    try:
        return time.clock_gettime(time.pthread_getcpuclockid(worker.ident))
    except (AttributeError, OSError):   # no such clock here, or the thread ended between the two reads
        return float(box.get("cpu", float("nan")))


class _HeldSettings:
    """The process-wide settings (an :class:`~contextlib.ExitStack` of :func:`flnotes.config.one_blas_thread` and
    :func:`flnotes.config.quick_thread_switch`) that a step answered at its cut-off keeps while its solve runs on in
    ``worker``; apart from :class:`MPC` so that a finalizer can set them back without keeping the controller alive.
    :meth:`release` waits for the solve first and must run in the thread that stepped the controller (OpenBLAS ignores
    a thread count raised from another thread): the solve's thread does not refer to the controller, so a controller
    dropped by its last reference is freed in the thread that drops it."""

    def __init__(self) -> None:
        self.stack: Optional[ExitStack] = None
        self.worker: Optional[threading.Thread] = None
        self.done: Optional[threading.Event] = None

    def keep(self, stack: ExitStack, worker: threading.Thread, done: threading.Event) -> None:
        if self.stack is not None:  # never two at once: the next step waits for the solve first
            raise RuntimeError("a step kept the process settings while an earlier step's were still kept")
        self.stack, self.worker, self.done = stack, worker, done

    def release(self) -> None:
        """Wait for the solve, then set the settings back; an interrupt while it waits leaves them kept (for the
        next call)."""
        if self.stack is None:
            return
        worker = self.worker
        if worker is not None and worker is not threading.current_thread():
            _wait_for(worker, self.done)  # the solve keeps them until it ends (it was asked to stop at its cut-off)
        held = hold_signals()  # Ctrl-C (any handled signal) waits for the settings to come back (config.hold_signals)
        try:
            stack, self.stack, self.worker, self.done = self.stack, None, None, None
            stack.close()
        finally:
            release_signals(held)

    def finalize(self) -> None:
        """:meth:`release` for a controller that is gone, which nobody can release later: an interrupt while it
        waits for the solve is raised only once the settings are back."""
        interrupt = None
        while self.stack is not None:
            try:
                self.release()
            except KeyboardInterrupt as exc:
                interrupt = exc
        if interrupt is not None:
            raise interrupt


class MPC:
    """The MPC of eq. (MPC_form_miqp): the network constraint at every predicted step, solved exactly.

    At each sampling instant

        min   sum_{k=0}^{N_p-1} ||z(k) - z_ref(k)||_Q^2 + ||v(k)||_R^2  (+ ||z(N_p) - z_ref(N_p)||_{P_f}^2)
        s.t.  |Phi_NN(z(k), v(k))| <= u_max^eps = u_max - eps,   k = 0..N_p-1   (MPC_form_miqp_b)
              z(k+1) = A_d z(k) + B_d v(k)                                       (MPC_form_miqp_c)
              z(k) in Z_z (k = 1..N_p), v(k) in the network's v-range Z_v        (MPC_form_miqp_d)
              z(N_p) in Z_f, F_inf z(N_p) <= psi f_inf  (optional terminal set)

    ``Z_z x Z_v`` is the network's domain box, where ``|Phi - Phi_NN| <= eps`` (eq. approx_err) holds, so every
    predicted step satisfies the true bound ``|Phi(z(k), v(k))| <= u_max`` for the nominal model.

    Parameters
    ----------
    system
        The feedback-linearizable system (Brunovsky pair, domain box, ``u_max``, ``Phi``).
    net
        ``Phi_NN`` on ``system``'s domain box.
    eps
        Error bound of eq. (approx_err), scalar or (m,). A margin such as the intersample drift ``Delta(t_s)``
        is added here: ``eps + Delta`` gives ``u_max^{eps+Delta}``.
    horizon, ts
        ``N_p`` and the sampling time ``t_s`` (seconds).
    Q, R, P
        Stage weights (n_z, n_z), (m, m) and the optional terminal weight ``P_f`` on ``z(N_p)`` (the paper's cost
        stops at ``k = N_p - 1``: ``P=None`` reproduces it). Scalars or vectors are made diagonal.
    terminal
        Optional terminal set: ``(F, g)`` for ``F z(N_p) <= g``, or an object with ``constraint() -> (F, g)``
        (:class:`flnotes.TerminalSet`, ``Z_f``; its gain ``K``, the book's ``K_f``, then gives the shifted plan's
        last input ``v = K_f z``).
    options
        An :class:`MPCOptions` (the levers and the constraint model); or give its fields as keywords
        (``backend=``, ``bounds=``, ``screening=``, ``lazy=``, ``warm_start=``, ``encode=``,
        ``eliminate_stable=``, ``lp=``, ``constraint=``, ``iterations=``), not both.
    time_limit
        Seconds per control step, or ``None``. The whole step counts: the checks before the solve, the engine
        (screening QP, node bounds, every round; each solver call gets the time left) and the fallback after
        it. The reference (``backend="cvxpy-scip"``) has no reserve and no cut-off: its rounds share the limit
        (each SCIP call gets the time left), SCIP itself keeps to it only as closely as it checks its clock, and
        cvxpy's compilation of the program and the fallback come on top (0.1 to 0.2 s were measured on the book's
        and the unseen systems, whatever the limit); at the limit its status is ``"time_limit"``.
        :attr:`reserve` seconds are kept back from the engine for its overrun and the fallback (what this
        controller measured of them, decaying, at most :data:`RESERVE_MAX_SHARE` of the limit), and the fallback's
        repairs stop at :data:`FALLBACK_POST_SHARE` of the limit (at least :data:`FALLBACK_POST_MIN_S`) before
        it. The engine's own limit ends at the cut-off (see ``cut_off``). An answer can still come after the limit
        when the machine does not give the controller the CPU (``info["cpu_time"]`` against ``solve_time``, the
        whole call, tells the two apart; ``info["process_cpu_time"]`` is the CPU of every thread of the process
        meanwhile) or when one call that does not check the time (a forward pass, a QP, the exact first input
        of the fallback) outlasts what is left. The caller's own process counts too: a thread of it that holds
        Python's interpreter lock in a C call (the answer cannot run meanwhile), or OpenBLAS's threads still spinning
        after the caller's own product with several BLAS threads (they take the answer's core for 100 ms and more),
        delayed answers to up to 2.9 t_s where the controller alone was on time; run such code with one BLAS thread
        (``with fl.config.one_blas_thread():`` around the loop, or ``OPENBLAS_NUM_THREADS=1``) and keep C calls that
        hold the lock out of the control thread's process. ``info["process_cpu_time"]`` above ``info["cpu_time"]``
        says that another thread of the process took the time. With the cut-off, ``info["wake_lag"]`` is how long
        after it was due (the cut-off, or the solve's end when earlier) the answering thread resumed and
        ``info["wake_runqueue"]`` how much of that it waited for a core (Linux; NaN elsewhere): a lag without such a
        wait is time the thread was not runnable, a timer that fired late on the machine or the interpreter lock held
        by another thread, not the controller's work. ``info["engine_runqueue"]`` is how long the engine's thread
        waited for a core during the step: where it covers such a lag, the lock was held by the engine's thread while
        that thread waited for a core (the machine had more runnable threads than cores), which no share of the limit
        kept back can rule out. ``info["after_wake"]`` is the wall time from that resumption to the answer and
        ``info["after_wake_blocked"]`` the part of it the thread neither ran nor waited for a core (the interpreter
        lock held by another thread in a C call, or by the engine's thread, lowered at the cut-off, while it waits
        for a core, or the host of a virtual machine running something else on the thread's CPU; NaN where the wait
        for a core is not known); ``info["steal_time"]`` is the time the host took the machine's CPUs during the call
        (:func:`flnotes.config.machine_steal`, summed over the CPUs, in ticks of 10 ms on most systems: where it
        covers a lag, the machine, not the controller, took the time);
        ``info["post_time"]`` is the time after the engine (the fallback and the checks) and
        ``info["post_runqueue"]`` its wait for a core; ``info["previous_wait"]`` the time the step waited at its start
        for a solve the previous step left running (see ``cut_off``). The wall time of a step answered at its cut-off
        is the sum of ``enter_time`` (the call's set-up), ``cut_off_s`` (when the cut-off came), ``wake_lag``,
        ``after_wake`` and ``exit_time`` (the settings set back or kept after the step's own work). On hit the
        status is ``"time_limit"`` and the plan
        is, in this order: the best plan found that passes :meth:`plan_feasible` (the engine's incumbent or the
        warm start), else
        :meth:`fallback_plan` (the shifted plan, its repairs, the plan built along the QP without the network;
        only when none passes the check, a plan whose first input is admissible, ``info["plan_feasible"]``
        False). The engine's best plan counts from the moment it passes the check (the relaxation repaired along the
        QP is offered before the moves that improve it); a repair of the relaxation that the cut-off stopped part-way
        is continued by the fallback, not started again (``info["repair_resumed_at"]``), so where its rest fits before
        the fallback's deadline the plan is the one the uninterrupted repair gives. ``bound`` is a valid lower bound
        of eq. (MPC_form_miqp) (the QP without the network, the levels
        proven empty, a solver's bound) and ``gap = (objective - bound) / max(1, |objective|)``; both NaN for a
        plan that fails the check. A solver call need not stop at its limit (DAQP reads its clock every 32
        iterations and nodes): :attr:`reserve` follows what this controller has measured of that, and with
        ``cut_off`` (the default) the step answers at its cut-off while such a call runs on.
        ``python -m flnotes.bench deadline`` reports the answers after the limit. With a time limit, the controller
        solves once when it is built (:meth:`NetworkEngine.warm_up`), so that its first step does not pay the
        process's one-off costs.
    work_limit
        A work budget per step instead of the wall clock (a time limit is needed, and kept as a safety net only):
        ``None`` (default: the engine's decisions read the clock), a positive number of branch-and-bound nodes for
        all the rounds of a step, or ``"auto"`` (:data:`NODES_PER_SECOND` times ``time_limit``). With a budget no
        decision of the engine reads the clock (its solver calls get a node limit, no time limit; node bounds,
        incumbent searches and rounds run to their end), so the same state gives the same status and plan on every
        run, machine and load: a step that spends its budget answers with status ``"time_limit"`` and a message
        saying "work limit". The wall clock still answers at the cut-off when the budget takes longer than the
        limit (``info["safety_net"]`` True, as when the fallback's repairs stop at their deadline): those steps
        depend on timing, and :meth:`summary` counts them. A budget cannot cut the node bounds, the incumbent search
        and a round's first node: where those alone take longer than ``time_limit`` (measured per system by the
        budget floor of ``python -m flnotes.bench deadline``: most cold MSD states at ``t_s = 0.1`` s, for one), no
        budget answers in time and the safety net decides. DAQP's branch and bound takes no node limit (DAQP 0.11:
        a time limit and a per-node iteration limit only), so under a budget ``backend="auto"`` solves every
        mixed-integer program with SCIP, and ``backend="daqp"`` with a budget is an error.
    cut_off
        With a time limit and the network engine (default on there): the engine solves in a worker thread and the
        step answers at its cut-off, before ``time_limit``, with the best plan the engine has found so far when the
        solve has not returned by then (``info["cut_off"]`` True), so that a solver that overruns its own limit
        does not make the answer late (:meth:`_engine_solve`). ``False`` waits for the engine (its answer is then
        late by the solver's overrun, and which plan a step returns depends on the states only, not on thread
        timing: the tests with a limit far below any solve use it). Given without a time limit, or with options
        that do not run the engine, it is an error. A solve answered at its cut-off runs on after the step has
        returned, with one BLAS thread, a short interpreter switch interval and the cyclic collector paused for the
        whole process (see :meth:`__call__`), until the next step, :meth:`reset` or :meth:`finish` waits for it;
        :func:`flnotes.simulate` calls :meth:`finish` when a run ends, and a controller dropped meanwhile waits for
        it as it is freed. The next step waits for it until its own cut-off at most: a solve that runs on past it
        (its solver call checks the time only now and then, and on a loaded machine its thread waits for a core)
        leaves that step to answer on time without a solve, with :meth:`fallback_plan` (the shifted plan where it
        passes; ``info["previous_ran_on"]`` True, ``info["previous_wait"]`` the seconds waited).
    gap
        Relative optimality gap at which a solver stops.
    discretization
        ``"rk4"`` (the paper) or ``"exact"``; they coincide for chains of at most four integrators.
    v_box
        Range ``(v_lo, v_hi)`` of ``v`` in the program, of positive width and inside the network's domain box (where
        ``eps`` holds; a wider box is refused); default that domain box.
    solver_options
        Passed to :func:`flnotes.solvers.make_solver` (DAQP gets :data:`DAQP_OPTIONS` unless overridden). With
        ``backend="auto"`` (two solvers) give them per back-end: ``{"daqp": {...}, "scip": {...}}``.
    enclosure
        With the network engine (``constraint="network"``, a persistent back-end) only: the
        :class:`flnotes.AffineEnclosure` whose slab the engine's first QP (screening, the level set's center) adds at
        every step (:meth:`flnotes.mpc.prediction.Prediction.relaxation`) and cuts the level-set boxes to
        (:func:`flnotes.enclosure.contract`); exact: the slab holds every admissible input. ``"auto"`` (default)
        computes it on the network's domain box with :func:`flnotes.affine_enclosure` (MILPs, seconds on a (20, 20, 20)
        network, once per network in a process); an enclosure given must be of this network (same
        parameters), hold on a sample of its box (:func:`flnotes.enclosure.check_enclosure`) and contain the
        program's box; ``False``: neither the slab nor the cut.
    atlas
        Where the engine computes LP node bounds (``bounds="lp"``, or ``"levelset"`` with ``lp`` ``True`` or
        ``"auto"``) only: a :class:`flnotes.BoundAtlas` of the network (LP bounds on a grid of cells, computed once
        by :func:`flnotes.bound_atlas`) whose covers replace the LPs of every box inside its domain; exact: the
        covers hold at every admissible point. It must be of this network (checked on a sample,
        :func:`flnotes.check_atlas`), hold for a bound ``u`` at least this controller's ``u_max^eps``, and its
        domain must contain the program's box. ``"auto"`` (default): the atlas shipped for the network when there
        is one that serves this controller (:func:`flnotes.atlas.shipped_atlas`: today the MSD's network of the
        book), else none; ``False``: none.

    Attributes
    ----------
    history
        The :class:`flnotes.StepResult` of every call since the last :meth:`reset`.
    reserve_share
        The share of ``time_limit`` that :attr:`reserve` keeps back at least (:data:`RESERVE_SHARE`); a number in
        ``[0, 0.5]``, which ``python -m flnotes.bench deadline`` sets to 0 to measure the cut-off alone.
    cut_off
        Whether steps answer at the cut-off (the ``cut_off`` argument resolved against the time limit).
    fallback_deadline
        Under a time limit, whether the fallback's repairs stop at their deadline (default True, see ``time_limit``).
        ``False`` lets them run to the end, so that the answer is late by them: the tests and benchmarks with a limit
        far below any solve set it to obtain the repaired plans, which depend on the states only.

    Examples
    --------
    >>> mpc = fl.MPC(fl.quad1d(), net, eps=0.0322, horizon=10, ts=0.1, Q=[10, 1, 1], R=0.0175)
    >>> step = mpc(z, z_ref)            # z_ref of shape (horizon + 1, n_z), or (n_z,) for a constant one
    >>> step.v, step.z_pred, step.status, step.solve_time
    """

    def __init__(self, system: FLSystem, net: ReLUNet, eps, horizon: int = 10, ts: float = 0.1,
                 Q=None, R=None, P=None, *, terminal=None, options: Optional[MPCOptions] = None,
                 time_limit: Optional[float] = None, gap: float = 1e-6, discretization: str = "rk4",
                 v_box: Optional[tuple] = None, solver_options: Optional[dict] = None,
                 cut_off: Optional[bool] = None, work_limit=None, enclosure="auto", atlas="auto", **levers):
        self._init_args = dict(system=system, net=net, eps=eps, horizon=horizon, ts=ts, Q=Q, R=R, P=P,
                               terminal=terminal, options=options, time_limit=time_limit, gap=gap, cut_off=cut_off,
                               work_limit=work_limit, enclosure=enclosure, atlas=atlas,
                               discretization=discretization, v_box=v_box, solver_options=solver_options, **levers)
        if not isinstance(system, FLSystem):
            raise TypeError(f"system must be a flnotes.FLSystem (e.g. fl.msd()), got {type(system).__name__}")
        if not isinstance(net, ReLUNet):
            raise TypeError(f"net must be a flnotes.ReLUNet (e.g. fl.paper_net('MSD')[0]), got {type(net).__name__}")
        if options is not None and levers:
            raise ValueError(f"give either options=MPCOptions(...) or the keywords {sorted(levers)}, not both")
        if options is None:
            unknown = sorted(set(levers) - set(MPCOptions.__dataclass_fields__))
            if unknown:
                raise TypeError(f"MPC got unexpected keyword(s) {unknown}; the options are "
                                f"{sorted(MPCOptions.__dataclass_fields__)}")
            options = MPCOptions(**levers)
        if not isinstance(options, MPCOptions):
            raise TypeError(f"options must be an MPCOptions, got {type(options).__name__}")
        self.options = o = options
        if net.n_in != system.n_in or net.n_out != system.m:
            raise ValueError(f"net maps R^{net.n_in} -> R^{net.n_out} but the system needs (z, v) in R^{system.n_in} "
                             f"-> u in R^{system.m}")
        # any finite real number of its kind (a Fraction, a Decimal, a 0-d array), never a boolean or a time span
        horizon = check_count(horizon, "horizon (N_p)", 1, "steps of the prediction")
        time_limit = check_number(time_limit, "time_limit", "seconds per step", strict=True, none=True)
        gap = check_number(gap, "gap", "a relative optimality gap in [0, 1), e.g. 1e-6")
        if gap >= 1:
            raise ValueError(f"gap must be a relative optimality gap in [0, 1) (e.g. 1e-6), got {gap!r}")
        ts = check_number(ts, "ts", "a positive sampling time in seconds", strict=True)
        engine = o.constraint == "network" and not o.is_reference
        if cut_off is not None:
            if not isinstance(cut_off, bool):
                raise TypeError(f"cut_off must be True, False or None, got {cut_off!r}")
            if time_limit is None:
                raise ValueError("cut_off answers at a time limit: give time_limit=... or leave cut_off unset")
            if cut_off and not engine:
                raise ValueError(f"cut_off needs the network engine (constraint='network', a persistent back-end); "
                                 f"these options are {o}: leave cut_off unset")
        self.node_limit = self._work_budget(work_limit, time_limit, engine, o)
        used = ("daqp", "scip") if o.backend == "auto" else ("scip",) if o.is_reference else (o.backend,)
        for b in used:
            _require(b)  # ImportError naming the package, here, not at a solve
        if o.constraint == "network" and not o.is_reference:
            _require("highs")  # the engine's LP bounds and QPs: imported here, not during the first timed step (60 ms)
        with one_blas_thread():  # its thread controller is built here too (it inspects the loaded libraries)
            pass
        if o.is_reference:
            try:
                import cvxpy  # noqa: F401
            except ImportError as exc:  # pragma: no cover - cvxpy is a requirement
                raise ImportError("backend='cvxpy-scip' needs cvxpy: pip install cvxpy") from exc
        self.system, self.net = system, net
        self.n_z, self.m, self.N = system.n_z, system.m, int(horizon)
        if o.bang_bang and self.m != 1:
            raise ValueError(f"bang_bang=True tries one-switch plans of one input; {system.name} has m = {self.m} "
                             "inputs: drop bang_bang")
        if engine and o.repair and o.bang_bang is None:  # the context's default: for one input
            self.options = o = dataclasses.replace(o, bang_bang=self.m == 1)
        self.ts = float(ts)
        self.eps = as_vector(eps, self.m, "eps")
        self.u_eps = system.u_max - self.eps
        if np.any(self.eps < 0) or np.any(self.u_eps <= 0):
            raise ValueError(f"need 0 <= eps < u_max: eps = {self.eps}, u_max = {system.u_max} leaves no admissible "
                             f"input (u_max - eps = {self.u_eps})")
        self.Q = weight_matrix(Q if Q is not None else np.eye(self.n_z), self.n_z, "Q")
        self.R = weight_matrix(R if R is not None else np.eye(self.m), self.m, "R", definite=True)
        self.P = weight_matrix(P, self.n_z, "P") if P is not None else np.zeros((self.n_z, self.n_z))
        self.discretization = discretization
        self.Ad, self.Bd = system.discretize(self.ts, discretization)
        self.z_lo, self.z_hi = system.lo[: self.n_z].copy(), system.hi[: self.n_z].copy()
        vb = (system.lo[self.n_z:], system.hi[self.n_z:]) if v_box is None else as_pair(v_box, "v_box")
        self.v_lo, self.v_hi = box_in_domain(vb[0], vb[1], system.lo[self.n_z:], system.hi[self.n_z:],
                                             names=("v_box[0]", "v_box[1]"))
        self.terminal = terminal
        Fg = None
        if terminal is not None:
            Fg = terminal.constraint() if hasattr(terminal, "constraint") else terminal
            if not (isinstance(Fg, (tuple, list)) and len(Fg) == 2):
                raise TypeError("terminal must be (F, g) or an object with constraint() -> (F, g), e.g. fl.TerminalSet")
        K = getattr(terminal, "K", None)
        self.K_terminal = None if K is None else as_floats(K, "terminal.K").reshape(self.m, self.n_z)
        self.time_limit, self.gap = time_limit, float(gap)
        self.cut_off = bool(time_limit is not None and engine and (cut_off is None or cut_off))
        self.reserve_share = RESERVE_SHARE
        self.fallback_deadline = True
        self._fallback_s = 0.0  # the longest fallback (CPU s of this controller's thread), decaying: see reserve
        self._late_s = 0.0  # the engine's largest lateness after its budget (its CPU share), decaying: see reserve
        self._answer_s = 0.0  # the longest wall time from a cut-off to its answer, decaying: see _engine_solve
        self._running: Optional[tuple] = None  # a solve answered at its cut-off and still running: see _engine_solve
        self._held = _HeldSettings()  # the process settings it keeps: see __call__
        # a controller dropped while it holds them gives them back, in the thread that drops it, once its solve ends
        weakref.finalize(self, self._held.finalize)
        if solver_options and not engine:
            raise ValueError(f"solver_options set the persistent back-ends of the network engine; these options "
                             f"(constraint={o.constraint!r}, backend={o.backend!r}) do not run it: leave solver_options unset")
        self.solver_options = _per_backend(o.backend, used, solver_options)
        #: The network's :class:`flnotes.AffineEnclosure` the engine's relaxation uses (``None``: none).
        self.enclosure = self._enclosure(enclosure, engine, net, system)
        lp_runs = engine and (o.bounds == "lp" or (o.bounds == "levelset" and o.lp is not False))
        #: The network's :class:`flnotes.BoundAtlas` whose covers replace the engine's LP bounds (``None``: none).
        self.atlas = self._atlas(atlas, lp_runs, net)
        self.pred = Prediction(net, self.Ad, self.Bd, self.N, self.Q, self.R, self.P, z_lo=self.z_lo, z_hi=self.z_hi,
                               v_lo=self.v_lo, v_hi=self.v_hi, u_eps=self.u_eps, terminal=Fg, enclosure=self.enclosure)
        self.box_bounds = fbbt(net, np.r_[self.z_lo, self.v_lo], np.r_[self.z_hi, self.v_hi])
        if o.constraint != "network":
            self.solver = LinearModel(self.pred, o, system)
        elif o.is_reference:
            self.solver = ReferenceProgram(self.pred, o, self.box_bounds)
        else:
            self.solver = NetworkEngine(self.pred, o, self.box_bounds, self.solver_options, atlas=self.atlas)
            if time_limit is not None:  # the one-off costs of a first solve are paid here, not in the first step
                self.solver.warm_up()
        #: How much ``u_max^eps`` was tightened in the reference's rows at the last solve (the engine has its own).
        self.margin = 0.0
        self.history: list[StepResult] = []
        self._plan: Optional[tuple[Array, Array]] = None
        self._qp_plan: Optional[Array] = None

    def _atlas(self, atlas, lp_runs: bool, net: ReLUNet) -> Optional[BoundAtlas]:
        """The ``atlas`` argument validated and resolved (``None``: LP bounds as without it)."""
        lo, hi = np.r_[self.z_lo, self.v_lo], np.r_[self.z_hi, self.v_hi]
        if isinstance(atlas, str) and atlas == "auto":
            return shipped_atlas(net, lo, hi, self.u_eps) if lp_runs else None
        if atlas is False:
            return None
        if not lp_runs:
            raise ValueError(f"atlas={atlas if isinstance(atlas, str) else type(atlas).__name__} replaces the engine's "
                             "LP node bounds, and these options compute none "
                             "(they need the network engine with bounds='lp', or 'levelset' with lp=True or 'auto'): "
                             "leave atlas unset")
        if not isinstance(atlas, BoundAtlas):
            raise TypeError(f"atlas must be 'auto', False or a flnotes.BoundAtlas, got {type(atlas).__name__} "
                            f"{atlas!r:.60}")
        check_atlas(net, atlas)  # of this network, and it holds on a sample of its domain
        if not atlas._covers(lo, hi)[0]:
            raise ValueError(f"the atlas's domain [{atlas.lo}, {atlas.hi}] must contain the program's box [{lo}, {hi}]: "
                             "compute it on the network's domain box")
        if np.any(self.u_eps > atlas.u):
            raise ValueError(f"the atlas holds for |Phi_NN| <= {atlas.u}, below this controller's u_max^eps = "
                             f"{self.u_eps}: compute it with u >= u_max^eps")
        return atlas

    @staticmethod
    def _enclosure(enclosure, engine: bool, net: ReLUNet, system: FLSystem) -> Optional[AffineEnclosure]:
        """The ``enclosure`` argument validated and resolved (``None``: no slab)."""
        if isinstance(enclosure, str) and enclosure == "auto":
            return affine_enclosure(net, system.lo, system.hi) if engine else None
        if not engine:
            raise ValueError(f"enclosure={enclosure!r} tightens the network engine's relaxation; these options do not "
                             "run it (constraint='network' with a persistent back-end): leave enclosure unset")
        if enclosure is False:
            return None
        if not isinstance(enclosure, AffineEnclosure):
            raise TypeError(f"enclosure must be 'auto', False or a flnotes.AffineEnclosure, got {enclosure!r}")
        check_enclosure(net, enclosure)  # of this network, and it holds on a sample of its box
        return enclosure

    @staticmethod
    def _work_budget(work_limit, time_limit: Optional[float], engine: bool, o: MPCOptions) -> Optional[int]:
        """``work_limit`` validated and resolved to a node budget per step (``None``: the wall clock decides)."""
        if work_limit is None:
            return None
        if isinstance(work_limit, str):
            if work_limit not in WORK_LIMITS:
                raise ValueError(f"work_limit must be None, 'auto' or a positive number of nodes, got {work_limit!r}")
        elif isinstance(work_limit, bool) or not isinstance(work_limit, (int, np.integer)) or work_limit < 1:
            raise ValueError(f"work_limit must be None, 'auto' or a positive number of nodes, got {work_limit!r}")
        if time_limit is None:
            raise ValueError("work_limit replaces the wall clock inside a time-limited step (which stays as a safety "
                             "net): give time_limit=... too, or leave work_limit unset")
        if not engine:
            raise ValueError(f"work_limit budgets the network engine's branch and bound (constraint='network', a "
                             f"persistent back-end); these options are {o}: leave work_limit unset")
        if o.backend not in ("auto", "scip"):
            why = ("DAQP's branch and bound has no node limit" if o.backend == "daqp" else
                   "the package passes no node limit to this optional back-end")
            raise ValueError(f"work_limit needs a back-end that takes a node limit: SCIP (backend='scip', or 'auto', "
                             f"which then solves every mixed-integer program with SCIP); {o.backend!r} stops on the "
                             f"clock only ({why}): leave work_limit unset")
        if work_limit != "auto" and work_limit > MAX_WORK_LIMIT:
            raise ValueError(f"work_limit = {work_limit} nodes is more than SCIP's node limit takes "
                             f"(at most {MAX_WORK_LIMIT}); give fewer nodes, or no work_limit")
        if work_limit == "auto":
            return max(1, int(np.floor(NODES_PER_SECOND * float(time_limit))))
        return int(work_limit)

    # ------------------------------------------------------------------ state
    @property
    def n_binaries_full(self) -> int:
        """``N_p * sum_k n_k``: the binaries of eq. (MPC_form_miqp) without any elimination (paper, footnote)."""
        return self.N * self.net.n_hidden

    @property
    def last(self) -> Optional[StepResult]:
        """The last step's record."""
        return self.history[-1] if self.history else None

    @property
    def reserve(self) -> float:
        """Seconds of :attr:`time_limit` kept back from the engine, for the answer it gives after its budget and the
        fallback after it: :attr:`reserve_share` (:data:`RESERVE_SHARE`) of the limit, or what this controller has
        measured when that is more (the engine's largest lateness after its budget plus the longest fallback it
        ran, both on this controller's own CPU time, not on waiting for the machine), the measured part at most
        :data:`RESERVE_MAX_SHARE` of the limit. The measures shrink by :data:`RESERVE_DECAY` at every step and
        :meth:`reset` clears them, so one slow fallback never keeps the engine from optimizing the later steps.

        The engine answers after its budget by what a solver call overran its time limit: DAQP reads its clock every
        32 iterations of a node's active-set solve and every 32 nodes of its branch and bound, so a search of short
        nodes runs on by up to 32 of them (up to 9 ms past a 25 ms limit on the systems of the benchmark), SCIP by 1
        to 2 ms. The lateness is measured after every step; the
        fallback of a cold state without a feasible plan took 25 to 35 ms on the Quad-1D at N_p = 20. With
        :attr:`cut_off` a solve that has not returned by ``time_limit`` less the largest of half the reserve, the
        longest fallback and :data:`CUT_OFF_MIN_S` (at most :data:`RESERVE_MAX_SHARE` of the limit) is answered from
        what it has found so far, and its lateness is measured when it ends.
        """
        if self.time_limit is None:
            return 0.0
        tl = float(self.time_limit)
        if not 0.0 <= self.reserve_share <= 0.5:
            raise ValueError(f"reserve_share must be in [0, 0.5], got {self.reserve_share!r}")
        return max(self.reserve_share * tl, min(self._late_s + self._fallback_s, RESERVE_MAX_SHARE * tl))

    @property
    def measured(self) -> dict:
        """What this controller has measured (seconds, decaying by :data:`RESERVE_DECAY` per step, cleared by
        :meth:`reset`): ``late`` (the engine's lateness after its budget, scaled by the CPU share of its solve: waiting
        for the machine does not count) and ``fallback`` (the longest fallback's CPU time), which :attr:`reserve`
        keeps back from the engine; ``answer`` (the longest wall time from a cut-off to its answer, waiting for the
        machine included), which moves the cut-off earlier (:meth:`_engine_solve`) but never by more than
        :data:`RESERVE_MAX_SHARE` of the limit."""
        return dict(late=self._late_s, fallback=self._fallback_s, answer=self._answer_s)

    @property
    def backend(self) -> str:
        return self.options.backend

    @property
    def bounds(self) -> Optional[str]:
        return self.options.bounds

    def reset(self) -> None:
        """Forget the previous plan, the history, the kept LP bounds (``MPCOptions.bound_cache``) and the measures of
        :attr:`reserve`; called by :func:`flnotes.simulate` at the start of a run."""
        self._finish_running()
        self.history = []
        self._plan = None
        self._fallback_s = self._late_s = self._answer_s = 0.0  # what was measured on other states and loads
        if isinstance(self.solver, NetworkEngine):
            self.solver.reset()

    def finish(self) -> None:
        """Wait for a solve that the last step answered at its cut-off (it runs on in the engine's thread until its
        own limit) and set back the process-wide settings it kept: one BLAS thread, the short interpreter switch
        interval and the paused cyclic collector (see :meth:`__call__`). What they were before the step comes back,
        so a switch interval or collector state that other code set meanwhile is replaced. The next step and
        :meth:`reset` do this first; call it when you stop stepping the controller, e.g. before other numerical work
        in the same process (:func:`flnotes.simulate` calls it when a run ends, also by an exception). The
        controller keeps its plan, history and measures. Call it from the thread that steps the controller: OpenBLAS
        ignores a thread count set back from another thread. A controller dropped meanwhile does it as it is freed,
        in the thread that drops its last reference; one held in a reference cycle is freed only by a later
        collection, possibly in another thread, so call this first."""
        self._finish_running()

    def set_previous_plan(self, plan: Optional[tuple[Array, Array]]) -> None:
        """Set (or clear, with ``None``) the plan ``(z_pred, v_pred)`` that the next call shifts for its warm start."""
        if plan is None:
            self._plan = None
            return
        self._plan = self._check_plan(*as_pair(plan, "plan"))

    def _check_plan(self, z_pred, v_pred) -> tuple[Array, Array]:
        """A plan ``(z_pred, v_pred)`` as finite float arrays of shapes (N_p + 1, n_z) and (N_p, m), else
        ``ValueError`` naming what is wrong."""
        Z, V = as_floats(z_pred, "z_pred"), self._check_inputs(v_pred)
        if Z.shape != (self.N + 1, self.n_z):
            raise ValueError(f"a plan is (z_pred, v_pred) of shapes ({self.N + 1}, {self.n_z}) and ({self.N}, "
                             f"{self.m}), got {Z.shape} and {V.shape}")
        if not np.all(np.isfinite(Z)):
            raise ValueError("a plan's z_pred must be finite: it contains NaN or inf")
        return Z.copy(), V.copy()

    def _check_inputs(self, v_pred) -> Array:
        """``v_pred`` as finite inputs of shape (N_p, m) (a flat (N_p m,) array too, as :class:`Prediction` takes
        it), else ``ValueError`` naming it."""
        V = as_floats(v_pred, "v_pred")
        if V.shape == (self.N * self.m,):  # flat, as Prediction takes it
            V = V.reshape(self.N, self.m)
        if V.shape != (self.N, self.m) or not np.all(np.isfinite(V)):
            raise ValueError(f"v_pred must be finite inputs of shape (N_p, m) = ({self.N}, {self.m}), got shape "
                             f"{V.shape}")
        return V

    def clone(self, **changes) -> "MPC":
        """A new controller with the same settings except ``changes`` (no history, no previous plan).

        ``clone(time_limit=None)`` also leaves out ``cut_off`` and ``work_limit`` (both act only under a time
        limit, so neither can be kept), unless given again in ``changes`` (then the combination is checked as
        in :class:`MPC`). Any lever keyword replaces the options as :class:`MPCOptions` fields.
        """
        args = {**self._init_args, **changes}
        if args.get("time_limit") is None and "cut_off" not in changes:
            args["cut_off"] = None  # a clone without a time limit has no cut-off to keep
            if "work_limit" not in changes:
                args["work_limit"] = None  # nor a work budget
        levers = sorted(set(changes) & set(MPCOptions.__dataclass_fields__))
        if "options" in changes and changes["options"] is not None:
            args = {k: v for k, v in args.items() if k not in MPCOptions.__dataclass_fields__}
        elif levers:
            if self._init_args.get("options") is not None and "options" not in changes:
                raise ValueError(f"this MPC was built with options=MPCOptions(...), so the keywords {levers} would "
                                 "replace those options: give clone(options=MPCOptions(...)) with every option wanted")
            args["options"] = None
        return MPC(**args)

    # ------------------------------------------------------------------ the model
    def predict(self, z: Array, v_pred: Array) -> Array:
        """Predicted states ``z(0..N_p)`` of eq. (MPC_form_miqp_c) for inputs ``v_pred`` of shape (N_p, m)."""
        return self.pred.predict(as_state(z, self.n_z, "z"), self._check_inputs(v_pred))

    def cost(self, z_pred: Array, v_pred: Array, z_ref: Array) -> float:
        """Eq. (MPC_form_miqp_a) for a plan ``(z_pred, v_pred)`` and the reference ``z_ref`` ((N_p + 1, n_z) or
        (n_z,))."""
        Z, V = self._check_plan(z_pred, v_pred)
        return self.pred.plan_cost(Z, V, self._check_ref(z_ref))

    def plan_feasible(self, z_pred: Array, v_pred: Array) -> bool:
        """Does a plan satisfy eq. (MPC_form_miqp_b)-(d) and the terminal rows (:meth:`Prediction.feasible`)?

        Only ``z_pred[0]`` and ``v_pred`` are read: the states checked are the ones the model predicts from them
        (eq. MPC_form_miqp_c), so a ``z_pred`` that is not that prediction is judged by the prediction, not by its
        own rows (build plans with :meth:`predict`)."""
        Z, V = self._check_plan(z_pred, v_pred)
        return self.pred.feasible(Z[0], V)

    def problem(self, z: Array, z_ref, steps=None):
        """The assembled MIQP (:class:`flnotes.solvers.MIQP`) at ``z`` for ``z_ref``, for inspection and benchmarks.

        ``steps`` selects the encoded steps (default: those the options need); node bounds follow the options.
        """
        if not isinstance(self.solver, NetworkEngine):
            raise ValueError(f"problem() shows the program of a persistent back-end; these options are {self.options}")
        self._finish_running()
        return self.solver.program(self._check_z(z), self._check_ref(z_ref), steps)

    # ------------------------------------------------------------------ checks
    def _check_z(self, z) -> Array:
        z = as_floats(z, "z")
        if z.shape != (self.n_z,):
            raise ValueError(f"z must be the measured state of shape ({self.n_z},), got shape {z.shape}")
        if not np.all(np.isfinite(z)):
            raise ValueError(f"z contains NaN or inf: {z}")
        self.system.check_domain(z, what="the measured state z")
        return project_to_box(z, self.z_lo, self.z_hi, "z")  # on the face of the box up to BOX_TOL: on it

    def _check_ref(self, z_ref) -> Array:
        return horizon_reference(z_ref, self.N, self.n_z)

    # ------------------------------------------------------------------ solving
    def __call__(self, z: Array, z_ref) -> StepResult:
        """Solve at the measured ``z`` (n_z,) for the reference ``z_ref`` ((N_p + 1, n_z) or (n_z,)).

        Returns the :class:`flnotes.StepResult` (appended to :attr:`history`): ``v`` to apply, the plan, status
        and statistics. A step without a proven plan applies :meth:`fallback_plan` (``fallback=True``). An
        infeasible program is reported (``status="infeasible"``), not raised; so is a program whose optimum the
        solvers' tolerances cannot settle (``status="error"``, a message that starts "not proven": the optimum lies
        on a ridge of the network at ``u_max^eps``, see :mod:`flnotes.solvers`). The step runs with one BLAS
        thread (:func:`flnotes.config.one_blas_thread`) and, under a time limit, without Python's cyclic garbage
        collector (:func:`flnotes.config.no_cyclic_gc`: a collection that falls due starts after the call has
        returned, at the caller's next allocation of a tracked object) and with
        a short interpreter-lock switch interval (:func:`flnotes.config.quick_thread_switch`: the answer at a
        cut-off does not wait for the engine's thread) and, on Linux 6.12 and later, a short scheduler slice for the
        answering thread (:func:`flnotes.config.answer_slice`: waking at the cut-off, it takes a core at once instead
        of waiting for the running thread's slice to end; ``info["answer_slice"]`` says whether it was granted).
        Under a time limit, every signal that Python handles in the main thread (Ctrl-C's ``SIGINT``, a timeout's
        ``SIGALRM``, ...) is held back until these settings are back, then delivered to its handler
        (:func:`flnotes.config.hold_signals`): an exception raised by a handler (``KeyboardInterrupt``, a timeout's
        own) is raised by the call as it returns, never inside the threading primitives the step shares with its
        solve's thread, which CPython does not make safe against such exceptions. A step thus delays a handler by at
        most its own length (about ``time_limit``).
        """
        t0, p0 = time.perf_counter(), time.process_time()
        if self.time_limit is None:
            f0, s0 = major_faults(), machine_steal()
            with one_blas_thread():
                step = self._solve_step(z, z_ref, t0)
        else:
            # first, allocating nothing: the signals Python handles held back until the settings are back, and no
            # collection starts in the call (see config.no_cyclic_gc)
            held = pause_for_step()
            step = None
            try:
                f0, s0 = major_faults(), machine_steal()  # they allocate: after the pause
                shared = ExitStack()  # process-wide settings, kept while a solve answered at its cut-off runs on
                try:
                    shared.enter_context(one_blas_thread())
                    shared.enter_context(quick_thread_switch())
                    with answer_slice() as short:
                        step = self._solve_step(z, z_ref, t0)
                finally:  # also when an interrupt lands in the set-up above
                    if self._running is not None and self._held.stack is None:
                        # the engine's solve runs on after the answer: it keeps one BLAS thread (a second one spins
                        # after each product and took the next answer's core: answers at up to 3.7 t_s) and the
                        # short switch interval (the caller's code gets the interpreter lock from it) until it ends;
                        # they are set back in this thread when the next step, reset() or finish() has waited for it
                        # (OpenBLAS ignores a thread count raised from another thread); the collector stays paused by
                        # the solve's own pause (see _engine_solve)
                        self._held.keep(shared.pop_all(), self._running[0], self._running[1]["done"])
                    else:
                        shared.close()
                step.info["answer_slice"] = short
                self._timed(step, t0, p0, f0, s0)
            finally:
                if self._running is not None:  # the answer is out: a solve stopped at the cut-off goes on to its end
                    self.solver.answered()
                    if step is not None:  # the solve it released may take the interpreter lock at once: this
                        # thread's wait for it is the caller's wait too, so the record's end comes after it
                        end = time.perf_counter() - t0
                        step.info["exit_time"] = step.info.get("exit_time", 0.0) + end - step.solve_time
                        step.solve_time = end
                # last: a collection that fell due starts after the return, and the signals held back are delivered
                resume_after_step(held)
            return step
        self._timed(step, t0, p0, f0, s0)
        return step

    @staticmethod
    def _timed(step: StepResult, t0: float, p0: float, f0: float, s0: float) -> None:
        """The whole call in the record: ``solve_time`` (what the caller waited, the contexts' ends included),
        ``info["process_cpu_time"]``, the CPU time of every thread of the process meanwhile (against
        ``info["cpu_time"]``, the step's own threads: the rest is other work of the process, e.g. a library's or the
        caller's own threads), ``info["exit_time"]`` (the part of ``solve_time`` after the step's own work: the
        settings set back or kept), ``info["major_faults"]``, the process's major page faults meanwhile
        (:func:`flnotes.config.major_faults`: waits for the disk, the machine's time), and ``info["steal_time"]``,
        the seconds the host of a virtual machine took the machine's CPUs meanwhile (:func:`flnotes.config.machine_steal`,
        summed over the CPUs, in clock ticks of 10 ms on most systems: the machine's time; NaN where the system does
        not say)."""
        end = time.perf_counter() - t0
        # after the step's own record (its solve_time): setting back or keeping the process-wide settings, whose
        # system calls let another thread of the process take the interpreter lock
        step.info["exit_time"] = end - step.info.get("enter_time", 0.0) - step.solve_time
        step.solve_time = end
        step.info["process_cpu_time"] = time.process_time() - p0
        step.info["major_faults"] = major_faults() - f0
        step.info["steal_time"] = machine_steal() - s0

    def _solve_step(self, z: Array, z_ref, t_call: float) -> StepResult:
        t0, c0 = time.perf_counter(), time.thread_time()
        # a solve the last step answered at its cut-off ends first, inside this step's budget: waited for until this
        # step's own cut-off at most (the engine's models are that solve's until it ends)
        gave_up = self._previous_ended(t_call, t0)
        ended = gave_up is None
        waited = time.perf_counter() - t0
        self._fallback_s *= RESERVE_DECAY
        self._late_s *= RESERVE_DECAY
        self._answer_s *= RESERVE_DECAY
        if ended:
            release_retired()  # the solver models the last step kept alive are freed here, inside this step's budget
        z = self._check_z(z)
        R = self._check_ref(z_ref)
        shifted = self.shifted_plan(z)
        o = self.options
        if not ended:  # the previous step's solve still runs: this step answers at its cut-off without a solve
            step = StepResult(None, "time_limit", bound=-np.inf,
                              message="time limit: cut off before the solve started, while the solve of the previous "
                                      "step (answered at its cut-off) ran on")
            step.info.update(cut_off=True, cut_off_at=time.perf_counter(), engine_cpu_time=0.0, **gave_up)
        elif o.constraint != "network":
            step = self.solver.solve(z, R, previous=self._plan[0] if self._plan is not None else None)
        elif o.is_reference:
            step = self._solve_reference(z, R)
        else:
            inc = shifted[1] if shifted is not None and self.plan_feasible(*shifted) else None
            # the step's time counts from the call's start (t_call): the set-up before this line is the caller's wait
            budget = self._engine_time(t_call)
            if self.cut_off:
                step = self._engine_solve(z, R, inc, budget, t0, t_call)
            else:
                c_s = time.thread_time()
                self.solver.go()  # a stop() asked before this solve (e.g. by the caller) does not carry over into it
                step = self.solver.solve(z, R, incumbent=inc, time_limit=budget, gap=self.gap,
                                         node_limit=self.node_limit, safety_deadline=self._safety(t_call))
                if budget is not None:  # how late the engine answered after its budget (see reserve)
                    self._measure_late(step.solve_time - budget, time.thread_time() - c_s, step.solve_time)
        if step.v is not None and o.is_reference and not self.plan_feasible(step.z_pred, step.v_pred):
            # never a plan that breaks the program labelled as a solution; under the limit it is the limit that came
            # before a plan that passes (the engine's status there too), otherwise an error
            step.status = "time_limit" if step.status == "time_limit" else "error"
            step.v = None
            step.message += "; the returned plan fails the forward-pass check"
        t_post, q_post = time.perf_counter(), thread_run_delay()
        if step.v is None:
            step = self._fallback(z, R, step, shifted, t_call)
        elif step.status == "time_limit" and not np.isfinite(step.bound):
            self._record_gap(z, R, step, -np.inf)  # the engine had no bound (no QP solved): the QP's
        step.u_nn_pred = self.net(np.hstack([step.z_pred[: self.N], step.v_pred]))
        if o.constraint == "network" or step.fallback:
            step.input_admissible = bool(step.input_admissible and np.all(np.abs(step.u_nn_pred[0]) <= self.u_eps + BOUND_TOL))
        step.info["z_ref"] = R
        if self.node_limit is not None:  # did the wall clock decide anything in this step (see work_limit)?
            step.info["work_limit"] = self.node_limit
            step.info["safety_net"] = (bool(step.info.get("safety_net")) or bool(step.info.get("cut_off"))
                                       or "deadline" in step.message)
        step.info["plan_feasible"] = self.plan_feasible(step.z_pred, step.v_pred)
        # the step's end, read once for every figure below: the wait for a core first (reading it is a system call,
        # after which the thread may wait for the interpreter lock: counted in the wall time, never in the core's or
        # the CPU's), then the CPU, then the wall clock
        q_end = thread_run_delay()
        c_end = time.thread_time()
        step.solve_time = time.perf_counter() - t0
        step.info["post_time"] = step.solve_time - (t_post - t0)
        # of it, the time this thread waited for a core (Linux; NaN elsewhere): the rest was its work or the lock
        step.info["post_runqueue"] = q_end - q_post
        step.info["previous_wait"] = waited  # spent waiting for the previous step's solve (see _previous_ended)
        step.info["enter_time"] = t0 - t_call  # the call's set-up before this step's own work (the settings)
        step.info["previous_ran_on"] = not ended
        if "woke_at" in step.info:  # from when this thread resumed after the engine to the answer: wall, CPU, core
            t_w, c_w, q_w = step.info.pop("woke_at")
            after = t0 + step.solve_time - t_w
            # the rest of that wall time this thread was neither running nor waiting for a core: it waited for the
            # interpreter lock (held by another thread of the process in a C call), for the operating system, or for
            # the host of a virtual machine (see steal_time)
            step.info["after_wake"] = after
            step.info["after_wake_blocked"] = after - (c_end - c_w) - (q_end - q_w)
        # the CPU time of the step's work until its answer: this thread's and, with the cut-off, the engine's thread's
        step.info["cpu_time"] = c_end - c0 + step.info.get("engine_cpu_time", 0.0)
        if "cut_off_at" in step.info:  # how long the answer took after the cut-off, on the wall clock
            self._answer_s = max(self._answer_s, t0 + step.solve_time - step.info.pop("cut_off_at"))
        self._plan = (step.z_pred, step.v_pred)
        self.history.append(step)
        return step

    def _solve_reference(self, z: Array, R: Array) -> StepResult:
        """The cold reference; when SCIP's tolerance lets the plan exceed ``u_max^eps``, the rows are tightened.

        ``time_limit`` bounds the whole step: each round gets what the earlier ones left (a round that starts with
        nothing left is not run, and the step ends with status ``"time_limit"``)."""
        self.margin = 0.0  # per solve, as in the engine
        t0 = time.perf_counter()
        step = self.solver.solve(z, R, self.u_eps, time_limit=self.time_limit, gap=self.gap)
        lb_free = -np.inf  # the untightened program's lower bound (SCIP's, at its tolerance)
        for k in range(2, 7):  # rounds 2 to 6
            if step.v is None or step.status != "optimal":
                return self._backed(step, lb_free)
            ex = float(np.max(np.abs(self.net(np.hstack([step.z_pred[: self.N], step.v_pred]))) - self.u_eps))
            if ex <= BOUND_TOL:
                return self._backed(step, lb_free)
            if self.margin == 0.0:
                lb_free = min(float(step.bound), float(step.objective)) if np.isfinite(step.bound) else float(step.objective)
            self.margin = next_margin(self.margin, ex, float(np.max(self.u_eps)))
            left = None if self.time_limit is None else self.time_limit - (time.perf_counter() - t0)
            if left is not None and left <= 0.0:
                step.status = "time_limit"
                step.message += f"; the time limit came before round {k} (the rows tightened by {self.margin:.1e})"
                return step
            step = self.solver.solve(z, R, self.u_eps - self.margin, time_limit=left, gap=self.gap)
        return self._backed(step, lb_free)

    def _backed(self, step: StepResult, lb_free: float) -> StepResult:
        """``step`` of the reference, unless it is a verdict of rows tightened by ``self.margin`` that the untightened
        program's lower bound ``lb_free`` does not back: an optimum more than ``gap`` (at least
        :data:`flnotes.solvers.TIGHTENED_GAP`) above it, or no plan at all
        (the tightened rows remove plans that meet ``u_max^eps``, e.g. on a ridge of the network). That step becomes
        an ``"error"`` that says so; its plan is dropped."""
        if self.margin == 0.0 or step.status not in ("optimal", "infeasible"):
            return step
        if step.status == "optimal" and step.objective <= lb_free + max(self.gap, TIGHTENED_GAP) * max(1.0, abs(step.objective)):
            step.bound = min(float(step.bound), lb_free) if np.isfinite(step.bound) else lb_free
            step.gap = abs(step.objective - step.bound) / max(1.0, abs(step.objective))
            return step
        what = "no plan" if step.status == "infeasible" else f"an optimum of cost {step.objective:.9g}"
        return StepResult(None, "error", backend=step.backend, n_binaries=step.n_binaries, rounds=step.rounds,
                          nodes=step.nodes, encoded_steps=step.encoded_steps, solve_time=step.solve_time,
                          message=f"not proven: {what} with u_max^eps tightened by {self.margin:.1e} (SCIP's "
                          f"tolerance let its plan through), while the untightened program's lower bound is "
                          f"{lb_free:.9g}: its optimum lies within the solver's tolerance of the network bound (e.g. "
                          f"on a ridge of the network); {step.message}")

    def step(self, z: Array, t: float, reference: Optional[Callable[[Array], Array]] = None) -> StepResult:
        """One sampling instant for :func:`flnotes.simulate`: ``z_ref(k) = reference(t + k t_s)``, k = 0..N_p.

        Under a time limit the cyclic collector is paused from the first line, before the reference is evaluated,
        to the last (see :meth:`__call__`): no collection starts inside the step."""
        held = pause_for_step() if self.time_limit is not None else None  # first (see __call__)
        try:
            t = check_number(t, "t", "the time of the step in seconds", low=-np.inf)
            if reference is None:
                R = np.zeros((self.N + 1, self.n_z))
            else:
                R = as_floats(reference(t + self.ts * np.arange(self.N + 1)), "reference(t)")
            return self(z, R)
        finally:
            if self.time_limit is not None:
                resume_after_step(held)

    def _engine_solve(self, z: Array, R: Array, inc: Optional[Array], budget: float, t0: float,
                      start: float) -> StepResult:
        """The engine's solve under the time limit, answered at the cut-off if it has not returned by then.

        The solve runs in a worker thread with ``budget`` seconds; this thread waits for it until the cut-off,
        ``start + time_limit`` (``start``: the call's start; ``t0``: the step's own, after the call's set-up) less the
        largest of half of :attr:`reserve`, the longest fallback run so far (CPU time),
        the longest time an answer took after its cut-off (wall clock: on a loaded machine the answer waits for a
        core) and :data:`CUT_OFF_MIN_S`, at most :data:`RESERVE_MAX_SHARE` of the limit (the rest of the reserve is
        for the engine's overrun after its budget); these measures decay by :data:`RESERVE_DECAY` per step.
        A solve that has not returned then is asked to stop and to wait, once stopped, until the answer is out before
        it builds its result (:meth:`NetworkEngine.stop` with ``hold=True``, :meth:`NetworkEngine.answered` at the
        end of :meth:`__call__`: what is left of it then competes less with the answer), and the step answers with
        what it has published (:meth:`NetworkEngine.answer_now`: its best plan that passed the forward-pass check
        and its lower bound, ``info["cut_off"]`` True). The solver calls release the GIL (DAQP, HiGHS, SCIP), so the
        answer does not wait for a solver that overruns its own limit; on Linux the engine's thread is then lowered to
        nice :data:`flnotes.config.CUT_OFF_NICE` (:func:`flnotes.config.yield_core`, ``info["engine_yielded"]``), so
        that where it shares a core with the answer the answer gets most of it. The solve ends on its own (at its next check
        of the time, or when its solver call returns) and the next step waits for it first, until that step's own
        cut-off at most (:meth:`_previous_ended`); :meth:`reset` and :meth:`finish` wait until it ends.
        """
        box: dict = {}
        own_slice = slice_before_answer()  # the slice this thread had before the step's short one (None: not changed)

        # the solve's thread refers to these, not to the controller: a controller dropped while its solve runs on is
        # then freed (and its finalizer run) in the caller's thread, which OpenBLAS needs (see _HeldSettings)
        solve, gap, node_limit, safety = self.solver.solve, self.gap, self.node_limit, self._safety(start)

        def run() -> None:
            # the solve's own pause of the collector, taken while this step's is held and ended as the solve ends: a
            # solve that runs on after the answer at the cut-off starts no collection in its thread, which would
            # hold the interpreter lock
            pause_gc()
            c_s = time.thread_time()
            try:
                box["tid"] = threading.get_native_id()
                set_back_slice(own_slice)  # the engine solves with its creator's own slice, not the answer's short one
                # the engine's own limit never runs past the cut-off, counted from when this thread starts (on a busy
                # machine a new thread can wait for a core): after the cut-off its thread would compete with the
                # answer for the interpreter lock and the cores
                limit = box["limit"] = None if budget is None else max(min(budget, cut - time.perf_counter()), 1e-9)
                box["step"] = solve(z, R, incumbent=inc, time_limit=limit, gap=gap, node_limit=node_limit,
                                    safety_deadline=safety)
            except BaseException as exc:  # handed to the caller's thread, never dropped: see _finish_running
                box["error"] = exc
            finally:
                box["cpu"] = time.thread_time() - c_s
                box["run_delay"] = thread_run_delay()  # this new thread's wait for a core, all of it
                resume_gc()  # the solve's own pause
                box["t_done"] = time.perf_counter()
                box["done"].set()

        cut = self._cut_off(start)
        # the incumbent search stops at the cut-off by itself, except under a work budget, where no decision of the
        # engine reads the clock (the caller's stop() at the cut-off is the safety net, flagged as such)
        self.solver.go(stop_at=None if self.node_limit is not None else cut)
        worker = threading.Thread(target=run, name="flnotes-mpc-solve")
        box["done"] = threading.Event()
        self._running = (worker, box, budget)  # whatever ends this call, the next one waits for this solve first
        worker.start()
        queued = thread_run_delay()
        done = _wait_for(worker, box["done"], max(cut - time.perf_counter(), 0.0))
        t_woke, c_woke, q_woke = time.perf_counter(), time.thread_time(), thread_run_delay()
        # how long after it was due (the cut-off, or the solve's end if earlier) this thread resumed, and of that
        # how long it waited for a core: the rest it was not runnable (a timer that fired late, the interpreter lock)
        wake = dict(wake_lag=max(t_woke - min(cut, box.get("t_done", cut)), 0.0),
                    wake_runqueue=q_woke - queued,
                    # the engine's thread's wait for a core so far (its own figure once it has ended)
                    engine_runqueue=box["run_delay"] if "run_delay" in box else
                    thread_run_delay(box["tid"]) if "tid" in box else float("nan"),
                    woke_at=(t_woke, c_woke, q_woke),  # see _solve_step: what the answer spent after it resumed
                    cut_off_s=cut - t0)  # when the cut-off came, in seconds after the step's own start
        if not done:
            self.solver.stop(hold=True)  # its result waits for this answer (answered(), at the end of __call__)
            yielded = yield_core(box.get("tid"))  # a solver call still running in C shares the core less with the answer
            box["cut_off"] = True
            t_cut = time.perf_counter()
            engine_cpu = _thread_cpu(worker, box)
            step = self.solver.answer_now()
            if self.node_limit is not None:  # the budget took longer than the limit: the clock decided this step
                step.message = step.message.replace("time limit: cut off", "wall-clock safety net: cut off at the "
                                                    "time limit before the work limit", 1)
            step.info["cut_off_at"] = t_cut
            step.info["engine_yielded"] = yielded
            step.info["engine_cpu_time"] = engine_cpu
            step.info.update(wake)
            step.solve_time = time.perf_counter() - t0
            return step
        step = self._finish_running()
        step.info["cut_off"] = False
        step.info["engine_cpu_time"] = box["cpu"]
        step.info.update(wake)
        return step

    def _safety(self, start: float) -> Optional[float]:
        """Under a work budget with the cut-off: the step's time limit (a :func:`time.perf_counter` value), at which a
        solver call stops as a safety net (:meth:`NetworkEngine.solve`), so that a call answered at the cut-off does
        not run on into the next step; ``None`` otherwise (without the cut-off the budget alone decides)."""
        return start + float(self.time_limit) if self.node_limit is not None and self.cut_off else None

    def _cut_off(self, start: float) -> float:
        """The cut-off of a call that started at ``start`` (a :func:`time.perf_counter` value): ``start + time_limit`` less
        the time kept for the answer (see :meth:`_engine_solve`)."""
        answer_s = min(max(0.5 * self.reserve, self._fallback_s, self._answer_s, CUT_OFF_MIN_S),
                       RESERVE_MAX_SHARE * self.time_limit)
        return start + float(self.time_limit) - answer_s

    def _fallback_until(self, start: float) -> Optional[float]:
        """The deadline of the fallback's repairs in a call that started at ``start`` (a :func:`time.perf_counter`
        value): ``start + time_limit`` less :data:`FALLBACK_POST_SHARE` of the limit, at least
        :data:`FALLBACK_POST_MIN_S` (see :meth:`_fallback`); ``None`` without a time limit."""
        if self.time_limit is None:
            return None
        tl = float(self.time_limit)
        return start + tl - max(FALLBACK_POST_SHARE * tl, FALLBACK_POST_MIN_S)

    def _previous_ended(self, start: float, t0: float) -> Optional[dict]:
        """Wait for a solve that the previous step answered at its cut-off, until this step's own cut-off at most.

        ``None`` when no solve runs or it has ended (:meth:`_finish_running` has then taken its result). When it
        still runs at this step's cut-off, the record of the wait (``cut_off_s``, ``wake_lag``, ``wake_runqueue`` and
        the readings from which the step's end computes ``after_wake``, as in :meth:`_engine_solve`). Such a solve
        was asked to stop at the previous cut-off, but a solver call ends only at its next check of the time, and on
        a loaded machine its thread waits for a core. The step then
        answers without a solve (:meth:`_fallback`: the shifted plan when it passes the program's checks) and the
        next step waits for that solve again. Without a time limit or the cut-off no solve runs on. The wait ends
        when this thread gets the interpreter lock back: held by that solve's thread, lowered at its cut-off
        (:func:`flnotes.config.yield_core`) while another process takes the other core, it can end well after the
        cut-off (``info["previous_wait"]`` says so; with a second CPU-bound process, up to 2 t_s was seen at
        t_s = 20 ms).
        """
        if self._running is None:
            return None
        if self.time_limit is not None and self.cut_off:
            worker, box, _ = self._running
            cut, queued = self._cut_off(start), thread_run_delay()
            if not _wait_for(worker, box["done"], max(cut - time.perf_counter(), 0.0)):
                t_woke, c_woke, q_woke = time.perf_counter(), time.thread_time(), thread_run_delay()
                return dict(cut_off_s=cut - t0, wake_lag=max(t_woke - cut, 0.0), wake_runqueue=q_woke - queued,
                            woke_at=(t_woke, c_woke, q_woke))
        self._finish_running()
        return None

    def _finish_running(self) -> Optional[StepResult]:
        """Wait for the solve of :meth:`_engine_solve` to end; re-raise its error; measure how late it was after
        its budget (see :attr:`reserve`). Returns its result, ``None`` when no solve was running."""
        if self._running is None:
            return None
        worker, box, budget = self._running
        self.solver.answered()  # never wait for a solve that waits for the answer (see NetworkEngine.stop)
        _wait_for(worker, box["done"])
        self._held.release()  # the settings the solve kept (see __call__), set back in the caller's thread
        self._running = None
        self.solver.go()
        if "step" not in box and "error" not in box:  # never started (interrupted before)
            return None
        if "error" in box:
            if box.get("cut_off"):
                box["error"].add_note("raised by the solve that the previous step answered at its cut-off")
            raise box["error"]
        step = box["step"]
        if budget is not None:  # late after the limit the engine was given (see _engine_solve)
            self._measure_late(step.solve_time - box.get("limit", budget), box.get("cpu", step.solve_time),
                               step.solve_time)
        return step

    def _measure_late(self, late: float, cpu: float, wall: float) -> None:
        """Keep the engine's lateness after its budget (see :attr:`reserve`), scaled by the share of its solve that
        was its own CPU work (``cpu / wall``): the time the machine gave to other processes is not kept back."""
        if late > 0.0:
            self._late_s = max(self._late_s, late * min(1.0, max(cpu, 0.0) / max(wall, 1e-12)))

    # ------------------------------------------------------------------ the fallback
    def _engine_time(self, start: float) -> Optional[float]:
        """The seconds left for the engine: the time limit less what this step has spent and :attr:`reserve`."""
        if self.time_limit is None or self.node_limit is not None:  # a work budget: no clock inside the engine
            return None
        left = self.time_limit - (time.perf_counter() - start) - self.reserve
        return max(left, 1e-9)  # positive: the engine then returns at its first check of the time

    def _fallback(self, z: Array, R: Array, step: StepResult, shifted, t0: Optional[float] = None) -> StepResult:
        """No plan from this solve: apply :meth:`fallback_plan`, flagged, the solve's status and message kept.

        Under a time limit its repairs stop at ``t0 + time_limit`` less :data:`FALLBACK_POST_SHARE` of the limit
        (at least :data:`FALLBACK_POST_MIN_S`)
        (``deadline`` of :func:`flnotes.mpc.fallback.fallback_plan`; the first input is made admissible whatever the
        time), and its CPU time is what :attr:`reserve` keeps back for it. The engine's first incumbent that its
        cut-off stopped while it was built (``info["repair_state"]`` of :meth:`NetworkEngine.answer_now`) is continued
        there, not built again (``info["repair_resumed_at"]``: the step it went on from, where the plan applied is
        that build continued to its end; ``None`` otherwise).

        When the fallback plan satisfies the whole program (:meth:`Prediction.feasible`), its optimality gap is
        recorded against a valid lower bound of eq. (MPC_form_miqp): the optimum ``J_c`` of the QP without the
        network, or the engine's bound at a time limit when it is larger. Otherwise ``bound`` and ``gap`` are NaN.
        """
        f, _ = self.pred.linear(z, R)
        engine_bound = step.bound
        deadline = None if t0 is None or not self.fallback_deadline else self._fallback_until(t0)
        resume = step.info.pop("repair_state", None)  # the engine's first incumbent, cut short at the cut-off
        c_fb = time.thread_time()
        Z, V, what, ok = fallback.fallback_plan(self.pred, z, shifted, f=f,
                                                qp_repair_failed=bool(step.info.get("repair_failed")),
                                                deadline=deadline, infeasible=step.status == "infeasible",
                                                resume=resume)
        # the step the engine's cut-off build went on from, where the plan applied is that build, continued to its end
        step.info["repair_resumed_at"] = resume.k if resume is not None and what.startswith(fallback.CONTINUED) else None
        self._fallback_s = max(self._fallback_s, time.thread_time() - c_fb)
        step.v, step.z_pred, step.v_pred = V[0].copy(), Z, V
        step.objective = self.cost(Z, V, R)
        step.fallback, step.input_admissible = True, ok
        step.message = (step.message + f"; applied {what}").lstrip("; ")
        step.bound, step.gap = np.nan, np.nan
        if self.plan_feasible(Z, V):
            self._record_gap(z, R, step, engine_bound if step.status == "time_limit" else -np.inf)
        return step

    def _record_gap(self, z: Array, R: Array, step: StepResult, bound: float) -> None:
        """``bound`` and ``gap`` of a plan that satisfies the program: the larger of ``bound`` (a valid lower bound,
        or ``-inf``) and the optimum of the QP without the network, a lower bound of eq. (MPC_form_miqp)."""
        f, c0 = self.pred.linear(z, R)
        _, fq, _ = self.pred.relaxation(f, z)
        bound = max(fq + c0, bound if np.isfinite(bound) else -np.inf)
        if np.isfinite(bound):
            step.bound = min(bound, step.objective)
            step.gap = (step.objective - step.bound) / max(1.0, abs(step.objective))

    def shifted_plan(self, z: Array) -> Optional[tuple[Array, Array]]:
        """The previous plan shifted by one step, re-predicted from the measured ``z``.

        Its new last input is ``K_f z(N_p)`` when a terminal set with a gain ``K_f`` is given (the candidate of
        the recursive-feasibility argument), else :meth:`feasible_tail`. ``None`` without a previous plan.
        """
        if self._plan is None:
            return None
        V = self._plan[1]
        V = np.vstack([V[1:], V[-1:]])
        Z = self.pred.predict(z, V)
        V[-1] = (self.K_terminal @ Z[-2] if self.K_terminal is not None
                 else fallback._feasible_tail(self.pred, Z[-2], V[-1], last=True))
        return self.pred.predict(z, V), V

    def repair_plan(self, z: Array, v_guess: Array, first: bool = True) -> tuple[Array, Array]:
        """:func:`flnotes.mpc.fallback.repair_plan`: a plan built step by step from ``v_guess`` ((N_p, m) or flat).

        ``z`` and ``v_guess`` must be finite numbers of these shapes and ``first`` True or False (``ValueError``
        naming the argument otherwise)."""
        return fallback.repair_plan(self.pred, z, v_guess, first)

    def feasible_tail(self, z: Array, v_guess: Array, last: bool = False) -> Array:
        """:func:`flnotes.mpc.fallback.feasible_tail`: an admissible input closest to ``v_guess`` (m,) at ``z`` (n_z,).

        Both must be finite numbers and ``last`` True or False (``ValueError`` naming the argument otherwise)."""
        return fallback.feasible_tail(self.pred, z, v_guess, last=last)

    def fallback_plan(self, z: Array) -> tuple[Array, Array, str, bool]:
        """:func:`flnotes.mpc.fallback.fallback_plan` from the measured ``z`` and the shifted previous plan."""
        z = as_state(z, self.n_z, "z")
        return fallback.fallback_plan(self.pred, z, self.shifted_plan(z))

    def safe_input(self, z: Array, v_guess: Array) -> tuple[Array, bool]:
        """:func:`flnotes.mpc.fallback.safe_input`: an admissible input, or the least-violation one."""
        return fallback.safe_input(self.pred, as_state(z, self.n_z, "z"), as_vector(v_guess, self.m, "v_guess"))

    # ------------------------------------------------------------------ statistics
    def stats(self) -> dict:
        """Per-step statistics of :attr:`history` as arrays (one entry per call)."""
        h = self.history
        return dict(status=[s.status for s in h], wall_ms=np.array([s.solve_time for s in h]) * 1e3,
                    gap=np.array([s.gap for s in h]), nodes=np.array([s.nodes for s in h]),
                    n_binaries=np.array([s.n_binaries for s in h]),
                    encoded=np.array([len(s.encoded_steps) for s in h]), rounds=np.array([s.rounds for s in h]),
                    screened=np.array([s.screened for s in h], bool), fallback=np.array([s.fallback for s in h], bool),
                    warm_started=np.array([s.warm_started for s in h], bool))

    def summary(self) -> dict:
        """Min/max/mean time per step (ms), time-limit hits (``cut_offs`` of them answered at the cut-off), fallbacks,
        screened steps, binaries."""
        if not self.history:
            return dict(steps=0)
        s = self.stats()
        mi = ~s["screened"]
        return dict(
            steps=len(self.history), ms_min=float(s["wall_ms"].min()), ms_max=float(s["wall_ms"].max()),
            ms_mean=float(s["wall_ms"].mean()), ms_median=float(np.median(s["wall_ms"])),
            time_limit_hits=int(sum(st == "time_limit" for st in s["status"])),
            cut_offs=int(sum(bool(r.info.get("cut_off")) for r in self.history)),
            safety_net_hits=int(sum(bool(r.info.get("safety_net")) for r in self.history)),
            fallbacks=int(s["fallback"].sum()), screened=int(s["screened"].sum()), miqp_steps=int(mi.sum()),
            nodes_mean=float(s["nodes"][mi].mean()) if mi.any() else 0.0, binaries_full=self.n_binaries_full,
            binaries_mean=float(s["n_binaries"][mi].mean()) if mi.any() else 0.0,
            binaries_max=int(s["n_binaries"][mi].max()) if mi.any() else 0,
            encoded_mean=float(s["encoded"][mi].mean()) if mi.any() else 0.0,
            non_optimal=int(sum(st != "optimal" for st in s["status"])))

    def __repr__(self) -> str:
        term = ", terminal set" if self.terminal is not None else ""
        return (f"MPC({self.system.name}, N_p={self.N}, ts={self.ts}, {self.options}{term}, "
                f"time_limit={self.time_limit}" + (f", cut_off={self.cut_off}" if self.time_limit is not None else "")
                + (f", work_limit={self.node_limit} nodes" if self.node_limit is not None else "")
                + ")")
