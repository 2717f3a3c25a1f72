//! How much the intrinsics depend on which views were taken: each view left out in turn and
//! the rest fitted again (a jackknife over the views).
//!
//! A fit's σ comes from the corners' scatter about the model: it says how well the views
//! pin the parameters *if the model holds*. When the views disagree beyond that (a slightly
//! flexed board, focus breathing, a view whose corners carry a shared error), the estimate
//! moves with the choice of views by more than σ says — on OpenCV's 13 left sample views,
//! every point kept, fx's spread is 2.3 × its σ (docs/calibration.md). The jackknife's
//! standard error over the views,
//! `√((n−1)/n · Σ (θ₋ᵢ − θ̄)²)`, measures that; `calibrate` prints it beside σ and warns when
//! it exceeds σ by more than [`UNDERSTATED_FACTOR`].

use crate::fit::CalibrationRun;
use crate::solve::{self, SolveOptions, PARAM_NAMES};

/// The jackknife spread above which the fit's σ is said to understate the uncertainty.
pub const UNDERSTATED_FACTOR: f64 = 2.0;

/// Views needed for the spread: each leave-one-out fit keeps at least three.
pub const MIN_VIEWS_FOR_SPREAD: usize = 4;

/// The spread of fx, fy, cx, cy over the leave-one-view-out fits.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewSpread {
    /// Leave-one-out fits that converged (of as many as there are views).
    pub fits: usize,
    /// Jackknife standard error of fx, fy, cx, cy, px.
    pub spread_px: [f64; 4],
    /// The fit's 1σ of the same (0 for a parameter held fixed), px.
    pub sigma_px: [f64; 4],
    /// Per parameter, the view whose absence moves it most and by how much, px.
    pub most: [(String, f64); 4],
}

impl ViewSpread {
    /// The parameters (of fx, fy, cx, cy) whose spread exceeds [`UNDERSTATED_FACTOR`] × σ.
    pub fn understated(&self) -> Vec<&'static str> {
        (0..4).filter(|&i| self.ratio(i).is_some_and(|r| r > UNDERSTATED_FACTOR)).map(|i| PARAM_NAMES[i]).collect()
    }

    /// Spread over σ of parameter `i` (fx, fy, cx, cy); `None` when held fixed.
    pub fn ratio(&self, i: usize) -> Option<f64> {
        (self.sigma_px[i] > 0.0).then(|| self.spread_px[i] / self.sigma_px[i])
    }

    /// The lines `calibrate` prints: the spread beside σ, and a warning when σ understates.
    pub fn text(&self) -> String {
        let mut out = format!("across views (each of {} views left out in turn, jackknife 1σ):\n", self.fits);
        for i in 0..4 {
            let (view, shift) = &self.most[i];
            let ratio = self.ratio(i).map_or("fixed".to_string(), |r| format!("{r:.1} × σ"));
            out.push_str(&format!(
                "  {:<3} ± {:.3} px ({ratio}; the fit's σ ± {:.3} px); without {view} it moves {shift:+.3} px\n",
                PARAM_NAMES[i], self.spread_px[i], self.sigma_px[i]
            ));
        }
        let under = self.understated();
        if !under.is_empty() {
            out.push_str(&format!(
                "WARNING the views disagree on {} by more than {UNDERSTATED_FACTOR} × the fit's σ: σ understates the uncertainty; \
                 take the spread across views as its uncertainty, or retake the views (a flat, rigid target; focus and zoom locked)\n",
                under.join(", ")
            ));
        }
        out
    }
}

/// The spread of `run`'s fx, fy, cx, cy over its views: each kept view left out in turn and
/// the others fitted again with `options` (every point kept: the outliers were dropped by the
/// run). `None` with fewer than [`MIN_VIEWS_FOR_SPREAD`] views or fewer than that many fits
/// converging.
pub fn view_spread(run: &CalibrationRun, options: &SolveOptions) -> Option<ViewSpread> {
    let views = &run.views;
    if views.len() < MIN_VIEWS_FOR_SPREAD {
        return None;
    }
    let (w, h) = (run.calibration.intrinsics.width, run.calibration.intrinsics.height);
    let mut fits: Vec<(String, [f64; 4])> = Vec::new();
    for i in 0..views.len() {
        let mut rest = views.clone();
        let gone = rest.remove(i);
        if let Ok(c) = solve::calibrate(&rest, w, h, options) {
            let k = c.intrinsics;
            fits.push((gone.name, [k.fx, k.fy, k.cx, k.cy]));
        }
    }
    if fits.len() < MIN_VIEWS_FOR_SPREAD {
        return None;
    }
    let n = fits.len() as f64;
    let all = {
        let k = &run.calibration.intrinsics;
        [k.fx, k.fy, k.cx, k.cy]
    };
    let s = run.calibration.sigmas();
    let mut spread_px = [0.0; 4];
    let mut most: [(String, f64); 4] = Default::default();
    for j in 0..4 {
        let mean = fits.iter().map(|f| f.1[j]).sum::<f64>() / n;
        spread_px[j] = ((n - 1.0) / n * fits.iter().map(|f| (f.1[j] - mean).powi(2)).sum::<f64>()).sqrt();
        let worst = fits.iter().max_by(|a, b| (a.1[j] - all[j]).abs().total_cmp(&(b.1[j] - all[j]).abs()));
        most[j] = worst.map(|f| (f.0.clone(), f.1[j] - all[j])).unwrap_or_default();
    }
    Some(ViewSpread { fits: fits.len(), spread_px, sigma_px: [s[0], s[1], s[2], s[3]], most })
}
