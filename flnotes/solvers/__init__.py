"""One solver layer for the mixed-integer programs of the controllers.

The CLF-CBF programs (eq. CLF_CBF with the costs eq. LP_cost / eq. QP_cost) and
the MPC (eq. MPC_form_miqp) are all instances of

    min  0.5 w'H w + c'w + c0
    s.t. rl <= A w <= ru,   lb <= w <= ub,   w_i integer where integrality[i] == 1,

with the big-M constraints of eq. (MIP_general) inside ``A``. A controller
builds the program once (:class:`MIQP`), hands it to :func:`make_solver`, and
at every control step only changes numbers in place (:meth:`Solver.update`:
the measured state enters through ``lb``/``ub`` or ``rl``/``ru``, the
reference through ``c``, new node bounds through the big-M coefficients of
``A``) before calling :meth:`Solver.solve`. The back-ends keep their model
between calls:

* ``"highs"``: HiGHS through highspy (MILPs and continuous QPs; HiGHS has no
  mixed-integer QP solver);
* ``"scip"``: SCIP through PySCIPOpt, the reference MIQP solver (the quadratic
  objective becomes one epigraph ``s_i >= 0.5 lam_i y_i^2`` per eigenvalue of ``H``,
  with lean settings for a mixed-integer QP; see :class:`ScipSolver`);
* ``"daqp"``: DAQP, a dual active-set QP solver with its own depth-first
  branch and bound over binary constraints, written for hybrid MPC
  (Arnström, Bemporad & Axehill 2022);
* ``"gurobi"``, ``"cplex"``: commercial solvers, used only when installed.

``"auto"`` picks SCIP for a MILP (on the book's small big-M programs it was
measured faster than HiGHS and never wrong, while HiGHS returned sub-optimal
points as optimal at a few states, see :class:`HighsSolver`), HiGHS for a
continuous program and DAQP for a mixed-integer QP (the fastest exact back-end
measured on the MPC programs, see the chapter "Making it real-time"). Every
back-end reports the same :class:`MIQPResult`, with the objective re-evaluated
from the returned ``w`` (constants included) so that back-ends can be compared
number for number.

What "optimal" means
--------------------
A result has status ``"optimal"`` only when the optimum is proven: by a solver
status that is a proof (HiGHS ``kOptimal``, SCIP ``optimal``/``gaplimit``,
DAQP exit flag 1 after a search of at most :data:`VERIFY_NODES`
nodes on a mixed-integer program; every other status of each back-end is mapped explicitly, see
:data:`HIGHS_STATUS`, :data:`SCIP_STATUS`, :data:`DAQP_STATUS`) *and* a returned
point that satisfies the program's rows, bounds and integrality to
:data:`FEAS_TOL`. A claim that is not a proof is verified by an independent
solver instead of being trusted: DAQP's exit flags other than 1 (its flag 4,
returned after proximal-point iterations on the singular ``H`` of the big-M
programs, is not documented as optimal and was measured sub-optimal up to 12x)
and its "infeasible" on a mixed-integer program (its depth-first branch and
bound has declared feasible big-M programs infeasible), and its optimum after
a longer search (it has returned sub-optimal points as optimal there) are re-solved by SCIP
(HiGHS for a continuous program), warm-started with DAQP's point; HiGHS's
"infeasible" on a mixed-integer program is confirmed by SCIP. The result's
``message`` says when this happened.

The tolerance policy (one place, used by the controllers): :data:`BOX_TOL`
for a measured state on the face of the domain box, :data:`FEAS_TOL` for the
solvers' rows, and the network bound checked with the forward pass to
:data:`BOUND_TOL` (round-off of the forward pass itself); the controllers
tighten ``u_max^eps`` in the rows they hand to a solver until the returned
point passes that check (:func:`next_margin`).

Optimal up to these tolerances. Two degenerate cases are where tolerances decide: a step whose admissible inputs
shrink to a face (the network's output touches ``u_max^eps`` at a ridge and stays above it around), and an output
equal to ``u_max^eps`` exactly on a whole flat piece (a region where it is constant, as when ``u_max`` is set to a
quantile of sampled outputs that many samples share). A solver's point a tolerance past such a face lies where the
output exceeds ``u_max^eps``, and any margin removes the whole piece or ridge: on random networks the MPC once
returned a plan 1.5e-5 above the optimum as optimal, and its cold reference a plan 0.76 % above, or "infeasible"
for a program with an optimum. So before any margin the MPC (:class:`flnotes.mpc.engine.NetworkEngine`) and its
reference make such a point exact on a linear region of the network (the point's own, then the one the solver's
binaries name, each with the region's margin and then without it, the forward-pass check deciding, the cost within
the gap, at least :data:`TIGHTENED_GAP`, of the solver's; a constant output row never gets a margin), and the MPC has
SCIP (1e-9) solve a round again whose DAQP point (1e-6) is over the bound. A verdict of tightened rows (an optimum,
"nothing cheaper", no plan) counts as a proof only where the untightened program's lower bound backs it to the gap
(at least :data:`TIGHTENED_GAP`): the bound of the round where the rows were first tightened, or, where that one falls
short (a level-set round below the optimum), the bound SCIP gives for the deciding round's untightened program, whose
own plan is the answer where it passes the forward-pass check within the gap. Otherwise the step is an ``"error"``
whose message starts "not proven".

Limits: ``Solver.solve(time_limit=...)`` on the wall clock, and ``node_limit=...``, a work budget of the branch and
bound that stops the same program at the same node on every machine and load (``Solver.supports_node_limit``: SCIP's
``limits/totalnodes``, HiGHS's ``mip_max_nodes``; DAQP 0.11's branch and bound has a time limit and a per-node
iteration limit only, so it refuses a node limit on a mixed-integer program). What SoPlex, SCIP's LP solver, writes
straight to the C streams whatever SCIP's verbosity (a tolerance notice, :data:`C_NOTICES`) is dropped by a filter on
file descriptors 1 and 2 while any SCIP call runs; everything else written meanwhile passes.

Layout: :mod:`.problem` (the program, its result, the tolerance policy),
:mod:`.base` (the persistent-model interface and back-end selection), one
module per back-end (:mod:`.highs`, :mod:`.scip`, :mod:`.daqp`, :mod:`.gurobi`,
:mod:`.cplex`), and :mod:`.cvxpy_bridge` (SCIP as a cvxpy custom solver for a
program cvxpy writes: its QP form through :class:`ScipSolver`, or cvxpy's cone form
run without the interpreter lock; imported on demand, it needs cvxpy). Every SCIP
solve here first gives SCIP its own error printer back
(:func:`.scip.default_error_printer`): the one PySCIPOpt's ``redirectOutput``
installs for the whole process calls Python without the lock. This package sits at
the bottom of :mod:`flnotes`: it imports numpy, scipy and the solver libraries
only (cvxpy in the bridge), never a controller; a back-end fix never touches
MPC or CLF-CBF logic.
"""
from .base import SOLVER_BACKENDS, Solver, available_backends, make_solver, release_retired, retire
from .daqp import DAQP_STATUS, HANDOVER_S, VERIFY_NODES, DaqpSolver
from .highs import HIGHS_STATUS, HighsSolver
from .problem import BOUND_TOL, BOX_TOL, FEAS_TOL, MIQP, TIGHTENED_GAP, MIQPResult, next_margin, project_to_box
from .scip import C_NOTICES, SCIP_STATUS, ScipSolver

__all__ = ["SOLVER_BACKENDS", "Solver", "available_backends", "make_solver", "release_retired", "retire",
           "DAQP_STATUS", "DaqpSolver", "HANDOVER_S", "VERIFY_NODES", "HIGHS_STATUS", "HighsSolver", "BOUND_TOL",
           "BOX_TOL", "FEAS_TOL", "MIQP", "TIGHTENED_GAP", "MIQPResult", "next_margin", "project_to_box", "SCIP_STATUS",
           "ScipSolver", "C_NOTICES"]
