// The live page of tagdeflect: feed lines from /events (Server-Sent Events), the run's
// state from /api/status once a second, camera snapshots from /camera/NAME.jpg.
// No build step, no network beyond the daemon that serves this file.
"use strict";

const MAX_POINTS = 20000; // per series; beyond, every second point is dropped
const COLOURS = ["#ff8c00", "#00c8ff", "#7cb342", "#e040fb", "#ffd600", "#ff5252", "#40c4ff", "#b2ff59", "#ff6e40",
  "#ea80fc", "#64ffda", "#ffab40", "#82b1ff", "#f4ff81", "#ff80ab"];

const S = {
  t0: null,            // first line's t_ns
  t: [],               // seconds since t0
  load: [], net: [], stroke: [],
  tagIds: [],          // specimen tag ids in column order
  tags: new Map(),     // id -> downward displacement [mm] aligned with t
  selected: new Set(),
  up: [0, 0, 1],
  frameInterval: 0.2,
  lastLineAt: 0,
  lastLine: null,
  status: null,
  statusOk: false,
  mode: "live",
  dirty: false,
  charts: {},
  cams: new Map(),     // name -> card elements
};

const $ = (id) => document.getElementById(id);
const fmt = (v, d) => (v === null || v === undefined || Number.isNaN(v)) ? "–" : v.toFixed(d);

function axis(label) {
  return { label, stroke: "#c8ccd2", labelSize: 22, size: 64, grid: { stroke: "#2c323b" }, ticks: { stroke: "#2c323b" },
    font: "14px system-ui, sans-serif", labelFont: "bold 15px system-ui, sans-serif" };
}

function size(el) {
  const w = Math.max(300, el.clientWidth || el.parentElement.clientWidth - 24);
  return { width: w, height: el.classList.contains("tall") ? 340 : 260 };
}

function makeTimeChart(el, yLabel, series) {
  const opts = {
    ...size(el),
    scales: { x: { time: false } },
    axes: [axis("time [s]"), axis(yLabel)],
    series: [{ label: "t [s]", value: (u, v) => fmt(v, 1) }, ...series],
    legend: { live: true },
    cursor: { drag: { x: true, y: false } },
  };
  return new uPlot(opts, [[], ...series.map(() => [])], el);
}

function makeCurve(el) {
  const opts = {
    mode: 2,
    ...size(el),
    height: 340,
    scales: { x: { time: false }, y: {} },
    axes: [axis("net deflection [mm]"), axis("load [kN]")],
    series: [{}, { label: "load vs net deflection", stroke: "#ff8c00", width: 2, paths: uPlot.paths.linear(), points: { show: false },
      facets: [{ scale: "x", auto: true }, { scale: "y", auto: true }] }],
    legend: { show: false },
    cursor: { drag: { x: false, y: false }, points: { show: false } },
  };
  return new uPlot(opts, [null, [[], []]], el);
}

function initCharts() {
  S.charts.curve = makeCurve($("curve"));
  S.charts.defl = makeTimeChart($("defl"), "net deflection [mm]", [{ label: "net deflection [mm]", stroke: "#ff8c00", width: 2, value: (u, v) => fmt(v, 3) }]);
  S.charts.load = makeTimeChart($("load"), "load [kN]", [{ label: "load [kN]", stroke: "#00c8ff", width: 2, value: (u, v) => fmt(v, 2) }]);
  rebuildTagChart();
  window.addEventListener("resize", () => {
    for (const [k, c] of Object.entries(S.charts)) c.setSize(size($(k === "tags" ? "tags" : k)));
  });
}

function rebuildTagChart() {
  const el = $("tags");
  if (S.charts.tags) S.charts.tags.destroy();
  const ids = S.tagIds.filter((id) => S.selected.has(id));
  S.charts.tags = makeTimeChart(el, "displacement [mm]",
    ids.map((id) => ({ label: `tag ${id} [mm]`, stroke: COLOURS[S.tagIds.indexOf(id) % COLOURS.length], width: 2, value: (u, v) => fmt(v, 3) })));
  S.tagChartIds = ids;
  S.dirty = true;
}

function addTag(id, role) {
  if (S.tags.has(id)) return;
  S.tagIds.push(id);
  S.tags.set(id, new Array(S.t.length).fill(null));
  // Midspan and support tags are shown first; every tag can be picked.
  if (role || S.selected.size < 3) S.selected.add(id);
  const lab = document.createElement("label");
  const cb = document.createElement("input");
  cb.type = "checkbox";
  cb.checked = S.selected.has(id);
  cb.dataset.tag = id;
  cb.addEventListener("change", () => {
    if (cb.checked) S.selected.add(id); else S.selected.delete(id);
    rebuildTagChart();
  });
  lab.style.color = COLOURS[(S.tagIds.length - 1) % COLOURS.length];
  lab.append(cb, ` tag ${id}${role ? " (" + role + ")" : ""}`);
  $("tag-picks").append(lab);
}

function decimate() {
  const keep = (a) => a.filter((_, i) => i % 2 === 0);
  S.t = keep(S.t); S.load = keep(S.load); S.net = keep(S.net); S.stroke = keep(S.stroke);
  for (const [id, a] of S.tags) S.tags.set(id, keep(a));
}

function onLine(line) {
  if (S.t0 === null) S.t0 = line.t_ns;
  const [ux, uy, uz] = S.up;
  S.t.push((line.t_ns - S.t0) / 1e9);
  S.load.push(line.load_kN ?? null);
  S.net.push(line.net_deflection_mm ?? null);
  S.stroke.push(line.stroke_mm ?? null);
  const seen = new Map();
  for (const t of line.tags || []) seen.set(t.id, -(t.disp_mm[0] * ux + t.disp_mm[1] * uy + t.disp_mm[2] * uz));
  for (const id of seen.keys()) if (!S.tags.has(id)) { addTag(id, null); S.tags.get(id).pop(); rebuildTagChart(); }
  for (const [id, a] of S.tags) a.push(seen.has(id) ? seen.get(id) : null);
  if (S.t.length > MAX_POINTS) decimate();
  S.lastLine = line;
  S.lastLineAt = performance.now();
  S.dirty = true;
  onTestLine(line);
}

function redraw() {
  if (!S.dirty) return;
  S.dirty = false;
  const xs = [], ys = [];
  for (let i = 0; i < S.t.length; i++) if (S.net[i] !== null && S.load[i] !== null) { xs.push(S.net[i]); ys.push(S.load[i]); }
  S.charts.curve.setData([null, [xs, ys]]);
  $("curve").dataset.points = xs.length;
  S.charts.defl.setData([S.t, S.net]);
  $("defl").dataset.points = S.net.filter((v) => v !== null).length;
  S.charts.load.setData([S.t, S.load]);
  $("load").dataset.points = S.load.filter((v) => v !== null).length;
  S.charts.tags.setData([S.t, ...S.tagChartIds.map((id) => S.tags.get(id))]);
  $("tags").dataset.points = S.t.length;
  const l = S.lastLine;
  if (l) {
    $("r-load").textContent = fmt(l.load_kN, 2);
    $("r-net").textContent = fmt(l.net_deflection_mm, 3);
    $("r-stroke").textContent = fmt(l.stroke_mm, 3);
    $("r-seq").textContent = l.seq;
    chip("c-latency", l.latency_ms === undefined ? "latency – ms" : `latency ${fmt(l.latency_ms, 1)} ms`, l.latency_ms > 1000 ? "warn" : "");
    chip("c-dropped", `dropped sets ${l.dropped_sets ?? 0}`, (l.dropped_sets ?? 0) > 0 ? "warn" : "ok");
  }
}

function chip(id, text, cls) {
  const el = $(id);
  el.textContent = text;
  el.className = "chip" + (cls ? " " + cls : "");
}

function cameraCard(src) {
  let c = S.cams.get(src.name);
  if (c) return c;
  const el = document.createElement("div");
  el.className = "camera";
  el.dataset.camera = src.name;
  // Built as elements with text, never markup from data: a camera name is the config's,
  // and a recording's config may come from anywhere.
  const node = (tag, cls, text) => {
    const n = document.createElement(tag);
    if (cls) n.className = cls;
    if (text !== undefined) n.textContent = text;
    return n;
  };
  const head = node("div", "head");
  head.append(node("span", "", src.name), node("span", "chip state", "–"));
  const img = node("img", "thumb");
  img.alt = `camera ${src.name}: no snapshot yet`;
  const dl = node("dl");
  for (const [label, cls] of [["pose reprojection", "reproj"], ["frame rate", "rate"], ["frames / dropped", "frames"], ["tags seen", "seen"]]) {
    dl.append(node("dt", "", label), node("dd", cls, "–"));
  }
  el.append(head, img, dl);
  $("cameras").append(el);
  c = { el, img: el.querySelector("img"), state: el.querySelector(".state"), reproj: el.querySelector(".reproj"),
    rate: el.querySelector(".rate"), frames: el.querySelector(".frames"), seen: el.querySelector(".seen"), seq: -1 };
  S.cams.set(src.name, c);
  return c;
}

function showSnapshot(name, url, seq) {
  const c = S.cams.get(name);
  if (!c || seq === c.seq) return;
  c.seq = seq;
  c.img.src = url;
}

function onStatus(st) {
  const first = S.status === null;
  S.status = st;
  S.mode = st.mode;
  S.up = st.world_up || S.up;
  if (st.frame_interval_s) S.frameInterval = st.frame_interval_s;
  $("mode").textContent = st.mode === "live" ? "— live" : st.finished ? "— replay (recording consumed)" : "— replay";
  if (first) for (const t of st.specimen_tags) addTag(t.id, t.role);
  if (first) rebuildTagChart();
  for (const src of st.sources) {
    const c = cameraCard(src);
    let state = "posed", cls = "ok";
    if (src.lost) { state = "lost"; cls = "bad"; }
    else if (src.stale) { state = "stale"; cls = "bad"; }
    else if (src.bumped_recently) { state = "bumped"; cls = "warn"; }
    else if (!src.posed) { state = "not posed"; cls = "warn"; }
    c.state.textContent = state;
    c.state.className = "chip state " + cls;
    c.el.dataset.state = state;
    c.reproj.textContent = src.pose_reproj_px === null ? "–" : `${fmt(src.pose_reproj_px, 3)} px`;
    c.rate.textContent = src.frame_rate_hz === null ? "–" : `${fmt(src.frame_rate_hz, 1)} Hz` + (src.fps ? ` (set ${src.fps} Hz)` : "");
    c.frames.textContent = `${src.frames} / ${src.frames_dropped}` + (src.bumps ? ` · ${src.bumps} bump${src.bumps > 1 ? "s" : ""}` : "");
    c.seen.textContent = src.background_tags === null ? "–" : `${src.specimen_tags} specimen, ${src.background_tags} background`;
    if (src.snapshot) showSnapshot(src.name, src.snapshot.url, src.snapshot.seq);
  }
  const u = st.utm;
  chip("c-utm", u.state === "none" ? "no UTM" : `UTM ${u.state}`, u.state === "ok" ? "ok" : u.state === "none" ? "" : "bad");
  const r = st.recording;
  chip("c-rec", r.failed ? "recording FAILED" : r.active ? `recording${r.dropped ? " (" + r.dropped + " dropped)" : ""}` : "not recording",
    r.failed ? "bad" : r.active ? "ok" : "");
  if (!S.lastLine) chip("c-dropped", `dropped sets ${st.feed.dropped_sets}`, st.feed.dropped_sets > 0 ? "warn" : "ok");
  updateBanner();
}

function updateBanner() {
  const problems = S.statusOk && S.status ? [...S.status.problems] : ["no connection to tagdeflect: the daemon may have stopped"];
  // The page's own check: lines stop arriving (also when /api/status still answers).
  const live = S.status && S.status.mode !== "replay" && !S.status.finished;
  const quiet = (performance.now() - S.lastLineAt) / 1000;
  const limit = Math.max(5 * S.frameInterval, 2);
  if (live && S.lastLineAt > 0 && quiet > limit && !problems.some((p) => p.startsWith("no feed line")))
    problems.push(`no feed line for ${quiet.toFixed(1)} s`);
  const b = $("banner");
  if (problems.length === 0) { b.hidden = true; b.replaceChildren(); return; }
  b.replaceChildren(...problems.map((p) => { const d = document.createElement("div"); d.textContent = "⚠ " + p; return d; }));
  b.hidden = false;
}

async function pollStatus() {
  try {
    const r = await fetch("/api/status", { cache: "no-store" });
    if (!r.ok) throw new Error(r.status);
    S.statusOk = true;
    onStatus(await r.json());
  } catch (e) {
    S.statusOk = false;
    updateBanner();
  }
}

function connect() {
  const es = new EventSource("/events");
  es.onopen = () => chip("c-conn", "connected", "ok");
  es.onerror = () => chip("c-conn", "reconnecting…", "bad");
  es.onmessage = (e) => { try { onLine(JSON.parse(e.data)); } catch (err) { console.error(err); } };
  es.addEventListener("snapshot", (e) => { const n = JSON.parse(e.data); showSnapshot(n.camera, n.url, n.seq); });
}

// The test panel: the state from GET /api/test, the commands as POSTs with the token, asked
// once per browser session (sessionStorage). Text only through textContent.
const T = { state: null, startedNs: null, peak: null, lastRate: null };
function testMessage(text, bad) { const m = $("t-message"); m.textContent = text; m.className = bad ? "bad" : "muted"; }
function token() {
  let t = sessionStorage.getItem("tagdeflect-token");
  if (!t) {
    t = window.prompt("Control token (printed by the daemon at start, or in its tests folder's .token):") || "";
    t = t.trim();
    if (t) sessionStorage.setItem("tagdeflect-token", t);
  }
  return t;
}
async function command(cmd, body) {
  const t = token();
  if (!t) { testMessage("no token given", true); return; }
  const r = await fetch("/api/test/" + cmd, {
    method: "POST", cache: "no-store",
    headers: { "Content-Type": "application/json", "Authorization": "Bearer " + t },
    body: JSON.stringify(body || {}),
  });
  let answer = {};
  try { answer = await r.json(); } catch (e) { answer = {}; }
  if (r.status === 401) sessionStorage.removeItem("tagdeflect-token");
  if (!r.ok) { testMessage(cmd + " refused (" + r.status + "): " + (answer.error || ""), true); return; }
  testMessage(cmd === "stop" ? "stopped; folder " + (answer.folder || "") : cmd + " done", false);
  await pollTest();
}
function onTest(st) {
  T.state = st.state;
  const running = st.state === "running";
  $("t-state").textContent = running ? "running: " + st.id + (st.zeroing ? " (taking its zero)" : "") : st.state;
  $("t-specimen").textContent = running ? st.specimen : "–";
  T.startedNs = running ? st.started_t_ns : null;
  if (!running) T.peak = null;
  $("b-start").disabled = running || st.state === "off";
  for (const id of ["b-mark", "b-zero", "b-stop"]) $(id).disabled = !running;
  $("t-auto").textContent = st.auto ? "automatic (" + st.auto.state + "): waiting for " + st.auto.waiting_for : "";
  if (st.state === "off") testMessage("tests are off: start the daemon with --tests DIR or [output] tests", false);
}
function onTestLine(line) {
  if (!line.test) return;
  if (line.load_kN !== undefined && (T.peak === null || line.load_kN > T.peak)) T.peak = line.load_kN;
  if (line.net_deflection_mm !== undefined) {
    if (T.lastRate) {
      const dt = (line.t_ns - T.lastRate.t) / 6e10;
      if (dt > 0.05 / 60) { T.rate = (line.net_deflection_mm - T.lastRate.v) / dt; T.lastRate = { t: line.t_ns, v: line.net_deflection_mm }; }
    } else T.lastRate = { t: line.t_ns, v: line.net_deflection_mm };
  }
  $("t-peak").textContent = fmt(T.peak, 2);
  $("t-rate").textContent = fmt(T.rate, 3);
  if (T.startedNs !== null) {
    const s = Math.max(0, (line.t_ns - T.startedNs) / 1e9);
    $("t-elapsed").textContent = Math.floor(s / 60) + " min " + (s % 60).toFixed(0).padStart(2, "0") + " s";
  }
}
async function pollTest() {
  try {
    const r = await fetch("/api/test", { cache: "no-store" });
    if (r.ok) onTest(await r.json());
  } catch (e) { /* the status poll reports a lost server */ }
}
$("t-form").addEventListener("submit", (e) => {
  e.preventDefault();
  const body = { specimen: $("f-specimen").value.trim() };
  for (const k of ["operator", "standard", "notes"]) { const v = $("f-" + k).value.trim(); if (v) body[k] = v; }
  command("start", body);
});
$("b-mark").addEventListener("click", () => { const note = window.prompt("Mark (e.g. first crack seen):"); if (note !== null) command("mark", { note }); });
$("b-zero").addEventListener("click", () => command("zero"));
$("b-stop").addEventListener("click", () => { if (window.confirm("Stop the test and complete its folder?")) command("stop"); });

initCharts();
pollTest();
setInterval(pollTest, 1000);
pollStatus().then(connect);
setInterval(pollStatus, 1000);
setInterval(redraw, 250);
setInterval(updateBanner, 500);
