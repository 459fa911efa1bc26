"""Grading a folder of downloads: every file, one sandbox each, a gradebook and a report per student.

``batch`` takes the folder of verified bundles (``make assignments``) and a folder of
submissions as a learning-management system delivers them: any file names, any mix of
assignments. Each file's assignment is read from the notebook itself (otter's
``assignment_name`` in its metadata, else the name its first cell gives ``otter.Notebook``),
never from the file name. Each submission is graded alone (:func:`flnotes.grading.grade`),
in its own sandbox, with fresh test objects; whatever it does (not a notebook, another
assignment, a crash, a time-out, too much memory, an attack) it scores 0 with the reason
and the batch goes on. Writes ``gradebook.csv`` and ``reports/<file>.txt``.
"""
from __future__ import annotations

import csv
import re
import traceback
from pathlib import Path
from typing import Optional

from .bundles import MANIFEST, Bundle, load_bundle
from .grade import GradeReport, Question, grade, read_submission
from .sandbox import Limits, SandboxUnavailable, bwrap_status

__all__ = ["batch", "identify", "load_bundles"]

_INIT = re.compile(r"""otter\.Notebook\(\s*["']([A-Za-z0-9_.-]+)\.ipynb["']""")


def load_bundles(bundle_dir: str | Path) -> dict[str, Bundle]:
    """Every ``*-autograder.zip`` of ``bundle_dir``, each checked against the recorded SHA-256."""
    bundle_dir = Path(bundle_dir)
    paths = sorted(bundle_dir.glob("*-autograder.zip"))
    if not paths or not (bundle_dir / MANIFEST).is_file():
        raise FileNotFoundError(f"{bundle_dir} holds no bundles with their {MANIFEST}: run `make assignments`")
    return {b.name: b for b in (load_bundle(p) for p in paths)}


def identify(nb, assignments) -> Optional[str]:
    """The assignment a notebook answers, from its content: otter's metadata, else its ``otter.Notebook`` call."""
    meta = nb.metadata.get("otter") if isinstance(nb.metadata.get("otter"), dict) else {}
    name = meta.get("assignment_name")
    if isinstance(name, str) and name in assignments:
        return name
    for cell in nb.cells[:10]:
        m = _INIT.search(cell.source) if cell.cell_type == "code" else None
        if m and m.group(1) in assignments:
            return m.group(1)
    return None


def _safe(rel: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", rel).strip("._")[:150] or "submission"


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
    bundles = load_bundles(bundle_dir)
    submissions, out_dir = Path(submissions), Path(out_dir)
    files = sorted(p for p in submissions.rglob("*") if p.is_file() and not p.is_symlink())
    if not files:
        raise FileNotFoundError(f"no files under {submissions}")
    (out_dir / "reports").mkdir(parents=True, exist_ok=True)
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
        report_path = out_dir / "reports" / f"{_safe(rel)}.txt"
        report_path.write_text(report.table() + "\n", encoding="utf-8")
        rows.append({"file": rel, "assignment": report.assignment, "score": f"{report.score:g}",
                     "possible": f"{report.possible:g}", "error": report.error[:500],
                     "unsafe": "yes" if report.unsafe else "no", "report": report_path.relative_to(out_dir).as_posix()})
        reports.append(report)
        if verbose:
            print(f"{rel}: {report.assignment or '?'} {report.score:g}/{report.possible:g}"
                  + (f"  ({report.error[:120]})" if report.error else ""), flush=True)
    with open(out_dir / "gradebook.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return reports
