"""weld - the arc-welding cell of the thesis' reference application (sections 5.1, 5.4, appendix 2).

The pure, bus-free core that the simulator, the drivers and the CHC task hierarchy build on:

* :mod:`chcos.apps.weld.seam` - the gap on the plate, its markers, the linear light sensor's view;
* :mod:`chcos.apps.weld.kinematics` - the 5-joint arm: DH table, T5, inverse kinematics;
* :mod:`chcos.apps.weld.model` - the cell physics stepped on explicit simulated time;
* :mod:`chcos.apps.weld.faults` - fault injection and scenario parsing.

The raw-CAN part of the cell (light curtain, arc temperature, gap markers, gas supply, wire feed)
is described by ``chcos/apps/weld/maps/weld_cell.dbc``, found at :data:`DBC_PATH` in a source
checkout.
"""

from __future__ import annotations

from pathlib import Path

from chcos import resources
from chcos.apps.weld.faults import (
    FAULT_KINDS,
    SENSOR_NAMES,
    AtSeam,
    AtTime,
    Fault,
    Immediate,
    Scenario,
    parse_fault,
    parse_scenario,
    parse_scenario_toml,
    scenario_from_table,
)
from chcos.apps.weld.kinematics import Arm, ToolPose, UnreachableError
from chcos.apps.weld.model import (
    DBC_MESSAGE_SENSORS,
    CellConfig,
    FaultEvent,
    Flaw,
    Readings,
    SimulationError,
    WeldCell,
    WeldProgress,
    dbc_signals,
)
from chcos.apps.weld.seam import LinearView, Seam, SeamPoint, SeamSpec

DBC_PATH: Path = resources.path("chcos.apps.weld", "maps", "weld_cell.dbc")
"""The cell's DBC file, shipped as package data (``chcos/apps/weld/maps/weld_cell.dbc``)."""

__all__ = [
    "DBC_MESSAGE_SENSORS",
    "DBC_PATH",
    "FAULT_KINDS",
    "SENSOR_NAMES",
    "Arm",
    "AtSeam",
    "AtTime",
    "CellConfig",
    "Fault",
    "FaultEvent",
    "Flaw",
    "Immediate",
    "LinearView",
    "Readings",
    "Scenario",
    "Seam",
    "SeamPoint",
    "SeamSpec",
    "SimulationError",
    "ToolPose",
    "UnreachableError",
    "WeldCell",
    "WeldProgress",
    "dbc_signals",
    "parse_fault",
    "parse_scenario",
    "parse_scenario_toml",
    "scenario_from_table",
]
