"""Running suites and bulk map building on Dask distributed (optional: dask[distributed]).

`scheduler="local"` starts a LocalCluster of worker processes on this machine; any other value
is the address of a running cluster (`dask scheduler` on one machine, `dask worker ADDRESS` on
each of the others; the workers need this package and the data at the same paths). Work units
are independent and write nothing but their own atomic result, so a unit lost with a killed
worker is simply run again (by Dask, or by a resumed run).
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Callable, Iterable, Iterator

from mf_lpr_ros.errors import UnitFailure
from mf_lpr_ros.optional import require
from mf_lpr_ros.progress import progress_bar


@contextmanager
def dask_client(scheduler: str, workers: int | None = None) -> Iterator[Any]:
    """A distributed.Client: a LocalCluster of `workers` single-threaded processes for "local",
    else connected to the cluster at `scheduler`; closed on exit."""
    distributed = require("distributed")
    if scheduler == "local":
        cluster = distributed.LocalCluster(n_workers=workers or 2, threads_per_worker=1,
                                           processes=True, dashboard_address=":0")
        client = distributed.Client(cluster)
    else:
        cluster = None
        client = distributed.Client(scheduler, timeout="20s")
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run_units(client, function: Callable, units: Iterable[tuple[str, tuple]], *,
              progress: bool = True, description: str = "units") -> dict[str, Any]:
    """function(*arguments) for every (name, arguments) unit on the cluster; results by name,
    with a progress bar over completed units. Units that fail are all run before the failures
    are raised together (UnitFailure names each)."""
    distributed = require("distributed")
    units = list(units)
    futures = {client.submit(function, *arguments, key=f"mf_lpr-{name}", pure=False): name
               for name, arguments in units}
    results: dict[str, Any] = {}
    failures: list[str] = []
    for future in progress_bar(distributed.as_completed(futures), total=len(futures),
                               desc=description, enabled=progress, unit="unit"):
        name = futures[future]
        try:
            results[name] = future.result()
        except Exception as error:  # a unit's own failure, reported by name below
            failures.append(f"{name}: {type(error).__name__}: {error}")
    if failures:
        raise UnitFailure(f"{len(failures)} of {len(units)} units failed:\n  "
                          + "\n  ".join(failures))
    return results
