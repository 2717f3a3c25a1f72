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
  cmodv: [],           // the CMOD gauge's value, aligned with t
  netHi: [], netLo: [], // net deflection ± 2σ (net_deflection_sigma_mm), aligned with t
  partial: [],         // the net deflection of a partial frame set (else null), aligned with t
  testIds: [],         // the test of each line (null between tests), aligned with t
  zeroing: [],         // true for a test's line that is one of its zero's sets, aligned with t
  earlier: [],         // the day's stopped tests: {id, specimen, net_deflection_mm, load_kn}
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

function makeTimeChart(el, yLabel, series, extra) {
  const opts = {
    ...(extra || {}),
    ...size(el),
    scales: { x: { time: false } },
    axes: [axis("time [s]"), axis(yLabel)],
    series: [{ label: "t [s]", value: (u, v) => fmt(v, 1) }, ...series],
    legend: { live: true },
    cursor: { drag: { x: true, y: false } },
  };
  return new uPlot(opts, [[], ...series.map(() => [])], el);
}

// Load over a deflection (mode 2: every series its own x); `earlier` grey curves under the
// live one (the day's stopped tests). With `sigma`, the live curve's ±2σ in deflection
// (net_deflection_sigma_mm) as two thin lines either side, and its partial frame sets as red
// points: the series after the live one are −2σ, +2σ, partial.
function makeCurve(el, earlier, xLabel, sigma) {
  const facets = [{ scale: "x", auto: true }, { scale: "y", auto: true }];
  const grey = { stroke: "#6b717a", width: 1, paths: uPlot.paths.linear(), points: { show: false }, facets };
  const edge = { stroke: "rgba(255,140,0,0.45)", width: 1, dash: [4, 3], paths: uPlot.paths.linear(), points: { show: false }, facets };
  const extra = sigma ? [{ label: "−2σ", ...edge }, { label: "+2σ", ...edge },
    { label: "partial set", stroke: "#ff5252", fill: "#ff5252", paths: uPlot.paths.points(), points: { show: true, size: 7, fill: "#ff5252" }, facets }] : [];
  const opts = {
    mode: 2,
    ...size(el),
    height: 340,
    // The live curve's x axis reaches L/150 once the test's span is known (live_curve.js).
    scales: { x: sigma ? { time: false, range: (u, lo, hi) => (typeof curveXRange === "function" ? curveXRange(lo, hi) : [lo ?? 0, hi ?? 1]) } : { time: false }, y: {} },
    axes: [axis(xLabel), axis("load [kN]")],
    series: [{}, ...Array.from({ length: earlier }, () => ({ ...grey })),
      { label: "load vs " + xLabel, stroke: "#ff8c00", width: 2, paths: uPlot.paths.linear(), points: { show: false }, facets }, ...extra],
    legend: { show: false },
    cursor: { drag: { x: false, y: false }, points: { show: false } },
    // The live curve's marks, L/600, L/150 and P1 (live_curve.js) drawn over it.
    hooks: sigma ? { draw: [(u) => { if (typeof drawCurveMarks === "function") drawCurveMarks(u); }] } : {},
  };
  return new uPlot(opts, [null, ...Array.from({ length: earlier + 1 + extra.length }, () => [[], []])], el);
}

// The deflected shape: each specimen tag's downward displacement at its place along the beam
// (points) and the elastic curve fitted through them (line); the y axis points down.
function makeProfile(el) {
  const facets = [{ scale: "x", auto: true }, { scale: "y", auto: true }];
  const opts = {
    mode: 2,
    ...size(el),
    scales: { x: { time: false }, y: { dir: -1 } },
    axes: [axis("along the beam [mm]"), axis("down [mm]")],
    series: [{},
      { label: "tags", stroke: "#ff8c00", fill: "#ff8c00", paths: uPlot.paths.points(), points: { show: true, size: 9, fill: "#ff8c00" }, facets },
      { label: "elastic fit", stroke: "#00c8ff", width: 2, paths: uPlot.paths.linear(), points: { show: false }, facets }],
    legend: { show: false },
    cursor: { drag: { x: false, y: false }, points: { show: false } },
  };
  return new uPlot(opts, [null, [[], []], [[], []]], el);
}

function rebuildCurve() {
  if (S.charts.curve) S.charts.curve.destroy();
  S.charts.curve = makeCurve($("curve"), S.earlier.length, "net deflection [mm]", true);
  $("curve-note").textContent = S.earlier.length ? `(the day's ${S.earlier.length} earlier test${S.earlier.length > 1 ? "s" : ""} in grey)` : "";
  S.dirty = true;
}

function initCharts() {
  rebuildCurve();
  S.charts.profile = makeProfile($("profile"));
  // The net deflection with its ±2σ band, and the frame sets that lacked a camera marked.
  S.charts.defl = makeTimeChart($("defl"), "net deflection [mm]", [
    { label: "net deflection [mm]", stroke: "#ff8c00", width: 2, value: (u, v) => fmt(v, 3) },
    { label: "+2σ", stroke: "rgba(255,140,0,0.35)", width: 1, value: (u, v) => fmt(v, 3) },
    { label: "−2σ", stroke: "rgba(255,140,0,0.35)", width: 1, value: (u, v) => fmt(v, 3) },
    { label: "partial set", stroke: "#ff5252", fill: "#ff5252", paths: () => null, points: { show: true, size: 7, stroke: "#ff5252", fill: "#ff5252" }, value: (u, v) => fmt(v, 3) },
  ], { bands: [{ series: [2, 3], fill: "rgba(255,140,0,0.18)" }] });
  S.charts.load = makeTimeChart($("load"), "load [kN]", [{ label: "load [kN]", stroke: "#00c8ff", width: 2, value: (u, v) => fmt(v, 2) }]);
  rebuildTagChart();
  window.addEventListener("resize", () => {
    const el = { cmod: "cmodcurve" };
    for (const [k, c] of Object.entries(S.charts)) c.setSize(size($(el[k] || k)));
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
  S.cmodv = keep(S.cmodv); S.testIds = keep(S.testIds); S.zeroing = keep(S.zeroing);
  S.netHi = keep(S.netHi); S.netLo = keep(S.netLo); S.partial = keep(S.partial);
  for (const [id, a] of S.tags) S.tags.set(id, keep(a));
}

function onLine(line) {
  if (S.t0 === null) S.t0 = line.t_ns;
  const [ux, uy, uz] = S.up;
  S.t.push((line.t_ns - S.t0) / 1e9);
  S.load.push(line.load_kN ?? null);
  S.net.push(line.net_deflection_mm ?? null);
  const net = line.net_deflection_mm, sig = line.net_deflection_sigma_mm;
  const banded = net !== undefined && sig !== undefined && sig !== null;
  S.netHi.push(banded ? net + 2 * sig : null);
  S.netLo.push(banded ? net - 2 * sig : null);
  S.partial.push(line.partial_set && net !== undefined ? net : null);
  S.stroke.push(line.stroke_mm ?? null);
  const cmod = S.status && S.status.cmod_gauge && line.gauges ? line.gauges[S.status.cmod_gauge] : undefined;
  S.cmodv.push(cmod ? cmod.value : null);
  S.testIds.push(line.test ? line.test.id : null);
  S.zeroing.push(Boolean(line.test && line.test.zeroing));
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
  // While a test runs, its own lines (counted from its zero); else every line.
  const testId = T.state === "running" ? T.id : null;
  const curveOf = (xv) => {
    const xs = [], ys = [];
    for (let i = 0; i < S.t.length; i++) {
      if ((testId === null || S.testIds[i] === testId) && xv[i] !== null && S.load[i] !== null) { xs.push(xv[i]); ys.push(S.load[i]); }
    }
    return [xs, ys];
  };
  const cur = curveOf(S.net), lo = curveOf(S.netLo), hi = curveOf(S.netHi), part = curveOf(S.partial);
  S.charts.curve.setData([null, ...S.earlier.map((e) => [e.net_deflection_mm, e.load_kn]), cur, lo, hi, part]);
  $("curve").dataset.points = cur[0].length;
  $("curve").dataset.band = lo[0].length;
  $("curve").dataset.partial = part[0].length;
  $("curve").dataset.earlier = S.earlier.length;
  if (S.charts.cmod) {
    const c = curveOf(S.cmodv);
    S.charts.cmod.setData([null, c]);
    $("cmodcurve").dataset.points = c[0].length;
  }
  S.charts.defl.setData([S.t, S.net, S.netHi, S.netLo, S.partial]);
  $("defl").dataset.points = S.net.filter((v) => v !== null).length;
  $("defl").dataset.band = S.netHi.filter((v) => v !== null).length;
  $("defl").dataset.partial = S.partial.filter((v) => v !== null).length;
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
    showGauges(l);
    showProfile(l);
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
  for (const [label, cls] of [["pose reprojection", "reproj"], ["frame rate", "rate"], ["frames / dropped", "frames"], ["arrival delay", "delay"], ["tags seen", "seen"]]) {
    dl.append(node("dt", "", label), node("dd", cls, "–"));
  }
  el.append(head, img, dl);
  $("cameras").append(el);
  c = { el, img: el.querySelector("img"), state: el.querySelector(".state"), reproj: el.querySelector(".reproj"),
    rate: el.querySelector(".rate"), frames: el.querySelector(".frames"), delay: el.querySelector(".delay"), seen: el.querySelector(".seen"), seq: -1 };
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
  if (first && st.cmod_gauge) {
    $("cmod-panel").hidden = false;
    $("cmod-name").textContent = "(gauge " + st.cmod_gauge + ")";
    S.charts.cmod = makeCurve($("cmodcurve"), 0, "CMOD [mm]");
  }
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
    c.delay.textContent = src.arrival_delay_ms == null ? "–" : `${fmt(src.arrival_delay_ms, 0)} ms`;
    c.seen.textContent = src.background_tags === null ? "–" : `${src.specimen_tags} specimen, ${src.background_tags} background`;
    if (src.snapshot) showSnapshot(src.name, src.snapshot.url, src.snapshot.seq);
  }
  const u = st.utm;
  chip("c-utm", u.state === "none" ? "no UTM" : `UTM ${u.state}`, u.state === "ok" ? "ok" : u.state === "none" ? "" : "bad");
  const r = st.recording;
  chip("c-rec", r.failed ? "recording FAILED" : r.active ? `recording${r.dropped ? " (" + r.dropped + " dropped)" : ""}` : "not recording",
    r.failed ? "bad" : r.active ? "ok" : "");
  const ar = st.archive;
  $("c-archive").hidden = !ar;
  if (ar) {
    const text = !ar.connected ? `archive: broker unreachable (${ar.unconfirmed_lines} waiting)`
      : !ar.heard ? "archive: not heard yet" : `archive lag ${ar.lag_lines} lines`;
    chip("c-archive", text, !ar.connected ? "bad" : !ar.heard ? "" : ar.lag_lines > 100 ? "warn" : "ok");
    $("c-archive").dataset.lag = ar.heard ? ar.lag_lines : "";
  }
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
  if (T.rateAlarm) problems.push(T.rateAlarm);
  // Alarms once the page has heard from the daemon (not the page's own start).
  if (S.status) updateAlarms(problems);
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
const T = { state: null, id: null, standard: null, startedNs: null, peak: null, lastRate: null, rate: null, outSince: null, rateAlarm: null };
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
// A start refused because the previous test is still being stopped (409 with Retry-After) is
// pressed again by the page after the time it is told, at most this many times.
const START_RETRIES = 6;
async function command(cmd, body) {
  const t = token();
  if (!t) { testMessage("no token given", true); return; }
  let r, answer;
  for (let attempt = 0; ; attempt++) {
    r = await fetch("/api/test/" + cmd, {
      method: "POST", cache: "no-store",
      headers: { "Content-Type": "application/json", "Authorization": "Bearer " + t },
      body: JSON.stringify(body || {}),
    });
    answer = {};
    try { answer = await r.json(); } catch (e) { answer = {}; }
    const after = Number(r.headers.get("Retry-After"));
    if (cmd !== "start" || r.status !== 409 || !(after > 0) || attempt >= START_RETRIES) break;
    testMessage(`start waits: ${answer.error || "the previous test is still being stopped"} (again in ${after} s)`, false);
    await new Promise((done) => setTimeout(done, after * 1000));
  }
  if (r.status === 401) sessionStorage.removeItem("tagdeflect-token");
  if (!r.ok) { testMessage(cmd + " refused (" + r.status + "): " + (answer.error || ""), true); return; }
  testMessage(cmd === "stop" ? "stopped; folder " + (answer.folder || "") : cmd + " done", false);
  if (cmd === "stop" || cmd === "start") $("t-report").textContent = answer.report_error ? "no report: " + answer.report_error : "";
  await pollTest();
}
function onTest(st) {
  const wasRunning = T.state === "running";
  T.state = st.state;
  const running = st.state === "running";
  if (running && T.id !== st.id) { T.lastRate = null; T.rate = null; T.outSince = null; T.rateAlarm = null; }
  T.id = running ? st.id : null;
  T.standard = running ? st.standard || null : null;
  T.method = running ? st.method || null : null;
  T.measured = running ? st.measured || {} : {};
  if (wasRunning && !running) { T.rateAlarm = null; T.outSince = null; fetchEarlier(); }
  $("t-state").textContent = running ? "running: " + st.id + (st.zeroing ? " (taking its zero)" : "") : st.stopping ? "stopping: " + st.stopping : st.state;
  $("t-specimen").textContent = running ? st.specimen : "–";
  T.startedNs = running ? st.started_t_ns : null;
  if (!running) T.peak = null;
  // While a stopped test's folder is completed (`stopping`) a start would wait for it.
  $("b-start").disabled = running || st.state === "off" || Boolean(st.stopping);
  for (const id of ["b-mark", "b-zero", "b-stop"]) $(id).disabled = !running;
  $("t-auto").textContent = st.auto ? "automatic (" + st.auto.state + "): waiting for " + st.auto.waiting_for : "";
  if (!running && st.last) $("t-report").textContent = st.last.report_error ? "no report: " + st.last.report_error : "";
  if (st.state === "off") testMessage("tests are off: start the daemon with --tests DIR or [output] tests", false);
  for (const f of TEST_LISTENERS) f(st);
}
// The page's other parts that follow the test's state (live_curve.js, review.js).
const TEST_LISTENERS = [];
// A request with the token (asked once, as for the commands): the answer as
// {ok, status, body}; a 401 drops the token.
async function authed(path, init) {
  const t = token();
  if (!t) return { ok: false, status: 0, body: { error: "no token given" } };
  const headers = Object.assign({ "Authorization": "Bearer " + t }, (init && init.headers) || {});
  const r = await fetch(path, Object.assign({ cache: "no-store" }, init || {}, { headers }));
  let body = {};
  try { body = await r.json(); } catch (e) { body = {}; }
  if (r.status === 401) sessionStorage.removeItem("tagdeflect-token");
  return { ok: r.ok, status: r.status, body };
}
// The rate of the standard's controlled quantity (CMOD for EN 14651, else the net deflection)
// against the standard's window for this beam (/api/status rate_windows; the report's): green
// inside, amber within 25 % beyond its edges, red further; red for 10 s is an alarm.
function controlled(line) {
  const cmod = T.standard === "en-14651" && S.status && S.status.cmod_gauge;
  if (cmod) { const g = (line.gauges || {})[cmod]; return { name: "CMOD rate", v: g ? g.value : undefined, rate: undefined }; }
  return { name: "deflection rate", v: line.net_deflection_mm, rate: line.net_deflection_rate_mm_per_min };
}
function judgeRate(line, q) {
  const box = $("t-rate");
  const windows = S.status && S.status.rate_windows ? S.status.rate_windows : {};
  const w = (T.standard && methodWindow(T.standard, T.method, T.measured)) || (T.standard ? windows[T.standard] : undefined);
  if (!w) {
    box.dataset.window = "none";
    $("t-rate-window").textContent = T.standard ? "no window: no span (measured, the specimen's row or [specimen.beam])" : "no standard: no window";
    return;
  }
  const below = q.v === undefined || q.v < w.split_mm;
  const [lo, hi] = below ? w.below_mm_per_min : w.above_mm_per_min;
  $("t-rate-window").textContent = `window ${lo}–${hi} mm/min (${below ? "up to" : "beyond"} ${fmt(w.split_mm, 3)} mm)`;
  if (T.rate === null || T.rate === undefined || line.test.zeroing) { box.dataset.window = "none"; return; }
  const r = T.rate;
  const verdict = r >= lo && r <= hi ? "ok" : r >= 0.75 * lo && r <= 1.25 * hi ? "warn" : "bad";
  box.dataset.window = verdict;
  if (verdict === "bad") {
    if (T.outSince === null) T.outSince = line.t_ns;
    if (line.t_ns - T.outSince >= 10e9) T.rateAlarm = `${q.name} ${fmt(r, 3)} mm/min out of the standard's window ${lo}–${hi} mm/min`;
  } else { T.outSince = null; T.rateAlarm = null; }
}
function onTestLine(line) {
  if (!line.test) return;
  if (line.load_kN !== undefined && (T.peak === null || line.load_kN > T.peak)) T.peak = line.load_kN;
  const q = controlled(line);
  $("t-rate-label").textContent = q.name;
  if (q.rate !== undefined && q.rate !== null) T.rate = q.rate;
  else if (q.v !== undefined) {
    if (T.lastRate) {
      const dt = (line.t_ns - T.lastRate.t) / 6e10;
      if (dt > 0.05 / 60) { T.rate = (q.v - T.lastRate.v) / dt; T.lastRate = { t: line.t_ns, v: q.v }; }
    } else T.lastRate = { t: line.t_ns, v: q.v };
  }
  $("t-peak").textContent = fmt(T.peak, 2);
  $("t-rate").textContent = fmt(T.rate, 3);
  judgeRate(line, q);
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
  for (const k of ["operator", "standard", "notes", "method"]) { const v = $("f-" + k).value.trim(); if (v) body[k] = v; }
  // The specimen's measured dimensions: the report computes with them.
  const measured = typed();
  if (Object.keys(measured).length) body.measured = measured;
  command("start", body);
});
$("b-mark").addEventListener("click", () => { const note = window.prompt("Mark (e.g. first crack seen):"); if (note !== null) command("mark", { note }); });
$("b-zero").addEventListener("click", () => command("zero"));
$("b-stop").addEventListener("click", () => { if (window.confirm("Stop the test and complete its folder?")) command("stop", stopBody()); });

// Gauges (and the net deflection) with their 1-σ, as the line gives them.
const DECIMALS = { "mm": 3, "mrad": 3, "1/km": 2 };
function showGauges(l) {
  const rows = [];
  if (l.net_deflection_mm !== undefined) rows.push(["net deflection", l.net_deflection_mm, l.net_deflection_sigma_mm, "mm"]);
  for (const [name, g] of Object.entries(l.gauges || {})) rows.push([name, g.value, g.sigma, g.unit || ""]);
  const body = $("gauges").tBodies[0];
  if (rows.length === 0) {
    const td = document.createElement("td"); td.className = "muted"; td.textContent = "no gauge in this line ([[gauge]] in the config)";
    const tr = document.createElement("tr"); tr.append(td); body.replaceChildren(tr); return;
  }
  body.replaceChildren(...rows.map(([name, v, sigma, unit]) => {
    const d = DECIMALS[unit] ?? 0;
    const tr = document.createElement("tr");
    tr.dataset.gauge = name;
    const cells = [[name, "name"], [fmt(v, d), "num"], [sigma === undefined || sigma === null ? "± ?" : "± " + fmt(sigma, d), "num sigma"], [unit, "muted"]];
    for (const [text, cls] of cells) { const td = document.createElement("td"); td.className = cls; td.textContent = text; tr.append(td); }
    return tr;
  }));
}

// The bending profile. The beam's axis: the horizontal direction the tags spread along (the
// principal direction of their rest positions across world.up). Supports: the `support`
// tags, else [specimen.beam] span_mm about the midspan tags (or the tags' middle). The elastic
// curve of a simply supported beam under two loads a = (L − L/3)/2 from the supports (third-
// point loading, ASTM C1609; one load at midspan for EN 14651), plus a line for the supports'
// own movement: w(x) = c0 + c1·x + k·f(x), least squares over the tags.
function shape(x, L, a) {
  const f = (u) => u <= a ? u * (3 * L * a - 3 * a * a - u * u) : a * (3 * L * u - 3 * u * u - a * a);
  const slope0 = 3 * L * a - 3 * a * a;
  const peak = a * (0.75 * L * L - a * a);
  let v;
  if (x < 0) v = x * slope0; else if (x > L) v = (L - x) * slope0; else v = x <= L / 2 ? f(x) : f(L - x);
  return v / peak;
}
function solve3(A, b) {
  const m = A.map((r, i) => [...r, b[i]]);
  for (let c = 0; c < 3; c++) {
    let p = c;
    for (let r = c + 1; r < 3; r++) if (Math.abs(m[r][c]) > Math.abs(m[p][c])) p = r;
    if (Math.abs(m[p][c]) < 1e-12) return null;
    [m[c], m[p]] = [m[p], m[c]];
    for (let r = 0; r < 3; r++) if (r !== c) { const k = m[r][c] / m[c][c]; for (let j = c; j < 4; j++) m[r][j] -= k * m[c][j]; }
  }
  return [m[0][3] / m[0][0], m[1][3] / m[1][1], m[2][3] / m[2][2]];
}
function showProfile(l) {
  const tags = (l.tags || []).filter((t) => t.pos_mm && t.disp_mm);
  const el = $("profile");
  if (tags.length < 2) { S.charts.profile.setData([null, [[], []], [[], []]]); el.dataset.points = 0; el.dataset.fit = "none"; return; }
  const up = S.up;
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const rest = tags.map((t) => t.pos_mm.map((p, i) => p - t.disp_mm[i]));
  const mean = [0, 1, 2].map((i) => rest.reduce((s, p) => s + p[i], 0) / rest.length);
  const flat = rest.map((p) => { const d = p.map((v, i) => v - mean[i]); const h = dot(d, up); return d.map((v, i) => v - h * up[i]); });
  // Power iteration on the horizontal scatter.
  let ax = flat.reduce((best, d) => (dot(d, d) > dot(best, best) ? d : best), [1e-9, 0, 0]);
  for (let it = 0; it < 30; it++) {
    const n = [0, 0, 0];
    for (const d of flat) { const k = dot(d, ax); for (let i = 0; i < 3; i++) n[i] += k * d[i]; }
    const len = Math.sqrt(dot(n, n)) || 1;
    ax = n.map((v) => v / len);
  }
  const big = ax.reduce((b, v, i) => (Math.abs(v) > Math.abs(ax[b]) ? i : b), 0);
  if (ax[big] < 0) ax = ax.map((v) => -v);
  const roles = new Map(((S.status && S.status.specimen_tags) || []).map((t) => [t.id, t.role]));
  const s = flat.map((d) => dot(d, ax));
  const w = tags.map((t) => -dot(t.disp_mm, up));
  const sup = s.filter((_, i) => roles.get(tags[i].id) === "support");
  const mid = s.filter((_, i) => roles.get(tags[i].id) === "midspan");
  let left = null, L = null;
  if (sup.length >= 2) { left = Math.min(...sup); L = Math.max(...sup) - left; }
  else if (S.status && S.status.beam) {
    L = S.status.beam.span_mm;
    const c = mid.length ? mid.reduce((a, b) => a + b, 0) / mid.length : (Math.min(...s) + Math.max(...s)) / 2;
    left = c - L / 2;
  }
  const xs = s.map((v) => left === null ? v : v - left);
  S.charts.profile.setData([null, [xs, w], [[], []]]);
  el.dataset.points = xs.length;
  el.dataset.fit = "none";
  if (L === null || !(L > 0) || tags.length < 3) { $("profile-note").textContent = "(no fit: give support tags or [specimen.beam])"; return; }
  // One load at midspan for EN 14651, and for a notched beam when no standard says otherwise.
  const notched = S.status && S.status.beam && S.status.beam.notch_mm;
  const threePoint = T.standard === "en-14651" || (!T.standard && notched);
  const a = threePoint ? L / 2 : L / 3;
  const rows = xs.map((x) => [1, x, shape(x, L, a)]);
  const A = [0, 1, 2].map((i) => [0, 1, 2].map((j) => rows.reduce((acc, r) => acc + r[i] * r[j], 0)));
  const b = [0, 1, 2].map((i) => rows.reduce((acc, r, k) => acc + r[i] * w[k], 0));
  const c = solve3(A, b);
  if (!c) { $("profile-note").textContent = "(no fit: the tags do not span the beam)"; return; }
  const lo = Math.min(0, ...xs), hi = Math.max(L, ...xs);
  const fx = [], fy = [];
  for (let i = 0; i <= 80; i++) { const x = lo + (hi - lo) * i / 80; fx.push(x); fy.push(c[0] + c[1] * x + c[2] * shape(x, L, a)); }
  const res = rows.map((r, k) => w[k] - (c[0] + c[1] * r[1] + c[2] * r[2]));
  const rms = Math.sqrt(res.reduce((acc, v) => acc + v * v, 0) / res.length);
  S.charts.profile.setData([null, [xs, w], [fx, fy]]);
  el.dataset.fit = "ok";
  el.dataset.bending = c[2].toFixed(4);
  el.dataset.loading = threePoint ? "three-point" : "third-point";
  $("profile-note").textContent = `(x from the left support; ${threePoint ? "one load at midspan" : "loads at the third points"}; fit: bending ${fmt(c[2], 3)} mm at midspan, rms ${fmt(rms * 1000, 0)} µm over ${xs.length} tags)`;
}

// Alarms: everything the banner says, and a rate out of its window for 10 s, listed until
// acknowledged (in this browser). An alarm whose cause went away stays, amber, until
// acknowledged; an acknowledged one stays, grey, while its cause lasts.
const ALARMS = new Map(); // key (the text without its numbers) -> {text, since, active, acked}
function updateAlarms(problems) {
  const now = new Set();
  for (const text of problems) {
    const key = text.replace(/[0-9]+([.,][0-9]+)?/g, "#");
    now.add(key);
    const a = ALARMS.get(key);
    if (!a) ALARMS.set(key, { text, since: new Date(), active: true, acked: false });
    else { a.text = text; if (!a.active) { a.active = true; a.acked = false; a.since = new Date(); } }
  }
  for (const [key, a] of ALARMS) if (!now.has(key)) { a.active = false; if (a.acked) ALARMS.delete(key); }
  renderAlarms();
}
function acknowledge(key) {
  const a = ALARMS.get(key);
  if (!a) return;
  a.acked = true;
  if (!a.active) ALARMS.delete(key);
  renderAlarms();
}
function renderAlarms() {
  const items = [];
  let open = 0;
  for (const [key, a] of ALARMS) {
    const state = a.acked ? "acked" : a.active ? "active" : "cleared";
    if (!a.acked) open++;
    const li = document.createElement("li");
    li.dataset.state = state;
    const when = document.createElement("span"); when.className = "when"; when.textContent = a.since.toLocaleTimeString();
    const text = document.createElement("span"); text.className = "text";
    text.textContent = a.text + (state === "cleared" ? " — cleared" : state === "acked" ? " — acknowledged, still on" : "");
    li.append(when, text);
    if (!a.acked) {
      const b = document.createElement("button"); b.type = "button"; b.className = "small-button ack"; b.textContent = "acknowledge";
      b.addEventListener("click", () => acknowledge(key));
      li.append(b);
    }
    items.push(li);
  }
  $("alarms").replaceChildren(...items);
  $("alarm-count").textContent = ALARMS.size === 0 ? "none" : `${open} to acknowledge, ${ALARMS.size} listed`;
  $("b-ack").disabled = open === 0;
}
$("b-ack").addEventListener("click", () => { for (const key of [...ALARMS.keys()]) acknowledge(key); });

async function fetchEarlier() {
  try {
    const r = await fetch("/api/tests", { cache: "no-store" });
    if (!r.ok) return;
    const j = await r.json();
    S.earlier = (j.tests || []).filter((t) => Array.isArray(t.net_deflection_mm) && Array.isArray(t.load_kn));
    rebuildCurve();
  } catch (e) { /* the status poll reports a lost server */ }
}

initCharts();
fetchEarlier();
pollTest();
setInterval(pollTest, 1000);
pollStatus().then(connect);
setInterval(pollStatus, 1000);
setInterval(redraw, 250);
setInterval(updateBanner, 500);
