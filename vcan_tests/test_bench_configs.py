"""The benchmarks' own device maps stay valid: a map that ``chcos check`` refuses makes a
benchmark's satellites exit at start, which the benchmark sees only as "not up after 60 s"."""

from __future__ import annotations

from pathlib import Path

import pytest

from chcos.devices import devmap
from tools import bench_satellites


@pytest.mark.parametrize("kind", sorted(bench_satellites.LOADS))
def test_satellite_bench_map_passes_check(tmp_path: Path, kind: str) -> None:
    path = tmp_path / "devices.toml"
    path.write_text(bench_satellites.device_map(2, kind))
    loaded = devmap.load([path])
    assert {d.name for d in loaded.devices} == {"S0", "M0", "S1", "M1", "S0b", "M0b", "S1b",
                                                "M1b"}
    if kind == "echo":
        assert {d.name: d.address["actuator"] for d in loaded.devices
                if d.direction == "sensor"} == {"S0": "M0", "S1": "M1", "S0b": "M0b",
                                                "S1b": "M1b"}
