//! A small dense Levenberg–Marquardt for 6-DOF pose problems.
//!
//! Every problem in the solver has exactly six unknowns (a rigid pose), so the normal
//! equations are a fixed-size 6×6 system on the stack. The pose is updated on the manifold:
//! a step `δ = (ω, v)` maps `(R, t)` to `(exp(ω) R, t + v)` ([`retract`]), so there are no
//! Euler-angle singularities and no renormalisation.
//!
//! Why our own and not the `levenberg-marquardt` crate: that crate works on a flat parameter
//! vector with dynamically sized matrices and has no notion of a manifold update; wrapping a
//! rotation into it costs a parameter chart, heap matrices per iteration and gives no access
//! to the accumulated `JᵀJ` needed for the covariance. This one is ~100 lines, allocation
//! free, and accumulates `JᵀJ`/`Jᵀr` directly while the residuals are formed.

use nalgebra::{Matrix6, Rotation3, Vector3, Vector6};

use tagdeflect_core::camera::Pose;

/// Normal equations of a least-squares problem at one point.
#[derive(Debug, Clone, Copy)]
pub struct Evaluation {
    /// `JᵀJ` (6×6).
    pub jtj: Matrix6<f64>,
    /// `Jᵀr`.
    pub jtr: Vector6<f64>,
    /// Sum of squared residuals.
    pub ssr: f64,
    /// Number of scalar residuals.
    pub residuals: usize,
}

impl Evaluation {
    /// Zeroed normal equations, ready to accumulate into.
    pub fn zero() -> Self {
        Self { jtj: Matrix6::zeros(), jtr: Vector6::zeros(), ssr: 0.0, residuals: 0 }
    }

    /// Accumulates one 2-D residual `r` (and, when `with_jacobian`, its Jacobian `j`).
    pub fn add(&mut self, r: &nalgebra::Vector2<f64>, j: &nalgebra::Matrix2x6<f64>, with_jacobian: bool) {
        self.ssr += r.norm_squared();
        self.residuals += 2;
        if with_jacobian {
            self.jtj += j.transpose() * j;
            self.jtr += j.transpose() * r;
        }
    }
}

/// A least-squares problem over one rigid pose.
pub trait PoseProblem {
    /// Residuals at `pose`: the sum of squares, and when `with_jacobian` the normal
    /// equations for the step of [`retract`]. `None` when the pose is invalid (a point
    /// behind a camera).
    fn evaluate(&self, pose: &Pose, with_jacobian: bool) -> Option<Evaluation>;
}

/// Applies a step `(ω, v)` to a pose: `R ← exp(ω) R`, `t ← t + v`.
pub fn retract(pose: &Pose, delta: &Vector6<f64>) -> Pose {
    let w = Vector3::new(delta[0], delta[1], delta[2]);
    let v = Vector3::new(delta[3], delta[4], delta[5]);
    Pose { rotation: Rotation3::new(w) * pose.rotation, translation: pose.translation + v }
}

/// Stopping rules of [`minimize`].
#[derive(Debug, Clone, Copy)]
pub struct LmOptions {
    /// Most Jacobian evaluations (accepted steps).
    pub max_iterations: usize,
    /// Stop when a step's rotation part is below this (rad) and its translation part below
    /// this times `1 + |t|` (mm).
    pub step_tolerance: f64,
    /// Stop when an accepted step lowers the cost by less than this fraction.
    pub cost_tolerance: f64,
}

impl Default for LmOptions {
    fn default() -> Self {
        Self { max_iterations: 50, step_tolerance: 1e-8, cost_tolerance: 1e-10 }
    }
}

/// Result of [`minimize`].
#[derive(Debug, Clone, Copy)]
pub struct LmOutcome {
    /// The pose at the minimum found.
    pub pose: Pose,
    /// Normal equations at that pose.
    pub evaluation: Evaluation,
    /// Jacobian evaluations used (accepted steps + 1 for the start).
    pub iterations: usize,
}

/// Minimises a [`PoseProblem`] from `start`. `None` when the start itself is invalid or the
/// normal equations are singular there.
pub fn minimize<P: PoseProblem + ?Sized>(problem: &P, start: &Pose, options: &LmOptions) -> Option<LmOutcome> {
    let mut pose = *start;
    let mut eval = problem.evaluate(&pose, true)?;
    if !eval.ssr.is_finite() {
        return None;
    }
    let mut lambda = 1e-4;
    let mut iterations = 1;
    while iterations < options.max_iterations {
        if eval.ssr == 0.0 {
            break;
        }
        let mut accepted = None;
        for _ in 0..12 {
            let mut a = eval.jtj;
            for i in 0..6 {
                a[(i, i)] += lambda * eval.jtj[(i, i)].max(1e-12);
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let delta = -chol.solve(&eval.jtr);
            let candidate = retract(&pose, &delta);
            match problem.evaluate(&candidate, false) {
                Some(e) if e.ssr.is_finite() && e.ssr <= eval.ssr => {
                    accepted = Some((candidate, delta, e.ssr));
                    lambda = (lambda * 0.2).max(1e-12);
                    break;
                }
                _ => lambda *= 10.0,
            }
        }
        let Some((candidate, delta, new_ssr)) = accepted else { break };
        let old_ssr = eval.ssr;
        pose = candidate;
        eval = problem.evaluate(&pose, true)?;
        iterations += 1;
        let rot_step = Vector3::new(delta[0], delta[1], delta[2]).norm();
        let trans_step = Vector3::new(delta[3], delta[4], delta[5]).norm();
        let small_step = rot_step < options.step_tolerance && trans_step < options.step_tolerance * (1.0 + pose.translation.norm());
        let small_gain = old_ssr - new_ssr <= options.cost_tolerance * old_ssr;
        if small_step || small_gain {
            break;
        }
    }
    eval.jtj.cholesky()?;
    Some(LmOutcome { pose, evaluation: eval, iterations })
}

pub use tagdeflect_core::stats::median;

/// Corner-reprojection figures shared by the pose problems: their corners come in groups of
/// four (a tag seen by one camera), and both the camera-pose and the tag-pose solvers rank
/// starts by a capped cost and judge groups by their RMS.
pub trait CornerGroups {
    /// Number of groups.
    fn groups(&self) -> usize;
    /// Squared reprojection error (px²) of corner `k` (0..4) of group `g` at `pose`; `None`
    /// when the corner is behind the camera.
    fn corner_sq_error(&self, pose: &Pose, g: usize, k: usize) -> Option<f64>;

    /// RMS per group (per axis), `None` if a corner is behind the camera.
    fn group_rms(&self, pose: &Pose) -> Option<Vec<f64>> {
        (0..self.groups())
            .map(|g| {
                let mut s = 0.0;
                for k in 0..4 {
                    s += self.corner_sq_error(pose, g, k)?;
                }
                Some((s / 8.0).sqrt())
            })
            .collect()
    }

    /// Reprojection cost with each corner's squared error capped at (10 px)², for ranking
    /// starts without letting one wrong group dominate.
    fn robust_cost(&self, pose: &Pose) -> f64 {
        let mut s = 0.0;
        for g in 0..self.groups() {
            for k in 0..4 {
                s += self.corner_sq_error(pose, g, k).map_or(100.0, |e| e.min(100.0));
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Fits a pose to 3D point pairs: residual = R p + t − q.
    struct PointFit {
        pairs: Vec<(Vector3<f64>, Vector3<f64>)>,
    }

    impl PoseProblem for PointFit {
        fn evaluate(&self, pose: &Pose, with_jacobian: bool) -> Option<Evaluation> {
            let mut e = Evaluation::zero();
            for (p, q) in &self.pairs {
                let rp = pose.rotation * p;
                let r = rp + pose.translation - q;
                e.ssr += r.norm_squared();
                e.residuals += 3;
                if with_jacobian {
                    let mut j = nalgebra::Matrix3x6::zeros();
                    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-tagdeflect_core::camera::skew(&rp)));
                    j.fixed_view_mut::<3, 3>(0, 3).copy_from(&nalgebra::Matrix3::identity());
                    e.jtj += j.transpose() * j;
                    e.jtr += j.transpose() * r;
                }
            }
            Some(e)
        }
    }

    #[test]
    fn recovers_a_rigid_transform() {
        let truth = Pose::from_rvec_tvec([0.4, -0.3, 1.2], [10.0, -5.0, 30.0]);
        let pts = [Vector3::new(0.0, 0.0, 0.0), Vector3::new(100.0, 0.0, 0.0), Vector3::new(0.0, 50.0, 0.0), Vector3::new(0.0, 0.0, 70.0)];
        let problem = PointFit { pairs: pts.iter().map(|p| (*p, truth.transform(p))).collect() };
        let out = minimize(&problem, &Pose::identity(), &LmOptions::default()).expect("converges");
        assert!(out.pose.angle_to(&truth) < 1e-9, "angle {}", out.pose.angle_to(&truth));
        assert!((out.pose.translation - truth.translation).norm() < 1e-7);
        assert!(out.evaluation.ssr < 1e-12);
    }

    #[test]
    fn median_of_odd_and_even() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), Some(2.5));
        assert_eq!(median(&[]), None);
    }
}
