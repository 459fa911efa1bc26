"""ONNX in and out (ReLUNet.from_onnx, to_onnx), checked against onnxruntime.

The test models are written node by node in the patterns the exporters write
for a ReLU MLP (torch.onnx.export: Flatten + Gemm with transB=1, or MatMul +
Add; tf2onnx: MatMul + Add with Keras' normalization as Sub/Div, Identity at
the end; skl2onnx: the converter itself on an MLPRegressor and on a pipeline
with a StandardScaler), plus the Gemm variants (transA, transB, alpha, beta,
weights as the first operand). Every imported network's forward pass equals
onnxruntime's on 10,000 random points to 1e-6 relative (to the largest
output, since a float32 graph rounds every product), and the big-M MILP of
eq. (MIP_general) with the input fixed, node bounds over the whole box, has
its minimum and its maximum of every output at onnxruntime's value too.
"""
import functools
import warnings

import numpy as np
import pytest

import flnotes as fl

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from flnotes._onnx import NotAReLUMLP  # noqa: E402

N_POINTS = 10_000
RTOL = 1e-6
F32, F64 = TensorProto.FLOAT, TensorProto.DOUBLE


def _layers(n_in=3, widths=(8, 6), n_out=1, seed=0):
    rng = np.random.default_rng(seed)
    sizes = (n_in, *widths, n_out)
    return ([rng.normal(size=(b, a)) / np.sqrt(a) for a, b in zip(sizes[:-1], sizes[1:])],
            [0.3 * rng.normal(size=b) for b in sizes[1:]])


class _G:
    """A small graph builder: initializers by value, nodes by op."""

    def __init__(self, elem=F32):
        self.nodes, self.inits, self.elem, self.k = [], [], elem, 0
        self.dtype = helper.tensor_dtype_to_np_dtype(elem)

    def const(self, value, as_node=False):
        self.k += 1
        name = f"c{self.k}"
        arr = np.asarray(value, self.dtype) if np.asarray(value).dtype.kind == "f" else np.asarray(value)
        if as_node:  # a Constant node, as tf2onnx and torch sometimes write
            self.nodes.append(helper.make_node("Constant", [], [name], name=f"const{self.k}",
                                               value=numpy_helper.from_array(arr, name)))
        else:
            self.inits.append(numpy_helper.from_array(arr, name))
        return name

    def op(self, op, inputs, name=None, **attrs):
        self.k += 1
        out = f"t{self.k}"
        self.nodes.append(helper.make_node(op, list(inputs), [out], name=name or f"/{op}_{self.k}", **attrs))
        return out

    def model(self, x_name, x_shape, y, y_shape, opset=17):
        g = helper.make_graph(self.nodes, "mlp", [helper.make_tensor_value_info(x_name, self.elem, x_shape)],
                              [helper.make_tensor_value_info(y, self.elem, y_shape)], initializer=self.inits)
        m = helper.make_model(g, opset_imports=[helper.make_opsetid("", opset)])
        m.ir_version = 8
        onnx.checker.check_model(m)
        return m


def torch_gemm(W, b, elem=F32, flatten=True):
    """torch.onnx.export of nn.Sequential(Flatten, Linear, ReLU, ..., Linear): Gemm with transB=1."""
    g = _G(elem)
    x = g.op("Flatten", ["input"], name="/0/Flatten", axis=1) if flatten else "input"
    for k, (Wk, bk) in enumerate(zip(W, b)):
        x = g.op("Gemm", [x, g.const(Wk), g.const(bk)], name=f"/{2 * k + 1}/Gemm", alpha=1.0, beta=1.0, transB=1)
        if k < len(W) - 1:
            x = g.op("Relu", [x], name=f"/{2 * k + 2}/Relu")
    return g.model("input", ["batch_size", W[0].shape[1]], x, ["batch_size", W[-1].shape[0]])


def torch_matmul(W, b, elem=F32):
    """torch.onnx.export (dynamo) of the same: MatMul with the transposed weight, then Add of the bias."""
    g = _G(elem)
    x = "input"
    for k, (Wk, bk) in enumerate(zip(W, b)):
        x = g.op("Add", [g.op("MatMul", [x, g.const(Wk.T)]), g.const(bk)], name=f"linear_{k}")
        if k < len(W) - 1:
            x = g.op("Relu", [x], name=f"relu_{k}")
    return g.model("input", ["s0", W[0].shape[1]], x, ["s0", W[-1].shape[0]])


def tf2onnx_keras(W, b, x_mean, x_var, elem=F32, const_nodes=True):
    """tf2onnx of Keras Sequential([Normalization, Dense(relu), ..., Dense]): Sub/Div, MatMul + Add, Identity."""
    g = _G(elem)
    x = g.op("Sub", ["dense_input", g.const(x_mean, const_nodes)], name="sequential/normalization/sub")
    if const_nodes:  # the standard deviation computed in the graph from constants, sqrt(max(var, eps))
        std = g.op("Sqrt", [g.op("Max", [g.const(x_var, True), g.const([1e-7], True)], name="normalization/Maximum")],
                   name="normalization/Sqrt")
    else:
        std = g.const(np.sqrt(x_var))
    x = g.op("Div", [x, std], name="sequential/normalization/truediv")
    for k, (Wk, bk) in enumerate(zip(W, b)):
        x = g.op("MatMul", [x, g.const(Wk.T)], name=f"sequential/dense_{k}/MatMul")
        x = g.op("Add", [x, g.const(bk)], name=f"sequential/dense_{k}/BiasAdd")  # the bias second ...
        if k < len(W) - 1:
            x = g.op("Relu", [x], name=f"sequential/dense_{k}/Relu")
    x = g.op("Identity", [x], name="Identity")
    return g.model("dense_input", ["unk__6", W[0].shape[1]], x, ["unk__6", W[-1].shape[0]])


def gemm_variants(W, b, elem=F64):
    """Gemm in every orientation: transA on transposed data, weights as the first operand, alpha and beta;
    the bias before the data in an Add; a Reshape and Unsqueeze/Squeeze of the vector; output scaling by Mul/Add."""
    g = _G(elem)
    x = g.op("Reshape", ["x", g.const(np.array([0, -1], np.int64))], name="reshape_in")
    x = g.op("Transpose", [x], name="to_columns", perm=[1, 0])  # (n, batch)
    # layer 1: Gemm(A = data^T, transA=1), weight (n, m) untransposed, alpha/beta scaled
    x = g.op("Gemm", [x, g.const(W[0].T / 2.0), g.const(b[0] / 4.0)], name="gemm_transA", transA=1, alpha=2.0, beta=4.0)
    x = g.op("Relu", [x], name="relu1")
    # layer 2: weights first: Gemm(W, data, transB=1): (m, n) @ (n, batch) -> (m, batch), bias (m, 1)
    x = g.op("Gemm", [g.const(W[1]), x, g.const(b[1][:, None])], name="gemm_weights_first", transB=1)
    x = g.op("Relu", [x], name="relu2")
    x = g.op("Gemm", [g.const(W[2].T), x], name="gemm_transA_const", transA=1)  # no C: the bias comes as an Add
    x = g.op("Add", [g.const(b[2][:, None]), x], name="bias_first")  # (m, batch)
    x = g.op("Transpose", [x], name="to_rows", perm=[1, 0])
    x = g.op("Unsqueeze", [x, g.const(np.array([1], np.int64))], name="unsq")
    x = g.op("Squeeze", [x, g.const(np.array([1], np.int64))], name="sq")
    x = g.op("Mul", [x, g.const([3.0])], name="out_scale")
    x = g.op("Add", [x, g.const([-0.5])], name="out_offset")
    return g.model("x", ["N", W[0].shape[1]], x, ["N", W[-1].shape[0]])


@functools.lru_cache(maxsize=None)
def _skl_mlp(n_in=3, widths=(10, 8), seed=0, scaler=False):
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, (400, n_in)) * np.arange(1, n_in + 1)
    y = np.sin(X[:, 0]) + X[:, 1] * X[:, -1] / 4
    mlp = MLPRegressor(hidden_layer_sizes=widths, solver="lbfgs", max_iter=60, random_state=seed)
    model = make_pipeline(StandardScaler(), mlp) if scaler else mlp
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return model.fit(X, y)


def skl2onnx_model(model, n_in, elem=F32):
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import DoubleTensorType, FloatTensorType

    t = FloatTensorType if elem == F32 else DoubleTensorType
    return convert_sklearn(model, initial_types=[("input", t([None, n_in]))])


def run_ort(model, X):
    """onnxruntime's output for the rows of X, as (N, n_out) (the input fed as the graph declares it)."""
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    inp = sess.get_inputs()[0]
    dtype = {"tensor(double)": np.float64, "tensor(float16)": np.float16}.get(inp.type, np.float32)
    feed = X.astype(dtype).reshape((len(X),) + (1,) * (len(inp.shape) - 2) + (X.shape[1],))  # (N, 1, n) if declared so
    Y = sess.run(None, {inp.name: feed})[0]
    return np.asarray(Y, float).reshape(len(X), -1), X.astype(dtype).astype(float)


def assert_same_as_ort(net, model, n_in, seed=0, scale=2.0):
    """Forward pass == onnxruntime's on 10,000 random points, to 1e-6 relative; big-M MILP == it at fixed inputs."""
    X = np.random.default_rng(seed).uniform(-scale, scale, (N_POINTS, n_in))
    Y_ort, Xr = run_ort(model, X)  # Xr: the points as the runtime saw them (rounded to float32 if the graph is)
    Y = net(Xr)
    rel = np.abs(Y - Y_ort) / np.abs(Y_ort).max()  # relative to the output's size (float32 graphs round each product)
    assert rel.max() <= RTOL, f"forward pass differs from onnxruntime by {rel.max():.1e} relative"
    lo, hi = np.full(n_in, -scale), np.full(n_in, scale)
    form = fl.bigm_form(net, fl.fbbt(net, lo, hi))  # node bounds over the box: the binaries are free
    for x, y in zip(Xr[:3], Y_ort[:3]):
        lo_out, hi_out = _milp_extremes(form, x)
        assert np.all(np.abs(lo_out - y) <= RTOL * np.abs(Y_ort).max()), (lo_out, y)
        assert np.all(np.abs(hi_out - y) <= RTOL * np.abs(Y_ort).max()), (hi_out, y)
    return rel.max()


def _milp_extremes(form, x):
    """Min and max of every output of the big-M program of eq. (MIP_general) with the input fixed to x (HiGHS)."""
    from scipy.optimize import Bounds, LinearConstraint, milp

    lb, ub = form.lb.copy(), form.ub.copy()
    lb[form.x], ub[form.x] = x, x
    cons = [LinearConstraint(form.A_eq, form.b_eq, form.b_eq), LinearConstraint(form.A_ub, -np.inf, form.b_ub)]
    out = np.zeros((2, len(form.out)))
    for i, j in enumerate(form.out):
        for row, sign in ((0, 1.0), (1, -1.0)):
            c = np.zeros(form.n)
            c[j] = sign
            res = milp(c, integrality=form.integrality, bounds=Bounds(lb, ub), constraints=cons)
            assert res.status == 0, res.message
            out[row, i] = res.x[j]
    return out


# ----------------------------------------------------------------- exporters' patterns
@pytest.mark.parametrize("elem", [F32, F64])
@pytest.mark.parametrize("flatten", [True, False])
def test_torch_gemm_pattern(elem, flatten):
    W, b = _layers(3, (8, 6), 1, seed=1)
    model = torch_gemm(W, b, elem, flatten)
    net = fl.ReLUNet.from_onnx(model)
    assert net.widths == (8, 6) and (net.n_in, net.n_out) == (3, 1)
    assert_same_as_ort(net, model, 3)


def test_torch_matmul_pattern_several_outputs():
    W, b = _layers(4, (7, 7, 5), 2, seed=2)
    model = torch_matmul(W, b)
    net = fl.ReLUNet.from_onnx(model.SerializeToString())  # bytes work as well as a model
    assert net.widths == (7, 7, 5) and net.n_out == 2
    assert_same_as_ort(net, model, 4)


@pytest.mark.parametrize("const_nodes", [True, False])
def test_tf2onnx_pattern_folds_the_input_normalization(const_nodes):
    W, b = _layers(3, (9, 9), 1, seed=3)
    mean, var = np.array([0.5, -1.0, 2.0]), np.array([4.0, 0.25, 9.0])
    model = tf2onnx_keras(W, b, mean, var, const_nodes=const_nodes)
    net = fl.ReLUNet.from_onnx(model)
    assert net.widths == (9, 9), "the normalization is folded into the first layer, not a layer of its own"
    assert_same_as_ort(net, model, 3, scale=3.0)


def test_matmul_on_columns_three_d_input_and_negated_output():
    """Input (N, 1, n) flattened; MatMul with the weights first on transposed data; u = c - y through Sub and Neg."""
    W, b = _layers(3, (6, 6), 1, seed=12)
    g = _G(F64)
    x = g.op("Flatten", ["x"], name="flatten", axis=1)
    x = g.op("Transpose", [x], name="cols", perm=[1, 0])
    for k, (Wk, bk) in enumerate(zip(W, b)):
        x = g.op("Add", [g.op("MatMul", [g.const(Wk), x], name=f"mm{k}"), g.const(bk[:, None])], name=f"add{k}")
        if k < len(W) - 1:
            x = g.op("Relu", [x], name=f"relu{k}")
    x = g.op("Transpose", [x], name="rows", perm=[1, 0])
    x = g.op("Neg", [g.op("Sub", [g.const([2.0]), x], name="two_minus")], name="neg")  # y - 2
    model = g.model("x", ["N", 1, 3], x, ["N", 1])
    net = fl.ReLUNet.from_onnx(model)
    assert net.widths == (6, 6)
    assert_same_as_ort(net, model, 3)
    np.testing.assert_allclose(net(np.ones((1, 3))), fl.ReLUNet(W, b)(np.ones((1, 3))) - 2.0, rtol=1e-12)


def test_gemm_in_every_orientation_and_output_scaling():
    W, b = _layers(3, (6, 5), 2, seed=4)
    model = gemm_variants(W, b)
    net = fl.ReLUNet.from_onnx(model)
    assert net.widths == (6, 5)
    assert_same_as_ort(net, model, 3)


@pytest.mark.parametrize("elem", [F32, F64])
@pytest.mark.parametrize("scaler", [False, True])
def test_skl2onnx_mlp_regressor(elem, scaler):
    model = _skl_mlp(3, (10, 8), scaler=scaler)
    onx = skl2onnx_model(model, 3, elem)
    net = fl.ReLUNet.from_onnx(onx)
    assert net.widths == (10, 8)
    assert_same_as_ort(net, onx, 3, scale=4.0)
    X = np.random.default_rng(5).uniform(-4, 4, (500, 3))
    tol = 1e-4 if elem == F32 else 1e-10
    np.testing.assert_allclose(net(X)[:, 0], model.predict(X), rtol=tol, atol=tol)


def test_input_order_and_scaling_mapped_explicitly():
    """A network trained on (v, z1, z2) in standardized units, mapped to the system's [z1, z2, v]."""
    W, b = _layers(3, (8, 8), 1, seed=6)
    model = torch_gemm(W, b, F64)  # the graph itself knows nothing of the scaling, it is done outside
    raw = fl.ReLUNet.from_onnx(model)
    offset, scale = np.array([0.3, -0.2, 1.0]), np.array([2.0, 5.0, 0.5])  # of (v, z1, z2)
    u_offset, u_scale = 0.7, 3.0
    perm = [2, 0, 1]  # network input i is variable perm[i] of [z1, z2, v]
    M = np.diag(1 / scale) @ np.eye(3)[perm]
    net = fl.ReLUNet.from_onnx(model, input_map=(M, -offset / scale), output_map=([u_scale], [u_offset]))
    ZV = np.random.default_rng(7).uniform(-3, 3, (N_POINTS, 3))
    Y_ort, _ = run_ort(model, (ZV[:, perm] - offset) / scale)
    np.testing.assert_allclose(net(ZV), u_offset + u_scale * Y_ort, rtol=1e-9, atol=1e-9)
    # a permutation alone
    np.testing.assert_allclose(fl.ReLUNet.from_onnx(model, input_map=perm)(ZV), raw(ZV[:, perm]), rtol=1e-12, atol=1e-12)
    assert net.widths == raw.widths


@pytest.mark.parametrize("bad,match", [
    ([0, 1], "not a permutation"), ([0, 0, 1], "not a permutation"), ([0, 1, 3], "not a permutation"),
    ([0.0, 1.0, 2.0], "permutation"), ((np.eye(2), np.zeros(2)), "shape"), ((np.eye(3), [0, np.nan, 0]), "NaN"),
])
def test_bad_input_map(bad, match):
    W, b = _layers(3, (4,), 1)
    with pytest.raises(ValueError, match=match):
        fl.ReLUNet(W, b).mapped(input_map=bad)


def test_bad_output_map():
    W, b = _layers(3, (4,), 1)
    with pytest.raises(ValueError, match="output_map"):
        fl.ReLUNet(W, b).mapped(output_map=np.ones(2))
    with pytest.raises(ValueError, match=r"shape \(m, 1\)"):
        fl.ReLUNet(W, b).mapped(output_map=(np.ones((1, 2)), [0.0]))


def test_symbolic_feature_size_is_resolved_by_the_first_layer():
    W, b = _layers(3, (5,), 1, seed=8)
    model = torch_gemm(W, b, F64, flatten=False)
    model.graph.input[0].type.tensor_type.shape.dim[1].dim_param = "features"
    net = fl.ReLUNet.from_onnx(model)
    assert net.n_in == 3
    assert_same_as_ort(net, model, 3)


# ----------------------------------------------------------------- round trip
@pytest.mark.parametrize("name", ["MSD", "Quad-1D"])
def test_to_onnx_round_trip_is_exact_and_runs_in_onnxruntime(name, tmp_path):
    net = fl.paper_net(name)[0]
    path = tmp_path / f"{name}.onnx"
    model = net.to_onnx(path)
    onnx.checker.check_model(onnx.load(str(path)), full_check=True)
    back = fl.ReLUNet.from_onnx(path)
    assert back.widths == net.widths
    assert all(np.array_equal(a, c) for a, c in zip(back.W + back.b, net.W + net.b)), "float64 round trip is bit for bit"
    system = fl.paper.system(name)
    X = np.random.default_rng(9).uniform(system.lo, system.hi, (N_POINTS, net.n_in))
    Y_ort, _ = run_ort(model, X)
    np.testing.assert_allclose(Y_ort, net(X), rtol=1e-12, atol=1e-12)
    m32 = net.to_onnx(dtype="float32")
    onnx.checker.check_model(m32)
    back32 = fl.ReLUNet.from_onnx(m32)
    assert all(np.array_equal(a, np.float32(c)) for a, c in zip(back32.W + back32.b, net.W + net.b)), "float32: rounded weights"
    with pytest.raises(ValueError, match="dtype"):
        net.to_onnx(dtype="float16")


# ----------------------------------------------------------------- refused
def _hidden_op(op, **attrs):
    """The torch pattern with the first activation replaced by ``op``."""
    W, b = _layers(3, (4, 4), 1)
    model = torch_gemm(W, b, F64, flatten=False)
    node = next(n for n in model.graph.node if n.op_type == "Relu")
    node.op_type = op
    node.attribute.extend(helper.make_attribute(k, v) for k, v in attrs.items())
    return model, node.name


@pytest.mark.parametrize("op,attrs", [("Tanh", {}), ("Sigmoid", {}), ("LeakyRelu", {"alpha": 0.01}), ("Softplus", {})])
def test_other_activations_are_refused_by_name(op, attrs):
    model, name = _hidden_op(op, **attrs)
    with pytest.raises(NotAReLUMLP, match=rf"node '{name}' \({op}\) is not part of a ReLU MLP"):
        fl.ReLUNet.from_onnx(model)


def test_skip_connection_is_refused():
    W, b = _layers(3, (4, 4), 1)
    g = _G(F64)
    h1 = g.op("Relu", [g.op("Gemm", ["x", g.const(W[0]), g.const(b[0])], transB=1)], name="relu1")
    h2 = g.op("Relu", [g.op("Gemm", [h1, g.const(W[1]), g.const(b[1])], transB=1)], name="relu2")
    s = g.op("Add", [h1, h2], name="residual")
    y = g.op("Gemm", [s, g.const(W[2]), g.const(b[2])], transB=1)
    with pytest.raises(NotAReLUMLP, match=r"node 'residual' \(Add\) combines 2 tensors .*skip connection"):
        fl.ReLUNet.from_onnx(g.model("x", ["N", 3], y, ["N", 1]))


def test_unfused_batch_norm_is_refused():
    W, b = _layers(3, (4,), 1)
    g = _G(F64)
    x = g.op("Gemm", ["x", g.const(W[0]), g.const(b[0])], transB=1)
    x = g.op("BatchNormalization", [x, g.const(np.ones(4)), g.const(np.zeros(4)), g.const(np.zeros(4)), g.const(np.ones(4))],
             name="bn1")
    y = g.op("Gemm", [g.op("Relu", [x]), g.const(W[1]), g.const(b[1])], transB=1)
    with pytest.raises(NotAReLUMLP, match=r"node 'bn1' \(BatchNormalization\).*fold the batch norm"):
        fl.ReLUNet.from_onnx(g.model("x", ["N", 3], y, ["N", 1]))


def _view_batch(W, b, second, gather_index=0, shape_op=None, swap=False):
    """torch's x.view(x.size(0), -1) with dynamic axes: Shape -> Gather -> Unsqueeze -> Concat([batch, second]) -> Reshape."""
    g = _G(F64)
    shp = g.op("Shape", ["x"], name="/Shape")
    n0 = g.op("Gather", [shp, g.const(np.array(gather_index, np.int64))], name="/Gather", axis=0)
    if shape_op is not None:
        n0 = shape_op(g, n0)
    parts = [g.op("Unsqueeze", [n0, g.const(np.array([0], np.int64))], name="/Unsqueeze"),
             g.const(np.array([second], np.int64))]
    tgt = g.op("Concat", parts[::-1] if swap else parts, name="/Concat", axis=0)
    x = g.op("Reshape", ["x", tgt], name="/Reshape")
    y = g.op("Gemm", [g.op("Relu", [g.op("Gemm", [x, g.const(W[0]), g.const(b[0])], transB=1)]), g.const(W[1]),
                      g.const(b[1])], transB=1)
    return g.model("x", ["N", 1, 3], y, ["N", 1])


@pytest.mark.parametrize("second", [-1, 3])
def test_view_by_the_run_time_batch_size_is_read(second):
    """view(x.size(0), -1) (or the feature count) as torch.onnx.export writes it with a dynamic batch axis."""
    W, b = _layers(3, (4,), 1, seed=26)
    model = _view_batch(W, b, second)
    net = fl.ReLUNet.from_onnx(model)
    assert net.widths == (4,)
    assert_same_as_ort(net, model, 3)


@pytest.mark.parametrize("gather_index,shape_op,swap,match", [
    (1, None, False, r"node '/Reshape' \(Reshape\).*does not keep a dynamic batch axis first"),  # a fixed (1, 3)
    (0, None, True, r"node '/Reshape' \(Reshape\).*batch size at another place"),  # (3, batch)
    (0, lambda g, n: g.op("Mul", [n, g.const(np.array(2, np.int64))], name="/Mul"), False,
     r"node '/Mul' \(Mul\).*batch size read at run time"),
])
def test_other_run_time_shape_arithmetic_is_refused(gather_index, shape_op, swap, match):
    W, b = _layers(3, (4,), 1)
    with pytest.raises(NotAReLUMLP, match=match):
        fl.ReLUNet.from_onnx(_view_batch(W, b, 3, gather_index, shape_op, swap))


def test_lesser_input_layouts_and_gemm_flags_follow_onnxruntime():
    W, b = _layers(3, (5,), 1, seed=27)
    X = np.random.default_rng(28).uniform(-2, 2, (200, 3))
    ref = fl.ReLUNet(W, b)

    def ort_out(model, feed):
        sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        return sess.run(None, {"x": feed})[0].reshape(len(feed), -1)

    # an input declared (N, n, 1), flattened
    g = _G(F64)
    x = g.op("Flatten", ["x"], axis=1)
    y = g.op("Gemm", [g.op("Relu", [g.op("Gemm", [x, g.const(W[0]), g.const(b[0])], transB=1)]), g.const(W[1]),
                      g.const(b[1])], transB=1)
    model = g.model("x", ["N", 3, 1], y, ["N", 1])
    np.testing.assert_allclose(fl.ReLUNet.from_onnx(model)(X), ort_out(model, X[:, :, None]), rtol=1e-12, atol=1e-12)
    # a 1-D batch of scalars [N], unsqueezed to (N, 1)
    W1, b1 = _layers(1, (5,), 1, seed=29)
    g = _G(F64)
    x = g.op("Unsqueeze", ["x", g.const(np.array([-1], np.int64))])
    y = g.op("Gemm", [g.op("Relu", [g.op("Gemm", [x, g.const(W1[0]), g.const(b1[0])], transB=1)]), g.const(W1[1]),
                      g.const(b1[1])], transB=1)
    model = g.model("x", ["N"], y, ["N", 1])
    net = fl.ReLUNet.from_onnx(model)
    assert net.n_in == 1
    np.testing.assert_allclose(net(X[:, :1]), ort_out(model, X[:, 0]), rtol=1e-12, atol=1e-12)
    # a symbolic feature size scaled and shifted by scalars before the first layer
    g = _G(F64)
    x = g.op("Add", [g.op("Mul", ["x", g.const([0.5])]), g.const([-1.0])])
    y = g.op("Gemm", [g.op("Relu", [g.op("Gemm", [x, g.const(W[0]), g.const(b[0])], transB=1)]), g.const(W[1]),
                      g.const(b[1])], transB=1)
    model = g.model("x", ["N", "features"], y, ["N", 1])
    np.testing.assert_allclose(fl.ReLUNet.from_onnx(model)(X), ref(0.5 * X - 1.0), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ort_out(model, X), ref(0.5 * X - 1.0), rtol=1e-12, atol=1e-12)
    # Gemm's transA/transB: any nonzero value transposes, as onnxruntime reads it
    g = _G(F64)
    x = g.op("Transpose", ["x"], perm=[1, 0])
    h = g.op("Relu", [g.op("Gemm", [x, g.const(W[0]), g.const(b[0])], transA=2, transB=3)])
    y = g.op("Gemm", [h, g.const(W[1]), g.const(b[1])], transB=1)
    model = g.model("x", ["N", 3], y, ["N", 1])
    np.testing.assert_allclose(fl.ReLUNet.from_onnx(model)(X), ort_out(model, X), rtol=1e-12, atol=1e-12)


def test_non_finite_weights_are_refused_with_the_node():
    W, b = _layers(3, (4,), 1)
    W[1] = W[1].copy()
    W[1][0, 2] = np.nan
    with pytest.raises(ValueError, match=r"node '/3/Gemm' \(Gemm\).*NaN or inf"):
        fl.ReLUNet.from_onnx(torch_gemm(W, b, F64))
    b[0] = b[0].copy()
    b[0][1] = np.inf
    with pytest.raises(ValueError, match="NaN or inf"):
        fl.ReLUNet.from_onnx(tf2onnx_keras([W[0], W[0][:1]], b, np.zeros(3), np.ones(3)))


def test_several_inputs_or_outputs_are_refused(tmp_path):
    W, b = _layers(3, (4,), 1)
    model = torch_gemm(W, b, F64, flatten=False)
    model.graph.input.append(helper.make_tensor_value_info("extra", F64, ["N", 1]))
    with pytest.raises(NotAReLUMLP, match="2 inputs"):
        fl.ReLUNet.from_onnx(model)
    with pytest.raises(FileNotFoundError):
        fl.ReLUNet.from_onnx(tmp_path / "missing.onnx")
    with pytest.raises(TypeError, match="ONNX model"):
        fl.ReLUNet.from_onnx(42)


def test_network_of_the_wrong_size_meets_the_system():
    """An imported network whose input size is not (z, v) of the system is refused where it meets the system."""
    msd = fl.msd()
    W, b = _layers(4, (6,), 1, seed=10)  # 4 inputs, the MSD has (z1, z2, v)
    net = fl.ReLUNet.from_onnx(torch_gemm(W, b, F64))
    with pytest.raises(ValueError, match="3 dimensions"):
        fl.certify_error(msd, net)
    with pytest.raises(ValueError, match=r"\(z, v\) in R\^3"):
        fl.MPC(msd, net, 0.1, horizon=3, ts=0.1, Q=[1.0, 1.0], R=0.1)
    with pytest.raises(ValueError, match=r"\[z, v\] \(3 inputs\)"):
        fl.ClfCbfController(msd, net, 0.1, fl.QuadraticCLF(np.eye(2)), H=None, k=lambda z: -z.sum())


def test_from_torch_when_torch_is_installed():
    torch = pytest.importorskip("torch")
    nn = torch.nn
    torch.manual_seed(0)
    seq = nn.Sequential(nn.Flatten(), nn.Linear(3, 6), nn.ReLU(), nn.Linear(6, 4), nn.ReLU(), nn.Linear(4, 1)).double()
    net = fl.ReLUNet.from_torch(seq)
    X = np.random.default_rng(0).uniform(-2, 2, (1000, 3))
    np.testing.assert_allclose(net(X), seq(torch.from_numpy(X)).detach().numpy(), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="Tanh"):
        fl.ReLUNet.from_torch(nn.Sequential(nn.Linear(3, 4), nn.Tanh(), nn.Linear(4, 1)))


# ----------------------------------------------------------------- the book's shipped example
def test_shipped_example_is_what_onnxruntime_runs(tmp_path):
    """Chapter 2's network exported by skl2onnx: checksum checked, inputs (v, z1, z2) mapped to [z1, z2, v]."""
    from flnotes import _onnx

    path, about = fl.network.onnx_example("MSD-sklearn")
    assert about["inputs"] == ["v", "z1", "z2"] and about["input_map"] == [2, 0, 1]
    raw = fl.ReLUNet.from_onnx(str(path))
    net = fl.ReLUNet.from_onnx(path, input_map=about["input_map"])
    assert net.widths == raw.widths == tuple(about["settings"]["widths"])
    model = onnx.load(str(path))
    assert {n.op_type for n in model.graph.node} >= {"Scaler", "MatMul", "Add", "Relu"}, "skl2onnx's pattern, with a scaler"
    msd = fl.msd()
    ZV = np.random.default_rng(11).uniform(msd.lo, msd.hi, (N_POINTS, 3))
    Y_ort, Xr = run_ort(model, ZV[:, about["input_map"]])
    assert np.abs(raw(Xr) - Y_ort).max() <= RTOL * np.abs(Y_ort).max()
    np.testing.assert_allclose(net(Xr[:, [1, 2, 0]]), raw(Xr), rtol=1e-12, atol=1e-12)  # the map only reorders
    form = fl.bigm_form(net, fl.fbbt(net, msd.lo, msd.hi))
    for x in ZV[:3]:
        assert np.all(np.abs(_milp_extremes(form, x) - net(x)[0]) <= RTOL * np.abs(Y_ort).max())
    # a damaged copy is refused
    bad = tmp_path / path.name
    data = bytearray(path.read_bytes())
    data[-10] ^= 1
    bad.write_bytes(bytes(data))
    (tmp_path / f"{path.name}.json").write_text((path.parent / f"{path.name}.json").read_text())
    with pytest.raises(ValueError, match="checksum"):
        _onnx.example("MSD-sklearn", folder=tmp_path)
    with pytest.raises(FileNotFoundError, match="MSD-sklearn"):
        _onnx.example("nothing", folder=path.parent)


def _tiny(build, in_shape=("N", 3)):
    g = _G(F64)
    y = build(g)
    return g.model("x", list(in_shape), y, ["N", 1])


@pytest.mark.parametrize("build,match", [
    (lambda g: g.op("Mul", ["x", "x"], name="square"), r"node 'square' \(Mul\) combines 2 tensors"),
    (lambda g: g.op("Div", [g.const([1.0]), "x"], name="inv"), r"node 'inv' \(Div\): divides a constant by the data"),
    (lambda g: g.op("Cast", ["x"], name="to_int", to=TensorProto.INT64), r"node 'to_int' \(Cast\).*non-float"),
    (lambda g: g.op("Reshape", ["x", g.const(np.array([4, 3], np.int64))], name="fixed"), r"node 'fixed' \(Reshape\).*batch"),
])
def test_other_non_mlp_nodes_are_refused_by_name(build, match):
    with pytest.raises(NotAReLUMLP, match=match):
        fl.ReLUNet.from_onnx(_tiny(build))


def test_unresolvable_input_size_is_refused():
    model = _tiny(lambda g: g.op("Relu", ["x"], name="relu_first"), in_shape=("N", "features"))
    with pytest.raises(NotAReLUMLP, match=r"node 'relu_first' \(Relu\).*unknown size"):
        fl.ReLUNet.from_onnx(model)


# ----------------------------------------------------------------- found by an independent attack (regressions)
def _external_model(tmp_path, location="W1.bin"):
    """torch's Gemm pattern with its first weight stored in an external file next to the model."""
    from onnx.external_data_helper import set_external_data

    W, b = _layers(3, (4,), 1, seed=20)
    model = torch_gemm(W, b, F64, flatten=False)
    t = next(t for t in model.graph.initializer if t.name == model.graph.node[0].input[1])
    (tmp_path / "W1.bin").write_bytes(numpy_helper.to_array(t).astype(np.float64).tobytes())
    set_external_data(t, location)
    t.ClearField("double_data")
    t.ClearField("raw_data")
    t.data_location = TensorProto.EXTERNAL
    path = tmp_path / "net.onnx"
    path.write_bytes(model.SerializeToString())
    return model, path, W, b


def test_external_data_is_read_only_from_the_models_folder(tmp_path, monkeypatch):
    model, path, W, b = _external_model(tmp_path)
    net = fl.ReLUNet.from_onnx(path)  # a path: resolved next to the model
    assert np.array_equal(net.W[0], W[0]) and np.array_equal(net.b[0], b[0])
    other = tmp_path / "elsewhere"
    other.mkdir()
    (other / "W1.bin").write_bytes(np.full(12, 7.0).tobytes())  # a file of that name in the current directory
    monkeypatch.chdir(other)
    for given in (model, model.SerializeToString(), onnx.load(str(path), load_external_data=False)):
        with pytest.raises(NotAReLUMLP, match="external data.*pass the path"):
            fl.ReLUNet.from_onnx(given)
    _, esc, _, _ = _external_model(tmp_path, location="../W1.bin")
    with pytest.raises(NotAReLUMLP, match="outside the model's folder"):
        fl.ReLUNet.from_onnx(esc)


def _scaled_by(build, n_in=3):
    """A one-layer torch network whose input is multiplied by a constant vector computed by ``build(g)``."""
    W, b = _layers(n_in, (4,), 1, seed=21)
    g = _G(F32)
    x = g.op("Mul", ["x", build(g)], name="scale_in")
    for k, (Wk, bk) in enumerate(zip(W, b)):
        x = g.op("Gemm", [x, g.const(Wk), g.const(bk)], transB=1)
        if k < len(W) - 1:
            x = g.op("Relu", [x])
    return g.model("x", ["N", n_in], x, ["N", 1])


@pytest.mark.parametrize("to,expect", [
    (TensorProto.INT64, [2.0, -1.0, 0.0]), (TensorProto.INT32, [2.0, -1.0, 0.0]), (TensorProto.BOOL, [1.0, 1.0, 1.0]),
    (TensorProto.FLOAT16, np.float16([2.7, -1.6, 0.4]).astype(float)),
])
def test_cast_of_constants_converts_like_onnxruntime(to, expect):
    model = _scaled_by(lambda g: g.op("Cast", [g.op("Cast", [g.const([2.7, -1.6, 0.4])], to=to)], to=F32))
    net = fl.ReLUNet.from_onnx(model)
    plain = fl.ReLUNet.from_onnx(_scaled_by(lambda g: g.const(expect)))
    np.testing.assert_allclose(net.W[0], plain.W[0], rtol=0, atol=0)
    assert_same_as_ort(net, model, 3)


def test_integer_division_of_constants_truncates_toward_zero():
    model = _scaled_by(lambda g: g.op("Cast", [g.op("Div", [g.const(np.array([7, 5, -7], np.int64)),
                                                             g.const(np.array([2], np.int64))])], to=F32))
    net = fl.ReLUNet.from_onnx(model)
    plain = fl.ReLUNet.from_onnx(_scaled_by(lambda g: g.const([3.0, 2.0, -3.0])))
    np.testing.assert_array_equal(net.W[0], plain.W[0])
    assert_same_as_ort(net, model, 3)


def test_reduced_precision_data_paths_are_refused():
    W, b = _layers(3, (4,), 1, seed=22)
    g = _G(F32)
    x = g.op("Cast", [g.op("Cast", ["x"], name="to_half", to=TensorProto.FLOAT16)], name="back", to=F32)
    x = g.op("Gemm", [g.op("Relu", [g.op("Gemm", [x, g.const(W[0]), g.const(b[0])], transB=1)]), g.const(W[1]),
                      g.const(b[1])], transB=1)
    with pytest.raises(NotAReLUMLP, match=r"node 'to_half' \(Cast\): casts the data to float16"):
        fl.ReLUNet.from_onnx(g.model("x", ["N", 3], x, ["N", 1]))
    g = _G(F32)
    x = g.op("Cast", ["x"], name="to_bf16", to=TensorProto.BFLOAT16)
    x = g.op("Cast", [x], name="back", to=F32)
    x = g.op("Gemm", [x, g.const(W[0]), g.const(b[0])], transB=1)
    with pytest.raises(NotAReLUMLP, match=r"node 'to_bf16' \(Cast\): casts the data to bfloat16"):
        fl.ReLUNet.from_onnx(g.model("x", ["N", 3], x, ["N", 4]))
    half = torch_gemm(W, b, TensorProto.FLOAT16)
    assert run_ort(half, np.ones((2, 3)))[0].shape == (2, 1), "onnxruntime runs the float16 model"
    with pytest.raises(NotAReLUMLP, match="float16.*export it in float32 or float64"):
        fl.ReLUNet.from_onnx(half)


def test_flatten_at_the_rank_of_a_vector_is_a_column():
    """Flatten (axis=1) of a 1-D input (3,) gives (3, 1) in onnxruntime: features in front, refused."""
    W, b = _layers(3, (4,), 1, seed=23)
    g = _G(F64)
    x = g.op("Flatten", ["x"], name="flat", axis=1)
    x = g.op("Gemm", [x, g.const(W[0]), g.const(b[0])], transB=1)
    y = g.op("Gemm", [g.op("Relu", [x]), g.const(W[1]), g.const(b[1])], transB=1)
    model = g.model("x", [3], y, [1])
    with pytest.raises(Exception):  # onnxruntime: (3, 1) @ (3, 4)^T does not multiply
        run_ort_vector = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        run_ort_vector.run(None, {"x": np.ones(3)})
    with pytest.raises(NotAReLUMLP, match=r"node 'flat' \(Flatten\): keeps feature axes"):
        fl.ReLUNet.from_onnx(model)
    # at axis 0 the vector becomes a row (1, 3): a single sample, read as such
    g = _G(F64)
    x = g.op("Flatten", ["x"], name="flat", axis=0)
    x = g.op("Gemm", [x, g.const(W[0]), g.const(b[0])], transB=1)
    y = g.op("Gemm", [g.op("Relu", [x]), g.const(W[1]), g.const(b[1])], transB=1)
    net = fl.ReLUNet.from_onnx(g.model("x", [3], y, [1, 1]))
    assert net.widths == (4,)


def test_dead_nodes_are_ignored():
    W, b = _layers(3, (4,), 1, seed=24)
    model = torch_gemm(W, b, F64, flatten=False)
    g = model.graph
    dead = [helper.make_node("Relu", ["input"], ["dead_in"], name="dead_relu_in"),
            helper.make_node("Sigmoid", ["dead_in"], ["dead_sig"], name="dead_sigmoid"),
            helper.make_node("Relu", [g.output[0].name], ["dead_out"], name="dead_relu_out")]
    nodes = list(g.node)
    del g.node[:]
    g.node.extend([dead[0], dead[1]] + nodes + [dead[2]])
    onnx.checker.check_model(model)
    net = fl.ReLUNet.from_onnx(model)
    assert net.widths == (4,)
    assert_same_as_ort(net, model, 3)


def _bare(nodes, inits=(), x_shape=("N", 3), y="y", y_shape=("N", 1), elem=F64):
    g = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", elem, list(x_shape))],
                          [helper.make_tensor_value_info(y, elem, list(y_shape))], initializer=list(inits))
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    return m


@pytest.mark.parametrize("make,match", [
    (lambda W: [helper.make_node("Gemm", ["x"], ["y"], name="g1")], r"g1\b.*Gemm.*input size 1"),
    (lambda W: [helper.make_node("Gemm", ["x", "W"], [], name="g0")], r"g0\b.*Gemm.*output size 0"),
    (lambda W: [helper.make_node("Constant", [], [], name="k", value_float=1.0),
                helper.make_node("Gemm", ["x", "W"], ["y"], name="g1", transB=1)], r"name: k, type: Constant.*zero output"),
    (lambda W: [helper.make_node("MatMul", ["x", "W", "W"], ["y"], name="mm3")], r"mm3\b.*MatMul.*input size 3"),
    (lambda W: [helper.make_node("Gemm", ["x", "W"], ["h"], transB=1),
                helper.make_node("Add", ["h"], ["y"], name="add1")], r"add1\b.*Add.*input size 1"),
])
def test_malformed_models_are_refused_by_the_checker_with_the_node(make, match):
    W = numpy_helper.from_array(np.ones((1, 3)), "W")
    with pytest.raises(NotAReLUMLP, match=r"not valid ONNX.*" + match):
        fl.ReLUNet.from_onnx(_bare(make(W), [W]))


def test_integer_power_with_a_negative_exponent_is_refused():
    model = _scaled_by(lambda g: g.op("Cast", [g.op("Pow", [g.const(np.array([2, 2, 2], np.int64)),
                                                             g.const(np.array([-1], np.int64))], name="pow")], to=F32))
    with pytest.raises(NotAReLUMLP, match=r"node 'pow' \(Pow\).*negative integer power"):
        fl.ReLUNet.from_onnx(model)


def test_sparse_initializer_is_densified():
    W, b = _layers(3, (4,), 1, seed=25)
    W[0][np.abs(W[0]) < 0.4] = 0.0
    model = torch_gemm(W, b, F64, flatten=False)
    g = model.graph
    name = g.node[0].input[1]
    t = next(t for t in g.initializer if t.name == name)
    dense = numpy_helper.to_array(t)
    idx = np.flatnonzero(dense)
    sp = helper.make_sparse_tensor(numpy_helper.from_array(dense.ravel()[idx], name),
                                   numpy_helper.from_array(idx.astype(np.int64), ""), dense.shape)
    g.initializer.remove(t)
    g.sparse_initializer.append(sp)
    net = fl.ReLUNet.from_onnx(model)
    np.testing.assert_array_equal(net.W[0], W[0])
    assert_same_as_ort(net, model, 3)


@pytest.mark.parametrize("bad", ["list", "triple"])
def test_input_map_pair_given_otherwise_gets_the_documented_message(bad):
    W, b = _layers(3, (4,), 1)
    M, c = np.eye(3), np.zeros(3)
    with pytest.raises(ValueError, match=r"pair \(M, c\)"):
        fl.ReLUNet(W, b).mapped(input_map=[M, c] if bad == "list" else (M, c, c))


def test_input_shadowed_by_an_initializer_is_named():
    W, b = _layers(3, (4,), 1)
    model = torch_gemm(W, b, F64, flatten=False)
    model.graph.initializer.append(numpy_helper.from_array(np.zeros((1, 3)), "input"))
    with pytest.raises(NotAReLUMLP, match=r"\['input'\] have an initializer of the same name"):
        fl.ReLUNet.from_onnx(model)


def test_to_onnx_float32_refuses_weights_that_overflow_or_underflow():
    W, b = _layers(3, (4,), 1)
    for big in (1e39, 1e-50):
        W2 = [w.copy() for w in W]
        W2[1][0, 2] = big
        with pytest.raises(ValueError, match=r"W\^2\[0, 2\].*float32"):
            fl.ReLUNet(W2, b).to_onnx(dtype="float32")
        fl.ReLUNet(W2, b).to_onnx(dtype="float64")  # exact in float64


def test_output_map_vector_must_have_one_scale_per_output():
    W, b = _layers(3, (4,), 1)
    with pytest.raises(ValueError, match="diagonal scaling needs 1 scales"):
        fl.ReLUNet(W, b).mapped(output_map=(np.array([1.0, 2.0, 3.0]), np.zeros(3)))
    net = fl.ReLUNet(W, b).mapped(output_map=(np.array([2.0]), np.array([1.0])))
    x = np.ones((1, 3))
    np.testing.assert_allclose(net(x), 2 * fl.ReLUNet(W, b)(x) + 1)


def test_invalid_models_that_onnxruntime_rejects_are_refused():
    W, b = _layers(3, (4,), 1)
    # int64 weights in a float graph
    g = _G(F64)
    y = g.op("Gemm", ["x", g.const(np.ones((1, 3), np.int64)), g.const(b[1])], transB=1)
    with pytest.raises(NotAReLUMLP, match="type"):
        fl.ReLUNet.from_onnx(g.model("x", ["N", 3], y, ["N", 1]))
    # a Reshape shape given as floats
    g = _G(F64)
    x = g.op("Reshape", ["x", g.const(np.array([0.0, -1.0]))], name="r")
    y = g.op("Gemm", [x, g.const(W[1][:, :3]), g.const(b[1])], transB=1)
    with pytest.raises(NotAReLUMLP):
        fl.ReLUNet.from_onnx(_bare(g.nodes, g.inits, y=y))


@pytest.mark.parametrize("attrs,match", [({}, "needs both its offset and its scale"),
                                         ({"offset": [0.0, 1.0], "scale": [1.0, 2.0, 3.0]}, "differ in length"),
                                         ({"offset": [0.0], "scale": [1.0, 2.0, 3.0]}, "differ in length")])
def test_bad_scaler_is_refused(attrs, match):
    W, b = _layers(3, (4,), 1)
    g = _G(F32)
    g.nodes.append(helper.make_node("Scaler", ["x"], ["s"], name="scaler", domain="ai.onnx.ml", **attrs))
    y = g.op("Gemm", ["s", g.const(W[1][:, :3]), g.const(b[1])], transB=1)
    gr = helper.make_graph(g.nodes, "g", [helper.make_tensor_value_info("x", F32, ["N", 3])],
                           [helper.make_tensor_value_info(y, F32, ["N", 1])], initializer=g.inits)
    m = helper.make_model(gr, opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid("ai.onnx.ml", 3)])
    m.ir_version = 8
    with pytest.raises(NotAReLUMLP, match=rf"node 'scaler' \(Scaler\).*{match}"):
        fl.ReLUNet.from_onnx(m)


@pytest.mark.parametrize("layout", ["columns", "three_d"])
def test_output_not_in_batch_rows_is_refused(layout):
    W, b = _layers(3, (4,), 2)
    model = torch_gemm(W, b, F64, flatten=False)
    g = model.graph
    last = g.output[0].name
    if layout == "columns":
        g.node.append(helper.make_node("Transpose", [last], ["out"], name="t", perm=[1, 0]))
        shape = [2, "N"]
    else:
        g.node.append(helper.make_node("Unsqueeze", [last, "ax"], ["out"], name="u"))
        g.initializer.append(numpy_helper.from_array(np.array([0], np.int64), "ax"))
        shape = [1, "N", 2]
    del g.output[:]
    g.output.append(helper.make_tensor_value_info("out", F64, shape))
    with pytest.raises(NotAReLUMLP, match=r"output 'out' has the layout.*\(batch, m\)"):
        fl.ReLUNet.from_onnx(model)


@pytest.mark.parametrize("build,match", [
    (lambda g: g.op("Unsqueeze", ["x", g.const(np.array([3], np.int64))], name="u"), r"node 'u' \(Unsqueeze\): axes \[3\]"),
    (lambda g: g.op("Squeeze", ["x", g.const(np.array([5], np.int64))], name="s"), r"node 's' \(Squeeze\): axes \[5\]"),
    (lambda g: g.op("Transpose", ["x"], name="t", perm=[1, 2]), r"node 't' \(Transpose\): perm \[1, 2\]"),
    (lambda g: g.op("Mul", ["x", g.op("Unsqueeze", [g.const(np.ones(3)), g.const(np.array([2], np.int64))], name="uc")]),
     r"node 'uc' \(Unsqueeze\): axes \[2\]"),  # on constants
])
def test_out_of_range_axes_are_refused_not_wrapped(build, match):
    """onnxruntime refuses these; wrapping the axis modulo the rank would read another graph."""
    with pytest.raises(NotAReLUMLP, match=match):
        fl.ReLUNet.from_onnx(_tiny(lambda g: g.op("Gemm", [build(g), g.const(np.ones((1, 3))), g.const([0.0])], transB=1)))


def test_declared_output_shape_is_not_trusted_over_the_nodes():
    """onnxruntime runs a model whose declared output shape is wrong (it warns) and returns what the nodes compute."""
    W, b = _layers(3, (4,), 2, seed=30)
    model = torch_gemm(W, b, F64, flatten=False)
    model.graph.output[0].type.tensor_type.shape.dim[1].dim_value = 5
    net = fl.ReLUNet.from_onnx(model)
    assert net.n_out == 2
    assert_same_as_ort(net, model, 3)


def test_output_with_singleton_axes_after_the_batch_is_read():
    W, b = _layers(3, (4,), 2, seed=31)
    g = _G(F64)
    x = g.op("MatMul", ["x", g.const(W[0].T[None])], name="mm")
    x = g.op("Add", [x, g.const(b[0])])
    y = g.op("Add", [g.op("MatMul", [g.op("Relu", [x]), g.const(W[1].T)]), g.const(b[1])])
    model = g.model("x", ["N", 1, 3], y, ["N", 1, 2])
    with pytest.raises(NotAReLUMLP, match=r"node 'mm' \(MatMul\)"):  # a 3-D weight is not a layer of an MLP
        fl.ReLUNet.from_onnx(model)
    g = _G(F64)
    x = g.op("Add", [g.op("MatMul", ["x", g.const(W[0].T)]), g.const(b[0])])
    y = g.op("Add", [g.op("MatMul", [g.op("Relu", [x]), g.const(W[1].T)]), g.const(b[1])])
    model = g.model("x", ["N", 1, 3], y, ["N", 1, 2])
    net = fl.ReLUNet.from_onnx(model)
    assert net.n_out == 2
    assert_same_as_ort(net, model, 3)


def test_output_without_a_declared_shape_is_read():
    """onnxruntime runs a graph whose output declares no shape; checking the model must not refuse it."""
    W, b = _layers(3, (4,), 1, seed=32)
    model = torch_gemm(W, b, F64)
    model.graph.output[0].type.tensor_type.ClearField("shape")
    net = fl.ReLUNet.from_onnx(model)
    assert_same_as_ort(net, model, 3)


def test_external_data_in_a_constant_node_is_refused_without_a_path(tmp_path, monkeypatch):
    from onnx.external_data_helper import set_external_data

    W, b = _layers(3, (4,), 1, seed=33)
    g = _G(F64)
    y = g.op("Gemm", [g.op("Relu", [g.op("Gemm", ["x", g.const(W[0], as_node=True), g.const(b[0])], transB=1)]),
                      g.const(W[1]), g.const(b[1])], transB=1)
    model = g.model("x", ["N", 3], y, ["N", 1])
    t = model.graph.node[0].attribute[0].t
    monkeypatch.chdir(tmp_path)
    (tmp_path / "W.bin").write_bytes(np.full(12, 7.0).tobytes())
    set_external_data(t, "W.bin")
    t.ClearField("raw_data")
    t.data_location = TensorProto.EXTERNAL
    with pytest.raises(NotAReLUMLP, match="external data.*pass the path"):
        fl.ReLUNet.from_onnx(model.SerializeToString())
