"""preset "auto": descriptor parameters derived from the scans themselves.

A few scans are measured (SensorProfile) and the descriptor follows from rules, each stated
where it is applied (auto_descriptor). A dense 360-degree sensor keeps the given (default)
voxel and height band, and only its levelling is decided: on the tuning suite the voxel rule
and the ground floor below lost to the defaults on every such sensor (the simulated town:
recall@1 0.992 against 1.000, recall published 0.888 against 0.954; BALM 0.667 against 1.000
published; docs/RESULTS.md, session 27), as on a dense 64-beam handheld set we do not have
(0.704 against 1.000). A sparse or narrow sensor, which needs submaps, gets all of them:
- voxel size: the paper's inverse-linear rule on occupied 1 m voxels per scan
  (core.descriptor.voxel_size_for_density), no smaller than lets the window hold the nearer
  WINDOW_HOLDS_PERCENT % of the returns and no larger than lets it reach past 95 % of them.
  The rule's 0.3 m for any scan over ~1360 occupied voxels fits a forest's short sight lines
  but cut a town's streets to a 36 m window (simulated VLP-16: recall@1 0.654 against
  `default`'s 1.000; docs/RESULTS.md, session 17);
- height floor: the ground is found below the sensor as the densest thin layer of low points,
  and points less than GROUND_CLEARANCE_M above it are dropped, so a low mount keeps what a
  high one keeps; nothing is cut above (a ceiling at 4.5 m, KITTI's band relative to its
  ground, cost tall structure: docs/RESULTS.md, session 15);
- levelling: on when the scans' poses tilt (roll or pitch spread over 3 degrees, a handheld or
  vehicle-on-slopes sensor) and poses exist;
- submaps: a narrow sensor (field of view under FULL_CIRCLE_BELOW_DEG) or a sparse one (fewer
  than SPARSE_OCCUPIED_VOXELS occupied 1 m voxels per scan: one scan sees too little of the
  place to tell it apart) is described with the scans of its last AUTO_SUBMAP_M metres
  (core.submap); a dense 360-degree sensor keeps single scans (on the dense handheld BALM
  sequence a 3 m submap lost recall: 1.000 -> 0.714). Sparseness is read from what a scan
  covers, not from how many returns land on each surface: that count follows the integration
  time and any downsampling before us (BALM's scans give 8.4 returns per occupied voxel as
  .bin files and 5.0 as the 0.3 m bag; the real Avia keyframes 8.3, the simulated Mid-360 1.7),
  while the occupied voxels move by 3 % (1608 / 1564);
- field of view: the horizontal sector that holds points (a Livox Avia sees ~70 degrees) is
  measured, logged and recorded, but the wedge footprint is not applied: it
  (DescriptorParams.field_of_view_deg) left recall on the HKU Avia keyframes unchanged (0.714)
  and let 2 false closures through where the full footprint published none, so it stays a
  setting the user turns on (session 61, with narrow sensors' turns snapped right: on the
  HKU keyframes 97 closures published and none false, on a simulated Avia in a town 142
  false of 342).
What was measured and chosen is returned for the caller to log and to store in the map.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.descriptor import (
    FULL_CIRCLE_BELOW_DEG,
    finite_rows,
    largest_empty_run,
    occupied_unit_voxels,
    rows_where,
    voxel_size_for_density,
)
from mf_lpr_ros.core.pose import level_points
from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.params import DescriptorParams

SAMPLE_SCANS = 12
GROUND_BIN_M = 0.1
GROUND_CLEARANCE_M = 0.5
TILT_SPREAD_DEG = 3.0
AZIMUTH_BINS = 72
# Occupied 1 m voxels per scan on the tuning sets: the simulated Mid-360 851 and the Avia
# keyframes 709 (submaps help both), BALM's Ouster 1564-1608 (a 3 m submap hurts it), the
# simulated VLP-16 2674, forest 4150, KITTI 07's HDL-64 4461. The threshold is the geometric
# midpoint between the densest sensor submaps help and the sparsest they hurt.
SPARSE_OCCUPIED_VOXELS = 1150.0
# Chosen on the tuning sets: on the simulated Mid-360 world, published closures 0.17 (single
# scans) -> 0.62 (3 m), 0.56 (5 m), 0.34 (10 m, where recall@1 fell to 0.82: the window reaches
# round corners); the HKU Avia keyframes are unchanged by any window. Session 24: 10 m passed
# the tuning suite and was withdrawn on the demo's sparse world (0.987 -> 0.942, RESULTS.md).
AUTO_SUBMAP_M = 3.0
# The share of one scan's returns (by horizontal range) the descriptor window holds at least.
# Chosen on the tuning suite among the median (no change anywhere), 75 and 95.
WINDOW_HOLDS_PERCENT = 75.0


@dataclass(frozen=True)
class SensorProfile:
    """What auto measured on sample scans.

    occupied_voxels: mean occupied 1 m voxels per scan (the paper's density measure).
    ground_below_sensor_m: height of the sensor above the ground (NaN: no ground found).
    horizontal_fov_deg: width of the sector holding points; heading_deg its centre (0 = +x).
    tilt_spread_deg: spread (std) of the poses' roll and pitch (NaN without poses).
    range_p95_m: 95th percentile of horizontal point range.
    range_held_m: the horizontal range within which WINDOW_HOLDS_PERCENT % of points lie.
    """

    n_scans: int
    occupied_voxels: float
    ground_below_sensor_m: float
    horizontal_fov_deg: float
    heading_deg: float
    tilt_spread_deg: float
    range_p95_m: float
    range_held_m: float

    def to_dict(self) -> dict:
        return {key: (None if isinstance(value, float) and math.isnan(value) else value)
                for key, value in dataclasses.asdict(self).items()}


def measure_sensor(clouds: list[np.ndarray], orientations: list[np.ndarray] | None = None
                   ) -> SensorProfile:
    """A SensorProfile from sample clouds (sensor frame) and, when known, their world_R_sensor
    (used to level the points before the ground is looked for, and for the tilt spread)."""
    finite = [rows_where(xyz, finite_rows(xyz)) for xyz in (np.asarray(c)[:, :3] for c in clouds)]
    finite = [c for c in finite if len(c)]
    if not finite:
        raise InvalidCloudError("preset auto needs scans with finite points to measure")
    tilt = math.nan
    if orientations is not None and len(orientations) == len(clouds):
        tilts = np.array([_roll_pitch(r) for r in orientations])
        tilt = float(np.degrees(tilts.std(axis=0).max()))
        finite = [level_points(c, r) for c, r in zip(finite, orientations)]
    points = np.concatenate(finite)
    horizontal = np.hypot(points[:, 0], points[:, 1])
    fov, heading = _field_of_view(points[horizontal > 1.0])
    occupied = np.array([occupied_unit_voxels(c) for c in finite], dtype=np.float64)
    return SensorProfile(n_scans=len(finite),
                         occupied_voxels=float(occupied.mean()),
                         ground_below_sensor_m=_ground_depth(points, horizontal),
                         horizontal_fov_deg=fov, heading_deg=heading, tilt_spread_deg=tilt,
                         range_p95_m=float(np.percentile(horizontal, 95)),
                         range_held_m=float(np.percentile(horizontal, WINDOW_HOLDS_PERCENT)))


def auto_descriptor(profile: SensorProfile, base: DescriptorParams) -> DescriptorParams:
    """base with what the profile determines replaced (see the module doc): levelling always,
    and for a sensor that needs submaps the window, the voxel size and the height floor."""
    # The paper's rule, held between a window that holds most of what one scan sees and one
    # that reaches no farther than the sensor sees.
    holds = 2.0 * profile.range_held_m / base.size
    reach = 2.0 * profile.range_p95_m / base.size
    changes: dict = {}
    if math.isfinite(profile.tilt_spread_deg):
        changes["level"] = profile.tilt_spread_deg > TILT_SPREAD_DEG
    if needs_submaps(profile):
        changes["voxel_size"] = round(min(max(voxel_size_for_density(profile.occupied_voxels),
                                              holds), reach), 2)
        if math.isfinite(profile.ground_below_sensor_m):
            changes["z_min"] = round(GROUND_CLEARANCE_M - profile.ground_below_sensor_m, 2)
        changes["submap_m"] = AUTO_SUBMAP_M
    return dataclasses.replace(base, **changes)


def needs_submaps(profile: SensorProfile) -> bool:
    """A narrow or a sparse sensor (see the module doc)."""
    return profile.horizontal_fov_deg < FULL_CIRCLE_BELOW_DEG or is_sparse(profile)


def is_sparse(profile: SensorProfile) -> bool:
    """One scan covers fewer than SPARSE_OCCUPIED_VOXELS occupied 1 m voxels."""
    return profile.occupied_voxels < SPARSE_OCCUPIED_VOXELS


def auto_config(clouds: list[np.ndarray], base: Config,
                orientations: list[np.ndarray] | None = None) -> tuple[Config, SensorProfile]:
    """base with its descriptor derived from the clouds (no longer auto); and the profile."""
    profile = measure_sensor(clouds, orientations)
    return dataclasses.replace(base, descriptor=auto_descriptor(profile, base.descriptor),
                               auto=False), profile


def resolve_for_sequence(config: Config, sequence) -> tuple[Config, SensorProfile | None]:
    """config itself when it is not auto; else derived from SAMPLE_SCANS scans of sequence."""
    if not config.auto:
        return config, None
    clouds, orientations = profile_sequence_scans(
        sequence.iter_scans(sample_indices(len(sequence))))
    return auto_config(clouds, config, orientations)


# Where a map records its single_scan_warning (map metadata), for whatever searches it later.
SINGLE_SCAN_WARNING_KEY = "single_scan_warning"


def map_built_warning(metadata: dict) -> str | None:
    """What a search of a map should tell its user about how the map was built: the
    single_scan_warning its build recorded, if any."""
    warning = metadata.get(SINGLE_SCAN_WARNING_KEY)
    return None if warning is None else f"map built where {warning}"


def single_scan_warning(profile: SensorProfile, params: DescriptorParams) -> str | None:
    """What to tell a user whose named preset describes, one scan at a time, a sensor that auto
    gives submaps (a narrow or sparse one: one of its scans sees too little of a place to tell
    it apart; the held-out Mid-360 campus loop: recall@1 0.867 at `default`, 0.990 at `auto`);
    None when the descriptor has a submap window or the sensor needs none."""
    if params.submap_m > 0 or not needs_submaps(profile):
        return None
    narrow = profile.horizontal_fov_deg < FULL_CIRCLE_BELOW_DEG
    measured = (f"a field of view of {profile.horizontal_fov_deg:.0f} degrees" if narrow else
                f"{profile.occupied_voxels:.0f} occupied 1 m voxels a scan, under "
                f"{SPARSE_OCCUPIED_VOXELS:.0f}")
    return (f"these scans look {'narrow' if narrow else 'sparse'} ({measured}, measured on "
            f"{profile.n_scans} scans) but are described one at a time (descriptor.submap_m "
            f"0): preset auto, or livox, describes each from the scans of its last "
            f"{AUTO_SUBMAP_M:g} m of odometry, which such a sensor needs to tell places apart")


def single_scan_warning_for_sequence(config: Config, sequence) -> str | None:
    """single_scan_warning on SAMPLE_SCANS scans of sequence, for a config that is not auto and
    describes single scans (None otherwise, for sources of density images, and where the
    samples hold no finite point: the build itself says what is wrong with such scans)."""
    if config.auto or config.descriptor.submap_m > 0:
        return None
    try:
        profile = measure_sensor(*profile_sequence_scans(
            sequence.iter_scans(sample_indices(len(sequence)))))
    except InvalidCloudError:
        return None
    return single_scan_warning(profile, config.descriptor)


def map_metadata(profile: SensorProfile, params: DescriptorParams) -> dict:
    """What a map built with preset auto records about the choice."""
    return {"preset": "auto", "sensor_profile": profile.to_dict(),
            "choice": describe_choice(profile, params)}


def sample_indices(n_scans: int, count: int = SAMPLE_SCANS) -> np.ndarray:
    """count scans spread evenly over a sequence of n_scans."""
    return np.unique(np.linspace(0, n_scans - 1, min(count, n_scans)).round().astype(np.int64))


def describe_choice(profile: SensorProfile, params: DescriptorParams) -> str:
    """One line for the log: what was measured and chosen."""
    band = "unbounded below" if params.z_min is None else f"from {params.z_min} m"
    ground = (f"ground {profile.ground_below_sensor_m:.2f} m below the sensor"
              if math.isfinite(profile.ground_below_sensor_m) else "no ground found")
    narrow = (f" (under {FULL_CIRCLE_BELOW_DEG:.0f}: revisits from other headings share "
              f"no ground)" if profile.horizontal_fov_deg < FULL_CIRCLE_BELOW_DEG else "")
    measured = (f"preset auto on {profile.n_scans} scans: {profile.occupied_voxels:.0f} occupied "
                f"1 m voxels/scan, {WINDOW_HOLDS_PERCENT:.0f} % / 95 % of points within "
                f"{profile.range_held_m:.0f} / {profile.range_p95_m:.0f} m, {ground}, field of "
                f"view {profile.horizontal_fov_deg:.0f} deg{narrow}; "
                f"{'sparse' if is_sparse(profile) else 'dense'} "
                f"(under {SPARSE_OCCUPIED_VOXELS:.0f} voxels is sparse)")
    if needs_submaps(profile):
        chosen = (f"voxel {params.voxel_size:.2f} m, z {band}, level {params.level}, submaps of "
                  f"{params.submap_m:g} m")
    else:
        chosen = (f"voxel {params.voxel_size:.2f} m and z {band} as given (a dense 360-degree "
                  f"sensor), level {params.level}, single scans")
    return f"{measured} -> {chosen}"


def _ground_depth(points: np.ndarray, horizontal: np.ndarray) -> float:
    """The sensor's height above the densest thin layer among the low points nearby; NaN when
    the low points show no layer."""
    near = points[(horizontal > 1.0) & (horizontal < 30.0)]
    if len(near) < 100:
        return math.nan
    z = near[:, 2]
    low = z[z <= np.percentile(z, 50)]
    low = low[low < 0.0]
    if len(low) < 50:
        return math.nan
    edges = np.arange(low.min(), low.max() + GROUND_BIN_M, GROUND_BIN_M)
    if len(edges) < 2:
        return float(-low.mean())
    counts, edges = np.histogram(low, bins=edges)
    mode = int(np.argmax(counts))
    if counts[mode] < 0.05 * len(near):
        return math.nan
    return float(-(edges[mode] + edges[mode + 1]) / 2)


def _field_of_view(points: np.ndarray) -> tuple[float, float]:
    """(width, centre) in degrees of the smallest sector holding ~all points' azimuths."""
    if not len(points):
        return 360.0, 0.0
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0])) % 360.0
    counts, _ = np.histogram(azimuth, bins=AZIMUTH_BINS, range=(0.0, 360.0))
    seen = counts > 0.002 * len(points)
    if seen.all():
        return 360.0, 0.0
    # The largest run of empty bins (circularly) is what the sensor does not see.
    best_length, best_end = largest_empty_run(seen)
    bin_deg = 360.0 / AZIMUTH_BINS
    width = bin_deg * (AZIMUTH_BINS - best_length)
    gap_centre = (best_end + 1 - best_length / 2) * bin_deg
    # The sector seen is the complement of the gap: its centre is opposite the gap's.
    centre = (gap_centre + 180.0) % 360.0
    return width, (centre + 180.0) % 360.0 - 180.0


def _roll_pitch(orientation: np.ndarray) -> tuple[float, float]:
    orientation = np.asarray(orientation)
    pitch = math.asin(float(np.clip(-orientation[2, 0], -1.0, 1.0)))
    roll = math.atan2(float(orientation[2, 1]), float(orientation[2, 2]))
    return roll, pitch


def profile_sequence_scans(scans: Iterable) -> tuple[list[np.ndarray], list[np.ndarray] | None]:
    """Clouds and (when every scan has a finite pose) orientations of dataset Scans."""
    clouds, orientations = [], []
    for scan in scans:
        if scan.problem:
            # Nothing was read (Scan.problem): the build passes over such a scan too.
            continue
        if scan.points is None:
            raise InvalidCloudError("preset auto measures point clouds; this source gives density "
                                    "images (use a named preset, e.g. kitti)")
        clouds.append(scan.points)
        orientations.append(None if scan.pose is None or not np.isfinite(scan.pose).all()
                            else scan.pose[:3, :3])
    posed = all(o is not None for o in orientations)
    return clouds, (orientations if posed else None)
