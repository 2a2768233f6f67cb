"""A fleet's season of logs: each vehicle's joint batch fit over all its missions, solved
mission by mission on Dask (exactly the single-process joint fit), with a report of how
the vehicles differ. Needs the ``fleet`` extra (dask[distributed]). The solver
(:mod:`aqfg.fleet.solve`) is imported on first use of its names: ``aqfg fleet`` loads it
while the local workers start (:func:`aqfg.fleet.cluster.fleet_client`)."""
from typing import TYPE_CHECKING

from aqfg.fleet.cluster import FleetError
from aqfg.fleet.manifest import (
           Manifest,
           ManifestError,
           Vehicle,
           load_manifest,
           write_manifest,
)

if TYPE_CHECKING:
    from aqfg.fleet.solve import FleetResult, fit_fleet

__all__ = ["FleetError", "FleetResult", "Manifest", "ManifestError", "Vehicle", "fit_fleet",
           "load_manifest", "write_manifest"]


def __getattr__(name: str):
    if name in ("FleetResult", "fit_fleet"):
        from aqfg.fleet import solve
        return getattr(solve, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
