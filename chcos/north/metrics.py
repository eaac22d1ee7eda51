"""metrics - a Prometheus endpoint for a running system (prometheus-client).

:class:`SystemCollector` is a custom collector: every figure is read from the tables (Devtab,
Tsktab, Msgtab) when Prometheus scrapes, on the scrape thread, so the control loops pay nothing
for counters they already keep. The only thing measured on the kernel thread is what the tables
do not hold: :class:`StepTimes` (an instrument, added only when metrics are on) counts each
task step's duration and its scheduling latency (ready to running) into fixed histogram buckets
(two ``perf_counter`` calls and a bisect per step; no prometheus object is touched there).

Exported (``chcos_`` prefix; labels in brackets):

=========================================== ====================================================
``device_value``, ``device_age_seconds``    last value (numeric only), seconds since it [device]
``device_healthy``, ``device_status``       1/0; 1 for the current status [device, status]
``device_readings_total`` … ``_rejected``   readings, overwrites, dropped, commands, rejected
``bus_errors_total``, ``bus_devices``       errors by kind [bus, kind]; devices per bus [bus]
``task_executions_total``                   steps [task]; also activations, completions,
                                            ``task_abnormal_total``
``task_priority``, ``task_level``           current priority and level [task]
``task_step_seconds``                       histogram of step durations [task]
``task_schedule_latency_seconds``           histogram: made ready → first step [task]
``link_sent_total`` … ``_overwritten_total`` per link [link, type]; ``link_priority``
``node_state``                              1 for the node's current lifecycle state, 0 for the
                                            others [bus, node, state] (CANopen: WAITING_BOOT …
                                            OPERATIONAL, PREOP_HELD, FAILED)
``node_ready``                              1 if the node is in the state the map requires
``node_heartbeat_lost``                     1 while the node's heartbeat is lost [bus, node]
``node_boots_total``, ``node_nmt_starts``   boot-up messages seen, NMT starts sent [bus, node]
``node_heartbeat_losses_total``             heartbeat losses declared [bus, node]
``node_emcys_total``                        EMCY messages received [bus, node]
``node_restarts_total``                     restarts of the recovery policy since the node's
                                            last boot [bus, node]
``node_error_register``                     0x1001 as last read [bus, node]
``sync_cycles_total`` … ``_late_writes``    SYNC cycles, complete cycles, missing TPDOs, late
                                            SYNCs, RPDO answers after SYNC n+1 [bus];
                                            ``sync_acyclic_total`` type-0 TPDOs received,
                                            ``sync_given_up_total`` cycles given up
``sync_period_seconds``, ``sync_jitter``    the period; jitter [bus, quantile 0.5/0.99/max]
=========================================== ====================================================

The endpoint (:func:`serve`, aiohttp on its own loop thread) binds loopback by default; another
address needs a TLS certificate and key, as every north-side service here, *and* a bearer token
(``--metrics-token FILE``: the file holds the token; a scraper sends ``Authorization: Bearer
TOKEN``, Prometheus' ``authorization: {credentials_file: ...}``); a request without it is
answered 401 and sees nothing. A token given on loopback is required there too. Connections are
bounded as every north-side server's (:mod:`chcos.north.guard`: at most
:data:`MAX_CONNECTIONS`, request timeouts, refusals counted and logged once per period).
"""

from __future__ import annotations

import asyncio
import bisect
import hmac
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aiohttp import web
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
)
from prometheus_client.registry import Collector

from chcos.comm.config import is_loopback
from chcos.kernel.instrument import Instrument
from chcos.north import NorthError
from chcos.north.health import bus_stats, device_health
from chcos.serving.guard import (
    MAX_BODY,
    REQUEST_TIMEOUT,
    ConnectionGate,
    bound_port,
    connection_cap,
    http_limits,
    serve_http,
    throttle_library_logs,
)
from chcos.serving.loopthread import LoopThread

if TYPE_CHECKING:
    from chcos.system.embedded import System
    from chcos.tables.tasks import TaskEntry

#: Histogram bucket upper bounds, seconds (the last, +Inf, is implicit).
BUCKETS = (1e-5, 2.5e-5, 5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2, 0.1)
STATUSES = ("OK", "suspended", "failed", "stale")
#: Concurrent scrapes the endpoint takes (less if the descriptor limit is low).
MAX_CONNECTIONS = 32


class _Hist:
    __slots__ = ("counts", "total")

    def __init__(self) -> None:
        self.counts = [0] * (len(BUCKETS) + 1)
        self.total = 0.0

    def add(self, v: float) -> None:
        self.counts[bisect.bisect_left(BUCKETS, v)] += 1
        self.total += v

    def buckets(self) -> list[tuple[str, float]]:
        out, acc = [], 0
        for bound, n in zip((*map(str, BUCKETS), "+Inf"), list(self.counts), strict=True):
            acc += n
            out.append((bound, float(acc)))
        return out


class StepTimes(Instrument):
    """Per-task histograms of step durations and of the latency from being made ready to the
    next step, in wall-clock seconds (``perf_counter``)."""

    def __init__(self) -> None:
        self.steps: dict[str, _Hist] = {}
        self.latency: dict[str, _Hist] = {}
        self._ready: dict[int, float] = {}
        self._t0 = 0.0

    def task_scheduled(self, task: TaskEntry) -> None:
        """Remember when ``task`` became ready (first time since its last step)."""
        self._ready.setdefault(task.tid, time.perf_counter())

    def before_step(self, task: TaskEntry) -> None:
        """Count the scheduling latency; start timing the step."""
        now = time.perf_counter()
        ready = self._ready.pop(task.tid, None)
        if ready is not None:
            h = self.latency.get(task.name)
            if h is None:
                h = self.latency[task.name] = _Hist()
            h.add(now - ready)
        self._t0 = now

    def after_step(self, task: TaskEntry) -> None:
        """Count the step's duration."""
        h = self.steps.get(task.name)
        if h is None:
            h = self.steps[task.name] = _Hist()
        h.add(time.perf_counter() - self._t0)


def _num(v: Any) -> float | None:
    if isinstance(v, bool):
        return float(v)
    return float(v) if isinstance(v, int | float) else None


class SystemCollector(Collector):
    """Collects every ``chcos_`` metric of ``system`` at scrape time (see the module doc)."""

    def __init__(self, system: System, steps: StepTimes | None = None) -> None:
        self.system = system
        self.step_times = steps

    def collect(self) -> Iterator[Any]:
        """Yield the metric families (read from the tables; torn reads accepted)."""
        s = self.system
        now = s.kernel.clock.now()
        devs = list(s.devtab)
        value = GaugeMetricFamily("chcos_device_value", "last value in engineering units",
                                  labels=["device", "units"])
        age = GaugeMetricFamily("chcos_device_age_seconds", "seconds since the last value",
                                labels=["device"])
        healthy = GaugeMetricFamily("chcos_device_healthy", "1 if the device is OK",
                                    labels=["device"])
        status = GaugeMetricFamily("chcos_device_status", "1 for the device's current status",
                                   labels=["device", "status"])
        counters = {k: CounterMetricFamily(f"chcos_device_{k}", f"device {k} so far",
                                           labels=["device"])
                    for k in ("readings", "overwrites", "dropped", "commands", "rejected")}
        for d in devs:
            v = _num(d.value)
            if v is not None:
                value.add_metric([d.name, d.spec.units], v)
            if d.updated_at is not None:
                age.add_metric([d.name], max(0.0, now - d.updated_at))
            h = device_health(d)
            healthy.add_metric([d.name], 1.0 if h.healthy else 0.0)
            for st in STATUSES:
                status.add_metric([d.name, st], 1.0 if h.status == st else 0.0)
            for k, fam in counters.items():
                fam.add_metric([d.name], float(getattr(d, k)))
        yield from (value, age, healthy, status, *counters.values())

        errors = CounterMetricFamily("chcos_bus_errors", "bus errors by kind",
                                     labels=["bus", "kind"])
        bcounts = CounterMetricFamily("chcos_bus", "bus counters (frames, frames-sent, "
                                      "requests, reconnects, lost)", labels=["bus", "counter"])
        ndev = GaugeMetricFamily("chcos_bus_devices", "devices on the bus", labels=["bus"])
        for b in bus_stats(s.devtab):
            ndev.add_metric([b.name], float(b.devices))
            for kind, n in sorted(b.errors.items()):
                errors.add_metric([b.name, kind], float(n))
            for key, n in sorted(b.counts.items()):
                bcounts.add_metric([b.name, key], float(n))
        yield from (errors, bcounts, ndev)
        yield from node_families(s.devtab.bus_status())

        tasks = list(s.tsktab)
        fams = {k: CounterMetricFamily(f"chcos_task_{n}", d, labels=["task"]) for k, n, d in (
            ("steps", "executions", "task steps executed"),
            ("activations", "activations", "activations (commands started)"),
            ("completions", "completions", "normal completions"),
            ("abnormal", "abnormal", "abnormal completions"))}
        prio = GaugeMetricFamily("chcos_task_priority", "current priority", labels=["task"])
        level = GaugeMetricFamily("chcos_task_level", "level in the hierarchy", labels=["task"])
        for t in tasks:
            for k, fam in fams.items():
                fam.add_metric([t.name], float(getattr(t, k)))
            prio.add_metric([t.name], float(t.prio))
            level.add_metric([t.name], float(t.level))
        yield from (*fams.values(), prio, level)
        timer = self.step_times
        if timer is not None:
            for attr, name, doc in (("steps", "chcos_task_step_seconds", "step durations"),
                                    ("latency", "chcos_task_schedule_latency_seconds",
                                     "from being made ready to the next step")):
                fam_h = HistogramMetricFamily(name, doc, labels=["task"])
                for task, hist in sorted(dict(getattr(timer, attr)).items()):
                    fam_h.add_metric([task], hist.buckets(), hist.total)
                yield fam_h

        lfams = {k: CounterMetricFamily(f"chcos_link_{k}", f"messages {k}",
                                        labels=["link", "type"])
                 for k in ("sent", "delivered", "overwritten")}
        lprio = GaugeMetricFamily("chcos_link_priority", "link priority", labels=["link", "type"])
        for lk in list(s.msgtab):
            labels = [f"{lk.src}/{lk.dst}", lk.type.value]
            for k, fam in lfams.items():
                fam.add_metric(labels, float(getattr(lk, k)))
            lprio.add_metric(labels, float(lk.priority))
        yield from (*lfams.values(), lprio)


def node_families(status: dict[str, dict[str, Any]]) -> list[Any]:
    """The ``chcos_node_*`` and ``chcos_sync_*`` families from the drivers' status documents
    (:meth:`chcos.devices.devtab.Devtab.bus_status`)."""
    from chcos.devices.status import ErrorState
    from drivers.canopen_lifecycle import NodeLifecycle

    states = [s.name for s in NodeLifecycle]
    state = GaugeMetricFamily("chcos_node_state", "1 for the node's current lifecycle state",
                              labels=["bus", "node", "state"])
    ready = GaugeMetricFamily("chcos_node_ready", "1 if the node is in the state the map "
                              "requires", labels=["bus", "node"])
    boots = CounterMetricFamily("chcos_node_boots", "boot-up messages seen",
                                labels=["bus", "node"])
    starts = CounterMetricFamily("chcos_node_nmt_starts", "NMT start commands sent",
                                 labels=["bus", "node"])
    losses = CounterMetricFamily("chcos_node_heartbeat_losses", "heartbeat losses declared",
                                 labels=["bus", "node"])
    emcys = CounterMetricFamily("chcos_node_emcys", "EMCY messages received",
                                labels=["bus", "node"])
    restarts = CounterMetricFamily("chcos_node_restarts", "restarts of the node's recovery "
                                   "policy since its last boot", labels=["bus", "node"])
    lost = GaugeMetricFamily("chcos_node_heartbeat_lost", "1 while the node's heartbeat is "
                             "lost", labels=["bus", "node"])
    ereg = GaugeMetricFamily("chcos_node_error_register", "error register 0x1001 as last read",
                             labels=["bus", "node"])
    sync = {k: CounterMetricFamily(f"chcos_sync_{k}", d, labels=["bus"]) for k, d in (
        ("cycles", "SYNC cycles"), ("complete", "cycles whose synchronous TPDOs all arrived"),
        ("missing", "synchronous TPDOs missing at the end of their cycle"),
        ("late", "SYNCs sent late"),
        ("late_writes", "RPDO answers to cycle n sent after SYNC n+1"),
        ("acyclic", "acyclic synchronous TPDOs (type 0) received"),
        ("given_up", "SYNC cycles the producer gave up (a stall, a controller making no "
                     "progress)"))}
    period = GaugeMetricFamily("chcos_sync_period_seconds", "SYNC period", labels=["bus"])
    jitter = GaugeMetricFamily("chcos_sync_jitter_seconds", "SYNC period jitter "
                               "|interval - period|", labels=["bus", "quantile"])
    ctl_state = GaugeMetricFamily("chcos_can_controller_state", "1 for the CAN controller's "
                                  "state (error-active, error-warning, error-passive, bus-off)",
                                  labels=["bus", "state"])
    ctl_errors = GaugeMetricFamily("chcos_can_controller_errors", "the CAN controller's error "
                                   "counters as its last error frame gave them",
                                   labels=["bus", "direction"])
    ctl_events = CounterMetricFamily("chcos_can_controller_events", "CAN error frames, "
                                     "error-passive and bus-off episodes, restarts",
                                     labels=["bus", "event"])
    for bus, doc in status.items():
        ctl = doc.get("bus_state")
        if ctl:
            for es in ErrorState:
                ctl_state.add_metric([bus, es.value], 1.0 if ctl["state"] == es else 0.0)
            if ctl.get("tx_errors") is not None and ctl.get("rx_errors") is not None:
                ctl_errors.add_metric([bus, "tx"], float(ctl["tx_errors"]))
                ctl_errors.add_metric([bus, "rx"], float(ctl["rx_errors"]))
            for event in ("error_frames", "error_passive", "bus_offs", "restarts"):
                ctl_events.add_metric([bus, event], float(ctl.get(event, 0)))
        for n in doc.get("nodes", ()):
            labels = [bus, str(n["node"])]
            for name in states:
                state.add_metric([*labels, name], 1.0 if n["state"] == name else 0.0)
            ready.add_metric(labels, 1.0 if n["ready"] else 0.0)
            boots.add_metric(labels, float(n["boots"]))
            lost.add_metric(labels, 1.0 if n.get("heartbeat_lost") else 0.0)
            starts.add_metric(labels, float(n["nmt_starts"]))
            losses.add_metric(labels, float(n.get("heartbeat_losses", 0)))
            emcys.add_metric(labels, float(n.get("emcys", 0)))
            restarts.add_metric(labels, float(n.get("restarts", 0)))
            if n.get("error_register") is not None:
                ereg.add_metric(labels, float(n["error_register"]))
        st = doc.get("sync")
        if st:
            for k, fam in sync.items():
                fam.add_metric([bus], float(st.get(k, 0)))
            period.add_metric([bus], float(st["period"]))
            for q, key in (("0.5", "jitter_p50"), ("0.99", "jitter_p99"), ("max", "jitter_max")):
                jitter.add_metric([bus, q], float(st[key]))
    return [state, ready, lost, boots, starts, losses, emcys, restarts, ereg, *sync.values(),
            period, jitter, ctl_state, ctl_errors, ctl_events]


def read_token(path: str) -> str:
    """The bearer token in file ``path`` (its first line). Raises NorthError naming the file
    if it cannot be read or holds less than 16 characters."""
    try:
        token = Path(path).read_text(encoding="utf-8").strip().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise NorthError(f"--metrics-token {path}: cannot read: {exc}") from exc
    if not token or len(token[0].strip()) < 16:
        raise NorthError(f"--metrics-token {path}: expected a token of at least 16 characters "
                         "on its first line (e.g. `openssl rand -hex 32 > FILE`)")
    return token[0].strip()


class MetricsServer:
    """The running endpoint: ``url``, :meth:`stop`; ``gate`` bounds its connections and
    counts refusals; ``unauthorized`` counts requests refused for a missing or wrong token."""

    def __init__(self, system: System, registry: CollectorRegistry, steps: StepTimes,
                 host: str, port: int, ssl_context: Any, token: str | None) -> None:
        self.system = system
        self.registry = registry
        self.steps = steps
        self.host, self.port = host, port
        self.ssl_context = ssl_context
        self.token = token
        self.unauthorized = 0
        self.gate = ConnectionGate("metrics", connection_cap(MAX_CONNECTIONS))
        self._service = LoopThread("chcos-metrics")
        self.url = ""

    def start(self) -> MetricsServer:
        """Serve; returns self. Raises NorthError if the address cannot be bound."""
        try:
            self._service.start(self._serve)
        except Exception as exc:
            raise NorthError(f"metrics: cannot serve on {self.host}:{self.port}: "
                             f"{exc}") from exc
        self.system.kernel.add_instrument(self.steps)
        scheme = "https" if self.ssl_context is not None else "http"
        h = f"[{self.host}]" if ":" in self.host else self.host
        self.url = f"{scheme}://{h}:{self.port}/metrics"
        return self

    async def _metrics(self, request: web.Request) -> web.Response:
        if self.token is not None:
            given = request.headers.get("Authorization", "")
            if not hmac.compare_digest(given.encode(), f"Bearer {self.token}".encode()):
                self.unauthorized += 1
                self.gate.throttle.note("metrics: request without the right bearer token "
                                        "refused", f"from {request.remote}")
                return web.Response(status=401, text="a bearer token is required\n",
                                    headers={"WWW-Authenticate": 'Bearer realm="chcos"'})
        loop = asyncio.get_running_loop()
        body = await loop.run_in_executor(None, generate_latest, self.registry)
        return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST})

    async def _serve(self, service: LoopThread) -> None:
        throttle_library_logs()
        app = web.Application(middlewares=[http_limits(self.gate)], client_max_size=MAX_BODY)
        app.router.add_get("/metrics", self._metrics)
        app.router.add_get("/", self._metrics)
        runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0,
                               keepalive_timeout=REQUEST_TIMEOUT)
        await runner.setup()
        try:
            listener = await serve_http(runner, self.gate, self.host, self.port,
                                        self.ssl_context)
            self.port = bound_port(listener)
            service.ready()
            await service.stopped()
            listener.close()
        finally:
            await runner.cleanup()

    def stop(self) -> None:
        """Stop serving and remove the step timer from the kernel."""
        self._service.stop(timeout=10)
        self.system.kernel.remove_instrument(self.steps)


def serve(system: System, host: str = "127.0.0.1", port: int = 0, *,
          certfile: str | None = None, keyfile: str | None = None,
          token_file: str | None = None) -> MetricsServer:
    """Serve ``/metrics`` of ``system`` on ``host:port`` (0: a free port). Raises NorthError if
    the address is not loopback and no TLS certificate and key, or no bearer token file, are
    given, if the token file is unusable, or if it cannot bind."""
    if not is_loopback(host) and not (certfile and keyfile):
        raise NorthError(f"metrics on {host}: a non-loopback address needs TLS: give "
                         "--north-tls-cert and --north-tls-key (PEM certificate and key)")
    if not is_loopback(host) and not token_file:
        raise NorthError(f"metrics on {host}: a non-loopback address needs a bearer token: "
                         "give --metrics-token FILE (scrapers send Authorization: Bearer ...)")
    token = read_token(token_file) if token_file else None
    ctx = None
    if certfile and keyfile:
        import ssl

        ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        try:
            ctx.load_cert_chain(certfile, keyfile)
        except (OSError, ssl.SSLError) as exc:
            raise NorthError(f"metrics: cannot load {certfile} / {keyfile}: {exc}") from exc
    steps = StepTimes()
    registry = CollectorRegistry(auto_describe=False)
    registry.register(SystemCollector(system, steps))
    return MetricsServer(system, registry, steps, host, port, ctx, token).start()


__all__ = ["MetricsServer", "StepTimes", "SystemCollector", "node_families", "read_token",
           "serve"]
