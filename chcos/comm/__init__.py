"""comm - layer 4, the communications manager of thesis section 6.1.2: messages between
satellites over eclipse-zenoh.

:mod:`chcos.comm.manager` is the communications manager itself, :mod:`chcos.comm.batching` its
outgoing batches, :mod:`chcos.comm.ports` the narrow protocols of its collaborators;
:mod:`chcos.comm.payloads` are the typed payloads of link messages and :mod:`chcos.comm.codec`
their wire format; :mod:`chcos.comm.config` builds safe Zenoh configurations (loopback unless a
host address is given, and then only with TLS; :mod:`chcos.comm.tls` holds the TLS and
user/password settings, :mod:`chcos.comm.section` reads the ``[link]`` section of a system
file), :mod:`chcos.comm.secret` is the per-system secret and the role seals on every payload,
:mod:`chcos.comm.transport` is the :class:`Transport` the communications manager sits on
(on a :mod:`chcos.comm.session`; :mod:`chcos.comm.qos` maps priorities onto Zenoh's,
:mod:`chcos.comm.subscription` is the handle of what it declares).

The names below are imported lazily, so that the layers above that need only the payloads or
the codec do not load Zenoh.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from chcos.comm.codec import LinkMessage, MessageKind, decode, encode
    from chcos.comm.config import LinkConfig
    from chcos.comm.section import link_config_from_section
    from chcos.comm.tls import TlsSettings, UsrPwdAuth
    from chcos.comm.transport import Subscription, Transport, enable_zenoh_logging

_WHERE = {
    "LinkMessage": "codec", "MessageKind": "codec", "decode": "codec", "encode": "codec",
    "LinkConfig": "config", "TlsSettings": "tls", "UsrPwdAuth": "tls",
    "link_config_from_section": "section", "Subscription": "transport",
    "Transport": "transport", "enable_zenoh_logging": "transport",
}

__all__ = [
    "LinkConfig", "LinkMessage", "MessageKind", "Subscription", "TlsSettings", "Transport",
    "UsrPwdAuth", "decode", "enable_zenoh_logging", "encode", "link_config_from_section",
]


def __getattr__(name: str) -> Any:
    """Import ``name`` from its module on first use. Raises AttributeError for other names."""
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'chcos.comm' has no attribute {name!r}")
    return getattr(importlib.import_module(f"chcos.comm.{module}"), name)
