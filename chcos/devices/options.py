"""options - typed device-map options: one frozen dataclass per bus kind and per address kind,
one default per key, parsed once.

A bus kind declares its options (the keys of its ``[[bus]]`` table besides ``name`` and ``kind``)
and its device address (the keys of ``address = {...}``) as frozen dataclasses whose fields are
made with :func:`option`: the field's annotation is the key's type, its default the key's only
default, and its metadata the meaning, unit and accepted range that ``chcos check`` prints and the
device-map reference (``docs/device-map-reference.md``) is generated from::

    @dataclass(frozen=True)
    class TcpOptions:
        host: str = option(doc="host name or address of the server", check=nonempty)
        port: int = option(502, doc="TCP port", check=between(1, 65535))
        timeout: float = option(1.0, unit="s", doc="per request", check=positive)

:func:`parse` turns a table from a map into such a dataclass, or into every error at once, each as
``"<key path>: expected ..., got ..."`` (the form :mod:`chcos.devices.devmap` places at the file
and line). It is called once, when the map is checked; the parsed value travels with the map
(:attr:`chcos.devices.spec.BusSpec.config`, :attr:`chcos.devices.spec.DeviceSpec.addr`) and a
driver reads typed attributes from it (:meth:`chcos.devices.driver.Driver.bus_options`), never
the raw table. Adding a key to a bus kind is adding one field.

Supported annotations: ``bool``, ``int`` (not a bool), ``float`` (an integer is taken as a
float; NaN is refused), ``str``, ``Literal[...]``, an :class:`enum.Enum` (by value), ``X | None``
(absent: the default, usually None), ``tuple[X, ...]`` and ``tuple[X, Y]`` (from a TOML array),
``Mapping[str, X]`` / ``dict[str, X]`` (from a table), a nested option dataclass (from an inline
table), a union of the above (the first that fits), and ``Any`` (taken as written).
"""

from __future__ import annotations

import dataclasses
import enum
import math
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import MISSING, dataclass
from typing import Any, TypeVar, Union

from chcos.errors import ConfigError

T = TypeVar("T")

#: A check of a parsed value: None if it is acceptable, else what was expected ("an integer
#: 1..65535"); the parser prints ``"<key>: expected <that>, got <value>"``.
Check = Callable[[Any], str | None]


class _Required:
    """The default of a key that must be given."""

    def __repr__(self) -> str:
        return "REQUIRED"


REQUIRED: Any = _Required()

_META = "chcos.option"


@dataclass(frozen=True)
class OptionDoc:
    """What the reference says of one key: meaning, unit, how its type and default read, which
    variant of the kind it belongs to ("" for all), and its check."""

    doc: str
    unit: str = ""
    type_doc: str = ""
    default_doc: str = ""
    variant: str = ""
    check: Check | None = None
    nan: bool = False


def option(default: Any = REQUIRED, *, doc: str, unit: str = "", type_doc: str = "",
           default_doc: str = "", variant: str = "", check: Check | None = None,
           factory: Callable[[], Any] | None = None, nan: bool = False) -> Any:
    """A field of an option dataclass: ``default`` (:data:`REQUIRED` when the key must be
    given; ``factory`` for a mutable or computed default), the meaning ``doc``, the ``unit``
    (``"s"``, ``"ms"``, ``"Hz"``), how the reference shows the type and the default where the
    annotation and ``repr`` would not read well, the ``variant`` of the kind the key belongs to,
    and a ``check`` of the parsed value (see :data:`Check`); ``nan`` lets a float key be NaN
    (TOML's ``nan``: a value that means "none", never a measurement)."""
    meta = {_META: OptionDoc(doc, unit, type_doc, default_doc, variant, check, nan)}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


# ---- checks -------------------------------------------------------------------------------------
def between(lo: float, hi: float) -> Check:
    """A check for ``lo <= value <= hi``."""
    def check(v: Any) -> str | None:
        return None if lo <= v <= hi else f"a value {_num(lo)}..{_num(hi)}"
    return check


def at_least(lo: float) -> Check:
    """A check for ``value >= lo``."""
    def check(v: Any) -> str | None:
        return None if v >= lo else f"a value >= {_num(lo)}"
    return check


def positive(v: Any) -> str | None:
    """A check for a finite value > 0."""
    return None if v > 0 and not math.isinf(v) else "a finite value > 0"


def nonempty(v: Any) -> str | None:
    """A check for a non-empty string or collection."""
    return None if len(v) > 0 else "a non-empty value"


def _num(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _short(v: object, limit: int = 60) -> str:
    try:
        text = repr(v)
    except (RecursionError, ValueError):
        text = f"<{type(v).__name__}>"
    return text if len(text) <= limit else text[:limit - 3] + "..."


# ---- parsing -------------------------------------------------------------------------------------
class _Bad(Exception):
    """One value that does not fit its annotation: ``expected`` says what would."""

    def __init__(self, expected: str, key: str = "") -> None:
        super().__init__(expected)
        self.expected = expected
        self.key = key


def is_options(cls: object) -> bool:
    """True if ``cls`` is an option dataclass (a dataclass whose fields are options)."""
    return isinstance(cls, type) and dataclasses.is_dataclass(cls)


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _describe(tp: Any) -> str:
    """How a type reads in an error ("an integer", "one of 'N', 'E', 'O'")."""
    origin = typing.get_origin(tp)
    if tp is bool:
        return "true or false"
    if tp is int:
        return "an integer"
    if tp is float:
        return "a number"
    if tp is str:
        return "a string"
    if origin is typing.Literal:
        return "one of " + ", ".join(_short(a) for a in typing.get_args(tp))
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return "one of " + ", ".join(_short(m.value) for m in tp)
    if origin in (Union, types.UnionType):
        return " or ".join(_describe(a) for a in typing.get_args(tp) if a is not type(None))
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"an array of {_plural(_describe(args[0]))}"
        return f"an array of {len(args)} values"
    if origin in (dict, Mapping, typing.Mapping) or tp in (dict, Mapping):
        return "a table"
    if is_options(tp):
        return "an inline table"
    return "a value"


def _plural(text: str) -> str:
    return text[3:] + "s" if text.startswith("an ") else text[2:] + "s" \
        if text.startswith("a ") else text


def _convert(tp: Any, v: Any, key: str, errors: list[str]) -> Any:
    """``v`` converted to ``tp``; raises :class:`_Bad` when it does not fit. Nested option
    dataclasses add their own errors to ``errors`` (each with its full key) and raise
    :class:`_Bad` with an empty ``expected`` so that nothing more is said of the whole."""
    if tp is Any:
        return v
    origin = typing.get_origin(tp)
    if tp is bool:
        if isinstance(v, bool):
            return v
        raise _Bad(_describe(tp))
    if tp is int:
        if isinstance(v, int) and not isinstance(v, bool):
            return v
        raise _Bad(_describe(tp))
    if tp is float:
        if isinstance(v, (int, float)) and not isinstance(v, bool) and not (
                isinstance(v, float) and math.isnan(v)):
            return float(v)
        raise _Bad(_describe(tp))
    if tp is str:
        if isinstance(v, str):
            return v
        raise _Bad(_describe(tp))
    if origin is typing.Literal:
        for a in typing.get_args(tp):
            if v == a and type(v) is type(a):
                return a
        raise _Bad(_describe(tp))
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        try:
            return tp(v)
        except (ValueError, TypeError):
            raise _Bad(_describe(tp)) from None
    if origin in (Union, types.UnionType):
        kinds = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(kinds) == 1:   # X | None: X's own errors (a nested table's by key)
            return _convert(kinds[0], v, key, errors)
        for a in kinds:
            try:
                return _convert(a, v, key, [])
            except _Bad:
                continue
        raise _Bad(_describe(tp))
    if origin is tuple:
        return _convert_tuple(tp, v, key, errors)
    if origin in (dict, Mapping, typing.Mapping) or tp in (dict, Mapping):
        return _convert_table(tp, v, key, errors)
    if is_options(tp):
        if not isinstance(v, Mapping):
            raise _Bad(_describe(tp))
        value, errs = parse(tp, v, key)
        if errs:
            errors.extend(errs)
            raise _Bad("")
        return value
    raise TypeError(f"option annotation {tp!r} of {key} is not supported")


def _convert_tuple(tp: Any, v: Any, key: str, errors: list[str]) -> tuple[Any, ...]:
    args = typing.get_args(tp)
    if not isinstance(v, (list, tuple)):
        raise _Bad(_describe(tp))
    if len(args) == 2 and args[1] is Ellipsis:
        kinds = [args[0]] * len(v)
    elif len(args) == len(v):
        kinds = list(args)
    else:
        raise _Bad(_describe(tp))
    out = []
    for i, (k, item) in enumerate(zip(kinds, v, strict=True)):
        try:
            out.append(_convert(k, item, f"{key}[{i}]", errors))
        except _Bad as bad:
            if bad.expected:
                raise _Bad(bad.expected, f"{key}[{i}]") from None
            raise
    return tuple(out)


def _convert_table(tp: Any, v: Any, key: str, errors: list[str]) -> dict[str, Any]:
    args = typing.get_args(tp)
    item_tp = args[1] if len(args) == 2 else Any
    if not isinstance(v, Mapping) or not all(isinstance(k, str) for k in v):
        raise _Bad(_describe(tp))
    out = {}
    for k, item in v.items():
        try:
            out[k] = _convert(item_tp, item, f"{key}.{k}", errors)
        except _Bad as bad:
            if bad.expected:
                raise _Bad(bad.expected, f"{key}.{k}") from None
            raise
    return out


def parse(cls: type[T], table: Mapping[str, Any], path: str,
          ignore: Iterable[str] = ()) -> tuple[T | None, list[str]]:
    """Parse ``table`` (a map's table; keys in ``ignore`` are someone else's) into ``cls``.

    Returns ``(value, [])``, or ``(None, errors)`` with every error found: an unknown key (with
    the valid ones, and the variant of the table if ``cls`` names one in ``VARIANT``), a
    required key missing, a value of the wrong type or outside its check, and what the
    dataclass' own ``problems()`` method (if it has one: cross-key rules, returning
    ``(key, expected)`` pairs) finds in an otherwise valid value. Each error is
    ``"<path>.<key>: expected ..., got ..."``. Never raises for bad input; raises TypeError for
    an annotation this module does not support (a programming error)."""
    hints = _hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    skip = set(ignore)
    errors: list[str] = []
    for k in table:
        if k not in fields and k not in skip:
            if fields:   # a variant of a kind's table (VARIANT) says which
                variant = getattr(cls, "VARIANT", "")
                errors.append(f"{path}.{k}: unknown key"
                              f"{f' for the {variant} variant' if variant else ''}; expected "
                              f"one of {', '.join(sorted(fields))}")
            else:   # a kind whose table takes no key says why in NO_KEYS
                errors.append(f"{path}.{k}: unknown key; "
                              f"{getattr(cls, 'NO_KEYS', 'expected no key here')}")
    values: dict[str, Any] = {}
    for name, f in fields.items():
        key = f"{path}.{name}"
        if name not in table:
            if f.default is REQUIRED:
                errors.append(f"{key}: required; expected {_describe(hints[name])}")
            continue
        raw = table[name]
        meta = f.metadata.get(_META)
        if meta is not None and meta.nan and isinstance(raw, float) and math.isnan(raw):
            values[name] = raw
            continue
        try:
            value = _convert(hints[name], raw, key, errors)
        except _Bad as bad:
            if bad.expected:
                where = bad.key or key
                shown = raw if not bad.key else _element(raw, bad.key, key)
                errors.append(f"{where}: expected {bad.expected}, got {_short(shown)}")
            continue
        if meta is not None and meta.check is not None and value is not None:
            why = meta.check(value)
            if why is not None:
                if why.startswith("a value") and hints[name] in (int, float):
                    why = _describe(hints[name]) + why[len("a value"):]   # "an integer 1..9"
                errors.append(f"{key}: expected {why}, got {_short(raw)}")
                continue
        values[name] = value
    if errors:
        return None, errors
    result = cls(**values)
    problems = getattr(result, "problems", None)
    if callable(problems):
        found = [f"{path}.{k}: expected {why}" for k, why in problems()]
        if found:
            return None, found
    return result, []


def _element(raw: Any, where: str, key: str) -> Any:
    """The element of ``raw`` that ``where`` (``key[2]`` or ``key.sub``) names, for an error."""
    rest = where[len(key):]
    try:
        if rest.startswith("["):
            return raw[int(rest[1:rest.index("]")])]
        if rest.startswith("."):
            return raw[rest[1:].split(".")[0]]
    except (LookupError, ValueError, TypeError):
        pass
    return raw


def parsed(cls: type[T], table: Mapping[str, Any], path: str, where: str = "",
           ignore: Iterable[str] = ()) -> T:
    """:func:`parse`, raising :class:`chcos.errors.ConfigError` listing every error (each
    prefixed with ``where``, the file, when given) instead of returning them."""
    value, errors = parse(cls, table, path, ignore)
    if value is None:
        prefix = f"{where}: " if where else ""
        raise ConfigError("\n".join(prefix + e for e in errors))
    return value


def defaults(cls: type[T]) -> T:
    """``cls`` with every default (raises ConfigError if a key is required)."""
    return parsed(cls, {}, cls.__name__)


# ---- the reference -------------------------------------------------------------------------------
@dataclass(frozen=True)
class KeyDoc:
    """One key as the device-map reference lists it."""

    name: str
    type: str
    default: str
    meaning: str
    variant: str = ""


def _type_doc(tp: Any, unit: str) -> str:
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        parts = [a for a in typing.get_args(tp) if a is not type(None)]
        return " or ".join(_type_doc(a, unit) for a in parts)
    names = {bool: "bool", int: "integer", float: "float", str: "string"}
    if tp in names:
        text = names[tp]
    elif origin is typing.Literal or (isinstance(tp, type) and issubclass(tp, enum.Enum)):
        text = "string" if all(isinstance(v, str) for v in _choices(tp)) else "integer"
    elif origin is tuple:
        text = "array"
    elif is_options(tp) or origin in (dict, Mapping, typing.Mapping):
        text = "inline table"
    else:
        text = "value"
    return f"{text} {unit}" if unit else text


def _choices(tp: Any) -> list[Any]:
    if typing.get_origin(tp) is typing.Literal:
        return list(typing.get_args(tp))
    return [m.value for m in tp]


def _default_doc(f: dataclasses.Field[Any]) -> str:
    if f.default is REQUIRED:
        return "required"
    if f.default is MISSING:
        return "-"
    d = f.default
    if d is None:
        return "none"
    if isinstance(d, bool):
        return "true" if d else "false"
    if isinstance(d, enum.Enum):
        d = d.value
    if isinstance(d, str):
        return f'`"{d}"`' if d else '""'
    if isinstance(d, float):
        return f"{d:g}" if not d.is_integer() or abs(d) >= 1e16 else f"{d:.1f}"
    return f"`{d!r}`" if isinstance(d, tuple) else str(d)


def reference(cls: type) -> tuple[KeyDoc, ...]:
    """The keys of option dataclass ``cls`` for the device-map reference, in field order."""
    hints = _hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        meta = f.metadata.get(_META) or OptionDoc("")
        tp = hints[f.name]
        choices = ""
        if typing.get_origin(tp) is typing.Literal or (
                isinstance(tp, type) and issubclass(tp, enum.Enum)):
            choices = ": " + ", ".join(f"`{v}`" for v in _choices(tp))
        out.append(KeyDoc(f.name, meta.type_doc or _type_doc(tp, meta.unit),
                          meta.default_doc or _default_doc(f), meta.doc + choices, meta.variant))
    return tuple(out)
