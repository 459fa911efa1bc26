"""The assignments and their grader.

* ``otter assign`` turns every master notebook into a students' notebook and an
  autograder bundle; with ``run_tests`` it runs the master's own tests first and stops
  on a reference solution that fails them;
* each reference solution scores full marks, each students' version scores zero;
* the students' files (notebooks, the book's pages, the students' edition of the
  book as HTML) hold neither a reference solution nor a hidden test;
* submissions that try to game the grader score no more than the honest blank
  (zero): patching otter, numpy or the grader from a cell, shadowing built-ins,
  hard-coded answers, a checks file next to the submission, copying the network
  instead of solving the MILP, killing the kernel, looping forever, a6's program
  replaced by fl.MPC's plan or stripped of the network constraint, a5's controller
  replaced by a closed-form law without the network;
* a5's grader accepts the reference controller under either hold (u held, as in
  chapter 6, or v held, as in chapter 1);
* the bundles are verified (a changed bundle is refused), answers are decoded strictly,
  the students' edition holds no instructor material and points at the students' repository.

The sandbox's attack classes, graded in one batch, are in ``test_grading_attacks.py``.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import nbformat
import pytest
import yaml

from flnotes import grading

pytestmark = pytest.mark.skipif(grading.bwrap_status() is not None,
                                reason=f"no sandbox: {grading.bwrap_status()} (`make test` installs bubblewrap)")

ROOT = Path(__file__).resolve().parent.parent
ADIR = ROOT / "book" / "assignments"
MASTERS = sorted(grading.MASTER_DIR.glob("a*.ipynb"))
IDS = [p.stem for p in MASTERS]
MARKER = "REFSOL"  # planted in every reference solution of the masters


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """``{name: (student, bundle, solution)}`` written by ``otter assign``.

    otter's own run of each master's tests is skipped here: grading every reference solution with its
    bundle (:func:`test_reference_solution_scores_full_marks`) checks the same and more, and
    :func:`test_assign_runs_the_masters_tests_and_stops_on_a_failing_solution` checks that run itself.
    """
    out = tmp_path_factory.mktemp("assignments")
    written = grading.assign_all(grading.MASTER_DIR, out, run_tests=False)
    return {s.stem: (s, b, out / "solution" / s.name) for s, b in written}


def _nb(path) -> nbformat.NotebookNode:
    return nbformat.read(path, as_version=4)


def _with_cells(student: Path, dst: Path, *, before_end: list[str] = (), replace: dict[str, str] = None) -> Path:
    """A copy of a students' notebook with extra code cells at the end and some answers filled in.

    ``replace`` maps the first line of an answer cell (``def phi(z, v):``) to new source.
    """
    nb = _nb(student)
    for cell in nb.cells:
        first = cell.source.splitlines()[0] if cell.source else ""
        if replace and cell.cell_type == "code" and first in replace:
            cell.source = replace[first]
    nb.cells += [nbformat.v4.new_code_cell(src) for src in before_end]
    dst.parent.mkdir(parents=True, exist_ok=True)
    nbformat.write(nb, dst)
    return dst


def _strings(x) -> str:
    """Every string held by a notebook (sources, metadata, outputs), joined."""
    if isinstance(x, str):
        return x
    if isinstance(x, dict):
        return "\n".join(_strings(v) for v in x.values())
    if isinstance(x, list):
        return "\n".join(_strings(v) for v in x)
    return ""


def _grade(bundle, sub, **kw) -> grading.GradeReport:
    report = grading.grade(bundle, sub, verbose=False, **kw)
    print(report.table())
    return report


# ----------------------------------------------------------------------------------
def test_at_least_three_assignments():
    assert len(MASTERS) >= 3, f"expected at least three master notebooks in {grading.MASTER_DIR}, found {IDS}"


@pytest.mark.parametrize("name", IDS)
def test_each_question_has_hidden_tests_and_a_marked_solution(name, built):
    _, bundle, _ = built[name]
    tests, config = grading.load_bundle_tests(bundle)
    assert config.get("assignment_name") == name
    for t in tests:
        hidden = [c for c in t.test_cases if c.hidden]
        public = [c for c in t.test_cases if not c.hidden]
        assert hidden, f"{name} {t.name}: no hidden test"
        assert sum(c.points for c in hidden) == t.possible > 0, f"{name} {t.name}: the hidden tests must carry the points"
        assert all(c.points == 0 for c in public), f"{name} {t.name}: public tests are feedback, worth 0 points"
    marker = f"{MARKER}-{name.split('_')[0]}"
    inside, solution_cells, questions = False, 0, 0
    for cell in _nb(grading.MASTER_DIR / f"{name}.ipynb").cells:
        head = cell.source.strip().splitlines()[0] if cell.source.strip() else ""
        if cell.cell_type == "raw":
            questions += head == "# BEGIN QUESTION"
            inside = {"# BEGIN SOLUTION": True, "# END SOLUTION": False}.get(head, inside)
        elif inside:
            solution_cells += 1
            assert marker in cell.source, f"a reference solution of {name} lacks the marker {marker}: {cell.source[:80]!r}"
    assert questions >= len(tests) and solution_cells >= questions


@pytest.mark.parametrize("name", IDS)
def test_book_page_is_the_current_students_version(name, built, tmp_path):
    student, _, _ = built[name]
    expected = grading.student_page(student, tmp_path / f"{name}.ipynb").read_text(encoding="utf-8")
    page = ADIR / f"{name}.ipynb"
    assert page.is_file(), f"{page} is missing: run `make assignments`"
    assert page.read_text(encoding="utf-8") == expected, f"{page} is out of date with its master: run `make assignments`"


@pytest.mark.parametrize("name", IDS)
def test_students_files_hold_no_solution_and_no_hidden_test(name, built):
    student, bundle, _ = built[name]
    tests, _ = grading.load_bundle_tests(bundle)
    hidden_bodies = [c.body for t in tests for c in t.test_cases if c.hidden]
    for path in (student, ADIR / f"{name}.ipynb"):
        text = _strings(json.loads(path.read_text(encoding="utf-8")))
        assert MARKER not in text, f"{path} holds a reference solution"
        assert "BEGIN SOLUTION" not in text and "hidden: true" not in text
        for body in hidden_bodies:
            # the first line of code of a hidden test that is not an import
            line = next(l for l in body.splitlines() if l.startswith(">>> ") and "import" not in l)[4:]
            assert line not in text, f"{path} holds a hidden test ({line!r})"
        meta = _nb(path).metadata["otter"]["tests"]
        assert all(not c.get("hidden", False) for q in meta.values() for s in q["suites"] for c in s["cases"])


@pytest.mark.parametrize("name", IDS)
def test_reference_solution_scores_full_marks(name, built):
    _, bundle, solution = built[name]
    report = _grade(bundle, solution)
    assert not report.error and not report.cell_errors, report.table()
    assert report.possible > 0 and report.score == report.possible, report.table()


def test_assign_runs_the_masters_tests_and_stops_on_a_failing_solution(tmp_path):
    master = grading.MASTER_DIR / "a1_derive_phi.ipynb"
    nb = _nb(master)
    cells = [c for c in nb.cells if c.cell_type == "code" and MARKER in c.source]
    assert cells, "premise: the master has a marked reference solution"
    cells[0].source = cells[0].source.replace("return m * l**2 * v", "return 2 * m * l**2 * v")
    assert "2 * m * l**2" in cells[0].source, "premise: the reference solution was broken"
    broken = tmp_path / "master" / master.name
    broken.parent.mkdir()
    nbformat.write(nb, broken)
    with pytest.raises(RuntimeError, match="otter assign failed on a1_derive_phi") as err:
        grading.assign(broken, tmp_path / "bad")
    assert "phi differs from the reference" in str(err.value), "the failing hidden test is what stopped it"
    assert not (tmp_path / "bad" / "autograder").exists(), "nothing is written for a failing master"
    grading.assign(broken, tmp_path / "unchecked", run_tests=False)  # without the run the same master passes


@pytest.mark.parametrize("name", IDS)
def test_students_version_scores_zero(name, built):
    student, bundle, _ = built[name]
    report = _grade(bundle, student)
    tests, _ = grading.load_bundle_tests(bundle)
    assert [q.name for q in report.questions] == [t.name for t in tests], "every question must be reported"
    assert report.possible == sum(t.possible for t in tests) > 0
    assert report.score == 0, report.table()
    assert report.table().splitlines()[-1] == f"score: 0/{report.possible:g}"


def test_cli_grade_prints_a_score_per_question(built):
    _, bundle, solution = built[IDS[0]]
    out = subprocess.run([sys.executable, "-m", "flnotes.grading", "grade", "-a", str(bundle), str(solution)],
                         capture_output=True, text=True, timeout=600, check=True).stdout
    tests, _ = grading.load_bundle_tests(bundle)
    total = sum(t.possible for t in tests)
    lines = out.strip().splitlines()
    for t in tests:
        assert f"{t.name}" in " ".join(lines) and any(l.split()[:2] == [t.name, f"{t.possible:g}/{t.possible:g}"]
                                                       for l in lines if l.strip()), out
    assert lines[-1] == f"score: {total:g}/{total:g}", out


def test_instructor_toc_swaps_every_assignment(tmp_path):
    out = grading.instructor_toc(ROOT / "_toc.yml", tmp_path / "toc.yml")
    files = yaml.safe_dump(yaml.safe_load(out.read_text()))
    for name in IDS:
        assert f"book/assignments/master/{name}" in files
        assert f"book/assignments/{name}\n" not in files
    assert "book/assignments/master/index" in files
    assert "book/assignments/master/instructor_guide" in files, "the guide is in the instructor edition"
    assert "instructor" not in (ROOT / "_toc.yml").read_text(), "no instructor page in the students' table of contents"
    assert not list((ROOT / "book").glob("**/instructor*.md")) or all(
        "master" in p.parts for p in (ROOT / "book").glob("**/instructor*.md")), "instructor pages live with the masters"


def test_students_edition_holds_no_instructor_material(tmp_path, built):
    out = grading.students_edition(tmp_path / "students")
    url = grading.students_repository()
    assert not (out / "book" / "assignments" / "master").exists() and not (out / "tests").exists()
    assert not list(out.rglob("instructor*")) and not list(out.rglob("*-autograder.zip"))
    seeds = grading.hidden_test_lines()
    assert any("default_rng(101)" in line for line in seeds), "premise: the hidden tests' seeds are known"
    installs = 0
    for p in list(out.rglob("*.ipynb")) + list(out.rglob("*.md")):
        text = p.read_text(encoding="utf-8")
        assert "REFSOL" not in text and "hidden: true" not in text, p
        assert not [line for line in seeds if line in text], f"{p} reveals a hidden test"
        for m in re.finditer(r"flnotes(?:\[\w+\])? @ git\+([^\"\\]+)", text):
            assert m.group(1) == url, f"{p} installs from {m.group(1)}, not the students' repository {url}"
            installs += 1
    assert installs >= len(IDS), "the notebooks install the package"
    config = yaml.safe_load((out / "_config.yml").read_text())
    assert config["repository"]["url"] == url and config["html"]["use_repository_button"]
    for name in IDS:  # the students' notebooks written by `make assignments` install from there too
        student, _, _ = built[name]
        assert f"git+{url}" in student.read_text(encoding="utf-8")


def test_a_changed_bundle_is_refused(built, tmp_path):
    _, bundle, _ = built[IDS[0]]
    copy = tmp_path / "autograder"
    shutil.copytree(bundle.parent, copy)
    assert grading.load_bundle(copy / bundle.name).sha256 == hashlib.sha256(bundle.read_bytes()).hexdigest()
    target = copy / bundle.name
    target.chmod(0o644)
    with zipfile.ZipFile(target, "a") as zf:
        zf.writestr("tests/q9.py", "OK_FORMAT = True\ntest = {'name': 'q9', 'points': 100, 'suites': []}\n")
    with pytest.raises(ValueError, match="does not match its SHA-256"):
        grading.load_bundle(target)
    (copy / grading.MANIFEST).unlink()
    with pytest.raises(ValueError, match="missing"):
        grading.load_bundle(target)
    assert not os.access(bundle, os.W_OK) or os.geteuid() == 0, "bundles are written read-only"
    assert bundle.stat().st_mode & 0o222 == 0, "bundles are written read-only"


def test_answers_are_decoded_strictly():
    import numpy as np

    a = np.arange(6.0).reshape(2, 3)
    assert np.array_equal(grading.decode(json.loads(json.dumps(grading.encode((a, [1, "x"], {"k": None})))))[0], a)
    bad = [{"__nd__": [[1.0, 2.0]], "kind": "f", "shape": [2, 2]},      # data not of the declared shape
           {"__nd__": [1.0], "kind": "O", "shape": [1]},                # object dtype
           {"__nd__": ["a"], "kind": "f", "shape": [1]},                # a string in an array
           {"__float__": "1e308*10"}, {"__module__": "os"}, {"__nd__": [], "kind": "f", "shape": [10**7]}]
    for x in bad:
        with pytest.raises(grading.AnswerError):
            grading.decode(x)
    deep = 0
    for _ in range(50):
        deep = [deep]
    with pytest.raises(grading.AnswerError, match="deep"):
        grading.decode(deep)
    with pytest.raises(AssertionError, match="shape"):
        grading.expect_array(np.zeros(0), (200,))
    with pytest.raises(AssertionError, match="nan"):
        grading.expect_array([1.0, float("nan")], (2,))


# ----------------------------------------------------------------------------------
# the students' edition of the book, as HTML
def _student_toc(path: Path) -> Path:
    """A table of contents with the "Course material" pages of the book's _toc.yml under book/assignments."""
    toc = yaml.safe_load((ROOT / "_toc.yml").read_text())
    pages = []

    def walk(entries):
        for e in entries or []:
            if e.get("file", "").startswith("book/assignments/"):
                pages.append(e["file"])
            walk(e.get("sections"))

    for part in toc["parts"]:
        walk(part.get("chapters"))
    assert "book/assignments/index" in pages and all(f"book/assignments/{n}" in pages for n in IDS)
    path.write_text(yaml.safe_dump({"format": "jb-book", "root": pages[0],
                                    "chapters": [{"file": p} for p in pages[1:]]}))
    return path


def test_students_edition_html_holds_no_solution(tmp_path):
    """Build the book's assignment pages as `make book` does and search every file it writes."""
    exe = Path(sys.executable).parent / "jupyter-book"
    toc = _student_toc(tmp_path / "toc.yml")
    out = tmp_path / "site"
    proc = subprocess.run([str(exe), "build", str(ROOT), "--toc", str(toc), "--path-output", str(out), "--all",
                           "-W", "-n", "--keep-going"], cwd=ROOT, capture_output=True, text=True, timeout=900,
                          env=dict(os.environ, FLNOTES_FAST="1"))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    html = out / "_build" / "html"
    sites = [html]
    fast_build = ROOT / "_build" / "test_html" / "_build" / "html"  # tests/test_rendered.py's build, if there
    if (fast_build / "index.html").is_file():
        sites.append(fast_build)
    for site in sites:
        pages = [site / "book" / "assignments" / f"{n}.html" for n in IDS]
        assert all(p.is_file() for p in pages), f"students' pages missing in {site}"
        leaks = [p for p in site.rglob("*") if p.is_file() and p.suffix in (".html", ".ipynb", ".md", ".txt", ".js")
                 and MARKER in p.read_text(encoding="utf-8", errors="replace")]
        assert not leaks, f"reference solutions in the students' edition: {leaks}"
        assert not list(site.rglob("master")), "the master notebooks must not be part of the students' edition"
        assert not list(site.rglob("instructor*")), "no instructor page in the students' edition"
        seeds = {m for line in grading.hidden_test_lines() for m in re.findall(r"default_rng\(\d+\)", line)}
        assert "default_rng(101)" in seeds, "premise: the hidden tests' seeds are known"
        for p in site.rglob("*.html"):
            text = re.sub(r"<[^>]+>", "", p.read_text(encoding="utf-8", errors="replace"))
            assert not [s for s in seeds if s in text], f"{p} reveals a hidden test's seed"


# ----------------------------------------------------------------------------------
# submissions that try to game the grader: none may score more than the blank (0)
PATCH_EVERYTHING = r'''
import builtins, numpy, otter, otter.execute, otter.test_files
import flnotes.grading
numpy.allclose = lambda *a, **k: True
numpy.isclose = lambda *a, **k: numpy.True_
otter.execute.Checker.check = classmethod(lambda cls, *a, **k: None)
otter.test_files.TestFile.score = property(lambda self: self.possible)
flnotes.grading.grade = lambda *a, **k: None
flnotes.grading.GradeReport.score = property(lambda self: self.possible)
builtins.abs = lambda x: 0.0
AssertionError = type("AssertionError", (Exception,), {})
'''

SHADOW_BUILTINS = r'''
def abs(x):
    return 0.0
def float(x):
    return 0.0
def isinstance(a, b):
    return True
def len(x):
    return 0
'''


def _zero(report: grading.GradeReport):
    assert report.possible > 0 and report.score == 0, report.table()


def test_cheat_patching_otter_numpy_and_the_grader_from_a_cell(built, tmp_path):
    for name in IDS:
        student, bundle, _ = built[name]
        _zero(_grade(bundle, _with_cells(student, tmp_path / name / student.name, before_end=[PATCH_EVERYTHING])))


def test_cheat_shadowing_builtins(built, tmp_path):
    """Tests compare with abs(...) <= tol: a student's `abs` returning 0 must not be the one they call."""
    student, bundle, _ = built["a2_encode_by_hand"]
    free_y = ("def bigm_milp(W1, b1, W2, b2, lo, hi):\n"
              "    n, k = len(lo), len(b1)\n"
              "    return dict(A=np.zeros((1, n + 2 * k + 1)), row_lo=[0.0], row_hi=[0.0],\n"
              "                var_lo=np.r_[lo, np.zeros(2 * k), -1.0], var_hi=np.r_[hi, np.ones(2 * k), 1.0],\n"
              "                integrality=np.r_[np.zeros(n + k), np.ones(k), 0].astype(int))")
    sub = _with_cells(student, tmp_path / "a2" / student.name, before_end=[SHADOW_BUILTINS],
                      replace={"def bigm_milp(W1, b1, W2, b2, lo, hi):": free_y})
    _zero(_grade(bundle, sub))
    student, bundle, _ = built["a3_tune_gain"]
    sub = _with_cells(student, tmp_path / "a3" / student.name, before_end=[SHADOW_BUILTINS],
                      replace={"def max_abs_u(lam, z0):": "def max_abs_u(lam, z0):\n    return 0.0"})
    _zero(_grade(bundle, sub))


def test_cheat_a_checks_file_next_to_the_submission(built, tmp_path):
    student, bundle, _ = built["a1_derive_phi"]
    sub = _with_cells(student, tmp_path / "sub" / student.name)
    tests = sub.parent / "tests"
    tests.mkdir()
    for q in ("q1", "q2", "q3"):
        (tests / f"{q}.py").write_text(f"OK_FORMAT = True\ntest = {{'name': '{q}', 'points': 3, 'suites': "
                                       "[{'cases': [{'code': '>>> True\\nTrue', 'hidden': False}], "
                                       "'scored': True, 'setup': '', 'teardown': '', 'type': 'doctest'}]}\n")
    shutil.copy(tests / "q1.py", sub.parent / "a1_tests.py")
    with zipfile.ZipFile(sub.parent / "a1_derive_phi-autograder.zip", "w") as zf:  # a fake bundle beside it, too
        for q in ("q1", "q2", "q3"):
            zf.write(tests / f"{q}.py", f"tests/{q}.py")
    _zero(_grade(bundle, sub))


def test_cheat_hard_coded_answers(built, tmp_path):
    """The values of the notebook's example, hard-coded: public tests pass, hidden ones do not."""
    student, bundle, solution = built["a3_tune_gain"]
    ref = _grade(bundle, solution)
    assert ref.score == ref.possible
    sub = _with_cells(student, tmp_path / student.name, replace={
        "def admissible_gains(z0, u_max):": "def admissible_gains(z0, u_max):\n    return 0.2890, 1.3260",
        "def max_abs_u(lam, z0):": "def max_abs_u(lam, z0):\n    return float(np.max(np.abs(u_true(lam, t, Z0))))",
    })
    report = _grade(bundle, sub)
    assert report.scores()["q3"][0] == 0 and report.scores()["q2"][0] == 0, report.table()
    _zero(report)


def test_cheat_copying_the_network_instead_of_solving_the_milp(built, tmp_path):
    """milp_max by evaluating the network on a grid or at the box's corners; a program that pins y to nothing."""
    student, bundle, _ = built["a2_encode_by_hand"]
    grid = ("def milp_max(W1, b1, W2, b2, lo, hi):\n"
            "    g = np.stack(np.meshgrid(*[np.linspace(l, h, 301) for l, h in zip(lo, hi)]), -1).reshape(-1, len(lo))\n"
            "    y = forward(W1, b1, W2, b2, g)\n"
            "    return float(y.max()), g[np.argmax(y)]")
    corner = ("def milp_max(W1, b1, W2, b2, lo, hi):\n"
              "    import itertools\n"
              "    c = np.array(list(itertools.product(*zip(lo, hi))))\n"
              "    y = forward(W1, b1, W2, b2, c)\n"
              "    return float(y.max()), c[np.argmax(y)]")
    no_program = ("def bigm_milp(W1, b1, W2, b2, lo, hi):\n"
                  "    n, k = len(lo), len(b1)\n"
                  "    N = n + 2 * k + 1\n"
                  "    return dict(A=np.zeros((1, N)), row_lo=[0.0], row_hi=[0.0],\n"
                  "                var_lo=np.r_[lo, np.zeros(2 * k), -1e9], var_hi=np.r_[hi, np.ones(2 * k), 1e9],\n"
                  "                integrality=np.r_[np.zeros(n + k), np.ones(k), 0].astype(int))")
    for cheat in (grid, corner):
        report = _grade(bundle, _with_cells(student, tmp_path / "m" / student.name,
                                            replace={"def milp_max(W1, b1, W2, b2, lo, hi):": cheat}))
        assert report.scores()["q3"][0] == 0, report.table()
        _zero(report)
    _zero(_grade(bundle, _with_cells(student, tmp_path / "p" / student.name,
                                     replace={"def bigm_milp(W1, b1, W2, b2, lo, hi):": no_program})))


def test_cheat_returning_objects_that_equal_anything(built, tmp_path):
    student, bundle, _ = built["a1_derive_phi"]
    anything = ("class Anything(np.ndarray):\n"
                "    def __eq__(self, other):\n        return True\n"
                "def phi(z, v):\n    return np.zeros(np.shape(v)).view(Anything)")
    _zero(_grade(bundle, _with_cells(student, tmp_path / student.name, replace={"def phi(z, v):": anything})))


def test_killing_the_kernel_or_looping_forever_scores_zero(built, tmp_path):
    student, bundle, _ = built["a1_derive_phi"]
    dead = _grade(bundle, _with_cells(student, tmp_path / "d" / student.name, before_end=["import os\nos._exit(1)"]))
    _zero(dead)
    assert dead.error
    loop = _grade(bundle, _with_cells(student, tmp_path / "l" / student.name, before_end=["while True:\n    pass"]),
                  cell_timeout=3, total_timeout=60)
    _zero(loop)
    assert any("Timeout" in e for e in loop.cell_errors), loop.table()


def test_a_cell_that_raises_costs_the_points_it_affects(built, tmp_path):
    """The reference solution with one answer cell raising: that question fails, the others score."""
    _, bundle, solution = built["a1_derive_phi"]
    nb = _nb(solution)
    for cell in nb.cells:
        if cell.cell_type == "code" and cell.source.startswith("def v_interval(z):"):
            cell.source = "raise RuntimeError('unfinished')\n" + cell.source
    sub = tmp_path / solution.name
    nbformat.write(nb, sub)
    report = _grade(bundle, sub)
    assert any("RuntimeError" in e for e in report.cell_errors), report.table()
    scores = report.scores()
    assert scores["q3"][0] == 0 and scores["q1"][0] == scores["q1"][1] > 0, report.table()


def test_cheat_estimates_instead_of_certificates(built, tmp_path):
    """Enclosures from samples of each box, ε from samples: both miss the worst point."""
    student, bundle, solution = built["a4_certify_eps"]
    nb = _nb(solution)
    sampled_enclosure = ("def phi_enclosure(lo, hi):\n"
                         "    lo, hi = np.asarray(lo, float), np.asarray(hi, float)\n"
                         "    u = np.random.default_rng(0).uniform(size=(len(lo), 200, 3))\n"
                         "    pts = lo[:, None, :] + u * (hi - lo)[:, None, :]\n"
                         "    vals = phi(pts.reshape(-1, 3)).reshape(len(lo), 200)\n"
                         "    return vals.min(axis=1, keepdims=True), vals.max(axis=1, keepdims=True)")
    sampled_eps = ("def certified_eps(weights, biases):\n"
                   "    net = fl.ReLUNet([np.asarray(w, float) for w in weights], [np.asarray(b, float) for b in biases])\n"
                   "    X = np.random.default_rng(0).uniform(LO, HI, size=(20000, 3))\n"
                   "    e = float(np.max(np.abs(phi(X) - net(X))))\n"
                   "    return e, e")
    for cell in nb.cells:
        if cell.cell_type == "code" and cell.source.startswith("def phi_interval(X):"):
            cell.source = cell.source.split("def phi_enclosure")[0] + sampled_enclosure
        elif cell.cell_type == "code" and cell.source.startswith("def certified_eps("):
            cell.source = sampled_eps + "\n" + cell.source.split("# END SOLUTION", 1)[1]
    sub = tmp_path / solution.name
    nbformat.write(nb, sub)
    report = _grade(bundle, sub)
    scores = report.scores()
    assert scores["q2"][0] == 0 and scores["q3"][0] == 0, report.table()
    assert scores["q1"][0] == scores["q1"][1], "the honest part keeps its points"


def _a5_closed_loop(controller: str, extra: str = "") -> str:
    """A student's ``closed_loop`` cell for a5 that simulates ``controller`` (source text) with ``extra`` options."""
    return ("def closed_loop(z0):\n"
            f"    log = fl.simulate(cart, {controller}, t_final=T_FINAL, ts=TS, z0=z0{extra})\n"
            "    return dict(t=log.t, z=log.z, v=log.v, u=log.u)")


def test_cheat_the_nominal_law_without_the_barrier(built, tmp_path):
    """A controller that ignores the wall: its trajectory is the plant's, but not safe."""
    _, bundle, solution = built["a5_clf_cbf_wall"]
    nominal = _a5_closed_loop("lambda z: np.array([-z[0] - z[1]])")
    report = _grade(bundle, _with_cells(solution, tmp_path / solution.name, before_end=[nominal]))
    assert report.scores()["q2"][0] == 0 and report.scores()["q1"][0] == report.scores()["q1"][1], report.table()


def test_cheat_a_closed_form_law_without_the_network(built, tmp_path):
    """A one-line law that brakes for the barrier in closed form, with no network and no eps in the loop.

    Its trajectories are the plant's and stay in the safe set from the slow starts; the grader's start
    where the braking needs nearly the whole input shows that it ignores the network constraint.
    """
    _, bundle, solution = built["a5_clf_cbf_wall"]
    law = "lambda z: np.array([min(-z[0] - z[1], (4 * (0.4 - z[0] - 0.4 * z[1]) - z[1]) / 0.4)])"
    closed_form = _a5_closed_loop(law, ", hold='u'")
    report = _grade(bundle, _with_cells(solution, tmp_path / solution.name, before_end=[closed_form]))
    assert report.scores()["q2"][0] == 0 and report.scores()["q1"][0] == report.scores()["q1"][1], report.table()


def test_a5_either_hold_scores_full(built, tmp_path):
    """Chapter 6 holds u, chapter 1 holds v: a5's grader accepts the reference controller under either hold."""
    _, bundle, solution = built["a5_clf_cbf_wall"]
    hold_v = _a5_closed_loop("ctrl", ", net=net, hold='v'")
    report = _grade(bundle, _with_cells(solution, tmp_path / solution.name, before_end=[hold_v]))
    assert report.scores()["q2"][0] == report.scores()["q2"][1], report.table()


A6_PINNED_TO_MPC = """
_honest_program = mpc_program
def mpc_program(weights, biases, eps, z0):
    # the answer of one library call: fl.MPC's plan, pinned in the program's bounds
    p = _honest_program(weights, biases, eps, z0)
    net = fl.ReLUNet([np.asarray(w, float) for w in weights], [np.asarray(b, float) for b in biases])
    step = fl.MPC(cart, net, eps, horizon=N_P, ts=TS, Q=Q, R=R)(np.asarray(z0, float), np.zeros(2))
    w = np.r_[np.asarray(step.z_pred, float).ravel(), np.asarray(step.v_pred, float).ravel()]
    p["var_lo"][:len(w)], p["var_hi"][:len(w)] = w, w
    return p
"""

A6_NO_NETWORK = """
_honest_program = mpc_program
def mpc_program(weights, biases, eps, z0):
    # the program without the network constraint: the last row of every step made free
    p = _honest_program(weights, biases, eps, z0)
    k = len(np.asarray(biases[0]))
    for j in range(N_P):
        r = (j + 1) * (2 + 3 * k + 1) - 1
        p["row_lo"][r], p["row_hi"][r] = -np.inf, np.inf
    return p
"""


def test_cheat_the_horizon_program_from_the_library_or_without_the_network(built, tmp_path):
    """fl.MPC's plan pinned in the program, or the program without its network rows: q2 scores 0."""
    _, bundle, solution = built["a6_mpc_horizon"]
    for i, cheat in enumerate((A6_PINNED_TO_MPC, A6_NO_NETWORK)):
        report = _grade(bundle, _with_cells(solution, tmp_path / str(i) / solution.name, before_end=[cheat]))
        assert report.scores()["q2"][0] == 0 and report.scores()["q1"][0] == report.scores()["q1"][1], report.table()


def test_cheat_a_bracket_from_zero_to_the_certified_upper_end(built, tmp_path):
    """``(0, upper)`` is a bracket of every ε but not the certified one: the lower end must be an attained error."""
    student, bundle, solution = built["a4_certify_eps"]
    nb = _nb(solution)
    cheat = ("def certified_eps(weights, biases):\n"
             "    net = fl.ReLUNet([np.asarray(w, float) for w in weights], [np.asarray(b, float) for b in biases])\n"
             "    bracket = fl.certify_error(phi, net, LO, HI, f_interval=phi_interval)\n"
             "    return 0.0, float(bracket.upper[0])")
    for cell in nb.cells:
        if cell.cell_type == "code" and cell.source.startswith("def certified_eps("):
            cell.source = cheat + "\n" + cell.source.split("# END SOLUTION", 1)[1]
    sub = tmp_path / solution.name
    nbformat.write(nb, sub)
    report = _grade(bundle, sub)
    scores = report.scores()
    assert scores["q3"][0] == 0, report.table()
    assert scores["q1"][0] == scores["q1"][1] and scores["q2"][0] == scores["q2"][1], "the honest part keeps its points"
