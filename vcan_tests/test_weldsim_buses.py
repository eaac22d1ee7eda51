"""WeldSim on real protocols: every sensor of the welding cell reaches Devtab with the model's
value, and every actuator command reaches the model (CANopen, raw CAN, Modbus TCP, serial, all on
virtual CAN and loopback, on a VirtualClock)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.apps.weld.model import Readings
from chcos.apps.weld.slaves import NODE_IDS, format_line
from vcan_tests.support_weldsim import QUIET, WeldRig, make_rig

#: The tip 30 mm above the start of the gap, tool x along the seam (the linear sensor, 5 mm
#: ahead, sees the start marker); 30 mm is beyond the arc length at 24 V, so the arc is out.
ABOVE_START = ((550.0, -150.0, 30.0), math.pi / 2.0)


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[WeldRig]:
    r = make_rig(tmp_path, config=QUIET)
    yield r
    r.close()


def move_to(rig: WeldRig, position: tuple[float, float, float], yaw: float) -> tuple[float, ...]:
    """Command the joint targets that put the tip at ``position``; returns them."""
    q = rig.sim.model.arm.inverse_down(position, yaw)
    rig.command("JOINTS", **{f"target{j + 1}": v for j, v in enumerate(q)})
    return tuple(q)


def at_start(rig: WeldRig) -> Readings:
    """Drives on, power source on (24 V open circuit, 100 mm/s wire, gas), tip above the start;
    run until everything has settled; the model's readings then."""
    rig.command("POWER", drives_enable=1, volts_set=24.0, wire_set=100.0, gas_valve=1)
    rig.run(0.05)
    rig.enable_drives()
    move_to(rig, *ABOVE_START)
    rig.run(2.0)
    return rig.sim.model.readings()


def test_every_sensor_reaches_devtab_with_the_models_value(rig: WeldRig) -> None:
    r = at_start(rig)
    assert r.arc_voltage == pytest.approx(44.0) and r.wire_speed == pytest.approx(100.0)
    assert r.start_marker and r.range_mm == pytest.approx(30.0, abs=1e-3)
    for j in range(5):
        assert rig.value(f"theta{j + 1}") == pytest.approx(r.joints[j], abs=1.01e-6)
    assert rig.value("arc_temp") == pytest.approx(r.arc_temperature, abs=0.051)
    assert rig.value("start_marker") == 1 and rig.value("end_marker") == 0
    assert rig.value("intruder") == 0
    assert rig.value("arc_volts") == pytest.approx(r.arc_voltage, abs=0.0051)
    assert rig.value("arc_amps") == pytest.approx(r.arc_current, abs=0.051)
    assert rig.value("wire_speed") == pytest.approx(r.wire_speed, abs=0.0051)
    assert rig.value("gas_bottle") == pytest.approx(r.gas_bottle_pressure, abs=0.011)
    assert rig.value("gas_flow") == pytest.approx(r.gas_flow, abs=0.0051)
    assert rig.value("range") == pytest.approx(r.range_mm, abs=0.0051)
    for name in ("theta1", "arc_temp", "arc_volts", "gas_flow", "range", "intruder"):
        assert rig.status(name) == "OK" and rig.entry(name).readings > 10, name
    # and through the tasks' input ports
    seen = rig.read("SEAM", ["start_marker", "range"])
    rig.run(0.1)
    assert seen["seen"] == {"start_marker": 1, "range": pytest.approx(30.0, abs=0.01)}


def test_linear_sensor_reaches_devtab_as_its_pixel_string(rig: WeldRig) -> None:
    r = at_start(rig)
    pixels = format_line(r).split()[1]
    assert len(pixels) == 64 and "1" in pixels
    assert rig.value("linear") == pixels


def test_intruder_frame_goes_out_on_change_at_top_priority(rig: WeldRig) -> None:
    rig.run(0.105)                             # past the cyclic frame of the 0.1 s slot
    before = rig.entry("intruder").readings
    rig.sim.inject("intruder(for=0.05s)")
    rig.run(0.006)  # on change: in the 0.11 s slot, not at the next 20 ms cycle (0.12 s)
    assert rig.value("intruder") == 1
    assert rig.entry("intruder").readings == before + 1
    rig.run(0.005)                             # and nothing more until that cycle
    assert rig.entry("intruder").readings == before + 1
    rig.run(0.1)
    assert rig.value("intruder") == 0
    assert rig.entry("intruder").spec.priority == 99


def test_joint_targets_move_the_joints(rig: WeldRig) -> None:
    rig.command("POWER", drives_enable=1)
    rig.run(0.05)
    rig.enable_drives()
    q = move_to(rig, (520.0, -40.0, 60.0), 0.3)
    rig.run(0.05)
    model = rig.sim.model
    assert model.targets == pytest.approx(list(q), abs=1e-6)   # RPDO1 -> 0x607A -> model
    assert model.joints != pytest.approx(list(q), abs=1e-3)     # on the way, not there yet
    rig.run(2.0)
    assert model.joints == pytest.approx(list(q), abs=1e-6)
    assert model.pose.position == pytest.approx((520.0, -40.0, 60.0), abs=0.01)
    assert [rig.value(f"theta{n}") for n in NODE_IDS] == pytest.approx(list(q), abs=1.01e-6)


def test_targets_are_ignored_and_joints_held_while_drives_are_disabled(rig: WeldRig) -> None:
    home = list(rig.sim.model.joints)
    move_to(rig, (520.0, -40.0, 60.0), 0.3)   # drives start disabled: ignored
    rig.run(0.5)
    assert rig.sim.model.joints == home and not rig.sim.drives_enabled
    assert rig.sim.stats["target-ignored-disabled"] == 5
    rig.command("POWER", drives_enable=1)
    rig.run(0.05)
    move_to(rig, (520.0, -40.0, 60.0), 0.3)   # the relay on, the drives not enabled: ignored
    rig.run(0.5)
    assert rig.sim.model.joints == home
    assert rig.sim.stats["target-ignored-drive"] == 5
    assert all(d.ignored_targets == 2 for d in rig.sim.servo.drives.values())  # both batches
    rig.enable_drives()
    q = move_to(rig, (520.0, -40.0, 60.0), 0.3)
    rig.run(0.2)
    moving = list(rig.sim.model.joints)
    assert moving != pytest.approx(home, abs=1e-3) and moving != pytest.approx(list(q), abs=1e-3)
    rig.command("POWER", drives_enable=0)      # safe torque off mid-move: halt where it is
    rig.run(0.05)
    halted = list(rig.sim.model.joints)
    assert rig.sim.model.targets == halted
    rig.run(1.0)
    assert rig.sim.model.joints == halted
    assert [rig.value(f"theta{n}") for n in NODE_IDS] == pytest.approx(halted, abs=1.01e-6)
    rig.command("POWER", drives_enable=1)      # enabled again: stays put until a new target
    rig.run(0.5)
    assert rig.sim.model.joints == halted


def test_power_source_and_gas_commands_reach_the_model(rig: WeldRig) -> None:
    model = rig.sim.model
    rig.run(0.05)
    assert rig.value("arc_volts") == 0.0 and rig.value("gas_flow") == 0.0
    rig.command("POWER", volts_set=24.5, wire_set=120.0, gas_valve=1)
    rig.run(0.3)
    assert model.voltage_setpoint == pytest.approx(24.5)
    assert model.wire_setpoint == pytest.approx(120.0)
    assert model.gas_valve
    assert rig.value("arc_volts") == pytest.approx(44.5, abs=0.01)   # open circuit, arc out
    assert rig.value("wire_speed") == pytest.approx(120.0, abs=0.01)
    assert rig.value("gas_flow") == pytest.approx(15.0, abs=0.01)
    rig.command("POWER", volts_set=0.0, gas_valve=0)
    rig.run(0.1)
    assert model.voltage_setpoint == 0.0 and not model.gas_valve
    assert rig.value("arc_volts") == 0.0 and rig.value("gas_flow") == 0.0


def test_welding_heats_the_arc_and_reports_it_on_can(rig: WeldRig) -> None:
    rig.command("POWER", drives_enable=1, wire_set=80.0, gas_valve=1)
    rig.run(0.05)
    rig.enable_drives()
    move_to(rig, (550.0, -150.0, 10.0), math.pi / 2.0)
    rig.run(2.0)
    assert rig.value("arc_temp") == pytest.approx(20.0, abs=0.1)
    rig.command("POWER", volts_set=24.0)       # strike the arc at 10 mm stand-off
    rig.run(3.0)
    model = rig.sim.model
    assert model.arc_burning
    assert rig.value("arc_temp") > 1400.0
    assert rig.value("arc_temp") == pytest.approx(model.readings().arc_temperature, abs=5.0)
    assert rig.value("arc_amps") == pytest.approx(160.0, abs=0.1)


def test_safe_values_at_shutdown_reach_the_model(tmp_path: Path) -> None:
    rig = make_rig(tmp_path, config=QUIET)
    try:
        rig.command("POWER", drives_enable=1, volts_set=20.0, gas_valve=1)
        rig.run(0.1)
        assert rig.sim.drives_enabled and rig.sim.model.gas_valve
        rig.system.shutdown()                  # writes the safe values, stops the drivers
        assert rig.sim.store.read(1, "coil", 0, 2) == [False, False]
        rig.sim.settle(0.0)
        assert not rig.sim.drives_enabled and not rig.sim.model.gas_valve
        assert rig.sim.model.voltage_setpoint == 0.0
    finally:
        rig.sim.close()


def test_the_joint_drives_follow_the_controlword_on_canopen(tmp_path: Path) -> None:
    """The five drives are CiA 402 drives on the bus: what they received and the states they
    went through, on their side. Enabling walks shutdown, switch on, enable operation; a quick
    stop mid-move brakes the joint on the drive's ramp (short of its target, not dead) and the
    drive stays in QUICK STOP ACTIVE; the shutdown's safe stop then disables the voltage (the
    drive did not do it itself: quick stop option 6)."""
    from chcos.apps.sim.cia402_drive import Power
    from drivers.canopen_axis import AxisCode

    rig = make_rig(tmp_path, config=QUIET)
    try:
        servo = rig.sim.servo
        assert servo is not None
        drive = servo.drives[1]
        rig.command("POWER", drives_enable=1)
        rig.run(0.05)
        assert all(d.power is Power.SWITCH_ON_DISABLED for d in servo.drives.values())
        rig.enable_drives()
        for d in servo.drives.values():
            assert [cw for cw in d.received if cw][:3] == [0x06, 0x07, 0x0F], d.received
            assert d.mode_display == 8                                # CSP, shown on 0x6061
        assert rig.value("joint1.state") == "OPERATION_ENABLED"
        model = rig.sim.model
        start = model.joints[0]
        rig.command("JOINTS", target1=start + 1.0)
        rig.run(0.3)
        moving = model.joints[0]
        assert drive.velocity > 500_000
        rig.command("DRIVES", joint1=float(AxisCode.QUICK_STOP))
        rig.run(0.5)
        assert drive.power is Power.QUICK_STOP and drive.velocity == 0
        assert drive.received[-1] == 0x02
        stopped = model.joints[0]
        assert moving < stopped < start + 1.0 - 0.2
        assert rig.value("joint1.state") == "QUICK_STOP_ACTIVE"
        assert rig.value("joint1") == float(AxisCode.QUICK_STOP)     # confirmed by the drive
        rig.command("JOINTS", target1=start)                          # not taken: no motion
        rig.run(0.3)
        assert model.joints[0] == pytest.approx(stopped)
        assert [d.power for d in servo.drives.values()][1:] == [Power.ENABLED] * 4
    finally:
        rig.close()
    assert rig.system.devtab.safe_failures == []
    for d in servo.drives.values():
        assert d.power is Power.SWITCH_ON_DISABLED
        assert d.model.history[-2:] == [Power.QUICK_STOP, Power.SWITCH_ON_DISABLED]
        assert d.received[-1] == 0x00                  # disable voltage, sent by the master
