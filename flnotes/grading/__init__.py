"""Assignments and their grader: otter-grader's masters and bundles, a sandbox, data-only answers.

The assignments are otter-grader master notebooks (``book/assignments/master/``).
``otter assign`` turns each into a students' notebook and an autograder bundle with every
test, the hidden ones included. This package adds what a class that tries to cheat needs:

:mod:`~flnotes.grading.bundles`
    ``assign_all`` (``make assignments``): students' notebooks, read-only bundles with their
    SHA-256 recorded, the book's students' pages; ``instructor_toc`` and ``students_edition``.
:mod:`~flnotes.grading.sandbox`
    bubblewrap around the student's kernel and its whole process tree, with limits.
:mod:`~flnotes.grading.runner`
    what runs inside: the notebook, then the calls of the student's functions.
:mod:`~flnotes.grading.answers`
    the only thing that crosses back: JSON data, decoded strictly; ``expect_array`` for tests.
:mod:`~flnotes.grading.grade` and :mod:`~flnotes.grading.batch`
    one submission; a folder of submissions into a gradebook.

Command line::

    python -m flnotes.grading assign book/assignments/master _build/assignments --book-dir book/assignments
    python -m flnotes.grading batch _build/assignments/autograder downloads/ _build/grades
    python -m flnotes.grading grade -a _build/assignments/autograder/a1_derive_phi-autograder.zip submission.ipynb
    python -m flnotes.grading instructor-toc _toc.yml _build/instructor_toc.yml
    python -m flnotes.grading students-edition _build/students
"""
from __future__ import annotations

from .answers import AnswerError, decode, encode, expect_array
from .batch import batch, identify, load_bundles
from .bundles import (MANIFEST, MASTER_DIR, ROOT, Bundle, assign, assign_all, bundle_tests, hidden_test_lines,
                      instructor_toc, load_bundle, load_bundle_tests, student_page, students_edition,
                      students_repository)
from .grade import TRUSTED_NAMES, GradeReport, Question, StudentCodeError, grade, read_submission
from .sandbox import Limits, SandboxUnavailable, bwrap_status

__all__ = [
    "ROOT", "MASTER_DIR", "MANIFEST", "Bundle", "assign", "assign_all", "student_page", "load_bundle", "bundle_tests",
    "load_bundle_tests", "students_repository", "instructor_toc", "students_edition", "hidden_test_lines",
    "AnswerError", "encode", "decode", "expect_array", "GradeReport", "Question", "StudentCodeError", "grade",
    "read_submission", "TRUSTED_NAMES", "Limits", "SandboxUnavailable", "bwrap_status", "batch", "identify",
    "load_bundles", "main",
]


def main(argv: list[str] | None = None) -> int:
    from .__main__ import main as _main

    return _main(argv)
