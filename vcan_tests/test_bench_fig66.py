"""The figure 6.6 comparison systems: CHC execution counts match what the load implies (a
formula from the topology), the NBS side counts nine FSMs per cycle, latency runs are exact on
virtual time, and the emergency chain reaches every safe value."""

from __future__ import annotations

import math
from fractions import Fraction
from typing import Any

import pytest

from chcos.apps.bench import emergency, fig66
from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.errors import ConfigError
from chcos.kernel.clock import VirtualClock

RATES = {s: Fraction(10) for s in fig66.INPUTS}


def test_expected_rates_follow_the_topology() -> None:
    r = fig66.expected_rates(fig66.TOPOLOGY, RATES)
    # level 1: one execution per input message
    assert r["A1"] == RATES["S1"] + RATES["S2"]
    assert r["A2"] == RATES["S3"] and r["A3"] == RATES["testfile"]
    # level n+1: one message per five executions of each source
    assert r["B1"] == (r["A1"] + r["A2"]) / fig66.FAN_IN
    assert r["B2"] == (r["A2"] + r["A3"]) / fig66.FAN_IN
    assert r["C1"] == (r["B1"] + r["B2"]) / fig66.FAN_IN
    assert fig66.expected_rates({"T": ("X",)}, {"X": Fraction(7)}, fan_in=1) == {"T": 7}
    with pytest.raises(ConfigError, match="cycle"):
        fig66.expected_rates({"P": ("Q",), "Q": ("P",)}, {})
    with pytest.raises(ConfigError, match="neither"):
        fig66.expected_rates({"P": ("nope",)}, {})


@pytest.mark.parametrize("seed", [1, 2, 5])
def test_chcos_counts_match_the_load(seed: int) -> None:
    seconds = 10.0  # a multiple of the load's 2.5 s period: window counts are exact
    res = fig66.count_chcos(seconds, seed=seed)
    rates = fig66.expected_rates(fig66.TOPOLOGY, RATES)
    assert res.executions == {t: int(rates[t] * Fraction(seconds)) for t in fig66.TOPOLOGY}
    assert res.total == sum(rates.values()) * Fraction(seconds)
    assert res.messages == res.total          # one execution per message taken
    assert res.inputs == sum(RATES.values()) * Fraction(seconds)


@pytest.mark.parametrize("period", [0.028, 1 / 80])
def test_nbs_counts_nine_fsms_per_cycle_and_loses_nothing(period: float) -> None:
    res, extra = fig66.count_nbs(10.0, period)
    per = set(res.executions.values())
    assert len(res.executions) == 9 and len(per) == 1
    cycles = per.pop()
    assert abs(cycles - 10.0 / period) <= 1
    assert res.total == 9 * cycles
    assert extra["inputs_lost"] == 0
    assert extra["cycles"] == math.floor(12.5 / period + 1e-9)


def test_latency_runs_on_virtual_time() -> None:
    chc = fig66.latency_chcos_virtual(20.0)
    # S1, S2 (M1) and S3 (M2) react: 3 inputs x 10 Hz x 20 s, give or take the last events
    assert 3 * 10 * 20 - 3 <= len(chc) <= 3 * 10 * 20
    assert set(chc) == {0.0}
    probe, own = fig66.latency_nbs_virtual(20.0, 0.028)
    assert sorted(probe) == pytest.approx(sorted(own))
    assert len(probe) >= 3 * 10 * 20 - 6
    assert all(0.0 <= x <= 0.028 + 1e-9 for x in probe)


def test_load_rejects_bad_parameters() -> None:
    with pytest.raises(ConfigError):
        fig66.Load(rate_hz=0.0)
    with pytest.raises(ConfigError, match="jitter"):
        fig66.Load(jitter=0.2)
    a, b = fig66.Load(seed=4), fig66.Load(seed=4)
    assert a.phases == b.phases and len(set(a.phases.values())) == 4


def test_emergency_chain_reaches_every_safe_value_on_virtual_time() -> None:
    bus = BusSpec("mem", "memory")
    devs = [DeviceSpec(b, "sensor", 0, "mem") for b in (*emergency.BACKGROUND, "LC")]
    devs += [DeviceSpec(a, "actuator", 0, "mem", limits=(0.0, 4.0e9), safe_value=0.0)
             for a in emergency.ACTUATORS]
    s = emergency.build("unused", devices=DeviceMap((bus,), tuple(devs)), clock=VirtualClock())
    try:
        for k in range(1, 11):
            for b in emergency.BACKGROUND:
                s.devtab.inject(b, k)
            s.run_for(0.01)
        assert all(s.devtab.get(a).value == 11 for a in emergency.ACTUATORS)
        s.devtab.inject("LC", 1)
        s.run_for(0.1)
        assert all(s.devtab.get(a).value == 0.0 for a in emergency.ACTUATORS)
        assert all(s.tsktab.get(f"D{i}").frozen for i in range(4))
        assert s.tsktab.get("K").activations == 1
        for i in range(4):
            s.execute(f"resume D{i}")
        s.devtab.inject("B0", 15)
        s.run_for(0.1)
        s.devtab.inject("LC", 2)
        s.run_for(0.1)
        assert s.tsktab.get("K").activations == 2
        assert s.devtab.get("M0").value == 0.0
    finally:
        s.shutdown()


def test_emergency_probe_stamps_an_intruder_value_in_a_batch_too() -> None:
    """The emergency benchmark's probe between driver and Devtab sees the intruder value
    whether the driver hands readings over one by one or as a batch (the CAN driver's drains),
    and passes both on unchanged."""
    got: list[Any] = []
    stamps: list[float] = []

    class Host:
        def deliver(self, device: str, value: Any) -> None:
            got.append(("one", device, value))

        def deliver_many(self, readings: Any, at: float | None = None) -> None:
            got.append(("many", list(readings)))

    probe = emergency._HostProbe(Host(), stamps.append)
    probe.deliver_many([("D0", 5), ("LC", 0)])
    assert stamps == []
    probe.deliver_many([("D0", 6), ("LC", 1)])
    probe.deliver("LC", 2)
    assert len(stamps) == 2
    assert got == [("many", [("D0", 5), ("LC", 0)]), ("many", [("D0", 6), ("LC", 1)]),
                   ("one", "LC", 2)]
