"use strict";
// What the load–net-deflection curve shows of the test (docs/live-page.md): L/600 and L/150
// (vertical lines at span/600 and span/150 when the span is known: the test's measured span,
// else the config's beam), P1 (the first peak: while the test runs found on the page the way
// the report finds it, after the stop the report's own P1 and δ1), and the test's events —
// marks, zeros, preload, crack entries — at the point of the curve where they were made. The
// test's events are listed under the panel; the verification in force is named in the test
// panel (highlighted, with its reasons, when stale). Text only through textContent.
const C = { id: null, span: null, events: [], verification: null, reportP1: null };
const MARK_COLOURS = { mark: "#ffd600", zero: "#00c8ff", preload: "#9aa0a6", crack: "#ff5252", start: "#7cb342", stop: "#7cb342" };

// The test's points in time order: [{x, y, t}] (net deflection, load, s since the first line),
// from the line that completed its zero on — the report's curve starts there too, so a load
// met only while the zero was being taken is never the page's P1.
function testPoints(id) {
  const pts = [];
  for (let i = 0; i < S.t.length; i++) {
    if (S.testIds[i] === id && !S.zeroing[i] && S.net[i] !== null && S.load[i] !== null) pts.push({ x: S.net[i], y: S.load[i], t: S.t[i] });
  }
  return pts;
}

// P1 as the report finds it (tagdeflect_report::c1609): the first local maximum of the
// smoothed load above 10 % of the maximum after which the smoothed load falls by
// max(3σ_load, 0.5 % of the maximum) before exceeding it; P1 the largest measured load in the
// smoothing window there. The page smooths over 5 points (the report chooses its window from
// the noise) and takes σ_load from the successive differences (MAD): an approximation until
// the report is made, whose P1 replaces it.
function livePeak(pts) {
  if (pts.length < 10) return null;
  const h = 2;
  const sm = pts.map((_, i) => {
    const lo = Math.max(0, i - h), hi = Math.min(pts.length, i + h + 1);
    let s = 0;
    for (let j = lo; j < hi; j++) s += pts[j].y;
    return s / (hi - lo);
  });
  const diffs = pts.slice(1).map((p, i) => Math.abs(p.y - pts[i].y)).sort((a, b) => a - b);
  const sigma = diffs[Math.floor(diffs.length / 2)] / (0.6745 * Math.SQRT2);
  const pmax = Math.max(...pts.map((p) => p.y));
  const drop = Math.max(3 * sigma, 0.005 * Math.abs(pmax));
  let best = -Infinity, k = 0;
  for (let i = 0; i < sm.length; i++) {
    if (sm[i] > best) { best = sm[i]; k = i; }
    else if (best >= 0.1 * pmax && sm[i] <= best - drop) {
      let j = Math.max(0, k - h);
      for (let m = j; m < Math.min(pts.length, k + h + 1); m++) if (pts[m].y > pts[j].y) j = m;
      return pts[j];
    }
  }
  return null;
}

// The point of the curve nearest in time to an event.
function eventPoint(pts, tNs) {
  if (!pts.length || S.t0 === null) return null;
  const t = (tNs - S.t0) / 1e9;
  let best = pts[0];
  for (const p of pts) if (Math.abs(p.t - t) < Math.abs(best.t - t)) best = p;
  return best;
}

// The x range of the live curve: the data's, and up to L/150 while the test's span is known.
function curveXRange(lo, hi) {
  if (lo === null || hi === null || !Number.isFinite(lo) || !Number.isFinite(hi)) return [0, 1];
  if (C.id && C.span) hi = Math.max(hi, 1.05 * C.span / 150);
  if (hi - lo < 1e-6) { lo -= 0.5; hi += 0.5; }
  const pad = 0.03 * (hi - lo);
  return [lo - pad, hi + pad];
}

function testSpan() {
  const m = (T.measured && T.measured.span_mm) || null;
  return m || (F.beam && F.beam.span_mm) || (S.status && S.status.beam && S.status.beam.span_mm) || null;
}

// uPlot's draw hook of the live curve (app.js makeCurve).
function drawCurveMarks(u) {
  const el = $("curve");
  if (!C.id) { el.dataset.marks = 0; return; }
  const pts = testPoints(C.id);
  const ctx = u.ctx, bb = u.bbox, dpr = window.devicePixelRatio || 1;
  ctx.save();
  ctx.font = `${Math.round(13 * dpr)}px system-ui, sans-serif`;
  ctx.lineWidth = dpr;
  const drawn = { lines: [], p1: null, marks: 0 };
  const span = C.span;
  if (span) {
    for (const [label, over] of [["L/600", 600], ["L/150", 150]]) {
      const x = u.valToPos(span / over, "x", true);
      if (!(x >= bb.left && x <= bb.left + bb.width)) continue;
      ctx.strokeStyle = "#b0bec5"; ctx.setLineDash([6 * dpr, 4 * dpr]);
      ctx.beginPath(); ctx.moveTo(x, bb.top); ctx.lineTo(x, bb.top + bb.height); ctx.stroke();
      ctx.setLineDash([]); ctx.fillStyle = "#b0bec5";
      ctx.fillText(`${label} ${fmt(span / over, 3)} mm`, x + 4 * dpr, bb.top + 14 * dpr);
      drawn.lines.push(label);
    }
  }
  const p1 = C.reportP1 || livePeak(pts);
  if (p1) {
    const x = u.valToPos(p1.x, "x", true), y = u.valToPos(p1.y, "y", true);
    ctx.fillStyle = "#ffffff"; ctx.beginPath(); ctx.arc(x, y, 5 * dpr, 0, 2 * Math.PI); ctx.fill();
    ctx.fillText(`P1 ${fmt(p1.y, 2)} kN${C.reportP1 ? " (report)" : ""}`, x + 8 * dpr, y - 8 * dpr);
    drawn.p1 = Number(p1.y.toFixed(3));
  }
  for (const e of C.events) {
    if (!(e.kind in MARK_COLOURS) || e.kind === "start" || e.kind === "stop") continue;
    const p = eventPoint(pts, e.t_ns);
    if (!p) continue;
    const x = u.valToPos(p.x, "x", true), y = u.valToPos(p.y, "y", true);
    ctx.fillStyle = MARK_COLOURS[e.kind];
    ctx.beginPath(); ctx.moveTo(x, y - 4 * dpr); ctx.lineTo(x - 6 * dpr, y - 14 * dpr); ctx.lineTo(x + 6 * dpr, y - 14 * dpr); ctx.fill();
    const text = e.kind === "mark" ? (e.note || "mark") : e.kind;
    ctx.fillText(text.length > 28 ? text.slice(0, 27) + "…" : text, x + 8 * dpr, y - 16 * dpr);
    drawn.marks++;
  }
  ctx.restore();
  el.dataset.lines = drawn.lines.join(" ");
  el.dataset.p1 = drawn.p1 === null ? "" : drawn.p1;
  el.dataset.marks = drawn.marks;
}

// The events of the test, listed under the curve.
function showEvents() {
  const rows = C.events.map((e) => {
    const li = document.createElement("li");
    li.dataset.kind = e.kind;
    const t = S.t0 === null ? "" : `${fmt((e.t_ns - S.t0) / 1e9, 1)} s`;
    li.textContent = `${t} ${e.kind}${e.note ? ": " + e.note : ""}${e.user ? " (" + e.user + ")" : ""}`;
    return li;
  });
  $("t-events").replaceChildren(...rows);
}

// The verification in force (the test's, or the rig's when idle): class, date, id; stale:
// highlighted, with why.
function showVerification(v) {
  const box = $("t-verification");
  if (!v) { box.textContent = "verification: none named"; box.className = "muted"; box.dataset.state = "none"; return; }
  const head = `verification ${v.id.slice(0, 12)} of ${v.date}, class ${v.class_iso9513}, U(k=2) ${fmt(v.u_k2_mm * 1000, 1)} µm, valid until ${v.valid_until}`;
  const stale = Array.isArray(v.stale) && v.stale.length > 0;
  box.textContent = stale ? `${head} — STALE: ${v.stale.join("; ")}` : `${head}: in force`;
  box.className = stale ? "stale" : "muted";
  box.dataset.state = stale ? "stale" : "in-force";
}

TEST_LISTENERS.push((st) => {
  if (st.state === "running") {
    if (C.id !== st.id) { C.id = st.id; C.reportP1 = null; }
    C.events = st.events || [];
  }
  // The verification in force: the running test's, else the rig's now (GET /api/test gives it
  // idle too).
  if (st.state !== "off") {
    C.verification = st.verification || null;
    showVerification(C.verification);
  }
  C.span = testSpan() || C.span;
  showEvents();
  S.dirty = true;
});

// After the stop: the report's P1 and δ1 replace the page's (review.js reads report.json).
function useReportPeak(id, report) {
  if (id !== C.id || !report || !report.P1 || !report.delta1) return;
  C.reportP1 = { x: report.delta1.value, y: report.P1.value };
  S.dirty = true;
}
