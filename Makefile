# flnotes: build the book, run the tests, time the solvers, write the students' assignments.
# Everything runs from the project's own virtual environment .venv (created on demand
# from requirements.txt); nothing depends on an activated shell.

SHELL := /bin/bash
PYTHON3 ?= python3
VENV    := .venv
PY      := $(VENV)/bin/python
JB      := $(VENV)/bin/jupyter-book
STAMP   := $(VENV)/.installed

# seconds per notebook under nbmake (the fast mode is meant to take far less)
NBMAKE_TIMEOUT ?= 900
# pytest-xdist workers for `make test` (auto: one per CPU core); 0 runs everything in one process
TEST_JOBS ?= auto

.PHONY: all venv book book-instructor test bench assignments grade students-edition sandbox reference clean help

all: book

help:
	@echo "make book         build the book at full scale into _build/html (runs every notebook)"
	@echo "make test         ruff, unit tests + every notebook through nbmake, FLNOTES_FAST=1"
	@echo "make bench        solver benchmarks (python -m flnotes.bench); WORKERS=N or SCHEDULER=address to spread them"
	@echo "make book-instructor  the instructor edition (reference solutions, all tests, rubrics) into _build/instructor"
	@echo "make assignments  students' notebooks and autograder bundles (otter-grader) into _build/assignments"
	@echo "make grade SUBMISSIONS=dir  grade a folder of submissions in the sandbox: _build/grades/gradebook.csv"
	@echo "make students-edition  the tree published for students (no masters, hidden tests, rubrics) into _build/students"
	@echo "make reference    retrain and recertify the shipped networks and sweep table (changes the book's numbers); WORKERS=N or SCHEDULER=address"
	@echo "make clean        remove _build and caches (keeps .venv)"

# ---------------------------------------------------------------------------------
# The virtual environment: created with the machine's python3 if missing; the
# requirements are (re)installed whenever requirements.txt or pyproject.toml is
# newer than the stamp file.
venv: $(STAMP)

$(STAMP): requirements.txt pyproject.toml
	@test -x $(PY) || $(PYTHON3) -m venv $(VENV)
	-$(PY) -m pip install --upgrade pip
	$(PY) -m pip install -r requirements.txt
	touch $(STAMP)

# ---------------------------------------------------------------------------------
# Full-scale book: every notebook executed (see _config.yml: execute_notebooks: force,
# raise_on_error: true), warnings are errors, nitpicky cross-references.
book: venv
	env -u FLNOTES_FAST -u MPLBACKEND $(JB) build . --all -W -n --keep-going
	@echo "book written to _build/html/index.html"

# Unit tests and every notebook under book/ through nbmake, in fast mode, on TEST_JOBS
# pytest-xdist workers: a test module or a notebook stays on one worker (its module
# fixtures are built once), the longest first (tests/conftest.py orders them), and
# one BLAS thread per worker so that the workers do not compete for the cores.
test: venv sandbox
	$(VENV)/bin/ruff check .
	env FLNOTES_FAST=1 MPLBACKEND=Agg PYTHONDONTWRITEBYTECODE=1 \
	  OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \
	  $(PY) -m pytest tests/ --nbmake book/ --nbmake-timeout=$(NBMAKE_TIMEOUT) \
	  -n $(TEST_JOBS) --dist loadscope --no-loadscope-reorder \
	  --ignore-glob="**/.ipynb_checkpoints/*" -p no:cacheprovider -ra --durations=25

# Where `make bench` and `make reference` run their independent tasks: WORKERS=N local processes, or
# SCHEDULER=tcp://host:8786 a Dask cluster (flnotes.parallel); neither: one after the other, in one process.
WORKERS   ?=
SCHEDULER ?=
PARALLEL  := $(if $(WORKERS),--workers $(WORKERS)) $(if $(SCHEDULER),--scheduler $(SCHEDULER))

bench: venv
	$(PY) -m flnotes.bench $(PARALLEL)

# Rewrites flnotes/data/: the book's networks, their certified eps and chapter 5's sweep, trained on this
# machine. Only to change them on purpose; commit the result. An interrupted run resumes from the networks
# already finished (python -m flnotes.studies.shipped --fresh starts over).
reference: venv
	$(PY) -m flnotes.studies.shipped $(PARALLEL)

# Students' notebooks, autograder bundles (read-only, SHA-256 recorded in SHA256SUMS) and reference
# solutions of the otter-grader master notebooks (book/assignments/master) into _build/assignments;
# refreshes the students' pages of the book (book/assignments/a*.ipynb).
assignments: venv
	$(PY) -m flnotes.grading assign book/assignments/master _build/assignments --book-dir book/assignments

# bubblewrap, the sandbox the grader runs every submission in (Debian's package; as root, or with sudo)
sandbox:
	@command -v bwrap >/dev/null || { \
	  if command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq bubblewrap; \
	  elif command -v apt-get >/dev/null && command -v sudo >/dev/null; then sudo apt-get update -qq && sudo apt-get install -y -qq bubblewrap; \
	  else echo "bubblewrap (bwrap) is not installed and cannot be installed here: the grader refuses to grade"; fi; }

# Grade every file of SUBMISSIONS (any names, any mix of assignments) in the sandbox:
# $(GRADES)/gradebook.csv and one report per file in $(GRADES)/reports/.
SUBMISSIONS ?= submissions
GRADES ?= _build/grades
grade: venv sandbox
	rm -rf $(GRADES)/reports $(GRADES)/gradebook.csv
	$(PY) -m flnotes.grading batch _build/assignments/autograder $(SUBMISSIONS) $(GRADES)

# The tree published for students (the repository named in _config.yml's repository: url):
# the checkout without the masters, the instructor guide, the grader's tests and the build folders.
students-edition: venv
	$(PY) -m flnotes.grading students-edition _build/students

# Instructor edition of the book: the assignments' master notebooks (reference solutions,
# all tests, rubrics) instead of the students' pages, and the instructor guide, into _build/instructor/_build/html.
book-instructor: venv
	$(PY) -m flnotes.grading instructor-toc _toc.yml _build/instructor_toc.yml
	env -u FLNOTES_FAST -u MPLBACKEND $(JB) build . --all -W -n --keep-going \
	  --toc _build/instructor_toc.yml --path-output _build/instructor
	@echo "instructor edition written to _build/instructor/_build/html/index.html"

clean:
	rm -rf _build .pytest_cache
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -print0 | xargs -0 rm -rf
	find . -path ./$(VENV) -prune -o -name .ipynb_checkpoints -type d -print0 | xargs -0 rm -rf
