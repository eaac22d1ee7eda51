"""A truthful shutdown (issue 38): the run's summary and exit status come from what each driver
confirmed. Against pyModbusTCP's server in its own process, frozen (SIGSTOP) when the run
stops: a safe value not answered is NOT written (with the reason), the run is unhealthy, and
the server still holds the last command; a server that comes back within the shutdown window
gets its safe value, and the summary says written."""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.cli import cellrun
from chcos.devices import devtab
from tools.peers import ModbusPeer
from vcan_tests.netutil import free_port
from vcan_tests.support_faults import wait_until

VALVE = 1
WAIT = 30.0


@pytest.fixture
def peer(tmp_path: Path) -> Iterator[ModbusPeer]:
    p = ModbusPeer(free_port(), tmp_path / "peer.log", {"0": 80})
    p.start()
    try:
        yield p
    finally:
        p.kill()


def _cell(tmp_path: Path, port: int) -> Path:
    (tmp_path / "tasks").mkdir()
    (tmp_path / "tasks" / "follow.py").write_text(
        "async def main(ctx, command):\n"
        "    while True:\n"
        "        level = await ctx.read('level')\n"
        "        ctx.write('valve', level)\n", encoding="utf-8")
    (tmp_path / "devices.toml").write_text(f"""
[[bus]]
name = "plc"
kind = "modbus-tcp"
host = "127.0.0.1"
port = {port}
poll_period = 0.05
timeout = 0.3
retries = 0
reconnect_delay = 0.05
reconnect_delay_max = 0.2

[[device]]
name = "level"
direction = "sensor"
bus = "plc"
address = {{ table = "holding", address = 0 }}
stale_after = 2.0

[[device]]
name = "valve"
direction = "actuator"
bus = "plc"
address = {{ table = "holding", address = {VALVE} }}
limits = [0.0, 100.0]
safe_value = 0
units = "%"
""", encoding="utf-8")
    (tmp_path / "install.chcos").write_text(
        "install -m0 sysfile\ninstall -m0i1o1 follow level valve\ninvoke follow\n",
        encoding="utf-8")
    system = tmp_path / "system.toml"
    system.write_text('[system]\nname = "cell"\ndevmaps = ["devices.toml"]\n'
                      'task_path = ["tasks"]\ninstall = "install.chcos"\n', encoding="utf-8")
    return system


def _stop_once_commanded(peer: ModbusPeer, stop: threading.Event,
                         then: threading.Timer | None = None) -> threading.Thread:
    """A thread that waits until the task's command (80 %) is in the server, freezes the
    server, stops the run and starts ``then`` (if given)."""
    def watch() -> None:
        wait_until(lambda: any(w.address == VALVE and w.values == [80] for w in peer.writes()))
        peer.freeze()       # (also if it never came: the run is stopped either way)
        stop.set()
        if then is not None:
            then.start()
    t = threading.Thread(target=watch, daemon=True)
    t.start()
    return t


def test_a_frozen_server_at_shutdown_is_reported_not_written_and_the_run_unhealthy(
        tmp_path: Path, peer: ModbusPeer, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(devtab, "SHUTDOWN_FLUSH", 1.0)     # the window, shortened for the test
    system = _cell(tmp_path, peer.port)
    out = io.StringIO()
    stop = threading.Event()
    watcher = _stop_once_commanded(peer, stop)
    try:
        result = cellrun.run(system, duration=WAIT, out=out, stop=stop, workdir=tmp_path / "w")
    finally:
        watcher.join(WAIT)
        thawed = time.monotonic()
        peer.thaw()
    text = out.getvalue()
    assert "safe value valve = 0 %: NOT written: " in text, text
    assert "safe value valve = 0 %: written" not in text
    assert not result.healthy and "UNHEALTHY" in text
    assert any(p.startswith("actuator valve: safe value 0 % NOT written")
               for p in result.problems), result.problems
    # the server took no safe value while chcos waited (a request left in its socket may be
    # served once it is thawed, after the run reported it NOT written)
    assert [w for w in peer.writes() if w.address == VALVE and w.values == [0]
            and w.at < thawed] == []


def test_a_server_back_within_the_window_gets_its_safe_value(
        tmp_path: Path, peer: ModbusPeer) -> None:
    system = _cell(tmp_path, peer.port)
    out = io.StringIO()
    stop = threading.Event()
    thaw = threading.Timer(0.8, peer.thaw)      # well inside the 5 s window
    watcher = _stop_once_commanded(peer, stop, thaw)
    try:
        result = cellrun.run(system, duration=WAIT, out=out, stop=stop, workdir=tmp_path / "w")
    finally:
        watcher.join(WAIT)
        thaw.join(WAIT)
        peer.thaw()
    text = out.getvalue()
    assert "safe value valve = 0 %: written" in text, text
    assert peer.holding(VALVE) == 0
    assert result.healthy or all("valve" not in p for p in result.problems), text
