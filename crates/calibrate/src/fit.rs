//! The fit over all views with the outlier policy (see the crate doc) and, for tag boards,
//! the tag corners' systematic bias added to the σ.

use crate::error::CalibrateError;
use crate::solve::{Calibration, SolveOptions, View};
use crate::target::TargetSpec;
use crate::{solve, target};

/// A view that was not used, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejected {
    /// The view's name.
    pub name: String,
    /// Why.
    pub reason: String,
}

/// A calibration with its outlier bookkeeping.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationRun {
    /// The fit over the views kept.
    pub calibration: Calibration,
    /// The views kept (same order as the calibration's poses).
    pub views: Vec<View>,
    /// Views rejected as outliers.
    pub rejected: Vec<Rejected>,
    /// Single points dropped as outliers.
    pub dropped_points: usize,
}

/// Calibrates from detected views with the outlier policy of the module docs (none when
/// `keep_outliers`).
pub fn calibrate_views(
    views: Vec<View>,
    width: u32,
    height: u32,
    options: &SolveOptions,
    keep_outliers: bool,
) -> Result<CalibrationRun, CalibrateError> {
    let mut views = views;
    let mut rejected = Vec::new();
    let mut dropped_points = 0;
    loop {
        let cal = solve::calibrate(&views, width, height, options)?;
        if keep_outliers {
            return Ok(CalibrationRun { calibration: cal, views, rejected, dropped_points });
        }
        // Points first: a single mislabelled corner should not cost its view.
        let limit = (5.0 * cal.sigma_px).max(1.0);
        let mut dropped = 0;
        for (v, pose) in views.iter_mut().zip(&cal.poses) {
            let res = solve::residuals(&cal.intrinsics, pose, v);
            let keep: Vec<bool> = res.iter().map(|r| r.x.abs() <= limit && r.y.abs() <= limit).collect();
            let n = keep.iter().filter(|k| !**k).count();
            if n > 0 && n < v.object.len() / 4 {
                let mut it = keep.iter();
                v.object.retain(|_| *it.next().unwrap());
                let mut it = keep.iter();
                v.image.retain(|_| *it.next().unwrap());
                dropped += n;
            }
        }
        dropped_points += dropped;
        if dropped > 0 {
            continue;
        }
        let med = tagdeflect_core::stats::median(&cal.view_rms_px).unwrap_or(0.0);
        let view_limit = (3.0 * med).max(0.5);
        let worst =
            cal.view_rms_px.iter().enumerate().filter(|(_, r)| **r > view_limit).max_by(|a, b| a.1.total_cmp(b.1)).map(|(i, r)| (i, *r));
        match worst {
            Some((i, rms)) if views.len() > 3 => {
                let v = views.remove(i);
                rejected.push(Rejected {
                    name: v.name,
                    reason: format!(
                        "reprojection RMS {rms:.3} px > {view_limit:.3} px (3 × the median view's {med:.3} px, at least 0.5 px)"
                    ),
                });
            }
            _ => return Ok(CalibrationRun { calibration: cal, views, rejected, dropped_points }),
        }
    }
}

/// [`calibrate_views`] for views of `spec`. For tag targets the covariance also holds the
/// sub-pixel refinement's systematic corner bias: every corner may sit out along its tag's
/// diagonal by an amount shared by every view, uniform and growing as the tags' bits shrink
/// in pixels, with the prior of [`TargetSpec::corner_bias_prior`]; the first-order effect of
/// each of the two patterns on the intrinsics ([`tag_corner_bias`]) is added to the
/// statistical covariance ([`Calibration::set_corner_bias`]). Checkerboard corners have no
/// such term.
pub fn calibrate_target_views(
    views: Vec<View>,
    width: u32,
    height: u32,
    spec: &TargetSpec,
    options: &SolveOptions,
    keep_outliers: bool,
) -> Result<CalibrationRun, CalibrateError> {
    let mut run = calibrate_views(views, width, height, options, keep_outliers)?;
    if let Some(prior) = spec.corner_bias_prior() {
        let modes = tag_corner_bias(&run, spec, options, &prior).ok_or(CalibrateError::Solve(solve::SolveError::Singular))?;
        run.calibration.set_corner_bias(modes);
    }
    Ok(run)
}

/// The two patterns of a tag target's systematic corner bias in `run` (views of `spec`),
/// with the σ of `prior` ([`target::CornerBiasPrior`]): every corner moved outwards along
/// the image of its tag's diagonal (from the projected tag centre through the projected
/// corner, under the run's intrinsics and poses) by 1 px ("uniform"), and by
/// `R / b − 1` px with `b` its tag's bit size in the image ("size": the projected black
/// square's mean edge over its bits; `R` = [`target::CORNER_BIAS_REFERENCE_BIT_PX`]).
/// `None` for a checkerboard, or when a direction or a sensitivity cannot be computed.
pub fn tag_corner_bias(
    run: &CalibrationRun,
    spec: &TargetSpec,
    options: &SolveOptions,
    prior: &target::CornerBiasPrior,
) -> Option<Vec<solve::CornerBias>> {
    use nalgebra::Vector2;
    let c = &run.calibration;
    let k = &c.intrinsics;
    // Per view and point: the unit diagonal (image) and the tag's bit size (px).
    let geometry: Vec<Vec<(Vector2<f64>, f64)>> = run
        .views
        .iter()
        .zip(&c.poses)
        .map(|(v, pose)| {
            v.object
                .iter()
                .map(|x| {
                    let project = |p: &nalgebra::Vector3<f64>| k.project(&pose.transform(p)).map(|q| q.coords);
                    let (square, bits) = spec.tag_square_of(x)?;
                    let centre = spec.tag_centre_of(x)?;
                    let d = project(x)? - project(&centre)?;
                    let corners = square.iter().map(project).collect::<Option<Vec<_>>>()?;
                    let perimeter_px: f64 = (0..4).map(|j| (corners[(j + 1) % 4] - corners[j]).norm()).sum();
                    let bit_px = perimeter_px / (4.0 * bits as f64);
                    let len = d.norm();
                    (len > 1e-9 && bit_px > 1e-9 && len.is_finite() && bit_px.is_finite()).then(|| (d / len, bit_px))
                })
                .collect::<Option<Vec<_>>>()
        })
        .collect::<Option<Vec<_>>>()?;
    let pattern = |amount: &dyn Fn(f64) -> f64| -> Vec<Vec<Vector2<f64>>> {
        geometry.iter().map(|g| g.iter().map(|(d, bit_px)| d * amount(*bit_px)).collect()).collect()
    };
    let uniform = solve::bias_sensitivity(c, &run.views, options, &pattern(&|_| 1.0))?;
    let size = solve::bias_sensitivity(c, &run.views, options, &pattern(&|b| target::CORNER_BIAS_REFERENCE_BIT_PX / b - 1.0))?;
    Some(vec![
        solve::CornerBias { mode: "uniform along the tags' diagonals", sigma_px: prior.uniform_px, sensitivity_per_px: uniform },
        solve::CornerBias { mode: "growing as the bits shrink", sigma_px: prior.size_px, sensitivity_per_px: size },
    ])
}
