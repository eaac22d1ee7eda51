"""The simulated Modbus slaves against independent clients (issue 48): ``mbpoll`` (Debian) and a
libmodbus program of the tests' own (vcan_tests/peers/mb_client.c, one raw request, the answer's
bytes printed), over Modbus TCP and over RTU on a socat pty pair. Each asserts what the client
received - the register, the exception code, the silence - and what the slave holds after.

The slaves are as strict as a device (Modbus Application Protocol V1.1b3): only mapped entries
exist, per unit (02 otherwise, no neighbours); a function the device does not implement is 01
(no invented answer); a bad quantity, value or length is 03; RTU stays silent for other units and
carries out a broadcast write unanswered; a TCP gateway answers 0x0B for a unit it does not have,
a TCP device answers any unit id. Needs mbpoll, socat, gcc and libmodbus-dev.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.apps.sim.modbus_server import ModbusSimServer, SerialSlaveServer
from chcos.apps.sim.modbus_slave import RegisterStore
from drivers.codecs.modbus import crc16
from vcan_tests.netutil import free_port
from vcan_tests.support_rtu import PtyPair, build_client, need


def make_store() -> RegisterStore:
    """Unit 1: holding 5..6, coil 3, input 0; unit 2: holding 5 only."""
    store = RegisterStore(unit_spans={1: {"holding": [(5, 2)], "coil": [(3, 1)],
                                          "input": [(0, 1)]},
                                      2: {"holding": [(5, 1)]}})
    store.write(1, "holding", 5, [1234, 5])
    store.write(2, "holding", 5, [2222])
    return store


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_client(tmp_path_factory.mktemp("mb-client"))


def mbpoll(*args: str) -> subprocess.CompletedProcess[str]:
    need("mbpoll", shutil.which("mbpoll") is not None)
    return subprocess.run(["mbpoll", "-0", "-1", "-o", "0.5", *args], capture_output=True,
                          text=True, timeout=30)


def raw(client: Path, *args: str) -> str:
    """What mb_client prints for one request."""
    done = subprocess.run([str(client), *args], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def tcp_pdu(answer: str) -> bytes:
    """The PDU of a printed Modbus TCP answer (``ADU <hex>``: MBAP header, then the PDU)."""
    assert answer.startswith("ADU "), answer
    return bytes.fromhex(answer[4:])[7:]


@pytest.fixture
def gateway() -> Iterator[tuple[RegisterStore, int]]:
    store = make_store()
    port = free_port()
    with ModbusSimServer(store, port, role="gateway"):
        yield store, port


# ---- Modbus TCP ---------------------------------------------------------------------------------
def test_mbpoll_reads_the_mapped_registers_and_nothing_else(
        gateway: tuple[RegisterStore, int]) -> None:
    _, port = gateway
    tcp = ["-m", "tcp", "-p", str(port), "-t", "4"]
    ok = mbpoll(*tcp, "-a", "1", "-r", "5", "-c", "2", "127.0.0.1")
    assert ok.returncode == 0 and "[5]: \t1234" in ok.stdout and "[6]: \t5" in ok.stdout
    for unit, ref, count in (("1", "7", "1"),      # nothing mapped there
                             ("1", "4", "2"),      # 4 is not mapped, 5 is: no neighbours
                             ("2", "6", "1")):     # unit 1's register, not unit 2's
        refused = mbpoll(*tcp, "-a", unit, "-r", ref, "-c", count, "127.0.0.1")
        assert refused.returncode != 0 and "Illegal data address" in refused.stderr, \
            (unit, ref, refused.stderr)
    absent = mbpoll(*tcp, "-a", "9", "-r", "5", "127.0.0.1")      # no unit 9 behind it
    assert "Target device failed to respond" in absent.stderr


def test_a_function_the_device_lacks_is_exception_01(client: Path,
                                                     gateway: tuple[RegisterStore, int]) -> None:
    _, port = gateway
    for pdu in ("07", "0800000000", "0b", "0c", "11", "18", "2b0e0100", "17000500010005000102"
                                                                       "0001", "16000500ff0000"):
        got = tcp_pdu(raw(client, "tcp", "127.0.0.1", str(port), "1", pdu))
        assert got == bytes([int(pdu[:2], 16) | 0x80, 0x01]), (pdu, got.hex())


def test_bad_values_quantities_and_lengths_are_exception_03(
        client: Path, gateway: tuple[RegisterStore, int]) -> None:
    store, port = gateway
    for pdu, want in (("0500031234", "8503"),      # a coil value other than 0000 / ff00
                      ("0300050000", "8303"),      # quantity 0
                      ("030005007e", "8303"),      # quantity 126 > 125
                      ("030005", "8303"),          # truncated
                      ("03000500010000", "8303"),  # extra bytes
                      ("1000050001030001", "9003"),   # byte count 3 for one register
                      ("0500040000", "8502"),      # coil 4: not mapped (coil 3 is)
                      ("0f000300020101", "8f02")):  # coils 3..4: 4 not mapped
        got = tcp_pdu(raw(client, "tcp", "127.0.0.1", str(port), "1", pdu))
        assert got.hex() == want, (pdu, got.hex())
    assert store.read(1, "coil", 3) == [False]      # nothing was carried out
    got = tcp_pdu(raw(client, "tcp", "127.0.0.1", str(port), "1", "050003ff00"))
    assert got.hex() == "050003ff00" and store.read(1, "coil", 3) == [True]
    got = tcp_pdu(raw(client, "tcp", "127.0.0.1", str(port), "2", "06000504d2"))
    assert got.hex() == "06000504d2" and store.read(2, "holding", 5) == [1234]


def test_a_tcp_device_answers_any_unit_id(client: Path) -> None:
    store = RegisterStore(unit_spans={1: {"holding": [(5, 1)]}})
    store.write(1, "holding", 5, [77])
    port = free_port()
    with ModbusSimServer(store, port, role="device"):
        answer = raw(client, "tcp", "127.0.0.1", str(port), "7", "0300050001")
    adu = bytes.fromhex(answer[4:])
    assert adu[6] == 7 and adu[7:].hex() == "0302004d"     # unit id repeated, unit 1's data


# ---- Modbus RTU on a pty pair ---------------------------------------------------------------
@pytest.fixture
def line(tmp_path: Path) -> Iterator[tuple[RegisterStore, Path]]:
    pair = PtyPair(tmp_path, "rtu")
    store = make_store()
    slave = SerialSlaveServer(store, str(pair.b))
    slave.start()
    try:
        yield store, pair.a
    finally:
        slave.stop()
        pair.close()


def test_mbpoll_over_rtu_reads_its_unit_and_other_units_get_silence(
        line: tuple[RegisterStore, Path]) -> None:
    _, port = line
    rtu = ["-m", "rtu", "-b", "19200", "-P", "none", "-t", "4"]
    ok = mbpoll(*rtu, "-a", "2", "-r", "5", str(port))
    assert ok.returncode == 0 and "[5]: \t2222" in ok.stdout, ok.stdout + ok.stderr
    refused = mbpoll(*rtu, "-a", "1", "-r", "7", str(port))
    assert "Illegal data address" in refused.stderr
    silent = mbpoll(*rtu, "-a", "3", "-r", "5", str(port))       # no unit 3 on the line
    assert silent.returncode != 0 and "timed out" in silent.stderr.lower(), silent.stderr


def test_rtu_frames_exceptions_and_a_broadcast_against_libmodbus(
        client: Path, line: tuple[RegisterStore, Path]) -> None:
    store, port = line
    answer = raw(client, "rtu", str(port), "1", "11")           # report server id: not here
    frame = bytes.fromhex(answer[4:])
    assert frame[:3] == bytes([1, 0x91, 0x01])
    assert crc16(frame[:-2]).to_bytes(2, "big") == frame[-2:]
    assert raw(client, "rtu", str(port), "3", "0300050001") == "TIMEOUT"
    assert raw(client, "rtu", str(port), "0", "06000500" "2a", "noreply") == "SENT"
    assert store.wait_for(lambda s: s.read(1, "holding", 5) == [42]
                          and s.read(2, "holding", 5) == [42], 5.0)   # both units carried it out
    assert raw(client, "rtu", str(port), "0", "0300050001") == "TIMEOUT"   # nobody answers


# ---- chcos sim --from: the scripts apply before the first request -----------------------------
def test_sim_from_serves_the_scripts_value_from_its_first_answer(tmp_path: Path,
                                                                  client: Path) -> None:
    """``chcos sim --from MAP --value level=77``: the first request that gets an answer, sent
    as early as the port takes a connection, reads 77 (it used to read 0 until the script's
    first tick)."""
    import os
    import sys
    import time

    port = free_port()
    (tmp_path / "m.toml").write_text(
        f'[[bus]]\nname = "plc"\nkind = "modbus-tcp"\nhost = "127.0.0.1"\nport = {port}\n\n'
        '[[device]]\nname = "level"\ndirection = "sensor"\nbus = "plc"\n'
        'address = { table = "holding", address = 3 }\n', encoding="utf-8")
    sim = subprocess.Popen([sys.executable, "-m", "chcos.cli.main", "sim", "--from", "m.toml",
                            "--value", "level=77", "--duration", "30"], cwd=tmp_path,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                           env=dict(os.environ))
    try:
        deadline = time.monotonic() + 30
        answer = ""
        while time.monotonic() < deadline:
            answer = raw(client, "tcp", "127.0.0.1", str(port), "1", "0300030001")
            if answer.startswith("ADU"):
                break
        assert tcp_pdu(answer).hex() == "0302004d", answer      # 77, not 0
    finally:
        sim.terminate()
        sim.wait(20)


def test_chcos_sim_modbus_serves_rtu_on_a_pty(tmp_path: Path) -> None:
    """``chcos sim modbus --serial PATH``: the command-line slave on one end of a pty pair, read
    by mbpoll on the other (entries 0..SIZE-1 exist, SIZE does not)."""
    import threading

    from chcos.apps.sim import modbus_server

    pair = PtyPair(tmp_path, "cli")
    done: list[int] = []
    runner = threading.Thread(target=lambda: done.append(modbus_server.main(
        ["--serial", str(pair.b), "--units", "4", "--size", "8", "--duration", "4"])))
    runner.start()
    try:
        rtu = ["-m", "rtu", "-b", "19200", "-P", "none", "-t", "4", "-a", "4"]
        got = None
        for _ in range(20):                   # until the slave has its end of the pty open
            got = mbpoll(*rtu, "-r", "7", str(pair.a))
            if got.returncode == 0:
                break
        assert got is not None and got.returncode == 0 and "[7]: \t0" in got.stdout
        assert "Illegal data address" in mbpoll(*rtu, "-r", "8", str(pair.a)).stderr
    finally:
        runner.join(20)
        pair.close()
    assert done == [0]
