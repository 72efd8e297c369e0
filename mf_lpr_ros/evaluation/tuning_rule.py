"""The tuning rule, applied to two runs of a suite (docs/RESULTS.md, "How defaults are chosen").

A default changes only when the suite's mean rises and no pair drops by more than a point.
compare_runs reads a suite's output folder before and after a change (results.json and the
per-pair records under pairs/) and says, pair by pair, what moved and whether the change
passes: the rule lives here once, not in each session's arithmetic.

The rule's figures: recall_at_1, recall_at_1_corrected and recall_published (the recalls, in
points) and closures_false (a false loop closure bends a pose graph: none may be added).
The suite's mean is the mean of the three recalls over every pair both runs hold.

A suite that checks a change instead of choosing it (CHECK_SUITES: `sensors`, sensors the
tuning suite does not hold, standing in for the sets we do not have) has its own verdict: no
recall drops by more than a point, no false closure is added, and on every sensor `auto`
stays within a point of `default`'s recall@1. Its mean need not rise.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mf_lpr_ros.errors import DatasetError

RULE_RECALLS = ("recall_at_1", "recall_at_1_corrected", "recall_published")
ONE_POINT = 0.01
TABLE_FIGURES = ("recall_at_1", "recall_at_1_corrected", "candidate_recall",
                 "closures_published", "closures_false", "recall_published")
CHECK_SUITES = ("sensors",)


@dataclass(frozen=True)
class PairChange:
    """One pair and method in both runs: each figure before and after, and the share of its
    positive queries (a reference within tolerance) matched to the same reference in both
    (NaN when either run's records are missing)."""

    pair: str
    method: str
    n_queries: float
    before: dict[str, float]
    after: dict[str, float]
    same_reference: float

    def drop(self, figure: str) -> float:
        """How far figure fell (negative: it rose); NaN when either side lacks it."""
        return self.before.get(figure, math.nan) - self.after.get(figure, math.nan)


@dataclass
class RunComparison:
    """Two runs of a suite side by side and the rule's verdict."""

    changes: list[PairChange]
    only_before: list[str] = field(default_factory=list)
    only_after: list[str] = field(default_factory=list)
    suite: str | None = None

    @property
    def is_check(self) -> bool:
        """Whether the runs are of a suite that checks a change (CHECK_SUITES)."""
        return self.suite in CHECK_SUITES

    def mean(self, side: str) -> float:
        """The suite's mean: the rule's recalls averaged over every pair both runs hold."""
        return _nanmean([getattr(change, side).get(figure, math.nan)
                         for change in self.changes for figure in RULE_RECALLS])

    def drops_over_a_point(self) -> list[tuple[str, str, float]]:
        """(pair, figure, drop) for every recall that fell by more than ONE_POINT."""
        return [(change.pair, figure, change.drop(figure)) for change in self.changes
                for figure in RULE_RECALLS if change.drop(figure) > ONE_POINT + 1e-9]

    def false_closures_added(self) -> list[tuple[str, float]]:
        """(pair, closures added) for every pair whose false closures rose."""
        return [(change.pair, -change.drop("closures_false")) for change in self.changes
                if change.drop("closures_false") < 0]

    def auto_below_default(self) -> list[tuple[str, float, float]]:
        """(sensor, auto's recall@1, default's) after the change, wherever auto falls more
        than a point below default on the same pair's sensor ("NAME [auto]" beside
        "NAME [default]")."""
        after = {(change.pair, change.method): change.after.get("recall_at_1", math.nan)
                 for change in self.changes}
        below = []
        for (pair, method), auto in after.items():
            if not pair.endswith(" [auto]"):
                continue
            sensor = pair[: -len(" [auto]")]
            default = after.get((f"{sensor} [default]", method), math.nan)
            if default - auto > ONE_POINT + 1e-9:
                below.append((sensor, auto, default))
        return below

    @property
    def passes(self) -> bool:
        """No recall drops by more than a point on any pair, no pair gains a false closure,
        both runs hold the same pairs, and: the suite's mean rises (the tuning rule), or, for
        a suite that checks a change, auto stays within a point of default on every sensor."""
        shared = (not self.drops_over_a_point() and not self.false_closures_added()
                  and not self.only_before and not self.only_after)
        if self.is_check:
            return shared and not self.auto_below_default()
        return shared and self.mean("after") > self.mean("before")


def compare_runs(before: Path, after: Path) -> RunComparison:
    """The rule applied to two suite output folders (each holding results.json) of one
    suite."""
    (suite_before, rows_before), (suite_after, rows_after) = _run(Path(before)), _run(Path(after))
    if suite_before != suite_after:
        raise DatasetError(f"{before} and {after} are runs of different suites "
                           f"({suite_before} and {suite_after}): compare two runs of one")
    changes = []
    for key, row in rows_before.items():
        if key not in rows_after:
            continue
        changes.append(PairChange(
            pair=key[0], method=key[1], n_queries=float(row.get("n_queries", math.nan)),
            before={figure: float(row[figure]) for figure in TABLE_FIGURES if figure in row},
            after={figure: float(rows_after[key][figure]) for figure in TABLE_FIGURES
                   if figure in rows_after[key]},
            same_reference=_same_reference(Path(before), Path(after), *key)))
    return RunComparison(changes,
                         only_before=[f"{p} ({m})" for p, m in rows_before if (p, m)
                                      not in rows_after],
                         only_after=[f"{p} ({m})" for p, m in rows_after if (p, m)
                                     not in rows_before],
                         suite=suite_after)


def format_comparison(comparison: RunComparison) -> str:
    """A markdown before -> after table (as docs/RESULTS.md keeps them) and the verdict."""
    lines = ["| pair | queries | " + " | ".join(TABLE_FIGURES) + " | same reference (positives) |",
             "|---" * (len(TABLE_FIGURES) + 3) + "|"]
    for change in comparison.changes:
        cells = [f"{_figure(figure, change.before.get(figure, math.nan))} → "
                 f"{_figure(figure, change.after.get(figure, math.nan))}"
                 for figure in TABLE_FIGURES]
        lines.append(f"| {change.pair} | {change.n_queries:.0f} | " + " | ".join(cells)
                     + f" | {_figure('same', change.same_reference)} |")
    means = {side: [_nanmean([getattr(change, side).get(figure, math.nan)
                              for change in comparison.changes]) for figure in TABLE_FIGURES]
             for side in ("before", "after")}
    lines.append(f"| mean of the {len(comparison.changes)} pairs | | " + " | ".join(
        f"{_mean(figure, before)} → {_mean(figure, after)}"
        for figure, before, after in zip(TABLE_FIGURES, means["before"], means["after"]))
        + " | |")
    lines.append("")
    lines.append(f"suite mean ({', '.join(RULE_RECALLS)}): {comparison.mean('before'):.4f} → "
                 f"{comparison.mean('after'):.4f}")
    for pair, figure, drop in comparison.drops_over_a_point():
        lines.append(f"- {pair}: {figure} drops by {100 * drop:.1f} points")
    for pair, added in comparison.false_closures_added():
        lines.append(f"- {pair}: {added:.0f} false closure(s) added")
    if comparison.is_check:
        for sensor, auto, default in comparison.auto_below_default():
            lines.append(f"- {sensor}: auto's recall_at_1 {auto:.3f} is more than a point "
                         f"below default's {default:.3f}")
    for label, missing in (("only before", comparison.only_before),
                           ("only after", comparison.only_after)):
        if missing:
            lines.append(f"- pairs {label}: {', '.join(missing)}")
    verdict, asks = ((f"the {comparison.suite} check", "auto may not fall more than a point "
                      "below default") if comparison.is_check
                     else ("the tuning rule", "the mean must rise"))
    lines.append(f"passes {verdict}" if comparison.passes else
                 f"does NOT pass {verdict} ({asks}, no recall may drop by more than a point, "
                 "no false closure may be added)")
    return "\n".join(lines)


def _run(out: Path) -> tuple[str | None, dict[tuple[str, str], dict]]:
    """A suite's results.json: the suite it names (None where it names none) and its per-pair
    rows by (pair, method); left out: the means and the papers' published figures printed
    beside them (no queries were evaluated for those)."""
    path = out / "results.json"
    try:
        saved = json.loads(path.read_text())
        return saved.get("suite"), {
            (row["pair"], row["method"]): row for row in saved["results"]
            if not str(row["pair"]).startswith("mean of")
            and math.isfinite(float(row.get("n_evaluated", math.nan)))}
    except FileNotFoundError:
        raise DatasetError(f"{path}: no results.json here; run `mf-lpr suite` into this "
                           "folder first") from None
    except (json.JSONDecodeError, AttributeError, KeyError, TypeError, ValueError) as error:
        raise DatasetError(f"{path}: not a suite's results.json ({error})") from None


def _same_reference(before: Path, after: Path, pair: str, method: str) -> float:
    """The share of positive queries matched to the same reference in both runs."""
    records, tolerance = [], math.inf
    for out in (before, after):
        saved = next((run for run in map(_read_json, sorted(
            (out / "pairs").glob(f"{_glob_escape(pair)}__*.json")))
            if run.get("method") == method), None)
        if saved is None:
            return math.nan
        tolerance = float(saved["summary"]["tolerance_m"])
        records.append({(record["query_index"], record["stamp"]): record
                        for record in saved["records"]})
    positives = [key for key, record in records[0].items()
                 if record["nearest_reference_m"] <= tolerance and key in records[1]]
    if not positives:
        return math.nan
    return float(np.mean([records[0][key]["reference_index"] == records[1][key]["reference_index"]
                          for key in positives]))


def _read_json(path: Path) -> dict:
    return json.loads(path.read_text())


def _nanmean(values: list[float]) -> float:
    finite = [value for value in values if math.isfinite(value)]
    return float(np.mean(finite)) if finite else math.nan


def _glob_escape(name: str) -> str:
    return "".join(f"[{char}]" if char in "[]*?" else char for char in name)


def _figure(figure: str, value: float) -> str:
    if not math.isfinite(value):
        return "–"
    return f"{value:.0f}" if figure.startswith("closures_") else f"{value:.3f}"


def _mean(figure: str, value: float) -> str:
    if not math.isfinite(value):
        return "–"
    return f"{value:.1f}" if figure.startswith("closures_") else f"{value:.3f}"
