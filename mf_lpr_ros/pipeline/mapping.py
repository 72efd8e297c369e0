"""Maps from dataset sequences: which scans become references, described as the live map
builder describes them (mf_lpr_ros.core.references), with the preset auto resolved first."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.auto_params import (
    SINGLE_SCAN_WARNING_KEY,
    map_metadata,
    resolve_for_sequence,
    single_scan_warning_for_sequence,
)
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.references import (
    DescribedScan,
    PassedOver,
    add_references,
    describe_observation,
    descriptor_points,
    keeps_clouds,
    record_passed_over,
    select_references,
)
from mf_lpr_ros.core.submap import SubmapWindow
from mf_lpr_ros.datasets import Scan, Sequence
from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.params import DescriptorParams
from mf_lpr_ros.pipeline.submaps import with_submaps
from mf_lpr_ros.progress import progress_bar

# How the reason given for a query with nothing to describe begins (`localise`, evaluation).
NOT_DESCRIBED = "not described: "


def not_described(error: InvalidCloudError) -> str:
    """The reason given for a query with nothing to describe (describe_scan's error)."""
    return f"{NOT_DESCRIBED}{error}"


def describe_scan(scan: Scan, params: DescriptorParams, *, reference: bool) -> np.ndarray:
    """Occupancy of a scan, from its points or its ready density image. A scan with nothing to
    describe (Scan.problem, or nothing finite in the window) raises InvalidCloudError naming
    it: the tools pass over it (describe_references, localise, evaluate)."""
    if scan.problem:
        raise _unreadable(scan)
    if scan.density is None and scan.points is None:
        raise ValueError(f"scan {scan.index} has neither points nor a density image")
    try:
        points = None if scan.density is not None else prepared_points(scan, params)
        return describe_observation(params, reference=reference, stamp=scan.stamp,
                                    points=points, density=scan.density,
                                    density_pixel_m=scan.density_pixel_m)
    except InvalidCloudError as error:
        raise InvalidCloudError(f"{_named(scan)}: {error}") from error


def prepared_points(scan: Scan, params: DescriptorParams) -> np.ndarray:
    """The scan's points in the descriptor's frame (levelled when params.level)."""
    if scan.problem:
        raise _unreadable(scan)
    if scan.points is None:
        raise ValueError(f"scan {scan.index} has no points")
    return descriptor_points(scan.points, scan.pose, params)


def _named(scan: Scan) -> str:
    return f"scan {scan.index} (stamp {scan.stamp:.3f} s)"


def _unreadable(scan: Scan) -> InvalidCloudError:
    return InvalidCloudError(f"{_named(scan)}: {scan.problem}")


def described_scan(scan: Scan, params: DescriptorParams, *, reference: bool = True,
                   keep_cloud: bool = False) -> DescribedScan:
    """A scan described (as a reference by default), with its cloud when keep_cloud."""
    return DescribedScan(describe_scan(scan, params, reference=reference), scan.pose, scan.stamp,
                         scan.index, prepared_points(scan, params) if keep_cloud else None,
                         scan.sensor_offset_m)


def describe_references(sequence: Sequence, indices: np.ndarray, ends: np.ndarray,
                        describe: Callable[[Scan], DescribedScan], *, progress: bool = False
                        ) -> tuple[list[DescribedScan], list[PassedOver]]:
    """The planned references indices described in order. One whose scan has nothing to
    describe is taken from the next scan that has, before ends[k] (the next planned
    reference's scan) and with a pose, as the live map builder takes the next scan; with no
    such scan the map has no reference there. Returns the references and the scans passed
    over. progress: a progress bar over the planned references."""
    described, passed_over = [], []
    posed = np.isfinite(sequence.poses).all(axis=(1, 2))

    def attempt(scan: Scan) -> DescribedScan | None:
        try:
            return describe(scan)
        except InvalidCloudError as error:
            passed_over.append(PassedOver(scan.index, scan.stamp, str(error)))
            return None

    scans = progress_bar(sequence.iter_scans(indices), total=len(indices), desc="build map",
                         enabled=progress, unit="scan")
    for k, scan in enumerate(scans):
        reference = attempt(scan)
        if reference is None:
            later = np.arange(scan.index + 1, ends[k])
            replacements = sequence.iter_scans(later[posed[later]])
            reference = next((found for found in map(attempt, replacements)
                              if found is not None), None)
            replacements.close()
        if reference is not None:
            described.append(reference)
    return described, passed_over


@dataclass
class ReferencePlan:
    """The references a sequence gives a map, and the map they go into."""

    indices: np.ndarray
    config: Config
    name: str
    frame_id: str
    metadata: dict
    n_scans: int

    @property
    def ends(self) -> np.ndarray:
        """For each reference, the scan where the next one's begins (the last: the sequence's
        end): a reference with nothing to describe is taken from a scan before it."""
        return np.append(self.indices[1:], self.n_scans)

    def new_map(self, **metadata) -> ReferenceMap:
        return ReferenceMap(self.config.descriptor, sensor_frame_id=self.frame_id,
                            metadata=dict(self.metadata, **metadata))


def plan_references(sequence: Sequence, config: Config) -> ReferencePlan:
    """One reference every config.spacing_m metres among the posed scans; preset auto derives
    the descriptor from the sequence and records the choice in the map's metadata."""
    valid = sequence.valid_poses("a map")
    indices = select_references(sequence.poses[:, :3, 3], config.spacing_m, valid)
    resolved, profile = resolve_for_sequence(config, sequence)
    metadata = {"source": sequence.name, "spacing_m": resolved.spacing_m}
    if profile is not None:
        metadata["auto"] = map_metadata(profile, resolved.descriptor)
    warning = single_scan_warning_for_sequence(resolved, sequence)
    if warning is not None:
        metadata[SINGLE_SCAN_WARNING_KEY] = warning
    return ReferencePlan(indices, resolved, sequence.name, getattr(sequence, "frame_id", ""),
                         metadata, len(sequence))


def build_map(sequence: Sequence, config: Config, *, keep_clouds: bool = False,
              progress: bool = True) -> ReferenceMap:
    """A ReferenceMap from a sequence's scans, one reference every config.spacing_m metres
    (each described from its submap when the descriptor asks for one), with the scans' clouds
    when keep_clouds or when the resolved config verifies by ICP (references.keeps_clouds).
    A reference scan with nothing to describe is taken from the next one
    (describe_references); the map's metadata lists those passed over."""
    plan = plan_references(sequence, config)
    reference_map = plan.new_map()
    sequence = with_submaps(sequence, SubmapWindow.for_descriptor(plan.config.descriptor))
    keep_cloud = keeps_clouds(plan.config.search, keep_clouds)
    described, passed_over = describe_references(
        sequence, plan.indices, plan.ends,
        lambda scan: described_scan(scan, plan.config.descriptor, keep_cloud=keep_cloud),
        progress=progress)
    add_references(reference_map, described)
    record_passed_over(reference_map, passed_over, len(described), plan.name)
    return reference_map
