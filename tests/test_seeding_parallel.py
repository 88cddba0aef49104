"""Seeds are pinned (published datasets and evaluation sets depend on them) and the pool is order- and
worker-count-independent."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from ttompc.errors import UserError
from ttompc.parallel import WorkerError, _born_deaf, pool_map, single_threaded_env, single_torch_thread
from ttompc.seeding import DAGGER_STREAM, EVAL_STREAM, derive_seed, eval_seed, problem_seed, rng, rollout_seed


def test_seed_values_are_those_the_datasets_and_evaluations_were_made_with() -> None:
    # Values of the three helpers this module replaced (data/generate, evaluation/common, finetune/dagger).
    assert [problem_seed(0, 0), problem_seed(2026, 123), problem_seed(7, 4999)] == [
        4334430513956379144,
        2375127026177142128,
        5273732012477411103,
    ]
    assert [eval_seed(0, 0), eval_seed(0, 3, 2), eval_seed(2026, 17, 0)] == [
        4832382425257349988,
        4482400590825496091,
        5705296436410179328,
    ]
    assert [rollout_seed(0, 0, 0), rollout_seed(0, 2, 3), rollout_seed(5, 9, 199)] == [
        2851415092582726301,
        1254921352998600945,
        1249825889423175933,
    ]


def test_streams_are_disjoint_and_seeds_fit_int64() -> None:
    data = {problem_seed(0, i) for i in range(2000)}
    evals = {eval_seed(0, i) for i in range(2000)}
    dagger = {rollout_seed(0, 0, i) for i in range(2000)}
    assert len(data) == len(evals) == len(dagger) == 2000
    assert not (data & evals) and not (data & dagger) and not (evals & dagger)
    assert all(0 <= s < 2**63 for s in data | evals | dagger)
    assert EVAL_STREAM != DAGGER_STREAM and derive_seed(1, 5) != derive_seed(2, 5)
    np.testing.assert_array_equal(rng(3, 4).random(5), np.random.default_rng(problem_seed(3, 4)).random(5))


def _square(x: int) -> int:
    return x * x


def _pid(_: int) -> int:
    import torch

    return torch.get_num_threads() * 1_000_000 + int(os.environ.get("OMP_NUM_THREADS", "0"))


def test_pool_map_keeps_task_order_for_any_worker_count() -> None:
    tasks = list(range(7))
    assert list(pool_map(_square, tasks, 1, pin_torch=False)) == [t * t for t in tasks]
    assert list(pool_map(_square, tasks, 2, pin_torch=False)) == [t * t for t in tasks]
    assert list(pool_map(_square, [], 2)) == []


def test_every_worker_starts_before_the_pool_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    """A worker spawned while the executor's thread runs races that thread's walk over the worker dict when a
    worker dies (CPython 3.11: a RuntimeError traceback from the thread, beside the one-line error)."""
    from concurrent.futures.process import ProcessPoolExecutor

    thread_running_at_spawn: list[bool] = []
    spawn = ProcessPoolExecutor._spawn_process  # type: ignore[attr-defined]

    def recording_spawn(self: ProcessPoolExecutor) -> None:
        thread_running_at_spawn.append(self._executor_manager_thread is not None)
        spawn(self)

    monkeypatch.setattr(ProcessPoolExecutor, "_spawn_process", recording_spawn)
    assert list(pool_map(_square, range(4), 2, pin_torch=False)) == [0, 1, 4, 9]
    assert thread_running_at_spawn == [False, False]


def _fail_to_start(kind: str) -> None:
    if kind == "user":
        raise UserError("no model 'nope' in the zoo", "see `ttompc zoo list`")
    raise RuntimeError("a broken\ninstallation")


@pytest.mark.timeout(120)  # a pool that replaced its failed workers (multiprocessing.Pool) waited forever
@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("user", "no model 'nope' in the zoo; see `ttompc zoo list`"),
        ("bug", "a worker process failed while starting (RuntimeError: a broken installation); --debug shows where"),
    ],
)
def test_a_worker_that_fails_to_start_ends_the_pool_with_its_error(kind: str, message: str) -> None:
    with pytest.raises(WorkerError) as info:
        list(pool_map(_square, range(6), 2, _fail_to_start, (kind,), pin_torch=False))
    assert str(info.value) == message


def test_workers_get_one_thread_and_the_parent_is_restored() -> None:
    import torch

    before = torch.get_num_threads()
    inline = list(pool_map(_pid, [0], 1))
    assert inline[0] // 1_000_000 == 1 and torch.get_num_threads() == before
    spawned = list(pool_map(_pid, [0, 1], 2))
    assert all(v // 1_000_000 == 1 for v in spawned)
    if "OMP_NUM_THREADS" not in os.environ:
        assert all(v % 1_000_000 == 1 for v in spawned)


def _sigint_state(_: int) -> tuple[bool, bool]:
    """(ignored, blocked) of SIGINT in the calling process's thread."""
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    return signal.getsignal(signal.SIGINT) == signal.SIG_IGN, signal.SIGINT in blocked


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="no signal masks (Windows)")
def test_workers_are_born_deaf_to_ctrl_c_and_the_parent_still_hears_it() -> None:
    """A process the pool spawns starts with SIGINT blocked, so a Ctrl-C that reaches it while it imports is held,
    not a traceback; a started worker ignores it (unblocked); the parent's mask is as before."""
    before = _sigint_state(0)  # (False, False) from a terminal; ignored when the suite itself runs under `nohup ... &`
    blocked = "import signal; print(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, []))"
    with _born_deaf():
        inside = subprocess.run([sys.executable, "-c", blocked], capture_output=True, text=True, check=True)
    outside = subprocess.run([sys.executable, "-c", blocked], capture_output=True, text=True, check=True)
    assert (inside.stdout.strip(), outside.stdout.strip()) == ("True", "False")
    assert list(pool_map(_sigint_state, [0, 1], 2, pin_torch=False)) == [(True, False), (True, False)]
    assert _sigint_state(0) == before and not before[1]  # this process: as it was, SIGINT not left blocked


def test_thread_helpers_restore_state(monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")
    with single_threaded_env():
        assert os.environ["OMP_NUM_THREADS"] == "1" and os.environ["MKL_NUM_THREADS"] == "3"
    assert "OMP_NUM_THREADS" not in os.environ and os.environ["MKL_NUM_THREADS"] == "3"
    torch.set_num_threads(2)
    with single_torch_thread():
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
