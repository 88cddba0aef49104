"""Architecture hyper-parameters of the trajectory transformer (paper §IV-A). Plain dataclass so that it can be
a section of the OmegaConf training recipe and be stored as a primitive dict in checkpoints and planner bundles."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Activation = Literal["relu", "gelu", "silu"]
ValueForm = Literal["mlp", "gauss_newton"]
Layout = Literal["interleaved", "stacked"]

# interleaved: goal, rtg, ctg, state, action tokens per step (the paper's); stacked: one token per step
TOKENS_PER_STEP: dict[str, int] = {"interleaved": 5, "stacked": 1}
# how a cached rollout decodes (``ttompc.policy.rollout.RolloutContext``): "torch" (eager ops), "fused" (one numba
# call per rollout, ``ttompc.policy.fused``; refused where it cannot run) or "auto" (fused where it can, else torch)
DECODERS = ("torch", "fused", "auto")


@dataclass
class ModelConfig:
    state_dim: int = 6
    control_dim: int = 3
    n_embd: int = 384  # paper size: 384 wide, 6 layers, 6 heads (11M parameters)
    n_layer: int = 6
    n_head: int = 6
    mlp_ratio: int = 4
    dropout: float = 0.1
    # attention-probability dropout; None = ``dropout`` (the reference). 0 lets CPU training use the fused causal
    # attention kernel: with dropout, SDPA falls back to the slower math path (measured in docs/design.md).
    attn_dropout: float | None = None
    activation: Activation = "relu"  # the reference's HF DecisionTransformerConfig default
    max_steps: int = 100  # timestep-embedding table size = longest context in steps
    # "interleaved" is the paper's five tokens per step (and what bundles without a layout hold); "stacked" embeds
    # the same five modalities as one token per step: a departure, cheaper to train (measured in docs/design.md)
    layout: Layout = "interleaved"
    bias: bool = True
    init_std: float = 0.02
    # width of the value output V(goal, s_t, t) -> rtg_t (two hidden layers); 0: none (bundles from before it).
    # TTO-MPC's rtg_mode=value feeds it instead of the paper's ledger (ttompc.mpc.tto)
    value_width: int = 0
    # the value output's form (ttompc.policy.value): "mlp" (one output) or "gauss_newton" (v = β − ½‖r‖², r of
    # value_rank outputs, 0: state_dim), whose cost-to-go has a PSD Hessian: a window's terminal cost
    value_form: ValueForm = "mlp"
    value_rank: int = 0
    value_activation: Activation | None = None  # None: ``activation``

    def __post_init__(self) -> None:
        if self.n_embd % self.n_head != 0:
            raise ValueError(f"n_embd ({self.n_embd}) must be divisible by n_head ({self.n_head})")
        if min(self.state_dim, self.control_dim, self.n_layer, self.max_steps, self.mlp_ratio) < 1:
            raise ValueError(f"model dimensions must be positive: {self}")
        if self.value_width < 0:
            raise ValueError(f"value_width must be >= 0 (0: no value output), got {self.value_width}")
        if self.value_form not in ("mlp", "gauss_newton") or self.value_rank < 0:
            raise ValueError(f"value_form must be 'mlp' or 'gauss_newton' and value_rank >= 0, got {self}")
        if self.layout not in TOKENS_PER_STEP:
            raise ValueError(f"layout must be one of {sorted(TOKENS_PER_STEP)}, got {self.layout!r}")
        for name, p in (("dropout", self.dropout), ("attn_dropout", self.attn_dropout)):
            if p is not None and not 0.0 <= p < 1.0:
                raise ValueError(f"{name} must be in [0, 1), got {p}")

    @property
    def tokens_per_step(self) -> int:
        return TOKENS_PER_STEP[self.layout]

    @property
    def max_tokens(self) -> int:
        return self.tokens_per_step * self.max_steps
