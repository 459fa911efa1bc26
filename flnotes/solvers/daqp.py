"""DAQP back-end: dual active-set QP with its own branch and bound over binaries; only exit flag 1 is a proof.

Part of :mod:`flnotes.solvers` (see its docstring for what "optimal" means and the tolerance policy).
"""
from __future__ import annotations

import numbers
import time
from typing import Optional

import numpy as np
import scipy.linalg

from .base import Solver, _confirm, _require, available_backends, make_solver
from .scip import ScipSolver
from .problem import _INF, FEAS_TOL, MIQP, Array, MIQPResult, _result


# ---------------------------------------------------------------------------
# DAQP
# ---------------------------------------------------------------------------

def _confirm_qp(solver, p, backend: str, w, time_limit, gap, t0, claim: str, nodes: int):
    """:func:`flnotes.solvers.base._confirm`, and for a continuous QP that HiGHS (its verifier) fails on, SCIP.

    On an MSD program at the domain's corner DAQP's point failed the check and HiGHS's QP solver ended in "Solve
    error": the step returned "error" where SCIP proves the optimum. (Only here: SCIP's own polisher is a HiGHS QP.)
    """
    out = _confirm(solver, p, backend, w, time_limit, gap, t0, claim, nodes)
    if backend == "highs" and not p.is_mip and out.status == "error":
        left = None if time_limit is None else time_limit - (time.perf_counter() - t0)
        if left is None or left > 1e-3:
            return _confirm(solver, p, "scip", w, time_limit, gap, t0, f"{claim}; highs failed ({out.message})",
                            out.nodes)
    return out

class DaqpSolver(Solver):
    """DAQP (Arnström, Bemporad & Axehill 2022): dual active-set QP with branch and bound over binaries.

    Every variable's bounds become DAQP's "simple bounds"; a binary variable
    gets the ``BINARY`` sense (16: one of its two bounds must hold with
    equality), an equality row or a fixed variable the ``EQUALITY`` sense (5).
    DAQP's branch and bound is depth first and prunes every node whose
    relaxation is not better than ``fval_bound``.

    Positive semidefinite ``H``. DAQP factors ``H``; for the big-M programs
    ``H`` is zero on the network's variables. With ``reg=delta`` (default
    ``1e-6``) ``delta`` is added to the zero diagonal, with the secant of the
    square as linear correction (``reg_mode="secant"``, the default): DAQP
    solves ``J_s(w) = J(w) + 0.5 delta sum_i (w_i - l_i)(w_i - u_i)`` over the
    bounded perturbed variables, which is ``<= J`` on the box and ``= J`` at
    its bounds, hence at every integer point of a binary. The optimum of
    ``J_s`` (exit flag 1 is a proof for the positive definite ``J_s``) is then
    a lower bound on ``J*``, the certified gap at the returned point is
    ``0.5 delta sum_i (w_i - l_i)(u_i - w_i)`` over its continuous variables
    only (zero for the binaries and for every variable at a bound), and a
    point better than an incumbent has ``J_s < J(incumbent)``. The point is
    certified optimal when that gap is within the requested one (the result's
    ``bound``), and verified by SCIP otherwise. ``reg_mode="upper"`` is the
    plain ``J_r = J + 0.5 delta sum_i w_i^2`` with ``J <= J_r <= J + B``,
    ``B = 0.5 delta sum max(l_i^2, u_i^2)`` (a worst case over the box,
    binaries included: on the longer horizons it exceeds the gap at almost
    every step, and each such step was verified by SCIP). With ``reg=None``
    DAQP's proximal-point iterations (``eps_prox``) handle the singular
    directions instead; they end with the undocumented exit flag 4, which is
    no proof (measured up to 12x sub-optimal on the CLF-CBF programs), so
    every such answer is verified. When DAQP stops with an error (cycling on
    the degenerate big-M rows) it is called once more with the regularization
    multiplied by 10 (``reg_retry=True``, default), then with
    ``eps_prox=1e-4``, then the program goes to SCIP.

    Scaling (option ``scale``, default ``True``). DAQP solves the program in the variables ``w_hat = w / D``, where
    ``D`` is the range ``u - l`` of each bounded continuous variable (at least :data:`MIN_SPAN`; one for the
    binaries and the unbounded), with each row divided by its largest coefficient; the regularization ``reg``
    applies to ``w_hat`` (``reg / D^2`` in the program's own units), and everything above holds in the program's
    units. The network's variables of a big-M program have ranges up to the node bounds (hundreds on the stored
    programs) and no cost: as written, DAQP's branch and bound on one stored program (24 binaries) called a point
    3.8e-4 above the optimum optimal after 161 nodes, and in 8 of 11 orders of its variables a point up to 3.8e-3
    above; scaled, it proved the optimum itself in 10 orders (the 11th ended with an undocumented exit flag, which
    goes to SCIP), and the certified gap of the regularization fell from 2e-6 to
    1e-11 (relative), so that DAQP proves more answers by itself. On 172 programs the engine sent DAQP (random
    networks, the Quad-1D, the MSD) no claim was wrong either way; of their cold solves DAQP proved 115 by itself
    against 98, and left 7 unproven against 28 (4 more points came back outside ``FEAS_TOL``: 10 against 6).
    Scaling does not cure DAQP's long searches: on the other stored program (2e-2 above the optimum after thousands
    of nodes) it missed the optimum in 6 of 11 orders scaled and 4 unscaled, so those are still verified
    (:data:`VERIFY_NODES`). The point DAQP returns meets the program's rows to ``FEAS_TOL`` or is refused.

    Tolerances. DAQP's primal tolerance is its default, ``1e-6`` (option ``primal_tol``): with ``1e-7`` its branch
    and bound returned a point 6e-4 (relative) above the optimum as optimal on a program the tests keep. A point
    that violates the program by more than :data:`flnotes.solvers.FEAS_TOL` is refused and the program is verified
    by SCIP.

    Warm start. A feasible warm start ``w_ws`` gives the incumbent bound
    ``fval_bound = J(w_ws)`` (``+ B`` with ``reg_mode="upper"``, plus :data:`INCUMBENT_SLACK`), given in the units
    DAQP compares it in: its objective itself in the branch and bound, the objective of its least-distance form
    (``J + 0.5 c'H^-1 c``) in a QP's active-set solve (the tests check both). DAQP then only explores nodes that
    can match it. If none does (exit flag -1 under the bound), ``w_ws`` is optimal
    provided DAQP's branch and bound is right, which on the degenerate big-M
    rows it has not always been: an exit flag -1 on a mixed-integer program
    (with or without warm start) is verified by SCIP unless the option
    ``verify_infeasible=False`` is given (``make bench`` measures both). An optimum DAQP claims that costs more
    than the warm start in the program it solved contradicts the claim (its search missed a node): it is no proof,
    and SCIP verifies it.
    Without an incumbent the claim is about the feasible set only: with
    ``verify_feasibility="relaxation"`` (default) an infeasible continuous
    relaxation (an LP solved by HiGHS, a millisecond where building a SCIP model
    takes ten or more) proves it; otherwise, and with ``"milp"``, it is verified
    on the MILP with the same rows and a zero objective (SCIP spends most of its
    time on the cuts of the quadratic objective), and only a feasible or undecided
    MILP sends the program itself to SCIP (``"miqp"``: always the program).

    Long searches are verified. DAQP's depth-first search without cuts has returned sub-optimal points as optimal
    after long searches (:data:`VERIFY_NODES`): an optimum found after more than ``verify_nodes`` nodes is
    verified by SCIP, warm-started with DAQP's point.

    Hand-over. Without a time limit, DAQP's branch and bound gets :data:`HANDOVER_S` seconds (option
    ``handover``) on a mixed-integer program; if it has not answered by then, SCIP solves the program (warm-started
    with DAQP's incumbent, if any), and the message says so. With a time limit, DAQP gets the whole limit.

    ``scip_options`` (a dict) is passed to every SCIP model built to verify a
    claim or to take over after a failure (:class:`flnotes.solvers.ScipSolver`;
    its ``objective`` and ``miqp_params`` apply to the MIQPs, not to the
    feasibility MILP).
    """

    name = "daqp"
    OPTIONS = ("threads", "params", "reg", "reg_mode", "reg_retry", "eps_prox", "primal_tol", "scale", "handover",
               "verify_nodes", "verify_infeasible", "verify_feasibility", "fallback", "scip_options")

    @classmethod
    def _check_values(cls, options: dict) -> None:
        _check_values(options)

    def _build(self) -> None:
        daqp = _require("daqp")
        p = self.problem
        bad = np.flatnonzero((p.integrality == 1) & ((p.lb < 0) | (p.ub > 1)) & (p.lb < p.ub))
        if bad.size:
            raise ValueError(f"the 'daqp' back-end supports binary integers only (bounds within [0, 1]); "
                             f"variable {bad[0]} has bounds [{p.lb[bad[0]]}, {p.ub[bad[0]]}]: use backend='scip' or 'highs'")
        self._daqp = daqp
        reg = self.options.get("reg", 1e-6)
        H = np.zeros((p.n, p.n)) if p.H is None else p.H.toarray()
        self._eps_prox = 0.0
        self._dreg = np.zeros(p.n)  # the diagonal added to H (reg mode)
        if p.H is None or not _is_pd(H):
            if reg:
                d = (np.abs(np.diag(H)) <= 1e-12).astype(float)
                self._dreg = float(reg) * d
                if not _is_pd(H + np.diag(self._dreg)):
                    self._dreg = self._dreg + float(reg)
                H = H + np.diag(self._dreg)
            else:
                self._eps_prox = float(self.options.get("eps_prox", 1e-6))
                if p.H is None:
                    H = None if self._eps_prox else H
        self._H = H
        self._Ad = p.A.toarray()
        self._model = None
        # the big-M rows are degenerate: DAQP's default cycling guard (10 iterations without progress)
        # stops too early on them. The primal tolerance is DAQP's default: with 1e-7 its branch and bound returned a
        # sub-optimal point as optimal (tests/test_mpc.py keeps the program); a point that violates the program by
        # more than FEAS_TOL is refused below and the program goes to SCIP.
        self._settings = dict(eps_prox=self._eps_prox, primal_tol=float(self.options.get("primal_tol", 1e-6)),
                              cycle_tol=1000, progress_tol=1e-10)
        self._settings.update(self.options.get("params", {}))

    def _sense(self) -> Array:
        p = self.problem
        s = np.zeros(p.n + p.m, dtype=np.int32)
        binary = (p.integrality == 1) & (p.lb < p.ub)
        s[:p.n][binary] = 16
        s[:p.n][p.lb == p.ub] = 5
        s[p.n:][p.rl == p.ru] = 5
        return s

    def _bounds(self) -> tuple[Array, Array]:
        p = self.problem
        lb, ub = p.lb.copy(), p.ub.copy()
        ib = p.integrality == 1
        lb[ib], ub[ib] = np.ceil(lb[ib] - 1e-9), np.floor(ub[ib] + 1e-9)
        bu, bl = np.concatenate([ub, p.ru]), np.concatenate([lb, p.rl])
        bu[bu >= _INF] = np.inf
        bl[bl <= -_INF] = -np.inf
        return bu, bl

    def _push(self, changed: dict) -> None:
        if "A" in changed:
            self._Ad[self._Arow[changed["A"]], self._Acol[changed["A"]]] = self.problem.A.data[changed["A"]]

    def _solve(self, ws, time_limit, gap, t0) -> MIQPResult:
        p = self.problem
        incumbent = None
        if ws is not None and p.is_mip:
            w0 = ws.copy()
            ib = p.integrality == 1
            w0[ib] = np.round(w0[ib])
            if self._warm_ok(w0):
                incumbent = w0
        handover = self.options.get("handover", HANDOVER_S)
        limit = handover if (time_limit is None and p.is_mip and handover is not None) else time_limit
        res = self._attempt(incumbent, limit, t0, eps_prox=None, gap=gap)
        if res.status == "error" and np.any(self._dreg > 0) and self.options.get("reg_retry", True):
            # DAQP may cycle on the degenerate big-M rows; a stronger regularization (its secant gap is
            # certified or not, as always) usually removes the cycling
            retry = self._attempt(incumbent, limit, t0, gap=gap, reg_scale=10.0)
            if retry.status != "error":
                retry.message += " (after a retry with the regularization x10)"
                res = retry
        if res.status == "error" and "retry" not in res.message:
            # once more with a stronger proximal term
            retry = self._attempt(incumbent, limit, t0, eps_prox=1e-4, gap=gap)
            if retry.status != "error":
                retry.message += " (after a retry with eps_prox=1e-4)"
                res = retry
        verifier = "scip" if p.is_mip else "highs"
        if limit is not time_limit and (res.status == "time_limit" or (
                res.status == "unproven" and time.perf_counter() - t0 >= handover)):
            # no time limit: SCIP takes over the program (DAQP may also stop at its limit with an undocumented flag)
            return _confirm_qp(self, p, verifier, res.w, None, gap, t0,
                            f"daqp: no answer after the hand-over time of {handover:g} s", res.nodes)
        trust = self.options.get("verify_nodes", VERIFY_NODES)
        if p.is_mip and res.status == "optimal" and trust is not None and res.nodes > trust:
            # DAQP's depth-first search has returned sub-optimal points as optimal after long searches
            return _confirm_qp(self, p, verifier, res.w, time_limit, gap, t0,
                            f"daqp: {res.message}, after {res.nodes} nodes (more than {trust})", res.nodes)
        if res.status == "unproven":
            return _confirm_qp(self, p, verifier, res.w, time_limit, gap, t0, f"daqp: {res.message}", res.nodes)
        if res.status == "infeasible" and ((p.is_mip and self.options.get("verify_infeasible", True)) or self._eps_prox):
            # DAQP's branch and bound (and its proximal iterations on a singular H) have declared feasible
            # big-M programs infeasible, or found nothing below a warm start that was not optimal
            how = self.options.get("verify_feasibility", "relaxation")
            if incumbent is None and p.is_mip and how in ("relaxation", "milp"):
                # without an incumbent the claim is about the feasible set only: the MILP with the same rows and
                # a zero objective decides it (SCIP spends most of its time on the quadratic objective's cuts)
                if how == "relaxation":
                    # an infeasible continuous relaxation proves it (HiGHS, feasibility tolerance 1e-7: looser than
                    # SCIP's 1e-9, so no point that SCIP would accept is missed)
                    lp = MIQP(None, np.zeros(p.n), 0.0, p.A, p.rl, p.ru, p.lb, p.ub, np.zeros(p.n, dtype=int))
                    rel = make_solver(lp, "highs").solve(time_limit=None if time_limit is None else max(
                        time_limit - (time.perf_counter() - t0), 1e-3))
                    if rel.status == "infeasible":
                        return _result(p, "infeasible", None, np.inf, res.nodes, t0, self.name,
                                       "infeasible, proven by highs: the continuous relaxation is infeasible "
                                       f"(checked because daqp: {res.message} is no proof)")
                feas = MIQP(None, np.zeros(p.n), 0.0, p.A, p.rl, p.ru, p.lb, p.ub, p.integrality)
                chk = _confirm(self, feas, verifier, None, time_limit, gap, t0, f"daqp: {res.message}", res.nodes)
                if chk.status != "infeasible":  # feasible after all (or undecided): the program itself
                    return _confirm_qp(self, p, verifier, None, time_limit, gap, t0,
                                    f"daqp: {res.message} (the feasibility MILP: {chk.status})", chk.nodes)
                chk.message += " (the feasibility MILP with the same rows)"
                return chk
            return _confirm_qp(self, p, verifier, incumbent, time_limit, gap, t0, f"daqp: {res.message}", res.nodes)
        if res.status == "error":
            fb = self.options.get("fallback", "scip")
            if fb and fb != "daqp":
                return _confirm_qp(self, p, fb if p.is_mip else "highs", incumbent, time_limit, gap, t0,
                                f"daqp failed ({res.message})", res.nodes)
        return res

    def _attempt(self, incumbent, time_limit, t0, eps_prox=None, gap: float = 1e-6,
                 reg_scale: float = 1.0) -> MIQPResult:
        """One DAQP call on the program with its fixed variables substituted out (regularization x ``reg_scale``)."""
        daqp, p = self._daqp, self.problem
        bu_all, bl_all = self._bounds()
        lbv, ubv = bl_all[: p.n], bu_all[: p.n]
        fixed = lbv == ubv
        free = np.flatnonzero(~fixed)
        xf = np.where(fixed, lbv, 0.0)
        D = np.ones(p.n)  # w = D w_hat: each bounded continuous variable scaled to a unit range (option scale)
        scaled = bool(self.options.get("scale", True)) and self._H is not None
        if scaled:
            span = ubv - lbv
            cont = (p.integrality == 0) & ~fixed & np.isfinite(span)
            D[cont] = np.maximum(span[cont], MIN_SPAN)
        dr = reg_scale * self._dreg / D ** 2
        H = self._H
        if H is not None and np.any(dr != self._dreg):
            H = H + np.diag(dr - self._dreg)
        c_r = p.c[free].copy()
        if H is not None and fixed.any():
            c_r += H[np.ix_(free, np.flatnonzero(fixed))] @ xf[fixed]
        Hr = None if H is None else H[np.ix_(free, free)]
        A = self._Ad
        shift = A @ xf if p.m else np.zeros(0)
        Ar = A[:, free] if p.m else np.zeros((0, free.size))
        ru, rl = bu_all[p.n:] - shift, bl_all[p.n:] - shift
        keep = np.any(Ar != 0.0, axis=1) if p.m else np.zeros(0, bool)
        if p.m and np.any(~keep & ((rl > 1e-9) | (ru < -1e-9))):
            return _result(p, "infeasible", None, np.inf, 0, t0, self.name, "a row without free variables is violated")
        Ar, ru, rl = Ar[keep], ru[keep], rl[keep]
        bu = np.r_[ubv[free], ru]
        bl = np.r_[lbv[free], rl]
        sense = np.zeros(bu.size, dtype=np.int32)
        sense[: free.size][(p.integrality[free] == 1)] = 16
        sense[free.size:][rl == ru] = 5
        settings = dict(self._settings)
        if eps_prox is not None:
            settings["eps_prox"] = eps_prox
        elif self._eps_prox and Hr is not None and free.size and np.all(np.abs(np.diag(Hr)) > 0):
            try:  # the fixed variables may have carried all the singular directions
                np.linalg.cholesky(Hr)
                settings["eps_prox"] = 0.0
            except np.linalg.LinAlgError:
                pass
        if Hr is None and not settings.get("eps_prox"):
            Hr = np.zeros((free.size, free.size))
        if time_limit:
            settings["time_limit"] = max(float(time_limit) - (time.perf_counter() - t0), 1e-3)
        # reg mode. "secant" (default): DAQP minimizes J_s(w) = J(w) + 0.5 sum_i dreg_i (w_i - l_i)(w_i - u_i), which
        # is <= J on the box and equals J at the bounds (so at every integer point of a binary): J_s's optimum
        # is a lower bound on J*, its gap at the returned point is 0.5 sum dreg_i (w_i - l_i)(u_i - w_i), and a
        # point better than the incumbent has J_s < J(incumbent). "upper": J_r(w) = J(w) + 0.5 sum dreg_i w_i^2
        # with J <= J_r <= J + B on the box.
        pert = dr > 0
        secant = self.options.get("reg_mode", "secant") == "secant" and bool(np.all(np.isfinite(lbv[pert]))
                                                                          and np.all(np.isfinite(ubv[pert])))
        B = 0.0
        const = p.objective(xf)
        if secant and pert.any():
            lin = np.where(pert, -0.5 * dr * (lbv + ubv), 0.0)
            lin[fixed] = 0.0
            c_r += lin[free]
            const += float(0.5 * np.sum((dr * lbv * ubv)[pert & ~fixed]))
        elif pert.any():
            big = np.maximum(np.abs(lbv), np.abs(ubv))[pert]
            B = float(0.5 * np.sum(dr[pert] * big ** 2)) if np.all(np.isfinite(big)) else np.inf

        def J_s(w):  # DAQP's objective (plus its constant) at a full point w
            q = dr * (w - lbv) * (w - ubv) if secant else dr * w ** 2
            return p.objective(w) + 0.5 * float(np.sum(q[pert]))

        bnb = bool(np.any(sense[: free.size] == 16))
        # DAQP's branch and bound compares fval_bound with its objective 0.5 w'Hw + c'w; a QP's active-set solve
        # compares it with the objective of its least-distance form, J + 0.5 c' H^-1 c (``offset``)
        offset = (None if incumbent is None or settings.get("eps_prox") else 0.0 if bnb else _ldp_offset(Hr, c_r))
        if offset is not None and np.isfinite(B):
            # Any w at least as good as the incumbent has J_s(w) <= J(incumbent) (secant) or J_r(w) <= J(incumbent)
            # + B: nodes above that are pruned; the bound lies just above it, so that the incumbent's own node is
            # kept and a search that finds nothing better ends with it as its optimum, not with "infeasible"
            J_full = p.objective(incumbent)
            settings["fval_bound"] = J_full + B - const + offset + INCUMBENT_SLACK * max(1.0, abs(J_full))
        if free.size == 0:
            w = xf.copy()
            ok = p.violation(w) <= 1e-6
            return _result(p, "optimal" if ok else "infeasible", w if ok else None, np.nan, 0, t0, self.name,
                           "every variable is fixed")
        Df = D[free]
        if scaled:
            Hr = Hr * Df[:, None] * Df[None, :]
            c_r = c_r * Df
            Ar = Ar * Df[None, :]
            bu[: free.size] /= Df
            bl[: free.size] /= Df
            rs = np.abs(Ar).max(axis=1) if Ar.shape[0] else np.zeros(0)
            Ar = Ar / rs[:, None]
            bu[free.size:] /= rs
            bl[free.size:] /= rs
        x, fval, flag, info = daqp.solve(Hr, c_r, Ar, bu, bl, sense, **settings)
        x = np.asarray(x, float) * Df
        nodes = int(info.get("nodes", 0)) if p.is_mip else 0

        def full(xr):
            w = xf.copy()
            w[free] = np.asarray(xr, float)
            ib = p.integrality == 1
            w[ib] = np.round(w[ib])
            return w

        retry_note = "" if eps_prox is None and reg_scale == 1.0 else " retry"
        status = DAQP_STATUS.get(int(flag), "unproven" if flag > 0 else "error")
        msg = f"exitflag {flag} ({_DAQP_FLAGS.get(int(flag), 'not documented')}){retry_note}"
        if status in ("optimal", "unproven"):
            w = full(x)
            if p.violation(w) > FEAS_TOL:
                w = None
                msg += " but the point violates the program"
            cand = [v for v in (w, incumbent) if v is not None]
            best = min(cand, key=p.objective) if cand else None
            if status == "optimal" and w is not None and incumbent is not None:
                J_w, J_i = J_s(w), J_s(incumbent)
                if J_w > J_i + 1e-9 * max(1.0, abs(J_i)):
                    # the program DAQP solved is cheaper at the warm start than at its "optimum": its branch and
                    # bound missed the node of a better point (seen after 161 nodes: a plan 2.5e-4 above the optimum)
                    return _result(p, "unproven", best, -np.inf, nodes, t0, self.name,
                                   msg + f" (its point costs {J_w - J_i:.1e} more than the warm start in the "
                                   "program it solved: no proof)")
            if status == "optimal" and w is not None and (B > 0 or (secant and pert.any())):
                # certificate of the perturbed problem: J* >= J_s(w) (secant) or J* >= J_r(w) - B
                bound = min(J_s(w), float(fval) + const) if secant else J_s(w) - B
                if incumbent is not None:
                    bound = min(bound, p.objective(incumbent))
                J_best = p.objective(best)
                if abs(J_best - bound) <= gap * max(1.0, abs(J_best)):
                    return _result(p, "optimal", best, bound, nodes, t0, self.name,
                                   msg + f" (regularized by {float((dr * D ** 2).max()):.0e}: optimal within the relative gap "
                                   f"{gap:.0e}, certified: objective - bound = {J_best - bound:.1e}, "
                                   f"relative {(J_best - bound) / max(1.0, abs(J_best)):.1e})")
                return _result(p, "unproven", best, bound, nodes, t0, self.name,
                               msg + f" (regularized: objective - bound = {J_best - bound:.1e}, relative "
                               f"{(J_best - bound) / max(1.0, abs(J_best)):.1e}, above the requested gap {gap:.0e})")
            if status == "optimal" and w is not None:
                return _result(p, "optimal", best, np.nan, nodes, t0, self.name, msg)
            return _result(p, "unproven" if best is not None else "error", best, -np.inf, nodes, t0, self.name, msg)
        if status == "infeasible":
            if incumbent is not None:  # nothing better than the warm start under fval_bound (no proof of it)
                return _result(p, "infeasible", incumbent, np.nan, nodes, t0, self.name,
                               f"exitflag {flag}: nothing better than the warm start{retry_note}")
            return _result(p, "infeasible", None, np.inf, nodes, t0, self.name, msg)
        if status == "time_limit":
            return _result(p, "time_limit", incumbent, -np.inf, nodes, t0, self.name, msg)
        return _result(p, "error", None, -np.inf, nodes, t0, self.name, msg)


#: The smallest range a continuous variable is scaled to one from (option ``scale``): a narrower variable is scaled
#: by this, so that the regularization in the program's own units (``reg / span**2``) stays moderate.
MIN_SPAN = 1e-3

#: How far above the warm start's cost (relative) DAQP's branch and bound prunes its nodes (``fval_bound``): far
#: below the gap, so that the pruning keeps the warm start's own node, whose regularized objective can equal its cost.
INCUMBENT_SLACK = 1e-9

#: Seconds DAQP's branch and bound gets on a mixed-integer program solved without a time limit before SCIP takes
#: the program over (option ``handover``; ``None``: no hand-over). On the book's programs DAQP answers in
#: milliseconds; on programs of random networks with 30 to 50 binaries its depth-first search without cuts took up
#: to minutes where SCIP took a tenth of a second. A wall-clock decision: the answer is the proven optimum either way.
HANDOVER_S = 1.0

#: Nodes up to which DAQP's own claim of optimality on a mixed-integer program is taken as the proof (option
#: ``verify_nodes``; ``None``: always). Above, SCIP re-solves the program warm-started with DAQP's point. On programs
#: of random networks (one integrator, N_p = 5, 34 and 41 binaries) DAQP's branch and bound returned points 6e-4 and
#: 2e-2 (relative) above the optimum as optimal, after 4,504 and 27,543 nodes (and after 544 on a sub-program of the
#: first with a tighter primal tolerance); SCIP needed 15 and 14.
VERIFY_NODES = 200


#: DAQP exit flag -> status. Only flag 1 is a proof. Flag 2 ("soft optimal": soft constraints were relaxed; none
#: are declared here) and every undocumented positive flag (4 is returned after proximal-point iterations on a
#: singular H) give a point without proof, verified by another solver (:meth:`DaqpSolver._solve`); -1 is a claim
#: of infeasibility, verified on mixed-integer programs.
DAQP_STATUS = {1: "optimal", 2: "unproven", -1: "infeasible", -2: "error", -3: "error", -4: "error", -5: "error",
               -6: "error", -7: "time_limit", -8: "error"}


_DAQP_FLAGS = {1: "optimal", 2: "soft optimal", -1: "infeasible", -2: "cycling", -3: "unbounded",
               -4: "iteration limit", -5: "nonconvex", -6: "overdetermined initial active set",
               -7: "time limit reached", -8: "unsupported problem"}


#: The settings of ``daqp.solve`` (0.11) that option ``params`` may set (the rest of its arguments are the program's
#: data, and :data:`_RESERVED_SETTINGS` are refused).
DAQP_SETTINGS = ("dual_tol", "zero_tol", "pivot_tol", "progress_tol", "cycle_tol", "iter_limit", "eta_prox",
                 "rho_soft", "w_soft", "sing_tol", "refactor_tol", "eq_reduction", "presolve")

#: Settings of ``daqp.solve`` refused in ``params``, and why.
_RESERVED_SETTINGS = {"primal_tol": "give the option primal_tol", "eps_prox": "give the option eps_prox (with reg=None)",
                      "time_limit": "set by solve(time_limit=...) and the option handover",
                      "fval_bound": "set by the back-end from the warm start",
                      "rel_subopt": "DAQP's 'optimal' would then be sub-optimal (give gap= to solve())",
                      "abs_subopt": "DAQP's 'optimal' would then be sub-optimal (give gap= to solve())"}

#: DAQP settings that are tolerances (each in (0, 1)), counts (positive integers) and switches (integers); the
#: rest of :data:`DAQP_SETTINGS` are non-negative finite numbers.
_TOLERANCES = ("dual_tol", "zero_tol", "pivot_tol", "progress_tol", "sing_tol", "refactor_tol")
_COUNT_SETTINGS = ("cycle_tol", "iter_limit")
_SWITCH_SETTINGS = ("eq_reduction", "presolve")


def _real(x) -> bool:
    """A finite real number (not a bool, not complex, not a time delta, not an integer too large for a float)."""
    if not isinstance(x, numbers.Real) or isinstance(x, (bool, np.bool_, np.timedelta64)):
        return False
    try:
        return bool(np.isfinite(float(x)))
    except OverflowError:
        return False


def _check_values(options: dict) -> None:
    """Raise a ValueError naming the first DAQP back-end option (:class:`DaqpSolver`) whose value means nothing."""
    for k, allowed in (("reg_mode", ("secant", "upper")), ("verify_feasibility", ("relaxation", "milp", "miqp")),
                       ("reg_retry", (True, False)), ("verify_infeasible", (True, False)), ("scale", (True, False)),
                       ("fallback", ("scip", "gurobi", "cplex", "daqp", None, False))):
        x = options.get(k, allowed[0])
        is_bool = isinstance(x, (bool, np.bool_))
        if not any((a is None and x is None) or (isinstance(a, bool) and is_bool and bool(x) == a)
                   or (isinstance(a, str) and isinstance(x, str) and x == a) for a in allowed):
            raise ValueError(f"the DAQP option {k} must be one of {allowed}, got {x!r}")
    reg = options.get("reg", 1e-6)
    if reg is not None and not (_real(reg) and float(reg) >= 0.0):
        raise ValueError(f"the DAQP option reg must be a non-negative number (0 or None: proximal iterations), "
                         f"got {reg!r}")
    eps_prox, primal_tol = options.get("eps_prox", 1e-6), options.get("primal_tol", 1e-6)
    if not (_real(eps_prox) and float(eps_prox) >= 0.0):
        raise ValueError(f"the DAQP option eps_prox must be a non-negative number, got {eps_prox!r}")
    if not (_real(primal_tol) and float(primal_tol) > 0.0):
        raise ValueError(f"the DAQP option primal_tol must be a positive number, got {primal_tol!r}")
    if "eps_prox" in options and options.get("reg", 1e-6):
        raise ValueError(f"the DAQP option eps_prox applies without the regularization (reg=None or 0), but reg = "
                         f"{options.get('reg', 1e-6)!r}: drop eps_prox or set reg=None")
    for k, x in options.get("params", {}).items():
        if k in _RESERVED_SETTINGS:
            raise ValueError(f"the DAQP setting {k!r} is refused in params: {_RESERVED_SETTINGS[k]}")
        if k not in DAQP_SETTINGS:
            raise ValueError(f"DAQP has no setting {k!r} (option params); the settings it takes are "
                             f"{list(DAQP_SETTINGS)}")
        if k in _COUNT_SETTINGS:
            ok, what = isinstance(x, numbers.Integral) and not isinstance(x, (bool, np.bool_)) and 0 < x < 2**31, \
                "a positive integer"
        elif k in _SWITCH_SETTINGS:
            ok, what = isinstance(x, numbers.Integral) and not isinstance(x, (bool, np.bool_)) and -2**31 < x < 2**31, \
                "an integer"
        elif k in _TOLERANCES:
            ok, what = _real(x) and 0.0 < float(x) < 1.0, "a tolerance in (0, 1)"
        else:
            ok, what = _real(x) and float(x) >= 0.0, "a non-negative finite number"
        if not ok:
            raise ValueError(f"the DAQP setting {k} (option params) must be {what}, got {x!r}")
    fb = options.get("fallback", "scip")
    if fb in ("gurobi", "cplex") and fb not in available_backends():
        raise ValueError(f"the DAQP option fallback={fb!r} needs {fb}, which is not installed: use 'scip'")
    if "threads" in options:  # DAQP runs on one thread; the option is for the SCIP models that verify it
        try:
            ScipSolver.check_options({"threads": options["threads"]})
        except ValueError as exc:
            raise ValueError(f"the DAQP option threads (for its SCIP verifications): {exc}") from None
    if not isinstance(options.get("scip_options", {}), dict):
        raise ValueError(f"the DAQP option scip_options must be a dict of SCIP options (see ScipSolver), got "
                         f"{options['scip_options']!r}")
    if options.get("scip_options"):  # the options of every SCIP model built for a verification or a take-over
        if "threads" in options["scip_options"]:
            raise ValueError("the DAQP option scip_options must not set threads: give the DAQP option threads (the "
                             "SCIP models that verify DAQP use it)")
        try:
            ScipSolver.check_options(options["scip_options"])
        except ValueError as exc:
            raise ValueError(f"the DAQP option scip_options: {exc}") from None
    handover = options.get("handover", HANDOVER_S)
    if handover is not None and (isinstance(handover, (bool, np.timedelta64)) or not isinstance(handover, numbers.Real)
                                 or not 0.0 < float(handover) < np.inf):
        raise ValueError(f"the DAQP option handover must be a positive number of seconds or None, got {handover!r}")
    trust = options.get("verify_nodes", VERIFY_NODES)
    if trust is not None and (isinstance(trust, (bool, np.timedelta64)) or not isinstance(trust, numbers.Integral)
                              or trust < 0):
        raise ValueError(f"the DAQP option verify_nodes must be a non-negative integer or None, got {trust!r}")


def _ldp_offset(H: Optional[Array], c: Array) -> Optional[float]:
    """``0.5 c' H^-1 c``: DAQP solves ``min 0.5 w'Hw + c'w`` as the least-distance program ``min 0.5 ||u||^2`` with
    ``u = R w + R^-T c`` (``H = R'R``), whose objective is ``J + 0.5 c'H^-1 c``; its ``fval_bound`` is a bound on that
    objective (tests/test_solvers.py checks this against DAQP on QPs). ``None`` where ``H`` is missing or not positive
    definite (no bound is then given)."""
    if H is None or H.shape[0] == 0:
        return None
    try:
        R = np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        return None
    y = scipy.linalg.solve_triangular(R, c, lower=True)
    return 0.5 * float(y @ y)


def _is_pd(H: Array) -> bool:
    try:
        np.linalg.cholesky(H + 0.0)
    except np.linalg.LinAlgError:
        return False
    d = np.linalg.eigvalsh(H)
    return bool(d.min() > 1e-10 * max(1.0, d.max()))
