"""Model zoo: cards, their metrics files and the index, publish -> list -> download round trips, hash verification,
HTTP resume, path safety and "weights are never unpickled", and the shipped cards' layout (numbers in the metrics
file, rounded to their standard errors where shown, the recipe that built each model under recipes/zoo/). Everything
is local (tmp dirs, file://, a loopback HTTP server)."""

from __future__ import annotations

import hashlib
import http.server
import json
import pickle
import re
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import helpers
import numpy as np
import pytest
import yaml
from safetensors.numpy import save_file

from ttompc import zoo
from ttompc.cli import main
from ttompc.policy import Planner
from ttompc.zoo import cache, cards, registry
from ttompc.zoo.download import fetch
from ttompc.zoo.evaluations import METRICS_FILE, decode_evaluations, load_metrics
from ttompc.zoo.rounding import SE_DIGITS, se_decimals

REPO = Path(__file__).resolve().parents[1]
REPO_ZOO = REPO / "zoo"
METRICS = {"unit": {"command": "pytest tests/test_zoo.py", "what": "0 problems", "metrics": {"success_rate": 0.9}}}
BAD_NAMES = ["../x", "a/b", "..", ".hidden", "a\\b", "a..b", "", "x" * 101, "/abs", "name with space"]


def make_bundle(path: Path, seed: int = 0) -> Path:
    path.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    weights = {"w": rng.standard_normal((64, 32)).astype(np.float32), "b": np.zeros(32, np.float32)}
    save_file(weights, str(path / "model.safetensors"))
    config = {
        "format": "ttompc-planner",
        "format_version": 1,
        "model": {"n_layer": 1, "n_embd": 32},
        "scenario": {"name": "toy", "version": "0.1"},
        "recipe": {"lr": 1e-3},
        "code_version": "0.1.0+gtest",
    }
    (path / "config.json").write_text(json.dumps(config))
    return path


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def write_card(zoo_dir: Path, name: str, files: list[cards.FileEntry]) -> None:
    card = cards.ModelCard(
        name=name,
        kind="TTO",
        scenario="toy",
        scenario_version="0.1",
        architecture={},
        recipe="",
        data_card="",
        files=files,
        code_version="test",
    )
    (zoo_dir / f"{name}.md").write_text(cards.render_card(card))


def entries(url_of: dict[str, str], blobs: dict[str, bytes]) -> list[cards.FileEntry]:
    return [cards.FileEntry(f, url_of[f], sha256(b), len(b)) for f, b in blobs.items()]


def leftovers(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.is_file() and not p.name.endswith(".lock")]


@pytest.fixture
def env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An empty zoo and cache under tmp_path, selected through the environment like a user would."""
    (tmp_path / "zoo").mkdir()
    monkeypatch.setenv("TTOMPC_ZOO", str(tmp_path / "zoo"))
    monkeypatch.setenv("TTOMPC_HOME", str(tmp_path / "cache"))
    return tmp_path


class _Handler(http.server.BaseHTTPRequestHandler):
    """Serves ``server.files``; honours ``Range: bytes=N-`` only when ``server.ranges`` is set; logs requests."""

    server: Any

    def do_GET(self) -> None:
        data = self.server.files.get(self.path)
        self.server.requests.append((self.path, self.headers.get("Range")))
        if data is None:
            self.send_error(404)
            return
        start = 0
        if self.headers.get("Range") and self.server.ranges:
            start = int(self.headers["Range"].removeprefix("bytes=").rstrip("-"))
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
        else:
            self.send_response(200)
        self.send_header("Content-Length", str(len(data) - start))
        self.end_headers()
        # count before writing: the client can finish reading before this thread runs again
        self.server.sent += len(data) - start
        self.wfile.write(data[start:])

    def log_message(self, *args: Any) -> None:
        pass


@pytest.fixture
def server(monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    for var in ("http_proxy", "HTTP_PROXY", "https_proxy", "HTTPS_PROXY", "all_proxy", "ALL_PROXY"):
        monkeypatch.delenv(var, raising=False)
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    srv.files, srv.requests, srv.ranges, srv.sent = {}, [], True, 0  # type: ignore[attr-defined]
    srv.url = f"http://127.0.0.1:{srv.server_address[1]}"  # type: ignore[attr-defined]
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()


# ------------------------------------------------------------------------------------------------ cards, index
def test_repo_cards_parse_and_index_is_in_sync() -> None:
    registry.load_cards(REPO_ZOO)  # every committed card is valid
    assert registry.index_is_current(REPO_ZOO), "zoo/index.json is stale: run `ttompc zoo index`"
    assert main(["zoo", "index", "--check", "--zoo-dir", str(REPO_ZOO)]) == 0


def test_shipped_cards_keep_their_numbers_beside_their_bundles() -> None:
    """Every shipped card names its metrics file, shipped beside its bundle (``zoo/models/<name>/metrics.json``), and
    its front matter states no number but the model-index, each value rounded to its standard error."""
    for card in zoo.list_models(REPO_ZOO):
        entry = card.evaluations_entry
        assert entry is not None and entry.url == f"models/{card.name}/{METRICS_FILE}", card.name
        front = yaml.safe_load((REPO_ZOO / f"{card.name}.md").read_text().split("---\n")[1])
        assert front["evaluations"] == METRICS_FILE and "command" not in json.dumps(front), card.name
        metrics = {m["type"]: m["value"] for r in front["model-index"][0]["results"] for m in r["metrics"]}
        for key, value in metrics.items():
            se = card.metrics.get(f"{key}_se")
            assert value == (round(card.metrics[key], se_decimals(se)) if se else float(f"{card.metrics[key]:.3g}"))


NUMBER = r"[+\-−]?\d{1,3}(?:,\d{3})+(?:\.\d+)?|[+\-−]?\d+(?:\.\d+)?"
MEAN_SE = re.compile(rf"(?<![\w.])({NUMBER}) ± ({NUMBER})(?![\w.])")  # a standard error in exponent form is left out


def test_card_tables_show_what_the_standard_errors_support() -> None:
    """Every ``mean ± s.e.`` in a shipped card's text shows the standard error with at most two significant digits
    and the mean to no finer a decimal place than the standard error's second digit (0.84 ± 0.15, not 0.838 ±
    0.153): finer digits are noise."""
    finer = []
    for path in sorted(REPO_ZOO.glob("*-*.md")):
        for mean, se in MEAN_SE.findall(path.read_text()):
            se_digits = se.replace(",", "").replace(".", "").lstrip("0")
            places = se_decimals(float(se.replace(",", "")))
            decimals = len(mean.split(".")[1]) if "." in mean else 0
            if decimals > max(places, 0) or len(se_digits if "." in se else se_digits.rstrip("0")) > SE_DIGITS:
                finer.append(f"{path.name}: {mean} ± {se}")
    assert not finer, finer


def test_every_card_names_the_recipe_that_built_it_in_recipes_zoo() -> None:
    """The recipe that built a zoo model has one home, ``recipes/zoo/<name>.yaml`` (for a model trained in legs its
    last leg, ``<name>-legN.yaml``, whose header names the legs before it); ``recipes/<scenario>/`` holds the
    templates. Each card's recipe is there and loads with its command's loader (``ttompc finetune`` for a recipe with
    a ``dagger`` section, else ``ttompc train``); a training recipe builds the card's architecture."""
    from ttompc.finetune.config import load_finetune_config
    from ttompc.training.config import load_train_config

    for card in zoo.list_models(REPO_ZOO):
        assert re.fullmatch(rf"recipes/zoo/{re.escape(card.name)}(-leg\d+)?\.yaml", card.recipe), card.name
        path = REPO / card.recipe
        if "dagger" in yaml.safe_load(path.read_text()):
            load_finetune_config(path)
            continue
        model = load_train_config(path).model
        assert {k: getattr(model, k) for k in ("n_embd", "n_layer", "n_head")} == {
            k: card.architecture[k] for k in ("n_embd", "n_layer", "n_head")
        }, card.name


def test_card_round_trip_and_strict_parsing(env: Path) -> None:
    files = entries({"model.safetensors": "m", "config.json": "c"}, {"model.safetensors": b"1", "config.json": b"2"})
    write_card(env / "zoo", "m1", files)
    card = zoo.model_info("m1")
    assert cards.parse_card(cards.render_card(card)) == card
    front = card.to_dict()
    for broken in (
        {**front, "typo_key": 1},
        {**front, "kind": "GPT"},
        {**front, "evaluations": {"e": {"metrics": {"sr": 0.5}}}},  # numbers without the command that measured them
        {**front, "evaluations": {"e": {"command": "c", "metrics": {"sr": float("nan")}}}},
        {
            **front,
            "evaluations": {"e": {"command": "c", "metrics": {"sr": 1}}, "f": {"command": "d", "metrics": {"sr": 2}}},
        },
        {**front, "evaluations": METRICS_FILE},  # a metrics file the card does not list
        {**front, "evaluations": "config.json"},  # a bundle file is no metrics file
        {**front, "metrics": {"sr": {"value": 0.5}}},  # the first format: a metric without how it was measured
        {**front, "files": [{**front["files"][0], "sha256": "ab"}, front["files"][1]]},
        {**front, "files": [{**front["files"][0], "filename": "../model.safetensors"}, front["files"][1]]},
        {**front, "files": front["files"][:1]},  # config.json missing
    ):
        with pytest.raises(cards.CardError):
            cards.ModelCard.from_dict(broken)
    (env / "zoo" / "m2.md").write_text(cards.render_card(card))  # name does not match the file name
    with pytest.raises(cards.CardError, match="must match the file name"):
        zoo.list_models()


def test_numbers_live_in_the_metrics_file_beside_the_bundle(env: Path) -> None:
    """A published card names its metrics file (``evaluations: metrics.json``), lists it with its sha256 and size
    beside the bundle's files, and states no number but its model-index; the file holds the evaluations at full
    precision. Bytes that are not the listed ones, or a model-index that is not their numbers, are refused."""
    measured = {
        "command": "ttompc evaluate warmstart --model m problems=9",
        "metrics": {
            "ws_suboptimality": 0.4327860321807093,
            "ws_suboptimality_se": 0.02843456346991821,
            "ws_iterations": 6.43,
        },
    }
    card = zoo.publish(make_bundle(env / "b"), "m", str(env / "zoo" / "models" / "m"), metrics={"warmstart": measured})
    text = (env / "zoo" / "m.md").read_text()
    front = yaml.safe_load(text.split("---\n")[1])
    assert front["evaluations"] == METRICS_FILE and measured["command"] not in text
    assert [f["filename"] for f in front["files"]] == ["model.safetensors", "config.json", METRICS_FILE]
    assert front["files"][2]["url"] == "models/m/metrics.json"
    values = {m["type"]: m["value"] for m in front["model-index"][0]["results"][0]["metrics"]}
    assert values == {"ws_suboptimality": 0.433, "ws_iterations": 6.43}  # rounded to s.e. 0.028; three digits
    data = (env / "zoo" / "models" / "m" / METRICS_FILE).read_bytes()
    assert decode_evaluations(data, "metrics") == {"warmstart": measured} == card.evaluations  # full precision
    assert zoo.model_info("m").evaluations == card.evaluations
    assert (zoo.download("m", progress=False) / METRICS_FILE).read_bytes() == data  # verified with the bundle

    (env / "zoo" / "models" / "m" / METRICS_FILE).write_bytes(data.replace(b"6.43", b"5.43"))
    with pytest.raises(cards.CardError, match=r"metrics\.json is not the file the card lists"):
        zoo.model_info("m")
    (env / "zoo" / "models" / "m" / METRICS_FILE).write_bytes(data)
    parsed = cards.parse_card(text.replace("value: 0.433}", "value: 0.4}"))
    with pytest.raises(cards.CardError, match=r"model-index does not match .*\(ws_suboptimality\)"):
        cards.load_evaluations(parsed, data)
    assert cards.load_evaluations(cards.parse_card(text), data) == card
    with pytest.raises(cards.CardError, match="has not been read"):
        cards.render_card(cards.parse_card(text))  # never written without its numbers


def test_a_remote_metrics_file_is_fetched_once_and_verified(env: Path, server: Any) -> None:
    """A card published with ``--base-url`` is indexed before its files are uploaded; reading it then fetches its
    metrics file into the cache once, checked like the weights."""
    zoo.publish(make_bundle(env / "b"), "m", str(env / "staging"), metrics=METRICS, base_url=server.url)
    assert registry.index_is_current() and server.requests == []
    server.files = {f"/{p.name}": p.read_bytes() for p in (env / "staging").iterdir()}
    assert zoo.model_info("m").evaluations == METRICS
    assert zoo.model_info("m").evaluations == METRICS  # from the cache
    assert server.requests == [(f"/{METRICS_FILE}", None)]


def test_cards_of_the_first_format_still_load(env: Path) -> None:
    """A card published before evaluations (``metrics: {key: {value, how}}``, the command quoted in every ``how``, the
    full model-index), e.g. on a user's Hub repository, loads with its numbers grouped by command; its model-index is
    still checked against the numbers, and it is never written back in that format."""
    files = entries({"model.safetensors": "m", "config.json": "c"}, {"model.safetensors": b"1", "config.json": b"2"})
    write_card(env / "zoo", "old", files)
    front = zoo.model_info("old").to_dict()
    ws, mpc = "ttompc evaluate warmstart --model old problems=3", "ttompc evaluate mpc --model old problems=2"
    first = {k: v for k, v in front.items() if k != "evaluations"} | {
        "metrics": {
            "ws_suboptimality": {"value": 0.25, "how": f"`{ws}`: 3 problems, mean (J - J_REL)/J_REL"},
            "mpc10_nominal_model_feasible_rate": {"value": 0.5, "how": f"`{mpc}`: 2 problems, share feasible"},
            "ws_iterations": {"value": 4.0, "how": f"`{ws}`: 3 problems, mean SCP iterations"},
            "success_rate": {"value": 0.9, "how": "counted by hand"},
        },
        "headline_metrics": ["ws_suboptimality"],
        "inference": {"rtg_scale": 1.0, "protocol": [ws, mpc]},
        "model-index": [
            {
                "name": "old",
                "results": [
                    {
                        "task": {"type": "trajectory-optimization"},
                        "dataset": {"type": "ttompc/toy", "name": "toy"},
                        "metrics": [
                            {"type": "ws_suboptimality", "value": 0.25},
                            {"type": "ws_iterations", "value": 4.0},
                        ],
                    }
                ],
            }
        ],
    }
    card = cards.parse_card(f"---\n{yaml.safe_dump(first)}---\nText.\n")
    assert card.evaluations == {
        "warmstart": {"command": ws, "metrics": {"ws_suboptimality": 0.25, "ws_iterations": 4.0}},
        "mpc": {"command": mpc, "metrics": {"mpc10_nominal_model_feasible_rate": 0.5}},
        "eval": {"command": "counted by hand", "metrics": {"success_rate": 0.9}},
    }
    assert card.inference == {"rtg_scale": 1.0} and card.body == "Text.\n"
    with pytest.raises(cards.CardError, match="holds its numbers in its front matter"):
        cards.render_card(card)
    first["model-index"][0]["results"][0]["metrics"][0]["value"] = 0.3
    with pytest.raises(cards.CardError, match=r"model-index does not match .*\(ws_suboptimality\)"):
        cards.parse_card(f"---\n{yaml.safe_dump(first)}---\n")
    with pytest.raises(cards.CardError, match="keep evaluations"):
        cards.ModelCard.from_dict({**front, "metrics": first["metrics"]})
    (env / "first.json").write_text(json.dumps(first["metrics"]))  # a `ttompc zoo metrics` file of the first format
    assert load_metrics(env / "first.json") == card.evaluations


def test_a_card_with_numbers_in_its_front_matter_loads_and_publishing_moves_them(env: Path) -> None:
    """A card of the format before metrics files (``evaluations: {name: {command, what, metrics}}`` in the front
    matter, its model-index at full precision) loads read-only; publishing the same bytes again writes the card with
    a metrics file holding the same numbers, and the rest of the card kept."""
    src, to = make_bundle(env / "b"), str(env / "zoo" / "models" / "m")
    zoo.publish(src, "m", to, skip_eval=True)
    numbers = {"warmstart": {"command": "ttompc evaluate warmstart --model m", "metrics": {"ws_suboptimality": 0.4328}}}
    front = zoo.model_info("m").front_matter() | {
        "evaluations": numbers,
        "model-index": [
            {
                "name": "m",
                "results": [{"task": {}, "dataset": {}, "metrics": [{"type": "ws_suboptimality", "value": 0.4328}]}],
            }
        ],
    }
    (env / "zoo" / "m.md").write_text(f"---\n{yaml.safe_dump(front)}---\nNotes.\n")
    old = zoo.model_info("m")
    assert old.evaluations == numbers and old.evaluations_file == ""
    card = zoo.publish(src, "m", to)  # no metrics: the same bytes keep theirs
    assert card.evaluations == numbers and card.evaluations_file == METRICS_FILE and card.body == "Notes.\n"
    assert "ws_suboptimality: 0.4328" not in (env / "zoo" / "m.md").read_text()
    assert decode_evaluations((env / "zoo" / "models" / "m" / METRICS_FILE).read_bytes(), "m") == numbers
    assert zoo.publish(src, "m", to, skip_eval=True).evaluations_file == ""
    assert not (env / "zoo" / "models" / "m" / METRICS_FILE).exists()  # a card without numbers has no metrics file


def test_publishing_an_evaluation_for_the_same_bytes_keeps_the_others(env: Path) -> None:
    """Refreshing one evaluation (``zoo metrics --mpc`` then ``zoo publish --card-metrics``) of the bytes a card
    describes replaces that evaluation in place and keeps the others, which were measured on the same bytes; new
    bytes keep none."""
    src, to = make_bundle(env / "b"), str(env / "zoo" / "models" / "m")
    ws = {"command": "ttompc evaluate warmstart --model m", "metrics": {"ws_suboptimality": 0.25}}
    old = {
        "command": "ttompc evaluate mpc --model m horizons=[10]",
        "metrics": {"mpc10_nominal_model_feasible_rate": 0.5},
    }
    zoo.publish(src, "m", to, metrics={"warmstart": ws, "mpc": old, "unit": METRICS["unit"]})
    new = {
        "command": "ttompc evaluate mpc --model m horizons=[10,30]",
        "metrics": {"mpc10_nominal_model_feasible_rate": 0.75},
    }
    card = zoo.publish(src, "m", to, metrics={"mpc": new})
    assert card.evaluations == {"warmstart": ws, "mpc": new, "unit": METRICS["unit"]}
    assert list(card.evaluations) == ["warmstart", "mpc", "unit"]
    card = zoo.publish(src, "m", to, metrics={"mpc_nominal": old})  # a metric in common: supersedes "mpc"
    assert list(card.evaluations) == ["warmstart", "unit", "mpc_nominal"]
    assert zoo.publish(make_bundle(env / "b2", seed=1), "m", to, metrics={"mpc": new}).evaluations == {"mpc": new}


def test_stale_index_is_detected(env: Path) -> None:
    make_bundle(env / "b")
    zoo.publish(env / "b", "m1", str(env / "zoo" / "models" / "m1"), skip_eval=True)
    assert registry.index_is_current()
    (env / "zoo" / "m1.md").write_text((env / "zoo" / "m1.md").read_text().replace("license: mit", "license: BSD"))
    assert not registry.index_is_current()
    assert main(["zoo", "index", "--check"]) == 1
    assert main(["zoo", "index"]) == 0 and registry.index_is_current()


# -------------------------------------------------------------------------------------- publish / list / download
def test_publish_list_download_round_trip(env: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = make_bundle(env / "bundle")
    (env / "metrics.json").write_text(json.dumps(METRICS))
    dest = env / "zoo" / "models" / "ff-tiny"
    argv = ["zoo", "publish", str(src), "--name", "ff-tiny", "--to", str(dest), "--card-metrics"]
    assert main([*argv, str(env / "metrics.json"), "--recipe", "recipes/toy.yaml"]) == 0
    card = zoo.model_info("ff-tiny")
    assert [f.url for f in card.files] == [
        f"models/ff-tiny/{f}" for f in ("model.safetensors", "config.json", METRICS_FILE)
    ]
    assert (card.scenario, card.scenario_version, card.recipe, card.evaluations) == (
        "toy",
        "0.1",
        "recipes/toy.yaml",
        METRICS,
    )
    assert registry.index_is_current()
    assert json.loads((env / "zoo" / "index.json").read_text())["models"] == [card.to_dict()]

    capsys.readouterr()
    assert main(["zoo", "list"]) == 0
    row = capsys.readouterr().out.splitlines()[1].split()
    assert row[:4] == ["ff-tiny", "toy", "v0.1", "TTO"] and row[-1] == "success_rate=0.9"
    assert main(["zoo", "info", "ff-tiny", "--raw"]) == 0
    assert capsys.readouterr().out == (env / "zoo" / "ff-tiny.md").read_text()
    assert main(["zoo", "info", "ff-tiny"]) == 0  # readable: the card's text first, the record summarised after
    readable = capsys.readouterr().out
    assert readable.startswith(card.body.strip()) and "success_rate=0.9" in readable and "sha256: " not in readable

    assert main(["zoo", "download", "ff-tiny", "--no-progress"]) == 0
    bundle = Path(capsys.readouterr().out.strip())
    assert bundle.is_relative_to(env / "cache")
    for name in ("model.safetensors", "config.json"):
        assert (bundle / name).read_bytes() == (src / name).read_bytes()
    assert json.loads((bundle / METRICS_FILE).read_text()) == METRICS
    assert zoo.download("ff-tiny", progress=False) == bundle  # cached: same snapshot, nothing refetched


def test_publish_records_the_conditioning(env: Path, toy, toy_stats) -> None:
    """--rtg-scale writes the model's conditioning into the published bundle: from then on the planner's default."""
    import torch

    from ttompc.policy import ModelConfig, Planner, TrajectoryGPT

    torch.manual_seed(0)
    src = Planner(TrajectoryGPT(ModelConfig(n_embd=16, n_layer=1, n_head=2, max_steps=12)), toy, toy_stats)
    src.save(env / "real")
    dest = env / "zoo" / "models" / "toy-k"
    argv = ["zoo", "publish", str(env / "real"), "--name", "toy-k", "--to", str(dest), "--skip-eval"]
    assert main([*argv, "--rtg-scale", "1.3"]) == 0
    assert json.loads((dest / "config.json").read_text())["extra"]["rtg_scale"] == 1.3
    assert (dest / "model.safetensors").read_bytes() == (env / "real" / "model.safetensors").read_bytes()
    assert Planner.from_pretrained("toy-k").rtg_scale == 1.3


def test_republish_keeps_hand_edits_and_makes_a_new_snapshot(env: Path) -> None:
    zoo.publish(make_bundle(env / "b1"), "m", str(env / "zoo" / "models" / "m"), metrics=METRICS)
    path = env / "zoo" / "m.md"
    path.write_text(path.read_text().replace("license: mit", "license: cc-by-4.0") + "\nHand-written notes.\n")
    first = zoo.download("m", progress=False)
    card = zoo.publish(make_bundle(env / "b2", seed=1), "m", str(env / "zoo" / "models" / "m"), skip_eval=True)
    assert card.license == "cc-by-4.0" and card.body.endswith("Hand-written notes.\n") and card.metrics == {}
    second = zoo.download("m", progress=False)
    assert second != first and (first / "model.safetensors").is_file()  # the old snapshot is not rewritten
    assert (second / "model.safetensors").read_bytes() == (env / "b2" / "model.safetensors").read_bytes()


def test_publish_metrics_hook_and_requirements(env: Path) -> None:
    src = make_bundle(env / "b")
    to = str(env / "zoo" / "models" / "m")
    with pytest.raises(zoo.PublishError, match="--skip-eval"):
        zoo.publish(src, "m", to)
    seen: list[Path] = []
    card = zoo.publish(src, "m", to, evaluate=lambda bundle: seen.append(bundle) or METRICS)
    assert seen == [src] and card.evaluations == METRICS
    with pytest.raises(zoo.PublishError, match="local directory or file://"):
        zoo.publish(src, "m", "https://example.org/models", skip_eval=True)


def test_download_via_file_url(env: Path) -> None:
    src = make_bundle(env / "b")
    card = zoo.publish(src, "m", (env / "elsewhere").as_uri(), skip_eval=True)
    assert all(f.url.startswith("file://") for f in card.files)
    bundle = zoo.download("m", progress=False)
    assert (bundle / "model.safetensors").read_bytes() == (src / "model.safetensors").read_bytes()


def test_download_via_http_is_verified(env: Path, server: Any) -> None:
    blobs = {"model.safetensors": b"w" * 5000, "config.json": b"{}"}
    server.files = {f"/{f}": b for f, b in blobs.items()}
    write_card(env / "zoo", "m", entries({f: f"{server.url}/{f}" for f in blobs}, blobs))
    bundle = zoo.download("m", progress=False)
    assert {f: (bundle / f).read_bytes() for f in blobs} == blobs
    assert {p for p, _ in server.requests} == {"/model.safetensors", "/config.json"}
    assert (cache.blob_path(env / "cache", sha256(blobs["config.json"]))).read_bytes() == b"{}"


@pytest.mark.parametrize("via", ["http", "file"])
def test_hash_mismatch_raises_and_leaves_no_file(env: Path, server: Any, via: str) -> None:
    published, served = b"the published bytes", b"tampered bytes!!!!!"
    (env / "served.bin").write_bytes(served)
    server.files = {"/model.safetensors": served}
    url = f"{server.url}/model.safetensors" if via == "http" else (env / "served.bin").as_uri()
    blobs = {"model.safetensors": published, "config.json": b"{}"}
    write_card(env / "zoo", "m", entries({"model.safetensors": url, "config.json": url}, blobs))
    with pytest.raises(zoo.ChecksumError) as info:
        zoo.download("m", progress=False)
    assert sha256(published) in str(info.value) and sha256(served) in str(info.value)
    assert leftovers(env / "cache") == []


def test_resume_uses_range_and_verifies(env: Path, server: Any) -> None:
    data = np.random.default_rng(0).bytes(300_000)
    server.files = {"/w": data}
    entry = cards.FileEntry("model.safetensors", f"{server.url}/w", sha256(data), len(data))
    dest = cache.blob_path(env / "cache", entry.sha256)
    dest.parent.mkdir(parents=True)
    dest.with_name(dest.name + ".part").write_bytes(data[:123_456])  # an interrupted earlier download
    fetch(entry, dest, progress=False)
    assert server.requests == [("/w", "bytes=123456-")] and server.sent == len(data) - 123_456
    assert sha256(dest.read_bytes()) == entry.sha256 and not dest.with_name(dest.name + ".part").exists()


def test_resume_restarts_when_server_ignores_range(env: Path, server: Any) -> None:
    data = np.random.default_rng(1).bytes(50_000)
    server.files, server.ranges = {"/w": data}, False
    entry = cards.FileEntry("model.safetensors", f"{server.url}/w", sha256(data), len(data))
    dest = cache.blob_path(env / "cache", entry.sha256)
    dest.parent.mkdir(parents=True)
    dest.with_name(dest.name + ".part").write_bytes(b"x" * 1000)  # wrong bytes: must not end up in the file
    fetch(entry, dest, progress=False)
    assert server.requests == [("/w", "bytes=1000-")] and server.sent == len(data)
    assert dest.read_bytes() == data


def test_corrupt_partial_fails_once_then_recovers(env: Path, server: Any) -> None:
    data = np.random.default_rng(2).bytes(20_000)
    server.files = {"/w": data}
    entry = cards.FileEntry("model.safetensors", f"{server.url}/w", sha256(data), len(data))
    dest = cache.blob_path(env / "cache", entry.sha256)
    dest.parent.mkdir(parents=True)
    dest.with_name(dest.name + ".part").write_bytes(b"x" * 1000)
    with pytest.raises(zoo.ChecksumError):
        fetch(entry, dest, progress=False)
    assert leftovers(env / "cache") == []
    assert fetch(entry, dest, progress=False).read_bytes() == data


# ------------------------------------------------------------------------------------------------------- safety
@pytest.mark.parametrize("name", BAD_NAMES)
def test_path_escaping_names_are_rejected(env: Path, name: str) -> None:
    with pytest.raises(cards.CardError):
        zoo.download(name)
    with pytest.raises(cards.CardError):
        zoo.publish(env, name, str(env / "out"), skip_eval=True)
    assert not (env / "out").exists()


def test_paths_cannot_leave_their_directory(env: Path, tmp_path_factory: pytest.TempPathFactory) -> None:
    root = env / "cache"
    (root / "models").mkdir(parents=True)
    outside = tmp_path_factory.mktemp("outside")
    (root / "models" / "evil").symlink_to(outside)
    with pytest.raises(cache.UnsafePathError):
        cache.inside(root, "models", "evil", "x")
    with pytest.raises(cache.UnsafePathError):
        cache.inside(root, "..", "x")
    (env / "secret").write_bytes(b"s")  # a card whose relative URL climbs out of the zoo dir
    blobs = {"model.safetensors": b"s", "config.json": b"s"}
    write_card(env / "zoo", "m", entries(dict.fromkeys(blobs, "../secret"), blobs))
    with pytest.raises(cache.UnsafePathError):
        zoo.download("m", progress=False)


def test_cache_dir_precedence(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for var in ("TTOMPC_HOME", "XDG_CACHE_HOME"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache.cache_root() == tmp_path / "home" / ".cache" / "ttompc"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache.cache_root() == tmp_path / "xdg" / "ttompc"
    monkeypatch.setenv("TTOMPC_HOME", str(tmp_path / "th"))
    assert cache.cache_root() == tmp_path / "th"
    assert cache.cache_root(tmp_path / "explicit") == tmp_path / "explicit"


def _pickle_bomb(marker: Path) -> bytes:
    """A pickle that creates ``marker`` when unpickled."""

    class Bomb:
        def __reduce__(self) -> tuple[Any, ...]:
            return (open, (str(marker), "w"))

    return pickle.dumps(Bomb())


def test_loading_never_unpickles(env: Path) -> None:
    marker = env / "unpickled"
    bundle = make_bundle(env / "b")
    (bundle / "model.safetensors").write_bytes(_pickle_bomb(marker))
    with pytest.raises(zoo.BundleError, match="damaged or not a safetensors file"):
        Planner.from_pretrained(bundle)
    with pytest.raises(zoo.BundleError, match="damaged or not a safetensors file"):
        zoo.publish(bundle, "m", str(env / "out"), skip_eval=True)
    assert not marker.exists()


def test_from_pretrained_loads_a_zoo_name_through_the_verified_cache(env: Path) -> None:
    """The real planner, published and fetched by name: same weights, read from the cache, not the source."""
    import torch

    src = helpers.tiny_toy_planner().save(env / "b")
    zoo.publish(src, "m", str(env / "zoo" / "models" / "m"), skip_eval=True)
    by_name = Planner.from_pretrained("m", progress=False)
    by_dir = Planner.from_pretrained(src)  # a local bundle dir wins over the zoo
    for key, value in by_dir.model.state_dict().items():
        torch.testing.assert_close(by_name.model.state_dict()[key], value, rtol=0, atol=0)
    assert by_name.scenario.name == "toy" and by_name.stats.to_dict() == by_dir.stats.to_dict()
    assert any(p.is_relative_to(env / "cache") for p in (env / "cache").rglob("model.safetensors"))
    with pytest.raises(zoo.UnknownModelError, match="no model 'nope'"):
        Planner.from_pretrained("nope")


def test_hf_urls_need_huggingface_hub(env: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "huggingface_hub", None)  # as if it were not installed
    entry = cards.FileEntry("model.safetensors", "hf://org/repo@v1/model.safetensors", "0" * 64, 1)
    with pytest.raises(zoo.DownloadError, match="need huggingface_hub"):
        fetch(entry, env / "blob", progress=False)
    with pytest.raises(zoo.DownloadError, match="expected hf://org/repo"):
        fetch(cards.FileEntry("x", "hf://org", "0" * 64, 1), env / "blob", progress=False)


def _corrupt_in_place(path: Path) -> None:
    """Flip the last bytes (tensor data, so the safetensors header still parses); same size, same inode."""
    path.chmod(0o644)
    data = bytearray(path.read_bytes())
    data[-8:] = bytes(b ^ 0xFF for b in data[-8:])
    path.write_bytes(bytes(data))


def test_cache_corrupted_in_place_is_fetched_again(env: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A cached blob edited in place (same size) is re-hashed on load and on `zoo download`, and re-fetched."""
    import torch

    src = helpers.tiny_toy_planner().save(env / "b")
    zoo.publish(src, "m", str(env / "zoo" / "models" / "m"), skip_eval=True)
    bundle = zoo.download("m", progress=False)
    weights = bundle / "model.safetensors"
    _corrupt_in_place(weights)  # hard-linked: the blob changes with it
    assert weights.stat().st_size == (src / "model.safetensors").stat().st_size
    loaded = Planner.from_pretrained("m", progress=False)
    assert "does not match its published sha256" in capsys.readouterr().err
    for key, value in Planner.from_pretrained(src).model.state_dict().items():
        torch.testing.assert_close(loaded.model.state_dict()[key], value, rtol=0, atol=0)

    bundle = zoo.download("m", progress=False)
    _corrupt_in_place(bundle / "config.json")
    assert main(["zoo", "download", "m", "--no-progress"]) == 0
    again = Path(capsys.readouterr().out.strip())
    for name in ("model.safetensors", "config.json"):
        assert (again / name).read_bytes() == (src / name).read_bytes()


def test_cache_corrupted_without_a_source_is_a_clear_error(env: Path) -> None:
    make_bundle(env / "b")
    zoo.publish(env / "b", "m", str(env / "zoo" / "models" / "m"), skip_eval=True)
    bundle = zoo.download("m", progress=False)
    _corrupt_in_place(bundle / "model.safetensors")
    (env / "zoo" / "models" / "m" / "model.safetensors").unlink()  # the published copy is gone too
    with pytest.raises(zoo.DownloadError, match="cannot read"):
        zoo.download("m", progress=False)


def test_the_zoo_imports_no_model_code(tmp_path: Path) -> None:
    """Layering: ``Planner.from_pretrained`` loads zoo names through ``ttompc.zoo``, so the zoo (cards, cache,
    downloads, publishing of bundle files) imports nothing of ttompc but itself, errors, version, the progress
    display, the claiming of output folders (``ttompc.outputs``) and the model slots' names (``ttompc.model_slots``,
    a card's kinds), not even inside a function: a checkpoint is converted to a bundle by ``ttompc zoo publish``, not
    by ``zoo.publish``."""
    import ast

    allowed = (
        "ttompc.zoo",
        "ttompc.errors",
        "ttompc.version",
        "ttompc.progress",
        "ttompc.outputs",
        "ttompc.model_slots",
    )
    for path in sorted((Path(zoo.__file__).parent).glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
            else:
                continue
            wrong = [n for n in names if n.split(".")[0] == "ttompc" and not n.startswith(allowed)]
            assert not wrong, f"{path.name}:{node.lineno} imports {wrong}"
    ckpt = tmp_path / "last.ckpt"
    ckpt.write_bytes(b"never read")
    with pytest.raises(zoo.PublishError, match=r"Lightning checkpoint, not a bundle.*ttompc zoo publish"):
        zoo.publish(ckpt, "m", str(tmp_path / "out"), zoo_dir=tmp_path / "zoo", skip_eval=True)


def test_zoo_list_headline_reads_the_protocol_numbers() -> None:
    """``ttompc zoo list`` says what a card measured in words; a card without the protocol's metrics shows its
    headline metrics as key=value."""
    from ttompc.commands.zoo import headline_text

    (v3,) = [c for c in zoo.list_models(REPO_ZOO) if c.name == "freeflyer-tto-v3"]
    text = headline_text(v3)
    assert "from REL 40.7% → from model 34.5%, 82.3% of the reachable gain" in text
    assert text.endswith("closed-loop goal reached 100% · 75%")
    v3.evaluations = {"unit": {"command": "unit test", "metrics": {"success_rate": 0.9}}}
    assert headline_text(v3) == "success_rate=0.9"
