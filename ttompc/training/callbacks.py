"""``ClosedLoopEvalCallback``: closed-loop TTO-MPC of the model being trained, logged while it trains.

Teacher-forced validation loss says little about closed-loop behaviour (covariate shift, paper §IV-C), so every
``every_n_val`` validation runs the callback runs TTO-MPC with the current weights on a fixed, seeded set of held-out
problems (REL solved once and cached) under the MPC settings of a protocol (``settings``, e.g. the recipe's
``callbacks.eval_mpc.protocol``), on the nominal or the perturbed plant (``plant``, seeded per problem), and logs
``ttompc.evaluation.episodes.closed_loop_metrics`` through ``pl_module.log`` (any logger): ``<prefix>/feasible_rate``,
``<prefix>/infeasible`` (count), ``<prefix>/cost_increment`` (mean (J − J_REL)/J_REL over feasible runs) and its
``_se``, ``<prefix>/cost``, ``<prefix>/target_change``, step times and fallbacks, plus a trajectory figure (PNG
under ``<root>/plots/``, and an image on wandb or TensorBoard). Runs on global rank 0 only. Counting validation
runs rather than epochs makes it work with the step-based validation of endless streaming epochs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import lightning as L

from ttompc.evaluation.problems import EvalProblem, eval_problem
from ttompc.mpc.plant import PlantNoise
from ttompc.mpc.settings import MPCSettings, protocol_settings
from ttompc.parallel import single_torch_thread

if TYPE_CHECKING:
    from ttompc.scenarios.base import Scenario


class ClosedLoopEvalCallback(L.Callback):
    def __init__(
        self,
        scenario: str | None = None,
        *,
        problems: int = 4,
        horizon: int = 10,
        max_steps: int | None = None,
        every_n_val: int = 1,
        seed: int = 0,
        settings: MPCSettings | None = None,
        plot: bool = True,
        prefix: str = "mpc",
        plant: str = "nominal",
    ) -> None:
        if problems < 1 or horizon < 1 or every_n_val < 1:
            raise ValueError("eval_mpc: problems, horizon and every_n_val must be >= 1")
        if plant not in ("nominal", "perturbed"):
            raise ValueError(f"eval_mpc: plant must be 'nominal' or 'perturbed', got {plant!r}")
        self.perturbed = plant == "perturbed"
        self.scenario_name, self.n_problems, self.horizon = scenario, problems, horizon
        self.max_steps, self.every_n_val, self.seed = max_steps, every_n_val, seed
        self.settings = settings or MPCSettings()
        self.plot, self.prefix = plot, prefix
        self._problems: list[EvalProblem] | None = None
        self._runs = 0
        self.last_metrics: dict[str, float] = {}

    @classmethod
    def from_config(cls, cfg: Any, scenario: str | None = None) -> ClosedLoopEvalCallback:
        """From the recipe section ``callbacks.eval_mpc``."""
        return cls(
            scenario,
            problems=cfg.problems,
            horizon=cfg.horizon,
            max_steps=cfg.max_steps,
            every_n_val=cfg.every_n_val,
            seed=cfg.seed,
            settings=protocol_settings(cfg.protocol),
            plant=cfg.plant,
        )

    def plant_noise(self, scenario: Scenario) -> PlantNoise | None:
        """The plant the episodes run on: None (nominal) or the scenario's perturbed plant."""
        return PlantNoise.perturbed(scenario) if self.perturbed else None

    def problems(self, scenario_name: str) -> list[EvalProblem]:
        """The fixed evaluation problems (REL-violating, seeded), solved once."""
        if self._problems is None:
            from ttompc.scenarios import get_scenario

            sc = get_scenario(scenario_name)
            self._problems = [
                eval_problem(sc, self.seed, i, nonconvex_only=True, backend=self.settings.backend)
                for i in range(self.n_problems)
            ]
        return self._problems

    def evaluate(self, pl_module: L.LightningModule) -> tuple[dict[str, float], list[Any], list[EvalProblem]]:
        """Closed-loop metrics of the module's current weights (model mode restored afterwards)."""
        from ttompc.evaluation.episodes import closed_loop_metrics
        from ttompc.policy import Planner
        from ttompc.scenarios import get_scenario
        from ttompc.training.module import TrajectoryTransformerModule

        if not isinstance(pl_module, TrajectoryTransformerModule):
            raise TypeError(f"{type(self).__name__} evaluates a TrajectoryTransformerModule, not {type(pl_module)}")
        name = self.scenario_name or pl_module.hparams["scenario"]
        problems = self.problems(name)
        model = pl_module.model
        was_training = model.training
        try:
            with single_torch_thread():
                planner = Planner(model, get_scenario(name), pl_module.stats)
                metrics, episodes = closed_loop_metrics(
                    planner,
                    problems,
                    self.horizon,
                    settings=self.settings,
                    max_steps=self.max_steps,
                    plant=self.plant_noise(planner.scenario),
                )
        finally:
            model.train(was_training)
        return metrics, episodes, problems

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        self._runs += 1
        if self._runs % self.every_n_val or not trainer.is_global_zero:
            return
        metrics, episodes, problems = self.evaluate(pl_module)
        self.last_metrics = metrics
        for k, v in metrics.items():
            pl_module.log(f"{self.prefix}/{k}", v, rank_zero_only=True)
        if self.plot:
            from ttompc.evaluation.plots import Panel, trajectory_figure
            from ttompc.scenarios import get_scenario
            from ttompc.training.loggers import log_figure

            ep, e = problems[0], episodes[0]
            label = f"TTO-MPC H={self.horizon}"
            panel = Panel(
                ep.problem,
                {"REL (open loop)": ep.rel.X, label: e.X},
                f"step {trainer.global_step}, problem seed {ep.seed}: cost {e.cost:.4g} (REL {ep.rel.cost:.4g})",
                set() if e.feasible else {label},
            )
            fig = trajectory_figure(get_scenario(self.scenario_name or pl_module.hparams["scenario"]), [panel])
            log_figure(trainer, f"{self.prefix}/trajectory", fig, trainer.global_step)
