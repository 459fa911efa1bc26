"""A hostile class, graded in one batch: every attack scores no more than a blank, no honest score moves.

The submissions are graded together, in one call of ``flnotes.grading.batch`` on a folder of
downloads with arbitrary names, two assignments mixed: the reference solutions (renamed, before
and after the attacks), the students' blank notebook, files that are not notebooks, and one
submission per attack the grader must withstand:

* reading the masters, the built solutions or the bundles from the file system and executing them;
* reading a classmate's submission (or the bundle) through ``/proc`` (command lines, working folders);
* binding globals to module objects whose import would run code in the grader or end it;
* rewriting the bundles, the gradebook and the reports; a symbolic link to the checkout;
* a detached (``setsid``) process that outlives the kernel and rewrites the reports;
* empty arrays (``np.allclose`` of an empty array with anything is True);
* printing 2 GB; children that take 800 MB each; a bounded fork storm; filling the file systems;
* a function that sleeps only when the grader calls it; an answer too large to be data;
* killing the sandbox's runner.

The sandbox is bubblewrap; ``make test`` (and ``.ci/run``) installs it when it is missing. When
it is neither installed nor installable, these tests are skipped with the reason in the report.
"""
from __future__ import annotations

import csv
import hashlib
import os
import resource
import textwrap
from pathlib import Path

import nbformat
import pytest

from flnotes import grading

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "flnotes-attack-" + hashlib.sha1(str(os.getpid()).encode()).hexdigest()[:10]

pytestmark = pytest.mark.skipif(grading.bwrap_status() is not None,
                                reason=f"no sandbox: {grading.bwrap_status()} (`make test` installs bubblewrap)")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """Bundles (and their SHA256SUMS) of assignments 1 and 3, their students' and reference notebooks."""
    out = tmp_path_factory.mktemp("assignments")
    for name in ("a1_derive_phi", "a3_tune_gain"):
        grading.assign(grading.MASTER_DIR / f"{name}.ipynb", out, run_tests=False)
    return out


def _attack(built: Path, *cells: str, name: str = "a1_derive_phi") -> nbformat.NotebookNode:
    """A notebook with the metadata of the students' version of ``name`` and only the given cells."""
    student = nbformat.read(built / "student" / f"{name}.ipynb", as_version=4)
    nb = nbformat.v4.new_notebook(metadata=student.metadata)
    nb.cells = [nbformat.v4.new_code_cell(textwrap.dedent(c)) for c in cells]
    return nb


EXEC_SOLUTIONS = r'''
def take(path):
    # the reference answers of a1, executed: what a grader without a sandbox would hand over
    global found
    try:
        text = open(path, "rb").read()
    except Exception:
        return
    if path.endswith(".zip"):
        found.append(path)
        return
    try:
        nb = json.loads(text)
    except Exception:
        return
    for c in nb.get("cells", []):
        s = "".join(c.get("source", ""))
        if s.startswith(("def phi(", "def theta_ddot_error(", "def v_interval(")):
            exec(s.replace("# BEGIN SOLUTION", "").replace("# END SOLUTION", ""), globals())
            found.append(path)
'''


def _attacks(built: Path, out_dir: Path) -> dict[str, nbformat.NotebookNode]:
    root, b = str(ROOT), str(built)
    head = "import os, sys, json, glob\nimport numpy as np\nm, l, g, b, u_max = 0.5, 0.6, 9.81, 0.1, 3.0\nfound = []\n"
    return {
        "read_masters": _attack(built, head + EXEC_SOLUTIONS + f'''
for pat in ["{root}/book/assignments/master/*.ipynb", "{b}/solution/*.ipynb", "{b}/autograder/*.zip",
            "{root}/_build/assignments/solution/*.ipynb", "/submission/../*.ipynb"]:
    for f in glob.glob(pat, recursive=True):
        take(f)
for top in sorted(set(os.listdir("/")) - {"usr", "proc", "sys", "dev"}):  # everything near the top
    for depth in range(0, 5):
        for f in glob.glob("/" + "/".join([top] + ["*"] * depth)):
            if f.endswith((".ipynb", ".zip")):
                take(f)
print("found", found)
'''),
        "proc_snoop": _attack(built, head + EXEC_SOLUTIONS + '''
for pid in os.listdir("/proc"):
    if not pid.isdigit():
        continue
    try:
        args = open(f"/proc/{pid}/cmdline", "rb").read().split(b"\\0")
    except Exception:
        continue
    for a in args:
        a = a.decode(errors="replace")
        if a.endswith((".ipynb", ".zip")):
            take(a if a.startswith("/") else f"/proc/{pid}/cwd/{a}")
    for f in glob.glob(f"/proc/{pid}/cwd/*") + glob.glob(f"/proc/{pid}/root/tmp/*/*.ipynb"):
        take(f)
print("found", found)
'''),
        "module_globals": _attack(built, f'''
import types, sys
np = types.ModuleType("{TOKEN.replace('-', '_')}_marker")
fl = types.ModuleType("antigravity")
exiter = types.ModuleType("{TOKEN.replace('-', '_')}_exit")
phi = types.ModuleType("this")
os_ = sys.modules["os"]
def v_interval(z):
    return sys
'''),
        "rewrite_bundles_and_reports": _attack(built, f'''
import os, glob, zipfile
hits = []
for pat in ["{b}/autograder/*", "{out_dir}/*", "{out_dir}/reports/*", "/submission/../*/SHA256SUMS", "/tmp/*/*.zip"]:
    for f in glob.glob(pat, recursive=True):
        try:
            open(f, "w").write("phi = lambda z, v: 0  # full marks")
            hits.append(f)
        except Exception as exc:
            hits.append(repr(exc))
for d in ["{b}/autograder", "{out_dir}/reports"]:
    try:
        os.makedirs(d, exist_ok=True)
        open(d + "/injected.txt", "w").write("x")
    except Exception as exc:
        hits.append(repr(exc))
os.symlink("{root}", "/submission/checkout")
print(hits)
'''),
        "setsid_detached": _attack(built, f'''
import subprocess, sys, os
loop = """
import glob, os, time, sys
for _ in range(600):
    for f in glob.glob('{out_dir}/reports/*') + glob.glob('{out_dir}/gradebook.csv'):
        try:
            open(f, 'w').write('score: 100/100')
        except Exception:
            pass
    time.sleep(0.2)
"""
subprocess.Popen([sys.executable, "-c", loop, "{TOKEN}"], start_new_session=True,
                 stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
if os.fork() == 0:
    os.setsid()
    os.execv("/bin/sh", ["/bin/sh", "-c", "sleep 600", "{TOKEN}"])
'''),
        "empty_arrays": _attack(built, '''
import numpy as np
def phi(z, v):
    return np.zeros(0)
def theta_ddot_error(z, v, b_model):
    return np.zeros(0)
def v_interval(z):
    return np.zeros(0), np.zeros(0)
'''),
        "print_2gb": _attack(built, '''
import sys
chunk = "x" * (1 << 20)
for _ in range(2048):
    sys.stdout.write(chunk)
''', '''
import os
os.write(1, b"y" * (64 << 20))
'''),
        "memory_children": _attack(built, f'''
import subprocess, sys, time
code = "b = bytearray(800 << 20); b[::4096] = b'x' * len(b[::4096]); import time; time.sleep(120)"
kids = [subprocess.Popen([sys.executable, "-c", code, "{TOKEN}"]) for _ in range(3)]
time.sleep(15)
'''),
        "fork_storm": _attack(built, f'''
import os
for _ in range(300):
    try:
        if os.fork() == 0:
            os.execv("/bin/sh", ["/bin/sh", "-c", "sleep 600", "{TOKEN}"])
    except OSError:
        break
'''),
        "sleep_under_grader": _attack(built, '''
import inspect, time
import numpy as np
def _graded():
    return any("__flnotes_grading__" in f.function for f in inspect.stack())
def phi(z, v):
    if _graded():
        time.sleep(10_000)
    return np.zeros(np.shape(v))
def theta_ddot_error(z, v, b_model):
    if _graded():
        time.sleep(10_000)
    return np.zeros(np.shape(v))
'''),
        "huge_answer": _attack(built, '''
import numpy as np
def phi(z, v):
    return np.zeros(6_000_000)
def v_interval(z):
    return [[[[[[[[[[[[[[[[[[[[[[[[0]]]]]]]]]]]]]]]]]]]]]]], 0
'''),
        "fill_memory_file_systems": _attack(built, '''
import os
for d in ("/", "/dev", "/dev/shm", "/tmp", "/submission"):
    try:
        with open(os.path.join(d, "fill"), "wb") as fh:
            for _ in range(2048):
                fh.write(b"\\0" * (1 << 20))
    except OSError:
        pass
'''),
        "kill_runner": _attack(built, '''
import os, signal
os.kill(os.getppid(), signal.SIGKILL)
'''),
    }


#: attacks graded in one submission each (one sandbox per line keeps the batch short); a group's
#: notebook holds each attack in its own cell, so that one failing does not stop the next
GROUPS = {
    "files_masters_proc_bundles": ("read_masters", "proc_snoop", "rewrite_bundles_and_reports"),
    "setsid_fork_storm_fill_file_systems": ("setsid_detached", "fork_storm", "fill_memory_file_systems"),
}


def _grouped(attacks: dict[str, nbformat.NotebookNode]) -> dict[str, nbformat.NotebookNode]:
    out = {k: v for k, v in attacks.items() if not any(k in g for g in GROUPS.values())}
    for name, members in GROUPS.items():
        nb = attacks[members[0]]
        nb.cells = [c for m in members for c in attacks[m].cells]
        out[name] = nb
    return out


def _procs_with(token: str) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                if token.encode() in Path(f"/proc/{d}/cmdline").read_bytes():
                    out.append(int(d))
            except OSError:
                pass
    return out


#: the batch's budgets: an honest submission (a1, a3) took 13 to 15 s in all, its longest cell less, when
#: graded in this test on a loaded machine (load average 3 on 2 cores); about 3 times that for the
#: submission, and its whole honest time for one cell or call. The attacks that sleep or loop end at these.
CELL_TIMEOUT, TOTAL_TIMEOUT = 15, 40


def test_a_hostile_class_in_one_batch(built, tmp_path, monkeypatch):
    sub, out = tmp_path / "downloads", tmp_path / "grades"
    sub.mkdir()
    # the grader must never import a module named by the kernel: these would leave a mark or end the batch
    mods = tmp_path / "mods"
    mods.mkdir()
    marker = tmp_path / "imported.txt"
    (mods / f"{TOKEN.replace('-', '_')}_marker.py").write_text(f"open({str(marker)!r}, 'w').write('imported')\n")
    (mods / f"{TOKEN.replace('-', '_')}_exit.py").write_text("import sys\nsys.exit(3)\n")
    monkeypatch.syspath_prepend(str(mods))

    solution = built / "solution" / "a1_derive_phi.ipynb"
    honest = {"000 Jane Doe - attempt 2 (1).ipynb": solution,          # renamed, as an LMS does
              "zzz_last_student_download": solution,                   # no extension at all
              "a3 by Sam.json": built / "solution" / "a3_tune_gain.ipynb"}
    for name, src in honest.items():
        (sub / name).write_bytes(src.read_bytes())
    # an honest notebook without otter's metadata: known by its otter.Notebook("a1_....ipynb") line alone
    bare = nbformat.read(solution, as_version=4)
    bare.metadata.pop("otter", None)
    nbformat.write(bare, sub / "zzz_last_student_download")
    # the blank's name differs from an honest one only where report names were once cut to the same file
    blank_name = "000 Jane Doe - attempt 2 [1].ipynb"
    (sub / blank_name).write_bytes((built / "student" / "a1_derive_phi.ipynb").read_bytes())
    (sub / "broken.ipynb").write_text('{"cells": [ not json')
    (sub / "notes.txt").write_text("my answers are in the pdf")
    unknown = _attack(built, "x = 1")
    unknown.metadata["otter"]["assignment_name"] = "a9_unknown"
    nbformat.write(unknown, sub / "unknown.ipynb")
    attacks = _grouped(_attacks(built, out))
    for name, nb in attacks.items():
        nbformat.write(nb, sub / f"{name}.ipynb")
    bundles_before = {p.name: p.read_bytes() for p in (built / "autograder").iterdir()}
    premise = grading.MASTER_DIR / "a1_derive_phi.ipynb"
    assert premise.is_file() and (built / "solution" / "a1_derive_phi.ipynb").is_file(), \
        "premise: the solutions the attacks look for exist on the grading machine"

    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    reports = grading.batch(built / "autograder", sub, out, cell_timeout=CELL_TIMEOUT, total_timeout=TOTAL_TIMEOUT,
                            limits=grading.Limits(memory_mb=3072, tree_memory_mb=1500, processes=64), verbose=True)
    rss_growth_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before) / 1024
    by = {r.submission: r for r in reports}
    for r in reports:
        print(r.table(messages=False))

    # every file has a line in the gradebook and a report
    rows = (out / "gradebook.csv").read_text().splitlines()
    assert len(rows) == 1 + len(list(sub.iterdir())) == 1 + len(reports)
    assert len(list((out / "reports").iterdir())) == len(reports)
    # the honest ones: full marks, before and after the attacks, under any file name
    for name in honest:
        r = by[name]
        assert r.possible > 0 and r.score == r.possible and not r.error, r.table()
    assert by["000 Jane Doe - attempt 2 (1).ipynb"].assignment == "a1_derive_phi"
    assert by["a3 by Sam.json"].assignment == "a3_tune_gain"
    blank = by[blank_name]
    assert blank.score == 0 and blank.possible > 0
    for name in ("broken.ipynb", "notes.txt", "unknown.ipynb"):
        assert by[name].score == 0 and by[name].error, by[name].table()
    assert "not a readable Jupyter notebook" in by["broken.ipynb"].error
    assert "not recognized" in by["unknown.ipynb"].error
    # every attack: no more than the blank, graded to the end
    for name in attacks:
        r = by[f"{name}.ipynb"]
        assert r.assignment == "a1_derive_phi" and r.possible == blank.possible, r.table()
        assert r.score <= blank.score, r.table()
    # the file-system attacks ran to their end (they found nothing to take, not too little time)
    files = by["files_masters_proc_bundles.ipynb"]
    assert not any("Timeout" in e for e in files.cell_errors) and not files.error, files.table()
    # the time budget covers the calls of the student's functions too
    assert by["sleep_under_grader.ipynb"].seconds <= TOTAL_TIMEOUT + 60, by["sleep_under_grader.ipynb"].table()
    # nothing the kernel named was imported here; the bundles and the other reports are untouched
    assert not marker.exists()
    assert {p.name: p.read_bytes() for p in (built / "autograder").iterdir()} == bundles_before
    assert (ROOT / "book" / "assignments" / "master").is_dir()
    book = {row["file"]: row for row in csv.DictReader((out / "gradebook.csv").open())}
    for name in honest:
        row = book[name]
        assert row["score"] == row["possible"] == f"{by[name].possible:g}" and row["error"] == "", row
        last = (out / row["report"]).read_text().strip().splitlines()[-1]
        assert last == f"score: {row['possible']}/{row['possible']}", last
    for p in (out / "reports").iterdir():
        assert "100/100" not in p.read_text()
    assert "100/100" not in (out / "gradebook.csv").read_text()
    # no process of any submission survives its grading; the grader's memory did not follow the output
    assert not _procs_with(TOKEN), "a process started by a submission outlived its grading"
    assert rss_growth_mb < 400, f"the grader grew by {rss_growth_mb:.0f} MB"


def test_without_a_sandbox_the_grader_refuses_unless_told_and_says_so(built, monkeypatch, tmp_path):
    from flnotes.grading import sandbox

    monkeypatch.setitem(sandbox._STATUS, "bwrap", "bwrap is not installed (simulated)")
    bundle = built / "autograder" / "a1_derive_phi-autograder.zip"
    solution = built / "solution" / "a1_derive_phi.ipynb"
    with pytest.raises(grading.SandboxUnavailable, match="refuses"):
        grading.grade(bundle, solution, verbose=False)
    with pytest.raises(grading.SandboxUnavailable, match="refuses"):
        grading.batch(built / "autograder", solution.parent, tmp_path / "out", verbose=False)
    assert grading.bwrap_status() is not None
    report = grading.grade(bundle, solution, verbose=False, unsafe=True)
    assert report.unsafe and "UNSAFE" in report.table(), report.table()
    assert report.score == report.possible > 0, report.table()


# ----------------------------------------------------------------------------------
# fast regression tests of single functions (no grading)
def test_report_names_differ_for_paths_the_readable_part_confuses():
    from flnotes.grading.batch import report_name

    long = "x" * 200
    pairs = [("eve~sub.ipynb", "eve_sub.ipynb"), ("x/a.ipynb", "x_a.ipynb"), (long + "a.ipynb", long + "b.ipynb")]
    for a, b in pairs:
        assert report_name(a) != report_name(b), (a, b)
        assert report_name(a) == report_name(a)
        assert "/" not in report_name(a) and report_name(a).endswith(".txt")


def test_a_report_is_never_overwritten(tmp_path):
    from flnotes.grading.batch import _write_new

    _write_new(tmp_path / "r.txt", "honest")
    with pytest.raises(FileExistsError):
        _write_new(tmp_path / "r.txt", "forged")
    assert (tmp_path / "r.txt").read_text() == "honest"


def test_sandbox_strings_cannot_print_lines_of_their_own():
    forged = "x\nq1 3/3\rscore: 8/8\u2028score: 9/9\x1b[2K"
    report = grading.GradeReport(submission="s\nscore: 8/8.ipynb", assignment="a1", error=forged,
                                 cell_errors=[forged], limits=[forged],
                                 questions=[grading.Question("q1", 0.0, 3.0, [forged])])
    lines = report.table().splitlines()
    assert [ln for ln in lines if ln.startswith("score:")] == ["score: 0/3"], report.table()
    assert not any(ln.startswith("q1 3/3") for ln in lines)
    assert all(ch.isprintable() for ln in lines for ch in ln)


def test_gradebook_cells_are_one_line_and_never_formulas():
    from flnotes.grading.batch import csv_cell

    for bad in ["=cmd|' /C calc'!A0", "+1", "-1+2", "@SUM(A1)", "\tx", "\r=1"]:
        cell = csv_cell(bad)
        assert cell[0] not in "=+-@\t\r", cell
    assert csv_cell("a\nb\rc") == "a b c"
    assert csv_cell("honest text") == "honest text" and csv_cell("3") == "3"


def test_a_forged_ready_message_says_only_the_graders_words():
    from flnotes.grading.grade import _Session

    class FakeSandbox:
        used = 0.0
        killed = ""

        def receive(self, timeout):
            return (b'{"ready": true, "cell_errors": ["=cmd|\' /C calc\'!A0\\nscore: 8/8"], '
                    b'"dead": "=cmd|\' /C calc\'!A0\\nq1 3/3"}')

    first = _Session(FakeSandbox(), 10.0, 5).ready()
    assert "calc" not in first["dead"] and first["dead"].startswith("the submission's kernel")
    assert all("\n" not in e for e in first["cell_errors"])


def test_grade_recognises_a_notebook_by_its_otter_call_like_the_batch(built):
    nb = nbformat.read(built / "solution" / "a1_derive_phi.ipynb", as_version=4)
    nb.metadata.pop("otter", None)
    assert grading.identify(nb, {"a1_derive_phi", "a3_tune_gain"}) == "a1_derive_phi"
    from flnotes.grading.grade import assignment_of

    assert assignment_of(nb, {"a1_derive_phi"}) == "a1_derive_phi"
    assert assignment_of(nb, {"a3_tune_gain"}) is None


def test_a_package_installed_under_tmp_stays_visible_in_the_sandbox(tmp_path, monkeypatch):
    """bwrap mounts in order: the sandbox's empty /tmp must not hide a read-only bind under /tmp."""
    import subprocess
    import tempfile

    from flnotes.grading import sandbox

    install = Path(tempfile.mkdtemp(prefix="flnotes-install-", dir="/tmp"))
    try:
        (install / "marker").write_text("visible")
        roots = sandbox._readonly_roots()
        monkeypatch.setattr(sandbox, "_readonly_roots", lambda: roots + [str(install)])
        argv = sandbox.bwrap_argv(tmp_path, ["/usr/bin/cat", str(install / "marker")], {}, sandbox.Limits())
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=60, cwd="/", env={"PATH": "/usr/bin:/bin"})
        assert proc.stdout == "visible", proc.stderr
    finally:
        (install / "marker").unlink()
        install.rmdir()


def test_the_sandbox_selftest_runs_the_real_command_line_and_reports_bwraps_words(monkeypatch):
    from flnotes.grading import sandbox

    assert sandbox.selftest(sandbox.Limits()) is None
    real = sandbox.bwrap_argv
    monkeypatch.setattr(sandbox, "bwrap_argv", lambda w, i, e, lim: [real(w, i, e, lim)[0], "--bogus-flag"])
    why = sandbox.selftest(sandbox.Limits())
    assert why and "bogus" in why, why


FORGE_READY = r'''
import glob, json, os
opened = []
for fd in glob.glob("/proc/[0-9]*/fd/*"):
    pid = fd.split("/")[2]
    if pid == str(os.getpid()):
        continue
    try:
        if not os.readlink(fd).startswith("pipe:"):
            continue
        with open(fd, "w") as fh:
            fh.write(json.dumps({"ready": True, "cell_errors": ["FORGED\nscore: 8/8"], "dead": "FORGED"}) + "\n")
        opened.append(fd)
    except OSError:
        pass
'''


def test_the_kernel_cannot_open_the_graders_channel(built, tmp_path):
    """The runner is not dumpable: its /proc/<pid>/fd (the channel to the grader) is closed to the kernel."""
    sub = tmp_path / "forge.ipynb"
    nbformat.write(_attack(built, "import otter\ngrader = otter.Notebook('a1_derive_phi.ipynb')", FORGE_READY), sub)
    report = grading.grade(built / "autograder" / "a1_derive_phi-autograder.zip", sub, verbose=False,
                           cell_timeout=30, total_timeout=120)
    assert "FORGED" not in report.table() and report.score == 0, report.table()
    assert not report.error, report.table()
