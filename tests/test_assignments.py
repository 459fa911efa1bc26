"""The assignments: reference solutions score full marks, students' versions score zero.

Also checks the grader itself: it survives notebooks whose cells raise, reports
every check, and the notebooks' ``grade`` cells and the checks files agree.
"""
import re
import subprocess
import sys
from pathlib import Path

import nbformat
import pytest

from flnotes import grading

ROOT = Path(__file__).resolve().parent.parent
ADIR = ROOT / "book" / "assignments"
ASSIGNMENTS = sorted(ADIR.glob("a*_*.ipynb"))
IDS = [p.stem for p in ASSIGNMENTS]


def test_at_least_three_assignments():
    assert len(ASSIGNMENTS) >= 3, f"expected at least three assignments in {ADIR}, found {IDS}"


@pytest.mark.parametrize("nb_path", ASSIGNMENTS, ids=IDS)
def test_checks_file_and_grade_cells_agree(nb_path):
    tests_file = grading.tests_path_for(nb_path)
    checks = grading.load_checks(tests_file)
    assert all(pts > 0 for _, _, pts in checks)
    names = {n for n, _, _ in checks}
    nb = nbformat.read(nb_path, as_version=4)
    tags = [set(c.metadata.get("tags", [])) for c in nb.cells]
    assert any("solution" in t for t in tags), "no cell tagged 'solution'"
    called = set()
    for cell, t in zip(nb.cells, tags):
        if "grade" in t:
            found = re.findall(r"check\(\s*['\"](\w+)['\"]\s*,\s*['\"](\w+)['\"]", cell.source)
            assert found, f"grade cell does not call check(...): {cell.source!r}"
            for prefix, name in found:
                assert prefix == nb_path.stem.split("_")[0], f"grade cell uses checks of {prefix}"
                called.add(name)
    assert called <= names, f"grade cells call unknown checks: {sorted(called - names)}"
    assert names <= called, f"checks without a grade cell in the notebook: {sorted(names - called)}"


@pytest.mark.parametrize("nb_path", ASSIGNMENTS, ids=IDS)
def test_reference_solution_scores_full_marks(nb_path):
    report = grading.grade(nb_path, verbose=False)
    print(report.table())
    assert not report.error, report.error
    assert not report.cell_errors, report.cell_errors
    assert report.total > 0
    assert report.score == report.total, report.table()


@pytest.mark.parametrize("nb_path", ASSIGNMENTS, ids=IDS)
def test_student_version_scores_zero(nb_path, tmp_path):
    student = grading.make_student_version(nb_path, tmp_path)
    nb = nbformat.read(student, as_version=4)
    for cell in nb.cells:
        tags = cell.metadata.get("tags", [])
        assert "solution" not in tags, "a solution cell survived"
        assert "solution-start" not in cell.source and "solution-end" not in cell.source
        if cell.cell_type == "code":
            assert cell.outputs == [] and cell.execution_count is None
        if "answer" in tags:
            assert cell.source == grading.STUDENT_STUB
        if "grade" in tags:
            assert cell.metadata.get("editable") is False and cell.metadata.get("deletable") is False

    report = grading.grade(student, tests=grading.tests_path_for(nb_path), verbose=False)
    print(report.table())
    assert not report.error, f"the grader failed on the students' version: {report.error}"
    expected = [n for n, _, _ in grading.load_checks(grading.tests_path_for(nb_path))]
    assert [c.name for c in report.checks] == expected, "every check must be reported"
    assert all(c.earned == 0 and not c.ok for c in report.checks), report.table()
    assert any("NotImplementedError" in e for e in report.cell_errors)
    assert report.table().splitlines()[-1] == f"score: 0/{report.total:g}"


def test_cli_grade_prints_score():
    nb_path = ASSIGNMENTS[0]
    out = subprocess.run(
        [sys.executable, "-m", "flnotes.grading", "grade", str(nb_path)],
        capture_output=True, text=True, timeout=600, check=True,
    ).stdout
    total = sum(p for _, _, p in grading.load_checks(grading.tests_path_for(nb_path)))
    assert out.strip().splitlines()[-1] == f"score: {total:g}/{total:g}", out


def test_cli_student_writes_every_assignment(tmp_path):
    subprocess.run(
        [sys.executable, "-m", "flnotes.grading", "student", str(ADIR), str(tmp_path / "out")],
        capture_output=True, text=True, timeout=120, check=True,
    )
    assert sorted(p.name for p in (tmp_path / "out").glob("*.ipynb")) == [p.name for p in ASSIGNMENTS]


def test_grader_survives_a_dead_notebook(tmp_path):
    """A submission that kills its kernel still gets a report, scored zero."""
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_code_cell("import os\nos._exit(1)")]
    path = tmp_path / "a1_broken.ipynb"
    nbformat.write(nb, path)
    report = grading.grade(path, tests=grading.tests_path_for(ASSIGNMENTS[0]), verbose=False, timeout=60)
    assert report.score == 0 and report.total > 0
    assert report.error
