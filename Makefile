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

.PHONY: all venv book test bench assignments reference clean help

all: book

help:
	@echo "make book         build the book at full scale into _build/html (runs every notebook)"
	@echo "make test         unit tests + every notebook through nbmake, FLNOTES_FAST=1"
	@echo "make bench        solver benchmarks (python -m flnotes.bench)"
	@echo "make assignments  students' versions of the assignments into _build/assignments"
	@echo "make reference    retrain and recertify the shipped networks and sweep table (changes the book's numbers)"
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

# Unit tests and every notebook under book/ through nbmake, in fast mode.
test: venv
	env FLNOTES_FAST=1 MPLBACKEND=Agg PYTHONDONTWRITEBYTECODE=1 \
	  $(PY) -m pytest tests/ --nbmake book/ --nbmake-timeout=$(NBMAKE_TIMEOUT) \
	  --ignore-glob="**/.ipynb_checkpoints/*" -p no:cacheprovider -ra

bench: venv
	$(PY) -m flnotes.bench

# Rewrites flnotes/data/: the book's networks, their certified eps and chapter 5's sweep, trained on this
# machine. Only to change them on purpose; commit the result.
reference: venv
	$(PY) -c "import flnotes.paper as p, flnotes.studies as s; print(*p.write_references(), sep='\n'); s.write_sweep()"

assignments: venv
	$(PY) -m flnotes.grading student book/assignments _build/assignments

clean:
	rm -rf _build .pytest_cache
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -print0 | xargs -0 rm -rf
	find . -path ./$(VENV) -prune -o -name .ipynb_checkpoints -type d -print0 | xargs -0 rm -rf
