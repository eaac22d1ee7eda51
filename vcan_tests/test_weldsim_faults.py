"""WeldSim fault injection on real protocols (heartbeat loss, sensor dropouts) and determinism of
a System + simulator run on virtual time."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest

from chcos.apps.weld.faults import Fault
from vcan_tests.support_fb import WAIT
from vcan_tests.support_weldsim import QUIET, SENSORS, WeldRig, make_rig


def watch_failures(rig: WeldRig, monkeypatch: pytest.MonkeyPatch,
                   device: str) -> tuple[threading.Event, threading.Event]:
    """Events set when a driver reports ``device`` failed / recovered (from its own thread)."""
    failed, recovered = threading.Event(), threading.Event()
    devtab = rig.system.devtab
    fail, recover = devtab.fail, devtab.recover

    def on_fail(name: str, reason: str) -> None:
        fail(name, reason)
        if name == device:
            failed.set()

    def on_recover(name: str, reason: str = "") -> None:
        recover(name, reason)
        if name == device:
            recovered.set()

    monkeypatch.setattr(devtab, "fail", on_fail)
    monkeypatch.setattr(devtab, "recover", on_recover)
    return failed, recovered


def test_servo_timeout_stops_heartbeat_and_tpdo_and_fails_the_joint(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rig = make_rig(tmp_path, config=QUIET)
    try:
        failed, recovered = watch_failures(rig, monkeypatch, "theta2")
        rig.run(0.2)
        assert all(rig.status(f"theta{n}") == "OK" for n in range(1, 6))
        rig.sim.inject(Fault("servo-timeout", joint=2, duration=0.3))
        before = rig.entry("theta2").readings
        # no TPDO of node 2 any more: stale on sim time (0.12 s: past stale_after 0.1 s, and
        # short in wall time, well before the heartbeat timeout of 0.5 s wall on a loaded host)
        rig.run(0.12)
        assert rig.entry("theta2").readings == before
        assert rig.status("theta2") == "stale" and rig.status("theta1") == "OK"
        assert failed.wait(WAIT), "the driver did not notice the missing heartbeat"
        rig.run(0.001)
        assert rig.status("theta2") == "failed" and "no heartbeat" in rig.entry("theta2").reason
        assert rig.status("target2") == "failed"          # every device of node 2
        assert rig.status("theta3") == "OK" and rig.status("target3") == "OK"
        rig.run(0.2)                           # the 0.3 s timeout is over: heartbeat back
        assert recovered.wait(WAIT), "the driver did not see the heartbeat return"
        rig.run(0.05)
        assert rig.status("theta2") == "OK" and rig.entry("theta2").readings > before
    finally:
        rig.close()


def test_sensor_dropouts_make_devices_stale_or_failed_alone(tmp_path: Path) -> None:
    rig = make_rig(tmp_path, config=QUIET)
    try:
        rig.run(0.3)
        assert {n: rig.status(n) for n in SENSORS} == dict.fromkeys(SENSORS, "OK")
        for sensor in ("arc_temperature", "linear_sensor", "joint4", "gap_markers",
                       "arc_voltage"):
            rig.sim.inject(f"sensor-dropout({sensor})")
        rig.run(0.5)
        stale = {"arc_temp", "linear", "range", "theta4", "start_marker", "end_marker"}
        assert {n for n in SENSORS if rig.status(n) == "stale"} == stale
        # a Modbus register cannot stay silent: the power source answers exception 11 for it
        assert {n for n in SENSORS if rig.status(n) == "failed"} == {"arc_volts"}
        assert "exception code 11" in rig.entry("arc_volts").reason
        assert rig.status("target4") == "OK"   # heartbeat still there: a sensor dropout only
    finally:
        rig.close()


def test_dropout_for_a_while_recovers(tmp_path: Path) -> None:
    rig = make_rig(tmp_path, config=QUIET)
    try:
        rig.run(0.1)
        rig.sim.inject("sensor-dropout(gas_flow;for=0.4s)")
        rig.run(0.3)
        assert rig.status("gas_flow") == "failed"
        rig.run(0.3)
        assert rig.status("gas_flow") == "OK"
    finally:
        rig.close()


SCENARIO = ("intruder(for=0.1s)@t=0.25s,sensor-dropout(arc_temperature;for=0.2s)@t=0.4s,"
            "gas-empty@t=0.7s")
SAMPLES = [0.0123 + 0.05 * k for k in range(20)]


def record_run(tmp_path: Path, attach_first: bool) -> list[tuple[float, dict[str, Any]]]:
    """One scripted run with noise and faults: the devices' (value, status, time of value) at
    fixed virtual times, plus the model's joints."""
    rig = make_rig(tmp_path, scenario=SCENARIO, seed=7, attach_first=attach_first)
    out: list[tuple[float, dict[str, Any]]] = []
    try:
        q = rig.sim.model.arm.inverse_down((540.0, -120.0, 40.0), 1.2)
        script = {2: lambda: rig.command("POWER", drives_enable=1, volts_set=24.0,
                                         wire_set=90.0, gas_valve=1),
                  3: lambda: rig.command("DRIVES", **{f"joint{n}": 1.0 for n in range(1, 6)}),
                  4: lambda: rig.command("JOINTS", **{f"target{j + 1}": v
                                                      for j, v in enumerate(q)}),
                  12: lambda: rig.command("POWER", drives_enable=0)}
        for k, t in enumerate(SAMPLES):
            if k in script:
                script[k]()
            rig.system.run(t)
            snap: dict[str, Any] = {n: (rig.value(n), rig.status(n), rig.entry(n).updated_at)
                                    for n in SENSORS}
            snap["joints"] = tuple(rig.sim.model.joints)
            out.append((rig.system.kernel.clock.now(), snap))
    finally:
        rig.close()
    return out


def test_two_runs_of_a_scenario_give_identical_readings(tmp_path: Path) -> None:
    first = record_run(tmp_path / "a", attach_first=False)
    second = record_run(tmp_path / "b", attach_first=True)  # attached before the boot
    assert [t for t, _ in first] == pytest.approx(SAMPLES)
    assert first == second
    by_time = dict(first)
    mid = by_time[SAMPLES[6]]                  # t = 0.31: the intruder is in the curtain
    assert mid["intruder"][0] == 1
    assert by_time[SAMPLES[10]]["arc_temp"][1] == "stale"   # t = 0.51: pyrometer silent
    assert by_time[SAMPLES[14]]["arc_temp"][1] == "OK"      # t = 0.71: back since 0.6 s
    assert by_time[SAMPLES[-1]]["gas_bottle"][0] == 0.0     # the bottle emptied at 0.7 s
    assert first[3][1]["joints"] != first[-1][1]["joints"]  # the arm moved meanwhile
