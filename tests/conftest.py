"""The order in which the tests are handed out, and the notebooks nbmake executed.

``make test`` runs on several pytest-xdist workers with ``--dist loadscope
--no-loadscope-reorder``: each test module and each notebook is one unit of work
(its module fixtures are built once), given in collection order to the next free
worker. The book's notebooks go first (every page's notebook is executed once, by
nbmake; the longest of them first), then ``test_rendered.py`` (it builds the book from the notebooks nbmake
executed, see below), then the other long units (:data:`LONG`: every option
combination of the MPC, the assignments' grader and the attacks on it), the other unit
tests, and the short ones last (the master notebooks of the assignments), so that
the workers finish at about the same time. Within a unit the order is kept.

Why ``test_rendered.py`` never waits on work queued behind it: the scheduler hands
out the units in this order, so every notebook is handed out before it; a notebook
handed to the same worker runs before it, and one handed to another worker runs
there whatever this worker does (a worker that holds only one pending test is given
more work or told to shut down as soon as it reports its previous test).

The executed notebooks: :func:`_keep_executed` wraps nbmake's
``NotebookRun.execute`` so that each notebook nbmake executes in this session is
written, with its outputs, to a staging folder of this run (``_build/nbmake/<run
id>/``, the run id shared by the controller and every xdist worker), or, when it
failed, a ``.failed`` marker with nbmake's summary. The ``executed_notebooks``
fixture gives that folder to ``test_rendered.py`` when every notebook of
``_toc.yml`` is an nbmake item of this session, so that the book is built without
executing them a second time.

The kernels nbmake starts render figures inline, as in ``make book``: ``make test``
sets ``MPLBACKEND=Agg`` for the tests' own process, and a kernel started with it
would not display a figure; it is removed from the kernel's environment.
"""
from __future__ import annotations

import os
import shutil
import uuid
from importlib.metadata import version
from pathlib import Path

import nbformat
import pytest

ROOT = Path(__file__).resolve().parents[1]
STAGING = ROOT / "_build" / "nbmake"

#: The longest units after test_rendered.py, longest first (9, 6 and 3 minutes of one worker in a
#: run of ``make test`` with ``--durations=0``; the next longest, a notebook, about one minute).
LONG = ("test_mpc_options.py", "test_assignments.py", "test_grading_attacks.py")
#: The longest notebook (about one minute), handed out first among the notebooks, so that
#: test_rendered.py, which waits for the last notebooks to end, does not wait for it.
FIRST_NOTEBOOKS = ("benchmark_report.ipynb",)

#: The nbmake release whose ``NotebookRun.execute`` is wrapped (pinned in requirements.txt).
NBMAKE_VERSION = "1.5.5"


def _rank(item: pytest.Item) -> tuple[int, int]:
    path = Path(str(item.path)).resolve()
    if path.suffix == ".ipynb":
        if "master" in (path.relative_to(ROOT) if path.is_relative_to(ROOT) else path).parts:
            return 4, 0
        return 0, (0 if path.name in FIRST_NOTEBOOKS else 1)
    if path.parent == ROOT / "tests":
        if path.name == "test_rendered.py":
            return 1, 0
        if path.name in LONG:
            return 2, LONG.index(path.name)
    return 3, 0


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    items.sort(key=_rank)  # stable: the order within each group is kept


# ----------------------------------------------------------------------------------
# the notebooks nbmake executed
def _run_id(config: pytest.Config) -> str:
    workerinput = getattr(config, "workerinput", None)
    if workerinput is not None:  # an xdist worker: the controller's run id
        return workerinput["testrunuid"]
    return config._flnotes_run_id  # type: ignore[attr-defined]


def staged_path(run_dir: Path, source: Path) -> Path:
    """Where the executed copy of the notebook ``source`` is written in ``run_dir``."""
    return run_dir / "executed" / Path(source).resolve().relative_to(ROOT)


def _keep_executed(run_dir: Path) -> None:
    """Wrap ``nbmake.pytest_items.NotebookRun.execute`` to write each executed notebook to ``run_dir``."""
    try:
        from nbmake import pytest_items
        run_cls = pytest_items.NotebookRun
        original = run_cls.execute
    except (ImportError, AttributeError) as err:
        raise pytest.UsageError(
            f"tests/conftest.py wraps nbmake.pytest_items.NotebookRun.execute, which this nbmake "
            f"({version('nbmake')}) does not have ({err}); pin nbmake=={NBMAKE_VERSION} in "
            f"requirements.txt or adapt the wrapper"
        ) from err
    if version("nbmake") != NBMAKE_VERSION:
        raise pytest.UsageError(
            f"tests/conftest.py wraps nbmake {NBMAKE_VERSION}'s NotebookRun.execute, found nbmake "
            f"{version('nbmake')}: check the wrapper against it and update NBMAKE_VERSION"
        )
    if getattr(original, "_flnotes_wrapped", False):
        return

    def execute(self):
        if not Path(self.filename).resolve().is_relative_to(ROOT):  # not one of the book's
            return original(self)
        target = staged_path(run_dir, self.filename)
        target.parent.mkdir(parents=True, exist_ok=True)
        failed = target.with_suffix(".failed")
        backend = os.environ.pop("MPLBACKEND", None)  # the kernel inherits this environment
        try:
            res = original(self)
        except BaseException as err:
            failed.write_text(f"nbmake raised {type(err).__name__}: {err}")
            raise
        finally:
            if backend is not None:
                os.environ["MPLBACKEND"] = backend
        if res.error is not None:
            failed.write_text(res.error.summary)
        else:
            tmp = target.with_suffix(".ipynb.part")
            nbformat.write(res.nb, str(tmp))
            os.replace(tmp, target)  # appears whole, or not at all
        return res

    execute._flnotes_wrapped = True  # type: ignore[attr-defined]
    run_cls.execute = execute


def pytest_configure(config: pytest.Config) -> None:
    if getattr(config, "workerinput", None) is None:  # the controller (or the only process)
        run_id = getattr(config.option, "testrunuid", None)
        if run_id is None:
            run_id = uuid.uuid4().hex
            if hasattr(config.option, "testrunuid"):
                config.option.testrunuid = run_id  # xdist hands it to every worker
        config._flnotes_run_id = run_id  # type: ignore[attr-defined]
    if config.getoption("nbmake", default=False):
        _keep_executed(STAGING / _run_id(config))


def pytest_unconfigure(config: pytest.Config) -> None:
    if getattr(config, "workerinput", None) is None:
        shutil.rmtree(STAGING / _run_id(config), ignore_errors=True)


@pytest.fixture(scope="module")
def executed_notebooks(request: pytest.FixtureRequest):
    """``(run_dir, staged_path, notebooks)`` when nbmake runs in this session, else ``None``.

    ``notebooks`` are the paths of this session's nbmake items ordered before the test that
    asks (so handed out before it: its worker never waits on one queued behind it); ``staged_path(run_dir,
    source)`` is where the executed copy of ``source`` appears (a ``.failed`` file in
    its place if nbmake failed on it).
    """
    if not request.config.getoption("nbmake", default=False):
        return None
    run_dir = STAGING / _run_id(request.config)
    return run_dir, staged_path, _notebooks_before(request.session.items, request.node)


def _notebooks_before(items: list[pytest.Item], node: pytest.Node) -> set[Path]:
    """The notebooks of the session's nbmake items that come before ``node``'s first test in the session's order."""
    mine = [i for i, item in enumerate(items) if item.nodeid == node.nodeid or item.nodeid.startswith(node.nodeid + "::")]
    if not mine:  # asked from outside the session's tests: nothing is known to come first
        return set()
    where = mine[0]
    return {Path(str(item.path)).resolve() for item in items[:where] if getattr(item, "nbmake", False)}
