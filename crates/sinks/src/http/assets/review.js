"use strict";
// After a stop and for review (docs/live-page.md): the verdict of the last test's report
// (valid, or invalid with the report's reasons, or why no report was made) with links to the
// report's HTML and PDF (GET /reports/ID/FILE); the user the token names (GET /api/user);
// sign-off (POST /api/test/sign: the reviewer is the token's user, the meaning typed),
// re-analysis with its reason (POST /api/test/reanalyse) and the audit trail of the test
// (GET /api/audit?test=ID, with the chain's state). Text only through textContent.
const R = { id: null, folder: null, user: null, retries: 0 };

function reviewMessage(text, bad) { const m = $("r-message"); m.textContent = text; m.className = bad ? "bad" : "muted"; }

function link(href, text) {
  const a = document.createElement("a");
  a.href = href; a.textContent = text; a.target = "_blank"; a.rel = "noopener";
  return a;
}

// The verdict of test `id`: its report.json read back, or the stop's report_error.
async function showVerdict(id, reportError) {
  const box = $("t-verdict");
  box.dataset.test = id;
  if (reportError) {
    box.dataset.verdict = "no-report";
    box.className = "verdict bad";
    box.replaceChildren(`${id}: no report — ${reportError}`);
    return;
  }
  const base = `/reports/${encodeURIComponent(id)}/`;
  let report = null, files = [];
  try {
    // Which report files there are first: a test without a standard has none (no 404 asked for).
    const i = await fetch(base.slice(0, -1), { cache: "no-store" });
    files = i.ok ? (await i.json()).files || [] : [];
    const r = files.includes("report.json") ? await fetch(base + "report.json", { cache: "no-store" }) : null;
    if (r && r.ok) report = await r.json();
  } catch (e) { /* no report: said below */ }
  if (!report) {
    box.dataset.verdict = "none";
    box.className = "verdict muted";
    box.replaceChildren(`${id}: no report (no standard named)`);
    return;
  }
  useReportPeak(id, report);
  const valid = report.valid === true;
  box.dataset.verdict = valid ? "valid" : "invalid";
  box.className = "verdict " + (valid ? "ok" : "bad");
  const head = document.createElement("div");
  head.className = "head";
  head.textContent = `${id}: ${valid ? "VALID" : "INVALID"} — ${report.standard_title || report.standard}`;
  const reasons = document.createElement("ul");
  reasons.id = "t-verdict-reasons";
  for (const why of report.invalid_reasons || []) { const li = document.createElement("li"); li.textContent = why; reasons.append(li); }
  const res = ["P1", "f1", "f600", "f150", "T150", "fR1", "fR3"].filter((k) => report[k] && typeof report[k].value === "number")
    .map((k) => `${k} ${fmt(report[k].value, 3)} ${report[k].unit || ""}`.trim()).join(" · ");
  const results = document.createElement("div");
  results.textContent = res;
  const links = document.createElement("div");
  links.id = "t-report-links";
  const outputs = Object.keys(report.outputs || {});
  links.append("report: ", link(base + "report.html", "HTML"));
  if (outputs.includes("report.pdf") || files.includes("report.pdf")) links.append(" · ", link(base + "report.pdf", "PDF"));
  links.append(" · ", link(base + "report.json", "JSON"));
  box.replaceChildren(head, reasons, results, links);
}

// Who the token names (asked only once a token is kept: the page never prompts for it here).
async function whoAmI() {
  if (!sessionStorage.getItem("tagdeflect-token")) { R.user = null; $("r-user").textContent = "no token given yet"; return; }
  const a = await authed("/api/user");
  R.user = a.ok ? a.body : null;
  $("r-user").textContent = a.ok ? `${a.body.user} (${a.body.role})` : "token refused";
}

async function showAudit() {
  const id = T.id || R.id;
  if (!id) { reviewMessage("no test to show the trail of", true); return; }
  const a = await authed("/api/audit?test=" + encodeURIComponent(id));
  if (!a.ok) { reviewMessage(`audit trail refused (${a.status}): ${a.body.error || ""}`, true); return; }
  const ch = a.body.chain || {};
  const chain = $("r-chain");
  chain.textContent = ch.ok ? `chain whole: ${ch.entries} entries, last ${String(ch.last_sha256 || "").slice(0, 12)}…` : `CHAIN BROKEN at line ${ch.line}: ${ch.error}`;
  chain.className = ch.ok ? "muted" : "bad";
  chain.dataset.ok = ch.ok ? "true" : "false";
  const rows = (a.body.entries || []).map((e) => {
    const tr = document.createElement("tr");
    tr.dataset.action = e.action;
    const detail = e.detail ? Object.entries(e.detail).filter(([, v]) => v !== null && typeof v !== "object")
      .map(([k, v]) => `${k}: ${String(v).length > 24 ? String(v).slice(0, 23) + "…" : v}`).join(", ") : "";
    for (const text of [e.seq, new Date(e.t_ns / 1e6).toISOString().replace("T", " ").slice(0, 19), e.user, e.role, e.action, detail]) {
      const td = document.createElement("td"); td.textContent = String(text); tr.append(td);
    }
    return tr;
  });
  $("r-audit").tBodies[0].replaceChildren(...rows);
  $("r-audit").dataset.entries = rows.length;
}

async function review(cmd, body) {
  const a = await authed("/api/test/" + cmd, { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
  await whoAmI();
  if (!a.ok) { reviewMessage(`${cmd} refused (${a.status}): ${a.body.error || ""}`, true); return null; }
  return a.body;
}

$("b-sign").addEventListener("click", async () => {
  const meaning = $("r-meaning").value.trim();
  if (!R.id || !meaning) { reviewMessage("sign: a stopped test and the meaning of the signature are needed", true); return; }
  const s = await review("sign", { test: R.id, meaning });
  if (s) reviewMessage(`signed by ${s.by} (${s.role}): "${s.meaning}", report.json ${String(s.report_json_sha256).slice(0, 12)}…, audit line ${s.audit_seq}`, false);
  await showAudit();
});
$("b-reanalyse").addEventListener("click", async () => {
  const reason = $("r-reason").value.trim();
  if (!R.id || !reason) { reviewMessage("re-analysis: a stopped test and the reason are needed", true); return; }
  const a = await review("reanalyse", { test: R.id, reason });
  if (a) { reviewMessage(`re-analysed: ${reason}`, false); await showVerdict(R.id, null); }
  await showAudit();
});
$("b-audit").addEventListener("click", showAudit);
$("b-user").addEventListener("click", async () => {
  sessionStorage.removeItem("tagdeflect-token");
  token();
  await whoAmI();
});
$("b-crack").addEventListener("click", async () => {
  const v = parseFloat($("f-crack").value);
  if (!Number.isFinite(v)) { testMessage("crack: type its position from mid-span, mm", true); return; }
  const a = await authed("/api/test/crack", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ position_mm: v }) });
  if (!a.ok) { testMessage(`crack refused (${a.status}): ${a.body.error || ""}`, true); return; }
  testMessage(`crack entered at ${v} mm from mid-span`, false);
  $("f-crack").value = "";
  await pollTest();
});

// The last stopped test: its verdict, once per stop (also a stop made elsewhere: the CLI, auto).
TEST_LISTENERS.push((st) => {
  $("b-crack").disabled = st.state !== "running";
  const last = st.state === "idle" && st.last ? st.last : null;
  // A report still being written when first asked for is asked for again (a few polls).
  if (last && last.id === R.id && $("t-verdict").dataset.verdict === "none" && R.retries > 0) { R.retries--; showVerdict(last.id, last.report_error); }
  if (!last || last.id === R.id) return;
  R.retries = 5;
  R.id = last.id;
  R.folder = last.folder;
  $("r-test").textContent = last.id;
  showVerdict(last.id, last.report_error);
  if (sessionStorage.getItem("tagdeflect-token")) { whoAmI(); showAudit(); }
});
