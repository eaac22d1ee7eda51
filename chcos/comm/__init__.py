"""comm - layer 4, the communications manager of thesis section 6.1.2: messages between
satellites over eclipse-zenoh.

:mod:`chcos.comm.manager` is the communications manager itself;
:mod:`chcos.comm.config` builds safe Zenoh configurations (loopback unless a host address is given,
and then only with TLS), :mod:`chcos.comm.codec` is the wire format of link messages,
:mod:`chcos.comm.secret` the per-system secret and the role seals on every payload,
:mod:`chcos.comm.transport` is the :class:`Transport` the communications manager sits on.
"""

from chcos.comm.codec import LinkMessage, MessageKind, decode, encode
from chcos.comm.config import LinkConfig, TlsSettings, UsrPwdAuth, link_config_from_section
from chcos.comm.transport import Subscription, Transport, enable_zenoh_logging

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
