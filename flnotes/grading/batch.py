"""Grading a folder of downloads: every file, one sandbox each, a gradebook and a report per student.

``batch`` takes the folder of verified bundles (``make assignments``) and a folder of
submissions as a learning-management system delivers them: any file names, any mix of
assignments. Each file's assignment is read from the notebook itself (otter's
``assignment_name`` in its metadata, else the name its first cell gives ``otter.Notebook``),
never from the file name. Each submission is graded alone (:func:`flnotes.grading.grade`),
in its own sandbox, with fresh test objects; whatever it does (not a notebook, another
assignment, a crash, a time-out, too much memory, an attack) it scores 0 with the reason
and the batch goes on. Writes ``gradebook.csv`` and ``reports/<file>-<hash>.txt``.
"""
from __future__ import annotations

import csv
import hashlib
import os
import re
import traceback
from pathlib import Path
from typing import Optional

from .bundles import MANIFEST, Bundle, load_bundle
from .grade import GradeReport, Question, assignment_of, clean, grade, read_submission
from .sandbox import Limits, SandboxUnavailable, bwrap_status, selftest

__all__ = ["batch", "identify", "load_bundles", "report_name", "csv_cell"]


def load_bundles(bundle_dir: str | Path) -> dict[str, Bundle]:
    """Every ``*-autograder.zip`` of ``bundle_dir``, each checked against the recorded SHA-256."""
    bundle_dir = Path(bundle_dir)
    paths = sorted(bundle_dir.glob("*-autograder.zip"))
    if not paths or not (bundle_dir / MANIFEST).is_file():
        raise FileNotFoundError(f"{bundle_dir} holds no bundles with their {MANIFEST}: run `make assignments`")
    return {b.name: b for b in (load_bundle(p) for p in paths)}


def identify(nb, assignments) -> Optional[str]:
    """The assignment a notebook answers (:func:`flnotes.grading.grade.assignment_of`, the rule ``grade`` uses)."""
    return assignment_of(nb, assignments)


def report_name(rel: str) -> str:
    """The report's file name for the submission at ``rel``: readable, and distinct for distinct ``rel``.

    The readable part alone is not (``eve~sub.ipynb`` and ``eve_sub.ipynb``, ``x/a.ipynb`` and
    ``x_a.ipynb``, long names cut at the same place), so a hash of the whole path is appended.
    """
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", rel).strip("._")[:120] or "submission"
    return f"{safe}-{hashlib.sha256(rel.encode('utf-8', 'surrogateescape')).hexdigest()[:12]}.txt"


def csv_cell(value: object) -> str:
    """One gradebook cell: one line, and never read as a formula by a spreadsheet (a leading ``'``)."""
    text = clean(value)
    return "'" + text if text[:1] in ("=", "+", "-", "@", "\t", "\r") else text


def _write_new(path: Path, text: str) -> None:
    """Write a file that must not exist yet (two reports never share a file)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.write(text)


def batch(bundle_dir: str | Path, submissions: str | Path, out_dir: str | Path, *, cell_timeout: int = 120,
          total_timeout: int = 900, limits: Optional[Limits] = None, unsafe: bool = False,
          verbose: bool = True) -> list[GradeReport]:
    """Grade every file under ``submissions``; write ``out_dir/gradebook.csv`` and ``out_dir/reports/``.

    Parameters as :func:`flnotes.grading.grade`. Without a working sandbox it refuses to start
    (``SandboxUnavailable``) unless ``unsafe``, and then every report says so.
    """
    if not unsafe and bwrap_status():
        raise SandboxUnavailable(f"{bwrap_status()}; the grader refuses to run student code without a sandbox "
                                 "(--unsafe-no-sandbox runs it anyway, unprotected)")
    if not unsafe:  # the very command line every submission gets, once: a broken one is not a 0 for everyone
        why = selftest(limits or Limits())
        if why:
            raise SandboxUnavailable(why)
    bundles = load_bundles(bundle_dir)
    submissions, out_dir = Path(submissions), Path(out_dir)
    files = sorted(p for p in submissions.rglob("*") if p.is_file() and not p.is_symlink())
    if not files:
        raise FileNotFoundError(f"no files under {submissions}")
    (out_dir / "reports").mkdir(parents=True, exist_ok=True)
    if any((out_dir / "reports").iterdir()):
        raise FileExistsError(f"{out_dir / 'reports'} holds the reports of an earlier batch: remove it or grade "
                              "into another folder (a report is never overwritten)")
    reports, rows = [], []
    for path in files:
        rel = path.relative_to(submissions).as_posix()
        report = GradeReport(submission=rel)
        try:
            nb = read_submission(path)
            name = identify(nb, bundles)
            if name is None:
                report.error = "not recognized as one of the assignments " + ", ".join(sorted(bundles))
            else:
                report = grade(bundles[name], path, cell_timeout=cell_timeout, total_timeout=total_timeout,
                               limits=limits, unsafe=unsafe, verbose=False, nb=nb)
                report.submission = rel
        except SandboxUnavailable:
            raise
        except BaseException as exc:  # noqa: BLE001 - one submission never stops the batch
            if isinstance(exc, KeyboardInterrupt):
                raise
            report.error = report.error or f"{type(exc).__name__}: {str(exc)[:300]}"
            if not isinstance(exc, ValueError):
                report.error += " | " + traceback.format_exc(limit=3).replace("\n", " ")[-500:]
            report.questions = [Question(q.name, 0.0, q.possible, ["not graded: " + report.error[:200]])
                                for q in report.questions]
        report_path = out_dir / "reports" / report_name(rel)
        _write_new(report_path, report.table() + "\n")  # FileExistsError: a collision, never an overwrite
        rows.append({k: csv_cell(v) for k, v in {
            "file": rel, "assignment": report.assignment, "score": f"{report.score:g}",
            "possible": f"{report.possible:g}", "error": report.error[:500],
            "unsafe": "yes" if report.unsafe else "no", "report": report_path.relative_to(out_dir).as_posix()}.items()})
        reports.append(report)
        if verbose:
            print(f"{rel}: {report.assignment or '?'} {report.score:g}/{report.possible:g}"
                  + (f"  ({report.error[:120]})" if report.error else ""), flush=True)
    with open(out_dir / "gradebook.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return reports
