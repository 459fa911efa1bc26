"""The order in which the tests are handed out.

``make test`` runs on several pytest-xdist workers with ``--dist loadscope
--no-loadscope-reorder``: each test module and each notebook is one unit of work
(its module fixtures are built once), given in collection order to the next free
worker. The long units go first (the fast build of the whole book in
``test_rendered.py``, then the chapters), the short ones last (the assignments), so
that the workers finish at about the same time. Within a unit the order is kept.
"""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _rank(item: pytest.Item) -> int:
    path = Path(str(item.path)).resolve()
    if path.name == "test_rendered.py":
        return 0
    if path.suffix == ".ipynb":
        return 1 if path.parent == ROOT / "book" else 3
    return 2


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    items.sort(key=_rank)  # stable: the order within each group is kept
