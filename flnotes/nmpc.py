"""Two baselines that work on the true input ``u``: nonlinear MPC on the original plant, and saturation.

The book's controllers decide the virtual input ``v`` of the Brunovsky chain and impose
``|Phi(z, v)| <= u_max`` through the network (eq. MPC_form_miqp). The comparative study sets
them against the two designs a control engineer would try first:

* :class:`NonlinearMPC`: MPC on the original plant ``x' = f(x, u)`` of eq. (sys_0) with
  ``|u| <= u_max`` (eq. constraintU) as a plain bound on the decision variables. No feedback
  linearization, no network, no ``eps``; the program is a nonconvex NLP, solved to a *local*
  optimum by IPOPT through CasADi (multiple shooting, RK4 with ``u`` held over ``t_s``, exact
  Hessian, warm start from the shifted previous solution). Its cost is the book's cost
  written on ``z = T(x)`` (``to_z``), with ``v = dz_n/dt = (dT_n/dx) f(x, u)``, so that both
  designs minimize the same function of the same trajectory.
* :class:`SaturatedInput`: any controller that returns ``v`` (typically the unconstrained
  linear MPC on the Brunovsky model), followed by the clipping ``u = sat(Phi(z, v))`` that a
  naive implementation applies at the actuator.

Both talk to :func:`flnotes.simulate` through the controller protocol ``step(z, t,
reference)``, which answers a ``v``; they return the ``v`` that produces their ``u`` through
the linearizing map, ``Phi(z, v) = u``. For the systems of the book ``Phi`` is affine in ``v``
(eq. coor_Phi: ``u = a(z) + b(z) v``), so this ``v`` is unique; :func:`input_to_v` checks
affinity at the point and raises otherwise. Run the nonlinear MPC with ``hold="u"`` (its
prediction model holds ``u`` over the sample) to apply exactly its ``u``.
"""
from __future__ import annotations

import dataclasses
import time
import warnings
from typing import Callable, Optional

import numpy as np

from ._checks import as_state, as_floats, as_vector, check_bool, check_count, check_number, horizon_reference, weight_matrix
from .errors import SolverFailure
from .result import StepResult
from .systems import FLSystem

Array = np.ndarray

__all__ = ["NonlinearMPC", "SaturatedInput", "input_to_v"]

#: IPOPT return statuses read as a solved program.
_SOLVED = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
_LIMIT = ("Maximum_Iterations_Exceeded", "Maximum_CpuTime_Exceeded", "Maximum_WallTime_Exceeded")
_INFEASIBLE = ("Infeasible_Problem_Detected",)


def _record(**fields) -> StepResult:
    """A :class:`flnotes.StepResult` from the given fields; those the record has no attribute for go to ``info``."""
    names = {f.name for f in dataclasses.fields(StepResult)}
    kw = {k: v for k, v in fields.items() if k in names}
    rest = {k: v for k, v in fields.items() if k not in names}
    if rest and "info" in names:
        kw["info"] = {**kw.get("info", {}), **rest}
    return StepResult(**kw)


def input_to_v(system: FLSystem, z: Array, u: Array) -> Array:
    """The virtual input ``v`` with ``Phi(z, v) = u`` (eq. coor_Phi inverted; ``Phi`` affine in ``v``).

    Parameters
    ----------
    system
        The system.
    z
        State, shape (n_z,).
    u
        True input, shape (m,).

    Returns
    -------
    v
        Shape (m,).
    """
    if not isinstance(system, FLSystem):
        raise TypeError(f"system must be a flnotes.FLSystem, got {type(system).__name__}")
    a, b = system.input_map(z)  # ValueError when Phi is not affine in v
    if not np.all(np.isfinite(b)) or abs(np.linalg.det(b)) < 1e-12 * max(1.0, np.abs(b).max()) ** system.m:
        raise ValueError(f"dPhi/dv of {system.name} is singular at z = {np.array2string(np.asarray(z), precision=4)}: "
                         "no v realizes a given u there")
    u = as_vector(u, system.m, "u")
    return np.linalg.solve(b, u - a)


class SaturatedInput:
    """Saturated feedback linearization: ``u = clip(Phi(z, v_inner), -u_max, u_max)``.

    Wraps a controller that answers a ``v`` (the unconstrained linear MPC on the Brunovsky
    model, ``fl.MPC(..., constraint="none")``, in the comparative study) and returns the ``v``
    whose true input is the clipped one, ``Phi(z, v) = sat(Phi(z, v_inner))``. With
    ``hold="v"`` the clipping acts at the sampling instants; between them ``u(t) = Phi(z(t), v)``
    moves with the state as for every controller that holds ``v``.

    Parameters
    ----------
    inner
        A controller with ``step(z, t, reference)``.
    system
        The system (``Phi``, ``u_max``).
    """

    def __init__(self, inner, system: FLSystem):
        if not hasattr(inner, "step"):
            raise TypeError(f"inner must be a controller with step(z, t, reference), got {type(inner).__name__}")
        if not isinstance(system, FLSystem):
            raise TypeError(f"system must be a flnotes.FLSystem, got {type(system).__name__}")
        self.inner, self.system = inner, system
        self.net = getattr(inner, "net", None)  # so that simulate checks the domain box as for the inner controller

    def reset(self) -> None:
        """Forget the inner controller's plan (called by :func:`flnotes.simulate` at the start of a run)."""
        if hasattr(self.inner, "reset"):
            self.inner.reset()

    def step(self, z: Array, t: float, reference: Optional[Callable[[Array], Array]] = None) -> StepResult:
        """The inner controller's step with ``v`` replaced so that the true input is clipped to ``+-u_max``."""
        t0 = time.perf_counter()
        res = self.inner.step(z, t, reference)
        u_inner = self.system.Phi(z, res.v)
        u = np.clip(u_inner, -self.system.u_max, self.system.u_max)
        v = input_to_v(self.system, z, u) if np.any(u != u_inner) else np.asarray(res.v, float)
        changes = dict(v=v, solve_time=time.perf_counter() - t0)
        if hasattr(res, "info") and isinstance(res.info, dict):
            changes["info"] = {**res.info, "u_unclipped": u_inner, "clipped": bool(np.any(u != u_inner))}
        return dataclasses.replace(res, **changes)


class NonlinearMPC:
    """Nonlinear MPC on the original plant ``x' = f(x, u)`` with ``|u| <= u_max`` as a bound (CasADi + IPOPT).

    The program, solved at every sampling instant for the measured ``x(0) = to_x(z)``::

        min   sum_{k=0}^{N_p-1} ||T(x_k) - z_ref(k)||_Q^2 + ||v_k||_R^2 + ||T(x_{N_p}) - z_ref(N_p)||_{P_f}^2
        s.t.  x_0 = x(0),  x_{k+1} = F_RK4(x_k, u_k)            (u held over t_s, multiple shooting)
              -u_max <= u_k <= u_max                             (eq. constraintU, a plain bound)
              z_lo <= T(x_k) <= z_hi,  v_lo <= v_k <= v_hi        (the domain box of the other methods)

    with ``T = to_z`` and ``v_k = (dT_n/dx)(x_k) f(x_k, u_k)``, the virtual input of the
    Brunovsky chain at the start of step ``k``: the cost is eq. (MPC_form_miqp_a) of the book's
    MPC. The NLP is nonconvex; IPOPT returns a local optimum (a KKT point).

    Parameters
    ----------
    system
        The plant; its ``f(x, u)`` and ``to_z(x)`` are evaluated on CasADi symbols
        (element-wise numpy arithmetic, as the Quad-1D's are written) unless ``f`` or ``to_z``
        is given.
    horizon, ts
        ``N_p`` and ``t_s`` (seconds).
    Q, R, P
        Weights as in :class:`flnotes.MPC` (``P=None``: no terminal term, as the paper).
    rk4_steps
        RK4 sub-steps per sampling interval in the prediction.
    state_box, v_box
        Keep ``T(x_k)`` and ``v_k`` in the system's domain box (default ``True``), as the
        FL-based methods do.
    max_iter
        IPOPT iteration limit per step. Reaching it is reported as ``status="time_limit"``.
    time_limit
        Wall-clock seconds per solve (IPOPT's ``max_wall_time``), or ``None``; reaching it is
        reported as ``status="time_limit"``.
    warm_start
        Start IPOPT from the previous solution shifted by one step (``False``: from the
        constant state and ``u = 0`` every time).
    ipopt_options
        Extra IPOPT options (``print_level`` is 0 and ``print_time`` off unless given).
    f, to_z
        Optional replacements of ``system.f`` and ``system.to_z`` written for CasADi symbols
        (element-wise arithmetic; e.g. ``to_z=lambda x: x`` when ``to_z`` converts with
        ``np.asarray(x, float)``, as the MSD's does). Whichever is used is checked against the
        system's own functions on random points of the domain box (``ValueError`` on a mismatch).

    Notes
    -----
    A step IPOPT does not solve (infeasible, iteration limit, numerical failure) applies the
    first input of its last iterate clipped to ``+-u_max`` (IPOPT keeps iterates inside the
    variable bounds), flagged ``fallback=True`` with the solver's message. The bound on ``u``
    therefore holds at every sample; nothing else is guaranteed at such a step.
    """

    def __init__(self, system: FLSystem, horizon: int = 10, ts: float = 0.1, Q=None, R=None, P=None, *,
                 rk4_steps: int = 1, state_box: bool = True, v_box: bool = True, max_iter: int = 200,
                 warm_start: bool = True, time_limit: Optional[float] = None, ipopt_options: Optional[dict] = None,
                 f: Optional[Callable] = None, to_z: Optional[Callable] = None):
        try:
            import casadi as ca
        except ImportError as exc:  # pragma: no cover - casadi is a requirement
            raise ImportError("NonlinearMPC needs CasADi: pip install casadi") from exc
        if not isinstance(system, FLSystem):
            raise TypeError(f"system must be a flnotes.FLSystem, got {type(system).__name__}")
        horizon = check_count(horizon, "horizon (N_p)", 1, "steps of the prediction")
        ts = check_number(ts, "ts", "a positive sampling time in seconds", strict=True)
        rk4_steps = check_count(rk4_steps, "rk4_steps", 1, "RK4 steps per sampling interval")
        max_iter = check_count(max_iter, "max_iter", 1, "IPOPT iterations per solve")
        time_limit = check_number(time_limit, "time_limit", "seconds per solve", strict=True, none=True)
        self.time_limit = time_limit
        self.system, self.N, self.ts = system, int(horizon), float(ts)
        self.n_z, self.m = system.n_z, system.m
        self.Q = weight_matrix(Q if Q is not None else np.eye(self.n_z), self.n_z, "Q")
        self.R = weight_matrix(R if R is not None else np.eye(self.m), self.m, "R", definite=True)
        self.P = weight_matrix(P, self.n_z, "P") if P is not None else np.zeros((self.n_z, self.n_z))
        self.u_max = system.u_max.copy()
        warm_start = check_bool(warm_start, "warm_start", "whether IPOPT starts from the shifted previous solution")
        state_box = check_bool(state_box, "state_box", "whether the predictions keep the state box")
        v_box = check_bool(v_box, "v_box", "whether v keeps its box")
        self.rk4_steps, self.warm_start, self.max_iter = int(rk4_steps), warm_start, int(max_iter)
        x_probe = np.asarray(system.to_x(np.zeros(self.n_z)), float).reshape(-1)
        self.n_x = len(x_probe)
        self._ca = ca
        for name, fun in (("f", f), ("to_z", to_z)):
            if fun is not None and not callable(fun):
                raise TypeError(f"{name} must be a function or None, got {type(fun).__name__}")
        self._f_sym = f if f is not None else system.f
        self._to_z_sym = to_z if to_z is not None else system.to_z
        self._build(ca, bool(state_box), bool(v_box), dict(ipopt_options or {}))
        self.history: list = []
        self._w: Optional[Array] = None

    # ------------------------------------------------------------------ the NLP
    def _symbolic(self, fun, *args):
        """``fun`` (written with numpy) on CasADi scalars, as one column."""
        ca = self._ca
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)  # numpy functions on CasADi scalars (legacy mode)
            out = fun(*[np.array([a[i] for i in range(a.shape[0])], dtype=object) for a in args])
        return ca.vertcat(*[ca.SX(o) if not isinstance(o, ca.SX) else o for o in np.ravel(out)])

    def _build(self, ca, state_box: bool, v_box: bool, ipopt_options: dict) -> None:
        n_x, m, N, n_z = self.n_x, self.m, self.N, self.n_z
        x, u = ca.SX.sym("x", n_x), ca.SX.sym("u", m)
        xdot = self._symbolic(self._f_sym, x, u)
        z = self._symbolic(self._to_z_sym, x)
        if xdot.shape[0] != n_x or z.shape[0] != n_z:
            raise ValueError(f"f(x, u) and to_z(x) of {self.system.name} must return {n_x} and {n_z} values on "
                             f"CasADi symbols, got {xdot.shape[0]} and {z.shape[0]}")
        self._check_symbolic(ca.Function("f", [x, u], [xdot]), ca.Function("T", [x], [z]))
        # the virtual input: v = dz_r/dt at the end of each chain (Brunovsky: z_r' = v)
        ends = [int(np.flatnonzero(self.system.B[:, j])[0]) for j in range(m)]
        vexpr = ca.vertcat(*[ca.jtimes(z[i], x, xdot) for i in ends])
        self._f = ca.Function("f", [x, u], [xdot])
        self._T = ca.Function("T", [x], [z])
        self._v = ca.Function("v", [x, u], [vexpr])
        h = self.ts / self.rk4_steps
        xk = x
        for _ in range(self.rk4_steps):
            k1 = self._f(xk, u)
            k2 = self._f(xk + h / 2 * k1, u)
            k3 = self._f(xk + h / 2 * k2, u)
            k4 = self._f(xk + h * k3, u)
            xk = xk + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        self._F = ca.Function("F", [x, u], [xk])

        X = ca.SX.sym("X", n_x, N + 1)
        U = ca.SX.sym("U", m, N)
        x0 = ca.SX.sym("x0", n_x)
        Zr = ca.SX.sym("Zr", n_z, N + 1)
        Q, R, P = (ca.DM(M) for M in (self.Q, self.R, self.P))
        J, g, glo, ghi = 0, [X[:, 0] - x0], [np.zeros(n_x)], [np.zeros(n_x)]
        z_lo, z_hi = self.system.lo[:n_z], self.system.hi[:n_z]
        v_lo, v_hi = self.system.lo[n_z:], self.system.hi[n_z:]
        for k in range(N):
            e = self._T(X[:, k]) - Zr[:, k]
            vk = self._v(X[:, k], U[:, k])
            J += ca.bilin(Q, e, e) + ca.bilin(R, vk, vk)
            g.append(self._F(X[:, k], U[:, k]) - X[:, k + 1])
            glo.append(np.zeros(n_x)), ghi.append(np.zeros(n_x))
            if v_box:
                g.append(vk), glo.append(v_lo), ghi.append(v_hi)
            if state_box and k >= 1:
                g.append(self._T(X[:, k])), glo.append(z_lo), ghi.append(z_hi)
        e = self._T(X[:, N]) - Zr[:, N]
        J += ca.bilin(P, e, e)
        if state_box:
            g.append(self._T(X[:, N])), glo.append(z_lo), ghi.append(z_hi)
        w = ca.vertcat(ca.vec(X), ca.vec(U))
        p = ca.vertcat(x0, ca.vec(Zr))
        opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.max_iter": self.max_iter,
                "show_eval_warnings": False, "ipopt.honor_original_bounds": "yes"}
        if self.time_limit is not None:
            opts["ipopt.max_wall_time"] = float(self.time_limit)
        opts.update({(k if k.startswith("ipopt.") or k in ("print_time",) else f"ipopt.{k}"): v
                     for k, v in ipopt_options.items()})
        self._solver = ca.nlpsol("nmpc", "ipopt", {"x": w, "f": J, "g": ca.vertcat(*g), "p": p}, opts)
        self._J = ca.Function("J", [w, p], [J])
        G = ca.vertcat(*g)
        self._kkt_fun = ca.Function("kkt", [w, p], [ca.gradient(J, w), G, ca.jacobian(G, w)])
        self._glo, self._ghi = np.concatenate(glo), np.concatenate(ghi)
        nX, nU = n_x * (N + 1), m * N
        self._lbw = np.r_[np.full(nX, -np.inf), np.tile(-self.u_max, N)]
        self._ubw = np.r_[np.full(nX, np.inf), np.tile(self.u_max, N)]
        self._nX, self._nU = nX, nU

    def _check_symbolic(self, fs, Ts, n: int = 20) -> None:
        """The CasADi versions of ``f`` and ``to_z`` must agree with the system's on random points of the box."""
        rng = np.random.default_rng(0)
        sysm = self.system
        for _ in range(n):
            zp = rng.uniform(sysm.lo[: self.n_z], sysm.hi[: self.n_z])
            xp = np.asarray(sysm.to_x(zp), float).reshape(-1)
            up = rng.uniform(-self.u_max, self.u_max)
            for name, a, b in (("f(x, u)", np.asarray(fs(xp, up), float).reshape(-1), sysm.f(xp, up)),
                               ("to_z(x)", np.asarray(Ts(xp), float).reshape(-1), sysm.to_z(xp))):
                b = np.asarray(b, float).reshape(-1)
                if a.shape != b.shape or not np.allclose(a, b, rtol=1e-9, atol=1e-9):
                    raise ValueError(f"{name} of {sysm.name} evaluated on CasADi symbols gives {a} instead of {b} "
                                     f"at x = {xp}: write it with element-wise arithmetic, or pass a CasADi-ready "
                                     f"version (NonlinearMPC(..., f=..., to_z=...))")

    # ------------------------------------------------------------------ helpers
    def reset(self) -> None:
        """Forget the previous solution and the history (called by :func:`flnotes.simulate`)."""
        self._w = None
        self.history = []

    def _split(self, w: Array) -> tuple[Array, Array]:
        X = w[: self._nX].reshape(self.N + 1, self.n_x)
        U = w[self._nX:].reshape(self.N, self.m)
        return X, U

    def _pack(self, X: Array, U: Array) -> Array:
        return np.r_[np.asarray(X, float).reshape(-1), np.asarray(U, float).reshape(-1)]

    def rollout(self, x0: Array, U: Array) -> Array:
        """States ``x_0..x_N`` of the RK4 prediction for inputs ``U`` (N_p, m) from ``x0``."""
        X = [np.asarray(x0, float)]
        for uk in np.asarray(U, float).reshape(self.N, self.m):
            X.append(np.asarray(self._F(X[-1], uk), float).reshape(-1))
        return np.array(X)

    def cost(self, x0: Array, U: Array, z_ref: Array) -> float:
        """The NLP's cost of the inputs ``U`` (N_p, m) from ``x0`` on the RK4 prediction."""
        R = self._check_ref(z_ref)
        X = self.rollout(x0, U)
        return float(self._J(self._pack(X, U), np.r_[np.asarray(x0, float), R.reshape(-1)]))

    def _check_ref(self, z_ref) -> Array:
        return horizon_reference(z_ref, self.N, self.n_z)

    def _guess(self, x0: Array, u_guess: Optional[Array] = None) -> Array:
        if u_guess is not None:
            U = as_floats(u_guess, "u_guess")
            if U.size != self.N * self.m or not np.all(np.isfinite(U)):
                raise ValueError(f"u_guess must be finite inputs of shape (N_p, m) = ({self.N}, {self.m}), got "
                                 f"shape {U.shape}")
            U = np.clip(U.reshape(self.N, self.m), -self.u_max, self.u_max)
            return self._pack(self.rollout(x0, U), U)
        if self.warm_start and self._w is not None:
            X, U = self._split(self._w)
            U = np.vstack([U[1:], U[-1:]])
            X = np.vstack([x0[None], X[2:], self._F(X[-1], U[-1]).full().reshape(1, -1)])
            return self._pack(X, U)
        U = np.zeros((self.N, self.m))
        return self._pack(self.rollout(x0, U), U)

    # ------------------------------------------------------------------ solving
    def solve(self, x0: Array, z_ref, u_guess: Optional[Array] = None) -> dict:
        """Solve the NLP for the plant state ``x0`` (n_x,) and the reference ``z_ref`` (N_p + 1, n_z).

        IPOPT starts from the shifted previous solution (with ``warm_start``), else from the
        RK4 rollout of ``u = 0``; ``u_guess`` (N_p, m), clipped to the bound, overrides both
        (the start is its rollout).

        Returns
        -------
        dict
            ``u`` (m,), ``x_pred`` (N_p + 1, n_x), ``u_pred`` (N_p, m), ``z_pred`` (N_p + 1, n_z),
            ``v_pred`` (N_p, m), ``objective``, ``status`` (``"optimal"``, ``"time_limit"``,
            ``"infeasible"`` or ``"error"``), ``ipopt_status``, ``iterations``, ``kkt``
            (the largest violation of the KKT conditions at the returned point: stationarity,
            primal feasibility, complementarity), ``solve_time`` (seconds).
        """
        t0 = time.perf_counter()
        x0 = as_state(x0, self.n_x, "x0")
        R = self._check_ref(z_ref)
        if u_guess is not None and np.shape(u_guess) not in ((self.N, self.m), (self.N * self.m,)):
            raise ValueError(f"u_guess must have shape (horizon, m) = ({self.N}, {self.m}), got {np.shape(u_guess)}")
        p = np.r_[x0, R.reshape(-1)]
        w0 = self._guess(x0, u_guess)
        sol = self._solver(x0=w0, p=p, lbx=self._lbw, ubx=self._ubw, lbg=self._glo, ubg=self._ghi)
        st = self._solver.stats()
        w = np.asarray(sol["x"], float).reshape(-1)
        ipopt = str(st.get("return_status", ""))
        if ipopt in _SOLVED:
            status = "optimal"
        elif ipopt in _LIMIT:
            status = "time_limit"
        elif ipopt in _INFEASIBLE:
            status = "infeasible"
        else:
            status = "error"
        X, U = self._split(w)
        out = dict(u=np.clip(U[0], -self.u_max, self.u_max), x_pred=X, u_pred=U,
                   z_pred=np.array([np.asarray(self._T(xx), float).reshape(-1) for xx in X]),
                   v_pred=np.array([np.asarray(self._v(X[k], U[k]), float).reshape(-1) for k in range(self.N)]),
                   objective=float(sol["f"]), status=status, ipopt_status=ipopt,
                   iterations=int(st.get("iter_count", 0)),
                   kkt=self._kkt(w, p, np.asarray(sol["lam_x"], float).reshape(-1),
                                 np.asarray(sol["lam_g"], float).reshape(-1)),
                   solve_time=time.perf_counter() - t0)
        if status == "optimal" and np.all(np.isfinite(w)):
            self._w = w
        return out

    def _kkt(self, w: Array, p: Array, lam_x: Array, lam_g: Array) -> dict:
        """KKT residuals of the NLP at ``(w, lam)`` in CasADi's sign convention (grad f + J' lam_g + lam_x = 0)."""
        grad, g, Jg = (np.asarray(a, float) for a in self._kkt_fun(w, p))
        grad, g = grad.reshape(-1), g.reshape(-1)
        stat = grad + Jg.T @ lam_g + lam_x
        prim = max(0.0, float(np.max(np.r_[self._glo - g, g - self._ghi, self._lbw - w, w - self._ubw])))
        # complementarity: a positive multiplier only on an active upper bound, a negative one on a lower bound
        sx = np.where(lam_x > 0, np.abs(lam_x) * np.abs(np.minimum(self._ubw - w, 1e3)),
                      np.abs(lam_x) * np.abs(np.minimum(w - self._lbw, 1e3)))
        sg = np.where(lam_g > 0, np.abs(lam_g) * np.abs(np.minimum(self._ghi - g, 1e3)),
                      np.abs(lam_g) * np.abs(np.minimum(g - self._glo, 1e3)))
        return dict(stationarity=float(np.abs(stat).max()), primal=prim,
                    complementarity=float(max(sx.max(initial=0.0), sg.max(initial=0.0))))

    def __call__(self, z: Array, z_ref) -> dict:
        """Solve for the measured linearizing state ``z`` (converted with ``to_x``); see :meth:`solve`."""
        z = as_state(z, self.n_z, "z")
        return self.solve(np.asarray(self.system.to_x(z), float).reshape(-1), z_ref)

    def step(self, z: Array, t: float, reference: Optional[Callable[[Array], Array]] = None) -> StepResult:
        """One sampling instant for :func:`flnotes.simulate`: solve, then return ``v`` with ``Phi(z, v) = u``.

        ``z_ref(k) = reference(t + k t_s)``, k = 0..N_p (zero without a reference). A step
        IPOPT does not solve applies its last iterate's first input clipped to ``+-u_max``,
        flagged ``fallback=True``.
        """
        t0 = time.perf_counter()
        t = check_number(t, "t", "the time of the step in seconds", low=-np.inf)
        R = (np.zeros((self.N + 1, self.n_z)) if reference is None
             else as_floats(reference(t + self.ts * np.arange(self.N + 1)), "reference(t)"))
        s = self(z, R)
        u = s["u"]
        if not np.all(np.isfinite(u)):
            raise SolverFailure(f"NonlinearMPC at t = {t:.3f} s: IPOPT returned no finite input "
                                f"({s['ipopt_status']})", status=s["status"])
        v = input_to_v(self.system, z, u)
        fallback = s["status"] != "optimal"
        message = f"IPOPT: {s['ipopt_status']}, {s['iterations']} iterations" + (
            "; applied the last iterate's first input clipped to +-u_max" if fallback else "")
        self.history.append(s)
        return _record(v=v, status=s["status"], solve_time=time.perf_counter() - t0, fallback=fallback,
                       input_admissible=True, objective=s["objective"], message=message, u=u,
                       z_pred=s["z_pred"], v_pred=s["v_pred"], u_pred=s["u_pred"], z_ref=R,
                       iterations=s["iterations"], wall_time=time.perf_counter() - t0)

    def __repr__(self) -> str:
        return (f"NonlinearMPC({self.system.name}, N_p={self.N}, ts={self.ts}, RK4 x{self.rk4_steps}, "
                f"IPOPT max_iter={self.max_iter}, warm_start={self.warm_start})")
