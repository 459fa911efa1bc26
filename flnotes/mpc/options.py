"""The MPC's options as one validated value: :class:`MPCOptions`.

Every field is a lever or a model choice of eq. (MPC_form_miqp); a combination that means nothing is
rejected with a message that says what to change, never silently ignored. :meth:`MPCOptions.combinations`
lists every accepted combination (the test suite solves each on recorded states and compares it with the
cold SCIP reference).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, fields
from typing import Iterator, Optional, Sequence, Union

#: Accepted MPC back-ends: ``"auto"`` (DAQP for a program with at most
#: :data:`flnotes.mpc.levers.AUTO_DAQP_BINARIES` binaries, :data:`flnotes.mpc.levers.AUTO_DAQP_COLD_BINARIES`
#: when the round has no incumbent to warm-start from, SCIP above), the persistent solvers of
#: :mod:`flnotes.solvers` that solve a mixed-integer QP, and ``"cvxpy-scip"``, the reference (the program written
#: with :func:`flnotes.encode`, solved cold by SCIP).
MPC_BACKENDS = ("auto", "daqp", "scip", "gurobi", "cplex", "cvxpy-scip")
#: Node bounds of eq. (MIP_general_c) per predicted step (see :mod:`flnotes.mpc.levers`).
BOUNDS = ("box", "horizon", "lp", "levelset")
#: The input-constraint model of the program: the network (the book's MIQP), or a linear model of the exact
#: constraint (a QP; see :mod:`flnotes.mpc.linear`).
CONSTRAINTS = ("network", "measured", "previous", "none")

_NETWORK_LEVERS = ("bounds", "screening", "lazy", "warm_start", "encode", "eliminate_stable", "lp", "first_level",
                   "repair", "branching", "bound_cache", "bang_bang")
#: DAQP's branching order (the binaries' column order, :data:`flnotes.mpc.program.ORDERS`).
BRANCHINGS = ("layers", "steps")
#: The first level ``J_up`` of the level-set rounds (``bounds="levelset"``; see :mod:`flnotes.mpc.engine`).
FIRST_LEVELS = ("incumbent", "relaxation")


@dataclass(frozen=True)
class MPCOptions:
    """How :class:`flnotes.MPC` builds and solves its program; every field is exact (none changes the optimum).

    Fields left ``None`` take the default of their context; a field given where it means nothing raises.

    Attributes
    ----------
    constraint
        ``"network"`` (default): ``|Phi_NN(z(k), v(k))| <= u_max^eps`` at every predicted step, the
        big-M MIQP of eq. (MPC_form_miqp). The others are the linear models a QP-based MPC uses instead
        (chapter "A comparative study"): ``"measured"`` the exact constraint at the measured state turned into
        linear bounds on ``v`` and applied at every step (constant extension); ``"previous"`` the exact
        constraint along the previous prediction, shifted (Kurtz & Henson 1998); ``"none"`` no input
        constraint (only the boxes of eq. MPC_form_miqp_d).
    backend
        One of :data:`MPC_BACKENDS` for ``"network"``. ``"auto"`` (default): each program assembled in a solve
        goes to DAQP when it has at most :data:`flnotes.mpc.levers.AUTO_DAQP_BINARIES` binaries (its branch and
        bound was measured fastest on small programs) and to SCIP above (faster on large ones, measured in the
        chapter "Making it real-time"); a round without an incumbent (nothing to warm-start DAQP from, most often
        an infeasible program) goes to DAQP only up to :data:`flnotes.mpc.levers.AUTO_DAQP_COLD_BINARIES`
        binaries. ``"daqp"`` or ``"scip"`` use one solver for every program. The linear
        models are QPs solved by DAQP (``"daqp"`` only).
    bounds
        Node bounds: ``"box"`` (FBBT on the domain box, the paper's setting), ``"horizon"`` (FBBT on the
        reachable boxes, ``z(0)`` fixed), ``"lp"`` (those, LP-tightened with ``|Phi_NN| <= u_max^eps``),
        ``"levelset"`` (default; the reachable boxes cut by the level set of the relaxation). The reference
        back-end accepts ``"box"`` (its default), ``"horizon"`` and ``"lp"``.
    screening
        Solve the QP without the network constraint first; its optimum is the MIQP's when it meets the
        constraint at every step.
    lazy
        Constraint generation: encode the network only at steps found violated, add violated ones, repeat.
        Needs ``encode="needed"``.
    warm_start
        The previous plan, shifted, as the first incumbent (and the level set's first level).
    encode
        ``"needed"`` (default): only steps whose output bounds do not already lie within
        ``[-u_max^eps, u_max^eps]``; ``"all"``: every step (the paper's program).
    eliminate_stable
        Stable neurons substituted (``y = a`` or ``y = 0``), no binary; ``False`` keeps a fixed binary each
        (the paper's count, ``N_p sum_k n_k``).
    lp
        With ``bounds="levelset"`` only: LP tightening (:func:`flnotes.lp_bounds`) of the needed steps on the
        level-set boxes, each round. ``"auto"`` (default): only in the rounds where FBBT leaves more than
        :data:`flnotes.mpc.levers.LP_AUTO_BINARIES` unstable neurons in the steps to encode (below that the
        branch and bound was measured cheaper than the LPs); ``True``: every round; ``False``: never.
    first_level
        With ``bounds="levelset"`` only: the level ``J_up`` of the first level-set round. ``"incumbent"``
        (default): the cost of the incumbent (the warm start, or the repaired plan of ``repair``), so one round
        holds the optimum; without an incumbent (most often an infeasible program), ``J_c + max(1, |J_c|)``
        (:data:`flnotes.mpc.engine.FIRST_LEVEL_NO_INCUMBENT`). ``"relaxation"``: the relaxation's optimum
        ``J_c`` plus ``1e-3 max(1, |J_c|)``. Either margin is multiplied by 4 per round until a plan is found
        (a small level: fewer unstable neurons per round, more rounds).
    repair
        The relaxation's optimum repaired step by step along the QP without the network
        (:func:`flnotes.mpc.fallback.qp_repair`: at step ``k`` the QP with ``v(0..k-1)`` fixed, its ``v(k)`` moved
        to the nearest admissible input) is the first incumbent when it passes the program's check
        (:meth:`flnotes.mpc.prediction.Prediction.feasible`) and is cheaper than the warm start; the cheaper of the
        two is then optimized over the network's linear region around it and its neighbours
        (:func:`flnotes.mpc.region.region_qp`, a convex QP per region). Under a time limit this is the plan returned
        when the branch and bound does not finish, so a poor warm start is not carried from step to step.
    bang_bang
        With ``repair`` only, for one input: when neither the warm start nor the repaired relaxation gives an
        incumbent, the ``2 N_p`` one-switch plans at the input bounds (``v`` at ``v_hi`` for the first ``s`` steps,
        then at ``v_lo``, and the reverse), each repaired step by step
        (:func:`flnotes.mpc.bang_bang.one_switch_plans`), are tried; the cheapest that passes the check is the first
        incumbent, optimized over its linear region as above. Where the bound is active over most of the horizon
        the optimum is often of this shape, and the greedy repair of the relaxation misses it. Left ``None``, the
        :class:`flnotes.MPC` sets it to ``True`` for one input and ``False`` for more; ``True`` with more than one
        input is an error.
    branching
        With a back-end that runs DAQP (``"auto"``, ``"daqp"``) only: DAQP branches on the first fractional binary
        in column order, so the order of the binaries is its branching order. ``"layers"`` (default): the
        first hidden layer's binaries of every encoded step (early steps first) before the second layer's;
        ``"steps"``: step by step, each step's layers in order.
    bound_cache
        Where LP bounds are computed (``bounds="lp"``, or ``"levelset"`` with ``lp`` ``True`` or ``"auto"``) only:
        keep them and start the LPs of a later box from the kept bounds of every box that contains it
        (:class:`flnotes.mpc.bound_cache.BoundCache`; valid there, so exact). Default ``True`` there. The kept bounds
        hold for the network and ``u_max^eps``, not for a state, so they serve every later step;
        :meth:`flnotes.MPC.reset` forgets them.
    iterations
        With ``constraint="previous"`` only: QPs per sampling instant, each linearizing along the last plan
        (1 is Kurtz & Henson's scheme; more iterate it within the period).
    """

    constraint: str = "network"
    backend: Optional[str] = None
    bounds: Optional[str] = None
    screening: Optional[bool] = None
    lazy: Optional[bool] = None
    warm_start: Optional[bool] = None
    encode: Optional[str] = None
    eliminate_stable: Optional[bool] = None
    lp: Optional[Union[bool, str]] = None
    first_level: Optional[str] = None
    repair: Optional[bool] = None
    branching: Optional[str] = None
    bound_cache: Optional[bool] = None
    bang_bang: Optional[bool] = None
    iterations: Optional[int] = None

    def __post_init__(self) -> None:
        given = {f.name for f in fields(self) if getattr(self, f.name) is not None}
        put = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 - frozen: resolve defaults once
        for k in ("screening", "lazy", "warm_start", "eliminate_stable", "repair", "bound_cache", "bang_bang"):
            if k in given and not isinstance(getattr(self, k), bool):
                raise TypeError(f"{k} must be True or False, got {getattr(self, k)!r}")
        if "lp" in given and not (isinstance(self.lp, bool) or self.lp == "auto"):
            raise TypeError(f"lp must be True, False or 'auto', got {self.lp!r}")
        if self.constraint not in CONSTRAINTS:
            raise ValueError(f"constraint must be one of {CONSTRAINTS}, got {self.constraint!r}")
        if self.constraint != "network":
            bad = sorted(given & set(_NETWORK_LEVERS))
            if bad:
                raise ValueError(f"{', '.join(bad)} only apply to constraint='network' (the MIQP); with "
                                 f"constraint={self.constraint!r} the program is a QP without the network: drop them")
            if self.backend not in (None, "daqp", "auto"):
                raise ValueError(f"constraint={self.constraint!r} gives a QP solved by DAQP: backend must be 'daqp' "
                                 "(or 'auto', which picks it), "
                                 f"got {self.backend!r}")
            if self.constraint != "previous" and self.iterations is not None:
                raise ValueError("iterations only applies to constraint='previous' (the linearization along the "
                                 "previous prediction)")
            it = 1 if self.iterations is None else self.iterations
            if isinstance(it, bool) or int(it) != it or it < 1:
                raise ValueError(f"iterations must be a positive integer, got {self.iterations!r}")
            put("backend", "daqp")
            put("iterations", int(it) if self.constraint == "previous" else None)
            return
        if self.iterations is not None:
            raise ValueError("iterations only applies to constraint='previous'")
        backend = "auto" if self.backend is None else self.backend
        if backend == "highs":
            raise ValueError("HiGHS solves MILPs and convex QPs but not mixed-integer QPs such as eq. (MPC_form_miqp): "
                             f"choose one of {MPC_BACKENDS}")
        if backend not in MPC_BACKENDS:
            raise ValueError(f"backend must be one of {MPC_BACKENDS}, got {backend!r}")
        put("backend", backend)
        if backend == "cvxpy-scip":
            # the reference: the whole program written with fl.encode, solved cold; no lever applies
            if given & {"first_level", "branching", "bound_cache", "bang_bang"}:
                raise ValueError("backend='cvxpy-scip' is the cold reference without a level set, DAQP, kept LP "
                                 "bounds or a first incumbent: first_level, branching, bound_cache and bang_bang do "
                                 "not apply (drop them or choose 'daqp' or 'auto')")
            for k, off in (("screening", False), ("lazy", False), ("warm_start", False), ("lp", False),
                           ("encode", "all"), ("eliminate_stable", True), ("repair", False)):
                if k in given and getattr(self, k) != off:
                    raise ValueError(f"backend='cvxpy-scip' is the cold reference: every step encoded, no lever; "
                                     f"{k}={getattr(self, k)!r} does not apply (drop it or choose 'daqp' or 'scip')")
                put(k, off)
            bounds = "box" if self.bounds is None else self.bounds
            if bounds not in ("box", "horizon", "lp"):
                raise ValueError(f"backend='cvxpy-scip' takes bounds 'box', 'horizon' or 'lp', got {bounds!r} "
                                 f"('levelset' restricts the program to a level of the cost: a persistent back-end's lever)")
            put("bounds", bounds)
            return
        bounds = "levelset" if self.bounds is None else self.bounds
        if bounds not in BOUNDS:
            raise ValueError(f"bounds must be one of {BOUNDS}, got {bounds!r}")
        put("bounds", bounds)
        encode = "needed" if self.encode is None else self.encode
        if encode not in ("needed", "all"):
            raise ValueError(f"encode must be 'needed' or 'all', got {encode!r}")
        put("encode", encode)
        if encode == "all" and self.lazy:
            raise ValueError("lazy=True (constraint generation) encodes a subset of the steps; encode='all' encodes "
                             "every step: choose one")
        put("lazy", encode == "needed" if self.lazy is None else self.lazy)
        if self.lp and bounds != "levelset":
            raise ValueError(f"lp={self.lp!r} tightens the level-set boxes (bounds='levelset'); for LP bounds on the "
                             "reachable boxes use bounds='lp'")
        put("lp", ("auto" if bounds == "levelset" else False) if self.lp is None else self.lp)
        if "first_level" in given:
            if bounds != "levelset":
                raise ValueError(f"first_level={self.first_level!r} sets the first level of the level set "
                                 f"(bounds='levelset'); with bounds={bounds!r} drop it")
            if self.first_level not in FIRST_LEVELS:
                raise ValueError(f"first_level must be one of {FIRST_LEVELS}, got {self.first_level!r}")
        put("first_level", ("incumbent" if bounds == "levelset" else None) if self.first_level is None
            else self.first_level)
        if "branching" in given:
            if backend not in ("auto", "daqp"):
                raise ValueError(f"branching={self.branching!r} orders DAQP's branch and bound; backend={backend!r} "
                                 "branches by its own rules: drop it or choose backend 'auto' or 'daqp'")
            if self.branching not in BRANCHINGS:
                raise ValueError(f"branching must be one of {BRANCHINGS}, got {self.branching!r}")
        put("branching", ("layers" if backend in ("auto", "daqp") else None) if self.branching is None
            else self.branching)
        lp_runs = bounds == "lp" or (bounds == "levelset" and self.lp is not False)
        if "bound_cache" in given and not lp_runs:
            raise ValueError(f"bound_cache={self.bound_cache!r} keeps LP bounds, and with bounds={bounds!r}"
                             + (", lp=False" if bounds == "levelset" else "") + " no LP bound is computed: drop it, "
                             "or choose bounds='lp' or bounds='levelset' with lp=True or 'auto'")
        put("bound_cache", (True if lp_runs else None) if self.bound_cache is None else self.bound_cache)
        for k in ("screening", "warm_start", "eliminate_stable", "repair"):
            put(k, True if getattr(self, k) is None else getattr(self, k))
        if "bang_bang" in given and not self.repair:
            raise ValueError(f"bang_bang={self.bang_bang!r} adds first incumbents to repair, and repair=False: drop "
                             "bang_bang or set repair=True")

    # ------------------------------------------------------------------ helpers
    @property
    def is_reference(self) -> bool:
        """The cold SCIP reference through cvxpy."""
        return self.backend == "cvxpy-scip"

    @classmethod
    def combinations(cls, backends: Sequence[str] = ("auto", "daqp", "scip", "cvxpy-scip"),
                     constraints: Sequence[str] = CONSTRAINTS) -> Iterator["MPCOptions"]:
        """Every accepted combination for the given back-ends and constraint models (each exactly once)."""
        seen = set()
        for constraint in constraints:
            if constraint != "network":
                for it in ((1, 3) if constraint == "previous" else (None,)):
                    o = cls(constraint=constraint, iterations=it)
                    if o not in seen:
                        seen.add(o)
                        yield o
                continue
            for backend in backends:
                if backend == "cvxpy-scip":
                    grid = [dict(bounds=b) for b in ("box", "horizon", "lp")]
                else:
                    grid = [dict(bounds=b, screening=s, warm_start=w, eliminate_stable=e, encode=enc, lazy=lz, lp=lp,
                                 first_level=fl, repair=rp, branching=br, bound_cache=bc, bang_bang=bb)
                            for b, s, w, e, (enc, lz), lp, fl, (rp, bb), br, bc in itertools.product(
                                BOUNDS, (True, False), (True, False), (True, False),
                                (("needed", True), ("needed", False), ("all", False)), (False, True, "auto"),
                                FIRST_LEVELS + (None,), ((True, True), (True, False), (False, None)),
                                BRANCHINGS + (None,), (True, False, None))
                            if not (lp and b != "levelset") and (fl is None) == (b != "levelset")
                            and (br is None) == (backend not in ("auto", "daqp"))
                            and (bc is None) == (b not in ("lp", "levelset") or (b == "levelset" and lp is False))]
                for kw in grid:
                    o = cls(constraint="network", backend=backend, **kw)
                    if o not in seen:
                        seen.add(o)
                        yield o

    def __str__(self) -> str:
        if self.constraint != "network":
            return f"{self.constraint} (QP, DAQP" + (f", {self.iterations} iteration(s))" if self.iterations else ")")
        if self.is_reference:
            return f"cvxpy-scip (cold reference), bounds={self.bounds}"
        on = [k for k in ("screening", "lazy", "warm_start") if getattr(self, k)]
        on += {True: ["lp"], "auto": ["lp when large"], False: []}[self.lp]
        on += ["repair"] if self.repair else []
        on += ["first level: relaxation"] if self.first_level == "relaxation" else []
        on += ["branching step by step"] if self.branching == "steps" else []
        on += ["LP bounds not kept"] if self.bound_cache is False else []
        on += ["no one-switch plans"] if self.repair and self.bang_bang is False else []
        extra = [] if self.eliminate_stable else ["stable neurons kept"]
        extra += [] if self.encode == "needed" else ["every step encoded"]
        return f"{self.backend}, bounds={self.bounds}" + "".join(f", {s}" for s in on + extra)
