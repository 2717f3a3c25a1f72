//! A specimen tag's recent multi-view history, used to constrain what one camera cannot
//! measure.
//!
//! A tag seen by a single camera is located well across the line of sight but poorly along
//! it (depth comes from the tag's apparent size alone: about a millimetre of scatter for a
//! 30 mm tag at 1.5 m). When the same tag was solved from several cameras a moment ago, its
//! position now is predicted from that history (constant velocity over the last two
//! multi-view solutions, with an uncertainty that grows with the time since), and the
//! monocular solution is fused with the prediction by their covariances (a Kalman update):
//! the prediction fixes the depth, the view fixes the rest. The fused covariance gives the
//! honest σ. Without a recent multi-view history (a one-camera rig, or a tag seen by one
//! camera only) the monocular solution stands alone.

use nalgebra::{Matrix3, Vector3};

/// Multi-view history older than this is not used, ns.
pub(crate) const MAX_AGE_NS: i64 = 2_000_000_000;
/// Unmodelled change of velocity, mm/s per √s: how far a tag may stray from a straight
/// path between solutions. Beams in a bending test move at most a few mm/s.
pub(crate) const ACCEL_NOISE_MM_S: f64 = 2.0;

/// The last multi-view solutions of one tag.
#[derive(Debug, Clone, Default)]
pub struct TagMotion {
    last: Option<(i64, Vector3<f64>, Matrix3<f64>)>,
    prev: Option<(i64, Vector3<f64>)>,
}

impl TagMotion {
    /// Records a multi-view solution (centre, mm, and its covariance, mm²) at `t_ns`.
    pub fn observe(&mut self, t_ns: i64, centre: Vector3<f64>, cov: Matrix3<f64>) {
        if let Some((t, c, _)) = self.last {
            if t_ns > t {
                self.prev = Some((t, c));
            }
        }
        self.last = Some((t_ns, centre, cov));
    }

    /// Predicted centre and covariance at `t_ns`, or `None` without recent history.
    pub fn predict(&self, t_ns: i64) -> Option<(Vector3<f64>, Matrix3<f64>)> {
        let (t1, c1, cov1) = self.last?;
        let dt = (t_ns - t1) as f64 * 1e-9;
        if !(0.0..=MAX_AGE_NS as f64 * 1e-9).contains(&dt) {
            return None;
        }
        let mut centre = c1;
        let mut cov = cov1;
        if let Some((t0, c0)) = self.prev.filter(|(t0, _)| t1 - t0 <= MAX_AGE_NS) {
            let span = (t1 - t0) as f64 * 1e-9;
            let v = (c1 - c0) / span;
            centre += v * dt;
            // The velocity's own error: both ends carry ~cov1.
            cov += cov1 * (2.0 * (dt / span).powi(2));
        }
        cov += Matrix3::identity() * (ACCEL_NOISE_MM_S.powi(2) * dt.powi(3) / 3.0 + 1e-8);
        Some((centre, cov))
    }

    /// Fuses a monocular solution with the prediction at `t_ns`; `None` when there is no
    /// prediction or the two disagree beyond chance (χ² with 3 d.o.f. above 16: then the
    /// tag really moved, or the view is wrong — the monocular solution is kept as it is).
    pub fn fuse(&self, t_ns: i64, centre: Vector3<f64>, cov: Matrix3<f64>) -> Option<(Vector3<f64>, Matrix3<f64>)> {
        let (pc, pcov) = self.predict(t_ns)?;
        let s = cov + pcov;
        let s_inv = s.try_inverse()?;
        let d = centre - pc;
        if d.dot(&(s_inv * d)) > 16.0 {
            return None;
        }
        let gain = pcov * s_inv;
        let fused = pc + gain * d;
        let fused_cov = (Matrix3::identity() - gain) * pcov;
        let fused_cov = (fused_cov + fused_cov.transpose()) * 0.5;
        Some((fused, fused_cov))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_comes_from_the_history_and_the_rest_from_the_view() {
        let mut m = TagMotion::default();
        let small = Matrix3::identity() * 0.01f64.powi(2);
        // Moving down 1 mm/s, solved from several cameras at 10 Hz.
        for k in 0..5 {
            m.observe(k * 100_000_000, Vector3::new(0.0, 0.0, -0.1 * k as f64), small);
        }
        // A monocular view at t = 0.5 s: good in x, z; 1 mm off along y (its line of sight).
        let mono = Vector3::new(0.003, 1.0, -0.5);
        let cov = Matrix3::from_diagonal(&Vector3::new(0.02f64.powi(2), 0.7f64.powi(2), 0.02f64.powi(2)));
        let (c, cc) = m.fuse(500_000_000, mono, cov).expect("fused");
        assert!(c.y.abs() < 0.05, "depth from the history: {c}");
        assert!((c.z + 0.5).abs() < 0.02 && (c.x - 0.003).abs() < 0.02, "{c}");
        assert!(cc[(1, 1)].sqrt() < 0.05, "σ along the line of sight shrinks: {}", cc[(1, 1)].sqrt());
    }

    #[test]
    fn no_history_or_stale_history_or_disagreement_leaves_the_view_alone() {
        let mut m = TagMotion::default();
        let small = Matrix3::identity() * 1e-4;
        assert!(m.fuse(0, Vector3::zeros(), small).is_none());
        m.observe(0, Vector3::zeros(), small);
        assert!(m.fuse(3_000_000_000, Vector3::zeros(), small).is_none(), "stale");
        assert!(m.fuse(100_000_000, Vector3::new(5.0, 0.0, 0.0), small).is_none(), "a 5 mm jump is not fused away");
    }
}
