"""suite_sections - the sections of tools/bench_suite.py, each measuring one group of figures
beside its baseline in the same run and adding its rows to the suite's table.

A section is a function ``section(run: SuiteRun) -> None``: it measures (``run.reps`` batches of
every real-time figure, the batches of chcos and of its baseline interleaved), stores what it
measured under its own key of ``run.res`` (written to results.json) and appends rows
``(figure and what it includes, target, measured, met?)`` to ``run.rows``. Real-time figures are
printed as min / median / max over the batches; a target is judged on the median. Counts on
virtual time are exact and measured once. Errors: whatever the measured code raises (a
benchmark that cannot run stops the suite).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path
from typing import Any

from chcos.apps.bench import emergency, fig66, model64, saturated
from chcos.apps.bench.stats import summarize
from tools import bench_core, bench_fullpath
from tools.suite_common import (
    ROOT,
    THESIS_INTERRUPTS_PER_SATELLITE,
    SuiteRun,
    lat,
    med,
    one_core,
    p50s,
    p99s,
    spread,
    yes,
)

NBS_PERIOD = 0.028
NBS_80HZ = 1.0 / 80.0

def cycle_model(run: SuiteRun) -> None:
    """0. The thesis' section 6.4 cycle model, computed (chcos.apps.bench.model64)."""
    model_rows = model64.table()
    run.res["model64"] = {"rows": [vars(r) for r in model_rows],
                          "remote_cost_bounds": model64.remote_cost_bounds(),
                          "assumptions": list(model64.ASSUMPTIONS)}
    for mr in model_rows:
        tp, tt = model64.THESIS_TABLE[mr.satellites]
        run.rows.append((
            f"6.4 cycle model computed from the thesis' cycle counts, {mr.satellites} "
            "satellite(s): interrupts/s per CPU, total", f"thesis {tp}/CPU, {tt} total",
            f"{mr.per_cpu:,}/CPU, {mr.total:,} total ({mr.cycles_per_interrupt:,.1f} "
            f"cycles/interrupt; {mr.ratio_to_one:.2f}x)",
            yes((mr.per_cpu, mr.total) == (tp, tt))))


def executions(run: SuiteRun) -> None:
    """1. Task executions per second of the figure 6.6 system, CHC vs NBS, virtual time."""
    count_s = 20.0 if run.quick else 60.0   # a multiple of the load's 2.5 s hyper-period
    rates = fig66.expected_rates(fig66.TOPOLOGY, {s: Fraction(10) for s in fig66.INPUTS})
    chc = fig66.count_chcos(count_s, seed=run.seed)
    n28, x28 = fig66.count_nbs(count_s, NBS_PERIOD, seed=run.seed)
    n80, x80 = fig66.count_nbs(count_s, NBS_80HZ, seed=run.seed)
    c: dict[str, Any] = {"expected_per_task": {k: float(v) for k, v in rates.items()},
         "expected_total": float(sum(rates.values())), "chcos": chc.as_dict(),
         "nbs_28ms": {**n28.as_dict(), **x28}, "nbs_80hz": {**n80.as_dict(), **x80}}
    run.res["executions"] = c
    chc_rate, exp = c["chcos"]["per_second"], c["expected_total"]
    r28, r80 = c["nbs_28ms"]["per_second"], c["nbs_80hz"]["per_second"]
    run.rows += [
        ("fig 6.6 task executions/s, CHC (virtual time, counted exactly)",
         f"= load-implied {exp:g}/s (thesis est. 51)", f"{chc_rate:.2f}/s",
         yes(abs(chc_rate - exp) < 1e-9)),
        ("fig 6.7 FSM executions/s, NBS every 28 ms (same System, devices and load)",
         f"9 FSM / 28 ms = {9 / NBS_PERIOD:.1f}/s (thesis printed 3200)",
         f"{r28:.2f}/s, lost {c['nbs_28ms']['inputs_lost']}", yes(abs(r28 - 9 / NBS_PERIOD) < 0.5)),
        ("fig 6.7 FSM executions/s, NBS at 80 Hz", "thesis 720/s", f"{r80:.2f}/s",
         yes(abs(r80 - 720) < 0.5)),
        ("NBS/CHC executions ratio", "thesis 720/51 = 14.1x",
         f"28 ms: {r28 / chc_rate:.1f}x, 80 Hz: {r80 / chc_rate:.1f}x", "-"),
    ]


def reaction(run: SuiteRun) -> None:
    """2. Reaction latency sensor event -> actuator command: CHC and NBS on virtual time, CHC on
    real time beside a bare thread hand-off in the same batch."""
    vlat_s = 60.0 if run.quick else 300.0
    rt_s = 2.0 if run.quick else 6.0
    v_chc = fig66.latency_chcos_virtual(vlat_s, seed=run.seed)
    v28, v28_own = fig66.latency_nbs_virtual(vlat_s, NBS_PERIOD, seed=run.seed)
    v80, _ = fig66.latency_nbs_virtual(vlat_s, NBS_80HZ, seed=run.seed)
    chc_b, raw_b = [], []
    for r in range(run.reps):
        chc, raw = fig66.latency_chcos_real(rt_s, seed=run.seed + r)
        chc_b.append(chc)
        raw_b.append(raw)
    s_vchc, s_v28, s_v80 = summarize(v_chc), summarize(v28), summarize(v80)
    run.res["latency"] = {
        "chcos_virtual": s_vchc.as_dict(), "nbs_28ms_virtual": s_v28.as_dict(),
        "nbs_28ms_virtual_executor_own": summarize(v28_own).as_dict(),
        "nbs_80hz_virtual": s_v80.as_dict(),
        "real_batches": [{"chcos": summarize(a).as_dict(), "raw": summarize(b).as_dict()}
                         for a, b in zip(chc_b, raw_b, strict=True)],
        "jitter_s": 0.028, "virtual_seconds": vlat_s, "real_seconds_per_batch": rt_s}
    mid = sorted(range(run.reps), key=lambda i: summarize(chc_b[i]).p99)[run.reps // 2]
    run.plot += [("NBS every 28 ms (virtual time)", v28, ""),
                 ("NBS at 80 Hz (virtual time)", v80, "6,3"),
                 ("CHC on real time (processing, median batch)", chc_b[mid], ""),
                 ("bare Python thread hand-off (same batch)", raw_b[mid], "2,3"),
                 ("CHC on virtual time (reacts at event time)", v_chc, "")]
    n = run.reps
    run.rows += [
        ("reaction latency, CHC, virtual time (design)", "reacts at event time",
         lat(s_vchc), yes(s_vchc.max == 0)),
        ("reaction latency, NBS 28 ms, virtual time", "up to one cycle (28 ms)", lat(s_v28), "-"),
        ("reaction latency, NBS 80 Hz, virtual time", "up to one cycle (12.5 ms)", lat(s_v80),
         "-"),
        (f"reaction latency, CHC on real time: injected reading -> actuator command in Devtab "
         f"(interrupt queue, wake-up, tasks A1/A2); p50 and p99 in ms, {n} batches",
         "its processing (no target)",
         f"p50 {spread(p50s(chc_b), '{:.3f}')}; p99 {spread(p99s(chc_b), '{:.3f}')}", "-"),
        ("  bare Python thread hand-off (queue.SimpleQueue), same batches", "baseline",
         f"p50 {spread(p50s(raw_b), '{:.3f}')}; p99 {spread(p99s(raw_b), '{:.3f}')}", "-"),
        ("NBS 28 ms p99 / CHC real-time p99 (median batch)", "-",
         f"{s_v28.p99 * 1e3 / med(p99s(chc_b)):.0f}x", "-"),
    ]


def full_path(run: SuiteRun) -> None:
    """3. Full path frame -> task -> frame on one core beside the raw bus and the hand-written
    asyncio program; task-to-task messages beside the minimal heap kernel, asyncio and heapq."""
    loops = 5000 if run.quick else 40_000
    msgs = 50_000 if run.quick else 300_000
    pairs = 5 if run.quick else bench_fullpath.PAIRS
    raw, path, hand, to_raw, to_hand = [], [], [], [], []
    core_t: dict[str, list[float]] = {k: [] for k in (
        "read", "read_any", "minimal", "asyncio_queue", "asyncio_event", "heapq")}
    with one_core() as core:
        for r in range(run.reps):
            tag = f"{os.getpid()}-{r}"
            b = bench_fullpath.paired_batch(loops, 64, pairs, f"suite-{tag}")
            raw.append(b.rate("raw"))
            path.append(b.rate("chcos"))
            hand.append(b.rate("asyncio_cantools"))
            to_raw.append(b.ratio("chcos", "raw"))
            to_hand.append(b.ratio("chcos", "asyncio_cantools"))
        ops = bench_fullpath.instruction_profile(64, 500 if run.quick else 2000)
        per_min: list[float] = []
        for _ in range(run.reps):  # interleaved: each batch's ratio is taken within the batch
            med_ratio, per_c, per_m = bench_core.paired_ratio(msgs)
            per_min.append(med_ratio)
            core_t["read"].append(per_c)
            core_t["minimal"].append(per_m)
            dt, got = bench_core.run_chcos(msgs, False, True)
            if got != msgs:
                raise SystemExit(f"bench_core: delivered {got} of {msgs}")
            core_t["read_any"].append(dt / msgs)
            core_t["asyncio_queue"].append(bench_core.run_asyncio_queue(msgs)[0] / msgs)
            core_t["asyncio_event"].append(bench_core.run_asyncio_event(msgs)[0] / msgs)
            core_t["heapq"].append(bench_core.run_heapq(msgs) / msgs)
    t = core_t

    def ratio(a: str, b: str) -> list[float]:
        return [x / y for x, y in zip(t[a], t[b], strict=True)]

    q_speed, e_speed = ratio("asyncio_queue", "read"), ratio("asyncio_event", "read")
    run.res["fullpath"] = {"core": core, "loops": loops, "raw_frames_per_s": raw,
                           "loops_per_s": path, "handwritten_loops_per_s": hand,
                           "ratio_to_raw": to_raw, "ratio_to_handwritten": to_hand,
                           "instructions": ops}
    ops_tot = {k: sum(v.values()) for k, v in ops.items()}
    run.res["core"] = {"messages": msgs, "seconds_per_message": t,
                       "ratio_to_minimal": per_min, "asyncio_queue_speedup": q_speed,
                       "asyncio_event_speedup": e_speed}
    us = "{:.3f}"
    interrupts = 2 * med(path)
    run.rows += [
        ("full path frame -> task -> frame, one core (python-can virtual bus; chcos = reader "
         "thread, decode, kernel, driver task, write, send; loops/s; each batch "
         f"{pairs} alternating rounds of raw bus, chcos and program, its rates and ratios "
         "the rounds' medians)", ">= 20,000 loops/s",
         spread(path, "{:,.0f}"), yes(med(path) >= 20_000)),
        ("  raw python-can virtual send+recv, one thread, same batches (frames/s)",
         ">= 0.33 of raw (ceiling 0.5)", f"{spread(raw, '{:,.0f}')}; chcos/raw "
         f"{spread(to_raw)}", yes(med(to_raw) >= 0.33)),
        ("  asyncio + can.Notifier + cantools program, same peer and window (loops/s)",
         ">= 1.0x", f"{spread(hand, '{:,.0f}')}; chcos/program {spread(to_hand)}",
         yes(med(to_hand) >= 1.0)),
        ("  bytecode instructions, counted in every thread (peer included; C code counts as "
         "its call): raw bus per frame, chcos and the program per loop", "-",
         f"raw {ops_tot['raw']:,.0f}; chcos {ops_tot['chcos']:,.0f} (own code "
         f"{ops['chcos'].get('chcos', 0):,.0f}, python-can {ops['chcos'].get('python-can', 0):,.0f}"
         f"); program {ops_tot['asyncio_cantools']:,.0f}; by count chcos/raw "
         f"{ops_tot['raw'] / ops_tot['chcos']:.2f}, chcos/program "
         f"{ops_tot['asyncio_cantools'] / ops_tot['chcos']:.2f}", "-"),
        ("  vs thesis, 1 MC68000 satellite (sensor + actuator interrupts/s)",
         "1150 interrupts/s (estimate)", f"{interrupts:,.0f} (median)",
         f"{interrupts / THESIS_INTERRUPTS_PER_SATELLITE:.0f}x"),
        ("task-to-task message, one core (tools.bench_core: producer put + checkpoint, "
         "consumer read at a higher priority, newest-wins link; CPU µs per message)",
         ">= 300,000 msg/s", f"{spread([x * 1e6 for x in t['read']], us)} µs = "
         f"{spread([1 / x for x in t['read']], '{:,.0f}')} msg/s",
         yes(1 / med(t["read"]) >= 300_000)),
        (f"  minimal priority-heap kernel (coroutines + heapq + one-slot port), same batches "
         f"({bench_core.PAIRS} alternating pairs each, the median pair's ratio)",
         "chcos <= 1.5x", f"{spread([x * 1e6 for x in t['minimal']], us)} µs; chcos/minimal "
         f"{spread(per_min)}x", yes(med(per_min) <= 1.5)),
        ("  issue 40's guard (500,000 msg/s where chcos, hand-inlined, did 1,090,748 at 1.43x "
         "the minimal kernel): the same on any host, against the minimal kernel of these batches",
         f"chcos <= {bench_core.GUARD_VS_MINIMAL}x", f"chcos/minimal {spread(per_min)}x",
         yes(med(per_min) <= bench_core.GUARD_VS_MINIMAL)),
        ("  asyncio Queue / Event + sleep(0), same batches", "chcos >= 2x faster",
         f"Queue {spread(q_speed)}x, Event {spread(e_speed)}x slower than chcos",
         yes(med(q_speed) >= 2 and med(e_speed) >= 2)),
        ("  read_any instead of read; heapq push N + pop N per message", "-",
         f"read_any/read {spread(ratio('read_any', 'read'))}x; chcos/heapq "
         f"{spread(ratio('read', 'heapq'))}x", "-"),
    ]


def field_buses(run: SuiteRun) -> None:
    """3a. Modbus TCP and CANopen SDO through chcos beside the libraries alone
    (tools.bench_fieldbus, ``run.reps`` separate runs in fresh interpreters, each round
    interleaving the programs)."""
    runs = []
    with tempfile.TemporaryDirectory(prefix="chcos-suite-") as tmp:
        for r in range(run.reps):
            out = Path(tmp) / f"fieldbus-{r}.json"
            subprocess.run([sys.executable, "-m", "tools.bench_fieldbus", "--repeat",
                            "1" if run.quick else "3", "--json", str(out)],
                           check=False, cwd=ROOT, stdout=subprocess.DEVNULL)
            runs.append(json.loads(out.read_text(encoding="utf-8")))
    run.res["fieldbus"] = runs
    for si, sec in enumerate(runs[0]["sections"]):
        base = sec["rows"][0]
        run.rows.append((f"{sec['title']}: {base['label']}", "baseline",
                         spread([rr["sections"][si]["rows"][0]["rate"] for rr in runs],
                                "{:,.0f}") + " reads/s", "-"))
        for ri, row in enumerate(sec["rows"][1:], start=1):
            ratios = [rr["sections"][si]["rows"][ri]["ratio"] for rr in runs]
            rates = [rr["sections"][si]["rows"][ri]["rate"] for rr in runs]
            target = row.get("target")
            run.rows.append((f"  {row['label']} / baseline",
                             "-" if target is None else f">= {target}",
                             f"{spread(ratios)} (reads/s {spread(rates, '{:,.0f}')})",
                             "-" if target is None else yes(med(ratios) >= target)))


def saturated_bus(run: SuiteRun) -> None:
    """3b. A saturated CAN bus: 8,800 frames/s in, 1,000 answers/s out through tasks, one core."""
    B = saturated.run_saturated(run.saturated_s)
    bal = B.unaccounted()
    run.res["saturated"] = {k: v for k, v in vars(B).items() if k != "reaction"} | {
        "cpu_chcos": B.cpu_chcos, "cpu_total": B.cpu_total, "unaccounted": bal,
        "reaction_p50": B.percentile(0.5), "reaction_p99": B.percentile(0.99),
        "reaction_max": B.percentile(1.0)}
    rin, rout = B.sent_measured / B.seconds, B.answers_measured / B.seconds
    run.rows += [
        (f"saturated CAN bus, one core, {B.seconds:.0f} s (8 DBC messages, 8 driver tasks + 1 "
         f"level-2 task, sensor links queued {B.queue})", "8,800 in + 1,000 out frames/s",
         f"{rin:,.0f} in, {rout:,.0f} out frames/s", yes(rin >= 8700 and rout >= 990)),
        ("  frames lost without a count", "0",
         ", ".join(f"{k} {v}" for k, v in bal.items() if v) or
         f"0 (sent {B.sent:,} = received {B.received_by_driver:,}; answered "
         f"{B.answers_received:,} of {B.requests:,})", yes(not any(bal.values()))),
        ("  CPU of chcos (process minus the peer's threads)", "<= 50 % of a core",
         f"{B.cpu_chcos * 100:.1f} % (whole process {B.cpu_total * 100:.1f} %)",
         yes(B.cpu_chcos <= 0.5)),
        ("  peer alone: python-can send 8,800/s + receive, same run", "baseline",
         f"{(B.cpu_peer / B.seconds) * 100:.1f} % of a core",
         f"chcos/peer {(B.cpu_chcos * B.seconds) / max(B.cpu_peer, 1e-9):.1f}x"),
        ("  reaction, request frame in -> answer frame out", "p99 printed",
         f"p50 {B.percentile(0.5) * 1e3:.3f} / p99 {B.percentile(0.99) * 1e3:.3f} / max "
         f"{B.percentile(1.0) * 1e3:.3f} ms; machine load {B.load[0]:.2f} on {B.cpus} CPUs", "-"),
    ]


def emergency_reaction(run: SuiteRun) -> None:
    """4. Emergency reaction under 5,000 background frames/s through the real CAN driver: each
    batch one run with the process pinned to one CPU (as ``system.cpus`` pins a cell's
    ``chcos run``) and one not pinned, alternately."""
    trials = 50 if run.quick else 200
    cpu = max(os.sched_getaffinity(0))
    E: list[emergency.EmergencyResult] = []
    U: list[emergency.EmergencyResult] = []
    for r in range(run.reps):
        E.append(emergency.run_emergency(trials, 5000.0, seed=run.seed + r, cpus=[cpu]))
        U.append(emergency.run_emergency(trials, 5000.0, seed=run.seed + r))

    def batches(rs: list[emergency.EmergencyResult]) -> list[dict[str, Any]]:
        return [{"trials": e.trials, "failed": e.failed, "background_rate": e.background_rate,
                 "load": list(e.load), "cpus_pinned": list(e.cpus_pinned),
                 **{k: summarize(getattr(e, k)).as_dict() if getattr(e, k) else None
                    for k in ("from_send", "from_driver", "on_wire", "stamped", "raw_echo")}}
                for e in rs]

    run.res["emergency"] = {"trials_per_batch": trials, "background_frames_per_s": 5000.0,
                            "pinned_to_cpu": cpu, "batches": batches(E),
                            "batches_not_pinned": batches(U)}
    mid = sorted(E, key=lambda e: summarize(e.stamped).p99 if e.stamped else 1e9)[len(E) // 2]
    run.plot.append(("CHC emergency: intruder send -> last safe value (median batch)",
                     mid.from_send, "8,3"))
    failed = sum(e.failed for e in E + U)
    bg = min(e.background_rate for e in E + U)
    wire = p99s([e.stamped for e in E])
    loads = ", ".join(f"{e.load[0]:.2f}" for e in E)

    def ms(key: str, rs: list[emergency.EmergencyResult] = E) -> str:
        b = [getattr(e, key) for e in rs]
        return f"p50 {spread(p50s(b), '{:.3f}')}; p99 {spread(p99s(b), '{:.3f}')} ms"

    run.rows += [
        (f"emergency: peer's send() of the intruder frame -> last safe-value frame on the wire, "
         f"by the bus's time stamp of it (exception task, assassin, estop of 4 actuators; "
         f"{run.reps} batches of {trials}; the process - system, peer and echo - pinned to CPU "
         f"{cpu}, as system.cpus pins a cell's chcos run)", "p99 < 0.5 ms on a quiet machine",
         f"{ms('stamped')}; load {loads} on {E[0].cpus} CPUs",
         yes(med(wire) < 0.5 and failed == 0)),
        ("  the same until the peer's listener thread has the frame (its wake-up included)",
         "-", ms("on_wire"), "-"),
        ("  the same to the last safe value written in Devtab", "-", ms("from_send"), "-"),
        ("  from the driver's hand-off of the intruder value to the same", "-",
         ms("from_driver"), "-"),
        ("  bare Python echo thread on the same kind of bus, same batches", "baseline",
         ms("raw_echo"), "-"),
        ("  the same, the process not pinned (a run beside each of the above): last safe-value "
         "frame by its time stamp; the bare echo", "-",
         f"{ms('stamped', U)}; echo {ms('raw_echo', U)}", "-"),
        ("  background load, failed trials (both kinds of run)", "5,000 frames/s, 0",
         f"{bg:,.0f} frames/s, {failed} of {sum(e.trials for e in E + U)}",
         yes(bg >= 4900 and failed == 0)),
    ]


def canopen_sync(run: SuiteRun) -> None:
    """4a. The CANopen SYNC cycle on real SocketCAN beside a C producer (tools.bench_canopen_sync)
    inside the User-Mode-Linux guest (tools/uml/run-in-uml): missed SYNC cycles at 250 Hz and
    the p99 jitter against the C reference's, per rate; "not measured" where the guest cannot
    run (no UML kernel, no SocketCAN inside)."""
    seconds = 10 if run.quick else 60
    runner = ROOT / "tools" / "uml" / "run-in-uml"
    results: list[dict[str, Any]] = []
    why = ""
    if not Path(os.environ.get("CHCOS_UML_KERNEL", "/usr/bin/linux")).exists():
        why = "no SocketCAN guest (no User-Mode-Linux kernel: apt-get install user-mode-linux)"
    else:
        proc = subprocess.run(
            [str(runner), "--timeout", str(seconds * 6 + 300), "--", sys.executable, "-m",
             "tools.bench_canopen_sync", "--seconds", str(seconds), "--rates", "1000", "250"],
            check=False, cwd=ROOT, capture_output=True, text=True)
        results = [json.loads(line.split("RESULT ", 1)[1]) for line in proc.stdout.splitlines()
                   if line.strip().startswith("RESULT ")]
        if not results:
            why = (f"no SocketCAN guest (run-in-uml exit {proc.returncode}: "
                   f"{(proc.stderr.strip().splitlines() or ['no output'])[0]})")
    run.res["canopen_sync"] = {"seconds": seconds, "results": results, "not_measured": why}
    if not results:
        run.rows.append(("CANopen SYNC cycle on SocketCAN beside a C producer", "-",
                         f"not measured: {why}", "-"))
        return
    for r in results:
        ref, ours, rate = r["reference"], r["chcos"], r["rate_hz"]
        ref_missed = ref["expected"] - ref["on_wire"]
        run.rows.append((
            f"CANopen SYNC at {rate} Hz, {r['seconds']:g} s, UML guest (SocketCAN, pinned): "
            f"chcos (SYNC producer process) beside C (clock_nanosleep + raw "
            f"socket)", "0 missed cycles at 250 Hz; p99 jitter <= 2x C",
            f"missed cycles {r['missed_cycles']} of {ours['expected']:,} (C {ref_missed}); "
            f"jitter p50/p99/max {ours['p50_us'] / 1e3:.3f}/"
            f"{ours['p99_us'] / 1e3:.3f}/{ours['max_us'] / 1e3:.1f} ms (C "
            f"{ref['p50_us'] / 1e3:.3f}/{ref['p99_us'] / 1e3:.3f}/{ref['max_us'] / 1e3:.1f}), "
            f"p99 {r['p99_ratio']:.2f}x C; TPDOs missing {ours['missing']} (C's wire "
            f"{ref['wire_missing']}); late {ours['late']} (C {ref['late']}); CPU "
            f"{ours['cpu_pct']:.0f} % (C {ref['cpu_pct']:.0f} %)",
            yes(bool(r["met"])) if rate == 250 else yes(r["p99_ratio"] <= 2.0)))


def soak(run: SuiteRun) -> None:
    """5. Resident size over a soak at 10,000 frames/s."""
    S = emergency.run_soak(run.soak_s, 10_000.0)
    run.res["soak"] = {"seconds": S.seconds, "rate": S.rate, "achieved_rate": S.achieved_rate,
                       "rss_start_kb": S.rss_start_kb, "rss_end_kb": S.rss_end_kb,
                       "rss_max_kb": S.rss_max_kb, "growth_kb": S.growth_kb,
                       "samples_kb": S.samples_kb, "frames_sent": S.frames_sent,
                       "frames_received_by_driver": S.frames_received_by_driver,
                       "readings": S.readings}
    small = S.growth_kb < 5 * 1024
    run.rows.append((f"RSS growth, {S.seconds:.0f} s soak at 10,000 frames/s", "< 5 MB",
                     f"{S.growth_kb / 1024:+.2f} MB ({S.rss_start_kb / 1024:.1f} -> "
                     f"{S.rss_end_kb / 1024:.1f} MB, max {S.rss_max_kb / 1024:.1f}; "
                     f"{S.achieved_rate:,.0f} frames/s, {S.readings:,} of {S.frames_sent:,} read)",
                     "yes" if small and S.seconds >= 60 - 1e-6 else
                     ("yes (short soak)" if small else "NO")))


def satellites(run: SuiteRun) -> None:
    """6. Satellite scaling with 1, 2 and 3 CPU-bound satellite processes beside the model's
    ratios, ``run.reps`` times; cross-satellite latency beside the bare transport."""
    from tools.bench_satellites import latency, raw_latency, scaling_table

    seconds = 3.0 if run.quick else 5.0
    tables = [scaling_table(seconds) for _ in range(run.reps)]
    lats: list[dict[str, float]] = []
    raws: list[dict[str, float]] = []
    lats_free: list[dict[str, float]] = []
    raws_free: list[dict[str, float]] = []
    for _ in range(run.reps):   # side by side, batch by batch: the transport's own tail moves
        lats.append(latency(5000, seconds, pin=True))
        raws.append(raw_latency(5000, seconds, pin=True))
        lats_free.append(latency(5000, seconds))
        raws_free.append(raw_latency(5000, seconds))
    run.res["satellite_scaling"] = {"tables": tables, "latency_us": lats,
                                    "raw_latency_us": raws, "latency_us_not_pinned": lats_free,
                                    "raw_latency_us_not_pinned": raws_free}
    for i, n in enumerate((1, 2, 3)):
        rows = [t["rows"][i] for t in tables]
        ok = [r for r in rows if not r.get("error")]
        target = {1: "-", 2: ">= 1.8x of 1 (2 cores)", 3: "reported (bounded by the cores)"}[n]
        got = (f"{spread([r['total'] for r in ok], '{:,.0f}')}/s = "
               f"{spread([r['ratio'] for r in ok])}x of 1; CPU per process "
               f"{spread([c for r in ok for c in r['cpu']])} cores" if ok else "not measured")
        tops = [r for r in ok if r.get("ceiling") and not r["ceiling"].get("error")]
        if tops:
            got += (f"; the machine's ceiling (as many unlinked) "
                    f"{spread([r['ceiling_ratio'] for r in tops])}x, linked/unlinked "
                    f"{spread([r['total'] / r['ceiling']['total'] for r in tops])}")
        if n == 1 and any(r.get("runs") for r in ok):
            got += ("; each batch's baseline the mean of a run before and one after the "
                    "others (" + "; ".join(" and ".join(f"{v:,.0f}" for v in r["runs"])
                                            for r in ok if r.get("runs")) + ")")
        if len(ok) < len(rows):
            got += f"; {len(rows) - len(ok)} of {len(rows)} not set up ({rows[0].get('error')})"
        model = rows[0]
        verdict = f"model {model['model_total']:,} = {model['model_ratio']:.2f}x"
        if n == 2:
            verdict += " - " + yes(bool(ok) and med([r["ratio"] for r in ok]) >= 1.8)
        run.rows.append((f"satellite scaling, {n} CPU-bound satellite process(es), two closed "
                         f"loops each: sensor reading -> driver task -> actuator -> its echo, "
                         f"the next reading; interrupts/s ({run.reps} runs)",
                         target, got, verdict))
    def ms(batches: list[dict[str, float]], key: str) -> str:
        return spread([b[key] / 1000 for b in batches], "{:.3f}")

    p99 = med([b["p99"] for b in lats])

    def vs(a: list[dict[str, float]], b: list[dict[str, float]]) -> str:
        return "chcos/bare p99 " + spread([x["p99"] / y["p99"] for x, y in zip(a, b, strict=True)],
                                          "{:.1f}") + "x"

    run.rows.append((f"cross-satellite latency at 5,000 msg/s (queued link, every message; "
                     f"{run.reps} batches; each satellite pinned to a CPU of its own, "
                     f"[[satellite]] cpus)", "p99 < 1 ms",
                     f"p50 {ms(lats, 'p50')}; p99 {ms(lats, 'p99')}; max {ms(lats, 'max')} ms",
                     yes(p99 < 1000)))
    run.rows.append(("  bare transport (Zenoh + one thread hand-off), same batches, pinned alike",
                     "baseline",
                     f"p50 {ms(raws, 'p50')}; p99 {ms(raws, 'p99')}; max {ms(raws, 'max')} ms",
                     vs(lats, raws)))
    run.rows.append(("  the same, not pinned (a run beside each of the above): chcos; the bare "
                     "transport", "-",
                     f"p50 {ms(lats_free, 'p50')}; p99 {ms(lats_free, 'p99')} ms; bare p50 "
                     f"{ms(raws_free, 'p50')}; p99 {ms(raws_free, 'p99')} ms",
                     vs(lats_free, raws_free)))
    seal = seal_cost(run)
    run.rows.append(("  sealing and encryption alone (tools.bench_link micro: AES-256-GCM seal, "
                     "open with the replay window; thread CPU time, best of 15 rounds), per "
                     "64 B / 1 KiB message", "-",
                     f"seal+open {seal['seal+open 64']:.1f} / {seal['seal+open 1024']:.1f} µs; "
                     f"a bare serialize {seal['serialize 64']:.1f} / "
                     f"{seal['serialize 1024']:.1f} µs",
                     f"x{seal['ratio 64']:.1f} / x{seal['ratio 1024']:.1f} a serialize"))


def seal_cost(run: SuiteRun) -> dict[str, float]:
    """What sealing and encrypting a link message costs by itself (``tools.bench_link.micro``,
    with a throw-away secret), recorded in ``run.res["seal_us"]``."""
    import contextlib
    import io

    from tools.bench_link import micro

    with tempfile.TemporaryDirectory(prefix="chcos-suite-") as tmp, \
            contextlib.redirect_stdout(io.StringIO()):
        out = micro(str(Path(tmp) / "secret"), 5 if run.quick else 15)
    run.res["seal_us"] = out
    return out


def growth(run: SuiteRun) -> None:
    """7. Setup growth at 10², 10³, 10⁴ in a fresh interpreter (this one's heap would slow its
    garbage collector)."""
    sizes = "100,1000,3000" if run.quick else "100,1000,10000"
    with tempfile.TemporaryDirectory(prefix="chcos-suite-") as tmp:
        out = Path(tmp) / "growth.json"
        subprocess.run([sys.executable, "-m", "tools.bench_growth", "--sizes", sizes, "--json",
                        str(out)], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
        G: dict[str, Any] = json.loads(out.read_text(encoding="utf-8"))
    run.res["growth"] = G
    for name, g in G.items():
        n_last, t_last = g["points"][-1]
        measured = g["target_n"] in [n for n, _ in g["points"]]
        run.rows.append((f"setup growth: {name}", f"{g['target_n']:,} in <= {g['target_s']:g} s, "
                         "linear", f"{n_last:,}: {t_last:.3f} s; exponent {g['slope']:.2f}"
                         + ("" if measured else f"; {g['target_n']:,} from the fit: "
                                                f"{g['at_target']:.3f} s"),
                         yes(g["met"] and g["slope"] < 1.3)))


def real_time_factor(run: SuiteRun) -> None:
    """8. The real-time factor of each shipped cell on virtual time, side by side with the
    plain loop that only moves the buses cell's frames (tools/bench_rtf.py, issue 47)."""
    from tools import bench_rtf

    seconds = 10.0 if run.quick else 30.0
    results = bench_rtf.run_all(seconds, run.reps)
    run.res["real_time_factor"] = {c: [vars(f) | {"rtf": f.rtf,
                                                   "cpu_per_virtual": f.cpu_per_virtual}
                                       for f in fs] for c, fs in results.items()}
    run.rows += bench_rtf.rows(results)


def test_suite(run: SuiteRun) -> None:
    """9. The test suite's own wall time on two workers (tools/run-tests' pytest), a benchmark
    line and not a limit (issue 47: 5 minutes on 2 cores at load ~1). Runs only when asked
    (``--only "test suite"``): it takes the suite's minutes."""
    t0 = time.perf_counter()
    res = subprocess.run([str(ROOT / ".venv" / "bin" / "pytest"), "-q", "-p",
                          "no:cacheprovider", "-n", "2"], cwd=ROOT,
                         capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    tail = (res.stdout.strip().splitlines() or [""])[-1]
    run.res["test_suite"] = {"wall_s": wall, "returncode": res.returncode, "last_line": tail}
    run.rows.append(("test suite wall time, pytest on two workers (tools/run-tests)",
                     "<= 300 s at load ~1 (a benchmark, not a limit)",
                     f"{wall:.0f} s ({tail})", yes(wall <= 300.0 and res.returncode == 0)))


#: the sections in the order they run, with their names for the progress lines
SECTIONS: list[tuple[str, Callable[[SuiteRun], None]]] = [
    ("6.4 cycle model", cycle_model), ("executions (virtual time)", executions),
    ("reaction latency", reaction), ("full path and kernel (one core)", full_path),
    ("field buses", field_buses), ("saturated bus", saturated_bus),
    ("emergency reaction", emergency_reaction), ("CANopen SYNC (UML guest)", canopen_sync),
    ("memory soak", soak),
    ("satellites", satellites), ("setup growth", growth),
    ("real-time factor", real_time_factor)]
#: sections run only when named in ``--only``
ON_REQUEST: list[tuple[str, Callable[[SuiteRun], None]]] = [("test suite", test_suite)]
