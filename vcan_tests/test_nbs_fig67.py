"""The figure 6.6/6.7 system of thesis 6.4 run as NBS: counted executions, inputs, outputs."""

from __future__ import annotations

import pytest

from chcos.apps.nbs.fig67 import FAN_IN, SENSORS, main, run_fig67
from chcos.apps.nbs.scheduling import VirtualScheduler
from chcos.errors import ConfigError, KernelError


def test_28ms_cycle_for_10s_counts_every_fsm_every_cycle() -> None:
    r = run_fig67(VirtualScheduler(), 10.0)
    assert r.cycles == 357
    assert r.executions == {f"{k}{n}": 357 for n in (1, 2, 3) for k in "GMH"}
    assert r.total_executions == 3213
    assert r.executions_per_second == pytest.approx(321.3)


def test_80hz_polling_gives_the_thesis_720_per_second() -> None:
    r = run_fig67(VirtualScheduler(), 10.0, period=1 / 80)
    assert r.total_executions == 9 * 800
    assert r.executions_per_second == pytest.approx(720.0)


def test_inputs_and_fan_in_outputs_are_counted() -> None:
    r = run_fig67(VirtualScheduler(), 10.0)
    assert r.inputs_produced == dict.fromkeys(SENSORS, 100)
    seen = sum(r.inputs_seen.values())
    assert r.lost == 0  # a 28 ms poll never misses a 100 ms input
    assert seen + r.unpolled == 400
    assert r.unpolled == 4  # the values of t = 10.0 s arrive after the last cycle (9.996 s)
    assert r.outputs == {1: seen // FAN_IN, 2: seen // FAN_IN**2, 3: seen // FAN_IN**3}
    assert r.outputs == {1: 79, 2: 15, 3: 3}


def test_reactions_follow_figure_6_5_and_latency_is_below_one_cycle() -> None:
    r = run_fig67(VirtualScheduler(), 10.0)
    # every poll that saw new S1/S2 values wrote M1 once, every new S3 value wrote M2 once
    assert r.actuator_writes == 2 * 99
    assert {(x.sensor, x.actuator) for x in r.latencies} == {
        ("S1", "M1"), ("S2", "M1"), ("S3", "M2")}
    assert len(r.latencies) == 3 * 99
    assert r.latency_max is not None and r.latency_max <= 0.028 + 1e-12
    assert r.latency_mean is not None and 0 < r.latency_mean < 0.028


def test_polling_slower_than_the_inputs_loses_values() -> None:
    r = run_fig67(VirtualScheduler(), 10.0, period=0.15)
    assert r.cycles == 66
    assert r.lost > 0
    assert sum(r.inputs_seen.values()) + r.lost + r.unpolled == 400
    assert r.latency_max is not None and r.latency_max <= 0.15 + 1e-12


def test_bad_arguments_are_rejected() -> None:
    with pytest.raises(ConfigError, match="run time"):
        run_fig67(VirtualScheduler(), 0)
    with pytest.raises(ConfigError, match="fan_in"):
        run_fig67(VirtualScheduler(), 1.0, fan_in=0)
    with pytest.raises(ConfigError, match="input rate"):
        run_fig67(VirtualScheduler(), 1.0, input_rate_hz=0)
    with pytest.raises(KernelError, match="period"):
        run_fig67(VirtualScheduler(), 1.0, period=0)


def test_command_line_prints_the_counts() -> None:
    lines: list[str] = []
    assert main(["--seconds", "1", "--period", "0.0125"], out=lines.append) == 0
    assert lines[0] == "cycles 80 in 1 s (period 12.5 ms)"
    assert lines[1] == "FSM executions 720 (720.0/s)"
