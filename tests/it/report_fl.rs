//! EN 14651's F_L against its truth on a noisy CMOD gauge: the report's F_L and σ through
//! the library (the feed's curve put on the UTM's samples, as `report` does), over many
//! simulated climbs per gauge σ.

use rand::SeedableRng;
use tagdeflect_report::{en14651, BeamConfig};

/// A notched beam's elastic climb: 200 kN per mm of CMOD up to the crack at CMOD 0.08 mm
/// (16 kN), then 12 kN softening. F_L (the largest load in CMOD 0–0.05 mm) is 10 kN.
fn elastic_notch(x: f64) -> f64 {
    if x <= 0.08 {
        200.0 * x.max(0.0)
    } else {
        12.0 - 2.0 * (x - 0.08)
    }
}
const F_L_TRUTH_KN: f64 = 10.0;

/// One climb: 2 s at rest, then the CMOD at 1.2 mm/min read by a gauge of σ `sx` at 10 Hz,
/// the load by a UTM at 100 Hz (`common::simulated_utm_curve`). `Err` is F_L's reason when it
/// was not determined.
fn fl_of_one_climb(rng: &mut rand_chacha::ChaCha8Rng, sx: f64) -> Result<(f64, f64), String> {
    let x_at = |t: f64| (t - 2.0).max(0.0) / 60.0 * 1.2;
    let curve = crate::common::simulated_utm_curve(rng, &elastic_notch, &x_at, 32.0, sx, "CMOD");
    let beam = BeamConfig { width_mm: 150.0, depth_mm: 150.0, span_mm: 500.0, notch_mm: Some(25.0), ..Default::default() };
    let e = en14651::compute(&curve, &beam);
    let fl = e.iter().find(|e| e.key == "FL").unwrap();
    fl.result.as_ref().map(|q| (q.value, q.sigma)).map_err(|e| e.clone())
}

/// Per gauge σ (0.003 mm, a camera gauge on large images, to 0.06 mm, more than the
/// interval itself), 120 climbs: of the F_L determined, ~95 % within 2σ of the truth and at
/// most 90 % within 1σ (the σ not inflated); gauges to 0.01 mm always determine it, 0.02 mm
/// nearly always, the
/// 0.06 mm gauge (0.027 mm smoothed: more than a quarter of the interval) leaves it
/// undetermined with its reason rather than a confident wrong value.
#[test]
fn f_l_is_within_its_sigma_of_the_truth_on_a_noisy_cmod_gauge() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(14651);
    let trials = 120;
    for sx in [0.003, 0.01, 0.02, 0.06] {
        let (mut w1, mut w2, mut got, mut sum_sigma, mut sum_err) = (0, 0, 0, 0.0, 0.0);
        let mut reasons = Vec::new();
        for _ in 0..trials {
            match fl_of_one_climb(&mut rng, sx) {
                Ok((v, s)) => {
                    let e = v - F_L_TRUTH_KN;
                    got += 1;
                    w1 += usize::from(e.abs() <= s);
                    w2 += usize::from(e.abs() <= 2.0 * s);
                    sum_sigma += s;
                    sum_err += e;
                }
                Err(why) => reasons.push(why),
            }
        }
        let pct = |k: usize| 100.0 * k as f64 / got.max(1) as f64;
        println!(
            "REPORT F_L on a CMOD gauge of σ {sx} mm: {got} of {trials} determined, {:.1} % within 2σ, {:.1} % within 1σ, \
             mean σ {:.2} kN, mean error {:+.2} kN; undetermined e.g. {:?}",
            pct(w2),
            pct(w1),
            sum_sigma / got.max(1) as f64,
            sum_err / got.max(1) as f64,
            reasons.first()
        );
        if sx <= 0.01 {
            assert_eq!(got, trials, "gauge σ {sx}: {reasons:?}");
        } else if sx <= 0.02 {
            // Smoothed σ ≈ 0.009 mm: the rate over the readings within 0.025 mm of 0.05 mm is
            // at times not 2σ from zero (measured 8 of 120): undetermined, said so.
            assert!(got * 10 >= trials * 9, "gauge σ {sx}: {got} of {trials} determined: {reasons:?}");
        } else {
            // Smoothed over 5 lines, σ ≈ 0.027 mm: more than a quarter of the interval.
            assert!(reasons.len() * 10 >= trials * 8, "gauge σ {sx}: only {} of {trials} undetermined", reasons.len());
            assert!(reasons.iter().all(|r| r.contains("CMOD")), "{reasons:?}");
        }
        if got >= 30 {
            // Binomial 2σ of 120 trials at 95 %: ±4 %.
            assert!(pct(w2) >= 90.0, "gauge σ {sx}: {:.1} % within 2σ", pct(w2));
            assert!(pct(w1) <= 90.0, "gauge σ {sx}: {:.1} % within 1σ — σ too large", pct(w1));
        }
    }
}
