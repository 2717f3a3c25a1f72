//! `[[gauge]]`: the virtual gauges' definitions — the config section and its validation —
//! read by the solver (`tagdeflect_estimate::gauges` computes them), the simulator's truth and
//! the report (which gauge is the net deflection, which the CMOD).

use std::collections::{HashMap, HashSet};

use crate::rig::{SpecimenConfig, TagRole};
use crate::Problem;
use serde::{Deserialize, Serialize};

/// What a gauge measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GaugeKind {
    /// Midspan relative to the supports' line (a yoke), mm.
    NetDeflection,
    /// Change of length between two tags (mm) and strain over the gauge length (µε).
    Distance,
    /// Opening across a notch between two tags, along a direction (CMOD), mm.
    Opening,
    /// A tag's rotation about an axis, mrad.
    Rotation,
    /// Curvature from three tags along the beam, 1/km.
    Curvature,
}

impl GaugeKind {
    const NAMES: &'static str = "\"net_deflection\", \"distance\", \"opening\", \"rotation\" or \"curvature\"";

    /// The kind named in a config (`"opening"`), or `None`.
    pub fn parse(s: &str) -> Option<GaugeKind> {
        Some(match s {
            "net_deflection" => GaugeKind::NetDeflection,
            "distance" => GaugeKind::Distance,
            "opening" => GaugeKind::Opening,
            "rotation" => GaugeKind::Rotation,
            "curvature" => GaugeKind::Curvature,
            _ => return None,
        })
    }

    /// The unit of the gauge's value in the feed.
    pub fn unit(self) -> &'static str {
        match self {
            GaugeKind::NetDeflection | GaugeKind::Distance | GaugeKind::Opening => "mm",
            GaugeKind::Rotation => "mrad",
            GaugeKind::Curvature => "1/km",
        }
    }
}

/// Unit of the `<name>.strain` entry of a `distance` gauge.
pub const STRAIN_UNIT: &str = "µε";

/// One validated `[[gauge]]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GaugeConfig {
    /// Name: the key in the feed's `gauges` (letters, digits, `_`, `-`).
    pub name: String,
    /// What it measures.
    pub kind: GaugeKind,
    /// The specimen tags it uses (`net_deflection`: optional subset, by role).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub tags: Vec<u32>,
    /// `opening`: the direction of the component measured (normalised on load).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direction: Option<[f64; 3]>,
    /// `rotation`: the axis (normalised on load).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis: Option<[f64; 3]>,
    /// `distance`: strain is reported over this length, mm (default: the reference distance).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gauge_length_mm: Option<f64>,
    /// `opening`: the point (world, at rest, mm) where the opening is measured, e.g. the
    /// notch mouth; default midway between the two tags.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub at_mm: Option<[f64; 3]>,
}

/// A `[[gauge]]` as written (the kind as a string, vectors of any length), checked by
/// [`resolve_gauges`].
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GaugeSection {
    name: String,
    kind: String,
    #[serde(default)]
    tags: Option<Vec<u32>>,
    #[serde(default)]
    direction: Option<Vec<f64>>,
    #[serde(default)]
    axis: Option<Vec<f64>>,
    #[serde(default)]
    gauge_length_mm: Option<f64>,
    #[serde(default)]
    at_mm: Option<Vec<f64>>,
}

fn unit_vector(x: &[f64], key: &str) -> Result<[f64; 3], Problem> {
    let err = |m: String| Problem::new(key, m);
    if x.len() != 3 {
        return Err(err(format!("expected [x, y, z], got {} numbers", x.len())));
    }
    let n = (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
    if !(n.is_finite() && n > 1e-9) {
        return Err(err("must be a non-zero direction, e.g. [1.0, 0.0, 0.0]".into()));
    }
    Ok([x[0] / n, x[1] / n, x[2] / n])
}

/// Checks every `[[gauge]]` against the specimen tags (ids, roles) and returns the gauges.
/// `[[gauge]]` is an array of the file's root table, so its keys start there (`gauge[1].tags`),
/// as `[[camera]]`'s do.
pub fn resolve_gauges(raw: &[GaugeSection], specimen: &SpecimenConfig) -> Result<Vec<GaugeConfig>, Problem> {
    let mut names = HashSet::new();
    let mut out = Vec::new();
    let roles: HashMap<u32, Option<TagRole>> = specimen.tags.iter().map(|t| (t.id, t.role)).collect();
    for (i, g) in raw.iter().enumerate() {
        let key = |k: &str| format!("gauge[{i}].{k}");
        let err = |k: &str, m: String| Problem::new(key(k), m);
        let name = g.name.trim().to_string();
        if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-') {
            return Err(err(
                "name",
                format!("\"{name}\": a gauge name is letters, digits, `_` and `-` (it is a feed key and a CSV column)"),
            ));
        }
        if !names.insert(name.clone()) {
            return Err(err("name", format!("duplicate gauge name \"{name}\"")));
        }
        let kind = GaugeKind::parse(g.kind.trim())
            .ok_or_else(|| err("kind", format!("\"{}\" is not a gauge kind: expected {}", g.kind, GaugeKind::NAMES)))?;
        let tags: Vec<u32> = g.tags.clone().unwrap_or_default();
        let needed = match kind {
            GaugeKind::NetDeflection => None,
            GaugeKind::Distance | GaugeKind::Opening => Some(2),
            GaugeKind::Rotation => Some(1),
            GaugeKind::Curvature => Some(3),
        };
        if let Some(n) = needed {
            if tags.len() != n {
                return Err(err(
                    "tags",
                    format!("a {} gauge uses {n} specimen tag{}, got {}", kind_name(kind), if n == 1 { "" } else { "s" }, tags.len()),
                ));
            }
        }
        let mut seen = HashSet::new();
        for id in &tags {
            if !roles.contains_key(id) {
                return Err(err("tags", format!("tag {id} is not a [[specimen.tag]] id")));
            }
            if !seen.insert(*id) {
                return Err(err("tags", format!("tag {id} is listed twice")));
            }
        }
        if kind == GaugeKind::NetDeflection {
            let used: Vec<Option<TagRole>> =
                if tags.is_empty() { roles.values().copied().collect() } else { tags.iter().map(|id| roles[id]).collect() };
            let has = |r: TagRole| used.contains(&Some(r));
            if !has(TagRole::Support) || !has(TagRole::Midspan) {
                return Err(err(
                    "tags",
                    "a net_deflection gauge needs tags with role = \"support\" and role = \"midspan\" (set in [[specimen.tag]])".into(),
                ));
            }
        }
        let direction = match (&g.direction, kind) {
            (Some(d), GaugeKind::Opening) => Some(unit_vector(d, &key("direction"))?),
            (None, GaugeKind::Opening) => {
                return Err(err("direction", "an opening gauge needs `direction = [x, y, z]` (the component measured)".into()))
            }
            (Some(_), GaugeKind::Rotation) => return Err(err("direction", "a rotation gauge takes `axis = [x, y, z]`".into())),
            (Some(_), _) => return Err(err("direction", format!("not used by a {} gauge", kind_name(kind)))),
            (None, _) => None,
        };
        let axis = match (&g.axis, kind) {
            (Some(a), GaugeKind::Rotation) => Some(unit_vector(a, &key("axis"))?),
            (None, GaugeKind::Rotation) => return Err(err("axis", "a rotation gauge needs `axis = [x, y, z]`".into())),
            (Some(_), _) => return Err(err("axis", format!("not used by a {} gauge", kind_name(kind)))),
            (None, _) => None,
        };
        let gauge_length_mm = match &g.gauge_length_mm {
            None => None,
            Some(l) if kind != GaugeKind::Distance => {
                return Err(err("gauge_length_mm", format!("not used by a {} gauge", kind_name(kind))))
            }
            Some(l) => {
                let v = *l;
                if !(v.is_finite() && v > 0.0) {
                    return Err(err("gauge_length_mm", format!("must be a positive length in mm, got {v}")));
                }
                Some(v)
            }
        };
        let at_mm = match &g.at_mm {
            None => None,
            Some(a) if kind != GaugeKind::Opening => return Err(err("at_mm", format!("not used by a {} gauge", kind_name(kind)))),
            Some(a) => {
                let v = a;
                if v.len() != 3 || v.iter().any(|x| !x.is_finite()) {
                    return Err(err("at_mm", "expected a point [x, y, z] in mm".into()));
                }
                Some([v[0], v[1], v[2]])
            }
        };
        out.push(GaugeConfig { name, kind, tags, direction, axis, gauge_length_mm, at_mm });
    }
    Ok(out)
}

fn kind_name(kind: GaugeKind) -> &'static str {
    match kind {
        GaugeKind::NetDeflection => "net_deflection",
        GaugeKind::Distance => "distance",
        GaugeKind::Opening => "opening",
        GaugeKind::Rotation => "rotation",
        GaugeKind::Curvature => "curvature",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kinds_parse_and_have_units() {
        assert_eq!(GaugeKind::parse("opening"), Some(GaugeKind::Opening));
        assert_eq!(GaugeKind::parse("cmod"), None);
        assert_eq!(GaugeKind::Curvature.unit(), "1/km");
        assert_eq!(GaugeKind::Rotation.unit(), "mrad");
    }
}
