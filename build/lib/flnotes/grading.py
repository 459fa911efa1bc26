"""Assignments: students' versions and automatic grading.

An assignment is a notebook under ``book/assignments/`` holding the instructor's
reference solution, plus a file of checks beside it (``a1_derive_phi.ipynb`` goes
with ``a1_tests.py``: the part of the notebook's name before the first ``_``).

Cell tags (cell metadata ``tags``) drive everything:

``solution``
    A code cell whose source is the reference solution. In the students' version
    its source becomes ``# YOUR CODE HERE`` / ``raise NotImplementedError()`` and
    its outputs are dropped. A *markdown* cell tagged ``solution`` (the reference
    answer to a question in words, or the ``{solution-start}``/``{solution-end}``
    fences of sphinx-exercise) is removed from the students' version.
``grade``
    A code cell that runs one of the instructor's checks on the notebook's own
    namespace, e.g. ``check("a1", "check_phi", globals())``. It is kept verbatim
    and locked (not editable, not deletable) in the students' version, so that a
    student can test a part before submitting; the grader does not rely on it.

The checks file is plain Python: functions ``check_xxx(ns)`` (``ns`` is the
notebook's global namespace) that raise ``AssertionError`` with a helpful message
when the work is wrong, each worth the points given by ``@points(n)`` (1 if not
decorated). The grader executes a submitted notebook in a temporary folder with
errors allowed (a cell that raises does not stop the run), then runs every check
in the same kernel and prints a score table ending in ``score: X/Y``.

Command line::

    python -m flnotes.grading grade book/assignments/a1_derive_phi.ipynb
    python -m flnotes.grading student book/assignments _build/assignments
"""
from __future__ import annotations

import argparse
import copy
import importlib.util
import json
import shutil
import sys
import tempfile
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

__all__ = [
    "SOLUTION_TAG",
    "GRADE_TAG",
    "STUDENT_STUB",
    "points",
    "check",
    "tests_path_for",
    "load_checks",
    "run_checks",
    "make_student_version",
    "make_student_versions",
    "CheckResult",
    "GradeReport",
    "grade",
    "main",
]

SOLUTION_TAG = "solution"
GRADE_TAG = "grade"
STUDENT_STUB = "# YOUR CODE HERE\nraise NotImplementedError()"

#: where the instructor's assignments (and their checks) live in a checkout
ASSIGNMENTS_DIR = Path(__file__).resolve().parent.parent / "book" / "assignments"

_MARK_BEGIN = "<<<FLNOTES-GRADE-BEGIN>>>"
_MARK_END = "<<<FLNOTES-GRADE-END>>>"


# ----------------------------------------------------------------------------------
# Writing checks
def points(n: float) -> Callable[[Callable], Callable]:
    """Decorator giving a check function its value in points."""
    if n <= 0:
        raise ValueError("a check must be worth a positive number of points")

    def deco(fn: Callable) -> Callable:
        fn.points = n  # type: ignore[attr-defined]
        return fn

    return deco


def tests_path_for(notebook: str | Path, tests_dir: str | Path | None = None) -> Path:
    """The checks file of an assignment notebook: ``a1_derive_phi.ipynb`` -> ``a1_tests.py``.

    It is looked up in ``tests_dir`` if given, else beside the notebook, else in the
    instructor's ``book/assignments`` (so a student's copy anywhere still finds it).
    """
    nb = Path(notebook)
    name = nb.stem.split("_", 1)[0] + "_tests.py"
    candidates = [Path(tests_dir) / name] if tests_dir is not None else [nb.parent / name, ASSIGNMENTS_DIR / name]
    for cand in candidates:
        if cand.is_file():
            return cand.resolve()
    raise FileNotFoundError(f"no checks file {name} for {nb} (looked in: {', '.join(map(str, candidates))})")


def _import_file(path: Path):
    spec = importlib.util.spec_from_file_location(f"_flnotes_checks_{path.stem}", path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot import {path}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def load_checks(tests_file: str | Path) -> list[tuple[str, Callable, float]]:
    """``(name, function, points)`` for every ``check_*`` function, in file order."""
    module = _import_file(Path(tests_file))
    out = []
    for name, obj in vars(module).items():
        if name.startswith("check_") and callable(obj):
            out.append((name, obj, float(getattr(obj, "points", 1))))
    if not out:
        raise ValueError(f"{tests_file} defines no check_* function")
    return out


def run_checks(tests_file: str | Path, ns: dict, only: Iterable[str] | None = None) -> list[dict]:
    """Run the checks of ``tests_file`` against the namespace ``ns``.

    Returns one dict per check: name, points, earned, ok, message. Never raises
    for a failing check: any exception counts as a failure and its text is kept.
    """
    wanted = set(only) if only is not None else None
    results = []
    for name, fn, pts in load_checks(tests_file):
        if wanted is not None and name not in wanted:
            continue
        try:
            fn(ns)
        except AssertionError as exc:
            msg = str(exc) or "assertion failed"
            results.append(dict(name=name, points=pts, earned=0.0, ok=False, message=msg))
        except Exception as exc:  # noqa: BLE001 - a student's error is a result, not a crash
            msg = f"{type(exc).__name__}: {exc}"
            results.append(dict(name=name, points=pts, earned=0.0, ok=False, message=msg))
        else:
            results.append(dict(name=name, points=pts, earned=pts, ok=True, message=""))
    return results


def check(assignment: str, name: str, ns: dict, tests_dir: str | Path | None = None) -> None:
    """Run one check inside a notebook (``grade`` cells); raise AssertionError if it fails.

    ``assignment`` is the prefix of the checks file (``"a1"`` for ``a1_tests.py``).
    """
    base = Path(tests_dir) if tests_dir is not None else ASSIGNMENTS_DIR
    tests_file = base / f"{assignment}_tests.py"
    (res,) = run_checks(tests_file, ns, only=[name]) or [None]
    if res is None:
        raise KeyError(f"{tests_file.name} has no check named {name}")
    if not res["ok"]:
        raise AssertionError(f"{name} failed: {res['message']}")
    print(f"{name}: passed ({res['points']:g} point{'s' if res['points'] != 1 else ''})")


def _run_checks_marked(tests_file: str, ns: dict) -> None:
    """Used by the grader inside the student's kernel: print results between markers."""
    try:
        results = run_checks(tests_file, ns)
        payload = {"results": results}
    except Exception:  # noqa: BLE001
        payload = {"error": traceback.format_exc()}
    print(_MARK_BEGIN + json.dumps(payload) + _MARK_END)


# ----------------------------------------------------------------------------------
# Students' versions
def _tags(cell) -> list[str]:
    return list(cell.get("metadata", {}).get("tags", []))


def _strip_outputs(cell) -> None:
    if cell.get("cell_type") == "code":
        cell["outputs"] = []
        cell["execution_count"] = None


def make_student_version(src: str | Path, dst: str | Path) -> Path:
    """Write the students' version of the assignment notebook ``src`` to ``dst``.

    ``dst`` may be a folder (the file name is kept). Solution code cells become a
    stub that raises ``NotImplementedError``; solution markdown cells are dropped;
    grade cells are locked; every output is removed.
    """
    import nbformat

    src, dst = Path(src), Path(dst)
    if dst.is_dir() or (not dst.suffix and not dst.exists()):
        dst = dst / src.name
    nb = nbformat.read(src, as_version=4)
    out = copy.deepcopy(nb)
    cells = []
    n_solution = 0
    for cell in out.cells:
        tags = _tags(cell)
        if SOLUTION_TAG in tags:
            n_solution += 1
            if cell.cell_type != "code":
                continue  # reference answers in words and sphinx-exercise fences go
            cell.source = STUDENT_STUB
            cell.metadata["tags"] = [t for t in tags if t != SOLUTION_TAG] + ["answer"]
        if GRADE_TAG in tags:
            cell.metadata["editable"] = False
            cell.metadata["deletable"] = False
        _strip_outputs(cell)
        cells.append(cell)
    if n_solution == 0:
        raise ValueError(f"{src} has no cell tagged '{SOLUTION_TAG}': nothing to hide")
    out.cells = cells
    dst.parent.mkdir(parents=True, exist_ok=True)
    nbformat.write(out, dst)
    return dst


def make_student_versions(src_dir: str | Path, dst_dir: str | Path) -> list[Path]:
    """Students' versions of every assignment notebook in ``src_dir`` (``a*_*.ipynb``)."""
    src_dir, dst_dir = Path(src_dir), Path(dst_dir)
    written = []
    for nb in sorted(src_dir.glob("a*_*.ipynb")):
        written.append(make_student_version(nb, dst_dir / nb.name))
    if not written:
        raise FileNotFoundError(f"no assignment notebooks (a*_*.ipynb) in {src_dir}")
    return written


# ----------------------------------------------------------------------------------
# Grading
@dataclass
class CheckResult:
    name: str
    points: float
    earned: float
    ok: bool
    message: str = ""


@dataclass
class GradeReport:
    notebook: str
    checks: list[CheckResult] = field(default_factory=list)
    cell_errors: list[str] = field(default_factory=list)
    error: str = ""

    @property
    def score(self) -> float:
        return sum(c.earned for c in self.checks)

    @property
    def total(self) -> float:
        return sum(c.points for c in self.checks)

    def table(self) -> str:
        width = max([len(c.name) for c in self.checks] + [5])
        lines = [f"grading {self.notebook}"]
        if self.cell_errors:
            lines.append(f"{len(self.cell_errors)} cell(s) raised while running the notebook:")
            lines += [f"  - {e}" for e in self.cell_errors]
        if self.error:
            lines.append("the checks could not be run: " + self.error.strip().splitlines()[-1])
        lines.append(f"{'check':<{width}}  points  result")
        for c in self.checks:
            res = "ok" if c.ok else "FAILED: " + c.message.strip().replace("\n", " ")[:300]
            lines.append(f"{c.name:<{width}}  {c.earned:g}/{c.points:g}{'':<3}  {res}")
        lines.append(f"score: {self.score:g}/{self.total:g}")
        return "\n".join(lines)


def _cell_errors(nb) -> list[str]:
    errs = []
    for i, cell in enumerate(nb.cells):
        if cell.cell_type != "code":
            continue
        for o in cell.get("outputs", []):
            if o.get("output_type") == "error":
                first = cell.source.strip().splitlines()[0] if cell.source.strip() else ""
                what = f"{o.get('ename')}: {o.get('evalue')}" if o.get("evalue") else f"{o.get('ename')}"
                errs.append(f"cell {i} ({first[:50]!r}): {what}")
    return errs


def grade(
    notebook_path: str | Path,
    tests: str | Path | None = None,
    *,
    timeout: int = 300,
    kernel_name: str = "python3",
    verbose: bool = True,
) -> GradeReport:
    """Execute a submitted notebook and score it with the instructor's checks.

    ``tests`` is the checks file (default: found by :func:`tests_path_for`). The
    notebook runs in a temporary copy of its folder with errors allowed; then the
    checks run in the same kernel against its namespace. Prints the score table
    when ``verbose`` and returns the :class:`GradeReport`.
    """
    import nbformat
    from nbclient import NotebookClient

    nb_path = Path(notebook_path).resolve()
    tests_file = Path(tests).resolve() if tests is not None else tests_path_for(nb_path)
    names = [(n, p) for n, _, p in load_checks(tests_file)]

    nb = nbformat.read(nb_path, as_version=4)
    for cell in nb.cells:
        _strip_outputs(cell)
    n_user = len(nb.cells)
    grader_src = (
        "from flnotes.grading import _run_checks_marked as __flnotes_grade\n"
        f"__flnotes_grade({str(tests_file)!r}, globals())"
    )
    nb.cells.append(nbformat.v4.new_code_cell(grader_src))

    report = GradeReport(notebook=str(notebook_path))
    with tempfile.TemporaryDirectory(prefix="flnotes-grade-") as tmp:
        # the notebook's sibling files (data, helper modules) come along, nothing else
        for sib in nb_path.parent.iterdir():
            if sib.is_file() and sib.suffix != ".ipynb":
                shutil.copy2(sib, tmp)
        client = NotebookClient(
            nb,
            timeout=timeout,
            kernel_name=kernel_name,
            allow_errors=True,
            resources={"metadata": {"path": tmp}},
        )
        try:
            client.execute()
        except Exception as exc:  # noqa: BLE001 - dead kernel, timeout: still report
            report.error = f"{type(exc).__name__}: {exc}"

    report.cell_errors = _cell_errors(nbformat.from_dict({"cells": nb.cells[:n_user]}))
    payload = None
    for o in nb.cells[-1].get("outputs", []):
        text = o.get("text", "") if o.get("output_type") == "stream" else ""
        if _MARK_BEGIN in text and _MARK_END in text:
            payload = json.loads(text.split(_MARK_BEGIN, 1)[1].split(_MARK_END, 1)[0])
    if payload is None or "error" in payload:
        if payload is not None:
            report.error = payload["error"]
        elif not report.error:
            report.error = "the grading cell printed no result"
        report.checks = [CheckResult(n, p, 0.0, False, "not run") for n, p in names]
    else:
        report.checks = [CheckResult(**r) for r in payload["results"]]
    if verbose:
        print(report.table())
    return report


# ----------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m flnotes.grading", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("grade", help="execute a submitted notebook and print its score")
    g.add_argument("notebook")
    g.add_argument("--tests", help="checks file (default: <prefix>_tests.py beside the notebook or in book/assignments)")
    g.add_argument("--timeout", type=int, default=300, help="seconds per cell")
    s = sub.add_parser("student", help="write the students' versions of the assignments")
    s.add_argument("src_dir")
    s.add_argument("dst_dir")
    args = parser.parse_args(argv)

    if args.cmd == "grade":
        report = grade(args.notebook, args.tests, timeout=args.timeout)
        return 0 if not report.error or report.checks else 1
    written = make_student_versions(args.src_dir, args.dst_dir)
    for p in written:
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
