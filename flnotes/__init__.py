"""flnotes: constrained feedback linearization with ReLU networks encoded as MILPs.

The data flow, one direction::

    FLSystem --phi, box--> fit_relu --> ReLUNet --> fbbt / lp_bounds --> encode (big-M) --> controller --> simulate
       |                                  |                                                   ^
       +------------phi, box--------------+--> pso_max_error / certify_error ------eps--------+

Layers, lowest first (a module imports only from layers below it)::

    base         config, _checks, errors, tables (Table, time_stats), repeats, result (StepResult, STATUSES)
    models       systems, network, reference (shipped data), interval
    solvers      solvers/ (MIQP, one module per back-end; numpy, scipy and the solver libraries only)
    constraint   bounds, tightening, encoding (big-M), error (eps), pieces, simulate (owns time)
    controllers  control (CLF-CBF), mpc/ (the one MPC engine: options, prediction, program, levers,
                 engine, reference, linear, fallback, region, controller), nmpc (CasADi/IPOPT on the plant),
                 terminal, intersample, arm
    chapters     paper, studies/ (the only importers of paper, with bench/), plots/, widgets, grading

``import flnotes as fl`` gives every public name below, re-exported by name
(see ``__all__``); the modules and which equation each owns are listed in
the README's architecture section.
"""
from .config import FAST, scale
from .tables import Table, time_stats
from . import repeats
from .systems import FLSystem, brunovsky, discretize, integrators, msd, quad1d
from .network import ReLUNet, TrainingReport, fit_relu, uniform_grid
from .bounds import NodeBounds, fbbt, interval_affine, sample_preactivations
from .encoding import BigMForm, Encoding, bigm_form, encode, forward_milp
from .errors import SolverFailure
from .result import STATUSES, StepResult
from .simulate import Controller, FeedbackLaw, SimLog, simulate
from . import interval, plots, reference, solvers, widgets
from .error import (ErrorEstimate, ErrorBracket, NotCertifiable, pso_max_error, sample_max_error, grid_max_error, de_max_error,
                    certify_error, error_function, worst_violation, local_max_error, enclosure_widths)
from .solvers import SOLVER_BACKENDS, MIQP, MIQPResult, Solver, available_backends, make_solver
from .tightening import EmptyBoxError, lp_bounds, horizon_boxes, intersect, propagate, LPTightener, ellipsoid_box
from .enclosure import AffineEnclosure, affine_enclosure
from .atlas import BoundAtlas, bound_atlas, check_atlas, load_atlas
from .control import (Certificate, QuadraticCLF, DistanceCBF, as_certificate, PiecewiseAffine1D, network_pieces_1d,
                      exact_1d_feasible_set, solve_exact_1d, ClfCbfController, CLF_CBF_BACKENDS, AffineCBF,
                      ExponentialCBF, cbf_condition_fails)
from .mpc import MPC, MPC_BACKENDS, MPCOptions, sine_reference
from . import nmpc
from .nmpc import NonlinearMPC, SaturatedInput, input_to_v
from . import paper
from .paper import paper_net, paper_eps
from . import studies
from .arm import two_link_arm, arm_net
from . import arm, pieces
from . import intersample, terminal
from .terminal import RegionOfAttraction, TerminalSet, region_of_attraction, terminal_set
from .intersample import DriftBound, drift_curve, intersample_drift

__all__ = [
    'FAST', 'scale', 'Table', 'time_stats', 'repeats', 'FLSystem', 'brunovsky', 'discretize', 'integrators', 'msd', 'quad1d',
    'ReLUNet', 'TrainingReport', 'fit_relu', 'uniform_grid', 'NodeBounds', 'fbbt', 'interval_affine',
    'sample_preactivations', 'BigMForm', 'Encoding', 'bigm_form', 'encode', 'forward_milp', 'SolverFailure',
    'Controller', 'FeedbackLaw', 'SimLog', 'StepResult', 'STATUSES', 'simulate', 'interval', 'plots', 'reference',
    'solvers', 'widgets',
    'ErrorEstimate', 'ErrorBracket', 'NotCertifiable', 'pso_max_error', 'sample_max_error', 'grid_max_error',
    'de_max_error', 'certify_error', 'error_function', 'worst_violation', 'local_max_error', 'enclosure_widths',
    'SOLVER_BACKENDS', 'MIQP', 'MIQPResult', 'Solver', 'available_backends',
    'make_solver', 'EmptyBoxError', 'lp_bounds', 'horizon_boxes', 'intersect', 'propagate', 'LPTightener',
    'ellipsoid_box', 'AffineEnclosure', 'affine_enclosure', 'BoundAtlas', 'bound_atlas', 'check_atlas', 'load_atlas',
    'Certificate', 'QuadraticCLF', 'DistanceCBF', 'as_certificate', 'PiecewiseAffine1D',
    'network_pieces_1d', 'exact_1d_feasible_set', 'solve_exact_1d', 'ClfCbfController', 'CLF_CBF_BACKENDS', 'AffineCBF',
    'ExponentialCBF', 'cbf_condition_fails', 'MPC', 'MPCOptions', 'MPC_BACKENDS', 'sine_reference',
    'nmpc', 'NonlinearMPC', 'SaturatedInput', 'input_to_v', 'paper', 'paper_net',
    'paper_eps', 'studies', 'two_link_arm', 'arm_net', 'arm', 'pieces', 'intersample', 'terminal',
    'RegionOfAttraction', 'TerminalSet', 'region_of_attraction', 'terminal_set', 'DriftBound', 'drift_curve',
    'intersample_drift'
]
