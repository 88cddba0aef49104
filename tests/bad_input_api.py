"""The Python entries behind the CLI cases of ``tests/bad_input_cases.py``: ``API_CALLS[case](world)`` calls the
library function a command runs (``train``, ``finetune``, ``generate``, ``run_closed_loop``, ``run_warmstart``,
``run_target_error``, ``run_fit_loss``, ``publish``, ``Planner.from_pretrained``, ``solve_problem``) with the inputs
of that case, ``world`` being the fixture's folders (``bad_input_cases.make_world``)."""

from __future__ import annotations

from collections.abc import Callable

from bad_input_cases import BUNDLE, FINETUNE, MILLION, QUAD_TINY, TINY


def _train(recipe: str, *overrides: str) -> object:
    from ttompc.training.config import load_train_config
    from ttompc.training.run import train

    return train(load_train_config(recipe, list(overrides)))


def _finetune(*overrides: str) -> object:
    from ttompc.finetune import finetune
    from ttompc.finetune.config import load_finetune_config

    return finetune(load_finetune_config(FINETUNE, list(overrides)), "m")


def _generate(**settings: object) -> object:
    from ttompc.data.config import GenerateConfig, SplitConfig
    from ttompc.data.generate import generate

    one_split = SplitConfig(train=1, val=0, test=0)
    return generate(GenerateConfig(problems=2, splits=one_split, **settings), progress=False)  # type: ignore[arg-type]


def _closed_loop(**settings: object) -> object:
    from ttompc.evaluation.closed_loop import ClosedLoopConfig, run_closed_loop

    return run_closed_loop(ClosedLoopConfig(scenario="freeflyer", **settings))  # type: ignore[arg-type]


def _warmstart(**settings: object) -> object:
    from ttompc.evaluation.warmstart import WarmStartConfig, run_warmstart

    return run_warmstart(WarmStartConfig(scenario="freeflyer", **settings))  # type: ignore[arg-type]


def _target(**settings: object) -> object:
    from ttompc.evaluation.target_error import TargetErrorConfig, run_target_error

    return run_target_error(TargetErrorConfig(scenario="freeflyer", **settings))  # type: ignore[arg-type]


def _loss(**settings: object) -> object:
    from ttompc.training.fit_loss import LossConfig, run_fit_loss

    return run_fit_loss(LossConfig(**settings))  # type: ignore[arg-type]


def _publish(to: str) -> object:
    from ttompc.zoo import publish

    return publish(BUNDLE, "x", to)


def _load(source: str, device: str = "cpu") -> object:
    import ttompc

    return ttompc.load_pretrained(source, device=device)


def _controller(source: str) -> object:
    import ttompc

    return ttompc.Controller.from_pretrained(source)


def _solve(backend: str) -> object:
    import numpy as np

    import ttompc

    sc = ttompc.get_scenario("freeflyer")
    return ttompc.solve_problem(sc, sc.sample(np.random.default_rng(0)), backend=backend)


API_CALLS: dict[str, Callable[[dict[str, str]], object]] = {
    "train-resumes-another-scenario": lambda w: _train(
        QUAD_TINY, f"data.paths=[{w['quad']}]", f"trainer.out_dir={w['ff_run']}"
    ),
    "train-into-a-users-folder": lambda w: _train(TINY, f"data.paths=[{w['ff']}]", f"trainer.out_dir={w['user']}"),
    "train-loader-workers-beyond-the-machine": lambda w: _train(
        TINY, f"data.paths=[{w['ff']}]", f"data.num_workers={MILLION}"
    ),
    "finetune-into-a-users-folder": lambda w: _finetune(f"data.paths=[{w['ff']}]", f"trainer.out_dir={w['user']}"),
    "generate-into-a-users-folder": lambda w: _generate(out=w["user"]),
    "generate-workers-beyond-the-machine": lambda w: _generate(workers=int(MILLION), out="o"),
    "mpc-into-a-users-folder": lambda w: _closed_loop(problems=1, out=w["user"]),
    "mpc-workers-beyond-the-machine": lambda w: _closed_loop(workers=int(MILLION)),
    "warmstart-into-a-users-folder": lambda w: _warmstart(model=BUNDLE, problems=1, out=w["user"]),
    "warmstart-over-another-configuration": lambda w: _warmstart(model=BUNDLE, problems=1, out=w["ws_report"]),
    "warmstart-workers-beyond-the-machine": lambda w: _warmstart(model="m", workers=int(MILLION)),
    "target-into-a-users-folder": lambda w: _target(model=BUNDLE, problems=1, out=w["user"]),
    "loss-into-a-users-folder": lambda w: _loss(model=BUNDLE, out=w["user"]),
    "publish-into-a-users-folder": lambda w: _publish(w["user"]),
    "demo-model-missing": lambda w: _load(w["missing"]),
    "mpc-model-missing": lambda w: _controller(w["missing"]),
    "mpc-device-that-does-not-exist": lambda w: _load(BUNDLE, device="nosuch"),
    "solve-unknown-backend": lambda w: _solve("nosuch"),
}
