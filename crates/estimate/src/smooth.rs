//! A fixed-lag Rauch–Tung–Striebel smoother over the temporal estimator's feed lines
//! (`replay --smooth`).
//!
//! The live feed must be causal: a line says what is known when its frame set is solved.
//! A replay knows what came after, and a tag's position at a frame set is best estimated
//! from the sets on both sides of it. [`FixedLag`] holds the last `lag` lines with every
//! tag's filter step ([`TagStep`]), and each line that leaves it is smoothed by a backward
//! RTS pass from the newest held step of that tag down to the line's (a restart of the
//! filter cuts the chain). Memory and time per line are bounded by the lag, so a recording
//! of any length is smoothed as it is replayed.
//!
//! What a smoothed line changes: each tag's `pos_mm`, `disp_mm` (by the same shift) and
//! `sigma_mm` (the smoothed covariance, floored at [`SMOOTHED_FLOOR_SHARE`] of the filtered
//! line's floor, plus the camera poses' part), `disp_sigma_mm` (the smoothed displacement's:
//! the smoothed covariance and cross-covariance with the tag's zero, see
//! [`FixedLag::smooth_tag`]) — both with the smoothed position's departure from the set's own
//! solve where one camera saw the tag in a full set ([`TagStep::departure_from`], as the
//! filtered line's σ holds the filter's); `net_deflection_mm`, its σ (with the same
//! floor) and its rate. The gauges (`[[gauge]]`, which use the tags' orientations too) are
//! left as the filter gave them; the line says `"smoothed": true`.

use std::collections::{HashMap, VecDeque};

use nalgebra::{Matrix3, Matrix6, SMatrix, Vector3, Vector6};
use tagdeflect_core::feed::{round_mm, FeedLine};
use tagdeflect_core::rig::TagRole;

use crate::temporal::Step;

/// Share of the filtered line's σ floor (variance) that floors a smoothed line's: smoothing
/// averages over sets on both sides, but consecutive sets' errors are partly correlated.
/// Measured on the control test's scenes (docs/control.md): the whole floor 100 % within 2σ
/// (inflated), half 54–86 %, three quarters 83–97 %.
pub const SMOOTHED_FLOOR_SHARE: f64 = 0.75;

/// What the smoother needs of one tag in one frame set.
#[derive(Debug, Clone, Copy)]
pub struct TagStep {
    /// Tag id.
    pub id: u32,
    /// The filter's step of this set.
    pub step: Step,
    /// The camera poses' part of the position covariance (added back for the absolute σ), mm².
    pub pose_part: Matrix3<f64>,
    /// The floor of the covariance that enters the net deflection's σ, mm².
    pub floor: Matrix3<f64>,
    /// What the displacement's σ needs of this step (`None`: the smoothed line gives none).
    pub disp: Option<DispStep>,
    /// This set's own solve of the tag's centre, mm, when the σ given out holds the position's
    /// departure from it (one camera saw the tag in a full set: `measure`'s
    /// `monocular_departure`); the smoothed line's σ holds the smoothed position's.
    pub departure_from: Option<Vector3<f64>>,
}

/// The displacement's σ at one filter step (see `measure::disp_sigma`): the filtered line's
/// is `white·(P + N_0 − C − Cᵀ) + M (+ poses)`; the smoothed line's takes the smoothed `P`
/// and `C`.
#[derive(Debug, Clone, Copy)]
pub struct DispStep {
    /// `C = Cov(filter state error, the zero's error)` after this step, mm² (position and
    /// rate rows).
    pub cross: SMatrix<f64, 6, 3>,
    /// The white share of the pixel noise the pixel-noise terms are taken at.
    pub white: f64,
    /// The terms that do not depend on the estimate: `white·N_0 + M (+ the poses' parts after
    /// a re-pose)`, mm².
    pub rest: Matrix3<f64>,
}

/// One tag's smoothed state, covariance and displacement covariance (mm, mm²).
struct Smoothed {
    x: Vector6<f64>,
    p: Matrix6<f64>,
    disp_cov: Option<Matrix3<f64>>,
}

/// The fixed-lag smoother (see the module docs).
#[derive(Debug, Clone)]
pub struct FixedLag {
    lag: usize,
    up: Vector3<f64>,
    roles: HashMap<u32, Option<TagRole>>,
    held: VecDeque<(FeedLine, Vec<TagStep>)>,
}

/// Default lag of `replay --smooth`, frame sets.
pub const DEFAULT_LAG_SETS: usize = 30;

impl FixedLag {
    /// A smoother holding `lag` lines; `up` is the world's up, `roles` the specimen tags'.
    pub fn new(lag: usize, up: Vector3<f64>, roles: HashMap<u32, Option<TagRole>>) -> FixedLag {
        FixedLag { lag: lag.max(1), up: up.normalize(), roles, held: VecDeque::new() }
    }

    /// Takes a filtered line with its tags' steps; gives back the line `lag` sets older,
    /// smoothed, once that many are held.
    pub fn push(&mut self, line: FeedLine, steps: Vec<TagStep>) -> Option<FeedLine> {
        self.held.push_back((line, steps));
        (self.held.len() > self.lag).then(|| self.pop_smoothed())
    }

    /// The lines still held, smoothed (at the end of a run).
    pub fn finish(&mut self) -> Vec<FeedLine> {
        let mut out = Vec::with_capacity(self.held.len());
        while !self.held.is_empty() {
            out.push(self.pop_smoothed());
        }
        out
    }

    fn pop_smoothed(&mut self) -> FeedLine {
        let smoothed: Vec<Smoothed> = {
            let (_, steps) = &self.held[0];
            steps.iter().map(|ts| self.smooth_tag(ts)).collect()
        };
        let (mut line, steps) = self.held.pop_front().expect("a held line");
        let mut covs: HashMap<u32, (Matrix3<f64>, Vector3<f64>)> = HashMap::new();
        for (Smoothed { x, p, disp_cov }, ts) in smoothed.iter().zip(&steps) {
            let id = &ts.id;
            let Some(tag) = line.tags.iter_mut().find(|t| t.id == *id) else { continue };
            let centre = x.fixed_rows::<3>(0).into_owned();
            let cov: Matrix3<f64> = p.fixed_view::<3, 3>(0, 0).into_owned();
            let shift = centre - ts.step.x.fixed_rows::<3>(0);
            let pos = Vector3::from(tag.pos_mm) + shift;
            let disp = Vector3::from(tag.disp_mm) + shift;
            tag.pos_mm = [round_mm(pos.x), round_mm(pos.y), round_mm(pos.z)];
            tag.disp_mm = [round_mm(disp.x), round_mm(disp.y), round_mm(disp.z)];
            // A floor, as the filtered line's: consecutive sets' errors are partly
            // correlated, and the gain on white noise does not shrink that part
            // ([`SMOOTHED_FLOOR_SHARE`] of the filtered line's floor).
            let var = |m: &Matrix3<f64>| (self.up.transpose() * m * self.up)[(0, 0)];
            let floor = ts.floor * SMOOTHED_FLOOR_SHARE;
            let net_cov = if var(&cov) < var(&floor) { floor } else { cov };
            let departure = ts.departure_from.map_or(Matrix3::zeros(), |set| (centre - set) * (centre - set).transpose());
            let absolute = net_cov + ts.pose_part + departure;
            tag.sigma_mm = Some([0, 1, 2].map(|k| round_mm(absolute[(k, k)].max(0.0).sqrt().max(1e-5))));
            let disp_cov = disp_cov.map(|c| c + departure);
            tag.disp_sigma_mm = disp_cov.map(|c| [0, 1, 2].map(|k| round_mm(c[(k, k)].max(0.0).sqrt().max(1e-5))));
            covs.insert(*id, (net_cov, x.fixed_rows::<3>(3).into_owned()));
        }
        if line.net_deflection_mm.is_some() {
            if let Some((value, sigma, rate)) = self.net(&line, &covs) {
                line.net_deflection_mm = Some(round_mm(value));
                line.net_deflection_sigma_mm = Some(round_mm(sigma.max(1e-5)));
                line.net_deflection_rate_mm_per_min = rate.map(|r| (r * 60.0 * 1e6).round() / 1e6);
            }
        }
        line.smoothed = true;
        line
    }

    /// The smoothed state of one tag at the oldest held line: a backward RTS pass over the
    /// tag's steps in the held lines, from the newest down.
    ///
    /// The displacement's σ: with the gain `G_k`, the smoothed error is
    /// `e^s_k = e_k + G_k (e^s_{k+1} − F_{k+1} e_k + w_{k+1})`, the process noise `w`
    /// independent of the zero's error `v_0`, so its cross-covariance with the zero follows the
    /// same pass: `C^s_k = C_k + G_k (C^s_{k+1} − F_{k+1} C_k)`, from `C^s_N = C_N` at the
    /// newest step; the displacement's covariance is then the filtered line's with `P^s`, `C^s`.
    fn smooth_tag(&self, first: &TagStep) -> Smoothed {
        // The chain of this tag's steps after the first, up to a restart.
        let mut chain: Vec<&TagStep> = vec![first];
        for (_, steps) in self.held.iter().skip(1) {
            let Some(ts) = steps.iter().find(|s| s.id == first.id) else { continue };
            let prev = &chain.last().expect("not empty").step;
            if ts.step.t_ns == prev.t_ns {
                continue;
            }
            if ts.step.restart || ts.step.t_ns < prev.t_ns {
                break;
            }
            chain.push(ts);
        }
        let last = chain.last().expect("not empty");
        let (mut x, mut p) = (last.step.x, last.step.p);
        let mut cross = last.disp.map(|d| d.cross);
        for k in (0..chain.len() - 1).rev() {
            let (cur, next) = (&chain[k].step, &chain[k + 1].step);
            let Some(pp_inv) = next.p_pred.try_inverse() else {
                (x, p, cross) = (cur.x, cur.p, chain[k].disp.map(|d| d.cross));
                continue;
            };
            let g = cur.p * next.f.transpose() * pp_inv;
            x = cur.x + g * (x - next.x_pred);
            let ps = cur.p + g * (p - next.p_pred) * g.transpose();
            p = (ps + ps.transpose()) * 0.5;
            cross = match (cross, chain[k].disp) {
                (Some(cs), Some(d)) => Some(d.cross + g * (cs - next.f * d.cross)),
                _ => None,
            };
        }
        let disp_cov = match (first.disp, cross) {
            (Some(d), Some(cs)) => {
                let c: Matrix3<f64> = cs.fixed_view::<3, 3>(0, 0).into_owned();
                let cov = (p.fixed_view::<3, 3>(0, 0) - c - c.transpose()) * d.white + d.rest;
                Some((cov + cov.transpose()) * 0.5)
            }
            _ => None,
        };
        Smoothed { x, p, disp_cov }
    }

    /// The net deflection of a smoothed line (as `Measurement`'s): midspan tags' mean
    /// downward displacement minus the supports'; σ from the tags' covariances; the rate
    /// when every tag has one.
    fn net(&self, line: &FeedLine, covs: &HashMap<u32, (Matrix3<f64>, Vector3<f64>)>) -> Option<(f64, f64, Option<f64>)> {
        let (mut value, mut var, mut rate) = (0.0, 0.0, Some(0.0));
        for (role, sign) in [(TagRole::Midspan, 1.0), (TagRole::Support, -1.0)] {
            let members: Vec<_> = line.tags.iter().filter(|t| self.roles.get(&t.id).copied().flatten() == Some(role)).collect();
            if members.is_empty() {
                return None;
            }
            let w = sign / members.len() as f64;
            for t in members {
                value += w * -Vector3::from(t.disp_mm).dot(&self.up);
                match covs.get(&t.id) {
                    Some((cov, r)) => {
                        var += w * w * (self.up.transpose() * cov * self.up)[(0, 0)];
                        rate = rate.map(|acc| acc - w * r.dot(&self.up));
                    }
                    None => rate = None,
                }
            }
        }
        Some((value, var.max(0.0).sqrt(), rate))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::temporal::{TagFilter, TemporalConfig};
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    use tagdeflect_core::feed::FeedTag;

    /// One midspan and one support tag; the midspan moves down along a ramp; 3 µm noise.
    /// The smoothed net deflection is closer to the truth than the filtered one, its σ no
    /// larger, and the lines come out in order, all of them.
    #[test]
    fn the_fixed_lag_smoother_beats_the_filter_and_keeps_every_line() {
        let dt = 100_000_000i64;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let noise = Normal::new(0.0, 0.003).unwrap();
        let cov = Matrix3::identity() * 0.003f64.powi(2);
        let roles: HashMap<u32, Option<TagRole>> = [(0, Some(TagRole::Midspan)), (1, Some(TagRole::Support))].into();
        let mut lag = FixedLag::new(20, Vector3::new(0.0, 1.0, 0.0), roles);
        let mut filters: Vec<Option<TagFilter>> = vec![None, None];
        let truth = |k: i64| if k < 20 { 0.0 } else { (k - 20) as f64 * 0.01 };
        let (mut filtered, mut smoothed) = (Vec::new(), Vec::new());
        let mut out = Vec::new();
        for k in 0..200i64 {
            let t = k * dt;
            let mut tags = Vec::new();
            let mut steps = Vec::new();
            for id in 0..2u32 {
                let y = if id == 0 { -truth(k) } else { 0.0 };
                let z = Vector3::new(noise.sample(&mut rng), y + noise.sample(&mut rng), noise.sample(&mut rng));
                let f = &mut filters[id as usize];
                match f.as_mut() {
                    Some(f) => {
                        f.update(t, z, &cov, &cov, false);
                    }
                    None => *f = Some(TagFilter::new(TemporalConfig::default(), t, z, &cov)),
                }
                let f = f.as_ref().unwrap();
                let c = f.centre();
                tags.push(FeedTag {
                    id,
                    pos_mm: c.into(),
                    disp_mm: c.into(),
                    views: 3,
                    sigma_mm: Some([0.003; 3]),
                    disp_sigma_mm: None,
                    reproj_px: None,
                });
                steps.push(TagStep {
                    id,
                    step: *f.last_step(),
                    pose_part: Matrix3::zeros(),
                    floor: Matrix3::zeros(),
                    disp: None,
                    departure_from: None,
                });
            }
            let net = -tags[0].disp_mm[1] + tags[1].disp_mm[1];
            let line = FeedLine { seq: k as u64, t_ns: t, tags, net_deflection_mm: Some(net), ..FeedLine::default() };
            filtered.push((net - truth(k)).abs());
            out.extend(lag.push(line, steps));
        }
        out.extend(lag.finish());
        assert_eq!(out.len(), 200);
        for (k, l) in out.iter().enumerate() {
            assert_eq!(l.seq, k as u64);
            assert!(l.smoothed);
            smoothed.push((l.net_deflection_mm.unwrap() - truth(k as i64)).abs());
        }
        let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
        let (f, s) = (rms(&filtered[30..]), rms(&smoothed[30..]));
        println!("net deflection RMS: filtered {:.2} µm, smoothed {:.2} µm", f * 1e3, s * 1e3);
        assert!(s < 0.8 * f, "smoothed {s} filtered {f}");
    }

    /// One camera saw the tag in a full set: the smoothed line's σ (position and
    /// displacement) holds `d dᵀ`, `d` the smoothed position minus the set's own solve, as
    /// the filtered line's holds the filter's; without it nothing is added, and the
    /// position is the same either way.
    #[test]
    fn a_one_camera_tags_smoothed_sigma_holds_the_smoothed_positions_departure_from_the_set() {
        let noise = Matrix3::identity() * 0.002f64.powi(2);
        let run = |offset: Option<Vector3<f64>>| {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
            let n = Normal::new(0.0, 0.002).unwrap();
            let mut f: Option<TagFilter> = None;
            let mut lag = FixedLag::new(8, Vector3::new(0.0, 1.0, 0.0), HashMap::new());
            let mut out = Vec::new();
            let mut sets = Vec::new();
            for k in 0..20i64 {
                let z = Vector3::new(n.sample(&mut rng), n.sample(&mut rng), n.sample(&mut rng));
                let f = match f.as_mut() {
                    Some(f) => {
                        f.update(k * 50_000_000, z, &noise, &noise, false);
                        f
                    }
                    None => f.insert(TagFilter::new(TemporalConfig::default(), 0, z, &noise)),
                };
                let c = f.centre();
                // The set's own solve: here its measurement shifted by the offset.
                let set = offset.map(|o| z + o);
                sets.push(set);
                let tag =
                    FeedTag { id: 0, pos_mm: c.into(), disp_mm: c.into(), views: 1, sigma_mm: None, disp_sigma_mm: None, reproj_px: None };
                let disp = DispStep { cross: SMatrix::zeros(), white: 1.0, rest: noise };
                let step = TagStep { id: 0, step: *f.last_step(), pose_part: noise, floor: noise, disp: Some(disp), departure_from: set };
                out.extend(lag.push(FeedLine { seq: k as u64, t_ns: k * 50_000_000, tags: vec![tag], ..FeedLine::default() }, vec![step]));
            }
            out.extend(lag.finish());
            (out, sets)
        };
        let (plain, _) = run(None);
        let (with, sets) = run(Some(Vector3::new(0.0, 0.05, -0.02)));
        assert_eq!(plain.len(), 20);
        for ((p, w), set) in plain.iter().zip(&with).zip(&sets) {
            let (p, w) = (&p.tags[0], &w.tags[0]);
            assert_eq!(p.pos_mm, w.pos_mm, "σ moves no position");
            let d = Vector3::from(w.pos_mm) - set.expect("a set");
            for k in 0..3 {
                let added = w.sigma_mm.unwrap()[k].powi(2) - p.sigma_mm.unwrap()[k].powi(2);
                let added_disp = w.disp_sigma_mm.unwrap()[k].powi(2) - p.disp_sigma_mm.unwrap()[k].powi(2);
                // Rounded to 0.00001 mm on the feed: a tolerance of that order on σ².
                let tol = 4e-5 * w.sigma_mm.unwrap()[k] + 1e-9;
                assert!((added - d[k] * d[k]).abs() <= tol, "axis {k}: σ² grew by {added:.3e}, d² {:.3e}", d[k] * d[k]);
                assert!((added_disp - d[k] * d[k]).abs() <= tol, "axis {k}: displacement σ² grew by {added_disp:.3e}");
            }
        }
    }
}
