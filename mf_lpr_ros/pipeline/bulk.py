"""Maps from many sources at once, serially or on a Dask cluster (pipeline.distributed).

Each source's references are chosen as pipeline.mapping.build_map chooses them; describing
them is cut into chunks of scans, one work unit each (a unit opens its source itself, so a
worker on another machine needs only the same paths). The chunks are put back in order, so
every map equals the serial build_map's of the same source; combined, the sources' references
follow one another in the order given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.references import (
    DescribedScan,
    PassedOver,
    add_references,
    keeps_clouds,
    record_passed_over,
)
from mf_lpr_ros.core.submap import SubmapWindow
from mf_lpr_ros.datasets import open_source
from mf_lpr_ros.pipeline.distributed import run_units
from mf_lpr_ros.pipeline.mapping import (
    ReferencePlan,
    describe_references,
    described_scan,
    plan_references,
)
from mf_lpr_ros.pipeline.submaps import with_submaps
from mf_lpr_ros.progress import progress_bar

CHUNK_SCANS = 64


@dataclass(frozen=True)
class SourceSpec:
    """Where a source is and, for bags, which topics to read."""

    path: str
    cloud_topic: str | None = None
    pose_topic: str | None = None

    def open(self):
        return open_source(self.path, self.cloud_topic, self.pose_topic)


def describe_chunk(spec: SourceSpec, indices: np.ndarray, ends: np.ndarray, config: Config,
                   keep_clouds: bool) -> tuple[list[DescribedScan], list[PassedOver]]:
    """The work unit: these planned references of one source described (a scan with nothing to
    describe taken from the next one before ends, as mapping.describe_references does), and
    the scans passed over."""
    sequence = with_submaps(spec.open(), SubmapWindow.for_descriptor(config.descriptor))
    return describe_references(
        sequence, indices, ends,
        lambda scan: described_scan(scan, config.descriptor, keep_cloud=keep_clouds))


@dataclass
class _SourcePlan:
    spec: SourceSpec
    plan: ReferencePlan

    @property
    def chunks(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The planned references in chunks, each with its references' ends (ReferencePlan)."""
        indices, ends = self.plan.indices, self.plan.ends
        return [(indices[start:start + CHUNK_SCANS], ends[start:start + CHUNK_SCANS])
                for start in range(0, len(indices), CHUNK_SCANS)]


def build_maps(specs: list[SourceSpec], config: Config, *, combine: bool = False,
               keep_clouds: bool = False, client=None, progress: bool = True
               ) -> list[ReferenceMap]:
    """One map per source (or, combine, one map of them all), described serially or as units
    on client's cluster. Combined sources share one descriptor: with preset auto it is derived
    from the first source."""
    if not specs:
        raise ValueError("build_maps needs at least one source")
    plans: list[_SourcePlan] = []
    for spec in specs:
        if combine and plans:
            config = plans[0].plan.config
        plans.append(_SourcePlan(spec, plan_references(spec.open(), config)))
    units = [(f"{k}:{c}", (source.spec, indices, ends, source.plan.config,
                           keeps_clouds(source.plan.config.search, keep_clouds)))
             for k, source in enumerate(plans)
             for c, (indices, ends) in enumerate(source.chunks)]
    if client is None:
        described = {name: describe_chunk(*arguments) for name, arguments in progress_bar(
            units, total=len(units), desc="describe", enabled=progress, unit="chunk")}
    else:
        described = run_units(client, describe_chunk, units, progress=progress,
                              description="describe")
    maps = []
    for k, source in enumerate(plans):
        chunks = [described[f"{k}:{c}"] for c in range(len(source.chunks))]
        scans = [scan for chunk_scans, _ in chunks for scan in chunk_scans]
        passed_over = [scan for _, chunk_passed in chunks for scan in chunk_passed]
        if combine and maps:
            add_references(maps[0], scans)
            maps[0].metadata["sources"].append(source.plan.name)
            record_passed_over(maps[0], passed_over, len(scans), source.plan.name)
            continue
        reference_map = source.plan.new_map(**({"sources": [source.plan.name]} if combine else {}))
        add_references(reference_map, scans)
        record_passed_over(reference_map, passed_over, len(scans), source.plan.name)
        maps.append(reference_map)
    return maps
