"""``Measurement``: one closed-loop measurement — which held-out problems, which planning horizons and plants, under
which MPC settings — in the one shape that ``ttompc evaluate mpc`` (``ClosedLoopConfig``), the training callback
(``callbacks.eval_mpc``), DAgger's keep/reject decision and rollouts (``dagger.eval``) and the demo take.

The MPC settings are named as a protocol (``protocol``: a preset of ``ttompc.mpc.settings`` or a YAML file) with
single-key overrides (``mpc``, e.g. ``mpc.end_horizon=20``) and resolved once, when the measurement is built
(``settings``; build a new one, e.g. with ``dataclasses.replace``, to change either). ``problem_set`` is the one
place its held-out problems are made; ``runs`` says how each (plant, horizon) runs (``ttompc.mpc.loop.MPCRun``).
``with_settings`` is what ``--print-config`` shows: a config with each measurement's resolved settings beside its
protocol, so that ``protocol=zoo`` does not hide its end horizon.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from typing import TYPE_CHECKING, Any

from ttompc.mpc.loop import MPCRun
from ttompc.mpc.plant import PlantNoise
from ttompc.mpc.settings import MPCSettings, protocol_settings
from ttompc.ranges import Checked, setting

if TYPE_CHECKING:
    from ttompc.evaluation.problems import EvalProblem
    from ttompc.scenarios.base import Scenario

PLANTS = ("nominal", "perturbed")


@dataclass
class Measurement(Checked):
    """A closed-loop measurement (module doc); ``__post_init__`` checks it and resolves its settings."""

    protocol: str = "paper"  # MPC settings: a preset (paper, zoo, recommended; ttompc/mpc/presets) or a YAML file
    mpc: dict[str, Any] = field(default_factory=dict)  # single MPCSettings keys over the protocol's, e.g. mpc.mode=hard
    problems: int = setting(20, ge=1)  # held-out problems whose REL solution violates a keep-out zone
    # root seed of the evaluation stream (disjoint from data generation and DAgger rollouts)
    seed: int = setting(0, ge=0)
    horizons: list[int] = setting(factory=lambda: [10], ge=1, nonempty=True, unique=True)  # planning horizons H
    # nominal: the exact dynamics; perturbed: below
    plants: list[str] = setting(factory=lambda: ["nominal"], nonempty=True, unique=True)
    # the perturbed plant's disturbances; None: the scenario's own (Scenario.perturbation)
    plant: PlantNoise = field(default_factory=lambda: PlantNoise(None, None, None))
    max_steps: int | None = setting(None, ge=1)  # MPC steps per episode (None: whole episodes; fewer: smoke runs)
    # the target blend of the one model method that the callback and DAgger run (rollouts and keep/reject): 0 runs
    # TTO-MPC (the paper's target), > 0 R-TTO-MPC (the robust target that the zoo's headlines report); ``ttompc
    # evaluate mpc`` runs both, the robust ones with this blend
    robust_blend: float = setting(0.0, ge=0, lt=1)

    def __post_init__(self) -> None:
        super().__post_init__()
        bad = [p for p in self.plants if p not in PLANTS]
        if bad:
            raise ValueError(f"invalid plants={self.plants}: each must be one of {list(PLANTS)}")
        self._settings = protocol_settings(self.protocol, self.mpc)  # raises ConfigError naming what does not fit

    @property
    def settings(self) -> MPCSettings:
        """The resolved MPC settings: the protocol's with the ``mpc`` overrides (resolved when built)."""
        return self._settings

    def check_single(self, section: str) -> None:
        """Consumers that log one set of metrics (the training callback, DAgger's keep/reject decision) measure one
        horizon on one plant; raises ``ValueError`` naming ``section`` otherwise."""
        if len(self.horizons) != 1 or len(self.plants) != 1:
            raise ValueError(
                f"{section} measures one horizon on one plant, got horizons={self.horizons} plants={self.plants}"
            )

    def problem_set(
        self, scenario: Scenario, indices: Sequence[int] | None = None, *, progress: str = ""
    ) -> list[EvalProblem]:
        """Problems ``indices`` (default: all ``problems``) of the evaluation stream of ``seed``: the first draws that
        are valid and whose REL solution, solved with the settings' backend, violates a keep-out zone
        (``ttompc.evaluation.problems.eval_problem``). ``progress``: the label of a progress bar ("": none)."""
        from ttompc.evaluation.problems import eval_problem
        from ttompc.progress import Bar

        chosen = range(self.problems) if indices is None else indices
        out = []
        with Bar(len(chosen), progress, "problem", show=bool(progress)) as bar:
            for i in chosen:
                out.append(eval_problem(scenario, self.seed, i, nonconvex_only=True, backend=self.settings.backend))
                bar.update()
        return out

    def runs(self, scenario: Scenario) -> list[tuple[str, MPCRun]]:
        """(plant, how its episodes run) for every plant, then every horizon, in the given order: the resolved
        settings, ``max_steps``, and on the perturbed plant ``plant`` with the scenario's own disturbance where it
        leaves a component unset (None on the nominal plant)."""
        out = []
        for name in self.plants:
            noise = self.plant.resolve(scenario) if name == "perturbed" else None
            out += [(name, MPCRun(H, self.settings, self.max_steps, noise)) for H in self.horizons]
        return out


def with_settings(cfg: Any) -> dict[str, Any]:
    """``to_container(cfg)`` of a config dataclass with the resolved ``settings`` of every ``Measurement`` in it
    placed after its ``mpc`` overrides: what ``--print-config`` shows (not a recipe: ``settings`` is no key)."""
    from ttompc.config import to_container

    out = to_container(cfg)

    def add(obj: Any, node: dict[str, Any]) -> None:
        if isinstance(obj, Measurement):
            items = list(node.items())
            at = list(node).index("mpc") + 1
            node.clear()
            node.update([*items[:at], ("settings", asdict(obj.settings)), *items[at:]])
        for f in fields(obj):
            value = getattr(obj, f.name)
            if is_dataclass(value) and isinstance(node.get(f.name), dict):
                add(value, node[f.name])

    add(cfg, out)
    return out
