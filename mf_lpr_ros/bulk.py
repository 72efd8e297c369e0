"""Maps from many sources at once, serially or on a Dask cluster (mf_lpr_ros/distributed.py).

Each source's references are chosen as pipeline.build_map chooses them; describing them is cut
into chunks of scans, one work unit each (a unit opens its source itself, so a worker on another
machine needs only the same paths). The chunks are put back in order, so every map equals the
serial build_map's of the same source; combined, the sources' references follow one another in
the order given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .auto_params import map_metadata, resolve_for_sequence
from .config import Config
from .datasets import open_source
from .map_store import ReferenceMap
from .pipeline import describe_scan, prepared_points, record_sensor_offset, select_references
from .progress import progress_bar

CHUNK_SCANS = 64


@dataclass(frozen=True)
class SourceSpec:
    """Where a source is and, for bags, which topics to read."""

    path: str
    cloud_topic: str | None = None
    pose_topic: str | None = None

    def open(self):
        return open_source(self.path, self.cloud_topic, self.pose_topic)


@dataclass
class DescribedChunk:
    """The reference descriptors of one chunk of a source's selected scans."""

    occupancy: np.ndarray
    poses: np.ndarray
    stamps: np.ndarray
    indices: np.ndarray
    clouds: list | None
    offsets: set


def describe_chunk(spec: SourceSpec, indices: np.ndarray, config: Config,
                   keep_clouds: bool) -> DescribedChunk:
    """The work unit: reference descriptors of these scans of one source."""
    occupancy, poses, stamps, clouds, offsets = [], [], [], [], set()
    for scan in spec.open().iter_scans(indices):
        occupancy.append(describe_scan(scan, config.descriptor, reference=True))
        poses.append(scan.pose)
        stamps.append(scan.stamp)
        if keep_clouds:
            clouds.append(prepared_points(scan, config.descriptor))
        offsets.add(scan.sensor_offset_m)
    size = config.descriptor.size
    return DescribedChunk(np.array(occupancy, dtype=bool).reshape(-1, size, size),
                          np.array(poses).reshape(-1, 4, 4), np.array(stamps, dtype=float),
                          np.asarray(indices, dtype=np.int64), clouds if keep_clouds else None,
                          offsets)


@dataclass
class _Plan:
    spec: SourceSpec
    name: str
    frame_id: str
    config: Config
    metadata: dict
    chunks: list[np.ndarray]


def _plan(spec: SourceSpec, config: Config) -> _Plan:
    sequence = spec.open()
    if sequence.poses is None:
        raise ValueError(f"{sequence.name}: this source has no poses; a map needs them")
    valid = np.isfinite(sequence.poses).all(axis=(1, 2))
    indices = select_references(sequence.poses[:, :3, 3], config.spacing_m, valid)
    resolved, profile = resolve_for_sequence(config, sequence)
    metadata = {"source": sequence.name, "spacing_m": resolved.spacing_m}
    if profile is not None:
        metadata["auto"] = map_metadata(profile, resolved.descriptor)
    chunks = [indices[start:start + CHUNK_SCANS] for start in range(0, len(indices), CHUNK_SCANS)]
    return _Plan(spec, sequence.name, getattr(sequence, "frame_id", ""), resolved, metadata,
                 chunks)


def build_maps(specs: list[SourceSpec], config: Config, *, combine: bool = False,
               keep_clouds: bool = False, client=None, progress: bool = True
               ) -> list[ReferenceMap]:
    """One map per source (or, combine, one map of them all), described serially or as units
    on client's cluster. Combined sources share one descriptor: with preset auto it is derived
    from the first source."""
    if not specs:
        raise ValueError("build_maps needs at least one source")
    plans = []
    for spec in specs:
        if combine and plans:
            config = plans[0].config
        plans.append(_plan(spec, config))
    units = [(f"{k}:{c}", (plan.spec, chunk, plan.config, keep_clouds))
             for k, plan in enumerate(plans) for c, chunk in enumerate(plan.chunks)]
    if client is None:
        described = {name: describe_chunk(*arguments) for name, arguments in progress_bar(
            units, total=len(units), desc="describe", enabled=progress, unit="chunk")}
    else:
        from .distributed import run_units

        described = run_units(client, describe_chunk, units, progress=progress,
                              description="describe")
    maps = []
    for k, plan in enumerate(plans):
        chunks = [described[f"{k}:{c}"] for c in range(len(plan.chunks))]
        if combine and maps:
            _append(maps[0], chunks)
            maps[0].metadata["sources"].append(plan.name)
            continue
        metadata = dict(plan.metadata, sources=[plan.name]) if combine else plan.metadata
        reference_map = ReferenceMap(plan.config.descriptor, sensor_frame_id=plan.frame_id,
                                     metadata=metadata)
        _append(reference_map, chunks)
        maps.append(reference_map)
    return maps


def _append(reference_map: ReferenceMap, chunks: list[DescribedChunk]) -> None:
    offsets = {reference_map.metadata.get("sensor_offset_m", 0.0)} if len(reference_map) else set()
    for chunk in chunks:
        for k in range(len(chunk.stamps)):
            reference_map.append(chunk.occupancy[k], chunk.poses[k], float(chunk.stamps[k]),
                                 int(chunk.indices[k]),
                                 None if chunk.clouds is None else chunk.clouds[k])
        offsets |= chunk.offsets
    record_sensor_offset(reference_map, offsets)
