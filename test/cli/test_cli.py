import csv
import json

import numpy as np
import pytest

from mf_lpr_ros.cli import main
from mf_lpr_ros.config import load_config, preset
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.prefilter_cache import cache_path
from mf_lpr_ros.core.search import MatchedFilterIndex
from mf_lpr_ros.sim.synthetic import route, write_kitti_sequence


@pytest.fixture(scope="module")
def traversals(tmp_path_factory, world):
    root = tmp_path_factory.mktemp("traversals")
    write_kitti_sequence(root / "first", world, route(60), seed=1)
    write_kitti_sequence(root / "second", world, route(20, lateral_offset_m=1.0, reverse=True),
                         seed=2)
    return root


def test_build_localise_evaluate_round_trip(traversals, tmp_path, capsys):
    map_path = tmp_path / "maps" / "first.mfmap"
    assert main(["build-map", str(traversals / "first"), "--out", str(map_path), "--preset",
                 "kitti",
                 "--quiet"]) == 0
    reference_map = ReferenceMap.load(map_path)
    assert 25 <= len(reference_map) <= 60
    assert not cache_path(map_path).exists()        # a small map: its spectra stay in memory
    steps = np.linalg.norm(np.diff(reference_map.planar_poses[:, :2], axis=0), axis=1)
    assert steps.min() >= 2.0

    results = tmp_path / "results.csv"
    assert main(["localise", str(map_path), str(traversals / "second"), "--out", str(results),
                 "--preset", "kitti", "--quiet"]) == 0
    rows = list(csv.DictReader(results.open()))
    assert len(rows) == 20
    errors = np.array([float(r["translation_error_m"]) for r in rows])
    assert np.median(errors) < 0.2
    assert {"ref_index", "ref_stamp", "confidence", "yaw_error_deg", "reason"} <= set(rows[0])
    # Verified as the localiser verifies: the first match to pass the other tests has no earlier
    # match to agree with, and is accepted once later ones agree with it.
    accepted = [r for r in rows if r["accepted"] == "1"]
    first_candidate = next(r for r in rows
                           if r["reason"].startswith(("accepted", "odometry consistency")))
    assert first_candidate["accepted"] == "1"
    assert first_candidate["reason"] == "accepted: confirmed by later matches"
    assert len(accepted) >= 10 and all(r["reason"].startswith("accepted") for r in accepted)
    assert max(float(r["translation_error_m"]) for r in accepted) < 1.0

    out = tmp_path / "eval.json"
    assert main(["evaluate", "--reference", str(traversals / "first"), "--query",
                 str(traversals / "second"), "--tolerance", "3", "--preset", "kitti", "--json",
                 str(out), "--quiet"]) == 0
    report = json.loads(out.read_text())
    for key in ("recall_at_1", "recall_at_1_corrected", "recall_at_5", "rte_mean_m", "rre_mean_deg",
                "success_rate", "f1_max", "n_queries", "ms_per_query", "ms_descriptor", "ms_global",
                "ms_local"):
        assert key in report
    assert report["n_queries"] == 20 and report["recall_at_1_corrected"] >= 0.95
    assert main(["info", str(map_path)]) == 0
    assert '"references"' in capsys.readouterr().out


def test_build_map_writes_the_prefilter_cache_a_large_map_starts_from(traversals, tmp_path,
                                                                       capsys):
    """A map whose search reads its spectra on demand (here forced: one above 50,000
    references gets it by default) is saved with its prefilter's features beside it, so the
    localiser's first start loads them."""
    config = tmp_path / "on_demand.yaml"
    config.write_text("search:\n  reference_spectra: on_demand\n")
    map_path = tmp_path / "large.mfmap"
    assert main(["build-map", str(traversals / "first"), "--out", str(map_path), "--preset",
                 "kitti", "--config", str(config), "--quiet"]) == 0
    assert f"prefilter features of {map_path}: no cache at" in capsys.readouterr().out
    search = load_config(config, preset("kitti")).search
    index = MatchedFilterIndex(ReferenceMap.load(map_path), search)
    assert index.prefilter_cache_status.startswith("loaded from")


def test_single_sequence_protocol_excludes_recent_frames(traversals, tmp_path):
    out = tmp_path / "loop.json"
    # One lap of 4 m steps: with 50 frames excluded only the closing frames can revisit the start.
    assert main(["evaluate", "--reference", str(traversals / "first"), "--tolerance", "5",
                 "--exclude-recent-frames", "50", "--preset", "kitti", "--json", str(out),
                 "--quiet"]) == 0
    report = json.loads(out.read_text())
    assert 0 < report["n_queries"] < 10 and report["n_evaluated"] == 9
    assert report["recall_at_1_corrected"] == 1.0


def test_errors_are_reported_not_raised(tmp_path, capsys):
    bad = tmp_path / "bad.mfmap"
    bad.write_bytes(b"garbage")
    assert main(["info", str(bad)]) == 2
    assert "truncated map file" in capsys.readouterr().err
    assert main(["build-map", str(tmp_path), "--out", str(tmp_path / "m.mfmap")]) == 2
    assert "unknown dataset layout" in capsys.readouterr().err
    # Refused before a world is simulated: nothing is written.
    assert main(["demo", "--out", str(tmp_path / "demo"), "--rate", "0"]) == 2
    assert "--rate must be > 0, got 0.0" in capsys.readouterr().err
    assert not (tmp_path / "demo").exists()


def test_icp_refinement_needs_clouds_and_tightens_poses(traversals, tmp_path, capsys):
    plain, with_clouds = tmp_path / "plain.mfmap", tmp_path / "clouds.mfmap"
    assert main(["build-map", str(traversals / "first"), "--out", str(plain), "--preset", "kitti",
                 "--quiet"]) == 0
    assert main(["localise", str(plain), str(traversals / "second"), "--out",
                 str(tmp_path / "x.csv"), "--icp", "--quiet"]) == 2
    assert "--keep-clouds" in capsys.readouterr().err
    assert main(["build-map", str(traversals / "first"), "--out", str(with_clouds), "--preset",
                 "kitti", "--keep-clouds", "--quiet"]) == 0
    errors = {}
    for name, extra in (("mf", []), ("icp", ["--icp"])):
        out = tmp_path / f"{name}.csv"
        assert main(["localise", str(with_clouds), str(traversals / "second"), "--out", str(out),
                     "--preset", "kitti", "--quiet", *extra]) == 0
        rows = csv.DictReader(out.open())
        errors[name] = np.array([float(r["translation_error_m"]) for r in rows])
    assert np.median(errors["icp"]) < 0.05
    assert np.median(errors["icp"]) <= np.median(errors["mf"])


def test_compare_runs_both_methods_on_one_protocol(traversals, tmp_path, capsys):
    out = tmp_path / "compare.json"
    assert main(["compare", "--reference", str(traversals / "first"), "--query",
                 str(traversals / "second"), "--tolerance", "3", "--preset", "kitti", "--json",
                 str(out), "--quiet"]) == 0
    results = json.loads(out.read_text())["results"]
    ours, baseline = results["MF-LPR (ours)"], results["Scan Context"]
    assert ours["n_queries"] == baseline["n_queries"] == 20
    assert ours["n_references"] == baseline["n_references"]
    # Day 2 drives the route backwards 1 m aside: Scan Context finds most places, and
    # its yaw comes from the column shift (within a 6 degree sector).
    assert baseline["recall_at_1"] >= 0.5           # a random pick among ~30 refs: ~0.1
    assert baseline["rre_mean_deg"] < 6.0
    assert ours["recall_at_1_corrected"] >= baseline["recall_at_1_corrected"]
    table = capsys.readouterr().out
    assert "| MF-LPR (ours) |" in table and "| Scan Context |" in table


def test_progress_is_one_line_per_loop_in_a_log_and_a_bar_on_request(traversals, tmp_path,
                                                                       capsys, monkeypatch):
    # pytest's captured stderr is not a terminal: what a log file or CI sees.
    assert main(["build-map", str(traversals / "first"), "--out", str(tmp_path / "a.mfmap"),
                 "--preset", "kitti"]) == 0
    logged = capsys.readouterr().err
    assert "\r" not in logged
    lines = [line for line in logged.splitlines() if line.startswith("build map: ")]
    references = len(ReferenceMap.load(tmp_path / "a.mfmap"))
    assert lines == [lines[0]] and lines[0].startswith(f"build map: {references} scan in ")
    monkeypatch.setenv("MF_LPR_PROGRESS", "bar")
    assert main(["build-map", str(traversals / "first"), "--out", str(tmp_path / "b.mfmap"),
                 "--preset", "kitti"]) == 0
    assert "\r" in capsys.readouterr().err
    monkeypatch.delenv("MF_LPR_PROGRESS")
    assert main(["build-map", str(traversals / "first"), "--out", str(tmp_path / "c.mfmap"),
                 "--preset", "kitti", "--quiet"]) == 0
    assert capsys.readouterr().err == ""


def test_preset_auto_builds_localises_and_evaluates(traversals, tmp_path, capsys):
    map_path = tmp_path / "auto.mfmap"
    assert main(["build-map", str(traversals / "first"), "--out", str(map_path), "--preset",
                 "auto", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "preset auto on" in printed and "ground 1.7" in printed
    reference_map = ReferenceMap.load(map_path)
    assert reference_map.metadata["auto"]["choice"] in printed
    results = tmp_path / "auto.csv"
    assert main(["localise", str(map_path), str(traversals / "second"), "--out", str(results),
                 "--preset", "auto", "--quiet"]) == 0
    errors = np.array([float(r["translation_error_m"]) for r in csv.DictReader(results.open())])
    assert np.median(errors) < 0.3
    out = tmp_path / "auto.json"
    assert main(["evaluate", "--reference", str(traversals / "first"), "--query",
                 str(traversals / "second"), "--tolerance", "3", "--preset", "auto", "--json",
                 str(out), "--quiet"]) == 0
    report = json.loads(out.read_text())
    assert report["auto"]["sensor_profile"]["ground_below_sensor_m"] > 1.5
    assert report["recall_at_1_corrected"] >= 0.9


def test_build_map_and_localise_warn_when_a_sparse_sensor_is_described_one_scan_at_a_time(
        world, tmp_path, capsys):
    # 97 % of the returns dropped: a sparse sensor's scans, which the preset describes singly.
    write_kitti_sequence(tmp_path / "sparse", world, route(20), seed=4, dropout=0.97)
    assert main(["build-map", str(tmp_path / "sparse"), "--out", str(tmp_path / "s.mfmap"),
                 "--preset", "default", "--quiet"]) == 0
    assert "warning: these scans look sparse" in capsys.readouterr().err
    assert main(["localise", str(tmp_path / "s.mfmap"), str(tmp_path / "sparse"), "--out",
                 str(tmp_path / "s.csv"), "--quiet"]) == 0
    assert "warning: map built where these scans look sparse" in capsys.readouterr().err
    assert main(["build-map", str(tmp_path / "sparse"), "--out", str(tmp_path / "l.mfmap"),
                 "--preset", "livox", "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err
