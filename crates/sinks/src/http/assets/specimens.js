"use strict";
// The specimen table on the page (docs/methods.md "Specimens"): a CSV chosen from a file or
// pasted, POSTed to /api/specimens with the token (a refused table's "row N, column C" shown,
// nothing imported), and the table as GET /api/specimens answers it (start_form.js polls it):
// each row's means, cast date and age, mix, fibre, client, and the test that took it.
// Text only through textContent.
function specimenMessage(text, bad) { const m = $("s-message"); m.textContent = text; m.className = bad ? "bad" : "muted"; }

$("s-file").addEventListener("change", () => {
  const f = $("s-file").files[0];
  if (!f) return;
  if (f.size > 256 * 1024) { specimenMessage(`${f.name}: a table of at most 256 KiB`, true); return; }
  const reader = new FileReader();
  reader.onload = () => { $("s-csv").value = String(reader.result); specimenMessage(`${f.name} read: press import`, false); };
  reader.readAsText(f);
});

$("b-import").addEventListener("click", async () => {
  const text = $("s-csv").value;
  if (!text.trim()) { specimenMessage("choose a CSV file or paste the table first", true); return; }
  const a = await authed("/api/specimens", { method: "POST", headers: { "Content-Type": "text/csv" }, body: text });
  if (!a.ok) { specimenMessage(`import refused (${a.status}): ${a.body.error || ""}`, true); return; }
  specimenMessage(`imported ${a.body.imported} specimen${a.body.imported === 1 ? "" : "s"}; next: ${a.body.next || "none"}`, false);
  await loadSpecimens();
});

const SPECIMEN_COLUMNS = [
  ["id", (r) => r.id],
  ["width mm", (r) => r.means && r.means.width_mm !== undefined ? fmt(r.means.width_mm, 1) : ""],
  ["depth mm", (r) => r.means && r.means.depth_mm !== undefined ? fmt(r.means.depth_mm, 1) : ""],
  ["span mm", (r) => r.means && r.means.span_mm !== undefined ? fmt(r.means.span_mm, 0) : ""],
  ["notch mm", (r) => r.means && r.means.notch_mm !== undefined ? fmt(r.means.notch_mm, 1) : ""],
  ["cast", (r) => r.cast_date || ""],
  ["age d", (r) => r.age_days ?? ""],
  ["mix", (r) => r.mix || ""],
  ["fibre", (r) => [r.fibre, r.dosage_kg_m3 !== undefined && r.dosage_kg_m3 !== null ? r.dosage_kg_m3 + " kg/m³" : ""].filter(Boolean).join(", ")],
  ["client / project", (r) => [r.client, r.project].filter(Boolean).join(" / ")],
  ["tested", (r) => r.tested ? r.test : (r.id === F.next ? "next" : "not yet")],
];

// Called by start_form.js each time it has read the table.
function renderSpecimenTable() {
  const table = $("s-table");
  const head = document.createElement("tr");
  for (const [name] of SPECIMEN_COLUMNS) { const th = document.createElement("th"); th.textContent = name; head.append(th); }
  table.tHead.replaceChildren(head);
  table.tBodies[0].replaceChildren(...F.table.map((r) => {
    const tr = document.createElement("tr");
    tr.dataset.specimen = r.id;
    tr.dataset.tested = r.tested ? "true" : "false";
    for (const [, cell] of SPECIMEN_COLUMNS) { const td = document.createElement("td"); td.textContent = String(cell(r)); tr.append(td); }
    return tr;
  }));
  $("s-count").textContent = F.table.length ? `(${F.table.filter((r) => r.tested).length} of ${F.table.length} tested)` : "(none entered)";
}
