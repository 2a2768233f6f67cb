"""A fleet's season of logs: each vehicle's joint batch fit over all its missions, solved
mission by mission on Dask (exactly the single-process joint fit), with a report of how
the vehicles differ. Needs the ``fleet`` extra (dask[distributed])."""
from aqfg.fleet.manifest import (
           Manifest,
           ManifestError,
           Vehicle,
           load_manifest,
           write_manifest,
)
from aqfg.fleet.solve import FleetError, FleetResult, fit_fleet

__all__ = ["FleetError", "FleetResult", "Manifest", "ManifestError", "Vehicle", "fit_fleet",
           "load_manifest", "write_manifest"]
