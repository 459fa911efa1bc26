"""Study: how much of the MIQP's root gap stronger formulations of the network close (the benchmark's MSD rows).

At a state, the program whose optimum the engine must prove (:func:`level_program`: eq. MPC_form_miqp restricted to
the level set at the optimum's cost, LP node bounds on the level-set boxes, the steps whose output can exceed
``u_max^eps`` encoded; the engine's round with the optimal warm start as incumbent) is relaxed (``alpha`` in
``[0, 1]``) and tightened by one of two families of valid inequalities, separated at the relaxation's optimum in
rounds:

``"ideal"``
    the cuts of the ideal (convex-hull) formulation of one neuron over the box of its inputs (Anderson et al. 2020,
    Theorem 1): for a neuron ``y = max(0, w'x + b)`` with ``x`` in ``[x_lo, x_hi]`` and any subset ``I`` of its
    inputs, ``y <= sum_{i in I} w_i (x_i - Lb_i (1 - alpha)) + (b + sum_{i not in I} w_i Ub_i) alpha``, with
    ``Lb_i, Ub_i`` the input's bound where ``w_i x_i`` is least and largest (:func:`ideal_cuts`); the strongest
    formulation of each neuron on its own, hence a bound for the partition formulations of Tsay et al. 2021, which
    lie between big-M and it;
``"projection"``
    per encoded step ``k``, ``g'x <= beta`` on ``x = [z(k); v(k)]``, with ``g`` the network's gradient at the
    relaxation's point (where it exceeds the bound) and ``beta = max{g'x : x in the step's box, |Phi_NN(x)| <=
    u_in}`` proven by SCIP on one copy of the network (:func:`projection_cut`): the whole network at one step
    rather than one neuron.

Both keep every plan of the program (they are valid for every point of its mixed-integer set), so the program's
optimum is unchanged; the rows of :func:`cut_rows` measure the root bound they reach, the share of the gap they
close, their cost, and SCIP's time and nodes on the program with them. Speed is measured in the benchmark, never
asserted in tests.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Optional, Sequence

import numpy as np
import scipy.sparse as sp

from ..bounds import NodeBounds
from ..encoding import bigm_form
from ..mpc import MPC, MPCOptions
from ..mpc.levers import needed_steps, node_bounds
from ..mpc.prediction import Prediction
from ..mpc.program import compact_program, encoded_layers, plan_vector
from ..network import ReLUNet
from ..solvers import MIQP, make_solver

Array = np.ndarray

#: The families of cuts (see the module docstring).
FAMILIES = ("big-M", "ideal", "projection")

#: Relative slack added to a projection cut's proven ``beta`` (SCIP's bound holds to its tolerances).
BETA_SLACK = 1e-7

#: Seconds SCIP gets per projection cut: the bound it has proven by then is the cut's ``beta`` (valid, maybe weaker).
PROJECTION_LIMIT = 10.0

#: SCIP's settings for a projection cut's program: without its cutting planes. On the MSD's programs (one network
#: copy, 15 to 30 binaries) SCIP's root separation took 1 to 3 s and HiGHS 0.2 to 0.7 s; without separation SCIP
#: proved the same optima in 0.04 to 0.09 s (1 to 5 nodes).
PROJECTION_SCIP = {"params": {"separating/maxroundsroot": 0, "separating/maxrounds": 0}}

#: A cut is added when the relaxation's point violates it by more than this (relative to ``max(1, |y|)``).
VIOLATION_TOL = 1e-6

#: Cut rounds stop when the relaxation's bound gains less than this (relative) in a round.
MIN_GAIN = 1e-5


@dataclass
class LevelProgram:
    """The program of one level-set round at a state (:func:`level_program`).

    ``prob`` is the program, ``nb`` its node bounds, ``steps`` the encoded steps, ``lo, hi`` the level-set boxes
    of ``[z(k); v(k)]``, ``u_in`` the output bound in its rows; ``V_opt`` and ``J_opt`` the plan and cost the level
    was set at (the controller's optimum).
    """

    pred: Prediction
    z0: Array
    prob: MIQP
    nb: NodeBounds
    steps: list
    lo: Array
    hi: Array
    u_in: Array
    V_opt: Array
    J_opt: float
    engine_cpu_s: float
    bounds_cpu_s: float


def level_program(ctrl: MPC, z0: Array, z_ref: Array) -> LevelProgram:
    """The engine's level-set round at ``z0`` with the optimum as incumbent: the program a proof of optimality solves.

    ``ctrl`` (a default :class:`flnotes.MPC`, no time limit) solves the step cold (after ``reset()``; its CPU time
    is kept as ``engine_cpu_s``, that of the LP node bounds below as ``bounds_cpu_s``); the level is its optimal
    cost (plus ``1e-9`` relative, so the optimum lies inside), the boxes are the reachable boxes cut by that level set
    (:meth:`flnotes.mpc.prediction.Prediction.level_boxes`), the node bounds FBBT and LP on them, and the encoded
    steps those whose output bounds leave ``[-u_max^eps, u_max^eps]`` (every one of them, as without constraint
    generation).
    """
    if ctrl.time_limit is not None:
        raise ValueError("level_program needs the proven optimum: give a controller without time_limit")
    ctrl.reset()
    t0 = time.process_time()
    res = ctrl(np.asarray(z0, float), np.asarray(z_ref, float))
    engine_cpu_s = time.process_time() - t0
    if res.status != "optimal":
        raise ValueError(f"the controller did not prove an optimum at this state (status {res.status!r}): "
                         "choose a state where the program is feasible")
    pred = ctrl.pred
    f, c0 = pred.linear(z0, z_ref)
    V_c, fq, flag = pred.qp(f, z0)
    if V_c is None:
        raise ValueError(f"the QP without the network has no optimum at this state (DAQP flag {flag})")
    J_opt = float(res.objective)
    J_up = J_opt + 1e-9 * max(1.0, abs(J_opt))
    lo_h, hi_h = pred.boxes(z0)
    lo, hi = pred.level_boxes(z0, V_c, max(J_up - (fq + c0), 0.0), lo_h, hi_h)
    hi = np.maximum(hi, lo)
    t0 = time.process_time()
    nb = node_bounds(pred, MPCOptions(lp=True), ctrl.box_bounds, lo, hi)
    bounds_cpu_s = time.process_time() - t0
    steps = needed_steps(nb, pred.u_eps, "needed") if nb is not None else None
    if not steps:
        raise ValueError("at this state no step needs the network in the level set (the optimum is proven without "
                         "a branch and bound): choose a harder state")
    u_in = np.atleast_1d(np.asarray(pred.u_eps, float))
    prob = compact_program(pred, z0, f, c0, nb, steps, u_in, lo=lo, hi=hi)
    return LevelProgram(pred, np.asarray(z0, float), prob, nb, list(steps), lo, hi, u_in,
                        np.asarray(res.v_pred, float), J_opt, engine_cpu_s, bounds_cpu_s)


def ideal_cuts(lp: LevelProgram, w: Array, tol: float = VIOLATION_TOL) -> tuple[list, list]:
    """The most violated ideal cut of every neuron at the point ``w`` (Anderson et al. 2020, Theorem 1).

    A neuron's inputs are ``x = Y w + y0`` (:func:`flnotes.mpc.program.encoded_layers`); their box is the step's
    level-set box for the first layer and ``[max(L, 0), max(U, 0)]`` of the previous layer after it. For each
    input the cut takes ``w_i (x_i - Lb_i (1 - alpha))`` or ``w_i Ub_i alpha``, whichever is smaller at the point;
    the cut is returned as a row ``r'w <= rhs`` when the point violates it. Returns ``(rows, rhs)``.
    """
    pred, net = lp.pred, lp.pred.net
    rows, rhs = [], []
    x_lo = x_hi = None
    for lay in encoded_layers(pred, lp.z0, lp.nb, lp.steps, lp.prob.n):
        if lay.layer == 0:
            x_lo, x_hi = np.asarray(lp.lo[lay.k], float), np.asarray(lp.hi[lay.k], float)
        if lay.idx.size:
            W, b = net.W[lay.layer][lay.idx], net.b[lay.layer][lay.idx]
            x = lay.Y @ w + lay.y0
            al, y = w[lay.ia][:, None], w[lay.iy]
            Lb, Ub = np.where(W >= 0, x_lo, x_hi), np.where(W >= 0, x_hi, x_lo)
            take = W * (x - Lb * (1.0 - al))
            skip = W * Ub * al
            in_I = take < skip
            viol = y - (np.where(in_I, take, skip).sum(axis=1) + b * al[:, 0])
            for j in np.flatnonzero(viol > tol * np.maximum(1.0, np.abs(y))):
                I = in_I[j] & (W[j] != 0)
                row = -(W[j, I] @ lay.Y[I])
                row[lay.iy[j]] += 1.0
                row[lay.ia[j]] -= W[j, I] @ Lb[j, I] + b[j] + W[j, ~I] @ Ub[j, ~I]
                rows.append(row)
                rhs.append(W[j, I] @ lay.y0[I] - W[j, I] @ Lb[j, I])
        x_lo, x_hi = np.maximum(lay.L, 0.0), np.maximum(lay.U, 0.0)
    return rows, rhs


def gradient(net: ReLUNet, x: Array) -> Array:
    """``d Phi_NN / d x`` at ``x`` (one output): the network's linear map on the region that holds ``x``."""
    if net.n_out != 1:
        raise ValueError(f"gradient takes a network with one output, this one has {net.n_out}")
    _, pre = net.forward(np.asarray(x, float)[None, :])
    J = net.W[0]
    for layer in range(1, net.K):
        J = net.W[layer] @ ((pre[layer - 1][0] > 0)[:, None] * J)
    return J[0]


def projection_beta(net: ReLUNet, nb: NodeBounds, k: int, x_lo: Array, x_hi: Array, u_in: Array, g: Array,
                    time_limit: float = PROJECTION_LIMIT) -> tuple[float, Optional[Array]]:
    """``max{g'x : x_lo <= x <= x_hi, |Phi_NN(x)| <= u_in}`` bounded from above by SCIP (eq. MIP_general at step
    ``k``'s node bounds ``nb``, valid on the box for inputs that meet the bound; :data:`PROJECTION_SCIP`), plus
    :data:`BETA_SLACK`:
    ``g'x <= beta`` holds for every such ``x``. SCIP stops at ``time_limit`` seconds with the bound proven by then.
    Returns ``(beta, x)``, ``x`` the best input SCIP found (``None``: none)."""
    nbk = NodeBounds([np.asarray(L)[k] for L in nb.L], [np.asarray(U)[k] for U in nb.U],
                     np.asarray(nb.out_L)[k], np.asarray(nb.out_U)[k])
    F = bigm_form(net, nbk)
    lb, ub = F.lb.copy(), F.ub.copy()
    lb[F.x], ub[F.x] = x_lo, x_hi
    lb[F.out], ub[F.out] = np.maximum(lb[F.out], -u_in), np.minimum(ub[F.out], u_in)
    c = np.zeros(F.n)
    c[F.x] = -np.asarray(g, float)
    A = sp.vstack([F.A_eq, F.A_ub], format="csr")
    res = make_solver(MIQP(None, c, 0.0, A, np.r_[F.b_eq, np.full(F.b_ub.size, -np.inf)], np.r_[F.b_eq, F.b_ub],
                           lb, ub, F.integrality), "scip", **PROJECTION_SCIP).solve(gap=1e-9, time_limit=time_limit)
    if not np.isfinite(res.bound):
        raise RuntimeError(f"SCIP proved no bound for a projection cut at step {k} (status {res.status!r}: "
                           f"{res.message})")
    beta = -float(res.bound)
    return beta + BETA_SLACK * max(1.0, abs(beta)), (None if res.w is None else np.asarray(res.w)[F.x])


def projection_cuts(lp: LevelProgram, w: Array, tol: float = VIOLATION_TOL) -> tuple[list, list]:
    """One projection cut (module docstring) per encoded step whose point ``x = [z(k); v(k)]`` at ``w`` exceeds
    the output bound: ``g'x <= beta`` with ``g`` the network's gradient there (signed), as rows over ``w``."""
    pred, net = lp.pred, lp.pred.net
    N, m = pred.N, pred.m
    V = w[: N * m]
    Zf = pred.Sx @ lp.z0
    rows, rhs = [], []
    for k in lp.steps:
        off = np.r_[Zf[k], np.zeros(m)]
        x = off + pred.T[k] @ V
        u = float(net(x[None, :])[0, 0])
        if abs(u) <= float(lp.u_in[0]) + tol:
            continue
        g = np.sign(u) * gradient(net, x)
        beta, _ = projection_beta(net, lp.nb, k, lp.lo[k], lp.hi[k], lp.u_in, g)
        row = np.zeros(lp.prob.n)
        row[: N * m] = g @ pred.T[k]
        rows.append(row)
        rhs.append(beta - g @ off)
    return rows, rhs


def relaxation(prob: MIQP) -> tuple[Optional[Array], float, str]:
    """The continuous relaxation of ``prob`` (``alpha`` in ``[0, 1]``), solved by SCIP: ``(w, bound, status)``."""
    relaxed = replace(prob, integrality=np.zeros(prob.n, dtype=int))
    res = make_solver(relaxed, "scip").solve(gap=1e-9)
    return res.w, (float(res.bound) if res.w is not None else -np.inf), res.status


def with_cuts(lp: LevelProgram, family: str, rounds: int = 10) -> dict:
    """The program with cuts of ``family`` (one of :data:`FAMILIES`) separated in up to ``rounds`` rounds.

    Each round solves the relaxation and adds the cuts its optimum violates; the rounds stop when none is violated
    or the bound gains less than :data:`MIN_GAIN`, and the relaxation is solved once more after the last cuts.
    Returns ``{"prob", "bounds" (the relaxation's bound before each round and after the last, the first without
    cuts), "cuts", "cut_s" (CPU s of the relaxations and the separation)}``; ``"big-M"`` adds nothing (one
    relaxation).
    """
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    separate = {"ideal": ideal_cuts, "projection": projection_cuts}.get(family)
    prob, bounds, n_cuts = lp.prob, [], 0
    t0 = time.process_time()
    for r in range(rounds + 1):  # a relaxation after each round of cuts: the bound they reach
        w, bound, status = relaxation(prob)
        if w is None:
            raise RuntimeError(f"the relaxation with {n_cuts} {family} cuts has no optimum (status {status!r})")
        bounds.append(bound)
        if separate is None or r == rounds or (r and bound - bounds[-2] < MIN_GAIN * max(1.0, abs(bound))):
            break
        rows, rhs = separate(lp, w)
        if not rows:
            break
        n_cuts += len(rows)
        prob = replace(prob, A=sp.vstack([prob.A, sp.csr_matrix(np.array(rows))], format="csr"),
                       rl=np.r_[prob.rl, np.full(len(rhs), -np.inf)], ru=np.r_[prob.ru, rhs])
    return dict(prob=prob, bounds=bounds, cuts=n_cuts, cut_s=time.process_time() - t0)


def cut_rows(ctrl: MPC, states: Sequence[tuple[str, Array, Array]], families: Sequence[str] = FAMILIES,
             rounds: int = 10, gap: float = 1e-6) -> list[dict]:
    """One row per state and family: the default engine's CPU time on the state (cold), that of the level
    program's LP node bounds, the root bound, the share of the root gap closed, the cuts' cost, SCIP's
    time and nodes on the program with them (warm-started at the optimum, as the engine's round), same optimum.

    ``states`` are ``(kind, z0, z_ref)``; ``ctrl`` a default :class:`flnotes.MPC` without time limit.
    """
    rows = []
    for kind, z0, z_ref in states:
        lp = level_program(ctrl, z0, z_ref)
        for fam in families:
            cut = with_cuts(lp, fam, rounds)
            prob = cut["prob"]
            w0 = plan_vector(lp.pred, lp.z0, lp.V_opt, lp.nb, lp.steps, prob)
            c0 = time.process_time()
            res = make_solver(prob, "scip").solve(warm_start=w0, gap=gap)
            scip_s = time.process_time() - c0
            root0, root = cut["bounds"][0], cut["bounds"][-1]  # without cuts, with them
            gap0 = lp.J_opt - root0
            rows.append({"state": kind, "family": fam, "engine cpu s": lp.engine_cpu_s,
                         "LP bounds cpu s": lp.bounds_cpu_s, "steps": len(lp.steps),
                         "binaries": int(prob.n_integer), "J_opt": lp.J_opt, "root bound": root,
                         "gap closed %": 100.0 * (root - root0) / gap0 if gap0 > 0 else 100.0,
                         "cuts": cut["cuts"], "cut rounds": len(cut["bounds"]) - 1, "cut cpu s": cut["cut_s"],
                         "scip cpu s": scip_s, "scip nodes": int(res.nodes), "status": res.status,
                         "same optimum": bool(res.status == "optimal" and abs(res.objective - lp.J_opt)
                                              <= gap * max(1.0, abs(lp.J_opt)) + 1e-9)})
    return rows


def _span(values: Sequence[float], fmt: str) -> str:
    """``"a to b"`` of the least and largest value in the format ``fmt``, or one value when both read the same."""
    lo, hi = format(min(values), fmt), format(max(values), fmt)
    return lo if lo == hi else f"{lo} to {hi}"


def cut_numbers(rows: Sequence[dict]) -> dict[str, str]:
    """The ranges over the states that the report's prose quotes, as text (``"0.85"`` when every state reads the
    same, ``"0.85 to 1.10"`` otherwise): the default engine's CPU seconds (``engine``), the level program's LP
    bounds (``lp``), SCIP's seconds and nodes without cuts (``scip``, ``nodes``), the big-M root gap relative to
    the optimum (``rel``), the share of it closed by each family (``ideal``, ``proj``), the projection cuts' cost
    (``proj_cut``) and SCIP's seconds with them (``proj_scip``). ``rows`` are :func:`cut_rows`'s with every family.
    """
    fam = {f: [r for r in rows if r["family"] == f] for f in FAMILIES}
    missing = [f for f, rs in fam.items() if not rs]
    if missing:
        raise ValueError(f"cut_numbers needs rows of every family {FAMILIES}; none for {missing}: run cut_rows with "
                         "the default families")
    big_m, col = fam["big-M"], lambda rs, key: [r[key] for r in rs]  # noqa: E731
    return {"engine": _span(col(big_m, "engine cpu s"), ".2f"), "lp": _span(col(big_m, "LP bounds cpu s"), ".2f"),
            "scip": _span(col(big_m, "scip cpu s"), ".2f"), "nodes": _span(col(big_m, "scip nodes"), "d"),
            "rel": _span([(r["J_opt"] - r["root bound"]) / max(1.0, abs(r["J_opt"])) for r in big_m], ".1%"),
            "ideal": _span([v / 100 for v in col(fam["ideal"], "gap closed %")], ".0%"),
            "proj": _span([v / 100 for v in col(fam["projection"], "gap closed %")], ".0%"),
            "proj_cut": _span(col(fam["projection"], "cut cpu s"), ".1f"),
            "proj_scip": _span(col(fam["projection"], "scip cpu s"), ".2f")}
