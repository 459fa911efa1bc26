"""Chapter studies: the functions behind the book's tables, sweeps and checks.

The library (systems, networks, bounds, encoding, error bounds, controllers,
simulation) knows nothing of the paper or of a chapter; the studies combine it
with the paper's settings and numbers (:mod:`flnotes.paper`) into what a
chapter shows. They are the only part of the package, with the benchmarks,
that imports :mod:`flnotes.paper`.
"""
from .networks import (architecture_sweep, book_sweep, estimates_table, fresh_vs_shipped, table1_rows,
                       width_experiment, write_sweep)

__all__ = ["architecture_sweep", "book_sweep", "estimates_table", "fresh_vs_shipped", "table1_rows",
           "width_experiment", "write_sweep"]
