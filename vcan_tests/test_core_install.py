"""System manager: the thesis' install script, hierarchy rules, setpri, sysfile.map, syntax."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest

from chcos.apps import fig65
from chcos.errors import CommandSyntaxError, ConfigError, InstallError, MessageError
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System, cmdline, sysmap
from chcos.tables.messages import LinkType
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel, task
from vcan_tests.conftest import MakeSystem, memory_map

M = "vcan_tests.test_core_install"
ROOT = Path(__file__).resolve().parent.parent


async def idle(ctx: TaskContext, cmd: Any) -> None:
    await ctx.sleep(1000.0)


class GapModel(WorldModel):
    def answer(self, topic: str, *args: Any) -> Any:
        if topic == "next_centre":
            return self.sensory.get("centre", 0.0) + 5.0
        return super().answer(topic, *args)


@task(world_model=GapModel)
async def modelled(ctx: TaskContext, cmd: Any) -> None:
    ctx.world.sensory["centre"] = 12.0
    await ctx.sleep(1000.0)




async def asker(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    await ctx.sleep(0.1)
    cmd["log"].append(await ctx.ask("D1", "next_centre"))
    try:
        await ctx.ask("X", "anything")
    except MessageError as exc:
        cmd["log"].append(str(exc))


async def lower(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    for i in range(3):
        await ctx.sleep(0.1)
        ctx.put(("reading", ctx.name, i))
    await ctx.sleep(1000.0)


async def exception_task(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    while True:
        src, value = await ctx.read_exception()
        cmd["log"].append((src, value, ctx.priority))


async def assassin(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    await ctx.sleep(0.15)
    ctx.suspend_task("L1")
    cmd["log"].append(("estop", ctx.estop("intruder")))


def _fig65(tmp_path: Path) -> System:
    shutil.copy(fig65.HERE / "testfile", tmp_path / "testfile")
    return System([ROOT / "chcos" / "apps" / "fig65" / "fig65.toml"], clock=VirtualClock(),
                  task_path=[fig65.HERE], base_dir=tmp_path, map_path=tmp_path / "sysfile.map")


def test_thesis_script_builds_figure_6_5(tmp_path: Path) -> None:
    with _fig65(tmp_path) as s:
        s.run_script(fig65.SCRIPT)
        assert [t.name for t in s.tsktab] == ["A1", "A2", "A3", "A4", "B1", "B2", "C1"]
        levels = {t.name: t.level for t in s.tsktab}
        assert levels == {"A1": 1, "A2": 1, "A3": 1, "A4": 1, "B1": 2, "B2": 2, "C1": 3}
        assert {t.name: t.machine for t in s.tsktab}["C1"] == 2
        # the Msgtab entries the thesis lists after "install -m0i2o1 A1 S1 S2 M1" and B1
        assert s.msgtab.find("S1", "A1").type is LinkType.SENSORY
        assert s.msgtab.find("A1", "M1").type is LinkType.COMMAND
        assert s.msgtab.find("A1", "B1").type is LinkType.SENSORY
        assert s.msgtab.find("B1", "A1").type is LinkType.COMMAND
        assert s.msgtab.find("C1", "B1").priority == 9
        assert s.msgtab.find("A4", "C1").priority == 9
        s.invoke("C1")
        s.run_for(5.0)
        assert s.tsktab.get("A1").steps > 40 and s.tsktab.get("B1").owner is not None
        s.execute("inject /dev/tty0 hello")
        s.run_for(0.5)
        assert "tty hello" in (tmp_path / "log").read_text()
        s.execute("inject /dev/tty0 stop")
        s.run_for(0.5)
        assert s.msgtab.find("host", "C1").status.value == "normal completion"


BAD_INSTALLS = [
    ("install -m0i1 A9 NOPE", "input NOPE of A9 does not exist"),
    ("install -m0i1 A9 M1", "input M1 of A9 is an actuator"),
    ("install -m0o1 A9 S1", "output S1 of A9 is a sensor"),
    ("install -m5i1 A9 S1", "machine 5 is not loaded"),
    ("install -m0i1 --level=1 A9 T1",
     "sensory link T1/A9 must go up to a strictly higher level: T1 is at level 1, A9 would be at "
     "level 1"),
    ("install -m0o1 --level=1 A9 T1",
     "command link A9/T1 must go down to a strictly lower level: T1 is at level 1"),
    ("install -m0i1 T1 S1", "task T1 is already installed on machine 0"),
    ("install -m0i2 A9 S1 S1", "inputs name S1 more than once"),
    ("install -m0i1 A9 ./missing.txt", "input file ./missing.txt of A9 does not exist"),
    ("install -m0i9 A9 S1 S1 S1 S1 S1 S1 S1 S1 S1", "input count 9 is out of range"),
    ("install -m0 --code=no.such.module:fn A9", "no module no.such.module"),
    (f"install -m0 --code={M}:GapModel A9", "GapModel is not an async def function"),
]


@pytest.mark.parametrize(("line", "expected"), BAD_INSTALLS)
def test_bad_install_is_rejected_whole(make_system: MakeSystem, line: str, expected: str) -> None:
    s = make_system(memory_map(["S1"], ["M1"]))
    s.execute(f"install -m0i1 --code={M}:idle T1 S1")
    before = json.dumps(s.sysmgr.map_doc(), default=str)
    with pytest.raises((InstallError, CommandSyntaxError)) as info:
        s.execute(line)
    assert expected in str(info.value)
    assert json.dumps(s.sysmgr.map_doc(), default=str) == before


def test_levels_follow_links_and_explicit_level_places_higher(make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S1"], ["M1"]))
    s.execute(f"install -m0i1o1 --code={M}:idle A S1 M1")
    s.execute(f"install -m0i1o1 --code={M}:idle B A A")
    s.execute(f"install -m0o1 --level=5 --code={M}:idle E B")
    assert [s.tsktab.get(n).level for n in "ABE"] == [1, 2, 5]


def test_setpri_unknown_link_and_range(make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S1"]))
    s.execute(f"install -m0i1 --code={M}:idle A S1")
    with pytest.raises(InstallError, match="no link A/S1"):
        s.execute("setpri -5 A S1")
    with pytest.raises(CommandSyntaxError, match="priority 100 is out of range"):
        s.execute("setpri -100 S1 A")
    s.execute("setpri -42 S1 A")
    assert s.msgtab.find("S1", "A").priority == 42


def test_the_task_decorator_names_the_world_model_and_refuses_a_non_callable(
        make_system: MakeSystem) -> None:
    s = make_system()
    s.execute(f"install -m0 --code={M}:modelled D1")
    s.execute(f"install -m0 --code={M}:idle X")
    assert type(s.tsktab.get("D1").world) is GapModel
    assert type(s.tsktab.get("X").world) is WorldModel
    with pytest.raises(ConfigError, match="world_model"):
        task(world_model=3)  # type: ignore[arg-type]


def test_world_model_is_queried_through_a_link(make_system: MakeSystem) -> None:
    s = make_system()
    s.execute(f"install -m0 --code={M}:modelled D1")
    s.execute(f"install -m0 --code={M}:idle X")
    s.execute(f"install -m0o1 --code={M}:asker E1 D1")
    log: list[Any] = []
    s.invoke("D1")
    s.invoke("E1", {"log": log})
    s.run_for(1.0)
    assert log[0] == 17.0
    assert "has no link to X" in log[1]


def test_exception_task_hears_all_lower_tasks_and_assassin_stops(
        make_system: MakeSystem) -> None:
    s = make_system(memory_map([], {"M1": 0.0, "M2": -5.0}))
    s.execute(f"install -m0o1 --code={M}:lower L1 M1")
    s.execute(f"install -m0o1 --role=exception --level=3 --code={M}:exception_task D3 M2")
    s.execute(f"install -m0o1 --code={M}:lower L2 M2")  # installed after D3: tapped too
    s.execute(f"install -m0 --role=assassin --level=4 --code={M}:assassin K")
    log: list[Any] = []
    s.invoke("D3", {"log": log})
    s.invoke("L1")
    s.invoke("L2")
    s.invoke("K", {"log": log})
    s.run_for(1.0)
    seen = [(src, v[2]) for src, v, _ in (e for e in log if len(e) == 3 and e[0] != "estop")]
    assert ("L1", 0) in seen and ("L2", 2) in seen
    assert all(e[2] == 99 for e in log if len(e) == 3 and e[0] in ("L1", "L2"))
    assert ("L1", 2) not in seen  # L1 was suspended by the assassin at 0.15 s
    assert ("estop", 2) in log
    assert s.devtab.get("M2").value == -5.0


def test_sysfile_map_round_trip(tmp_path: Path) -> None:
    with _fig65(tmp_path) as s:
        s.run_script(fig65.SCRIPT)
        doc = sysmap.read(tmp_path / "sysfile.map")
    assert [t["name"] for t in doc["tasks"]] == ["A1", "A2", "A3", "A4", "B1", "B2", "C1"]
    with System.from_map(tmp_path / "sysfile.map") as again:
        d2 = again.sysmgr.map_doc()
        assert [(t["name"], t["machine"], t["level"]) for t in d2["tasks"]] == \
            [(t["name"], t["machine"], t["level"]) for t in doc["tasks"]]
        assert {(lk["src"], lk["dst"], lk["priority"]) for lk in d2["links"]} == \
            {(lk["src"], lk["dst"], lk["priority"]) for lk in doc["links"]}


def test_map_is_written_atomically_and_rejects_garbage(tmp_path: Path) -> None:
    sysmap.write(tmp_path / "m.map", {"machines": [], "tasks": [], "links": []})
    assert list(tmp_path.iterdir()) == [tmp_path / "m.map"]
    (tmp_path / "bad.map").write_text("{not json")
    with pytest.raises(Exception, match="line 1: not valid JSON"):
        sysmap.read(tmp_path / "bad.map")


@pytest.mark.parametrize(("line", "want"), [
    ("install -m0i2o1 A1 S1 S2 M1", cmdline.Install("A1", 0, ("S1", "S2"), ("M1",), "A1")),
    ("install -m0i2o3 B1 A1 A2 A1 A2 A3",
     cmdline.Install("B1", 0, ("A1", "A2"), ("A1", "A2", "A3"), "B1")),
    ("install -m2i1 A3 ./testfile", cmdline.Install("A3", 2, ("./testfile",), (), "A3")),
    ("install --machine 1 --inputs=1 --outputs 1 A2 S3 M2",
     cmdline.Install("A2", 1, ("S3",), ("M2",), "A2")),
    ("install -m0 -i1 -o1 X=pkg.mod:fn S1 M1",
     cmdline.Install("X", 0, ("S1",), ("M1",), "pkg.mod:fn")),
    ("install -m1 sysfile", cmdline.Boot(1, "sysfile")),
    ("setpri -9 A4 C1", cmdline.SetPri(9, "A4", "C1")),
    ("setpri --priority 12 C1 B1", cmdline.SetPri(12, "C1", "B1")),
    ("invoke -20 C1 speed=0.5 mode=run", cmdline.Invoke("C1", {"speed": 0.5, "mode": "run"}, 20)),
    ("# a comment", None),
])
def test_command_syntax(line: str, want: Any) -> None:
    assert cmdline.parse(line) == want


@pytest.mark.parametrize(("line", "message"), [
    ("install A1 S1", "no machine given"),
    ("install -m0i2o1 A1 S1 M1", "-i2 -o1 announce 3 file(s) after the task, 2 given"),
    ("install -m0x A1", "bad option '-m0x'"),
    ("install -m0 --frobnicate=1 A1", "unknown option --frobnicate"),
    ("setpri A4 C1", "no priority given"),
    ("setpri -9 A4", "expected srctsk dsttsk"),
    ("invoke", "no task given"),
    ("invoke C1 speed", "expected key=value"),
    ("launch A1", "unknown command 'launch'"),
])
def test_command_syntax_errors(line: str, message: str) -> None:
    with pytest.raises(CommandSyntaxError) as info:
        cmdline.parse(line)
    assert message in str(info.value)
