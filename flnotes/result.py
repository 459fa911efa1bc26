"""One record for a controller's answer at one sampling instant, shared by every controller.

The CLF-CBF controller (:class:`flnotes.ClfCbfController`), the MPC (:class:`flnotes.MPC`), the plain
feedback laws and :func:`flnotes.simulate` all speak :class:`StepResult`, with one set of status words
(:data:`STATUSES`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

Array = np.ndarray

#: The status words of a step: a proven optimum, an incumbent at the time limit (its ``gap`` recorded), a
#: program without a feasible point, a solver or numerical failure (``message`` says which), a plain
#: feedback law that solves nothing.
STATUSES = ("optimal", "time_limit", "infeasible", "error", "nominal")


@dataclass
class StepResult:
    """A controller's answer at one sampling instant.

    Attributes
    ----------
    v
        The virtual input to apply, shape (m,); ``None`` only inside a controller, never handed to
        :func:`flnotes.simulate`.
    status
        One of :data:`STATUSES`; anything but ``"optimal"`` (or ``"nominal"`` for a plain law) says why
        ``v`` is not a proven optimum.
    objective, bound, gap
        Cost of the returned point, the solver's lower bound and the relative gap (NaN when not applicable).
    nodes
        Branch-and-bound nodes (0 when no mixed-integer program was solved).
    solve_time
        Seconds spent by the controller for this step (bounds, set-up, solves, checks).
    fallback
        True when ``v`` comes from the controller's documented fallback rather than from a solved program.
    input_admissible
        True when ``|Phi_NN(z, v)| <= u_max^eps`` holds at the measured state (forward pass); False only on a
        fallback where no admissible ``v`` exists.
    screened
        True when a program without the network constraint already satisfied it (hence was optimal).
    backend, message
        Which solver ran, and anything it or the controller said.
    z_pred, v_pred, u_nn_pred
        The predicted plan of a predictive controller, shapes (N_p + 1, n_z), (N_p, m), (N_p, m)
        (``Phi_NN`` along the plan); ``None`` for a one-step controller.
    n_binaries
        Binaries left free in the last mixed-integer program solved.
    encoded_steps
        Predicted steps whose network constraint was encoded in that program (step 0 included where, for one
        input, its constraint was the bounds of its exact range of inputs: ``flnotes.mpc.engine.FIRST_RANGE``).
    rounds
        Programs solved in this step (constraint-generation rounds; 0 when screened).
    warm_started
        True when a previous plan was handed to the solver as a first incumbent.
    info
        Controller-specific extras (e.g. the CLF-CBF's slack ``delta`` and certificate values; the MPC's
        reference ``z_ref`` over the horizon, ``plan_feasible`` (the forward-pass check of the plan),
        ``incumbent`` (where the first incumbent came from: ``"warm start"``, ``"repaired relaxation"``,
        ``"one-switch plan"`` or ``None``), ``region_improved`` (the QP of its linear region made it cheaper),
        ``bang_bang_s`` (seconds spent on the one-switch plans, ``None`` where they were not tried), ``lp_rounds`` and,
        under a time limit, ``cut_off`` (the step answered at its cut-off while the engine's solve ran on)); the
        MPC's ``cpu_time`` (seconds of CPU the step used until its answer: the calling thread's and, under a time
        limit, the engine thread's, ``engine_cpu_time``; against ``solve_time`` it tells the controller's own work
        from time the machine gave to other processes; as the sum of two threads that can run at once on two cores
        it can exceed ``solve_time``) and ``process_cpu_time`` (the CPU time of every thread of the
        process during the call: above ``cpu_time``, other threads of the process took it, e.g. a library's).
    """

    v: Optional[Array]
    status: str = "optimal"
    objective: float = np.nan
    bound: float = np.nan
    gap: float = np.nan
    nodes: int = 0
    solve_time: float = 0.0
    fallback: bool = False
    input_admissible: bool = True
    screened: bool = False
    backend: str = ""
    message: str = ""
    z_pred: Optional[Array] = None
    v_pred: Optional[Array] = None
    u_nn_pred: Optional[Array] = None
    n_binaries: int = 0
    encoded_steps: tuple = ()
    rounds: int = 0
    warm_started: bool = False
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}, got {self.status!r} (put details in message)")

    @property
    def ok(self) -> bool:
        """A point feasible for the whole program: optimal, or an incumbent at the time limit, not a fallback."""
        return self.v is not None and not self.fallback and self.status in ("optimal", "time_limit")
