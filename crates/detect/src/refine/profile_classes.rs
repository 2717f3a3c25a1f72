//! Pixel classes of the learned edge profile ([`super::profile`]) and the decision which
//! class is fitted with which profile: **where it pays**, judged by cross-validation over
//! the edges.
//!
//! A class's own profile removes the bias its real difference from the pooled profile gives
//! (a colour mosaic's sites, an astigmatic blur's orientations) but adds its own sampling
//! noise to every edge it fits, and the noise of a profile learned from a few frames' edges
//! is a bias that moves with each edge's phase. Whether a class *differs* from its parent
//! beyond its sampling noise (a significance test) does not say which of the two is larger:
//! a sharpened edge's classes differed so, yet fitting with them cost 1.5× on that scene.
//! So the decision asks which profile *predicts the edges it was not learned from* best:
//! - the samples of the first frame's edges are kept ([`Sample`]) and split by edge into two
//!   halves (by a hash of the edge's count: alternate edges would be alternate orientations);
//! - on each half every candidate is learned (per edge orientation: the pooled profile, the
//!   orientation's profile, the classes' own profiles) and scored on the other half's edges:
//!   each edge's samples fitted as `a + b · P(d) + c · P′(d)` with the candidate's `P` for
//!   each pixel's class — its levels and a shift refitted, as the edge fit does — and the
//!   residual sum of squares kept per edge;
//! - each candidate is then tested against the simpler one taken so far (orientation over
//!   pooled, then own over that): it is taken only when its held-out sum is lower by more
//!   than three standard errors of the per-edge differences (the edges are the independent
//!   units). The one-standard-error rule of cross-validation (Breiman et al. 1984, §3.4.3),
//!   used before, took a class with no real difference in ~16 % of the decisions, and a
//!   class's profile, learned from a quarter of its orientation's pixels, moves each edge by
//!   its sampling noise: on a sharpened scene that cost 1.9× → 3.0× the sharp scene's error
//!   (docs/accuracy.md, "A stricter class decision").
//!
//! A half's profiles are learned from half the samples, so they are noisier than the ones
//! used for the test: the decision leans to the simpler profile, which is the safe side.

use nalgebra::{DMatrix, DVector, Matrix3, Vector2, Vector3};

use super::fit::censored_residual;

use super::profile::{interpolate, min_class_node_weight, min_node_weight, node_d, node_px, nodes, tested_nodes, Nodes, RANGE_PX};

/// Pixel classes with a profile each: the edge's orientation (its normal nearer the image's
/// x or y axis) × the pixel's place in a 2 × 2 mosaic (column and row parity). An astigmatic
/// blur spreads a near-vertical edge differently from a near-horizontal one, and a colour
/// sensor's demosaic interpolates each of the mosaic's four pixels from different neighbours.
pub const CLASSES: usize = 8;

/// Samples kept for the decision, at most (a camera's first frames; ~2 MB).
const MAX_SAMPLES: usize = 120_000;
/// Edges each orientation's held-out scores need before a class can be chosen.
const MIN_SCORED_EDGES: usize = 8;
/// Samples of an edge (within the profile's tested nodes) needed to score it.
const MIN_EDGE_SAMPLES: usize = 8;

/// Which profile a pixel class is fitted with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ClassUse {
    /// The camera's pooled profile.
    #[default]
    Pooled,
    /// The profile of the class's edge orientation (both parities of both axes).
    Orientation,
    /// The class's own profile.
    Own,
}

/// Each pixel class's [`ClassUse`] (index: the class, see [`CLASSES`]).
pub type ClassChoice = [ClassUse; CLASSES];

/// How pixels are classed: 0 one pooled profile, 1 by edge orientation, 2 by orientation
/// and mosaic parity (both: every class with samples enough uses its own profile), 3 (the
/// default) by orientation and parity, each orientation's classes using the profile that
/// predicts held-out edges better beyond chance (the module docs). Measured on the
/// formations' scenes (docs/accuracy.md, "A stricter class decision" and "Class profiles
/// the default"): 3 is no worse than one pooled profile on any of them and much better where
/// the spread depends on the edge's orientation or mosaic site. `TAGDEFLECT_PROFILE_CLASSES`
/// (`off`: one pooled profile; `orientation`, `parity`; unset or `auto`: the default)
/// chooses a mode for a measurement.
pub(super) fn class_mode() -> u8 {
    static MODE: std::sync::OnceLock<u8> = std::sync::OnceLock::new();
    *MODE.get_or_init(|| match std::env::var("TAGDEFLECT_PROFILE_CLASSES").as_deref() {
        Ok("off") => 0,
        Ok("orientation") => 1,
        Ok("parity") => 2,
        _ => 3,
    })
}

/// Half width (nodes) of the triangular kernel a class profile's difference from its
/// parent's is smoothed with (see [`smoothed_towards`]); 0: not smoothed (the default).
/// `TAGDEFLECT_PROFILE_SMOOTH_NODES` sets it for a measurement.
pub(super) fn smooth_nodes() -> usize {
    static NODES_: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *NODES_.get_or_init(|| std::env::var("TAGDEFLECT_PROFILE_SMOOTH_NODES").ok().and_then(|v| v.parse().ok()).unwrap_or(0))
}

/// `own` (a class's profile) as its `parent`'s plus their difference smoothed by a triangular
/// kernel `half` nodes wide (the kernel shrunk near the table's ends). A class's difference
/// from its parent is a change of the spread's shape over a pixel or so (a demosaic's
/// neighbours, an astigmatic width), while its sampling noise, a quarter of its parent's
/// samples, is node to node: smoothing the difference keeps the first and averages the
/// second away.
pub(super) fn smoothed_towards(own: &[f64], parent: &[f64], half: usize) -> Vec<f64> {
    if half == 0 {
        return own.to_vec();
    }
    let n = own.len();
    (0..n)
        .map(|k| {
            let reach = half.min(k).min(n - 1 - k);
            let (mut sum, mut weight) = (0.0, 0.0);
            for j in k - reach..=k + reach {
                let w = (reach + 1 - j.abs_diff(k)) as f64;
                sum += w * (own[j] - parent[j]);
                weight += w;
            }
            parent[k] + sum / weight
        })
        .collect()
}

/// The [class](CLASSES) of the pixel at `index` of an image `width` pixels wide on an edge of
/// outward `normal` (ideal pixels; their axes are the image's); [`CLASSES`] when pixels are
/// not classed (see [`class_mode`]).
#[inline]
pub(super) fn pixel_class(normal: &Vector2<f64>, index: usize, width: u32) -> usize {
    class_in_mode(class_mode(), normal, index, width)
}

/// [`pixel_class`] in classing mode `mode`.
pub(super) fn class_in_mode(mode: u8, normal: &Vector2<f64>, index: usize, width: u32) -> usize {
    let orient = usize::from(normal.y.abs() > normal.x.abs());
    match mode {
        0 => CLASSES,
        1 => 4 * orient,
        _ => {
            let w = width.max(1) as usize;
            4 * orient + (index % w) % 2 + 2 * ((index / w) % 2)
        }
    }
}

/// One classed profile sample kept for the decision: its edge (a running count), its pixel's
/// class, its distance from the fitted edge (pixels) and its normalised value.
#[derive(Debug, Clone, Copy)]
pub(super) struct Sample {
    edge: u32,
    class: u8,
    d: f32,
    v: f32,
}

/// The samples kept for the decision (see the module docs), edge by edge.
#[derive(Debug, Clone, Default)]
pub(super) struct Samples {
    kept: Vec<Sample>,
    /// The edge the next samples belong to.
    edge: u32,
    /// No more samples are kept (the decision is made).
    done: bool,
}

impl Samples {
    /// Keeps a sample of class `class` (< [`CLASSES`]) while there is room.
    pub(super) fn push(&mut self, class: usize, d: f64, v: f64) {
        if !self.done && self.kept.len() < MAX_SAMPLES {
            self.kept.push(Sample { edge: self.edge, class: class as u8, d: d as f32, v: v as f32 });
        }
    }

    /// What follows is another edge's.
    pub(super) fn close_edge(&mut self) {
        self.edge = self.edge.wrapping_add(1);
    }

    /// Drops the samples and keeps no more.
    pub(super) fn finish(&mut self) {
        *self = Self { done: true, ..Self::default() };
    }

    /// Each class's [`ClassUse`] where it pays (see the module docs), per edge orientation.
    pub(super) fn decide(&self) -> ClassChoice {
        let mut choice = ClassChoice::default();
        for o in 0..2 {
            let scores = self.held_out_scores(o);
            let pick = sequential_choice(&scores);
            if scores.len() >= MIN_SCORED_EDGES {
                let (orient, own) = (gain_in_se(&scores, 0, 1), gain_in_se(&scores, 0, 2));
                tracing::debug!(
                    orientation = o,
                    edges = scores.len(),
                    orient_se = orient,
                    own_se = own,
                    ?pick,
                    "pixel classes: held-out gains over pooled, in standard errors"
                );
            }
            choice[4 * o..4 * o + 4].fill(pick);
        }
        choice
    }

    /// Per edge of orientation `o`, its residual sums of squares under the three candidates
    /// (pooled, orientation, own) learned on the other half of the edges.
    fn held_out_scores(&self, o: usize) -> Vec<[f64; 3]> {
        let mut scores = Vec::new();
        for fold in 0..2 {
            let Some(profiles) = FoldProfiles::learn(self.kept.iter().filter(|s| half(s.edge) != fold), o) else {
                return Vec::new();
            };
            let test = self.kept.iter().filter(|s| half(s.edge) == fold && usize::from(s.class) / 4 == o);
            let edges: Vec<&Sample> = test.collect();
            for edge in edges.chunk_by(|a, b| a.edge == b.edge) {
                let per: Option<Vec<f64>> = (0..3).map(|cand| refit_ssr(edge, |c, d| profiles.value_slope(cand, c, d))).collect();
                if let Some(per) = per {
                    scores.push([per[0], per[1], per[2]]);
                }
            }
        }
        scores
    }
}

/// The half (0 or 1) edge `edge` falls in: a hash of its count, not its parity — a tag's
/// edges come in turn around it, so alternate edges are alternate orientations.
fn half(edge: u32) -> u32 {
    edge.wrapping_mul(0x9e37_79b1) >> 31
}

/// The candidates' profiles learned on one half of the edges, for one orientation.
struct FoldProfiles {
    pooled: Vec<f64>,
    oriented: Option<Vec<f64>>,
    own: [Option<Vec<f64>>; 4],
}

impl FoldProfiles {
    /// Learns them from `train` (half the samples; half the node weights a full profile
    /// needs); `None` when the pooled one cannot be built.
    fn learn<'a>(train: impl Iterator<Item = &'a Sample>, o: usize) -> Option<Self> {
        let (mut pooled, mut oriented) = (Nodes::default(), Nodes::default());
        let mut own: [Nodes; 4] = Default::default();
        for s in train {
            let x = (f64::from(s.d) + RANGE_PX) / node_px();
            if !(x >= 0.0 && x < (nodes() - 1) as f64) {
                continue;
            }
            pooled.add(x, f64::from(s.v));
            if usize::from(s.class) / 4 == o {
                oriented.add(x, f64::from(s.v));
                own[usize::from(s.class) % 4].add(x, f64::from(s.v));
            }
        }
        let class_weight = 0.5 * min_class_node_weight();
        let pooled_curve = pooled.curve(0.5 * min_node_weight())?;
        let oriented_curve = oriented.filled_curve(&pooled, class_weight).map(|c| smoothed_towards(&c, &pooled_curve, smooth_nodes()));
        let parent = oriented_curve.clone().unwrap_or_else(|| pooled_curve.clone());
        Some(Self {
            pooled: pooled_curve,
            oriented: oriented_curve,
            own: own.map(|n| n.filled_curve(&oriented, class_weight).map(|c| smoothed_towards(&c, &parent, smooth_nodes()))),
        })
    }

    /// `P(d)` and `P′(d)` of candidate `cand` (0 pooled, 1 orientation, 2 own; a profile that
    /// could not be built falls back to its parent's) for a pixel of class `class`.
    fn value_slope(&self, cand: usize, class: usize, d: f64) -> (f64, f64) {
        let oriented = self.oriented.as_deref().unwrap_or(&self.pooled);
        let table = match cand {
            0 => &self.pooled[..],
            1 => oriented,
            _ => self.own[class % 4].as_deref().unwrap_or(oriented),
        };
        interpolate(table, d)
    }
}

/// The residual sum of squares of an edge's samples (those on the profile's tested nodes)
/// fitted as `a + b · P(d) + c · P′(d)` (its levels and a shift) with `profile(class, d)`;
/// `None` when too few samples or a singular fit.
fn refit_ssr(edge: &[&Sample], profile: impl Fn(usize, f64) -> (f64, f64)) -> Option<f64> {
    edge_refit_ssr(edge.iter().map(|s| (f64::from(s.d), f64::from(s.v), usize::from(s.class))), |class, d| profile(class, d))
}

/// The residual sum of squares of an edge's samples `(d, v, key)` on the profile's tested
/// nodes, fitted as `a + b · P(d) + c · P′(d)` (its levels and a shift refitted) with
/// `(P, P′) = model(key, d)`: how well a model predicts a held-out edge, whatever the model (a
/// class profile, the physical formation). `None` when too few samples or a singular fit.
pub(super) fn edge_refit_ssr<K>(edge: impl Iterator<Item = (f64, f64, K)>, model: impl Fn(K, f64) -> (f64, f64)) -> Option<f64> {
    let (lo, hi) = (node_d(*tested_nodes().start()), node_d(*tested_nodes().end()));
    let (mut ata, mut aty, mut yy, mut n) = (Matrix3::<f64>::zeros(), Vector3::<f64>::zeros(), 0.0, 0);
    for (d, v, key) in edge {
        if !(lo..=hi).contains(&d) {
            continue;
        }
        let (p, slope) = model(key, d);
        let x = Vector3::new(1.0, p, slope);
        ata += x * x.transpose();
        aty += v * x;
        yy += v * v;
        n += 1;
    }
    if n < MIN_EDGE_SAMPLES {
        return None;
    }
    let beta = ata.try_inverse()? * aty;
    Some((yy - beta.dot(&aty)).max(0.0))
}

/// Sub-pixel phase bins of an edge's position score ([`edge_phase_ssr`]): a quarter pixel
/// each.
const PHASE_BINS: usize = 4;
/// Samples a phase bin needs to have its own shift.
const MIN_BIN_SAMPLES: usize = 4;

/// How far a model's fitted position of a held-out edge depends on where the edge crosses the
/// pixel grid: the edge's samples `(d, v, clip, key)` (`clip` as `fit::clip_side`, in the
/// sign of `v`; 0 where not censored) on the profile's tested nodes fitted twice with
/// `(P, P′) = model(key, d)`, as `a + b · P(d) + c · P′(d)` (one shift) and with one shift
/// `c_k` per quarter-pixel bin of the sample's phase `d − round(d)`; the residual sum the
/// shifts per phase remove. A model whose response is right gives each bin the same shift,
/// up to the noise (about `(k − 1) σ²` for `k` bins, whatever the model); a wrong one gives
/// each phase its own bias, and removes more. Only bins with [`MIN_BIN_SAMPLES`] samples
/// count; `None` when fewer than two have them (an edge at one phase says nothing of the
/// bias across phases) or a fit is singular. Clipped samples are censored
/// ([`censored_lsq`]).
pub(super) fn edge_phase_ssr<K: Copy>(edge: impl Iterator<Item = (f64, f64, i8, K)>, model: impl Fn(K, f64) -> (f64, f64)) -> Option<f64> {
    let (lo, hi) = (node_d(*tested_nodes().start()), node_d(*tested_nodes().end()));
    let mut rows: Vec<(usize, f64, f64, f64, i8)> = Vec::new();
    for (d, v, clip, key) in edge.filter(|s| (lo..=hi).contains(&s.0)) {
        let bin = (((d - d.round() + 0.5) * PHASE_BINS as f64) as usize).min(PHASE_BINS - 1);
        let (p, slope) = model(key, d);
        rows.push((bin, p, slope, v, clip));
    }
    let mut counts = [0usize; PHASE_BINS];
    rows.iter().for_each(|r| counts[r.0] += 1);
    let used: Vec<usize> = (0..PHASE_BINS).filter(|&b| counts[b] >= MIN_BIN_SAMPLES).collect();
    if used.len() < 2 {
        return None;
    }
    rows.retain(|r| counts[r.0] >= MIN_BIN_SAMPLES);
    let one: Vec<(Vec<f64>, f64, i8)> = rows.iter().map(|&(_, p, g, v, c)| (vec![1.0, p, g], v, c)).collect();
    let per_bin: Vec<(Vec<f64>, f64, i8)> = rows
        .iter()
        .map(|&(bin, p, g, v, c)| {
            let mut x = vec![1.0, p];
            x.extend(used.iter().map(|&b| if b == bin { g } else { 0.0 }));
            (x, v, c)
        })
        .collect();
    Some((censored_lsq(&one)? - censored_lsq(&per_bin)?).max(0.0))
}

/// The residual sum of squares of the least-squares fit of `rows` (`(x, v, clip)`: the
/// regressors, the value and the clipped side, as in [`edge_phase_ssr`]), the clipped rows
/// censored (`fit::censored_residual`) by an active set: a clipped row enters the fit, at
/// its bound, once a fit without it falls on the wrong side of that bound (at most four
/// rounds, until no more enter); the residual sum counts a clipped row only where the last
/// fit is on the wrong side of it. `None` when singular.
pub(super) fn censored_lsq(rows: &[(Vec<f64>, f64, i8)]) -> Option<f64> {
    let cols = rows.first()?.0.len();
    let mut active = vec![false; rows.len()];
    let mut ssr = 0.0;
    for _ in 0..4 {
        let (mut ata, mut aty) = (DMatrix::<f64>::zeros(cols, cols), DVector::<f64>::zeros(cols));
        for ((x, v, clip), &on) in rows.iter().zip(&active) {
            if *clip == 0 || on {
                let x = DVector::from_column_slice(x);
                ata += &x * x.transpose();
                aty += *v * x;
            }
        }
        let beta = ata.cholesky()?.solve(&aty);
        ssr = 0.0;
        let mut changed = false;
        for ((x, v, clip), on) in rows.iter().zip(active.iter_mut()) {
            let model: f64 = x.iter().zip(beta.iter()).map(|(a, b)| a * b).sum();
            let r = censored_residual(model - v, *clip);
            ssr += r * r;
            if *clip != 0 && r != 0.0 && !*on {
                (*on, changed) = (true, true);
            }
        }
        if !changed {
            break;
        }
    }
    Some(ssr)
}

/// Standard errors by which a candidate's held-out residual sum must fall below its simpler
/// parent's to be taken (see [`sequential_choice`]).
pub(super) const DECISION_SE: f64 = 3.0;

/// The candidate (pooled, orientation, own) taken by testing each against the simpler one
/// taken so far: orientation over pooled, then own over what was taken, each only when its
/// held-out residual sum over the `scores`' edges is lower by more than [`DECISION_SE`]
/// standard errors of the difference (counted over edges: the edges are the independent
/// units); pooled when too few edges were scored. With no real difference a candidate passes
/// in ~0.1 % of decisions (Student's t with ≥ 7 degrees of freedom, one-sided: ≤ 1 %), where
/// the one-standard-error rule of cross-validation passed ~16 %.
fn sequential_choice(scores: &[[f64; 3]]) -> ClassUse {
    if scores.len() < MIN_SCORED_EDGES {
        return ClassUse::Pooled;
    }
    let mut taken = 0;
    for cand in 1..3 {
        if gain_in_se(scores, taken, cand) > DECISION_SE {
            taken = cand;
        }
    }
    match taken {
        0 => ClassUse::Pooled,
        1 => ClassUse::Orientation,
        _ => ClassUse::Own,
    }
}

/// How many standard errors of the difference (counted over the edges) candidate `cand`'s
/// held-out residual sum lies below candidate `parent`'s (∞ when every edge gains alike).
pub(super) fn gain_in_se(scores: &[[f64; 3]], parent: usize, cand: usize) -> f64 {
    let g = scores.len() as f64;
    let gains: Vec<f64> = scores.iter().map(|s| s[parent] - s[cand]).collect();
    let sum: f64 = gains.iter().sum();
    let mean = sum / g;
    let spread: f64 = gains.iter().map(|x| (x - mean).powi(2)).sum();
    let se = (g / (g - 1.0) * spread).sqrt();
    if se > 0.0 {
        sum / se
    } else if sum > 0.0 {
        f64::INFINITY
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::super::profile::tests::{gauss, gaussian_esf, uniform};
    use super::super::profile::{EdgeProfile, ProfileLearner};
    use super::*;

    /// `edges` edges of each orientation as a camera sees a tag's near-axis-aligned edge: 6
    /// columns across it (distances `φ + j − 2.99`, `φ` the edge's phase), 12 rows along it
    /// (the edge tilted by up to ±3°: each row's distance moves by up to 0.05 px),
    /// each pixel classed by its orientation and mosaic parity and valued by `esf_of(class)`;
    /// what an edge's fit shares among its pixels — its distance off by 0.03 px RMS and its
    /// contrast by 1 % — besides each pixel's noise (1.5 % of the contrast).
    fn learner_of(esf_of: &dyn Fn(usize) -> Box<dyn Fn(f64) -> f64>, edges: usize, seed: u64) -> ProfileLearner {
        let mut learner = ProfileLearner::default();
        let mut seed = seed;
        for e in 0..2 * edges {
            let o = e % 2;
            let (phase, delta, scale) = (uniform(&mut seed), 0.03 * gauss(&mut seed), 1.0 + 0.01 * gauss(&mut seed));
            let (col0, row0) = ((uniform(&mut seed) * 2.0) as usize, (uniform(&mut seed) * 2.0) as usize);
            let tilt = 0.1 * uniform(&mut seed) - 0.05;
            for j in 0..6 {
                for r in 0..12 {
                    let d = -2.99 + phase + j as f64 + tilt * r as f64;
                    let class = 4 * o + (col0 + j) % 2 + 2 * ((row0 + r) % 2);
                    learner.add_sample(class, d, scale * esf_of(class)(d + delta) + 0.015 * gauss(&mut seed));
                }
            }
            learner.close_edge();
        }
        learner.set_edges_for_tests();
        learner
    }

    /// A sharpened edge's profile: the step minus a wider blurred copy (symmetric overshoots).
    fn sharpened(d: f64) -> f64 {
        2.0 * gaussian_esf(0.35, 0.0)(d) - gaussian_esf(0.8, 0.0)(d)
    }

    #[test]
    fn a_class_is_taken_where_its_profile_predicts_held_out_edges_better_and_not_where_it_does_not_pay() {
        let decide = |esf_of: &dyn Fn(usize) -> Box<dyn Fn(f64) -> f64>, edges| {
            learner_of(esf_of, edges, 0x9e37_79b9_7f4a_7c15).build_in(3, None).expect("enough samples").choice()
        };
        // One profile (a sharpened edge's, steep with overshoots) in every class: the classes'
        // own profiles only add their sampling noise.
        assert_eq!(decide(&|_| Box::new(sharpened), 60), [ClassUse::Pooled; CLASSES], "one sharpened profile");
        assert_eq!(decide(&|_| Box::new(gaussian_esf(0.6, 0.0)), 60), [ClassUse::Pooled; CLASSES], "one Gaussian profile");
        // A real but small difference between the parities (σ 0.60 against 0.63 px), seen on
        // a first frame's edges: each class's profile would cost more than it removes.
        let slight = |c: usize| -> Box<dyn Fn(f64) -> f64> { Box::new(gaussian_esf(if c % 2 == 1 { 0.63 } else { 0.6 }, 0.0)) };
        assert_eq!(decide(&slight, 30), [ClassUse::Pooled; CLASSES], "a slight difference on few edges");
        // A mosaic whose parities differ (σ 0.5 against 0.8 px): each class its own, on 100
        // edges an orientation as on a first frame's 30 (whose halves' class profiles lack
        // a few nodes, filled from their parent's).
        let mosaic = |c: usize| -> Box<dyn Fn(f64) -> f64> { Box::new(gaussian_esf(if c % 2 == 1 { 0.8 } else { 0.5 }, 0.0)) };
        // An astigmatic blur: the orientations differ, the parities do not.
        let astig = |c: usize| -> Box<dyn Fn(f64) -> f64> { Box::new(gaussian_esf(if c < 4 { 0.5 } else { 0.8 }, 0.0)) };
        for edges in [100, 30] {
            assert_eq!(decide(&mosaic, edges), [ClassUse::Own; CLASSES], "a mosaic, {edges} edges");
            assert_eq!(decide(&astig, edges), [ClassUse::Orientation; CLASSES], "an astigmatic blur, {edges} edges");
        }
        assert_eq!(decide(&|_| Box::new(sharpened), 30), [ClassUse::Pooled; CLASSES], "one sharpened profile, 30 edges");
        // A decision made earlier is kept by a rebuild, whatever the samples say now.
        let kept = learner_of(&mosaic, 30, 7).build_in(3, Some(&[ClassUse::Pooled; CLASSES])).expect("enough samples");
        assert_eq!((kept.choice(), kept.own_classes()), ([ClassUse::Pooled; CLASSES], 0));
    }

    #[test]
    fn smoothing_a_class_difference_keeps_its_shape_and_averages_its_node_noise() {
        let (parent, class) = (EdgeProfile::from_fn(gaussian_esf(0.5, 0.0)), gaussian_esf(0.8, 0.0));
        let parent: Vec<f64> = (0..nodes()).map(|k| parent.value(node_d(k))).collect();
        let mut seed = 5;
        let noise: Vec<f64> = (0..nodes()).map(|_| 0.01 * gauss(&mut seed)).collect();
        let own: Vec<f64> = (0..nodes()).map(|k| class(node_d(k)) + noise[k]).collect();
        let smoothed = smoothed_towards(&own, &parent, 3);
        let rms = |f: &dyn Fn(usize) -> f64| ((0..nodes()).map(|k| f(k).powi(2)).sum::<f64>() / nodes() as f64).sqrt();
        let before = rms(&|k| own[k] - class(node_d(k)));
        let after = rms(&|k| smoothed[k] - class(node_d(k)));
        assert!(after < 0.7 * before, "smoothed error {after} against the node noise {before}");
        assert_eq!(smoothed_towards(&own, &parent, 0), own, "0 nodes: not smoothed");
    }

    /// `edges` edges' samples `(d, v)` of the profile `truth` as a camera sees near-aligned
    /// edges at every phase: 6 columns across, 12 rows along, the edge tilted so that its rows'
    /// phases cover a pixel; noise `noise` of the contrast.
    fn edges_of(truth: &dyn Fn(f64) -> f64, edges: usize, noise: f64, seed: u64) -> Vec<Vec<(f64, f64)>> {
        let mut seed = seed;
        (0..edges)
            .map(|_| {
                let (phase, tilt) = (uniform(&mut seed), 0.09 + 0.02 * uniform(&mut seed));
                let mut samples = Vec::new();
                for r in 0..12 {
                    for j in 0..6 {
                        let d = -2.99 + phase + j as f64 + tilt * r as f64;
                        samples.push((d, truth(d) + noise * gauss(&mut seed)));
                    }
                }
                samples
            })
            .collect()
    }

    /// `f` and its slope by central differences.
    fn with_slope(f: impl Fn(f64) -> f64) -> impl Fn(f64) -> (f64, f64) {
        move |d| (f(d), (f(d + 1e-5) - f(d - 1e-5)) / 2e-5)
    }

    #[test]
    fn the_position_score_tells_a_phase_bias_apart_where_the_shape_residual_ties() {
        let truth = |d: f64| gaussian_esf(0.5, 0.0)(d);
        let slope = move |d: f64| (truth(d + 1e-5) - truth(d - 1e-5)) / 2e-5;
        // Model B: right at the pixel's centre and boundary, but shifted by 0.05 px × sin 2πφ at
        // phase φ (the bias a wrong profile gives). Model A: a wide bump (0.18 of the contrast
        // at most) on the edge, which moves every phase alike.
        let b_model = with_slope(move |d| truth(d) + 0.05 * (std::f64::consts::TAU * d).sin() * slope(d));
        let bump = |scale: f64| with_slope(move |d| truth(d) + scale * (-d * d / 4.5).exp());
        let edges = edges_of(&truth, 160, 0.0, 3);
        let shape = |m: &dyn Fn(f64) -> (f64, f64), e: &[(f64, f64)]| edge_refit_ssr(e.iter().map(|&(d, v)| (d, v, ())), |_, d| m(d));
        let total = |m: &dyn Fn(f64) -> (f64, f64)| edges.iter().filter_map(|e| shape(m, e)).sum::<f64>();
        // The bump scaled so that, noise-free, its shape residual equals model B's.
        let scale = 0.1 * (total(&b_model) / total(&bump(0.1))).sqrt();
        let a_model = bump(scale);
        let noisy = edges_of(&truth, 160, 0.01, 4);
        let (mut shapes, mut positions) = (Vec::new(), Vec::new());
        for e in &noisy {
            let phase = |m: &dyn Fn(f64) -> (f64, f64)| edge_phase_ssr(e.iter().map(|&(d, v)| (d, v, 0, ())), |_, d| m(d));
            shapes.push([shape(&a_model, e).unwrap(), 0.0, shape(&b_model, e).unwrap()]);
            positions.push([phase(&a_model).unwrap(), 0.0, phase(&b_model).unwrap()]);
        }
        let (shape_se, position_se) = (gain_in_se(&shapes, 2, 0), gain_in_se(&positions, 2, 0));
        println!("bump {scale:.3}: A over B, shape {shape_se:.1} SE, position {position_se:.1} SE");
        assert!(shape_se.abs() < DECISION_SE, "the shapes tie: {shape_se}");
        assert!(position_se > 3.0 * DECISION_SE, "A's position bias is the smaller: {position_se}");
        // An edge seen at one phase says nothing of the bias across phases.
        let one_phase: Vec<(f64, f64, i8, ())> = (0..30).map(|k| (-1.9 + (k / 6) as f64 + 0.02 * (k % 6) as f64, 0.5, 0, ())).collect();
        assert!(edge_phase_ssr(one_phase.into_iter(), |_, d| a_model(d)).is_none());
    }

    #[test]
    fn a_clipped_edge_is_fitted_censored_where_it_is_clipped() {
        // A sharpened edge (overshoots 8 % of the contrast) moved 0.13 px, its white overshoot
        // clipped at 1.03; fitted as `a + b · P(d − s)` over trial shifts `s`.
        let sharp = |d: f64| 2.0 * gaussian_esf(0.35, 0.0)(d) - gaussian_esf(0.8, 0.0)(d);
        let truth = 0.13;
        let mut seed = 9;
        let samples: Vec<(f64, f64)> =
            (0..120).map(|k| -3.0 + 0.05 * k as f64).map(|d| (d, sharp(d - truth) + 0.005 * gauss(&mut seed))).collect();
        let clipped = |v: f64| if v >= 1.03 { (1.03, 1) } else { (v, 0) };
        let fit = |s: f64, censored: bool| {
            let rows: Vec<(Vec<f64>, f64, i8)> = samples
                .iter()
                .map(|&(d, v)| {
                    let (v, clip) = clipped(v);
                    (vec![1.0, sharp(d - s)], v, if censored { clip } else { 0 })
                })
                .collect();
            censored_lsq(&rows).expect("a fit")
        };
        let best =
            |censored: bool| (0..=300).map(|k| 0.001 * k as f64).min_by(|a, b| fit(*a, censored).total_cmp(&fit(*b, censored))).unwrap();
        let (censored, as_values) = (best(true), best(false));
        assert!(samples.iter().filter(|s| clipped(s.1).1 != 0).count() >= 5, "the overshoot is clipped");
        println!("shift {truth}: censored {censored:.3}, clipped values as values {as_values:.3}");
        assert!((censored - truth).abs() < 0.005, "censored: {censored}");
        assert!((as_values - truth).abs() > 2.0 * (censored - truth).abs().max(0.002), "as values: {as_values}");
        // The right model's residual at the truth is the noise's alone (120 samples of 0.005).
        assert!(fit(truth, true) < 2.0 * 120.0 * 0.005f64.powi(2), "{}", fit(truth, true));
    }

    #[test]
    fn a_candidate_is_taken_only_when_it_beats_its_simpler_parent_by_three_standard_errors() {
        // Own better on average by 1 with a spread of ±5 over 10 edges: within chance.
        let noisy: Vec<[f64; 3]> = (0..10).map(|e| [10.0, 10.0, if e % 2 == 0 { 4.0 } else { 14.0 }]).collect();
        assert_eq!(sequential_choice(&noisy), ClassUse::Pooled);
        // Own better by 1 ± 2 (1.5 standard errors): the one-standard-error rule took it, this
        // rule does not.
        let slight: Vec<[f64; 3]> = (0..10).map(|e| [10.0, 10.0, if e % 2 == 0 { 7.0 } else { 11.0 }]).collect();
        assert!((gain_in_se(&slight, 0, 2) - 1.5).abs() < 1e-9, "{}", gain_in_se(&slight, 0, 2));
        assert_eq!(sequential_choice(&slight), ClassUse::Pooled);
        // Own better by 1 on every edge, the orientation no better than pooled: own.
        let steady: Vec<[f64; 3]> = (0..10).map(|e| [10.0 - 0.01 * (e % 2) as f64, 10.0, 9.0]).collect();
        assert_eq!(sequential_choice(&steady), ClassUse::Own);
        // The orientation better beyond chance, own no better than it: the orientation.
        let oriented: Vec<[f64; 3]> = (0..10).map(|e| [10.0 + 0.01 * e as f64, 9.0, 9.0 + 0.01 * (e % 3) as f64]).collect();
        assert_eq!(sequential_choice(&oriented), ClassUse::Orientation);
        // Too few edges scored: pooled.
        assert_eq!(sequential_choice(&steady[..4]), ClassUse::Pooled);
    }
}
