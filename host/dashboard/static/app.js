// upright dashboard page: Server-Sent Events in, uPlot out, commands as POSTs.
//
// Every telemetry row arrives with the time the server read it off the link (epoch ms);
// the plots are redrawn at most once per animation frame, and the frame-to-screen latency of
// the newest row drawn is taken at the *next* animation frame (the drawn frame has then been
// handed to the screen): a conservative figure.  The page pings the server every 250 ms with
// its screen-update times and latencies; the server keeps the board's heartbeat fed only
// while pages ping (see host/dashboard/hub.py).  window.dash exposes the state to tests.
//
// Every POST carries this run's token (the server wrote it into the page's <meta
// name="upright-token">): the server takes commands only from the page it served.
//
// The force plot shows the force applied to the cart: the telemetry's force while the board
// is balancing (state from the heartbeat), 0 otherwise -- the driver is off then, whatever
// force value the last telemetry frame still carries.
"use strict";

const WINDOW_S = 10;
const KEEP = 20000;
const TOKEN = (document.querySelector('meta[name="upright-token"]') || {}).content || "";
const dash = window.dash = {
  id: null, columns: [], received: new Map(), nrows: 0, heartbeat: null, hello: null,
  latency: [], updates: [], stats: null, feeding: false, notes: [], balancing: null, drawn: null,
};
const $ = (id) => document.getElementById(id);
let C = {};            // column name -> index
const buf = { n: [], t: [], phi: [], x: [], ref: [], force: [], duty: [] };
dash.drawn = buf;

function appliedForce(r) {
  // the force on the cart: 0 unless the board is balancing (the driver is off otherwise)
  return r[C.state] === dash.balancing ? r[C.force] : 0;
}
let dirty = false, raf = 0, newestRx = null;
let plots = [];
let pendingLat = [], pendingUpd = [];

function plotHeight() {
  // three plots fill the window below the header (each with its title and legend)
  return Math.max(140, Math.floor((window.innerHeight - 60) / 3) - 75);
}

function mkPlot(el, title, series, scales) {
  const w = Math.max(300, el.clientWidth - 10);
  const opts = {
    title, width: w, height: plotHeight(),
    scales: Object.assign({ x: { time: false } }, scales || {}),
    axes: [{ label: "t (s)" }].concat(series.axes),
    series: [{ label: "t" }].concat(series.lines),
    legend: { live: true },
    cursor: { drag: { x: false, y: false } },
  };
  return new uPlot(opts, [[]].concat(series.lines.map(() => [])), el);
}

function setupPlots() {
  plots = [
    { keys: ["phi"], u: mkPlot($("p-tilt"), "tilt", {
        lines: [{ label: "phi (rad)", stroke: "#c0392b", width: 1.5 }],
        axes: [{ label: "rad" }] }) },
    { keys: ["x", "ref"], u: mkPlot($("p-cart"), "cart position and reference", {
        lines: [{ label: "x (m)", stroke: "#1f6fb2", width: 1.5 },
                { label: "ref (m)", stroke: "#888", width: 1.5, dash: [6, 4] }],
        axes: [{ label: "m" }] }) },
    { keys: ["force", "duty"], u: mkPlot($("p-force"), "force and duty", {
        lines: [{ label: "applied force (N)", stroke: "#1f8f4e", width: 1.5, scale: "N" },
                { label: "duty", stroke: "#8e44ad", width: 1, scale: "duty" }],
        axes: [{ label: "N", scale: "N" }, { label: "duty", scale: "duty", side: 1, grid: { show: false } }] },
      { N: { auto: true }, duty: { auto: true } }) },
  ];
  window.addEventListener("resize", () => {
    for (const p of plots) p.u.setSize({ width: Math.max(300, p.u.root.parentElement.clientWidth - 10), height: plotHeight() });
  });
}

function onRow(d) {
  const r = d.r;
  const n = r[C.n];
  if (!dash.received.has(n)) dash.nrows++;
  dash.received.set(n, r);
  if (dash.received.size > KEEP) dash.received.delete(dash.received.keys().next().value);
  buf.n.push(n);
  buf.t.push(r[C.t]);
  for (const k of ["phi", "x", "ref", "duty"]) buf[k].push(r[C[k]]);
  buf.force.push(appliedForce(r));
  const tmin = r[C.t] - WINDOW_S;
  let cut = 0;
  while (cut < buf.t.length && buf.t[cut] < tmin) cut++;
  if (cut) for (const k in buf) buf[k].splice(0, cut);
  if (d.rx != null) newestRx = d.rx;
  dirty = true;
  if (!raf) raf = requestAnimationFrame(draw);
}

function draw() {
  raf = 0;
  if (!dirty) return;
  dirty = false;
  for (const p of plots) p.u.setData([buf.t].concat(p.keys.map((k) => buf[k])));
  const rx = newestRx;
  newestRx = null;
  // the frame with this draw is on screen by the next animation frame
  requestAnimationFrame(() => {
    const now = performance.timeOrigin + performance.now();
    pendingUpd.push(now);
    if (rx != null) { const l = now - rx; pendingLat.push(l); dash.latency.push(l); if (dash.latency.length > 5000) dash.latency.shift(); }
    dash.updates.push(now);
    if (dash.updates.length > 5000) dash.updates.shift();
  });
}

function showHeartbeat(hb) {
  dash.heartbeat = hb;
  const el = $("state");
  el.textContent = hb.state_name || "no heartbeat";
  el.className = "state s-" + (hb.state == null ? "none" : hb.state);
  el.dataset.state = hb.state == null ? "" : String(hb.state);
  for (const f of document.querySelectorAll(".fault")) {
    f.classList.toggle("on", ((hb.faults || 0) & Number(f.dataset.bit)) !== 0);
  }
  $("hbinfo").textContent = hb.uptime_ms != null ? `boot ${hb.boot} · up ${(hb.uptime_ms / 1000).toFixed(1)} s · faults ${hb.faults}` : "–";
}

function showGains(g) {
  $("gcrc").textContent = g.crc != null ? "0x" + g.crc.toString(16).padStart(4, "0")
    : g.crc_low8 != null ? "0x??" + g.crc_low8.toString(16).padStart(2, "0") : "?";
  $("glabel").textContent = g.label || "";
}

function note(n) {
  dash.notes.push(n.text);
  const d = document.createElement("div");
  d.textContent = `${n.t.toFixed(1)} s  ${n.text}`;
  d.title = n.text;
  $("notes").prepend(d);
  while ($("notes").childElementCount > 6) $("notes").lastElementChild.remove();
}

function message(text, err) {
  const m = $("msg");
  m.textContent = text || "";
  m.className = "card small" + (err ? " err" : "");
}

async function post(path, body, raw) {
  const headers = { "X-Upright-Page": dash.id || "page", "X-Upright-Token": TOKEN };
  if (!raw) headers["Content-Type"] = "application/json";
  const res = await fetch(path, { method: "POST", headers, body: raw ? body : JSON.stringify(body || {}) });
  let data = {};
  try { data = await res.json(); } catch (e) { /* empty */ }
  if (!res.ok) throw new Error(data.error || res.statusText);
  return data;
}

function action(id, fn) {
  $(id).addEventListener("click", async () => {
    try { const r = await fn(); message(r || ""); }
    catch (e) { message(e.message, true); }
  });
}

function wire() {
  action("arm", async () => { await post("/api/arm"); return "armed"; });
  action("disarm", async () => { await post("/api/disarm"); return "disarmed"; });
  action("clear", async () => { await post("/api/clear"); return "faults cleared"; });
  action("upright", async () => { await post("/api/upright"); return "pendulum upright"; });
  action("step", async () => { const x = Number($("refx").value); await post("/api/reference", { x }); return `reference ${x} m`; });
  action("zero", async () => { await post("/api/reference", { x: 0 }); return "reference 0 m"; });
  action("sqstart", async () => {
    await post("/api/square", { amplitude: Number($("sqamp").value), period: Number($("sqper").value), low: 0 });
    return "square wave on";
  });
  action("sqstop", async () => { await post("/api/square", { stop: true }); return "square wave off"; });
  action("gupload", async () => {
    const r = await post("/api/gains?design=" + encodeURIComponent($("gdesign").value));
    showGains(r); return "uploaded " + r.label;
  });
  action("gfileup", async () => {
    const f = $("gfile").files[0];
    if (!f) throw new Error("choose a file first (upright export --out gains.py, or --blob)");
    const r = await post("/api/gains?file=" + encodeURIComponent(f.name), await f.arrayBuffer(), true);
    showGains(r); return "uploaded " + r.label;
  });
  action("recstart", async () => { const r = await post("/api/record/start"); return "recording to " + r.path; });
  action("recstop", async () => { const r = await post("/api/record/stop"); showRecord(r); return `recorded ${r.rows} rows`; });
}

function showRecord(r) {
  $("recinfo").textContent = r.path ? `${r.recording ? "recording" : "recorded"} ${r.rows} rows (${r.lost} lost) · ${r.path}` : "not recording";
}

async function ping() {
  if (!dash.id) return;
  const lat = pendingLat, upd = pendingUpd;
  pendingLat = []; pendingUpd = [];
  try {
    const res = await fetch("/api/ping", {
      method: "POST", headers: { "X-Upright-Page": dash.id, "X-Upright-Token": TOKEN, "Content-Type": "application/json" },
      body: JSON.stringify({ latency_ms: lat, updates: upd }),
    });
    const d = await res.json();
    if (d.stats) {
      dash.stats = d.stats;
      dash.feeding = d.feeding;
      if (d.record) showRecord(d.record);
      const s = d.stats, f = (v, n) => (v == null ? "–" : v.toFixed(n));
      const L = s.page_latency_ms || {};
      $("rate").textContent = `${f(s.telemetry_hz, 0)} rows/s · ${f(s.page_updates_hz, 0)} updates/s · latency p50 ${f(L.p50, 0)} ms, p95 ${f(L.p95, 0)} ms`;
      const fe = $("feeding");
      fe.textContent = d.feeding ? "heartbeat on" : "heartbeat off";
      fe.className = "pill " + (d.feeding ? "on" : "off");
    }
  } catch (e) { /* the server is gone: the event stream says so */ }
}

function connect() {
  const es = new EventSource("/events");
  es.addEventListener("hello", (e) => {
    const h = JSON.parse(e.data);
    dash.hello = h;
    dash.id = h.id;
    dash.columns = h.columns;
    C = {};
    h.columns.forEach((c, i) => { C[c] = i; });
    const bal = Object.keys(h.states).find((k) => h.states[k] === "balancing");
    dash.balancing = bal == null ? null : Number(bal);
    const info = h.info || {};
    $("conn").textContent = `${info.mode || ""} ${info.port || ""}`.trim() + ` · page ${h.id}`;
    $("upright").hidden = !h.virtual;
    const fl = $("faults");
    fl.innerHTML = "";
    for (const [bit, name, doc] of h.faults) {
      const s = document.createElement("span");
      s.className = "fault"; s.dataset.bit = bit; s.textContent = name; s.title = `${bit}: ${doc}`;
      fl.appendChild(s);
    }
    showHeartbeat(h.heartbeat);
    showGains(h.gains);
    showRecord(h.record);
    for (const n of h.notes || []) note(n);
  });
  es.addEventListener("t", (e) => onRow(JSON.parse(e.data)));
  es.addEventListener("hb", (e) => showHeartbeat(JSON.parse(e.data)));
  es.addEventListener("gains", (e) => showGains(JSON.parse(e.data)));
  es.addEventListener("note", (e) => {
    const n = JSON.parse(e.data);
    note(n);
    if (/record/.test(n.text)) fetch("/api/status").then((r) => r.json()).then((s) => showRecord(s.record)).catch(() => {});
  });
  es.onerror = () => { $("conn").textContent = "disconnected: reconnecting…"; dash.id = null; };
}

setupPlots();
wire();
connect();
setInterval(ping, 250);
