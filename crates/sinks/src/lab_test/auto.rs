//! Automatic start and stop of a test (`[output.auto_test]`, off by default; SPEC "Tests").
//!
//! A testing machine's own software starts a test when the load reaches a preload and ends it
//! at the standard's end or when the load has dropped from its peak; this does the same from
//! the feed's lines, as a small deterministic state machine:
//!
//! ```text
//!            load < rearm_load_kn          load ≥ start_load_kn
//!  Disarmed ─────────────────────▶ Armed ─────────────────────▶ start ──▶ Running
//!     ▲                                                                      │ an end reached
//!     └──────── the test has stopped (automatically or by the operator) ◀── Stopping
//! ```
//!
//! - It begins **disarmed**: a beam already under load when the daemon (re)starts does not
//!   start a test; the load must first be seen below `rearm_load_kn` (default half the start
//!   load). After every stop it is disarmed again, so unloading a broken beam starts nothing
//!   and the next specimen starts once it is seated and loaded.
//! - **Start**: the load at or above `start_load_kn` on [`CONFIRM_LINES`] lines in a row. The
//!   test's zero is taken from the next frame sets, at that load — as a testing machine zeroes
//!   its extension at the preload.
//! - **Stop**, for any running test (started automatically or by hand) once its zero has
//!   formed, when one of these holds on [`CONFIRM_LINES`] lines in a row (a single frame set
//!   that lacks a camera and throws the deflection does not end a test):
//!   - ASTM C1609 / C1856: the net deflection (from the test's zero) at or past L/150 +
//!     `end_margin_mm` — the report reads the load at L/150, so the curve must go beyond it;
//!   - EN 14651: the CMOD gauge at or past 4 mm (the report's last value is at 3.5 mm);
//!   - the load below `stop_below_peak_fraction` of the test's peak, once that peak has
//!     passed the start load (0 turns this off).
//!
//!   The standard is the running test's own; `stop_at_end = false` leaves only the load drop.
//! - **No load** (no reply from the testing machine): nothing starts — the page says so —; a
//!   running test still ends at the standard's end.
//!
//! [`AutoTest::step`] takes a line and the running test and says what to do; the caller
//! ([`super::LabTests`]) does it.

use serde::{Deserialize, Serialize};
use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::Problem;

use super::TestMeta;

/// Lines in a row a condition must hold on before it starts or stops a test.
pub const CONFIRM_LINES: u32 = 3;
/// EN 14651's end: the CMOD at which the test may stop, mm.
pub const EN14651_END_CMOD_MM: f64 = 4.0;

/// `[output.auto_test]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AutoTestConfig {
    /// Start a test when the load reaches this, kN (the preload).
    pub start_load_kn: f64,
    /// The load must have been below this before the next automatic start, kN (default: half
    /// of `start_load_kn`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rearm_load_kn: Option<f64>,
    /// The specimen id of an automatically started test (default `auto`; the test's id adds
    /// the UTC start time, so ids stay unique).
    #[serde(default = "default_specimen")]
    pub specimen: String,
    /// The standard of an automatically started test (default: `[report] standard`, if any).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub standard: Option<String>,
    /// The method of an automatically started test (a shipped one or the lab's own in
    /// `<tests>/methods/`): recorded in its `test.json`, its preload waited for, and its
    /// `[end]` (net deflection or CMOD) where the test stops; its standard is the test's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<String>,
    /// Stop at the standard's end (default true).
    #[serde(default = "yes")]
    pub stop_at_end: bool,
    /// ASTM: how far past L/150 the test goes on, mm (default 0.5).
    #[serde(default = "default_margin")]
    pub end_margin_mm: f64,
    /// Stop when the load has fallen below this fraction of the test's peak (default 0.1;
    /// 0 = never).
    #[serde(default = "default_fraction")]
    pub stop_below_peak_fraction: f64,
}

fn default_specimen() -> String {
    "auto".into()
}
fn yes() -> bool {
    true
}
fn default_margin() -> f64 {
    0.5
}
fn default_fraction() -> f64 {
    0.1
}

impl AutoTestConfig {
    /// Checks the table; keys relative to it.
    pub fn validate(&self) -> Result<(), Problem> {
        if !(self.start_load_kn.is_finite() && self.start_load_kn > 0.0) {
            return Err(Problem::new("start_load_kn", format!("{}: a positive load in kN", self.start_load_kn)));
        }
        let rearm = self.rearm_kn();
        if !(rearm.is_finite() && rearm >= 0.0 && rearm < self.start_load_kn) {
            return Err(Problem::new(
                "rearm_load_kn",
                format!("{rearm}: a load from 0 to below start_load_kn ({} kN)", self.start_load_kn),
            ));
        }
        TestMeta { specimen: self.specimen.clone(), standard: self.standard.clone(), ..TestMeta::default() }.validate()?;
        if !(self.end_margin_mm.is_finite() && (0.0..=50.0).contains(&self.end_margin_mm)) {
            return Err(Problem::new("end_margin_mm", format!("{}: from 0 to 50 mm", self.end_margin_mm)));
        }
        if !(self.stop_below_peak_fraction.is_finite() && (0.0..1.0).contains(&self.stop_below_peak_fraction)) {
            return Err(Problem::new("stop_below_peak_fraction", format!("{}: from 0 (never) to below 1", self.stop_below_peak_fraction)));
        }
        Ok(())
    }

    /// The re-arm load, kN.
    pub fn rearm_kn(&self) -> f64 {
        self.rearm_load_kn.unwrap_or(0.5 * self.start_load_kn)
    }
}

/// The rules in force: the table and what the rest of the config tells about the ends.
#[derive(Debug, Clone, PartialEq)]
pub struct AutoRules {
    /// `[output.auto_test]`.
    pub config: AutoTestConfig,
    /// The standard of automatically started tests (the table's, else `[report]`'s).
    pub standard: Option<String>,
    /// The beam's span, mm (`[specimen.beam]`): C1609's end is L/150.
    pub span_mm: Option<f64>,
    /// The CMOD gauge (EN 14651's end).
    pub cmod_gauge: Option<String>,
    /// The method of `[output.auto_test] method`, found when the config was read, and what a
    /// test records of it.
    pub method: Option<(tagdeflect_core::method::Method, tagdeflect_core::method::MethodRef)>,
}

/// What a test ends at, by its standard (the gauge's name borrowed from the rules: nothing
/// is allocated per line).
#[derive(Debug, Clone, Copy, PartialEq)]
enum End<'a> {
    /// Net deflection at or past this, mm.
    Net(f64),
    /// This gauge at or past this, mm.
    Gauge(&'a str, f64),
}

impl AutoRules {
    /// The end of a test with `standard` (none when there is none, or it cannot be known).
    fn end(&self, standard: Option<&str>) -> Option<End<'_>> {
        if !self.config.stop_at_end {
            return None;
        }
        if let Some(m) = self.method.as_ref().map(|l| &l.0).filter(|m| Some(m.standard.as_str()) == standard) {
            let at = m.end.at_mm.or(m.end.at_span_over.zip(self.span_mm).map(|(n, l)| l / n))?;
            return match m.end.gauge.as_str() {
                "cmod" => self.cmod_gauge.as_deref().map(|g| End::Gauge(g, at)),
                _ => Some(End::Net(at + self.config.end_margin_mm)),
            };
        }
        match standard? {
            "astm-c1609" | "astm-c1856" => self.span_mm.map(|l| End::Net(l / 150.0 + self.config.end_margin_mm)),
            "en-14651" => self.cmod_gauge.as_deref().map(|g| End::Gauge(g, EN14651_END_CMOD_MM)),
            _ => None,
        }
    }
}

impl AutoRules {
    /// The net deflection's end as the stop's note names it: `L/150`, or the method's.
    fn end_name(&self) -> String {
        match self.method.as_ref().map(|l| &l.0) {
            Some(m) => match m.end.at_span_over {
                Some(n) => format!("L/{n} of method {}", m.name),
                None => format!("the end of method {}", m.name),
            },
            None => "L/150".into(),
        }
    }

    /// What an automatically started test records of its method, the preload it waits for and
    /// whether it records its frames.
    pub(super) fn method_of_start(&self) -> Option<(tagdeflect_core::method::MethodRef, Option<f64>, Option<bool>)> {
        self.method.as_ref().map(|(m, r)| (r.clone(), m.preload_kn, m.record_frames))
    }
}

/// What the caller is to do.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// Start a test with this.
    Start(TestMeta, String),
    /// Stop the running test; the note says why.
    Stop(String),
}

#[derive(Debug, Clone, PartialEq)]
enum State {
    Disarmed,
    Armed,
    Running { peak_kn: Option<f64> },
    Stopping(String),
}

/// The machine of the module doc.
#[derive(Debug, Clone)]
pub struct AutoTest {
    rules: AutoRules,
    state: State,
    /// Lines in a row the current condition has held on.
    streak: u32,
    /// The newest line's load, kN.
    load_kn: Option<f64>,
    /// The running test's standard, and its newest net deflection and CMOD.
    standard: Option<String>,
    net_mm: Option<f64>,
    cmod_mm: Option<f64>,
    zero_formed: bool,
}

/// The running test as the machine sees it.
#[derive(Debug, Clone, Copy)]
pub struct RunningTest<'a> {
    /// Its standard.
    pub standard: Option<&'a str>,
    /// Its zero has formed (values count from it).
    pub zero_formed: bool,
}

impl AutoTest {
    /// Disarmed (see the module doc).
    pub fn new(rules: AutoRules) -> AutoTest {
        AutoTest {
            rules,
            state: State::Disarmed,
            streak: 0,
            load_kn: None,
            standard: None,
            net_mm: None,
            cmod_mm: None,
            zero_formed: false,
        }
    }

    /// The rules in force.
    pub fn rules(&self) -> &AutoRules {
        &self.rules
    }

    fn set(&mut self, s: State) {
        if self.state != s {
            self.state = s;
            self.streak = 0;
        }
    }

    /// One feed line: before a start (`running` none: the line's load) or of the running test
    /// (its values counted from the test's zero).
    pub fn step(&mut self, line: &FeedLine, running: Option<RunningTest<'_>>) -> Option<Action> {
        self.load_kn = line.load_kn.filter(|l| l.is_finite());
        // The numbers only (this runs for every feed line: no allocation).
        let c = &self.rules.config;
        let (start_kn, rearm_kn, margin_mm, fraction) = (c.start_load_kn, c.rearm_kn(), c.end_margin_mm, c.stop_below_peak_fraction);
        let Some(test) = running else {
            if matches!(self.state, State::Running { .. } | State::Stopping(_)) {
                // The test stopped (ours or the operator's): wait for the unloading.
                self.set(State::Disarmed);
            }
            let load = self.load_kn?;
            match self.state {
                State::Disarmed if load < rearm_kn => self.set(State::Armed),
                State::Armed if load >= start_kn => {
                    self.streak += 1;
                    if self.streak >= CONFIRM_LINES {
                        let meta = TestMeta {
                            specimen: self.rules.config.specimen.clone(),
                            standard: self.rules.standard.clone(),
                            ..TestMeta::default()
                        };
                        let why = format!("auto: the load reached {load:.2} kN (start at {start_kn:.2} kN)");
                        self.set(State::Running { peak_kn: Some(load) });
                        return Some(Action::Start(meta, why));
                    }
                }
                State::Armed => self.streak = 0,
                _ => {}
            }
            return None;
        };
        if matches!(self.state, State::Disarmed | State::Armed) {
            // A test started by the operator.
            self.set(State::Running { peak_kn: None });
        }
        self.standard = test.standard.map(str::to_string);
        self.zero_formed = test.zero_formed;
        let end = self.rules.end(test.standard);
        self.net_mm = line.net_deflection_mm;
        self.cmod_mm = match &end {
            Some(End::Gauge(g, _)) => line.gauges.get(*g).map(|r| r.value),
            _ => None,
        };
        let State::Running { peak_kn } = &mut self.state else { return None };
        if let Some(l) = self.load_kn {
            *peak_kn = Some(peak_kn.map_or(l, |p| p.max(l)));
        }
        let peak = *peak_kn;
        if !test.zero_formed {
            self.streak = 0;
            return None;
        }
        let mut why = match &end {
            Some(End::Net(at)) => self
                .net_mm
                .filter(|v| v >= at)
                .map(|v| format!("net deflection {v:.3} mm reached the end {at:.3} mm ({} + {margin_mm:.2} mm)", self.rules.end_name())),
            Some(End::Gauge(g, at)) => self.cmod_mm.filter(|v| v >= at).map(|v| format!("{g} {v:.3} mm reached EN 14651's end {at:.1} mm")),
            None => None,
        };
        if why.is_none() && fraction > 0.0 {
            if let (Some(p), Some(l)) = (peak, self.load_kn) {
                if p >= start_kn && l < fraction * p {
                    why = Some(format!("the load {l:.2} kN fell below {:.0} % of the peak {p:.2} kN", 100.0 * fraction));
                }
            }
        }
        match why {
            Some(w) => {
                self.streak += 1;
                if self.streak >= CONFIRM_LINES {
                    let note = format!("auto: {w}");
                    self.set(State::Stopping(note.clone()));
                    return Some(Action::Stop(note));
                }
            }
            None => self.streak = 0,
        }
        None
    }

    /// What it waits for, for `GET /api/test` and the page.
    pub fn status(&self) -> serde_json::Value {
        let c = &self.rules.config;
        let now = |v: Option<f64>, unit: &str, digits: usize| match v {
            Some(v) => format!("now {v:.digits$} {unit}"),
            None => "no value now".into(),
        };
        let (state, waiting) = match &self.state {
            State::Disarmed if self.load_kn.is_none() => {
                ("disarmed", "a load from the testing machine (none now): nothing starts without it".to_string())
            }
            State::Disarmed => (
                "disarmed",
                format!("the load to fall below {:.2} kN before the next automatic start ({})", c.rearm_kn(), now(self.load_kn, "kN", 2)),
            ),
            State::Armed if self.load_kn.is_none() => {
                ("armed", format!("the load to reach {:.2} kN — but no load comes from the testing machine now", c.start_load_kn))
            }
            State::Armed => {
                ("armed", format!("the load to reach {:.2} kN to start a test ({})", c.start_load_kn, now(self.load_kn, "kN", 2)))
            }
            State::Running { .. } if !self.zero_formed => ("running", "the test's zero to form".to_string()),
            State::Running { peak_kn } => {
                let mut ends = Vec::new();
                match self.rules.end(self.standard.as_deref()) {
                    Some(End::Net(at)) => ends.push(format!("net deflection {at:.3} mm ({})", now(self.net_mm, "mm", 3))),
                    Some(End::Gauge(g, at)) => ends.push(format!("{g} {at:.1} mm ({})", now(self.cmod_mm, "mm", 3))),
                    None => {}
                }
                if c.stop_below_peak_fraction > 0.0 {
                    match peak_kn {
                        Some(p) if *p >= c.start_load_kn => ends.push(format!(
                            "the load below {:.2} kN ({:.0} % of the peak {p:.2} kN; {})",
                            c.stop_below_peak_fraction * p,
                            100.0 * c.stop_below_peak_fraction,
                            now(self.load_kn, "kN", 2)
                        )),
                        _ => ends.push(format!(
                            "the load to pass {:.2} kN, then to fall below {:.0} % of its peak",
                            c.start_load_kn,
                            100.0 * c.stop_below_peak_fraction
                        )),
                    }
                }
                if ends.is_empty() {
                    ("running", "the operator's stop (no automatic end for this test)".to_string())
                } else {
                    ("running", ends.join(", or "))
                }
            }
            State::Stopping(why) => ("stopping", format!("the stop to complete ({why})")),
        };
        serde_json::json!({
            "state": state,
            "waiting_for": waiting,
            "start_load_kn": c.start_load_kn,
            "rearm_load_kn": c.rearm_kn(),
            "load_kn": self.load_kn,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tagdeflect_core::feed::GaugeReading;

    fn rules(standard: Option<&str>) -> AutoRules {
        AutoRules {
            config: AutoTestConfig {
                start_load_kn: 2.0,
                rearm_load_kn: None,
                specimen: "auto".into(),
                standard: None,
                method: None,
                stop_at_end: true,
                end_margin_mm: 0.5,
                stop_below_peak_fraction: 0.1,
            },
            standard: standard.map(str::to_string),
            span_mm: Some(450.0),
            cmod_gauge: Some("cmod".into()),
            method: None,
        }
    }

    fn line(load: Option<f64>, net: Option<f64>, cmod: Option<f64>) -> FeedLine {
        let mut l = FeedLine { load_kn: load, net_deflection_mm: net, ..FeedLine::default() };
        if let Some(c) = cmod {
            l.gauges.insert("cmod".into(), GaugeReading::new(c, 0.002, "mm"));
        }
        l
    }

    /// Drives the machine over `(load, net, cmod)` lines, starting and stopping tests as told;
    /// returns what it did, by line index.
    fn drive(a: &mut AutoTest, lines: &[(Option<f64>, Option<f64>, Option<f64>)], zero_after: usize) -> Vec<(usize, Action)> {
        let mut out = Vec::new();
        let mut running: Option<(Option<String>, usize)> = None;
        for (k, (load, net, cmod)) in lines.iter().enumerate() {
            let l = line(*load, *net, *cmod);
            let rt = running.as_ref().map(|(s, since)| RunningTest { standard: s.as_deref(), zero_formed: k - since >= zero_after });
            match a.step(&l, rt) {
                Some(Action::Start(meta, why)) => {
                    running = Some((meta.standard.clone(), k + 1));
                    out.push((k, Action::Start(meta, why)));
                }
                Some(Action::Stop(why)) => {
                    running = None;
                    out.push((k, Action::Stop(why)));
                }
                None => {}
            }
        }
        out
    }

    #[test]
    fn a_loaded_beam_at_start_waits_for_the_unloading_and_a_test_ends_at_l_over_150() {
        let mut a = AutoTest::new(rules(Some("astm-c1609")));
        // The daemon starts with a beam under 5 kN: nothing until the load has been below 1 kN.
        let mut lines = vec![(Some(5.0), None, None); 5];
        lines.extend([(Some(0.5), None, None); 3]);
        // Loading: 1.0, 1.5, ... kN; the net deflection (from the test's zero) grows by 0.1 mm a line.
        for k in 0..60 {
            let net = if k >= 3 { Some(0.1 * (k - 3) as f64) } else { None };
            lines.push((Some(1.0 + 0.5 * k as f64), net, None));
        }
        let acts = drive(&mut a, &lines, 5);
        // 2.0 kN at k = 2 → lines 10, 11, 12 at or past it: start on the third.
        let Action::Start(meta, why) = &acts[0].1 else { panic!("{acts:?}") };
        assert_eq!(acts[0].0, 8 + 4, "{acts:?}");
        assert_eq!(meta.specimen, "auto");
        assert_eq!(meta.standard.as_deref(), Some("astm-c1609"));
        assert!(why.contains("2.00 kN"), "{why}");
        // L/150 + 0.5 = 3.5 mm: net 3.5 at k = 38 (line 46), confirmed on line 48.
        let Action::Stop(why) = &acts[1].1 else { panic!("{acts:?}") };
        assert_eq!(acts[1].0, 8 + 38 + 2, "{acts:?}");
        assert!(why.starts_with("auto: net deflection") && why.contains("L/150"), "{why}");
        assert_eq!(acts.len(), 2, "disarmed after the stop: the load is still high: {acts:?}");
    }

    #[test]
    fn a_method_s_end_stops_the_test_there() {
        use tagdeflect_core::method::{library, Method, SHIPPED};
        let with = |text: &str| {
            let m = Method::parse(text).unwrap();
            let r = tagdeflect_core::method::MethodRef {
                name: m.name.clone(),
                version: m.version,
                standard: m.standard.clone(),
                sha256: library::sha256_hex(text.as_bytes()),
                review: None,
            };
            AutoRules { method: Some((m, r)), ..rules(Some("astm-c1609")) }
        };
        let mut lines = vec![(Some(0.0), None, None); 2];
        for k in 0..60 {
            lines.push((Some(3.0), Some(0.1 * k as f64), None));
        }
        // C1609-19: L/150 = 3 mm (+ 0.5): net 3.5 on the 36th line of the test, confirmed two later.
        let acts = drive(&mut AutoTest::new(with(SHIPPED[0].1)), &lines, 0);
        let Action::Stop(why) = &acts[1].1 else { panic!("{acts:?}") };
        assert!(why.contains("reached the end 3.500 mm (L/150 of method C1609-19 + 0.50 mm)"), "{why}");
        // A lab's method ending at L/300: the test stops at 1.5 + 0.5 mm.
        let l300 = SHIPPED[0].1.replace("at_span_over = 150.0", "at_span_over = 300.0");
        let acts = drive(&mut AutoTest::new(with(&l300)), &lines, 0);
        let Action::Stop(why) = &acts[1].1 else { panic!("{acts:?}") };
        assert!(why.contains("reached the end 2.000 mm (L/300 of method C1609-19 + 0.50 mm)"), "{why}");
    }

    #[test]
    fn one_thrown_set_does_not_end_a_test_and_the_load_drop_does() {
        let mut a = AutoTest::new(rules(Some("astm-c1609")));
        let mut lines = vec![(Some(0.0), None, None); 2];
        lines.extend([(Some(3.0), Some(0.0), None); 3]); // start on the third
        lines.extend([(Some(10.0), Some(0.5), None); 6]);
        // One thrown set (9 mm, past L/150) and one load glitch: no stop.
        lines.push((Some(10.0), Some(9.0), None));
        lines.push((Some(0.1), Some(0.5), None));
        lines.extend([(Some(20.0), Some(1.0), None); 3]);
        // The beam breaks: 20 → 1.5 kN (below 10 % of 20 = 2 kN) on three lines.
        lines.extend([(Some(1.5), Some(2.0), None); 3]);
        // Unloaded, then the next specimen.
        lines.extend([(Some(0.5), None, None); 2]);
        lines.extend([(Some(2.5), Some(0.0), None); 3]);
        let acts = drive(&mut a, &lines, 2);
        let kinds: Vec<(usize, &str)> =
            acts.iter().map(|(k, a)| (*k, if matches!(a, Action::Start(..)) { "start" } else { "stop" })).collect();
        assert_eq!(kinds, [(4, "start"), (18, "stop"), (23, "start")], "{acts:?}");
        let Action::Stop(why) = &acts[1].1 else { unreachable!() };
        assert!(why.contains("below 10 % of the peak 20.00 kN"), "{why}");
    }

    #[test]
    fn en_14651_ends_at_a_cmod_of_4_mm_and_no_load_starts_nothing() {
        let mut a = AutoTest::new(rules(Some("en-14651")));
        let mut lines = vec![(None, None, None); 4];
        assert!(drive(&mut a, &lines, 1).is_empty());
        assert!(a.status()["waiting_for"].as_str().unwrap().contains("nothing starts without it"), "{}", a.status());
        lines.extend([(Some(0.0), None, None); 2]);
        lines.extend([(Some(5.0), Some(0.0), Some(0.0)); 3]);
        for k in 0..50 {
            // The load softens past its peak but stays above 10 %; the CMOD opens 0.1 mm a line.
            lines.push((Some(12.0 - 0.1 * k as f64), Some(0.05 * k as f64), Some(0.1 * k as f64)));
        }
        let mut a = AutoTest::new(rules(Some("en-14651")));
        let acts = drive(&mut a, &lines, 2);
        assert!(matches!(&acts[0], (8, Action::Start(..))), "{acts:?}");
        let Action::Stop(why) = &acts[1].1 else { panic!("{acts:?}") };
        // CMOD 4.0 at k = 40 (line 49), confirmed on line 51.
        assert_eq!(acts[1].0, 9 + 40 + 2, "{acts:?}");
        assert!(why.starts_with("auto: cmod 4.200 mm reached EN 14651's end 4.0 mm"), "{why}");
    }

    #[test]
    fn a_test_started_by_hand_is_stopped_by_the_rules_and_the_page_is_told_what_they_wait_for() {
        let mut a = AutoTest::new(rules(None));
        let running = RunningTest { standard: Some("astm-c1609"), zero_formed: true };
        assert_eq!(a.step(&line(Some(0.3), Some(0.0), None), Some(running)), None);
        let st = a.status();
        assert_eq!(st["state"], "running");
        let w = st["waiting_for"].as_str().unwrap();
        assert!(w.contains("net deflection 3.500 mm (now 0.000 mm)") && w.contains("the load to pass 2.00 kN"), "{w}");
        for _ in 0..2 {
            assert_eq!(a.step(&line(Some(8.0), Some(3.6), None), Some(running)), None);
        }
        assert!(matches!(a.step(&line(Some(8.0), Some(3.6), None), Some(running)), Some(Action::Stop(_))));
        assert_eq!(a.status()["state"], "stopping");
        // The stop went through: disarmed until the load is below 1 kN.
        assert_eq!(a.step(&line(Some(8.0), None, None), None), None);
        assert!(a.status()["waiting_for"].as_str().unwrap().contains("fall below 1.00 kN"), "{}", a.status());
        assert_eq!(a.step(&line(Some(0.2), None, None), None), None);
        assert!(a.status()["waiting_for"].as_str().unwrap().contains("reach 2.00 kN"), "{}", a.status());
    }

    #[test]
    fn the_table_is_checked_key_by_key() {
        let good = rules(None).config;
        assert!(good.validate().is_ok());
        let bad = |f: &dyn Fn(&mut AutoTestConfig)| {
            let mut c = good.clone();
            f(&mut c);
            c.validate().unwrap_err().key
        };
        assert_eq!(bad(&|c| c.start_load_kn = 0.0), "start_load_kn");
        assert_eq!(bad(&|c| c.rearm_load_kn = Some(2.0)), "rearm_load_kn");
        assert_eq!(bad(&|c| c.specimen = "a/b".into()), "specimen");
        assert_eq!(bad(&|c| c.standard = Some("iso-1".into())), "standard");
        assert_eq!(bad(&|c| c.end_margin_mm = f64::NAN), "end_margin_mm");
        assert_eq!(bad(&|c| c.stop_below_peak_fraction = 1.0), "stop_below_peak_fraction");
    }
}
