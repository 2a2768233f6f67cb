"""Puts Fossen's Python Vehicle Simulator (MIT licence, not on PyPI) on ``sys.path``: its
``src/`` folder, from ``PVS_SRC`` or ``experiments/heldout/pvs/src`` (see README.md here).
Imported by the mission generators before they import the simulator."""
import os
import sys

PVS = os.environ.get("PVS_SRC") or os.path.join(os.path.dirname(os.path.abspath(__file__)), "pvs", "src")
if not os.path.isdir(os.path.join(PVS, "python_vehicle_simulator")):
    sys.exit(f"Fossen's Python Vehicle Simulator not found at {PVS}; clone "
             "https://github.com/cybergalactic/PythonVehicleSimulator and set PVS_SRC to its src/")
sys.path.insert(0, PVS)
