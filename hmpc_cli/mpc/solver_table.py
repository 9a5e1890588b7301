"""The NLP back-ends of the MPC (``mpc.solver``): one table, name -> :class:`Backend`.

Each entry says how to build its cold ``nlpsol`` options, whether it needs stage-wise
dynamics, whether it has a warm instance, whether it loads the build cache's compiled
NLPs, which back-end re-solves its failed solves, and which ``mpc.solver_options``
sections are its own. The settings' allowed names (:data:`SolverName`), the stage-wise
check, :class:`~hmpc_cli.mpc.solver.SolverSession` and the build cache
(:mod:`hmpc_cli.mpc.cache`) read the table, so a new back-end is one
:func:`register_backend` call.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Annotated, Any

from pydantic import AfterValidator, Strict, ValidationError
from pydantic_core import InitErrorDetails, PydanticCustomError

from hmpc_cli.core.settings_types import magnitude_problem
from hmpc_cli.mpc.backends import OCPStructure, rti_step_kept, rti_success, sqp_options


@dataclass(frozen=True)
class WarmStart:
    """Options of the warm IPOPT instance (primal-dual warm starts).

    Attributes:
        mu_init: initial barrier parameter.
        bound_push: ``warm_start_{bound,mult_bound,slack_bound}_push``.
    """

    mu_init: float
    bound_push: float


@dataclass(frozen=True)
class SolverArgs:
    """What a back-end's cold options are built from.

    Attributes:
        max_iter: iteration limit.
        tol: convergence tolerance.
        max_wall_time: wall-time cap [s] (None: none).
        equality: per row, True for equality rows, shape (ng,) (stage-wise back-ends).
        nlpsol: the user's ``nlpsol`` options (``mpc.solver_options`` without any
            back-end's sections).
        sections: the user's options of this back-end's own sections.
        nlp: the NLP ``{"x", "p", "f", "g"}``, or a compiled library's path.
        structure: the NLP's stage structure (stage-wise back-ends).
        sqp_iter: SQP iterations per solve (real-time iterations).
        residuals: least-squares residuals of the cost (see
            :func:`hmpc_cli.mpc.backends.gauss_newton_hessian`).
    """

    max_iter: int
    tol: float = 1e-8
    max_wall_time: float | None = None
    equality: list[bool] | None = None
    nlpsol: dict = field(default_factory=dict)
    sections: dict = field(default_factory=dict)
    nlp: dict | str | None = None
    structure: OCPStructure | None = None
    sqp_iter: int = 10
    residuals: Any = None


@dataclass(frozen=True)
class Backend:
    """One NLP back-end.

    Attributes:
        name: the value of ``mpc.solver``.
        plugin: the CasADi ``nlpsol`` plugin.
        options: :class:`SolverArgs` -> the cold instance's ``nlpsol`` options.
        summary: one phrase for the settings' description.
        stagewise: needs stage-wise dynamics (refuses ``input_hold = "foh"``); its
            session gets the NLP's equality rows and stage structure.
        warm: (cold options, :class:`WarmStart`, own sections, :class:`SolverArgs`) ->
            the warm instance's options (None: warm starts run on the cold instance).
        compilable: loads the build cache's compiled NLP (IPOPT's generated functions).
        judge: (status, converged, max violation) -> success, for a bounded run (a
            fixed number of SQP iterations): :func:`~hmpc_cli.mpc.backends.rti_success`
            or :func:`~hmpc_cli.mpc.backends.rti_step_kept` (None: the solver's own flag).
        fallback: the back-end that solves again a solve this one failed (None: none).
        switching: back-end of the switching chain NLP when ``mpc.switching_solver`` is
            unset (None: this one).
        sections: ``mpc.solver_options`` keys that are this back-end's (the other
            back-ends drop them).
        probe: unknown options show only when it solves: the set-up checks solve a tiny
            NLP with them (:func:`~hmpc_cli.mpc.solver.option_problems`).
    """

    name: str
    plugin: str
    options: Callable[[SolverArgs], dict]
    summary: str = ""
    stagewise: bool = False
    warm: Callable[[dict, WarmStart, dict, SolverArgs], dict] | None = None
    compilable: bool = False
    judge: Callable[[str, bool, float], bool] | None = None
    fallback: str | None = None
    switching: str | None = None
    sections: tuple[str, ...] = ()
    probe: bool = False


#: the back-ends by name (in the order of the settings' ``enum``)
SOLVERS: dict[str, Backend] = {}


def register_backend(backend: Backend) -> Backend:
    """Adds ``backend`` to :data:`SOLVERS` (replacing one of its name); returns it.

    Raises:
        ValueError: its fallback or switching back-end is not in the table.
    """
    for ref in (backend.fallback, backend.switching):
        if ref is not None and ref not in SOLVERS and ref != backend.name:
            raise ValueError(f"back-end {backend.name!r} names the unknown back-end {ref!r}")
    SOLVERS[backend.name] = backend
    return backend


def unknown(name: object) -> str:
    """``unknown NLP back-end 'x'`` with the closest name and the known names."""
    close = difflib.get_close_matches(str(name), list(SOLVERS), n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"unknown NLP back-end {name!r}{hint}; known: {', '.join(SOLVERS)}"


def backend_of(name: str) -> Backend:
    """The table's entry ``name``.

    Raises:
        ValueError: no such back-end (the message names the known ones).
    """
    try:
        return SOLVERS[name]
    except (KeyError, TypeError):
        raise ValueError(unknown(name)) from None


def _known(name: str) -> str:
    backend_of(name)
    return name


class _NameSchema:
    """JSON schema of a back-end name: a string with the table's names as its ``enum``."""

    def __get_pydantic_json_schema__(self, core_schema, handler) -> dict:
        return {**handler(core_schema), "enum": list(SOLVERS)}


#: a settings field holding a back-end name: checked against the table when validated
SolverName = Annotated[str, Strict(), AfterValidator(_known), _NameSchema()]


def describe() -> str:
    """The settings' description of the back-ends: ``"name" (summary)``, comma-separated."""
    return ", ".join(f'"{b.name}" ({b.summary})' if b.summary else f'"{b.name}"'
                     for b in SOLVERS.values())


#: an option of a back-end's section the message of a section that is no table shows
_EXAMPLE = {"ipopt": "tol = 1e-8", "ipopt_warm": "mu_init = 1e-6", "hpipm": "iter_max = 30",
            "fatrop": "mu_init = 0.1"}


def _reason(reason: str) -> PydanticCustomError:
    return PydanticCustomError("solver_option", "{reason}", {"reason": reason})


def _value_errors(value: Any, loc: tuple) -> list[InitErrorDetails]:
    """The errors of one option value (tables and arrays walked, without recursion)."""
    out: list[InitErrorDetails] = []
    todo = [(value, loc)]
    while todo:
        v, at = todo.pop()
        if isinstance(v, dict):
            todo += [(x, (*at, str(k))) for k, x in reversed(v.items())]
        elif isinstance(v, list | tuple):
            todo += [(x, (*at, i)) for i, x in reversed(list(enumerate(v)))]
        elif isinstance(v, float) and not math.isfinite(v):
            out.append(InitErrorDetails(type="finite_number", loc=at, input=v))
        elif isinstance(v, int) and not isinstance(v, bool):  # floats: IPOPT's 1e19/1e20
            why = magnitude_problem(v)
            why = why and f"{why} (an integer; a float, e.g. {float(v):g}, may be larger)"
            if why is not None:
                out.append(InitErrorDetails(type=_reason(why), loc=at, input=v))
        elif not isinstance(v, bool | str | float):  # a TOML date or time
            out.append(InitErrorDetails(type=_reason(
                f"a {type(v).__name__} is no solver option value (give a number, text, a "
                "boolean, an array or a table)"), loc=at, input=str(v)))
    return out


def check_options(options: dict) -> dict:
    """``mpc.solver_options`` as given, if every value in it can be a solver option.

    A back-end's section (``ipopt``, ``ipopt_warm``, ``hpipm``) must be a table of
    ``option = value``; numbers anywhere in it must be finite, integers within the
    settings' magnitude bound (:func:`~hmpc_cli.core.settings_types.magnitude_problem`;
    a float may be larger: IPOPT's infinities are 1e19 and 1e20); TOML dates and times
    are refused.

    Raises:
        ValidationError: one error per bad value, located at its key path inside the
            options (pydantic puts ``mpc.solver_options`` before it).
    """
    sections = {s for b in SOLVERS.values() for s in b.sections}
    errors: list[InitErrorDetails] = []
    for key, value in options.items():
        if key in sections and not isinstance(value, dict):
            example = _EXAMPLE.get(key, "option = value")
            errors.append(InitErrorDetails(type=_reason(
                f"must be a table of option = value, not {value!r} (e.g. {key} = "
                f"{{{example}}}, or [mpc.solver_options.{key}] with {example} below it)"),
                loc=(key,), input=value))
        else:
            errors += _value_errors(value, (key,))
    if errors:
        raise ValidationError.from_exception_data("solver_options", errors)
    return options


#: ``mpc.solver_options``: a table checked by :func:`check_options`
SolverOptions = Annotated[dict, AfterValidator(check_options)]


def split_options(backend: Backend, extra: dict | None) -> tuple[dict, dict]:
    """The user's options as (``nlpsol`` options, the back-end's own sections).

    A section of another back-end is dropped (``mpc.solver_options`` is shared by
    ``mpc.solver`` and ``mpc.switching_solver``).
    """
    taken = {s for b in SOLVERS.values() for s in b.sections}
    extra = extra or {}
    return ({k: v for k, v in extra.items() if k not in taken},
            {k: v for k, v in extra.items() if k in backend.sections})


# ------------------------------------------------------------------ built-in entries
def ipopt_options(a: SolverArgs) -> dict:
    """IPOPT: interior point; ``sections["ipopt"]`` are IPOPT options."""
    ipopt = {"print_level": 0, "sb": "yes", "max_iter": a.max_iter, "tol": a.tol,
             "constr_viol_tol": 1e-8, "mu_strategy": "adaptive"}
    if a.max_wall_time is not None:
        ipopt["max_wall_time"] = a.max_wall_time
    ipopt.update(a.sections.get("ipopt", {}))
    return {"expand": True, "ipopt": ipopt, "print_time": False, **a.nlpsol}


def warm_options(cold: dict, warm: WarmStart, extra: dict | None = None,
                 args: SolverArgs | None = None) -> dict:
    """Options of the warm IPOPT instance (``args`` unused).

    Returns:
        ``cold`` with the warm-start IPOPT options and the user's ``ipopt_warm`` section
        of ``extra`` (``mpc.solver_options``).
    """
    push = warm.bound_push
    ipopt = {**cold["ipopt"], "warm_start_init_point": "yes", "mu_init": warm.mu_init,
             "warm_start_bound_push": push, "warm_start_mult_bound_push": push,
             "warm_start_slack_bound_push": push, **(extra or {}).get("ipopt_warm", {})}
    return {**cold, "ipopt": ipopt}


def sqpmethod_options(a: SolverArgs) -> dict:
    """CasADi's SQP: exact Hessian, sparse active-set QP (qrqp)."""
    return {"expand": True, "max_iter": a.max_iter, "print_time": False,
            "print_header": False, "print_iteration": False, "print_status": False,
            "qpsol": "qrqp",
            "qpsol_options": {"print_iter": False, "print_header": False,
                              "error_on_fail": False}, **a.nlpsol}


def fatrop_options(a: SolverArgs) -> dict:
    """fatrop: structure detected from the equality rows; ``tol`` its tolerance.

    ``sections["fatrop"]``: fatrop's own options, over hmpc's.
    """
    opts: dict = {"expand": True, "structure_detection": "auto", "print_time": False}
    if a.equality is not None:
        opts["equality"] = list(a.equality)
    opts["fatrop"] = {"print_level": 0, "max_iter": a.max_iter, "tol": a.tol,
                      **a.sections.get("fatrop", {})}
    return {**opts, **a.nlpsol}


def sqp_hpipm_options(a: SolverArgs) -> dict:
    """SQP, Gauss-Newton Hessian, HPIPM (:func:`~hmpc_cli.mpc.backends.sqp_options`).

    Raises:
        ValueError: no NLP expressions or no stage structure.
    """
    if a.structure is None or not isinstance(a.nlp, dict):
        raise ValueError("the SQP back-ends (sqp_hpipm, rti) need the NLP's expressions and "
                         "its stage structure")
    return {**sqp_options(a.nlp, a.structure, a.sqp_iter, a.tol, a.residuals,
                          a.sections.get("hpipm", {})), **a.nlpsol}


register_backend(Backend(
    "ipopt", "ipopt", ipopt_options, summary="interior point, MUMPS", warm=warm_options,
    compilable=True, sections=("ipopt", "ipopt_warm"), probe=True))
register_backend(Backend(
    "sqp_hpipm", "sqpmethod", sqp_hpipm_options, summary="SQP with a Gauss-Newton Hessian "
    "and HPIPM's Riccati QP solver, IPOPT fallback on failure; needs input_hold = \"zoh\"",
    stagewise=True, judge=rti_success, fallback="ipopt", switching="ipopt",
    sections=("hpipm",)))


#: rti: SQP iterations of a solve without a warm start (a new plan's first solve, whose
#: guess is the planner's rollout: one step from it is not yet a plan to fly; 2 lose a
#: replanning trial in real time, 5 double the switching p95: results/bench/rti_levers.md)
RTI_COLD_ITER = 3
#: rti: HPIPM's residual tolerances (stationarity, equalities, inequalities,
#: complementarity): a real-time step's QP needs no 1e-8 (its default), and at these it
#: stops in about a third of the IPM iterations (docs/performance.md, "Real time")
RTI_HPIPM = {"res_g_max": 1e-4, "res_b_max": 1e-6, "res_d_max": 1e-6, "res_m_max": 1e-5}


def rti_options(a: SolverArgs) -> dict:
    """Real-time iterations, cold instance: :data:`RTI_COLD_ITER` full SQP steps.

    :func:`sqp_hpipm_options` with every step taken in full (no line search) and the QP
    solved to :data:`RTI_HPIPM` (the user's ``hpipm`` section over it).

    Raises:
        ValueError: no NLP expressions or no stage structure.
    """
    hpipm = {**RTI_HPIPM, **a.sections.get("hpipm", {})}
    return {**sqp_hpipm_options(replace(a, sqp_iter=max(a.sqp_iter, RTI_COLD_ITER),
                                        sections={**a.sections, "hpipm": hpipm})),
            "max_iter_ls": 0, **a.nlpsol}


def rti_warm_options(cold: dict, warm: WarmStart, extra: dict | None = None,
                     args: SolverArgs | None = None) -> dict:
    """Real-time iterations, warm instance: ``args.sqp_iter`` full SQP steps.

    ``args.sqp_iter`` is ``mpc.max_sqp_iter``; the steps start from the previous plan's
    primal-dual solution, shifted.
    """
    return {**cold, "max_iter": args.sqp_iter if args is not None else 1}


register_backend(Backend(
    "rti", "sqpmethod", rti_options, summary="real-time iterations: mpc.max_sqp_iter SQP "
    "steps per warm-started solve (a new plan's first solve: up to 3), Gauss-Newton "
    "Hessian, HPIPM's Riccati QP, each step taken in full and kept, the switching NLP "
    "too, no fallback; needs input_hold = \"zoh\"",
    stagewise=True, warm=rti_warm_options, judge=rti_step_kept, sections=("hpipm",)))
register_backend(Backend("fatrop", "fatrop", fatrop_options, summary='needs "zoh"',
                         stagewise=True, sections=("fatrop",)))
register_backend(Backend("sqpmethod", "sqpmethod", sqpmethod_options,
                         summary="exact Hessian, sparse active-set QP"))
