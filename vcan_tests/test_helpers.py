"""chcos.helpers: the small helpers every layer shares (one copy each)."""

from __future__ import annotations

import socket

import pytest

from chcos.helpers import free_port, free_ports, is_int, is_number


@pytest.mark.parametrize(("value", "int_", "number"), [
    (0, True, True), (-7, True, True), (2**70, True, True), (1.5, False, True),
    (True, False, False), (False, False, False), ("1", False, False), (None, False, False),
    ([1], False, False)])
def test_int_and_number_never_take_a_bool(value: object, int_: bool, number: bool) -> None:
    assert is_int(value) is int_
    assert is_number(value) is number


def test_free_port_is_a_loopback_port_that_can_be_bound() -> None:
    port = free_port()
    assert 1 <= port <= 65535
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", port))
    with pytest.raises(OSError):
        free_port("192.0.2.1")   # TEST-NET-1: not an address of this machine


def test_free_ports_are_distinct_and_can_each_be_bound() -> None:
    """Two free_port() calls may return the same port (each socket is closed before the next
    binds); free_ports holds them all until it has them."""
    ports = free_ports(16)
    assert len(set(ports)) == 16
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as a, \
            socket.socket(socket.AF_INET, socket.SOCK_STREAM) as b:
        a.bind(("127.0.0.1", ports[0]))
        b.bind(("127.0.0.1", ports[1]))
    with pytest.raises(OSError):
        free_ports(2, "192.0.2.1")
