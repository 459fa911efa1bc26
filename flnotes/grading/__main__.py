"""``python -m flnotes.grading``: assign, batch, grade, instructor-toc, students-edition."""
from __future__ import annotations

import argparse
import sys

from . import __doc__ as _doc
from .batch import batch
from .bundles import assign_all, instructor_toc, students_edition
from .grade import grade
from .sandbox import Limits


def _limits(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cell-timeout", type=int, default=120, help="seconds per cell and per call of a student function")
    p.add_argument("--total-timeout", type=int, default=900, help="seconds of the whole submission (notebook and calls)")
    p.add_argument("--memory-mb", type=int, default=4096, help="address space per process in the sandbox")
    p.add_argument("--tree-memory-mb", type=int, default=6144, help="resident memory of all the submission's processes")
    p.add_argument("--processes", type=int, default=64, help="processes the submission may start")
    p.add_argument("--unsafe-no-sandbox", action="store_true",
                   help="grade even without bubblewrap (UNSAFE: the student's code runs unconfined; reports say so)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m flnotes.grading", description=_doc.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("assign", help="students' notebooks and verified autograder bundles (otter assign)")
    a.add_argument("master_dir")
    a.add_argument("out_dir")
    a.add_argument("--book-dir", help="also refresh the book's students' pages in this folder")
    a.add_argument("--no-run-tests", action="store_true", help="do not run the masters' tests first")
    b = sub.add_parser("batch", help="grade every file of a folder of downloads: gradebook.csv and reports/")
    b.add_argument("bundle_dir", help="the bundles written by `make assignments` (_build/assignments/autograder)")
    b.add_argument("submissions")
    b.add_argument("out_dir")
    _limits(b)
    g = sub.add_parser("grade", help="grade one submission")
    g.add_argument("-a", "--autograder", required=True, help="bundle written by `make assignments`")
    g.add_argument("submission")
    _limits(g)
    t = sub.add_parser("instructor-toc", help="table of contents of the instructor edition")
    t.add_argument("toc")
    t.add_argument("out")
    s = sub.add_parser("students-edition", help="write the tree published for students")
    s.add_argument("out_dir")
    args = parser.parse_args(argv)

    if args.cmd == "assign":
        for student, bundle in assign_all(args.master_dir, args.out_dir, args.book_dir,
                                          run_tests=not args.no_run_tests):
            print(f"wrote {student}\nwrote {bundle}")
        return 0
    if args.cmd in ("batch", "grade"):
        kw = dict(cell_timeout=args.cell_timeout, total_timeout=args.total_timeout, unsafe=args.unsafe_no_sandbox,
                  limits=Limits(memory_mb=args.memory_mb, tree_memory_mb=args.tree_memory_mb,
                                processes=args.processes, cpu_seconds=max(args.total_timeout + 60, 60)))
        if args.cmd == "batch":
            reports = batch(args.bundle_dir, args.submissions, args.out_dir, **kw)
            print(f"graded {len(reports)} file(s): {args.out_dir}/gradebook.csv, {args.out_dir}/reports/")
            return 0
        report = grade(args.autograder, args.submission, **kw)
        return 0 if not report.error else 1
    if args.cmd == "instructor-toc":
        print(f"wrote {instructor_toc(args.toc, args.out)}")
        return 0
    print(f"wrote {students_edition(args.out_dir)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
