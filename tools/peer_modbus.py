"""peer_modbus - pyModbusTCP's server as an independent Modbus TCP peer for the fault tests and
benchmarks (started by :class:`tools.peers.ModbusPeer`).

Run as a process (so a test can kill, SIGSTOP and restart it):
``python -m tools.peer_modbus PORT LOGFILE [ADDR=VALUE ...]`` serves 127.0.0.1:PORT with
holding registers and coils preset from ``ADDR=VALUE`` (``c3=1`` is coil 3), prints ``ready``
once it listens, and appends one line per write request to LOGFILE:
``<time.monotonic()> <h|c> <address> <values> <ok|busy>``. While holding register 900 is non-zero
every other write is answered with exception 6 (server device busy).
"""

from __future__ import annotations

import signal
import sys
import time
from typing import Any

from pyModbusTCP.constants import EXP_SLAVE_DEVICE_BUSY
from pyModbusTCP.server import DataBank, DataHandler, ModbusServer

BUSY_REGISTER = 900


class _Handler(DataHandler):  # type: ignore[misc]
    """Logs every write; answers busy while the busy register is set."""

    def __init__(self, bank: DataBank, log: str) -> None:
        super().__init__(bank)
        self._log = log

    def _note(self, table: str, address: int, values: list[Any], outcome: str) -> None:
        with open(self._log, "a", encoding="ascii") as f:
            f.write(f"{time.monotonic():.6f} {table} {address} "
                    f"{','.join(str(int(v)) for v in values)} {outcome}\n")

    def _busy(self, address: int) -> bool:
        regs = self.data_bank.get_holding_registers(BUSY_REGISTER)
        return address != BUSY_REGISTER and bool(regs and regs[0])

    def write_h_regs(self, address: int, words_l: list[int], srv_info: Any) -> Any:
        if self._busy(address):
            self._note("h", address, words_l, "busy")
            return DataHandler.Return(exp_code=EXP_SLAVE_DEVICE_BUSY)
        self._note("h", address, words_l, "ok")
        return super().write_h_regs(address, words_l, srv_info)

    def write_coils(self, address: int, bits_l: list[bool], srv_info: Any) -> Any:
        if self._busy(address):
            self._note("c", address, bits_l, "busy")
            return DataHandler.Return(exp_code=EXP_SLAVE_DEVICE_BUSY)
        self._note("c", address, bits_l, "ok")
        return super().write_coils(address, bits_l, srv_info)


def main(argv: list[str]) -> None:
    """Serve until killed."""
    port, log = int(argv[0]), argv[1]
    bank = DataBank()
    for item in argv[2:]:
        addr, value = item.split("=")
        if addr.startswith("c"):
            bank.set_coils(int(addr[1:]), [bool(int(value))])
        else:
            bank.set_holding_registers(int(addr), [int(value)])
    server = ModbusServer(host="127.0.0.1", port=port, no_block=True,
                          data_hdl=_Handler(bank, log))
    server.start()
    print("ready", flush=True)
    signal.sigwait({signal.SIGTERM, signal.SIGINT})
    server.stop()


if __name__ == "__main__":
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM, signal.SIGINT})
    main(sys.argv[1:])
