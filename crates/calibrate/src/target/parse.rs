//! The `--target` syntax (module docs of [`crate::target`]) parsed into a [`TargetSpec`].

use tagdeflect_core::tags::TagFamily;

use super::TargetSpec;

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
                let family: TagFamily = parts[1].parse().map_err(|e: tagdeflect_core::tags::UnknownTagFamily| err(&e.to_string()))?;
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
                if parts.len() != 4 {
                    return Err(err("expected aprilgrid:COLSxROWS:TAG_M:SPACING_RATIO (Kalibr's tagCols x tagRows, tagSize in metres, \
                         tagSpacing), e.g. aprilgrid:6x6:0.088:0.3"));
                }
                let (cols, rows) = parse_dims(parts[1]).ok_or_else(|| err("COLSxROWS must be two positive numbers of tags, e.g. 6x6"))?;
                let t = parts[2].trim();
                let tag_mm = if let Some(mm) = t.strip_suffix("mm") {
                    mm.trim().parse::<f64>().ok()
                } else {
                    t.trim_end_matches('m').trim().parse::<f64>().ok().map(|m| 1000.0 * m)
                }
                .filter(|v| v.is_finite() && *v > 0.0)
                .ok_or_else(|| err("TAG_M must be the tag edge in metres (Kalibr's tagSize, e.g. 0.088) or in mm with a unit (88mm)"))?;
                let spacing: f64 = parts[3]
                    .trim()
                    .parse()
                    .ok()
                    .filter(|v: &f64| v.is_finite() && (0.05..=2.0).contains(v))
                    .ok_or_else(|| err("SPACING_RATIO must be the gap over the tag edge (Kalibr's tagSpacing, 0.05 to 2, e.g. 0.3)"))?;
                if cols as u64 * rows as u64 > TagFamily::Tag36h11.code_count() as u64 {
                    return Err(err(&format!("{cols}x{rows} tags exceed the {} codes of tag36h11", TagFamily::Tag36h11.code_count())));
                }
                Ok(TargetSpec::AprilGrid { cols, rows, tag_mm, spacing })
            }
            _ => Err(err(
                "unknown target: expected checkerboard:COLSxROWS:SQUARE_MM, tagboard:FAMILY:COLSxROWS:SIZE_MM:PITCH_MM[:FIRST_ID] \
                 or aprilgrid:COLSxROWS:TAG_M:SPACING_RATIO",
            )),
        }
    }
}
