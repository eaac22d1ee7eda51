"""The north side started from a running system: Prometheus metrics read at scrape time (parsed
by prometheus-client's own text parser), the flags of ``chcos run``, and every service attached
to the welding job while it runs (the view, metrics, the Modbus facade read by pyModbusTCP, OPC
UA read by python-opcua)."""

from __future__ import annotations

import argparse
import io
import threading
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.errors import DeviceError
from chcos.kernel.clock import VirtualClock
from chcos.north import NorthError
from chcos.north.metrics import serve as serve_metrics
from chcos.north.services import NorthOptions, add_north_arguments, host_port
from chcos.system.embedded import System
from vcan_tests.support_view import get_json

ME = "vcan_tests.support_view"
TIMEOUT = 30.0
_opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def scrape(url: str) -> dict[str, list[Any]]:
    """Samples by metric family name."""
    with _opener.open(url, timeout=TIMEOUT) as resp:
        text = resp.read().decode()
    out: dict[str, list[Any]] = {}
    for fam in text_string_to_metric_families(text):
        out.setdefault(fam.name, []).extend(fam.samples)
    return out


def value(samples: list[Any], name: str, **labels: str) -> float:
    """The one sample called ``name`` with ``labels``."""
    hits = [s.value for s in samples if s.name == name and
            all(s.labels.get(k) == v for k, v in labels.items())]
    assert len(hits) == 1, (name, labels, hits)
    return float(hits[0])


def test_metrics_from_the_tables(tmp_path: Path) -> None:
    devmap = DeviceMap((BusSpec("mem", "memory"),), (
        DeviceSpec("P1", "sensor", 0, "mem", units="bar", stale_after=0.5),
        DeviceSpec("V1", "actuator", 0, "mem", safe_value=0.0, limits=(-100, 100))))
    s = System(devmap, clock=VirtualClock(), base_dir=tmp_path)
    for line in ("install -m0 sysfile", f"install -m0i1o1 --code={ME}:follow T1 P1 V1",
                 "invoke T1"):
        s.execute(line)
    m = serve_metrics(s)
    try:
        for k in range(5):
            s.execute(f"inject P1 {k}.5")
            s.run_for(0.1)
        s.call(s.devtab.write, "V1", 7.0)
        with pytest.raises(DeviceError, match="outside its limits"):
            s.devtab.write("V1", 1000.0, "test")
        got = scrape(m.url)
        assert m.url.startswith("http://127.0.0.1:")
        assert value(got["chcos_device_value"], "chcos_device_value", device="P1",
                     units="bar") == 4.5
        assert value(got["chcos_device_age_seconds"], "chcos_device_age_seconds",
                     device="P1") == pytest.approx(0.1, abs=1e-9)
        assert value(got["chcos_device_healthy"], "chcos_device_healthy", device="P1") == 1
        assert value(got["chcos_device_rejected"], "chcos_device_rejected_total",
                     device="V1") == 1
        assert value(got["chcos_device_readings"], "chcos_device_readings_total",
                     device="P1") == 5
        t1 = s.tsktab.get("T1")
        assert value(got["chcos_task_executions"], "chcos_task_executions_total",
                     task="T1") == t1.steps
        lk = s.msgtab.find("P1", "T1")
        for what in ("sent", "delivered", "overwritten"):
            assert value(got[f"chcos_link_{what}"], f"chcos_link_{what}_total", link="P1/T1",
                         type="sensory") == getattr(lk, what)
        hist = got["chcos_task_step_seconds"]
        # every step of T1 ran after the metrics started: each one is in the histogram
        assert value(hist, "chcos_task_step_seconds_count", task="T1") == t1.steps > 0
        assert value(hist, "chcos_task_step_seconds_bucket", task="T1", le="+Inf") == t1.steps
        lat = got["chcos_task_schedule_latency_seconds"]
        # made ready by the invoke before the metrics started, the first step has no latency
        assert value(lat, "chcos_task_schedule_latency_seconds_count", task="T1") == \
            t1.steps - 1
        # P1 goes stale: the next scrape says so, with no change on the hot path
        s.run_for(1.0)
        got = scrape(m.url)
        assert value(got["chcos_device_healthy"], "chcos_device_healthy", device="P1") == 0
        assert value(got["chcos_device_status"], "chcos_device_status", device="P1",
                     status="stale") == 1
        assert "chcos_bus_devices" in got
    finally:
        m.stop()
        s.shutdown()
    with pytest.raises(NorthError, match="needs TLS"):
        serve_metrics(s, "192.0.2.1", 0)


def test_flags_and_addresses() -> None:
    ap = argparse.ArgumentParser()
    add_north_arguments(ap)
    args = ap.parse_args(["--view", "--metrics", "127.0.0.1:0", "--opcua"])
    opts = NorthOptions.from_args(args)
    assert (opts.view, opts.metrics, opts.modbus_facade) == ("127.0.0.1:8765", "127.0.0.1:0",
                                                            None)
    assert opts.opcua == "opc.tcp://127.0.0.1:4840/chcos/" and opts.any
    assert not NorthOptions.from_args(ap.parse_args([])).any
    assert host_port("[::1]:80", "view") == ("::1", 80)
    with pytest.raises(NorthError, match="--view 'nope': expected HOST:PORT"):
        host_port("nope", "view")


def _stream_until(url: str, pred: Any) -> bool:
    """Follow the view's stream (snapshot, then merge patches) until ``pred(state)``."""
    import json

    state: dict[str, Any] = {}

    def merge(target: Any, patch: Any) -> Any:
        if not isinstance(patch, dict):
            return patch
        target = target if isinstance(target, dict) else {}
        for k, v in patch.items():
            if v is None:
                target.pop(k, None)
            else:
                target[k] = merge(target.get(k), v)
        return target

    with _opener.open(url, timeout=TIMEOUT) as resp:
        for raw in resp:
            line = raw.decode().rstrip("\n")
            if not line.startswith("data: "):
                continue
            msg = json.loads(line[6:])
            state = msg["state"] if msg["type"] == "snapshot" else merge(state, msg["patch"])
            if pred(state):
                return True
    return False


class _Lines(io.StringIO):
    """Output that signals when the job has printed ``marker`` (by default the first host
    answer, which the welding job prints after the services' addresses)."""

    def __init__(self, marker: str = "  host: ") -> None:
        super().__init__()
        self.marker = marker
        self.ready = threading.Event()

    def write(self, s: str) -> int:
        n = super().write(s)
        if self.marker in self.getvalue():
            self.ready.set()
        return n


def test_chcos_run_serves_every_north_service(tmp_path: Path) -> None:
    from opcua import Client
    from pyModbusTCP.client import ModbusClient

    from chcos.apps.weld.runner import run

    out = _Lines()
    opts = NorthOptions(metrics="127.0.0.1:0", modbus_facade="127.0.0.1:0",
                        opcua="opc.tcp://127.0.0.1:0/chcos/", view="127.0.0.1:0")
    result: dict[str, Any] = {}

    def job() -> None:
        try:
            result["summary"] = run("direct", real_time=True, duration=6.0, workdir=tmp_path,
                                    out=out, north=opts)
        except BaseException as exc:  # reported below
            result["error"] = exc
            out.ready.set()

    th = threading.Thread(target=job)
    th.start()
    try:
        assert out.ready.wait(TIMEOUT), out.getvalue()
        assert "error" not in result, result
        urls = dict(line.strip().split(": ", 1) for line in out.getvalue().splitlines()
                    if line.startswith("  ") and ": " in line and line.split(":")[0].strip()
                    in ("metrics", "modbus", "opcua", "view"))
        # the live view of the running job (read-only: no users)
        snap = get_json(urls["view"] + "api/snapshot?svg=0")
        assert {"E2", "D1", "A1"} <= {t["name"] for t in snap["map"]["tasks"]}
        assert get_json(urls["view"] + "api/session") == {"user": None, "read_only": True}
        assert _stream_until(urls["view"] + "api/stream",
                             lambda st: st["tasks"]["E2"]["steps"] >= 1)  # the job runs
        got = scrape(urls["metrics"])
        assert value(got["chcos_task_executions"], "chcos_task_executions_total",
                     task="E2") >= 1
        host, port = urls["modbus"].removeprefix("modbus-tcp://").rsplit(":", 1)
        mc = ModbusClient(host=host, port=int(port), timeout=10.0)
        regs = mc.read_input_registers(0, 4)
        assert regs is not None and len(regs) == 4, mc.last_error_as_txt
        mc.close()
        c = Client(urls["opcua"], timeout=TIMEOUT)
        c.connect()
        try:
            i = c.get_namespace_index("urn:chcos")
            assert c.get_node(f"ns={i};s=Tasks.E2.Level").get_value() >= 1
        finally:
            c.disconnect()
    finally:
        th.join(timeout=120)
    assert "summary" in result, result


def test_users_file_and_passwd(tmp_path: Path) -> None:
    from chcos.errors import ConfigError
    from chcos.north.services import north_main
    from chcos.serving.auth import Users

    out = io.StringIO()
    import contextlib

    with contextlib.redirect_stdout(out):
        assert north_main(["passwd"], stdin=io.StringIO("s3cret\n")) == 0
    digest = out.getvalue().strip()
    assert digest.startswith("pbkdf2-sha256$") and "s3cret" not in digest
    f = tmp_path / "users.toml"
    f.write_text(f'[users.alice]\nrole = "operator"\npassword_hash = "{digest}"\n')
    users = Users.from_file(f)
    assert users.check("alice", "s3cret") is not None
    assert users.check("alice", "wrong") is None and users.check("bob", "s3cret") is None
    f.write_text(f'[users.alice]\nrole = "root"\npassword_hash = "{digest}"\n')
    with pytest.raises(ConfigError, match=r"users\.alice\.role: expected one of observer"):
        Users.from_file(f)
    f.write_text('[users.alice]\nrole = "operator"\npassword = "plain"\n')
    with pytest.raises(ConfigError, match="unknown key"):
        Users.from_file(f)


def test_chcos_run_system_serves_metrics_and_view(tmp_path: Path) -> None:
    """``chcos run SYSTEM`` (any system file, here figure 6.5's) takes the same north-side
    flags: the view and the metrics attach to the running cell, and they refuse virtual time."""
    from chcos.cli.cellrun import run
    from chcos.errors import ChcosError

    system = Path(__file__).resolve().parent.parent / "chcos/apps/fig65/system.toml"
    with pytest.raises(ChcosError, match="need real time"):
        run(system, virtual=True, duration=1.0, workdir=tmp_path,
            north=NorthOptions(metrics="127.0.0.1:0"))
    out = _Lines("  view: ")
    stop = threading.Event()
    result: dict[str, Any] = {}

    def job() -> None:
        try:
            result["run"] = run(system, workdir=tmp_path, out=out, stop=stop, outputs=False,
                                north=NorthOptions(metrics="127.0.0.1:0", view="127.0.0.1:0"))
        except BaseException as exc:  # reported below
            result["error"] = exc
            out.ready.set()

    th = threading.Thread(target=job)
    th.start()
    try:
        assert out.ready.wait(TIMEOUT), out.getvalue()
        assert "error" not in result, result
        urls = dict(line.strip().split(": ", 1) for line in out.getvalue().splitlines()
                    if line.startswith("  ") and line.split(":")[0].strip()
                    in ("metrics", "view"))
        snap = get_json(urls["view"] + "api/snapshot?svg=0")
        assert {"A1", "B1", "C1"} <= {t["name"] for t in snap["map"]["tasks"]}
        got = scrape(urls["metrics"])
        assert any(s.labels.get("device") == "S1" for s in got["chcos_device_healthy"])
    finally:
        stop.set()
        th.join(timeout=120)
    assert "run" in result, result


@pytest.mark.parametrize("host", ["192.0.2.1", "0.0.0.0", "::", "::ffff:127.0.0.1",
                                  "example.invalid"])
def test_off_loopback_refused_without_tls_or_allow_remote(tmp_path: Path, host: str) -> None:
    """Every north service asked for an address off loopback (or a wildcard, or a name other
    than localhost) without TLS - or, for Modbus, without --modbus-allow-remote - refuses to
    start, naming what it needs; nothing is bound (the refusal comes before any socket), and a
    service started before the refused one is stopped again."""
    from chcos.north.services import start as start_north

    devmap = DeviceMap((BusSpec("mem", "memory"),), (DeviceSpec("P1", "sensor", 0, "mem"),))
    s = System(devmap, clock=VirtualClock(), base_dir=tmp_path)
    try:
        h = f"[{host}]" if ":" in host else host
        for opts, match in ((NorthOptions(metrics=f"{h}:0"), "needs TLS"),
                            (NorthOptions(view=f"{h}:0"), "needs TLS"),
                            (NorthOptions(modbus_facade=f"{h}:0"), "no authentication"),
                            (NorthOptions(opcua=f"opc.tcp://{h}:0/chcos/"), "certificate")):
            with pytest.raises(NorthError, match=match):
                start_north(s, opts)
        # a loopback service started first is stopped again when a later one is refused
        with pytest.raises(NorthError, match="needs TLS"):
            start_north(s, NorthOptions(metrics="127.0.0.1:0", view=f"{h}:0"))
        assert all(type(i).__name__ != "StepTimes" for i in s.kernel.instruments)
        # the flag is parsed and passed on
        ap = argparse.ArgumentParser()
        add_north_arguments(ap)
        opts = NorthOptions.from_args(ap.parse_args(["--modbus-facade", f"{h}:0",
                                                     "--modbus-allow-remote"]))
        assert opts.modbus_allow_remote
        if host == "192.0.2.1":  # allowed, it gets past the refusal to the bind (no such
            # address here: nothing listens, nothing is sent)
            with pytest.raises(NorthError, match="cannot serve"):
                start_north(s, opts)
    finally:
        s.shutdown()
