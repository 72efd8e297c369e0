"""Benchmark presets (the paper's dataset pairs and protocols) and the suite runner.

A suite resolves to pairs of sequences under a dataset root; each pair is run by every method
under the pair's protocol, saved at once (so an interrupted run resumes), then gathered into
results.csv, results.json (per pair and averaged over pairs), table.md and figures.
"""

from __future__ import annotations

import csv
import json
import math
import os
import tempfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from mf_lpr_ros.config import preset
from mf_lpr_ros.datasets import open_source
from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.evaluation.methods import METHODS
from mf_lpr_ros.evaluation.protocol import PairResult, Protocol, evaluate_pair
from mf_lpr_ros.progress import progress_bar
from mf_lpr_ros.sim.simulator import OFF_GRID_DAY2, SIMULATION_VERSION, WORLDS, world_bags

DEFAULT_METHODS = ("mf-lpr", "scan-context")
TABLE_COLUMNS = ("recall_at_1", "recall_at_1_corrected", "recall_at_5", "candidate_recall",
                 "rte_mean_m", "rre_mean_deg", "success_rate", "f1_max", "closures_published",
                 "closures_false", "precision_published", "recall_published",
                 "recall_at_100_precision", "ms_per_query")


@dataclass(frozen=True)
class Pair:
    """One evaluation: references from reference, queries from query (None: the reference's own
    loop closures), a parameter preset, a protocol, and optionally the dataset's query split."""

    name: str
    reference: Path
    query: Path | None
    preset: str
    protocol: Protocol
    query_stamps: tuple[float, ...] | None = None
    # A simulated world (sim.simulator.WORLDS): its bags are written before the run.
    simulated: str | None = None


@dataclass(frozen=True)
class Rule:
    """How a suite makes pairs from folders under the root (glob patterns).

    cross: every reference against every query folder. ordered: every ordered pair of distinct
    folders within each group (a group is one pattern), queries restricted to the split named by
    query_split (a file under the root, '{group}' replaced by the group's folder name).
    single: each folder's own loop closures. simulated: each world named in references
    (sim.simulator.WORLDS), day 2 against day 1 with day 2 off the world's grid
    (sim.simulator.OFF_GRID_DAY2), written under simulated_root() when first run, not under the
    dataset root. by_preset: the preset is appended to the pairs'
    names (rules that run the same folders under different presets); label, likewise a word
    of the rule's own (rules that run the same folders under different protocols)."""

    kind: str
    preset: str
    protocol: Protocol
    references: tuple[str, ...] = ()
    queries: tuple[str, ...] = ()
    query_split: str | None = None
    by_preset: bool = False
    label: str = ""


@dataclass(frozen=True)
class Published:
    """A figure another method's paper reports for one of the suite's pairs (recall@1)."""

    pair: str
    method: str
    recall_at_1: float


@dataclass(frozen=True)
class Suite:
    name: str
    description: str
    rules: tuple[Rule, ...]
    published: tuple[Published, ...] = ()

    def pairs(self, root: Path) -> list[Pair]:
        root = Path(root)
        if not root.is_dir():
            raise DatasetError(f"{root}: no such dataset root")
        pairs = []
        for rule in self.rules:
            pairs.extend(_rule_pairs(rule, root))
        return pairs


def _matches(root: Path, pattern: str) -> list[Path]:
    found = sorted(p for p in root.glob(pattern) if p.is_dir())
    if not found:
        raise DatasetError(f"{root}: no sequence folder matches {pattern!r} (the suite expects "
                           "the dataset's own folder names under --root)")
    return found


def _label(root: Path, path: Path) -> str:
    return str(path.relative_to(root)).replace(os.sep, "_")


def _rule_pairs(rule: Rule, root: Path) -> list[Pair]:
    pairs = _untagged_pairs(rule, root)
    for tag in (rule.label, rule.preset if rule.by_preset else ""):
        if tag:
            pairs = [replace(pair, name=f"{pair.name} [{tag}]") for pair in pairs]
    return pairs


def simulated_root() -> Path:
    """Where simulated worlds' bags are written: $MF_LPR_SIM_CACHE, else
    ~/.cache/mf_lpr_ros/simulated."""
    configured = os.environ.get("MF_LPR_SIM_CACHE")
    return Path(configured) if configured else Path.home() / ".cache" / "mf_lpr_ros" / "simulated"


def _untagged_pairs(rule: Rule, root: Path) -> list[Pair]:
    if rule.kind == "simulated":
        unknown = [world for world in rule.references if world not in WORLDS]
        if unknown:
            raise ValueError(f"unknown simulated worlds {unknown}; choose from {sorted(WORLDS)}")
        folders = {world: simulated_root() / f"{world}_off_grid" for world in rule.references}
        return [Pair(f"sim_{world}", folder / "day1", folder / "day2", rule.preset,
                     rule.protocol, simulated=world) for world, folder in folders.items()]
    if rule.kind == "single":
        return [Pair(_label(root, path), path, None, rule.preset, rule.protocol)
                for pattern in rule.references for path in _matches(root, pattern)]
    if rule.kind == "cross":
        references = [p for pattern in rule.references for p in _matches(root, pattern)]
        queries = [p for pattern in rule.queries for p in _matches(root, pattern)]
        return [Pair(f"{_label(root, ref)}__{_label(root, query)}", ref, query, rule.preset,
                     rule.protocol)
                for ref in references for query in queries if query != ref]
    if rule.kind == "ordered":
        from mf_lpr_ros.datasets.wildplaces import read_query_split

        pairs = []
        for pattern in rule.references:
            members = _matches(root, pattern)
            group = members[0].parent.name
            split = None
            if rule.query_split:
                split_path = root / rule.query_split.format(group=group)
                if not split_path.exists():
                    raise DatasetError(f"{split_path}: the {group} query split is missing (the "
                                       "dataset release's evaluation pickle)")
                split = read_query_split(split_path)
                if len(split) != len(members):
                    raise DatasetError(f"{split_path}: {len(split)} sequences in the split, "
                                       f"{len(members)} folders match {pattern!r}")
            for i, ref in enumerate(members):
                for j, query in enumerate(members):
                    if i != j:
                        stamps = tuple(split[j].tolist()) if split is not None else None
                        pairs.append(Pair(f"{_label(root, ref)}__{_label(root, query)}", ref,
                                          query, rule.preset, rule.protocol, stamps))
        return pairs
    raise ValueError(f"unknown suite rule kind {rule.kind!r}")


def run_suite(suite: Suite, root: Path, out: Path, *, methods=None, progress: bool = True,
              figures: bool = True, client=None) -> list[dict]:
    """Runs (or resumes) a suite; returns one row per pair and method plus per-method means.

    client: a distributed.Client (pipeline.distributed): each (pair, method) run still to
    do becomes one unit on its cluster; results are the serial run's.
    """
    methods = list(methods or DEFAULT_METHODS)
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown methods {unknown}; choose from {sorted(METHODS)}")
    pairs = suite.pairs(root)
    out = Path(out)
    (out / "pairs").mkdir(parents=True, exist_ok=True)
    # Written here, once per world, so that units running at once never write the same bags.
    for pair in {pair.reference: pair for pair in pairs if pair.simulated}.values():
        _write_simulated(pair, progress)
    results: dict[tuple[str, str], PairResult] = {}
    to_run = []
    for pair in pairs:
        for method in methods:
            path = out / "pairs" / f"{pair.name}__{method}.json"
            saved = _load_saved(path, _fingerprint(pair, method))
            if saved is None:
                to_run.append((pair, method, path))
            else:
                results[(pair.name, method)] = saved
    if client is None:
        bar = progress_bar(to_run, desc=suite.name, enabled=progress, unit="run")
        for pair, method, path in bar:
            bar.set_postfix_str(f"{pair.name} {method}")
            results[(pair.name, method)] = run_unit(pair, method, path)
    else:
        from mf_lpr_ros.pipeline.distributed import run_units

        done = run_units(client, run_unit,
                         [(f"{pair.name}__{method}", (pair, method, path))
                          for pair, method, path in to_run],
                         progress=progress, description=suite.name)
        for pair, method, _ in to_run:
            results[(pair.name, method)] = done[f"{pair.name}__{method}"]
    # A run saved before a column existed shows it as NaN.
    rows = [{"pair": pair.name, "method": results[(pair.name, m)].method,
             **dict.fromkeys(TABLE_COLUMNS, math.nan), **results[(pair.name, m)].summary}
            for pair in pairs for m in methods]
    rows += [published_row(figure, rows) for figure in suite.published]
    rows += average_rows(rows)
    _write_outputs(out, suite, pairs, rows)
    if figures:
        from mf_lpr_ros.evaluation.figures import write_suite_figures

        write_suite_figures(out, pairs, methods, results)
    return rows


def run_unit(pair: Pair, method: str, path: Path) -> PairResult:
    """One (pair, method) run, its result written atomically to path (the unit of a suite,
    serial or on a cluster)."""
    if pair.simulated is not None:
        _write_simulated(pair, progress=False)
    reference = open_source(pair.reference)
    query = open_source(pair.query) if pair.query is not None else None
    stamps = np.array(pair.query_stamps) if pair.query_stamps is not None else None
    result = evaluate_pair(reference, preset(pair.preset), pair.protocol, query=query,
                           query_stamps=stamps, method=method, progress=False)
    write_json_atomic(path, {"fingerprint": _fingerprint(pair, method), **result.to_dict()})
    return result


def _write_simulated(pair: Pair, progress: bool) -> None:
    """A simulated pair's bags, written unless already there (sim.simulator.world_bags)."""
    world_bags(pair.simulated, pair.reference.parent, day2_offset=OFF_GRID_DAY2,
               progress=progress)


def _fingerprint(pair: Pair, method: str) -> dict:
    return {"pair": pair.name, "reference": str(pair.reference),
            "query": str(pair.query) if pair.query else None, "method": method,
            "config": preset(pair.preset).to_dict(), "protocol": asdict(pair.protocol),
            "n_query_stamps": None if pair.query_stamps is None else len(pair.query_stamps),
            "simulated": None if pair.simulated is None else {
                "world": pair.simulated, "version": SIMULATION_VERSION,
                "day2_offset": list(OFF_GRID_DAY2)}}


def _load_saved(path: Path, fingerprint: dict) -> PairResult | None:
    """A finished run saved by an earlier (interrupted) suite, when its settings are the same."""
    if not path.exists():
        return None
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if saved.get("fingerprint") != json.loads(json.dumps(fingerprint)):
        return None
    return PairResult.from_dict(saved)


def write_json_atomic(path: Path, payload: dict) -> None:
    """JSON written to a temporary file and renamed over path: never half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle = tempfile.NamedTemporaryFile("w", dir=path.parent, suffix=".tmp", delete=False)
    try:
        with handle:
            json.dump(payload, handle)
        os.replace(handle.name, path)
    except BaseException:
        Path(handle.name).unlink(missing_ok=True)
        raise


def published_row(figure: Published, rows: list[dict]) -> dict:
    """A table row for a published figure: its recall@1, the pair's query count, NaN elsewhere."""
    queries = next((row["n_queries"] for row in rows if row["pair"] == figure.pair), math.nan)
    row = {key: math.nan for key in ("n_evaluated", "n_references", *TABLE_COLUMNS)}
    row.update(pair=figure.pair, method=figure.method, n_queries=queries,
               recall_at_1=figure.recall_at_1)
    return row


def average_rows(rows: list[dict]) -> list[dict]:
    """Per method, the mean of each metric over pairs (the paper's averaged table)."""
    averaged = []
    for method in dict.fromkeys(row["method"] for row in rows):
        mine = [row for row in rows if row["method"] == method]
        mean = {"pair": f"mean of {len(mine)} pairs", "method": method}
        for key in ("n_queries", "n_evaluated", "n_references", *TABLE_COLUMNS):
            values = np.array([row[key] for row in mine], dtype=float)
            mean[key] = float(np.nanmean(values)) if np.isfinite(values).any() else math.nan
        averaged.append(mean)
    return averaged


def format_table(rows: list[dict]) -> str:
    """A markdown table of rows (pair, method, TABLE_COLUMNS)."""
    lines = ["| pair | method | queries | " + " | ".join(TABLE_COLUMNS) + " |",
             "|---" * (len(TABLE_COLUMNS) + 3) + "|"]
    for row in rows:
        lines.append(f"| {row['pair']} | {row['method']} | {row['n_queries']:.0f} | "
                     + " | ".join(f"{row[key]:.0f}" if key.startswith("closures_")
                                  else f"{row[key]:.3f}" for key in TABLE_COLUMNS) + " |")
    return "\n".join(lines)


def _write_outputs(out: Path, suite: Suite, pairs: list[Pair], rows: list[dict]) -> None:
    scalar_keys = [k for k, v in rows[0].items() if not isinstance(v, (list, dict))]
    buffer = out / "results.csv.tmp"
    with open(buffer, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=scalar_keys, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    os.replace(buffer, out / "results.csv")
    write_json_atomic(out / "results.json", {
        "suite": suite.name, "description": suite.description,
        "pairs": [{"name": p.name, "reference": str(p.reference),
                   "query": str(p.query) if p.query else None, "preset": p.preset,
                   "protocol": asdict(p.protocol)} for p in pairs],
        "results": rows})
    (out / "table.md").write_text(f"# {suite.name}\n\n{suite.description}\n\n"
                                  + format_table(rows) + "\n")
