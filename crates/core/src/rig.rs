//! The rig's geometry as the config gives it: `[world]`, `[background]` (tags at known world
//! positions) and `[specimen]` (the tags to measure, their roles, `[specimen.beam]`).

use serde::{Deserialize, Serialize};

use crate::beam::BeamConfig;
use crate::tags::TagFamily;

/// `[world]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldConfig {
    /// World direction that points up (normalised on load); deflection is positive downward.
    pub up: [f64; 3],
}

impl Default for WorldConfig {
    fn default() -> Self {
        Self { up: [0.0, 0.0, 1.0] }
    }
}

/// `[background]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackgroundConfig {
    /// Tag family name, e.g. `tag25h9`.
    pub family: TagFamily,
    /// Edge of the black square, mm.
    pub size_mm: f64,
    /// The tags with their world corners.
    #[serde(rename = "tag")]
    pub tags: Vec<BackgroundTag>,
}

/// One background tag at a known world position.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackgroundTag {
    /// Tag id within the background family.
    pub id: u32,
    /// World corners of the black square: bottom-left, bottom-right, top-right, top-left
    /// as the tag is printed.
    pub corners_mm: [[f64; 3]; 4],
}

/// `[specimen]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpecimenConfig {
    /// Tag family name, e.g. `tag36h11`.
    pub family: TagFamily,
    /// Edge of the black square, mm.
    pub size_mm: f64,
    /// The tags to measure.
    #[serde(rename = "tag")]
    pub tags: Vec<SpecimenTag>,
    /// `[specimen.beam]`: the specimen's geometry (for the report).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub beam: Option<BeamConfig>,
}

/// One specimen tag.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpecimenTag {
    /// Tag id within the specimen family.
    pub id: u32,
    /// Optional role for the net deflection.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub role: Option<TagRole>,
}

/// Role of a specimen tag in the net deflection (ASTM C1609 sense).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TagRole {
    /// Over a support.
    Support,
    /// At midspan.
    Midspan,
}

impl WorldConfig {
    /// `[world]` checked, `up` normalised; keys relative to `[world]`.
    pub fn normalised(&self) -> Result<WorldConfig, crate::Problem> {
        let v = self.up;
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        if !(n.is_finite() && n > 1e-9) {
            return Err(crate::Problem::new("up", "must be a non-zero direction, e.g. [0.0, 0.0, 1.0]"));
        }
        Ok(WorldConfig { up: [v[0] / n, v[1] / n, v[2] / n] })
    }
}

/// `[background]` as written (checked by [`resolve_tag_sets`]).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackgroundSection {
    /// Tag family name.
    pub family: String,
    /// Edge of the black square, mm.
    pub size_mm: f64,
    /// The tags with their world corners.
    #[serde(default)]
    pub tag: Vec<BackgroundTagSection>,
    /// Not allowed here (the beam belongs in `[specimen.beam]`); read to say so.
    #[serde(default)]
    pub beam: Option<serde::de::IgnoredAny>,
}

/// One `[[background.tag]]` as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackgroundTagSection {
    /// Tag id.
    pub id: u32,
    /// World corners, mm.
    pub corners_mm: Vec<Vec<f64>>,
}

/// `[specimen]` as written (checked by [`resolve_tag_sets`]).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpecimenSection {
    /// Tag family name.
    pub family: String,
    /// Edge of the black square, mm.
    pub size_mm: f64,
    /// The tags to measure.
    #[serde(default)]
    pub tag: Vec<SpecimenTag>,
    /// `[specimen.beam]`.
    #[serde(default)]
    pub beam: Option<BeamConfig>,
}

/// `[background]` and `[specimen]` checked together (the ids they must not share); keys are
/// whole paths (`background.tag[1].corners_mm`).
pub fn resolve_tag_sets(
    background: Option<&BackgroundSection>,
    specimen: Option<&SpecimenSection>,
) -> Result<(BackgroundConfig, SpecimenConfig), crate::Problem> {
    use crate::Problem;
    let bg = background.ok_or_else(|| Problem::new("background", "a [background] section is required"))?;
    let background = resolve_background(bg).map_err(|p| p.within("background"))?;
    let sp = specimen.ok_or_else(|| Problem::new("specimen", "a [specimen] section is required"))?;
    let specimen = resolve_specimen(sp).map_err(|p| p.within("specimen"))?;
    if specimen.family == background.family {
        if let Some(t) = specimen.tags.iter().find(|t| background.tags.iter().any(|b| b.id == t.id)) {
            return Err(Problem::new(
                "specimen.tag.id",
                format!(
                    "id {} is both a background and a specimen tag of {}: with one family for both, ids must differ",
                    t.id, specimen.family
                ),
            ));
        }
    }
    Ok((background, specimen))
}

fn parse_family(f: &str) -> Result<TagFamily, crate::Problem> {
    f.parse::<TagFamily>().map_err(|e| crate::Problem::new("family", e.to_string()))
}

fn check_size(v: f64) -> Result<f64, crate::Problem> {
    if !(v.is_finite() && v > 0.0) {
        return Err(crate::Problem::new("size_mm", format!("must be a positive edge length in mm, got {v}")));
    }
    Ok(v)
}

/// A tag id of `family` at `key`: within the family's codes, not seen before in its set.
fn check_id(family: TagFamily, id: u32, seen: bool, set: &str, key: &str) -> Result<(), crate::Problem> {
    if seen {
        return Err(crate::Problem::new(format!("{key}.id"), format!("duplicate {set} tag id {id}")));
    }
    if id >= family.code_count() {
        return Err(crate::Problem::new(format!("{key}.id"), format!("{family} has ids 0..{}, got {id}", family.code_count() - 1)));
    }
    Ok(())
}

fn resolve_background(bg: &BackgroundSection) -> Result<BackgroundConfig, crate::Problem> {
    use crate::Problem;
    if bg.beam.is_some() {
        return Err(Problem::new("beam", "the beam's geometry belongs in [specimen.beam]"));
    }
    let family = parse_family(&bg.family)?;
    let size_mm = check_size(bg.size_mm)?;
    if bg.tag.is_empty() {
        return Err(Problem::new("tag", "at least one [[background.tag]] with world corners is required"));
    }
    let mut tags: Vec<BackgroundTag> = Vec::new();
    for (i, t) in bg.tag.iter().enumerate() {
        let key = format!("tag[{i}]");
        let id = t.id;
        check_id(family, id, tags.iter().any(|o| o.id == id), "background", &key)?;
        let c = &t.corners_mm;
        if c.len() != 4 || c.iter().any(|p| p.len() != 3) {
            return Err(Problem::new(
                format!("{key}.corners_mm"),
                format!("expected 4 corners of [x, y, z] mm (bottom-left, bottom-right, top-right, top-left), got {} corners", c.len()),
            ));
        }
        let p: Vec<[f64; 3]> = c.iter().map(|p| [p[0], p[1], p[2]]).collect();
        check_square(&p, size_mm).map_err(|e| e.within(&key))?;
        tags.push(BackgroundTag { id, corners_mm: [p[0], p[1], p[2], p[3]] });
    }
    Ok(BackgroundConfig { family, size_mm, tags })
}

/// Checks that four world corners form a planar square whose edge matches `size_mm`
/// (within 2 %, so measured positions with small survey errors pass). The problem's key is
/// `corners_mm` (relative to the tag).
fn check_square(p: &[[f64; 3]], size_mm: f64) -> Result<(), crate::Problem> {
    let problem = |m: String| crate::Problem::new("corners_mm", m);
    let v = |a: usize, b: usize| nalgebra::Vector3::new(p[b][0] - p[a][0], p[b][1] - p[a][1], p[b][2] - p[a][2]);
    if p.iter().flatten().any(|x| !x.is_finite()) {
        return Err(problem("corners must be finite numbers".into()));
    }
    let edges = [v(0, 1), v(1, 2), v(2, 3), v(3, 0)];
    let lens: Vec<f64> = edges.iter().map(|e| e.norm()).collect();
    if lens.iter().any(|&l| l < 1e-6) {
        return Err(problem("degenerate square: two corners coincide".into()));
    }
    let mean = lens.iter().sum::<f64>() / 4.0;
    if lens.iter().any(|&l| (l - mean).abs() > 0.02 * mean) {
        return Err(problem(format!("not a square: edge lengths {:.2?} mm differ", lens)));
    }
    let d1 = v(0, 2).norm();
    let d2 = v(1, 3).norm();
    if (d1 - d2).abs() > 0.02 * d1 || (d1 - mean * 2f64.sqrt()).abs() > 0.03 * d1 {
        return Err(problem(format!("not a square: diagonals {d1:.2} and {d2:.2} mm (edges {mean:.2} mm)")));
    }
    let n = edges[0].cross(&edges[1]).normalize();
    if n.dot(&v(0, 3)).abs() > 0.02 * mean {
        return Err(problem("the four corners are not in one plane".into()));
    }
    if (mean - size_mm).abs() > 0.02 * size_mm {
        return Err(problem(format!("edge {mean:.2} mm does not match background.size_mm = {size_mm}")));
    }
    Ok(())
}

fn resolve_specimen(sp: &SpecimenSection) -> Result<SpecimenConfig, crate::Problem> {
    use crate::Problem;
    let family = parse_family(&sp.family)?;
    let size_mm = check_size(sp.size_mm)?;
    if sp.tag.is_empty() {
        return Err(Problem::new("tag", "at least one [[specimen.tag]] is required"));
    }
    let mut tags: Vec<SpecimenTag> = Vec::new();
    for (i, t) in sp.tag.iter().enumerate() {
        let id = t.id;
        check_id(family, id, tags.iter().any(|o| o.id == id), "specimen", &format!("tag[{i}]"))?;
        tags.push(t.clone());
    }
    if let Some(b) = &sp.beam {
        b.validate().map_err(|p| p.within("beam"))?;
    }
    Ok(SpecimenConfig { family, size_mm, tags, beam: sp.beam.clone() })
}

impl SpecimenConfig {
    /// Role of a specimen tag.
    pub fn role_of(&self, id: u32) -> Option<TagRole> {
        self.tags.iter().find(|t| t.id == id).and_then(|t| t.role)
    }
}
