"""Link security: with user/password authentication configured, only sessions presenting
credentials from the dictionary connect; the others are refused (and the refusal is logged)."""

from __future__ import annotations

from pathlib import Path

import pytest

from chcos.comm import LinkConfig, Transport, UsrPwdAuth
from vcan_tests.netutil import free_port
from vcan_tests.support_link import Child, Collector, child_args

REFUSED = "Received a close message"  # what Zenoh logs when the listener refuses a session


@pytest.fixture
def users(tmp_path: Path) -> Path:
    path = tmp_path / "users.txt"
    path.write_text("host:host-secret\nsat1:sat1-secret\n")
    return path


def test_right_credentials_connect(users: Path) -> None:
    host_port = free_port()
    auth = UsrPwdAuth("host", "host-secret", users)
    with Transport(LinkConfig(host_port, auth=auth)) as host:
        joins = Collector()
        host.watch("chcos/alive/*", joins, lambda _k: None)
        args = child_args(
            listen=free_port(),
            connect=[host_port],
            token="chcos/alive/sat1",
            auth=("sat1", "sat1-secret", users),
            zenoh_log="warn",
        )
        with Child(args) as child:
            ready = child.expect("ready")
            assert joins.get() == "chcos/alive/sat1"
            assert ready["zid"] in host.peers()
            assert child.stop() == 0
        assert not any(REFUSED in line for line in child.log_lines)


@pytest.mark.parametrize(
    "credentials",
    [None, ("sat1", "wrong-secret", None), ("intruder", "sat1-secret", None)],
    ids=["no-credentials", "wrong-password", "unknown-user"],
)
def test_wrong_or_missing_credentials_are_refused_and_logged(
    users: Path, credentials: tuple[str, str, Path | None] | None
) -> None:
    host_port = free_port()
    auth = UsrPwdAuth("host", "host-secret", users)
    with Transport(LinkConfig(host_port, auth=auth)) as host:
        joins = Collector()
        host.watch("chcos/alive/*", joins, lambda _k: None)
        args = child_args(
            connect=[host_port], token="chcos/alive/intruder", auth=credentials, zenoh_log="warn"
        )
        with Child(args) as child:
            ready = child.expect("ready")
            # the refusal is logged by the connecting side, and again at each retry
            line = child.wait_log(REFUSED)
            assert f"tcp/127.0.0.1:{host_port}" in line  # names the refusing listener
            child.wait_log(REFUSED)
            assert child.peers() == []
            assert ready["zid"] not in host.peers()
            assert host.alive("chcos/alive/*", timeout=0.3) == []
            assert joins.empty()
            assert child.stop() == 0
