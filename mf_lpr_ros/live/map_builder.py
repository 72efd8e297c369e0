"""The map builder's logic without ROS: references one spacing_m apart, saved atomically."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.auto_params import (
    SAMPLE_SCANS,
    SINGLE_SCAN_WARNING_KEY,
    auto_config,
    map_metadata,
    measure_sensor,
    single_scan_warning,
)
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.references import (
    DescribedScan,
    PassedOver,
    SpacingGate,
    add_references,
    describe_observation,
    descriptor_points,
    keeps_clouds,
    note_passed_over,
)
from mf_lpr_ros.core.submap import Submap, SubmapWindow
from mf_lpr_ros.errors import InvalidCloudError, InvalidPoseError
from mf_lpr_ros.live.pose_buffer import PairedScan


class MapBuilder:
    """Keeps a reference every spacing_m metres of travel and saves the map atomically.

    With preset auto (config.auto) and a new map, the first auto_params.SAMPLE_SCANS scans are
    held back until the descriptor is derived from them (auto_choice then says what was
    chosen), and then described like every later scan; an existing map keeps its parameters.
    A named preset that describes single scans measures the first SAMPLE_SCANS scans the same
    way, and single_scan_warning then says (once) when the sensor looks like one that needs
    submaps.
    Reference clouds are kept as core.references.keeps_clouds says (a search that verifies by
    ICP needs them).
    Every scan offered joins the submap window (core.submap) when the descriptor has one, so a
    reference is described from the scans of its last descriptor.submap_m metres; a caller
    that already keeps the same window (the loop-closure localiser) passes it as submap.
    A scan offer refuses (or the node rejects, pass_over) is noted in the map's metadata as the
    offline build notes the scans it passes over (core.references.PassedOver).
    """

    def __init__(self, config: Config, map_path: str | Path | None, *, frame_id: str = "map",
                 sensor_frame_id: str = "", keep_clouds: bool = False,
                 reference_map: ReferenceMap | None = None,
                 submap: Submap | None = None) -> None:
        self.map_path = None if map_path is None else Path(map_path)
        # A map keeps clouds when asked, when its verification needs them, and (extended)
        # when it already does: every reference then needs one. A map with a site cloud cuts
        # every reference's cloud from it, those added here too.
        site = reference_map is not None and reference_map.site_cloud is not None
        self.keep_clouds = not site and (keeps_clouds(config.search, keep_clouds) or (
            reference_map is not None and reference_map.has_reference_clouds))
        self.auto_choice: str | None = None
        self.single_scan_warning: str | None = None
        self._sampled: list[PairedScan] | None = (
            [] if not config.auto and config.descriptor.submap_m <= 0 else None)
        self.rejected_while_held = 0
        self._passed_over_unsaved = False
        self._held: list[PairedScan] | None = None
        if reference_map is None:
            reference_map = ReferenceMap(config.descriptor, frame_id=frame_id,
                                         sensor_frame_id=sensor_frame_id,
                                         metadata={"source": "map_builder",
                                                   "spacing_m": config.spacing_m})
            if config.auto:
                self._held = []
        elif config.auto:
            config = replace(config, descriptor=reference_map.params, auto=False)
        else:
            reference_map.check_params(config.descriptor)
        self.config = config
        self.map = reference_map
        self.submap = submap if submap is not None else _submap_for(config)
        self.saved_references = len(reference_map)
        positions = reference_map.poses[:, :3, 3]
        self._spacing = SpacingGate(config.spacing_m, positions[-1] if len(positions) else None)

    @property
    def waiting_for_auto(self) -> bool:
        """Scans are still held back for preset auto."""
        return self._held is not None

    def offer(self, scan: PairedScan) -> int | None:
        """Adds the scan as a reference when it is spacing_m from the last one; its index or None
        (or, for preset auto, the last reference the held-back scans gave once derived)."""
        if self._held is not None:
            self._held.append(scan)
            return self.derive_auto() if len(self._held) >= SAMPLE_SCANS else None
        if self._sampled is not None:
            self._sample(scan)
        return self._offer_noting(scan)

    def pass_over(self, index: int, stamp: float, why: str) -> None:
        """Notes in the map's metadata a scan that was not used, and why (saved with the map)."""
        note_passed_over(self.map, [PassedOver(index, stamp, why)], "map_builder")
        self._passed_over_unsaved = True

    def _offer_noting(self, scan: PairedScan) -> int | None:
        """_offer, noting a scan it refuses (pass_over) before the error propagates."""
        try:
            return self._offer(scan)
        except (InvalidCloudError, InvalidPoseError, ValueError) as error:
            self.pass_over(scan.index, scan.stamp, str(error))
            raise

    def _sample(self, scan: PairedScan) -> None:
        """Keeps the scan for the single-scan check until SAMPLE_SCANS are kept, then checks."""
        if not np.isfinite(scan.pose).all():
            return
        self._sampled.append(scan)
        if len(self._sampled) < SAMPLE_SCANS:
            return
        sampled, self._sampled = self._sampled, None
        try:
            profile = measure_sensor([kept.points for kept in sampled],
                                     [kept.pose[:3, :3] for kept in sampled])
        except InvalidCloudError:
            return
        self.single_scan_warning = single_scan_warning(profile, self.config.descriptor)
        if self.single_scan_warning is not None:
            self.map.metadata[SINGLE_SCAN_WARNING_KEY] = self.single_scan_warning

    def derive_auto(self) -> int | None:
        """Derive the descriptor from the held-back scans (preset auto) and add them; the last
        reference added or None. Nothing to do when nothing is held."""
        held = self._held
        if not held:
            return None
        try:
            resolved, profile = auto_config([scan.points for scan in held], self.config,
                                            [scan.pose[:3, :3] for scan in held])
        except InvalidCloudError:
            self._held = []
            raise
        self._held = None
        self.config = resolved
        self.keep_clouds = keeps_clouds(resolved.search, self.keep_clouds)
        self.submap = _submap_for(resolved)
        metadata = dict(self.map.metadata, auto=map_metadata(profile, resolved.descriptor))
        self.map = ReferenceMap(resolved.descriptor, frame_id=self.map.frame_id,
                                sensor_frame_id=self.map.sensor_frame_id, metadata=metadata)
        self._spacing = SpacingGate(resolved.spacing_m)
        self.auto_choice = metadata["auto"]["choice"]
        last = None
        for scan in held:
            try:
                index = self._offer_noting(scan)
            except (InvalidCloudError, InvalidPoseError, ValueError):
                self.rejected_while_held += 1
                continue
            last = index if index is not None else last
        return last

    def _offer(self, scan: PairedScan) -> int | None:
        if self.submap is not None:
            self.submap.add(scan.stamp, scan.points, scan.pose)
        position = scan.pose[:3, 3]
        if not self._spacing.far_enough(position):
            return None
        params = self.config.descriptor
        points = self.submap.points_at(scan.stamp).points \
            if self.submap is not None and self.submap.holds(scan.stamp) else scan.points
        points = descriptor_points(points, scan.pose, params)
        occupancy = describe_observation(params, reference=True, stamp=scan.stamp, points=points)
        index = add_references(self.map, [DescribedScan(
            occupancy, scan.pose, scan.stamp, scan.index, points if self.keep_clouds else None)])
        self._spacing.mark(position)
        return index

    @property
    def unsaved(self) -> int:
        """References not yet on disk."""
        return len(self.map) - self.saved_references

    @property
    def needs_save(self) -> bool:
        """References, or scans passed over beside some, not yet on disk."""
        return self.unsaved > 0 or (self._passed_over_unsaved and len(self.map) > 0)

    def save(self) -> int:
        """Writes the map (temporary file, fsync, rename); returns the references now on disk.
        On failure the previous file is untouched, the in-memory map is kept, and the error
        propagates for the caller to report."""
        if self.map_path is None:
            raise RuntimeError("this map builder has no map_path to save to")
        count = len(self.map)
        self.map.save(self.map_path)
        self.saved_references = count
        self._passed_over_unsaved = False
        return count


def _submap_for(config: Config) -> Submap | None:
    """The submap window of config's descriptor, None for single scans (or preset auto, whose
    window is known only once derived)."""
    window = SubmapWindow.for_descriptor(config.descriptor)
    return Submap(window) if window.active and not config.auto else None
