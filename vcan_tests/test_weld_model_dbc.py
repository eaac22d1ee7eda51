"""chcos/apps/weld/maps/weld_cell.dbc: cantools loads it, ids fit beside CANopen, model readings
encode."""

from __future__ import annotations

from typing import Any

import cantools
import pytest

from chcos.apps.weld import DBC_PATH
from chcos.apps.weld.faults import SENSOR_NAMES, Fault, parse_scenario
from chcos.apps.weld.model import DBC_MESSAGE_SENSORS, WeldCell, dbc_signals


@pytest.fixture(scope="module")
def db() -> cantools.database.can.Database:
    loaded = cantools.database.load_file(str(DBC_PATH))
    assert isinstance(loaded, cantools.database.can.Database)
    return loaded


def test_messages_ids_and_cycle_times(db: cantools.database.can.Database) -> None:
    by_name = {m.name: m for m in db.messages}
    assert {n: hex(m.frame_id) for n, m in by_name.items()} == {
        "LightCurtain": "0x10",
        "ArcTemperature": "0x120",
        "GapMarkers": "0x130",
        "GasSupply": "0x140",
        "WireFeed": "0x150",
    }
    assert by_name["LightCurtain"].cycle_time == 20
    assert by_name["ArcTemperature"].cycle_time == 20
    assert by_name["ArcTemperature"].get_signal_by_name("ArcTemp").unit == "degC"
    for m in db.messages:
        assert not m.is_extended_frame
        assert m.senders and m.senders[0] != "Chcos"


def test_ids_are_free_in_the_canopen_predefined_connection_set(
    db: cantools.database.can.Database,
) -> None:
    used = {0x000, 0x080, 0x100}
    for node in range(1, 128):
        used |= {0x080 + node, 0x700 + node, 0x580 + node, 0x600 + node}
        used |= {base + node for base in (0x180, 0x200, 0x280, 0x300, 0x380, 0x400, 0x480, 0x500)}
    for m in db.messages:
        assert m.frame_id not in used, m.name
    # the light curtain wins arbitration against every other frame of the cell
    assert min(m.frame_id for m in db.messages) == db.get_message_by_name("LightCurtain").frame_id


def test_every_message_maps_to_known_sensors(db: cantools.database.can.Database) -> None:
    assert set(DBC_MESSAGE_SENSORS) == {m.name for m in db.messages}
    for sensors in DBC_MESSAGE_SENSORS.values():
        assert set(sensors) <= set(SENSOR_NAMES)


def test_model_readings_round_trip_through_the_dbc(db: cantools.database.can.Database) -> None:
    cell = WeldCell(seed=4, scenario=parse_scenario("intruder"))
    cell.set_gas_valve(True)
    cell.set_wire_speed(120.0)
    for _ in range(20):
        cell.step(0.05)
    r = cell.readings()
    signals = dbc_signals(r, counter=17)
    assert set(signals) == set(DBC_MESSAGE_SENSORS)
    decoded: dict[str, Any] = {}
    for name, values in signals.items():
        msg = db.get_message_by_name(name)
        data = msg.encode(values)
        assert len(data) == msg.length
        decoded[name] = msg.decode(data)
    assert decoded["LightCurtain"]["Intruder"] == 1
    assert decoded["LightCurtain"]["AliveCounter"] == 1
    assert decoded["ArcTemperature"]["ArcTemp"] == pytest.approx(r.arc_temperature, abs=0.06)
    assert str(decoded["ArcTemperature"]["ArcTempStatus"]) == "ok"
    assert decoded["GasSupply"]["BottlePressure"] == pytest.approx(r.gas_bottle_pressure, abs=0.01)
    assert decoded["GasSupply"]["GasFlow"] == pytest.approx(r.gas_flow, abs=0.01)
    assert decoded["WireFeed"]["WireSpeed"] == pytest.approx(r.wire_speed, abs=0.01)
    assert decoded["WireFeed"]["WireRemaining"] == pytest.approx(r.wire_remaining, abs=0.001)
    assert decoded["GapMarkers"]["StartOfGap"] == 0


def test_out_of_range_temperature_and_silent_sensors() -> None:
    cell = WeldCell()
    cell.inject(Fault("sensor-dropout", sensor="gas_flow"))
    cell.temperature = 3500.0
    cell.step(0.01)
    signals = dbc_signals(cell.readings(), counter=0)
    assert "GasSupply" not in signals  # the gas monitor stopped sending
    assert signals["ArcTemperature"]["ArcTemp"] == 3000.0
    assert signals["ArcTemperature"]["ArcTempStatus"] == "over_range"
