//! The camera's image formation in its physical order (a measurement switch,
//! `TAGDEFLECT_EDGE_MODEL=formation` / `formation-sites`; docs/accuracy.md, "The physical
//! formation"): the light → a Gaussian blur before the pixel of covariance `Σ` → a square
//! aperture of width `w ≤ 1` px (the fill factor) → a discrete 5 × 5 kernel `K` after the
//! pixel (sum 1; one per 2 × 2 mosaic site with `formation-sites`).
//!
//! For a straight edge of unit normal `n` the 2-D Gaussian is a 1-D one across the edge, of
//! variance `σ_n² = nᵀΣn`, and the aperture's projection on `n` is a trapezoid (the sum of two
//! uniforms of widths `w|n_x|` and `w|n_y|`). A pixel whose centre lies `t` from the edge then
//! sees
//!
//! ```text
//! R(t) = E Φ((t + U) / σ_n) = σ² / (ab) · Σ± ± G₂((t ± a/2 ± b/2) / σ),   G₂(z) = ((z² + 1) Φ(z) + z φ(z)) / 2
//! ```
//!
//! (`a ≥ b` the trapezoid's two widths; `G₂` the second antiderivative of `Φ`, so the form is
//! exact; one uniform when `b` vanishes, the aperture's area alone when `σ` does), and after
//! the pixel `P(d) = Σ_o K_o R(d + n·o)` ([`super::kernel2d`], whose area model is the case
//! `Σ = 0`, `w = 1`). Unlike a kernel over box-integrated steps, this represents a blur
//! before the pixel at every sub-pixel phase, and an aperture smaller than the pixel.
//!
//! **Learning.** The continuous parameters (`Σ` as σ_x, σ_y and their correlation, and `w`)
//! are found by a small search ([`FormationLearner::search`]: a grid of round blurs and
//! apertures, then coordinate descent) on held-out edges' residuals, `K` solved linearly at
//! each trial on the other half of the edges (its ridge pulls it towards the identity, which
//! it stays at when the light's side explains the edges). The samples are the profile's
//! (each well-fitted edge's pixels as `(d, (I − B)/C)`), kept in a rolling store so the
//! parameters follow the frames; each search starts from the last one found.
//!
//! **The choice.** The model replaces the learned profile for a camera only where it fits
//! held-out edges better (the better of the pooled profile and the classes' own profiles
//! learned on the same halves: a camera never gets the worse of the two), judged first by
//! **position**, then by shape:
//! - the *position score* of a held-out edge ([`edge_phase_ssr`]) is how much of its residual
//!   a shift per quarter-pixel of sub-pixel phase (where the edge crosses the pixel grid)
//!   removes beyond one shift for the whole edge. A wrong model's position bias depends on
//!   the phase, so the phases' shifts disagree; a right one's agree up to the noise, whose
//!   share is the same for both models on the same pixels, and cancels in the per-edge
//!   differences. What the displacement needs is exactly this part: a bias common to every
//!   phase moves an edge alike in every frame and cancels in a displacement, one that
//!   changes with the phase moves with the tag. The shape residual (one shift; [`edge_refit_ssr`])
//!   weighs every misfit alike, one that moves no edge as much as one that does: on the
//!   fill-factor scene the search found the aperture yet the shape kept the profile;
//! - the formation is refused when its position scores are higher by more than
//!   [`DECISION_SE`] standard errors of the per-edge differences; otherwise taken when its
//!   shape residual is lower by as much (as before), or when its position scores are lower by
//!   as much and its shape residual no higher. Taken on position alone (shape worse), it cost
//!   the fill-factor scene of a second seed 0.0047 → 0.0050 mm: a position gain of 3–4
//!   standard errors on a few builds' edges is not enough against a worse shape
//!   (docs/accuracy.md, "The formation chosen by position").
//!
//! **Clipped pixels** (at the sensor's 0 or top level: a sharpened edge's overshoot) are kept
//! censored, not dropped: such a pixel says only that the light was at or beyond its level, so
//! a model beyond it is not wrong there (`fit::censored_residual`, Tobit-style). So in the
//! kernel's solve ([`FormationLearner::learn`], one active-set round), the held-out residuals,
//! the choice's position scores and the edge fit with the formation (`profile_fit`). The
//! profile, which learns clipped pixels as values and so holds their average clipped shape,
//! is scored on them as values, as it fits them; its candidates in the choice are learned
//! from the unclipped samples.

use nalgebra::Vector2;

use super::fit::{censored_residual, phi_pdf};
use super::kernel2d::{area, offsets, Kernel2d, KernelLearner, SITES, TAPS};
use super::profile::{interpolate, min_class_node_weight, min_node_weight, node_px, nodes, Nodes, RANGE_PX};
use super::profile_classes::{edge_phase_ssr, edge_refit_ssr, gain_in_se, DECISION_SE};

#[cfg(test)]
mod tests;

/// Below this σ across the edge (pixels) the blur is none: the aperture's area alone.
const SIGMA_MIN_PX: f64 = 0.02;
/// Samples kept for learning, at most (a rolling store: newer frames replace older samples).
const MAX_KEPT: usize = 12_000;
/// Samples needed before a search.
const MIN_KEPT: usize = 3_000;
/// Edges of a half needed to score the choice.
const MIN_SCORED_EDGES: usize = 8;

/// The light's side of the formation: a Gaussian blur before the pixel (σ along x and y,
/// pixels, and their correlation) and a centred square aperture `width_px` wide.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Light {
    /// σ of the blur along the image's x axis, pixels.
    pub sigma_x_px: f64,
    /// σ of the blur along the image's y axis, pixels.
    pub sigma_y_px: f64,
    /// The correlation of the blur's x and y (−1 to 1).
    pub corr: f64,
    /// The aperture's width, pixels (≤ 1; its area is the fill factor).
    pub width_px: f64,
}

impl Light {
    /// No blur, the whole pixel.
    pub const SHARP: Light = Light { sigma_x_px: 0.0, sigma_y_px: 0.0, corr: 0.0, width_px: 1.0 };

    /// σ of the blur across an edge of unit normal `normal`: `√(nᵀΣn)`.
    pub fn sigma_across(&self, normal: &Vector2<f64>) -> f64 {
        let (sx, sy) = (self.sigma_x_px, self.sigma_y_px);
        let var = normal.x * normal.x * sx * sx + normal.y * normal.y * sy * sy + 2.0 * normal.x * normal.y * self.corr * sx * sy;
        var.max(0.0).sqrt()
    }

    /// The aperture's projected widths across an edge of unit normal `normal`, larger first.
    pub fn widths(&self, normal: &Vector2<f64>) -> (f64, f64) {
        let (x, y) = (normal.x.abs() * self.width_px, normal.y.abs() * self.width_px);
        (x.max(y), x.min(y))
    }

    /// The parameters as a vector (σ_x, σ_y, correlation, width).
    fn to_array(self) -> [f64; 4] {
        [self.sigma_x_px, self.sigma_y_px, self.corr, self.width_px]
    }

    /// The light of parameters `p`, clamped to their ranges.
    fn from_array(p: [f64; 4]) -> Self {
        Light {
            sigma_x_px: p[0].clamp(0.0, 2.5),
            sigma_y_px: p[1].clamp(0.0, 2.5),
            corr: p[2].clamp(-0.95, 0.95),
            width_px: p[3].clamp(0.2, 1.0),
        }
    }
}

/// `G₁(z) = zΦ(z) + φ(z)` and `G₂(z) = ((z² + 1)Φ(z) + zφ(z)) / 2` (the first and second
/// antiderivatives of Φ).
#[inline(always)]
fn g1_g2(z: f64) -> (f64, f64) {
    let (c, p) = phi_pdf(z);
    (z * c + p, 0.5 * ((z * z + 1.0) * c + z * p))
}

/// A pixel's response `R(t)` and `dR/dt` to a straight edge `t` from its centre (towards
/// white), through the aperture's trapezoid of widths `a ≥ b` and a Gaussian of σ `sigma`
/// across the edge (see the module docs).
#[inline(always)]
pub(super) fn response(t: f64, a: f64, b: f64, sigma: f64) -> (f64, f64) {
    if sigma < SIGMA_MIN_PX {
        return area(t, a, b);
    }
    let reach = 0.5 * (a + b) + 8.5 * sigma;
    if t <= -reach {
        return (0.0, 0.0);
    }
    if t >= reach {
        return (1.0, 0.0);
    }
    let inv = 1.0 / sigma;
    if b < 1e-3 {
        let (p, m) = (g1_g2((t + 0.5 * a) * inv), g1_g2((t - 0.5 * a) * inv));
        let (cp, cm) = (phi_pdf((t + 0.5 * a) * inv).0, phi_pdf((t - 0.5 * a) * inv).0);
        return (sigma / a * (p.0 - m.0), (cp - cm) / a);
    }
    let (mut v, mut g) = (0.0, 0.0);
    for (sa, sb, sign) in [(1.0, 1.0, 1.0), (1.0, -1.0, -1.0), (-1.0, 1.0, -1.0), (-1.0, -1.0, 1.0)] {
        let (g1, g2) = g1_g2((t + 0.5 * (sa * a + sb * b)) * inv);
        v += sign * g2;
        g += sign * g1;
    }
    let ab = a * b;
    (v * sigma * sigma / ab, g * sigma / ab)
}

/// The responses of the kernel's taps to a sample `d` from an edge of normal `normal`.
fn row_of(light: &Light, normal: &Vector2<f64>, d: f64) -> [f64; TAPS] {
    let (a, b) = light.widths(normal);
    let sigma = light.sigma_across(normal);
    let mut row = [0.0; TAPS];
    for (r, (x, y)) in row.iter_mut().zip(offsets()) {
        *r = response(d + normal.x * x + normal.y * y, a, b, sigma).0;
    }
    row
}

/// One kept sample: its edge (a running count), mosaic site, the edge's normal, its distance
/// from the fitted edge (pixels), its normalised value and whether the camera clipped it (+1:
/// the light was at least `v`, −1: at most; 0 not clipped; see `fit::censored_residual`).
#[derive(Debug, Clone, Copy)]
pub(super) struct FormationSample {
    edge: u32,
    site: u8,
    normal: [f32; 2],
    d: f32,
    v: f32,
    clip: i8,
}

impl FormationSample {
    fn normal(&self) -> Vector2<f64> {
        Vector2::new(f64::from(self.normal[0]), f64::from(self.normal[1]))
    }

    /// The residual of the model's value `model` here, censored where the sample is clipped.
    fn censored(&self, model: f64) -> f64 {
        censored_residual(model - f64::from(self.v), self.clip)
    }
}

/// A kernel's prediction from the taps' responses `row`.
fn predict(kernel: &[f64; TAPS], row: &[f64; TAPS]) -> f64 {
    kernel.iter().zip(row).map(|(k, r)| k * r).sum()
}

/// The half (0 or 1) edge `edge` falls in (a hash of its count: a tag's edges come in turn).
fn half(edge: u32) -> usize {
    (edge.wrapping_mul(0x9e37_79b1) >> 31) as usize
}

/// A camera's samples for the formation, and the light last found (the next search's start).
#[derive(Debug, Clone, Default)]
pub struct FormationLearner {
    kept: Vec<FormationSample>,
    edge: u32,
    added: u64,
    warm: Option<Light>,
}

impl FormationLearner {
    /// Keeps a sample, clipped on side `clip` of `v` (0: not clipped) (rolling: once full, a
    /// newer sample replaces a pseudo-random older one).
    pub(super) fn push(&mut self, site: usize, normal: &Vector2<f64>, d: f64, v: f64, clip: i8) {
        let s = FormationSample {
            edge: self.edge,
            site: site as u8,
            normal: [normal.x as f32, normal.y as f32],
            d: d as f32,
            v: v as f32,
            clip,
        };
        self.added += 1;
        if self.kept.len() < MAX_KEPT {
            self.kept.push(s);
        } else {
            let k = (self.added.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 11) as usize % MAX_KEPT;
            self.kept[k] = s;
        }
    }

    /// What follows is another edge's.
    pub(super) fn close_edge(&mut self) {
        self.edge = self.edge.wrapping_add(1);
    }

    /// Forgets the samples, keeping the light last found as the next search's start.
    pub(super) fn clear(&mut self) {
        *self = Self { warm: self.warm, ..Self::default() };
    }

    /// The formation learned from the samples (kernels per site when `per_site` and they
    /// predict held-out samples better than one kernel), when it
    /// predicts held-out edges better than the profile (the module docs); `None` otherwise or
    /// while too few samples are kept. The light found is kept as the next search's start.
    pub(super) fn solve(&mut self, per_site: bool) -> Option<Kernel2d> {
        let (light, ssr) = self.search(per_site, self.warm)?;
        self.warm = Some(light);
        // A kernel per mosaic site only where it predicts held-out samples better than one.
        let per_site = per_site && self.held_out_ssr(&light, false).is_none_or(|one| ssr < one);
        // A kernel after the pixel only where it predicts held-out edges better than none,
        // beyond chance (a sharp camera's is the identity; learned, its taps add their noise).
        let after = (gain_in_se(&self.identity_scores(&light, per_site)?, 0, 1) > DECISION_SE).then_some(per_site);
        let kernel = self.kernel_of(&light, after, None)?;
        let wins = self.beats_the_profile(&light, after);
        tracing::debug!(?light, ?after, wins, "image formation learned");
        wins.then_some(kernel)
    }

    /// Per held-out edge, the residual sums of squares of its samples after `light` with no
    /// kernel after the pixel and with the kernels learned on the other half of the edges.
    fn identity_scores(&self, light: &Light, per_site: bool) -> Option<Vec<[f64; 3]>> {
        let rows = self.rows(light);
        let kernels = [self.learn(&rows, per_site, Some(0))?, self.learn(&rows, per_site, Some(1))?];
        let mut edges: std::collections::BTreeMap<u32, [f64; 3]> = std::collections::BTreeMap::new();
        for (s, row) in self.kept.iter().zip(&rows) {
            let p = predict(kernels[1 - half(s.edge)].site(usize::from(s.site)), row);
            let e = edges.entry(s.edge).or_default();
            e[0] += s.censored(row[TAPS / 2]).powi(2);
            e[1] += s.censored(p).powi(2);
        }
        Some(edges.into_values().collect())
    }

    /// The kernels after `light` (with it), from the samples (of half `half_only` only, when
    /// given): one, or one per site with `Some(true)`; `None`: none after the pixel.
    fn kernel_of(&self, light: &Light, after: Option<bool>, half_only: Option<usize>) -> Option<Kernel2d> {
        let Some(per_site) = after else { return Some(Kernel2d::identity().with_light(*light)) };
        self.learn(&self.rows(light), per_site, half_only).map(|k| k.with_light(*light))
    }

    /// Each kept sample's taps' responses after `light`.
    fn rows(&self, light: &Light) -> Vec<[f64; TAPS]> {
        self.kept.iter().map(|s| row_of(light, &s.normal(), f64::from(s.d))).collect()
    }

    /// The kernels solved from the samples (their taps' responses `rows`) of half `half_only`
    /// (all: `None`), the clipped ones censored by one active-set round: solved without them,
    /// then again with those the first solution puts on the wrong side of their bound, at the
    /// bound (`fit::censored_residual`).
    fn learn(&self, rows: &[[f64; TAPS]], per_site: bool, half_only: Option<usize>) -> Option<Kernel2d> {
        let chosen = |s: &FormationSample| half_only.is_none_or(|h| half(s.edge) == h);
        let mut learner = KernelLearner::default();
        for (s, row) in self.kept.iter().zip(rows).filter(|(s, _)| s.clip == 0 && chosen(s)) {
            learner.add_row(usize::from(s.site), row, f64::from(s.v));
        }
        let first = learner.solve(per_site)?;
        let mut wrong_side = 0;
        for (s, row) in self.kept.iter().zip(rows).filter(|(s, _)| s.clip != 0 && chosen(s)) {
            if s.censored(predict(first.site(usize::from(s.site)), row)) != 0.0 {
                learner.add_row(usize::from(s.site), row, f64::from(s.v));
                wrong_side += 1;
            }
        }
        if wrong_side == 0 {
            return Some(first);
        }
        learner.solve(per_site)
    }

    /// The held-out residual sum of squares of `light`: the kernels solved on each half of
    /// the edges, the other half's samples predicted, clipped ones censored (`None`: too few
    /// samples).
    pub(super) fn held_out_ssr(&self, light: &Light, per_site: bool) -> Option<f64> {
        let rows = self.rows(light);
        let kernels = [self.learn(&rows, per_site, Some(0))?, self.learn(&rows, per_site, Some(1))?];
        let mut ssr = 0.0;
        for (s, row) in self.kept.iter().zip(&rows) {
            ssr += s.censored(predict(kernels[1 - half(s.edge)].site(usize::from(s.site)), row)).powi(2);
        }
        Some(ssr)
    }

    /// The light of the least held-out residual ([`FormationLearner::held_out_ssr`]): from
    /// `start`, or else the best of a grid of round blurs and apertures, by coordinate descent
    /// over (σ_x, σ_y, correlation, width) with halving steps; with its residual sum.
    pub(super) fn search(&self, per_site: bool, start: Option<Light>) -> Option<(Light, f64)> {
        if self.kept.len() < MIN_KEPT {
            return None;
        }
        let cost = |l: &Light| self.held_out_ssr(l, per_site).unwrap_or(f64::INFINITY);
        let (mut best, mut best_cost, mut step) = match start {
            Some(l) => (l, cost(&l), [0.04, 0.04, 0.12, 0.04]),
            None => {
                let mut grid = Vec::new();
                for s in [0.0, 0.3, 0.5, 0.7, 0.9, 1.2] {
                    for w in [1.0, 0.7] {
                        grid.push(Light { sigma_x_px: s, sigma_y_px: s, corr: 0.0, width_px: w });
                    }
                }
                let (l, c) = grid.into_iter().map(|l| (l, cost(&l))).min_by(|a, b| a.1.total_cmp(&b.1))?;
                (l, c, [0.16, 0.16, 0.4, 0.16])
            }
        };
        if !best_cost.is_finite() {
            return None;
        }
        let levels = if start.is_some() { 2 } else { 4 };
        for _ in 0..levels {
            let mut moved = true;
            let mut rounds = 0;
            while moved && rounds < 3 {
                moved = false;
                rounds += 1;
                for k in 0..4 {
                    for sign in [1.0, -1.0] {
                        let mut p = best.to_array();
                        p[k] += sign * step[k];
                        let cand = Light::from_array(p);
                        if cand == best {
                            continue;
                        }
                        let c = cost(&cand);
                        if c < best_cost {
                            (best, best_cost, moved) = (cand, c, true);
                            break;
                        }
                    }
                }
            }
            step.iter_mut().for_each(|s| *s *= 0.5);
        }
        Some((best, best_cost))
    }

    /// Whether the formation of `light` is to replace the profile, from held-out edges (the
    /// module docs): refused where its position scores are worse beyond [`DECISION_SE`]
    /// standard errors; taken where its shape residual is better by as much, or its position
    /// scores are and its shape residual is no worse.
    fn beats_the_profile(&self, light: &Light, after: Option<bool>) -> bool {
        let Some((shape, position)) = self.held_out_edge_scores(light, after) else { return false };
        if shape.len() < 2 * MIN_SCORED_EDGES {
            return false;
        }
        let gain = |scores: &[[f64; 3]]| {
            let (pooled, own): (f64, f64) = scores.iter().fold((0.0, 0.0), |(p, o), s| (p + s[0], o + s[1]));
            gain_in_se(scores, usize::from(own < pooled), 2)
        };
        let shape_se = gain(&shape);
        let position_se = if position.len() >= 2 * MIN_SCORED_EDGES { gain(&position) } else { 0.0 };
        let wins = position_se > -DECISION_SE && (shape_se > DECISION_SE || (position_se > DECISION_SE && shape_se >= 0.0));
        tracing::debug!(
            edges = shape.len(),
            position_edges = position.len(),
            shape_se,
            position_se,
            wins,
            "image formation against the profile, held out"
        );
        wins
    }

    /// Per held-out edge, the profile's (pooled, the classes' own) and the formation's scores
    /// learned on the other half of the edges: the shape residual ([`edge_refit_ssr`], on the
    /// unclipped samples) and, of the edges seen at two phases or more, the position score
    /// ([`edge_phase_ssr`]; the formation's clipped samples censored, the profile's taken as
    /// values, as each is fitted). `None` when a half's models cannot be learned — the
    /// profile's too when the unclipped samples leave its nodes empty (a strongly sharpened
    /// edge's clipped overshoot: that camera keeps the profile).
    fn held_out_edge_scores(&self, light: &Light, after: Option<bool>) -> Option<(Vec<[f64; 3]>, Vec<[f64; 3]>)> {
        let (mut shape, mut position) = (Vec::new(), Vec::new());
        for fold in 0..2 {
            let kernel = self.kernel_of(light, after, Some(1 - fold))?;
            // The profile's candidates from the unclipped samples (learned from the clipped ones
            // as values as well, they took the formation on the sharpened scenes, worse:
            // docs/accuracy.md, "The formation chosen by position").
            let profiles = FoldProfiles::learn(self.kept.iter().filter(|s| half(s.edge) != fold && s.clip == 0))?;
            let mut test: Vec<&FormationSample> = self.kept.iter().filter(|s| half(s.edge) == fold).collect();
            test.sort_by_key(|s| s.edge);
            for edge in test.chunk_by(|a, b| a.edge == b.edge) {
                let along = kernel.along(&edge[0].normal());
                let formation = |s: &FormationSample, d| along.value_slope(usize::from(s.site), d, false);
                let pooled = |_: &FormationSample, d| interpolate(&profiles.pooled, d);
                let own = |s: &FormationSample, d| interpolate(profiles.class(s), d);
                let unclipped: Vec<&FormationSample> = edge.iter().copied().filter(|s| s.clip == 0).collect();
                if let (Some(f), Some(p), Some(o)) =
                    (refit_ssr(&unclipped, formation), refit_ssr(&unclipped, pooled), refit_ssr(&unclipped, own))
                {
                    shape.push([p, o, f]);
                }
                let (f, p, o) = (phase_ssr(edge, true, formation), phase_ssr(edge, false, pooled), phase_ssr(edge, false, own));
                if let (Some(f), Some(p), Some(o)) = (f, p, o) {
                    position.push([p, o, f]);
                }
            }
        }
        Some((shape, position))
    }
}

/// The profile's candidates learned on one half of the edges: pooled, and per class
/// (orientation × mosaic site) filled from the pooled one.
struct FoldProfiles {
    pooled: Vec<f64>,
    classes: Vec<Option<Vec<f64>>>,
}

impl FoldProfiles {
    fn learn<'a>(train: impl Iterator<Item = &'a FormationSample>) -> Option<Self> {
        let mut pooled = Nodes::default();
        let mut classes: Vec<Nodes> = vec![Nodes::default(); 8];
        for s in train {
            let x = (f64::from(s.d) + RANGE_PX) / node_px();
            if !(x >= 0.0 && x < (nodes() - 1) as f64) {
                continue;
            }
            pooled.add(x, f64::from(s.v));
            classes[class_of(s)].add(x, f64::from(s.v));
        }
        let curve = pooled.curve(0.5 * min_node_weight())?;
        let classes = classes.iter().map(|c| c.filled_curve(&pooled, 0.5 * min_class_node_weight())).collect();
        Some(Self { pooled: curve, classes })
    }

    /// The profile of sample `s`'s class (its own, else the pooled one).
    fn class(&self, s: &FormationSample) -> &[f64] {
        self.classes[class_of(s)].as_deref().unwrap_or(&self.pooled)
    }
}

/// A sample's profile class: its edge's orientation × its mosaic site.
fn class_of(s: &FormationSample) -> usize {
    4 * usize::from(s.normal[1].abs() > s.normal[0].abs()) + usize::from(s.site) % SITES
}

/// An edge's position score with `model(sample, d)` ([`edge_phase_ssr`]), its clipped samples
/// censored when `censored` (else taken as values).
fn phase_ssr(edge: &[&FormationSample], censored: bool, model: impl Fn(&FormationSample, f64) -> (f64, f64)) -> Option<f64> {
    let clip = |s: &FormationSample| if censored { s.clip } else { 0 };
    edge_phase_ssr(edge.iter().map(|&s| (f64::from(s.d), f64::from(s.v), clip(s), s)), model)
}

/// The residual sum of squares of an edge's samples fitted with `model(sample, d)`
/// ([`edge_refit_ssr`]: its levels and a shift refitted, on the profile's tested nodes).
fn refit_ssr(edge: &[&FormationSample], model: impl Fn(&FormationSample, f64) -> (f64, f64)) -> Option<f64> {
    edge_refit_ssr(edge.iter().map(|&s| (f64::from(s.d), f64::from(s.v), s)), model)
}

/// The search's start handed between copies of a camera's samples (a build beside the frame
/// loop searches on a copy: `crate::learned`).
impl FormationLearner {
    /// The light last found (the next search's start).
    pub(super) fn warm_light(&self) -> Option<Light> {
        self.warm
    }

    /// Starts the next search from `light`.
    pub(super) fn start_from(&mut self, light: Option<Light>) {
        self.warm = light;
    }
}
