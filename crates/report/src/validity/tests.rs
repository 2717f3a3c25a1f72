//! The validity rules on synthetic curves. Each rule on a hand-made test: one fault at a time, the sentence asserted exactly, and
//! the fault just inside the rule's tolerance passing.

use super::*;
use crate::config::Response;
use tagdeflect_core::feed::FeedLine;

const T0: i64 = 1_767_225_600_000_000_000;
/// σ of every deflection (CMOD) reading, mm.
const SIGMA: f64 = 0.002;
/// Time between feed lines, s.
const DT: f64 = 0.5;

fn c1609_beam() -> BeamConfig {
    BeamConfig { width_mm: 150.0, depth_mm: 150.0, span_mm: 450.0, ..Default::default() }
}

fn en_beam() -> BeamConfig {
    BeamConfig { width_mm: 150.0, depth_mm: 150.0, span_mm: 500.0, notch_mm: Some(25.0), ..Default::default() }
}

/// Elastic to 40 kN at 0.05 mm, a drop to 30 kN, softening to 20 kN at 0.5 mm, 10 kN at 5 mm.
fn softening(x: f64) -> f64 {
    if x <= 0.05 {
        800.0 * x
    } else if x <= 0.5 {
        30.0 - 10.0 * (x - 0.05) / 0.45
    } else {
        20.0 - 10.0 * (x - 0.5) / 4.5
    }
}

/// Against CMOD: elastic to 16 kN at 0.03 mm, a drop to 12 kN, then down to 8 kN at 4 mm.
fn notched(x: f64) -> f64 {
    if x <= 0.03 {
        16.0 / 0.03 * x
    } else {
        12.0 - 4.0 * (x - 0.03) / 3.97
    }
}

/// `x` every `DT` s: 5 s at rest, then `rate` mm/min (`rate2` beyond CMOD 0.1 mm) to `x_end`.
fn ramp(rate: f64, rate2: Option<f64>, x_end: f64) -> Vec<f64> {
    let mut xs = vec![0.0; 10];
    let mut x: f64 = 0.0;
    while x < x_end - 1e-9 {
        let r = match rate2 {
            Some(r2) if x >= 0.1 - 1e-12 => r2,
            _ => rate,
        };
        x = (x + r / 60.0 * DT).min(x_end);
        xs.push(x);
    }
    xs
}

/// The C1609 test at 0.08 mm/min to 3.2 mm (L/150 = 3 mm).
fn c1609_x() -> Vec<f64> {
    ramp(0.08, None, 3.2)
}

/// The EN 14651 test at 0.05 then 0.2 mm/min to CMOD 3.6 mm.
fn en_x() -> Vec<f64> {
    ramp(0.05, Some(0.2), 3.6)
}

/// A test as the check sees it: times (s from the first line), x, load.
struct Case {
    standard: Standard,
    beam: BeamConfig,
    t_s: Vec<f64>,
    x: Vec<f64>,
    load: Vec<f64>,
    utm_gaps: Vec<(f64, f64)>,
    utm_outages_s: f64,
    max_gap_s: f64,
    method: Option<tagdeflect_core::method::Method>,
    /// Each point's σ of x, mm.
    x_sigma: f64,
}

impl Case {
    fn new(standard: Standard, x: Vec<f64>) -> Case {
        let law = if standard == Standard::En14651 { notched } else { softening };
        let load = x.iter().map(|&v| law(v)).collect();
        let beam = if standard == Standard::En14651 { en_beam() } else { c1609_beam() };
        let t_s = (0..x.len()).map(|k| k as f64 * DT).collect();
        Case { standard, beam, t_s, x, load, utm_gaps: Vec::new(), utm_outages_s: 0.0, max_gap_s: 2.0, method: None, x_sigma: SIGMA }
    }

    /// Drops the lines with `from < t < to`.
    fn without(mut self, from: f64, to: f64) -> Case {
        let keep: Vec<bool> = self.t_s.iter().map(|&t| !(t > from && t < to)).collect();
        let pick = |v: &[f64]| v.iter().zip(&keep).filter(|(_, k)| **k).map(|(v, _)| *v).collect::<Vec<f64>>();
        (self.t_s, self.x, self.load) = (pick(&self.t_s), pick(&self.x), pick(&self.load));
        self
    }

    fn check(&self) -> Validity {
        let n = self.t_s.len();
        let t_ns: Vec<i64> = self.t_s.iter().map(|t| T0 + (t * 1e9).round() as i64).collect();
        // No smoothing: the sentences' numbers are the readings'.
        let curve = Curve::new(t_ns.clone(), self.load.clone(), self.x.clone(), vec![Some(self.x_sigma); n], 0.0, 1, 0.0, "x").unwrap();
        let lines: Vec<FeedLine> =
            t_ns.iter().enumerate().map(|(k, &t_ns)| FeedLine { seq: k as u64, t_ns, ..Default::default() }).collect();
        let feed = Feed::from_lines(std::path::Path::new("feed.jsonl"), &lines).unwrap();
        let x_name = if self.standard == Standard::En14651 { "CMOD" } else { "net deflection" };
        check(&Input {
            standard: self.standard,
            response: Response::Softening,
            beam: &self.beam,
            feed_curve: &curve,
            load_curve: &curve,
            feed: &feed,
            x_name,
            max_gap_s: self.max_gap_s,
            utm_gaps: self.utm_gaps.clone(),
            utm_outages_s: self.utm_outages_s,
            method: self.method.as_ref(),
        })
    }
}

/// The reasons of a verdict that must be invalid.
fn reasons(v: &Validity) -> Vec<String> {
    assert!(!v.valid, "must be invalid");
    v.reasons.clone()
}

fn assert_valid(what: &str, v: &Validity) {
    assert!(v.valid && v.reasons.is_empty(), "{what}: {:?}", v.reasons);
}

#[test]
fn the_clean_tests_the_faults_are_made_from_are_valid() {
    for (standard, x) in [(Standard::AstmC1609, c1609_x()), (Standard::AstmC1856, c1609_x()), (Standard::En14651, en_x())] {
        let v = Case::new(standard, x).check();
        assert_valid(standard.id(), &v);
        assert_eq!(v.rates.len(), 2, "{}: both phases' rates measured", standard.id());
    }
}

/// An unloading (load cycles): the deflection goes back by 0.3 mm after L/150.
#[test]
fn a_deflection_that_goes_back_is_not_monotonic_loading() {
    let with_dip = |depths: &[f64]| {
        let x = c1609_x();
        let i0 = x.iter().position(|&v| v >= 3.1 - 1e-9).unwrap();
        let top = x[i0];
        let mut y = x[..=i0].to_vec();
        y.extend(depths.iter().map(|d| top - d));
        y.extend_from_slice(&x[i0 + 1..]);
        (Case::new(Standard::AstmC1609, y), i0)
    };
    // Down 0.3 mm in six steps, up again in five.
    let depths: Vec<f64> = (1..=6).map(|j| 0.05 * j as f64).chain((1..=5).rev().map(|j| 0.05 * j as f64)).collect();
    let (case, i0) = with_dip(&depths);
    let t = (i0 + 6) as f64 * DT;
    assert_eq!(
        reasons(&case.check()),
        [format!(
            "The net deflection went back by 0.300 mm (from 3.100 mm to 2.800 mm, {t:.1} s into the feed): the loading was not \
             monotonic (load cycles or an unloading); the standard loads continuously."
        )]
    );
    // One reading back by 6 σ is a fault, by 4 σ (the readings' scatter) is not.
    let (case, i0) = with_dip(&[6.0 * SIGMA]);
    let t = (i0 + 1) as f64 * DT;
    assert_eq!(
        reasons(&case.check()),
        [format!(
            "The net deflection went back by 0.012 mm (from 3.100 mm to 3.088 mm, {t:.1} s into the feed): the loading was not \
             monotonic (load cycles or an unloading); the standard loads continuously."
        )]
    );
    assert_valid("back by 4 σ", &with_dip(&[4.0 * SIGMA]).0.check());
}

/// A load cell not zeroed: the load starts at 3 kN (7 % of the 43 kN peak); 2 kN (4.7 %,
/// within 5 % of the peak) passes.
#[test]
fn a_load_not_starting_near_zero_is_named() {
    let offset = |dp: f64| {
        let mut c = Case::new(Standard::AstmC1609, c1609_x());
        c.load.iter_mut().for_each(|p| *p += dp);
        c.check()
    };
    assert_eq!(
        reasons(&offset(3.0)),
        ["The load was already 3.00 kN at the first point (7 % of the peak load): the test was not recorded from its start, \
          or the load cell was not zeroed."]
    );
    assert_valid("2 kN at the start", &offset(2.0));
    // EN 14651 the same way (peak 16 kN: 1.5 kN is 9 %).
    let mut c = Case::new(Standard::En14651, en_x());
    c.load.iter_mut().for_each(|p| *p += 1.5);
    assert_eq!(
        reasons(&c.check()),
        ["The load was already 1.50 kN at the first point (9 % of the peak load): the test was not recorded from its start, \
          or the load cell was not zeroed."]
    );
}

/// A deflection not zeroed (0.2 mm at the first line), and a feed that starts mid-test
/// (at 0.5 mm, 20 kN): the deflection and the load are named.
#[test]
fn a_test_not_recorded_from_its_start_is_named() {
    let mut c = Case::new(Standard::AstmC1609, c1609_x());
    c.x.iter_mut().for_each(|x| *x += 0.2);
    assert_eq!(
        reasons(&c.check()),
        ["The net deflection was already 0.200 mm at the first line: the test was not recorded from its start."]
    );
    // Within 5 σ + 1 % of L/150 (0.04 mm) of zero: valid.
    let mut c = Case::new(Standard::AstmC1609, c1609_x());
    c.x.iter_mut().for_each(|x| *x += 0.03);
    assert_valid("0.03 mm at the start", &c.check());
    // Started at 0.5 mm.
    let x: Vec<f64> = c1609_x().into_iter().skip_while(|&x| x < 0.5 - 1e-9).collect();
    let r = reasons(&Case::new(Standard::AstmC1609, x).check());
    assert!(
        r.contains(&"The net deflection was already 0.500 mm at the first line: the test was not recorded from its start.".to_string()),
        "{r:?}"
    );
    assert!(
        r.contains(
            &"The load was already 20.00 kN at the first point (100 % of the peak load): the test was not recorded from its start, \
              or the load cell was not zeroed."
                .to_string()
        ),
        "{r:?}"
    );
}

/// Stopped before L/150 (C1609, C1856) or CMOD 3.5 mm (EN 14651).
#[test]
fn a_test_stopped_before_its_end_reached_only() {
    let x: Vec<f64> = c1609_x().into_iter().take_while(|&x| x <= 2.5 + 1e-9).collect();
    assert_eq!(
        reasons(&Case::new(Standard::AstmC1609, x.clone()).check()),
        ["The net deflection reached only 2.500 mm: ASTM C1609 needs the test carried to L/150 = 3.00 mm."]
    );
    assert_eq!(
        reasons(&Case::new(Standard::AstmC1856, x).check()),
        ["The net deflection reached only 2.500 mm: ASTM C1856 (its flexural test, ASTM C1609) needs the test carried to L/150 = 3.00 mm."]
    );
    let x: Vec<f64> = en_x().into_iter().take_while(|&x| x <= 3.0 + 1e-9).collect();
    assert_eq!(
        reasons(&Case::new(Standard::En14651, x).check()),
        ["The CMOD reached only 3.000 mm: EN 14651 needs the test carried to CMOD = 3.5 mm."]
    );
    // Just past the end: valid.
    let x: Vec<f64> = en_x().into_iter().take_while(|&x| x <= 3.51).collect();
    assert_valid("CMOD to 3.51 mm", &Case::new(Standard::En14651, x).check());
}

/// Lines missing for 3.5 s, UTM samples missing, the UTM unreachable.
#[test]
fn gaps_and_outages_in_the_feed_and_the_utm_stream_are_named() {
    let base = || Case::new(Standard::AstmC1609, c1609_x());
    assert_eq!(
        reasons(&base().without(1000.0, 1003.5).check()),
        ["The feed has 1 gap(s) longer than 2 s without a line (the longest 3.5 s, from 1000.0 s to 1003.5 s into the feed): \
          the curve is not measured there."]
    );
    assert_eq!(
        reasons(&base().without(1000.0, 1003.5).without(1500.0, 1505.0).check()),
        ["The feed has 2 gap(s) longer than 2 s without a line (the longest 5.0 s, from 1500.0 s to 1505.0 s into the feed): \
          the curve is not measured there."]
    );
    // 1.5 s without a line is within max_gap_s (2 s); 3.5 s is within a max_gap_s of 5 s.
    assert_valid("a 1.5 s gap", &base().without(1000.0, 1001.5).check());
    let mut c = base().without(1000.0, 1003.5);
    c.max_gap_s = 5.0;
    assert_valid("a 3.5 s gap, max_gap_s 5", &c.check());

    let mut c = base();
    c.utm_gaps = vec![(100.0, 104.5), (2000.0, 2002.5)];
    assert_eq!(
        reasons(&c.check()),
        ["The UTM stream has 2 gap(s) longer than 2 s (the longest 4.5 s, from 100.0 s to 104.5 s into the feed): the load is not \
          known there."]
    );
    let mut c = base();
    c.utm_outages_s = 3.0;
    assert_eq!(reasons(&c.check()), ["The UTM was unreachable for 3.0 s during the test: the load is not known then."]);
    // All at once: each named once, in the order of the rules.
    let mut c = base().without(1000.0, 1003.5);
    c.utm_gaps = vec![(100.0, 104.5)];
    c.utm_outages_s = 3.0;
    let r = reasons(&c.check());
    assert_eq!(r.len(), 3, "{r:?}");
    assert!(
        r[0].starts_with("The feed has 1 gap(s)")
            && r[1].starts_with("The UTM stream has 1 gap(s)")
            && r[2].starts_with("The UTM was unreachable")
    );
}

fn shipped(name: &str) -> tagdeflect_core::method::Method {
    let text = tagdeflect_core::method::SHIPPED.iter().find(|m| m.0 == name).unwrap().1;
    tagdeflect_core::method::Method::parse(text).unwrap()
}

#[test]
fn a_test_too_fast_for_its_method_is_invalid_naming_the_phase_and_the_rate() {
    let with = |x: Vec<f64>| Case { method: Some(shipped("C1609-19")), ..Case::new(Standard::AstmC1609, x) }.check();
    let v = with(c1609_x());
    assert_valid("C1609-19 at 0.08 mm/min", &v);
    assert_eq!(v.rates.len(), 2, "the method's two phases for a 150 mm deep beam: {:?}", v.rates);
    assert!(v.rates[0].0.contains("up to L/900 (deeper beams)") && v.rates[0].2 == (0.035, 0.10), "{:?}", v.rates);
    let r = reasons(&with(ramp(0.2, None, 3.2)));
    assert_eq!(
        r,
        vec!["The net deflection increased at 0.200 mm/min in phase \"up to L/900 (deeper beams)\" of method C1609-19; \
             the method asks for 0.035 to 0.1 mm/min."
            .to_string()]
    );
}

#[test]
fn a_test_stopped_before_its_method_s_end_says_it_ended_early() {
    let with = |x: Vec<f64>| Case { method: Some(shipped("EN14651-05")), ..Case::new(Standard::En14651, x) }.check();
    // Carried to CMOD 3.6 mm: enough for the standard's f_R,4 at 3.5 mm, not for the method's 4 mm.
    let r = reasons(&with(en_x()));
    assert_eq!(r, vec!["The CMOD reached only 3.600 mm: the test ended early; method EN14651-05 ends at CMOD = 4 mm.".to_string()]);
    let v = with(ramp(0.05, Some(0.2), 4.1));
    assert_valid("EN14651-05 to CMOD 4.1 mm", &v);
    assert!(v.rates[1].0.contains("from CMOD 0.1 mm to the end"), "{:?}", v.rates);
}

/// A rate outside its window by less than 2 σ of the fitted rate (a gauge whose noise is as
/// large as the phase itself) cannot make the test invalid, nor pass it: it is unchecked,
/// saying so; with the gauge's σ small the same rate is a reason.
#[test]
fn a_rate_the_gauges_noise_cannot_tell_from_its_window_is_unchecked_not_a_reason() {
    let slow = ramp(0.03, Some(0.2), 3.6);
    let r = reasons(&Case::new(Standard::En14651, slow.clone()).check());
    assert_eq!(r, vec!["The CMOD increased at 0.030 mm/min up to CMOD = 0.1 mm; the standard asks for 0.04 to 0.06 mm/min.".to_string()]);
    let v = Case { x_sigma: 0.1, ..Case::new(Standard::En14651, slow) }.check();
    assert_valid("the first phase's rate within 2 σ of its window", &v);
    let said = v.unchecked.iter().find(|u| u.contains("could not be told from its window")).unwrap_or_else(|| panic!("{:?}", v.unchecked));
    assert!(said.contains("0.030 ±") && said.contains("0.04 to 0.06 mm/min") && said.contains("σ 0.100 mm a point"), "{said}");
}

/// EN 14651: a CMOD gauge too noisy to tell where the CMOD passes 0.05 mm (its σ over a
/// quarter of the interval) leaves F_L undetermined; the test is then *unchecked* on that
/// criterion, saying why, and not invalid — the same curve read by a fine gauge is valid with
/// no such sentence.
#[test]
fn an_undetermined_f_l_leaves_the_test_unchecked_on_it_not_invalid() {
    let fine = Case::new(Standard::En14651, en_x()).check();
    assert_valid("the notched test on a fine gauge", &fine);
    assert!(!fine.unchecked.iter().any(|u| u.contains("F_L")), "a fine gauge determines F_L: {:?}", fine.unchecked);

    let v = Case { x_sigma: 0.02, ..Case::new(Standard::En14651, en_x()) }.check();
    assert_valid("the notched test on a gauge of σ 0.02 mm", &v);
    let said = v.unchecked.iter().find(|u| u.starts_with("F_L could not be determined:")).unwrap_or_else(|| panic!("{:?}", v.unchecked));
    assert!(said.contains("the CMOD's σ (0.020 mm) is too large for the interval 0 to 0.05 mm") && said.contains("clip gauge"), "{said}");
    assert!(!v.reasons.iter().any(|r| r.contains("F_L")), "{:?}", v.reasons);
}
