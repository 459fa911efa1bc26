"""Chapter studies: the functions behind the book's tables, sweeps and checks.

The library (systems, networks, bounds, encoding, error bounds, controllers,
simulation) knows nothing of the paper or of a chapter; the studies combine it
with the paper's settings and numbers (:mod:`flnotes.paper`) into what a
chapter shows. They are the only part of the package, with the benchmarks,
that imports :mod:`flnotes.paper`.

``networks``
    chapters 2, 4 and 5: fresh against shipped networks, exact node ranges, Table 1, sweeps over architectures;
``clfcbf``
    chapter 6: checks of a CLF-CBF run, Table 2's rows, the exact method against a back-end;
``mpc``
    chapters 7 and 8: checks of an MPC run, Table 2's MPC row, horizon sweeps, lever studies;
``cheap_networks``
    chapter 8: networks cheaper to encode (other seeds, a weight penalty, other widths) against the MPC's work;
``unseen``
    chapter 8: five systems not in the book, their shipped networks, the default MPC on them;
``size``
    the benchmark report: the time per MPC step against the width and depth of the network (Quad-1D, MSD);
``cuts``
    the benchmark report: the MSD MIQP's root gap, and what the ideal cuts of a neuron and the projection cuts of a
    step close;
``realtime``
    chapter 8: the MPC under a time limit in a periodic loop, and where the garbage collector runs;
``guarantees``
    chapter 9: nominal loops with and without terminal ingredients, horizon sweeps, the drift margin;
``multi``
    chapter 10: the two-link arm, the exact two-input CLF-CBF against SCIP, obstacle and MPC runs;
``compare``
    chapter 11: the five methods of the comparative study, their metrics and the Monte Carlo;
``shipped``
    ``make reference``: every shipped network and table, rewritten on local workers or a Dask cluster.
"""
from . import cheap_networks, compare, cuts, guarantees, multi, realtime, size, unseen
from .clfcbf import (braking_scan, cbf_failure_set_bounded, chapter_eps, clf_cbf_checks, cross_check_exact,
                     exponential_cbf_grid_check, highs_alone_check, largest_change_within_sample, paper_mean_ms,
                     sampled_clf_decrease, solve_time_table)
from .mpc import (active_fraction, binaries_per_step, closed_loop_checks, compare_to_reference, hardest_steps,
                  input_guarantee, log_head,
                  horizon_sweep, lever_repeats, lever_study, prediction_mismatch, recorded_problems, run_closed_loop,
                  repeat_numbers, shifted_plans,
                  table2, time_limit_numbers, tracking_error)
from .networks import (architecture_sweep, book_sweep, estimates_table, exact_preactivation_range, fresh_vs_shipped,
                       slope_in_v, table1_rows, width_experiment, write_sweep)

__all__ = ["braking_scan", "repeat_numbers", "time_limit_numbers",
           "cheap_networks", "compare", "cuts", "guarantees", "multi", "realtime", "size", "unseen", "architecture_sweep",
           "book_sweep", "estimates_table", "exact_preactivation_range", "slope_in_v",
           "fresh_vs_shipped", "table1_rows",
           "width_experiment", "write_sweep", "chapter_eps", "clf_cbf_checks", "cross_check_exact", "exponential_cbf_grid_check",
           "sampled_clf_decrease", "largest_change_within_sample", "cbf_failure_set_bounded",
           "solve_time_table", "highs_alone_check", "paper_mean_ms", "active_fraction", "binaries_per_step", "closed_loop_checks",
           "compare_to_reference",
           "hardest_steps", "log_head", "horizon_sweep", "lever_repeats", "lever_study",
           "prediction_mismatch", "recorded_problems",
           "run_closed_loop", "shifted_plans", "table2", "tracking_error", "input_guarantee"]
