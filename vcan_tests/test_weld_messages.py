"""The welding tasks' typed messages: a console command (a dict) is converted at the boundary into
the receiver's message class, and a wrong message is refused with an error naming the task and
the message, in a running cell as well; sensory messages and completions are typed too, and the
system map shows a typed value kept in a world model as its fields."""

from __future__ import annotations

from pathlib import Path

import pytest

from chcos.apps.weld.cell import open_cell
from chcos.apps.weld.tasks import A4, B1, B4, C1, D3
from chcos.apps.weld.tasks.common import sighted
from chcos.apps.weld.tasks.messages import (
    Alarm,
    HoldMotion,
    Job,
    Monitor,
    MoveTo,
    Step,
    StopMotion,
    Unstick,
    WatchTip,
    WeldOff,
    WeldOn,
    expect,
    from_host,
    record,
)
from chcos.apps.weld.tasks.results import Memorized, Reached
from chcos.apps.weld.tasks.sensed import GapImage, SensorFailed, TipPose, WeldState
from chcos.errors import MessageError
from chcos.system import sysmap


def test_console_dicts_become_the_receivers_messages() -> None:
    assert A4.motion_command({"p": [1.0, 2.0, 3.0], "speed": 5.0}) == \
        MoveTo(p=[1.0, 2.0, 3.0], speed=5.0)
    assert A4.motion_command({"op": "stop"}) == StopMotion()
    assert A4.motion_command({}) == Monitor() and A4.motion_command(None) == Monitor()
    assert B4.step_command({"d": [1, 0, 0], "yaw": 0.5}) == Step(d=[1, 0, 0], yaw=0.5)
    assert B4.step_command({"op": "hold"}) == HoldMotion()
    assert B1.weld_command({"op": "on", "volts": 20.0}) == WeldOn(volts=20.0)
    assert B1.weld_command(None) == WeldOff()
    assert from_host("E2", {"inspect_only": True}, {"job": Job}, "job", "a Job") == \
        Job(inspect_only=True)
    typed = Step(d=(0.0, 1.0, 0.0), dist=2.0)
    assert B4.step_command(typed) is typed  # a typed message passes as it is


@pytest.mark.parametrize(("convert", "message", "words"), [
    (A4.motion_command, Unstick(), ["A4: expected a MoveTo", "Unstick(lift=None)"]),
    (A4.motion_command, {"op": "fly"}, ["A4: unknown op 'fly'", "move, hold, stop, monitor"]),
    (A4.motion_command, {"op": "move"}, ["A4: move:", "'p'"]),
    (B4.step_command, {"d": [1, 0, 0], "sped": 5}, ["B4: step: unknown key(s) sped",
                                                    "expected d, dist, speed, yaw"]),
    (lambda m: from_host("E2", m, {"job": Job}, "job", "a Job"), {"inspect": True},
     ["E2: job: unknown key(s) inspect", "inspect_only"]),
    (B1.weld_command, "on", ["B1: expected a WeldOn or WeldOff, got 'on'"]),
    (B1.weld_command, HoldMotion(), ["B1: expected a WeldOn or WeldOff", "HoldMotion()"]),
])
def test_a_wrong_message_is_refused_naming_the_task_and_the_message(
        convert: object, message: object, words: list[str]) -> None:
    assert callable(convert)
    with pytest.raises(MessageError) as err:
        convert(message)
    for word in words:
        assert word in str(err.value)


def test_the_alarm_keeps_its_record_form() -> None:
    alarm = Alarm("intruder", "light curtain broken", 1.5)
    assert alarm.record() == {"alarm": "intruder", "detail": "light curtain broken", "t": 1.5}


def test_in_a_running_cell_console_commands_work_and_wrong_ones_are_refused(
        tmp_path: Path) -> None:
    with open_cell(workdir=tmp_path) as cell:
        s = cell.system
        s.run_for(0.2)
        s.execute("invoke B1 op=off")                 # typed at the console: converted
        s.run_for(0.5)
        b1 = s.tsktab.get("B1")
        assert b1.completions >= 1 and b1.abnormal == 0
        assert b1.world is not None and b1.world.snapshot()["command"]["weld"] == "off"
        s.execute("invoke B1 op=of")                  # a typo: refused, naming B1
        s.execute("invoke C1 op=unstick lift=5 speed=3")
        s.run_for(0.5)
        assert b1.abnormal == 1
        assert "B1: unknown op 'of'" in b1.last_error and "on, off" in b1.last_error
        c1 = s.tsktab.get("C1")
        assert c1.abnormal == 1 and "C1: unstick: unknown key(s) speed" in c1.last_error
    assert C1.TIP_COMMANDS["watch"] is WatchTip


def test_sensory_messages_are_matched_by_class() -> None:
    image = GapImage(range=12.0, pattern="start", centre=0.5, width=2.0, marker=0.2, start=True,
                     end=False, t=1.0)
    assert sighted(image, "start") and not sighted(image, "end")
    assert not sighted(SensorFailed("linear", "stale", 1.0), "start")
    assert not sighted({"start": True}, "start")  # a bare dict is no sighting any more
    # D3 hears every lower task: it judges the kinds that can mean danger, nothing else
    assert D3.classify("A4", TipPose((1.0, 2.0, 3.0), 0.0, False, 1.0), 400, 2600) is None
    assert D3.classify("B1", WeldState("on"), 400, 2600) is None
    assert D3.classify("A7", SensorFailed("linear", "stale", 2.0), 400, 2600) == (
        "sensor failure", "linear (reported by A7): stale")


def test_a_completion_is_read_as_its_class_or_refused() -> None:
    reached = Reached((1.0, 2.0, 3.0))
    assert expect("B3", reached, Reached) is reached
    assert record(reached) == {"at": (1.0, 2.0, 3.0), "op": "move"}
    with pytest.raises(MessageError) as err:
        expect("E2", {"at": [1, 2, 3]}, Reached)
    assert "E2: expected a Reached" in str(err.value) and "'at'" in str(err.value)


def test_a_typed_value_in_a_world_model_reaches_the_system_map_as_its_fields(
        tmp_path: Path) -> None:
    with open_cell(workdir=tmp_path) as cell:
        s = cell.system
        s.run_for(0.2)
        s.execute("invoke A6")                        # memorize the position under "last"
        s.run_for(0.5)
        a6 = s.tsktab.get("A6")
        assert a6.completions >= 1 and a6.abnormal == 0
        assert a6.world is not None
        last = a6.world.answer("position", "last")
        assert isinstance(last, Memorized) and last.tag == "last" and not last.stopped
        s.execute("map")                              # writes sysfile.map
    doc = sysmap.read(tmp_path / "sysfile.map")
    task = next(t for t in doc["tasks"] if t["name"] == "A6")
    shown = task["world"]["sensory"]["positions"]["last"]
    assert shown["tag"] == "last" and shown["pos"] == pytest.approx(list(last.pos))
    assert shown["thetas"] == pytest.approx(list(last.thetas)) and shown["stopped"] is False
