"""NBS state tables: the Appendix-1 tables load, fit together, reject bad data, interpret rows."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from chcos.apps.nbs.statetable import (
    BUILTIN_TABLES,
    Call,
    Expr,
    Machine,
    StateTable,
    StateTableError,
    check_hierarchy,
    load_builtin,
    load_table,
    parse_table,
)
from chcos.errors import ChcosError, ConfigError

# Rows per command as transcribed from Appendix 1 (NOTES.md explains each repair).
EXPECTED_ROWS = {
    "H1": {
        "MOVE TO P": 4,
        "TURN ON ARC": 3,
        "TURN OFF ARC": 3,
        "TURN ON INERT GAS": 4,
        "TURN OFF INERT GAS": 3,
        "ADVANCE ELECTRODE SPEED": 4,
        "RETARD ELECTRODE SPEED": 4,
        "MOVE 5mm DIR": 4,
        "STOP": 2,
        "APPROACH": 2,
    },
    "H2": {
        "TURN ON WELD": 5,
        "TURN OFF WELD": 5,
        "GOTO HOME": 2,
        "UNSTICK TIP": 12,
        "STOP": 6,
        "FIND START OF GAP": 7,
        "MOVE 5mm DIR": 2,
        "ADVANCE ELECTRODE SPEED": 2,
        "RETARD ELECTRODE SPEED": 2,
    },
    "H3": {"INSPECT GAP": 9, "WELD GAP": 17, "STOP": 2},
}

GOOD = """
module = "HX"
level = 1
[[command]]
name = "GO"
params = ["p", "speed=0.5"]
rows = [
  [1, "-", "-", 2, "START(p, speed)", "go notdone"],
  [2, "ready", "-", 0, "-", "go done"],
]
"""


def tables() -> list[StateTable]:
    return [load_builtin(n) for n in BUILTIN_TABLES]


# ---------------------------------------------------------------- loading the shipped tables


@pytest.mark.parametrize("name", BUILTIN_TABLES)
def test_every_row_of_the_appendix_tables_loads(name: str) -> None:
    table = load_builtin(name)
    assert table.module == name
    assert table.level == int(name[1])
    got = {c.name: len(c.rows) for c in table.commands.values()}
    assert got == EXPECTED_ROWS[name]
    numbers = [r.number for r in table.rows]
    assert numbers == list(range(1, sum(EXPECTED_ROWS[name].values()) + 1))


def test_tables_fit_together_as_a_hierarchy() -> None:
    check_hierarchy(tables())  # raises ConfigError on any mismatch


def test_no_row_of_the_shipped_tables_is_shadowed() -> None:
    for table in tables():
        assert table.shadowed_rows() == [], table.module


def test_load_table_reads_a_file(tmp_path: Path) -> None:
    path = tmp_path / "hx.toml"
    path.write_text(GOOD, encoding="utf-8")
    table = load_table(path)
    row = table.command("GO").rows[0]
    assert row.lower is not None and row.lower.name == "START"
    assert [a.text for a in row.lower.args] == ["p", "speed"]


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope.toml"):
        load_table(tmp_path / "nope.toml")


def test_unknown_builtin_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="H9"):
        load_builtin("H9")


# ---------------------------------------------------------------- rejecting bad tables

BAD_ROWS = [
    ('[1, "-", "-", 2, "X"]', "row 2 .*state, sensory, report"),
    ('["one", "-", "-", 0, "X", "r"]', "row 2 .*state 'one'"),
    ('[0, "-", "-", 0, "X", "r"]', "row 2 .*state 0 is the done state"),
    ('[1, "-", "-", "-", "X", "r"]', "row 2 .*next state"),
    ('[1, "", "-", 0, "X", "r"]', "row 2 .*sensory feedback"),
    ('[1, "a,,b", "-", 0, "X", "r"]', "row 2 .*empty term"),
    ('[1, "-", "-", 0, "X(1 +)", "r"]', "row 2 .*cannot parse"),
    ('[1, "-", "-", 0, "X(a=1)", "r"]', "row 2 .*positional"),
    ('[1, "-", "-", 0, "X(__import__(\'os\'))", "r"]', "row 2 .*reserved"),
    ('[1, "-", "-", 0, "X(a.b)", "r"]', "row 2 .*Attribute"),
    ('[1, "-", "-", 0, "X", ""]', "row 2 .*report up"),
    ('[1, "-", "-", 0, "X", "r", {set = {"1a" = "2"}}]', "row 2 .*assignment"),
    ('[1, "-", "-", 0, "X", "r", {let = {a = "2"}}]', "row 2 .*7th cell"),
    ('[1, "-", "-", 7, "X", "r"]', "row 2 .*next state 7 has no rows"),
]


@pytest.mark.parametrize(("row", "message"), BAD_ROWS)
def test_bad_row_is_rejected_naming_file_and_row(row: str, message: str) -> None:
    text = f"""
module = "HX"
level = 1
[[command]]
name = "GO"
rows = [
  [1, "-", "-", 0, "-", "ok"],
  {row},
]
"""
    with pytest.raises(ConfigError, match=f"bad.toml: command 'GO' .*{message}"):
        parse_table(text, "bad.toml")


BAD_DOCS = [
    ("module = 'HX'\nlevel = 1\n", "at least one \\[\\[command\\]\\]"),
    ("level = 1\n[[command]]\nname='A'\nrows=[[1,'-','-',0,'-','r']]", "'module'"),
    ("module='HX'\nlevel=0\n[[command]]\nname='A'\nrows=[[1,'-','-',0,'-','r']]", "'level'"),
    ("module='HX'\nlevel=1\nextra=1\n", "unknown top-level keys"),
    ("module='HX'\nlevel=1\n[[command]]\nname='A'\nrows=[]", "non-empty 'rows'"),
    ("module='HX'\nlevel=1\n[[command]]\nname='A'\nrows=[[2,'-','-',0,'-','r']]", "state 1"),
    (
        "module='HX'\nlevel=1\n[[command]]\nname='A'\nrows=[[1,'-','-',0,'-','r']]\n"
        "[[command]]\nname='A'\nrows=[[1,'-','-',0,'-','r']]",
        "defined twice",
    ),
    (
        "module='HX'\nlevel=1\n[[command]]\nname='A'\nparams=['a=1', 'b']\n"
        "rows=[[1,'-','-',0,'-','r']]",
        "without default follows",
    ),
    ("module = [", "not valid TOML"),
]


@pytest.mark.parametrize(("text", "message"), BAD_DOCS)
def test_bad_document_is_rejected_naming_the_file(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=f"bad.toml: .*{message}"):
        parse_table(text, "bad.toml")


def test_hierarchy_check_rejects_unknown_lower_command() -> None:
    h1 = load_builtin("H1")
    h2 = parse_table(
        "module='H2'\nlevel=2\n[[command]]\nname='A'\n"
        "rows=[[1,'-','-',0,'TURN ON GAS','r']]",
        "h2.toml",
    )
    with pytest.raises(ConfigError, match=r"h2.toml: command 'A' row 1 .*'TURN ON GAS'"):
        check_hierarchy([h1, h2])


def test_hierarchy_check_rejects_wrong_arity_and_unknown_report() -> None:
    h1 = load_builtin("H1")
    too_many = parse_table(
        "module='H2'\nlevel=2\n[[command]]\nname='A'\n"
        "rows=[[1,'-','-',0,'APPROACH(1, 2)','r']]",
        "h2.toml",
    )
    with pytest.raises(ConfigError, match=r"takes 1..1 arguments, the row gives 2"):
        check_hierarchy([h1, too_many])
    bad_report = parse_table(
        "module='H2'\nlevel=2\n[[command]]\nname='A'\nrows=[[1,'-','gas fall',0,'-','r']]",
        "h2.toml",
    )
    with pytest.raises(ConfigError, match="report term 'gas fall'"):
        check_hierarchy([h1, bad_report])
    with pytest.raises(ConfigError, match="level 2 found where level 1"):
        check_hierarchy([bad_report])


def test_shadowed_row_is_detected() -> None:
    table = parse_table(
        "module='HX'\nlevel=1\n[[command]]\nname='A'\nrows=[\n"
        " [1,'gas flowing','-',1,'-','on'],\n [1,'gas flowing','timeout',0,'-','fail']]",
        "x.toml",
    )
    [(earlier, later)] = table.shadowed_rows()
    assert (earlier.index, later.index) == (1, 2)


# ---------------------------------------------------------------- interpreter


def gas_facts(flowing: bool) -> dict[str, bool]:
    return {"gas flowing": flowing, "gas not flowing": not flowing}


def test_turn_on_inert_gas_with_bottle_empty_closes_valve() -> None:
    h1 = load_builtin("H1")
    # no level-0 report at all: no row fires, the machine holds
    assert h1.evaluate("TURN ON INERT GAS", 1, gas_facts(False), None) is None
    d = h1.evaluate("TURN ON INERT GAS", 1, {**gas_facts(False), "bottle empty": True}, None)
    assert d is not None
    assert (d.next_state, d.lower, d.up) == (0, Call("CLOSE VALVE"), "bottle empty")
    assert d.row.index == 2


def test_turn_on_inert_gas_opens_valve_until_flowing() -> None:
    h1 = load_builtin("H1")
    d = h1.evaluate("TURN ON INERT GAS", 1, gas_facts(False), "bottle full")
    assert d is not None and (d.next_state, d.lower, d.up) == (1, Call("OPEN VALVE"), "gas off")
    d = h1.evaluate("TURN ON INERT GAS", 1, gas_facts(True), "bottle full")
    assert d is not None and (d.next_state, d.lower, d.up) == (0, None, "gas on")
    d = h1.evaluate("TURN ON INERT GAS", 1, gas_facts(False), "timeout")
    assert d is not None and (d.lower, d.up) == (Call("CLOSE VALVE"), "gas fail")


def test_comparisons_use_values_and_variables() -> None:
    h1 = load_builtin("H1")
    hot = {"temp": 900.0, "threshold": 800.0}
    d = h1.evaluate("TURN ON ARC", 1, {}, "arc on", values=hot)
    assert d is not None and (d.next_state, d.lower, d.up) == (0, Call("KEEP VOLTAGE"), "arc on")
    cold = {"temp": 20.0, "threshold": 800.0}
    d = h1.evaluate("TURN ON ARC", 1, {}, "arc off", values=cold)
    assert d is not None and d.lower == Call("INCR VOLTAGE")
    # inconsistent: cold but the arc reported on -> catch-all row 3
    d = h1.evaluate("TURN ON ARC", 1, {}, "arc on", values=cold)
    assert d is not None and (d.row.index, d.up) == (3, "arc fail")


def test_facts_override_comparisons_and_may_be_callables() -> None:
    h1 = load_builtin("H1")
    calls: list[str] = []

    def cold() -> bool:
        calls.append("cold")
        return True

    facts: dict[str, bool | Callable[[], bool]] = {
        "temp < threshold": cold, "temp >= threshold": False}
    d = h1.evaluate("TURN ON ARC", 1, facts, "arc off")
    assert d is not None and d.lower == Call("INCR VOLTAGE")
    assert calls == ["cold"]


def test_first_matching_row_wins() -> None:
    h1 = load_builtin("H1")
    # timeout and "gas flowing" both hold: the earlier (timeout) row fires, not "CLOSE VALVE"
    d = h1.evaluate("TURN OFF INERT GAS", 1, gas_facts(True), "timeout")
    assert d is not None and (d.row.index, d.up) == (1, "gas fail")
    d = h1.evaluate("TURN OFF INERT GAS", 1, gas_facts(True), None)
    assert d is not None and (d.row.index, d.lower) == (2, Call("CLOSE VALVE"))


def test_state_zero_and_wildcard_state() -> None:
    h1 = load_builtin("H1")
    assert h1.evaluate("MOVE TO P", 0, {}, "timeout", {"p": "home", "speed": 0.9}) is None
    d = h1.evaluate("MOVE TO P", 2, {}, "timeout", {"p": "home", "speed": 0.9})
    assert d is not None and (d.row.index, d.lower, d.up) == (4, Call("MOTORS OFF"), "move fail")


def test_unknown_sensory_fact_names_table_command_and_row() -> None:
    h1 = load_builtin("H1")
    with pytest.raises(StateTableError, match=r"H1.toml: command 'TURN ON INERT GAS' row 1 .*"
                       r"'gas not flowing'"):
        h1.evaluate("TURN ON INERT GAS", 1, {}, "bottle full")


def test_unresolved_name_and_unknown_command() -> None:
    h1 = load_builtin("H1")
    with pytest.raises(StateTableError, match=r"row 1 .*name 'speed'"):
        h1.evaluate("ADVANCE ELECTRODE SPEED", 1, {}, None, {"x": 3})
    with pytest.raises(StateTableError, match="no command 'FLY'"):
        h1.evaluate("FLY", 1, {}, None)
    assert issubclass(StateTableError, ChcosError)


def test_expressions_are_evaluated_with_sets_before_arguments() -> None:
    h2 = load_builtin("H2")
    d = h2.evaluate("FIND START OF GAP", 1, {}, "move done", {"start": "s", "target": "t"})
    assert d is not None
    assert d.lower == Call("MOVE 5mm DIR", (0, 1))
    assert {k: d.variables[k] for k in ("d", "max", "i")} == {"d": 0, "max": 2, "i": 2}
    # spiral: at i >= max turn by 90 degrees and widen
    v = {"start": "s", "target": "t", "d": 0, "max": 2, "i": 2}
    d = h2.evaluate("FIND START OF GAP", 3, {}, "notat(t)", v)
    assert d is not None and d.variables["d"] == 90 and d.variables["max"] == 3
    assert d.lower == Call("MOVE 5mm DIR", (90, 1))
    v = {"start": "s", "target": "t", "d": 0, "max": 5, "i": 2}
    d = h2.evaluate("FIND START OF GAP", 3, {}, "notat(t)", v)
    assert d is not None and d.variables["i"] == 4 and d.variables["d"] == 0


def test_value_map_functions_can_be_called() -> None:
    h3 = load_builtin("H3")
    values = {"pos": (3.0, 4.0), "dir_to": lambda p: round(p[1] / p[0], 3)}
    facts = {"pos(next gapcentre)": True}
    d = h3.evaluate("INSPECT GAP", 1, facts, "at gapstart", {}, values)
    assert d is not None and d.variables["d"] == 1.333 and d.lower is None and d.up is None


def test_expr_rejects_unsafe_syntax() -> None:
    for text in ("a.b", "x[0]", "lambda: 1", "f(y=1)", "True and 1", "1 if 2 else 3"):
        with pytest.raises(ValueError):
            Expr.parse(text)
    assert Expr.parse("-(x + 1) * 2 / 4").evaluate({"x": 1}.__getitem__) == -1.0


# ---------------------------------------------------------------- machine


def test_machine_binds_parameters_and_steps_move_to_p() -> None:
    m = Machine(load_builtin("H1"))
    m.start("MOVE TO P", ("home",))
    assert m.variables == {"p": "home", "speed": 0.9}
    s = m.step({}, "not arrived")
    assert (s.state, s.lower, s.lower_new, s.report) == (
        2, Call("GET THETA TO", ("home",)), True, "move notdone")
    s = m.step({}, "not arrived")
    assert (s.lower, s.lower_new) == (Call("MOTORS ON", (0.9,)), True)
    s = m.step({}, "not arrived")
    assert (s.lower, s.lower_new) == (Call("MOTORS ON", (0.9,)), False)  # standing command
    s = m.step({}, "arrived")
    assert (s.state, s.lower, s.report) == (0, Call("MOTORS OFF"), "move done")
    assert m.idle
    s = m.step({}, "timeout")  # done: nothing fires in state 0, the report stands
    assert (s.row, s.lower, s.report) == (None, None, "move done")


def test_machine_holds_when_no_row_matches() -> None:
    m = Machine(load_builtin("H1"))
    m.start("MOVE TO P", ("home",))
    s = m.step({}, "arrived")  # already there: state 1 has no row for it
    assert (s.row, s.state, s.lower, s.report) == (None, 1, None, None)


def test_machine_parameter_default_from_values() -> None:
    m = Machine(load_builtin("H1"))
    m.start("ADVANCE ELECTRODE SPEED", values={"speed": 4})
    assert m.variables == {"x": 4}
    s = m.step({}, None, {"speed": 4})
    assert (s.state, s.lower) == (2, Call("SPEEDUP", (5,)))
    s = m.step({}, None, {"speed": 5})
    assert (s.state, s.report) == (0, "speedup done")
    with pytest.raises(StateTableError, match=r"parameter 'x'.*'speed'"):
        m.start("ADVANCE ELECTRODE SPEED", values={})


def test_machine_rejects_bad_arguments() -> None:
    m = Machine(load_builtin("H1"))
    with pytest.raises(StateTableError, match=r"takes 1..2 arguments, got 0"):
        m.start("MOVE TO P")
    with pytest.raises(StateTableError, match=r"takes 1..2 arguments, got 3"):
        m.start("MOVE TO P", (1, 2, 3))
    with pytest.raises(StateTableError, match="no command"):
        m.start("JUMP")
