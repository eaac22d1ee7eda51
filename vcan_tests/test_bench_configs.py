"""The benchmarks' own device maps stay valid: a map that ``chcos check`` refuses makes a
benchmark's satellites exit at start, which the benchmark sees only as "not up after 60 s"."""

from __future__ import annotations

from pathlib import Path

from chcos.devices import devmap
from tools import bench_satellites


def test_satellite_bench_map_passes_check(tmp_path: Path) -> None:
    devices = "".join(bench_satellites.DEVICE.format(m=m, lane=lane,
                                                     hz=bench_satellites.SAMPLE_HZ)
                      for m in range(2) for lane in bench_satellites.LANES)
    path = tmp_path / "devices.toml"
    path.write_text(bench_satellites.DEVMAP.format(devices=devices))
    loaded = devmap.load([path])
    assert {d.name for d in loaded.devices} == {"S0", "M0", "S1", "M1", "S0b", "M0b", "S1b",
                                                "M1b"}
