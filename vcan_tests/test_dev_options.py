"""Typed device-map options (chcos.devices.options): one dataclass per table, parsed once."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Literal

import pytest

from chcos.devices import devmap
from chcos.devices.options import (
    REQUIRED,
    between,
    defaults,
    option,
    parse,
    parsed,
    positive,
    reference,
)
from chcos.errors import ConfigError
from drivers.memory import MemoryDriver, MemoryOptions


class Parity(enum.StrEnum):
    NONE = "N"
    EVEN = "E"


@dataclass(frozen=True)
class Watchdog:
    address: int = option(doc="register", check=between(0, 65535))
    period: float = option(1.0, unit="s", doc="write period", check=positive)


@dataclass(frozen=True)
class LineOptions:
    port: str = option(REQUIRED, doc="serial port")
    baudrate: int = option(19200, doc="bit/s", check=between(1, 4_000_000))
    timeout: float = option(1.0, unit="s", doc="per request", check=positive)
    parity: Parity = option(Parity.NONE, doc="parity")
    stopbits: Literal[1, 2] = option(1, doc="stop bits")
    units: tuple[int, ...] = option(factory=tuple, doc="unit ids")
    watchdog: Watchdog | None = option(None, doc="watchdog register")
    echo: bool = option(False, doc="local echo")

    def problems(self) -> list[tuple[str, str]]:
        if self.echo and self.baudrate > 115200:
            return [("echo", "false above 115200 bit/s")]
        return []


def test_a_valid_table_becomes_the_dataclass_with_every_default_once() -> None:
    cfg, errors = parse(LineOptions, {"port": "/dev/ttyS0", "timeout": 2, "parity": "E",
                                      "units": [1, 2], "watchdog": {"address": 7}}, "bus[0]")
    assert errors == []
    assert cfg == LineOptions(port="/dev/ttyS0", timeout=2.0, parity=Parity.EVEN, units=(1, 2),
                              watchdog=Watchdog(address=7))
    assert isinstance(cfg.timeout, float) and cfg.baudrate == 19200 and cfg.stopbits == 1


def test_every_error_names_its_key_and_what_was_expected() -> None:
    cfg, errors = parse(LineOptions, {"baudrate": True, "timeout": -1.0, "parity": "X",
                                      "stopbits": 3, "units": [1, "two"], "speed": 9,
                                      "watchdog": {"address": 70000, "period": "fast"}},
                        "bus[3]")
    assert cfg is None
    assert sorted(errors) == sorted([
        "bus[3].speed: unknown key; expected one of baudrate, echo, parity, port, stopbits, "
        "timeout, units, watchdog",
        "bus[3].port: required; expected a string",
        "bus[3].baudrate: expected an integer, got True",
        "bus[3].timeout: expected a finite value > 0, got -1.0",
        "bus[3].parity: expected one of 'N', 'E', got 'X'",
        "bus[3].stopbits: expected one of 1, 2, got 3",
        "bus[3].units[1]: expected an integer, got 'two'",
        "bus[3].watchdog.address: expected an integer 0..65535, got 70000",
        "bus[3].watchdog.period: expected a number, got 'fast'",
    ])


def test_nan_is_no_number_and_a_cross_key_rule_is_an_error_of_its_key() -> None:
    assert parse(LineOptions, {"port": "p", "timeout": float("nan")}, "b")[1] == [
        "b.timeout: expected a number, got nan"]
    assert parse(LineOptions, {"port": "p", "echo": True, "baudrate": 230400}, "b")[1] == [
        "b.echo: expected false above 115200 bit/s"]


def test_parsed_raises_one_config_error_listing_every_error_with_the_file() -> None:
    with pytest.raises(ConfigError) as err:
        parsed(LineOptions, {"baudrate": 0}, "bus[0]", "cell.toml")
    assert str(err.value).splitlines() == [
        "cell.toml: bus[0].port: required; expected a string",
        "cell.toml: bus[0].baudrate: expected an integer 1..4000000, got 0"]
    with pytest.raises(ConfigError):
        defaults(LineOptions)
    assert defaults(MemoryOptions) == MemoryOptions(100)


def test_the_reference_is_generated_from_the_fields() -> None:
    keys = {k.name: k for k in reference(LineOptions)}
    assert list(keys) == ["port", "baudrate", "timeout", "parity", "stopbits", "units",
                          "watchdog", "echo"]
    assert (keys["port"].type, keys["port"].default) == ("string", "required")
    assert (keys["timeout"].type, keys["timeout"].default) == ("float s", "1.0")
    assert keys["parity"].default == '`"N"`' and "`N`, `E`" in keys["parity"].meaning
    assert (keys["watchdog"].type, keys["watchdog"].default) == ("inline table", "none")
    assert keys["echo"].default == "false"


def test_a_checked_map_carries_its_typed_options_to_the_driver(tmp_path) -> None:
    f = tmp_path / "m.toml"
    f.write_text('[[bus]]\nname = "b"\nkind = "memory"\nhistory = 7\n\n'
                 '[[device]]\nname = "M"\ndirection = "actuator"\nbus = "b"\nsafe_value = 0\n')
    dmap = devmap.load(f)
    assert dmap.bus("b").config == MemoryOptions(history=7)
    assert MemoryDriver.bus_options(dmap.bus("b"), MemoryOptions).history == 7
    f.write_text('[[bus]]\nname = "b"\nkind = "memory"\nhistory = 0\n')
    _, errors, _ = devmap.check(f)
    assert errors == [f"{f}:1: bus[0].history: expected an integer 1..1000000, got 0"]
