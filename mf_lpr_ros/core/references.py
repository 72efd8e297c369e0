"""How scans become a map's references: the one path every map is built by.

Offline maps (pipeline.mapping.build_map), maps described in parallel (pipeline.bulk), the live
map builder (live.map_builder.MapBuilder) and the evaluation's MF-LPR method all use these:
SpacingGate keeps one scan per spacing_m of travel, descriptor_points levels a scan when the
descriptor asks for it, describe_observation turns points or a density image into occupancy,
and add_references appends described scans and records their common sensor offset. A scan
that could not be described is passed over, and the map's metadata says so (PassedOver).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from mf_lpr_ros.core.descriptor import describe_density_image, describe_points, stamp_seed_key
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import level_points
from mf_lpr_ros.errors import InvalidCloudError, InvalidPoseError
from mf_lpr_ros.params import DescriptorParams, SearchParams


class SpacingGate:
    """Admits a position when it lies at least spacing_m from the last one marked."""

    def __init__(self, spacing_m: float, last_position: np.ndarray | None = None) -> None:
        self.spacing_m = spacing_m
        self.last_position = last_position

    def far_enough(self, position: np.ndarray) -> bool:
        return self.last_position is None or \
            float(np.linalg.norm(position - self.last_position)) >= self.spacing_m

    def mark(self, position: np.ndarray) -> None:
        self.last_position = np.asarray(position)


def select_references(positions: np.ndarray, spacing_m: float,
                      valid: np.ndarray | None = None) -> np.ndarray:
    """Indices of scans kept as references: the first, then each one at least spacing_m from the
    last one kept."""
    valid = np.ones(len(positions), dtype=bool) if valid is None else valid
    gate = SpacingGate(spacing_m)
    kept = []
    for index in np.flatnonzero(valid):
        if gate.far_enough(positions[index]):
            gate.mark(positions[index])
            kept.append(int(index))
    return np.asarray(kept, dtype=np.int64)


def descriptor_points(points: np.ndarray, pose: np.ndarray | None,
                      params: DescriptorParams) -> np.ndarray:
    """Points in the descriptor's frame: levelled by the pose's roll and pitch when params.level."""
    if not params.level:
        return points
    if pose is None or not np.isfinite(pose).all():
        raise InvalidPoseError("descriptor.level needs each scan's orientation; no pose is known "
                               "for this scan (give the scans poses, or set a pose source)")
    return level_points(points, pose[:3, :3])


def keeps_clouds(search: SearchParams, asked: bool) -> bool:
    """Whether a new map keeps its references' clouds: when asked, and whenever its
    verification needs them (search.verify_fitness > 0: ICP against the reference's cloud)."""
    return asked or search.verify_fitness > 0


def describe_observation(params: DescriptorParams, *, reference: bool, stamp: float,
                         points: np.ndarray | None = None, density: np.ndarray | None = None,
                         density_pixel_m: float | None = None) -> np.ndarray:
    """Occupancy of a scan from its points (already in the descriptor's frame) or its ready
    density image; stamp seeds a reference's patch cap."""
    if density is not None:
        return describe_density_image(density, density_pixel_m, params, reference=reference,
                                      seed_key=stamp_seed_key(stamp))
    return describe_points(points, params, reference=reference, seed_key=stamp_seed_key(stamp))


@dataclass
class DescribedScan:
    """A scan's occupancy with what the map stores beside it."""

    occupancy: np.ndarray
    pose: np.ndarray
    stamp: float
    source_index: int
    cloud: np.ndarray | None = None
    sensor_offset_m: float = 0.0


def add_references(reference_map: ReferenceMap, described: Iterable[DescribedScan]) -> int | None:
    """Append described scans as references; the last index added (None when none were).
    Their sensor offset must be the one the map already records (see record_sensor_offset)."""
    offsets = {reference_map.metadata.get("sensor_offset_m", 0.0)} if len(reference_map) else set()
    last = None
    for scan in described:
        last = reference_map.append(scan.occupancy, scan.pose, scan.stamp, scan.source_index,
                                    scan.cloud)
        offsets.add(scan.sensor_offset_m)
    record_sensor_offset(reference_map, offsets)
    return last


def record_sensor_offset(reference_map: ReferenceMap, offsets: set[float]) -> None:
    """Store the references' common sensor offset in the map (the search reads it)."""
    if len(offsets) > 1:
        raise ValueError(f"the references mix sensor offsets {sorted(offsets)} (density images "
                         f"of different layouts); build one map per layout")
    offset = offsets.pop() if offsets else 0.0
    if offset:
        reference_map.metadata["sensor_offset_m"] = offset


@dataclass(frozen=True)
class PassedOver:
    """A scan a map's build passed over, and why: nothing inside the descriptor's window and
    height band, a file or message that could not be read, or (the map builder node) a message
    it rejected."""

    index: int
    stamp: float
    why: str

    def to_dict(self) -> dict:
        return {"scan": self.index, "stamp": self.stamp, "why": self.why}


# Where a map's metadata notes the scans its build passed over, and how many it lists by name
# (the count covers them all).
PASSED_OVER_KEY = "scans_passed_over"
PASSED_OVER_LISTED = 20


def note_passed_over(reference_map: ReferenceMap, passed_over: list[PassedOver],
                     source: str) -> None:
    """Notes in the map's metadata the scans of source its build passed over: all in the
    count, the first PASSED_OVER_LISTED by name."""
    if not passed_over:
        return
    noted = reference_map.metadata.setdefault(PASSED_OVER_KEY, {"count": 0, "scans": []})
    noted["count"] += len(passed_over)
    room = max(PASSED_OVER_LISTED - len(noted["scans"]), 0)
    noted["scans"] += [dict(scan.to_dict(), source=source) for scan in passed_over[:room]]


def record_passed_over(reference_map: ReferenceMap, passed_over: list[PassedOver], added: int,
                       source: str) -> None:
    """note_passed_over for an offline build that added `added` references from source; a
    source none of whose references could be described is refused, naming the first scan's
    problem."""
    if passed_over and not added:
        raise InvalidCloudError(f"{source}: no reference could be described; "
                                f"{len(passed_over)} scan(s) had nothing to describe, the "
                                f"first: {passed_over[0].why}")
    note_passed_over(reference_map, passed_over, source)


def passed_over_summary(metadata: dict) -> str | None:
    """One line for a map's builder: how many scans it passed over and the first one's problem
    (None when it passed over none)."""
    noted = metadata.get(PASSED_OVER_KEY)
    if not noted:
        return None
    return (f"passed over {noted['count']} scan(s) with nothing to describe (a reference's "
            f"taken from the next scan that has something; the map's metadata lists them); "
            f"the first: {noted['scans'][0]['why']}")
