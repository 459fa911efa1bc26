"""ReLU networks: weights, biases and a forward pass (eq. recur), and their training.

A network is just ``W^k``, ``b^k`` with the recursion

    y^k = sigma(W^k y^{k-1} + b^k),  k = 1..K-1,     y^K = W^K y^{K-1} + b^K

of eq. (recur). Nothing downstream depends on how it was trained.
"""
from __future__ import annotations

import hashlib
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence, Union

import numpy as np

from ._checks import as_batch, as_floats, check_box, check_int, check_number

Array = np.ndarray


class ReLUNet:
    """A feed-forward ReLU network ``Phi_NN`` as in eq. (recur).

    Parameters
    ----------
    weights
        ``[W^1, ..., W^K]`` with ``W^k`` of shape (n_k, n_{k-1}) (the paper's
        convention: rows are the neurons of layer k).
    biases
        ``[b^1, ..., b^K]`` with ``b^k`` of shape (n_k,).

    Notes
    -----
    ``K = len(weights)`` layers: ``K - 1`` hidden ReLU layers and a linear
    output layer, so the paper's "K = 4, n = 20" is ``widths == (20, 20, 20)``.
    """

    def __init__(self, weights: Sequence[Array], biases: Sequence[Array]):
        if len(weights) != len(biases) or len(weights) < 1:
            raise ValueError(f"need as many weight matrices as bias vectors (>= 1), got {len(weights)} and {len(biases)}")
        self.W: list[Array] = []
        self.b: list[Array] = []
        for k, (W, b) in enumerate(zip(weights, biases), start=1):
            W, b = np.array(as_floats(W, f"W^{k}"), ndmin=2), as_floats(b, f"b^{k}").reshape(-1)
            if W.shape[0] != b.shape[0]:
                raise ValueError(f"layer {k}: W^{k} has {W.shape[0]} rows but b^{k} has {b.shape[0]} entries")
            if self.W and W.shape[1] != self.W[-1].shape[0]:
                raise ValueError(f"layer {k}: W^{k} has {W.shape[1]} columns but layer {k - 1} has {self.W[-1].shape[0]} neurons")
            if not (np.all(np.isfinite(W)) and np.all(np.isfinite(b))):
                raise ValueError(f"layer {k}: weights or biases contain NaN or inf")
            self.W.append(W)
            self.b.append(b)

    # ------------------------------------------------------------------ sizes
    @property
    def K(self) -> int:
        """Number of layers (the paper's K): K - 1 hidden layers plus the output layer."""
        return len(self.W)

    @property
    def weights(self) -> list[Array]:
        return self.W

    @property
    def biases(self) -> list[Array]:
        return self.b

    @property
    def n_in(self) -> int:
        return self.W[0].shape[1]

    @property
    def n_out(self) -> int:
        return self.W[-1].shape[0]

    @property
    def widths(self) -> tuple[int, ...]:
        """Hidden widths ``(n_1, ..., n_{K-1})``."""
        return tuple(W.shape[0] for W in self.W[:-1])

    @property
    def n_hidden(self) -> int:
        """Number of hidden neurons ``sum_k n_k``: the binaries of one copy of eq. (MIP_general)."""
        return int(sum(self.widths))

    # --------------------------------------------------------------- forward
    def __call__(self, x: Array) -> Array:
        """Evaluate the network: (N, n_in) -> (N, n_out); (n_in,) -> (n_out,)."""
        a = as_floats(x, "x")
        y = self._forward(as_batch(a, self.n_in, "x"))[0]
        return y[0] if a.ndim == 1 else y

    def forward(self, X: Array) -> tuple[Array, list[Array]]:
        """Output (N, n_out) and the hidden pre-activations ``W^k y^{k-1} + b^k`` (each (N, n_k)) of a batch
        ``X`` (N, n_in); one point (n_in,) gives (n_out,) and (n_k,), and any leading axes are kept."""
        X = as_floats(X, "X")
        if X.ndim == 0 or X.shape[-1] != self.n_in:
            raise ValueError(f"X must have shape (N, {self.n_in}) or ({self.n_in},), got {X.shape}")
        if not np.all(np.isfinite(X)):
            raise ValueError("X contains NaN or inf")
        return self._forward(X)

    def _forward(self, X: Array) -> tuple[Array, list[Array]]:
        """:meth:`forward` on a checked (N, n_in) float array."""
        y, pre = X, []
        for W, b in zip(self.W[:-1], self.b[:-1]):
            a = y @ W.T + b
            pre.append(a)
            y = np.maximum(a, 0.0)
        return y @ self.W[-1].T + self.b[-1], pre

    def preactivations(self, x: Array) -> list[Array]:
        """Hidden pre-activations for a batch, one (N, n_k) array per hidden layer."""
        return self._forward(as_batch(x, self.n_in, "x"))[1]

    def activation_pattern(self, x: Array) -> list[Array]:
        """Which neurons are active (pre-activation > 0): the binaries ``alpha^k`` of eq. (MIP_general_c)."""
        return [a > 0 for a in self.preactivations(x)]

    # ------------------------------------------------------------ transforms
    def affine_wrapped(self, x_offset: Array, x_scale: Array, y_offset: Array, y_scale: Array) -> "ReLUNet":
        """Fold input/output scalings into the first and last layer.

        Returns the network ``x -> y_offset + y_scale * net((x - x_offset) / x_scale)``,
        which works on raw units.
        """
        xo, xs = (np.broadcast_to(as_floats(a, name), (self.n_in,)) if np.size(a) in (1, self.n_in) else
                  as_floats(a, name) for a, name in ((x_offset, "x_offset"), (x_scale, "x_scale")))
        yo, ys = (np.broadcast_to(as_floats(a, name), (self.n_out,)) if np.size(a) in (1, self.n_out) else
                  as_floats(a, name) for a, name in ((y_offset, "y_offset"), (y_scale, "y_scale")))
        for name, a, n in (("x_offset", xo, self.n_in), ("x_scale", xs, self.n_in), ("y_offset", yo, self.n_out),
                           ("y_scale", ys, self.n_out)):
            if a.shape != (n,) or not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be finite, a number or shape ({n},), got {a}")
        if np.any(xs == 0):
            raise ValueError(f"x_scale must be nonzero (the input is divided by it), got {xs}")
        W, b = [w.copy() for w in self.W], [c.copy() for c in self.b]
        W[0] = self.W[0] / xs[None, :]
        b[0] = self.b[0] - W[0] @ xo
        W[-1] = ys[:, None] * W[-1] if len(W) > 1 else ys[:, None] * W[0]
        b[-1] = ys * b[-1] + yo
        return ReLUNet(W, b)

    @classmethod
    def from_sklearn(cls, model, x_offset: Optional[Array] = None, x_scale: Optional[Array] = None,
                     y_offset: Optional[Array] = None, y_scale: Optional[Array] = None) -> "ReLUNet":
        """Import a fitted :class:`sklearn.neural_network.MLPRegressor` with ReLU activation.

        The optional affine maps are folded in (see :meth:`affine_wrapped`).
        """
        if getattr(model, "activation", None) != "relu":
            raise ValueError("only ReLU networks can be encoded as MILPs; the model uses "
                             f"activation={getattr(model, 'activation', None)!r}")
        if not hasattr(model, "coefs_"):
            raise ValueError("the MLPRegressor is not fitted yet: call model.fit(X, y) first")
        net = cls([c.T for c in model.coefs_], list(model.intercepts_))
        if any(a is not None for a in (x_offset, x_scale, y_offset, y_scale)):
            n_in, n_out = net.n_in, net.n_out
            net = net.affine_wrapped(
                np.zeros(n_in) if x_offset is None else x_offset, np.ones(n_in) if x_scale is None else x_scale,
                np.zeros(n_out) if y_offset is None else y_offset, np.ones(n_out) if y_scale is None else y_scale)
        return net

    def mapped(self, input_map=None, output_map=None) -> "ReLUNet":
        """The network on the system's variables: ``x -> D net(M x + c) + d``, folded into the first and last layer.

        A network trained elsewhere may order or scale its inputs differently
        from the system's stacked ``[z, v]`` (eq. recur's ``y^0``), or return
        ``u`` in other units. Say how, and the result takes ``[z, v]`` and
        returns ``u``; it has the same hidden layers (eq. eq-02-fold of
        chapter 2 with full matrices).

        Parameters
        ----------
        input_map
            ``None`` (the network's input is ``[z, v]``); a sequence of
            integers, a permutation: the network's input ``i`` is the
            variable ``input_map[i]`` of ``[z, v]`` (e.g. ``[2, 0, 1]`` for a
            network trained on ``(v, z1, z2)``); or a pair ``(M, c)``: the
            network's input is ``M @ [z, v] + c``, ``M`` of shape
            ``(net.n_in, n)`` for a system with ``n`` variables (a scaling of
            the inputs: ``M = diag(1 / scale)``, ``c = -offset / scale``).
        output_map
            ``None`` or a pair ``(D, d)``: ``u = D @ net(...) + d``, ``D`` of
            shape ``(m, net.n_out)`` (or a vector of ``net.n_out`` scales: a
            diagonal scaling).

        Raises
        ------
        ValueError
            An ``input_map`` that is not a permutation of ``0..net.n_in-1`` or
            a tuple ``(M, c)``, or a map of the wrong shape or with NaN or inf.
        """
        W, b = [w.copy() for w in self.W], [c.copy() for c in self.b]
        if input_map is not None:
            M, c = _input_map(input_map, self.n_in)
            b[0] = b[0] + W[0] @ c
            W[0] = W[0] @ M
        if output_map is not None:
            D, d = _output_map(output_map, self.n_out)
            W[-1], b[-1] = D @ W[-1], D @ b[-1] + d
        return ReLUNet(W, b)

    # ------------------------------------------------------------------ ONNX
    @classmethod
    def from_onnx(cls, model, input_map=None, output_map=None) -> "ReLUNet":
        """Read a ReLU MLP from an ONNX model: the graphs ``torch.onnx.export``, tf2onnx and skl2onnx write.

        ``Gemm`` (any ``transA``, ``transB``, ``alpha``, ``beta``), ``MatMul``
        and ``Add`` (either operand order), ``Relu``, ``Identity``,
        ``Flatten``/``Reshape``/``Squeeze``/``Unsqueeze`` of a vector, and
        scalings of the input and the output by ``Sub``/``Div``/``Mul``/``Add``
        with constants (initializers or ``Constant`` nodes) or by the
        ``Scaler`` skl2onnx writes for a ``StandardScaler``, folded into the
        first and last layer (eq. recur). Anything else is refused with the
        node's name and op.

        Parameters
        ----------
        model
            A path to an ``.onnx`` file (tensors in external data files are
            read from its folder only), its bytes, or an ``onnx.ModelProto``.
        input_map, output_map
            How the network's inputs and outputs relate to the system's
            ``[z, v]`` and ``u`` (see :meth:`mapped`); the default is that they
            are the same.

        Raises
        ------
        flnotes._onnx.NotAReLUMLP
            (a ``ValueError``) the graph is not a ReLU MLP (the message names
            the node and op), is not valid ONNX (``onnx.checker``, type
            inference), computes in float16 or bfloat16, or has external data
            that cannot be read from the model's folder.
        ValueError
            Non-finite weights; a bad ``input_map``/``output_map``.
        """
        from . import _onnx

        W, b, _ = _onnx.read(model)
        return cls(W, b).mapped(input_map, output_map)

    def to_onnx(self, path: Optional[Union[str, Path]] = None, dtype: str = "float64"):
        """Write the network as an ONNX model: ``Gemm`` + ``Relu`` per layer, input ``(batch, n_in)``.

        Any ONNX tool (onnxruntime, Netron, the MILP libraries that read ONNX)
        opens it. ``dtype="float64"`` keeps the weights exactly, so
        ``ReLUNet.from_onnx(net.to_onnx())`` has the same ``W^k, b^k``;
        ``"float32"`` rounds them (a weight that overflows or underflows
        float32 is a ``ValueError``). The model passes ``onnx.checker``.

        Returns
        -------
        onnx.ModelProto
            The model (also saved to ``path`` when one is given).
        """
        from . import _onnx

        model = _onnx.write(self.W, self.b, dtype=dtype, doc=repr(self))
        if path is not None:
            Path(path).write_bytes(model.SerializeToString())
        return model

    @classmethod
    def from_torch(cls, module, input_map=None, output_map=None) -> "ReLUNet":
        """Import a PyTorch ``nn.Sequential`` of ``nn.Linear`` and ``nn.ReLU`` (``nn.Flatten``, ``nn.Identity``,
        ``nn.Dropout`` are skipped).

        PyTorch is never a dependency of flnotes: this works when it happens to
        be installed. ``input_map``, ``output_map`` as in :meth:`mapped`.
        """
        try:
            import torch.nn as nn
        except ImportError as exc:
            raise ImportError("from_torch needs PyTorch, which flnotes does not install; without it, export the model "
                              "with torch.onnx.export and read it with ReLUNet.from_onnx") from exc
        if not isinstance(module, nn.Sequential):
            raise TypeError(f"give an nn.Sequential of Linear and ReLU layers, got {type(module).__name__}")
        W, b, last = [], [], "relu"
        for i, layer in enumerate(module):
            if isinstance(layer, (nn.Flatten, nn.Identity, nn.Dropout)):
                continue
            if isinstance(layer, nn.Linear) and last == "relu":
                W.append(layer.weight.detach().cpu().double().numpy())
                bias = layer.bias
                b.append(np.zeros(layer.out_features) if bias is None else bias.detach().cpu().double().numpy())
                last = "linear"
            elif isinstance(layer, nn.ReLU) and last == "linear" and i < len(module) - 1:
                last = "relu"
            else:
                raise ValueError(f"layer {i} ({type(layer).__name__}) of the Sequential is not part of a ReLU MLP: expected "
                                 "Linear, ReLU, Linear, ..., Linear (ReLU between two Linear layers)")
        if last != "linear":
            raise ValueError("the Sequential must end with an nn.Linear layer (the output layer of eq. recur)")
        return cls(W, b).mapped(input_map, output_map)

    # ------------------------------------------------------------- save/load
    def save(self, path: Union[str, Path]) -> None:
        """Save to ``.npz`` (``W1..WK``, ``b1..bK``)."""
        arrays = {f"W{k + 1}": W for k, W in enumerate(self.W)} | {f"b{k + 1}": b for k, b in enumerate(self.b)}
        np.savez(path, K=self.K, **arrays)

    @classmethod
    def load(cls, path: Union[str, Path]) -> "ReLUNet":
        """Load a network saved by :meth:`save`."""
        with np.load(path) as d:
            K = int(d["K"])
            return cls([d[f"W{k}"] for k in range(1, K + 1)], [d[f"b{k}"] for k in range(1, K + 1)])

    def __repr__(self) -> str:
        return f"ReLUNet(n_in={self.n_in}, widths={self.widths}, n_out={self.n_out})"


def fingerprint(net: ReLUNet) -> str:
    """A digest of the network's layer shapes, weights and biases (two networks share it only when they are the same
    function written the same way)."""
    h = hashlib.sha256()
    for W, b in zip(net.W, net.b):  # the shapes too: the same numbers in other layers are another network
        h.update(repr((W.shape, b.shape)).encode())
        h.update(np.ascontiguousarray(W, float).tobytes())
        h.update(np.ascontiguousarray(b, float).tobytes())
    return h.hexdigest()


def onnx_example(name: str = "MSD-sklearn") -> tuple[Path, dict]:
    """A network trained outside flnotes, shipped as an ``.onnx`` file (chapter 2), with what is known about it.

    ``"MSD-sklearn"``: the mass-spring-damper's ``Phi`` fitted by a
    scikit-learn pipeline (``StandardScaler``, ``MLPRegressor``) on inputs
    ordered ``(v, z1, z2)`` and exported by skl2onnx in float32. The file's
    SHA-256 checksum is checked against the one shipped beside it.

    Returns
    -------
    path, about
        The file, and its description (``inputs``, ``outputs``, ``input_map``
        for :meth:`ReLUNet.from_onnx`, ``producer``, ``settings``, ``file_sha256``).
    """
    from . import _onnx

    return _onnx.example(name)


def _input_map(input_map, n_net: int) -> tuple[Array, Array]:
    """``(M, c)`` of :meth:`ReLUNet.mapped` from a permutation or a pair, validated."""
    if isinstance(input_map, (tuple, list)) and any(np.ndim(x) == 2 for x in input_map if _is_array_like(x)):
        if not (isinstance(input_map, tuple) and len(input_map) == 2 and np.ndim(input_map[0]) == 2):
            raise ValueError("input_map with a matrix must be a pair (M, c) (a tuple of two: M of shape (net.n_in, n) "
                             f"and c of shape (net.n_in,)), got a {type(input_map).__name__} of {len(input_map)}")
        M, c = as_floats(input_map[0], "input_map's M"), as_floats(input_map[1], "input_map's c").reshape(-1)
        if M.shape[0] != n_net or c.shape != (n_net,):
            raise ValueError(f"input_map = (M, c) must have M of shape ({n_net}, n) and c of shape ({n_net},) for a network "
                             f"with {n_net} inputs, got M {M.shape} and c {c.shape}")
        if not (np.all(np.isfinite(M)) and np.all(np.isfinite(c))):
            raise ValueError("input_map (M, c) contains NaN or inf")
        return M, c
    try:
        perm = np.asarray(input_map)
    except ValueError:
        perm = np.asarray(None)
    if perm.ndim == 1 and perm.dtype.kind in "iu":  # its entries as numbers: a True among integers is no index
        as_floats(input_map, "input_map")
    if perm.ndim != 1 or perm.dtype.kind not in "iu":
        raise ValueError("input_map must be a permutation (a list of integers: the network's input i is variable "
                         f"input_map[i] of [z, v]) or a pair (M, c) with M a 2-D array; got {input_map!r}")
    if sorted(perm.tolist()) != list(range(n_net)):
        raise ValueError(f"input_map {perm.tolist()} is not a permutation of 0..{n_net - 1} (the network has {n_net} inputs); "
                         "for a network that uses fewer or other variables, give input_map = (M, c)")
    return np.eye(n_net)[perm], np.zeros(n_net)


def _is_array_like(x) -> bool:
    try:
        np.asarray(x, float)
    except (TypeError, ValueError):
        return False
    return True


def _output_map(output_map, n_net: int) -> tuple[Array, Array]:
    if not (isinstance(output_map, tuple) and len(output_map) == 2):
        raise ValueError(f"output_map must be a pair (D, d): u = D @ net(...) + d, got {output_map!r}")
    D, d = as_floats(output_map[0], "output_map's D"), as_floats(output_map[1], "output_map's d").reshape(-1)
    if D.ndim == 1:  # a diagonal scaling, one scale per output (or one scale of a single output)
        if D.shape[0] != n_net:
            raise ValueError(f"output_map = (D, d) with D a vector: a diagonal scaling needs {n_net} scales (one per output "
                             f"of the network), got {D.shape[0]}; for a map to other outputs give D of shape (m, {n_net})")
        D = np.diag(D)
    if D.ndim != 2 or D.shape[1] != n_net or d.shape != (D.shape[0],):
        raise ValueError(f"output_map = (D, d) must have D of shape (m, {n_net}) (or a vector of {n_net} scales) and d of "
                         f"shape (m,), got D {np.shape(output_map[0])} and d {np.shape(output_map[1])}")
    if not (np.all(np.isfinite(D)) and np.all(np.isfinite(d))):
        raise ValueError("output_map (D, d) contains NaN or inf")
    return D, d


@dataclass
class TrainingReport:
    """What :func:`fit_relu` did and how well the result fits the grid."""

    time_s: float
    n_grid: int
    n_train: int
    n_iter: int
    widths: tuple[int, ...]
    n_per_axis: tuple[int, ...]
    grid_max_error: Array
    grid_rmse: Array
    settings: dict = field(default_factory=dict)

    def __str__(self) -> str:
        # no time: it depends on the machine that trained (``time_s`` keeps it)
        return (f"trained {self.widths} on {self.n_train:,} of {self.n_grid:,} grid points "
                f"({self.n_iter} iterations); grid max |error| = {np.array2string(self.grid_max_error, precision=4)}, "
                f"rmse = {np.array2string(self.grid_rmse, precision=4)}")


def uniform_grid(lo: Array, hi: Array, n_per_axis: Union[int, Sequence[int]]) -> Array:
    """All points of a uniform grid with ``n_per_axis`` points per axis over ``[lo, hi]``, (N, n)."""
    lo_a = as_floats(lo, "lo")
    if lo_a.ndim > 1:
        raise ValueError(f"lo must be a vector (the box's lower corner, shape (n,)), got shape {lo_a.shape}")
    lo, hi = check_box(lo_a, hi, lo_a.size)
    k = as_floats(n_per_axis, "n_per_axis")
    if k.ndim > 1 or k.size not in (1, lo.size) or not np.all(np.isfinite(k)) or np.any(k != np.round(k)) \
            or np.any(k < 2):
        raise ValueError(f"n_per_axis must be an integer >= 2, or one per axis (shape ({lo.size},)), got "
                         f"{n_per_axis!r}")
    n = np.broadcast_to(k.astype(int), lo.shape)
    axes = [np.linspace(l, h, k) for l, h, k in zip(lo, hi, n)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(lo))


def fit_relu(f: Callable[[Array], Array], lo: Array, hi: Array, widths: Sequence[int] = (20, 20, 20),
             n_per_axis: Union[int, Sequence[int]] = 30, max_train: Optional[int] = 60_000,
             max_iter: int = 3000, seed: int = 0, alpha: float = 0.0, tol: float = 1e-10,
             threads: Optional[int] = 1) -> tuple[ReLUNet, TrainingReport]:
    """Train ``Phi_NN`` by regression on a uniform grid (the paper's Sec. III-A.1 and IV).

    The scheme: sample ``f`` on the full grid of ``n_per_axis`` points per axis;
    standardize inputs and outputs; fit a scikit-learn ``MLPRegressor`` with
    ReLU hidden layers by full-batch L-BFGS (as MATLAB's ``fitrnet`` does) on
    the grid, or on a random subset of ``max_train`` grid points when the grid
    is larger (a 35^4 grid has 1.5 million points, far more than a 3x10 net
    needs; full-batch L-BFGS on all of them would take many minutes); fold the
    scaling back into the first and last layer; report the error on the whole
    grid.

    Parameters
    ----------
    f
        Function to approximate on stacked inputs, (N, n_in) -> (N, m) (for a
        system: ``system.phi_stacked``).
    lo, hi
        Training box ``T``, shape (n_in,).
    widths
        Hidden widths ``(n_1, ..., n_{K-1})``; the paper's Table 1 uses
        ``(20, 20, 20)`` (MSD) and ``(10, 10, 10)`` (Quad-1D).
    n_per_axis
        Grid points per axis ``n_s`` (30 and 35 in Table 1).
    max_train
        Train on at most this many grid points (random subset, fixed seed);
        ``None`` uses the whole grid.
    max_iter, tol, alpha
        L-BFGS iterations, tolerance, and L2 penalty (0: plain least squares).
    seed
        Seed of the initial weights and of the subset.
    threads
        Threads the BLAS and OpenMP pools may use while training (through
        :mod:`threadpoolctl`); ``None`` leaves them as they are. One thread is
        the default: the products of full-batch L-BFGS are small, and on a
        busy two-core machine more threads oversubscribe the cores and make
        the training time erratic (``make bench`` measures both).

    Returns
    -------
    net, report
        The network on raw units and a :class:`TrainingReport`.
    """
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.neural_network import MLPRegressor
    from threadpoolctl import threadpool_limits

    if not callable(f):
        hint = " (for a system, pass system.phi_stacked)" if hasattr(f, "phi_stacked") else ""
        raise TypeError(f"f must be a function (N, n_in) -> (N, m) to approximate, got {type(f).__name__}{hint}")
    lo_a = as_floats(lo, "lo")
    if lo_a.ndim > 1:
        raise ValueError(f"lo must be a vector (the box's lower corner, shape (n_in,)), got shape {lo_a.shape}")
    lo, hi = check_box(lo_a, hi, lo_a.size)
    if isinstance(widths, (str, bytes)) or not hasattr(widths, "__iter__"):
        raise ValueError(f"widths must list the hidden widths (n_1, ..., n_K-1), e.g. (20, 20, 20), got {widths!r}")
    widths = tuple(check_int(w, "each of widths", 1, "neurons of a hidden layer") for w in widths)
    if not widths:
        raise ValueError("widths must list at least one hidden width, e.g. (20, 20, 20)")
    max_iter = check_int(max_iter, "max_iter", 1, "L-BFGS iterations of the training")
    seed = check_int(seed, "seed", 0, "seed of the initial weights and of the training subset")
    if max_train is not None:
        check_int(max_train, "max_train", 1, "most grid points used for training, or None for all")
    if threads is not None:
        check_int(threads, "threads", 1, "BLAS threads of the training, or None to leave the thread pools alone")
    alpha = check_number(alpha, "alpha", "the L2 penalty of the training")
    tol = check_number(tol, "tol", "the training's tolerance")
    t0 = time.perf_counter()
    X = uniform_grid(lo, hi, n_per_axis)
    Y = as_floats(f(X), "f(X) on the training grid")
    if Y.ndim not in (1, 2) or Y.shape[0] != len(X) or Y.size == 0:
        raise ValueError(f"f must map the grid (N, n_in) = {X.shape} to values of shape (N,) or (N, m), got shape "
                         f"{Y.shape}")
    Y = Y.reshape(len(X), -1)
    if not np.all(np.isfinite(Y)):
        raise ValueError("f returned NaN or inf on the training grid: shrink the box away from singularities")
    rng = np.random.default_rng(seed)
    idx = np.arange(len(X)) if (max_train is None or len(X) <= max_train) else rng.choice(len(X), max_train, replace=False)
    x_off, x_sc = (lo + hi) / 2, np.maximum((hi - lo) / 2, 1e-12)
    y_off, y_sc = Y.mean(0), np.maximum(Y.std(0), 1e-12)
    model = MLPRegressor(hidden_layer_sizes=widths, activation="relu", solver="lbfgs", alpha=alpha,
                         max_iter=max_iter, max_fun=10 * max_iter, tol=tol, random_state=seed)
    with warnings.catch_warnings(), threadpool_limits(limits=None if threads is None else int(threads)):
        warnings.simplefilter("ignore", ConvergenceWarning)
        model.fit((X[idx] - x_off) / x_sc, ((Y[idx] - y_off) / y_sc).squeeze() if Y.shape[1] == 1 else (Y[idx] - y_off) / y_sc)
    net = ReLUNet.from_sklearn(model, x_off, x_sc, y_off, y_sc)
    err = np.abs(net(X) - Y)
    report = TrainingReport(
        time_s=time.perf_counter() - t0, n_grid=len(X), n_train=len(idx), n_iter=int(model.n_iter_),
        widths=widths, n_per_axis=tuple(np.broadcast_to(np.asarray(n_per_axis, int), lo.shape).tolist()),
        grid_max_error=err.max(0), grid_rmse=np.sqrt((err**2).mean(0)),
        settings=dict(max_train=max_train, max_iter=max_iter, seed=seed, alpha=alpha, tol=tol, threads=threads),
    )
    return net, report
