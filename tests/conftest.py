"""The order in which the tests are handed out.

``make test`` runs on several pytest-xdist workers with ``--dist loadscope
--no-loadscope-reorder``: each test module and each notebook is one unit of work
(its module fixtures are built once), given in collection order to the next free
worker. The long units go first (:data:`LONG`: the fast build of the whole book in
``test_rendered.py``, the assignments' grader and the attacks on it, every option combination of the MPC),
then the chapters, the other unit tests, and the short ones last (the assignments'
notebooks), so that the workers finish at about the same time. Within a unit the
order is kept.
"""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: The longest units, longest first (each took 6 to 8 minutes of one worker in a run of ``make test``
#: with ``--durations=0``; the next longest, a chapter, about one minute).
LONG = ("test_rendered.py", "test_assignments.py", "test_grading_attacks.py", "test_mpc_options.py")


def _rank(item: pytest.Item) -> tuple[int, int]:
    path = Path(str(item.path)).resolve()
    if path.parent == ROOT / "tests" and path.name in LONG:
        return 0, LONG.index(path.name)
    if path.suffix == ".ipynb":
        return (1 if path.parent == ROOT / "book" else 3), 0
    return 2, 0


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    items.sort(key=_rank)  # stable: the order within each group is kept
