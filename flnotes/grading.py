"""Assignments: what otter-grader does not do for this course.

The assignments are otter-grader master notebooks (``book/assignments/master/``).
``otter assign`` turns each into a students' notebook (solutions replaced by ``...``,
only the public tests, kept in the notebook's metadata) and an autograder bundle
(a zip with every test, the hidden ones included). This module adds three things:

``assign``
    Runs ``otter assign`` on every master notebook, writes the students' notebooks
    and the bundles under one folder (``make assignments``: ``_build/assignments``)
    and refreshes the students' pages of the book (``book/assignments/a*.ipynb``,
    shown without being executed, since their answer cells are empty).
``grade``
    Grades one submission against a bundle with the tests *outside* the student's
    reach. ``otter run`` runs the tests inside the kernel that ran the student's
    cells, so a student cell can replace otter's checker or its results; here the
    tests are read from the bundle before any student code runs, the submission
    is executed alone in a fresh folder by a kernel under a memory and a time
    limit, and the tests run in this (the grader's) process. The test code sees the
    student's names through proxies: a student function is called in the kernel
    and only its return value (numbers, arrays, tuples, lists, dicts, strings)
    comes back, as JSON. Whatever the kernel does, it can only change the values
    the student's functions return; the comparison with the instructor's
    reference, the points and the score are computed here.
``instructor-toc``
    The table of contents of the instructor edition of the book: the students'
    pages replaced by the master notebooks (``make book-instructor``).

Command line::

    python -m flnotes.grading assign book/assignments/master _build/assignments --book-dir book/assignments
    python -m flnotes.grading grade -a _build/assignments/autograder/a1_derive_phi-autograder.zip submission.ipynb
    python -m flnotes.grading instructor-toc _toc.yml _build/instructor_toc.yml
"""
from __future__ import annotations

import argparse
import ast
import builtins
import importlib
import json
import math
import os
import re
import secrets
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np
from nbclient.exceptions import DeadKernelError

__all__ = [
    "ROOT",
    "MASTER_DIR",
    "assign",
    "assign_all",
    "student_page",
    "load_bundle_tests",
    "GradeReport",
    "grade",
    "instructor_toc",
    "main",
]

#: the checkout's top folder and the master notebooks in it
ROOT = Path(__file__).resolve().parent.parent
MASTER_DIR = ROOT / "book" / "assignments" / "master"

#: modules a submission may import under any name (``np``, ``plt``, ``fl``): the tests see
#: the grader's own copy of them, imported here, never an object from the kernel
TRUSTED_MODULES = ("numpy", "scipy", "matplotlib", "math", "cmath", "itertools", "functools", "flnotes",
                   "cvxpy", "highspy", "pyscipopt", "daqp")

_BUILTIN_NAMES = frozenset(dir(builtins))

#: largest answer (characters of JSON) accepted from one call of a student function
MAX_ANSWER_CHARS = 20_000_000


# ----------------------------------------------------------------------------------
# otter assign: students' notebooks and autograder bundles
def _otter_cmd() -> list[str]:
    return [sys.executable, "-m", "otter"]


def assign(master: str | Path, out_dir: str | Path, *, run_tests: bool = True) -> tuple[Path, Path]:
    """Run ``otter assign`` on one master notebook.

    Writes ``out_dir/student/<name>.ipynb`` (the students' version),
    ``out_dir/autograder/<name>-autograder.zip`` (the bundle with all the tests) and
    ``out_dir/solution/<name>.ipynb`` (the reference solution as a submission would
    look, for the instructor) and returns the first two paths. With ``run_tests`` otter first runs the master notebook and
    its tests, so a reference solution that fails its own tests stops here.
    """
    master, out_dir = Path(master).resolve(), Path(out_dir).resolve()
    if not master.is_file() or master.suffix != ".ipynb":
        raise ValueError(f"master={master} is not a notebook file (.ipynb)")
    name = master.stem
    with tempfile.TemporaryDirectory(prefix=f"otter-assign-{name}-") as tmp:
        cmd = _otter_cmd() + ["assign", str(master), tmp]
        if not run_tests:
            cmd.append("--no-run-tests")
        proc = subprocess.run(cmd, cwd=master.parent, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"otter assign failed on {master.name}:\n{proc.stdout}\n{proc.stderr}")
        zips = sorted(Path(tmp, "autograder").glob("*.zip"))
        if len(zips) != 1:
            raise RuntimeError(f"otter assign wrote {len(zips)} bundles for {master.name}, expected 1")
        (out_dir / "student").mkdir(parents=True, exist_ok=True)
        (out_dir / "autograder").mkdir(parents=True, exist_ok=True)
        (out_dir / "solution").mkdir(parents=True, exist_ok=True)
        shutil.copy2(Path(tmp, "autograder", master.name), out_dir / "solution" / master.name)
        student = out_dir / "student" / master.name
        bundle = out_dir / "autograder" / f"{name}-autograder.zip"
        shutil.copy2(Path(tmp, "student", master.name), student)
        shutil.copy2(zips[0], bundle)
    return student, bundle


def student_page(student_nb: str | Path, page: str | Path) -> Path:
    """Write the book's page of a students' notebook: no outputs, not executed by the build.

    The answer cells of a students' notebook are ``...``, so the book shows it as it
    is (notebook metadata ``mystnb.execution_mode: off``) instead of running it, and
    nbmake runs it with errors allowed (``execution.allow_errors``): the cells after
    an empty answer raise.
    """
    import nbformat

    nb = nbformat.read(student_nb, as_version=4)
    for cell in nb.cells:
        cell.pop("id", None)
        if cell.cell_type == "code":
            cell.outputs, cell.execution_count = [], None
    nb.metadata["mystnb"] = {"execution_mode": "off"}
    nb.metadata["execution"] = {"allow_errors": True}
    nb.nbformat_minor = 4
    page = Path(page)
    page.write_text(nbformat.writes(nb), encoding="utf-8")
    return page


def assign_all(master_dir: str | Path, out_dir: str | Path, book_dir: str | Path | None = None,
               *, run_tests: bool = True) -> list[tuple[Path, Path]]:
    """:func:`assign` every ``a*.ipynb`` of ``master_dir``; refresh the book's students' pages."""
    masters = sorted(Path(master_dir).glob("a*.ipynb"))
    if not masters:
        raise FileNotFoundError(f"no master notebooks (a*.ipynb) in {master_dir}")
    written = []
    for m in masters:
        student, bundle = assign(m, out_dir, run_tests=run_tests)
        if book_dir is not None:
            student_page(student, Path(book_dir) / m.name)
        written.append((student, bundle))
    return written


# ----------------------------------------------------------------------------------
# reading the bundle (before any student code runs)
def load_bundle_tests(autograder: str | Path) -> tuple[list, dict]:
    """The otter test files of an autograder bundle, parsed without executing them.

    Returns ``(tests, config)``: a list of ``otter.test_files.OKTestFile`` (public and
    hidden cases) in name order and the bundle's ``otter_config.json``.
    """
    from otter.test_files.ok_test import OKTestFile

    path = Path(autograder)
    if not zipfile.is_zipfile(path):
        raise ValueError(f"autograder={path} is not a zip file written by otter assign")
    tests = []
    with zipfile.ZipFile(path) as zf:
        names = sorted(n for n in zf.namelist() if n.startswith("tests/") and n.endswith(".py"))
        config = json.loads(zf.read("otter_config.json")) if "otter_config.json" in zf.namelist() else {}
        for n in names:
            tree = ast.parse(zf.read(n).decode("utf-8"), filename=n)
            spec = None
            for node in tree.body:
                if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "test" for t in node.targets):
                    spec = ast.literal_eval(node.value)
            if spec is None:
                raise ValueError(f"{path.name}:{n} is not an OK-format otter test (no `test = {{...}}`)")
            tests.append(OKTestFile.from_spec(spec, path=n))
    if not tests:
        raise ValueError(f"autograder={path} holds no tests (tests/*.py)")
    return tests, config


# ----------------------------------------------------------------------------------
# values crossing between the kernel and the grader: JSON with arrays and tuples
_KERNEL_HELPER = r'''
def __flnotes_grading__(request):
    import json, math
    import numpy
    def enc(x, depth=0):
        if depth > 20:
            raise TypeError("nested too deep")
        if x is None or isinstance(x, (bool, str)):
            return x
        if isinstance(x, (int, float, numpy.integer, numpy.floating, numpy.bool_)):
            x = x.item() if hasattr(x, "item") else x
            if isinstance(x, float) and not math.isfinite(x):
                return {"__float__": repr(x)}
            return x
        if isinstance(x, numpy.ndarray):
            if x.dtype.kind not in "biuf":
                raise TypeError(f"an array of dtype {x.dtype}")
            return {"__nd__": enc(x.tolist(), depth + 1), "kind": x.dtype.kind, "shape": list(x.shape)}
        if isinstance(x, tuple):
            return {"__tuple__": [enc(v, depth + 1) for v in x]}
        if isinstance(x, list):
            return [enc(v, depth + 1) for v in x]
        if isinstance(x, dict):
            return {"__dict__": [[enc(k, depth + 1), enc(v, depth + 1)] for k, v in x.items()]}
        raise TypeError(f"an object of type {type(x).__name__}")
    def dec(x):
        if isinstance(x, list):
            return [dec(v) for v in x]
        if isinstance(x, dict):
            if "__nd__" in x:
                kind = {"b": bool, "i": int, "u": int, "f": float}[x["kind"]]
                return numpy.array(dec(x["__nd__"]), dtype=kind).reshape(x["shape"])
            if "__tuple__" in x:
                return tuple(dec(v) for v in x["__tuple__"])
            if "__float__" in x:
                return float(x["__float__"])
            return {dec(k): dec(v) for k, v in x["__dict__"]}
        return x
    req = json.loads(request)
    g = globals()
    out = {}
    try:
        if req["op"] == "names":
            names = {}
            for k, v in list(g.items()):
                if k.startswith("_") or k in ("In", "Out", "get_ipython", "exit", "quit", "open") or isinstance(v, type):
                    continue
                if type(v).__name__ == "module":
                    names[k] = {"module": str(getattr(v, "__name__", ""))}
                    continue
                if callable(v):
                    names[k] = {"callable": True}
                else:
                    try:
                        names[k] = {"callable": False, "value": enc(v)}
                    except TypeError:
                        pass
            out = {"ok": names}
        else:
            fn = g[req["name"]]
            args = dec(req["args"])
            kwargs = dec(req["kwargs"])
            try:
                value = fn(*args, **kwargs)
            except BaseException as exc:
                out = {"raised": f"{type(exc).__name__}: {exc}"}
            else:
                try:
                    out = {"ok": enc(value)}
                except TypeError as exc:
                    out = {"raised": f"TypeError: {req['name']} returned {exc}, which cannot be graded "
                                     "(return numbers, arrays, tuples, lists, dicts or strings)"}
    except BaseException as exc:
        out = {"raised": f"{type(exc).__name__}: {exc}"}
    return req["nonce"] + json.dumps(out) + req["nonce"]
'''


def _enc(x: Any, depth: int = 0) -> Any:
    """Grader side of the JSON protocol (same encoding as the kernel's helper)."""
    if depth > 20:
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
        return {"__nd__": _enc(x.tolist(), depth + 1), "kind": x.dtype.kind, "shape": list(x.shape)}
    if isinstance(x, tuple):
        return {"__tuple__": [_enc(v, depth + 1) for v in x]}
    if isinstance(x, list):
        return [_enc(v, depth + 1) for v in x]
    if isinstance(x, dict):
        return {"__dict__": [[_enc(k, depth + 1), _enc(v, depth + 1)] for k, v in x.items()]}
    raise TypeError(f"cannot send an object of type {type(x).__name__} to the kernel")


_KINDS = {"b": bool, "i": np.int64, "u": np.int64, "f": np.float64}


def _dec(x: Any) -> Any:
    if isinstance(x, list):
        return [_dec(v) for v in x]
    if isinstance(x, dict):
        if "__nd__" in x:
            kind = x.get("kind")
            if kind not in _KINDS:
                raise ValueError(f"array of unknown kind {kind!r} from the kernel")
            return np.array(_dec(x["__nd__"]), dtype=_KINDS[kind]).reshape([int(s) for s in x["shape"]])
        if "__tuple__" in x:
            return tuple(_dec(v) for v in x["__tuple__"])
        if "__float__" in x:
            text = str(x["__float__"])
            if text not in ("nan", "inf", "-inf"):
                raise ValueError(f"bad float {text!r} from the kernel")
            return float(text)
        if "__dict__" in x:
            return {_dec(k) if not isinstance(k, list) else tuple(k): _dec(v) for k, v in x["__dict__"]}
        raise ValueError("malformed value from the kernel")
    if isinstance(x, (bool, int, float, str)) or x is None:
        return x
    raise ValueError(f"malformed value of type {type(x).__name__} from the kernel")


class StudentCodeError(Exception):
    """A student function raised, returned something that cannot be graded, or the kernel is gone."""


# ----------------------------------------------------------------------------------
# the kernel that runs the submission
def _last_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[-1][:200] if lines else ""


class _Kernel:
    """The submission's notebook executed cell by cell in its own kernel process."""

    def __init__(self, nb, cwd: str, cell_timeout: int, memory_mb: Optional[int]):
        from nbclient import NotebookClient

        self.nb = nb
        self.client = NotebookClient(nb, timeout=cell_timeout, kernel_name="python3", allow_errors=True,
                                     resources={"metadata": {"path": cwd}})
        self.memory_mb = memory_mb
        self.limits: list[str] = []
        self.cell_errors: list[str] = []
        self.dead = ""

    def __enter__(self):
        self.client.create_kernel_manager()
        # one thread per numerical library: grading time does not depend on the machine's load
        env = dict(os.environ, **{k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")})
        self.client.start_new_kernel(env=env)
        self.client.start_new_kernel_client()
        self._limit_memory()
        return self

    def __exit__(self, *exc):
        try:
            self.client._cleanup_kernel()
        finally:
            return False

    def _limit_memory(self) -> None:
        if self.memory_mb is None:
            return
        import resource

        pid = getattr(getattr(self.client.km, "provisioner", None), "pid", None)
        if pid is None or not hasattr(resource, "prlimit"):
            self.limits.append("memory limit NOT applied (needs Linux's prlimit)")
            return
        cap = int(self.memory_mb) * 1024 * 1024
        resource.prlimit(pid, resource.RLIMIT_AS, (cap, cap))
        self.limits.append(f"kernel memory limited to {self.memory_mb} MB")

    def run_notebook(self, deadline: float) -> None:
        """Execute the submission's cells in order; a cell that raises is recorded, the run goes on."""
        for i, cell in enumerate(self.nb.cells):
            if cell.cell_type != "code":
                continue
            if time.monotonic() > deadline:
                self.cell_errors.append(f"cell {i}: not run, the submission's time limit was reached")
                continue
            try:
                self.client.execute_cell(cell, i)
            except Exception as exc:  # noqa: BLE001 - timeout or dead kernel: reported, grading goes on
                self.cell_errors.append(f"cell {i}: {type(exc).__name__}: {_last_line(exc)}")
                if isinstance(exc, DeadKernelError):
                    self.dead = f"the kernel died while running cell {i}"
                    break
                continue
            for o in cell.get("outputs", []):
                if o.get("output_type") == "error":
                    first = cell.source.strip().splitlines()[0] if cell.source.strip() else ""
                    self.cell_errors.append(f"cell {i} ({first[:50]!r}): {o.get('ename')}: {str(o.get('evalue'))[:200]}")

    def request(self, req: dict, raw: bool = False) -> Any:
        """Send one request to the helper in the kernel; return the decoded answer."""
        if self.dead:
            raise StudentCodeError(self.dead)
        nonce = "@@" + secrets.token_hex(16) + "@@"
        req = dict(req, nonce=nonce)
        cell = self._append(f"print(__flnotes_grading__({json.dumps(json.dumps(req))}))")
        try:
            self.client.execute_cell(cell, len(self.nb.cells) - 1)
        except Exception as exc:  # noqa: BLE001 - timeout or dead kernel: the call failed
            if isinstance(exc, DeadKernelError):
                self.dead = "the kernel died while running a student function"
            raise StudentCodeError(f"{type(exc).__name__}: {_last_line(exc)}") from None
        text = "".join(o.get("text", "") for o in cell.outputs if o.get("output_type") == "stream"
                       and o.get("name") == "stdout")
        first, last = text.find(nonce), text.rfind(nonce)
        if first < 0 or last <= first:
            errs = [f"{o.get('ename')}: {o.get('evalue')}" for o in cell.outputs if o.get("output_type") == "error"]
            raise StudentCodeError("no answer from the kernel" + (f" ({errs[0]})" if errs else ""))
        payload = text[first + len(nonce):last]
        if len(payload) > MAX_ANSWER_CHARS:
            raise StudentCodeError("the answer is too large to be graded")
        try:  # whatever the kernel printed is data: parsed as JSON, never executed
            out = json.loads(payload)
            if not isinstance(out, dict) or not ({"raised", "ok"} & set(out)):
                raise ValueError("not an answer")
            if "raised" in out:
                raise StudentCodeError(str(out["raised"])[:2000])
            return out["ok"] if raw else _dec(out["ok"])
        except (ValueError, TypeError, KeyError, RecursionError) as exc:
            raise StudentCodeError(f"unreadable answer from the kernel ({type(exc).__name__})") from None

    def _append(self, source: str):
        import nbformat

        cell = nbformat.v4.new_code_cell(source)
        self.nb.cells.append(cell)
        return cell

    def install_helper(self) -> None:
        cell = self._append(_KERNEL_HELPER)
        try:
            self.client.execute_cell(cell, len(self.nb.cells) - 1)
        except Exception as exc:  # noqa: BLE001
            self.dead = self.dead or f"the grader could not talk to the kernel: {type(exc).__name__}"


class _Remote:
    """A student function, called in the kernel; only its (decoded) return value comes back."""

    def __init__(self, kernel: _Kernel, name: str):
        self._kernel, self.__name__ = kernel, name

    def __call__(self, *args, **kwargs):
        return self._kernel.request({"op": "call", "name": self.__name__, "args": _enc(list(args)),
                                     "kwargs": _enc(dict(kwargs))})

    def __repr__(self) -> str:
        return f"<student function {self.__name__}>"


# ----------------------------------------------------------------------------------
@dataclass
class GradeReport:
    """Scores of one submission: per question (otter's test files), plus what went wrong."""

    submission: str
    tests: list = field(default_factory=list)  # otter OKTestFile, run
    cell_errors: list[str] = field(default_factory=list)
    limits: list[str] = field(default_factory=list)
    error: str = ""

    @property
    def score(self) -> float:
        return float(sum(t.score for t in self.tests))

    @property
    def possible(self) -> float:
        return float(sum(t.possible for t in self.tests))

    def scores(self) -> dict[str, tuple[float, float]]:
        """``{question: (score, possible)}``."""
        return {t.name: (float(t.score), float(t.possible)) for t in self.tests}

    def table(self, messages: bool = True) -> str:
        lines = [f"grading {self.submission}"]
        lines += [f"  ({x})" for x in self.limits]
        if self.error:
            lines.append(f"error: {self.error}")
        if self.cell_errors:
            lines.append(f"{len(self.cell_errors)} cell(s) of the submission raised:")
            lines += [f"  - {e}" for e in self.cell_errors]
        width = max([len(t.name) for t in self.tests] + [8])
        lines.append(f"{'question':<{width}}  score")
        for t in self.tests:
            lines.append(f"{t.name:<{width}}  {float(t.score):g}/{float(t.possible):g}")
            if messages:
                for r in t.test_case_results:
                    if not r.passed:
                        kind = "hidden" if r.test_case.hidden else "public"
                        msg = [m.strip() for m in r.message.splitlines() if m.strip()]
                        errs = [m for m in msg if re.match(r"^[A-Za-z_.]*(Error|Exception)\b", m)]
                        tail = (errs[-1] if errs else msg[-1] if msg else "failed")[:300]
                        lines.append(f"{'':<{width}}    {kind} test ({r.test_case.name}): {tail}")
        lines.append(f"score: {self.score:g}/{self.possible:g}")
        return "\n".join(lines)


def grade(autograder: str | Path, submission: str | Path, *, cell_timeout: int = 120,
          total_timeout: int = 900, memory_mb: Optional[int] = 4096, verbose: bool = True) -> GradeReport:
    """Grade one submitted notebook with the tests of an otter autograder bundle.

    Parameters
    ----------
    autograder : path of the bundle written by ``otter assign`` (``make assignments``).
    submission : the student's notebook (``.ipynb``); only this file is used, any file
        beside it (a ``tests`` folder, a checks file) is ignored.
    cell_timeout : seconds for one cell of the submission and for one call of a
        student function by a test.
    total_timeout : seconds for running the whole submission; cells after it are not run.
    memory_mb : address-space limit of the kernel (Linux), ``None`` for none.

    Returns
    -------
    GradeReport
        The per-question scores (printed as a table when ``verbose``).
    """
    import nbformat

    if cell_timeout <= 0 or total_timeout <= 0:
        raise ValueError("cell_timeout and total_timeout must be positive numbers of seconds")
    tests, config = load_bundle_tests(autograder)  # read before any student code runs
    sub = Path(submission)
    if sub.suffix != ".ipynb" or not sub.is_file():
        raise ValueError(f"submission={sub} is not a notebook file (.ipynb)")
    report = GradeReport(submission=str(submission))
    nb = nbformat.read(sub, as_version=4)
    expected = config.get("assignment_name")
    got = nb.metadata.get("otter", {}).get("assignment_name")
    if expected and got != expected:
        report.error = f"this submission is for assignment {got!r}, the bundle grades {expected!r}"
    for cell in nb.cells:
        if cell.cell_type == "code":
            cell.outputs, cell.execution_count = [], None

    env_names: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="flnotes-grade-") as tmp:
        # the submission alone, under its own name (otter's init cell reads it for the public tests)
        shutil.copy2(sub, Path(tmp) / sub.name)
        with _Kernel(nb, tmp, cell_timeout, memory_mb) as kernel:
            report.limits = kernel.limits + [f"{cell_timeout} s per cell, {total_timeout} s for the notebook, "
                                             "one thread per numerical library"]
            kernel.run_notebook(time.monotonic() + total_timeout)
            report.cell_errors = kernel.cell_errors
            if kernel.dead:
                report.error = report.error or kernel.dead
            kernel.install_helper()
            try:
                listing = kernel.request({"op": "names"}, raw=True)
                if not isinstance(listing, dict):
                    raise StudentCodeError("unreadable list of names")
            except StudentCodeError as exc:
                listing = {}
                report.error = report.error or f"the submission's names could not be read: {exc}"
            for name, info in listing.items():
                if not isinstance(info, dict) or not isinstance(name, str) or not name.isidentifier() or name in _BUILTIN_NAMES:
                    continue  # a student's `abs` or `len` must not replace the one the tests call
                if "module" in info:
                    mod = str(info["module"])
                    if mod.split(".")[0] in TRUSTED_MODULES:  # the grader's own copy, never the kernel's
                        env_names[name] = importlib.import_module(mod)
                elif info.get("callable"):
                    env_names[name] = _Remote(kernel, name)
                else:
                    try:
                        env_names[name] = _dec(info.get("value"))
                    except (ValueError, TypeError, KeyError, RecursionError):
                        continue
            for t in tests:
                env = {"__name__": "__grading__", **env_names}
                if report.error.startswith("this submission is for"):
                    env = {"__name__": "__grading__"}
                t.run(env)
            report.tests = tests
    if verbose:
        print(report.table())
    return report


# ----------------------------------------------------------------------------------
def instructor_toc(toc: str | Path, out: str | Path, master_dir: str | Path = MASTER_DIR) -> Path:
    """The instructor edition's table of contents: students' pages -> master notebooks.

    Every entry of ``toc`` whose file has a namesake in ``master_dir`` (the
    assignments' masters ``a*.ipynb`` and the instructor's ``index.md``) points to
    the namesake instead; every master must replace an entry.
    """
    import yaml

    master_dir = Path(master_dir).resolve()
    rel = master_dir.relative_to(ROOT).as_posix()
    masters = {p.stem for p in master_dir.iterdir() if p.suffix in (".ipynb", ".md")}
    data = yaml.safe_load(Path(toc).read_text(encoding="utf-8"))
    swapped = []

    def walk(entries):
        for e in entries or []:
            f = e.get("file")
            if f and Path(f).name in masters and not f.startswith(rel):
                e["file"] = f"{rel}/{Path(f).name}"
                swapped.append(Path(f).name)
            walk(e.get("sections"))

    for part in data.get("parts", []):
        walk(part.get("chapters"))
    walk(data.get("chapters"))
    if sorted(swapped) != sorted(masters):
        raise ValueError(f"{toc} lists the assignments {sorted(swapped)}, the masters are {sorted(masters)}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("# written by `python -m flnotes.grading instructor-toc`; do not edit\n"
                   + yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m flnotes.grading", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("assign", help="students' notebooks and autograder bundles (otter assign)")
    a.add_argument("master_dir")
    a.add_argument("out_dir")
    a.add_argument("--book-dir", help="also refresh the book's students' pages in this folder")
    a.add_argument("--no-run-tests", action="store_true", help="do not run the masters' tests first")
    g = sub.add_parser("grade", help="grade one submission, tests outside the student's kernel")
    g.add_argument("-a", "--autograder", required=True, help="bundle written by `make assignments`")
    g.add_argument("submission")
    g.add_argument("--cell-timeout", type=int, default=120)
    g.add_argument("--total-timeout", type=int, default=900)
    g.add_argument("--memory-mb", type=int, default=4096)
    t = sub.add_parser("instructor-toc", help="table of contents of the instructor edition")
    t.add_argument("toc")
    t.add_argument("out")
    args = parser.parse_args(argv)

    if args.cmd == "assign":
        for student, bundle in assign_all(args.master_dir, args.out_dir, args.book_dir,
                                          run_tests=not args.no_run_tests):
            print(f"wrote {student}\nwrote {bundle}")
        return 0
    if args.cmd == "grade":
        report = grade(args.autograder, args.submission, cell_timeout=args.cell_timeout,
                       total_timeout=args.total_timeout, memory_mb=args.memory_mb)
        return 0 if not report.error else 1
    print(f"wrote {instructor_toc(args.toc, args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
