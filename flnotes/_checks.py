"""Argument checks with messages that say what to change."""
from __future__ import annotations

import collections
import collections.abc
import datetime
import decimal
import itertools
import mmap
import numbers
import reprlib
import warnings
from typing import Any, Optional

import numpy as np


#: Kinds of numpy arrays (``dtype.kind``) that :func:`as_floats` refuses although numpy would convert them to floats:
#: booleans, strings and bytes, complex numbers (numpy drops the imaginary part), dates and time spans, records.
_NOT_REAL = {"b": "booleans", "U": "strings", "T": "strings", "S": "bytes", "c": "complex numbers", "M": "dates",
             "m": "time spans", "V": "records or raw bytes"}

#: The same for single Python or numpy objects (the elements of an array of objects).
_NOT_REAL_TYPES = (((bool, np.bool_), "booleans"), ((str, np.str_), "strings"),
                   ((bytes, bytearray, np.bytes_), "bytes"), ((complex, np.complexfloating), "complex numbers"),
                   ((np.datetime64, datetime.date), "dates"), ((np.timedelta64, datetime.timedelta), "time spans"),
                   (type(None), "None (a missing value)"))


def _types_not_real(types: set) -> Optional[str]:
    """What a value of one of ``types`` is when it is no real number (:data:`_NOT_REAL_TYPES`), else ``None``."""
    for bad, what in _NOT_REAL_TYPES:
        if any(issubclass(t, bad) for t in types):
            return what
    return None


#: What a masked array with masked entries holds: numpy reads it without its mask (the hidden values, or NaN).
_MASKED = "masked (missing) values"


def _is_masked(e: Any) -> bool:
    """Whether ``e`` is a masked array with at least one masked entry (``np.ma.masked`` included)."""
    return isinstance(e, np.ma.MaskedArray) and bool(np.ma.is_masked(e))


def _not_real(e: Any) -> Optional[str]:
    """What the object ``e`` is when it is no real number (an array by its type, an array of objects by its elements),
    else ``None``."""
    if _is_masked(e):
        return _MASKED
    if isinstance(e, np.ndarray):
        return _NOT_REAL.get(e.dtype.kind) or (_objects_not_real(e.reshape(-1)) if e.dtype.kind == "O" else None)
    return _types_not_real({type(e)})


def _objects_not_real(items) -> Optional[str]:
    """:func:`_not_real` over ``items`` (an iterable of objects): the types first (at C speed), then each array, then
    any other object (:func:`_others_not_real`)."""
    items = list(items)
    types = set(map(type, items))
    what = _types_not_real(types)
    if what is None and any(issubclass(t, np.ndarray) for t in types):
        what = next(filter(None, (_not_real(e) for e in items if isinstance(e, np.ndarray))), None)
    if what is None:
        what = _others_not_real(items, types)
    return what


#: Values judged by their type alone (:data:`_NOT_REAL_TYPES`) or, arrays, by :func:`_not_real`.
_PLAIN = (numbers.Number, decimal.Decimal, np.generic, np.ndarray, str, bytes, bytearray, type(None), datetime.date,
          datetime.timedelta)


class _NotReal(ValueError):
    """What an argument holds that is no real number (raised inside :func:`_read`)."""

    def __init__(self, what: str):
        super().__init__(what)
        self.what = what


def _container(t: type) -> bool:
    """Whether numpy reads an object of type ``t`` as an array of its own contents: a buffer, an object with
    ``__array__`` or the array interface, a memory map, or a sequence (``__len__`` and ``__getitem__``). Any other
    object (e.g. one with ``__float__`` only, a set, a generator) is one element, which ``float()`` reads or refuses."""
    return (issubclass(t, (memoryview, mmap.mmap)) or any(hasattr(t, a) for a in (
        "__array__", "__array_interface__", "__array_struct__", "__buffer__")) or
        (hasattr(t, "__len__") and hasattr(t, "__getitem__") and not issubclass(t, (dict, collections.abc.Mapping))))


def _others_not_real(items, types: set) -> Optional[str]:
    """What the first element of ``items`` that is a container other than a Python sequence (:func:`_container`)
    holds when it is no real number, judged as a whole argument (:func:`_read`): a memoryview, an object with
    ``__array__``, another sequence (e.g. a ``UserList``) inside a list hide their contents from a look at the
    types."""
    other = {t for t in types if not issubclass(t, _PLAIN + _SEQUENCES) and _container(t)}
    if not other:
        return None
    for e in items:
        if type(e) in other:
            try:
                _read(e)
            except _NotReal as exc:
                return exc.what
            except Exception as exc:  # noqa: BLE001 - any failure to read the element says it is no number
                return f"an element numpy cannot read as numbers ({type(exc).__name__})"
    return None


def _beyond_float(items) -> Optional[str]:
    """Whether a finite number among ``items`` (the elements numpy turned into inf or NaN) lies beyond the float
    range: a ``Decimal`` such as ``Decimal("1e400")`` becomes ``inf`` without a word (a Python int or a Fraction that
    large raises)."""
    if any(isinstance(e, decimal.Decimal) and e.is_finite() for e in items):
        return "a number beyond the float range (too large)"
    return None


_SEQUENCES = (list, tuple, collections.deque)


def _sequence_not_real(x) -> Optional[str]:
    """:func:`_not_real` over the leaves of the nested Python sequences ``x`` (lists, tuples, deques), read level by
    level at C speed before numpy reads them: numpy reads a bytearray or a 0-d boolean array inside them as numbers."""
    level, found = [x], set()
    for _ in range(65):  # numpy reads at most 64 dimensions
        items = list(itertools.chain.from_iterable(level))
        types = set(map(type, items))
        seq = {t for t in types if issubclass(t, _SEQUENCES)}
        found |= types - seq
        if any(issubclass(t, np.ndarray) for t in types):
            what = next(filter(None, (_not_real(e) for e in items if isinstance(e, np.ndarray))), None)
            if what is not None:
                return what
        what = _others_not_real(items, types - seq)
        if what is not None:
            return what
        if not seq:
            break
        level = items if seq == types else [e for e in items if isinstance(e, _SEQUENCES)]
    return _types_not_real(found)


def _reads_as_array(x) -> bool:
    """Whether numpy reads ``x`` as an array of its own type (``__array__``, the array interface, a buffer), so that
    the type of that array says what ``x`` holds; otherwise numpy reads it element by element (the sequence
    protocol), and the elements are looked at."""
    if any(hasattr(x, a) for a in ("__array__", "__array_interface__", "__array_struct__")):
        return True
    try:
        memoryview(x)
    except TypeError:
        return False
    return True


def _unwrapped(x: Any) -> tuple[Any, Optional[str]]:
    """``(x, what)`` for an object that numpy reads through a protocol which would hide what it holds: a memoryview
    of bytes (numpy reads its characters as uint8 numbers) is bytes; an object whose ``__array__`` gives a masked
    array (numpy keeps the values and drops the mask) is read once, here, and judged by that array."""
    if isinstance(x, mmap.mmap):  # numpy reads its bytes as uint8 numbers
        return x, "bytes"
    if isinstance(x, memoryview):  # of raw bytes, unless cast to another format (e.g. "d": floats)
        raw = isinstance(x.obj, (bytes, bytearray, mmap.mmap)) and x.format.lstrip("@=<>!") in ("B", "b", "c")
        return x, ("bytes" if raw else None)
    na = getattr(getattr(x, "dtype", None), "na_value", None)  # pandas' nullable types: pd.NA would become NaN
    if type(na).__name__ == "NAType" and callable(getattr(x, "isna", None)) and bool(np.asarray(x.isna()).any()):
        return x, "missing values (pandas NA)"
    if hasattr(x, "__array__") and not isinstance(x, np.generic):
        arr = x.__array__()
        if not isinstance(arr, np.ndarray):  # numpy refuses it too
            return x, f"an __array__ method that gives no array ({type(arr).__name__})"
        return arr, (_MASKED if _is_masked(arr) else None)
    return x, None


_REPR = reprlib.Repr()
_REPR.maxother = _REPR.maxstring = 80


def brief(x: Any) -> str:
    """A short one-line ``repr`` of ``x`` for a message (long containers and strings cut, whitespace folded)."""
    try:
        return " ".join(_REPR.repr(x).split())
    except Exception:  # noqa: BLE001 - an object whose repr fails is still named by its type
        return f"<{type(x).__name__}>"


def as_floats(x: Any, name: str) -> np.ndarray:
    """``x`` as a float array (any shape): real numbers only. Booleans, strings, bytes, complex numbers, dates, time
    spans, ``None`` and masked entries, which numpy would convert without a word (``True`` to 1, ``"1"`` to 1,
    ``1 + 2j`` to 1, ``None`` to NaN, a masked entry to the value it hides), are refused with a ``ValueError`` naming
    ``name``, also inside lists or arrays of objects; so is anything numpy cannot read as an array of numbers, or only
    with a warning (e.g. beyond the float range).

    An array is judged by its type (numpy's speed); an array of objects, nested Python lists, tuples and deques (where
    numpy turns ``[1.0, True]`` into ``[1.0, 1.0]`` and ``[bytearray(b"1")]`` into ``[[49.0]]``) and other containers
    numpy reads are judged by the types of their elements, at every depth, before or after numpy reads them. A
    memoryview of bytes is bytes, and an object whose ``__array__`` gives a masked array is judged by that array
    (numpy would read the characters as numbers, and drop the mask)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a complex part dropped, an overflow: an error here
            return _read(x)
    except _NotReal as exc:
        raise ValueError(f"{name} must be numbers (an array of floats), got {brief(x)} (it holds {exc.what})") from None
    except Exception as exc:  # numpy's errors, a warning, an element's own __float__: all say x is no array of numbers
        raise ValueError(f"{name} must be numbers (an array of floats), got {brief(x)} ({type(exc).__name__}: "
                         f"{exc!s:.200})") from exc


def _read(x: Any) -> np.ndarray:
    """The body of :func:`as_floats`: ``x`` as a float array, or :class:`_NotReal` saying what it holds."""
    if isinstance(x, _SEQUENCES):
        what = _sequence_not_real(x)
    else:
        what = (_MASKED if _is_masked(x) else None) if isinstance(x, np.ndarray) else _not_real(x)
    if what is None and not isinstance(x, np.ndarray):
        x, what = _unwrapped(x)
    if what is None:
        raw = np.asarray(x)
        what = _NOT_REAL.get(raw.dtype.kind)
        if what is None and raw.dtype.kind == "O":
            what = _objects_not_real(raw.reshape(-1))
        elif what is None and not isinstance(x, _SEQUENCES) and raw.ndim and not _reads_as_array(x):
            # another container numpy reads (e.g. the sequence protocol): its elements, as objects
            what = _objects_not_real(np.asarray(x, dtype=object).reshape(-1))
        if what is None:
            out = np.asarray(raw, float)
            if raw.dtype.kind == "O" and not np.all(np.isfinite(out)):
                what = _beyond_float(raw.reshape(-1)[~np.isfinite(out.reshape(-1))])
            if what is None:
                return out
    raise _NotReal(what)


_floats = as_floats


def as_vector(x: Any, n: int, name: str) -> np.ndarray:
    """``x`` as a float vector of length ``n`` (a scalar is broadcast)."""
    a = _floats(x, name)
    if a.ndim == 0:
        a = np.full(n, float(a))
    a = a.reshape(-1) if a.ndim == 2 and 1 in a.shape else a
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {np.shape(x)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf: {a}")
    return a


def as_state(x: Any, n: int, name: str) -> np.ndarray:
    """``x`` as one state, a float vector of length ``n`` (:func:`as_vector`, without its broadcast): a number is a
    state only when ``n == 1`` (``z = 0.5`` of a two-state system is refused, not read as ``[0.5, 0.5]``)."""
    a = _floats(x, name)
    if a.ndim == 0 and n != 1:
        raise ValueError(f"{name} must have shape ({n},) (one state; a single number is no state of {n} "
                         f"coordinates), got {brief(x)}")
    return as_vector(a, n, name)


def as_batch(x: Any, n: int, name: str) -> np.ndarray:
    """``x`` as an (N, n) float array; a single point of shape (n,) becomes (1, n)."""
    a = _floats(x, name)
    if a.ndim == 1 and a.shape[0] == n:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != n:
        raise ValueError(f"{name} must have shape (N, {n}) or ({n},), got {np.shape(x)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf")
    return a


def check_box(lo: Any, hi: Any, n: int, lo_name: str = "lo", hi_name: str = "hi") -> tuple[np.ndarray, np.ndarray]:
    """Validate a box ``lo <= hi`` of dimension ``n``."""
    lo_a, hi_a = as_vector(lo, n, lo_name), as_vector(hi, n, hi_name)
    bad = np.flatnonzero(lo_a > hi_a)
    if bad.size:
        i = bad[0]
        raise ValueError(f"box is empty: {lo_name}[{i}] = {lo_a[i]} > {hi_name}[{i}] = {hi_a[i]}; "
                         f"every lower bound must be <= its upper bound")
    return lo_a, hi_a


def as_pair(box: Any, name: str) -> tuple[Any, Any]:
    """``box`` as its two parts ``(lo, hi)``: a tuple, list or array of length 2. Anything else (a third part, a
    single part, a string, a dict or a set) is an error."""
    if not isinstance(box, (tuple, list, np.ndarray)) or len(box) != 2:
        raise ValueError(f"{name} must be a pair (lo, hi) (a tuple, list or array of length 2), got {brief(box)}")
    return box[0], box[1]


def box_in_domain(lo: Any, hi: Any, dom_lo: np.ndarray, dom_hi: np.ndarray, what: str = "v_box",
                  names: tuple[str, str] = ("v_lo", "v_hi")) -> tuple[np.ndarray, np.ndarray]:
    """A box ``lo <= x <= hi`` (``lo < hi``) inside the network's domain ``[dom_lo, dom_hi]`` (the part of the domain
    box for ``x``: the state ``z`` or the input ``v``, where ``eps`` is certified), as two new float vectors (the
    caller's arrays are copied: changing them later changes nothing).

    Outside the domain the network extrapolates: ``|Phi - Phi_NN| <= eps`` is not certified there, so a controller
    whose ``v`` (or predicted ``z``) may leave it loses the bound ``|u| <= u_max``. A box wider than the domain is
    refused, not clipped."""
    dom_lo, dom_hi = np.asarray(dom_lo, float), np.asarray(dom_hi, float)
    m = dom_lo.shape[0]
    lo_a, hi_a = as_vector(lo, m, names[0]).copy(), as_vector(hi, m, names[1]).copy()
    if np.any(lo_a >= hi_a):
        raise ValueError(f"{what} is empty or a point: need {names[0]} < {names[1]} (a box of positive width), got "
                         f"{lo_a} and {hi_a}")
    tol = 1e-12 * np.maximum(1.0, np.abs(dom_hi - dom_lo))
    for i in range(m):
        for val, edge, side, out in ((lo_a[i], dom_lo[i], names[0], dom_lo[i] - tol[i] - lo_a[i]),
                                     (hi_a[i], dom_hi[i], names[1], hi_a[i] - dom_hi[i] - tol[i])):
            if out > 0:
                raise ValueError(
                    f"{what} leaves the network's domain [{dom_lo}, {dom_hi}]: {side}[{i}] = {float(val)!r} lies "
                    f"{out + tol[i]:.3g} beyond the domain's face {float(edge)!r}. eps is certified only inside the domain "
                    f"(outside it the network extrapolates and |u| <= u_max is not guaranteed): give a box inside "
                    f"it, or train and certify the network on a wider domain")
    return lo_a, hi_a


def check_boxes(lo: Any, hi: Any, n: int, infinite: bool = False) -> tuple[np.ndarray, np.ndarray, bool]:
    """One box ``(n,)`` or a batch ``(T, n)`` of boxes as (T, n) arrays, and whether a batch was given; a number
    is taken for every coordinate, of one box or of every box of the other bound's batch. Bounds are finite, or
    with ``infinite`` ``±inf`` too (a box that reaches out without end; NaN is refused either way)."""
    lo_a, hi_a = as_floats(lo, "lo"), as_floats(hi, "hi")
    shape = next((a.shape for a in (lo_a, hi_a) if a.ndim == 2), (n,))  # of the other bound's batch, if any
    lo_a, hi_a = (np.full(shape, float(a)) if a.ndim == 0 else a for a in (lo_a, hi_a))
    batch = lo_a.ndim == 2
    lo2, hi2 = np.atleast_2d(lo_a), np.atleast_2d(hi_a)
    if lo2.shape != hi2.shape or lo2.ndim != 2 or lo2.shape[1] != n:
        raise ValueError(f"lo and hi must have shape ({n},) or (T, {n}), got {np.shape(lo)} and {np.shape(hi)}")
    fine = (lambda a: ~np.isnan(a)) if infinite else np.isfinite
    ok = np.all(fine(lo2), axis=1) & np.all(fine(hi2), axis=1) & np.all(lo2 <= hi2, axis=1)
    for t in np.flatnonzero(~ok)[:1]:  # the first bad box, named as check_box names it (its row in a batch)
        names = (f"lo[{t}]", f"hi[{t}]") if batch else ("lo", "hi")
        if infinite:
            for name, a in zip(names, (lo2[t], hi2[t])):
                if np.any(np.isnan(a)):
                    raise ValueError(f"{name} contains NaN: {a}")
            i = int(np.flatnonzero(lo2[t] > hi2[t])[0])
            raise ValueError(f"box is empty: {names[0]}[{i}] = {lo2[t][i]} > {names[1]}[{i}] = {hi2[t][i]}; every "
                             f"lower bound must be <= its upper bound")
        check_box(lo2[t], hi2[t], n, *names)
    return lo2, hi2, batch


def weight_matrix(W, n: int, name: str, definite: bool = False) -> np.ndarray:
    """A weight matrix (Q, R, P of eq. MPC_form_miqp_a) from a scalar, a diagonal or a matrix.

    Symmetric positive semidefinite, or positive definite with ``definite=True``; else a ValueError naming ``name``.
    """
    W = as_floats(W, name)
    if W.ndim == 0:
        W = W * np.eye(n)
    elif W.ndim == 1:
        if W.shape != (n,):
            raise ValueError(f"{name} as a vector must have shape ({n},) (its diagonal), got {W.shape}")
        W = np.diag(W)
    if W.shape != (n, n):
        raise ValueError(f"{name} must have shape ({n}, {n}), got {W.shape}")
    if not np.all(np.isfinite(W)):
        raise ValueError(f"{name} contains NaN or inf")
    if not np.allclose(W, W.T):
        raise ValueError(f"{name} must be symmetric, got {W.tolist()}")
    lam = float(np.min(np.linalg.eigvalsh(W)))
    if definite and lam <= 0:
        raise ValueError(f"{name} must be positive definite (smallest eigenvalue {lam:g}): give every input a "
                         f"positive weight, e.g. {name}=0.0175")
    if lam < -1e-12:
        raise ValueError(f"{name} must be positive semidefinite (smallest eigenvalue {lam:g})")
    return W


def horizon_reference(z_ref: Any, horizon: int, n_z: int) -> np.ndarray:
    """A predictive controller's reference ``z_ref(k)``, k = 0..N_p: shape (N_p + 1, n_z), or (n_z,) repeated."""
    R = as_floats(z_ref, "z_ref")
    if R.shape == (n_z,):
        R = np.repeat(R[None], horizon + 1, axis=0)
    if R.shape != (horizon + 1, n_z):
        raise ValueError(f"z_ref must have shape (horizon + 1, n_z) = ({horizon + 1}, {n_z}) (the reference for "
                         f"k = 0..N_p) or ({n_z},) for a constant reference; got shape {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError("z_ref contains NaN or inf")
    return R


def check_int(x: Any, name: str, low: int, what: str) -> int:
    """``x`` as an int ``>= low`` (``ValueError`` naming ``name`` and ``what`` it counts otherwise; ``bool`` refused)."""
    if isinstance(x, np.ndarray) and x.ndim == 0 and x.dtype.kind in "iu":  # a 0-d integer array is its number
        x = x.item()
    if isinstance(x, (bool, np.bool_, np.timedelta64)) or not isinstance(x, (int, np.integer)) or x < low:
        raise ValueError(f"{name} must be an integer >= {low} ({what}), got {x!r}")
    return int(x)


#: numpy's own seed objects, taken as they are by ``np.random.default_rng``.
SEED_OBJECTS = (np.random.Generator, np.random.BitGenerator, np.random.SeedSequence)


def check_seed(seed: Any, name: str = "seed", what: str = "the seed of the random sample, or None for a fresh one"):
    """``seed`` for ``np.random.default_rng``: ``None`` (a fresh random sample), an integer >= 0 (a 0-d integer
    array too), a sequence of them (as a list) or numpy's own seed objects (a ``Generator``, ``BitGenerator`` or
    ``SeedSequence``), returned as given (an integer as an ``int``); anything else (a boolean, a float, a negative
    integer) is a ``ValueError`` naming ``name``."""
    if seed is None or isinstance(seed, SEED_OBJECTS):
        return seed
    if isinstance(seed, (list, tuple, np.ndarray)) and np.ndim(seed) == 1 and len(seed):  # numpy's entropy sequence
        return [check_int(e.item() if isinstance(e, np.generic) else e, f"{name}[{i}]", 0, what)
                for i, e in enumerate(seed)]
    return check_int(seed, name, 0, what)


def one_number(x: Any, name: str) -> Any:
    """``x``, or its single entry when it is an array, list or tuple of one number (``u_max=[5.0]`` of a single
    input, a bound as ``np.array([4.8])``); anything else is returned as it is, for :func:`check_number` to judge."""
    return as_floats(x, name).reshape(-1)[0] if np.size(x) == 1 and np.ndim(x) > 0 else x


def check_count(x: Any, name: str, low: int, what: str) -> int:
    """``x`` as an int ``>= low``, given as any real number that is an integer (``3``, ``3.0``, ``Decimal(3)``, a 0-d
    array), else ``ValueError`` naming ``name`` (a boolean, a time span, ``2.5`` refused)."""
    v = check_number(x, name, f"{what}, an integer", low=low)
    y = x.item() if isinstance(x, np.ndarray) else x
    if v != int(v) or y != int(v):  # exact: Decimal("2.99999999999999999999") is 3.0 as a float, no integer
        raise ValueError(f"{name} must be an integer >= {low} ({what}), got {brief(x)}")
    return int(v)


def check_number(x: Any, name: str, what: str, low: float = 0.0, strict: bool = False,
                 none: bool = False) -> Optional[float]:
    """``x`` as a finite float ``>= low`` (``> low`` if ``strict``; ``None`` kept if ``none``; ``low=-inf``: any
    finite number), else ``ValueError``."""
    if x is None and none:
        return None
    if isinstance(x, np.ndarray) and x.ndim == 0 and x.dtype.kind in "iufO" and not _is_masked(x):
        x = x.item()  # a 0-d real array is its number
    v = np.nan  # the value as a float, compared with low (Fraction(1, 10**400) is 0.0 > 0: refused where strict)
    if not isinstance(x, (bool, np.bool_, np.timedelta64, np.datetime64)) and isinstance(x, (numbers.Real,
                                                                                           decimal.Decimal)):
        try:
            v = float(x)
        except (OverflowError, ValueError, TypeError):  # beyond the float range, a signalling NaN
            v = np.nan
    if not np.isfinite(v) or (v <= low if strict else v < low):
        bound = "" if low == -np.inf else f" {'>' if strict else '>='} {low:g}"  # low = -inf: any finite number
        raise ValueError(f"{name} must be a finite number{bound} ({what}){' or None' if none else ''}, got {brief(x)}")
    return float(v)


def check_bool(x: Any, name: str, what: str) -> bool:
    """``x`` if it is ``True`` or ``False`` (numpy's too), else ``ValueError`` naming ``name``."""
    if not isinstance(x, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False ({what}), got {x!r}")
    return bool(x)
