"""Offline localisation (`mf-lpr localise`): every scan is a relocalisation request."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

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
    open field, a preset's band above everything it sees) stops a batch: the error says which."""
    write_kitti_sequence(tmp_path / "first", world, route(12), seed=1)
    banded = dataclasses.replace(preset("default").descriptor, z_min=40.0, z_max=50.0)
    scan = next(open_source(tmp_path / "first").iter_scans([5]))
    with pytest.raises(InvalidCloudError, match=rf"scan 5 \(stamp {scan.stamp:.3f} s\): no finite"):
        describe_scan(scan, banded, reference=False)
