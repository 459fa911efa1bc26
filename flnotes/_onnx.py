"""Reading and writing ReLU networks as ONNX graphs (behind :meth:`ReLUNet.from_onnx` and :meth:`ReLUNet.to_onnx`).

An ONNX graph is read by walking its nodes in order and keeping, for each
tensor computed from the graph's input, the affine map from the last ReLU
output ``y^{k-1}`` (or the input ``y^0``) to it. An affine node (``Gemm``,
``MatMul``, ``Add``/``Sub``/``Mul``/``Div``/``Neg`` with a constant, and the
``Scaler`` of ``ai.onnx.ml`` that skl2onnx writes for a ``StandardScaler``)
composes that map; a ``Relu`` closes layer ``k`` of eq. (recur), ``W^k, b^k`` being the
map it is applied to; shape nodes (``Identity``, ``Flatten``, ``Reshape``,
``Squeeze``, ``Unsqueeze``, ``Transpose``, ``Cast``, inference ``Dropout``)
keep the map and track where the batch axis is. The graph's output is the
last affine map, ``W^K, b^K``. Scalings of the input and the output are thus
folded into the first and last layer, as eq. (eq-02-fold) of chapter 2 does.
These are the node patterns that ``torch.onnx.export``, tf2onnx and skl2onnx
write for a ReLU multilayer perceptron, including torch's
``x.view(x.size(0), -1)`` (``Shape -> Gather -> Unsqueeze -> Concat ->
Reshape``: the batch size is followed, see :class:`_Shp`). Any other node that
touches the data (another activation, a second data operand as in a skip
connection, an unfused ``BatchNormalization``, other arithmetic on a shape
read at run time, a cast of the data to float16 or bfloat16) is refused with
its name and op.

What the reader does not guess: the model must pass ``onnx.checker`` (the
arity of every node) and, once read, onnx's strict type inference (what
onnxruntime would reject); nodes that do not reach the output are ignored, as
onnxruntime ignores them; nodes on constants only are folded with ONNX's
types (``Cast`` converts, integer ``Div`` truncates toward zero); float16 and
bfloat16 data paths are refused (their rounding is far above what an ``eps``
certified on the float64 weights covers); tensors stored in external data
files are read only when the model is given as a path, and only from the
model's folder; sparse initializers are densified.

The ``onnx`` package is needed only here and is imported on first use.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import numpy as np

Array = np.ndarray
B = "batch"  # the batch axis in a tracked shape

#: ops that only change the shape, the dtype or nothing at all
_SHAPE_OPS = {"Identity", "Flatten", "Reshape", "Squeeze", "Unsqueeze", "Transpose", "Cast", "Dropout"}
#: ops read as affine maps of the data (with constant operands)
_AFFINE_OPS = {"Gemm", "MatMul", "Add", "Sub", "Mul", "Div", "Neg"}
#: what a node may be to be read; anything else is refused
SUPPORTED_OPS = tuple(sorted(_SHAPE_OPS | _AFFINE_OPS | {"Relu", "Constant", "Scaler"}))


def _onnx():
    try:
        import onnx
    except ImportError as exc:  # pragma: no cover - the requirements install it
        raise ImportError("reading and writing ONNX needs the onnx package: pip install 'flnotes[onnx]' "
                          "(make venv installs it)") from exc
    return onnx


class NotAReLUMLP(ValueError):
    """The ONNX graph is not a feed-forward ReLU network flnotes can read (the message names the node and op)."""


@dataclass
class _Data:
    """A tensor computed from the input: ``features = A @ y + c`` with ``y`` the last ReLU output (or the input).

    ``A`` is ``None`` for the identity of a size not known yet (a graph input
    declared with a symbolic feature size); ``shape`` is the tensor's shape
    with :data:`B` at the batch axis (no batch axis for a single vector).
    """

    A: Optional[Array]
    c: Array
    shape: tuple
    k: float = 1.0  # with A None: features = k * y + c (c empty or one value for every feature)

    @property
    def n(self) -> Optional[int]:
        return None if self.A is None else self.A.shape[0]


@dataclass
class _Shp:
    """An integer tensor read from the data's shape at run time (``Shape``), its entries ints or :data:`B`.

    torch writes ``x.view(x.size(0), -1)`` as ``Shape -> Gather(0) -> Unsqueeze
    -> Concat([batch, -1]) -> Reshape``: the batch size is followed through
    these nodes so that the ``Reshape`` keeps the batch axis.
    """

    v: list
    scalar: bool = False

    def value(self) -> Union["_Shp", Array]:
        """Itself, or a plain int64 array when no entry depends on the batch size."""
        if any(e == B or e is None for e in self.v):
            return self
        arr = np.array(self.v, np.int64)
        return arr.reshape(()) if self.scalar else arr


def _where(node) -> str:
    name = node.name or (node.output[0] if node.output else "?")
    return f"node {name!r} ({node.op_type})"


def _attrs(node) -> dict:
    onnx = _onnx()
    return {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}


def _features(shape: tuple) -> int:
    return int(np.prod([d for d in shape if d != B], dtype=int))


def _constant_value(node) -> Array:
    a = _attrs(node)
    if "value" in a:
        return _tensor(a["value"], node)
    if "sparse_value" in a:
        return _dense(a["sparse_value"], f"{_where(node)}: its sparse value")
    for key, dt in (("value_float", np.float32), ("value_int", np.int64)):
        if key in a:
            return np.array(a[key], dt)
    for key, dt in (("value_floats", np.float32), ("value_ints", np.int64)):
        if key in a:
            return np.array(list(a[key]), dt)
    raise NotAReLUMLP(f"{_where(node)}: a Constant of kind {sorted(a)} is not a number array")


#: the float types whose rounding the folded float64 weights follow closely enough (a float16 or bfloat16 data path
#: rounds each product to 3 significant digits, which an ``eps`` certified on the float64 network would not cover)
_FULL_FLOATS = (1, 11)  # FLOAT, DOUBLE
_REDUCED = {10: "float16", 16: "bfloat16"}


def _tensor(t, where) -> Array:
    """A TensorProto's value; a tensor stored in an external file must have been loaded already (see :func:`_load`)."""
    onnx = _onnx()
    if t.data_location == onnx.TensorProto.EXTERNAL:
        raise NotAReLUMLP(f"{where if isinstance(where, str) else _where(where)}: tensor {t.name!r} is stored in an "
                          "external data file that was not loaded; pass the path of the .onnx file (its external data "
                          "is read from the model's folder), not its bytes or a model loaded with load_external_data=False")
    return onnx.numpy_helper.to_array(t)


def _dense(sp, where: str) -> Array:
    """A SparseTensorProto as a dense array (as onnxruntime densifies a sparse initializer)."""
    values = _tensor(sp.values, where)
    idx = _tensor(sp.indices, where).astype(np.int64)
    dims = tuple(int(x) for x in sp.dims)
    out = np.zeros(int(np.prod(dims, dtype=np.int64)), values.dtype)
    flat = idx if idx.ndim == 1 else (np.ravel_multi_index(tuple(idx.T), dims) if idx.size else idx.reshape(0))
    if flat.size and (flat.min() < 0 or flat.max() >= out.size) or len(flat) != values.size:
        raise NotAReLUMLP(f"{where}: sparse tensor {sp.values.name!r} has indices that do not fit its shape {dims}")
    out[flat] = values.ravel()
    return out.reshape(dims)


def _all_tensors(model):
    """Every TensorProto of the model: initializers, sparse ones' parts, tensors in node attributes (and subgraphs)."""
    graphs = [model.graph]
    while graphs:
        g = graphs.pop()
        yield from g.initializer
        for sp in g.sparse_initializer:
            yield sp.values
            yield sp.indices
        for node in g.node:
            for a in node.attribute:
                if a.HasField("t"):
                    yield a.t
                yield from a.tensors
                if a.HasField("sparse_tensor"):
                    yield a.sparse_tensor.values
                    yield a.sparse_tensor.indices
                if a.HasField("g"):
                    graphs.append(a.g)
                graphs.extend(a.graphs)


def _load(model) -> Any:
    """The ModelProto of a path, bytes or a model; external data only from a path, inside the model's folder."""
    onnx = _onnx()
    from onnx import external_data_helper as ext

    base = None
    if isinstance(model, (str, Path)):
        path = Path(model)
        if not path.exists():
            raise FileNotFoundError(f"no ONNX file {str(path)!r}")
        model = onnx.load(str(path), load_external_data=False)
        base = path.resolve().parent
    elif isinstance(model, (bytes, bytearray)):
        model = onnx.load_from_string(bytes(model))
    if not isinstance(model, onnx.ModelProto):
        raise TypeError(f"give an ONNX model (onnx.ModelProto), its bytes or a path to an .onnx file, got {type(model).__name__}")
    external = [t for t in _all_tensors(model) if ext.uses_external_data(t)]
    if external and base is None:
        raise NotAReLUMLP(f"tensor {external[0].name!r} is stored in an external data file, and a model given as bytes or "
                          "as a ModelProto has no folder to read it from: pass the path of the .onnx file instead")
    if external:
        model = onnx.ModelProto.FromString(model.SerializeToString())  # do not fill the caller's model
        for t in _all_tensors(model):
            if not ext.uses_external_data(t):
                continue
            loc = ext.ExternalDataInfo(t).location
            target = (base / loc).resolve()
            if Path(loc).is_absolute() or base not in target.parents:
                raise NotAReLUMLP(f"tensor {t.name!r} points to external data {loc!r} outside the model's folder {base.name!r}: "
                                  "only a file name relative to the .onnx file's folder is read")
            if not target.is_file():
                raise FileNotFoundError(f"tensor {t.name!r}: its external data file {loc!r} is not next to the model")
            ext.load_external_data_for_tensor(t, str(base))
            t.data_location = onnx.TensorProto.DEFAULT
            del t.external_data[:]
    return model


def _check(model) -> None:
    """onnx.checker's structural check (arity of every node, attributes), its message turned into a clear refusal."""
    onnx = _onnx()
    undeclared = [o for o in model.graph.output if o.type.HasField("tensor_type")
                  and not o.type.tensor_type.HasField("shape")]
    if undeclared:  # onnxruntime runs a graph whose output has no declared shape; the checker wants the field
        model = onnx.ModelProto.FromString(model.SerializeToString())
        for o in model.graph.output:
            if o.type.HasField("tensor_type") and not o.type.tensor_type.HasField("shape"):
                o.type.tensor_type.shape.SetInParent()
    try:
        onnx.checker.check_model(model)
    except onnx.checker.ValidationError as exc:
        raise NotAReLUMLP(f"the model is not valid ONNX (onnx.checker: {str(exc).strip().splitlines()[0]}); "
                          "fix the node it names (onnxruntime would refuse it too)") from None


def _check_types(model) -> None:
    """onnx's strict type and shape inference: what onnxruntime rejects (int weights in a float graph, ...)."""
    onnx = _onnx()
    model = onnx.ModelProto.FromString(model.SerializeToString())
    del model.graph.value_info[:]  # declared shapes of intermediates and of the output: onnxruntime merges them leniently
    for o in model.graph.output:
        if o.type.tensor_type.HasField("shape"):
            o.type.tensor_type.ClearField("shape")
    try:
        onnx.shape_inference.infer_shapes(model, check_type=True, strict_mode=True, data_prop=True)
    except (onnx.shape_inference.InferenceError, onnx.checker.ValidationError) as exc:
        raise NotAReLUMLP(f"the model does not type-check (onnx shape inference: {str(exc).strip().splitlines()[0]}); "
                          "onnxruntime would refuse it: fix the node it names") from None


def _live(g) -> list:
    """The nodes whose outputs reach the graph's output (dead nodes are ignored, as onnxruntime does)."""
    need = {o.name for o in g.output}
    live = [False] * len(g.node)
    changed = True
    while changed:
        changed = False
        for i, node in enumerate(g.node):
            if not live[i] and any(o in need for o in node.output if o):
                live[i], changed = True, True
                need.update(x for x in node.input if x)
    return [n for n, keep in zip(g.node, live) if keep]


def _input_shape(vi) -> tuple:
    """The declared shape of the graph input, the batch axis marked; refuses what cannot be resolved."""
    t = vi.type.tensor_type
    if not t.HasField("shape"):
        raise NotAReLUMLP(f"graph input {vi.name!r} has no declared shape; export with a fixed feature size "
                          "(e.g. input shape (batch, n_in))")
    dims = [d.dim_value if d.HasField("dim_value") and d.dim_value > 0 else None for d in t.shape.dim]
    if len(dims) == 1:  # a dynamic 1-D input is a batch of scalars (as onnxruntime runs it), a fixed one a vector
        return (B,) if dims[0] is None else (dims[0],)
    if len(dims) < 1:
        raise NotAReLUMLP(f"graph input {vi.name!r} is a scalar, not a vector of inputs")
    # the first axis is the batch (dynamic or fixed), one other axis the features (known, or fixed by the first
    # layer), any other axes of size 1
    rest = dims[1:]
    if sum(1 for d in rest if d != 1) > 1:
        raise NotAReLUMLP(f"graph input {vi.name!r} has shape {dims}: expected (batch, n_in), (batch, 1, ..., n_in) or "
                          "(batch, n_in, 1, ...) with the other axes of size 1 (None is a dynamic size)")
    return (B, *rest)


def _broadcast_const(K: Array, d: _Data, node) -> Array:
    """The constant operand of an elementwise node, as one value per feature (or a scalar)."""
    K = np.asarray(K, float)
    if K.ndim > len(d.shape):
        raise NotAReLUMLP(f"{_where(node)}: the constant of shape {K.shape} has more axes than the data {d.shape}: "
                          "it would add axes to the tensor")
    if K.size == 1:
        return np.full(1, K.ravel()[0])
    shape = tuple(1 if s == B else s for s in d.shape)
    if any(s is None for s in shape):  # a symbolic feature size: the constant must be a vector along it
        if K.ndim >= 1 and np.prod(K.shape[:-1]) == 1 and K.shape[-1] > 1 and len(shape) >= 1 and shape[-1] is None:
            return K.ravel()
        raise NotAReLUMLP(f"{_where(node)}: cannot broadcast the constant of shape {K.shape} against a tensor of shape {d.shape}")
    try:
        out = np.broadcast_shapes(K.shape, shape)
    except ValueError:
        out = None
    if out != shape:
        raise NotAReLUMLP(f"{_where(node)}: the constant of shape {K.shape} does not broadcast along the features of a "
                          f"tensor of shape {d.shape} (it would grow the tensor or mix samples of the batch)")
    return np.broadcast_to(K.reshape((1,) * (len(shape) - K.ndim) + K.shape), shape).ravel().copy()


def _need(d: _Data, n: int, node) -> _Data:
    """``d`` with its size resolved to ``n`` features (a symbolic input size is fixed by its first use)."""
    if d.A is None:
        if n < 1:
            raise NotAReLUMLP(f"{_where(node)}: cannot resolve the input size")
        return _Data(d.k * np.eye(n), np.zeros(n) + (d.c[0] if d.c.size else 0.0),
                     tuple(n if s is None else s for s in d.shape))
    if d.n != n:
        raise NotAReLUMLP(f"{_where(node)}: expects {n} features but its data input has {d.n}")
    return d


def _scale(d: _Data, s: Array, node) -> _Data:
    if s.size > 1:
        d = _need(d, s.size, node)
    if d.A is None:  # a scalar times the identity of unknown size: kept until the first layer fixes the size
        return _Data(None, d.c * s[0], d.shape, d.k * s[0])
    return _Data(s[:, None] * d.A, s * d.c, d.shape)


def _shift(d: _Data, s: Array, node) -> _Data:
    if s.size > 1:
        d = _need(d, s.size, node)
    if d.A is None:  # one shift of every feature of a tensor of unknown size
        return _Data(None, (d.c if d.c.size else np.zeros(1)) + s, d.shape, d.k)
    return _Data(d.A, d.c + s, d.shape)


def _matmul(d: _Data, W: Array, node, shape: tuple) -> _Data:
    """``features -> W @ features`` with ``W`` (m, n)."""
    d = _need(d, W.shape[1], node)
    return _Data(W @ d.A, W @ d.c, shape)


def _check_finite(a: Array, node, what: str) -> None:
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{_where(node)}: its {what} contains NaN or inf; a network with non-finite weights has no "
                         "meaningful MILP encoding: fix the exported model")


def _only_singletons(shape: tuple, keep: int) -> bool:
    """All axes but the batch axis and axis ``keep`` have size 1."""
    return all(s in (1, B) for i, s in enumerate(shape) if i != keep % len(shape))


def _reshape(d: _Data, target: Sequence[int], allowzero: int, node) -> tuple:
    S = d.shape
    T = [t if t == B else int(t) for t in target]
    if B in T[1:] or (B in T and B not in S):
        raise NotAReLUMLP(f"{_where(node)}: reshape target {T} puts the batch size at another place than the first axis")
    if B not in S:
        n = _features(S) if None not in S else None
        if n is None:
            raise NotAReLUMLP(f"{_where(node)}: reshapes a tensor of unknown size")
        out = [S[i] if (t == 0 and not allowzero) else t for i, t in enumerate(T)]
        if out.count(-1) > 1:
            raise NotAReLUMLP(f"{_where(node)}: reshape target {T} has more than one -1")
        if -1 in out:
            known = int(np.prod([t for t in out if t != -1]))
            out[out.index(-1)] = n // known if known and n % known == 0 else -2
        if int(np.prod(out)) != n:
            raise NotAReLUMLP(f"{_where(node)}: cannot reshape {n} features to {T}")
        return tuple(out)
    if S.index(B) != 0:
        raise NotAReLUMLP(f"{_where(node)}: reshapes a tensor whose batch axis is not first ({S}); this would mix samples")
    n = None if None in S else _features(S)
    out = []
    for i, t in enumerate(T):
        if t == 0 and not allowzero:
            t = S[i] if i < len(S) else None
            if t is None:
                raise NotAReLUMLP(f"{_where(node)}: reshape target {T} copies an axis the input does not have")
        out.append(t)
    if not out or out[0] not in (-1, B) or (out[0] == -1 and -1 in out[1:]):
        raise NotAReLUMLP(f"{_where(node)}: reshape target {T} does not keep a dynamic batch axis first (-1 or 0 first, the "
                          "features after it)")
    rest = out[1:]
    if rest.count(-1) > 1:
        raise NotAReLUMLP(f"{_where(node)}: reshape target {T} has more than one -1")
    if -1 in rest:
        known = int(np.prod([t for t in rest if t != -1], dtype=int))
        if n is None or known == 0 or n % known:
            raise NotAReLUMLP(f"{_where(node)}: cannot resolve reshape target {T} for {n} features")
        rest[rest.index(-1)] = n // known
    if n is None:
        if sum(1 for t in rest if t != 1) > 1:
            raise NotAReLUMLP(f"{_where(node)}: reshapes a tensor of unknown size to {T}")
        return tuple([B] + [None if t != 1 else 1 for t in rest]) if any(t != 1 for t in rest) else tuple([B] + rest)
    if int(np.prod(rest, dtype=int)) != n:
        raise NotAReLUMLP(f"{_where(node)}: cannot reshape {n} features to {rest}")
    return tuple([B] + rest)


def _axes(node, axes, r: int) -> list:
    """Axes of a tensor of rank ``r`` in ``[-r, r - 1]``, made non-negative; out of range or repeated is refused."""
    axes = [int(x) for x in axes]
    if any(not -r <= x < r for x in axes) or len({x % r for x in axes}) != len(axes):
        raise NotAReLUMLP(f"{_where(node)}: axes {axes} are out of range [-{r}, {r - 1}] or repeated for a tensor of rank {r}")
    return sorted(x % r for x in axes)


def _transpose(S: tuple, perm: Optional[Sequence[int]], node) -> tuple:
    perm = list(range(len(S)))[::-1] if perm is None else [int(p) for p in perm]
    if sorted(perm) != list(range(len(S))):
        raise NotAReLUMLP(f"{_where(node)}: perm {perm} is not a permutation of the {len(S)} axes of {S}")
    big = [i for i, s in enumerate(S) if s not in (1, B)]
    if len(big) > 1:
        raise NotAReLUMLP(f"{_where(node)}: transposes a tensor of shape {S} with several feature axes")
    return tuple(S[p] for p in perm)


def _gemm(node, a: Any, b: Any, cval: Optional[Array], attrs: dict) -> _Data:
    """``Y = alpha op(A) op(B) + beta C``, with either A or B the data."""
    alpha, beta = float(attrs.get("alpha", 1.0)), float(attrs.get("beta", 1.0))
    tA, tB = int(bool(attrs.get("transA", 0))), int(bool(attrs.get("transB", 0)))
    if isinstance(a, _Data) == isinstance(b, _Data):
        raise NotAReLUMLP(f"{_where(node)}: needs exactly one operand computed from the input and one constant weight "
                          "matrix" + (" (two data operands: not a layer of an MLP)" if isinstance(a, _Data) else ""))
    data, W = (a, b) if isinstance(a, _Data) else (b, a)
    W = np.asarray(W, float)
    if W.ndim != 2 or len(data.shape) != 2:
        raise NotAReLUMLP(f"{_where(node)}: Gemm needs 2-D operands, got data of shape {data.shape} and weight {W.shape}")
    _check_finite(W, node, "weight matrix")
    if isinstance(a, _Data):
        S = data.shape[::-1] if tA else data.shape  # op(A): (rows, n)
        if S[0] not in (B, 1) or not _only_singletons(data.shape, 1 - tA):
            raise NotAReLUMLP(f"{_where(node)}: op(A) must be (batch, features), the data has shape {data.shape} "
                              f"with transA={tA}")
        Wop = W.T if tB else W  # (n, m)
        m = Wop.shape[1]
        out = _matmul(data, alpha * Wop.T, node, (S[0], m))
        bias_shape = (S[0], m)
    else:
        S = data.shape[::-1] if tB else data.shape  # op(B): (n, cols)
        if S[1] not in (B, 1) or not _only_singletons(data.shape, tB):
            raise NotAReLUMLP(f"{_where(node)}: op(B) must be (features, batch), the data has shape {data.shape} "
                              f"with transB={tB}")
        Wop = W.T if tA else W  # (m, n)
        m = Wop.shape[0]
        out = _matmul(data, alpha * Wop, node, (m, S[1]))
        bias_shape = (m, S[1])
    if cval is not None:
        cval = np.asarray(cval, float)
        _check_finite(cval, node, "bias")
        out = _shift(out, beta * _broadcast_const(cval, _Data(out.A, out.c, bias_shape), node), node)
    return out


def read(model: Union[str, Path, Any]) -> tuple[list[Array], list[Array], dict]:
    """Weights and biases ``W^k, b^k`` of eq. (recur) read from an ONNX model (see the module docstring).

    Parameters
    ----------
    model
        A path to an ``.onnx`` file (external data is read from its folder
        only), its bytes, or an ``onnx.ModelProto`` (both without external
        data: they have no folder to read it from).

    Returns
    -------
    weights, biases, info
        The layers, and ``info`` with the graph's ``input``/``output`` names and
        their ``input_shape``/``output_shape`` (the batch axis as ``"batch"``).

    Raises
    ------
    NotAReLUMLP
        A node that is not part of a ReLU MLP (named with its op), several
        inputs or outputs, a shape that cannot be resolved, a model that
        ``onnx.checker`` or onnx's type inference rejects, a float16 or
        bfloat16 data path, external data that cannot be read safely.
    ValueError
        Non-finite weights (the node is named).
    """
    model = _load(model)
    _check(model)
    if model.graph.sparse_initializer:  # densified, as onnxruntime does (and for onnx's type inference)
        onnx = _onnx()
        dense = [onnx.numpy_helper.from_array(_dense(sp, f"sparse initializer {sp.values.name!r}"), sp.values.name)
                 for sp in model.graph.sparse_initializer]
        model = onnx.ModelProto.FromString(model.SerializeToString())
        del model.graph.sparse_initializer[:]
        model.graph.initializer.extend(dense)
    g = model.graph
    consts: dict[str, Array] = {t.name: _tensor(t, f"initializer {t.name!r}") for t in g.initializer}
    shadowed = [vi.name for vi in g.input if vi.name in consts]
    inputs = [vi for vi in g.input if vi.name not in consts]
    if len(inputs) != 1:
        note = (f"; inputs {shadowed} have an initializer of the same name, so they are read as constants (weights "
                "with a default value): rename the data input or the initializer") if shadowed and not inputs else ""
        raise NotAReLUMLP(f"the graph has {len(inputs)} inputs {[vi.name for vi in inputs]}; a network of flnotes has one "
                          f"input vector [z, v]: concatenate the inputs before exporting{note}")
    if len(g.output) != 1:
        raise NotAReLUMLP(f"the graph has {len(g.output)} outputs {[o.name for o in g.output]}; expected one output Phi_NN")
    elem = inputs[0].type.tensor_type.elem_type
    if elem not in _FULL_FLOATS:
        kind = _REDUCED.get(elem)
        raise NotAReLUMLP(f"graph input {inputs[0].name!r} is of type "
                          f"{kind or _onnx().helper.tensor_dtype_to_string(elem)}: "
                          + (f"a {kind} network rounds every product to a few digits, which the MILP's eps would not "
                             "cover; export it in float32 or float64" if kind else "expected a float32 or float64 input"))
    in_shape = _input_shape(inputs[0])
    feats = [s for s in in_shape if s != B]
    n0 = None if None in feats else int(np.prod(feats, dtype=int))
    data: dict[str, _Data] = {inputs[0].name: _Data(None if n0 is None else np.eye(n0),
                                                    np.zeros(0 if n0 is None else n0), in_shape)}
    weights, biases = [], []
    layer_of: dict[str, int] = {inputs[0].name: 0}  # which ReLU output a data tensor is affine in

    def val(name):
        if name == "":
            return None
        if name in data:
            return data[name]
        if name in consts:
            return consts[name]
        raise NotAReLUMLP(f"tensor {name!r} is used before it is computed (not topologically sorted?)")

    for node in _live(g):
        op = node.op_type
        if node.domain not in ("", "ai.onnx") and not (node.domain == "ai.onnx.ml" and op == "Scaler"):
            raise NotAReLUMLP(f"{_where(node)} of domain {node.domain!r} is not part of a ReLU MLP; supported ops: "
                              f"{', '.join(SUPPORTED_OPS)}")
        if op == "Constant":
            consts[node.output[0]] = _constant_value(node)
            continue
        args = [val(x) for x in node.input]
        datas = [x for x in args if isinstance(x, _Data)]
        if op == "Shape" and datas:  # the data's shape at run time: followed for a Reshape that keeps the batch
            a = _attrs(node)
            consts[node.output[0]] = _Shp(list(datas[0].shape)[slice(a.get("start", 0), a.get("end"))]).value()
            continue
        if any(isinstance(x, _Shp) for x in args) and not (op == "Reshape" and datas and len(args) > 1
                                                            and isinstance(args[1], _Shp)):
            if datas:
                raise NotAReLUMLP(f"{_where(node)}: computes with the shape of the data read at run time; "
                                  "export with a fixed feature size and a dynamic batch axis")
            consts[node.output[0]] = _fold_shape(node, args)
            continue
        if not datas:  # a node on constants only: fold it
            consts[node.output[0]] = _fold(node, args)
            continue
        if op not in SUPPORTED_OPS:
            hint = {"BatchNormalization": " (fold the batch norm into the preceding linear layer before exporting, "
                                          "e.g. export the model in eval mode with the batch norm fused)",
                    "Shape": " (a shape computed at run time: export with a fixed feature size and a dynamic batch axis)"}
            raise NotAReLUMLP(f"{_where(node)} is not part of a ReLU MLP{hint.get(op, '')}; supported ops: "
                              f"{', '.join(SUPPORTED_OPS)}")
        srcs = {layer_of[x] for x in node.input if x in data}
        if len(datas) > 1 or len(srcs) > 1:
            raise NotAReLUMLP(f"{_where(node)} combines {len(datas)} tensors computed from the input "
                              f"({', '.join(x for x in node.input if x in data)}): a skip connection or a "
                              "branch, not a ReLU MLP")
        d = datas[0]
        a = _attrs(node)
        out = node.output[0]
        if op == "Relu":
            if d.A is None:
                raise NotAReLUMLP(f"{_where(node)}: applied to an input of unknown size; export with a fixed feature size")
            if layer_of[node.input[0]] != len(weights):
                raise NotAReLUMLP(f"{_where(node)}: its input is not computed from the last layer")
            _check_finite(d.A, node, "folded weights")
            weights.append(d.A)
            biases.append(d.c)
            n = d.n
            data[out] = _Data(np.eye(n), np.zeros(n), d.shape)
            layer_of[out] = len(weights)
            continue
        if op in ("Gemm",):
            cval = args[2] if len(args) > 2 else None
            if isinstance(cval, _Data):
                raise NotAReLUMLP(f"{_where(node)}: its bias C is computed from the input (a skip connection)")
            new = _gemm(node, args[0], args[1], cval, a)
        elif op == "MatMul":
            x, y = args
            if isinstance(x, _Data):
                W = np.asarray(y, float)
                _check_finite(W, node, "weight matrix")
                if W.ndim != 2 or not _only_singletons(x.shape, -1) or x.shape[-1] == B:
                    raise NotAReLUMLP(f"{_where(node)}: data of shape {x.shape} times a weight of shape {W.shape} is not "
                                      "a layer (expected (batch, n) @ (n, m))")
                new = _matmul(x, W.T, node, x.shape[:-1] + (W.shape[1],))
            else:
                W = np.asarray(x, float)
                _check_finite(W, node, "weight matrix")
                if W.ndim != 2 or len(y.shape) not in (1, 2) or (len(y.shape) == 2 and y.shape[1] not in (B, 1)):
                    raise NotAReLUMLP(f"{_where(node)}: a weight of shape {W.shape} times data of shape {y.shape} is not "
                                      "a layer (expected (m, n) @ (n, batch))")
                new = _matmul(y, W, node, (W.shape[0],) + y.shape[1:])
        elif op in ("Add", "Sub", "Mul", "Div"):
            first = isinstance(args[0], _Data)
            K = args[1] if first else args[0]
            K = np.asarray(K, float)
            _check_finite(K, node, "constant")
            k = _broadcast_const(K, d, node)
            if op == "Add":
                new = _shift(d, k, node)
            elif op == "Sub":
                new = _shift(d, -k, node) if first else _shift(_scale(d, -np.ones(1), node), k, node)
            elif op == "Mul":
                new = _scale(d, k, node)
            else:
                if not first:
                    raise NotAReLUMLP(f"{_where(node)}: divides a constant by the data, which is not affine")
                if np.any(k == 0):
                    raise ValueError(f"{_where(node)}: divides by zero")
                new = _scale(d, 1.0 / k, node)
        elif op == "Neg":
            new = _scale(d, -np.ones(1), node)
        elif op == "Scaler":  # ai.onnx.ml, skl2onnx's StandardScaler: (x - offset) * scale
            if "offset" not in a or "scale" not in a:
                raise NotAReLUMLP(f"{_where(node)}: a Scaler needs both its offset and its scale attributes "
                                  "(onnxruntime refuses it without them); give both")
            off, sc = (np.asarray(a[k], float).ravel() for k in ("offset", "scale"))
            if off.size != sc.size:
                raise NotAReLUMLP(f"{_where(node)}: its offset ({off.size} values) and scale ({sc.size} values) differ in "
                                  "length (onnxruntime refuses it); give as many offsets as scales")
            _check_finite(off, node, "offset")
            _check_finite(sc, node, "scale")
            new = _scale(_shift(d, -_broadcast_const(off, d, node), node), _broadcast_const(sc, d, node), node)
        else:
            new = _Data(d.A, d.c, _shape_op(node, op, d, args, a), d.k)
        data[out] = new
        layer_of[out] = layer_of[node.input[0] if node.input[0] in data else next(x for x in node.input if x in data)]
    oname = g.output[0].name
    if oname not in data:
        raise NotAReLUMLP(f"the graph's output {oname!r} is not computed from its input {inputs[0].name!r}")
    d = data[oname]
    if d.A is None:
        raise NotAReLUMLP(f"cannot resolve the size of input {inputs[0].name!r}: no layer fixes it")
    if layer_of[oname] != len(weights):
        raise NotAReLUMLP(f"the graph's output {oname!r} does not come from the last ReLU layer (a branch)")
    if not (np.all(np.isfinite(d.A)) and np.all(np.isfinite(d.c))):
        raise ValueError(f"the last layer, folded up to the output {oname!r}, contains NaN or inf: fix the exported model")
    if B in d.shape and (d.shape[0] != B or sum(1 for s in d.shape[1:] if s != 1) > 1):
        raise NotAReLUMLP(f"the graph's output {oname!r} has the layout {d.shape} ('batch' is the batch axis); flnotes reads "
                          "a network whose output is (batch, m) (or (batch, 1, ..., m)): transpose or reshape the output "
                          "before exporting")
    _check_types(model)
    weights.append(d.A)
    biases.append(d.c)
    n_in = weights[0].shape[1]
    info = dict(input=inputs[0].name, output=oname,
                input_shape=tuple(n_in if s is None else s for s in in_shape), output_shape=d.shape)
    return weights, biases, info


def _shape_op(node, op: str, d: _Data, args: list, a: dict) -> tuple:
    """The tracked shape after a shape-only node."""
    S = d.shape
    if op in ("Identity", "Cast"):
        to = a.get("to")
        if op == "Cast" and to in _REDUCED:
            raise NotAReLUMLP(f"{_where(node)}: casts the data to {_REDUCED[to]}, which rounds every value to a few digits "
                              "(the MILP's eps would not cover it); remove the cast or cast to float32/float64")
        if op == "Cast" and to not in _FULL_FLOATS:
            raise NotAReLUMLP(f"{_where(node)}: casts the data to a non-float type ({to}); remove the cast")
        return S
    if op == "Dropout":
        if len(args) > 2 and args[2] is not None and bool(np.asarray(args[2]).ravel()[0]):
            raise NotAReLUMLP(f"{_where(node)}: dropout in training mode is random; export the model in eval mode")
        if len(node.output) > 1 and node.output[1]:
            raise NotAReLUMLP(f"{_where(node)}: its mask output is used; export the model in eval mode")
        return S
    if op == "Flatten":
        r, axis = len(S), int(a.get("axis", 1))
        if not -r <= axis <= r:
            raise NotAReLUMLP(f"{_where(node)}: axis={axis} is outside [-{r}, {r}] for a tensor of rank {r}")
        axis = axis + r if axis < 0 else axis
        head, tail = S[:axis], S[axis:]
        if B in tail:
            if head:
                raise NotAReLUMLP(f"{_where(node)}: flattens the batch axis together with the features ({S}, axis={axis})")
            return (1, B) if all(s in (1, B) for s in tail) and len(tail) == 1 else _refuse_batch(node, S)
        if head and not all(s in (1, B) for s in head):
            raise NotAReLUMLP(f"{_where(node)}: keeps feature axes {head} in front ({S}, axis={axis})")
        return ((B if B in head else 1), None if None in tail else (_features(tail) if tail else 1))
    if op == "Reshape":
        if len(args) < 2 or isinstance(args[1], _Data) or args[1] is None:
            raise NotAReLUMLP(f"{_where(node)}: its target shape is computed from the data at run time and cannot be "
                              "resolved; export with a constant shape (e.g. a Flatten)")
        if isinstance(args[1], _Shp):
            if None in args[1].v:
                raise NotAReLUMLP(f"{_where(node)}: its target shape uses a feature size not known before run time; "
                                  "export with a fixed feature size")
            return _reshape(d, args[1].v, int(a.get("allowzero", 0)), node)
        return _reshape(d, np.asarray(args[1]).ravel(), int(a.get("allowzero", 0)), node)
    if op in ("Squeeze", "Unsqueeze"):
        axes = a.get("axes")
        if axes is None and len(args) > 1 and args[1] is not None:
            if isinstance(args[1], _Data):
                raise NotAReLUMLP(f"{_where(node)}: its axes are computed from the data")
            axes = np.asarray(args[1]).ravel().tolist()
        if op == "Squeeze":
            if axes is None:
                axes = [i for i, s in enumerate(S) if s == 1]
            axes = _axes(node, axes, len(S))
            if any(S[i] != 1 for i in axes):
                raise NotAReLUMLP(f"{_where(node)}: squeezes an axis of size other than 1 in {S}")
            return tuple(s for i, s in enumerate(S) if i not in axes)
        if axes is None:
            raise NotAReLUMLP(f"{_where(node)}: Unsqueeze without axes")
        out = list(S)
        for x in _axes(node, axes, len(S) + len(axes)):
            out.insert(x, 1)
        return tuple(out)
    if op == "Transpose":
        return _transpose(S, a.get("perm"), node)
    raise NotAReLUMLP(f"{_where(node)} is not part of a ReLU MLP")  # pragma: no cover


def _refuse_batch(node, S):
    raise NotAReLUMLP(f"{_where(node)}: flattens the batch axis of {S}")


def _fold_shape(node, args: list) -> Union[_Shp, Array]:
    """Follow the batch size through the shape arithmetic torch writes for ``x.view(x.size(0), -1)``."""
    op, a = node.op_type, _attrs(node)
    x = args[0]

    def refuse(why: str):
        return NotAReLUMLP(f"{_where(node)}: {why}; flnotes follows the batch size only through Shape -> Gather -> "
                           "Unsqueeze -> Concat -> Reshape (as torch writes x.view(x.size(0), -1)): export with a "
                           "constant target shape")

    if op in ("Identity", "Cast"):
        if op == "Cast" and int(a.get("to", 0)) not in (6, 7):  # int32, int64
            raise refuse("casts a shape to a non-integer type")
        return x
    if op == "Gather" and isinstance(x, _Shp) and not isinstance(args[1], _Shp):
        idx = np.asarray(args[1])
        if int(a.get("axis", 0)) != 0 or idx.ndim > 1 or x.scalar:
            raise refuse("gathers a shape along an axis other than 0")
        n = len(x.v)
        if np.any((idx < -n) | (idx >= n)):
            raise refuse(f"gathers index {idx.tolist()} of a shape of {n} entries")
        return _Shp([x.v[int(i)] for i in idx.ravel()], scalar=idx.ndim == 0).value()
    if op in ("Unsqueeze", "Squeeze") and isinstance(x, _Shp):
        axes = a.get("axes") if "axes" in a else (np.asarray(args[1]).ravel().tolist() if len(args) > 1 else None)
        if op == "Unsqueeze" and x.scalar and [int(v) for v in (axes or [])] in ([0], [-1]):
            return _Shp(x.v)
        if op == "Squeeze" and not x.scalar and len(x.v) == 1 and (axes is None or [int(v) for v in axes] in ([0], [-1])):
            return _Shp(x.v, scalar=True)
        raise refuse(f"{op.lower()}s a shape in an unexpected way")
    if op == "Concat":
        if int(a.get("axis", 0)) not in (0, -1):
            raise refuse("concatenates shapes along an axis other than 0")
        v = []
        for y in args:
            if isinstance(y, _Shp):
                if y.scalar:
                    raise refuse("concatenates a scalar")
                v += y.v
            else:
                y = np.asarray(y)
                if y.ndim != 1 or y.dtype.kind not in "iu":
                    raise refuse("concatenates a shape with a non-integer vector")
                v += [int(t) for t in y]
        return _Shp(v).value()
    raise refuse("computes with the batch size read at run time")


def _fold(node, args: list) -> Array:
    """Evaluate a node whose inputs are all constants (shape arithmetic, scalings computed in the graph)."""
    op, a = node.op_type, _attrs(node)
    x = [None if v is None else np.asarray(v) for v in args]
    if op == "Identity" and x:
        return x[0]
    if op == "Cast":
        return _cast(node, x[0], int(a.get("to", 0)))
    if op == "Div" and x[0].dtype.kind in "iu" and x[1].dtype.kind in "iu":  # integer division truncates toward zero
        if np.any(x[1] == 0):
            raise NotAReLUMLP(f"{_where(node)}: an integer division by zero in the constants")
        q = np.abs(x[0]) // np.abs(x[1])
        return (np.where((x[0] < 0) != (x[1] < 0), -q, q)).astype(np.result_type(x[0], x[1]))
    if op in ("Add", "Sub", "Mul", "Div"):
        return {"Add": np.add, "Sub": np.subtract, "Mul": np.multiply, "Div": np.divide}[op](x[0], x[1])
    if op in ("Neg", "Sqrt", "Reciprocal", "Abs", "Exp", "Log"):
        return {"Neg": np.negative, "Sqrt": np.sqrt, "Reciprocal": np.reciprocal, "Abs": np.abs, "Exp": np.exp,
                "Log": np.log}[op](x[0])
    if op in ("Max", "Min", "Sum") and all(v is not None for v in x):
        return {"Max": np.maximum, "Min": np.minimum, "Sum": np.add}[op].reduce(np.broadcast_arrays(*x))
    if op == "Pow":
        if x[0].dtype.kind in "iu" and x[1].dtype.kind in "iu" and np.any(x[1] < 0):
            raise NotAReLUMLP(f"{_where(node)}: an integer raised to a negative integer power; make the constants float")
        return np.power(x[0], x[1]).astype(x[0].dtype)
    if op == "Transpose":
        perm = a.get("perm")
        if perm is not None and sorted(int(p) for p in perm) != list(range(x[0].ndim)):
            raise NotAReLUMLP(f"{_where(node)}: perm {list(perm)} is not a permutation of the {x[0].ndim} axes")
        return np.transpose(x[0], perm)
    if op == "Reshape":
        t = [s if (s != 0 or a.get("allowzero", 0)) else x[0].shape[i] for i, s in enumerate(x[1].astype(int).tolist())]
        return x[0].reshape(t)
    if op == "Concat":
        return np.concatenate(x, axis=int(a.get("axis", 0)))
    if op in ("Unsqueeze", "Squeeze"):
        axes = a.get("axes") if "axes" in a else (x[1].ravel().tolist() if len(x) > 1 and x[1] is not None else None)
        if op == "Squeeze":
            if axes is None:
                return np.squeeze(x[0])
            axes = _axes(node, axes, x[0].ndim)
            if any(x[0].shape[i] != 1 for i in axes):
                raise NotAReLUMLP(f"{_where(node)}: squeezes an axis of size other than 1 in {x[0].shape}")
            return np.squeeze(x[0], axis=tuple(axes))
        if axes is None:
            raise NotAReLUMLP(f"{_where(node)}: Unsqueeze without axes")
        out = x[0]
        for v in _axes(node, axes, out.ndim + len(axes)):
            out = np.expand_dims(out, v)
        return out
    raise NotAReLUMLP(f"{_where(node)} on constants only is not folded by flnotes; simplify the graph "
                      "(e.g. with onnx's constant folding) before importing")


def _cast(node, x: Array, to: int) -> Array:
    """``Cast`` of a constant, to the ``to`` type exactly as onnxruntime does (float to int truncates toward zero)."""
    onnx = _onnx()
    names = {1: np.float32, 11: np.float64, 10: np.float16, 9: np.bool_, 2: np.uint8, 3: np.int8, 4: np.uint16,
             5: np.int16, 6: np.int32, 7: np.int64, 12: np.uint32, 13: np.uint64}
    if to not in names:
        raise NotAReLUMLP(f"{_where(node)}: casts a constant to {onnx.helper.tensor_dtype_to_string(to) if to else to}, "
                          "which flnotes does not fold; cast to a float or an integer type")
    dt = np.dtype(names[to])
    if dt.kind in "iub" and x.dtype.kind == "f":
        if not np.all(np.isfinite(x)):
            raise NotAReLUMLP(f"{_where(node)}: casts NaN or inf to an integer type (undefined); fix the constants")
        if dt.kind != "b":
            info = np.iinfo(dt)
            if np.any(np.trunc(x) < info.min) or np.any(np.trunc(x) > info.max):
                raise NotAReLUMLP(f"{_where(node)}: casts a constant out of the range of {dt}")
            return np.trunc(x).astype(dt)
    return x.astype(dt)


def write(weights: Sequence[Array], biases: Sequence[Array], *, dtype: str = "float64", opset: int = 17,
          input_name: str = "zv", output_name: str = "u", graph_name: str = "ReLUNet",
          doc: str = "") -> Any:
    """An ``onnx.ModelProto`` of eq. (recur): ``Gemm`` (``transB=1``, the paper's ``W^k`` rows) and ``Relu`` per layer.

    The input is ``(batch, n_in)`` with a dynamic batch axis, the output
    ``(batch, n_out)``. ``dtype="float64"`` keeps the weights bit for bit
    (``from_onnx(to_onnx(net))`` is ``net``); ``"float32"`` is what most
    tools default to, rounded; a weight that overflows float32 (to inf) or
    underflows it (a nonzero weight to 0) is a ``ValueError``.
    """
    onnx = _onnx()
    from onnx import TensorProto, helper, numpy_helper

    if dtype not in ("float64", "float32"):
        raise ValueError(f"dtype must be 'float64' (exact) or 'float32', got {dtype!r}")
    elem = TensorProto.DOUBLE if dtype == "float64" else TensorProto.FLOAT
    nodes, inits, x = [], [], input_name
    K = len(weights)
    for k, (W, b) in enumerate(zip(weights, biases), start=1):
        for what, v in ((f"W^{k}", np.asarray(W, float)), (f"b^{k}", np.asarray(b, float))):
            with np.errstate(over="ignore", under="ignore"):
                r = v.astype(np.float32) if dtype == "float32" else v
            bad = ~np.isfinite(r) | ((r == 0) & (v != 0))
            if np.any(bad):
                i = tuple(int(j) for j in np.argwhere(bad)[0])
                raise ValueError(f"{what}{list(i)} = {v[i]!r} overflows or underflows in {dtype} (it would be written as "
                                 f"{r[i]!r}): write the network with dtype='float64', or rescale it")
        inits.append(numpy_helper.from_array(np.asarray(W, dtype), f"W{k}"))
        inits.append(numpy_helper.from_array(np.asarray(b, dtype), f"b{k}"))
        y = output_name if k == K else f"a{k}"
        nodes.append(helper.make_node("Gemm", [x, f"W{k}", f"b{k}"], [y], name=f"layer{k}", transB=1))
        if k < K:
            nodes.append(helper.make_node("Relu", [y], [f"y{k}"], name=f"relu{k}"))
            x = f"y{k}"
    n_in, n_out = np.shape(weights[0])[1], np.shape(weights[-1])[0]
    graph = helper.make_graph(nodes, graph_name, [helper.make_tensor_value_info(input_name, elem, ["N", n_in])],
                              [helper.make_tensor_value_info(output_name, elem, ["N", n_out])], initializer=inits,
                              doc_string=doc)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)], producer_name="flnotes")
    model.ir_version = min(model.ir_version, 8)
    onnx.checker.check_model(model, full_check=True)
    return model


# --------------------------------------------------------------------------- the shipped example
#: the example network shipped in ``flnotes/data`` (``<name>.onnx`` and ``<name>.onnx.json``; the checksum of the
#: file is ``file_sha256``, not the ``sha256`` of a reference network, so :func:`flnotes.reference.reference_names`
#: does not list it)
EXAMPLE = "MSD-sklearn"


def _sha256_file(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def example(name: str = EXAMPLE, folder: Optional[Path] = None) -> tuple[Path, dict]:
    """The path of a shipped ``.onnx`` example and what is known about it, after checking its checksum."""
    import json

    from .reference import DATA_DIR

    folder = DATA_DIR if folder is None else Path(folder)
    path, meta = folder / f"{name}.onnx", folder / f"{name}.onnx.json"
    if not (path.exists() and meta.exists()):
        have = sorted(p.name[:-len(".onnx")] for p in folder.glob("*.onnx"))
        raise FileNotFoundError(f"no shipped ONNX example {name!r}; shipped: {have}")
    about = json.loads(meta.read_text())
    digest = _sha256_file(path)
    if digest != about["file_sha256"]:
        raise ValueError(f"the shipped ONNX example {path.name} does not match its checksum ({digest[:12]}... != "
                         f"{about['file_sha256'][:12]}...): the file is damaged; reinstall flnotes")
    return path, about


def write_msd_example(folder: Optional[Path] = None, widths: Sequence[int] = (20, 20, 20),
                      n_per_axis: Sequence[int] = (30, 60, 30), max_iter: int = 3000, seed: int = 2) -> Path:
    """Write the book's example of a network trained elsewhere: ``EXAMPLE.onnx`` and its ``.onnx.json``.

    A scikit-learn pipeline ``StandardScaler`` + ``MLPRegressor`` (ReLU,
    L-BFGS) fitted to the mass-spring-damper's ``Phi`` on a grid, with its
    inputs in the order ``(v, z1, z2)`` (not the system's ``[z, v]``), and
    exported by skl2onnx in float32 as any scikit-learn user would. Chapter 2
    reads it with an ``input_map``. The book and the tests read the shipped
    file; this rewrites it (training is not reproducible across machines, so
    the weights, and the checksum, change):
    ``python -c "from flnotes._onnx import write_msd_example as w; print(w())"``.
    """
    import json
    import warnings as _w

    import sklearn
    import skl2onnx
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    from threadpoolctl import threadpool_limits

    from .network import uniform_grid
    from .reference import DATA_DIR
    from .systems import msd

    folder = DATA_DIR if folder is None else Path(folder)
    sysm, order = msd(), [2, 0, 1]  # the pipeline's input i is variable order[i] of [z1, z2, v]
    X = uniform_grid(sysm.lo, sysm.hi, n_per_axis)
    y = sysm.phi_stacked(X)[:, 0]
    pipe = make_pipeline(StandardScaler(), MLPRegressor(hidden_layer_sizes=tuple(widths), solver="lbfgs", max_iter=max_iter,
                                                        max_fun=10 * max_iter, tol=1e-10, random_state=seed))
    with _w.catch_warnings(), threadpool_limits(limits=1):
        _w.simplefilter("ignore", ConvergenceWarning)
        pipe.fit(X[:, order], y)
    model = convert_sklearn(pipe, initial_types=[("input", FloatTensorType([None, 3]))], target_opset={"": 17, "ai.onnx.ml": 3})
    model.doc_string = "MSD Phi(z, v) fitted by a scikit-learn pipeline (StandardScaler, MLPRegressor); inputs (v, z1, z2)"
    path = folder / f"{EXAMPLE}.onnx"
    path.write_bytes(model.SerializeToString())
    about = dict(name=EXAMPLE, file_sha256=_sha256_file(path), system="MSD", inputs=["v", "z1", "z2"], outputs=["u"],
                 input_map=order, producer=f"skl2onnx {skl2onnx.__version__}", dtype="float32",
                 model="make_pipeline(StandardScaler(), MLPRegressor(relu, lbfgs))",
                 settings=dict(widths=list(widths), n_per_axis=list(n_per_axis), max_iter=max_iter, seed=seed),
                 n_iter=int(pipe[-1].n_iter_), versions=dict(scikit_learn=sklearn.__version__, skl2onnx=skl2onnx.__version__))
    (folder / f"{EXAMPLE}.onnx.json").write_text(json.dumps(about, indent=1, sort_keys=True) + "\n")
    return path
