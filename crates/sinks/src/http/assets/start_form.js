"use strict";
// The start form's method and specimen (docs/methods.md): the methods and the config's beam
// from GET /api/methods, the specimen table's next untested row from GET /api/specimens; the
// chosen method's standard taken and its required dimensions shown (missing ones named); the
// rate window from the method's phases and the test's own span (measured, the specimen's row,
// else [specimen.beam]). Text only through textContent.
const F = { methods: [], beam: {}, next: null, table: [], specimenTouched: false };
const DIMS = ["width_mm", "depth_mm", "span_mm", "notch_mm"];
function methodNamed(name) { return F.methods.find((m) => m.name === name); }
// The window of the test's controlled quantity: the test's method, else the shipped method of
// its standard; undefined while the span it needs is not known.
function methodWindow(standard, method, measured) {
  const m = (method && methodNamed(method.name)) || F.methods.find((x) => x.standard === standard && x.origin === "built-in");
  if (!m || !Array.isArray(m.phase)) return undefined;
  const dims = Object.assign({}, F.beam, measured || {});
  const depth = dims.depth_mm;
  const phases = m.phase.filter((p) => !p.for_depth_mm || depth === undefined || (depth >= p.for_depth_mm[0] && depth <= p.for_depth_mm[1]));
  if (!phases.length) return undefined;
  const first = phases[0];
  let split = first.until_mm;
  if (split === undefined && first.until_span_over) {
    if (!dims.span_mm) return undefined;
    split = dims.span_mm / first.until_span_over;
  }
  if (split === undefined) split = Infinity;
  return { split_mm: split, below_mm_per_min: first.rate_mm_per_min, above_mm_per_min: (phases[1] || first).rate_mm_per_min };
}
function formRow() {
  const id = $("f-specimen").value.trim();
  return F.table.find((r) => r.id === (id === "next" ? F.next : id));
}
function typed() {
  const out = {};
  for (const [id, key] of [["f-width", "width_mm"], ["f-depth", "depth_mm"], ["f-span", "span_mm"], ["f-notch", "notch_mm"]]) {
    const v = parseFloat($(id).value);
    if (Number.isFinite(v) && v > 0) out[key] = v;
  }
  return out;
}
// What the chosen method (or standard) needs, and which of it nothing gives yet.
function showRequires() {
  const m = methodNamed($("f-method").value);
  if (m) $("f-standard").value = m.standard;
  $("f-standard").disabled = !!m;
  const std = $("f-standard").value;
  const requires = m ? m.requires : std ? DIMS.filter((k) => k !== "notch_mm" || std === "en-14651") : [];
  const row = formRow();
  const have = Object.assign({}, F.beam, row ? row.means : {}, typed());
  const missing = requires.filter((k) => !(k in have));
  $("l-notch").hidden = !requires.includes("notch_mm");
  const box = $("f-requires");
  box.textContent = !requires.length ? "" : `${m ? m.name + " v" + m.version + (m.review ? ", reviewed by " + m.review.by : ", not reviewed") : std} needs ${requires.join(", ")}`
    + (missing.length ? ` — missing: ${missing.join(", ")}` : " — all given");
  box.className = missing.length ? "warn" : "muted";
  $("f-next").textContent = F.next ? `next from the table: ${F.next}` + (row ? ` (${row.id}${row.cast_date ? ", cast " + row.cast_date : ""})` : "") : "";
}
async function loadMethods() {
  try {
    const r = await fetch("/api/methods", { cache: "no-store" });
    if (!r.ok) return;
    const a = await r.json();
    F.methods = (a.methods || []).filter((m) => !m.error);
    F.beam = a.beam_mm || {};
    const sel = $("f-method");
    const keep = sel.value;
    const none = document.createElement("option"); none.value = ""; none.textContent = "none";
    sel.replaceChildren(none, ...F.methods.map((m) => { const o = document.createElement("option"); o.value = m.name; o.textContent = m.name; return o; }));
    sel.value = keep;
    showRequires();
  } catch (e) { /* the status poll reports a lost server */ }
}
async function loadSpecimens() {
  try {
    const r = await fetch("/api/specimens", { cache: "no-store" });
    if (!r.ok) return;
    const a = await r.json();
    F.table = a.specimens || [];
    F.next = a.next || null;
    // "next" is filled in only while the operator has not touched the field: a refresh that
    // wrote into a field being cleared or typed in would glue "next" to what is typed.
    if (F.next && !F.specimenTouched && !$("f-specimen").value) $("f-specimen").value = "next";
    showRequires();
    if (typeof renderSpecimenTable === "function") renderSpecimenTable();
  } catch (e) { /* as above */ }
}
// The stop's body: the crack entry typed beside the stop button, if any.
function stopBody() {
  const v = parseFloat($("f-crack").value);
  return Number.isFinite(v) ? { crack: { position_mm: v } } : {};
}
for (const ev of ["focus", "input"]) $("f-specimen").addEventListener(ev, () => { F.specimenTouched = true; });
for (const id of ["f-method", "f-standard", "f-specimen", "f-width", "f-depth", "f-span", "f-notch"]) {
  $(id).addEventListener("input", showRequires);
  $(id).addEventListener("change", showRequires);
}
loadMethods();
loadSpecimens();
setInterval(loadSpecimens, 5000);
