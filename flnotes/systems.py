"""Feedback-linearizable systems in Brunovsky form.

A system knows its physics and nothing of networks: the Brunovsky pair
``(A, B)`` of eq. (linearizedDyna), the linearizing map ``u = phi(z, v)`` of
eq. (coor_Phi), the domain box over the stacked ``(z, v)``, the input bound
``u_max`` of eq. (constraintU), Remark 1's extra constraints, the true plant
``f(x, u)`` of eq. (sys_0) and the coordinate change ``x -> z``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence, Union

import numpy as np
from scipy.linalg import expm

from ._checks import as_state, as_batch, as_floats, as_vector, check_box, check_number, one_number

Array = np.ndarray


def brunovsky(orders: Union[int, Sequence[int]]) -> tuple[Array, Array]:
    """Continuous Brunovsky pair for chains of integrators.

    Parameters
    ----------
    orders
        Length of each chain, one per input (the relative degrees), e.g.
        ``(2,)`` for a double integrator, ``(3,)`` for a triple integrator,
        ``(2, 2)`` for two decoupled double integrators; a bare integer is one chain.

    Returns
    -------
    A, B
        ``A`` of shape (n_z, n_z) and ``B`` of shape (n_z, m) with
        ``n_z = sum(orders)`` and ``m = len(orders)`` such that each chain reads
        ``z_1' = z_2, ..., z_r' = v``.
    """
    try:
        nd = np.ndim(orders)
    except ValueError:  # ragged nesting: numpy cannot tell its depth
        nd = None
    items = [orders] if nd == 0 else list(orders) if nd == 1 else None
    items = [r.item() if isinstance(r, np.ndarray) else r for r in items or ()]  # a 0-d array is its number
    if not items or any(isinstance(r, (bool, np.bool_, np.timedelta64)) or not isinstance(r, (int, np.integer)) or r < 1
                        for r in items):
        raise ValueError("orders must be a positive integer or a non-empty sequence of positive integers (the "
                         f"length of each chain), got {orders!r}")
    orders = [int(r) for r in items]
    n_z, m = sum(orders), len(orders)
    A, B = np.zeros((n_z, n_z)), np.zeros((n_z, m))
    start = 0
    for i, r in enumerate(orders):
        A[start : start + r - 1, start + 1 : start + r] += np.eye(r - 1)
        B[start + r - 1, i] = 1.0
        start += r
    return A, B


def discretize(A: Array, B: Array, ts: float, method: str = "exact") -> tuple[Array, Array]:
    """Discretize ``z' = A z + B v`` with ``v`` held over one sample ``ts``.

    Parameters
    ----------
    A, B
        Continuous pair, shapes (n, n) and (n, m).
    ts
        Sampling time ``t_s`` in seconds, > 0.
    method
        ``"exact"``: zero-order hold through the matrix exponential
        ``A_d = e^{A t_s}``, ``B_d = int_0^{t_s} e^{A s} ds B``.
        ``"rk4"``: one classical Runge-Kutta step, as in the paper's Sec. IV-B,
        ``A_d = I + hA + (hA)^2/2 + (hA)^3/6 + (hA)^4/24`` and
        ``B_d = h(I + hA/2 + (hA)^2/6 + (hA)^3/24) B``. For chains of at most
        four integrators ``A^4 = 0`` and both methods coincide.

    Returns
    -------
    Ad, Bd
    """
    A, B = np.atleast_2d(as_floats(A, "A")), as_floats(B, "B")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
        raise ValueError("A and B must be finite: they contain NaN or inf")
    if B.ndim == 1:
        B = B[:, None]
    n = A.shape[0]
    if A.shape != (n, n) or B.shape[0] != n:
        raise ValueError(f"A must be square and B must have as many rows: got A {A.shape}, B {B.shape}")
    ts = check_number(ts, "ts", "a positive sampling time in seconds", strict=True)
    if method == "exact":
        M = np.zeros((n + B.shape[1], n + B.shape[1]))
        M[:n, :n], M[:n, n:] = A, B
        with np.errstate(all="ignore"):
            E = expm(M * ts)
        Ad, Bd = E[:n, :n], E[:n, n:]
    elif method == "rk4":
        hA, I = ts * A, np.eye(n)
        with np.errstate(all="ignore"):
            Ad = I + hA + hA @ hA / 2 + hA @ hA @ hA / 6 + hA @ hA @ hA @ hA / 24
            Bd = ts * (I + hA / 2 + hA @ hA / 6 + hA @ hA @ hA / 24) @ B
    else:
        raise ValueError(f"method must be 'exact' or 'rk4', got {method!r}")
    if not (np.all(np.isfinite(Ad)) and np.all(np.isfinite(Bd))):
        raise ValueError(f"the discretized model overflows at ts = {ts!r} (Ad, Bd beyond the float range): give a "
                         f"sampling time on the scale of the system's dynamics")
    return Ad, Bd


def condense(Ad: Array, Bd: Array, horizon: int, Q: Array, R: Array, P: Array) -> tuple[Array, Array, Array]:
    """The prediction ``z(k) = Sx[k] z(0) + Su[k] V`` of eq. (MPC_form_miqp_c), ``V = [v(0); ...; v(N_p-1)]``.

    Parameters
    ----------
    Ad, Bd
        Discrete pair, shapes (n, n) and (n, m).
    horizon
        ``N_p``.
    Q, R, P
        Stage weights (n, n), (m, m) and terminal weight (n, n) of
        ``sum_k ||z(k) - z_ref(k)||_Q^2 + ||v(k)||_R^2 + ||z(N_p) - z_ref(N_p)||_P^2``.

    Returns
    -------
    Sx, Su, H
        Shapes (N_p + 1, n, n), (N_p + 1, n, N_p m) and the symmetric Hessian (N_p m, N_p m)
        of that cost in ``V`` (written ``0.5 V' H V + ...``).
    """
    N, (n, m) = int(horizon), np.shape(Bd)
    Sx, Su = np.zeros((N + 1, n, n)), np.zeros((N + 1, n, N * m))
    Sx[0] = np.eye(n)
    for k in range(N):
        Sx[k + 1] = Ad @ Sx[k]
        Su[k + 1] = Ad @ Su[k]
        Su[k + 1][:, k * m:(k + 1) * m] = Bd
    Wk = [Q] * N + [P]
    H = 2 * (sum(Su[k].T @ Wk[k] @ Su[k] for k in range(N + 1)) + np.kron(np.eye(N), R))
    return Sx, Su, 0.5 * (H + H.T)


@dataclass
class FLSystem:
    """A feedback-linearizable system ``x' = f(x, u)``, ``|u| <= u_max``.

    In the coordinates ``z = to_z(x)`` with the input transformation
    ``u = Phi(z, v)`` (eq. coor_Phi) the closed loop is the Brunovsky chain
    ``z' = A z + B v`` (eq. linearizedDyna). The input box becomes the
    state-dependent set ``V = {(z, v): |Phi(z, v)| <= u_max}`` (eq.
    contraint_new_set), which the course learns with a ReLU network.

    Parameters
    ----------
    name
        Short label used in figures and tables.
    A, B
        Continuous Brunovsky pair, shapes (n_z, n_z) and (n_z, m); see
        :func:`brunovsky`.
    phi
        The linearizing map ``Phi(z, v)``. It must be vectorized: ``z`` of
        shape (N, n_z) and ``v`` of shape (N, m) give (N, m). Call it through
        :meth:`FLSystem.Phi`, which also accepts single points and checks shapes.
    lo, hi
        Domain box over the stacked input ``(z, v)``, shape (n_z + m,). It is
        the training box ``T`` of the network and the region ``Z`` where the
        error bound of eq. (approx_err) is claimed.
    u_max
        Input bound of eq. (constraintU), shape (m,), > 0.
    f
        True plant ``x' = f(x, u)`` with ``x`` of shape (n_x,), ``u`` of shape (m,).
    to_z
        The coordinate change ``x -> z`` (one point, shape (n_x,) -> (n_z,)).
    to_x
        Its inverse ``z -> x`` (used to start a simulation from ``z(0)``).
    extra
        Remark 1's operating constraints ``varphi(z, v) <= 0``, vectorized like
        ``phi`` and returning (N, p); ``None`` when there are none.
    phi_interval
        Optional interval enclosure of ``Phi`` over a box, used to certify the
        approximation error (see :mod:`flnotes.error`).
    state_names, input_names
        Labels for plots.
    params
        The physical parameters, for the record.
    """

    name: str
    A: Array
    B: Array
    phi: Callable[[Array, Array], Array]
    lo: Array
    hi: Array
    u_max: Array
    f: Callable[[Array, Array], Array]
    to_z: Callable[[Array], Array]
    to_x: Callable[[Array], Array]
    extra: Optional[Callable[[Array, Array], Array]] = None
    phi_interval: Optional[Callable] = None
    state_names: Sequence[str] = ()
    input_names: Sequence[str] = ()
    params: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise TypeError(f"name must be a string, got {type(self.name).__name__}")
        # copies: the system owns its arrays, so a caller's later edit of the arrays it passed changes nothing here
        self.A = np.atleast_2d(as_floats(self.A, "A")).copy()
        self.B = as_floats(self.B, "B").copy()
        if not (np.all(np.isfinite(self.A)) and np.all(np.isfinite(self.B))):
            raise ValueError("A and B must be finite: they contain NaN or inf")
        if self.B.ndim == 1:
            self.B = self.B[:, None]
        n_z = self.A.shape[0]
        if self.A.shape != (n_z, n_z):
            raise ValueError(f"A must be square, got shape {self.A.shape}")
        if self.B.shape[0] != n_z:
            raise ValueError(f"B must have n_z={n_z} rows, got shape {self.B.shape}")
        m = self.B.shape[1]
        self.u_max = as_vector(self.u_max, m, "u_max").copy()
        if np.any(self.u_max <= 0):
            raise ValueError(f"u_max must be positive, got {self.u_max}")
        lo, hi = check_box(self.lo, self.hi, n_z + m, "lo", "hi")
        if np.any(lo >= hi):
            raise ValueError(f"the domain box [lo, hi] must have a positive width in every coordinate of [z; v], got "
                             f"lo = {lo} and hi = {hi}")
        self.lo, self.hi = lo.copy(), hi.copy()
        what = dict(phi="phi(z (N, n_z), v (N, m)) -> u (N, m)", f="f(x, u) -> x'", to_z="to_z(x) -> z",
                    to_x="to_x(z) -> x", extra="extra(z, v) -> varphi (N, p), or None",
                    phi_interval="phi_interval(z, v) on flnotes.interval.Interval, or None")
        for name, sig in what.items():
            fun = getattr(self, name)
            if not callable(fun) and not (fun is None and name in ("extra", "phi_interval")):
                raise TypeError(f"{name} must be a function {sig}, got {type(fun).__name__}")
        if not self.state_names:
            self.state_names = tuple(f"z{i + 1}" for i in range(n_z))
        if not self.input_names:
            self.input_names = ("v",) if m == 1 else tuple(f"v{i + 1}" for i in range(m))

    # ------------------------------------------------------------------ sizes
    @property
    def n_z(self) -> int:
        """Dimension of the linearizing state ``z``."""
        return self.A.shape[0]

    @property
    def m(self) -> int:
        """Number of inputs."""
        return self.B.shape[1]

    @property
    def n_in(self) -> int:
        """Dimension of the stacked network input ``(z, v)``."""
        return self.n_z + self.m

    # --------------------------------------------------------------- the map
    def Phi(self, z: Array, v: Array) -> Array:
        """Evaluate ``u = Phi(z, v)`` (eq. coor_Phi) with shape checks.

        ``z`` of shape (n_z,) and ``v`` of shape (m,) give (m,); batches
        (N, n_z) and (N, m) give (N, m). A scalar ``v`` is accepted when m = 1.
        """
        Z, V, single = self._pair(z, v)
        U = np.asarray(self.phi(Z, V), float).reshape(len(Z), -1)
        if U.shape != (len(Z), self.m):
            raise ValueError(f"phi returned shape {U.shape}, expected {(len(Z), self.m)}")
        return U[0] if single else U

    def input_map(self, z: Array, rtol: float = 1e-9) -> tuple[Array, Array]:
        """``a(z)``, ``B(z)`` with ``Phi(z, v) = a(z) + B(z) v`` for every ``v`` (eq. coor_Phi), at one ``z``.

        Feedback linearization of a plant affine in its input (``x' = f_0(x) + g(x) u``) gives a map affine
        in ``v``: ``a = Phi(z, 0)``, column ``j`` of ``B`` is ``Phi(z, e_j) - Phi(z, 0)``. Checked at eight
        seeded points of the ``v``-box; a map that is not affine in ``v`` raises ``ValueError``.

        Returns
        -------
        a, B
            Shapes (m,) and (m, m).
        """
        z = as_state(z, self.n_z, "z")
        rtol = check_number(rtol, "rtol", "the relative tolerance of the affine check", strict=True)
        m = self.m
        U = self.Phi(np.repeat(z[None], m + 1, axis=0), np.vstack([np.zeros(m), np.eye(m)]))
        a, B = U[0], (U[1:] - U[0]).T
        Vt = np.random.default_rng(0).uniform(self.lo[self.n_z:], self.hi[self.n_z:], (8, m))
        Ut = self.Phi(np.repeat(z[None], 8, axis=0), Vt)
        err = np.abs(Ut - (a + Vt @ B.T))
        if np.any(err > rtol * (1.0 + np.abs(Ut))):
            raise ValueError(f"Phi of {self.name} is not affine in v at z = {np.array2string(z, precision=4)} "
                             f"(deviation {err.max():.3g}): u = a(z) + B(z) v does not hold, so its input set is not "
                             "a polytope in v and u cannot be turned into a unique v")
        return a, B

    def stack(self, z: Array, v: Array) -> Array:
        """The network input ``y^0 = [z, v]`` of eq. (MIP_general_a), shape (N, n_z + m)."""
        Z, V, single = self._pair(z, v)
        X = np.hstack([Z, V])
        return X[0] if single else X

    def split(self, X: Array) -> tuple[Array, Array]:
        """Inverse of :meth:`stack`: ``X`` of shape (N, n_z + m) -> ``(z, v)``."""
        X = as_batch(X, self.n_in, "X")
        return X[:, : self.n_z], X[:, self.n_z :]

    def phi_stacked(self, X: Array) -> Array:
        """``Phi`` on stacked inputs ``X = [z, v]`` of shape (N, n_z + m) -> (N, m)."""
        z, v = self.split(X)
        return self.Phi(z, v)

    def in_domain(self, z: Array, v: Optional[Array] = None, tol: float = 1e-9) -> Array:
        """Boolean mask: is ``(z, v)`` (or ``z`` alone) inside the domain box?"""
        if v is None:
            Z = as_batch(z, self.n_z, "z")
            lo, hi = self.lo[: self.n_z], self.hi[: self.n_z]
            return np.all((Z >= lo - tol) & (Z <= hi + tol), axis=1)
        X = as_batch(self.stack(z, v), self.n_in, "(z, v)")
        return np.all((X >= self.lo - tol) & (X <= self.hi + tol), axis=1)

    def check_domain(self, z: Array, v: Optional[Array] = None, what: str = "z") -> None:
        """Raise ``ValueError`` if a point leaves the box where the guarantee holds."""
        ok = self.in_domain(z, v)
        if not np.all(ok):
            Z = as_batch(z, self.n_z, "z")
            bad = Z[~ok][0] if v is None else self.stack(z, v).reshape(-1, self.n_in)[~ok][0]
            raise ValueError(
                f"{what} = {np.array2string(bad, precision=4)} is outside the network's trained domain "
                f"lo = {np.array2string(self.lo, precision=3)}, hi = {np.array2string(self.hi, precision=3)} "
                f"(stacked (z, v)); the error bound eps and hence |u| <= u_max are only guaranteed inside it. "
                f"Start inside the box or retrain on a larger one."
            )

    def discretize(self, ts: float, method: str = "exact") -> tuple[Array, Array]:
        """``(A_d, B_d)`` of eq. (MPC_form_miqp_c); see :func:`discretize`."""
        return discretize(self.A, self.B, ts, method)

    def linearized_rhs(self, z: Array, v: Array) -> Array:
        """``A z + B v``, the Brunovsky dynamics of eq. (linearizedDyna)."""
        return self.A @ as_state(z, self.n_z, "z") + self.B @ as_vector(v, self.m, "v")

    def grid(self, n_per_axis: int | Sequence[int]) -> Array:
        """Uniform grid over the domain box with ``n_per_axis`` points per axis, (N, n_in)."""
        from .network import uniform_grid  # the one grid (and its checks of n_per_axis)

        return uniform_grid(self.lo, self.hi, n_per_axis)

    def _pair(self, z: Array, v: Array) -> tuple[Array, Array, bool]:
        z, v = as_floats(z, "z"), as_floats(v, "v")
        single = z.ndim == 1
        Z = as_batch(z, self.n_z, "z")
        if v.ndim == 0 or (v.ndim == 1 and single):
            V = as_batch(v.reshape(-1), self.m, "v")
        elif v.ndim == 1 and self.m == 1:
            V = v.reshape(-1, 1)
        else:
            V = as_batch(v, self.m, "v")
        if len(V) != len(Z):
            raise ValueError(f"z and v must hold the same number of points, got {len(Z)} and {len(V)}")
        for name, arr in (("z", Z), ("v", V)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contains NaN or inf")
        return Z, V, single

    def __repr__(self) -> str:
        return (f"FLSystem({self.name!r}, n_z={self.n_z}, m={self.m}, u_max={self.u_max}, "
                f"lo={self.lo}, hi={self.hi})")


def integrators(orders: Union[int, Sequence[int]], lo: Sequence[float], hi: Sequence[float],
                u_max: Union[float, Sequence[float]], name: str = "integrator") -> FLSystem:
    """Chains of integrators, ``z' = A z + B u`` with ``(A, B) = brunovsky(orders)``: the system already in
    Brunovsky form, so ``Phi(z, v) = v`` (eq. coor_Phi with ``u = v``) and the plant state is ``z``.

    The simplest system to test a network or a controller on: the admissible set of eq. (contraint_new_set) is
    ``|v| <= u_max``, known exactly, and any ReLU network on ``[z; v]`` may be handed to the controllers as an
    approximation of it (:func:`flnotes.certify_error` certifies its ``eps``: the system carries the interval version
    of ``Phi``).

    Parameters
    ----------
    orders
        The order of each input's chain (an int for one input), as in :func:`brunovsky`.
    lo, hi
        The domain box of ``[z; v]``, length ``sum(orders) + len(orders)``.
    u_max
        The input bound, one per input (a float for one input).
    name
        Short label used in figures and tables.
    """
    A, B = brunovsky(orders)

    def f(x: Array, u: Array) -> Array:
        return A @ x + B @ u

    def ident(x: Array) -> Array:
        return np.asarray(x, float).copy()

    def phi(z: Array, v: Array) -> Array:
        return np.array(v, float)

    def phi_interval(z, v):  # Phi = v on flnotes.interval.Interval, for certifying eps (flnotes.error)
        return v

    return FLSystem(name, A, B, phi=phi, lo=lo, hi=hi, u_max=u_max, f=f, to_z=ident, to_x=ident,
                    phi_interval=phi_interval)


# --------------------------------------------------------------------------
# The paper's two systems
# --------------------------------------------------------------------------
def stribeck(x2: Array) -> Array:
    """Stribeck friction ``s(x_2) = (0.8 + 0.2 e^{-100|x_2|}) tanh(10 x_2) + x_2`` (Sec. IV-A)."""
    return (0.8 + 0.2 * np.exp(-100.0 * np.abs(x2))) * np.tanh(10.0 * x2) + x2


def msd(u_max: float = 5.0, z_box: float = 5.0, v_box: float = 10.0) -> FLSystem:
    """The nonlinear mass-spring-damper of eq. (MSD_model).

    ``x1' = x2``, ``x2' = -s(x2) - x1 + u``, ``|u| <= 5``; ``z = x`` and
    ``Phi(z, v) = v + s(z_2) + z_1``. Training box ``T = {|z| <= 5, |v| <= 10}``.
    """
    from .interval import msd_phi  # interval version of Phi, for certifying eps (flnotes.error)

    u_max = one_number(u_max, "u_max")
    u_max, z_box, v_box = (check_number(x, name, what, strict=True) for x, name, what in (
        (u_max, "u_max", "the input bound"), (z_box, "z_box", "the half-width of the state box"),
        (v_box, "v_box", "the half-width of the v box")))
    A, B = brunovsky([2])

    def phi(z: Array, v: Array) -> Array:
        return v + stribeck(z[:, 1:2]) + z[:, 0:1]

    def f(x: Array, u: Array) -> Array:
        return np.array([x[1], -stribeck(x[1]) - x[0] + u[0]])

    return FLSystem(
        name="MSD", A=A, B=B, phi=phi,
        lo=[-z_box, -z_box, -v_box], hi=[z_box, z_box, v_box], u_max=[u_max],
        f=f, to_z=lambda x: np.asarray(x, float).copy(), to_x=lambda z: np.asarray(z, float).copy(),
        phi_interval=msd_phi,
        state_names=("z1 (position)", "z2 (velocity)"), input_names=("v",),
        params=dict(u_max=u_max),
    )


def quad1d(Gamma: float = 10.0, gamma: float = 0.3, tau: float = 0.2, u_max: float = 0.1745,
           z_box: float = 5.0, v_box: float = 15.0, zeta_max: float = 0.99) -> FLSystem:
    """The horizontal 1-D quadrotor of eq. (quad1D_nonlinear).

    ``x'' = Gamma sin(theta) - gamma x'``, ``theta' = (u - theta) / tau`` with
    plant state ``x = [x, x', theta]`` and ``z = [x, x', x'']``. With
    ``zeta(z) = (z_3 + gamma z_2) / Gamma = sin(theta)`` the linearizing map is
    ``Phi(z, v) = tau (v + gamma z_3) / (Gamma sqrt(1 - zeta^2)) + asin(zeta)``
    and ``z_1''' = v``. The map is singular at ``|zeta| = 1`` (pitch of 90 deg):
    Remark 1's extra constraint ``|zeta(z)| - zeta_max <= 0`` keeps it away.
    On the training box ``|z| <= 5`` it holds automatically, since there
    ``|zeta| <= (5 + 0.3*5)/10 = 0.65``.
    """
    from .interval import make_quad1d_phi  # interval version of Phi, for certifying eps (flnotes.error)

    gamma = check_number(gamma, "gamma", "the drag coefficient")
    u_max = one_number(u_max, "u_max")
    Gamma, tau, u_max, z_box, v_box = (check_number(x, name, what, strict=True) for x, name, what in (
        (Gamma, "Gamma", "the thrust gain"),
        (tau, "tau", "the pitch time constant (s)"), (u_max, "u_max", "the input bound (rad)"),
        (z_box, "z_box", "the half-width of the state box"), (v_box, "v_box", "the half-width of the v box")))
    zeta_max = check_number(zeta_max, "zeta_max", "the bound on |zeta(z)| of Remark 1, below 1", strict=True)
    if zeta_max >= 1:
        raise ValueError(f"zeta_max must lie in (0, 1) (|zeta| = 1 is the singularity of Remark 1), got {zeta_max!r}")
    A, B = brunovsky([3])

    def zeta(z: Array) -> Array:
        return (z[:, 2:3] + gamma * z[:, 1:2]) / Gamma

    def phi(z: Array, v: Array) -> Array:
        s = zeta(z)
        if np.any(np.abs(s) >= 1):
            raise ValueError("Quad-1D: |zeta(z)| >= 1, the linearizing map is singular there (Remark 1)")
        return tau * (v + gamma * z[:, 2:3]) / (Gamma * np.sqrt(1 - s**2)) + np.arcsin(s)

    def extra(z: Array, v: Array) -> Array:
        return np.abs(zeta(z)) - zeta_max

    def f(x: Array, u: Array) -> Array:
        return np.array([x[1], Gamma * np.sin(x[2]) - gamma * x[1], (u[0] - x[2]) / tau])

    def to_z(x: Array) -> Array:
        return np.array([x[0], x[1], Gamma * np.sin(x[2]) - gamma * x[1]])

    def to_x(z: Array) -> Array:
        s = (z[2] + gamma * z[1]) / Gamma
        if abs(s) >= 1:
            raise ValueError(f"z = {z} has |zeta| = {abs(s):.3f} >= 1: no pitch angle realizes it")
        return np.array([z[0], z[1], np.arcsin(s)])

    sysm = FLSystem(
        name="Quad-1D", A=A, B=B, phi=phi,
        lo=[-z_box] * 3 + [-v_box], hi=[z_box] * 3 + [v_box], u_max=[u_max],
        f=f, to_z=to_z, to_x=to_x, extra=extra, phi_interval=make_quad1d_phi(Gamma, gamma, tau),
        state_names=("x", "x'", "x''"), input_names=("v",),
        params=dict(Gamma=Gamma, gamma=gamma, tau=tau, u_max=u_max, zeta_max=zeta_max),
    )
    sysm.zeta = lambda z: zeta(as_batch(z, 3, "z"))[:, 0]  # type: ignore[attr-defined]
    return sysm
