"""SCIP back-end (PySCIPOpt): MILPs and mixed-integer QPs (epigraph of the quadratic cost), the reference solver.

Part of :mod:`flnotes.solvers` (see its docstring for what "optimal" means and the tolerance policy).
"""
from __future__ import annotations

import functools
import numbers
import os
import re
import sys
import threading
import time
from typing import Optional

import numpy as np
import scipy.sparse as sp

from .base import Solver, _require, make_solver
from .problem import _INF, FEAS_TOL, MIQP, Array, MIQPResult, _result

#: SCIP status -> result status. "optimal" and "gaplimit" (the requested gap is proven) are proofs; the limits
#: return the incumbent without proof; "unbounded", "inforunbd", "unknown", "terminate" are errors.
SCIP_STATUS = {"optimal": "optimal", "gaplimit": "optimal", "infeasible": "infeasible",
               "timelimit": "time_limit", "nodelimit": "time_limit", "totalnodelimit": "time_limit",
               "stallnodelimit": "time_limit", "memlimit": "time_limit", "sollimit": "time_limit",
               "bestsollimit": "time_limit", "restartlimit": "time_limit", "userinterrupt": "time_limit",
               "primallimit": "time_limit", "duallimit": "time_limit",
               "unbounded": "error", "inforunbd": "error", "unknown": "error", "terminate": "error"}


#: The formulations of a quadratic objective (:class:`ScipSolver`, option ``objective``).
OBJECTIVES = ("separable", "epigraph")

#: Seconds that must be left under a time limit to polish SCIP's point (a HiGHS QP with the integers fixed: 3 to 9 ms
#: on the Quad-1D's programs at N_p = 20, model included); with less, an optimum is returned unpolished as a time limit.
POLISH_MIN_LEFT = 0.003

#: SCIP's settings for a mixed-integer QP (:class:`ScipSolver`, option ``miqp_params``).
MIQP_PARAMS = ("lean", "default")

#: ``miqp_params="lean"``: presolving rounds (SCIP's default -1: until nothing changes). Measured first on the SCIP
#: programs of the book's Quad-1D loops at N_p = 15 and 20 and of 120 diverse states at N_p = 10 (chapter "Making it
#: real-time"): one round took 16-32 % less time in all than unlimited rounds. Measured again side by side with
#: :data:`LEAN_RESTARTS` (``python -m flnotes.bench msd_realtime``, :func:`flnotes.bench.msd_realtime.scip_settings_runs`:
#: CPU time of whole MPC steps, one process, the settings interleaved state by state, two passes; per-state speed-up
#: of none and no restarts against one round and restarts, the two passes' medians, min-max over both): the MSD's 8
#: hardest of 40 cold states x1.22 and x1.23 (1.13-1.56), its Monte Carlo loop (3 scenarios x 3 s, the 12 steps that
#: reached SCIP) x1.21 and x1.21 (1.03-1.43), the Quad-1D loop at N_p = 20 (the 6 of 60 steps that reached SCIP) x1.25 and x1.21
#: (1.13-1.46), at N_p = 15 (1 of 60 steps) x1.15 and x1.06, the MSD with the (30, 30, 30) network of the size study
#: (7 of 10 cold states) x1.09 and x1.10 (1.06-1.16), the Quad-1D with the (20, 20, 20) network at N_p = 20 (6 of 8
#: cold states) x1.17 and x1.13 (0.94-1.30); the per-state ratio of one setting's two passes lay within
#: 0.90-1.10 (a median's within 0.96-1.04). Same optima everywhere on those programs. (At N_p = 10 no program of the
#: book's Quad-1D loop reaches SCIP.) Not the default: on badly scaled random mixed-integer QPs (entries of H about
#: 1e5-1e6) no presolving round made SCIP end in "error in LP solver" or stop unproven at its limit where one round
#: proved the optimum at the root; one round stays, until a profile is both faster and as robust.
LEAN_PRESOLVE_ROUNDS = 1

#: ``miqp_params="lean"``: restarts of the root (SCIP's ``presolving/maxrestarts``, default -1: unlimited) and
#: probing rounds in presolving (``propagating/probing/maxprerounds``, default -1: unlimited). On one of the MSD's
#: programs SCIP restarted the root ten times (eleven runs for one node), each run presolving anew, and on another
#: probing took a seventh of a solve. Both off against both on, with one presolving round either way and the same optima
#: everywhere:
#:
#: * whole MPC steps (:func:`flnotes.bench.msd_realtime.scip_settings_runs`, two passes, CPU time; per-state
#:   speed-up over the steps that reached SCIP, each pass's median, min-max over both): the MSD's 24 cold states of
#:   seed 1 (17 reached SCIP) x1.60 and x1.51 (1.25-2.46), its Monte Carlo loop (3 scenarios x 3 s, 13 steps)
#:   x1.54 and x1.55 (0.97-2.89); the book's Quad-1D loop at N_p = 15 (2 steps) x1.17 and x1.37, at N_p = 20
#:   (4 steps) x1.12 and x1.03 (0.82-1.18), where SCIP is a small part of a step; a setting's own two passes lay
#:   within 0.68-1.49 per state;
#: * the programs alone (the 60 SCIP programs of 48 other cold MSD states, seeds 2 and 3, and of the loop; the 25 of
#:   the Quad-1D loops; every setting in turn on each program, the order reversed at every other one): per-program
#:   median x2.01 (0.81-3.23) on the MSD, x1.40 (0.70-2.04) on the Quad-1D; restarts off alone x1.44 and x1.30.
#:
#: No presolving round (with no restarts) was as fast on the programs alone (x2.06 and x1.37) but is not as robust:
#: on 50 badly scaled random mixed-integer QPs (entries of ``H`` of 1e3 to 3e6, big-M rows, a 5 s limit) it stopped
#: unproven or ended in "error" on 5 that one round proved (and proved 2 that one round did not), while one round
#: without restarts and probing searched as with them (the same node counts, or both stopped at the limit, on the 10
#: programs checked).
LEAN_RESTARTS = 0

#: ``miqp_params="lean"``: probing rounds in presolving (``propagating/probing/maxprerounds``); measured together
#: with :data:`LEAN_RESTARTS` (see there).
LEAN_PROBING_ROUNDS = 0


#: What SoPlex (SCIP's LP solver) writes straight to the C streams, whatever SCIP's verbosity (``hideOutput`` does not
#: reach it): with SCIP's feasibility tolerance at 1e-9, an LP tolerance SCIP tightens by its factor 1e-3 for a
#: numerically hard LP is below what SoPlex accepts without GMP, and it says so on file descriptor 2 ("Cannot set
#: feasibility tolerance to small value 1e-12 without GMP - using 1e-10."). Lines that start with one of these are
#: dropped by :class:`_quiet_c_output`; everything else passes.
C_NOTICES = (b"Cannot set feasibility tolerance to small value",)

#: SCIP's own error lines, which its C code writes to file descriptor 2 whatever its verbosity (``[solve.c:4948]
#: ERROR: ... unresolved numerical troubles in LP``, ``EMAISM: numerical violation ...``), and the line cvxpy writes
#: after such a failed call. Inside :class:`_quiet_c_output` they are not written out but kept, for the caller to put
#: in its result's message (:func:`take_solver_errors`): the failure is reported where it is handled.
C_ERRORS = re.compile(rb"\s*(\[[\w./-]+:\d+\] ERROR: |EMAISM: |Error encountered when optimising )")
_ERROR_HEADS = (b"[", b"EMAISM: ", b"Error encountered when optimising ")

_FILTER_LOCK = threading.Lock()
# the SCIP calls running, per filtered descriptor (fd, saved, read end, thread), and the error lines kept
_filter: dict = dict(depth=0, fds=[], errors=[])
_ERRORS_LOCK = threading.Lock()


def _may_become(head: bytes) -> bool:
    """Whether a line's beginning ``head`` (no line end yet) may still become a notice or an error line."""
    return any(n.startswith(head) or head.startswith(n) for n in C_NOTICES + _ERROR_HEADS)


def _split_notices(buf: bytes, final: bool = False) -> tuple[bytes, bytes]:
    """``buf`` less the lines that are notices of :data:`C_NOTICES` or solver errors of :data:`C_ERRORS` (those are
    kept, see :func:`take_solver_errors`): ``(what to write now, what to hold)``. A last piece without its line end
    is held only while it may still become one of them (``final``: nothing is held)."""
    out, parts = [], buf.splitlines(keepends=True)
    hold = b""
    if parts and not parts[-1].endswith((b"\n", b"\r")):
        last = parts.pop()
        if not final and (_may_become(last.lstrip()) or C_ERRORS.match(last)):  # an error line may come in pieces
            hold = last
        else:
            parts.append(last)
    for part in parts:
        if C_ERRORS.match(part):
            with _ERRORS_LOCK:
                _filter["errors"].append(part.strip().decode("utf-8", "replace"))
        elif not part.lstrip().startswith(C_NOTICES):
            out.append(part)
    return b"".join(out), hold


@functools.lru_cache(maxsize=1)
def _printer_reset():
    """SCIP's ``SCIPmessageSetErrorPrintingDefault`` through :mod:`ctypes`, or ``None`` where it is not exported."""
    try:
        import ctypes

        from pyscipopt import scip as _scip_module

        reset = ctypes.CDLL(_scip_module.__file__).SCIPmessageSetErrorPrintingDefault
    except (OSError, AttributeError, ImportError):
        return None
    reset.restype, reset.argtypes = None, []
    return reset


def default_error_printer() -> bool:
    """Give SCIP's process-wide error printer back to SCIP's own (C's ``fputs`` to ``stderr``); whether it could.

    PySCIPOpt's ``Model.redirectOutput`` (which cvxpy's SCIP interface calls on every solve) installs, for the whole
    process, an error printer that writes through Python's ``sys.stderr`` without taking the interpreter lock. A SCIP
    error line (``[solve.c:...] ERROR: ...``) printed by a later solve run without the lock (``optimizeNogil``, as
    :class:`ScipSolver` runs SCIP) then crashes the process (a segmentation fault, seen on the first such line). SCIP
    exports the reset (``SCIPmessageSetErrorPrintingDefault``), which PySCIPOpt does not wrap: it is called through
    :mod:`ctypes` on PySCIPOpt's extension module (its dynamic symbol search covers the SCIP library it loads).
    ``False`` where that library does not export it to :mod:`ctypes` (e.g. on Windows): there, no code of this package
    installs Python's printer (the MPC reference uses :class:`flnotes.solvers.cvxpy_bridge.ScipConic`), and a caller
    that calls ``redirectOutput`` itself must not run this package's SCIP solves after it.

    The reset is made as each solve starts: it does not cover a ``redirectOutput`` (or a ``cp.SCIP`` solve) in
    another thread while a solve of this package runs (a time-limited MPC's engine thread, or the caller's own
    threads). In a process that runs SCIP in threads, solve cvxpy programs with
    :class:`flnotes.solvers.cvxpy_bridge.ScipConic` instead of ``cp.SCIP``."""
    reset = _printer_reset()
    if reset is None:
        return False
    reset()
    return True


def take_solver_errors() -> list:
    """The solver error lines (:data:`C_ERRORS`) the filter of :class:`_quiet_c_output` kept since the last call,
    oldest first; they are forgotten here. Read them after the ``with`` block: its end waits for the filter."""
    with _ERRORS_LOCK:
        out, _filter["errors"] = _filter["errors"], []
    return out


def _forward(r: int, saved: int) -> None:
    """Copy what arrives on the pipe ``r`` to the descriptor ``saved``, without the notices, until the pipe closes."""
    pending = b""
    while True:
        try:
            chunk = os.read(r, 65536)
        except OSError:
            break
        if not chunk:
            break
        now, pending = _split_notices(pending + chunk)
        while now:
            try:
                now = now[os.write(saved, now):]
            except OSError:
                break
    now, _ = _split_notices(pending, final=True)
    if now:
        try:
            os.write(saved, now)
        except OSError:
            pass


def _flush_c_streams() -> None:
    """Flush Python's and C's buffered output, so that it goes out on the descriptor it was written for."""
    for f in (sys.stdout, sys.stderr):
        try:
            f.flush()
        except Exception:  # a closed or replaced stream: nothing to flush
            pass
    try:
        import ctypes

        ctypes.CDLL(None).fflush(None)
    except Exception:  # pragma: no cover - no C library to flush
        pass


def _filter_enter() -> None:
    """A SCIP call starts: file descriptors 1 and 2 go through a filter that drops :data:`C_NOTICES` (the first of
    the calls running at once starts it)."""
    with _FILTER_LOCK:
        _filter["depth"] += 1
        if _filter["depth"] > 1:
            return
        _flush_c_streams()
        for fd in (1, 2):
            try:
                saved = os.dup(fd)
                r, w = os.pipe()
                os.dup2(w, fd)
                os.close(w)
            except OSError:
                continue
            t = threading.Thread(target=_forward, args=(r, saved), name=f"flnotes-c-output-{fd}", daemon=True)
            t.start()
            _filter["fds"].append((fd, saved, r, t))


def _filter_leave() -> None:
    """A SCIP call ends: the last one running gives file descriptors 1 and 2 back (what the filter holds is written
    first)."""
    with _FILTER_LOCK:
        if _filter["depth"] == 0:
            return
        _filter["depth"] -= 1
        if _filter["depth"] > 0:
            return
        _flush_c_streams()
        for fd, saved, r, t in _filter["fds"]:
            os.dup2(saved, fd)  # the pipe's last write end closes: the forwarding thread reads to its end
            t.join(5.0)
            os.close(saved)
            os.close(r)
        _filter["fds"].clear()


def c_output_filtered() -> bool:
    """Whether file descriptors 1 and 2 go through the filter of :class:`_quiet_c_output` now (a SCIP call runs)."""
    return _filter["depth"] > 0


class _quiet_c_output:
    """Inside a ``with`` block (a SCIP call), file descriptors 1 and 2 pass through a filter that drops the notices
    of :data:`C_NOTICES` and forwards everything else. The filter stays while any such call runs, in any thread: a
    SCIP call that runs on after its caller answered at a cut-off drops its notices too, and what the rest of the
    process writes meanwhile still comes out."""

    def __enter__(self):
        _filter_enter()
        return self

    def __exit__(self, *exc):
        _filter_leave()
        return False


def _hinf(a: Array) -> Array:
    from highspy import kHighsInf
    out = np.asarray(a, float).copy()
    out[out >= _INF] = kHighsInf
    out[out <= -_INF] = -kHighsInf
    return out


# ---------------------------------------------------------------------------
# SCIP
# ---------------------------------------------------------------------------
#: SCIP parameters and values :meth:`ScipSolver.check_options` has set on a model without error.
_CHECKED_PARAMS: set = set()

#: SCIP parameters that :class:`ScipSolver` sets itself (at each solve, or from an option): refused in ``params``.
RESERVED_PARAMS = {"limits/time": "solve(time_limit=...)", "limits/gap": "solve(gap=...)",
                   "limits/absgap": "solve(gap=...)", "limits/totalnodes": "solve(node_limit=...)",
                   "numerics/feastol": "the option feastol", "parallel/maxnthreads": "the option threads"}

#: Groups of SCIP parameters refused in ``params``, and why.
RESERVED_GROUPS = {"limits": "stops the search early: a stop is a status the back-end maps (give time_limit= or "
                             "node_limit= to solve())",
                   "timing": "changes how the time limit is measured (the back-end's is the wall clock)",
                   "visual": "writes files", "display": "prints (the back-end is silent)"}

_KIND_NAMES = {(bool, np.bool_): "True or False", str: "a string", numbers.Integral: "an integer",
               numbers.Real: "a finite number"}


def _within_gap(J: float, bound: float, gap: float) -> bool:
    """Whether a point of cost ``J`` is optimal to the relative ``gap`` given the lower ``bound``."""
    return bool(J - bound <= gap * max(1.0, abs(J)) + 1e-12)


def _needs_polish(p: MIQP, status: str, w: Array, bound: float, gap: float) -> bool:
    """Whether SCIP's point ``w`` of a mixed-integer QP ``p`` is polished (:meth:`ScipSolver._polish`): a point at a
    limit, and an optimum whose point misses the gap on its true cost or the program's rows; an optimum whose own
    point meets both is returned as SCIP found it."""
    if status == "time_limit":
        return True
    return status == "optimal" and not (p.violation(w) <= FEAS_TOL and _within_gap(p.objective(w), bound, gap))


class ScipSolver(Solver):
    """SCIP (Bestuzheva et al. 2021) through PySCIPOpt: the reference solver for mixed-integer QPs.

    The quadratic objective (option ``objective``). ``"separable"`` (default for a program with ``H``): with
    ``H_S = Q diag(lam) Q'`` the eigendecomposition of ``H`` on the variables ``S`` it touches,
    ``0.5 w'Hw = sum_i 0.5 lam_i y_i^2`` with ``y = Q' w_S``; the model gets ``y`` (linear rows) and one
    epigraph ``0.5 lam_i y_i^2 <= s_i`` per positive ``lam_i`` and minimizes ``sum_i s_i + c'w + c0``, the
    extended (disaggregated) formulation whose tangent cuts approximate each one-dimensional term on its own (on
    the book's Quad-1D programs they closed the gap far faster than those of one epigraph; not on every program, see
    below). ``"epigraph"``: ``min t + c'w + c0`` s.t. ``0.5 w'Hw <= t``. Both are the
    same program. Measured side by side against the lean profile (``python -m flnotes.bench msd_realtime``, see
    :data:`LEAN_PRESOLVE_ROUNDS`), one epigraph with the lean settings was as fast or faster on the MSD (hardest cold
    states x1.35 and x1.40 where ``"separable"`` gave x1.22 and x1.23, loop x1.24 and x1.23 against x1.21 and x1.21,
    the (30, 30, 30) network x1.09 and x1.13 against x1.09 and x1.10) but slower on the book's Quad-1D loop at N_p =
    20 (x0.86 and x0.83 against x1.25 and x1.21, per state down to x0.39), on programs of 56 to 105 binaries like the
    MSD loop's 56 to 220: no rule by size separates them, and ``"separable"`` stays the default. Option
    ``miqp_params`` (a program with ``H`` only): ``"lean"`` (default) turns SCIP's aggregation separator (c-MIR, flow
    cover, knapsack cover cuts) and its primal heuristics off, presolves :data:`LEAN_PRESOLVE_ROUNDS` round (one),
    where the book's big-M programs spent much of their time without gain, without probing
    (:data:`LEAN_PROBING_ROUNDS`), and never restarts the root (:data:`LEAN_RESTARTS`) (chapter "Making it
    real-time", ``python -m flnotes.bench mpc`` and ``msd_realtime``);
    ``"default"`` keeps SCIP's settings. Option ``params`` sets any SCIP parameter after these. Either never changes
    the optimum, only the time to prove it. The model is persistent: between solves it is returned to the problem
    stage (``freeTransform``) and bounds, row sides and coefficients are changed in place (``chgVarLb/Ub``,
    ``chgLhs/chgRhs``, ``chgCoefLinear``); the linear objective is reset with ``setObjective``.
    A warm start is added as a solution (``addSol``).

    ``c0`` is the model's objective offset, so SCIP's relative gap is that of the program's cost. SCIP's gap is still
    judged on its own values (the epigraph's terms met to its tolerance), so an optimum is checked on its point's true
    cost (polished first where that misses the gap, :meth:`_polish`): where that lies further above the bound than the
    gap asked (a stored program, with ``c0`` left out of the model: 7.4e-6 for 1e-6), the program is solved once more
    in the step ``d`` from that point (:meth:`_recentred`: the same program, whose quadratic terms are then small); if
    the gap still fails the status is ``"time_limit"`` where the time limit or the call's node budget stopped that
    solve (it gets what the first solve left of ``node_limit``; the point and bound kept, unproven), else ``"error"``,
    saying so; never ``"optimal"``.
    """

    name = "scip"
    supports_node_limit = True
    _recentring = False  # a model of the program about another point (:meth:`_recentred`)
    OPTIONS = ("threads", "params", "feastol", "objective", "miqp_params")

    @classmethod
    def _check_values(cls, options: dict) -> None:
        for key, allowed in (("objective", OBJECTIVES), ("miqp_params", MIQP_PARAMS)):
            if key in options and not (isinstance(options[key], str) and options[key] in allowed):
                raise ValueError(f"the SCIP option {key} must be one of {allowed}, got {options[key]!r}")
        params = options.get("params", {})
        for k in params:
            if not isinstance(k, str):
                raise ValueError(f"the SCIP option params takes SCIP's parameter names (strings), got {k!r}")
            if k in RESERVED_PARAMS:
                raise ValueError(f"the SCIP parameter {k!r} (option params) is set by {RESERVED_PARAMS[k]}: "
                                 f"give it there, not in params")
            if k.split("/")[0] in RESERVED_GROUPS:
                raise ValueError(f"the SCIP parameter {k!r} (option params) {RESERVED_GROUPS[k.split('/')[0]]}")
        # the options with a SCIP parameter behind them are checked by SCIP too (its ranges, e.g. feastol <= 1e-1)
        native = [("option feastol", "numerics/feastol", options["feastol"])] if "feastol" in options else []
        native += [("option threads", "parallel/maxnthreads", options["threads"])] if "threads" in options else []
        native += [(f"parameter {k!r} (option params)", k, v) for k, v in params.items()]
        new = [(what, k, v) for what, k, v in native if (k, repr(v)) not in _CHECKED_PARAMS]
        if new:  # each on a model of its own (a few ms, once per parameter and value)
            m = _require("scip").Model()
            m.hideOutput()
            for what, k, v in new:
                try:
                    cur = m.getParam(k)
                except (KeyError, LookupError):
                    raise ValueError(f"the SCIP {what}: SCIP has no parameter {k!r}") from None
                kind = ((bool, np.bool_) if isinstance(cur, bool) else str if isinstance(cur, str) else
                        numbers.Integral if isinstance(cur, int) else numbers.Real)
                is_bool = isinstance(v, (bool, np.bool_))
                ok = is_bool if isinstance(cur, bool) else (isinstance(v, kind) and not is_bool)
                if ok and kind is numbers.Real:
                    try:
                        ok = bool(np.isfinite(float(v)))
                    except OverflowError:
                        ok = False
                if not ok:
                    raise ValueError(f"the SCIP {what} must be {_KIND_NAMES[kind]} ({k} is), got {v!r}")
                v = v.item() if isinstance(v, np.generic) else v
                try:
                    m.setParam(k, v)
                except (ValueError, TypeError, OverflowError, LookupError) as exc:
                    raise ValueError(f"the SCIP {what} = {v!r} is refused by SCIP ({k}): {exc}") from None
                _CHECKED_PARAMS.add((k, repr(v)))

    def _build(self) -> None:
        scip = _require("scip")
        p = self.problem
        m = scip.Model()
        m.hideOutput()
        m.setParam("parallel/maxnthreads", int(self.options.get("threads", 1)))
        # tighter than SCIP's default 1e-6: the comparisons between back-ends are at 1e-6 relative
        m.setParam("numerics/feastol", float(self.options.get("feastol", 1e-9)))
        for key, allowed in (("objective", OBJECTIVES), ("miqp_params", MIQP_PARAMS)):
            if key in self.options and (p.H is None or self.options[key] not in allowed):
                raise ValueError(f"the SCIP option {key}={self.options[key]!r} " + (
                    f"must be one of {allowed}" if p.H is not None else
                    "applies to a program with a quadratic objective (H is None here): drop it"))
        if p.H is not None and self.options.get("miqp_params", "lean") == "lean":
            m.setHeuristics(scip.SCIP_PARAMSETTING.OFF)
            m.setParam("separating/aggregation/freq", -1)
            m.setParam("presolving/maxrounds", LEAN_PRESOLVE_ROUNDS)
            m.setParam("presolving/maxrestarts", LEAN_RESTARTS)
            m.setParam("propagating/probing/maxprerounds", LEAN_PROBING_ROUNDS)
        for k, v in self.options.get("params", {}).items():
            m.setParam(k, v.item() if isinstance(v, np.generic) else v)
        self._inf = m.infinity()
        self._x = [m.addVar(name=f"w{i}", vtype="I" if p.integrality[i] else "C", lb=self._s(p.lb[i]),
                            ub=self._s(p.ub[i])) for i in range(p.n)]
        A = p.A
        self._cons = []
        for r in range(p.m):
            s, e = A.indptr[r], A.indptr[r + 1]
            expr = scip.quicksum(float(a) * self._x[j] for a, j in zip(A.data[s:e], A.indices[s:e]))
            cons = m.addCons(self._range(expr, p.rl[r], p.ru[r]), name=f"r{r}")
            self._cons.append(cons)
        self._t, self._y, self._sq, self._lam, self._Q, self._S = None, [], [], None, None, None
        if p.H is not None and self.options.get("objective", "separable") == "separable":
            H = p.H.toarray()
            S = np.flatnonzero(np.any(H != 0.0, axis=1))
            lam, Q = np.linalg.eigh(H[np.ix_(S, S)])
            keep = lam > 1e-12 * max(float(lam.max(initial=0.0)), 1e-300)
            if np.any(lam[~keep] < -1e-9 * max(float(np.abs(lam).max(initial=0.0)), 1.0)):
                raise ValueError("H is not positive semidefinite: objective='separable' needs a convex objective; "
                                 "objective='epigraph' hands a nonconvex one to SCIP's spatial branch and bound")
            self._lam, self._Q, self._S = lam[keep], Q[:, keep], S
            for i in range(self._lam.size):  # y_i = q_i' w_S and 0.5 lam_i y_i^2 <= s_i
                y = m.addVar(name=f"y{i}", lb=None, ub=None)
                m.addCons(y - scip.quicksum(float(q) * self._x[j] for q, j in zip(self._Q[:, i], S) if q != 0.0) == 0,
                          name=f"eig{i}")
                s_i = m.addVar(name=f"s{i}", lb=0.0, ub=None)
                m.addCons(0.5 * float(self._lam[i]) * y * y - s_i <= 0, name=f"epigraph{i}")
                self._y.append(y)
                self._sq.append(s_i)
        elif p.H is not None:
            self._t = m.addVar(name="t", lb=None, ub=None)
            Hu = sp.triu(p.H, format="coo")
            quad = scip.quicksum((0.5 if i == j else 1.0) * float(v) * self._x[i] * self._x[j]
                                 for i, j, v in zip(Hu.row, Hu.col, Hu.data))
            m.addCons(quad - self._t <= 0, name="epigraph")
        self._m, self._scip = m, scip
        self._polisher = None  # a HiGHS QP with the integers fixed, built at the first polish
        self._set_objective()

    def _s(self, v: float):
        return None if abs(v) >= _INF else float(v)

    def _range(self, expr, lo: float, hi: float):
        if lo == hi:
            return expr == float(lo)
        lo_f, hi_f = lo > -_INF, hi < _INF
        if lo_f and hi_f:
            return (float(lo) <= expr) <= float(hi)
        if lo_f:
            return expr >= float(lo)
        if hi_f:
            return expr <= float(hi)
        return expr <= self._inf

    def _set_objective(self) -> None:
        p, scip = self.problem, self._scip
        nz = np.flatnonzero(p.c)
        obj = scip.quicksum(float(p.c[i]) * self._x[i] for i in nz)
        if self._t is not None:
            obj = obj + self._t
        if self._sq:
            obj = obj + scip.quicksum(self._sq)
        # c0 is the model's objective offset: SCIP's relative gap is then that of the program's cost (without it, a
        # cost of 1 made of terms of 3.6e4 was called optimal 1.17 above its bound for a gap of 1e-4)
        self._m.setObjective(obj + float(p.c0), "minimize", clear=True)

    def _push(self, changed: dict) -> None:
        m, p = self._m, self.problem
        m.freeTransform()
        if "c" in changed or "c0" in changed:
            self._set_objective()
        if "bounds" in changed:
            for i in range(p.n):
                # widen first, so that lb <= ub holds at every moment
                m.chgVarLb(self._x[i], None)
                m.chgVarUb(self._x[i], None)
                m.chgVarLb(self._x[i], self._s(p.lb[i]))
                m.chgVarUb(self._x[i], self._s(p.ub[i]))
        if "rows" in changed:
            for r, cons in enumerate(self._cons):
                m.chgLhs(cons, None)
                m.chgRhs(cons, None)
                m.chgLhs(cons, self._s(p.rl[r]))
                m.chgRhs(cons, self._s(p.ru[r]))
        if "A" in changed:
            vals = p.A.data
            for k in changed["A"]:
                m.chgCoefLinear(self._cons[int(self._Arow[k])], self._x[int(self._Acol[k])], float(vals[k]))

    def _solve(self, ws, time_limit, gap, t0) -> MIQPResult:
        m, p = self._m, self.problem
        m.freeTransform()
        m.setParam("limits/time", float(time_limit) if time_limit else 1e20)
        nl = getattr(self, "_node_limit", None)
        m.setParam("limits/totalnodes", -1 if nl is None else int(nl))  # a work budget (Solver.solve)
        m.setParam("limits/gap", 0.5 * gap)  # SCIP divides by min(|primal|, |dual|): keep a margin
        m.setParam("limits/absgap", 0.5 * gap)
        if ws is not None and self._warm_ok(ws):
            sol = m.createSol()
            for i in range(p.n):
                m.setSolVal(sol, self._x[i], float(ws[i]))
            if self._t is not None:
                m.setSolVal(sol, self._t, float(0.5 * ws @ (p.H @ ws)) + 1e-9)
            if self._sq:
                y = self._Q.T @ np.asarray(ws, float)[self._S]
                for i in range(y.size):
                    m.setSolVal(sol, self._y[i], float(y[i]))
                    m.setSolVal(sol, self._sq[i], float(0.5 * self._lam[i] * y[i] ** 2) + 1e-9)
            m.addSol(sol, free=True)
        try:
            default_error_printer()  # SCIP's own error printer: a Python one would run without the lock here
            with _quiet_c_output():  # SoPlex prints tolerance notices straight to the C streams
                m.optimizeNogil()  # other threads run meanwhile (a caller may answer while this call runs on)
        except Exception as exc:  # e.g. "SCIP: error in LP solver!": SCIP's own lines belong to this failure, not
            said = take_solver_errors()  # to the next solve's result
            if said:
                raise type(exc)(f"{exc} (SCIP said: {' / '.join(said)})") from exc
            raise
        raw = m.getStatus()
        st, said = raw, take_solver_errors()
        if said:  # SCIP's error lines, kept from the C streams: they belong to this result (its status is SCIP's,
            st += f" (SCIP said: {' / '.join(said)})"  # and its point is checked below like any other)
        nodes = m.getNNodes() if p.is_mip else 0
        w = None
        if m.getNSols() > 0:
            best = m.getBestSol()
            w = np.array([m.getSolVal(best, x) for x in self._x])
        try:
            bound = m.getDualbound()  # c0 included (the objective's offset)
        except Exception:
            bound = -np.inf
        if abs(bound) >= 1e19:
            bound = -np.inf
        status = SCIP_STATUS.get(raw, "error")
        left = None if not time_limit else time_limit - (time.perf_counter() - t0)
        if w is not None and p.H is not None and _needs_polish(p, status, w, bound, gap):
            late = left is not None and left <= POLISH_MIN_LEFT
            if not late:
                w, late = self._polish(w, left)
            if status == "optimal" and late:
                # SCIP's point without the polish: its objective may be off by the epigraph's tolerance, no proof
                status = "time_limit"
                st += " (the time limit came before the point was polished)"
        if status == "optimal" and (w is None or p.violation(w) > FEAS_TOL):
            status = "error"
            st += ": no point" if w is None else f": the point violates the program by {p.violation(w):.1e}"
        if (status == "optimal" and p.H is not None and not self._recentring
                and not _within_gap(p.objective(w), bound, gap)):
            # SCIP's gap is judged on its own values (the epigraph's terms met to its tolerance), not on its point's
            # true cost
            w, bound, status, st, more = self._recentred(w, bound, gap, time_limit, t0, st, nodes)
            nodes += more
        if status == "time_limit" and w is not None and p.violation(w) > FEAS_TOL:
            w = None
        if status == "infeasible":
            return _result(p, "infeasible", None, np.inf, nodes, t0, self.name, st)
        return _result(p, status, w if status in ("optimal", "time_limit") else None,
                       bound if status != "error" else -np.inf, nodes, t0, self.name, st)

    def _recentred(self, w: Array, bound: float, gap: float, time_limit: Optional[float], t0: float, st: str,
                   nodes: int = 0) -> tuple[Optional[Array], float, str, str, int]:
        """The program again, in the step ``d = w' - w`` from SCIP's (polished) point ``w``, where SCIP's true gap
        exceeds ``gap``.

        ``J(w + d) = J(w) + (c + H w)'d + 0.5 d'Hd``: near ``w`` the quadratic terms are small, so SCIP's relative
        tolerance on them is small in absolute terms too (a binary ``d_i`` stays integer, its bounds shifted to
        ``[-w_i, 1 - w_i]``). Returns ``(point, bound, status, message, nodes)``: the better point with the larger bound
        and ``"optimal"`` where the gap then holds; where it does not, ``"time_limit"`` when the time limit stopped
        that solve or left no time for it (the point feasible and the bound valid, only unproven), otherwise
        ``"error"`` saying so (SCIP's point kept for the caller's information only). The second solve gets what is
        left of the call's node budget after the ``nodes`` of the first (``"time_limit"`` when nothing is left);
        the returned ``nodes`` are those it searched."""
        p = self.problem
        J_w = p.objective(w)
        shifted = MIQP(p.H, p.c + p.H @ w, J_w, p.A, p.rl - p.A @ w, p.ru - p.A @ w, p.lb - w, p.ub - w,
                       p.integrality)
        solver = ScipSolver(shifted, **self.options)
        solver._recentring = True  # once: its own point is not moved again
        nl = getattr(self, "_node_limit", None)
        solver._node_limit = None if nl is None else nl - int(nodes)  # the rest of the call's work budget
        left = None if not time_limit else max(time_limit - (time.perf_counter() - t0), 1e-3)
        go = (not left or left > 1e-3) and (solver._node_limit is None or solver._node_limit >= 1)
        r = solver._solve(np.zeros(p.n), left, gap, time.perf_counter()) if go else None
        more = 0 if r is None else int(r.nodes)
        said = f"{st}; its point lay {(J_w - bound) / max(1.0, abs(J_w)):.1e} (relative) above its bound"
        if r is not None and r.w is not None and r.status in ("optimal", "time_limit"):
            w2 = w + r.w
            w2[p.integrality == 1] = np.round(w2[p.integrality == 1])
            if p.violation(w2) <= FEAS_TOL and p.objective(w2) <= J_w:
                w, J_w = w2, p.objective(w2)
            bound = max(bound, float(r.bound)) if np.isfinite(r.bound) else bound
        if r is not None and _within_gap(J_w, bound, gap):
            return w, bound, "optimal", f"{said}; solved again about that point: {r.message}", more
        if r is None or r.status == "time_limit":
            return w, bound, "time_limit", (f"{said}; the time or node limit came before solving again about that "
                                            f"point proved it optimal to the gap {gap:.0e}"), more
        return (w, bound, "error", f"{said}, also solved again about that point: not optimal to the gap {gap:.0e}",
                more)

    def _polish(self, w: Array, time_limit: Optional[float] = None) -> tuple[Array, bool]:
        """The QP optimum with the integers fixed at ``w``'s (HiGHS), when it is better than ``w``.

        SCIP enforces the epigraph ``0.5 w'Hw <= t`` through cutting planes, to
        a tolerance that is relative: near a zero optimum its point can be off
        by 1e-5 in the objective. Re-solving the convex QP of the same integer
        assignment removes that error and never makes the point worse. Returns
        the point and whether ``time_limit`` stopped the QP (``w`` unchanged then).

        It runs where it serves: on a point at a time limit (a better incumbent), and on an optimum whose point, at
        its true cost, lies further above SCIP's bound than the gap asked. An optimum whose own point already meets
        the gap is returned as SCIP found it: on 24 cold states of the MSD's MPC (``python -m flnotes.bench
        msd_realtime``) SCIP's point lay within 3e-7 (relative) of its bound on every program (25), the polish
        lowered its cost by less than 1e-11 (relative) and took 7 to 62 ms per program. The price: such an optimum
        may lie up to the gap above the best point of its own integer assignment, where the polish returned that
        point (random programs solved with a gap of 1e-3: up to 4.6e-4 above it; with 1e-6: 3.2e-7). Its bound and
        the gap on its true cost are what "optimal" promises, with or without the polish.
        """
        p = self.problem
        ints = p.integrality == 1
        lb, ub = p.lb.copy(), p.ub.copy()
        lb[ints] = ub[ints] = np.clip(np.round(w[ints]), p.lb[ints], p.ub[ints])
        try:
            if self._polisher is None:
                self._polisher = make_solver(MIQP(p.H, p.c, p.c0, p.A, p.rl, p.ru, lb, ub,
                                                  np.zeros(p.n, int)), "highs")
            else:
                self._polisher.update(c=p.c, c0=p.c0, rl=p.rl, ru=p.ru, lb=lb, ub=ub, A=p.A)
            r = self._polisher.solve(time_limit=time_limit)
        except Exception:  # polishing is an improvement, never a requirement
            return w, False
        if r.status == "optimal" and r.w is not None and r.objective < p.objective(w) \
                and p.violation(r.w) <= 1e-7:
            return r.w, False
        return w, r.status == "time_limit"
