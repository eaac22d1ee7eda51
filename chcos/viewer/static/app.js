// chcos view: live hierarchy page. Plain JS, no build step. Data: server-sent events from
// /api/stream (one JSON snapshot per message); commands: POST /api/command {"line": "..."}.
"use strict";

const ALERTS = new Set(["abnormal", "estop", "suspend", "preempt", "device-failed",
                        "device-stale", "assassin"]);
const MAX_EVENTS = 300;
let lastSvg = "";
let linkOptions = "";
let taskOptions = "";

function $(id) { return document.getElementById(id); }

function cell(tr, text, cls) {
  const td = document.createElement("td");
  td.textContent = text;
  if (cls) td.className = cls;
  tr.appendChild(td);
}

function fmt(v) {
  if (v === null || v === undefined) return "–";
  if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toPrecision(4);
  return String(v);
}

function fillTable(id, rows, build) {
  const body = $(id).tBodies[0];
  const frag = document.createDocumentFragment();
  for (const r of rows) {
    const tr = document.createElement("tr");
    build(tr, r);
    frag.appendChild(tr);
  }
  body.replaceChildren(frag);
}

function setOptions(select, values, labels, memoKey) {
  const sig = values.join("|");
  if (select.dataset.sig === sig) return;
  const keep = select.value;
  select.replaceChildren(...values.map((v, i) => {
    const o = document.createElement("option");
    o.value = v; o.textContent = labels[i];
    return o;
  }));
  if (values.includes(keep)) select.value = keep;
  select.dataset.sig = sig;
}

function addEvents(events) {
  const list = $("events");
  for (const e of events) {
    const li = document.createElement("li");
    li.value = e.seq;
    li.dataset.kind = e.kind;
    if (ALERTS.has(e.kind)) li.className = "alert";
    const t = document.createElement("span");
    t.textContent = e.time.toFixed(2) + " ";
    const k = document.createElement("span");
    k.className = "kind"; k.textContent = e.kind;
    const d = document.createElement("span");
    d.className = "detail"; d.textContent = " " + e.detail;
    li.append(t, k, d);
    list.prepend(li);
  }
  while (list.children.length > MAX_EVENTS) list.lastChild.remove();
}

function update(snap) {
  const map = snap.map;
  $("clock").textContent = snap.time.toFixed(2);
  $("snap-error").textContent = snap.error || "";
  if (snap.svg !== lastSvg) {
    $("graph").innerHTML = snap.svg;
    lastSvg = snap.svg;
  }
  const frozen = new Set(map.frozen || []);
  fillTable("tasks", map.tasks, (tr, t) => {
    if (t.abnormal || frozen.has(t.name) || snap.marks[t.name]) tr.className = "alert";
    tr.dataset.name = t.name;
    cell(tr, t.name); cell(tr, t.level, "num"); cell(tr, t.machine, "num");
    cell(tr, frozen.has(t.name) ? "FROZEN (" + t.status + ")" : t.status);
    cell(tr, t.owner || "–"); cell(tr, t.priority, "num"); cell(tr, t.steps, "num");
    cell(tr, t.abnormal, "num"); cell(tr, t.last_error || "");
  });
  const links = map.links.filter((l) => !l.implicit);
  fillTable("links", links, (tr, l) => {
    tr.dataset.link = l.src + "/" + l.dst;
    if (l.status !== "OK") tr.className = "alert";
    cell(tr, l.src + "/" + l.dst); cell(tr, l.type); cell(tr, l.priority, "num");
    cell(tr, (l.rate || 0).toFixed(1), "num"); cell(tr, l.sent, "num");
    cell(tr, l.overwritten, "num"); cell(tr, l.status);
  });
  fillTable("devices", map.devices || [], (tr, d) => {
    tr.dataset.name = d.name;
    if (d.status === "stale" || d.status === "failed") tr.className = "alert";
    cell(tr, d.name); cell(tr, d.direction); cell(tr, d.machine, "num");
    cell(tr, fmt(d.value) + " " + (d.units || "") +
             (d.pending !== null && d.pending !== undefined ? " (pending " + fmt(d.pending) + ")"
              : ""), "num");
    const age = snap.ages[d.name];
    cell(tr, age === null || age === undefined ? "–" : age.toFixed(2), "num");
    cell(tr, d.status + (d.since !== null && d.since !== undefined && d.reason
                         ? " since t=" + Number(d.since).toFixed(3) : "") +
             (d.reason ? ": " + d.reason : "") +
             (d.write_errors ? " [write errors " + d.write_errors + ": " +
              (d.last_write_error || "") + "]" : ""));
  });
  setOptions($("setpri-link"), links.map((l) => l.src + " " + l.dst),
             links.map((l) => l.src + "/" + l.dst + " (" + l.type + ")"));
  const names = map.tasks.map((t) => t.name);
  setOptions($("invoke-task"), names, names);
  addEvents(snap.events || []);
  $("seq").textContent = snap.seq;
  $("seq").dataset.seq = snap.seq;
}

async function command(line) {
  const out = $("cmd-result");
  out.className = ""; out.textContent = "› " + line;
  try {
    const resp = await fetch("/api/command", {
      method: "POST", headers: {"Content-Type": "application/json"},
      body: JSON.stringify({line: line}),
    });
    const res = await resp.json();
    out.className = res.ok ? "ok" : "error";
    out.textContent = res.ok ? res.answer : "error: " + res.error;
  } catch (err) {
    out.className = "error"; out.textContent = "error: " + err;
  }
}

$("setpri-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  const link = $("setpri-link").value;
  command("setpri -" + $("setpri-prio").value.trim() + " " + link);
});

$("invoke-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  const prio = $("invoke-prio").value.trim();
  const args = $("invoke-args").value.trim();
  command("invoke " + (prio ? "-" + prio + " " : "") + $("invoke-task").value +
          (args ? " " + args : ""));
});

$("graph").addEventListener("click", (ev) => {
  const link = ev.target.closest("g.link");
  if (link && !link.classList.contains("implicit")) {
    $("setpri-link").value = link.dataset.link.replace("/", " ");
    return;
  }
  const node = ev.target.closest("g.node.task");
  if (node) $("invoke-task").value = node.dataset.name;
});

function connect() {
  const es = new EventSource("/api/stream");
  es.onopen = () => { $("conn").textContent = "live"; $("conn").className = "conn up"; };
  es.onmessage = (msg) => update(JSON.parse(msg.data));
  es.onerror = () => { $("conn").textContent = "disconnected"; $("conn").className = "conn down"; };
}
connect();
