"""The Hugging Face Hub: ``ttompc zoo publish --to hf://`` and ``Planner.from_pretrained("hf://...")`` with the real
``huggingface_hub`` client against the loopback stand-in of ``hub_server.py`` (no network), cards published before
the metrics file still loading, and the Hub metadata of the shipped cards read back by ``huggingface_hub.ModelCard``."""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import helpers
import hub_server
import numpy as np
import pytest
import yaml

from ttompc import zoo
from ttompc.cli import main
from ttompc.policy import Planner
from ttompc.scenarios import get_scenario
from ttompc.zoo import cards, registry
from ttompc.zoo.evaluations import METRICS_FILE
from ttompc.zoo.hub import parse_hf_url, upload
from ttompc.zoo.rounding import rounded

REPO_ZOO = Path(__file__).resolve().parents[1] / "zoo"
TOKEN = "hf_test_token"
METRICS = {  # the evaluations of `ttompc zoo metrics`, and one of neither kind (no headline: not in the model-index)
    "warmstart": {
        "command": "ttompc evaluate warmstart --model m problems=3 seed=1",
        "metrics": {"ws_suboptimality": 0.25, "ws_failures": 0.0},
    },
    "mpc": {
        "command": "ttompc evaluate mpc --model m problems=2",
        "what": "test",
        "metrics": {"mpc10_nominal_model_feasible_rate": 0.5, "mpc10_nominal_model_step_time_s": 0.1},
    },
    "other": {"command": "python bench/x.py", "metrics": {"success_rate": 0.9}},
}


@pytest.fixture
def hub(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[hub_server.HubServer]:
    """The test hub as the client's endpoint, online, with a token in HF_TOKEN and caches under tmp_path.

    huggingface_hub reads HF_ENDPOINT, HF_HUB_OFFLINE and HF_HUB_CACHE once, when it is imported, so the fixture
    sets the constants they were read into (what a user sets in the environment before starting Python)."""
    from huggingface_hub import constants

    for var in ("http_proxy", "HTTP_PROXY", "https_proxy", "HTTPS_PROXY", "all_proxy", "ALL_PROXY"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HF_TOKEN", TOKEN)
    monkeypatch.setenv("TTOMPC_ZOO", str(tmp_path / "zoo"))
    monkeypatch.setenv("TTOMPC_HOME", str(tmp_path / "ttompc-cache"))
    with hub_server.running({TOKEN}) as server:
        monkeypatch.setattr(constants, "ENDPOINT", server.url)
        monkeypatch.setattr(
            constants, "HUGGINGFACE_CO_URL_TEMPLATE", server.url + "/{repo_id}/resolve/{revision}/{filename}"
        )
        monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
        monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "hf-cache"))
        monkeypatch.setattr(constants, "HF_TOKEN_PATH", str(tmp_path / "no-token-file"))
        monkeypatch.setattr(constants, "AGENT_HARNESSES_PATH", str(tmp_path / "agent-harnesses.json"))
        yield server
        assert not server.unhandled, f"the client called endpoints the test hub does not implement: {server.unhandled}"


def hf_cache_files(tmp_path: Path) -> dict[str, bytes]:
    """Every regular file in the Hugging Face cache (blobs and refs; snapshot entries are links to blobs)."""
    root = tmp_path / "hf-cache"
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file() and not p.is_symlink()}


def publish(bundle: Path, to: str, capsys: pytest.CaptureFixture[str], *extra: str) -> str:
    """``ttompc zoo publish`` to the test hub; returns the revision it printed."""
    metrics = bundle.parent / "metrics.json"
    metrics.write_text(json.dumps(METRICS))
    assert main(["zoo", "publish", str(bundle), "--to", to, "--card-metrics", str(metrics), *extra]) == 0
    out = capsys.readouterr().out
    return out.split(" at revision ")[1].split(":")[0]


def one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ttompc zoo: error: "), captured.err
    return lines[0]


def test_publish_download_plan_gives_the_same_warm_start(
    hub: hub_server.HubServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """publish -> download at the printed revision -> plan: the warm start is the local bundle's, bit for bit."""
    import huggingface_hub

    local = helpers.tiny_toy_planner(seed=3)
    bundle = local.save(tmp_path / "bundle")
    revision = publish(bundle, "hf://org/toy-tto", capsys)
    assert hub.commits_posted() == 1  # bundle and card in one commit
    repo = hub.repos[("model", "org/toy-tto")]
    assert repo.branches["main"] == revision and not repo.private
    tree = repo.commits[revision]
    for name in ("model.safetensors", "config.json"):
        assert tree[name] == (bundle / name).read_bytes()
    assert json.loads(tree[METRICS_FILE]) == METRICS  # the numbers beside the bundle, at full precision

    loaded = Planner.from_pretrained(f"hf://org/toy-tto@{revision}", progress=False)
    problems = [get_scenario("toy").sample(np.random.default_rng(s)) for s in range(3)]
    X, U = local.warm_start(problems, rtg0=-2.0)
    X_hub, U_hub = loaded.warm_start(problems, rtg0=-2.0)
    assert np.array_equal(X, X_hub) and np.array_equal(U, U_hub)
    snapshot = tmp_path / "hf-cache" / "models--org--toy-tto" / "snapshots" / revision
    assert (snapshot / "model.safetensors").read_bytes() == (bundle / "model.safetensors").read_bytes()

    card = huggingface_hub.ModelCard.load(snapshot / "README.md")
    assert card.data.library_name == "ttompc" and card.data.license == "mit"
    results = {r.metric_type: (r.task_type, r.metric_value) for r in card.data.eval_results}
    assert results == {  # the headline: not ws_failures, nor the step time, nor the metric of neither evaluation
        "ws_suboptimality": ("trajectory-optimization", 0.25),
        "mpc10_nominal_model_feasible_rate": ("model-predictive-control", 0.5),
    }
    assert [r.dataset_config for r in card.data.eval_results] == ["warmstart", "mpc"]  # the evaluation of each
    ours = cards.parse_card((snapshot / "README.md").read_text())
    assert 'Planner.from_pretrained("hf://org/toy-tto")' in ours.body and ours.evaluations_file == METRICS_FILE
    cards.load_evaluations(ours, (snapshot / METRICS_FILE).read_bytes())
    assert ours.evaluations == METRICS and ours.inference["rtg_scale"] == local.rtg_scale

    assert main(["zoo", "download", "hf://org/toy-tto", "--no-progress"]) == 0  # main: the same commit
    assert capsys.readouterr().out.strip() == str(snapshot)


def test_republish_is_a_new_revision_and_old_revisions_still_load(
    hub: hub_server.HubServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    first = publish(helpers.tiny_toy_planner(seed=1).save(tmp_path / "b1"), "hf://org/m", capsys)
    second = publish(helpers.tiny_toy_planner(seed=2).save(tmp_path / "b2"), "hf://org/m", capsys)
    assert first != second and hub.commits_posted() == 2
    old, new = Planner.from_pretrained(f"hf://org/m@{first}"), Planner.from_pretrained("hf://org/m")
    w = "model.safetensors"
    assert (tmp_path / "b1" / w).read_bytes() != (tmp_path / "b2" / w).read_bytes()
    for planner, seed in ((old, 1), (new, 2)):
        expected = helpers.tiny_toy_planner(seed=seed).model.state_dict()
        assert all(np.array_equal(v.numpy(), expected[k].numpy()) for k, v in planner.model.state_dict().items())


def test_a_card_published_before_the_metrics_file_still_loads(hub: hub_server.HubServer, tmp_path: Path) -> None:
    """A Hub repository published before cards had a metrics file holds the bundle and a README.md with the numbers
    in its front matter (and a model-index at full precision): it loads for ``Planner.from_pretrained`` and
    ``ttompc zoo download``, its numbers read from the front matter."""
    local = helpers.tiny_toy_planner(seed=4)
    bundle = local.save(tmp_path / "bundle")
    card, _ = zoo.publish_to_hub(bundle, "hf://org/new", metrics=METRICS)
    front = card.front_matter() | {
        "files": [f.to_dict() for f in card.files if f.filename != METRICS_FILE],
        "evaluations": METRICS,
        "model-index": [
            {
                "name": "old",
                "results": [
                    {
                        "task": {},
                        "dataset": {"config": "warmstart"},
                        "metrics": [{"type": "ws_suboptimality", "value": 0.25}],
                    }
                ],
            }
        ],
    }
    readme = tmp_path / "README.md"
    readme.write_text(f"---\n{yaml.safe_dump(front, sort_keys=False)}---\nAn earlier card.\n")
    files = {"README.md": readme, **{f: bundle / f for f in ("model.safetensors", "config.json")}}
    upload(parse_hf_url("hf://org/old"), files, "Publish old", private=False)

    loaded = Planner.from_pretrained("hf://org/old", progress=False)
    assert all(
        np.array_equal(v.numpy(), local.model.state_dict()[k].numpy()) for k, v in loaded.model.state_dict().items()
    )
    snapshot, _ = zoo.download_model("hf://org/old", progress=False)
    old = cards.parse_card((snapshot / "README.md").read_text())
    assert old.evaluations == METRICS and old.evaluations_file == "" and not (snapshot / METRICS_FILE).exists()


def test_a_fine_tuned_model_names_its_base_model_and_data(hub: hub_server.HubServer, tmp_path: Path) -> None:
    import huggingface_hub

    planner = helpers.tiny_toy_planner()
    planner.extra.update(finetuned_from="hf://org/base@0123abc", rtg_scale=1.3)  # what `ttompc finetune` records
    card, revision = zoo.publish_to_hub(
        planner.save(tmp_path / "b"), "hf://org/ft", skip_eval=True, card_fields={"datasets": ["org/data-v1"]}
    )
    assert card.kind == "FT-TTO" and card.inference["rtg_scale"] == 1.3 and "model-index" not in card.front_matter()
    readme = huggingface_hub.hf_hub_download("org/ft", "README.md", revision=revision)
    data = huggingface_hub.ModelCard.load(readme).data
    assert data.base_model == "org/base" and data.datasets == ["org/data-v1"] and data.eval_results is None
    assert Planner.from_pretrained("hf://org/ft", progress=False).rtg_scale == 1.3


def test_private_repositories_need_the_token(
    hub: hub_server.HubServer, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    publish(helpers.tiny_toy_planner().save(tmp_path / "b"), "hf://org/secret", capsys, "--private")
    assert hub.repos[("model", "org/secret")].private
    monkeypatch.delenv("HF_TOKEN")
    assert main(["zoo", "download", "hf://org/secret", "--no-progress"]) == 2
    assert "no model repository org/secret" in one_error_line(capsys)


def test_missing_token_is_one_line_and_sends_nothing(
    hub: hub_server.HubServer, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("HF_TOKEN")
    bundle = helpers.tiny_toy_planner().save(tmp_path / "b")
    assert main(["zoo", "publish", str(bundle), "--to", "hf://org/m", "--skip-eval"]) == 2
    line = one_error_line(capsys)
    assert "needs a Hugging Face token" in line and "HF_TOKEN" in line
    assert hub.requests == [] and hub.repos == {}


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("hf://org/nope", "no model repository org/nope"),
        ("hf://org/m@nope", "no revision 'nope' in model repository org/m"),
        ("hf://org/m@v1/x", "expected hf://ORG/NAME[@REVISION]"),
    ],
)
def test_unknown_repository_or_revision_is_one_line_and_caches_nothing(
    hub: hub_server.HubServer, tmp_path: Path, capsys: pytest.CaptureFixture[str], url: str, message: str
) -> None:
    publish(helpers.tiny_toy_planner().save(tmp_path / "b"), "hf://org/m", capsys)
    assert main(["zoo", "download", url, "--no-progress"]) == 2
    assert message in one_error_line(capsys)
    assert hf_cache_files(tmp_path) == {}


def test_a_corrupted_download_is_refused_and_removed(
    hub: hub_server.HubServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Bytes that are not the card's never reach torch and do not stay in the cache; the next try downloads
    again (and succeeds once the served bytes are right)."""
    bundle = helpers.tiny_toy_planner().save(tmp_path / "b")
    revision = publish(bundle, "hf://org/m", capsys)
    good = hub.repos[("model", "org/m")].commits[revision]["model.safetensors"]
    hub.tamper("org/m", "model.safetensors")
    for _ in range(2):
        assert main(["zoo", "download", "hf://org/m", "--no-progress"]) == 2
        line = one_error_line(capsys)
        assert "model.safetensors: sha256 mismatch" in line and "removed from the Hugging Face cache" in line
        cached = hf_cache_files(tmp_path)
        assert not any(len(data) == len(good) for data in cached.values())  # neither the bad bytes nor a partial
        assert not any(".incomplete" in name for name in cached)
    with pytest.raises(zoo.ChecksumError):
        Planner.from_pretrained("hf://org/m", progress=False)
    hub.repos[("model", "org/m")].commits[revision]["model.safetensors"] = good
    assert Planner.from_pretrained("hf://org/m", progress=False).rtg_scale == 1.0


def test_offline_uses_the_cache_or_says_what_is_missing(
    hub: hub_server.HubServer, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from huggingface_hub import constants

    revision = publish(helpers.tiny_toy_planner().save(tmp_path / "b"), "hf://org/m", capsys)
    Planner.from_pretrained("hf://org/m", progress=False)
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    hub.requests.clear()
    for url in ("hf://org/m", f"hf://org/m@{revision}"):
        assert Planner.from_pretrained(url, progress=False).scenario.name == "toy"
    assert hub.requests == []
    assert main(["zoo", "download", "hf://org/other", "--no-progress"]) == 2
    line = one_error_line(capsys)
    assert "hf://org/other: README.md is not in the Hugging Face cache" in line and "HF_HUB_OFFLINE=1" in line
    assert hub.requests == []


def test_dataset_folder_publishes_in_one_commit_and_loads_with_datasets(
    hub: hub_server.HubServer, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A `ttompc generate` folder goes to a dataset repository in one commit, byte for byte, and
    `datasets.load_dataset("ORG/NAME")` reads its splits from the Hub through the card's `configs:` section."""
    import data_fakes as fakes
    import datasets

    out = tmp_path / "fake-v1"
    manifest = helpers.tiny_dataset(out, "data-fake", 12, (0.5, 0.25, 0.25), shard_size=6, seed=7, solver=fakes.SOLVER)
    assert main(["zoo", "publish", str(out), "--to", "hf://datasets/org/fake-v1"]) == 0
    revision = capsys.readouterr().out.strip().rsplit(" ", 1)[1]
    assert hub.commits_posted() == 1
    tree = hub.repos[("dataset", "org/fake-v1")].commits[revision]
    local = {p.relative_to(out).as_posix(): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    published = {k: v for k, v in tree.items() if k != ".gitattributes"}
    assert published == {k: v for k, v in local.items() if k in published}
    assert {"README.md", "manifest.json"} <= set(published) and any(k.endswith(".parquet") for k in published)

    monkeypatch.setattr(datasets.config, "HF_ENDPOINT", hub.url)  # datasets keeps its own copies of these
    monkeypatch.setattr(datasets.config, "HF_HUB_OFFLINE", False)
    monkeypatch.setattr(datasets.config, "HF_DATASETS_CACHE", tmp_path / "datasets-cache")
    loaded = datasets.load_dataset("org/fake-v1", revision=revision, streaming=True)
    hf_split = {"train": "train", "validation": "val", "test": "test"}
    rows = {s: sum(1 for _ in loaded[s]) for s in loaded}
    assert rows == {s: manifest["splits"]["rows"][hf_split[s]] for s in loaded} and sum(rows.values()) > 0
    capsys.readouterr()  # datasets' own warnings
    (out / next(k for k in published if k.endswith(".parquet"))).write_bytes(b"damaged")
    assert main(["zoo", "publish", str(out), "--to", "hf://datasets/org/fake-v1"]) == 2
    assert "does not match manifest.json" in one_error_line(capsys) and hub.commits_posted() == 1


def test_shipped_cards_give_the_hub_their_results() -> None:
    """Every shipped card's model-index, read by huggingface_hub, holds its headline: the open-loop suboptimality and
    SCP iterations against REL's, and the closed-loop goals and cost at H = 10 (nominal plant) of the model's better
    variant beside REL-MPC's, each with the card's value and naming the evaluation it came from."""
    import huggingface_hub

    for path in sorted(REPO_ZOO.glob("*.md")):
        if path.name == "README.md":
            continue
        ours = registry.get_card(path.stem, REPO_ZOO)
        hub_card = huggingface_hub.ModelCard.load(path)
        assert hub_card.data.library_name == "ttompc" and hub_card.data.license == "mit"
        results = hub_card.data.eval_results
        for r in results:  # the card's number, rounded to its standard error
            assert r.metric_value == rounded(ours.evaluations[r.dataset_config]["metrics"], r.metric_type), path.name
        types = {r.metric_type for r in results}
        if "ws_suboptimality" in ours.metrics:
            assert {"ws_suboptimality", "ws_suboptimality_rel", "ws_iterations", "ws_iterations_rel"} <= types
        if "mpc10_nominal_model_feasible_rate" in ours.metrics:
            assert "mpc10_nominal_rel_feasible_rate" in types and types & {
                "mpc10_nominal_model_feasible_rate",
                "mpc10_nominal_robust_feasible_rate",
            }
        per_evaluation = Counter(r.dataset_config for r in results)
        assert types and max(per_evaluation.values()) <= 6, path.name  # the headline, not every number
        assert ours.inference["rtg_scale"] > 0 and set(ours.inference) == {"rtg_scale", "conditioning"}, path.name


def test_cards_refuse_a_model_index_that_is_not_their_metrics(tmp_path: Path) -> None:
    text = (REPO_ZOO / "rpod-tto-small.md").read_text()
    numbers = (REPO_ZOO / "models" / "rpod-tto-small" / METRICS_FILE).read_bytes()
    value = rounded(registry.get_card("rpod-tto-small", REPO_ZOO).metrics, "ws_suboptimality")
    edited = text.replace(f"type: ws_suboptimality, value: {value}}}", "type: ws_suboptimality, value: 0.0}")
    assert edited.count("0.0}") == text.count("0.0}") + 1
    with pytest.raises(cards.CardError, match="model-index does not match the evaluations' metrics"):
        cards.load_evaluations(cards.parse_card(edited), numbers)
    with pytest.raises(cards.CardError, match="must be the Hugging Face id ORG/NAME"):
        cards.parse_card(text.replace("kind: TTO", "kind: TTO\nbase_model: org/base"))
