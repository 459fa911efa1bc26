"""Values that cross the sandbox's wall: JSON, decoded strictly.

A student function's return value leaves the sandbox as JSON text: numbers, strings,
``None``, lists, tuples, dicts and numeric arrays (``{"__nd__": ..., "kind": ..., "shape": ...}``).
:func:`decode` turns it into plain Python and numpy values and nothing else: an array's
kind must be bool, integer or float, its nested lists must have exactly the declared
shape, non-finite floats only as the tokens ``nan``, ``inf``, ``-inf``, and the whole
answer is capped (nesting, elements, characters). No object of the kernel's, no module,
no pickle crosses. :func:`expect_array` is what a hidden test calls on an answer: the
dtype, the exact shape and finiteness it expects, with a message saying what was wrong.
"""
from __future__ import annotations

import math
from typing import Any, Optional, Sequence

import numpy as np

__all__ = ["AnswerError", "encode", "decode", "expect_array", "MAX_ELEMENTS", "MAX_DEPTH"]

#: caps of one decoded answer
MAX_ELEMENTS = 5_000_000
MAX_DEPTH = 20
MAX_STRING = 100_000

_KINDS = {"b": np.bool_, "i": np.int64, "u": np.int64, "f": np.float64}
_FLOATS = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


class AnswerError(ValueError):
    """An answer from the sandbox that is not well-formed data."""


def encode(x: Any, depth: int = 0) -> Any:
    """Grader -> sandbox: the JSON form of a test's arguments (same format as the kernel's)."""
    if depth > MAX_DEPTH:
        raise TypeError("argument nested too deep")
    if x is None or isinstance(x, (bool, str)):
        return x
    if isinstance(x, (int, float, np.integer, np.floating, np.bool_)):
        x = x.item() if hasattr(x, "item") else x
        if isinstance(x, float) and not math.isfinite(x):
            return {"__float__": repr(x)}
        return x
    if isinstance(x, np.ndarray):
        if x.dtype.kind not in "biuf":
            raise TypeError(f"cannot send an array of dtype {x.dtype} to the kernel")
        return {"__nd__": encode(x.tolist(), depth + 1), "kind": x.dtype.kind, "shape": list(x.shape)}
    if isinstance(x, tuple):
        return {"__tuple__": [encode(v, depth + 1) for v in x]}
    if isinstance(x, list):
        return [encode(v, depth + 1) for v in x]
    if isinstance(x, dict):
        return {"__dict__": [[encode(k, depth + 1), encode(v, depth + 1)] for k, v in x.items()]}
    raise TypeError(f"cannot send an object of type {type(x).__name__} to the kernel")


class _Budget:
    def __init__(self):
        self.left = MAX_ELEMENTS

    def take(self, n: int = 1) -> None:
        self.left -= n
        if self.left < 0:
            raise AnswerError(f"the answer holds more than {MAX_ELEMENTS} values")


def _scalar(x: Any) -> Any:
    if x is None or isinstance(x, bool):
        return x
    if isinstance(x, int):
        if abs(x) > 2**63:
            raise AnswerError("an integer out of range")
        return x
    if isinstance(x, float):
        if not math.isfinite(x):
            raise AnswerError("a non-finite float outside the nan/inf tokens")
        return x
    if isinstance(x, str):
        if len(x) > MAX_STRING:
            raise AnswerError("a string longer than the grader accepts")
        return x
    if isinstance(x, dict) and set(x) == {"__float__"} and x["__float__"] in _FLOATS:
        return _FLOATS[x["__float__"]]
    raise AnswerError(f"not a number, string or None: {type(x).__name__}")


def _array(x: dict, budget: _Budget) -> np.ndarray:
    if set(x) != {"__nd__", "kind", "shape"} or x["kind"] not in _KINDS:
        raise AnswerError("malformed array")
    shape = x["shape"]
    if not isinstance(shape, list) or len(shape) > 8 or not all(type(s) is int and 0 <= s for s in shape):
        raise AnswerError("malformed array shape")
    size = math.prod(shape)
    budget.take(size)

    def flat(v, dims):
        if not dims:
            return [_scalar(v)]
        if not isinstance(v, list) or len(v) != dims[0]:
            raise AnswerError(f"an array whose data do not have its declared shape {tuple(shape)}")
        out = []
        for w in v:
            out += flat(w, dims[1:])
        return out

    values = flat(x["__nd__"], shape)
    if any(v is None or isinstance(v, str) for v in values):
        raise AnswerError("an array holding a non-number")
    return np.array(values, dtype=_KINDS[x["kind"]]).reshape(shape)


def decode(x: Any, depth: int = 0, budget: Optional[_Budget] = None) -> Any:
    """Sandbox -> grader: the Python value of a JSON answer; :class:`AnswerError` if malformed."""
    budget = budget or _Budget()
    if depth > MAX_DEPTH:
        raise AnswerError("an answer nested too deep")
    budget.take()
    if isinstance(x, list):
        return [decode(v, depth + 1, budget) for v in x]
    if isinstance(x, dict):
        if "__nd__" in x:
            return _array(x, budget)
        if set(x) == {"__tuple__"} and isinstance(x["__tuple__"], list):
            return tuple(decode(v, depth + 1, budget) for v in x["__tuple__"])
        if set(x) == {"__dict__"} and isinstance(x["__dict__"], list):
            out = {}
            for kv in x["__dict__"]:
                if not isinstance(kv, list) or len(kv) != 2:
                    raise AnswerError("malformed dict")
                k = decode(kv[0], depth + 1, budget)
                if isinstance(k, list) or isinstance(k, dict) or isinstance(k, np.ndarray):
                    raise AnswerError("a dict key that is not a number, string or tuple")
                out[k] = decode(kv[1], depth + 1, budget)
            return out
        return _scalar(x)
    return _scalar(x)


def expect_array(x: Any, shape: Sequence[int], *, name: str = "the answer", finite: bool = True,
                 dtype: type = float) -> np.ndarray:
    """``x`` as an array of ``dtype`` with exactly ``shape``; AssertionError (a failed test) otherwise.

    What a hidden test calls on every answer before comparing it: ``np.allclose`` broadcasts
    (an empty array is "close" to anything), so the shape is checked first, exactly.
    """
    try:
        a = np.asarray(x, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise AssertionError(f"{name} is not an array of {dtype.__name__}: {exc}") from None
    if a.shape != tuple(shape):
        raise AssertionError(f"{name} has shape {a.shape}, expected {tuple(shape)}")
    if finite and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise AssertionError(f"{name} holds nan or inf")
    return a
