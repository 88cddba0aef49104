"""DAgger fine-tuning of a pretrained trajectory transformer for MPC (paper Alg. 1). Importing this package does not
import Lightning; ``finetune`` does when it trains."""

from ttompc.finetune.config import FinetuneConfig, load_finetune_config
from ttompc.finetune.dagger import FinetuneResult, collect_rollout, expert_schedule, finetune, rollout_seed

__all__ = [
    "FinetuneConfig",
    "FinetuneResult",
    "collect_rollout",
    "expert_schedule",
    "finetune",
    "load_finetune_config",
    "rollout_seed",
]
