"""``chcos run``'s progress and summary show each CANopen node's lifecycle (state, boot-ups
seen, NMT starts, error register, last EMCY) and the bus's SYNC cycle, against a durand node
rebooted during the run (issue 36)."""

from __future__ import annotations

import io
import threading
import time
from pathlib import Path

from durand.services.nmt import StateEnum

from chcos.cli import cellrun
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_node import WAIT, DurandNode
from vcan_tests.support_canopen_system import NODE, write_devmap

REBOOTED = f"node     co/{NODE:<13} OPERATIONAL, 1 boot-up(s) seen, 2 NMT start(s)"


def test_run_summary_has_a_line_per_node_and_the_sync_cycle(tmp_path: Path) -> None:
    node = DurandNode(unique_channel("run"), NODE)
    write_devmap(tmp_path, node)
    (tmp_path / "install.chcos").write_text("install -m0 sysfile\n", encoding="utf-8")
    system = tmp_path / "system.toml"
    system.write_text('[system]\nname = "cell"\ndevmaps = ["devices.toml"]\n'
                      'install = "install.chcos"\n', encoding="utf-8")
    out = io.StringIO()
    stop = threading.Event()
    seen: list[str] = []

    def reboot_then_stop() -> None:
        """Once the driver started the node, power-cycle it; stop the run once the progress
        shows it OPERATIONAL again with the boot-up counted."""
        deadline = time.monotonic() + 4 * WAIT
        while time.monotonic() < deadline and not stop.is_set():
            if not seen and node.state == StateEnum.OPERATIONAL and \
                    f"node     co/{NODE:<13} OPERATIONAL, 0 boot-up(s)" in out.getvalue():
                seen.append("rebooted")
                node.power_cycle()
            if seen and REBOOTED in out.getvalue():
                break
            stop.wait(0.02)
        stop.set()

    watcher = threading.Thread(target=reboot_then_stop, daemon=True)
    watcher.start()
    try:
        result = cellrun.run(system, out=out, stop=stop, period=0.2, workdir=tmp_path / "w")
        heartbeat_ms = node.read(0x1017)        # configured again after the reboot
    finally:
        stop.set()
        watcher.join(timeout=WAIT)
        node.close()
    text = out.getvalue()
    summary = text.split("\nsummary\n")[1]
    assert seen == ["rebooted"], text
    line = next(ln for ln in summary.splitlines() if REBOOTED in ln)
    assert " heartbeat loss(es), 0 EMCY(s), error register 0x00, last EMCY none" in line, text
    sync = next(line for line in summary.splitlines() if line.startswith("  SYNC     co"))
    cycles = int(sync.split()[2])
    assert cycles >= 10 and "cycles of 10 ms" in sync and "jitter p50" in sync, sync
    assert "safe value target = 0: written" in summary
    assert heartbeat_ms == 20
    # the reboot is what made the run unhealthy, and the summary says so
    assert [p for p in result.problems if "rebooted" in p] == result.problems != [], text
