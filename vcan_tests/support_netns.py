"""Support for the multi-host tests: computers made of Linux network namespaces joined by veth pairs
to a bridge (in a namespace of its own) on a private test subnet, test certificates made with the
openssl tool, and a host driver that runs inside a namespace and answers JSON requests on its
standard input (``python -m vcan_tests.support_netns SYSTEM_FILE``)."""

from __future__ import annotations

import json
import os
import selectors
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

from chcos.user.context import TaskContext

ROOT = Path(__file__).resolve().parent.parent
SUBNET = "10.19.0"


def missing() -> str:
    """What this machine lacks for the namespace tests ('' if nothing)."""
    if os.geteuid() != 0:
        return "root (network namespaces need CAP_NET_ADMIN)"
    for tool in ("ip", "openssl"):
        if shutil.which(tool) is None:
            return f"the {tool} tool (Debian: iproute2 / openssl)"
    return ""


@contextmanager
def loopback_only(tag: str) -> Iterator[str]:
    """A network namespace of the test's own whose only interface is loopback, with a route
    for multicast on it (python-can's udp_multicast between processes), named ``tag`` + this
    process and a random suffix; removed after. Skips (fails under CI) where namespaces are
    missing (:func:`missing`)."""
    from vcan_tests.conftest import require

    require(not missing(), missing() or "network namespaces")
    name = f"{tag}{os.getpid()}x{uuid.uuid4().hex[:6]}"
    subprocess.run(["ip", "netns", "add", name], check=True, timeout=30)
    try:
        for args in (["link", "set", "lo", "up"], ["route", "add", "224.0.0.0/4", "dev", "lo"]):
            subprocess.run(["ip", "-n", name, *args], check=True, timeout=30)
        yield name
    finally:
        subprocess.run(["ip", "netns", "del", name], timeout=30)


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=30)


def _remove_orphans() -> None:
    """Remove namespaces left by a test run that was killed (its process is gone)."""
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True,
                         timeout=30).stdout
    for ns in (line.split()[0] for line in out.splitlines() if line.startswith("c19x")):
        pid = ns[4:].split("x", 1)[0]
        if pid.isdigit() and not Path(f"/proc/{pid}").exists():
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)


class Net:
    """Namespaces ``<tag><name>`` for ``names``, each with one interface ``eth0`` at
    ``10.19.0.<address>``, joined through a bridge in namespace ``<tag>br``. :meth:`close`
    removes everything (deleting a namespace deletes its veth ends)."""

    def __init__(self, addresses: dict[str, int]) -> None:
        _remove_orphans()
        self.tag = f"c19x{os.getpid()}x"
        self.addresses = {n: f"{SUBNET}.{a}" for n, a in addresses.items()}
        self.made: list[str] = []
        try:
            self._build()
        except BaseException:
            self.close()
            raise

    def ns(self, name: str) -> str:
        """The namespace of node ``name``."""
        return f"{self.tag}{name}"

    def _build(self) -> None:
        br = f"{self.tag}br"
        _ip("netns", "add", br)
        self.made.append(br)
        _ip("-n", br, "link", "add", "br0", "type", "bridge")
        _ip("-n", br, "link", "set", "br0", "up")
        for i, (name, addr) in enumerate(self.addresses.items()):
            ns = self.ns(name)
            _ip("netns", "add", ns)
            self.made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "link", "add", "eth0", "type", "veth", "peer", "name", f"p{i}",
                "netns", br)
            _ip("-n", br, "link", "set", f"p{i}", "master", "br0")
            _ip("-n", br, "link", "set", f"p{i}", "up")
            _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")

    def close(self) -> None:
        """Remove every namespace made (and with them their interfaces)."""
        for ns in reversed(self.made):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)
        self.made.clear()

    def popen(self, name: str, args: list[str], log: Path, **kw: Any) -> subprocess.Popen[Any]:
        """Start ``python args...`` in the namespace of ``name``, output to ``log``."""
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        out = open(log, "ab")  # noqa: SIM115 - the child keeps it
        return subprocess.Popen(["ip", "netns", "exec", self.ns(name), sys.executable, *args],
                                cwd=ROOT, env=env, stdout=kw.pop("stdout", out), stderr=out,
                                **kw)


def pki(root: Path, ips: list[str], cn: str = "chcos test CA") -> tuple[Path, Path, Path]:
    """A CA and one certificate naming every address in ``ips`` signed by it, made with
    openssl: (ca.pem, cert.pem, key.pem), owner-only."""
    root.mkdir(parents=True)
    sans = ",".join(f"IP:{ip}" for ip in ips)
    (root / "ext.cnf").write_text(
        f"subjectAltName = {sans}\nbasicConstraints = CA:FALSE\n"
        "keyUsage = digitalSignature, keyEncipherment\n"
        "extendedKeyUsage = serverAuth, clientAuth\n")

    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=root, check=True, capture_output=True,
                       timeout=60)

    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem",
        "-days", "2", "-subj", f"/CN={cn}")
    run("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "key.pem", "-out", "cert.csr",
        "-subj", "/CN=chcos node")
    run("x509", "-req", "-in", "cert.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
        "-CAcreateserial", "-out", "cert.pem", "-days", "2", "-extfile", "ext.cnf")
    for f in root.iterdir():
        f.chmod(0o600)
    return root / "ca.pem", root / "cert.pem", root / "key.pem"


def tls_section(ca: Path, cert: Path, key: Path) -> str:
    """A [link.tls] table with mutual TLS for these files."""
    return (f'[link.tls]\nroot_ca_certificate = "{ca}"\nlisten_certificate = "{cert}"\n'
            f'listen_private_key = "{key}"\nconnect_certificate = "{cert}"\n'
            f'connect_private_key = "{key}"\nenable_mtls = true\n')


class RemoteHost:
    """A host session running inside a namespace (this module's ``main``), driven over its
    standard input and output."""

    def __init__(self, net: Net, node: str, system: Path, log: Path,
                 reach: float = 20.0) -> None:
        """``reach``: how long the session tries to reach a first satellite (Host timeout)
        before an operation fails with "no satellite ... is reachable"."""
        self.proc = net.popen(node, ["-m", "vcan_tests.support_netns", str(system), str(reach)],
                              log, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self._sel = selectors.DefaultSelector()
        assert self.proc.stdout is not None
        self._out: IO[bytes] = self.proc.stdout
        self._sel.register(self._out, selectors.EVENT_READ)

    def call(self, op: str, timeout: float = 60.0, **kw: Any) -> Any:
        """The result of request ``op``; raises RuntimeError with the host's error."""
        assert self.proc.stdin is not None
        self.proc.stdin.write((json.dumps({"op": op, **kw}) + "\n").encode())
        self.proc.stdin.flush()
        if not self._sel.select(timeout):
            raise TimeoutError(f"host driver: no answer to {op} in {timeout} s")
        line = self._out.readline()
        if not line:
            raise RuntimeError(f"host driver exited ({self.proc.poll()})")
        reply = json.loads(line)
        if not reply["ok"]:
            raise RuntimeError(reply["error"])
        return reply["result"]

    def wait_until(self, pred: Any, timeout: float = 30.0, machine: int | None = None) -> Any:
        """Poll the map (each poll a round trip) until ``pred(map)``; AssertionError after
        ``timeout`` with the last map."""
        deadline = time.monotonic() + timeout
        doc: Any = {}
        while time.monotonic() < deadline:
            doc = self.call("map", machine=machine)
            if pred(doc):
                return doc
        raise AssertionError(f"condition not met in {timeout} s; last map: {doc}")

    def close(self) -> None:
        """End the driver."""
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)


async def stopper(ctx: TaskContext, cmd: Any) -> None:
    """Emergency-stops the whole system (every satellite) with reason ``cmd['why']``."""
    ctx.estop(str((cmd or {}).get("why", "test")))


def main() -> int:
    """The host driver: one JSON request per input line, one JSON answer per output line."""
    from chcos.errors import ChcosError
    from chcos.satellites import sysfile
    from chcos.satellites.host import Host

    sf = sysfile.load(sys.argv[1])
    reach = float(sys.argv[2]) if len(sys.argv) > 2 else 20.0
    with Host(sf, timeout=reach, settle=5.0) as host:
        for line in sys.stdin:
            req = json.loads(line)
            op = req["op"]
            try:
                if op == "exec":
                    result: Any = host.execute(req["line"])
                elif op == "map":
                    result = host.map_doc(req.get("machine"))
                elif op == "wait_for":
                    result = host.wait_for(req["machines"], timeout=req.get("timeout", 30.0))
                elif op == "heads":
                    result = {str(k): v for k, v in host.log_heads().items()}
                else:
                    raise ValueError(f"unknown op {op!r}")
                reply = {"ok": True, "result": result}
            except (ChcosError, ValueError) as exc:
                reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
            print(json.dumps(reply, default=str), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
