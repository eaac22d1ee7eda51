"""link - the chcos inter-satellite transport over eclipse-zenoh.

:mod:`chcos.link.config` builds safe Zenoh configurations (loopback unless a host address is given,
and then only with TLS), :mod:`chcos.link.codec` is the wire format of link messages,
:mod:`chcos.link.secret` the per-system secret and the role seals on every payload,
:mod:`chcos.link.transport` is the :class:`Transport` the communications manager sits on.
"""

from chcos.link.codec import LinkMessage, MessageKind, decode, encode
from chcos.link.config import LinkConfig, TlsSettings, UsrPwdAuth, link_config_from_section
from chcos.link.transport import Subscription, Transport, enable_zenoh_logging

__all__ = [
    "LinkConfig",
    "LinkMessage",
    "MessageKind",
    "Subscription",
    "TlsSettings",
    "Transport",
    "UsrPwdAuth",
    "decode",
    "enable_zenoh_logging",
    "encode",
    "link_config_from_section",
]
