"""``ClosedLoopEvalCallback``: closed-loop TTO-MPC of the model being trained, logged while it trains.

Teacher-forced validation loss says little about closed-loop behaviour (covariate shift, paper §IV-C), so every
``every_n_val`` validation runs the callback runs TTO-MPC with the current weights as a ``Measurement`` says (the
recipe's ``callbacks.eval_mpc``): on its fixed, seeded held-out problems (REL solved once and cached), under its
protocol's MPC settings, at its one horizon on its one plant (nominal, or perturbed: seeded per problem), and logs
``ttompc.evaluation.episodes.closed_loop_metrics`` through ``pl_module.log`` (any logger): ``mpc/feasible_rate``,
``mpc/infeasible`` (count), ``mpc/cost_increment`` (mean (J − J_REL)/J_REL over feasible runs) and its
``_se``, ``mpc/cost``, ``mpc/target_change``, step times and fallbacks, plus a trajectory figure (PNG
under ``<root>/plots/``, and an image on wandb or TensorBoard). Runs on global rank 0 only. Counting validation
runs rather than epochs makes it work with the step-based validation of endless streaming epochs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import lightning as L

from ttompc.parallel import single_torch_thread

if TYPE_CHECKING:
    from ttompc.evaluation.measurement import Measurement
    from ttompc.evaluation.problems import EvalProblem
    from ttompc.training.config import EvalMPCConfig


class ClosedLoopEvalCallback(L.Callback):
    """Measures ``measurement`` (one horizon, one plant) every ``every_n_val`` validation runs on ``scenario`` (None:
    the module's) and logs its metrics and a trajectory figure under ``PREFIX`` (module doc)."""

    PREFIX = "mpc"

    def __init__(self, measurement: Measurement, scenario: str | None = None, *, every_n_val: int = 1) -> None:
        measurement.check_single("eval_mpc")
        if every_n_val < 1:
            raise ValueError(f"eval_mpc: every_n_val must be >= 1, got {every_n_val}")
        self.measurement, self.scenario_name, self.every_n_val = measurement, scenario, every_n_val
        self._problems: list[EvalProblem] | None = None
        self._runs = 0
        self.last_metrics: dict[str, float] = {}

    @classmethod
    def from_config(cls, cfg: EvalMPCConfig, scenario: str | None = None) -> ClosedLoopEvalCallback:
        """From the recipe section ``callbacks.eval_mpc``."""
        return cls(cfg, scenario, every_n_val=cfg.every_n_val)

    def problems(self, scenario_name: str) -> list[EvalProblem]:
        """The fixed evaluation problems (``Measurement.problem_set``), solved once."""
        if self._problems is None:
            from ttompc.scenarios import get_scenario

            self._problems = self.measurement.problem_set(get_scenario(scenario_name))
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
                metrics, episodes = closed_loop_metrics(planner, self.measurement, problems)
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
            pl_module.log(f"{self.PREFIX}/{k}", v, rank_zero_only=True)
        from ttompc.evaluation.plots import Panel, trajectory_figure
        from ttompc.scenarios import get_scenario
        from ttompc.training.loggers import log_figure

        ep, e = problems[0], episodes[0]
        label = f"{e.method} H={e.horizon}"  # the method as ttompc.mpc.methods names it
        panel = Panel(
            ep.problem,
            {"REL (open loop)": ep.rel.X, label: e.X},
            f"step {trainer.global_step}, problem seed {ep.seed}: cost {e.cost:.4g} (REL {ep.rel.cost:.4g})",
            set() if e.feasible else {label},
        )
        fig = trajectory_figure(get_scenario(self.scenario_name or pl_module.hparams["scenario"]), [panel])
        log_figure(trainer, f"{self.PREFIX}/trajectory", fig, trainer.global_step)
