"""The one MPC engine of the book: eq. (MPC_form_miqp) with the network constraint at every predicted step.

Layout (a module imports only modules above it in this list):

* :mod:`.options`: :class:`MPCOptions`, the levers and the constraint model as one validated value;
* :mod:`.prediction`: :class:`Prediction`, condensing, cost, boxes, terminal rows, the screening QP and
  the one feasibility check;
* :mod:`.program`: the program form handed to a solver (condensed, free binaries only);
* :mod:`.bound_cache`: :class:`BoundCache`, LP node bounds kept for the later boxes they contain;
* :mod:`.levers`: node bounds per option, the steps that need encoding;
* :mod:`.fallback`: what is applied when a solve gives no plan, and the step-by-step repairs;
* :mod:`.bang_bang`: one-switch plans at the input bounds, repaired step by step in a batch (a first incumbent);
* :mod:`.region`: the program on one activation region of the network (a convex QP), the first incumbent's
  last improvement;
* :mod:`.engine`: :class:`NetworkEngine`, the exact solve with the levers (level set, constraint generation,
  warm start);
* :mod:`.reference`: the paper's program written with :func:`flnotes.encode`, solved cold by SCIP;
* :mod:`.linear`: the linear models of the exact constraint used by the QP-based MPCs of the comparison;
* :mod:`.controller`: :class:`MPC`, the controller (validation, warm start, fallback, history, the cut-off).
"""
from .bang_bang import bang_bang_incumbent, nearest_admissible, one_switch_plans
from .bound_cache import CACHE_BOXES, BoundCache
from .controller import (CUT_OFF_MIN_S, FALLBACK_POST_MIN_S, FALLBACK_POST_SHARE, MPC, NODES_PER_SECOND,
                         RESERVE_DECAY, RESERVE_MAX_SHARE, RESERVE_SHARE, WORK_LIMITS, sine_reference)
from .engine import NetworkEngine
from .levers import AUTO_DAQP_BINARIES, AUTO_DAQP_COLD_BINARIES, LP_AUTO_BINARIES
from .options import BOUNDS, CONSTRAINTS, MPC_BACKENDS, MPCOptions
from .prediction import DAQP_OPTIONS, Prediction
from .region import REGION_MOVES, region_qp, region_rows

__all__ = ["MPC", "MPCOptions", "MPC_BACKENDS", "BOUNDS", "CONSTRAINTS", "Prediction", "NetworkEngine",
           "DAQP_OPTIONS", "sine_reference", "LP_AUTO_BINARIES", "AUTO_DAQP_BINARIES", "AUTO_DAQP_COLD_BINARIES",
           "REGION_MOVES", "region_qp", "region_rows", "RESERVE_SHARE", "RESERVE_MAX_SHARE", "RESERVE_DECAY",
           "FALLBACK_POST_SHARE", "FALLBACK_POST_MIN_S", "CUT_OFF_MIN_S",
           "NODES_PER_SECOND", "WORK_LIMITS",
           "BoundCache", "CACHE_BOXES", "one_switch_plans",
           "bang_bang_incumbent", "nearest_admissible"]
