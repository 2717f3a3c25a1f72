//! The course of the simulated test: the midspan deflection over time, the beam's
//! deformation at a deflection, and the UTM's readings (load law, stroke, outage).

use tagdeflect_io::utm::UtmSample;

use super::law::{self, BeamMotion};
use super::SimRig;

impl SimRig {
    /// Midspan deflection (mm, positive downward) at `t_ns`: zero for `rest_frames` frame
    /// sets, then a linear ramp reaching `max_deflection_mm` `hold_frames` sets before the
    /// last (held after it, or repeated down and up again with `cyclic`), its first
    /// `seat_frames` sets a slow seating to `seat_mm` when set; a step at set
    /// `rest_frames` (half a frame period before it) when no set is left for the ramp.
    ///
    /// In a verification run (`verify_steps`) it is the rigid bar's drop instead: each step's
    /// position held for an equal share of the frame sets, moved half a frame period before
    /// the step's first set.
    pub fn midspan_deflection(&self, t_ns: i64) -> f64 {
        let p = &self.params;
        if !self.verify_steps_mm.is_empty() {
            return self.verify_step_at(t_ns).map_or(0.0, |i| self.verify_steps_mm[i]);
        }
        let s = (t_ns - p.start_ns) as f64 * 1e-9;
        let period = 1.0 / p.fps;
        let rest = p.rest_frames as f64 * period;
        if !self.rate_phases.is_empty() {
            return at_rates(&self.rate_phases, s - rest);
        }
        let ramp = (p.frame_sets as f64 - 1.0 - p.rest_frames as f64 - p.hold_frames as f64).max(0.0) * period;
        let max = p.max_deflection_mm;
        if ramp <= 0.0 {
            // Half a period before set `rest_frames`: no frame's jitter straddles the step.
            return if s >= rest - 0.5 * period { max } else { 0.0 };
        }
        if !p.cyclic {
            return self.loaded_for((s - rest).clamp(0.0, ramp), ramp);
        }
        let cycle = rest + 2.0 * ramp;
        let u = s.rem_euclid(cycle);
        if u < rest {
            0.0
        } else if u < rest + ramp {
            self.loaded_for(u - rest, ramp)
        } else {
            // Unloaded as it was loaded, the seating last.
            self.loaded_for(rest + 2.0 * ramp - u, ramp)
        }
    }

    /// The midspan deflection `u` s into a loading of `ramp` s to `max_deflection_mm`: the
    /// seating first (`seat_mm` over `seat_frames` sets, when set), then the ramp.
    fn loaded_for(&self, u: f64, ramp: f64) -> f64 {
        let p = &self.params;
        let seat = (p.seat_frames as f64 / p.fps).min(ramp);
        if seat <= 0.0 {
            return self.ramp_from(0.0, u, ramp);
        }
        if u < seat {
            return u / seat * p.seat_mm;
        }
        let rest_of = ramp - seat;
        if rest_of <= 0.0 {
            return p.seat_mm;
        }
        self.ramp_from(p.seat_mm, u - seat, rest_of)
    }

    /// The ramp from `start` mm to `max_deflection_mm` over `time` s, `u` s into it: linear,
    /// or up to `slow_to_mm` at a quarter of the rate of the rest (see `SimParams::slow_to_mm`).
    fn ramp_from(&self, start: f64, u: f64, time: f64) -> f64 {
        let (max, slow) = (self.params.max_deflection_mm, self.params.slow_to_mm);
        if slow <= start {
            return start + u / time * (max - start);
        }
        let rate = (4.0 * (slow - start) + (max - slow)) / time;
        let slow_s = 4.0 * (slow - start) / rate;
        if u < slow_s {
            start + 0.25 * rate * u
        } else {
            slow + rate * (u - slow_s)
        }
    }

    /// The time (s after the rest) at which a test loaded at rates (`rates`) reaches its last
    /// phase's end (then held); `None` for the ramp.
    pub fn rates_end_s(&self) -> Option<f64> {
        let mut t = 0.0;
        let mut from = 0.0;
        for &(rate, until) in &self.rate_phases {
            t += (until - from).max(0.0) / rate * 60.0;
            from = until;
        }
        (!self.rate_phases.is_empty()).then_some(t)
    }

    /// The beam's deformation at midspan deflection `d` (mm); in a verification run, the
    /// rigid bar moved down by `d`.
    pub(crate) fn motion_at(&self, d: f64) -> BeamMotion {
        if self.verify_steps_mm.is_empty() {
            BeamMotion::new(&self.params, &self.beam, d)
        } else {
            BeamMotion::rigid(&self.params, &self.beam, d)
        }
    }

    /// The first frame set of verification step `i` (of `n`).
    fn verify_step_start(&self, i: usize) -> u64 {
        let n = self.verify_steps_mm.len() as u64;
        i as u64 * self.params.frame_sets as u64 / n
    }

    /// The verification step held at `t_ns` (by frame set, changing half a period before
    /// the step's first set); `None` outside a verification run.
    pub(crate) fn verify_step_at(&self, t_ns: i64) -> Option<usize> {
        let half = 0.5e9 / self.params.fps;
        (0..self.verify_steps_mm.len()).rev().find(|&i| i == 0 || t_ns as f64 >= self.set_time_ns(self.verify_step_start(i)) as f64 - half)
    }

    /// The steps of a verification run with their windows `[start, end)` in ns (the moves
    /// half a frame period before each step's first set); empty for a test.
    pub fn verify_windows(&self) -> Vec<(f64, i64, i64)> {
        let half = (0.5e9 / self.params.fps).round() as i64;
        let n = self.verify_steps_mm.len();
        let edge = |i: usize| {
            if i == n {
                self.set_time_ns(self.params.frame_sets as u64 - 1) + half
            } else {
                self.set_time_ns(self.verify_step_start(i)) - half
            }
        };
        (0..n).map(|i| (self.verify_steps_mm[i], edge(i), edge(i + 1))).collect()
    }

    /// The UTM's reading at true time `t_ns`: load = the load law at the midspan deflection
    /// (elastic: stiffness × deflection, see the `law` module); stroke = the deflection under the
    /// loading points + machine compliance × load.
    pub fn utm_sample(&self, t_ns: i64) -> UtmSample {
        let d = self.midspan_deflection(t_ns);
        if !self.verify_steps_mm.is_empty() {
            // The crosshead carries the rigid bar: no load, the stroke is the bar's drop.
            return UtmSample { t_ns, load_kn: 0.0, stroke_mm: Some(d) };
        }
        let load = law::load_at(&self.params, d);
        let under_load = self.beam.deflection(0.5 * self.beam.load_span, d);
        UtmSample { t_ns, load_kn: load, stroke_mm: Some(under_load + self.params.compliance_mm_per_kn * load) }
    }

    /// UTM samples at `utm_hz` (with `utm_phase_ms` against the frame clock) covering the
    /// recording from 0.25 s (+ the clock offset) before the first frame set to 0.25 s (+ the
    /// offset) after the last, stamped on the UTM's clock (`utm_clock_offset_ms` ahead).
    pub(crate) fn utm_samples(&self) -> Vec<UtmSample> {
        let p = &self.params;
        let dt = 1e9 / p.utm_hz;
        let margin = 250_000_000 + (p.utm_clock_offset_ms.abs() * 1e6).round() as i64;
        let t_first = p.start_ns - margin;
        let t_last = self.set_time_ns(p.frame_sets as u64 - 1) + margin;
        let phase = p.utm_phase_ms * 1e6;
        let j0 = ((t_first - p.start_ns) as f64 - phase) / dt;
        let j1 = ((t_last - p.start_ns) as f64 - phase) / dt;
        let outage = self.utm_outage();
        let offset_ns = (p.utm_clock_offset_ms * 1e6).round() as i64;
        (j0.ceil() as i64..=j1.floor() as i64)
            .map(|j| p.start_ns + (phase + j as f64 * dt).round() as i64)
            .filter(|t| outage.is_none_or(|(a, b)| *t < a || *t >= b))
            // Stamped on the UTM's clock: taken at true time `stamp - offset`.
            .map(|stamp| UtmSample { t_ns: stamp, ..self.utm_sample(stamp - offset_ns) })
            .collect()
    }

    /// The simulated UTM outage (`utm_outage_at_s`, `utm_outage_s`) as [start, end) in ns
    /// since the Unix epoch, when one is set.
    pub(crate) fn utm_outage(&self) -> Option<(i64, i64)> {
        let p = &self.params;
        p.utm_outage_at_s.map(|a| {
            let start = p.start_ns + (a * 1e9) as i64;
            (start, start + (p.utm_outage_s * 1e9) as i64)
        })
    }
}

/// The deflection `s` seconds after the rest of a test loaded at `phases` (mm/min, until mm):
/// each phase's rate up to its end, held at the last end.
fn at_rates(phases: &[(f64, f64)], mut s: f64) -> f64 {
    let mut d = 0.0;
    for &(rate, until) in phases {
        if s <= 0.0 {
            break;
        }
        let need = (until - d).max(0.0) / rate * 60.0;
        if s < need {
            return d + rate / 60.0 * s;
        }
        s -= need;
        d = until.max(d);
    }
    d
}

#[cfg(test)]
mod tests {
    use crate::params::SimParams;
    use crate::SimRig;

    fn deflections(p: SimParams) -> Vec<f64> {
        let rig = SimRig::new(&p).unwrap();
        (0..p.frame_sets as u64).map(|k| rig.midspan_deflection(rig.set_time_ns(k))).collect()
    }

    #[test]
    fn the_ramp_can_end_early_and_hold_or_be_a_step() {
        let base =
            SimParams { cameras: 1, width: 320, height: 240, frame_sets: 11, fps: 10.0, max_deflection_mm: 1.0, ..SimParams::default() };
        // Rest 2, ramp over 8 periods to set 10.
        let d = deflections(SimParams { rest_frames: 2, ..base.clone() });
        assert!(d[2].abs() < 1e-9 && (d[10] - 1.0).abs() < 1e-9, "{d:?}");
        assert!((d[6] - 0.5).abs() < 1e-9, "{d:?}");
        // Rest 2, hold 4: the ramp reaches 1.0 at set 6 and holds.
        let d = deflections(SimParams { rest_frames: 2, hold_frames: 4, ..base.clone() });
        assert!((d[4] - 0.5).abs() < 1e-9, "{d:?}");
        assert!(d[6..].iter().all(|&v| (v - 1.0).abs() < 1e-9), "{d:?}");
        // Rest 4, hold 6: no set left for a ramp — a step at set 4.
        let d = deflections(SimParams { rest_frames: 4, hold_frames: 6, ..base.clone() });
        assert!(d[..4].iter().all(|&v| v == 0.0) && d[4..].iter().all(|&v| v == 1.0), "{d:?}");
        assert!(SimParams { hold_frames: 1, cyclic: true, ..base }.validate().unwrap_err().to_string().contains("hold_frames"));
    }

    #[test]
    fn a_seated_cycle_approaches_slowly_by_frame_sets_then_ramps_and_unloads_the_same_way() {
        let base = SimParams {
            cameras: 1,
            width: 320,
            height: 240,
            frame_sets: 21,
            fps: 10.0,
            rest_frames: 2,
            max_deflection_mm: 1.0,
            seat_frames: 8,
            seat_mm: 0.04,
            cyclic: true,
            ..SimParams::default()
        };
        let rig = SimRig::new(&base).unwrap();
        // 18 sets of loading: 8 seating (0.005 mm a set), then 10 up to 1.0 mm (0.096 a set).
        let d: Vec<f64> = (0..40u64).map(|k| rig.midspan_deflection(rig.set_time_ns(k))).collect();
        assert!(d[2].abs() < 1e-9 && (d[6] - 0.02).abs() < 1e-9 && (d[10] - 0.04).abs() < 1e-9, "{d:?}");
        assert!((d[15] - 0.52).abs() < 1e-9 && (d[20] - 1.0).abs() < 1e-9, "{d:?}");
        // Unloaded the same way: the seating's slow part last, then the next rest.
        assert!((d[30] - 0.04).abs() < 1e-9 && (d[34] - 0.02).abs() < 1e-9 && d[38].abs() < 1e-9, "{d:?}");
        let bad = SimParams { seat_mm: 2.0, ..base.clone() }.validate().unwrap_err().to_string();
        assert!(bad.contains("seat_mm"), "{bad}");
        assert!(SimParams { seat_frames: 0, ..base }.validate().unwrap_err().to_string().contains("seat_mm"));
    }

    #[test]
    fn a_slow_first_part_of_the_ramp_goes_at_a_quarter_of_the_rate_in_the_same_time() {
        let base = SimParams {
            cameras: 1,
            width: 320,
            height: 240,
            frame_sets: 21,
            fps: 10.0,
            rest_frames: 2,
            max_deflection_mm: 1.0,
            seat_frames: 8,
            seat_mm: 0.04,
            slow_to_mm: 0.16,
            ..SimParams::default()
        };
        let rig = SimRig::new(&base).unwrap();
        // 1.0 s after the seating: 0.12 mm at r/4, 0.84 mm at r: r = (4·0.12 + 0.84)/1.0 =
        // 1.32 mm/s; the slow part 0.33 mm/s for 0.363 636 s.
        let d: Vec<f64> = (0..21u64).map(|k| rig.midspan_deflection(rig.set_time_ns(k))).collect();
        assert!((d[10] - 0.04).abs() < 1e-9 && (d[12] - 0.106).abs() < 1e-9 && (d[13] - 0.139).abs() < 1e-9, "{d:?}");
        assert!((d[16] - (0.16 + 1.32 * (0.6 - 0.48 / 1.32))).abs() < 1e-9 && (d[20] - 1.0).abs() < 1e-9, "{d:?}");
        for bad_mm in [0.02, 1.0, -0.1] {
            let bad = SimParams { slow_to_mm: bad_mm, ..base.clone() }.validate().unwrap_err().to_string();
            assert!(bad.contains("slow_to_mm"), "{bad}");
        }
    }

    #[test]
    fn a_test_at_rates_follows_each_phase_s_rate_and_holds_at_the_end() {
        let p = SimParams {
            cameras: 1,
            width: 320,
            height: 240,
            frame_sets: 600,
            fps: 1.0,
            rest_frames: 5,
            max_deflection_mm: 1.0,
            rates: "0.06:0.3,0.3".into(),
            ..SimParams::default()
        };
        let rig = SimRig::new(&p).unwrap();
        let at = |s: f64| rig.midspan_deflection(p.start_ns + (s * 1e9) as i64);
        assert_eq!(at(4.0), 0.0);
        assert!((at(5.0 + 60.0) - 0.06).abs() < 1e-9, "0.06 mm/min");
        assert!((at(5.0 + 300.0) - 0.3).abs() < 1e-9, "0.3 mm at 5 min");
        assert!((at(5.0 + 360.0) - 0.6).abs() < 1e-9, "then 0.3 mm/min");
        assert!((at(5.0 + 440.0) - 1.0).abs() < 1e-9 && (at(5.0 + 590.0) - 1.0).abs() < 1e-9, "held at the maximum");
        assert_eq!(rig.rates_end_s(), Some(300.0 + 140.0));
        for bad in ["0.06:x", "0.06:0.3,x", "0.06:0.3,0.1:0.2", "-1"] {
            let e = SimParams { rates: bad.into(), ..p.clone() }.validate().unwrap_err();
            assert!(e.to_string().contains("rates"), "{bad}: {e}");
        }
    }

    #[test]
    fn a_verification_run_moves_the_bar_rigidly_through_its_steps() {
        let p = SimParams { cameras: 1, width: 320, height: 240, frame_sets: 9, verify_steps: "0, 0.5,1".into(), ..SimParams::default() };
        assert_eq!(deflections(p.clone()), vec![0.0, 0.0, 0.0, 0.5, 0.5, 0.5, 1.0, 1.0, 1.0]);
        let rig = SimRig::new(&p).unwrap();
        let rest = rig.truth_line(0);
        let moved = rig.truth_line(7);
        assert!(moved.net_deflection_mm.unwrap().abs() < 1e-12, "a rigid bar does not bend");
        for (a, b) in rest.tags.iter().zip(&moved.tags) {
            assert!((a.center_mm[2] - b.center_mm[2] - 1.0).abs() < 1e-12 && a.center_mm[0] == b.center_mm[0]);
        }
        assert_eq!(rig.utm_sample(rig.set_time_ns(4)).stroke_mm, Some(0.5));
        let w = rig.verify_windows();
        let half = 50_000_000;
        assert_eq!(w[1], (0.5, rig.set_time_ns(3) - half, rig.set_time_ns(6) - half));
        assert_eq!(w[2].2, rig.set_time_ns(8) + half);
        let bad = SimParams { verify_steps: "0,x".into(), ..p.clone() };
        assert!(bad.validate().unwrap_err().to_string().contains("verify_steps"));
        assert!(SimParams { verify_steps: "0,7".into(), ..p }.validate().is_err(), "beyond max_deflection_mm");
    }
}
