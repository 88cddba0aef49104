"""DAgger fine-tuning of a pretrained trajectory transformer for MPC (paper Alg. 1): ``collect`` (rollouts and their
labels by the expert of ``ttompc.mpc.expert``), ``loop`` (iterations, state, ranks, keep/reject), ``config`` (the
typed recipe). Importing this package does not import Lightning; ``finetune`` does when it trains."""

from ttompc.finetune.collect import collect_rollout, collect_rollouts, expert_schedule
from ttompc.finetune.config import FinetuneConfig, load_finetune_config
from ttompc.finetune.loop import FinetuneError, FinetuneResult, finetune, improves

__all__ = [
    "FinetuneConfig",
    "FinetuneError",
    "FinetuneResult",
    "collect_rollout",
    "collect_rollouts",
    "expert_schedule",
    "finetune",
    "improves",
    "load_finetune_config",
]
