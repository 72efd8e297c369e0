"""The self-contained demo: a generated world, two traversals, a map, relocalisation, a figure."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .config import Config, DescriptorParams, SearchParams
from .datasets import KittiSequence
from .map_store import ReferenceMap
from .pipeline import build_map, localise_sequence
from .synthetic import make_world, route, write_kitti_sequence

ACCEPT_CONFIDENCE = 0.2
CORRECT_WITHIN_M = 3.0


def demo_config() -> Config:
    return Config(DescriptorParams(voxel_size=0.4, z_min=-1.2, z_max=8.0), SearchParams(),
                  spacing_m=2.0)


def run_demo(out: Path, seed: int = 7, n_scans: int = 120, progress: bool = True) -> int:
    """Build a map from traversal 1, relocalise traversal 2 (offset 1.5 m, reversed), report."""
    out.mkdir(parents=True, exist_ok=True)
    world = make_world(seed)
    first, second = out / "traversal_1", out / "traversal_2"
    if not (first / "poses.txt").exists():
        write_kitti_sequence(first, world, route(n_scans), seed + 1)
    if not (second / "poses.txt").exists():
        write_kitti_sequence(second, world, route(n_scans // 2, lateral_offset_m=1.5, reverse=True),
                             seed + 2)
    config = demo_config()
    map_path = out / "demo.mfmap"
    build_map(KittiSequence(first), config, progress=progress).save(map_path)
    reference_map = ReferenceMap.load(map_path)
    outcomes = localise_sequence(reference_map, KittiSequence(second), config.search,
                                 progress=progress)
    errors = np.array([o.translation_error_m for o in outcomes])
    yaw_errors = np.array([o.yaw_error_deg for o in outcomes])
    accepted = np.array([o.match.confidence >= ACCEPT_CONFIDENCE for o in outcomes])
    correct = errors <= CORRECT_WITHIN_M
    latency = np.array([o.descriptor_ms + o.match.timings_ms["global"] + o.match.timings_ms["local"]
                        for o in outcomes])
    print(f"\nmap: {len(reference_map)} references -> {map_path}")
    print(f"{'queries':>28}: {len(outcomes)}")
    print(f"{'recall@1 (pose within 3 m)':>28}: {correct.mean():.3f}")
    print(f"{'median translation error':>28}: {np.median(errors[correct]):.3f} m")
    print(f"{'median yaw error':>28}: {np.median(yaw_errors[correct]):.3f} deg")
    print(f"{'accepted (confidence >= 0.2)':>28}: {accepted.mean():.3f}")
    print(f"{'median latency per scan':>28}: {np.median(latency):.1f} ms")
    figure = out / "demo.png"
    _plot(figure, reference_map, outcomes, correct)
    print(f"figure: {figure}")
    return 0


def _plot(path: Path, reference_map: ReferenceMap, outcomes, correct: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    refs = reference_map.planar_poses
    truth = np.array([o.truth for o in outcomes])
    estimate = np.array([o.match.pose for o in outcomes])
    fig, ax = plt.subplots(figsize=(7, 7))
    ax.plot(refs[:, 0], refs[:, 1], ".", color="0.6", label="map references")
    ax.plot(truth[:, 0], truth[:, 1], "-", color="tab:blue", lw=1, label="query ground truth")
    ax.scatter(estimate[correct, 0], estimate[correct, 1], s=14, color="tab:green",
               label="estimate (within 3 m)")
    ax.scatter(estimate[~correct, 0], estimate[~correct, 1], s=14, color="tab:red",
               label="estimate (wrong)")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="upper right")
    ax.set_title("mf_lpr_ros demo: relocalising traversal 2 in the map of traversal 1")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
