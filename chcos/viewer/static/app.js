// chcos view: live hierarchy page. Plain JS, no build step. Data: server-sent events from
// /api/stream (a first snapshot, then JSON merge patches); commands (after logging in):
// POST /api/command {"line": "..."} with the session's X-CHCOS-Token header.
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

let state = null;
let session = {user: null, token: null, commands: []};

// JSON merge patch (RFC 7386): null deletes a key, objects merge, anything else replaces.
function mergePatch(target, patch) {
  if (patch === null || typeof patch !== "object" || Array.isArray(patch)) return patch;
  if (target === null || typeof target !== "object" || Array.isArray(target)) target = {};
  for (const [k, v] of Object.entries(patch)) {
    if (v === null) delete target[k];
    else target[k] = mergePatch(target[k], v);
  }
  return target;
}

// Fit the drawing to the pane, but never below 60 % of its natural size (text stays legible;
// the pane scrolls instead), nor above it (a small system is not blown up).
function fitGraph() {
  const svg = $("graph").querySelector("svg");
  if (!svg) return;
  const natural = Number(svg.getAttribute("width"));
  const pane = $("graph-pane").clientWidth - 2;
  svg.style.width = Math.max(Math.min(natural, pane), natural * 0.6) + "px";
}
window.addEventListener("resize", fitGraph);

function nn(v) { return v === undefined ? null : v; }

function render(snap, events) {
  $("clock").textContent = snap.time.toFixed(2);
  $("snap-error").textContent = snap.error || "";
  const collected = snap.errors || [];  // what the system collected (System.check raises it)
  $("collected-errors").textContent = collected.length
    ? collected.length + " collected error(s), last: " + collected[collected.length - 1] : "";
  $("collected-errors").title = collected.join("\n");
  if (snap.svg !== undefined && snap.svg !== lastSvg) {
    $("graph").innerHTML = snap.svg;
    lastSvg = snap.svg;
    fitGraph();
  }
  const marks = snap.marks || {};
  const tasks = Object.entries(snap.tasks || {});
  fillTable("tasks", tasks, (tr, [name, t]) => {
    if (t.abnormal || t.frozen || marks[name]) tr.className = "alert";
    tr.dataset.name = name;
    cell(tr, name); cell(tr, t.level, "num"); cell(tr, t.machine, "num");
    cell(tr, t.frozen ? "FROZEN (" + t.status + ")" : t.status);
    cell(tr, nn(t.owner) || "–"); cell(tr, t.priority, "num"); cell(tr, t.steps, "num");
    cell(tr, t.abnormal, "num"); cell(tr, nn(t.last_error) || "");
  });
  const links = Object.values(snap.links || {}).filter((l) => !l.implicit);
  fillTable("links", links, (tr, l) => {
    tr.dataset.link = l.src + "/" + l.dst;
    if (l.status !== "OK") tr.className = "alert";
    cell(tr, l.src + "/" + l.dst); cell(tr, l.type); cell(tr, l.priority, "num");
    cell(tr, (l.rate || 0).toFixed(1), "num"); cell(tr, l.sent, "num");
    cell(tr, l.overwritten, "num"); cell(tr, l.status);
  });
  fillTable("devices", Object.entries(snap.devices || {}), (tr, [name, d]) => {
    tr.dataset.name = name;
    if (d.status === "stale" || d.status === "failed") tr.className = "alert";
    cell(tr, name); cell(tr, d.direction); cell(tr, d.machine, "num");
    cell(tr, fmt(nn(d.value)) + " " + (d.units || "") +
             (nn(d.pending) !== null ? " (pending " + fmt(d.pending) + ")" : ""), "num");
    const age = nn(d.age);
    cell(tr, age === null ? "–" : age.toFixed(2), "num");
    cell(tr, d.status + (nn(d.since) !== null && d.reason
                         ? " since t=" + Number(d.since).toFixed(3) : "") +
             (d.reason ? ": " + d.reason : "") +
             (d.write_errors ? " [write errors " + d.write_errors + ": " +
              (d.last_write_error || "") + "]" : ""));
    const spark = document.createElement("td");
    spark.className = "spark";
    spark.innerHTML = sparkline(history[name] || []);
    tr.appendChild(spark);
  });
  setOptions($("setpri-link"), links.map((l) => l.src + " " + l.dst),
             links.map((l) => l.src + "/" + l.dst + " (" + l.type + ")"));
  const names = tasks.map(([name]) => name);
  setOptions($("invoke-task"), names, names);
  addEvents(events || []);
  $("seq").textContent = snap.seq;
  $("seq").dataset.seq = snap.seq;
}

// each device's recent values (GET /api/history every 2 s), drawn as a sparkline per device
let history = {};

function sparkline(points) {
  if (points.length < 2) return "";
  const w = 120, h = 18;
  const t0 = points[0][0], t1 = points[points.length - 1][0];
  let lo = Infinity, hi = -Infinity;
  for (const [, v] of points) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  const span = hi - lo || 1, dt = t1 - t0 || 1;
  const xy = points.map(([t, v]) => ((t - t0) / dt * w).toFixed(1) + "," +
                                    (h - 1 - (v - lo) / span * (h - 2)).toFixed(1));
  return '<svg width="' + w + '" height="' + h + '" viewBox="0 0 ' + w + " " + h +
         '"><title>' + lo.toPrecision(4) + " .. " + hi.toPrecision(4) + " over the last " +
         Math.round(dt) + ' s</title><polyline fill="none" stroke="#1565c0" points="' +
         xy.join(" ") + '"/></svg>';
}

async function loadHistory() {
  try {
    const resp = await fetch("/api/history");
    if (resp.ok) history = (await resp.json()).devices || {};
  } catch (e) { /* the stream shows the connection state */ }
}

function update(msg) {
  if (msg.type === "snapshot") state = msg.state;
  else if (state !== null) state = mergePatch(state, msg.patch);
  if (state !== null) render(state, msg.events);
}

function showSession(s) {
  session = {user: s.user || null, token: s.token || null, commands: s.commands || []};
  $("who").textContent = session.user ? session.user + " (" + s.role + ")"
                                       : (s.read_only ? "read-only" : "not logged in");
  $("login-form").hidden = !!session.user || !!s.read_only;
  $("logout-go").hidden = !session.user;
  $("setpri-form").hidden = !session.commands.includes("setpri");
  $("invoke-form").hidden = !session.commands.includes("invoke");
}

async function loadSession() {
  try {
    const resp = await fetch("/api/session", {credentials: "same-origin"});
    showSession(await resp.json());
  } catch (err) {
    showSession({user: null, read_only: true});
  }
}

async function command(line) {
  const out = $("cmd-result");
  out.className = ""; out.textContent = "› " + line;
  try {
    const resp = await fetch("/api/command", {
      method: "POST", credentials: "same-origin",
      headers: {"Content-Type": "application/json", "X-CHCOS-Token": session.token || ""},
      body: JSON.stringify({line: line}),
    });
    const res = await resp.json();
    out.className = res.ok ? "ok" : "error";
    out.textContent = res.ok ? res.answer : "error: " + res.error;
  } catch (err) {
    out.className = "error"; out.textContent = "error: " + err;
  }
}

$("login-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const out = $("cmd-result");
  const resp = await fetch("/api/login", {
    method: "POST", credentials: "same-origin", headers: {"Content-Type": "application/json"},
    body: JSON.stringify({user: $("login-user").value, password: $("login-password").value}),
  });
  const res = await resp.json();
  $("login-password").value = "";
  if (res.ok) { showSession(res); out.className = "ok"; out.textContent = "logged in"; }
  else { out.className = "error"; out.textContent = "error: " + res.error; }
});

$("logout-go").addEventListener("click", async () => {
  await fetch("/api/logout", {method: "POST", credentials: "same-origin",
                              headers: {"Content-Type": "application/json"}, body: "{}"});
  loadSession();
});

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
loadSession();
connect();
loadHistory();
setInterval(loadHistory, 2000);
