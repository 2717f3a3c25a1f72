//! Guard rails: a calibration that refuses to be wrong.
//!
//! - **Views.** Fewer than [`MIN_VIEWS`] views of the target are refused (`--force`
//!   calibrates from as few as three, and the verdict says poor).
//! - **Board size.** A `--target` that is not the board in the images is refused
//!   ([`check_board`]): a checkerboard whose images show more inner corners than declared
//!   (outer lines of corners beyond the declared size), or of which no view shows the whole
//!   declared grid (the board is smaller); a tag board of which tags of the family with ids
//!   outside the board's range are seen (the board is larger, or starts at another id), or
//!   some of whose ids are never seen in any view (the board is smaller).
//! - **Views of another camera or focus** ([`split_views`]). At the joint minimum every
//!   view pulls the intrinsics its own way; views of one camera pull like noise, the views of
//!   a second camera (or of the same camera at another focus or zoom) all one way. The views
//!   are split along the main direction of their whitened pulls, each group is calibrated
//!   alone, every view goes to the group whose intrinsics fit it better (its own pose
//!   re-fitted), and that is repeated until no view moves. The split is real when two sets of
//!   intrinsics explain the views much better than one: the F statistic of the extra
//!   parameters exceeds [`SPLIT_F_LIMIT`] *and* the residual sum of squares falls by at least
//!   [`SPLIT_SSR_DROP`]. (Both are far above what splitting one camera's views gives, which
//!   the tests measure: the search for a split makes F larger than the textbook F
//!   distribution says.)
//! - **Verdict** ([`verdict`]): good / usable / poor from the number of views, the coverage
//!   of the image, the reprojection RMS, the error the parameters' σ means for a deflection at
//!   the test's distance, and parameters the views do not determine; with hints.

use std::fmt::Write as _;

use nalgebra::DMatrix;

use crate::error::CalibrateError;
use crate::fit::CalibrationRun;
use crate::report::{uncertainty_at, Coverage};
use crate::solve::{self, SolveOptions, View};
use crate::target::{BoardSeen, TargetSpec};
use tagdeflect_core::camera::CameraIntrinsics;

/// Views below which a calibration is refused without `--force`.
pub const MIN_VIEWS: usize = 10;

/// Views from which the view count is good.
pub const GOOD_VIEWS: usize = 15;

/// Views needed at all (with `--force`): Zhang's start needs three.
pub const ABSOLUTE_MIN_VIEWS: usize = 3;

/// Reprojection RMS up to which a calibration is good / usable, px.
pub const RMS_GOOD_PX: f64 = 0.5;
/// See [`RMS_GOOD_PX`].
pub const RMS_USABLE_PX: f64 = 1.0;

/// The deflection whose error the verdict weighs, mm.
pub const VERDICT_DEFLECTION_MM: f64 = 10.0;
/// 1-σ error of a [`VERDICT_DEFLECTION_MM`] deflection in the image corner up to which the
/// calibration is good (0.1 %, below the measurement's own scatter of a few µm per tag),
/// mm.
pub const DEFLECTION_GOOD_MM: f64 = 0.010;
/// The same, usable (0.25 %).
pub const DEFLECTION_USABLE_MM: f64 = 0.025;

/// The F statistic above which two groups of views are two cameras (or focus settings).
pub const SPLIT_F_LIMIT: f64 = 25.0;
/// The fraction of the residual sum of squares two sets of intrinsics must remove.
pub const SPLIT_SSR_DROP: f64 = 0.2;

/// A relative σ (of a focal length, a scale) above which the figure is said "undetermined".
pub const UNDETERMINED_RELATIVE: f64 = 0.5;

/// `± σ` in `unit` (`sigma` times `scale`, `decimals` places), or `undetermined` when σ is not
/// finite or larger than `of` (the figure it is the σ of, in `sigma`'s unit): a σ of 181 mm on
/// a 10 mm deflection says that the views do not determine it, not a number to read.
pub fn sigma_text(sigma: f64, of: f64, scale: f64, decimals: usize, unit: &str) -> String {
    if sigma.is_finite() && sigma <= of {
        format!("± {:.*} {unit}", decimals, scale * sigma)
    } else {
        "undetermined".into()
    }
}

fn list(names: &[&str], max: usize) -> String {
    if names.len() <= max {
        names.join(", ")
    } else {
        format!("{} and {} more", names[..max].join(", "), names.len() - max)
    }
}

/// Ranges of sorted ids, `0..5, 9, 12..13`.
fn id_ranges(ids: &[u32]) -> String {
    let mut out = Vec::new();
    let mut i = 0;
    while i < ids.len() {
        let mut j = i;
        while j + 1 < ids.len() && ids[j + 1] == ids[j] + 1 {
            j += 1;
        }
        out.push(if j > i { format!("{}..{}", ids[i], ids[j]) } else { ids[i].to_string() });
        i = j + 1;
    }
    out.join(", ")
}

/// Refuses a `--target` that is not the board the images show (see the module docs);
/// `seen` holds what the detector saw in every view where it found the target. `force` lets
/// a board that only partly matches through (never a board that shows more corners than
/// declared: its corners would be mislabelled).
pub fn check_board(spec: &TargetSpec, text: &str, seen: &[(String, BoardSeen)], force: bool) -> Result<(), CalibrateError> {
    if seen.is_empty() {
        return Ok(());
    }
    let target = format!("--target {text}");
    match *spec {
        TargetSpec::Checkerboard { cols, rows, .. } => {
            let larger: Vec<(&str, (u32, u32))> =
                seen.iter().filter_map(|(n, s)| s.grid.filter(|g| g.0 > cols || g.1 > rows).map(|g| (n.as_str(), g))).collect();
            if !larger.is_empty() {
                let (_, (a, b)) = larger[0];
                let names: Vec<&str> = larger.iter().map(|(n, _)| *n).collect();
                return Err(CalibrateError::BoardMismatch(format!(
                    "{target} declares {cols}x{rows} inner corners, but {} of {} views show more: a {a}x{b} grid in {}; \
                     count the inner corners (where four squares meet) along each side of the board",
                    larger.len(),
                    seen.len(),
                    list(&names, 3)
                )));
            }
            let whole = seen.iter().filter(|(_, s)| s.grid == Some((cols, rows))).count();
            if whole == 0 && !force {
                let (name, best) =
                    seen.iter().filter_map(|(n, s)| s.grid.map(|g| (n.as_str(), g))).max_by_key(|(_, g)| g.0 * g.1).unwrap_or(("", (0, 0)));
                return Err(CalibrateError::BoardMismatch(format!(
                    "{target} declares {cols}x{rows} inner corners, but no view shows the whole board: the largest grid seen is \
                     {}x{} (in {name}). Is the board {}x{}? Partial views are used, but at least one view must show the whole \
                     board; --force calibrates anyway",
                    best.0, best.1, best.0, best.1
                )));
            }
        }
        TargetSpec::TagBoard { .. } | TargetSpec::AprilGrid { .. } => {
            let (family, cols, rows, first_id) = match *spec {
                TargetSpec::TagBoard { family, cols, rows, first_id, .. } => (family, cols, rows, first_id),
                TargetSpec::AprilGrid { cols, rows, .. } => (tagdeflect_core::tags::TagFamily::Tag36h11, cols, rows, 0),
                TargetSpec::Checkerboard { .. } => unreachable!("matched above"),
            };
            let last = first_id + cols * rows - 1;
            let mut outside: Vec<u32> = seen.iter().flat_map(|(_, s)| s.outside_ids.iter().copied()).collect();
            outside.sort_unstable();
            outside.dedup();
            if !outside.is_empty() && !force {
                let names: Vec<&str> = seen.iter().filter(|(_, s)| !s.outside_ids.is_empty()).map(|(n, _)| n.as_str()).collect();
                return Err(CalibrateError::BoardMismatch(format!(
                    "{target} declares {family} ids {first_id}..{last} ({cols}x{rows} tags), but tags {} of {family} are seen too \
                     (in {}): is the board larger, or does it start at another id (FIRST_ID)? --force ignores them",
                    id_ranges(&outside),
                    list(&names, 3)
                )));
            }
            let mut found: Vec<u32> = seen.iter().flat_map(|(_, s)| s.ids.iter().copied()).collect();
            found.sort_unstable();
            found.dedup();
            let missing: Vec<u32> = (first_id..=last).filter(|i| found.binary_search(i).is_err()).collect();
            if !missing.is_empty() && !force {
                return Err(CalibrateError::BoardMismatch(format!(
                    "{target} declares {family} ids {first_id}..{last} ({cols}x{rows} tags), but ids {} are in none of the {} \
                     views: is the board smaller? --force calibrates anyway",
                    id_ranges(&missing),
                    seen.len()
                )));
            }
        }
    }
    Ok(())
}

/// Two groups of views that two sets of intrinsics explain much better than one.
#[derive(Debug, Clone, PartialEq)]
pub struct Split {
    /// Indices (into the run's views) of the larger group (the first when they are equal).
    pub majority: Vec<usize>,
    /// Indices of the other group.
    pub minority: Vec<usize>,
    /// The intrinsics of the larger and the smaller group.
    pub intrinsics: [CameraIntrinsics; 2],
    /// RMS with one set of intrinsics for all views, px.
    pub rms_joint_px: f64,
    /// RMS with one set per group, px.
    pub rms_split_px: f64,
    /// F statistic of the second set of intrinsics.
    pub f: f64,
}

impl Split {
    /// What the split is, for messages: both groups with their focal length and principal
    /// point, and the RMS with one and with two sets of intrinsics.
    pub fn describe(&self, views: &[View]) -> String {
        let names = |idx: &[usize]| -> Vec<&str> { idx.iter().map(|&i| views[i].name.as_str()).collect() };
        let k = |k: &CameraIntrinsics| format!("fx {:.1}, cx {:.1}, cy {:.1}, k1 {:.3}", k.fx, k.cx, k.cy, k.dist[0]);
        format!(
            "{} views ({}) fit {}; {} views ({}) fit {}; reprojection RMS {:.3} px with one camera, {:.3} px with two (F = {:.0})",
            self.majority.len(),
            list(&names(&self.majority), 4),
            k(&self.intrinsics[0]),
            self.minority.len(),
            list(&names(&self.minority), 4),
            k(&self.intrinsics[1]),
            self.rms_joint_px,
            self.rms_split_px,
            self.f
        )
    }
}

/// Searches the run's views for two groups seen by different cameras (or focus settings);
/// see the module docs. `None` when there are fewer than six views, no split holds at least
/// three views a side, or the split is not significant.
pub fn split_views(run: &CalibrationRun, options: &SolveOptions) -> Option<Split> {
    split_views_stats(run, options).filter(SplitStats::significant).map(|s| s.split)
}

/// The best split and its statistics whether significant or not (what the tests look at).
#[derive(Debug, Clone, PartialEq)]
pub struct SplitStats {
    /// The split.
    pub split: Split,
    /// Fraction of the joint residual sum of squares the second set removes.
    pub ssr_drop: f64,
}

impl SplitStats {
    /// Both limits exceeded.
    pub fn significant(&self) -> bool {
        self.split.f > SPLIT_F_LIMIT && self.ssr_drop > SPLIT_SSR_DROP
    }
}

/// The search of [`split_views`], returning the best split found with its statistics.
pub fn split_views_stats(run: &CalibrationRun, options: &SolveOptions) -> Option<SplitStats> {
    let views = &run.views;
    let n = views.len();
    if n < 2 * ABSOLUTE_MIN_VIEWS {
        return None;
    }
    let (w, h) = (run.calibration.intrinsics.width, run.calibration.intrinsics.height);
    let pulls = solve::view_pulls(&run.calibration, views, options)?;
    let m = pulls.first()?.len();
    let mut scatter = DMatrix::<f64>::zeros(m, m);
    for p in &pulls {
        scatter += p * p.transpose();
    }
    let eig = scatter.symmetric_eigen();
    let (imax, _) = eig.eigenvalues.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1))?;
    let dir = eig.eigenvectors.column(imax).into_owned();
    let mut in_a: Vec<bool> = pulls.iter().map(|p| p.dot(&dir) >= 0.0).collect();
    let group =
        |in_a: &[bool], a: bool| -> Vec<View> { views.iter().zip(in_a).filter(|(_, g)| **g == a).map(|(v, _)| v.clone()).collect() };
    let mut fits = None;
    for _ in 0..8 {
        let (ga, gb) = (group(&in_a, true), group(&in_a, false));
        if ga.len() < ABSOLUTE_MIN_VIEWS || gb.len() < ABSOLUTE_MIN_VIEWS {
            return None;
        }
        let ca = solve::calibrate(&ga, w, h, options).ok()?;
        let cb = solve::calibrate(&gb, w, h, options).ok()?;
        let next: Vec<bool> = views
            .iter()
            .zip(&in_a)
            .map(|(v, &was)| {
                let sa = solve::view_ssr(&ca.intrinsics, v).unwrap_or(f64::INFINITY);
                let sb = solve::view_ssr(&cb.intrinsics, v).unwrap_or(f64::INFINITY);
                if sa == sb {
                    was
                } else {
                    sa < sb
                }
            })
            .collect();
        let stable = next == in_a;
        fits = Some((ca, cb, ga, gb, in_a.clone()));
        if stable {
            break;
        }
        in_a = next;
    }
    let (ca, cb, ga, gb, in_a) = fits?;
    let npts = |v: &[View]| -> f64 { v.iter().map(|v| v.object.len()).sum::<usize>() as f64 };
    let ssr = |c: &solve::Calibration, v: &[View]| c.rms_px * c.rms_px * npts(v);
    let ssr_split = ssr(&ca, &ga) + ssr(&cb, &gb);
    let ssr_joint = ssr(&run.calibration, views);
    let total_pts = npts(views);
    let free = run.calibration.parameters - 6 * n;
    let dof = (2.0 * total_pts - (2 * free + 6 * n) as f64).max(1.0);
    let f = ((ssr_joint - ssr_split) / free.max(1) as f64) / (ssr_split / dof).max(1e-300);
    let a: Vec<usize> = (0..n).filter(|&i| in_a[i]).collect();
    let b: Vec<usize> = (0..n).filter(|&i| !in_a[i]).collect();
    let (majority, minority, intrinsics) =
        if a.len() >= b.len() { (a, b, [ca.intrinsics, cb.intrinsics]) } else { (b, a, [cb.intrinsics, ca.intrinsics]) };
    Some(SplitStats {
        split: Split {
            majority,
            minority,
            intrinsics,
            rms_joint_px: run.calibration.rms_px,
            rms_split_px: (ssr_split / total_pts).sqrt(),
            f,
        },
        ssr_drop: 1.0 - ssr_split / ssr_joint.max(1e-300),
    })
}

/// The overall grade of a calibration.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Grade {
    /// Ready for a test.
    Good,
    /// Usable, with the reasons why not good.
    Usable,
    /// Not fit for a test: calibrate again.
    Poor,
}

impl std::fmt::Display for Grade {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Grade::Good => "good",
            Grade::Usable => "usable",
            Grade::Poor => "poor",
        })
    }
}

/// The verdict on a calibration: a grade, the reasons (each with its own grade) and hints.
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    /// The worst of the reasons' grades.
    pub grade: Grade,
    /// Every criterion with its grade and figures.
    pub reasons: Vec<(Grade, String)>,
    /// What to do for a better calibration.
    pub hints: Vec<String>,
}

impl Verdict {
    /// The verdict as text lines (what `tagdeflect calibrate` prints).
    pub fn text(&self) -> String {
        let mut out = String::new();
        let _ = writeln!(out, "verdict: {}", self.grade.to_string().to_uppercase());
        for (g, r) in &self.reasons {
            let _ = writeln!(out, "  [{g:<6}] {r}");
        }
        for h in &self.hints {
            let _ = writeln!(out, "  hint: {h}");
        }
        out
    }
}

/// The verdict on `run` (see the module docs) for a test at `distance_mm`.
pub fn verdict(run: &CalibrationRun, coverage: &Coverage, distance_mm: f64) -> Verdict {
    let c = &run.calibration;
    let k = &c.intrinsics;
    let s = c.sigmas();
    let v = solve::to_vector(k);
    let mut reasons = Vec::new();
    let mut hints = Vec::new();
    let nv = run.views.len();
    let g = if nv >= GOOD_VIEWS {
        Grade::Good
    } else if nv >= MIN_VIEWS {
        Grade::Usable
    } else {
        Grade::Poor
    };
    reasons.push((g, format!("{nv} views (good from {GOOD_VIEWS}, usable from {MIN_VIEWS})")));
    if g != Grade::Good {
        hints.push(format!("take {} more views (15–30 in all), tilted up to ~45° both ways", GOOD_VIEWS - nv));
    }
    let empty = coverage.empty_corners.len();
    let g = match (coverage.warning().is_some(), coverage.covered_fraction) {
        (false, _) => Grade::Good,
        (true, f) if f >= 0.4 => Grade::Usable,
        _ => Grade::Poor,
    };
    let mut cov_text = format!("coverage {:.0} % of the image cells", 100.0 * coverage.covered_fraction);
    if empty > 0 {
        let _ = write!(cov_text, ", no points in the {} corner(s)", coverage.empty_corners.join(", "));
    }
    let _ = write!(cov_text, ", {} of {} border cells empty", coverage.empty_border_cells, coverage.border_cells);
    reasons.push((g, cov_text));
    if g != Grade::Good {
        let where_ = if empty > 0 { format!("in the {} corner(s) and ", coverage.empty_corners.join(", ")) } else { String::new() };
        hints
            .push(format!("add views with the target {where_}along the image borders (distortion is largest there; see the coverage map)"));
    }
    let g = if c.rms_px <= RMS_GOOD_PX {
        Grade::Good
    } else if c.rms_px <= RMS_USABLE_PX {
        Grade::Usable
    } else {
        Grade::Poor
    };
    reasons.push((g, format!("reprojection RMS {:.3} px (good up to {RMS_GOOD_PX} px, usable up to {RMS_USABLE_PX} px)", c.rms_px)));
    if g != Grade::Good {
        let worst = c.view_rms_px.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map(|(i, r)| (run.views[i].name.as_str(), *r));
        if let Some((name, r)) = worst {
            hints.push(format!(
                "an RMS this high means blur, a target that is not flat, or wrong corners: look at the worst view, {name} ({r:.3} px)"
            ));
        }
    }
    let u = uncertainty_at(k, &c.covariance, distance_mm, VERDICT_DEFLECTION_MM);
    let corner = u.iter().find(|p| p.place == "corner").map_or(f64::NAN, |p| p.displacement_error_mm);
    let g = if corner <= DEFLECTION_GOOD_MM {
        Grade::Good
    } else if corner <= DEFLECTION_USABLE_MM {
        Grade::Usable
    } else {
        Grade::Poor
    };
    reasons.push((
        g,
        format!(
            "a {VERDICT_DEFLECTION_MM:.0} mm deflection at {distance_mm:.0} mm in the image corner {} from the parameters' σ \
             (fx {}; good up to {:.0} µm, usable up to {:.0} µm)",
            sigma_text(corner, VERDICT_DEFLECTION_MM, 1e3, 1, "µm"),
            sigma_text(s[0] / k.fx, UNDETERMINED_RELATIVE, 1e6, 0, "ppm"),
            1e3 * DEFLECTION_GOOD_MM,
            1e3 * DEFLECTION_USABLE_MM
        ),
    ));
    if g != Grade::Good {
        hints.push("more views, and views that fill the image and tilt the target, shrink the parameters' σ".into());
    }
    // k3: the usual undetermined parameter of an ordinary lens.
    if s[8] > 0.0 && v[8].abs() < 2.0 * s[8] {
        reasons.push((Grade::Usable, format!("k3 = {:.4} ± {:.4} is not determined by these views (|k3| < 2σ)", v[8], s[8])));
        hints.push(
            "--fix-k3 (k3 = 0, the usual choice for a lens that is not wide-angle): an undetermined k3 widens the other \
             parameters' σ and extrapolates badly outside the views"
                .into(),
        );
    }
    if !run.rejected.is_empty() {
        let names: Vec<&str> = run.rejected.iter().map(|r| r.name.as_str()).collect();
        reasons.push((Grade::Good, format!("{} views rejected ({}), see above", names.len(), list(&names, 4))));
    }
    let grade = reasons.iter().map(|(g, _)| *g).max().unwrap_or(Grade::Good);
    Verdict { grade, reasons, hints }
}
