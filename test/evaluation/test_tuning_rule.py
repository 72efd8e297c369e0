"""The tuning rule over two suite runs: mean rises, no pair drops a point, no false closure."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from mf_lpr_ros.cli import main
from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.evaluation.tuning_rule import compare_runs, format_comparison

METHOD = "MF-LPR (ours)"


def _run(out: Path, figures: dict[str, tuple[float, float, float, int]],
         matched: dict[str, list[int]] | None = None, suite: str | None = None) -> Path:
    """A suite output folder: per pair (recall@1, corrected, recall published, false closures)
    and, optionally, the references its queries matched (query k lies 1 m from a reference,
    except the last, 9 m away: not a positive at 5 m)."""
    (out / "pairs").mkdir(parents=True)
    rows = [{"pair": pair, "method": METHOD, "n_queries": 10, "n_evaluated": 12, "recall_at_1": r1,
             "recall_at_1_corrected": corrected, "recall_published": published,
             "closures_published": 8, "closures_false": false}
            for pair, (r1, corrected, published, false) in figures.items()]
    # What the suite adds after the pairs: a paper's published figure and the means.
    rows.append({"pair": next(iter(figures)), "method": "BEVPlace (published)",
                 "n_evaluated": math.nan, "recall_at_1": 0.0})
    rows.append({"pair": f"mean of {len(rows)} pairs", "method": METHOD, "n_evaluated": 12,
                 "recall_at_1": 0.0})
    (out / "results.json").write_text(json.dumps({
        "results": rows, **({"suite": suite} if suite else {})}))
    for pair, references in (matched or {}).items():
        records = [{"query_index": k, "stamp": float(k), "reference_index": reference,
                    "nearest_reference_m": 9.0 if k == len(references) - 1 else 1.0}
                   for k, reference in enumerate(references)]
        (out / "pairs" / f"{pair}__mf-lpr.json").write_text(
            json.dumps({"method": METHOD, "summary": {"tolerance_m": 5.0}, "records": records}))
    return out


def test_a_change_that_raises_the_mean_without_drops_passes(tmp_path):
    before = _run(tmp_path / "before", {"a": (0.90, 0.95, 0.50, 0), "b [x]": (0.80, 0.85, 0.3, 0)},
                  {"b [x]": [1, 2, 3, 4]})
    after = _run(tmp_path / "after", {"a": (0.92, 0.95, 0.55, 0), "b [x]": (0.795, 0.85, 0.3, 0)},
                 {"b [x]": [1, 2, 9, 7]})
    comparison = compare_runs(before, after)
    assert comparison.passes
    assert comparison.mean("after") > comparison.mean("before")
    by_pair = {change.pair: change for change in comparison.changes}
    # Queries 0-2 are positives (the last lies 9 m from every reference): 2 of 3 kept theirs.
    assert by_pair["b [x]"].same_reference == pytest.approx(2 / 3)
    assert by_pair["a"].drop("recall_at_1") == pytest.approx(-0.02)
    table = format_comparison(comparison)
    assert "| a | 10 | 0.900 → 0.920 |" in table and "passes the tuning rule" in table
    assert [change.method for change in comparison.changes] == [METHOD, METHOD]


@pytest.mark.parametrize("after_b, why", [
    ((0.78, 0.85, 0.30, 0), "b: recall_at_1 drops by 2.0 points"),
    ((0.80, 0.85, 0.30, 1), "b: 1 false closure(s) added"),
])
def test_a_rising_mean_does_not_excuse_a_drop_or_a_false_closure(tmp_path, after_b, why):
    before = _run(tmp_path / "before", {"a": (0.50, 0.50, 0.50, 0), "b": (0.80, 0.85, 0.30, 0)})
    after = _run(tmp_path / "after", {"a": (0.90, 0.90, 0.90, 0), "b": after_b})
    comparison = compare_runs(before, after)
    assert comparison.mean("after") > comparison.mean("before")
    assert not comparison.passes
    assert why in format_comparison(comparison)


def test_an_unchanged_suite_does_not_pass_and_missing_pairs_are_named(tmp_path):
    figures = {"a": (0.9, 0.9, 0.5, 0)}
    assert not compare_runs(_run(tmp_path / "same1", figures),
                            _run(tmp_path / "same2", figures)).passes
    comparison = compare_runs(_run(tmp_path / "before", figures),
                              _run(tmp_path / "after", {**figures, "new": (1.0, 1.0, 1.0, 0)}))
    assert comparison.only_after == [f"new ({METHOD})"] and not comparison.passes


def test_the_command_checks_and_names_a_folder_that_is_not_a_run(tmp_path, capsys):
    before = _run(tmp_path / "before", {"a": (0.9, 0.9, 0.5, 0)})
    worse = _run(tmp_path / "worse", {"a": (0.8, 0.9, 0.5, 0)})
    assert main(["suite-diff", str(before), str(worse)]) == 0
    assert main(["suite-diff", str(before), str(worse), "--check"]) == 1
    assert "does NOT pass" in capsys.readouterr().out
    assert main(["suite-diff", str(before), str(tmp_path)]) == 2
    assert "no results.json" in capsys.readouterr().err
    with pytest.raises(DatasetError, match="not a suite's results.json"):
        (tmp_path / "broken").mkdir()
        (tmp_path / "broken" / "results.json").write_text("{")
        compare_runs(before, tmp_path / "broken")


SENSOR_RUN = {"town [auto]": (0.99, 0.99, 0.95, 0), "town [default]": (0.99, 0.99, 0.95, 0),
              "forest [auto]": (0.985, 0.985, 0.9, 0), "forest [default]": (0.985, 0.985, 0.9, 0)}


def test_a_check_suite_needs_no_rising_mean_but_auto_within_a_point_of_default(tmp_path):
    before = _run(tmp_path / "before", SENSOR_RUN, suite="sensors")
    unchanged = compare_runs(before, _run(tmp_path / "same", SENSOR_RUN, suite="sensors"))
    assert unchanged.is_check and unchanged.passes
    assert "passes the sensors check" in format_comparison(unchanged)
    # The tuning suite's own rule asks for a rising mean.
    assert not compare_runs(_run(tmp_path / "t1", SENSOR_RUN, suite="tuning"),
                            _run(tmp_path / "t2", SENSOR_RUN, suite="tuning")).passes
    # In the forest default rises and auto stays: half a point behind passes, 1.5 does not.
    behind = compare_runs(before, _run(tmp_path / "behind", {
        **SENSOR_RUN, "forest [default]": (0.99, 0.99, 0.9, 0)}, suite="sensors"))
    assert behind.passes, "auto half a point below default is within a point"
    below = compare_runs(before, _run(tmp_path / "below", {
        **SENSOR_RUN, "forest [default]": (1.0, 1.0, 0.9, 0)}, suite="sensors"))
    assert below.auto_below_default() == [("forest", 0.985, 1.0)]
    assert not below.passes and not below.drops_over_a_point()
    assert "- forest: auto's recall_at_1 0.985 is more than a point below default's 1.000" \
        in format_comparison(below)


def test_a_check_suite_fails_on_a_drop_and_runs_of_two_suites_are_refused(tmp_path):
    before = _run(tmp_path / "before", SENSOR_RUN, suite="sensors")
    dropped = compare_runs(before, _run(tmp_path / "dropped", {
        **SENSOR_RUN, "town [default]": (0.99, 0.99, 0.90, 0)}, suite="sensors"))
    assert not dropped.passes
    table = format_comparison(dropped)
    assert "town [default]: recall_published drops by 5.0 points" in table
    assert "does NOT pass the sensors check" in table
    with pytest.raises(DatasetError, match="different suites .sensors and tuning."):
        compare_runs(before, _run(tmp_path / "tuning", SENSOR_RUN, suite="tuning"))
