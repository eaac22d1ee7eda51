"""statetable - NBS H-module state tables as data, and the interpreter that runs them.

A state table (Appendix 1 of the thesis) is the command part of one level of the NBS
cross-coupled processing hierarchy. Each command owns an ordered list of rows::

    state | sensory feedback | report from lower level | next state | lower command | report up

Matching (the interpreter's contract):

* A machine that accepts a command enters state 1; state 0 means the command is done: no row is
  evaluated in state 0 and the standing report up is kept. A row state ``"-"`` matches any state
  other than 0.
* **Row order matters: within the current command the first row whose state and both conditions
  hold fires.** Its next state, lower command and report up are the step's output.
  If no row fires, the machine holds: same state, no lower command issued, report unchanged.
* A condition is ``"-"`` (don't care) or comma-separated terms that must all hold. Terms are
  symbolic facts, compared after collapsing white space. A term holds when:

  1. (report column only) it equals the lower level's current report; otherwise
  2. the fact map supplied by the level's G/M functions has it: its value, or the result of
     calling it when it is a zero-argument callable (facts are evaluated lazily, in row order);
     otherwise
  3. it is a comparison (``i < max``, ``speed = (x+1)``; a single ``=`` means equality) whose
     names all resolve in the machine's variables or in the G/M value map: it is evaluated.
  4. Otherwise a sensory term is an error (:class:`StateTableError`: G/M must supply every fact
     the table names), while a report term simply does not hold (reports are what the lower
     level happened to say).

* A row's ``set`` assignments run in order (each sees the previous ones), then the lower
  command's arguments are evaluated. Names resolve in the machine variables (command parameters
  and assigned variables) first, then in the G/M value map; callables in the value map may be
  called (``dir_to(pos)``). Expressions are a small safe subset of Python: numbers, strings,
  names, ``+ - * /``, unary minus, comparisons and calls.

The interpreter knows nothing about cycles or common memory: :class:`Machine` can be stepped by
the NBS executor every 28 ms or by an ordinary CHC task when a message arrives.

Errors: :class:`~chcos.errors.ConfigError` for a table file that cannot be used (names the file,
the command and the row); :class:`StateTableError` for a failure while running a table.

Why one module of this size (about 850 lines, over the project's ~400): it is the transcription
of Appendix 1's state-table notation as a whole - the row grammar, the term and expression
subset, the table parser with its checks (coverage of earlier rows, arities across levels) and
the matching rules above are one contract, and every rule of the parser is a rule the
interpreter relies on. Split in two, the grammar and its meaning would have to be read side by
side in two files; kept together, the module docstring above is the whole specification and
the code below it implements it in the same order.
"""

from __future__ import annotations

import ast
import re
import tomllib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from chcos.errors import ChcosError, ConfigError
from chcos.helpers import is_int

__all__ = [
    "BUILTIN_TABLES",
    "Call",
    "CommandSpec",
    "Decision",
    "Expr",
    "Facts",
    "LowerSpec",
    "Machine",
    "Param",
    "Row",
    "StateTable",
    "StateTableError",
    "Step",
    "Term",
    "check_hierarchy",
    "load_builtin",
    "load_table",
    "parse_table",
]

Facts = Mapping[str, bool | Callable[[], bool]]
"""Fact map from a level's G/M functions: fact text -> truth value or zero-argument predicate."""

BUILTIN_TABLES = ("H1", "H2", "H3")
"""The Appendix-1 tables shipped in ``chcos/apps/nbs/tables``."""

DONT_CARE = "-"


class StateTableError(ChcosError):
    """A state table failed while running: an unknown fact, an unresolved name in an
    expression, a command the table does not have, a missing command parameter."""


def _norm(text: str) -> str:
    """Collapse runs of white space so facts compare by words, not by spacing."""
    return " ".join(text.split())


# --------------------------------------------------------------------------- expressions

_BINOPS: dict[type[ast.operator], Callable[[Any, Any], Any]] = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
}
_CMPOPS: dict[type[ast.cmpop], Callable[[Any, Any], bool]] = {
    ast.Lt: lambda a, b: bool(a < b),
    ast.LtE: lambda a, b: bool(a <= b),
    ast.Gt: lambda a, b: bool(a > b),
    ast.GtE: lambda a, b: bool(a >= b),
    ast.Eq: lambda a, b: bool(a == b),
    ast.NotEq: lambda a, b: bool(a != b),
}
_EQUALS = re.compile(r"(?<![<>!=])=(?!=)")


def _check_node(node: ast.AST, text: str) -> None:
    """Reject every syntax outside the small expression subset (raises ValueError)."""
    if isinstance(node, ast.Constant):
        if not isinstance(node.value, int | float | str) or isinstance(node.value, bool):
            raise ValueError(f"constant {node.value!r} is not a number or a string")
    elif isinstance(node, ast.Name):
        if node.id.startswith("__"):
            raise ValueError(f"name {node.id!r} is reserved (names may not start with '__')")
    elif isinstance(node, ast.BinOp):
        if type(node.op) not in _BINOPS:
            raise ValueError(f"operator {type(node.op).__name__} is not one of + - * /")
        _check_node(node.left, text)
        _check_node(node.right, text)
    elif isinstance(node, ast.UnaryOp):
        if not isinstance(node.op, ast.USub | ast.UAdd):
            raise ValueError("only unary + and - are allowed")
        _check_node(node.operand, text)
    elif isinstance(node, ast.Compare):
        for op in node.ops:
            if type(op) not in _CMPOPS:
                raise ValueError(f"comparison {type(op).__name__} is not allowed")
        _check_node(node.left, text)
        for comparator in node.comparators:
            _check_node(comparator, text)
    elif isinstance(node, ast.Call):
        if not isinstance(node.func, ast.Name) or node.keywords:
            raise ValueError("only calls of a plain name with positional arguments are allowed")
        _check_node(node.func, text)
        for arg in node.args:
            _check_node(arg, text)
    else:
        raise ValueError(f"{type(node).__name__} is not allowed in a table expression")


@dataclass(frozen=True)
class Expr:
    """A compiled table expression (argument, assignment or comparison).

    ``names`` are the free names it reads; :meth:`evaluate` resolves them through ``lookup``.
    Build with :meth:`parse`, which raises ValueError for text outside the subset.
    """

    text: str
    tree: ast.expr = field(compare=False, repr=False)
    names: frozenset[str] = field(compare=False)

    @classmethod
    def parse(cls, text: str) -> Expr:
        """Compile ``text``; raises ValueError (with the reason) if it is not a table expression."""
        try:
            tree = ast.parse(text.strip(), mode="eval").body
        except SyntaxError as exc:
            raise ValueError(f"cannot parse {text!r}: {exc.msg}") from exc
        _check_node(tree, text)
        called = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}
        names = frozenset(
            n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and id(n) not in called
        )
        return cls(text=text.strip(), tree=tree, names=names)

    @property
    def is_comparison(self) -> bool:
        """True when the expression is a comparison (usable as a condition term)."""
        return isinstance(self.tree, ast.Compare)

    def evaluate(self, lookup: Callable[[str], object]) -> object:
        """Evaluate; ``lookup(name)`` supplies every name (it raises for unknown ones).

        Arithmetic errors (division by zero, adding a string to a number) raise ValueError.
        """
        try:
            return self._eval(self.tree, lookup)
        except (TypeError, ZeroDivisionError, ArithmeticError) as exc:
            raise ValueError(f"{self.text!r}: {exc}") from exc

    def _eval(self, node: ast.expr, lookup: Callable[[str], object]) -> Any:
        if isinstance(node, ast.Constant):
            return node.value
        if isinstance(node, ast.Name):
            return lookup(node.id)
        if isinstance(node, ast.BinOp):
            left, right = self._eval(node.left, lookup), self._eval(node.right, lookup)
            return _BINOPS[type(node.op)](left, right)
        if isinstance(node, ast.UnaryOp):
            value = self._eval(node.operand, lookup)
            return -value if isinstance(node.op, ast.USub) else +value
        if isinstance(node, ast.Compare):
            left = self._eval(node.left, lookup)
            for op, comparator in zip(node.ops, node.comparators, strict=True):
                right = self._eval(comparator, lookup)
                if not _CMPOPS[type(op)](left, right):
                    return False
                left = right
            return True
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            fn = lookup(node.func.id)
            if not callable(fn):
                raise TypeError(f"{node.func.id} is not a function")
            return fn(*(self._eval(a, lookup) for a in node.args))
        raise TypeError(f"unsupported node {type(node).__name__}")  # excluded by _check_node


# --------------------------------------------------------------------------- table model


@dataclass(frozen=True)
class Term:
    """One condition term: the fact text, and its comparison form when it parses as one."""

    text: str
    comparison: Expr | None = None

    @classmethod
    def parse(cls, text: str) -> Term:
        """Normalise ``text``; keep a comparison form if it is one (``=`` read as ``==``)."""
        norm = _norm(text)
        try:
            expr = Expr.parse(_EQUALS.sub("==", norm))
        except ValueError:
            return cls(norm)
        return cls(norm, expr if expr.is_comparison else None)


@dataclass(frozen=True)
class Call:
    """A command with evaluated arguments, as issued to a lower level (or received from above)."""

    name: str
    args: tuple[object, ...] = ()

    def __str__(self) -> str:
        if not self.args:
            return self.name
        return f"{self.name}({', '.join(repr(a) for a in self.args)})"


@dataclass(frozen=True)
class LowerSpec:
    """The lower-command cell of a row: a command name and argument expressions."""

    name: str
    args: tuple[Expr, ...]


@dataclass(frozen=True)
class Param:
    """A command parameter; ``default`` is evaluated on the G/M value map when not passed."""

    name: str
    default: Expr | None = None


@dataclass(frozen=True)
class Row:
    """One state-table row. ``number`` counts rows of the whole file from 1 (for messages);
    ``index`` counts rows within the command from 1."""

    command: str
    index: int
    number: int
    state: int | None  # None: any running state ("-")
    sensory: tuple[Term, ...]
    report: tuple[Term, ...]
    next_state: int
    lower: LowerSpec | None
    up: str | None  # None: leave the report up unchanged ("-")
    sets: tuple[tuple[str, Expr], ...] = ()

    def where(self, path: str) -> str:
        """Location text for messages: file, command and row."""
        return f"{path}: command {self.command!r} row {self.index} (file row {self.number})"


@dataclass(frozen=True)
class CommandSpec:
    """A command of a table: its parameters and its ordered rows."""

    name: str
    params: tuple[Param, ...]
    rows: tuple[Row, ...]

    @property
    def required(self) -> int:
        """How many leading parameters have no default."""
        return sum(1 for p in self.params if p.default is None)


@dataclass(frozen=True)
class Decision:
    """What the interpreter decided for one evaluation: the row that fired and its outputs."""

    row: Row
    next_state: int
    lower: Call | None
    up: str | None
    variables: Mapping[str, object]


@dataclass(frozen=True)
class StateTable:
    """A loaded, validated H-module state table (see the module docstring for its semantics)."""

    path: str
    module: str
    level: int
    commands: Mapping[str, CommandSpec]
    lower_commands: Mapping[str, tuple[Param, ...]]  # declared level-0 vocabulary (lowest table)
    lower_reports: frozenset[str]
    report_facts: frozenset[str]

    def command(self, name: str) -> CommandSpec:
        """The command called ``name``; raises StateTableError when the table has none."""
        try:
            return self.commands[_norm(name)]
        except KeyError:
            known = ", ".join(self.commands)
            raise StateTableError(
                f"{self.path}: table {self.module} has no command {name!r} (it has: {known})"
            ) from None

    @property
    def rows(self) -> tuple[Row, ...]:
        """Every row in file order."""
        return tuple(r for c in self.commands.values() for r in c.rows)

    def reports(self) -> frozenset[str]:
        """Every report this table can send up."""
        return frozenset(r.up for r in self.rows if r.up is not None)

    def sensory_facts(self) -> frozenset[str]:
        """Every sensory term that is not a comparison: the facts G/M must supply."""
        return frozenset(t.text for r in self.rows for t in r.sensory if t.comparison is None)

    def shadowed_rows(self) -> list[tuple[Row, Row]]:
        """Pairs (earlier, later) where the earlier row fires whenever the later one would.

        A shadowed row can never fire under first-match order; the shipped tables have none.
        """
        found: list[tuple[Row, Row]] = []
        for spec in self.commands.values():
            for j, later in enumerate(spec.rows):
                for earlier in spec.rows[:j]:
                    if _covers(earlier, later):
                        found.append((earlier, later))
                        break
        return found

    def evaluate(
        self,
        command: str,
        state: int,
        facts: Facts,
        report: str | None,
        variables: Mapping[str, object] | None = None,
        values: Mapping[str, object] | None = None,
    ) -> Decision | None:
        """Find the first row of ``command`` that fires in ``state``; None if none does.

        ``facts`` and ``values`` come from the level's G/M functions, ``report`` is the lower
        level's current report (None when it has not answered), ``variables`` the machine's
        command variables. Nothing is mutated: the decision carries the updated variables.
        Raises StateTableError for an unknown command, a sensory fact missing from ``facts``,
        or an expression that names something neither map has.
        """
        spec = self.command(command)
        if state == 0:
            return None
        variables = dict(variables or {})
        values = values or {}
        for row in spec.rows:
            if row.state is not None and row.state != state:
                continue
            if not self._holds(row, row.sensory, facts, None, variables, values, sensory=True):
                continue
            if not self._holds(row, row.report, facts, report, variables, values, sensory=False):
                continue
            for name, expr in row.sets:
                variables[name] = self._eval(row, expr, variables, values)
            lower = None
            if row.lower is not None:
                args = tuple(self._eval(row, a, variables, values) for a in row.lower.args)
                lower = Call(row.lower.name, args)
            return Decision(row, row.next_state, lower, row.up, variables)
        return None

    def _lookup(
        self, row: Row, variables: Mapping[str, object], values: Mapping[str, object]
    ) -> Callable[[str], object]:
        def lookup(name: str) -> object:
            if name in variables:
                return variables[name]
            if name in values:
                return values[name]
            raise StateTableError(
                f"{row.where(self.path)}: name {name!r} is neither a command variable "
                f"({', '.join(sorted(variables)) or 'none'}) nor a value from G/M"
            )

        return lookup

    def _eval(
        self, row: Row, expr: Expr, variables: Mapping[str, object], values: Mapping[str, object]
    ) -> object:
        try:
            return expr.evaluate(self._lookup(row, variables, values))
        except ValueError as exc:
            raise StateTableError(f"{row.where(self.path)}: {exc}") from exc

    def _holds(
        self,
        row: Row,
        terms: tuple[Term, ...],
        facts: Facts,
        report: str | None,
        variables: Mapping[str, object],
        values: Mapping[str, object],
        *,
        sensory: bool,
    ) -> bool:
        for term in terms:
            if not sensory and report is not None and _norm(report) == term.text:
                continue
            if term.text in facts:
                fact = facts[term.text]
                if bool(fact() if callable(fact) else fact):
                    continue
                return False
            if term.comparison is not None:
                if self._eval(row, term.comparison, variables, values):
                    continue
                return False
            if sensory:
                raise StateTableError(
                    f"{row.where(self.path)}: sensory fact {term.text!r} is not supplied by G/M "
                    "(give it in the fact map)"
                )
            return False
        return True


def _covers(earlier: Row, later: Row) -> bool:
    """True when ``earlier`` matches in every situation ``later`` matches (shadowing)."""
    if earlier.state is not None and earlier.state != later.state:
        return False
    sens = {t.text for t in later.sensory}
    rep = {t.text for t in later.report}
    return all(t.text in sens for t in earlier.sensory) and all(
        t.text in rep for t in earlier.report
    )


# --------------------------------------------------------------------------- loading

_CALL = re.compile(r"^(?P<name>[^()]+?)\s*(?:\((?P<args>.*)\))?$")
_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_TOP_KEYS = {"module", "level", "lower", "report_facts", "command"}


def _parse_call_text(text: str) -> tuple[str, tuple[Expr, ...]]:
    """``NAME`` or ``NAME(expr, ...)`` -> (name, args); raises ValueError."""
    m = _CALL.match(text.strip())
    if m is None:
        raise ValueError(f"{text!r} is not NAME or NAME(arg, ...)")
    name = _norm(m["name"])
    if not name:
        raise ValueError(f"{text!r} has no command name")
    raw = m["args"]
    if raw is None or not raw.strip():
        return name, ()
    try:
        tree = ast.parse(f"f({raw})", mode="eval").body
    except SyntaxError as exc:
        raise ValueError(f"cannot parse the arguments of {text!r}: {exc.msg}") from exc
    if not isinstance(tree, ast.Call) or tree.keywords:
        raise ValueError(f"the arguments of {text!r} must be positional expressions")
    return name, tuple(Expr.parse(ast.unparse(a)) for a in tree.args)


def _parse_param(text: object) -> Param:
    if not isinstance(text, str):
        raise ValueError(f"parameter {text!r} is not a string 'name' or 'name=default'")
    name, eq, default = text.partition("=")
    name = name.strip()
    if not _IDENT.match(name):
        raise ValueError(f"parameter name {name!r} is not an identifier")
    return Param(name, Expr.parse(default) if eq else None)


def _parse_params(items: object) -> tuple[Param, ...]:
    if not isinstance(items, list):
        raise ValueError("params must be a list of 'name' or 'name=default' strings")
    params = tuple(_parse_param(p) for p in items)
    seen_default = False
    for p in params:
        if p.default is None and seen_default:
            raise ValueError(f"parameter {p.name!r} without default follows one with a default")
        seen_default = seen_default or p.default is not None
    if len({p.name for p in params}) != len(params):
        raise ValueError("parameter names repeat")
    return params


def _condition(cell: object, what: str) -> tuple[Term, ...]:
    if not isinstance(cell, str) or not cell.strip():
        raise ValueError(f"{what} must be a non-empty string ('-' for don't care)")
    if cell.strip() == DONT_CARE:
        return ()
    parts, depth, cur = [], 0, ""
    for ch in cell:
        depth += (ch == "(") - (ch == ")")
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    parts.append(cur)
    if any(not p.strip() for p in parts):
        raise ValueError(f"{what} {cell!r} has an empty term")
    return tuple(Term.parse(p) for p in parts)


def _state(cell: object, what: str, *, wildcard: bool) -> int | None:
    if wildcard and cell == DONT_CARE:
        return None
    if not is_int(cell) or cell < 0:
        allowed = "an integer >= 0 or '-'" if wildcard else "an integer >= 0"
        raise ValueError(f"{what} {cell!r} is not {allowed}")
    return cell


def _row(command: str, index: int, number: int, cells: object) -> Row:
    if not isinstance(cells, list) or len(cells) not in (6, 7):
        raise ValueError(
            "a row is [state, sensory, report, next, lower, up] with an optional {set = {...}}"
        )
    state = _state(cells[0], "state", wildcard=True)
    if state == 0:
        raise ValueError("state 0 is the done state: no row can start from it")
    sensory = _condition(cells[1], "sensory feedback")
    report = _condition(cells[2], "report from lower level")
    next_state = _state(cells[3], "next state", wildcard=False)
    assert next_state is not None
    lower_cell, up_cell = cells[4], cells[5]
    if not isinstance(lower_cell, str) or not lower_cell.strip():
        raise ValueError("lower command must be a non-empty string ('-' for none)")
    lower = None
    if lower_cell.strip() != DONT_CARE:
        lower = LowerSpec(*_parse_call_text(lower_cell))
    if not isinstance(up_cell, str) or not up_cell.strip():
        raise ValueError("report up must be a non-empty string ('-' for unchanged)")
    up = None if up_cell.strip() == DONT_CARE else _norm(up_cell)
    sets: list[tuple[str, Expr]] = []
    if len(cells) == 7:
        extra = cells[6]
        ok = isinstance(extra, dict) and set(extra) == {"set"} and isinstance(extra["set"], dict)
        if not ok:
            raise ValueError("the 7th cell must be {set = {var = \"expr\", ...}}")
        for var, text in extra["set"].items():
            if not _IDENT.match(var) or not isinstance(text, str):
                raise ValueError(f"assignment {var!r} = {text!r} needs an identifier and a string")
            sets.append((var, Expr.parse(text)))
    return Row(command, index, number, state, sensory, report, next_state, lower, up, tuple(sets))


def parse_table(text: str, path: str) -> StateTable:
    """Parse and validate table text; ``path`` names it in messages. Raises ConfigError."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    unknown = set(doc) - _TOP_KEYS
    if unknown:
        raise ConfigError(
            f"{path}: unknown top-level keys {sorted(unknown)}; expected {sorted(_TOP_KEYS)}"
        )
    module = doc.get("module")
    if not isinstance(module, str) or not module:
        raise ConfigError(f"{path}: 'module' must be a non-empty string such as \"H1\"")
    level = doc.get("level")
    if not is_int(level) or level < 1:
        raise ConfigError(f"{path}: 'level' must be an integer >= 1, got {level!r}")

    lower_commands: dict[str, tuple[Param, ...]] = {}
    lower_reports: frozenset[str] = frozenset()
    lower = doc.get("lower", {})
    if not isinstance(lower, dict) or set(lower) - {"commands", "reports"}:
        raise ConfigError(f"{path}: [lower] may only hold 'commands' and 'reports' lists")
    for i, sig in enumerate(lower.get("commands", []), start=1):
        try:
            if not isinstance(sig, str):
                raise ValueError(f"{sig!r} is not a string")
            name, args = _parse_call_text(sig)
            params = _parse_params([a.text for a in args])
        except ValueError as exc:
            raise ConfigError(f"{path}: [lower] commands item {i}: {exc}") from exc
        lower_commands[name] = params
    reports = lower.get("reports", [])
    if not isinstance(reports, list) or not all(isinstance(r, str) for r in reports):
        raise ConfigError(f"{path}: [lower] reports must be a list of strings")
    lower_reports = frozenset(_norm(r) for r in reports)
    rfacts = doc.get("report_facts", [])
    if not isinstance(rfacts, list) or not all(isinstance(r, str) for r in rfacts):
        raise ConfigError(f"{path}: report_facts must be a list of strings")

    commands: dict[str, CommandSpec] = {}
    raw_commands = doc.get("command")
    if not isinstance(raw_commands, list) or not raw_commands:
        raise ConfigError(f"{path}: expected at least one [[command]] table")
    number = 0
    for ci, raw in enumerate(raw_commands, start=1):
        if not isinstance(raw, dict) or set(raw) - {"name", "params", "rows"}:
            raise ConfigError(f"{path}: [[command]] {ci} may only hold name, params and rows")
        raw_name = raw.get("name")
        if not isinstance(raw_name, str) or not raw_name.strip():
            raise ConfigError(f"{path}: [[command]] {ci} needs a non-empty 'name'")
        name = _norm(raw_name)
        if name in commands:
            raise ConfigError(f"{path}: command {name!r} is defined twice")
        try:
            params = _parse_params(raw.get("params", []))
        except ValueError as exc:
            raise ConfigError(f"{path}: command {name!r} params: {exc}") from exc
        raw_rows = raw.get("rows")
        if not isinstance(raw_rows, list) or not raw_rows:
            raise ConfigError(f"{path}: command {name!r} needs a non-empty 'rows' list")
        rows: list[Row] = []
        for ri, cells in enumerate(raw_rows, start=1):
            number += 1
            try:
                rows.append(_row(name, ri, number, cells))
            except ValueError as exc:
                raise ConfigError(
                    f"{path}: command {name!r} row {ri} (file row {number}): {exc}"
                ) from exc
        states = {r.state for r in rows}
        if 1 not in states and None not in states:
            raise ConfigError(f"{path}: command {name!r} has no row for state 1, where it starts")
        for r in rows:
            if r.next_state not in states and r.next_state != 0 and None not in states:
                raise ConfigError(
                    f"{r.where(path)}: next state {r.next_state} has no rows of its own"
                )
        commands[name] = CommandSpec(name, params, tuple(rows))

    return StateTable(
        path=path,
        module=module,
        level=level,
        commands=commands,
        lower_commands=lower_commands,
        lower_reports=lower_reports,
        report_facts=frozenset(_norm(r) for r in rfacts),
    )


def load_table(path: str | Path) -> StateTable:
    """Load and validate a table file. Raises ConfigError naming the file (and row)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read state table: {exc.strerror or exc}") from exc
    return parse_table(text, str(p))


def load_builtin(name: str) -> StateTable:
    """Load one of the Appendix-1 tables shipped with chcos (``"H1"``, ``"H2"``, ``"H3"``).

    Raises ConfigError for an unknown name or a damaged file.
    """
    if name not in BUILTIN_TABLES:
        raise ConfigError(f"no built-in state table {name!r}; expected one of {BUILTIN_TABLES}")
    res = resources.files("chcos.apps.nbs.tables").joinpath(f"{name}.toml")
    try:
        text = res.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"chcos/apps/nbs/tables/{name}.toml: cannot read: {exc}") from exc
    return parse_table(text, f"chcos/apps/nbs/tables/{name}.toml")


def _arity_error(vocab: Mapping[str, tuple[Param, ...]], row: Row, path: str) -> str | None:
    assert row.lower is not None
    params = vocab.get(row.lower.name)
    if params is None:
        return (
            f"{row.where(path)}: lower command {row.lower.name!r} is not a command of the level "
            "below"
        )
    required = sum(1 for p in params if p.default is None)
    if not required <= len(row.lower.args) <= len(params):
        return (
            f"{row.where(path)}: lower command {row.lower.name!r} takes {required}..{len(params)} "
            f"arguments, the row gives {len(row.lower.args)}"
        )
    return None


def check_hierarchy(tables: Sequence[StateTable]) -> None:
    """Check that tables ordered from level 1 upward fit together; raises ConfigError.

    Levels must be 1, 2, ...; every lower command of a table must be a command of the table
    below (the lowest table: of its declared ``[lower] commands``) with a fitting number of
    arguments; every report term must be a report the level below can give, a declared
    ``report_facts`` entry, or a comparison.
    """
    for i, table in enumerate(tables):
        if table.level != i + 1:
            raise ConfigError(
                f"{table.path}: level {table.level} found where level {i + 1} belongs"
            )
        if i == 0:
            vocab: Mapping[str, tuple[Param, ...]] = table.lower_commands
            below_reports: Iterable[str] = table.lower_reports
        else:
            below = tables[i - 1]
            vocab = {n: c.params for n, c in below.commands.items()}
            below_reports = below.reports()
        allowed = set(below_reports) | set(table.report_facts)
        for row in table.rows:
            if row.lower is not None:
                problem = _arity_error(vocab, row, table.path)
                if problem:
                    raise ConfigError(problem)
            for term in row.report:
                if term.comparison is None and term.text not in allowed:
                    raise ConfigError(
                        f"{row.where(table.path)}: report term {term.text!r} is neither a report "
                        "of the level below nor listed in report_facts"
                    )


# --------------------------------------------------------------------------- machine


@dataclass(frozen=True)
class Step:
    """The outcome of one :meth:`Machine.step`.

    ``row`` is the row that fired (None: the machine held or is idle); ``lower`` the command
    issued this step (None: nothing issued); ``lower_new`` is true when that command starts a
    new activation below (the row changed state, or the command or its arguments differ from
    the last one issued), false when it re-issues the standing command; ``report`` is the
    standing report up after the step.
    """

    row: Row | None
    state: int
    lower: Call | None
    lower_new: bool
    report: str | None


class Machine:
    """One running H module: a state table plus its current command, state and variables.

    Independent of any executor: step it every NBS cycle or from a CHC task when input arrives.
    """

    def __init__(self, table: StateTable) -> None:
        self.table = table
        self.command: Call | None = None
        self.state = 0
        self.variables: dict[str, object] = {}
        self.report: str | None = None
        self.last_lower: Call | None = None
        self.activations = 0

    @property
    def idle(self) -> bool:
        """True when no command is running (none accepted yet, or the last one is done)."""
        return self.state == 0

    def start(
        self, name: str, args: Sequence[object] = (), values: Mapping[str, object] | None = None
    ) -> None:
        """Accept command ``name`` with positional ``args``: bind parameters and enter state 1.

        Defaults of missing parameters are evaluated on ``values`` (the G/M value map) and the
        parameters bound before them. Raises StateTableError for an unknown command, too many
        or too few arguments, or a default that cannot be evaluated.
        """
        spec = self.table.command(name)
        if not spec.required <= len(args) <= len(spec.params):
            raise StateTableError(
                f"{self.table.path}: command {spec.name!r} takes {spec.required}.."
                f"{len(spec.params)} arguments, got {len(args)}"
            )
        bound: dict[str, object] = {}
        values = values or {}
        for i, param in enumerate(spec.params):
            if i < len(args):
                bound[param.name] = args[i]
                continue
            assert param.default is not None
            env = {**values, **bound}

            def lookup(n: str, env: Mapping[str, object] = env, p: Param = param) -> object:
                if n in env:
                    return env[n]
                raise StateTableError(
                    f"{self.table.path}: command {spec.name!r} parameter {p.name!r}: default "
                    f"{p.default.text if p.default else ''!r} names {n!r}, which G/M do not supply"
                )

            try:
                bound[param.name] = param.default.evaluate(lookup)
            except ValueError as exc:
                raise StateTableError(
                    f"{self.table.path}: command {spec.name!r} parameter {param.name!r}: {exc}"
                ) from exc
        self.command = Call(spec.name, tuple(args))
        self.state = 1
        self.variables = bound
        self.last_lower = None
        self.activations += 1

    def step(
        self, facts: Facts, report: str | None, values: Mapping[str, object] | None = None
    ) -> Step:
        """Evaluate the current command once; see the module docstring for the rules.

        Raises StateTableError as :meth:`StateTable.evaluate` does.
        """
        if self.command is None or self.state == 0:
            return Step(None, self.state, None, False, self.report)
        decision = self.table.evaluate(
            self.command.name, self.state, facts, report, self.variables, values
        )
        if decision is None:
            return Step(None, self.state, None, False, self.report)
        changed_state = decision.next_state != self.state
        self.state = decision.next_state
        self.variables = dict(decision.variables)
        if decision.up is not None:
            self.report = decision.up
        new = False
        if decision.lower is not None:
            new = changed_state or decision.lower != self.last_lower
            self.last_lower = decision.lower
        return Step(decision.row, self.state, decision.lower, new, self.report)
