"""The live view attached to a system on three satellite processes through the host's link
(``chcos view --system``): the merged map with device ages and frozen tasks, an operator's
setpri reaching every satellite, and the event log made from successive maps."""

from __future__ import annotations

import io
import shutil
import threading
from pathlib import Path
from typing import Any

from chcos.apps import fig65
from chcos.cli.view import view_main
from chcos.satellites import sysfile
from chcos.viewer.server import Viewer
from vcan_tests.support_sat import Cluster, link, task
from vcan_tests.support_view import FIG65_TASKS, ROLES, get_json, login, post_json, viewer_users


def test_view_attaches_to_three_satellites(tmp_path: Path) -> None:
    shutil.copy(fig65.HERE / "testfile", tmp_path / "testfile")
    root = Path(__file__).resolve().parent.parent
    c = Cluster(tmp_path)
    (tmp_path / "system.toml").write_text(
        (tmp_path / "system.toml").read_text().replace(
            'devmaps = ["devices.toml"]',
            f'devmaps = ["{root}/chcos/apps/fig65/fig65.toml"]\ntask_path = ["{fig65.HERE}"]'))
    c.sf = sysfile.load(tmp_path / "system.toml")
    users = tmp_path / "users.toml"
    users.write_text("".join(
        f'[users.{n}]\nrole = "{ROLES[n]}"\npassword_hash = "{u.password_hash}"\n'
        for n, u in viewer_users().users.items()))
    seen: dict[str, Any] = {}
    stop = threading.Event()

    def on_ready(v: Viewer) -> None:
        try:
            snap = get_json(v.url + "api/snapshot?svg=0&since=0")
            seen["tasks"] = {t["name"]: t["machine"] for t in snap["map"]["tasks"]}
            seen["kinds"] = [e["kind"] for e in snap["events"]]
            seen["ages"] = snap["ages"]
            seen["frozen"] = snap["map"]["frozen"]
            alice = login(v.url, "alice")
            seen["setpri"] = post_json(v.url + "api/command", {"line": "setpri -13 C1 B1"},
                                       alice)
            seen["suspend"] = post_json(v.url + "api/command", {"line": "suspend A1"},
                                        login(v.url, "sam"))
            snap = get_json(v.url + "api/snapshot?svg=0&since=0")
            seen["events"] = [(e["kind"], e["detail"]) for e in snap["events"]]
            seen["svg"] = get_json(v.url + "api/snapshot")["svg"]
        finally:
            stop.set()

    try:
        for m in (0, 1, 2):
            c.start(m)
        c.host.wait_for([0, 1, 2])
        for line in fig65.SCRIPT.read_text().splitlines():
            c.host.execute(line)
        c.host.execute("invoke C1")
        c.wait_until(lambda d: task(d, "B1")["owner"] == "C1")
        c.host.execute("suspend A2")
        c.wait_until(lambda d: task(d, "A2")["frozen"])
        out = io.StringIO()
        assert view_main(["--system", str(tmp_path / "system.toml"), "--users", str(users)],
                         stop=stop, on_ready=on_ready, out=out) == 0, out.getvalue()
        assert "satellites of" in out.getvalue()
        assert seen["tasks"] == {"A1": 0, "A2": 1, "A3": 2, "A4": 2, "B1": 0, "B2": 1, "C1": 2}
        assert set(seen["tasks"]) == set(FIG65_TASKS)
        assert seen["kinds"][0] == "attach"
        # the satellites' device ages and frozen flags reach the view: S1..S3 are waveform
        # generators, read continuously on machines 0 and 1
        assert set(seen["ages"]) == {"S1", "S2", "S3", "M1", "M2"}
        for name in ("S1", "S2", "S3"):
            age = seen["ages"][name]
            assert age is not None and 0.0 <= age < 30.0, (name, age)
        assert seen["frozen"] == ["A2"]
        assert seen["setpri"] == (200, {"ok": True, "answer": "C1/B1 priority 13"})
        status, ans = seen["suspend"]
        assert status == 403 and "only setpri and invoke" in ans["error"]
        assert ("setpri", "C1/B1 9 -> 13") in seen["events"]
        assert 'data-name="C1"' in seen["svg"]
        # every satellite has the new priority
        for m in (0, 1, 2):
            assert link(c.host.map_doc(m), "C1", "B1")["priority"] == 13
    finally:
        c.close()
