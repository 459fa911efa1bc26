"""Grading one submission: the notebook runs in the sandbox, the tests run here on its answers.

The bundle's tests are read (and the bundle's hash checked) before any student code runs.
The submission is copied alone, under its assignment's own name (whatever the file was
called), into a fresh folder that becomes the sandbox's only writable place; the
sandbox runs the notebook (:mod:`flnotes.grading.runner`). Then the tests run in this
process: each student function is a :class:`_Remote` that sends its arguments into the
sandbox and gets back the return value as data (:func:`flnotes.grading.answers.decode`);
each student constant is data too. Module globals of the submission are never imported:
the tests see the grader's own ``numpy``, ``flnotes``, ``cvxpy`` under a fixed table of
names (:data:`TRUSTED_NAMES`). One time budget, ``total_timeout``, covers everything the
submission does: the run of its notebook and every call of its functions by the tests.
"""
from __future__ import annotations

import builtins
import importlib
import json
import re
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from .answers import AnswerError, decode, encode
from .bundles import Bundle, bundle_tests, load_bundle
from .sandbox import SUB, Limits, Sandbox, SandboxUnavailable, bwrap_status

__all__ = ["GradeReport", "Question", "grade", "StudentCodeError", "TRUSTED_NAMES", "read_submission",
           "assignment_of", "clean"]

_INIT = re.compile(r"""otter\.Notebook\(\s*["']([A-Za-z0-9_.-]+)\.ipynb["']""")
#: control characters, and the Unicode line and paragraph separators: a report line stays one line
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def clean(text: Any) -> str:
    """``text`` as one line: every control character (newline, carriage return, escape...) becomes a space.

    Every string that came out of the sandbox goes through this before it is written into a
    report or the gradebook, so that it cannot print a line of its own (a forged ``score:``).
    """
    return _CONTROL.sub(" ", str(text))


def assignment_of(nb, assignments) -> Optional[str]:
    """The assignment a notebook answers, from its content: otter's metadata, else its ``otter.Notebook`` call.

    ``None`` when neither names one of ``assignments``. The batch and :func:`grade` use this one rule.
    """
    meta = nb.metadata.get("otter") if isinstance(nb.metadata.get("otter"), dict) else {}
    name = meta.get("assignment_name")
    if isinstance(name, str) and name in assignments:
        return name
    for cell in nb.cells[:10]:
        m = _INIT.search(cell.source) if cell.cell_type == "code" else None
        if m and m.group(1) in assignments:
            return m.group(1)
    return None

#: names under which the tests see the grader's own modules, when the submission binds that name to a module
TRUSTED_NAMES = {"np": "numpy", "numpy": "numpy", "fl": "flnotes", "flnotes": "flnotes", "cp": "cvxpy",
                 "cvxpy": "cvxpy", "iv": "flnotes.interval", "math": "math"}
_BUILTIN_NAMES = frozenset(dir(builtins))


class StudentCodeError(Exception):
    """A student function raised, returned something that is not data, ran out of time, or the sandbox is gone."""


@dataclass
class Question:
    """One question's result."""

    name: str
    score: float
    possible: float
    failures: list[str] = field(default_factory=list)


@dataclass
class GradeReport:
    """Scores of one submission, per question, and what went wrong."""

    submission: str
    assignment: str = ""
    questions: list[Question] = field(default_factory=list)
    cell_errors: list[str] = field(default_factory=list)
    limits: list[str] = field(default_factory=list)
    error: str = ""
    unsafe: bool = False
    seconds: float = 0.0

    @property
    def score(self) -> float:
        return float(sum(q.score for q in self.questions))

    @property
    def possible(self) -> float:
        return float(sum(q.possible for q in self.questions))

    def scores(self) -> dict[str, tuple[float, float]]:
        """``{question: (score, possible)}``."""
        return {q.name: (q.score, q.possible) for q in self.questions}

    def table(self, messages: bool = True) -> str:
        lines = [f"grading {clean(self.submission)}" + (f" as {clean(self.assignment)}" if self.assignment else "")]
        if self.unsafe:
            lines.append("  UNSAFE: graded WITHOUT a sandbox (--unsafe-no-sandbox); the submission could read and "
                         "change anything this user can")
        lines += [f"  ({clean(x)})" for x in self.limits]
        if self.error:
            lines.append(f"error: {clean(self.error)}")
        if self.cell_errors:
            lines.append(f"{len(self.cell_errors)} cell(s) of the submission raised:")
            lines += [f"  - {clean(e)}" for e in self.cell_errors[:50]]
        width = max([len(q.name) for q in self.questions] + [8])
        lines.append(f"{'question':<{width}}  score")
        for q in self.questions:
            lines.append(f"{clean(q.name):<{width}}  {q.score:g}/{q.possible:g}")
            if messages:
                lines += [f"{'':<{width}}    {clean(m)}" for m in q.failures]
        lines.append(f"score: {self.score:g}/{self.possible:g}")
        return "\n".join(lines)


def _short(text: str, n: int = 300) -> str:
    msg = [m.strip() for m in str(text).splitlines() if m.strip()]
    errs = [m for m in msg if "Error" in m.split(":")[0] or "Exception" in m.split(":")[0]]
    return (errs[0] if errs else msg[-1] if msg else "failed")[:n]  # the first failure: the cause


def read_submission(path: str | Path):
    """The submission as a notebook (nbformat 4), outputs removed; ValueError saying why it is not one."""
    import nbformat

    path = Path(path)
    try:
        if path.stat().st_size > 50 * 1024 * 1024:
            raise ValueError("larger than 50 MB")
        nb = nbformat.read(path, as_version=4)
        if not isinstance(nb.get("cells"), list) or not all(
                isinstance(c, dict) and c.get("cell_type") in ("code", "markdown", "raw")
                and isinstance(c.get("source"), str) for c in nb.cells):
            raise ValueError("its cells are not notebook cells")
    except Exception as exc:  # noqa: BLE001 - any unreadable file is reported as such
        raise ValueError(f"{path.name} is not a readable Jupyter notebook ({type(exc).__name__}: "
                         f"{str(exc).strip().splitlines()[0][:200] if str(exc).strip() else ''})") from None
    for cell in nb.cells:
        if cell.cell_type == "code":
            cell.outputs, cell.execution_count = [], None
    return nb


class _Session:
    """The sandbox of one submission, its time budget and the calls into it."""

    def __init__(self, sandbox: Sandbox, budget: float, cell_timeout: int):
        self.sb, self.budget, self.cell_timeout = sandbox, budget, cell_timeout
        self.n = 0
        self.dead = ""

    def remaining(self) -> float:
        return self.budget - self.sb.used

    def _receive(self, timeout: float) -> bytes:
        try:
            line = self.sb.receive(timeout)
        except TimeoutError:
            if self.remaining() <= 0:
                self.dead = "the submission's time limit was reached"
            else:
                self.dead = f"a call took longer than {self.cell_timeout} s"
            self.sb.kill()
            raise StudentCodeError(self.dead) from None
        if line is None:
            self.dead = self.sb.killed or "the submission's sandbox ended"
            raise StudentCodeError(self.dead)
        return line

    def ready(self) -> dict:
        line = self._receive(self.remaining())
        try:
            msg = json.loads(line)
            if not (isinstance(msg, dict) and msg.get("ready") is True):
                raise ValueError
            errors = [str(e)[:400] for e in msg.get("cell_errors", [])][:200] if isinstance(
                msg.get("cell_errors"), list) else []
            # the runner's words are not trusted (the kernel may reach its channel): a fixed phrase of the grader
            dead = "the submission's kernel died or stopped answering while its notebook ran" if msg.get("dead") else ""
            return {"cell_errors": [clean(e) for e in errors], "dead": dead}
        except (ValueError, TypeError, RecursionError):
            raise StudentCodeError("unreadable first message from the sandbox") from None

    def request(self, req: dict, raw: bool = False) -> Any:
        if self.dead:
            raise StudentCodeError(self.dead)
        self.n += 1
        self.sb.send(json.dumps(req))
        line = self._receive(min(self.cell_timeout + 15, self.remaining()))
        head, _, rest = line.partition(b" ")
        _, _, payload = rest.partition(b" ")
        if head != str(self.n).encode():
            raise StudentCodeError("an answer out of order from the sandbox")
        try:  # whatever the sandbox sent is data: parsed as JSON, never executed
            out = json.loads(payload)
            if not isinstance(out, dict) or len({"raised", "ok"} & set(out)) != 1:
                raise AnswerError("not an answer")
            if "raised" in out:
                raise StudentCodeError(str(out["raised"])[:2000])
            return out["ok"] if raw else decode(out["ok"])
        except (ValueError, TypeError, KeyError, RecursionError) as exc:
            raise StudentCodeError(f"unreadable answer from the sandbox ({type(exc).__name__}: {str(exc)[:200]})") from None


class _Remote:
    """A student function: called in the sandbox; only its decoded return value comes back."""

    def __init__(self, session: _Session, name: str):
        self._session, self.__name__ = session, name

    def __call__(self, *args, **kwargs):
        try:
            payload = {"op": "call", "name": self.__name__, "args": encode(list(args)), "kwargs": encode(dict(kwargs))}
        except TypeError as exc:
            raise StudentCodeError(f"the test's arguments cannot be sent: {exc}") from None
        return self._session.request(payload)

    def __repr__(self) -> str:
        return f"<student function {self.__name__}>"


def _names(session: _Session, listing: Any) -> dict[str, Any]:
    env: dict[str, Any] = {}
    if not isinstance(listing, dict):
        return env
    for name, info in listing.items():
        if (not isinstance(info, dict) or not isinstance(name, str) or not name.isidentifier()
                or name in _BUILTIN_NAMES or name.startswith("_")):
            continue  # a student's `abs` or `len` must not replace the one the tests call
        if info.get("module") is True:
            if name in TRUSTED_NAMES:  # the grader's own module under a fixed name; nothing named by the kernel
                env[name] = importlib.import_module(TRUSTED_NAMES[name])
        elif info.get("callable") is True:
            env[name] = _Remote(session, name)
        elif "value" in info:
            try:
                env[name] = decode(info["value"])
            except AnswerError:
                continue
    return env


def _run_tests(tests: list, env: dict[str, Any]) -> list[Question]:
    out = []
    for t in tests:
        try:
            t.run({"__name__": "__grading__", **env})
            fails = []
            for r in t.test_case_results:
                if not r.passed:
                    kind = "hidden" if r.test_case.hidden else "public"
                    fails.append(f"{kind} test ({r.test_case.name}): {_short(r.message)}")
            out.append(Question(t.name, float(t.score), float(t.possible), fails))
        except BaseException as exc:  # noqa: BLE001 - a test that cannot run scores 0, the others still run
            if isinstance(exc, KeyboardInterrupt):
                raise
            out.append(Question(t.name, 0.0, float(t.possible), [f"not graded: {type(exc).__name__}: {_short(str(exc))}"]))
    return out


def _zero(tests: list, why: str) -> list[Question]:
    return [Question(t.name, 0.0, float(t.possible), [f"not graded: {why}"]) for t in tests]


def grade(autograder: str | Path | Bundle, submission: str | Path, *, cell_timeout: int = 120,
          total_timeout: int = 900, limits: Optional[Limits] = None, unsafe: bool = False,
          verbose: bool = True, nb=None) -> GradeReport:
    """Grade one submitted notebook with the tests of a verified otter autograder bundle.

    Parameters
    ----------
    autograder : a bundle written by ``make assignments`` (its SHA-256 must match the
        record written beside it) or a :class:`~flnotes.grading.bundles.Bundle`.
    submission : the student's notebook, under any file name; only this file is used.
    cell_timeout : seconds for one cell and for one call of a student function by a test.
    total_timeout : seconds of the submission's own time in all: the run of its notebook
        and every call of its functions by the tests.
    limits : the sandbox's :class:`~flnotes.grading.sandbox.Limits` (default ``Limits()``).
    unsafe : run WITHOUT a sandbox when bubblewrap is missing (never the default; the report
        says so). Without it a missing sandbox raises
        :class:`~flnotes.grading.sandbox.SandboxUnavailable`.

    Returns
    -------
    GradeReport
        The per-question scores (printed as a table when ``verbose``).
    """
    if cell_timeout <= 0 or total_timeout <= 0:
        raise ValueError("cell_timeout and total_timeout must be positive numbers of seconds")
    limits = limits or Limits()
    bundle = autograder if isinstance(autograder, Bundle) else load_bundle(autograder)
    tests, config = bundle_tests(bundle)  # read before any student code runs
    expected = str(config.get("assignment_name") or bundle.name)
    sub = Path(submission)
    report = GradeReport(submission=str(submission), assignment=expected)
    if not unsafe and bwrap_status():
        raise SandboxUnavailable(f"{bwrap_status()}; the grader refuses to run student code without a sandbox "
                                 "(pass unsafe=True / --unsafe-no-sandbox to run it anyway, unprotected)")
    report.unsafe = unsafe and bwrap_status() is not None
    t_start = time.monotonic()
    try:
        nb = nb if nb is not None else read_submission(sub)
    except ValueError as exc:
        report.error, report.questions = str(exc), _zero(tests, "the file is not a notebook")
        return _done(report, verbose, t_start)
    if assignment_of(nb, {expected}) != expected:
        meta = nb.metadata.get("otter") if isinstance(nb.metadata.get("otter"), dict) else {}
        got = clean(meta.get("assignment_name"))[:100] if meta.get("assignment_name") is not None else None
        report.error = f"this submission is for assignment {got!r}, the bundle grades {expected!r}"
        report.questions = _zero(tests, "another assignment")
        return _done(report, verbose, t_start)
    import nbformat

    workdir = tempfile.mkdtemp(prefix="flnotes-grade-")
    sandbox = None
    try:
        nbformat.write(nb, Path(workdir) / f"{expected}.ipynb")  # its own name: otter.Notebook("<name>.ipynb")
        env = {"PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin", "HOME": SUB if not report.unsafe else workdir,
               "MPLBACKEND": "Agg", "MPLCONFIGDIR": "/tmp/mpl", "IPYTHONDIR": "/tmp/ipython",
               "JUPYTER_RUNTIME_DIR": "/tmp/jupyter", "JUPYTER_CONFIG_DIR": "/tmp/jupyter-config",
               "PYTHONDONTWRITEBYTECODE": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
               "MKL_NUM_THREADS": "1", "LANG": "C.UTF-8"}
        if report.unsafe:
            for k in ("MPLCONFIGDIR", "IPYTHONDIR", "JUPYTER_RUNTIME_DIR", "JUPYTER_CONFIG_DIR"):
                env[k] = str(Path(workdir) / ".cfg" / k.lower())
        inner = [sys.executable, "-m", "flnotes.grading.runner", f"{expected}.ipynb", str(cell_timeout)]
        sandbox = Sandbox(workdir, inner, env, limits, unsafe=report.unsafe)
        report.limits = [limits.describe() if not report.unsafe else "per-process limits only, no sandbox",
                         f"{cell_timeout} s per cell or call, {total_timeout} s for the whole submission"]
        session = _Session(sandbox, float(total_timeout), cell_timeout)
        names: dict[str, Any] = {}
        try:
            first = session.ready()
            report.cell_errors = first["cell_errors"]
            if first["dead"]:
                report.error = first["dead"]
            names = _names(session, session.request({"op": "names"}, raw=True))
        except StudentCodeError as exc:
            report.error = report.error or str(exc)
        report.questions = _run_tests(tests, names)
        if session.dead and not report.error:
            report.error = session.dead
        if sandbox.killed:
            report.error = sandbox.killed + (f"; {report.error}" if report.error and report.error != sandbox.killed else "")
    finally:
        if sandbox is not None:
            sandbox.kill()
        shutil.rmtree(workdir, ignore_errors=True)
    return _done(report, verbose, t_start)


def _done(report: GradeReport, verbose: bool, t_start: float) -> GradeReport:
    report.seconds = time.monotonic() - t_start
    if verbose:
        print(report.table())
    return report
