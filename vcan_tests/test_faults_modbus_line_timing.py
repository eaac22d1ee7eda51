"""The timing of a Modbus RTU line and the thinning of a dead unit's requests (issue 38), pure:
the 3.5-character silence from the serial options, the back-off of a unit that stops answering,
and the warnings ``chcos check`` gives for a timeout the line's timing defeats."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from chcos.devices.devmap import check
from drivers.codecs.modbus import LineTiming, UnitBackoff


@pytest.mark.parametrize("line, char_ms, silence_ms", [
    (LineTiming(9600), 10 / 9.6, 3.5 * 10 / 9.6),                 # 8N1: 10 bits
    (LineTiming(19200, parity="E"), 11 / 19.2, 3.5 * 11 / 19.2),  # 8E1: 11 bits
    (LineTiming(9600, bytesize=7, stopbits=2), 10 / 9.6, 3.5 * 10 / 9.6),
    (LineTiming(38400), 10 / 38.4, 1.75),                         # above 19200: fixed 1.75 ms
    (LineTiming(115200, parity="O", stopbits=2), 12 / 115.2, 1.75),
])
def test_the_silence_is_three_and_a_half_characters(line: LineTiming, char_ms: float,
                                                   silence_ms: float) -> None:
    assert line.char_time * 1e3 == pytest.approx(char_ms)
    assert line.silence * 1e3 == pytest.approx(silence_ms)


def test_a_dead_unit_is_tried_ever_less_often_up_to_the_cap() -> None:
    units = UnitBackoff(cap=8)
    tried = []
    for turn in range(60):
        if units.due(2):
            tried.append(turn)
            units.silent(2)
        assert units.due(1)                       # the live unit is never held back
    gaps = [b - a for a, b in itertools.pairwise(tried)]
    assert gaps[:4] == [1, 2, 4, 8] and set(gaps[4:]) == {8}
    assert units.dead(2) and units.epoch(2) == 1  # one death, however many tries
    assert units.answered(2) and not units.dead(2) and units.due(2)
    assert not units.answered(2)                  # answering again is news only once
    assert units.silent(2) and units.epoch(2) == 2


MAP = """
[[bus]]
name = "line"
kind = "modbus-rtu"
port = "/dev/ttyUSB0"
baudrate = {baud}
timeout = {timeout}
{extra}

[[device]]
name = "a"
direction = "sensor"
bus = "line"
address = {{ unit = 1, table = "holding", address = 0, type = "float32" }}

[[device]]
name = "b"
direction = "sensor"
bus = "line"
address = {{ unit = 2, table = "input", address = 0, type = "uint16" }}

[[device]]
name = "wide"
direction = "sensor"
bus = "line"
address = {{ unit = 2, table = "input", address = 1, type = "float64" }}
"""


def run_check(tmp_path: Path, baud: int, timeout: float, extra: str = "") -> tuple[list[str],
                                                                                  list[str]]:
    path = tmp_path / "line.toml"
    path.write_text(MAP.format(baud=baud, timeout=timeout, extra=extra), encoding="utf-8")
    _, errors, warnings = check(path)
    return errors, warnings


def test_check_warns_about_a_timeout_the_line_cannot_keep(tmp_path: Path) -> None:
    # 1200 baud: unit 2's read of 5 registers is 8 + 15 bytes, 10 bits each, 192 ms and more
    errors, warnings = run_check(tmp_path, 1200, 0.15, "retries = 0\npoll_period = 1.0")
    assert errors == []
    assert [w for w in warnings if "shorter than the longest exchange" in w] == [
        w for w in warnings if "bus[0].timeout" in w and "1200 baud" in w]
    assert len(warnings) == 1 and "line.toml" in warnings[0]
    errors, warnings = run_check(tmp_path, 1200, 0.3, "retries = 0\npoll_period = 1.0")
    assert (errors, warnings) == ([], [])


def test_check_warns_when_a_dead_unit_costs_more_than_the_poll_period(tmp_path: Path) -> None:
    errors, warnings = run_check(tmp_path, 19200, 1.0)        # the defaults: 2 s per try
    assert errors == [] and len(warnings) == 1
    assert "bus[0].timeout" in warnings[0] and "holds the line 2 s per try" in warnings[0]
    assert "longer than the poll period 0.1 s" in warnings[0]
    assert "every 380 poll periods" in warnings[0]   # a twentieth of the line's time at most
    _, warnings = run_check(tmp_path, 19200, 1.0, "dead_unit_backoff = 20")
    assert "every 20 poll periods" in warnings[0]
    _, warnings = run_check(tmp_path, 19200, 0.04, "retries = 1")
    assert "holds the line 0.54 s per try" in warnings[0]     # 2 x 0.04 s, then the line guard
    _, warnings = run_check(tmp_path, 19200, 0.04, "retries = 1\nline_guard = 0.04")
    assert warnings == []                                     # slaves that are never deaf


def test_check_refuses_a_bad_dead_unit_backoff(tmp_path: Path) -> None:
    errors, _ = run_check(tmp_path, 19200, 0.04, "dead_unit_backoff = 0")
    assert len(errors) == 1 and "bus[0].dead_unit_backoff: expected an integer >= 1" in errors[0]
