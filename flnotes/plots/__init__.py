"""The book's figures: each function turns a system, a network or a run log into one figure.

Submodules hold the figures of one part of the book each; everything is
re-exported here by name so a notebook writes ``fl.plots.phase_portrait(...)``.
Plots only draw: what they show is computed by the library or by
:mod:`flnotes.studies`.
"""
from .style import COLORS, bound_lines, new_axes, use_book_style
from .foundations import (static_feasible_set, fl_identity_residual, affine_v_interval,
                          plot_feasible_set, plot_feasible_v, explore_feasible_set,
    plot_zeta, plot_input_violation, discretization_gap, plot_discretization_gap, plot_error_slice, plot_line_cut,
    plot_width_experiment, plot_relu_bigm, bounds_looseness, plot_bounds_vs_samples, unstable_fixed_z,
    plot_unstable_fixed_z, unstable_vs_box_size, plot_unstable_vs_box_size)
from .error import (static_architecture, error_slice, pso_swarm, estimator_convergence, certification_progress, partition_slice,
    eps_sweep, violation_line, show_source, explore_architecture)
from .clfcbf import (clfcbf_phase_portrait, clfcbf_signals, clfcbf_figure4, exact_1d_plot, solve_time_plot, cbf_failure_plot,
    wall_runs_plot)
from .mpc import plot_mpc_tracking, plot_mpc_input, plot_horizon_sweep, plot_intersample, plot_step_times, explore_horizon
from .realtime import step_times, scaling, lever_bars
from .static import FramePlayer, frame_player
from .multi import input_sets_plot
from .compare import METHOD_COLORS, plot_methods_run, plot_monte_carlo
from .guarantees import plot_drift_curve, plot_region_of_attraction, plot_terminal_bisection, plot_terminal_sweep
from .deadline import answer_times, gap_histogram
from .size import size_plot

__all__ = [
    'METHOD_COLORS', 'plot_methods_run', 'plot_monte_carlo', 'plot_terminal_sweep',
    'COLORS', 'new_axes', 'bound_lines', 'use_book_style', 'static_feasible_set', 'fl_identity_residual',
    'affine_v_interval', 'plot_feasible_set', 'plot_feasible_v', 'explore_feasible_set', 'plot_zeta', 'plot_input_violation',
    'discretization_gap', 'plot_discretization_gap', 'plot_error_slice', 'plot_line_cut', 'plot_width_experiment',
    'plot_relu_bigm', 'bounds_looseness', 'plot_bounds_vs_samples', 'unstable_fixed_z', 'plot_unstable_fixed_z',
    'unstable_vs_box_size', 'plot_unstable_vs_box_size', 'static_architecture', 'error_slice', 'pso_swarm',
    'estimator_convergence', 'certification_progress', 'partition_slice', 'eps_sweep', 'violation_line',
    'show_source', 'explore_architecture', 'clfcbf_phase_portrait', 'clfcbf_signals', 'clfcbf_figure4',
    'exact_1d_plot', 'solve_time_plot', 'cbf_failure_plot', 'wall_runs_plot', 'plot_mpc_tracking',
    'plot_mpc_input', 'plot_horizon_sweep', 'plot_intersample', 'plot_step_times', 'explore_horizon',
    'step_times', 'scaling', 'lever_bars', 'FramePlayer', 'frame_player', 'input_sets_plot',
    'plot_drift_curve', 'plot_region_of_attraction', 'plot_terminal_bisection', 'gap_histogram', 'answer_times',
    'size_plot'
]
