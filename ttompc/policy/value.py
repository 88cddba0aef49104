"""The value output V(goal, s_t, t): the predicted reward-to-go of an optimal plan from s_t at step t (a departure:
the paper feeds a ledger), a small MLP beside the trunk, and its local model for an MPC window's terminal cost.

Two forms (``ModelConfig.value_form``), both reading z = [goal, s_t, t/max_steps] (normalised goal and state):

* ``mlp``: v = MLP(z), one output (the normalised rtg). With ReLU it is piecewise linear: no curvature.
* ``gauss_newton``: v = β − ½‖r(z)‖², r = MLP(z) ∈ R^k, β = −μ/σ fixed by the rtg's normalisation (μ, σ;
  ``GaussNewtonValue.set_floor``). The cost-to-go J = −rtg is then σ·½‖r‖² ≥ 0, zero where r is (the goal at the
  end), and its Gauss–Newton Hessian σ·J_rᵀJ_r is positive semidefinite by construction: a convex quadratic local
  model of J about any state, what a window's terminal cost needs (``ValueModel.expand``). (A learned β floored J
  above the last steps' cost-to-go: 41% error 1–5 steps to go on the quadrotor.) A smooth activation
  (``value_activation: silu``) gives r a continuous Jacobian.

``ValueModel`` evaluates the head in numpy (float64) at batch 1 with its Jacobian in closed form (two hidden
layers): the per-SCP-iteration expansion of a window's terminal cost costs tens of microseconds, no torch call.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor, nn

if TYPE_CHECKING:
    from ttompc.policy.config import ModelConfig
    from ttompc.policy.stats import NormStats

ACTIVATIONS = {"relu": nn.ReLU, "gelu": nn.GELU, "silu": nn.SiLU}


def value_activation(cfg: ModelConfig) -> str:
    """The value head's activation: ``value_activation``, else the trunk's."""
    return cfg.value_activation or cfg.activation


class GaussNewtonValue(nn.Module):
    """v = β − ½‖r(z)‖² with r a two-hidden-layer MLP (``net``, k outputs) and β = −μ/σ a buffer (``set_floor``)."""

    offset: Tensor

    def __init__(self, n_in: int, width: int, rank: int, activation: str) -> None:
        super().__init__()
        act = ACTIVATIONS[activation]
        self.net = nn.Sequential(nn.Linear(n_in, width), act(), nn.Linear(width, width), act(), nn.Linear(width, rank))
        self.register_buffer("offset", torch.zeros(1))

    def set_floor(self, rtg_mean: float, rtg_std: float) -> None:
        """β = −μ/σ: the normalised rtg of a zero cost-to-go, so that J = σ·½‖r‖² (saved with the weights)."""
        self.offset.fill_(-rtg_mean / rtg_std)

    def forward(self, z: Tensor) -> Tensor:
        r = self.net(z)  # (..., k)
        return self.offset - 0.5 * (r * r).sum(dim=-1, keepdim=True)  # (..., 1)


def build_value_head(cfg: ModelConfig) -> nn.Module | None:
    """The value head of ``cfg`` (None when ``value_width`` is 0). The ``mlp`` form keeps the layout of bundles
    made before the forms existed (``value_head.{0,2,4}``), so they load unchanged."""
    if cfg.value_width <= 0:
        return None
    n_in, w = 2 * cfg.state_dim + 1, cfg.value_width
    act = value_activation(cfg)
    if cfg.value_form == "gauss_newton":
        return GaussNewtonValue(n_in, w, cfg.value_rank or cfg.state_dim, act)
    a = ACTIVATIONS[act]
    return nn.Sequential(nn.Linear(n_in, w), a(), nn.Linear(w, w), a(), nn.Linear(w, 1))


# ---------------------------------------------------------------------------------------------- numpy evaluation
def _act(name: str, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(φ(a), φ'(a)) of the activation ``name``, elementwise."""
    if name == "relu":
        return np.maximum(a, 0.0), (a > 0).astype(a.dtype)
    if name == "silu":
        s = 1.0 / (1.0 + np.exp(-a))
        return a * s, s * (1.0 + a * (1.0 - s))
    # gelu (erf form, torch's default)
    from scipy.special import erf

    cdf = 0.5 * (1.0 + erf(a / np.sqrt(2.0)))
    return a * cdf, cdf + a * np.exp(-0.5 * a * a) / np.sqrt(2.0 * np.pi)


def head_output(head: nn.Module, activation: str, z: np.ndarray) -> np.ndarray:
    """The value head's normalised output v (B,) at inputs z (B, 2n+1) in numpy: what ``head(z)`` computes on the
    CPU, in the dtype of its parameters, read in place (no copy: the current weights). No torch call: at batch 1
    that is ~20 µs where the torch call costs ~0.2 ms (``bench/model_calls.py``)."""
    net = head.net if isinstance(head, GaussNewtonValue) else head
    lin = [m for m in net.modules() if isinstance(m, nn.Linear)]
    h = z.astype(np.float64 if lin[0].weight.dtype == torch.float64 else np.float32, copy=False)
    for i, m in enumerate(lin):
        h = h @ m.weight.detach().numpy().T
        if m.bias is not None:
            h += m.bias.detach().numpy()
        if i < len(lin) - 1:
            h = _act(activation, h)[0]
    if isinstance(head, GaussNewtonValue):
        return head.offset.detach().numpy()[0] - 0.5 * (h * h).sum(axis=1)
    return h[:, 0]


@dataclass(frozen=True)
class ValueExpansion:
    """The cost-to-go J(x) = −rtg at one state, in the optimisation state's units: value, gradient (n,) and a
    positive semidefinite Hessian (n, n) (Gauss–Newton for that form; the Hessian of ``mlp`` is 0: piecewise
    linear with ReLU, its curvature not used with a smooth activation either)."""

    value: float
    gradient: np.ndarray
    hessian: np.ndarray


class ValueModel:
    """The value head in numpy, float64: J(x, t) and its local model for one problem's goal, at states in the
    optimisation representation. ``model_jacobian(t)`` maps an optimisation state at step t to the model's state
    (a linear map: the identity, or RPOD's ROE -> RTN)."""

    def __init__(self, head: nn.Module, cfg: ModelConfig, stats: NormStats) -> None:
        self.form = cfg.value_form
        self.act = value_activation(cfg)
        net = head.net if isinstance(head, GaussNewtonValue) else head
        lin = [m for m in net.modules() if isinstance(m, nn.Linear)]  # in order: the two hidden layers, the output
        self.W = [m.weight.detach().double().cpu().numpy() for m in lin]
        self.b = [m.bias.detach().double().cpu().numpy() for m in lin]
        self.offset = float(head.offset.detach()) if isinstance(head, GaussNewtonValue) else 0.0
        self.max_steps = cfg.max_steps
        self.n = cfg.state_dim
        mu_s, sd_s = stats.mean_std("states", np.zeros(self.n))
        mu_g, sd_g = stats.mean_std("goals", np.zeros(self.n))
        mu_r, sd_r = stats.mean_std("rtg", np.zeros(1))
        self.state_mu, self.state_sd = mu_s, sd_s
        self.goal_mu, self.goal_sd = mu_g, sd_g
        self.rtg_mu, self.rtg_sd = float(mu_r[0]), float(sd_r[0])

    def _forward(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The head's output (k,) at z and its Jacobian (k, len(z))."""
        h, D = z, np.eye(len(z))
        for W, b in zip(self.W[:-1], self.b[:-1], strict=True):
            a = W @ h + b
            h, d = _act(self.act, a)
            D = d[:, None] * (W @ D)
        return self.W[-1] @ h + self.b[-1], self.W[-1] @ D

    def expand(self, goal_model: np.ndarray, x_model: np.ndarray, t: int, M: np.ndarray) -> ValueExpansion:
        """J and its local model at the optimisation state x (whose model state is ``x_model`` = M x) at step t,
        for the problem whose model goal is ``goal_model``."""
        z = np.concatenate(
            [
                (goal_model - self.goal_mu) / self.goal_sd,
                (x_model - self.state_mu) / self.state_sd,
                [t / self.max_steps],
            ]
        )
        out, Jz = self._forward(z)
        n = self.n
        dz_dx = (1.0 / self.state_sd)[:, None] * M  # (n, n): d z_state / d x
        Jx = Jz[:, n : 2 * n] @ dz_dx  # (k, n)
        sd = self.rtg_sd
        if self.form == "gauss_newton":
            v = self.offset - 0.5 * float(out @ out)  # normalised rtg
            grad = sd * (Jx.T @ out)  # dJ/dx = −σ dv/dx = σ J_rᵀ r
            hess = sd * (Jx.T @ Jx)
        else:
            v = float(out[0])
            grad = -sd * Jx[0]
            hess = np.zeros((n, n))
        return ValueExpansion(value=-(v * sd + self.rtg_mu), gradient=grad, hessian=0.5 * (hess + hess.T))
