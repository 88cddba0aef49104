"""``ttompc zoo list|info|download|publish|metrics|index``: the command-line face of ``ttompc.zoo``.

The zoo's errors are ``UserError``s (one line, exit 2, through ``ttompc.cli``); so are unreadable input files."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ttompc import zoo
from ttompc.errors import UserError
from ttompc.zoo.cards import KINDS, ModelCard
from ttompc.zoo.evaluations import headline_metrics, load_metrics
from ttompc.zoo.hub import parse_hf_url
from ttompc.zoo.registry import index_is_current, write_index, zoo_path
from ttompc.zoo.rounding import SE_SUFFIX, round_to_se, shown


def add_arguments(parser: argparse.ArgumentParser) -> None:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--zoo-dir", help="directory of model cards (default: $TTOMPC_ZOO or the repository's zoo/)")
    sub = parser.add_subparsers(dest="zoo_command", metavar="ACTION", required=True)

    p = sub.add_parser("list", parents=[common], help="table of the models in the zoo")
    p.add_argument("--json", action="store_true", help="print the index entries as JSON")

    p = sub.add_parser("info", parents=[common], help="print a model card (the text, then a summary of its record)")
    p.add_argument("name")
    p.add_argument("--json", action="store_true", help="print the card's front matter as JSON")
    p.add_argument("--raw", action="store_true", help="print the card file as stored (YAML front matter first)")

    p = sub.add_parser("download", parents=[common], help="fetch and verify a model into the local cache")
    p.add_argument("name", help="zoo model name, or hf://ORG/NAME[@REVISION] (into the Hugging Face cache)")
    p.add_argument("--cache-dir", help="cache root (default: $TTOMPC_HOME, $XDG_CACHE_HOME/ttompc, ~/.cache/ttompc)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    p = sub.add_parser(
        "publish", parents=[common], help="publish a bundle with its card (a folder or the Hub) or a dataset (the Hub)"
    )
    p.add_argument(
        "source",
        help="bundle directory (model.safetensors + config.json), a Lightning .ckpt, or with --to hf://datasets/... "
        "a dataset folder of `ttompc generate`",
    )
    p.add_argument("--name", help="model name (required for a folder; default for the Hub: the repository's NAME)")
    p.add_argument(
        "--to",
        required=True,
        help="destination directory or file:// URL (e.g. zoo/models/NAME), or a Hugging Face repository "
        "hf://ORG/NAME[@BRANCH] (a dataset: hf://datasets/ORG/NAME), uploaded in one commit",
    )
    p.add_argument("--private", action="store_true", help="create the Hub repository as private")
    p.add_argument(
        "--card-metrics",
        help="JSON file of evaluations {name: {command, what, metrics}} from `ttompc zoo metrics`, published as the "
        "card's metrics.json (for the bytes the card describes: replaces its evaluations of the same name, keeps the "
        "others)",
    )
    p.add_argument("--skip-eval", action="store_true", help="publish without metrics")
    p.add_argument("--base-url", help="card URLs become BASE_URL/<file> (when the files are uploaded there)")
    p.add_argument("--kind", choices=KINDS, help="override the kind read from config.json")
    p.add_argument(
        "--rtg-scale",
        type=float,
        help="record the model's conditioning rtg_0 = -RTG_SCALE*J_REL (what evaluation and MPC use by default)",
    )
    p.add_argument("--license", help="licence of the weights (default: the existing card's, else MIT)")
    p.add_argument("--recipe", help="path of the training recipe, e.g. recipes/freeflyer/pretrain.yaml")
    p.add_argument("--data-card", help="path or name of the training data card")
    p.add_argument("--tag", action="append", dest="tags", help="card tag (repeatable; replaces the default tags)")
    p.add_argument(
        "--dataset", action="append", dest="datasets", help="Hub id ORG/NAME of the training data (repeatable)"
    )
    p.add_argument("--base-model", help="Hub id ORG/NAME of the model a fine-tuned (FT-TTO) model started from")

    p = sub.add_parser(
        "metrics", help="card evaluations ({name: {command, what, metrics}}) from `ttompc evaluate` reports"
    )
    p.add_argument("--method", required=True, choices=KINDS, help="which model of the reports (TTO or FT-TTO)")
    p.add_argument("--warmstart", help="warmstart.json of `ttompc evaluate warmstart`")
    p.add_argument("--mpc", help="mpc.json of `ttompc evaluate mpc`")
    p.add_argument("--horizon", type=int, default=10, help="closed-loop horizon to report (default 10)")
    p.add_argument(
        "--out",
        help="write the JSON here (for `zoo publish --card-metrics`) instead of stdout, and print the headline "
        "rounded to its standard errors (a Markdown table for the card's body)",
    )

    p = sub.add_parser("index", parents=[common], help="regenerate zoo/index.json from the cards")
    p.add_argument("--check", action="store_true", help="only check that index.json is up to date (exit 1 if not)")


def resume_hint(args: argparse.Namespace) -> str:
    if args.zoo_command == "download":
        return "re-run the same command (verified files are kept and a partial download resumes)"
    return "run the command again (it writes its files atomically: nothing half-written is left)"


def run(args: argparse.Namespace) -> int:
    try:
        return _ACTIONS[args.zoo_command](args)
    except (FileNotFoundError, IsADirectoryError, PermissionError, json.JSONDecodeError) as err:
        raise UserError(str(err)) from err


def _list(args: argparse.Namespace) -> int:
    cards = zoo.list_models(args.zoo_dir)
    if args.json:
        print(json.dumps([c.to_dict() for c in cards], indent=2))
        return 0
    if not cards:
        print("no models in the zoo yet")
        return 0
    print(format_table(cards))
    return 0


def format_table(cards: list[ModelCard]) -> str:
    rows = [("NAME", "SCENARIO", "KIND", "SIZE", "HEADLINE")]
    for c in cards:
        rows.append((c.name, f"{c.scenario} v{c.scenario_version}", c.kind, _human(c.size), headline_text(c)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    return "\n".join("  ".join([*(v.ljust(w) for v, w in zip(r, widths, strict=False)), r[-1]]) for r in rows)


def headline_text(card: ModelCard) -> str:
    """A card's protocol numbers in words, each rounded to its standard error: open loop (J − J_REL)/J_REL of SCP from
    REL → from the model and the share of the reachable gain, closed-loop goal-reached rates at H = 10 (nominal ·
    perturbed); a card without them shows its first two metrics as key=value."""
    m = card.metrics
    parts = []
    if "ws_suboptimality" in m:
        rel = f"from REL {_pct(m, 'ws_suboptimality_rel')} → " if "ws_suboptimality_rel" in m else ""
        gain = f", {_pct(m, 'ws_gain_share')} of the reachable gain" if "ws_gain_share" in m else ""
        parts.append(f"open loop above J_REL {rel}from model {_pct(m, 'ws_suboptimality')}{gain}")
    rates = [k for p in ("nominal", "perturbed") if (k := f"mpc10_{p}_model_feasible_rate") in m]
    if rates:
        parts.append("closed-loop goal reached " + " · ".join(_pct(m, k) for k in rates))
    return "; ".join(parts) or ", ".join(f"{k}={shown(m, k)}" for k in list(m)[:2]) or "-"


def _pct(metrics: dict[str, int | float], key: str) -> str:
    """Metric ``key`` of ``metrics`` in per cent, rounded to its standard error (``key_se``) where it has one."""
    se = metrics.get(key + SE_SUFFIX)
    return f"{round_to_se(100 * metrics[key], None if se is None else 100 * se):g}%"


def _human(n: int) -> str:
    power = min(max(n.bit_length() - 1, 0) // 10, 3)
    return f"{n} B" if power == 0 else f"{n / 1024**power:.1f} {('KiB', 'MiB', 'GiB')[power - 1]}"


def _info(args: argparse.Namespace) -> int:
    card = zoo.model_info(args.name, args.zoo_dir)
    if args.json:
        print(json.dumps(card.to_dict(), indent=2))
    elif args.raw:
        sys.stdout.write((zoo_path(args.zoo_dir) / f"{card.name}.md").read_text(encoding="utf-8"))
    else:
        sys.stdout.write(readable_card(card))
    return 0


def readable_card(card: ModelCard) -> str:
    """The card's text first, then what a reader needs from the front matter: files, each evaluation's command and
    metrics (rounded to their standard errors: ``value ± se``), and where the full record is (``--json``/``--raw``,
    the metrics file)."""
    arch = ", ".join(f"{k}={card.architecture[k]}" for k in ("n_layer", "n_embd", "n_head") if k in card.architecture)
    lines = [
        card.body.strip(),
        "",
        "-" * 80,
        f"{card.name}: {card.kind}, scenario {card.scenario} v{card.scenario_version}" + (f", {arch}" if arch else ""),
        f"recipe: {card.recipe or '-'}   data: {card.data_card or '-'}   licence: {card.license}",
        "files: " + ", ".join(f"{f.filename} ({_human(f.size)}, sha256 {f.sha256[:12]}…)" for f in card.files),
    ]
    for name, evaluation in card.evaluations.items():
        lines.append(f"{name}: {evaluation['command']}" + (f"  ({evaluation['what']})" if "what" in evaluation else ""))
        metrics = evaluation["metrics"]
        shown_keys = [k for k in metrics if not (k.endswith(SE_SUFFIX) and k.removesuffix(SE_SUFFIX) in metrics)]
        values = ", ".join(f"{k}={shown(metrics, k)}" for k in shown_keys)
        lines += textwrap.wrap(values, width=110, initial_indent="  ", subsequent_indent="  ")
    where = f"; every number at full precision: its {card.evaluations_file}" if card.evaluations_file else ""
    lines.append(f"the full record: ttompc zoo info {card.name} --json (--raw: the card file){where}")
    return "\n".join(lines) + "\n"


def _download(args: argparse.Namespace) -> int:
    if zoo.is_hub_ref(args.name):  # the Hugging Face cache, not ours: --cache-dir does not apply
        print(zoo.download_model(args.name, progress=not args.no_progress)[0])
        return 0
    print(zoo.download(args.name, args.cache_dir, zoo_dir=args.zoo_dir, progress=not args.no_progress))
    return 0


@contextlib.contextmanager
def _as_bundle(source: Path, extra: dict[str, Any]) -> Iterator[Path]:
    """A Lightning checkpoint, or a bundle whose metadata gains ``extra``, as a temporary bundle (the zoo publishes
    bundles and never builds a model); anything else as given. Checkpoints are pickles, read with
    ``weights_only=True``: publish only those you made yourself."""
    if not (source.is_file() and source.suffix == ".ckpt") and not extra:
        yield source
        return
    from ttompc.policy import Planner

    planner = Planner.from_pretrained(source)
    planner.extra.update(extra)
    with tempfile.TemporaryDirectory(prefix="ttompc-publish-") as tmp:
        yield planner.save(tmp)


def _publish(args: argparse.Namespace) -> int:
    hub = zoo.is_hub_ref(args.to)
    if hub and parse_hf_url(args.to).repo_type == "dataset":
        commit = zoo.publish_dataset(args.source, args.to, private=args.private)
        print(f"published {args.source} to {args.to} at revision {commit}")
        return 0
    if not hub and args.name is None:
        raise UserError("zoo publish to a folder needs --name NAME")
    if not hub and args.private:
        raise UserError("--private is for a Hugging Face repository (--to hf://ORG/NAME)")
    if not hub:
        from ttompc.zoo.publish import claim_destination

        claim_destination(args.to)  # before a checkpoint is converted
    if hub and args.base_url:
        raise UserError("--base-url is for a folder destination: a Hub card lists the repository's own files")
    given = {
        "kind": args.kind,
        "license": args.license,
        "tags": args.tags,
        "recipe": args.recipe,
        "data_card": args.data_card,
        "datasets": args.datasets,
        "base_model": args.base_model,
    }
    fields = {k: v for k, v in given.items() if v is not None}
    if args.rtg_scale is not None:
        from ttompc.mpc.tto import check_rtg_scale

        try:
            check_rtg_scale(args.rtg_scale, "--rtg-scale")
        except ValueError as err:
            raise UserError(str(err)) from None
    extra = {"rtg_scale": args.rtg_scale} if args.rtg_scale is not None else {}
    metrics = load_metrics(args.card_metrics) if args.card_metrics else None
    with _as_bundle(Path(args.source), extra) as source:
        if hub:
            card, commit = zoo.publish_to_hub(
                source,
                args.to,
                name=args.name,
                private=args.private,
                zoo_dir=args.zoo_dir,
                metrics=metrics,
                skip_eval=args.skip_eval,
                card_fields=fields,
            )
        else:
            card = zoo.publish(
                source,
                args.name,
                args.to,
                zoo_dir=args.zoo_dir,
                metrics=metrics,
                skip_eval=args.skip_eval,
                base_url=args.base_url,
                card_fields=fields,
            )
    files = ", ".join(f"{f.filename} ({f.size} B, sha256 {f.sha256[:12]}…)" for f in card.files)
    print(
        f"published {card.name} to {args.to} at revision {commit}: {files}"
        if hub
        else f"published {card.name}: {files}"
    )
    return 0


def _metrics(args: argparse.Namespace) -> int:
    from ttompc.evaluation.card_metrics import card_metrics
    from ttompc.evaluation.report_files import read_report

    if not args.warmstart and not args.mpc:
        raise UserError("zoo metrics needs a report", "pass --warmstart FILE and/or --mpc FILE")
    pairs = (("warmstart", args.warmstart), ("mpc", args.mpc))
    reports = {k: read_report(v, k) if v else None for k, v in pairs}  # complete reports only
    try:
        metrics = card_metrics(args.method, horizon=args.horizon, **reports)
    except KeyError as err:
        raise UserError(str(err.args[0]), "evaluate with --model (TTO) and --ft-model (FT-TTO)") from err
    text = json.dumps(metrics, indent=2)
    if not args.out:
        print(text)
        return 0
    Path(args.out).write_text(text + "\n")
    print(f"wrote {args.out}; the headline (the card's model-index), rounded to its standard errors:")
    print(headline_table(metrics, args.method))
    return 0


def headline_table(evaluations: dict[str, dict[str, Any]], kind: str) -> str:
    """The headline of a ``kind`` model's ``evaluations`` (what the card's model-index states) as a Markdown table,
    each value with its standard error, at the precision the standard error supports (``ttompc.zoo.rounding``)."""
    rows = ["| evaluation | metric | value |", "|---|---|---|"]
    for name, evaluation in evaluations.items():
        headline = headline_metrics(evaluation["metrics"], kind)
        for key, label in headline[1] if headline else []:
            rows.append(f"| {name} | {label} | {shown(evaluation['metrics'], key)} |")
    return "\n".join(rows)


def _index(args: argparse.Namespace) -> int:
    if args.check:
        if index_is_current(args.zoo_dir):
            return 0
        print("zoo/index.json is out of date: run `ttompc zoo index`", file=sys.stderr)
        return 1
    print(write_index(args.zoo_dir))
    return 0


_ACTIONS = {
    "list": _list,
    "info": _info,
    "download": _download,
    "publish": _publish,
    "metrics": _metrics,
    "index": _index,
}
