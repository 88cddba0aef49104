"""Architecture hyper-parameters of the trajectory transformer (paper §IV-A). Plain dataclass so that it can be
a section of the OmegaConf training recipe and be stored as a primitive dict in checkpoints and planner bundles."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ttompc.ranges import Checked, setting

Activation = Literal["relu", "gelu", "silu"]
ValueForm = Literal["mlp", "gauss_newton"]
Layout = Literal["interleaved", "stacked"]

# interleaved: goal, rtg, ctg, state, action tokens per step (the paper's); stacked: one token per step
TOKENS_PER_STEP: dict[str, int] = {"interleaved": 5, "stacked": 1}
# how a cached rollout decodes (``ttompc.policy.rollout.RolloutContext``): "torch" (eager ops), "fused" (one numba
# call per rollout, ``ttompc.policy.fused``; refused where it cannot run) or "auto" (fused where it can, else torch)
DECODERS = ("torch", "fused", "auto")


@dataclass
class ModelConfig(Checked):
    state_dim: int = setting(6, ge=1)
    control_dim: int = setting(3, ge=1)
    n_embd: int = setting(384, ge=1)  # paper size: 384 wide, 6 layers, 6 heads (11M parameters)
    n_layer: int = setting(6, ge=1)
    n_head: int = setting(6, ge=1)
    mlp_ratio: int = setting(4, ge=1)
    dropout: float = setting(0.1, ge=0, lt=1)
    # attention-probability dropout; None = ``dropout`` (the reference). 0 lets CPU training use the fused causal
    # attention kernel: with dropout, SDPA falls back to the slower math path (measured in docs/design.md).
    attn_dropout: float | None = setting(None, ge=0, lt=1)
    activation: Activation = "relu"  # the reference's HF DecisionTransformerConfig default
    max_steps: int = setting(100, ge=1)  # timestep-embedding table size = longest context in steps
    # "interleaved" is the paper's five tokens per step (and what bundles without a layout hold); "stacked" embeds
    # the same five modalities as one token per step: a departure, cheaper to train (measured in docs/design.md)
    layout: Layout = "interleaved"
    bias: bool = True
    init_std: float = setting(0.02, gt=0)
    # width of the value output V(goal, s_t, t) -> rtg_t (two hidden layers); 0: none (bundles from before it).
    # TTO-MPC's rtg_mode=value feeds it instead of the paper's ledger (ttompc.mpc.tto)
    value_width: int = setting(0, ge=0, meaning="0: no value output")
    # the value output's form (ttompc.policy.value): "mlp" (one output) or "gauss_newton" (v = β − ½‖r‖², r of
    # value_rank outputs, 0: state_dim), whose cost-to-go has a PSD Hessian: a window's terminal cost
    value_form: ValueForm = "mlp"
    value_rank: int = setting(0, ge=0, meaning="0: state_dim")
    value_activation: Activation | None = None  # None: ``activation``

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.n_embd % self.n_head != 0:
            raise ValueError(f"n_embd ({self.n_embd}) must be divisible by n_head ({self.n_head})")
        if self.value_form not in ("mlp", "gauss_newton"):
            raise ValueError(f"value_form must be 'mlp' or 'gauss_newton', got {self.value_form!r}")
        if self.layout not in TOKENS_PER_STEP:
            raise ValueError(f"layout must be one of {sorted(TOKENS_PER_STEP)}, got {self.layout!r}")

    @property
    def tokens_per_step(self) -> int:
        return TOKENS_PER_STEP[self.layout]

    @property
    def max_tokens(self) -> int:
        return self.tokens_per_step * self.max_steps
