"""Notebooks are kept without outputs: the build and the tests execute them.

Committed outputs bloat the history, go stale, and hide whether a notebook runs.
Strip them with, e.g., ``jupyter nbconvert --clear-output --inplace book/*.ipynb``.
"""
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = sorted(p for p in (ROOT / "book").rglob("*.ipynb") if ".ipynb_checkpoints" not in p.parts)


def test_there_are_notebooks():
    assert NOTEBOOKS, "no notebook found under book/"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[str(p.relative_to(ROOT)) for p in NOTEBOOKS])
def test_notebook_has_no_outputs(path):
    nb = json.loads(path.read_text(encoding="utf-8"))
    problems = []
    for i, cell in enumerate(nb.get("cells", [])):
        if cell.get("cell_type") != "code":
            continue
        where = f"cell {i}" + (f" (id {cell['id']})" if "id" in cell else "")
        first = "".join(cell.get("source", [])).strip().splitlines()[:1]
        where += f" {first[0][:40]!r}" if first else ""
        if cell.get("outputs"):
            problems.append(f"{where}: has {len(cell['outputs'])} output(s)")
        if cell.get("execution_count") is not None:
            problems.append(f"{where}: has execution_count {cell['execution_count']}")
    assert not problems, f"{path.relative_to(ROOT)} is not clean:\n  " + "\n  ".join(problems)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[str(p.relative_to(ROOT)) for p in NOTEBOOKS])
def test_cells_have_unique_ids_where_the_format_wants_them(path):
    """nbformat 4.5 and later give every cell an id, unique in its notebook (a cell copied or split by hand can miss
    one or repeat one; nbformat then warns, and a later version refuses the file)."""
    nb = json.loads(path.read_text(encoding="utf-8"))
    if (nb.get("nbformat", 4), nb.get("nbformat_minor", 0)) < (4, 5):
        return
    ids = [cell.get("id") for cell in nb.get("cells", [])]
    missing = [i for i, c in enumerate(ids) if not c]
    repeated = sorted({c for c in ids if c and ids.count(c) > 1})
    assert not missing and not repeated, f"cells without an id: {missing}; ids used twice: {repeated}"
