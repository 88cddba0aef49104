"""Which solvers a ``backend=`` name runs (``backend_chain``), the trust-region norm it implies
(``default_trust_norm``), and the cache of built solver structures (``get_solver``)."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

from ttompc.errors import ConfigError
from ttompc.scenarios.base import Scenario
from ttompc.solvers.backends.base import SubproblemSolver, is_qp
from ttompc.solvers.backends.conic import BACKENDS, AssembledSolver
from ttompc.solvers.backends.qp import PIQPSolver
from ttompc.solvers.backends.riccati import RiccatiSolver
from ttompc.solvers.backends.riccati import supports as riccati_supports
from ttompc.solvers.spec import SubproblemSpec

# every name ``backend=`` takes: the chains (``backend_chain``), the solvers, and the naive cvxpy baseline
BACKEND_NAMES = ("auto", "conic", "riccati", "piqp", *BACKENDS, "cvxpy-naive")


def backend_chain(name: str, scenario: Scenario | None = None) -> list[str]:
    """The solvers ``name`` runs on ``scenario``'s subproblems, in fallback order (each subproblem goes to the first
    that takes its structure; a numerical failure to the next):

    * ``auto`` (the default): the Riccati interior-point kernel (``riccati.py``) ahead of the scenario's
      ``auto_backends`` where those start with PIQP, else ``auto_backends`` alone. On the default chain
      ``riccati, piqp, qoco, clarabel`` the kernel takes the penalised QP subproblems and the MPC windows whose one
      cone is their soft terminal term (``riccati.supports``), PIQP the other QPs, QOCO the other cone programs, and
      each passes its numerical failures on. RPOD's: Clarabel alone.
    * ``riccati``: the same as ``auto`` (the name that selected the kernel before it was the default).
    * ``piqp``: PIQP first, then the rest of ``auto_backends``, without the kernel: what ``auto`` ran before issue
      36 made the kernel the default (records from before then that say ``auto`` mean this), kept for comparisons.
    * ``conic``: QOCO then Clarabel on every subproblem (the default before the QP path, kept for comparisons).
    * ``qoco``, ``clarabel``, ``cvxpy-naive``: that solver alone.

    Every solver is a dependency, so a chain does not depend on what is installed; any other name is a
    ``ConfigError`` (``check_backend``)."""
    default = list(scenario.auto_backends) if scenario is not None else ["piqp", "qoco", "clarabel"]
    if name in ("auto", "riccati"):
        return ["riccati", *default] if default[0] == "piqp" else default
    if name == "piqp":
        return ["piqp", *(b for b in default if b not in ("piqp", "riccati"))]
    if name == "conic":
        return ["qoco", "clarabel"]
    return [check_backend(name)]


def check_backend(name: str) -> str:
    """``name`` when it is one of ``BACKEND_NAMES``, else a ``ConfigError`` (a ``ValueError``) in the words ``ttompc``
    prints for it."""
    if name not in BACKEND_NAMES:
        raise ConfigError(f"unknown solver backend {name!r}", f"choose one of: {', '.join(BACKEND_NAMES)}")
    return name


def default_trust_norm(backend: str, scenario: Scenario | None = None) -> str:
    """The scenario's ``trust_norm`` (∞-norm without a scenario); ``conic``, the previous default path kept for
    comparisons, keeps its 2-norm."""
    if backend == "conic":
        return "l2"
    return scenario.trust_norm if scenario is not None else "linf"


def solver_path(backend: str, scenario: Scenario) -> dict[str, Any]:
    """What ``backend`` resolves to for ``scenario`` (recorded by reports and datasets): the name, the chain of
    solvers and the trust-region norm."""
    return {
        "backend": backend,
        "chain": backend_chain(backend, scenario),
        "trust_norm": default_trust_norm(backend, scenario),
    }


_CACHE: OrderedDict[tuple[SubproblemSpec, tuple[str, ...]], SubproblemSolver] = OrderedDict()
_CACHE_SIZE = 256  # receding-horizon REL uses one structure per remaining length (up to N = 100)


def clear_solver_cache() -> None:
    """Forget every built solver structure (benchmarks that time building them)."""
    _CACHE.clear()


def get_solver(spec: SubproblemSpec, backend: str, scenario: Scenario | None = None) -> SubproblemSolver:
    """One solver per (structure, backends), least-recently-used cache (a receding-horizon REL needs one per
    remaining length, its windows a handful more)."""
    chain = tuple(backend_chain(backend, scenario))
    key = (spec, chain)
    solver = _CACHE.get(key)
    if solver is None:
        if chain[0] == "riccati" and riccati_supports(spec):
            rest = chain[1:]
            solver = RiccatiSolver(spec, lambda: _build(spec, rest))
        else:
            solver = _build(spec, tuple(b for b in chain if b != "riccati"))
        _CACHE[key] = solver
        if len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    else:
        _CACHE.move_to_end(key)
    return solver


def _build(spec: SubproblemSpec, chain: tuple[str, ...]) -> SubproblemSolver:
    conic = tuple(b for b in chain if b != "piqp") or ("clarabel",)
    if chain == ("cvxpy-naive",):
        from ttompc.solvers.naive import NaiveCvxpySolver

        return NaiveCvxpySolver(spec)
    if chain[0] == "piqp" and (is_qp(spec) or len(chain) == 1):  # a lone "piqp" rejects cones itself
        fallback = (lambda: AssembledSolver(spec, conic)) if len(chain) > 1 else None
        return PIQPSolver(spec, fallback)
    return AssembledSolver(spec, conic)
