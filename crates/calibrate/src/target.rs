//! Calibration targets: the `--target` syntax, their board geometry and their detection.
//!
//! ```text
//! checkerboard:COLSxROWS:SQUARE_MM                       inner corners, e.g. checkerboard:9x6:25
//! tagboard:FAMILY:COLSxROWS:SIZE_MM:PITCH_MM[:FIRST_ID]  e.g. tagboard:tag36h11:6x4:30:40
//! ```
//!
//! **Checkerboard.** `COLS` × `ROWS` inner corners (OpenCV's `patternSize`), squares of
//! `SQUARE_MM`. Corners are found and labelled by the `calib-targets-chessboard` crate
//! (ChESS X-junction detector + topological grid labelling that tolerates distortion and
//! partial views; MIT/Apache-2.0), then refined here to sub-pixel precision by the gradient
//! orthogonality condition (the method of OpenCV's `cornerSubPix`: at the true saddle every
//! image gradient in the window is orthogonal to the vector from the corner to its pixel),
//! in a window scaled to the local square size. Views that show only part of the board are
//! used: any consistent labelling of a square grid is the board up to a planar isometry,
//! which the view's pose absorbs.
//!
//! **Tag board.** A grid of `COLS` × `ROWS` AprilTags of one family (`tag36h11`,
//! `tag25h9`, `tag16h5`), black-square edge `SIZE_MM` (the same "size" as the config's
//! tags), centre-to-centre pitch `PITCH_MM`, ids row-major from the top-left tag as printed,
//! starting at `FIRST_ID` (default 0). Detected with the product's own detector and its
//! sub-pixel edge refinement (`tagdeflect_detect`), four corners per tag. Board frame: x to the
//! right, y up as printed, origin at the centre of the top-left tag (tag frames as in
//! [`tagdeflect_core::tags::tag_corners`]).
//!
//! Kalibr's AprilGrid (`aprilgrid:...`) is recognised and refused with an explanation: the
//! one Rust detector for it (`aprilgrid`) brings a second linear-algebra stack and every
//! image codec into the build; an AprilGrid's tags have a 2-bit border the AprilTag library
//! does not decode.

use std::fmt::Write as _;

use nalgebra::{Point2, Vector3};

use super::solve::View;
use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::tags::{tag_corners, TagFamily};
use tagdeflect_detect::{Detector, DetectorOptions};

/// A calibration target (parsed `--target`).
#[derive(Debug, Clone, PartialEq)]
pub enum TargetSpec {
    /// A checkerboard of `cols` × `rows` inner corners, `square_mm` squares.
    Checkerboard {
        /// Inner corners per row.
        cols: u32,
        /// Inner corners per column.
        rows: u32,
        /// Square edge, mm.
        square_mm: f64,
    },
    /// A grid of AprilTags.
    TagBoard {
        /// Tag family.
        family: TagFamily,
        /// Tags per row.
        cols: u32,
        /// Tag rows.
        rows: u32,
        /// Black-square edge, mm.
        size_mm: f64,
        /// Centre-to-centre pitch, mm.
        pitch_mm: f64,
        /// Id of the top-left tag; ids run row-major.
        first_id: u32,
    },
}

/// A bad `--target`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("--target {spec:?}: {message}")]
pub struct TargetError {
    /// The text given.
    pub spec: String,
    /// What is wrong.
    pub message: String,
}

fn parse_dims(s: &str) -> Option<(u32, u32)> {
    let (a, b) = s.split_once(['x', 'X'])?;
    let (a, b) = (a.trim().parse().ok()?, b.trim().parse().ok()?);
    (a > 0 && b > 0).then_some((a, b))
}

fn parse_mm(s: &str) -> Option<f64> {
    let t = s.trim().trim_end_matches("mm");
    let v: f64 = t.parse().ok()?;
    (v.is_finite() && v > 0.0).then_some(v)
}

impl std::str::FromStr for TargetSpec {
    type Err = TargetError;

    fn from_str(spec: &str) -> Result<Self, TargetError> {
        let err = |m: &str| TargetError { spec: spec.to_string(), message: m.to_string() };
        let parts: Vec<&str> = spec.split(':').collect();
        match parts[0] {
            "checkerboard" | "chessboard" => {
                if parts.len() != 3 {
                    return Err(err("expected checkerboard:COLSxROWS:SQUARE_MM (inner corners, e.g. checkerboard:9x6:25)"));
                }
                let (cols, rows) =
                    parse_dims(parts[1]).ok_or_else(|| err("COLSxROWS must be two positive numbers of inner corners, e.g. 9x6"))?;
                if cols < 2 || rows < 2 {
                    return Err(err("a checkerboard needs at least 2x2 inner corners"));
                }
                let square_mm = parse_mm(parts[2]).ok_or_else(|| err("SQUARE_MM must be a positive length in mm"))?;
                Ok(TargetSpec::Checkerboard { cols, rows, square_mm })
            }
            "tagboard" => {
                if !(5..=6).contains(&parts.len()) {
                    return Err(err("expected tagboard:FAMILY:COLSxROWS:SIZE_MM:PITCH_MM[:FIRST_ID], e.g. tagboard:tag36h11:6x4:30:40"));
                }
                let family: TagFamily = parts[1].parse().map_err(|e: String| err(&e))?;
                let (cols, rows) = parse_dims(parts[2]).ok_or_else(|| err("COLSxROWS must be two positive numbers of tags, e.g. 6x4"))?;
                let size_mm = parse_mm(parts[3]).ok_or_else(|| err("SIZE_MM (black-square edge) must be a positive length in mm"))?;
                let pitch_mm = parse_mm(parts[4]).ok_or_else(|| err("PITCH_MM must be a positive length in mm"))?;
                if pitch_mm <= size_mm {
                    return Err(err("PITCH_MM must be larger than SIZE_MM (tags may not touch)"));
                }
                let first_id: u32 = match parts.get(5) {
                    Some(s) => s.trim().parse().map_err(|_| err("FIRST_ID must be a tag id"))?,
                    None => 0,
                };
                let last = first_id as u64 + cols as u64 * rows as u64;
                if last > family.code_count() as u64 {
                    return Err(err(&format!("ids {first_id}..{} exceed the {} codes of {family}", last - 1, family.code_count())));
                }
                Ok(TargetSpec::TagBoard { family, cols, rows, size_mm, pitch_mm, first_id })
            }
            "aprilgrid" => {
                Err(err("Kalibr AprilGrid targets are not supported: use a tag board (tagboard:FAMILY:COLSxROWS:SIZE_MM:PITCH_MM) \
                 or a checkerboard; an existing Kalibr calibration can be imported with `calibration = \"camchain.yaml\"`"))
            }
            _ => Err(err(
                "unknown target: expected checkerboard:COLSxROWS:SQUARE_MM or tagboard:FAMILY:COLSxROWS:SIZE_MM:PITCH_MM[:FIRST_ID]",
            )),
        }
    }
}

impl TargetSpec {
    /// Every board point (mm, z = 0), for renderers and tests: checkerboard corners row-major
    /// (`x = col · square`, `y = row · square`); tag-board corners tag by tag in SPEC order.
    pub fn board_points(&self) -> Vec<Vector3<f64>> {
        match *self {
            TargetSpec::Checkerboard { cols, rows, square_mm } => {
                (0..rows).flat_map(|r| (0..cols).map(move |c| Vector3::new(c as f64 * square_mm, r as f64 * square_mm, 0.0))).collect()
            }
            TargetSpec::TagBoard { cols, rows, size_mm, pitch_mm, .. } => (0..rows)
                .flat_map(|r| (0..cols).map(move |c| (r, c)))
                .flat_map(|(r, c)| tag_corners(size_mm).map(|p| p + tag_centre(c, r, pitch_mm)))
                .collect(),
        }
    }

    /// A short text for reports (`checkerboard 9x6, 25 mm squares`).
    pub fn describe(&self) -> String {
        match self {
            TargetSpec::Checkerboard { cols, rows, square_mm } => {
                format!("checkerboard {cols}x{rows} inner corners, {square_mm} mm squares")
            }
            TargetSpec::TagBoard { family, cols, rows, size_mm, pitch_mm, first_id } => {
                format!("{family} board {cols}x{rows}, {size_mm} mm tags at {pitch_mm} mm pitch, ids from {first_id}")
            }
        }
    }
}

/// Centre of tag (`col`, `row`) of a tag board (x right, y up; row 0 at the top).
pub(crate) fn tag_centre(col: u32, row: u32, pitch_mm: f64) -> Vector3<f64> {
    Vector3::new(col as f64 * pitch_mm, -(row as f64) * pitch_mm, 0.0)
}

/// Detects targets in images; holds the AprilTag detector between images.
pub struct TargetDetector {
    spec: TargetSpec,
    tags: Option<Detector>,
}

impl TargetDetector {
    /// A detector for `spec`.
    pub fn new(spec: TargetSpec) -> Result<Self, tagdeflect_detect::DetectError> {
        let tags = match &spec {
            TargetSpec::TagBoard { family, .. } => Some(Detector::new(DetectorOptions::for_families(&[*family]))?),
            TargetSpec::Checkerboard { .. } => None,
        };
        Ok(Self { spec, tags })
    }

    /// Finds the target in `image`: board points and their sub-pixel pixels. `Err` says
    /// why nothing usable was found.
    pub fn detect(&mut self, image: &GrayImage, name: &str) -> Result<View, String> {
        self.detect_seen(image, name).map(|(v, _)| v)
    }

    /// [`detect`](Self::detect), plus what the detector saw of the board beyond the points
    /// used (for [`crate::guard::check_board`]).
    pub fn detect_seen(&mut self, image: &GrayImage, name: &str) -> Result<(View, BoardSeen), String> {
        match self.spec.clone() {
            TargetSpec::Checkerboard { cols, rows, square_mm } => detect_checkerboard(image, name, cols, rows, square_mm),
            TargetSpec::TagBoard { cols, rows, size_mm, pitch_mm, first_id, .. } => {
                let det = self.tags.as_mut().expect("tag detector for a tag board");
                let mut object = Vec::new();
                let mut pixels = Vec::new();
                let mut found = 0;
                let mut seen = BoardSeen::default();
                for d in det.detect(image) {
                    if d.id < first_id || d.id >= first_id + cols * rows {
                        seen.outside_ids.push(d.id);
                        continue;
                    }
                    seen.ids.push(d.id);
                    let k = d.id - first_id;
                    let (c, r) = (k % cols, k / cols);
                    let centre = tag_centre(c, r, pitch_mm);
                    found += 1;
                    for (corner, px) in tag_corners(size_mm).iter().zip(d.corners) {
                        object.push(corner + centre);
                        pixels.push(px);
                    }
                }
                if found < 2 {
                    let mut m = format!("{found} board tags found (need at least 2)");
                    if !seen.outside_ids.is_empty() {
                        seen.outside_ids.sort_unstable();
                        let _ = write!(
                            m,
                            "; tags {:?} of the family seen, outside the board's ids {first_id}..{}",
                            seen.outside_ids,
                            first_id + cols * rows - 1
                        );
                    }
                    return Err(m);
                }
                seen.outside_ids.sort_unstable();
                seen.ids.sort_unstable();
                Ok((View { name: name.to_string(), object, image: pixels }, seen))
            }
        }
    }
}

/// What the detector saw of the board in one view, beyond the points it used: the evidence
/// that the `--target` given is not the board in the images.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BoardSeen {
    /// Checkerboard: the dense grid of inner corners the view shows (outer lines with less
    /// than half of a full line's corners trimmed), in the declared orientation (cols, rows).
    pub grid: Option<(u32, u32)>,
    /// Checkerboard: the whole grid the detector labelled (same orientation).
    pub labelled: Option<(u32, u32)>,
    /// Tag board: the board ids found.
    pub ids: Vec<u32>,
    /// Tag board: ids of the family found outside the board's range.
    pub outside_ids: Vec<u32>,
}

/// Checkerboard corners: ChESS + grid labelling (`calib-targets-chessboard`), trimmed to
/// the board's size, refined by [`refine_saddle`].
fn detect_checkerboard(image: &GrayImage, name: &str, cols: u32, rows: u32, square_mm: f64) -> Result<(View, BoardSeen), String> {
    use calib_targets_chessboard as ct;
    let view = ct::GrayImageView { width: image.width as usize, height: image.height as usize, data: &image.data };
    let corners = ct::detect_corners(&view, &ct::default_chess_config());
    let detector = ct::ChessboardDetector::new(ct::ChessboardParams::default()).map_err(|e| format!("chessboard detector: {e}"))?;
    let det = detector.detect(&corners).ok_or_else(|| format!("no checkerboard found ({} X-junctions)", corners.len()))?;
    let mut pts: Vec<(i32, i32, Point2<f64>)> =
        det.corners.iter().map(|c| (c.grid.u, c.grid.v, Point2::new(c.position.x as f64, c.position.y as f64))).collect();
    // The labelling may be the board transposed (cols along v): pick the orientation whose
    // extent fits, trimming sparse outer lines when the grid is larger than the board.
    let extent = |p: &[(i32, i32, Point2<f64>)]| {
        let (umin, umax) = p.iter().fold((i32::MAX, i32::MIN), |a, q| (a.0.min(q.0), a.1.max(q.0)));
        let (vmin, vmax) = p.iter().fold((i32::MAX, i32::MIN), |a, q| (a.0.min(q.1), a.1.max(q.1)));
        (umin, umax, vmin, vmax)
    };
    let on = |p: &(i32, i32, Point2<f64>), (is_u, k): (bool, i32)| if is_u { p.0 == k } else { p.1 == k };
    let labelled = {
        let (umin, umax, vmin, vmax) = extent(&pts);
        ((umax - umin + 1) as u32, (vmax - vmin + 1) as u32)
    };
    // The dense grid: outer lines holding less than half of a full line's corners trimmed
    // (stray X-junctions next to the board; a line cut by the image's edge) — what the view
    // shows of the board whatever the target declares.
    let dense = {
        let mut q = pts.clone();
        loop {
            let (umin, umax, vmin, vmax) = extent(&q);
            let (eu, ev) = (umax - umin + 1, vmax - vmin + 1);
            let lines = [((true, umin), ev), ((true, umax), ev), ((false, vmin), eu), ((false, vmax), eu)];
            let (line, frac) = lines
                .iter()
                .map(|&(l, len)| (l, q.iter().filter(|p| on(p, l)).count() as f64 / len as f64))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .expect("four lines");
            if frac >= 0.5 || eu <= 2 || ev <= 2 {
                break (eu, ev);
            }
            q.retain(|p| !on(p, line));
        }
    };
    let (cu, cv) = {
        let (eu, ev) = dense;
        // Transposed when that fits better.
        if (eu > ev) == (cols >= rows) {
            (cols as i32, rows as i32)
        } else {
            (rows as i32, cols as i32)
        }
    };
    // Outer lines: (is a u line, index). Drop the sparsest until the grid fits the board.
    loop {
        let (umin, umax, vmin, vmax) = extent(&pts);
        if umax - umin < cu && vmax - vmin < cv {
            break;
        }
        let mut lines: Vec<(bool, i32)> = Vec::new();
        if umax - umin >= cu {
            lines.extend([(true, umin), (true, umax)]);
        }
        if vmax - vmin >= cv {
            lines.extend([(false, vmin), (false, vmax)]);
        }
        let drop = lines.into_iter().min_by_key(|&l| pts.iter().filter(|p| on(p, l)).count()).expect("a line to drop");
        pts.retain(|p| !on(p, drop));
    }
    let min_points = ((cols * rows) as usize / 3).max(6);
    if pts.len() < min_points {
        return Err(format!("only {} checkerboard corners labelled (need {min_points})", pts.len()));
    }
    let (umin, _, vmin, _) = extent(&pts);
    let spacing = det.cell_size.map(|c| c as f64).unwrap_or(20.0);
    let half = (0.4 * spacing).round().clamp(2.0, 11.0) as i32;
    let mut object = Vec::with_capacity(pts.len());
    let mut pixels = Vec::with_capacity(pts.len());
    for (u, v, p) in pts {
        object.push(Vector3::new((u - umin) as f64 * square_mm, (v - vmin) as f64 * square_mm, 0.0));
        pixels.push(refine_saddle(image, p, half).unwrap_or(p));
    }
    // In the declared orientation: (cols, rows) when cols ≥ rows matched u, else swapped.
    let orient = |(a, b): (u32, u32)| if cu as u32 == cols { (a, b) } else { (b, a) };
    let seen = BoardSeen { grid: Some(orient((dense.0 as u32, dense.1 as u32))), labelled: Some(orient(labelled)), ..BoardSeen::default() };
    Ok((View { name: name.to_string(), object, image: pixels }, seen))
}

/// Sub-pixel position of a checkerboard saddle near `start` (OpenCV pixels) from the gradient
/// orthogonality condition in a `(2 half + 1)²` window with Gaussian weights, iterated until
/// it moves less than 0.001 px. `None` when the window leaves the image, the structure
/// tensor is singular, or the corner wanders further than `half` from `start`.
fn refine_saddle(image: &GrayImage, start: Point2<f64>, half: i32) -> Option<Point2<f64>> {
    let (w, h) = (image.width as f64, image.height as f64);
    let hf = half as f64;
    let mut q = start;
    for _ in 0..40 {
        if q.x - hf - 1.0 < 0.0 || q.y - hf - 1.0 < 0.0 || q.x + hf + 1.0 > w - 1.0 || q.y + hf + 1.0 > h - 1.0 {
            return None;
        }
        let (mut a, mut b, mut c, mut bb1, mut bb2) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for j in -half..=half {
            for i in -half..=half {
                let (dx, dy) = (i as f64, j as f64);
                let (x, y) = (q.x + dx, q.y + dy);
                let gx = image.sample(x + 1.0, y) - image.sample(x - 1.0, y);
                let gy = image.sample(x, y + 1.0) - image.sample(x, y - 1.0);
                let m = (-(dx * dx + dy * dy) / (hf * hf)).exp();
                let (gxx, gxy, gyy) = (m * gx * gx, m * gx * gy, m * gy * gy);
                a += gxx;
                b += gxy;
                c += gyy;
                bb1 += gxx * dx + gxy * dy;
                bb2 += gxy * dx + gyy * dy;
            }
        }
        let det = a * c - b * b;
        if det.is_nan() || det.abs() <= 1e-9 * (a * c).abs().max(1e-300) {
            return None;
        }
        let step = nalgebra::Vector2::new(c * bb1 - b * bb2, a * bb2 - b * bb1) / det;
        q += step;
        if (q - start).norm() > hf {
            return None;
        }
        if step.norm() < 1e-3 {
            break;
        }
    }
    Some(q)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_targets_and_names_the_fault() {
        assert_eq!("checkerboard:9x6:25".parse::<TargetSpec>().unwrap(), TargetSpec::Checkerboard { cols: 9, rows: 6, square_mm: 25.0 });
        assert_eq!(
            "tagboard:tag36h11:6x4:30mm:40:10".parse::<TargetSpec>().unwrap(),
            TargetSpec::TagBoard { family: TagFamily::Tag36h11, cols: 6, rows: 4, size_mm: 30.0, pitch_mm: 40.0, first_id: 10 }
        );
        let e = "checkerboard:9:25".parse::<TargetSpec>().unwrap_err();
        assert!(e.to_string().contains("COLSxROWS"), "{e}");
        let e = "tagboard:tag25h9:10x10:30:40".parse::<TargetSpec>().unwrap_err();
        assert!(e.to_string().contains("exceed"), "{e}");
        let e = "aprilgrid:6x6:88mm:0.3".parse::<TargetSpec>().unwrap_err();
        assert!(e.to_string().contains("AprilGrid"), "{e}");
        assert!("tagboard:tag36h11:6x4:40:30".parse::<TargetSpec>().is_err());
    }

    #[test]
    fn saddle_refinement_finds_a_rendered_corner() {
        // An anti-aliased saddle at (20.3, 17.8) with a lens's blur (σ 0.8 px).
        use tagdeflect_sim::render::{blur, gaussian_kernel};
        let (w, h) = (41u32, 37u32);
        let (x0, y0) = (20.3, 17.8);
        let mut area = vec![0.0f32; (w * h) as usize];
        for y in 0..h {
            for x in 0..w {
                // Exact area fractions of the pixel right of and below the corner.
                let fx = (x as f64 + 0.5 - x0).clamp(0.0, 1.0);
                let fy = (y as f64 + 0.5 - y0).clamp(0.0, 1.0);
                let bright = fx * fy + (1.0 - fx) * (1.0 - fy);
                area[(y * w + x) as usize] = (30.0 + 190.0 * bright) as f32;
            }
        }
        let blurred = blur(&area, w as usize, h as usize, &gaussian_kernel(0.8));
        let img = GrayImage { width: w, height: h, data: blurred.iter().map(|v| v.round() as u8).collect() };
        // From where the ChESS detector leaves a corner (within half a pixel).
        for start in [Point2::new(20.0, 18.0), Point2::new(20.6, 17.4)] {
            let q = refine_saddle(&img, start, 6).unwrap();
            assert!((q.x - x0).abs() < 0.05 && (q.y - y0).abs() < 0.05, "{start} → {q}");
        }
    }
}
