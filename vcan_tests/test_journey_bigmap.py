"""The satellites' ``map`` answer, paged (issue 39): a system of 10,000 devices, whose map is
several MiB of JSON (the link carries at most 1 MiB a message), is read whole by ``chcos host``
and the viewer's Host.map_doc; the request's wire form and its refusals."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from chcos.errors import CommandSyntaxError
from chcos.satellites import control
from chcos.system.textview import render_text
from vcan_tests.support_sat import DEVMAP, Cluster

N = 10_000


def test_map_request_pages_survive_the_wire() -> None:
    for req in (control.MapRequest(), control.MapRequest(3, "0-12")):
        assert control.decode(control.encode(req)) == req
    assert control.decode(b'{"op": "map"}') == control.MapRequest()
    with pytest.raises(TypeError, match="part: expected a page number"):
        control.decode(b'{"op": "map", "part": -1}')
    with pytest.raises(TypeError, match="token: expected a map answer's token"):
        control.decode(b'{"op": "map", "token": 7}')


def test_a_map_of_ten_thousand_devices_is_read_whole(tmp_path: Path) -> None:
    cluster = Cluster(tmp_path, machines=(0,))
    many = "".join(f'\n[[device]]\nname = "sensor_with_a_long_name_{i:05d}"\n'
                   f'direction = "sensor"\nmachine = 0\nbus = "mem"\n' for i in range(N))
    (tmp_path / "devices.toml").write_text(DEVMAP + many, encoding="utf-8")
    try:
        cluster.start(0)
        host = cluster.host
        host.wait_for([0], timeout=60)
        host.execute("install -m0 sysfile")
        doc = host.map_doc()
        names = {d["name"] for d in doc["devices"]}
        assert {f"sensor_with_a_long_name_{i:05d}" for i in range(N)} <= names
        assert len(json.dumps(doc)) > 2 * 1024 * 1024   # more than one link message carries
        assert f"sensor_with_a_long_name_{N - 1:05d}" in render_text(doc)   # chcos host map
        assert host.rejected(0) is not None
        # host input capped before it is sent: the satellite never sees a malformed request
        with pytest.raises(CommandSyntaxError, match=f"at most {control.MAX_LINE}"):
            host.execute("invoke T x=" + "1" * (control.MAX_LINE + 10))
        assert host.rejected(0) == {}
    finally:
        cluster.close()
