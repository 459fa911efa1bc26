"""Building the assignments (otter assign), recording and checking the bundles, the two editions.

``assign_all`` runs ``otter assign`` on every master notebook and writes, under one folder
(``make assignments``: ``_build/assignments``), the students' notebooks, the autograder
bundles (read-only, their SHA-256 recorded in :data:`MANIFEST`) and the reference
solutions; it refreshes the students' pages of the book. The students' notebooks install
the course package from the students' repository named once, in ``_config.yml``
(``repository: url``), which is also where the book's launch buttons point.
``load_bundle`` reads a bundle only if its hash matches the record. ``instructor_toc``
writes the instructor edition's table of contents; ``students_edition`` writes the tree
published for students (no masters, no hidden tests, no rubrics, no instructor guide).
"""
from __future__ import annotations

import ast
import hashlib
import io
import json
import re
import shutil
import stat
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

__all__ = ["ROOT", "MASTER_DIR", "MANIFEST", "Bundle", "assign", "assign_all", "student_page", "load_bundle",
           "bundle_tests", "load_bundle_tests", "students_repository", "instructor_toc", "students_edition",
           "hidden_test_lines"]

#: the checkout's top folder and the master notebooks in it
ROOT = Path(__file__).resolve().parents[2]
MASTER_DIR = ROOT / "book" / "assignments" / "master"
#: the record of the bundles' SHA-256, beside them (``sha256sum -c`` reads it too)
MANIFEST = "SHA256SUMS"
#: what the students' edition leaves out (paths relative to the checkout)
INSTRUCTOR_ONLY = ("book/assignments/master", "tests", ".ci", ".git", ".venv", "_build", "flnotes.egg-info")


def _otter_cmd() -> list[str]:
    return [sys.executable, "-m", "otter"]


def students_repository(config: str | Path = ROOT / "_config.yml") -> str:
    """The students' repository (``repository: url`` of ``_config.yml``): launch buttons and install line."""
    import yaml

    url = (yaml.safe_load(Path(config).read_text(encoding="utf-8")).get("repository") or {}).get("url")
    if not isinstance(url, str) or not re.fullmatch(r"https://[\w.-]+/[\w./-]+", url):
        raise ValueError(f"{config}: repository.url={url!r} must be the https address of the students' repository")
    return url


#: the package's install line in a notebook (``"flnotes @ git+..."``, ``"flnotes[book] @ git+..."``)
_INSTALL = re.compile(r'(flnotes(?:\[[\w,]+\])? @ git\+)https://[^"\\\s]+')


def assign(master: str | Path, out_dir: str | Path, *, run_tests: bool = True) -> tuple[Path, Path]:
    """Run ``otter assign`` on one master notebook.

    Writes ``out_dir/student/<name>.ipynb`` (the students' version, installing the package from
    :func:`students_repository`), ``out_dir/autograder/<name>-autograder.zip`` (the bundle with all
    the tests, read-only) and ``out_dir/solution/<name>.ipynb`` (the reference solution as a
    submission would look) and returns the first two paths. With ``run_tests`` otter first runs the
    master notebook and its tests, so a reference solution that fails its own tests stops here.
    """
    import nbformat

    master, out_dir = Path(master).resolve(), Path(out_dir).resolve()
    if not master.is_file() or master.suffix != ".ipynb":
        raise ValueError(f"master={master} is not a notebook file (.ipynb)")
    name = master.stem
    url = students_repository()
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
        for sub in ("student", "autograder", "solution"):
            (out_dir / sub).mkdir(parents=True, exist_ok=True)
        shutil.copy2(Path(tmp, "autograder", master.name), out_dir / "solution" / master.name)
        student = out_dir / "student" / master.name
        nb = nbformat.read(Path(tmp, "student", master.name), as_version=4)
        for cell in nb.cells:
            if cell.cell_type == "code" and "%pip install" in cell.source:
                cell.source = _INSTALL.sub(lambda m: m.group(1) + url, cell.source)
        nbformat.write(nb, student)
        bundle = out_dir / "autograder" / f"{name}-autograder.zip"
        if bundle.exists():
            bundle.chmod(0o644)
        shutil.copyfile(zips[0], bundle)
        bundle.chmod(stat.S_IRUSR | stat.S_IRGRP | stat.S_IROTH)
        _record(bundle)
    return student, bundle


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _record(bundle: Path) -> None:
    manifest = bundle.parent / MANIFEST
    lines = {}
    if manifest.is_file():
        for line in manifest.read_text().splitlines():
            h, _, f = line.partition("  ")
            if f:
                lines[f] = h
    lines[bundle.name] = _sha256(bundle.read_bytes())
    manifest.write_text("".join(f"{h}  {f}\n" for f, h in sorted(lines.items())))


def student_page(student_nb: str | Path, page: str | Path) -> Path:
    """Write the book's page of a students' notebook: no outputs, not executed by the build.

    The answer cells of a students' notebook are ``...``, so the book shows it as it
    is (notebook metadata ``mystnb.execution_mode: off``) instead of running it, and
    nbmake runs it with errors allowed (``execution.allow_errors``).
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
@dataclass(frozen=True)
class Bundle:
    """An autograder bundle, read once into memory after its hash was checked."""

    name: str
    path: str
    data: bytes
    sha256: str


def load_bundle(path: str | Path) -> Bundle:
    """Read a bundle; ValueError unless its SHA-256 is the one recorded beside it at build time."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"autograder={path} does not exist: run `make assignments`")
    data = path.read_bytes()
    manifest = path.parent / MANIFEST
    if not manifest.is_file():
        raise ValueError(f"{manifest} is missing: the bundles cannot be verified; rebuild them with `make assignments`")
    recorded = {f: h for h, _, f in (line.partition("  ") for line in manifest.read_text().splitlines())}
    if recorded.get(path.name) != _sha256(data):
        raise ValueError(f"{path.name} does not match its SHA-256 in {manifest}: the bundle was changed after "
                         "`make assignments` built it; rebuild it, and find out who changed it")
    if not zipfile.is_zipfile(io.BytesIO(data)):
        raise ValueError(f"autograder={path} is not a zip file written by otter assign")
    return Bundle(path.name.removesuffix("-autograder.zip"), str(path), data, _sha256(data))


def bundle_tests(bundle: Bundle) -> tuple[list, dict]:
    """The otter test files of a bundle, parsed without executing them: ``(tests, otter_config)``.

    The tests are fresh objects on every call: one submission's run never reaches another's.
    """
    from otter.test_files.ok_test import OKTestFile

    tests = []
    with zipfile.ZipFile(io.BytesIO(bundle.data)) as zf:
        names = sorted(n for n in zf.namelist() if n.startswith("tests/") and n.endswith(".py"))
        config = json.loads(zf.read("otter_config.json")) if "otter_config.json" in zf.namelist() else {}
        for n in names:
            tree = ast.parse(zf.read(n).decode("utf-8"), filename=n)
            spec = None
            for node in tree.body:
                if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "test" for t in node.targets):
                    spec = ast.literal_eval(node.value)
            if spec is None:
                raise ValueError(f"{bundle.path}:{n} is not an OK-format otter test (no `test = {{...}}`)")
            tests.append(OKTestFile.from_spec(spec, path=n))
    if not tests:
        raise ValueError(f"autograder={bundle.path} holds no tests (tests/*.py)")
    return tests, config


def load_bundle_tests(autograder: str | Path) -> tuple[list, dict]:
    """:func:`bundle_tests` of the verified bundle at ``autograder``."""
    return bundle_tests(load_bundle(autograder))


# ----------------------------------------------------------------------------------
def instructor_toc(toc: str | Path, out: str | Path, master_dir: str | Path = MASTER_DIR) -> Path:
    """The instructor edition's table of contents: students' pages -> master notebooks, plus the guide.

    Every entry of ``toc`` whose file has a namesake in ``master_dir`` (the assignments'
    masters ``a*.ipynb`` and the instructor's ``index.md``) points to the namesake instead;
    every master must replace an entry. The pages of ``master_dir`` without a namesake
    (the instructor guide) are added after the assignments.
    """
    import yaml

    master_dir = Path(master_dir).resolve()
    rel = master_dir.relative_to(ROOT).as_posix()
    masters = {p.stem for p in master_dir.iterdir() if p.suffix in (".ipynb", ".md")}
    data = yaml.safe_load(Path(toc).read_text(encoding="utf-8"))
    swapped: list[str] = []
    index_entry: list[dict] = []

    def walk(entries):
        for e in entries or []:
            f = e.get("file")
            if f and Path(f).name in masters and not f.startswith(rel):
                e["file"] = f"{rel}/{Path(f).name}"
                swapped.append(Path(f).name)
                if Path(f).name == "index":
                    index_entry.append(e)
            walk(e.get("sections"))

    for part in data.get("parts", []):
        walk(part.get("chapters"))
    walk(data.get("chapters"))
    extra = sorted(masters - set(swapped) - {n for n in masters if n.startswith("a") and n[1:2].isdigit()})
    missing = sorted(n for n in masters - set(swapped) if n not in extra)
    if missing or not index_entry:
        raise ValueError(f"{toc} lists the assignments {sorted(swapped)}, the masters are {sorted(masters)}")
    index_entry[0].setdefault("sections", []).extend({"file": f"{rel}/{n}"} for n in extra)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("# written by `python -m flnotes.grading instructor-toc`; do not edit\n"
                   + yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return out


def hidden_test_lines(master_dir: str | Path = MASTER_DIR) -> list[str]:
    """Lines of code of the masters' hidden tests and solutions that no student file may hold.

    The seeds (``default_rng(...)``) and every line of a hidden test that is not an import,
    a blank or a bare constant shared with the students' notebook.
    """
    import nbformat

    lines: set[str] = set()
    for m in sorted(Path(master_dir).glob("a*.ipynb")):
        for cell in nbformat.read(m, as_version=4).cells:
            if cell.cell_type == "code" and "hidden: true" in cell.source:
                body = cell.source.split("# END TEST CONFIG", 1)[-1]
                for line in body.splitlines():
                    s = line.strip()
                    if "default_rng(" in s or (s.startswith("assert ") and len(s) > 30):
                        lines.add(s)
    return sorted(lines)


def students_edition(out_dir: str | Path, root: str | Path = ROOT) -> Path:
    """Write the tree published for students: the checkout without what only instructors may see.

    Leaves out :data:`INSTRUCTOR_ONLY` (the masters with their solutions, hidden tests and
    rubrics, and the instructor guide among them; the tests of the grader; the build and
    environment folders), then checks that no file left holds a reference solution, a
    hidden test or its seed. This is the tree the launch buttons and the students'
    install line point at (``repository: url`` in ``_config.yml``).
    """
    root, out_dir = Path(root).resolve(), Path(out_dir).resolve()
    if out_dir == root or root in out_dir.parents and not str(out_dir.relative_to(root)).startswith("_build"):
        raise ValueError(f"out_dir={out_dir}: write the students' edition outside the checkout or under _build/")
    if out_dir.exists():
        shutil.rmtree(out_dir)
    skip = {root / p for p in INSTRUCTOR_ONLY}

    def ignore(folder, names):
        return [n for n in names if Path(folder, n) in skip or n in ("__pycache__", ".ipynb_checkpoints",
                                                                     ".pytest_cache") or n.endswith(".egg-info")]

    shutil.copytree(root, out_dir, ignore=ignore, symlinks=True)
    url = students_repository(root / "_config.yml")
    for p in list(out_dir.rglob("*.ipynb")) + list(out_dir.rglob("*.md")):
        text = p.read_text(encoding="utf-8")
        new = _INSTALL.sub(lambda m: m.group(1) + url, text)
        if new != text:
            p.write_text(new, encoding="utf-8")
    bad = hidden_test_lines(root / "book" / "assignments" / "master") + ["REFSOL", "# BEGIN SOLUTION", "BEGIN TESTS"]
    leaks = []
    for p in out_dir.rglob("*"):
        if p.is_file() and p.suffix in (".ipynb", ".md", ".yml", ".txt", ".html", ".json", ".py", ".toml", ""):
            text = p.read_text(encoding="utf-8", errors="replace")
            if p.suffix == ".py" and p.parent.name == "grading":
                continue  # the grader's own code names the markers it looks for
            leaks += [f"{p.relative_to(out_dir)}: {b[:60]!r}" for b in bad if b in text]
    if leaks:
        shutil.rmtree(out_dir)
        raise RuntimeError("the students' edition would publish instructor material:\n" + "\n".join(leaks[:20]))
    return out_dir


