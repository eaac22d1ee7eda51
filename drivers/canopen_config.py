"""canopen_config - what the device map says a CANopen node must be: its identity (0x1018) and
the configuration the driver downloads at every boot (heartbeat producer 0x1017, the consumer
entry 0x1016 that watches the master's heartbeat, error behaviour 0x1029, PDO communication and
mapping parameters, further SDO writes). Parsing and offline checks (``chcos check``: types,
ranges, PDO mappings against the node's EDS: at most 64 bits, only mappable objects, the access
a direction needs) and the ordered list of SDO writes a boot performs. No bus I/O.

Node keys (beside ``id``, ``eds``, ``heartbeat_timeout``, ``nmt_start``)::

    identity = {vendor = 0x1234, product = 0x42, revision = 0x10001, serial = 7}   # serial optional
    [bus.nodes.config]
    heartbeat_producer_ms = 50          # 0x1017
    master_consumer_ms = 300            # 0x1016:01 = master node id << 16 | ms (needs the bus's
                                        # master_heartbeat_ms)
    error_behaviour = 0                 # 0x1029:01 (0 pre-operational, 1 no change, 2 stopped)
    pdos = [{pdo = "rpdo1", cob_id = 0x205, transmission_type = 255, inhibit_100us = 0,
             event_timer_ms = 0, enabled = true, map = [[0x6040, 0], [0x6060, 0, 8]]}]
    sdo = [{index = 0x6007, subindex = 0, value = 3}]

Beside ``config``, ``store_config = true`` (or the sub-index of 0x1010 to use: 1 all parameters,
2 communication, 3 application, 4..127 manufacturer-specific) makes the boot procedure, once every
write was read back, send the "save" signature to the store parameters object 0x1010 (confirmed
by the node's SDO answer; an abort refuses the configuration). The store is skipped when the node
already held every configured value before the download (it came up with its stored
configuration): a node's flash is not written at every boot. Off by default: use it when
commissioning.

A PDO entry downloads only the keys it gives; ``map`` entries are ``[index, subindex]`` or
``[index, subindex, bits]`` (bits default to the object's data type size). ``cob_id`` defaults
to the EDS's. The driver's own view of the PDOs (which object rides which PDO) follows the
configuration, not the EDS defaults it replaces.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from canopen.objectdictionary import INTEGER_TYPES

from chcos.helpers import is_int, is_number

CONFIG_KEYS = ("heartbeat_producer_ms", "master_consumer_ms", "error_behaviour", "pdos", "sdo")
IDENTITY_KEYS = ("vendor", "product", "revision", "serial")
PDO_KEYS = ("pdo", "cob_id", "transmission_type", "inhibit_100us", "event_timer_ms", "enabled",
            "map")
SDO_KEYS = ("index", "subindex", "value")
PDO_NAME = re.compile(r"^(rpdo|tpdo)([1-9][0-9]{0,2})$")
COB_DISABLED = 0x8000_0000   # COB-ID bit 31: PDO not valid
COB_NO_RTR = 0x4000_0000     # COB-ID bit 30: no RTR (some nodes set it themselves)
#: the store parameters object and the "save" signature written to it (CiA 301 7.5.2.13: the
#: characters s, a, v, e as an UNSIGNED32, little-endian)
STORE_INDEX = 0x1010
SAVE_SIGNATURE = 0x65766173

#: the size in bits of the standard objects the configuration writes
U8, U16, U32 = 8, 16, 32


@dataclass(frozen=True)
class Identity:
    """The identity object 0x1018 the map expects (serial optional)."""

    vendor: int
    product: int
    revision: int
    serial: int | None = None

    def fields(self) -> list[tuple[int, str, int]]:
        """(subindex, name, expected value) of each field to compare."""
        out = [(1, "vendor", self.vendor), (2, "product", self.product),
               (3, "revision", self.revision)]
        if self.serial is not None:
            out.append((4, "serial", self.serial))
        return out


@dataclass(frozen=True)
class PdoConfig:
    """One PDO of the configuration (see the module doc)."""

    kind: Literal["rpdo", "tpdo"]
    number: int
    cob_id: int | None
    enabled: bool
    transmission_type: int | None
    inhibit_100us: int | None
    event_timer_ms: int | None
    mapping: tuple[tuple[int, int, int], ...] | None   # (index, subindex, bits)

    @property
    def name(self) -> str:
        return f"{self.kind.upper()}{self.number}"

    @property
    def com_index(self) -> int:
        return (0x1400 if self.kind == "rpdo" else 0x1800) + self.number - 1

    @property
    def map_index(self) -> int:
        return (0x1600 if self.kind == "rpdo" else 0x1A00) + self.number - 1


@dataclass(frozen=True)
class SdoWrite:
    """One write of the configuration: object, value, its size in bits for a standard object
    (None: the data type from the EDS), whether it can be read back, and what it is for."""

    index: int
    subindex: int
    value: int | float
    bits: int | None
    what: str
    read_back: bool = True
    #: bits ignored when comparing the read-back (a COB-ID's RTR bit)
    ignore_mask: int = 0


@dataclass(frozen=True)
class NodeConfig:
    """Identity and boot configuration of one node."""

    identity: Identity | None = None
    heartbeat_producer_ms: int | None = None
    master_consumer_ms: int | None = None
    error_behaviour: int | None = None
    pdos: tuple[PdoConfig, ...] = ()
    sdo: tuple[tuple[int, int, int | float], ...] = ()
    #: the sub-index of 0x1010 the configuration is stored with after the download (None: not
    #: stored; the node key ``store_config``)
    store_sub: int | None = None

    def store(self) -> SdoWrite | None:
        """The write that stores the configuration in the node (None without
        ``store_config``): the "save" signature to 0x1010, not read back (reading 0x1010 gives
        the node's storage capabilities, not the signature)."""
        if self.store_sub is None:
            return None
        return SdoWrite(STORE_INDEX, self.store_sub, SAVE_SIGNATURE, U32,
                        "store parameters (\"save\")", read_back=False)

    def writes(self, od: Any, node_id: int, master_id: int) -> list[SdoWrite]:
        """The SDO writes of a boot, in order: heartbeat producer, master consumer, error
        behaviour, each PDO (disabled, parameters, mapping, enabled: CiA 301 7.5.2.35), then the
        user's writes. ``od`` is the node's canopen object dictionary (EDS defaults)."""
        out: list[SdoWrite] = []
        if self.heartbeat_producer_ms is not None:
            out.append(SdoWrite(0x1017, 0, self.heartbeat_producer_ms, U16,
                                "heartbeat producer time"))
        if self.master_consumer_ms is not None:
            out.append(SdoWrite(0x1016, 1, (master_id << 16) | self.master_consumer_ms, U32,
                                "heartbeat consumer of the master"))
        if self.error_behaviour is not None:
            out.append(SdoWrite(0x1029, 1, self.error_behaviour, U8, "error behaviour"))
        for p in self.pdos:
            cob = effective_cob_id(p, od, node_id)
            out.append(SdoWrite(p.com_index, 1, cob | COB_DISABLED, U32,
                                f"{p.name} COB-ID (disabled)", ignore_mask=COB_NO_RTR))
            if p.transmission_type is not None:
                out.append(SdoWrite(p.com_index, 2, p.transmission_type, U8,
                                    f"{p.name} transmission type"))
            if p.inhibit_100us is not None:
                out.append(SdoWrite(p.com_index, 3, p.inhibit_100us, U16,
                                    f"{p.name} inhibit time"))
            if p.event_timer_ms is not None:
                out.append(SdoWrite(p.com_index, 5, p.event_timer_ms, U16,
                                    f"{p.name} event timer"))
            if p.mapping is not None:
                out.append(SdoWrite(p.map_index, 0, 0, U8, f"{p.name} mapping cleared"))
                for i, (index, sub, bits) in enumerate(p.mapping, 1):
                    out.append(SdoWrite(p.map_index, i, (index << 16) | (sub << 8) | bits, U32,
                                        f"{p.name} mapping entry {i}"))
                out.append(SdoWrite(p.map_index, 0, len(p.mapping), U8,
                                    f"{p.name} number of mapped objects"))
            out.append(SdoWrite(p.com_index, 1, cob | (0 if p.enabled else COB_DISABLED), U32,
                                f"{p.name} COB-ID ({'enabled' if p.enabled else 'disabled'})",
                                ignore_mask=COB_NO_RTR))
        for index, sub, value in self.sdo:
            var = od.get_variable(index, sub)
            out.append(SdoWrite(index, sub, value, None, "sdo write",
                                read_back=var is None or var.readable))
        return out


def effective_cob_id(p: PdoConfig, od: Any, node_id: int) -> int:
    """The PDO's COB-ID without the flag bits: the configuration's, else the EDS's default, else
    the pre-defined connection set's (PDO 1..4)."""
    if p.cob_id is not None:
        return p.cob_id & 0x1FFF_FFFF
    var = od.get_variable(p.com_index, 1)
    raw = None if var is None else (var.value if var.value is not None else var.default)
    if isinstance(raw, int):
        return raw & 0x1FFF_FFFF
    base = 0x200 if p.kind == "rpdo" else 0x180
    return base + 0x100 * (p.number - 1) + node_id


@dataclass(frozen=True)
class PdoView:
    """One PDO as the node will have it after its boot: its EDS's parameters with what the
    configuration downloads over them (``chcos check``'s timing warnings, the axes' check).
    ``transmission_type`` and ``event_timer_ms`` are None where neither gives them."""

    kind: Literal["rpdo", "tpdo"]
    number: int
    enabled: bool
    transmission_type: int | None
    event_timer_ms: int | None
    objects: tuple[tuple[int, int], ...]

    @property
    def name(self) -> str:
        return f"{self.kind.upper()}{self.number}"

    @property
    def synchronous(self) -> bool:
        """Transmission type 0..240: acted upon (RPDO) or sent (TPDO) at a SYNC."""
        return self.transmission_type is not None and 0 <= self.transmission_type <= 240


def _od_int(od: Any, index: int, sub: int) -> int | None:
    """An EDS object's value (else its default) if it is an integer, else None."""
    var = od.get_variable(index, sub)
    raw = None if var is None else (var.value if var.value is not None else var.default)
    return raw if isinstance(raw, int) else None


def effective_pdos(od: Any, cfg: NodeConfig) -> list[PdoView]:
    """Every PDO of the node's EDS (``od``) and of ``cfg``, as the node has it once
    configured: the configuration's keys over the EDS's defaults (COB-ID bit 31 for enabled,
    transmission type, event timer, mapping)."""
    out: list[PdoView] = []
    given = {(p.kind, p.number): p for p in cfg.pdos}
    kinds: tuple[tuple[Literal["rpdo", "tpdo"], int, int], ...] = (
        ("rpdo", 0x1400, 0x1600), ("tpdo", 0x1800, 0x1A00))
    for kind, com_base, map_base in kinds:
        numbers = {n - com_base + 1 for n in range(com_base, com_base + 512) if n in od}
        numbers |= {num for (k, num) in given if k == kind}
        for number in sorted(numbers):
            com, mp = com_base + number - 1, map_base + number - 1
            cob = _od_int(od, com, 1)
            enabled = cob is not None and not cob & COB_DISABLED
            tt = _od_int(od, com, 2)
            timer = _od_int(od, com, 5) if kind == "tpdo" else None
            count = _od_int(od, mp, 0) or 0
            objects = []
            for i in range(1, count + 1):
                entry = _od_int(od, mp, i)
                if entry:
                    objects.append((entry >> 16, (entry >> 8) & 0xFF))
            p = given.get((kind, number))
            if p is not None:
                enabled = p.enabled
                tt = p.transmission_type if p.transmission_type is not None else tt
                timer = p.event_timer_ms if p.event_timer_ms is not None else timer
                if p.mapping is not None:
                    objects = [(index, sub) for index, sub, _bits in p.mapping]
            out.append(PdoView(kind, number, enabled, tt, timer, tuple(objects)))
    return out


def object_bits(var: Any) -> int | None:
    """The size in bits of an EDS object's data type, None for strings and domains."""
    dt = var.data_type
    if dt == 0x01:
        return 1
    st = var.STRUCT_TYPES.get(dt)
    return None if st is None else 8 * st.size


def parse(node: Mapping[str, Any]) -> NodeConfig:
    """The identity and configuration of a node entry that :func:`check` accepted."""
    ident = node.get("identity")
    identity = None if ident is None else Identity(
        int(ident["vendor"]), int(ident["product"]), int(ident["revision"]),
        None if ident.get("serial") is None else int(ident["serial"]))
    cfg = node.get("config") or {}
    pdos = []
    for p in cfg.get("pdos", ()):
        m = PDO_NAME.match(str(p["pdo"]))
        assert m is not None   # checked
        kind: Literal["rpdo", "tpdo"] = "rpdo" if m.group(1) == "rpdo" else "tpdo"
        mapping = None
        if "map" in p:
            mapping = tuple((int(e[0]), int(e[1]), int(e[2]) if len(e) > 2 else -1)
                            for e in p["map"])
        pdos.append(PdoConfig(kind, int(m.group(2)), p.get("cob_id"), bool(p.get("enabled", True)),
                              p.get("transmission_type"), p.get("inhibit_100us"),
                              p.get("event_timer_ms"), mapping))
    sdo = tuple((int(w["index"]), int(w.get("subindex", 0)), w["value"])
                for w in cfg.get("sdo", ()))
    return NodeConfig(identity, cfg.get("heartbeat_producer_ms"), cfg.get("master_consumer_ms"),
                      cfg.get("error_behaviour"), tuple(pdos), sdo, store_sub(node))


def store_sub(node: Mapping[str, Any]) -> int | None:
    """The 0x1010 sub-index of a node entry's ``store_config`` that :func:`check` accepted
    (``true`` is 1, all parameters; ``false`` or absent: None)."""
    value = node.get("store_config", False)
    if value is True:
        return 1
    if value is False:
        return None
    return int(value)


def with_bits(cfg: NodeConfig, od: Any) -> NodeConfig:
    """``cfg`` with every mapping entry's default size (-1) replaced by its object's size from
    ``od`` (entries of unknown objects keep -1: :func:`check` reports them)."""
    pdos = []
    for p in cfg.pdos:
        if p.mapping is None:
            pdos.append(p)
            continue
        entries = []
        for index, sub, bits in p.mapping:
            if bits < 0:
                var = od.get_variable(index, sub)
                bits = (object_bits(var) or -1) if var is not None else -1
            entries.append((index, sub, bits))
        pdos.append(PdoConfig(p.kind, p.number, p.cob_id, p.enabled, p.transmission_type,
                              p.inhibit_100us, p.event_timer_ms, tuple(entries)))
    return NodeConfig(cfg.identity, cfg.heartbeat_producer_ms, cfg.master_consumer_ms,
                      cfg.error_behaviour, tuple(pdos), cfg.sdo, cfg.store_sub)


def _uint(value: object, bits: int) -> bool:
    return is_int(value) and 0 <= value < (1 << bits)


def check(k: str, node: Mapping[str, Any], od: Any | None, master_ms: float | None,
          has_sync: bool = True) -> list[str]:
    """Errors of the ``identity`` and ``config`` keys of node entry ``k``; ``od`` the node's
    EDS (None if unreadable: only the shapes are checked), ``master_ms`` the bus's
    ``master_heartbeat_ms`` (None without a master heartbeat), ``has_sync`` whether the bus
    produces SYNC (a synchronous TPDO without it is never sent)."""
    errs: list[str] = []
    ident = node.get("identity")
    if ident is not None:
        if not isinstance(ident, Mapping):
            errs.append(f"{k}.identity: expected a table {{vendor, product, revision, serial}}, "
                        f"got {ident!r}")
        else:
            errs += [f"{k}.identity.{key}: unknown key; valid keys: {', '.join(IDENTITY_KEYS)}"
                     for key in ident if key not in IDENTITY_KEYS]
            for key in IDENTITY_KEYS:
                if key == "serial" and key not in ident:
                    continue
                if not _uint(ident.get(key), 32):
                    errs.append(f"{k}.identity.{key}: expected an UNSIGNED32 (0x1018), got "
                                f"{ident.get(key)!r}")
    errs += check_store(k, node, od)
    cfg = node.get("config")
    if cfg is None:
        return errs
    if not isinstance(cfg, Mapping):
        return [*errs, f"{k}.config: expected a table ({', '.join(CONFIG_KEYS)}), got {cfg!r}"]
    kc = f"{k}.config"
    errs += [f"{kc}.{key}: unknown key; valid keys: {', '.join(CONFIG_KEYS)}"
             for key in cfg if key not in CONFIG_KEYS]
    hb = cfg.get("heartbeat_producer_ms")
    if hb is not None and not _uint(hb, 16):
        errs.append(f"{kc}.heartbeat_producer_ms: expected 0..65535 ms (0x1017), got {hb!r}")
    mc = cfg.get("master_consumer_ms")
    if mc is not None:
        if not (_uint(mc, 16) and mc > 0):
            errs.append(f"{kc}.master_consumer_ms: expected 1..65535 ms (0x1016), got {mc!r}")
        elif master_ms is None:
            errs.append(f"{kc}.master_consumer_ms: the node would watch a master heartbeat the "
                        f"bus does not produce; set the bus's master_heartbeat_ms")
        elif mc <= master_ms:
            errs.append(f"{kc}.master_consumer_ms: expected more than the bus's "
                        f"master_heartbeat_ms {master_ms} (2 to 3 times it), got {mc}")
    eb = cfg.get("error_behaviour")
    if eb is not None and not _uint(eb, 8):
        errs.append(f"{kc}.error_behaviour: expected 0..255 (0x1029:01; 0 pre-operational, "
                    f"1 no change, 2 stopped), got {eb!r}")
    pdos = cfg.get("pdos", [])
    if not isinstance(pdos, list):
        errs.append(f"{kc}.pdos: expected an array of PDO tables, got {pdos!r}")
        pdos = []
    seen: set[str] = set()
    for i, p in enumerate(pdos):
        errs += _check_pdo(f"{kc}.pdos[{i}]", p, od, seen)
        tt = p.get("transmission_type") if isinstance(p, Mapping) else None
        if (not has_sync and str(p.get("pdo", "")).startswith("tpdo") and is_int(tt)
                and 0 <= tt <= 240):
            errs.append(f"{kc}.pdos[{i}].transmission_type: a synchronous TPDO (type {tt}) on "
                        f"a bus without sync_period is never sent; set the bus's sync_period "
                        f"or use 254/255")
    sdo = cfg.get("sdo", [])
    if not isinstance(sdo, list):
        errs.append(f"{kc}.sdo: expected an array of {{index, subindex, value}} tables, "
                    f"got {sdo!r}")
        sdo = []
    for i, w in enumerate(sdo):
        errs += _check_sdo(f"{kc}.sdo[{i}]", w, od)
    return errs


def check_store(k: str, node: Mapping[str, Any], od: Any | None) -> list[str]:
    """Errors of node entry ``k``'s ``store_config``: true, false or a sub-index 1..127 of
    0x1010 that the node's EDS (``od``, None if unreadable) has."""
    if "store_config" not in node:
        return []
    value = node["store_config"]
    if not (isinstance(value, bool) or (is_int(value) and 1 <= value <= 127)):
        return [f"{k}.store_config: expected true, false or a sub-index of 0x1010 (1 all "
                f"parameters, 2 communication, 3 application, 4..127 manufacturer), "
                f"got {value!r}"]
    sub = store_sub(node)
    if sub is None or od is None:
        return []
    if STORE_INDEX not in od:
        return [f"{k}.store_config: the node's EDS has no object 0x1010 (store parameters): "
                f"the node cannot store its configuration; remove store_config"]
    obj = od[STORE_INDEX]
    subs = getattr(obj, "subindices", {})
    highest = getattr(subs.get(0), "default", None)
    if sub not in subs and not (isinstance(highest, int) and sub <= highest):
        return [f"{k}.store_config: the node's EDS has no 0x1010:{sub:02X} (store parameters "
                f"sub-index {sub})"]
    return []


#: the CAN-IDs CiA 301 (7.3.5) restricts to the services of the pre-defined connection set
RESTRICTED_COB_IDS = ((0x000, 0x000, "NMT"), (0x001, 0x07F, "reserved"),
                      (0x080, 0x080, "SYNC"), (0x081, 0x0FF, "EMCY"), (0x100, 0x100, "TIME"),
                      (0x101, 0x180, "reserved"), (0x581, 0x5FF, "an SDO answer"),
                      (0x601, 0x67F, "an SDO request"), (0x6E0, 0x6FF, "reserved"),
                      (0x701, 0x77F, "a heartbeat"), (0x780, 0x7FF, "reserved"))


def restricted_cob_id(cob: int) -> str | None:
    """What restricted CAN-ID ``cob`` is kept for, None if a PDO may use it."""
    return next((what for lo, hi, what in RESTRICTED_COB_IDS if lo <= cob <= hi), None)


def _check_pdo(k: str, p: object, od: Any | None, seen: set[str]) -> list[str]:
    if not isinstance(p, Mapping):
        return [f"{k}: expected a table {{pdo, cob_id, transmission_type, map...}}, got {p!r}"]
    errs = [f"{k}.{key}: unknown key; valid keys: {', '.join(PDO_KEYS)}"
            for key in p if key not in PDO_KEYS]
    name = p.get("pdo")
    m = PDO_NAME.match(name) if isinstance(name, str) else None
    if m is None or not 1 <= int(m.group(2)) <= 512:
        return [*errs, f"{k}.pdo: expected rpdo1..rpdo512 or tpdo1..tpdo512, got {name!r}"]
    if name in seen:
        errs.append(f"{k}.pdo: {name} is configured twice")
    seen.add(str(name))
    rx = m.group(1) == "rpdo"
    number = int(m.group(2))
    com = (0x1400 if rx else 0x1800) + number - 1
    if od is not None and com not in od:
        errs.append(f"{k}.pdo: the node's EDS has no {name} (no object 0x{com:04X})")
    if "cob_id" in p and not (is_int(p["cob_id"]) and 0x001 <= p["cob_id"] <= 0x7FF):
        errs.append(f"{k}.cob_id: expected an 11-bit COB-ID 0x001..0x7FF, got {p['cob_id']!r}")
    elif "cob_id" in p and (why := restricted_cob_id(p["cob_id"])):
        errs.append(f"{k}.cob_id: 0x{p['cob_id']:03X} is {why} (a restricted CAN-ID, CiA 301 "
                    f"7.3.5); a PDO cannot use it")
    tt = p.get("transmission_type")
    if tt is not None and not (_uint(tt, 8) and (tt <= 240 or tt >= 252)):
        errs.append(f"{k}.transmission_type: expected 0..240 (synchronous) or 252..255, got "
                    f"{tt!r}")
    for key in ("inhibit_100us", "event_timer_ms"):
        if key in p and not _uint(p[key], 16):
            errs.append(f"{k}.{key}: expected 0..65535, got {p[key]!r}")
    if "enabled" in p and not isinstance(p["enabled"], bool):
        errs.append(f"{k}.enabled: expected true or false, got {p['enabled']!r}")
    if "map" not in p:
        return errs
    entries = p["map"]
    if not isinstance(entries, list) or len(entries) > 64:
        return [*errs, f"{k}.map: expected an array of at most 64 [index, subindex(, bits)] "
                       f"entries, got {entries!r}"]
    total = 0
    for j, e in enumerate(entries):
        ke = f"{k}.map[{j}]"
        if not (isinstance(e, list) and len(e) in (2, 3) and is_int(e[0]) and is_int(e[1])
                and 0 <= e[0] <= 0xFFFF and 0 <= e[1] <= 0xFF
                and (len(e) == 2 or (is_int(e[2]) and 1 <= e[2] <= 64))):
            errs.append(f"{ke}: expected [index, subindex] or [index, subindex, bits 1..64], "
                        f"got {e!r}")
            continue
        bits = e[2] if len(e) == 3 else None
        where = f"0x{e[0]:04X}:{e[1]:02X}"
        if od is not None:
            var = od.get_variable(e[0], e[1])
            if var is None:
                errs.append(f"{ke}: {where} is not in the node's EDS")
                continue
            if not var.pdo_mappable:
                errs.append(f"{ke}: {where} ({var.name}) is not PDO-mappable in the node's EDS")
            if rx and not var.writable:
                errs.append(f"{ke}: {where} ({var.name}) is read-only; an RPDO writes it")
            if not rx and not var.readable:
                errs.append(f"{ke}: {where} ({var.name}) is not readable; a TPDO reads it")
            size = object_bits(var)
            if bits is None:
                if size is None:
                    errs.append(f"{ke}: {where} has no fixed size; give bits")
                    continue
                bits = size
            elif size is not None and bits != size:
                errs.append(f"{ke}: {where} is {size} bits in the node's EDS, not {bits}")
        total += bits or 0
    if total > 64:
        errs.append(f"{k}.map: {total} bits mapped, a PDO carries at most 64")
    return errs


def _check_sdo(k: str, w: object, od: Any | None) -> list[str]:
    if not isinstance(w, Mapping):
        return [f"{k}: expected a table {{index, subindex, value}}, got {w!r}"]
    errs = [f"{k}.{key}: unknown key; valid keys: {', '.join(SDO_KEYS)}"
            for key in w if key not in SDO_KEYS]
    index, sub, value = w.get("index"), w.get("subindex", 0), w.get("value")
    if not (is_int(index) and 0 <= index <= 0xFFFF):
        errs.append(f"{k}.index: expected an object index 0..0xFFFF, got {index!r}")
    if not (is_int(sub) and 0 <= sub <= 0xFF):
        errs.append(f"{k}.subindex: expected a subindex 0..255, got {sub!r}")
    if not is_number(value) or isinstance(value, bool):
        errs.append(f"{k}.value: expected a number, got {value!r}")
    if errs or od is None:
        return errs
    var = od.get_variable(index, sub)
    where = f"0x{index:04X}:{sub:02X}"
    if var is None:
        return [f"{k}: {where} is not in the node's EDS (its data type is needed)"]
    if not var.writable:
        return [f"{k}: {where} ({var.name}) is read-only in the node's EDS"]
    if var.data_type in INTEGER_TYPES and isinstance(value, float) and not value.is_integer():
        return [f"{k}.value: expected an integer for {where}, got {value!r}"]
    try:
        var.encode_raw(int(value) if var.data_type in INTEGER_TYPES else value)  # type: ignore[arg-type]
    except (ValueError, TypeError, OverflowError, struct.error) as exc:
        return [f"{k}.value: {value!r} does not fit {where}'s data type: {exc}"]
    return []

