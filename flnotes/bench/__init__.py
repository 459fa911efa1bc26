"""Benchmarks behind ``make bench``: per-step solve times and certification times.

Each section module (``training``, ``error``, ``clfcbf``, ``mpc``, ``exactness``, ``size``, ``compare``, ``multi``,
``parallel``, ...) defines ``run(fast: bool) -> dict`` returning

    {"title": str, "rows": [dict, ...], "notes": [str, ...], "figures": [path, ...]}

where every row is one line of the section's table (the paper's numbers sit
in rows of their own, with ``"source": "paper"``). ``python -m flnotes.bench``
runs all sections (``--workers N`` or ``--scheduler ADDRESS``: side by side, see :func:`main`),
then writes ``_build/bench/results.json``,
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

SECTIONS = ("training", "error", "clfcbf", "mpc", "exactness", "deadline", "cheap_networks", "size", "unseen", "compare",
            "msd_realtime", "routing", "cuts", "multi", "parallel")

#: Sections that start workers of their own: run in this process, after the others, never inside a worker.
IN_PROCESS = ("parallel",)


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


def _run_section(name: str, fast: bool, scheduler: Optional[str] = None) -> dict:
    """One section as a task: its dict, or a dict saying how it failed (the other sections still run)."""
    t0 = time.perf_counter()
    try:
        mod = importlib.import_module(f"flnotes.bench.{name}")
        sec = mod.run(fast=fast, scheduler=scheduler) if name in IN_PROCESS else mod.run(fast=fast)
        failed = False
    except Exception as exc:
        import traceback
        traceback.print_exc()
        sec = dict(title=name, rows=[], notes=[f"FAILED: {type(exc).__name__}: {exc}"], figures=[])
        failed = True
    sec["seconds"] = time.perf_counter() - t0
    sec["failed"] = failed
    return sec


def parse_args(argv: list[str]) -> dict:
    """``[--fast] [--workers N | --scheduler ADDRESS] [section ...]`` as a dict (``ValueError`` with the usage otherwise)."""
    from ..parallel import parse_workers

    usage = ("usage: python -m flnotes.bench [--fast] [--workers N | --scheduler ADDRESS] [section ...]; "
             f"sections: {', '.join(SECTIONS)}")
    try:
        workers, scheduler, rest = parse_workers(argv)
    except ValueError as exc:
        raise ValueError(f"{exc}. {usage}") from None
    bad = [a for a in rest if a.startswith("-") and a != "--fast"]
    if bad:
        raise ValueError(f"unknown option(s) {bad}. {usage}")
    sections = [a for a in rest if not a.startswith("-")]
    unknown = [a for a in sections if a not in SECTIONS]
    if unknown:
        raise ValueError(f"unknown section(s) {unknown}. {usage}")
    return dict(fast="--fast" in rest, workers=workers, scheduler=scheduler, sections=sections)


def main(argv: Optional[list[str]] = None) -> int:
    """``python -m flnotes.bench [--fast] [--workers N | --scheduler ADDRESS] [section ...]``: run and write.

    Sections not run this time keep their previous results in ``results.json`` (each
    section records the machine and the mode it ran in), so one section can be re-run alone.
    ``--workers N`` runs the sections as N local processes (``--scheduler ADDRESS``: on a Dask
    cluster), each in a worker of :class:`flnotes.parallel.Executor`, their tables in the usual order;
    sections running side by side share the machine, so their times include that competition
    (a cluster's workers on other machines do not). The ``parallel`` section starts workers of its
    own and always runs in this process, after the others.
    """
    argv = sys.argv[1:] if argv is None else argv
    try:
        args = parse_args(argv)
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 2
    fast = args["fast"] or os.environ.get("FLNOTES_FAST") == "1"
    only = args["sections"] or list(SECTIONS)
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
    from functools import partial

    from ..parallel import Executor

    def report(name: str, sec: dict) -> None:
        nonlocal status
        status = max(status, int(sec.pop("failed")))   # a failing section is reported, the others still run
        sec["machine"], sec["fast"] = info, fast
        sec["workers"] = args["scheduler"] or args["workers"] or 1
        results["sections"][name] = sec
        print(f"== {name} done ({sec['seconds']:.0f} s)")
        print(markdown_table(sec["rows"]), flush=True)
        for n in sec.get("notes", []):
            print("-", n)

    spread = [n for n in only if n not in IN_PROCESS]
    with Executor(workers=args["workers"], client=args["scheduler"]) as ex:
        if ex.engine != "serial":
            print(f"sections {spread} on {ex}", flush=True)
            for name, sec in zip(spread, ex.map(partial(_run_section, fast=fast), spread, desc="bench sections",
                                                progress=True)):
                report(name, sec)
        else:
            for name in spread:
                print(f"== {name}", flush=True)
                report(name, _run_section(name, fast))
    for name in (n for n in only if n in IN_PROCESS):
        print(f"== {name}", flush=True)
        report(name, _run_section(name, fast, args["scheduler"]))
    md = [f"# flnotes benchmarks\n\nMachine: {info['cores']} cores, {info['cpu']}, Python {info['python']}; "
          + ", ".join(f"{k} {v}" for k, v in info["versions"].items()) + ("\n\n(fast mode)\n" if fast else "\n")]
    md += [_section_md(results["sections"][n]) for n in SECTIONS if n in results["sections"]]
    (out / "results.json").write_text(json.dumps(results, indent=2, default=lambda o: getattr(o, "tolist", lambda: str(o))()))
    (out / "results.md").write_text("\n".join(md))
    print(f"wrote {out / 'results.json'} and {out / 'results.md'}")
    return status
