"""Loop-closure recall and pose accuracy on the real tuning sets (../shared/data).

Queries are subsampled to keep the suite fast; the closing notes give full-run numbers.
Thresholds sit a little under what this implementation measured, so a regression fails.
"""


from mf_lpr_ros.config import preset
from mf_lpr_ros.datasets import open_source
from mf_lpr_ros.evaluation.protocol import evaluate


def test_kitti00_bev_loop_closure(data_dir):
    report = evaluate(open_source(data_dir / "kitti_bev/00"), preset("kitti"), 5.0,
                      exclude_recent_frames=100, query_every=20, progress=False)
    # Measured: 42 positives, recall@1 0.976 (0.952 before nearest-place re-ranking),
    # corrected 1.0, RTE 0.27 m, RRE 0.34 deg.
    assert report["n_queries"] >= 40
    assert report["recall_at_1"] >= 0.95
    assert report["recall_at_1_corrected"] >= 0.95
    assert report["rte_mean_m"] < 0.35
    assert report["rre_mean_deg"] < 1.0


def test_kitti00_rotated_queries(data_dir):
    """Queries from 00_rot (each image turned by a random angle) against references from 00."""
    report = evaluate(open_source(data_dir / "kitti_bev/00"), preset("kitti"), 5.0,
                      query=open_source(data_dir / "kitti_bev/00_rot"), exclude_recent_frames=100,
                      query_every=40, progress=False)
    # Measured: 22 positives, recall@1 1.0 (0.818 with the square crop and no re-ranking),
    # corrected 1.0 (RRE is meaningless here: the images' rotations are unknown).
    assert report["n_queries"] >= 20
    assert report["recall_at_1"] >= 0.9
    assert report["recall_at_1_corrected"] >= 0.95


def test_balm_handheld_loop_closure(data_dir):
    report = evaluate(open_source(data_dir / "balm_realworld"), preset("handheld"), 3.0,
                      exclude_recent_frames=50, progress=False)
    # Measured: 7 positives, corrected recall@1 1.0, RTE 0.06 m, RRE 0.06 deg; retrieval recall
    # 0.571: with references 1 m apart the best-scoring one is often not the nearest (re-ranking,
    # which reported the nearest, is off by default since it lost 5.5 points on held-out KITTI
    # 02; docs/RESULTS.md). The pose, which is what a user gets, is within 3 m on all 7.
    assert report["n_queries"] == 7
    assert report["recall_at_1"] >= 0.5
    assert report["recall_at_1_corrected"] >= 0.85
    assert report["rte_mean_m"] < 0.2
    assert report["rre_mean_deg"] < 1.0


def test_levelling_is_what_makes_handheld_work(data_dir):
    from dataclasses import replace

    config = preset("handheld")
    tilted = replace(config, descriptor=replace(config.descriptor, level=False))
    report = evaluate(open_source(data_dir / "balm_realworld"), tilted, 3.0,
                      exclude_recent_frames=50, progress=False)
    # Measured: 4 of 7 without levelling (all 7 with it, test above); pose errors grow too.
    assert report["recall_at_1_corrected"] <= 0.75
