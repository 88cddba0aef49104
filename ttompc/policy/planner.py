"""``Planner``: a trained trajectory transformer bound to its scenario and normalisation statistics, i.e. everything
needed to turn problems into warm-start trajectories (paper §IV-B) or MPC guidance.

Bundle format (``Planner.save(dir)`` / ``Planner.from_pretrained(dir)``; the zoo publishes and caches these
directories)::

    <dir>/model.safetensors   TrajectoryGPT state dict (safetensors; nothing is ever unpickled)
    <dir>/config.json         {
                                "format": "ttompc-planner", "format_version": 1,
                                "model": {ModelConfig fields},
                                "scenario": {"name": str, "version": str, "spec": str},  # spec: how to load it
                                "norm_stats": NormStats.to_dict(),      # mean/std lists for the 5 modalities
                                "recipe": {training recipe as a plain dict, may be empty},
                                "code_version": str,                    # ttompc version + git commit of the trainer
                                "created": ISO-8601 UTC time,
                                "extra": {free-form metadata: training steps, solver path, dataset ...},
                                "sha256": {"model.safetensors": hex digest}  # written by save, checked by loads
                              }

Every load re-hashes the files ``"sha256"`` lists and refuses a mismatch with a ``BundleError`` naming the file
(``ttompc.zoo.check_bundle``), so damaged weights fail instead of planning NaNs. Bundles saved before the key
existed still load; zoo copies are also checked against their card's sha256 when fetched.

``Planner.from_pretrained`` is the one loader: a zoo model name (downloaded and verified into the cache), a Hugging
Face Hub model ``hf://ORG/NAME[@REVISION]`` (verified in the Hugging Face cache), a bundle directory, or a Lightning
``.ckpt`` written by ``TrajectoryTransformerModule`` (read without importing Lightning: its hyper-parameters are
primitives, so ``weights_only=True`` loading works). Weights are never unpickled.
"""

from __future__ import annotations

import datetime as _dt
import json
import pickle
import warnings
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ttompc.config import from_container
from ttompc.policy.config import ModelConfig
from ttompc.policy.gpt import TrajectoryGPT
from ttompc.policy.rollout import RolloutContext, RolloutResult
from ttompc.policy.stats import NormStats
from ttompc.policy.value import ValueModel, head_output, value_activation
from ttompc.scenarios import Problem, Scenario, find_scenario, scenario_spec
from ttompc.version import code_version

FORMAT = "ttompc-planner"
FORMAT_VERSION = 1
WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"


def _per_problem(value: float | Sequence[float] | np.ndarray, batch: int) -> torch.Tensor:
    """A scalar or per-problem value as a (B,) float64 tensor."""
    return torch.as_tensor(np.broadcast_to(np.asarray(value, dtype=np.float64), (batch,)).copy())


class Planner:
    """Model + scenario + normalisation statistics (+ provenance metadata)."""

    def __init__(
        self,
        model: TrajectoryGPT,
        scenario: Scenario,
        stats: NormStats,
        *,
        recipe: dict[str, Any] | None = None,
        trained_code_version: str | None = None,
        extra: dict[str, Any] | None = None,
    ) -> None:
        cfg = model.cfg
        if (cfg.state_dim, cfg.control_dim) != (scenario.state_dim, scenario.control_dim):
            raise ValueError(
                f"model dims ({cfg.state_dim}, {cfg.control_dim}) do not match scenario {scenario.name!r} "
                f"({scenario.state_dim}, {scenario.control_dim})"
            )
        self.model = model  # its train/eval mode is left alone: rollouts switch dropout off themselves
        self.scenario = scenario
        self.stats = stats
        self.recipe = dict(recipe or {})
        self.trained_code_version = trained_code_version or code_version()
        self.extra = dict(extra or {})
        self._value_model: ValueModel | None = None

    @property
    def rtg_scale(self) -> float:
        """κ of the conditioning rtg_0 = −κ·J_REL that this model plans best with, as recorded in its bundle
        (``extra["rtg_scale"]``, set when publishing from the protocol's measurements); the paper's 1 otherwise.
        Callers that leave ``rtg_scale`` unset (evaluation, TTO-MPC) use it."""
        return float(self.extra.get("rtg_scale", 1.0))

    @property
    def has_value(self) -> bool:
        """Whether the model has a value output (``ModelConfig.value_width`` > 0)."""
        return self.model.value_head is not None

    def value_model(self) -> ValueModel:
        """The value output in numpy (``ttompc.policy.value.ValueModel``: J and its local model per state), built
        once per planner from the current weights; raises ``ValueError`` for a model without a value output."""
        if self.model.value_head is None:
            raise ValueError("this model has no value output (model.value_width = 0)")
        if self._value_model is None:
            self._value_model = ValueModel(self.model.value_head, self.model.cfg, self.stats)
        return self._value_model

    @torch.no_grad()
    def cost_to_go(self, problems: Sequence[Problem], X: np.ndarray, t: int) -> np.ndarray:
        """The value output's cost-to-go V(x_t, t) = −rtg_t (B,) of B problems from their states ``X`` (B, n) at step
        ``t``, in the optimisation representation; raises ``ValueError`` for a model without a value output. On the
        CPU the head runs in numpy (``ttompc.policy.value.head_output``, the model's dtype), elsewhere in torch."""
        sc = self.scenario
        S = np.stack([sc.to_model_states(p, np.asarray(x)[None], start=t)[0] for p, x in zip(problems, X, strict=True)])
        goal = np.stack([sc.model_goal(p) for p in problems])
        head = self.model.value_head
        if head is None:
            raise ValueError("this model has no value output (model.value_width = 0)")
        param = next(head.parameters())
        if param.device.type == "cpu":
            cfg, stats = self.model.cfg, self.stats
            ftype = np.float64 if param.dtype == torch.float64 else np.float32
            steps = np.full((len(problems), 1), t, dtype=ftype) / ftype(cfg.max_steps)  # as ``TrajectoryGPT.value``
            z = np.concatenate(
                [stats.normalize("goals", goal.astype(ftype)), stats.normalize("states", S.astype(ftype)), steps],
                axis=1,
            )
            out = head_output(head, value_activation(cfg), z).astype(np.float64)
            return -stats.denormalize("rtg", out[:, None])[:, 0]
        dtype = next(self.model.parameters()).dtype
        as_t = lambda a: torch.as_tensor(a[:, None], dtype=dtype, device=self.device)  # noqa: E731  (B, 1, n)
        steps = torch.full((len(problems), 1), t, dtype=torch.long, device=self.device)
        v = self.model.value(self.stats.normalize("goals", as_t(goal)), self.stats.normalize("states", as_t(S)), steps)
        return -self.stats.denormalize("rtg", v.double())[:, 0, 0].cpu().numpy()

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    # ------------------------------------------------------------------------------------------------- planning
    def _start_tensors(self, problems: Sequence[Problem]) -> tuple[torch.Tensor, torch.Tensor]:
        sc = self.scenario
        s0 = np.stack([sc.to_model_states(p, p.x0[None], start=0)[0] for p in problems])
        goal = np.stack([sc.model_goal(p) for p in problems])
        dtype = next(self.model.parameters()).dtype
        return (
            torch.as_tensor(s0, dtype=dtype, device=self.device),
            torch.as_tensor(goal, dtype=dtype, device=self.device),
        )

    def context(
        self,
        problems: Sequence[Problem],
        rtg0: float | Sequence[float] | np.ndarray,
        ctg0: float | Sequence[float] | np.ndarray = 0.0,
        *,
        use_cache: bool = True,
        decoder: str = "torch",
    ) -> RolloutContext:
        """A step-0 rollout context for B problems, conditioned like the reference on rtg0 = −J_REL, ctg0 = 0
        (``decoder``: how it decodes, ``RolloutContext``).

        MPC keeps it for the whole episode: at step t, ``ctx.rollout(H)`` plans [t, t+H) from the cached history;
        after executing a_t, ``ctx.advance(a_t, s_{t+1})`` with the measured state in the *model* representation
        (``scenario.to_model_states(problem, X, start=t+1)``); plans come back in the model representation too
        (``scenario.from_model_states(problem, S, start=t)``)."""
        if not problems:
            raise ValueError("no problems given")
        s0, goal = self._start_tensors(problems)
        return RolloutContext.start(
            self.model,
            self.stats,
            self.scenario.batched_model(problems, device=self.device),
            self.scenario.cost_norm,
            s0,
            goal,
            _per_problem(rtg0, len(problems)),
            _per_problem(ctg0, len(problems)),
            use_cache=use_cache,
            decoder=decoder,
        )

    def generate(
        self,
        problems: Sequence[Problem],
        rtg0: float | Sequence[float] | np.ndarray,
        ctg0: float | Sequence[float] | np.ndarray = 0.0,
        *,
        horizon: int | None = None,
        use_cache: bool = True,
    ) -> RolloutResult:
        """Open-loop rollout from step 0 in the model representation (default horizon: the problems' N)."""
        horizon = horizon or problems[0].n_steps
        return self.context(problems, rtg0, ctg0, use_cache=use_cache).rollout(horizon)

    def warm_start(
        self,
        problems: Sequence[Problem],
        rtg0: float | Sequence[float] | np.ndarray,
        ctg0: float | Sequence[float] | np.ndarray = 0.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Full-horizon warm starts for the SCP engine: states (B, N+1, n) in the *optimisation* representation and
        controls (B, N, m), float64.

        Each problem is validated like the solvers do (``Scenario.validate``): a start or goal inside a keep-out zone
        raises the scenario's ``InfeasibleProblemError`` instead of yielding a plan no solver will accept."""
        for i, problem in enumerate(problems):
            try:
                self.scenario.validate(problem)
            except ValueError as err:  # InfeasibleProblemError included: same type and message as the solvers'
                if len(problems) == 1:
                    raise
                raise type(err)(f"problem {i} of a batch of {len(problems)}: {err}") from err
        steps = {p.n_steps for p in problems}
        if len(steps) != 1:
            raise ValueError(f"problems in one batch must share n_steps, got {sorted(steps)}")
        res = self.generate(problems, rtg0, ctg0)
        S = res.states.double().cpu().numpy()
        X = np.stack([self.scenario.from_model_states(p, S[i], start=0) for i, p in enumerate(problems)])
        X[:, 0] = [p.x0 for p in problems]  # exact, not the model dtype's rounding: the SCP fixes this state
        return X, res.actions.double().cpu().numpy()

    # ----------------------------------------------------------------------------------------------- persistence
    def metadata(self) -> dict[str, Any]:
        """The content of ``config.json`` but the weights' checksum, which ``save`` adds once they are written."""
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "model": asdict(self.model.cfg),
            "scenario": {
                "name": self.scenario.name,
                "version": self.scenario.version,
                "spec": scenario_spec(self.scenario),
            },
            "norm_stats": self.stats.to_dict(),
            "recipe": self.recipe,
            "code_version": self.trained_code_version,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "extra": self.extra,
        }

    def save(self, directory: str | Path) -> Path:
        """Write ``model.safetensors``, then ``config.json`` with the sha256 of the weights as written, into
        ``directory`` (created if needed)."""
        from safetensors.torch import save_file

        from ttompc.zoo.cache import CHECKSUMS, sha256_file

        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().cpu().contiguous() for k, v in self.model.state_dict().items()}
        save_file(state, str(out / WEIGHTS_FILE), metadata={"format": "pt"})
        meta = {**self.metadata(), CHECKSUMS: {WEIGHTS_FILE: sha256_file(out / WEIGHTS_FILE)}}
        (out / CONFIG_FILE).write_text(json.dumps(meta, indent=2) + "\n")
        return out

    @classmethod
    def from_pretrained(
        cls,
        source: str | Path,
        scenario: Scenario | None = None,
        *,
        device: str | torch.device = "cpu",
        check_version: bool = True,
        cache_dir: str | Path | None = None,
        zoo_dir: str | Path | None = None,
        progress: bool = True,
    ) -> Planner:
        """A planner from a Hugging Face Hub model (``hf://ORG/NAME[@REVISION]``: through the Hugging Face cache,
        every file checked against the repository card's sha256 first), a Lightning checkpoint (``*.ckpt``), a
        bundle directory or a zoo model name (downloaded into the verified cache if needed), in that order of
        precedence: a local path wins over a zoo name.

        The scenario defaults to the one the model was trained on (by name, else loaded from the recorded spec:
        ``ttompc.scenarios.find_scenario``); a scenario version different from the training one is an error unless
        ``check_version=False``. A ``device`` this machine lacks is a ``ConfigError``, in the CLI's words."""
        from ttompc.ranges import check_device
        from ttompc.zoo import BundleError, check_bundle, download, download_model, is_hub_ref
        from ttompc.zoo.cards import CardError, validate_name

        forms = (
            "pass a zoo model name (see `ttompc zoo list`), hf://ORG/NAME[@REVISION], a bundle folder or a "
            "Lightning .ckpt file"
        )
        if not isinstance(source, (str, Path)) or not str(source):
            raise BundleError(f"no model named by {source!r}", forms)
        check_device(device)  # before a file is read: safetensors would call a device it lacks a damaged file
        if is_hub_ref(source):
            path, meta = download_model(str(source), progress=progress)  # verified and checked like a bundle
            return cls._from_bundle(path, meta, scenario, device=device, check_version=check_version)
        path = Path(source)
        if path.is_file():
            if path.suffix != ".ckpt":
                raise BundleError(f"{path} is a file but not a Lightning checkpoint (*.ckpt)", forms)
            return cls._from_checkpoint(path, scenario, device=device, check_version=check_version)
        if not path.is_dir():
            try:
                validate_name(str(source))
            except CardError:
                raise BundleError(f"{str(source)!r}: no such bundle folder or .ckpt file", forms) from None
            path = download(str(source), cache_dir, zoo_dir=zoo_dir, progress=progress)
        meta = check_bundle(path)  # checksums, safetensors header and JSON, before torch reads any weight
        return cls._from_bundle(path, meta, scenario, device=device, check_version=check_version)

    @classmethod
    def _from_bundle(
        cls,
        src: Path,
        meta: dict[str, Any],
        scenario: Scenario | None,
        *,
        device: str | torch.device,
        check_version: bool,
    ) -> Planner:
        from safetensors.torch import load_file

        from ttompc.zoo import BundleError

        if meta.get("format") != FORMAT or meta.get("format_version") != FORMAT_VERSION:
            raise BundleError(f"{src}: not a {FORMAT} v{FORMAT_VERSION} bundle")
        state = load_file(str(src / WEIGHTS_FILE), device=str(device))
        return cls._build(
            meta["model"],
            meta["scenario"],
            meta["norm_stats"],
            state,
            scenario=scenario,
            device=device,
            check_version=check_version,
            recipe=meta.get("recipe"),
            trained_code_version=meta.get("code_version"),
            extra=meta.get("extra"),
        )

    @classmethod
    def _from_checkpoint(
        cls, path: Path, scenario: Scenario | None, *, device: str | torch.device, check_version: bool
    ) -> Planner:
        from ttompc.zoo import BundleError

        expected = "expected a Lightning .ckpt written by `ttompc train`, a bundle folder or a zoo model name"
        try:  # weights_only: tensors and primitives only, never arbitrary objects
            with warnings.catch_warnings():  # torch warns about the pickle protocol of foreign files
                warnings.simplefilter("ignore")
                ckpt = torch.load(path, map_location=device, weights_only=True)
        except PermissionError as err:
            raise BundleError(f"cannot read {path}: {err.strerror or err}") from None
        except (OSError, EOFError, RuntimeError, pickle.UnpicklingError, ValueError, TypeError, AttributeError):
            # a truncated archive can surface as OSError "Invalid argument"; torch's own text suggests
            # weights_only=False, never right for a file from elsewhere, so it is not shown
            raise BundleError(
                f"{path} is not a ttompc checkpoint (truncated, another format, or objects other than tensors and "
                f"plain values, which are never loaded); {expected}"
            ) from None
        hp = ckpt.get("hyper_parameters") if isinstance(ckpt, dict) else None
        if not isinstance(hp, dict) or not isinstance(ckpt.get("state_dict"), dict):
            raise BundleError(f"{path} is not a ttompc checkpoint (no hyper-parameters and weights); {expected}")
        missing = [k for k in ("model_config", "scenario", "scenario_version", "norm_stats") if k not in hp]
        if missing:
            raise BundleError(
                f"{path} is a checkpoint but not one written by `ttompc train` (its hyper-parameters lack "
                f"{', '.join(missing)}); {expected}"
            )
        state = {k.removeprefix("model."): v for k, v in ckpt["state_dict"].items() if k.startswith("model.")}
        extra: dict[str, Any] = {"global_step": int(ckpt.get("global_step", 0)), "epoch": int(ckpt.get("epoch", 0))}
        if "solver" in hp:  # the solver path the run recorded (checkpoints from before it have none)
            extra["solver"] = hp["solver"]
        if "precision" in ckpt:  # the training precision that ran (ttompc.training.precision)
            extra["precision"] = ckpt["precision"]
        return cls._build(
            hp["model_config"],
            {"name": hp["scenario"], "version": hp["scenario_version"], "spec": hp.get("scenario_spec")},
            hp["norm_stats"],
            state,
            scenario=scenario,
            device=device,
            check_version=check_version,
            recipe=hp.get("recipe"),
            trained_code_version=hp.get("code_version"),
            extra=extra,
        )

    @classmethod
    def _build(
        cls,
        model_cfg: dict[str, Any],
        trained_on: dict[str, Any],
        stats: dict[str, Any],
        state: dict[str, torch.Tensor],
        *,
        scenario: Scenario | None,
        device: str | torch.device,
        check_version: bool,
        **meta: Any,
    ) -> Planner:
        from ttompc.zoo import BundleError

        scenario_name, scenario_version = trained_on["name"], trained_on["version"]
        scenario = scenario or find_scenario(scenario_name, trained_on.get("spec"))
        if scenario.name != scenario_name:
            raise BundleError(f"model was trained on scenario {scenario_name!r}, not {scenario.name!r}")
        if check_version and scenario.version != scenario_version:
            raise BundleError(
                f"model was trained on {scenario_name} v{scenario_version} but the installed scenario is "
                f"v{scenario.version}",
                "use a model trained on the installed scenario, or pass check_version=False to use it anyway",
            )
        model = TrajectoryGPT(from_container(ModelConfig, model_cfg))
        model.load_state_dict(state)
        return cls(model.to(device).eval(), scenario, NormStats.from_dict(stats), **meta)
