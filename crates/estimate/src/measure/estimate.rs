//! Stage 4, temporal estimate: each solved tag's position and σ from this set and its
//! history — the temporal estimator ([`crate::temporal`], a partial set referred to the last
//! full sets by [`crate::partial`]) or the per-set one (a monocular view fused with the
//! recent motion, [`crate::motion`]).

use nalgebra::{Matrix3, Vector3};
use tagdeflect_core::camera::Pose;

use super::disp_sigma::{axis_sigma, drift_left_out, print_terms, terms_printed, white_share, DispInputs, DispZero, PoseParts};
use super::model_drift::{model_drift_switch, residuals_kept, set_residuals, TagResiduals};
use super::solve::{SolvedTag, SolvedTags};
use super::{Measurement, FULL_SET_FLOOR_SHARE};
use crate::partial::{RecentFull, Referred};
use crate::temporal::{Estimator, TagFilter, Update, UsualViews};
use crate::{TagMotion, TagSolution};

/// What the feed needs of each specimen tag from one frame set to the next.
pub(super) struct TagHistory {
    /// Last solution tag → world (warm start).
    pub(super) pose: Pose,
    /// Centre in the first frame set that solved the tag.
    first_centre: Vector3<f64>,
    /// Recent multi-view solutions: the depth of a monocular view (see `solve::motion`;
    /// the per-set estimator).
    motion: TagMotion,
    /// The temporal estimator's state (see `estimate::temporal`).
    filter: Option<TagFilter>,
    /// How many cameras usually see the tag (a set with fewer is partial).
    usual_views: UsualViews,
    /// The pixel-noise covariance of the tag's last full set's solve, mm².
    full_noise: Option<Matrix3<f64>>,
    /// The camera poses' part of the last full set's covariance, mm² (the absolute σ of a
    /// position referred to the full sets).
    full_pose_cov: Option<Matrix3<f64>>,
    /// The last full sets' views (a partial set is referred to them: `estimate::partial`).
    recent_full: RecentFull,
    /// Its corners' residuals kept for the model error's estimate (`model_drift`).
    residuals: TagResiduals,
    /// What the displacement's σ keeps of the tag's zero (`disp_sigma`).
    zero: DispZero,
}

impl TagHistory {
    /// The history of a tag solved for the first time (its zero).
    fn first(solution: &TagSolution, zero: DispZero) -> TagHistory {
        TagHistory {
            pose: solution.tag_to_world,
            first_centre: solution.centre_mm,
            motion: TagMotion::default(),
            filter: None,
            usual_views: Default::default(),
            full_noise: None,
            full_pose_cov: None,
            recent_full: Default::default(),
            residuals: TagResiduals::default(),
            zero,
        }
    }
}

/// What the net deflection needs of one solved tag: its downward-relevant displacement
/// covariance (pixel noise only, mm²) and its rate (mm/s) when the temporal estimator runs.
pub(super) struct NetInput {
    /// Covariance of the tag's position, mm².
    pub(super) cov: Matrix3<f64>,
    /// Its rate, mm/s.
    pub(super) rate: Option<Vector3<f64>>,
}

/// One tag's position from one frame set as given out.
struct Position {
    /// Centre, mm.
    centre: Vector3<f64>,
    /// Its σ per axis, mm.
    sigma: Vector3<f64>,
    /// Tag → world, its translation the centre when estimated.
    pose: Pose,
    /// The estimate's position covariance (pixel noise only), when not the solve's.
    fused_cov: Option<Matrix3<f64>>,
    /// What the net deflection takes of it.
    net: NetInput,
    /// σ of the displacement from the tag's zero per axis, mm (`disp_sigma`).
    disp_sigma: Vector3<f64>,
}

impl Position {
    /// The solve's own position (its displacement's σ still to come).
    fn solved(solution: &TagSolution) -> Position {
        Position {
            centre: solution.centre_mm,
            sigma: solution.sigma_mm,
            pose: solution.tag_to_world,
            fused_cov: None,
            net: NetInput { cov: noise_cov(solution), rate: None },
            disp_sigma: Vector3::zeros(),
        }
    }
}

/// One tag's estimate from one frame set: what the feed, the gauges and the net
/// deflection take of it.
pub(super) struct TagEstimate {
    /// Specimen tag id.
    pub(super) id: u32,
    /// The set's solve (views, reprojection error, pixel-noise covariance).
    pub(super) solution: TagSolution,
    /// Tag → world as reported (its translation the estimated centre).
    pub(super) pose: Pose,
    /// Estimated centre, mm.
    pub(super) centre_mm: Vector3<f64>,
    /// Its displacement since the tag's first solve, mm.
    pub(super) disp_mm: Vector3<f64>,
    /// σ of the centre per axis, mm.
    pub(super) sigma_mm: Vector3<f64>,
    /// σ of the displacement per axis, mm (without what the zero and this set share).
    pub(super) disp_sigma_mm: Vector3<f64>,
    /// The estimate's position covariance (pixel noise only, mm²) when not the solve's.
    pub(super) fused_cov: Option<Matrix3<f64>>,
    /// What the net deflection takes of it.
    pub(super) net: NetInput,
}

/// What the estimate stage made of a frame set's solved tags.
pub(super) struct Estimates {
    /// The tags, by id.
    pub(super) tags: Vec<TagEstimate>,
    /// Some tag was seen by fewer cameras than usual.
    pub(super) partial: bool,
    /// RMS reprojection error over all the solved views, px (the solve stage's).
    pub(super) reproj_px: Option<f64>,
}

/// The pixel-noise covariance of a solve's centre, mm².
fn noise_cov(solution: &TagSolution) -> Matrix3<f64> {
    solution.noise_covariance.fixed_view::<3, 3>(3, 3).into_owned()
}

impl Measurement {
    /// Estimates each solved tag from this set and its history (the configured estimator);
    /// keeps the filter steps when asked ([`Measurement::keep_steps`]).
    pub(super) fn estimate_tags(&mut self, t_ns: i64, solved: SolvedTags) -> Estimates {
        if let Some(steps) = self.last_steps.as_mut() {
            steps.clear();
        }
        let mut out = Estimates { tags: Vec::with_capacity(solved.tags.len()), partial: false, reproj_px: solved.reproj_px };
        for tag in solved.tags {
            let (estimate, partial) = self.estimate_tag(t_ns, tag, solved.pooled_sigma_px);
            out.partial |= partial;
            out.tags.push(estimate);
        }
        out
    }

    /// One tag's estimate, and whether its set was partial.
    fn estimate_tag(&mut self, t_ns: i64, tag: SolvedTag, pooled_sigma_px: Option<f64>) -> (TagEstimate, bool) {
        let mut history = self.tags.remove(&tag.id).unwrap_or_else(|| self.first_history(&tag));
        let partial = history.usual_views.observe(tag.solution.views);
        let (model, level) = self.model_error(&mut history, &tag, partial, pooled_sigma_px);
        let p = match self.config.measure.estimator {
            Estimator::PerSet => {
                let white = white_share(self.model_drift.white_variance_px2(), pooled_sigma_px);
                let mut p = per_set(&mut history, t_ns, &tag.solution, (white, &model), (&camera_pose_parts(&tag), &self.pose_epochs));
                p.sigma = p.sigma.zip_map(&level.diagonal(), |s, l| (s * s + l).sqrt());
                p
            }
            Estimator::Temporal => self.temporal(&mut history, t_ns, &tag, partial, pooled_sigma_px, (&model, &level)),
        };
        history.pose = p.pose;
        let disp_mm = p.centre - history.first_centre;
        self.tags.insert(tag.id, history);
        let estimate = TagEstimate {
            id: tag.id,
            solution: tag.solution,
            pose: p.pose,
            centre_mm: p.centre,
            disp_mm,
            sigma_mm: p.sigma,
            disp_sigma_mm: p.disp_sigma,
            fused_cov: p.fused_cov,
            net: p.net,
        };
        (estimate, partial)
    }

    /// The history of a tag solved for the first time: this solve is its zero.
    fn first_history(&self, tag: &SolvedTag) -> TagHistory {
        let sol = &tag.solution;
        let noise = noise_cov(sol);
        TagHistory::first(sol, DispZero::new(noise, &camera_pose_parts(tag), &self.pose_epochs))
    }

    /// The temporal estimator's position of a tag (see [`crate::temporal`]); `model` the
    /// edge model's error moved since the zero and `level` the position's common shift
    /// ([`Self::model_error`]).
    fn temporal(
        &mut self,
        history: &mut TagHistory,
        t_ns: i64,
        tag: &SolvedTag,
        partial: bool,
        pooled_sigma_px: Option<f64>,
        (model, level): (&Matrix3<f64>, &Matrix3<f64>),
    ) -> Position {
        let sol = &tag.solution;
        let noise = noise_cov(sol);
        let used = used_cameras(tag);
        let referred = self.refer_or_keep(history, t_ns, tag, &used, partial, pooled_sigma_px);
        let u = update_filter(history, &self.config.measure, t_ns, sol, referred.as_ref(), used.len() == 1, partial);
        // The feed's σ of the position adds the camera poses' part back (the full sets'
        // when the set was referred to them).
        let pose_part = match (&referred, history.full_pose_cov) {
            (Some(_), Some(p)) => p,
            _ => sol.centre_covariance - noise,
        };
        if !partial {
            history.full_noise = Some(noise);
        }
        let floor = sigma_floor(history, referred.as_ref(), sol, partial, used.len());
        let var = |m: &Matrix3<f64>| (self.up.transpose() * m * self.up)[(0, 0)];
        let cov = if var(&u.covariance) < var(&floor) { floor } else { u.covariance };
        if let Some(f) = history.filter.as_ref() {
            history.zero.follow(f.last_step());
        }
        let disp_model = if drift_left_out() { Matrix3::zeros() } else { *model };
        let white = white_share(self.model_drift.white_variance_px2(), pooled_sigma_px);
        let departure = monocular_departure(&u.centre, &sol.centre_mm, partial, used.len());
        let parts = camera_pose_parts(tag);
        let now = DispInputs {
            estimate: &u.covariance,
            temporal: true,
            white,
            model: &disp_model,
            pose_parts: &parts,
            epochs: &self.pose_epochs,
        };
        let disp = history.zero.covariance(&now) + departure;
        if terms_printed() {
            let terms = history.zero.terms(&now);
            print_terms(tag.id, t_ns, &(u.centre - history.first_centre), &[terms.as_slice(), &[departure]].concat());
        }
        // The edge model's error as the tag moves: in the σ given out (when asked), beside
        // the camera poses' part, never in the filter's weights (`model_drift`).
        let model = if model_drift_switch() { *model } else { Matrix3::zeros() };
        // The feed's σ of the position adds the camera poses' part back (an unreferred
        // partial set's floor holds it already).
        let absolute = model + level + departure + if partial && referred.is_none() && cov == floor { cov } else { cov + pose_part };
        let disp_step = self.last_steps.is_some().then(|| history.zero.smoothing_part(white, &disp_model, &parts, &self.pose_epochs));
        let pose_part = pose_part + model + level;
        let sigma = Vector3::new(absolute[(0, 0)], absolute[(1, 1)], absolute[(2, 2)]).map(|v| v.max(0.0).sqrt());
        if let (Some(steps), Some(f)) = (self.last_steps.as_mut(), history.filter.as_ref()) {
            let departure_from = departure_applies(partial, used.len()).then_some(sol.centre_mm);
            steps.push(crate::smooth::TagStep { id: tag.id, step: *f.last_step(), pose_part, floor, disp: disp_step, departure_from });
        }
        let mut pose = sol.tag_to_world;
        pose.translation = u.centre;
        let net = NetInput { cov, rate: Some(u.rate) };
        Position { centre: u.centre, sigma, pose, fused_cov: Some(u.covariance), net, disp_sigma: axis_sigma(&disp) }
    }

    /// The covariances the edge model's error adds to the tag's centre: what moved since the
    /// tag's reference (the corners' and their views' common shifts'), and the views' common
    /// shift itself (the position's; zero unless modelled, `model_drift`); a full set's
    /// residuals update the pooled estimates first.
    fn model_error(
        &mut self,
        history: &mut TagHistory,
        tag: &SolvedTag,
        partial: bool,
        pooled_sigma_px: Option<f64>,
    ) -> (Matrix3<f64>, Matrix3<f64>) {
        let drift = &mut self.model_drift;
        let sol = &tag.solution;
        let (views, cameras) = (&tag.views.views, &tag.views.cameras);
        if !partial && residuals_kept() {
            let size = self.config.specimen.size_mm;
            let now = set_residuals((views, cameras), (&sol.rejected_views, &sol.view_shifts), &self.pose_epochs, &sol.tag_to_world, size);
            drift.observe(&mut history.residuals, now);
        }
        let camera_of = |i: usize| cameras.get(i).copied();
        let moved = drift.common_centre_covariance(&sol.view_shifts, camera_of, true);
        let level = drift.common_centre_covariance(&sol.view_shifts, camera_of, false);
        (drift.centre_covariance(&noise_cov(sol), pooled_sigma_px) + moved, level)
    }

    /// A partial set referred to the last full sets (their cameras' pose errors, not this
    /// subset's), or a full set kept for that (`None`).
    fn refer_or_keep(
        &mut self,
        history: &mut TagHistory,
        t_ns: i64,
        tag: &SolvedTag,
        used: &[usize],
        partial: bool,
        pooled_sigma_px: Option<f64>,
    ) -> Option<Referred> {
        let sol = &tag.solution;
        let noise = noise_cov(sol);
        if !partial {
            let (views, cameras) = (&tag.views.views, &tag.views.cameras);
            history.recent_full.push(t_ns, views, cameras, &sol.rejected_views, &self.pose_epochs, &sol.tag_to_world);
            history.full_pose_cov = Some(sol.centre_covariance - noise);
            return None;
        }
        let size = self.config.specimen.size_mm;
        let view_of = |cam: usize, corners: [nalgebra::Point2<f64>; 4]| self.cameras[cam].view(corners);
        let referred = history.recent_full.refer(t_ns, sol.centre_mm, &noise, used, &self.pose_epochs, size, pooled_sigma_px, view_of);
        if referred.is_some() {
            self.stats.referred_partial_views += 1;
        }
        referred
    }
}

/// The per-set estimator's position of a tag: a multi-view solve as it is (kept for the
/// motion), a monocular one fused with the recent motion (see [`crate::motion`]); its
/// displacement's σ with `white` the pixel noise's white share, `model` the edge model's
/// error, `parts` the solve's camera-poses parts by camera and `epochs` the cameras' pose
/// epochs.
fn per_set(
    history: &mut TagHistory,
    t_ns: i64,
    sol: &TagSolution,
    (white, model): (f64, &Matrix3<f64>),
    (parts, epochs): (&PoseParts, &[u64]),
) -> Position {
    let mut p = Position::solved(sol);
    if sol.views >= 2 {
        history.motion.observe(t_ns, sol.centre_mm, sol.centre_covariance);
    } else if let Some((fc, fcov)) = history.motion.fuse(t_ns, sol.centre_mm, sol.centre_covariance) {
        p.centre = fc;
        p.sigma = Vector3::new(fcov[(0, 0)].sqrt(), fcov[(1, 1)].sqrt(), fcov[(2, 2)].sqrt());
        p.pose.translation = fc;
        p.fused_cov = Some(fcov);
        p.net.cov = fcov;
    }
    let disp_model = if drift_left_out() { Matrix3::zeros() } else { *model };
    p.disp_sigma = axis_sigma(&history.zero.covariance(&DispInputs {
        estimate: &p.net.cov,
        temporal: false,
        white,
        model: &disp_model,
        pose_parts: parts,
        epochs,
    }));
    p
}

/// Each camera's part of a solve's camera-poses covariance, by camera index.
fn camera_pose_parts(tag: &SolvedTag) -> Vec<(usize, Matrix3<f64>)> {
    tag.solution.camera_pose_parts.iter().filter_map(|&(i, part)| tag.views.cameras.get(i).map(|&c| (c, part))).collect()
}

/// The cameras of the views a solve used (not rejected as outliers).
fn used_cameras(tag: &SolvedTag) -> Vec<usize> {
    let rejected = &tag.solution.rejected_views;
    tag.views.cameras.iter().enumerate().filter(|(i, _)| !rejected.contains(i)).map(|(_, c)| *c).collect()
}

/// The tag's filter updated with this set (started on its first), `one_camera` when the
/// views used came from one camera.
///
/// What this set measures of the tag and how well: referred, the pixel noise alone;
/// otherwise (a partial set with nothing kept) the camera poses' part too. A referred set is
/// pixel noise alone, like a full one: the filter takes it as such (a jump included) when two
/// cameras or more saw the tag. Seen by one camera, it keeps that camera's own corner bias
/// and a monocular depth: taken as partial (down-weighted beyond the gate, never a jump, no
/// adaptation) — as a full set one such set moved a sharp scene's net deflection by 16 µm and
/// a 2-s one-camera outage drifted by 9 µm (docs/control.md). An unreferred partial set is
/// taken with its camera poses' part and never as a jump.
fn update_filter(
    history: &mut TagHistory,
    measure: &crate::measure_config::MeasureConfig,
    t_ns: i64,
    sol: &TagSolution,
    referred: Option<&Referred>,
    one_camera: bool,
    partial: bool,
) -> Update {
    let noise = noise_cov(sol);
    let (z, r_partial) = match referred {
        Some(r) => (r.centre_mm, r.covariance),
        None => (sol.centre_mm, sol.centre_covariance),
    };
    match history.filter.as_mut() {
        Some(f) if referred.is_some() => f.update(t_ns, z, &r_partial, &r_partial, one_camera),
        Some(f) => f.update(t_ns, z, &noise, &r_partial, partial),
        None => {
            let f = TagFilter::new(measure.temporal(), t_ns, sol.centre_mm, &noise);
            let u = Update { centre: f.centre(), covariance: f.covariance(), rate: f.rate(), partial, jump: false };
            history.filter = Some(f);
            u
        }
    }
}

/// What the σ given out adds when one camera saw the tag in a full set: `d dᵀ`, `d` the
/// filter's position minus this set's own solve (docs/accuracy.md, "Class profiles the
/// default, and one camera's σ"). There the σ is the set's own solve's (the floor,
/// [`sigma_floor`], takes all of it), while the position given out is the filter's. A
/// monocular depth's errors are correlated from set to set (its corners' phase bias as the
/// tag moves), which the filter takes for motion and extrapolates: its departure from the
/// set is then an error of its own that the set's covariance does not hold. Zero for two
/// cameras or more (the filter's own covariance, which averages, is taken there) and for a
/// partial set (its floor is what it measured with). `TAGDEFLECT_MONOCULAR_DEPARTURE=off`
/// leaves it out (a measurement).
fn monocular_departure(centre: &Vector3<f64>, set_centre: &Vector3<f64>, partial: bool, cameras_used: usize) -> Matrix3<f64> {
    if !departure_applies(partial, cameras_used) {
        return Matrix3::zeros();
    }
    let d = centre - set_centre;
    d * d.transpose()
}

/// Whether the σ given out holds [`monocular_departure`]: one camera saw the tag in a full
/// set, and it is not left out.
fn departure_applies(partial: bool, cameras_used: usize) -> bool {
    !partial && cameras_used == 1 && !departure_left_out()
}

/// Whether [`monocular_departure`] is left out: `TAGDEFLECT_MONOCULAR_DEPARTURE=off` (read
/// once per process).
fn departure_left_out() -> bool {
    static OFF: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *OFF.get_or_init(|| std::env::var("TAGDEFLECT_MONOCULAR_DEPARTURE").is_ok_and(|v| v == "off"))
}

/// The floor of the σ given out: a share of one full set's pixel-noise variance
/// ([`FULL_SET_FLOOR_SHARE`]; all of it when one camera saw the tag). The errors of
/// consecutive sets are partly correlated (the same held poses, a corner bias that changes
/// with the tag's sub-pixel place; seen by one camera, the tag's apparent size, which its
/// depth comes from), and the filter's gain on white noise does not shrink that part. A
/// partial set's floor is what it measured with: referred, its pixel noise and the offset's;
/// else its full covariance (camera poses included: the held poses' errors no longer cancel).
fn sigma_floor(history: &TagHistory, referred: Option<&Referred>, sol: &TagSolution, partial: bool, cameras_used: usize) -> Matrix3<f64> {
    if partial {
        return referred.map_or(sol.centre_covariance, |r| r.covariance);
    }
    let share = if cameras_used > 1 { FULL_SET_FLOOR_SHARE } else { 1.0 };
    history.full_noise.unwrap_or(noise_cov(sol)) * share
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_cameras_sigma_holds_the_filters_departure_from_the_set_and_nothing_else_does() {
        let (filtered, set) = (Vector3::new(1.0, -0.3, 0.2), Vector3::new(1.0, 0.1, 0.2));
        // One camera, a full set: d dᵀ, d = filtered − set (here 0.4 mm along −y).
        let dep = monocular_departure(&filtered, &set, false, 1);
        assert!((dep[(1, 1)] - 0.16).abs() < 1e-12 && dep[(0, 0)] == 0.0 && dep[(2, 2)] == 0.0, "{dep}");
        // Two cameras or more (the filter's own covariance), or a partial set: nothing.
        assert_eq!(monocular_departure(&filtered, &set, false, 2), Matrix3::zeros());
        assert_eq!(monocular_departure(&filtered, &set, true, 1), Matrix3::zeros());
        // The filter on the set's own solve: nothing either.
        assert_eq!(monocular_departure(&set, &set, false, 1), Matrix3::zeros());
    }
}
