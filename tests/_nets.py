"""Small networks the tests rely on, stored with the tests (trained once, the same on every machine).

They were written by :func:`flnotes.reference.save_reference` with ``folder=tests/data``; the JSON file
beside each ``.npz`` records the :func:`flnotes.fit_relu` settings that produced it.
"""
from pathlib import Path

import numpy as np

import flnotes as fl
from flnotes.reference import load_reference

DATA = Path(__file__).resolve().parent / "data"


def test_net(name: str):
    """The stored network ``name`` (checksum verified) and its training report."""
    ref = load_reference(name, folder=DATA)
    return ref.net, ref.report


test_net.__test__ = False  # a helper, not a test


def two_msd():
    """Two MSDs side by side (``Phi = v``, two inputs) with a random 6-8-2 network of explicit weights (seed 3)."""
    A, B = fl.brunovsky([2, 2])
    rng = np.random.default_rng(3)
    W1, W2 = rng.normal(size=(8, 6)) * 0.5, rng.normal(size=(2, 8)) * 0.5
    net = fl.ReLUNet([W1, W2], [rng.normal(size=8) * 0.1, np.zeros(2)])
    sysm = fl.FLSystem("2x MSD", A, B, phi=lambda z, v: v, lo=[-5] * 4 + [-10] * 2, hi=[5] * 4 + [10] * 2,
                       u_max=[5, 5], f=lambda x, u: A @ x + B @ u, to_z=lambda x: x, to_x=lambda z: z)
    return sysm, net


def stored_integrator_case(name: str):
    """A chain of integrators (one unless the file stores ``orders``) with a stored random network (``W0, b0, W1,
    ...``), state and reference (tests/data/NAME): ``(system, network, z, z_ref)``."""
    d = np.load(DATA / name)
    sysm = fl.integrators([int(r) for r in d["orders"]] if "orders" in d else [1], d["lo"], d["hi"], d["u_max"])
    layers = sum(1 for k in d.files if k.startswith("W"))
    net = fl.ReLUNet([d[f"W{i}"] for i in range(layers)], [d[f"b{i}"] for i in range(layers)])
    return sysm, net, d["z"], d["z_ref"]
