"""The welding cell's parts: the direct binding, the linear-image analysis, the tracker, the
exception task's patterns and context, and the hierarchy the install script builds."""

from __future__ import annotations

import io
import math
from pathlib import Path

import pytest

from chcos.apps.sim.cia402_drive import Power
from chcos.apps.weld import Seam
from chcos.apps.weld.cell import _direct_map, open_cell
from chcos.apps.weld.direct import WeldDirectDriver
from chcos.apps.weld.runner import main, run
from chcos.apps.weld.tasks import B1, D3
from chcos.apps.weld.tasks.common import Tracker, analyse, offset_mm
from chcos.apps.weld.tasks.sensed import ArcTemp, SensorFailed, WeldState
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.tables.messages import LinkType
from drivers.canopen_axis import AxisCode


def booted(tmp_path: Path, scenario: str = "") -> System:
    s = System(_direct_map(scenario, 0), clock=VirtualClock(), base_dir=tmp_path)
    s.execute("install -m0 sysfile")
    return s


def driver(s: System) -> WeldDirectDriver:
    d = s.devtab.drivers[0]
    assert isinstance(d, WeldDirectDriver)
    return d


# ---- the direct binding ----------------------------------------------------------------------
def test_direct_binding_delivers_at_the_bus_rates(tmp_path: Path) -> None:
    with booted(tmp_path) as s:
        s.run_for(1.0)
        n = {d.name: d.readings for d in s.devtab if d.is_sensor}
    assert n["theta1"] == n["theta5"] == 100
    assert n["arc_temp"] == n["linear"] == n["range"] == n["intruder"] == 50
    assert n["start_marker"] == n["end_marker"] == 20
    assert n["gas_bottle"] == n["arc_volts"] == n["wire_speed"] == 20


def test_direct_binding_honours_dropouts_and_servo_timeouts(tmp_path: Path) -> None:
    scenario = "sensor-dropout(arc_temperature)@t=0.5s,servo-timeout(2;for=0.3s)@t=0.5s"
    with booted(tmp_path, scenario) as s:
        s.run_for(0.7)
        assert s.devtab.get("arc_temp").status.value == "stale"
        assert s.devtab.get("theta2").status.value == "failed"
        assert "servo drive of joint 2" in s.devtab.get("theta2").reason
        assert s.devtab.get("theta1").status.value == "OK"
        temps = s.devtab.get("arc_temp").readings
        s.run_for(0.5)
        assert s.devtab.get("arc_temp").readings == temps  # silent for good
        assert s.devtab.get("theta2").status.value == "OK"  # the servo came back


def test_direct_binding_applies_actuators_and_holds_joints_when_disabled(tmp_path: Path) -> None:
    with booted(tmp_path) as s:
        drv = driver(s)
        cell = drv.cell
        drive = drv.drives[0]
        s.devtab.write("volts_set", 24.0)
        s.devtab.write("gas_valve", 1.0)
        s.devtab.write("wire_set", 80.0)
        assert (cell.voltage_setpoint, cell.gas_valve, cell.wire_setpoint) == (24.0, True, 80.0)
        before = list(cell.joints)
        # the relay on, the drive not enabled: a target does not move the joint
        s.devtab.write("drives_enable", 1.0)
        s.devtab.write("target1", before[0] + 0.3)
        s.run_for(0.5)
        assert cell.joints == pytest.approx(before)
        assert drive.power is Power.SWITCH_ON_DISABLED and drive.ignored_targets == 1
        # enabled through the axis (the command code), confirmed by the drive's statusword
        s.devtab.write("joint1", float(AxisCode.ENABLE))
        s.run_for(0.2)
        assert drive.power is Power.ENABLED
        assert drive.received[:3] == [0x06, 0x07, 0x0F]
        assert s.devtab.get("joint1").value == float(AxisCode.ENABLE)       # confirmed
        assert s.devtab.get("joint1.state").value == "OPERATION_ENABLED"
        # the relay off: the joint is held whatever its drive's state
        s.devtab.write("drives_enable", 0.0)
        s.devtab.write("target1", before[0] + 0.3)
        s.run_for(0.5)
        assert cell.joints == pytest.approx(before)
        s.devtab.write("drives_enable", 1.0)
        s.devtab.write("target1", before[0] + 0.3)
        s.run_for(0.5)
        assert cell.joints[0] == pytest.approx(before[0] + 0.3)
        assert s.devtab.get("joint1.position").value == pytest.approx(before[0] + 0.3, abs=1e-3)
        drv.write("wire_set", 999.0)  # past the Devtab check: the model refuses
        s.run_for(0.01)
        assert s.devtab.bus_errors[("cell", "refused")] == 1
        assert cell.wire_setpoint == 80.0


def test_direct_binding_quick_stop_decelerates_the_joint_and_the_safe_stop_disables(
        tmp_path: Path) -> None:
    """The in-process axis on the same drive model: a quick stop while the joint moves slows it
    down on the drive's ramp (it does not stop dead, nor run on to the target), and the safe
    stop (the axis's safe value) ends with the voltage disabled once it stands."""
    with booted(tmp_path) as s:
        drv = driver(s)
        cell = drv.cell
        drive = drv.drives[0]
        s.devtab.write("drives_enable", 1.0)
        s.devtab.write("joint1", float(AxisCode.ENABLE))
        s.run_for(0.2)
        start = cell.joints[0]
        s.devtab.write("target1", start + 1.0)          # 1 rad away: about 1 s at full speed
        s.run_for(0.3)
        moving = cell.joints[0]
        assert drive.velocity > 500_000                     # counts/s: over 0.5 rad/s
        s.devtab.write("joint1", float(AxisCode.QUICK_STOP))
        s.run_for(0.5)
        assert drive.power is Power.QUICK_STOP and drive.velocity == 0
        stopped = cell.joints[0]
        assert moving < stopped < start + 1.0 - 0.2         # braked, short of the target
        assert s.devtab.get("joint1").value == float(AxisCode.QUICK_STOP)  # confirmed
        s.devtab.write("target1", start)                    # ignored in QUICK STOP ACTIVE
        s.run_for(0.3)
        assert cell.joints[0] == pytest.approx(stopped)
        s.devtab.write("joint1", float(AxisCode.SAFE_STOP))
        s.run_for(0.3)
        assert drive.power is Power.SWITCH_ON_DISABLED
        assert drive.received[-2:] == [0x02, 0x00]          # quick stop, then disable voltage
        assert s.devtab.get("joint1.state").value == "SWITCH_ON_DISABLED"


def test_direct_binding_checks_its_options_and_addresses() -> None:
    bus = BusSpec("cell", "weld-direct", {"scenario": "tip-stuck@x=1", "tick": 0.5, "speed": 1},
                  key="bus[0]")
    errs = WeldDirectDriver.check_bus(bus)
    assert len(errs) == 3
    assert any("bus[0].speed: unknown key" in e for e in errs)
    assert any("bus[0].scenario:" in e and "trigger" in e for e in errs)
    assert any("bus[0].tick:" in e for e in errs)
    dev = DeviceSpec("nozzle", "sensor", 0, "cell", key="device[3]")
    (err,) = WeldDirectDriver.check_device(bus, dev)
    assert "device[3].address.signal: 'nozzle' is not a sensor of the welding cell" in err
    ok = DeviceSpec("T", "sensor", 0, "cell", address={"signal": "arc_temp"})
    assert WeldDirectDriver.check_device(bus, ok) == []
    axis = DeviceSpec("joint9", "actuator", 0, "cell", key="device[7]",
                      address={"profile": "cia402", "node": 9, "axis": 1})
    errs = WeldDirectDriver.check_device(bus, axis)
    assert any("device[7].address.node: 9 is no joint drive" in e for e in errs), errs
    assert any("device[7].address.axis:" in e for e in errs), errs


# ---- the linear image and the tracker --------------------------------------------------------
def view(seam: Seam, s: float, lateral: float = 0.0) -> str:
    x, y = seam.centre(s)
    h = seam.heading(s)
    x, y = x - lateral * math.sin(h), y + lateral * math.cos(h)
    v = seam.sense(x, y, 10.0, h + math.pi / 2)
    return "".join("1" if p else "0" for p in v.pixels)


def test_linear_images_of_the_seam_are_classified() -> None:
    seam = Seam()
    gap = analyse(view(seam, 40.0))
    assert gap.pattern == "gap" and gap.centre is not None and abs(gap.centre) <= 0.5
    assert gap.width is not None and 1.5 <= gap.width <= 2.5
    shifted = analyse(view(seam, 40.0, lateral=1.5))  # sensor 1.5 mm left: gap 1.5 mm right
    assert shifted.centre == pytest.approx(-1.5, abs=0.5)
    start = analyse(view(seam, 0.5))
    assert start.pattern == "start" and start.marker_centre == pytest.approx(0.0, abs=0.5)
    end = analyse(view(seam, seam.length + 3.0, lateral=2.0))
    assert end.pattern == "end" and end.marker_centre == pytest.approx(-2.0, abs=0.5)
    assert analyse("0" * 64).pattern == "none"
    assert offset_mm(63) == pytest.approx(15.75)


def test_tracker_predicts_and_steers_towards_the_gap() -> None:
    t = Tracker(heading=0.0, z_work=10.0)
    for k in range(6):  # tip moving along +x, the gap 1 mm to its left (+y), sensor 5 mm ahead
        t.sighting((float(k), 0.0, 10.0), 0.0, 1.0)
    assert t.heading == pytest.approx(0.0, abs=1e-9)
    nxt = t.predict(5.0)
    assert nxt is not None and nxt == pytest.approx((15.0, 1.0))
    d, yaw = t.steer((5.0, 0.0, 12.0))
    assert d[1] > 0 and d[0] > 0.9 and d[2] < 0  # towards the gap, and down to 10 mm
    assert yaw == pytest.approx(0.0)


# ---- D3's patterns and B1's context ----------------------------------------------------------
def test_exception_patterns() -> None:
    c = D3.classify
    assert c("A1", SensorFailed("arc_temp", "stale", 1.0), 400, 2600) == (
        "sensor failure", "arc_temp (reported by A1): stale")
    assert c("A1", ArcTemp(1500.0, None, None), 400, 2600) == ("heat?",
                                                              "arc temperature 1500 degC")
    assert c("A1", ArcTemp(2700.0, None, None), 400, 2600)[0] == "overheat"  # type: ignore[index]
    assert c("A1", ArcTemp(300.0, None, None), 400, 2600) is None
    assert c("B1", WeldState("fail", "gas fail"), 400, 2600) is None


def test_heat_is_expected_while_welding_and_while_cooling() -> None:
    wm = B1.WeldModel()
    assert not wm.answer("heat_expected", 10.0)
    wm.command["weld"] = "on"
    assert wm.answer("welding") and wm.answer("heat_expected", 10.0)
    wm.command.update(weld="off", off_at=10.0)
    assert wm.answer("heat_expected", 10.0 + B1.COOLING_S - 1)
    assert not wm.answer("heat_expected", 10.0 + B1.COOLING_S + 1)


# ---- the hierarchy ---------------------------------------------------------------------------
def test_install_script_builds_the_appendix_2_hierarchy(tmp_path: Path) -> None:
    with open_cell(workdir=tmp_path) as cell:
        s = cell.system
        levels = {t.name: t.level for t in s.tsktab}
        assert levels == {**{f"A{i}": 1 for i in range(1, 8)}, **{f"B{i}": 2 for i in range(1, 6)},
                          "C1": 3, "C2": 3, "D1": 4, "D2": 4, "D3": 4, "E1": 5, "E2": 5}
        roles = {t.name: t.role.value for t in s.tsktab if t.role.value != "task"}
        assert roles == {"D3": "exception", "E1": "assassin"}
        taps = {lk.src for lk in s.msgtab
                if lk.dst == "D3" and lk.tap and lk.type is LinkType.SENSORY}
        assert taps == {n for n, lv in levels.items() if lv < 4}
        e1 = s.tsktab.get("E1")
        assert set(e1.special_links) == {n for n, lv in levels.items() if lv < 5} - {"B2", "A6"}
        assert s.msgtab.find("E1", "B2").priority == 99
        assert s.msgtab.find("B2", "A4").priority == 90
        assert s.msgtab.get("D3", "E1", LinkType.SENSORY) is not None
        assert (tmp_path / "sysfile.map").is_file()


def test_unexpected_heat_while_only_inspecting_is_an_alarm(tmp_path: Path) -> None:
    with open_cell(workdir=tmp_path) as cell:
        cell.start_job({"inspect_only": True})
        cell.run(14.0)
        assert cell.phase() == "inspect/track"
        # someone switches the power source on behind the hierarchy's back
        cell.system.invoke("A2", {"volts": 24.0}, priority=50)
        cell.run(2.0)
        alarms = cell.world("D3")["sensory"]["alarms"]
        assert [a["alarm"] for a in alarms] == ["unexpected heat"]
        outcome = cell.outcome()
        assert outcome is not None and outcome["outcome"] == "aborted"
        assert cell.outputs()["volts_set"] == 0.0 and cell.model.voltage_setpoint == 0.0


def test_the_hierarchy_runs_on_the_real_buses_too(tmp_path: Path) -> None:
    with open_cell("buses", workdir=tmp_path) as cell:
        cell.run(0.5, until_done=False)
        s = cell.system
        assert all(s.devtab.get(f"theta{j}").status.value == "OK" for j in range(1, 6))
        pos = cell.world("A4")["sensory"]["pos"]  # T5 from the CANopen TPDOs, via A4
        assert pos == pytest.approx(cell.model.pose.position, abs=0.5)
        assert s.devtab.get("arc_temp").readings >= 20  # raw CAN, every 20 ms
        assert s.devtab.get("gas_bottle").readings >= 5  # Modbus TCP


def test_run_prints_progress_each_second_and_a_summary(tmp_path: Path) -> None:
    out = io.StringIO()
    summary = run(scenario="intruder(for=1s)@t=2.5s", duration=4.0, workdir=tmp_path, out=out)
    text = out.getvalue()
    progress = [ln for ln in text.splitlines() if ln.startswith("  t=")]
    assert [ln.split()[0] for ln in progress] == ["t=", "t=", "t="]  # 1, 2, 3 s: then aborted
    assert "inspect/search" in progress[0] and "messages/s" in progress[0]
    assert "job outcome: aborted (intruder: light curtain broken)" in text
    assert "assassin reaction (intruder interrupt -> all safe values): 0.00 ms" in text
    assert summary["outcome"]["outcome"] == "aborted"
    assert summary["latency_s"] == [0.0]
    assert set(summary["steps_by_level"]) == {1, 2, 3, 4, 5}


def test_main_reports_a_bad_scenario(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--scenario", "meteor@t=1s"]) == 2
    assert "unknown fault kind 'meteor'" in capsys.readouterr().err


def test_a_quick_stop_asked_during_the_safe_stop_joins_it(tmp_path: Path) -> None:
    """An e-stop's safe stop, then the quick stop of the task that stops the arm (A6 through
    B2): one sequence on the wire (quick stop, then disable voltage), both callers told it
    ended well, the safe value confirmed; before, the quick stop superseded the safe stop,
    which then failed."""
    from drivers.canopen_axis import AxisCall
    from drivers.codecs.cia402 import Op, Result

    with booted(tmp_path) as s:
        drv = driver(s)
        drive = drv.drives[2]
        s.devtab.write("drives_enable", 1.0)
        s.devtab.write("joint3", float(AxisCode.ENABLE))
        s.run_for(0.2)
        assert drive.power is Power.ENABLED
        got: list[Result | Exception] = []
        s.devtab.write("joint3", float(AxisCode.SAFE_STOP))
        assert drv.axis_status("joint3").busy is Op.SAFE_STOP
        drv.axis_call("joint3", AxisCall(Op.QUICK_STOP), got.append)
        s.run_for(0.3)
        assert len(got) == 1 and isinstance(got[0], Result) and got[0].ok, got
        assert drive.power is Power.SWITCH_ON_DISABLED
        assert drive.received[3:] == [0x02, 0x00]
        assert s.devtab.get("joint3").value == float(AxisCode.SAFE_STOP)
        assert s.devtab.safe_failures == []
