//! Virtual gauges (`[[gauge]]`): what a lab otherwise buys clip gauges, yokes and
//! extensometers for, computed from the solved specimen tags of each frame set, with a σ
//! propagated from the tags' covariance.
//!
//! Every gauge is a function of the tags' poses now and of their *reference* poses (each
//! tag's first solved pose, as the feed's `disp_mm`):
//!
//! | kind | tags | value | unit |
//! | --- | --- | --- | --- |
//! | `net_deflection` | by role (all tags with a role, or the listed ones) | per face: mean downward displacement of the `midspan` tags minus the line through the `support` tags (fitted along the beam) at the midspan tags' place — what a yoke measures; averaged over the faces that have both | mm |
//! | `distance` | 2 | change of the distance between the two tags' centres; a second entry `<name>.strain` = change / gauge length (`gauge_length_mm`, default the reference distance) | mm, µε |
//! | `opening` | 2 | component along `direction` of the relative displacement of the two tags at the point `at_mm` (reference position, world; default midway between the tags), each tag carrying the point rigidly (so the opening at a notch mouth below the tags is measured from the halves' turn); positive when the tags move apart | mm |
//! | `rotation` | 1 | the tag's rotation about `axis` (world, right hand) since its reference orientation | mrad |
//! | `curvature` | 3 | curvature of the beam's line through the three tags from their vertical displacements (second divided difference along the beam), sagging positive | 1/km |
//!
//! σ: first-order propagation, `σ² = Σ_k J_k Σ_k J_kᵀ` over the tags' present 6×6 pose
//! covariances (tags are solved independently; the reference poses count as exact — see
//! [`REFERENCE_IN_SIGMA`] — except a `rotation`'s, see [`ROTATION_VARIANCE_FACTOR`]; a gauge
//! at its own reference frame set is exact). Jacobians by central differences on the pose step
//! `(ω, v)` of [`retract`](super::lm::retract). A gauge is absent from a frame set in which
//! one of its tags was not solved (never interpolated); `net_deflection` needs, on one face
//! at least, a midspan tag and a support tag solved.

use std::collections::{BTreeMap, HashMap, HashSet};

use nalgebra::{Matrix6, Rotation3, Vector3, Vector6};

use super::lm::retract;
use tagdeflect_core::camera::Pose;
use tagdeflect_core::feed::GaugeReading;
use tagdeflect_core::rig::{SpecimenConfig, TagRole};

pub use tagdeflect_core::gauge::{resolve_gauges, GaugeConfig, GaugeKind, GaugeSection, STRAIN_UNIT};

/// Whether σ adds the reference poses' own covariance. It does not: a tag's errors in
/// frame sets of one test are strongly correlated (the same held camera poses, lens and
/// print), so its displacement errors are about as large as its position errors, not √2
/// larger — with the reference term σ came out 1.5× too large on simulated truth (every
/// error within 2σ, RMS error/σ 0.65); the feed's per-tag `sigma_mm` is the present pose's
/// σ for the same reason. The reference's error is an offset common to the whole test.
const REFERENCE_IN_SIGMA: bool = false;

/// A `rotation` gauge's variance over what the tag's covariances give, and its reference
/// pose's covariance counted (unlike [`REFERENCE_IN_SIGMA`]). A tag's corners are the
/// intersections of its four fitted edge lines; a line fitted evenly along its length `L`
/// has an offset variance `σρ²` and an angle variance `12σρ²/L²`, so the errors of its two
/// ends across it have variance `4σρ²` each and correlation −½: the pattern of a turn. The
/// tag's covariance takes the corners as independent with that variance, so a turn's variance
/// comes out `(4 + 4 + 2·2)/(4 + 4)` = 1.5 times too small (and a shift's `(4 + 4 − 2·2)/8` too
/// large, which keeps the position gauges on the safe side). A turn is measured from one
/// tag's corners in two frame sets whose pixel noise is independent, and nothing averages it
/// over sets, so the reference set's noise is in every reading. Measured (2026-12-05,
/// `gauges::softening_…`, optics that blur before the pixels integrate): the end rotation's
/// errors 0.21 mrad RMS, of which the reference set's ~0.18 is common to every line, with
/// the present pose's σ alone 0.065 mrad (8 of 24 within 2σ, RMS error/σ 3.1).
const ROTATION_VARIANCE_FACTOR: f64 = 1.5;

/// One solved specimen tag as the gauges see it: its pose (tag → world) and the 6×6
/// covariance of the pose step `(ω, v)` (rad, mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GaugeTag {
    /// Specimen tag id.
    pub id: u32,
    /// Tag frame → world.
    pub pose: Pose,
    /// Covariance of the pose step `(ω, v)`.
    pub covariance: Matrix6<f64>,
}

impl GaugeTag {
    /// A tag known exactly (truth).
    pub fn exact(id: u32, pose: Pose) -> GaugeTag {
        GaugeTag { id, pose, covariance: Matrix6::zeros() }
    }
}

/// The gauges of a run: their configs and each tag's reference (first solved) pose.
#[derive(Debug, Clone)]
pub struct Gauges {
    gauges: Vec<GaugeConfig>,
    up: Vector3<f64>,
    roles: HashMap<u32, Option<TagRole>>,
    refs: HashMap<u32, GaugeTag>,
}

/// Pose of one tag now and at its reference, for a gauge's value function.
#[derive(Clone, Copy)]
struct Pair {
    now: Pose,
    reference: Pose,
}

impl Gauges {
    /// The gauges of `gauges`; `up` is `world.up`; roles from the specimen tags.
    pub fn new(gauges: &[GaugeConfig], up: [f64; 3], specimen: &SpecimenConfig) -> Gauges {
        Gauges {
            gauges: gauges.to_vec(),
            up: Vector3::from(up).normalize(),
            roles: specimen.tags.iter().map(|t| (t.id, t.role)).collect(),
            refs: HashMap::new(),
        }
    }

    /// True when no gauge is configured.
    pub fn is_empty(&self) -> bool {
        self.gauges.is_empty()
    }

    /// Forgets the reference poses (a new test).
    pub fn reset(&mut self) {
        self.refs.clear();
    }

    /// The gauges of one frame set from the tags solved in it. Tags seen for the first time
    /// become their own reference.
    pub fn evaluate(&mut self, tags: &[GaugeTag]) -> BTreeMap<String, GaugeReading> {
        let mut out = BTreeMap::new();
        if self.gauges.is_empty() {
            return out;
        }
        let mut fresh = HashSet::new();
        for t in tags {
            if let std::collections::hash_map::Entry::Vacant(e) = self.refs.entry(t.id) {
                e.insert(*t);
                fresh.insert(t.id);
            }
        }
        let now: HashMap<u32, &GaugeTag> = tags.iter().map(|t| (t.id, t)).collect();
        for g in &self.gauges {
            let ids: Vec<u32> = match g.kind {
                GaugeKind::NetDeflection => self.net_tags(g, &now),
                _ => g.tags.clone(),
            };
            if ids.is_empty() || ids.iter().any(|id| !now.contains_key(id)) {
                continue;
            }
            let tags_now: Vec<&GaugeTag> = ids.iter().map(|id| now[id]).collect();
            let tags_ref: Vec<&GaugeTag> = ids.iter().map(|id| &self.refs[id]).collect();
            let pairs: Vec<Pair> = tags_now.iter().zip(&tags_ref).map(|(n, r)| Pair { now: n.pose, reference: r.pose }).collect();
            let f = |p: &[Pair]| self.value(g, &ids, p);
            let values = f(&pairs);
            if values.is_empty() {
                continue;
            }
            // σ² per output: Σ over tags of J Σ Jᵀ (now and reference).
            let mut var = vec![0.0f64; values.len()];
            for k in 0..pairs.len() {
                let same = fresh.contains(&ids[k]);
                let mut j_now = vec![Vector6::zeros(); values.len()];
                let mut j_ref = vec![Vector6::zeros(); values.len()];
                for q in 0..6 {
                    let h = if q < 3 { 1e-6 } else { 1e-4 };
                    let mut d = Vector6::zeros();
                    d[q] = h;
                    for (which, jac) in [(0, &mut j_now), (1, &mut j_ref)] {
                        let mut plus = pairs.clone();
                        let mut minus = pairs.clone();
                        if which == 0 {
                            plus[k].now = retract(&pairs[k].now, &d);
                            minus[k].now = retract(&pairs[k].now, &-d);
                        } else {
                            plus[k].reference = retract(&pairs[k].reference, &d);
                            minus[k].reference = retract(&pairs[k].reference, &-d);
                        }
                        let (a, b) = (f(&plus), f(&minus));
                        if a.len() != values.len() || b.len() != values.len() {
                            continue;
                        }
                        for (o, jo) in jac.iter_mut().enumerate() {
                            jo[q] = (a[o].1 - b[o].1) / (2.0 * h);
                        }
                    }
                }
                for o in 0..values.len() {
                    if same {
                        let j = j_now[o] + j_ref[o];
                        var[o] += (j.transpose() * tags_now[k].covariance * j)[(0, 0)];
                    } else {
                        var[o] += (j_now[o].transpose() * tags_now[k].covariance * j_now[o])[(0, 0)];
                        if REFERENCE_IN_SIGMA || g.kind == GaugeKind::Rotation {
                            var[o] += (j_ref[o].transpose() * tags_ref[k].covariance * j_ref[o])[(0, 0)];
                        }
                    }
                }
            }
            if g.kind == GaugeKind::Rotation {
                var.iter_mut().for_each(|v| *v *= ROTATION_VARIANCE_FACTOR);
            }
            for (o, (suffix, v, unit)) in values.iter().enumerate() {
                if !v.is_finite() {
                    continue;
                }
                let name = match suffix {
                    Some(s) => format!("{}.{s}", g.name),
                    None => g.name.clone(),
                };
                out.insert(name, GaugeReading::new(*v, var[o].max(0.0).sqrt(), unit));
            }
        }
        out
    }

    /// The tags a net_deflection gauge uses in this frame set: the solved ones with a role.
    fn net_tags(&self, g: &GaugeConfig, now: &HashMap<u32, &GaugeTag>) -> Vec<u32> {
        let mut ids: Vec<u32> = if g.tags.is_empty() {
            self.roles.iter().filter(|(_, r)| r.is_some()).map(|(id, _)| *id).collect()
        } else {
            g.tags.iter().copied().filter(|id| self.roles.get(id).copied().flatten().is_some()).collect()
        };
        ids.retain(|id| now.contains_key(id));
        ids.sort_unstable();
        ids
    }

    /// The gauge's outputs `(suffix, value, unit)` from its tags' poses (in `ids` order).
    fn value(&self, g: &GaugeConfig, ids: &[u32], p: &[Pair]) -> Vec<(Option<&'static str>, f64, &'static str)> {
        let unit = g.kind.unit();
        let disp = |k: usize| p[k].now.translation - p[k].reference.translation;
        match g.kind {
            GaugeKind::Distance => {
                let l0 = (p[1].reference.translation - p[0].reference.translation).norm();
                let l = (p[1].now.translation - p[0].now.translation).norm();
                let change = l - l0;
                let base = g.gauge_length_mm.unwrap_or(l0);
                vec![(None, change, unit), (Some("strain"), change / base * 1e6, STRAIN_UNIT)]
            }
            GaugeKind::Opening => {
                let d = Vector3::from(g.direction.unwrap_or([1.0, 0.0, 0.0]));
                let (a0, b0) = (p[0].reference.translation, p[1].reference.translation);
                let at = g.at_mm.map(Vector3::from).unwrap_or((a0 + b0) * 0.5);
                // The point carried rigidly by each tag from its reference pose to now.
                let carried = |k: usize| {
                    let rel = p[k].now.rotation * p[k].reference.rotation.inverse();
                    rel * (at - p[k].reference.translation) + p[k].now.translation
                };
                let sign = if d.dot(&(b0 - a0)) < 0.0 { -1.0 } else { 1.0 };
                vec![(None, sign * d.dot(&(carried(1) - carried(0))), unit)]
            }
            GaugeKind::Rotation => {
                let n = Vector3::from(g.axis.unwrap_or([0.0, 1.0, 0.0]));
                let rel: Rotation3<f64> = p[0].now.rotation * p[0].reference.rotation.inverse();
                vec![(None, n.dot(&rel.scaled_axis()) * 1e3, unit)]
            }
            GaugeKind::Curvature => {
                let (a0, c0) = (p[0].reference.translation, p[2].reference.translation);
                let mut u = c0 - a0;
                u -= self.up * self.up.dot(&u);
                if u.norm() < 1e-6 {
                    return Vec::new();
                }
                let u = u.normalize();
                let mut pts: Vec<(f64, f64)> = (0..3).map(|k| (u.dot(&p[k].reference.translation), self.up.dot(&disp(k)))).collect();
                pts.sort_by(|x, y| x.0.total_cmp(&y.0));
                let [(sa, ya), (sb, yb), (sc, yc)] = [pts[0], pts[1], pts[2]];
                if sb - sa < 1e-6 || sc - sb < 1e-6 {
                    return Vec::new();
                }
                let k = 2.0 * ((yc - yb) / (sc - sb) - (yb - ya) / (sb - sa)) / (sc - sa);
                vec![(None, k * 1e6, unit)]
            }
            GaugeKind::NetDeflection => {
                // Faces: tags whose reference normals agree within ~30°.
                let normal = |k: usize| p[k].reference.rotation * Vector3::z();
                let mut faces: Vec<(Vector3<f64>, Vec<usize>)> = Vec::new();
                for k in 0..p.len() {
                    let n = normal(k);
                    match faces.iter_mut().find(|(fnorm, _)| fnorm.dot(&n) > 0.85) {
                        Some(f) => f.1.push(k),
                        None => faces.push((n, vec![k])),
                    }
                }
                let mut per_face = Vec::new();
                for (n, members) in &faces {
                    let mut u = self.up.cross(n);
                    if u.norm() < 1e-6 {
                        u = Vector3::x();
                    }
                    let u = u.normalize();
                    let role = |k: usize| self.roles.get(&ids[k]).copied().flatten();
                    let down = |k: usize| -self.up.dot(&disp(k));
                    let s = |k: usize| u.dot(&p[k].reference.translation);
                    let sup: Vec<usize> = members.iter().copied().filter(|&k| role(k) == Some(TagRole::Support)).collect();
                    let mid: Vec<usize> = members.iter().copied().filter(|&k| role(k) == Some(TagRole::Midspan)).collect();
                    if sup.is_empty() || mid.is_empty() {
                        continue;
                    }
                    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
                    let mid_d = mean(&mid.iter().map(|&k| down(k)).collect::<Vec<_>>());
                    let mid_s = mean(&mid.iter().map(|&k| s(k)).collect::<Vec<_>>());
                    let ss: Vec<f64> = sup.iter().map(|&k| s(k)).collect();
                    let ds: Vec<f64> = sup.iter().map(|&k| down(k)).collect();
                    let (sm, dm) = (mean(&ss), mean(&ds));
                    let sxx: f64 = ss.iter().map(|x| (x - sm).powi(2)).sum();
                    let spread = ss.iter().cloned().fold(f64::NEG_INFINITY, f64::max) - ss.iter().cloned().fold(f64::INFINITY, f64::min);
                    let line = if spread > 1.0 {
                        let sxy: f64 = ss.iter().zip(&ds).map(|(x, y)| (x - sm) * (y - dm)).sum();
                        dm + sxy / sxx * (mid_s - sm)
                    } else {
                        dm
                    };
                    per_face.push(mid_d - line);
                }
                if per_face.is_empty() {
                    return Vec::new();
                }
                vec![(None, per_face.iter().sum::<f64>() / per_face.len() as f64, unit)]
            }
        }
    }
}
