"""Offline localisation (`mf-lpr localise`): every scan is a relocalisation request."""

from __future__ import annotations

import csv
import dataclasses

import numpy as np
import pytest

from mf_lpr_ros.cli import main
from mf_lpr_ros.config import preset
from mf_lpr_ros.core import search
from mf_lpr_ros.datasets import open_source
from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.pipeline import localise
from mf_lpr_ros.pipeline.mapping import build_map, describe_scan
from mf_lpr_ros.sim.synthetic import route, write_kitti_sequence


def test_every_scan_is_searched_as_a_request(world, tmp_path, monkeypatch):
    """The candidate stage made to leave every place out (the prefilter ranks in reverse, one
    candidate searched): each scan's weak match is searched again over the wider list, and the
    scans are localised."""
    write_kitti_sequence(tmp_path / "first", world, route(40), seed=1)
    write_kitti_sequence(tmp_path / "second", world, route(6, lateral_offset_m=1.0), seed=2)
    config = preset("kitti")
    reference_map = build_map(open_source(tmp_path / "first"), config, progress=False)
    requests = []

    class ReversedPrefilterIndex(search.MatchedFilterIndex):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            ranking = self.prefilter.top
            self.prefilter.top = lambda image, k, stop=None: ranking(
                image, len(self.prefilter), stop)[::-1][:k]

        def query(self, occupancy, n_active=None, **options):
            requests.append(options.get("request", False))
            return super().query(occupancy, n_active, **options)

    monkeypatch.setattr(localise, "MatchedFilterIndex", ReversedPrefilterIndex)
    narrow = dataclasses.replace(config.search, prefilter_top_k=1, prefilter_expand_m=0.0)
    outcomes = localise.localise_sequence(reference_map, open_source(tmp_path / "second"),
                                          narrow, progress=False)
    assert requests == [True] * 6
    errors = [outcome.translation_error_m for outcome in outcomes]
    assert np.median(errors) < 0.3, errors
    assert all(outcome.match.searched is None for outcome in outcomes)


def test_a_scan_with_nothing_to_describe_is_named_in_the_error(world, tmp_path):
    """A scan with no point inside the descriptor's window and height band (a sensor facing an
    open field, a preset's band above everything it sees): an error that says which (building a
    map stops at it)."""
    write_kitti_sequence(tmp_path / "first", world, route(12), seed=1)
    banded = dataclasses.replace(preset("default").descriptor, z_min=40.0, z_max=50.0)
    scan = next(open_source(tmp_path / "first").iter_scans([5]))
    with pytest.raises(InvalidCloudError, match=rf"scan 5 \(stamp {scan.stamp:.3f} s\): no finite"):
        describe_scan(scan, banded, reference=False)


def test_localise_passes_over_a_scan_it_cannot_describe_and_says_why(world, tmp_path, capsys):
    """As the live localiser does: the scans after it are still localised, and the CSV row of
    the one passed over has no match and the reason."""
    write_kitti_sequence(tmp_path / "first", world, route(40), seed=1)
    write_kitti_sequence(tmp_path / "second", world, route(6, lateral_offset_m=1.0), seed=2)
    far = np.zeros((50, 4), dtype="<f4")
    far[:, 0] = 500.0                                 # every return beyond the window
    far.tofile(tmp_path / "second" / "velodyne" / "000002.bin")
    config = preset("kitti")
    reference_map = build_map(open_source(tmp_path / "first"), config, progress=False)
    outcomes = localise.localise_sequence(reference_map, open_source(tmp_path / "second"),
                                          config.search, progress=False)
    assert [outcome.match is None for outcome in outcomes] == [False] * 2 + [True] + [False] * 3
    assert outcomes[2].verdict.reason.startswith("not described: scan 2 ")
    assert np.isnan(outcomes[2].translation_error_m)
    assert np.nanmedian([outcome.translation_error_m for outcome in outcomes]) < 0.3

    reference_map.save(tmp_path / "map.mfmap")
    assert main(["localise", str(tmp_path / "map.mfmap"), str(tmp_path / "second"), "--preset",
                 "kitti", "--out", str(tmp_path / "run.csv"), "--quiet"]) == 0
    assert "; 1 passed over with nothing to describe" in capsys.readouterr().out
    rows = list(csv.DictReader(open(tmp_path / "run.csv")))
    assert len(rows) == 6 and rows[2]["ref_index"] == "" and rows[2]["accepted"] == "0"
    assert rows[2]["reason"].startswith("not described") and rows[3]["ref_index"] != ""
