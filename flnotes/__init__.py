"""flnotes: constrained feedback linearization with ReLU networks encoded as MILPs.

The data flow, one direction::

    FLSystem --phi, box--> fit_relu --> ReLUNet --> fbbt / lp_bounds --> encode (big-M) --> controller --> simulate
       |                                  |                                                   ^
       +------------phi, box--------------+--> pso_max_error / certify_error ------eps--------+

``import flnotes as fl`` gives every public name below.
"""
from .config import FAST, scale
from .tables import Table, time_stats
from .systems import FLSystem, brunovsky, discretize, msd, quad1d
from .network import ReLUNet, TrainingReport, fit_relu, uniform_grid
from .bounds import NodeBounds, fbbt, interval_affine, sample_preactivations
from .encoding import BigMForm, Encoding, bigm_form, encode, forward_milp
from .errors import SolverFailure
from .simulate import Controller, FeedbackLaw, SimLog, StepResult, simulate
from . import interval, plots, reference, widgets
from .error import *  # noqa: F401,F403  pso_max_error, certify_error, ErrorBracket, ...
from .miqp import BACKENDS, MIQP, HorizonMIQP, HorizonResult, MIQPResult, Solver, available_backends, make_solver
from .tightening import *  # noqa: F401,F403  lp_bounds, horizon_boxes, ...
from .control import *  # noqa: F401,F403  ClfCbfController, QuadraticCLF, DistanceCBF, exact 1-D solver, ...
from .control import AffineCBF, ExponentialCBF, cbf_condition_fails
from .mpc import *  # noqa: F401,F403  MPC, sine_reference, ...
from . import paper
from .paper import paper_net, paper_eps
from . import studies
