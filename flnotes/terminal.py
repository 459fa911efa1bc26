"""Terminal ingredients for the MPC of eq. (MPC_form_miqp): a terminal cost, a terminal set, a region of attraction.

The paper leaves recursive feasibility and stability of its MPC open ("adopting
the standard MPC axioms" is named as future work). The standard remedy (Mayne,
Rawlings, Rao & Scokaert 2000, Sec. 3.3, axioms A1-A4) adds to eq.
(MPC_form_miqp) a terminal cost ``V_f(z) = z' P_f z`` on ``z(N_p)`` and a terminal
constraint ``z(N_p) in Z_f`` such that, with a local law ``v = K_f z``,

* A1: ``Z_f`` lies in the state box ``Z_z`` (eq. MPC_form_miqp_d) and contains 0;
* A2: ``K_f z`` is admissible on ``Z_f``: ``v_lo <= K_f z <= v_hi`` and the network
  constraint ``|Phi_NN(z, K_f z)| <= u_max^eps`` (eq. MPC_form_miqp_b) hold;
* A3: ``Z_f`` is positively invariant under ``z+ = (A_d + B_d K_f) z``;
* A4: ``V_f((A_d + B_d K_f) z) - V_f(z) + ell(z, K_f z) <= 0`` on ``Z_f``.

Here ``K_f`` and ``P_f`` are the LQR gain and the solution of the discrete algebraic
Riccati equation of the Brunovsky model ``(A_d, B_d)`` (eq. MPC_form_miqp_c) with
the stage cost ``ell(z, v) = z'Qz + v'Rv``, so A4 holds with equality. ``Z_f``
is a polytope ``{z : F_inf z <= psi f_inf}`` (the MPC stays a mixed-integer QP with
linear constraints): ``O_inf = {F_inf z <= f_inf}`` is the maximal output-admissible set of
``z+ = (A_d + B_d K_f) z`` for the boxes (Gilbert & Tan 1991), which gives A1 and A3
and the v-box part of A2 for every level ``psi in (0, 1]``; the level ``psi``
is the largest for which the network part of A2 is **proved by a mixed-integer
program** over the network, the big-M encoding of eq. (MIP_general): the maximum
of ``+-Phi_NN(z, K_f z)`` over ``psi O_inf`` is at most ``u_max^eps``.

The code keeps short names for these: :class:`TerminalSet` stores ``K_f`` as ``K``, ``P_f`` as ``P``,
``F_inf, f_inf`` as ``F, g`` and the level ``psi`` as ``psi``.

With these ingredients the MPC is recursively feasible and its nominal closed
loop asymptotically stable (Mayne et al. 2000, Thm. 1): if ``(v(0), ..., v(N_p-1))``
is feasible at ``z``, the shifted plan ``(v(1), ..., v(N_p-1), K_f z(N_p))`` is
feasible at ``A_d z + B_d v(0)`` (A2, A3), and its cost shows that the optimal
cost decreases by at least ``ell(z, v(0))`` (A4). :func:`shifted_plan` builds that
candidate; :func:`region_of_attraction` draws the set of states from which the
horizon program is feasible, with and without the terminal constraint, as decided
by :class:`flnotes.MPC` itself.

Use: ``term = terminal_set(...)`` (the whole construction), then
``flnotes.MPC(..., P=term.P, terminal=term)``: the MPC reads ``TerminalSet.P``
(terminal weight ``P_f`` on ``z(N_p)``), ``TerminalSet.constraint()`` (``F_inf z(N_p) <= psi f_inf``)
and ``TerminalSet.K`` (the gain ``K_f``: the last input ``K_f z(N_p)`` of its shifted warm start, the
candidate of the proof).
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import scipy.sparse as sp
from scipy.linalg import solve_discrete_are
from scipy.optimize import Bounds, LinearConstraint, OptimizeWarning, linprog, milp

from ._checks import (as_state, as_batch, as_floats, as_pair, as_vector, box_in_domain, check_count, check_int,
                      check_number, weight_matrix)
from .bounds import fbbt
from .encoding import bigm_form
from .network import ReLUNet
from .systems import FLSystem

Array = np.ndarray

__all__ = ["lqr", "max_admissible_set", "remove_redundant", "network_max", "NETWORK_MAX_BACKENDS", "HIGHS_TOLERANCES",
           "SCIP_FEASTOL", "FEASIBILITY_TOLERANCE", "TerminalSet", "terminal_set",
           "shifted_plan", "RegionOfAttraction", "region_of_attraction"]


# ============================================================================ terminal cost
def lqr(Ad: Array, Bd: Array, Q: Array, R: Array) -> tuple[Array, Array]:
    """LQR gain and terminal weight of the discrete model (eq. MPC_form_miqp_c), axiom A4 of Mayne et al. 2000.

    ``P`` (the book's ``P_f``) solves the discrete algebraic Riccati equation
    ``P = A_d'PA_d - A_d'PB_d (R + B_d'PB_d)^{-1} B_d'PA_d + Q`` and
    ``K = -(R + B_d'PB_d)^{-1} B_d'PA_d`` (the book's ``K_f``), so that with ``v = K z``
    ``z+'Pz+ - z'Pz + z'Qz + v'Rv = 0``: the terminal cost ``||z(N_p)||_P^2``
    decreases by exactly the stage cost ``ell(z, v) = ||z||_Q^2 + ||v||_R^2`` of
    eq. (MPC_form_miqp_a).

    Parameters
    ----------
    Ad, Bd
        Discrete pair, shapes (n, n) and (n, m).
    Q, R
        Stage weights, (n, n) positive semidefinite and (m, m) positive definite
        (vectors or scalars are made diagonal).

    Returns
    -------
    K, P
        Gain (m, n) of the law ``v = K z`` and the symmetric positive definite (n, n) ``P``.
    """
    Ad, Bd = _pair(Ad, Bd)
    n, m = Bd.shape
    Q, R = weight_matrix(Q, n, "Q"), weight_matrix(R, m, "R", definite=True)
    if np.min(np.linalg.eigvalsh(R)) <= 0:
        raise ValueError("R must be positive definite (the LQR gain needs (R + B'PB)^{-1})")
    if np.min(np.linalg.eigvalsh(Q)) < -1e-12:
        raise ValueError("Q must be positive semidefinite")
    P = solve_discrete_are(Ad, Bd, Q, R)
    P = 0.5 * (P + P.T)
    K = -np.linalg.solve(R + Bd.T @ P @ Bd, Bd.T @ P @ Ad)
    return K, P


# ============================================================================ polytopes
def _lp_max(c: Array, F: Array, g: Array) -> float:
    """``max c'z s.t. F z <= g`` (HiGHS through scipy); ``inf`` if unbounded."""
    res = linprog(-c, A_ub=F, b_ub=g, bounds=[(None, None)] * len(c), method="highs")
    if res.status == 3:
        return np.inf
    if res.status != 0:
        raise RuntimeError(f"LP over the polytope failed: {res.message}")
    return float(-res.fun)


def remove_redundant(F: Array, g: Array, tol: float = 1e-9) -> tuple[Array, Array]:
    """Drop the rows of ``{z : F z <= g}`` implied by the others (one LP per row).

    Row ``i`` is redundant when ``max F_i z`` over the other rows (and
    ``F_i z <= g_i + 1``, to keep the LP bounded) is at most ``g_i + tol (1 + |g_i|)``.
    Rows are visited in order and a redundant row is removed at once, so the
    result describes the same set with no redundant row left.
    """
    F, g = as_floats(F, "F"), as_floats(g, "g").reshape(-1)
    if F.ndim != 2 or F.shape[0] != g.shape[0]:
        raise ValueError(f"F must be (p, n) and g (p,), got {F.shape} and {g.shape}")
    if not (np.all(np.isfinite(F)) and np.all(np.isfinite(g))):
        raise ValueError("F and g must be finite: they contain NaN or inf")
    tol = check_number(tol, "tol", "the relative tolerance of a redundant row")
    keep = np.ones(len(g), bool)
    for i in range(len(g)):
        keep[i] = False
        Fi, gi = np.vstack([F[keep], F[i]]), np.r_[g[keep], g[i] + 1.0]
        if _lp_max(F[i], Fi, gi) > g[i] + tol * (1.0 + abs(g[i])):
            keep[i] = True
    return F[keep], g[keep]


def max_admissible_set(A_cl: Array, C: Array, d: Array, max_iter: int = 200,
                       tol: float = 1e-9) -> tuple[Array, Array, int]:
    """Maximal output-admissible set of ``z+ = A_cl z`` for ``C z <= d`` (Gilbert & Tan 1991, Alg. 3.2).

    ``O_inf = {z : C A_cl^t z <= d, t = 0, 1, ...}``. For a Schur ``A_cl`` and a
    bounded ``{C z <= d}`` containing 0 in its interior, it is a polytope
    described by finitely many ``t``: the iteration adds ``C A_cl^{t+1}`` until
    every new row is implied by the rows ``0..t`` (one LP per row), then removes
    redundant rows (:func:`remove_redundant`).

    Parameters
    ----------
    A_cl
        Closed-loop matrix ``A_d + B_d K_f``, (n, n), Schur stable.
    C, d
        The constraints ``C z <= d``, (p, n) and (p,), with ``d > 0``.
    max_iter
        Largest ``t`` tried; ``RuntimeError`` if the set is not determined by then.

    Returns
    -------
    F, g, t_star
        ``O_inf = {F_inf z <= f_inf}`` (``F = F_inf``, ``g = f_inf``; irredundant) and the determinedness
        index ``t^star``.
    """
    A_cl = np.atleast_2d(as_floats(A_cl, "A_cl"))
    n = A_cl.shape[0]
    if A_cl.shape != (n, n):
        raise ValueError(f"A_cl must be square, got {A_cl.shape}")
    if not np.all(np.isfinite(A_cl)):
        raise ValueError("A_cl must be finite: it contains NaN or inf")
    max_iter = check_int(max_iter, "max_iter", 1, "steps t of the iteration")
    tol = check_number(tol, "tol", "the relative tolerance of an implied row")
    rho = np.max(np.abs(np.linalg.eigvals(A_cl)))
    if rho >= 1:
        raise ValueError(f"A_cl must be Schur stable (spectral radius {rho:.4g} >= 1): the closed loop with this K "
                         f"does not converge, so no bounded invariant set is determined by finitely many steps")
    C, d = as_floats(C, "C"), as_floats(d, "d").reshape(-1)
    if not (np.all(np.isfinite(C)) and np.all(np.isfinite(d))):
        raise ValueError("C and d must be finite: they contain NaN or inf")
    if C.ndim != 2 or C.shape != (len(d), n):
        raise ValueError(f"C must be ({len(d)}, {n}) to match d and A_cl, got {C.shape}")
    if np.any(d <= 0):
        raise ValueError("d must be > 0 (the constraint set must contain 0 in its interior)")
    F, g, Ak = C.copy(), d.copy(), np.eye(n)
    for t in range(max_iter):
        Ak = Ak @ A_cl
        Cn = C @ Ak
        if all(_lp_max(Cn[i], F, g) <= d[i] + tol * (1.0 + abs(d[i])) for i in range(len(d))):
            F, g = remove_redundant(F, g, tol)
            return F, g, t
        F, g = np.vstack([F, Cn]), np.r_[g, d]
    raise RuntimeError(f"the maximal output-admissible set is not determined after {max_iter} steps; raise max_iter")


def _bounding_box(F: Array, g: Array) -> tuple[Array, Array]:
    """Smallest box containing ``{F z <= g}`` (2 n LPs)."""
    n = F.shape[1]
    hi = np.array([_lp_max(np.eye(n)[j], F, g) for j in range(n)])
    lo = -np.array([_lp_max(-np.eye(n)[j], F, g) for j in range(n)])
    return lo, hi


# ============================================================================ the MILP certificate
@dataclass
class NetworkMax:
    """``max_{z in S} s Phi_NN,i(z, K z)`` over a polytope ``S`` (a gain ``K``, e.g. the terminal ``K_f``),
    from one MILP per sign and output.

    Attributes
    ----------
    upper
        Proved upper bound of ``max_S |Phi_NN,i(z, K z)|`` per output, shape (m,):
        the MILP's dual bound (of the back-end used), the larger of the two signs.
    lower
        ``|Phi_NN,i(z*, K z*)|`` at the best point found, evaluated by the
        network's forward pass, shape (m,): the maximum is at least this.
    argmax
        That point ``z*`` per output, shape (m, n_z).
    n_binaries
        Binaries of the encoding (unstable neurons under the node bounds).
    time_s
        Wall-clock time of the MILPs.
    """

    upper: Array
    lower: Array
    argmax: Array
    n_binaries: int
    time_s: float


#: The back-ends :func:`network_max` proves its bound with: ``"highs"`` (HiGHS through :func:`scipy.optimize.milp`)
#: and ``"scip"`` (SCIP through :mod:`flnotes.solvers`), two independent branch and bounds, each run at the
#: feasibility tolerances of :data:`FEASIBILITY_TOLERANCE`.
NETWORK_MAX_BACKENDS = ("highs", "scip")

#: HiGHS's tolerances for the MILPs of :func:`network_max`, set explicitly. HiGHS's defaults are looser:
#: ``mip_feasibility_tolerance`` = 1e-6 (the rows and the integrality of a MIP's solutions) and
#: ``primal_feasibility_tolerance`` = ``dual_feasibility_tolerance`` = 1e-7 (its LPs), and
#: :func:`scipy.optimize.milp` sets none of them. A binary of the big-M encoding that is 1e-6 away from 0 or 1 lets a
#: neuron's output move by 1e-6 times its big-M constant, so a certificate whose margin is a few 1e-6 would rest on
#: that default. :func:`network_max` passes these values through :func:`scipy.optimize.milp`'s options and turns
#: HiGHS refusing one into an error.
HIGHS_TOLERANCES = dict(mip_feasibility_tolerance=1e-9, primal_feasibility_tolerance=1e-9,
                        dual_feasibility_tolerance=1e-9)

#: SCIP's feasibility tolerance ``numerics/feastol`` for the MILPs of :func:`network_max` (SCIP's default is 1e-6).
SCIP_FEASTOL = 1e-9

#: The feasibility tolerance each back-end of :func:`network_max` runs at: a certificate's margin below
#: ``u_max^eps`` is read against it.
FEASIBILITY_TOLERANCE = {"highs": HIGHS_TOLERANCES["mip_feasibility_tolerance"], "scip": SCIP_FEASTOL}


def _highs_milp(c, integrality, bounds, constraints, options):
    """:func:`scipy.optimize.milp` with :data:`HIGHS_TOLERANCES` added to ``options``. scipy passes these
    options to HiGHS as they are, with a warning that is expected here; an option HiGHS refuses (a name or a value)
    raises ``OptimizeWarning`` as an error, so a run never proceeds at a tolerance other than the stated one."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Unrecognized options detected", category=RuntimeWarning)
        warnings.simplefilter("error", OptimizeWarning)
        return milp(c, integrality=integrality, bounds=bounds, constraints=constraints,
                    options={**options, **HIGHS_TOLERANCES})


def network_max(net: ReLUNet, K: Array, F: Array, g: Array, mip_rel_gap: float = 1e-6,
                time_limit: Optional[float] = None, backend: str = "highs") -> NetworkMax:
    """Maximize ``+-Phi_NN(z, K z)`` over ``{z : F z <= g}`` with the big-M encoding (eq. MIP_general).

    The input of the network is ``y^0 = [z, K z]``; the node bounds ``L``, ``U``
    of eq. (MIP_general_c) come from :func:`flnotes.fbbt` over the bounding box
    of the polytope and of ``K z`` on it (LPs), so the encoding is exact on the
    polytope. Each MILP is solved by HiGHS (:func:`scipy.optimize.milp`) or SCIP
    (``backend``); its dual bound is a proof that no point of the polytope gives a
    larger value, up to the solver's feasibility tolerance (:data:`FEASIBILITY_TOLERANCE`: 1e-9 for both, set
    explicitly, :data:`HIGHS_TOLERANCES` and :data:`SCIP_FEASTOL`) and its floating-point arithmetic: not an
    exact-arithmetic proof.

    Parameters
    ----------
    net
        ``Phi_NN`` with ``n_in = n_z + m`` inputs ``(z, v)`` and ``m`` outputs.
    K
        Gain (m, n_z) of the law ``v = K z`` (the terminal gain ``K_f`` in :func:`terminal_set`).
    F, g
        The polytope ``{F z <= g}``, (p, n_z) and (p,); it must be bounded and non-empty (in
        :func:`terminal_set`: ``F_inf z <= psi f_inf``).
    mip_rel_gap, time_limit
        Solver options (relative gap, seconds); a MILP that stops without proving optimality raises
        ``RuntimeError`` (a certificate must be a proof).
    backend
        ``"highs"`` (default) or ``"scip"`` (:data:`NETWORK_MAX_BACKENDS`): the same MILP, another solver. HiGHS
        has returned sub-optimal points labelled optimal on the book's big-M programs, so a certificate that
        matters is confirmed by the other one.

    Returns
    -------
    NetworkMax
    """
    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    if backend not in NETWORK_MAX_BACKENDS:
        raise ValueError(f"backend must be one of {NETWORK_MAX_BACKENDS}, got {backend!r}")
    K = np.atleast_2d(np.asarray(K, float))
    m, n = K.shape
    if net.n_in != n + m or net.n_out != m:
        raise ValueError(f"net maps R^{net.n_in} -> R^{net.n_out} but K of shape {K.shape} needs (z, Kz) in "
                         f"R^{n + m} -> R^{m}")
    F, g = np.asarray(F, float), np.asarray(g, float).reshape(-1)
    if F.ndim != 2 or F.shape != (len(g), n):
        raise ValueError(f"F must be ({len(g)}, {n}) to match g and K, got {F.shape}")
    t0 = time.perf_counter()
    zlo, zhi = _bounding_box(F, g)
    if not (np.all(np.isfinite(zlo)) and np.all(np.isfinite(zhi))):
        raise ValueError("the polytope {F z <= g} is unbounded: give a bounded terminal set")
    vhi = np.array([_lp_max(K[i], F, g) for i in range(m)])
    vlo = -np.array([_lp_max(-K[i], F, g) for i in range(m)])
    nb = fbbt(net, np.r_[zlo, vlo], np.r_[zhi, vhi])
    form = bigm_form(net, nb)
    N = form.n
    lb, ub = form.lb.copy(), form.ub.copy()
    lb[form.x], ub[form.x] = np.r_[zlo, vlo], np.r_[zhi, vhi]
    x_z, x_v = form.x[:n], form.x[n:]
    # v = K z:  K x_z - x_v = 0
    Lk = sp.lil_matrix((m, N))
    for i in range(m):
        Lk[i, x_z] = K[i]
        Lk[i, x_v[i]] = -1.0
    Fz = sp.lil_matrix((len(g), N))
    Fz[:, x_z] = F
    cons = [LinearConstraint(form.A_eq, form.b_eq, form.b_eq), LinearConstraint(form.A_ub, -np.inf, form.b_ub),
            LinearConstraint(Lk.tocsr(), 0.0, 0.0), LinearConstraint(Fz.tocsr(), -np.inf, g)]
    opts = dict(mip_rel_gap=mip_rel_gap)
    if time_limit is not None:
        opts["time_limit"] = float(time_limit)
    upper, lower, argmax = np.full(m, -np.inf), np.full(m, -np.inf), np.zeros((m, n))
    for i in range(m):
        for s in (1.0, -1.0):
            c = np.zeros(N)
            c[form.out[i]] = -s  # both minimize: min -s y^K_i = -max s y^K_i
            if backend == "highs":
                res = _highs_milp(c, form.integrality, Bounds(lb, ub), cons, opts)
                if res.status != 0 or res.x is None:
                    raise RuntimeError(f"the MILP max of {'+' if s > 0 else '-'}Phi_NN over the polytope was not "
                                       f"solved to optimality ({res.message}); no certificate")
                dual = getattr(res, "mip_dual_bound", None)
                up_s = -float(dual) if dual is not None and np.isfinite(dual) else -float(res.fun)
                up_s, x = max(up_s, -float(res.fun)), res.x
            else:
                up_s, x = _scip_max(c, cons, lb, ub, form.integrality, mip_rel_gap, time_limit, s)
            z_star = x[x_z]
            val = s * float(net(np.r_[z_star, K @ z_star][None])[0, i])
            upper[i] = max(upper[i], up_s, val)
            if val > lower[i]:
                lower[i], argmax[i] = val, z_star
    return NetworkMax(upper=upper, lower=lower, argmax=argmax, n_binaries=form.n_binaries,
                      time_s=time.perf_counter() - t0)


def _scip_max(c: Array, cons: list, lb: Array, ub: Array, integrality: Array, gap: float,
              time_limit: Optional[float], s: float) -> tuple[float, Array]:
    """``min c'w`` over the MILP's rows with SCIP (feasibility tolerance :data:`SCIP_FEASTOL`): ``(-bound, w)``, a
    proof or an error."""
    from .solvers import MIQP, make_solver

    A = sp.vstack([sp.csr_matrix(k.A) for k in cons]).tocsr()
    rl = np.concatenate([np.broadcast_to(k.lb, (k.A.shape[0],)) for k in cons])
    ru = np.concatenate([np.broadcast_to(k.ub, (k.A.shape[0],)) for k in cons])
    prob = MIQP(H=None, c=c, c0=0.0, A=A, rl=rl, ru=ru, lb=lb, ub=ub, integrality=integrality)
    res = make_solver(prob, "scip", feastol=SCIP_FEASTOL).solve(time_limit=time_limit, gap=gap)
    if res.status != "optimal" or res.w is None:
        raise RuntimeError(f"SCIP did not prove the MILP max of {'+' if s > 0 else '-'}Phi_NN over the polytope "
                           f"({res.status}: {res.message}); no certificate")
    return max(-float(res.bound), -float(res.objective)), res.w


# ============================================================================ the terminal set
@dataclass
class TerminalSet:
    """Terminal ingredients of the MPC (Mayne et al. 2000, axioms A1-A4) for eq. (MPC_form_miqp).

    Attributes
    ----------
    K, P
        The book's ``K_f`` and ``P_f``: LQR gain (m, n_z) of the terminal law ``v = K_f z`` and terminal
        weight (n_z, n_z) (:func:`lqr`).
    F, g
        The book's ``F_inf, f_inf``: the maximal output-admissible set ``O_inf = {F_inf z <= f_inf}`` of
        ``A_d + B_d K_f`` for the state box and the v-box (:func:`max_admissible_set`).
    psi
        The level ``psi``: ``Z_f = psi O_inf = {F_inf z <= psi f_inf}``, the largest in
        ``(0, 1]`` (within ``tol``) for which the MILP proves
        ``max_{Z_f} |Phi_NN(z, K_f z)| <= u_max^eps``.
    u_eps
        ``u_max^eps = u_max - eps`` (eq. Phi_NN_ep), shape (m,).
    certificate
        The :class:`NetworkMax` at ``psi``: ``upper <= u_eps`` is the proof.
    failed
        The :class:`NetworkMax` at the smallest level tried that failed
        (``None`` when ``psi = 1``): ``upper > u_eps`` for some output there.
    psi_failed
        That level (``psi < psi_failed <= psi (1 + tol)``), or ``None``.
    history
        One row per level tried, in order: ``(level, upper, lower, passed)`` with ``upper``, ``lower`` the
        largest over the outputs of :class:`NetworkMax`'s bounds on ``max |Phi_NN(z, K_f z)|`` over that
        level's set, and ``passed`` whether ``upper <= u_eps`` for every output.
    t_star
        Determinedness index ``t^star`` of ``O_inf``.
    Ad, Bd, Q, R, ts, z_lo, z_hi, v_lo, v_hi
        The model, weights and boxes it was built for.
    tol
        Relative tolerance of the bisection on the level ``psi``.
    discretization
        How ``(A_d, B_d)`` was computed (``"rk4"`` or ``"exact"``).
    time_s
        Wall-clock time of the whole construction.
    """

    K: Array
    P: Array
    F: Array
    g: Array
    psi: float
    u_eps: Array
    certificate: NetworkMax
    failed: Optional[NetworkMax]
    psi_failed: Optional[float]
    history: list
    t_star: int
    Ad: Array
    Bd: Array
    Q: Array
    R: Array
    ts: float
    z_lo: Array
    z_hi: Array
    v_lo: Array
    v_hi: Array
    tol: float
    discretization: str = "rk4"
    time_s: float = 0.0

    @property
    def A_cl(self) -> Array:
        """``A_d + B_d K_f``."""
        return self.Ad + self.Bd @ self.K

    def constraint(self) -> tuple[Array, Array]:
        """``(F_inf, psi f_inf)`` of the terminal constraint ``F_inf z(N_p) <= psi f_inf`` (``Z_f``)."""
        return self.F.copy(), self.psi * self.g

    def contains(self, z: Array, tol: float = 1e-9) -> Array:
        """Boolean mask: is ``z`` (n_z,) or (N, n_z) in ``Z_f = {F_inf z <= psi f_inf}``?"""
        Z = as_batch(z, self.F.shape[1], "z")
        return np.all(Z @ self.F.T <= self.psi * self.g + tol, axis=1)

    def terminal_cost(self, z: Array) -> Array:
        """``V_f(z) = z' P_f z``, for (n_z,) or (N, n_z)."""
        Z = as_batch(z, self.F.shape[1], "z")
        return np.einsum("ij,jk,ik->i", Z, self.P, Z)

    def sample(self, n: int, seed: int = 0) -> Array:
        """``n`` uniform points of ``Z_f`` (rejection sampling in its bounding box)."""
        lo, hi = _bounding_box(self.F, self.psi * self.g)
        rng = np.random.default_rng(seed)
        out, got = [], 0
        while got < n:
            Z = rng.uniform(lo, hi, (max(4 * n, 1000), len(lo)))
            Z = Z[self.contains(Z, tol=0.0)]
            out.append(Z)
            got += len(Z)
        return np.vstack(out)[:n]

    def summary(self) -> str:
        return (f"terminal set: {len(self.g)} faces (t^star = {self.t_star}), psi = {self.psi:.4g}; "
                f"max |Phi_NN(z, K_f z)| on Z_f in [{self.certificate.lower.max():.5g}, {self.certificate.upper.max():.5g}] "
                f"<= u_max^eps = {self.u_eps.max():.5g}; {len(self.history)} MILP pairs, {self.time_s:.2f} s")


def terminal_set(system: FLSystem, net: ReLUNet, eps, ts: float, Q, R, *, discretization: str = "rk4",
                 z_box: Optional[tuple] = None, v_box: Optional[tuple] = None, tol: float = 1e-2,
                 max_bisections: int = 40, mip_rel_gap: float = 1e-6) -> TerminalSet:
    """Terminal cost ``P_f``, law ``v = K_f z`` and certified terminal set ``Z_f`` for eq. (MPC_form_miqp).

    The construction follows the axioms of Mayne et al. 2000 (see the module
    docstring):

    1. ``K_f``, ``P_f`` from the Riccati equation of ``(A_d, B_d)`` with ``Q``, ``R`` (:func:`lqr`, A4);
    2. ``O_inf = {F_inf z <= f_inf}``, the maximal output-admissible set of ``A_d + B_d K_f``
       for ``z in Z_z`` and ``v_lo <= K_f z <= v_hi`` (:func:`max_admissible_set`,
       A1, A3 and the box part of A2); every ``psi O_inf`` with ``psi in (0, 1]``
       keeps these properties (a linear map and a convex set containing 0);
    3. the network part of A2, ``|Phi_NN(z, K_f z)| <= u_max^eps`` (eq. MPC_form_miqp_b),
       is proved on ``psi O_inf`` by MILPs (:func:`network_max`), and the largest
       such level ``psi`` is found by bisection: the sets are nested, so the
       maximum is non-decreasing in ``psi``. The bisection stops when the
       smallest failing level is within a factor ``1 + tol`` of the largest passing one.

    Parameters
    ----------
    system
        The system (Brunovsky pair, domain box, ``u_max``).
    net
        ``Phi_NN`` on ``system``'s stacked input ``(z, v)``.
    eps
        Certified error bound (scalar or (m,)): ``u_max^eps = u_max - eps``. To
        also keep ``|u| <= u_max`` between samples pass ``eps + Delta``
        (:mod:`flnotes.intersample`).
    ts
        Sampling time of the MPC.
    Q, R
        The MPC's stage weights (eq. MPC_form_miqp_a).
    discretization
        ``"rk4"`` (the paper) or ``"exact"``, as in the MPC.
    z_box, v_box
        ``(lo, hi)`` of the state box ``Z_z`` and of ``v``, inside the network's domain box (where ``eps`` holds; a
        wider box is refused); default that domain box.
    tol
        Relative tolerance of the bisection on the level ``psi``.

    Returns
    -------
    TerminalSet

    Raises
    ------
    ValueError
        If ``|Phi_NN(0, 0)| > u_max^eps`` (the origin itself is not admissible:
        no terminal set exists), or for arguments of the wrong shape.
    """
    t0 = time.perf_counter()
    if not isinstance(system, FLSystem):
        raise TypeError(f"system must be a flnotes.FLSystem, got {type(system).__name__}")
    if not isinstance(net, ReLUNet):
        raise TypeError(f"net must be a flnotes.ReLUNet, got {type(net).__name__}")
    if net.n_in != system.n_in or net.n_out != system.m:
        raise ValueError(f"net maps R^{net.n_in} -> R^{net.n_out} but {system.name} needs (z, v) in R^{system.n_in} "
                         f"-> u in R^{system.m}")
    tol = check_number(tol, "tol", "the relative width of the bisection on psi", strict=True)
    if tol >= 1:
        raise ValueError(f"tol must be in (0, 1), got {tol!r}")
    max_bisections = check_int(max_bisections, "max_bisections", 1, "steps of the bisection on psi")
    mip_rel_gap = check_number(mip_rel_gap, "mip_rel_gap", "the relative gap of the certifying MILPs")
    if mip_rel_gap >= 1:
        raise ValueError(f"mip_rel_gap must be in [0, 1), got {mip_rel_gap!r}")
    n, m = system.n_z, system.m
    eps = as_vector(eps, m, "eps")
    u_eps = system.u_max - eps
    if np.any(eps < 0) or np.any(u_eps <= 0):
        raise ValueError(f"need 0 <= eps < u_max: eps = {eps}, u_max = {system.u_max}")
    zb = (system.lo[:n], system.hi[:n]) if z_box is None else as_pair(z_box, "z_box")
    vb = (system.lo[n:], system.hi[n:]) if v_box is None else as_pair(v_box, "v_box")
    z_lo, z_hi = box_in_domain(zb[0], zb[1], system.lo[:n], system.hi[:n], "z_box", ("z_box[0]", "z_box[1]"))
    v_lo, v_hi = box_in_domain(vb[0], vb[1], system.lo[n:], system.hi[n:], "v_box", ("v_box[0]", "v_box[1]"))
    if np.any(z_lo >= 0) or np.any(z_hi <= 0) or np.any(v_lo >= 0) or np.any(v_hi <= 0):
        raise ValueError("z_box and v_box must contain 0 in their interior (the terminal set is built around the origin)")
    Ad, Bd = system.discretize(ts, discretization)
    K, P = lqr(Ad, Bd, Q, R)
    In = np.eye(n)
    C = np.vstack([In, -In, K, -K])
    d = np.r_[z_hi, -z_lo, v_hi, -v_lo]
    F, g, t_star = max_admissible_set(Ad + Bd @ K, C, d)
    u0 = net(np.zeros((1, n + m)))[0]
    if np.any(np.abs(u0) > u_eps):
        raise ValueError(f"|Phi_NN(0, 0)| = {np.abs(u0)} > u_max^eps = {u_eps}: the origin is not admissible for the "
                         f"network constraint, so no terminal set around it exists")

    history: list = []

    def check(a: float) -> tuple[bool, NetworkMax]:
        cert = network_max(net, K, F, a * g, mip_rel_gap=mip_rel_gap)
        ok = bool(np.all(cert.upper <= u_eps))
        history.append((a, float(np.max(cert.upper)), float(np.max(cert.lower)), ok))
        return ok, cert

    ok, cert = check(1.0)
    failed, a_fail = None, None
    if ok:
        psi, best = 1.0, cert
    else:
        lo, hi, best, failed = 0.0, 1.0, None, cert
        for _ in range(max_bisections):
            if lo > 0 and hi <= lo * (1.0 + tol):
                break
            mid = 0.5 * (lo + hi)
            ok, c = check(mid)
            if ok:
                lo, best = mid, c
            else:
                hi, failed = mid, c
        else:
            raise RuntimeError(f"the bisection on the level psi did not reach tol = {tol} in {max_bisections} steps "
                               f"(psi in [{lo:.3g}, {hi:.3g}])")
        psi, a_fail = lo, hi
    return TerminalSet(K=K, P=P, F=F, g=g, psi=psi, u_eps=u_eps, certificate=best, failed=failed,
                       psi_failed=a_fail, history=history, t_star=t_star, Ad=Ad, Bd=Bd,
                       Q=weight_matrix(Q, n, "Q"), R=weight_matrix(R, m, "R", definite=True), ts=float(ts),
                       z_lo=z_lo, z_hi=z_hi, v_lo=v_lo, v_hi=v_hi, tol=tol,
                       discretization=discretization, time_s=time.perf_counter() - t0)


# ============================================================================ recursive feasibility
def shifted_plan(term: TerminalSet, z_pred: Array, v_pred: Array) -> tuple[Array, Array]:
    """The candidate of the recursive-feasibility proof (Mayne et al. 2000, Sec. 3.3).

    Given a feasible plan ``z(0..N_p)``, ``v(0..N_p-1)`` of eq. (MPC_form_miqp)
    with ``z(N_p) in Z_f``, the plan from ``z(1)`` is ``v(1), ..., v(N_p-1), K_f z(N_p)``,
    with states ``z(1), ..., z(N_p), (A_d + B_d K_f) z(N_p)``. It is feasible for the
    nominal model: the old constraints hold for the kept steps, ``K_f z(N_p)`` is admissible on
    ``Z_f`` (A2) and ``(A_d + B_d K_f) z(N_p)`` is in ``Z_f`` (A3).

    Returns
    -------
    z_next, v_next
        Shapes (N_p + 1, n_z) and (N_p, m).
    """
    Z, V = np.asarray(z_pred, float), np.asarray(v_pred, float)
    n, m = term.K.shape[1], term.K.shape[0]
    if Z.ndim != 2 or Z.shape[1] != n or V.shape != (len(Z) - 1, m):
        raise ValueError(f"z_pred must be (N_p + 1, {n}) and v_pred (N_p, {m}), got {Z.shape} and {V.shape}")
    vN = term.K @ Z[-1]
    return np.vstack([Z[1:], term.A_cl @ Z[-1]]), np.vstack([V[1:], vN])


@dataclass
class RegionOfAttraction:
    """Feasibility of the horizon program on a 2-D grid of initial states.

    Attributes
    ----------
    x, y
        Grid values along the two sliced coordinates, shapes (n_x,) and (n_y,).
    axes
        The two coordinates of ``z`` that vary.
    z_fixed
        The value of ``z`` on the other coordinates, (n_z,).
    feasible, feasible_terminal
        Feasibility without / with the terminal constraint, shape (n_y, n_x),
        dtype float: 1 feasible, 0 infeasible, NaN undecided within the time limit.
    horizon, ts
        The program's ``N_p`` and ``t_s``.
    terminal
        The :class:`TerminalSet` used.
    time_s
        Wall-clock time (both grids).
    """

    x: Array
    y: Array
    axes: tuple
    z_fixed: Array
    feasible: Array
    feasible_terminal: Array
    horizon: int
    ts: float
    terminal: TerminalSet
    time_s: float

    def fraction(self) -> tuple[float, float]:
        """Share of decided grid points that are feasible, without and with the terminal constraint."""
        return float(np.nanmean(self.feasible)), float(np.nanmean(self.feasible_terminal))

    def points(self) -> Array:
        """All grid states, shape (n_y, n_x, n_z)."""
        X, Y = np.meshgrid(self.x, self.y)
        Z = np.broadcast_to(self.z_fixed, X.shape + (len(self.z_fixed),)).copy()
        Z[..., self.axes[0]], Z[..., self.axes[1]] = X, Y
        return Z


def region_of_attraction(system: FLSystem, net: ReLUNet, eps, terminal: TerminalSet, horizon: int,
                         axes: Sequence[int] = (0, 1), z_fixed: Optional[Array] = None, n_grid=15,
                         limits: Optional[tuple] = None, time_limit: Optional[float] = 10.0,
                         **mpc_kwargs) -> RegionOfAttraction:
    """The set of initial states from which eq. (MPC_form_miqp) has an admissible plan, on a 2-D slice.

    Decided by the MPC itself (:class:`flnotes.MPC`, the one program builder): at every grid state a fresh
    controller step (no previous plan) is solved without and with the terminal constraint
    (``terminal=terminal``; the terminal weight is left out, since the cost does not change the feasible set); the
    state is feasible when the step ends with a plan of its own (status
    ``"optimal"``, or ``"time_limit"`` with an admissible incumbent, and ``fallback`` False), infeasible when
    the status is ``"infeasible"``, and undecided (NaN) otherwise (the time limit hit without an admissible
    incumbent, or a solver error). With the terminal constraint the feasible set is the region of attraction
    of the MPC: from any of its states the loop stays feasible and converges (Mayne et al. 2000, Thm. 1).
    Without it, a feasible state may lead to an infeasible one later.

    Parameters
    ----------
    system, net, eps
        As for :class:`flnotes.MPC`.
    terminal
        The terminal ingredients (:func:`terminal_set`); its ``ts``, ``Q``, ``R``, discretization and v-box
        are the MPC's. Its state box must be the domain box (the MPC keeps its predictions there).
    horizon
        ``N_p``.
    axes
        The two coordinates of ``z`` on the grid.
    z_fixed
        Values of the other coordinates (default 0).
    n_grid
        Grid points per axis (an int or a pair).
    limits
        ``((x_lo, x_hi), (y_lo, y_hi))``; default the state box.
    time_limit
        Seconds per MPC step.
    mpc_kwargs
        Further options of :class:`flnotes.MPC` (back-end, bounds, ...).

    Returns
    -------
    RegionOfAttraction
    """
    from .mpc import MPC  # the engine sits above this module

    if not isinstance(terminal, TerminalSet):
        raise TypeError(f"terminal must be a flnotes.terminal.TerminalSet (from terminal_set), got {type(terminal).__name__}")
    n = system.n_z
    if not (np.allclose(terminal.z_lo, system.lo[:n]) and np.allclose(terminal.z_hi, system.hi[:n])):
        raise ValueError("terminal was built for a state box other than the domain box: the MPC keeps its predictions "
                         "in the domain box, so build the terminal set with the default z_box")
    axes = tuple(axes) if hasattr(axes, "__iter__") and not isinstance(axes, (str, bytes)) else (axes,)
    if len(axes) != 2:
        raise ValueError(f"axes must be two different coordinates of z in 0..{n - 1}, got {axes!r}")
    axes = tuple(check_count(a, "each of axes", 0, f"a coordinate of z in 0..{n - 1}") for a in axes)
    if axes[0] == axes[1] or not all(a < n for a in axes):
        raise ValueError(f"axes must be two different coordinates of z in 0..{n - 1}, got {axes}")
    horizon = check_count(horizon, "horizon (N_p)", 1, "steps of the prediction")
    z_fixed = np.zeros(n) if z_fixed is None else as_state(z_fixed, n, "z_fixed")
    grid = (n_grid, n_grid) if np.ndim(n_grid) == 0 else tuple(n_grid)
    if len(grid) != 2:
        raise ValueError(f"n_grid must be an integer >= 2 or a pair of them (one per axis), got {n_grid!r}")
    nx, ny = (check_count(k, "n_grid", 2, "grid points per axis") for k in grid)
    if limits is None:
        limits = ((terminal.z_lo[axes[0]], terminal.z_hi[axes[0]]), (terminal.z_lo[axes[1]], terminal.z_hi[axes[1]]))
    else:
        pairs = [as_floats(p, f"limits[{i}]").reshape(-1) for i, p in enumerate(as_pair(limits, "limits"))]
        if any(p.shape != (2,) or not np.all(np.isfinite(p)) or p[0] == p[1] for p in pairs):
            raise ValueError(f"limits must be two pairs of different finite numbers ((x_lo, x_hi), (y_lo, y_hi)), "
                             f"got {limits!r}")
        limits = tuple((float(p[0]), float(p[1])) for p in pairs)
    x, y = np.linspace(*limits[0], nx), np.linspace(*limits[1], ny)
    t0 = time.perf_counter()
    common = dict(horizon=int(horizon), ts=terminal.ts, Q=terminal.Q, R=terminal.R,
                  discretization=terminal.discretization, v_box=(terminal.v_lo, terminal.v_hi),
                  time_limit=time_limit, **mpc_kwargs)
    # feasibility does not depend on the cost: both programs keep the stage cost only (the terminal weight P
    # changes the optimum, not the feasible set, and makes each solve slower)
    mpcs = [MPC(system, net, eps, **common), MPC(system, net, eps, terminal=terminal, **common)]
    out = [np.full((ny, nx), np.nan), np.full((ny, nx), np.nan)]
    roa = RegionOfAttraction(x=x, y=y, axes=axes, z_fixed=z_fixed, feasible=out[0], feasible_terminal=out[1],
                             horizon=int(horizon), ts=terminal.ts, terminal=terminal, time_s=0.0)
    Z = roa.points()
    zero = np.zeros(n)
    for i in range(ny):
        for j in range(nx):
            for k, mpc in enumerate(mpcs):
                if k == 1 and out[0][i, j] == 0:  # the terminal constraint only removes plans
                    out[1][i, j] = 0.0
                    continue
                mpc.reset()
                out[k][i, j] = _decided(mpc(Z[i, j], zero))
    roa.time_s = time.perf_counter() - t0
    return roa


def _decided(step) -> float:
    """1 (an admissible plan of the program's own), 0 (proved infeasible) or NaN (undecided) for one MPC step."""
    if step.status in ("optimal", "time_limit") and not step.fallback:
        return 1.0
    if step.status == "infeasible":
        return 0.0
    return np.nan


# ============================================================================ helpers
def _pair(Ad: Array, Bd: Array) -> tuple[Array, Array]:
    Ad = np.atleast_2d(as_floats(Ad, "Ad"))
    Bd = as_floats(Bd, "Bd")
    if Bd.ndim == 1:
        Bd = Bd[:, None]
    n = Ad.shape[0]
    if Ad.shape != (n, n) or Bd.shape[0] != n:
        raise ValueError(f"Ad must be square and Bd must have as many rows: got Ad {Ad.shape}, Bd {Bd.shape}")
    return Ad, Bd
