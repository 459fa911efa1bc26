"""Reference data shipped with the package: the book's trained networks and their certified error brackets.

Training a ReLU network is not reproducible across machines: the BLAS
kernels, their thread counts and the processor's floating-point paths change
the weights L-BFGS converges to, and with them ``eps``, which states are
feasible and which solver edge cases appear. So the networks every chapter
and test relies on are trained once, certified once, and committed here as
small files; every machine then computes with the same ``W^k``, ``b^k`` and
the same ``eps`` of eq. (approx_err).

One reference is two files in ``flnotes/data/``:

``<slug>.npz``
    the weights and biases ``W1..WK``, ``b1..bK`` (:meth:`ReLUNet.save`);
``<slug>.json``
    the training report, the certified bracket of ``eps`` (when there is
    one), the settings that produced both, the library versions of the
    machine that trained them, and a SHA-256 checksum of the weights.

:func:`load_reference` refuses a file whose weights do not match their
checksum. :func:`save_reference` writes a new reference (``make reference``
rewrites the book's).
"""
from __future__ import annotations

import hashlib
import json
import os
import platform
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np

from .network import ReLUNet, TrainingReport

#: Folder of the shipped reference files (package data).
DATA_DIR: Path = Path(__file__).resolve().parent / "data"


def weights_sha256(net: ReLUNet) -> str:
    """SHA-256 of the network's weights and biases (float64, little endian, layer by layer).

    Independent of how the arrays were stored (zip metadata, dtype of the
    file), so it identifies the network itself.
    """
    h = hashlib.sha256()
    for W, b in zip(net.W, net.b):
        for a in (W, b):
            a = np.ascontiguousarray(a, dtype="<f8")
            h.update(str(a.shape).encode())
            h.update(a.tobytes())
    return h.hexdigest()


@dataclass(frozen=True)
class Reference:
    """A shipped network with what is known about it.

    Attributes
    ----------
    name
        The reference's name (e.g. ``"MSD"``).
    net
        The network ``Phi_NN`` of eq. (recur).
    report
        How it was trained (:class:`flnotes.TrainingReport`).
    bracket
        The certified bracket of ``eps`` as a plain dict (``lower``, ``upper``,
        ... of :class:`flnotes.error.ErrorBracket`), or ``None``.
    meta
        Settings, library versions and checksum, as stored.
    """

    name: str
    net: ReLUNet
    report: TrainingReport
    bracket: Optional[dict]
    meta: dict


def _slug(name: str) -> str:
    """File stem of a reference: the name with anything but letters, digits, '-' and '_' replaced by '-'."""
    if not name:
        raise ValueError("a reference needs a non-empty name")
    return "".join(c if c.isalnum() or c in "-_" else "-" for c in name)


def reference_names(folder: Optional[Path] = None) -> list[str]:
    """Names of the references shipped in ``folder`` (default :data:`DATA_DIR`)."""
    folder = DATA_DIR if folder is None else Path(folder)
    metas = (json.loads(p.read_text()) for p in folder.glob("*.json"))
    return sorted(m["name"] for m in metas if "sha256" in m)


def _versions() -> dict:
    import scipy
    import sklearn
    import threadpoolctl

    pools = [dict(api=p.get("internal_api"), version=p.get("version"), threads=p.get("num_threads"))
             for p in threadpoolctl.threadpool_info()]
    return dict(python=platform.python_version(), numpy=np.__version__, scipy=scipy.__version__,
                scikit_learn=sklearn.__version__, machine=platform.machine(), blas=pools)


def _plain(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, tuple):
        return list(x)
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    return x


def save_reference(name: str, net: ReLUNet, report: TrainingReport, settings: dict,
                   bracket: Optional[Any] = None, eps_settings: Optional[dict] = None,
                   folder: Optional[Path] = None) -> Path:
    """Write the reference ``name`` (weights, report, bracket, settings, versions, checksum).

    Parameters
    ----------
    name
        Name of the reference; the files are ``<name>.npz`` and ``<name>.json``.
    net, report
        The network and its :class:`flnotes.TrainingReport`.
    settings
        The arguments of :func:`flnotes.fit_relu` that produced it.
    bracket
        Optional :class:`flnotes.error.ErrorBracket` of ``eps`` for ``net``.
    eps_settings
        The settings of the certification that produced ``bracket``.
    folder
        Where to write (default :data:`DATA_DIR`).

    Returns
    -------
    Path
        The JSON file written.
    """
    folder = DATA_DIR if folder is None else Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    slug = _slug(name)
    npz, js = folder / f"{slug}.npz", folder / f"{slug}.json"
    tmp = npz.with_name(f"{slug}.{os.getpid()}.tmp.npz")
    net.save(tmp)
    os.replace(tmp, npz)
    br = None
    if bracket is not None:
        br = {k: _plain(v) for k, v in vars(bracket).items() if k not in ("partition", "history")}
    meta = dict(name=name, sha256=weights_sha256(net), widths=list(net.widths), n_in=net.n_in, n_out=net.n_out,
                report=_plain(vars(report)), settings=_plain(settings), bracket=br,
                eps_settings=_plain(eps_settings) if eps_settings is not None else None, versions=_versions())
    js.write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")
    return js


def load_reference(name: str, folder: Optional[Path] = None) -> Reference:
    """Load the reference ``name`` and check its weights against the stored checksum.

    Raises
    ------
    FileNotFoundError
        No reference of that name is shipped (the message lists those that are).
    ValueError
        The weights do not match their checksum (a corrupted or hand-edited file).
    """
    folder = DATA_DIR if folder is None else Path(folder)
    slug = _slug(name)
    npz, js = folder / f"{slug}.npz", folder / f"{slug}.json"
    if not (npz.exists() and js.exists()):
        have = sorted(p.stem for p in folder.glob("*.json"))
        raise FileNotFoundError(f"no shipped reference network {name!r} (files {npz.name}, {js.name} in the "
                                f"package's data folder); shipped references: {have}")
    meta = json.loads(js.read_text())
    net = ReLUNet.load(npz)
    digest = weights_sha256(net)
    if digest != meta["sha256"]:
        raise ValueError(f"the shipped network {name!r} does not match its checksum ({digest[:12]}... != "
                         f"{meta['sha256'][:12]}...): the file {npz.name} is damaged; reinstall flnotes or "
                         f"rewrite the reference (make reference)")
    rep = dict(meta["report"])
    rep["grid_max_error"], rep["grid_rmse"] = np.array(rep["grid_max_error"]), np.array(rep["grid_rmse"])
    rep["widths"], rep["n_per_axis"] = tuple(rep["widths"]), tuple(rep["n_per_axis"])
    return Reference(name=name, net=net, report=TrainingReport(**rep), bracket=meta.get("bracket"), meta=meta)


def save_table(name: str, args: dict, rows: list, folder: Optional[Path] = None) -> Path:
    """Write a shipped result table ``<name>.table.json``: the rows and the arguments that produced them."""
    folder = DATA_DIR if folder is None else Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{_slug(name)}.table.json"
    path.write_text(json.dumps(dict(name=name, args=_plain(args), rows=_plain(rows), versions=_versions()),
                               indent=1, sort_keys=True) + "\n")
    return path


def load_table(name: str, args: dict, folder: Optional[Path] = None) -> Optional[list]:
    """The rows of the shipped table ``name`` if it was computed with exactly ``args``, else ``None``."""
    folder = DATA_DIR if folder is None else Path(folder)
    path = folder / f"{_slug(name)}.table.json"
    if not path.exists():
        return None
    d = json.loads(path.read_text())
    return d["rows"] if d["args"] == _plain(args) else None
