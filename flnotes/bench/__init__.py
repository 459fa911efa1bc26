"""Benchmarks behind ``make bench``: per-step solve times and certification times.

Each section module (``training``, ``error``, ``clfcbf``, ``mpc``, ``exactness``, ``compare``, ``multi``) defines
``run(fast: bool) -> dict`` returning

    {"title": str, "rows": [dict, ...], "notes": [str, ...], "figures": [path, ...]}

where every row is one line of the section's table (the paper's numbers sit
in rows of their own, with ``"source": "paper"``). ``python -m flnotes.bench``
runs all sections, then writes ``_build/bench/results.json``,
``_build/bench/results.md`` and the plots, and prints the machine it ran on.
Speed is measured here, never asserted in tests.
"""
from __future__ import annotations

import importlib
import importlib.metadata
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Optional

from ..tables import Table

SECTIONS = ("training", "error", "clfcbf", "mpc", "exactness", "deadline", "cheap_networks", "unseen", "compare", "multi")


def out_dir() -> Path:
    path = Path(os.environ.get("FLNOTES_BENCH_DIR", Path(__file__).resolve().parents[2] / "_build" / "bench"))
    path.mkdir(parents=True, exist_ok=True)
    return path


def machine() -> dict:
    """Cores, CPU model, Python and solver versions: printed with every benchmark."""
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    versions = {}
    dists = {"numpy": "numpy", "scipy": "scipy", "sklearn": "scikit-learn", "cvxpy": "cvxpy",
             "highspy": "highspy", "pyscipopt": "PySCIPOpt", "daqp": "daqp"}
    for mod, dist in dists.items():
        try:
            versions[mod] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            versions[mod] = "not installed"
    return dict(cores=os.cpu_count(), cpu=cpu, python=platform.python_version(), platform=platform.platform(), versions=versions)


def markdown_table(rows: list[dict]) -> str:
    """Rows of dicts as a Markdown table (:meth:`flnotes.tables.Table.markdown`)."""
    return Table(rows).markdown()


def _section_md(sec: dict) -> str:
    return (f"\n## {sec['title']}\n\n" + markdown_table(sec["rows"]) + "".join(f"\n- {n}" for n in sec.get("notes", []))
            + "".join(f"\n\n![{Path(f).stem}]({Path(f).name})" for f in sec.get("figures", [])) + "\n")


def main(argv: Optional[list[str]] = None) -> int:
    """``python -m flnotes.bench [--fast] [section ...]``: run the sections (default all) and write the results.

    Sections not run this time keep their previous results in ``results.json`` (each
    section records the machine and the mode it ran in), so one section can be re-run alone.
    """
    argv = sys.argv[1:] if argv is None else argv
    fast = "--fast" in argv or os.environ.get("FLNOTES_FAST") == "1"
    only = [a for a in argv if not a.startswith("--")] or list(SECTIONS)
    unknown = [a for a in only if a not in SECTIONS]
    if unknown:
        print(f"unknown section(s) {unknown}; choose from {list(SECTIONS)}", file=sys.stderr)
        return 2
    info = machine()
    print(f"machine: {info['cores']} cores, {info['cpu']}, Python {info['python']}", flush=True)
    out = out_dir()
    results = dict(machine=info, fast=fast, sections={})
    old = out / "results.json"
    if old.is_file() and set(only) != set(SECTIONS):
        try:
            results["sections"] = json.loads(old.read_text()).get("sections", {})
        except (OSError, ValueError):
            pass
    status = 0
    for name in only:
        t0 = time.perf_counter()
        print(f"== {name}", flush=True)
        try:
            sec = importlib.import_module(f"flnotes.bench.{name}").run(fast=fast)
        except Exception as exc:  # a failing section is reported, the others still run
            import traceback
            traceback.print_exc()
            sec = dict(title=name, rows=[], notes=[f"FAILED: {type(exc).__name__}: {exc}"], figures=[])
            status = 1
        sec["seconds"] = time.perf_counter() - t0
        sec["machine"], sec["fast"] = info, fast
        results["sections"][name] = sec
        print(markdown_table(sec["rows"]), flush=True)
        for n in sec.get("notes", []):
            print("-", n)
    md = [f"# flnotes benchmarks\n\nMachine: {info['cores']} cores, {info['cpu']}, Python {info['python']}; "
          + ", ".join(f"{k} {v}" for k, v in info["versions"].items()) + ("\n\n(fast mode)\n" if fast else "\n")]
    md += [_section_md(results["sections"][n]) for n in SECTIONS if n in results["sections"]]
    (out / "results.json").write_text(json.dumps(results, indent=2, default=lambda o: getattr(o, "tolist", lambda: str(o))()))
    (out / "results.md").write_text("\n".join(md))
    print(f"wrote {out / 'results.json'} and {out / 'results.md'}")
    return status
