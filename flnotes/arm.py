"""A two-input system: the two-link planar arm with torque limits (computed torque).

Why this system
---------------
The course's systems have one input, so the set ``V(z) = {v : |Phi(z, v)| <= u_max}``
of eq. (contraint_new_set) is an interval. A system with two inputs makes it a
set in the ``v``-plane, and the arm makes it a *genuinely* two-dimensional one:

* computed torque ``u = Phi(z, v) = M(q) v + C(q, q') q' + g(q)`` is affine in
  ``v`` for a fixed ``z``, so ``V(z)`` is the parallelogram
  ``{v : -u_max <= M(q) v + h(q, q') <= u_max}`` (``h = C q' + g``) cut by the
  ``v``-box. The inertia matrix ``M(q)`` is full (``M_12 != 0``): each torque
  limit constrains *both* accelerations, the inputs are coupled, and the
  parallelogram's sides turn with the elbow angle ``q_2`` while its centre
  ``-M^{-1} h`` moves with gravity and the Coriolis/centrifugal terms;
* ``M(q)`` is positive definite for every ``q``, so ``Phi`` is smooth and
  bounded on any box: the network is trained, and ``eps`` certified, on a
  plain box over ``(z, v)``.

The dynamically extended unicycle (flat outputs ``x, y``) was the other
candidate. Its ``V(z)`` is a rectangle in the frame of the heading, scaled by
the speed ``s``; but ``Phi`` has the singularity ``omega = (...)/s`` at
``s = 0``, so a training box over ``z`` must exclude a neighbourhood of the
speed's zero: an annulus in ``(x', y')``, not a box, so it fits neither
:func:`flnotes.fit_relu` nor :func:`flnotes.certify_error` without Remark 1's
extra constraint doing the real work. The arm has no such singularity.

Coordinates
-----------
The plant state is ``x = (q_1, q_2, q_1', q_2')`` (joint angles measured from the
downward vertical, the arm moves in a vertical plane), the input ``u``
(joint torques, N m). ``fl.brunovsky((2, 2))`` orders the linearizing state as
two chains: ``z = (q_1, q_1', q_2, q_2')`` and ``z'' = v`` per chain, i.e.
``v = (q_1'', q_2'')``.

The network
-----------
:func:`arm_net` loads the network ``Phi_NN`` with two outputs shipped with the
package (reference ``"Arm2"``, :mod:`flnotes.reference`) and its error bound
``eps`` certified per output by :func:`flnotes.certify_error` on the whole
six-dimensional box; :func:`make_arm_reference` trains and certifies it anew.
:mod:`flnotes.pieces` draws the input sets as polygons and solves the
CLF-CBF program exactly for two inputs.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Optional, Sequence

import numpy as np

from . import interval as iv
from ._checks import as_batch, as_floats, as_state, as_vector, brief, check_count, check_number
from .control import Certificate
from .systems import FLSystem, brunovsky

Array = np.ndarray

__all__ = ["two_link_arm", "arm_parameters", "arm_mass_matrix", "arm_bias", "arm_net", "make_arm_reference",
           "ARM_REFERENCE", "ARM_SETTINGS", "ARM_EPS_SETTINGS",
           "arm_joint_positions", "arm_link_points", "links_distance", "ArmPointCBF", "arm_obstacle_cbfs"]

#: Name of the shipped reference network of :func:`two_link_arm` (see :func:`arm_net`).
ARM_REFERENCE = "Arm2"

#: Default physical parameters: two uniform links of 0.5 m and 1 kg.
_DEFAULTS = dict(l1=0.5, l2=0.5, m1=1.0, m2=1.0, g=9.81)


def arm_parameters(l1: float = 0.5, l2: float = 0.5, m1: float = 1.0, m2: float = 1.0, g: float = 9.81) -> dict:
    """The lumped constants of the arm's dynamics, for two uniform links (rods).

    With ``l_ci = l_i / 2`` and ``I_i = m_i l_i^2 / 12`` (rod about its centre):
    ``a_1 = I_1 + I_2 + m_1 l_c1^2 + m_2 (l_1^2 + l_c2^2)``, ``a_2 = m_2 l_1 l_c2``,
    ``a_3 = I_2 + m_2 l_c2^2``, ``b_1 = (m_1 l_c1 + m_2 l_1) g``, ``b_2 = m_2 l_c2 g``, so that

    ``M(q) = [[a_1 + 2 a_2 cos q_2, a_3 + a_2 cos q_2], [a_3 + a_2 cos q_2, a_3]]``,
    ``C(q, q') q' = a_2 sin q_2 [-(2 q_1' q_2' + q_2'^2), q_1'^2]``,
    ``g(q) = [b_1 sin q_1 + b_2 sin(q_1 + q_2), b_2 sin(q_1 + q_2)]``.
    """
    vals = dict(l1=l1, l2=l2, m1=m1, m2=m2, g=g)
    l1, l2, m1, m2, g = (check_number(x, k, "a link length (m), mass (kg) or gravity (m/s^2)", strict=True)
                         for k, x in vals.items())
    lc1, lc2 = l1 / 2, l2 / 2
    I1, I2 = m1 * l1**2 / 12, m2 * l2**2 / 12
    return dict(vals, a1=I1 + I2 + m1 * lc1**2 + m2 * (l1**2 + lc2**2), a2=m2 * l1 * lc2, a3=I2 + m2 * lc2**2,
                b1=(m1 * lc1 + m2 * l1) * g, b2=m2 * lc2 * g)


#: The keys of a parameter dict: the physical constants (arguments of :func:`arm_parameters`), the lumped ones it
#: derives, and the settings :func:`two_link_arm` adds to its ``params`` (ignored here).
_PHYSICAL = ("l1", "l2", "m1", "m2", "g")
_LUMPED = ("a1", "a2", "a3", "b1", "b2")
_SYSTEM = ("tau_max", "q1_box", "q2_box", "w_box", "v_box")


def _params(p: Optional[dict], name: str = "p") -> dict:
    """The arm's constants from ``p``: ``None`` (the shipped arm's), or a dict such as :func:`arm_parameters` returns
    (or a system's ``params``). Missing physical constants take their defaults and missing lumped ones follow from
    them; the values given must be finite numbers (the physical ones > 0) and the keys known, else a ``ValueError``
    naming ``name`` and the key (``TypeError`` for no dict)."""
    if p is None:
        return arm_parameters(**_DEFAULTS)
    if not isinstance(p, Mapping):
        raise TypeError(f"{name} must be a dict of the arm's constants (fl.arm.arm_parameters(...)) or None, got "
                        f"{type(p).__name__}")
    unknown = [k for k in p if k not in _PHYSICAL + _LUMPED + _SYSTEM]
    if unknown:
        raise ValueError(f"{name} holds unknown keys {brief(unknown)}: the arm's constants are "
                         f"{', '.join(_PHYSICAL + _LUMPED)} (make them with fl.arm.arm_parameters(...))")
    base = {k: check_number(p.get(k, _DEFAULTS[k]), f"{name}[{k!r}]",
                            "a link length (m), mass (kg) or gravity (m/s^2)", strict=True) for k in _PHYSICAL}
    out = arm_parameters(**base)
    for k in _LUMPED:
        if k in p:
            out[k] = check_number(p[k], f"{name}[{k!r}]", "a lumped constant of the dynamics", low=-np.inf)
    return out


def _point(x, name: str) -> Array:
    """A point of the workspace: two finite numbers ``(x, y)`` (m; a (2, 1) or (1, 2) array too), else
    ``ValueError`` naming ``name`` (a number is not broadcast to both coordinates)."""
    a = as_floats(x, name)
    if a.ndim == 2 and 1 in a.shape:
        a = a.reshape(-1)
    if a.shape != (2,):
        raise ValueError(f"{name} must be a point (x, y) of the workspace, shape (2,), got {brief(x)} of shape "
                         f"{a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf: {a.tolist()}")
    return a


def arm_mass_matrix(z: Array, p: Optional[dict] = None) -> Array:
    """``M(q)`` at states ``z = (q_1, q_1', q_2, q_2')`` of shape (N, 4) -> (N, 2, 2)."""
    return _mass_matrix(as_batch(z, 4, "z"), _params(p))


def _mass_matrix(Z: Array, p: dict) -> Array:
    """:func:`arm_mass_matrix` without its checks (the callers here pass a checked batch and constants)."""
    c2 = np.cos(Z[:, 2])
    M = np.empty((len(Z), 2, 2))
    M[:, 0, 0] = p["a1"] + 2 * p["a2"] * c2
    M[:, 0, 1] = M[:, 1, 0] = p["a3"] + p["a2"] * c2
    M[:, 1, 1] = p["a3"]
    return M


def arm_bias(z: Array, p: Optional[dict] = None) -> Array:
    """``h(q, q') = C(q, q') q' + g(q)`` at states ``z`` of shape (N, 4) -> (N, 2)."""
    return _bias(as_batch(z, 4, "z"), _params(p))


def _bias(Z: Array, p: dict) -> Array:
    """:func:`arm_bias` without its checks (the callers here pass a checked batch and constants)."""
    q1, w1, q2, w2 = Z.T
    s2, s12 = np.sin(q2), np.sin(q1 + q2)
    return np.column_stack([-p["a2"] * s2 * (2 * w1 * w2 + w2**2) + p["b1"] * np.sin(q1) + p["b2"] * s12,
                            p["a2"] * s2 * w1**2 + p["b2"] * s12])


def arm_joint_positions(q: Array, p: Optional[dict] = None) -> tuple[Array, Array]:
    """Elbow and hand positions (m) for joint angles ``q`` of shape (N, 2): two (N, 2) arrays.

    Angles from the downward vertical: the elbow is at ``l_1 (sin q_1, -cos q_1)``.
    """
    p = _params(p)
    Q = as_batch(q, 2, "q")
    elbow = p["l1"] * np.column_stack([np.sin(Q[:, 0]), -np.cos(Q[:, 0])])
    s = Q[:, 0] + Q[:, 1]
    return elbow, elbow + p["l2"] * np.column_stack([np.sin(s), -np.cos(s)])


def two_link_arm(tau_max=(8.0, 2.0), q1_box: float = 1.5, q2_box: float = 2.0, w_box: float = 2.0,
                 v_box: float = 10.0, l1: float = 0.5, l2: float = 0.5, m1: float = 1.0, m2: float = 1.0,
                 g: float = 9.81) -> FLSystem:
    """The two-link planar arm in a vertical plane with torque limits ``|tau_i| <= tau_max,i``.

    Computed torque: ``u = Phi(z, v) = M(q) v + C(q, q') q' + g(q)`` makes
    ``q'' = v`` (eq. coor_Phi with the Brunovsky pair ``fl.brunovsky((2, 2))``),
    ``z = (q_1, q_1', q_2, q_2')``; see :func:`arm_parameters` for ``M``, ``C``, ``g``.
    The input bound of eq. (constraintU) is ``|tau_i| <= tau_max,i``. With the
    defaults gravity alone asks up to about 9.8 N m of the shoulder (bound 8 N m)
    and 2.5 N m of the elbow (bound 2 N m): both strips ``|tau_i| <= tau_max,i``
    cut the ``v``-box at almost every state, so ``V(z)`` is a polygon with up
    to eight sides that turns and moves with ``z``; the bound is violated on about
    half of the ``(z, v)`` box.

    Parameters
    ----------
    tau_max
        Torque limits ``u_max`` (N m), shape (2,).
    q1_box, q2_box, w_box, v_box
        Half-widths of the domain box: ``|q_1| <= q1_box``, ``|q_2| <= q2_box`` (rad),
        ``|q_i'| <= w_box`` (rad/s), ``|v_i| <= v_box`` (rad/s^2).
    l1, l2, m1, m2, g
        Link lengths (m), masses (kg), gravity (m/s^2); uniform links.

    Returns
    -------
    FLSystem
        ``phi`` vectorized ((N, 4), (N, 2)) -> (N, 2), with ``phi_interval`` for
        :func:`flnotes.certify_error`; extra attributes ``mass_matrix(z)`` and
        ``bias(z)`` (``M`` and ``h = C q' + g``, so ``Phi = M v + h``).
    """
    p = arm_parameters(l1, l2, m1, m2, g)
    u_max = as_vector(tau_max, 2, "tau_max")
    q1_box, q2_box, w_box, v_box = (check_number(x, name, "a half-width of the domain box", strict=True) for name, x
                                    in dict(q1_box=q1_box, q2_box=q2_box, w_box=w_box, v_box=v_box).items())
    A, B = brunovsky((2, 2))
    a1, a2, a3, b1, b2 = (p[k] for k in ("a1", "a2", "a3", "b1", "b2"))

    def phi(z: Array, v: Array) -> Array:
        q1, w1, q2, w2 = z[:, 0:1], z[:, 1:2], z[:, 2:3], z[:, 3:4]
        v1, v2 = v[:, 0:1], v[:, 1:2]
        c2, s2, s12 = np.cos(q2), np.sin(q2), np.sin(q1 + q2)
        t1 = (a1 + 2 * a2 * c2) * v1 + (a3 + a2 * c2) * v2 - a2 * s2 * (2 * w1 * w2 + w2**2) \
            + b1 * np.sin(q1) + b2 * s12
        t2 = (a3 + a2 * c2) * v1 + a3 * v2 + a2 * s2 * w1**2 + b2 * s12
        return np.hstack([t1, t2])

    def phi_interval(z: iv.Interval, v: iv.Interval) -> iv.Interval:
        q1, w1, q2, w2 = z[:, 0:1], z[:, 1:2], z[:, 2:3], z[:, 3:4]
        v1, v2 = v[:, 0:1], v[:, 1:2]
        c2, s2, s12 = iv.cos(q2), iv.sin(q2), iv.sin(q1 + q2)
        t1 = (a1 + 2 * a2 * c2) * v1 + (a3 + a2 * c2) * v2 - a2 * s2 * (2.0 * w1 * w2 + iv.sqr(w2)) \
            + b1 * iv.sin(q1) + b2 * s12
        t2 = (a3 + a2 * c2) * v1 + a3 * v2 + a2 * s2 * iv.sqr(w1) + b2 * s12
        return iv.hstack([t1, t2])

    def f(x: Array, u: Array) -> Array:
        x = np.asarray(x, float)
        z = np.array([[x[0], x[2], x[1], x[3]]])
        qdd = np.linalg.solve(_mass_matrix(z, p)[0], np.asarray(u, float).reshape(2) - _bias(z, p)[0])
        return np.array([x[2], x[3], qdd[0], qdd[1]])

    def to_z(x: Array) -> Array:
        x = np.asarray(x, float)
        return np.array([x[0], x[2], x[1], x[3]])

    def to_x(z: Array) -> Array:
        z = np.asarray(z, float)
        return np.array([z[0], z[2], z[1], z[3]])

    zb = np.array([q1_box, w_box, q2_box, w_box])
    sysm = FLSystem(
        name="Arm", A=A, B=B, phi=phi,
        lo=np.r_[-zb, -v_box, -v_box], hi=np.r_[zb, v_box, v_box], u_max=u_max,
        f=f, to_z=to_z, to_x=to_x, phi_interval=phi_interval,
        state_names=("q1", "q1'", "q2", "q2'"), input_names=("v1 = q1''", "v2 = q2''"),
        params=dict(p, tau_max=u_max.tolist(), q1_box=q1_box, q2_box=q2_box, w_box=w_box, v_box=v_box),
    )
    sysm.mass_matrix = lambda z: _mass_matrix(as_batch(z, 4, "z"), p)  # type: ignore[attr-defined]
    sysm.bias = lambda z: _bias(as_batch(z, 4, "z"), p)  # type: ignore[attr-defined]
    return sysm


# ---------------------------------------------------------------------------
# The shipped network
# ---------------------------------------------------------------------------
#: How the shipped network of :func:`two_link_arm` (defaults) was trained (arguments of :func:`flnotes.fit_relu`).
ARM_SETTINGS = dict(widths=(32, 32), n_per_axis=8, seed=0, max_iter=3000, max_train=60_000)
#: How its error bound was certified (arguments of :func:`flnotes.certify_error`).
ARM_EPS_SETTINGS = dict(rtol=0.05, n_samples=10_000, seed=0)


def make_arm_reference(folder=None, workers: Optional[int] = None, client=None, progress: bool = False):
    """Train the arm's network with :data:`ARM_SETTINGS`, certify ``eps`` per output and write the reference.

    Minutes of CPU: only to change the shipped network on purpose. Returns the
    path of the JSON file written (see :func:`flnotes.reference.save_reference`).
    ``workers``, ``client``: where the certification's boxes are evaluated (:func:`flnotes.certify_error`;
    the bracket is the same on any of them); the training runs here.
    """
    from .error import certify_error
    from .network import fit_relu
    from .reference import save_reference

    sysm = two_link_arm()
    net, report = fit_relu(sysm.phi_stacked, sysm.lo, sysm.hi, **ARM_SETTINGS)
    bracket = certify_error(sysm, net, **ARM_EPS_SETTINGS, workers=workers, client=client, progress=progress)
    return save_reference(ARM_REFERENCE, net, report, dict(ARM_SETTINGS, system="Arm"), bracket=bracket,
                          eps_settings=ARM_EPS_SETTINGS, folder=folder)


def arm_net():
    """The shipped network ``Phi_NN`` of :func:`two_link_arm` and its certified error bound.

    The same weights on every machine (:mod:`flnotes.reference`, name
    :data:`ARM_REFERENCE`), trained with :data:`ARM_SETTINGS` on the default
    box, with ``eps`` of eq. (approx_err) certified per output by
    :func:`flnotes.certify_error` (:data:`ARM_EPS_SETTINGS`).

    Returns
    -------
    net, eps, ref
        The network, ``eps`` (the bracket's upper ends, shape (2,)) and the
        :class:`flnotes.reference.Reference` (training report, bracket, settings).
    """
    from .reference import load_reference

    ref = load_reference(ARM_REFERENCE)
    if ref.bracket is None:
        raise ValueError(f"the shipped reference {ARM_REFERENCE!r} has no certified bracket; rewrite it "
                         f"with flnotes.arm.make_arm_reference()")
    return ref.net, np.asarray(ref.bracket["upper"], float), ref


# ---------------------------------------------------------------------------
# An obstacle in the workspace, as a barrier on the joint state
# ---------------------------------------------------------------------------
def arm_link_points(q: Array, fractions: Sequence[float], p: Optional[dict] = None) -> Array:
    """Points of the second link at the given fractions of its length (0 = elbow, 1 = hand): (N, k, 2).

    ``r_s(q) = l_1 (sin q_1, -cos q_1) + s l_2 (sin(q_1 + q_2), -cos(q_1 + q_2))``. ``p``: the arm's constants
    (:func:`arm_parameters`), default the shipped arm's.
    """
    p = _params(p)
    Q = as_batch(q, 2, "q")
    s = as_floats(fractions, "fractions").reshape(-1)
    if not np.all((s >= 0) & (s <= 1)):  # NaN too
        raise ValueError(f"fractions must lie in [0, 1] (0 = elbow, 1 = hand), got {s.tolist()}")
    elbow = p["l1"] * np.column_stack([np.sin(Q[:, 0]), -np.cos(Q[:, 0])])
    q12 = Q[:, 0] + Q[:, 1]
    d2 = p["l2"] * np.column_stack([np.sin(q12), -np.cos(q12)])
    return elbow[:, None, :] + s[None, :, None] * d2[:, None, :]


def links_distance(q: Array, center: Array, p: Optional[dict] = None) -> Array:
    """Distance from ``center`` (2,) to the arm (both links as segments) at joint angles ``q`` (N, 2): (N,)."""
    p = _params(p)
    Q = as_batch(q, 2, "q")
    c = _point(center, "center")
    elbow, hand = arm_joint_positions(Q, p)
    out = np.full(len(Q), np.inf)
    for a, b in ((np.zeros_like(elbow), elbow), (elbow, hand)):
        e = b - a
        t = np.clip(np.einsum("ij,ij->i", c - a, e) / np.einsum("ij,ij->i", e, e), 0.0, 1.0)
        out = np.minimum(out, np.linalg.norm(a + t[:, None] * e - c, axis=1))
    return out


class ArmPointCBF(Certificate):
    """A disc obstacle in the workspace kept away from one point of the second link: a CBF on ``z``.

    The point ``p_eta(q)`` of the second link at fraction ``eta`` of its length
    (:func:`arm_link_points`) must stay outside the disc of centre ``c_o`` and
    radius ``R``: ``h(q) = ||p_eta(q) - c_o||^2 - R^2 >= 0``. ``h`` depends on the
    angles only, so on the chains ``z = (q_1, q_1', q_2, q_2')`` it has relative
    degree two (``grad h^T B = 0``) and, like :class:`flnotes.ExponentialCBF`
    for an affine ``h``, the controller is given

        H_2(z) = dh/dt + k_1 h = 2 (p_eta - c_o)^T D_eta(q) q' + k_1 h(q),

    with ``D_eta = dp_eta/dq``. Its gradient in ``z``: ``dH_2/dq' = 2 D_eta^T (p_eta - c_o)``
    (so ``grad H_2^T B v = 2 (p_eta - c_o)^T D_eta v``, zero only where the point
    cannot move away from ``c_o``), and
    ``dH_2/dq_i = 2 (D_eta e_i)^T D_eta q' + 2 (p_eta - c_o)^T (dD_eta/dq_i) q' + 2 k_1 (p_eta - c_o)^T D_eta e_i``.
    If the condition (CLF_CBF_d) keeps ``H_2 >= 0`` along the closed loop and
    ``h(z(0)) >= 0``, then ``dh/dt >= -k_1 h`` and ``h`` stays nonnegative.

    Parameters
    ----------
    center
        Centre ``c_o`` of the disc (m), shape (2,).
    radius
        Its radius ``R`` (m), > 0.
    fraction
        ``eta`` in [0, 1]: 0 the elbow, 1 the hand.
    k1
        Gain > 0 of the inner condition ``dh/dt >= -k_1 h``.
    params
        The arm's constants (:func:`arm_parameters`); default the shipped arm's.
    """

    name = "H2"

    def __init__(self, center: Array, radius: float, fraction: float = 1.0, k1: float = 2.0,
                 params: Optional[dict] = None):
        self.c = _point(center, "center")
        radius = check_number(radius, "radius", "of the obstacle (m)", strict=True)
        fraction = check_number(fraction, "fraction", "the point on the forearm: 0 = elbow, 1 = hand")
        if fraction > 1.0:
            raise ValueError(f"fraction must lie in [0, 1] (0 = elbow, 1 = hand), got {fraction!r}")
        k1 = check_number(k1, "k1", "a positive gain", strict=True)
        self.R, self.s, self.k1 = radius, fraction, k1
        self.p = _params(params, "params")

    def _geometry(self, Z: Array):
        q1, w1, q2, w2 = Z.T
        l1, sl2 = self.p["l1"], self.s * self.p["l2"]
        q12 = q1 + q2
        u1, u12 = np.column_stack([np.cos(q1), np.sin(q1)]), np.column_stack([np.cos(q12), np.sin(q12)])
        n1, n12 = np.column_stack([-np.sin(q1), np.cos(q1)]), np.column_stack([-np.sin(q12), np.cos(q12)])
        e = l1 * np.column_stack([np.sin(q1), -np.cos(q1)]) + sl2 * np.column_stack([np.sin(q12), -np.cos(q12)]) \
            - self.c
        J1, J2 = l1 * u1 + sl2 * u12, sl2 * u12                    # columns of J_s = dr_s/dq
        rdot = J1 * w1[:, None] + J2 * w2[:, None]                  # J_s q'
        dJ1 = l1 * n1 * w1[:, None] + sl2 * n12 * (w1 + w2)[:, None]   # (dJ_s/dq_1) q'
        dJ2 = sl2 * n12 * (w1 + w2)[:, None]                        # (dJ_s/dq_2) q'
        return e, J1, J2, rdot, dJ1, dJ2

    def value(self, Z: Array) -> Array:
        """``H_2(z)`` on a batch (N, 4) -> (N,)."""
        Z = as_batch(Z, 4, "z")
        e, _, _, rdot, _, _ = self._geometry(Z)
        return 2 * np.einsum("ij,ij->i", e, rdot) + self.k1 * (np.einsum("ij,ij->i", e, e) - self.R**2)

    def h(self, Z: Array) -> Array:
        """The barrier ``h(q) = ||r_s(q) - c||^2 - R^2`` on a batch (N, 4) -> (N,)."""
        e = self._geometry(as_batch(Z, 4, "z"))[0]
        return np.einsum("ij,ij->i", e, e) - self.R**2

    def grad(self, z: Array) -> Array:
        """``grad H_2(z)`` in the order of ``z = (q_1, q_1', q_2, q_2')``, shape (4,)."""
        z = as_state(z, 4, "z")
        q1, w1, q2, w2 = (float(x) for x in z)
        l1, sl2, k1 = self.p["l1"], self.s * self.p["l2"], self.k1
        c1, s1, c12, s12 = math.cos(q1), math.sin(q1), math.cos(q1 + q2), math.sin(q1 + q2)
        e = np.array([l1 * s1 + sl2 * s12 - self.c[0], -l1 * c1 - sl2 * c12 - self.c[1]])
        J2 = np.array([sl2 * c12, sl2 * s12])                     # columns of J_s = dr_s/dq
        J1 = np.array([l1 * c1, l1 * s1]) + J2
        rdot = J1 * w1 + J2 * w2                                   # J_s q'
        dJ2 = np.array([-sl2 * s12, sl2 * c12]) * (w1 + w2)        # (dJ_s/dq_2) q'
        dJ1 = np.array([-l1 * s1, l1 * c1]) * w1 + dJ2             # (dJ_s/dq_1) q'
        g_q1 = 2 * J1 @ rdot + 2 * e @ dJ1 + 2 * k1 * e @ J1
        g_q2 = 2 * J2 @ rdot + 2 * e @ dJ2 + 2 * k1 * e @ J2
        return np.array([g_q1, 2 * e @ J1, g_q2, 2 * e @ J2])

    def __repr__(self) -> str:
        return f"ArmPointCBF(center={self.c.tolist()}, radius={self.R}, fraction={self.s}, k1={self.k1})"


def arm_obstacle_cbfs(center: Array, radius: float, n_points: int = 5, k1: float = 2.0,
                      params: Optional[dict] = None) -> list:
    """Barriers keeping the whole second link out of a disc obstacle of radius ``r_o``: one :class:`ArmPointCBF` each.

    ``n_points`` points at equal spacing ``d = l_2 / (n_points - 1)`` along
    the second link (elbow to hand) are kept out of the inflated disc of radius
    ``bar r_o = sqrt(r_o^2 + (d / 2)^2)``. Then the segment between two neighbouring
    points stays out of the disc of radius ``r_o``: the point of a chord of length
    ``d`` nearest the centre is within ``d / 2`` of one end along the
    chord, so its distance is at least ``sqrt(bar r_o^2 - (d/2)^2) = r_o``. (The first
    link must not reach the disc: ``||c_o|| > l_1 + r_o``; checked.)

    ``center`` must be a point (x, y) of the workspace, shape (2,), ``radius`` a finite number > 0 and ``n_points``
    an integer >= 2 (any real type: ``5``, ``5.0``); anything else is a ``ValueError`` naming the argument.

    Returns
    -------
    list of ArmPointCBF
        Pass it as ``H`` to :class:`flnotes.ClfCbfController` (one condition (CLF_CBF_d) each).
    """
    p = _params(params, "params")
    c = _point(center, "center")
    radius = check_number(radius, "radius", "of the obstacle (m), a single number", strict=True)
    n_points = check_count(n_points, "n_points", 2, "points on the second link: elbow and hand at least")
    if np.linalg.norm(c) <= p["l1"] + radius:
        raise ValueError(f"the first link reaches the disc (||center|| = {np.linalg.norm(c):.3g} <= l1 + radius = "
                         f"{p['l1'] + radius:.3g}): these barriers guard the second link only; move the obstacle")
    delta = p["l2"] / (n_points - 1)
    R = float(np.hypot(radius, delta / 2))
    return [ArmPointCBF(c, R, s, k1, p) for s in np.linspace(0.0, 1.0, n_points)]
