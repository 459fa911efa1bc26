"""Sound interval arithmetic with outward rounding, vectorized over many boxes.

Certifying the error bound ``eps`` of eq. (approx_err) needs guaranteed
enclosures: for a box ``B`` of inputs, an interval that surely contains
``Phi(B)``, ``Phi_NN(B)`` and their gradients. This module provides them.

An :class:`Interval` holds two arrays ``lo <= hi`` of any shape (typically
(T, k) for T boxes at once) and, optionally, an enclosure of its gradient with
respect to ``n`` input variables (arrays ``dlo <= dhi`` of shape
``lo.shape + (n,)``; forward-mode automatic differentiation). Writing ``Phi``
once with these operations gives both its natural interval extension and, when
the inputs carry gradients (:meth:`Interval.variables`), an enclosure of
``grad Phi`` over the box, which the mean-value form :func:`mean_value_bound`
turns into a tight enclosure on small boxes.

Rounding
--------
Every result is widened outward so that floating-point rounding can never make
an enclosure too narrow:

* ``+ - * /`` and ``sqrt`` are correctly rounded in IEEE 754 double precision,
  so moving each result outward by one unit in the last place is enough
  (:func:`down`, :func:`up` move it by a few);
* ``exp``, ``log``, ``tanh``, ``arcsin``, ``arctan``, ``sin``, ``cos``,
  ``tan`` and integer powers come from the C math library / numpy's SIMD
  kernels, which are accurate to a few ulp but not correctly rounded; their
  results are widened by :data:`LIBM_ULPS` ulp (relative) plus
  :data:`TINY` (absolute); ``sin``, ``cos``, ``tan`` also by an absolute
  ``LIBM_ULPS * 2^-53`` (near their zeros). This is the assumption on the
  library: its error is below ``LIBM_ULPS`` ulp. It is not proven: 16 is a
  chosen safety factor, several times the errors of a few ulp that glibc
  documents for these functions (its table of known maximum errors) and that
  numpy's accuracy tests allow for its SIMD kernels;
* the extrema of ``sin`` and ``cos`` inside an interval (``+-1`` at
  ``pi/2 + k pi`` and ``k pi``) are detected with a small slack, so an
  interval ending just short of one still gets ``+-1``: wider, never unsound;
* matrix products (:func:`affine`) use the midpoint-radius form with the
  classical a-priori bound ``|fl(x.y) - x.y| <= gamma_n |x|.|y|``,
  ``gamma_n = n u / (1 - n u)``, ``u = 2^-53``, valid for any summation order
  (Higham, *Accuracy and Stability of Numerical Algorithms*, Sec. 3.1).

Nonsmooth functions (``abs``, ReLU) get Clarke generalized gradients
(``d|x| in [-1, 1]`` when ``0`` is in the interval); Lebourg's mean-value
theorem then keeps the mean-value form valid for Lipschitz functions.
"""
from __future__ import annotations

from typing import Optional, Sequence, Union

import numpy as np

Array = np.ndarray
Number = Union[float, int, Array]

#: Relative widening, in units of 2^-52, applied to the results of library functions (exp, log, sin, ...): a chosen
#: safety factor, several times the few ulp that glibc and numpy document for them (not a proven bound).
LIBM_ULPS = 16
#: Absolute widening added to every library-function result (covers underflow).
TINY = 1e-300
_U = 2.0**-53
_EPS = 2.0**-52
_INF = np.inf


class NotCertifiable(ValueError):
    """Raised when an interval operation leaves its domain (division by an interval
    containing 0, ``sqrt``, ``log`` or ``arcsin`` outside their domain, ``tan``
    across a pole, NaN)."""


# ---------------------------------------------------------------------- rounding
_STEP = 2.0**-50
_NORMAL = 2.0**-1022


def down(x: Array) -> Array:
    """A float below ``x`` by at least one ulp: a lower bound after one correctly rounded operation.

    If ``x = fl(y)`` is the correctly rounded result of one operation, the
    exact ``y >= x - ulp(x)/2``. With ``d = |x| 2^-50 + 2^-1022`` we have
    ``d >= 4 ulp(x)`` (also for subnormal ``x``), and the rounded difference
    ``fl(x - d) <= x - d + ulp(x - d)/2 <= x - 4 ulp(x) + ulp(x) < y``.
    Three array operations: much cheaper than :func:`numpy.nextafter`, at
    the price of a few ulp of extra width.
    """
    return x - (np.abs(x) * _STEP + _NORMAL)


def up(x: Array) -> Array:
    """A float above ``x`` by at least one ulp: an upper bound after one correctly rounded operation.

    See :func:`down` for the argument (``fl(x + d) >= x + 3 ulp(x) > y``).
    """
    return x + (np.abs(x) * _STEP + _NORMAL)


def _lib_down(x: Array) -> Array:
    return x - (np.abs(x) * (LIBM_ULPS * _EPS) + TINY)


def _lib_up(x: Array) -> Array:
    return x + (np.abs(x) * (LIBM_ULPS * _EPS) + TINY)


def gamma(n: int) -> float:
    """``gamma_n = n u / (1 - n u)``: relative error bound of an ``n``-term dot product."""
    return n * _U / (1.0 - n * _U)


def _mul_lo_hi(alo: Array, ahi: Array, blo: Array, bhi: Array) -> tuple[Array, Array]:
    """Outward-rounded ``[alo, ahi] * [blo, bhi]`` (broadcasting)."""
    p1, p2, p3, p4 = alo * blo, alo * bhi, ahi * blo, ahi * bhi
    lo = np.minimum(np.minimum(p1, p2), np.minimum(p3, p4))
    hi = np.maximum(np.maximum(p1, p2), np.maximum(p3, p4))
    # 0 * inf never occurs: finite inputs are checked where intervals are made
    return down(lo), up(hi)


def _add_lo_hi(alo, ahi, blo, bhi):
    return down(alo + blo), up(ahi + bhi)


# ---------------------------------------------------------------------- the class
class Interval:
    """Element-wise closed intervals ``[lo, hi]`` with an optional gradient enclosure.

    Parameters
    ----------
    lo, hi
        Arrays of the same shape with ``lo <= hi``.
    dlo, dhi
        Optional enclosure of the gradient with respect to ``n`` variables,
        arrays of shape ``lo.shape + (n,)``; ``None`` when not tracked.

    Notes
    -----
    Supports ``+ - * /`` (with numbers, arrays and other intervals), unary
    ``-``, integer powers ``x**k`` (:func:`power`), indexing and slicing like
    the arrays, and the functions of this module (:func:`exp`, :func:`log`,
    :func:`sqrt`, :func:`sin`, :func:`cos`, :func:`tan`, :func:`arctan`,
    :func:`tanh`, :func:`arcsin`, :func:`abs`, :func:`sqr`, :func:`hstack`).
    Leaving a function's domain (``1 / x`` or ``x ** -k`` with 0 inside,
    ``sqrt`` or ``log`` below 0, ``tan`` across a pole) raises
    :class:`NotCertifiable` with a message saying which. A plain float
    in an expression is an exact constant (the double it is stored as).
    """

    __slots__ = ("lo", "hi", "dlo", "dhi")
    __array_ufunc__ = None  # ndarray <op> Interval defers to Interval's reflected operator

    def __init__(self, lo: Number, hi: Optional[Number] = None, dlo: Optional[Array] = None,
                 dhi: Optional[Array] = None, check: bool = True):
        lo = np.asarray(lo, float)
        hi = lo if hi is None else np.asarray(hi, float)
        lo, hi = np.broadcast_arrays(lo, hi)
        if check:
            if np.isnan(lo).any() or np.isnan(hi).any():
                raise NotCertifiable("interval bound is NaN: the function left its domain on some box")
            if np.any(lo > hi):
                i = tuple(int(j) for j in np.argwhere(lo > hi)[0])
                at = str(list(i)) if i else ""
                raise ValueError(f"Interval: lo{at} = {lo[i]} > hi{at} = {hi[i]}; every lower bound must "
                                 f"be <= its upper bound")
        self.lo, self.hi = lo, hi
        if (dlo is None) != (dhi is None):
            raise ValueError("Interval: give both dlo and dhi or neither")
        self.dlo, self.dhi = dlo, dhi

    # ------------------------------------------------------------ constructors
    @classmethod
    def variables(cls, lo: Array, hi: Array) -> "Interval":
        """Independent variables over boxes: ``lo``, ``hi`` of shape (T, n), gradient = identity.

        Evaluating a function written with this module on the result gives the
        value enclosure and the gradient enclosure over each of the T boxes.
        """
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        if lo.ndim != 2 or lo.shape != hi.shape:
            raise ValueError(f"lo and hi must both have shape (T, n), got {lo.shape} and {hi.shape}")
        n = lo.shape[1]
        eye = np.broadcast_to(np.eye(n), lo.shape + (n,))
        return cls(lo, hi, eye, eye)

    @classmethod
    def point(cls, x: Array) -> "Interval":
        """Degenerate intervals ``[x, x]`` (no gradient)."""
        return cls(x, x)

    # ------------------------------------------------------------ properties
    @property
    def shape(self) -> tuple[int, ...]:
        return self.lo.shape

    @property
    def has_grad(self) -> bool:
        return self.dlo is not None

    @property
    def mid(self) -> Array:
        return 0.5 * (self.lo + self.hi)

    @property
    def width(self) -> Array:
        """Upper bound of ``hi - lo``."""
        return up(self.hi - self.lo)

    def mag(self) -> Array:
        """``max |x|`` over the interval."""
        return np.maximum(np.abs(self.lo), np.abs(self.hi))

    def contains(self, x: Array) -> Array:
        """Element-wise ``lo <= x <= hi``."""
        return (self.lo <= x) & (x <= self.hi)

    def __len__(self) -> int:
        return len(self.lo)

    def __repr__(self) -> str:
        g = f", grad over {self.dlo.shape[-1]} variables" if self.has_grad else ""
        if self.lo.size <= 6:
            return f"Interval(lo={self.lo}, hi={self.hi}{g})"
        return f"Interval(shape={self.shape}{g})"

    def __getitem__(self, key) -> "Interval":
        if self.has_grad:
            k = key if isinstance(key, tuple) else (key,)
            if any(x is Ellipsis for x in k):
                raise IndexError("Interval indexing with ... is not supported when gradients are tracked")
            return Interval(self.lo[key], self.hi[key], self.dlo[key], self.dhi[key], check=False)
        return Interval(self.lo[key], self.hi[key], check=False)

    # ------------------------------------------------------------ helpers
    @staticmethod
    def _lift(x) -> "Interval":
        if isinstance(x, Interval):
            return x
        a = np.asarray(x, float)
        if not np.all(np.isfinite(a)):
            raise NotCertifiable("a constant in the interval expression is NaN or inf")
        return Interval(a, a, check=False)

    def _grad_shape(self, other: "Interval") -> Optional[tuple]:
        g = [t for t in (self, other) if t.has_grad]
        if not g:
            return None
        return np.broadcast_shapes(*[t.lo.shape for t in (self, other)]) + (g[0].dlo.shape[-1],)

    # ------------------------------------------------------------ arithmetic
    def __neg__(self) -> "Interval":
        if self.has_grad:
            return Interval(-self.hi, -self.lo, -self.dhi, -self.dlo, check=False)
        return Interval(-self.hi, -self.lo, check=False)

    def __pos__(self) -> "Interval":
        return self

    def __add__(self, other) -> "Interval":
        o = self._lift(other)
        lo, hi = _add_lo_hi(self.lo, self.hi, o.lo, o.hi)
        gs = self._grad_shape(o)
        if gs is None:
            return Interval(lo, hi, check=False)
        if self.has_grad and o.has_grad:
            dlo, dhi = _add_lo_hi(self.dlo, self.dhi, o.dlo, o.dhi)
        else:
            g = self if self.has_grad else o
            dlo, dhi = np.broadcast_to(g.dlo, gs), np.broadcast_to(g.dhi, gs)
        return Interval(lo, hi, dlo, dhi, check=False)

    __radd__ = __add__

    def __sub__(self, other) -> "Interval":
        return self + (-self._lift(other))

    def __rsub__(self, other) -> "Interval":
        return self._lift(other) + (-self)

    def __mul__(self, other) -> "Interval":
        o = self._lift(other)
        lo, hi = _mul_lo_hi(self.lo, self.hi, o.lo, o.hi)
        gs = self._grad_shape(o)
        if gs is None:
            return Interval(lo, hi, check=False)
        # product rule: d(ab) = a db + b da, with interval factors
        parts = []
        if o.has_grad:
            parts.append(_mul_lo_hi(self.lo[..., None], self.hi[..., None], o.dlo, o.dhi))
        if self.has_grad:
            parts.append(_mul_lo_hi(o.lo[..., None], o.hi[..., None], self.dlo, self.dhi))
        dlo, dhi = parts[0]
        if len(parts) == 2:
            dlo, dhi = _add_lo_hi(dlo, dhi, *parts[1])
        return Interval(lo, hi, np.broadcast_to(dlo, gs), np.broadcast_to(dhi, gs), check=False)

    __rmul__ = __mul__

    def reciprocal(self) -> "Interval":
        """``1 / x``; raises :class:`NotCertifiable` if an interval contains 0."""
        if np.any((self.lo <= 0) & (self.hi >= 0)):
            raise NotCertifiable("division by an interval that contains 0: the function is singular on some box")
        lo, hi = down(1.0 / self.hi), up(1.0 / self.lo)
        if not self.has_grad:
            return Interval(lo, hi, check=False)
        # d(1/x) = -dx / x^2, with 1/x^2 in [lo^2, hi^2] of the reciprocal (ordered by magnitude)
        s_lo, s_hi = _sqr_lo_hi(lo, hi)
        dlo, dhi = _mul_lo_hi(-s_hi[..., None], -s_lo[..., None], self.dlo, self.dhi)
        return Interval(lo, hi, dlo, dhi, check=False)

    def __truediv__(self, other) -> "Interval":
        return self * self._lift(other).reciprocal()

    def __rtruediv__(self, other) -> "Interval":
        return self._lift(other) * self.reciprocal()

    def __pow__(self, k: int) -> "Interval":
        """``x ** k`` for an integer ``k`` (see :func:`power`)."""
        return power(self, k)

    def __abs__(self) -> "Interval":
        return abs_(self)

    # comparisons are ambiguous for intervals: refuse them with a clear message
    def __bool__(self):
        raise TypeError("an Interval has no truth value; compare its .lo / .hi explicitly")


# ---------------------------------------------------------------------- elementary functions
def _sqr_lo_hi(lo: Array, hi: Array) -> tuple[Array, Array]:
    a, b = lo * lo, hi * hi
    mx = up(np.maximum(a, b))
    mn = np.where((lo <= 0) & (hi >= 0), 0.0, down(np.minimum(a, b)))
    return mn, mx


def _chain(x: Interval, lo: Array, hi: Array, dflo: Array, dfhi: Array) -> Interval:
    """Result ``f(x)`` with value ``[lo, hi]`` and derivative enclosure ``f'(x) in [dflo, dfhi]``."""
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    dlo, dhi = _mul_lo_hi(dflo[..., None], dfhi[..., None], x.dlo, x.dhi)
    return Interval(lo, hi, dlo, dhi, check=False)


def sqr(x: Interval) -> Interval:
    """``x**2`` without the dependency problem (the result is >= 0)."""
    x = Interval._lift(x)
    lo, hi = _sqr_lo_hi(x.lo, x.hi)
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    return _chain(x, lo, hi, down(2.0 * x.lo), up(2.0 * x.hi))


def exp(x: Interval) -> Interval:
    """``e^x`` (monotone increasing)."""
    x = Interval._lift(x)
    lo = np.maximum(_lib_down(np.exp(x.lo)), 0.0)
    hi = _lib_up(np.exp(x.hi))
    if not np.all(np.isfinite(hi)):
        raise NotCertifiable("exp overflowed on some box")
    return _chain(x, lo, hi, lo, hi)


def tanh(x: Interval) -> Interval:
    """``tanh x`` (monotone increasing, values in [-1, 1]); ``tanh' = 1 - tanh^2``."""
    x = Interval._lift(x)
    lo = np.maximum(_lib_down(np.tanh(x.lo)), -1.0)
    hi = np.minimum(_lib_up(np.tanh(x.hi)), 1.0)
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    s_lo, s_hi = _sqr_lo_hi(lo, hi)
    return _chain(x, lo, hi, np.maximum(down(1.0 - s_hi), 0.0), np.minimum(up(1.0 - s_lo), 1.0))


def sqrt(x: Interval) -> Interval:
    """``sqrt x`` (monotone); the derivative ``1 / (2 sqrt x)`` needs ``x > 0`` when gradients are tracked."""
    x = Interval._lift(x)
    if np.any(x.lo < 0):
        raise NotCertifiable("sqrt of an interval reaching below 0: the function is undefined on some box")
    lo, hi = down(np.sqrt(x.lo)), up(np.sqrt(x.hi))
    lo = np.maximum(lo, 0.0)
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    if np.any(lo <= 0):
        raise NotCertifiable("sqrt is not differentiable at 0: keep its argument > 0 on the domain")
    return _chain(x, lo, hi, down(0.5 / hi), up(0.5 / lo))


def arcsin(x: Interval) -> Interval:
    """``arcsin x`` (monotone on [-1, 1]); derivative ``1 / sqrt(1 - x^2)`` needs ``|x| < 1``."""
    x = Interval._lift(x)
    if np.any(x.lo < -1) or np.any(x.hi > 1):
        raise NotCertifiable("arcsin of an interval leaving [-1, 1]: the function is undefined on some box")
    lo = np.maximum(_lib_down(np.arcsin(x.lo)), -np.pi / 2 - 1e-15)
    hi = np.minimum(_lib_up(np.arcsin(x.hi)), np.pi / 2 + 1e-15)
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    s = 1.0 - sqr(Interval(x.lo, x.hi, check=False))
    if np.any(s.lo <= 0):
        raise NotCertifiable("arcsin is not differentiable at +-1: keep its argument inside (-1, 1)")
    r = sqrt(s).reciprocal()
    return _chain(x, lo, hi, r.lo, r.hi)


def _lib_abs_down(x: Array) -> Array:
    """Lower bound for a periodic library function's result: relative and absolute widening."""
    return _lib_down(x) - _TRIG_ABS


def _lib_abs_up(x: Array) -> Array:
    return _lib_up(x) + _TRIG_ABS


#: Absolute widening of sin, cos, tan results (LIBM_ULPS units of 2^-53): covers the library's argument
#: reduction near a zero of the function, where a relative bound alone would be too strict an assumption.
_TRIG_ABS = LIBM_ULPS * _U
_TWO_PI = 2.0 * np.pi


def _hits(lo: Array, hi: Array, a: float, period: float = _TWO_PI) -> Array:
    """Does ``[lo, hi]`` (possibly) contain a point ``a + k period``, ``k`` integer?

    Computed with a small slack, so a point just outside counts as inside: that
    only widens an enclosure, never makes it too narrow.
    """
    mag = np.maximum(np.abs(lo), np.abs(hi))
    slack = 1e-9 * (1.0 + mag / period)
    return np.floor((hi - a) / period + slack) >= np.ceil((lo - a) / period - slack)


def _sin_cos(x: Interval, phase: float) -> tuple[Array, Array]:
    """Value bounds of ``cos(x - phase)`` written as sin (phase = pi/2) or cos (phase = 0), with extrema inside."""
    f = np.cos if phase == 0.0 else np.sin
    a, b = f(x.lo), f(x.hi)
    lo = _lib_abs_down(np.minimum(a, b))
    hi = _lib_abs_up(np.maximum(a, b))
    hi = np.where(_hits(x.lo, x.hi, phase), 1.0, hi)                # a maximum inside the interval
    lo = np.where(_hits(x.lo, x.hi, phase + np.pi), -1.0, lo)       # a minimum inside
    return np.clip(lo, -1.0, 1.0), np.clip(hi, -1.0, 1.0)


def _check_finite(x: Interval, name: str) -> None:
    if not (np.all(np.isfinite(x.lo)) and np.all(np.isfinite(x.hi))):
        raise NotCertifiable(f"{name} of an unbounded interval: the argument is infinite on some box")


def sin(x: Interval) -> Interval:
    """``sin x``: the end values, and ``+-1`` wherever a maximum ``pi/2 + 2k pi`` or minimum lies inside.

    The derivative enclosure is :func:`cos` of the same interval.
    """
    x = Interval._lift(x)
    _check_finite(x, "sin")
    lo, hi = _sin_cos(x, np.pi / 2)
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    dlo, dhi = _sin_cos(x, 0.0)
    return _chain(x, lo, hi, dlo, dhi)


def cos(x: Interval) -> Interval:
    """``cos x``: the end values, and ``+-1`` wherever a maximum ``2k pi`` or minimum ``pi + 2k pi`` lies inside.

    The derivative enclosure is ``-sin`` of the same interval.
    """
    x = Interval._lift(x)
    _check_finite(x, "cos")
    lo, hi = _sin_cos(x, 0.0)
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    slo, shi = _sin_cos(x, np.pi / 2)
    return _chain(x, lo, hi, -shi, -slo)


def tan(x: Interval) -> Interval:
    """``tan x`` (increasing between its poles ``pi/2 + k pi``); derivative ``1 + tan^2 x``.

    Raises :class:`NotCertifiable` if an interval contains (or touches) a pole.
    """
    x = Interval._lift(x)
    _check_finite(x, "tan")
    if np.any(_hits(x.lo, x.hi, np.pi / 2, np.pi)):
        raise NotCertifiable("tan of an interval containing a pole (pi/2 + k pi): tan is unbounded on some box; "
                             "keep its argument inside (-pi/2, pi/2) (mod pi) on the whole domain")
    lo, hi = _lib_abs_down(np.tan(x.lo)), _lib_abs_up(np.tan(x.hi))
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    s_lo, s_hi = _sqr_lo_hi(lo, hi)
    return _chain(x, lo, hi, down(1.0 + s_lo), up(1.0 + s_hi))


def arctan(x: Interval) -> Interval:
    """``arctan x`` (increasing, values in (-pi/2, pi/2)); derivative ``1 / (1 + x^2)``."""
    x = Interval._lift(x)
    lo = np.maximum(_lib_down(np.arctan(x.lo)), -np.pi / 2 - 1e-15)
    hi = np.minimum(_lib_up(np.arctan(x.hi)), np.pi / 2 + 1e-15)
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    s_lo, s_hi = _sqr_lo_hi(x.lo, x.hi)
    return _chain(x, lo, hi, np.maximum(down(1.0 / up(1.0 + s_hi)), 0.0), np.minimum(up(1.0 / down(1.0 + s_lo)), 1.0))


def log(x: Interval) -> Interval:
    """Natural logarithm (increasing); needs ``x > 0`` on the whole interval. Derivative ``1 / x``."""
    x = Interval._lift(x)
    if np.any(x.lo <= 0):
        raise NotCertifiable("log of an interval reaching 0 or below: the function is undefined on some box; "
                             "keep its argument > 0 on the whole domain")
    _check_finite(x, "log")
    lo, hi = _lib_down(np.log(x.lo)), _lib_up(np.log(x.hi))
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    return _chain(x, lo, hi, down(1.0 / x.hi), up(1.0 / x.lo))


def _pow_lo_hi(a: Array, k: int) -> tuple[Array, Array]:
    """Bounds of ``a ** k`` for ``a >= 0`` or odd ``k`` (k >= 1): the float power widened by k + LIBM_ULPS ulp."""
    with np.errstate(over="ignore"):
        p = np.power(a, k)
    w = np.abs(p) * ((k + LIBM_ULPS) * _EPS) + TINY
    return p - w, p + w


def power(x: Interval, k: int) -> Interval:
    """``x ** k`` for an integer ``k`` (also written ``x ** k``).

    Odd ``k``: increasing, ``[lo^k, hi^k]``. Even ``k``: ``[0, max(|lo|, |hi|)^k]``
    when 0 is inside, else ``[min(|lo|, |hi|)^k, max(|lo|, |hi|)^k]`` (no
    dependency problem, unlike repeated multiplication). ``k = 0`` gives 1,
    ``k < 0`` is ``1 / x^|k|`` and raises :class:`NotCertifiable` if an
    interval contains 0. Derivative ``k x^(k-1)``.
    """
    x = Interval._lift(x)
    if isinstance(k, (float, np.floating)) and float(k).is_integer():
        k = int(k)
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
        raise NotCertifiable(f"Interval ** {k!r}: only integer powers are supported; write x ** 0.5 as iv.sqrt(x) "
                             f"and a real power p of x > 0 as iv.exp(p * iv.log(x))")
    k = int(k)
    if k < 0:
        if np.any((x.lo <= 0) & (x.hi >= 0)):
            raise NotCertifiable(f"Interval ** {k}: division by an interval that contains 0 (a negative power of 0) "
                                 f"on some box")
        return power(x, -k).reciprocal()
    if k == 0:
        one = np.ones_like(x.lo)
        if not x.has_grad:
            return Interval(one, one, check=False)
        z = np.zeros_like(x.dlo)
        return Interval(one, one, z, z, check=False)
    if k == 1:
        return x
    if k == 2:
        return sqr(x)
    _check_finite(x, f"Interval ** {k}")
    if k % 2:
        lo, _ = _pow_lo_hi(x.lo, k)
        _, hi = _pow_lo_hi(x.hi, k)
    else:
        a, b = np.abs(x.lo), np.abs(x.hi)
        zero = (x.lo <= 0) & (x.hi >= 0)
        lo, _ = _pow_lo_hi(np.where(zero, 0.0, np.minimum(a, b)), k)
        _, hi = _pow_lo_hi(np.maximum(a, b), k)
        lo = np.maximum(lo, 0.0)
    if not np.all(np.isfinite(hi)) or not np.all(np.isfinite(lo)):
        raise NotCertifiable(f"Interval ** {k} overflowed on some box")
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    d = power(Interval(x.lo, x.hi, check=False), k - 1) * float(k)
    return _chain(x, lo, hi, d.lo, d.hi)


def abs_(x: Interval) -> Interval:
    """``|x|``; where 0 is inside, the (Clarke) derivative is the whole ``[-1, 1]``."""
    x = Interval._lift(x)
    pos, neg = x.lo >= 0, x.hi <= 0
    lo = np.where(pos, x.lo, np.where(neg, -x.hi, 0.0))
    hi = np.maximum(np.abs(x.lo), np.abs(x.hi))
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    slo = np.where(pos & (x.lo > 0), 1.0, -1.0)
    shi = np.where(neg & (x.hi < 0), -1.0, 1.0)
    return _chain(x, lo, hi, slo, shi)


def relu(x: Interval) -> Interval:
    """``max(x, 0)`` with derivative 1 (x > 0), 0 (x < 0) or [0, 1]."""
    x = Interval._lift(x)
    lo, hi = np.maximum(x.lo, 0.0), np.maximum(x.hi, 0.0)
    return _chain(x, lo, hi, np.where(x.lo > 0, 1.0, 0.0), np.where(x.hi < 0, 0.0, 1.0))


def hstack(parts: Sequence[Interval]) -> Interval:
    """Concatenate intervals of shape (T, k_i) along the last value axis -> (T, sum k_i)."""
    parts = [Interval._lift(p) for p in parts]
    lo = np.concatenate([p.lo for p in parts], axis=-1)
    hi = np.concatenate([p.hi for p in parts], axis=-1)
    if not any(p.has_grad for p in parts):
        return Interval(lo, hi, check=False)
    n = next(p.dlo.shape[-1] for p in parts if p.has_grad)
    gl, gh = [], []
    for p in parts:
        if p.has_grad:
            gl.append(p.dlo), gh.append(p.dhi)
        else:
            z = np.zeros(p.lo.shape + (n,))
            gl.append(z), gh.append(z)
    return Interval(lo, hi, np.concatenate(gl, axis=-2), np.concatenate(gh, axis=-2), check=False)


abs = abs_  # noqa: A001  (so that ``iv.abs(x)`` reads like ``np.abs(x)``)
pow = power  # noqa: A001  (``iv.pow(x, 3)`` reads like ``np.power(x, 3)``)
atan = arctan  # the names of the math module
asin = arcsin


# ---------------------------------------------------------------------- linear algebra
def _midrad(lo: Array, hi: Array) -> tuple[Array, Array]:
    """A float midpoint and a rigorous radius: ``[lo, hi]`` is inside ``[mid - rad, mid + rad]``."""
    mid = 0.5 * (lo + hi)
    rad = up(np.maximum(hi - mid, mid - lo))
    return mid, np.maximum(rad, 0.0)


def _matmul_bound(W: Array, mid: Array, rad: Array, bias: Optional[Array], axis_in: int) -> tuple[Array, Array]:
    """Rigorous enclosure of ``W x (+ b)`` for x in ``mid +- rad``.

    ``mid``, ``rad`` have the contraction axis at ``axis_in`` (-1 for (T, n)
    vectors, -2 for (T, n, q) matrices).
    """
    aW = np.abs(W)
    if axis_in == -1:
        c = mid @ W.T
        s = np.abs(mid) @ aW.T
        r = rad @ aW.T
        if bias is not None:
            c = c + bias
            s = s + np.abs(bias)
    else:  # (T, n, q): W @ M for each of the T matrices, as one (T q, n) x (n, p) product
        def mm(A: Array, M: Array) -> Array:
            return np.tensordot(M, A, axes=([1], [1])).transpose(0, 2, 1)
        c = mm(W, mid)
        s = mm(aW, np.abs(mid))
        r = mm(aW, rad)
    g = gamma(W.shape[1] + 3)
    R = up(up(r + up(2.0 * g * s)) * (1.0 + 2.0 * g))
    R = up(R + TINY)
    return down(c - R), up(c + R)


def affine(W: Array, b: Optional[Array], x: Interval) -> Interval:
    """Rigorous enclosure of ``W x + b`` for ``x`` an Interval of shape (T, n); ``W`` of shape (p, n).

    Value: the exact range over the box (up to the outward rounding margin).
    Gradient (if tracked): ``W dx``.
    """
    mid, rad = _midrad(x.lo, x.hi)
    lo, hi = _matmul_bound(W, mid, rad, b, -1)
    if not x.has_grad:
        return Interval(lo, hi, check=False)
    gm, gr = _midrad(x.dlo, x.dhi)
    dlo, dhi = _matmul_bound(W, gm, gr, None, -2)
    return Interval(lo, hi, dlo, dhi, check=False)


def net_interval(net, x: Interval) -> Interval:
    """Rigorous enclosure of the ReLU network of eq. (recur) over boxes.

    Parameters
    ----------
    net
        A :class:`flnotes.ReLUNet`.
    x
        Input boxes, an Interval of shape (T, n_in); if it tracks gradients
        (:meth:`Interval.variables`) the result encloses the network's
        (Clarke) Jacobian over each box too: a neuron whose pre-activation
        interval is strictly positive contributes 1, strictly negative 0,
        otherwise [0, 1].

    Returns
    -------
    Interval of shape (T, n_out).

    Notes
    -----
    Same propagation as FBBT (:func:`flnotes.fbbt`) but outward-rounded, so
    the enclosure is guaranteed despite floating point.
    """
    y = x
    for W, b in zip(net.W[:-1], net.b[:-1]):
        y = relu(affine(W, b, y))
    return affine(net.W[-1], net.b[-1], y)


def net_preactivations(net, x: Interval) -> list[Interval]:
    """Rigorous pre-activation intervals ``[L^k, U^k]`` of every hidden layer over the boxes ``x``."""
    out, y = [], Interval(x.lo, x.hi, check=False)
    for W, b in zip(net.W[:-1], net.b[:-1]):
        a = affine(W, b, y)
        out.append(a)
        y = relu(a)
    return out


def _sum_bounds(X: Array, axis: int = -1) -> tuple[Array, Array]:
    """Rigorous lower and upper bounds of ``X.sum(axis)`` (any summation order)."""
    S = X.sum(axis)
    E = np.abs(X).sum(axis)
    R = up(up(gamma(X.shape[axis] + 2) * E) * (1.0 + 4.0 * _U) + TINY)
    return down(S - R), up(S + R)


def dot_bounds(a: Array, x: Array) -> tuple[Array, Array]:
    """Rigorous lower and upper bounds of the row-wise dot products ``(a * x).sum(-1)``."""
    P = a * x
    lo, hi = _sum_bounds(P, -1)
    e = up(_EPS * np.abs(P).sum(-1) + TINY)  # each product was rounded once
    return down(lo - e), up(hi + e)


def net_linear_bound(net, pre: list[Interval], x: Interval, i: int, sign: float) -> tuple[Array, Array]:
    """A rigorous affine minorant of ``sign * Phi_NN,i`` over boxes (linear relaxation, back-substitution).

    Parameters
    ----------
    net
        The :class:`flnotes.ReLUNet`.
    pre
        Rigorous pre-activation bounds ``[L^k, U^k]`` over the boxes (from
        :func:`net_preactivations`), each of shape (T, n_k).
    x
        The input boxes, Interval of shape (T, n_in).
    i
        Output index.
    sign
        ``+1`` for a lower bound of ``Phi_NN,i``, ``-1`` for a lower bound of
        ``-Phi_NN,i`` (i.e. an upper bound of ``Phi_NN,i``).

    Returns
    -------
    a, c
        Arrays (T, n_in) and (T,) with ``sign * Phi_NN,i(x) >= a . x + c`` for
        every ``x`` in box t.

    Notes
    -----
    Starting from ``sign * y^K_i = sign W^K_i y^{K-1} + sign b^K_i``, the
    coefficients are pulled back through each layer (Zhang et al.'s CROWN,
    the linear-relaxation bounds surveyed by Grimstad & Andersson 2019):
    a ReLU with ``L < 0 < U`` multiplied by a positive coefficient is replaced
    by the lower line ``y >= s z`` (``s`` = 0 or 1, whichever is closer),
    with a negative coefficient by the chord ``y <= s z + t`` through
    ``(L, 0)`` and ``(U, U)``; stable neurons are exact. Every floating-point
    rounding error ``delta`` in a coefficient is moved into ``c`` as
    ``-|delta| max|variable|`` over the box, so the inequality holds exactly.
    On a box where all neurons are stable, ``a`` is the network's exact
    gradient there and the bound is tight.
    """
    lam = sign * np.broadcast_to(net.W[-1][i], (len(x), net.W[-1].shape[1]))
    c = np.full(len(x), sign * net.b[-1][i])
    for k in range(len(pre) - 1, -1, -1):
        L, U = pre[k].lo, pre[k].hi
        # --- through the ReLU of layer k+1: lam . relu(z) >= lam' . z + (contribution of t)
        active, inactive = L >= 0, U <= 0
        unstable = ~(active | inactive)
        pos = lam >= 0
        s_low = np.where(active | (unstable & (U >= -L)), 1.0, 0.0)           # lower line y >= s z
        with np.errstate(divide="ignore", invalid="ignore"):
            s_up = np.where(unstable, U / np.where(unstable, U - L, 1.0), np.where(active, 1.0, 0.0))
        s_up = np.clip(s_up, 0.0, 1.0)
        t_up = np.where(unstable, np.maximum(up(-(s_up * L)), up(U - down(s_up * U))), 0.0)  # chord intercept
        t_up = np.maximum(t_up, 0.0)
        slope = np.where(pos, s_low, s_up)
        lam_new = lam * slope
        d_lam = np.abs(lam_new) * _EPS + _NORMAL * (slope != 0)                 # |fl(lam s) - lam s|
        mag_z = np.maximum(np.abs(L), np.abs(U))
        lo_t, _ = _sum_bounds(down(np.where(pos, 0.0, lam * t_up)), -1)      # lam_j t_j <= 0 for lam_j < 0
        _, slack = _sum_bounds(up(d_lam * mag_z), -1)
        c = down(c + down(lo_t - slack))
        lam = lam_new
        # --- through the affine map z = W y + b
        W, b = net.W[k], net.b[k]
        g = gamma(W.shape[0] + 2)
        lam_next = lam @ W
        err = up(up(2.0 * g * (np.abs(lam) @ np.abs(W))) + TINY)  # >= |fl(lam W) - lam W| (g(1+g) <= 2g)
        if k > 0:
            prev = pre[k - 1]
            mag_y = np.maximum(np.maximum(prev.lo, 0.0), np.maximum(prev.hi, 0.0))
        else:
            mag_y = np.maximum(np.abs(x.lo), np.abs(x.hi))
        lb_b, _ = _sum_bounds(lam * b, -1)
        lb_b = down(lb_b - up(_EPS * np.abs(lam * b).sum(-1)))                # products lam_j b_j rounded too
        _, slack = _sum_bounds(up(err * mag_y), -1)
        c = down(c + down(lb_b - slack))
        lam = lam_next
    return lam, c


# ---------------------------------------------------------------------- mean-value form
def mean_value_bound(g_mid: Interval, grad: Interval, lo: Array, hi: Array, mid: Array) -> Interval:
    """Mean-value enclosure ``g(B) in g(m) + grad g(B) . (B - m)``.

    Parameters
    ----------
    g_mid
        Enclosure of ``g`` at the points ``m`` (Interval of shape (T, k)).
    grad
        Enclosure of the gradient of ``g`` over the boxes: an Interval whose
        ``dlo``, ``dhi`` have shape (T, k, n) (as returned by a function
        evaluated on :meth:`Interval.variables`).
    lo, hi, mid
        The boxes (T, n) and the points ``m`` inside them.

    Returns
    -------
    Interval of shape (T, k) enclosing ``g`` over each box.

    Notes
    -----
    For Lipschitz ``g`` (smooth maps, ReLU networks, ``abs``) Lebourg's
    mean-value theorem gives ``g(x) - g(m) = zeta . (x - m)`` with ``zeta`` in
    the Clarke generalized gradient on the segment, which the interval
    gradient encloses. The overestimation shrinks like the box width squared
    where ``g`` is smooth, against linearly for the plain interval extension.
    """
    r = up(np.maximum(hi - mid, mid - lo))[:, None, :]
    mag = np.maximum(np.abs(grad.dlo), np.abs(grad.dhi))
    # sum_j r_j mag_j, rounded up: a float sum of n non-negative terms has relative error <= gamma_n
    S = (r * mag).sum(-1)
    S = up(S * (1.0 + 2.0 * gamma(mag.shape[-1] + 2)) + TINY)
    return Interval(down(g_mid.lo - S), up(g_mid.hi + S), check=False)


def intersect(a: Interval, b: Interval) -> Interval:
    """Intersection of two enclosures of the same quantity (both valid, so is their intersection)."""
    return Interval(np.maximum(a.lo, b.lo), np.minimum(a.hi, b.hi), check=False)


# ---------------------------------------------------------------------- the book's two maps
def stribeck(x2: Interval) -> Interval:
    """Interval Stribeck friction ``s(x_2) = (0.8 + 0.2 e^{-100|x_2|}) tanh(10 x_2) + x_2`` (Sec. IV-A)."""
    return (0.8 + 0.2 * exp(-100.0 * abs_(x2))) * tanh(10.0 * x2) + x2


def msd_phi(z: Interval, v: Interval) -> Interval:
    """Interval version of the MSD map ``Phi(z, v) = v + s(z_2) + z_1`` (eq. MSD_model).

    ``z`` of shape (T, 2), ``v`` of shape (T, 1) -> (T, 1).
    """
    return v + stribeck(z[:, 1:2]) + z[:, 0:1]


def make_quad1d_phi(Gamma: float, gamma_: float, tau: float):
    """Interval version of the Quad-1D map of eq. (quad1D_nonlinear) for the given parameters.

    ``Phi(z, v) = tau (v + gamma z_3) / (Gamma sqrt(1 - zeta^2)) + arcsin(zeta)``,
    ``zeta = (z_3 + gamma z_2) / Gamma``; ``z`` (T, 3), ``v`` (T, 1) -> (T, 1).
    Raises :class:`NotCertifiable` if ``|zeta|`` can reach 1 on a box.
    """

    def quad1d_phi(z: Interval, v: Interval) -> Interval:
        zeta = (z[:, 2:3] + gamma_ * z[:, 1:2]) / Gamma
        return tau * (v + gamma_ * z[:, 2:3]) / (Gamma * sqrt(1.0 - sqr(zeta))) + arcsin(zeta)

    return quad1d_phi


__all__ = ["Interval", "NotCertifiable", "LIBM_ULPS", "TINY", "down", "up", "gamma", "sqr", "exp", "log", "tanh",
           "sqrt", "arcsin", "asin", "sin", "cos", "tan", "arctan", "atan", "power", "abs_", "relu", "hstack", "affine",
           "net_interval", "net_preactivations", "net_linear_bound", "dot_bounds",
           "mean_value_bound", "intersect", "stribeck", "msd_phi", "make_quad1d_phi"]
