"""The demo: simulated worlds through the nodes over DDS (mf-lpr demo)."""

import pytest

from mf_lpr_ros.cli import main
from mf_lpr_ros.core.map_store import ReferenceMap


@pytest.mark.slow
@pytest.mark.realtime
def test_reduced_demo_runs_end_to_end(tmp_path, capsys):
    """The three simulated worlds, every 5th scan, through map_builder and the localiser over
    DDS, day 2 replayed at twice the sensor's rate."""
    assert main(["demo", "--out", str(tmp_path), "--stride", "5", "--rate", "2", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "recall@1" in printed and "unseen scans searched and rejected" in printed
    assert "at 20 Hz" in printed
    assert (tmp_path / "demo.png").stat().st_size > 50_000
    for world in ("urban", "forest", "sparse"):
        assert len(ReferenceMap.load(tmp_path / world / "map.mfmap")) > 10
        assert (tmp_path / world / "day1" / "metadata.yaml").exists()
    # The sparse sensor's map was built by preset auto, which chose submaps for it.
    assert ReferenceMap.load(tmp_path / "sparse" / "map.mfmap").params.submap_m > 0
    # Measured among the scans searched: how many the newest-only policy drops depends on the
    # machine's speed, not on the method.
    row = next(line for line in printed.splitlines() if line.startswith("| recall@1 among"))
    assert all(float(value) >= 0.8 for value in row.split("|")[2:4])
    row = next(line for line in printed.splitlines() if line.startswith("| unseen scans search"))
    assert all(float(value) >= 0.95 for value in row.split("|")[2:4])
