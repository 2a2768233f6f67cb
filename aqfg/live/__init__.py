"""``aqfg live``: the fixed-lag smoother of ``aqfg fit --mode online`` on a MAVLink stream,
or on a log replayed as one (docs/on-the-vehicle.md).

Modules, one job each: :mod:`.source` (messages from a log or a link, replay pacing),
:mod:`.assemble` (messages -> the growing mission, with the importer's conversions),
:mod:`.runner` (the smoother's updates, fix by fix), :mod:`.outputs` (the files written as
it goes and at the end), :mod:`.send` (positions and parameters back to the autopilot).
"""
