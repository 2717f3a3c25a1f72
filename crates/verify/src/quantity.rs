//! The verified quantity: what the reference's displacements are compared with.

use serde::{Deserialize, Serialize};
use tagdeflect_core::feed::FeedLine;

use crate::series::{down_displacement, tag_down_displacement};

/// The quantity a verification compares with the reference (SPEC: the net deflection by
/// default, `--gauge NAME` or `--tag ID` for another).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Quantity {
    /// The feed's `net_deflection_mm` (the default).
    NetDeflection,
    /// A `[[gauge]]`'s value, counted from its value in the feed's first line that has it.
    Gauge(String),
    /// One specimen tag's vertical displacement, downward positive (the sense of a
    /// deflection): `−disp_mm · up`.
    Tag(u32),
    /// (extension) The mean downward displacement of the specimen tags solved in a line.
    TagsMean,
}

impl Quantity {
    /// A short description for the certificate and messages.
    pub fn describe(&self) -> String {
        match self {
            Quantity::NetDeflection => "net deflection".into(),
            Quantity::Gauge(name) => format!("gauge {name}"),
            Quantity::Tag(id) => format!("tag {id} (downward displacement)"),
            Quantity::TagsMean => "mean downward displacement of the specimen tags".into(),
        }
    }

    /// The quantity's reading in each line (`None` where the line lacks it), mm; `up` is the
    /// world's up direction.
    pub fn readings(&self, lines: &[FeedLine], up: [f64; 3]) -> Vec<Option<f64>> {
        match self {
            Quantity::NetDeflection => lines.iter().map(|l| l.net_deflection_mm).collect(),
            Quantity::Gauge(name) => {
                let value = |l: &FeedLine| l.gauges.get(name).map(|g| g.value).filter(|v| v.is_finite());
                let zero = lines.iter().find_map(value).unwrap_or(0.0);
                lines.iter().map(|l| value(l).map(|v| v - zero)).collect()
            }
            Quantity::Tag(id) => lines.iter().map(|l| tag_down_displacement(l, *id, up)).collect(),
            Quantity::TagsMean => lines.iter().map(|l| down_displacement(l, up)).collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tagdeflect_core::feed::GaugeReading;

    #[test]
    fn a_gauge_counts_from_its_first_value_and_a_tag_downward() {
        let mut lines = vec![FeedLine::default(), FeedLine::default(), FeedLine::default()];
        for (l, v) in lines[1..].iter_mut().zip([200.0, 200.25]) {
            l.gauges.insert("span".into(), GaugeReading { value: v, sigma: f64::NAN, unit: "mm".into() });
        }
        let g = Quantity::Gauge("span".into()).readings(&lines, [0.0, 0.0, 1.0]);
        assert_eq!(g, vec![None, Some(0.0), Some(0.25)]);
        lines[2].tags.push(tagdeflect_core::feed::FeedTag {
            id: 4,
            pos_mm: [0.0; 3],
            disp_mm: [0.0, 0.0, -0.5],
            views: 2,
            sigma_mm: None,
            disp_sigma_mm: None,
            reproj_px: None,
        });
        assert_eq!(Quantity::Tag(4).readings(&lines, [0.0, 0.0, 1.0]), vec![None, None, Some(0.5)]);
        assert_eq!(Quantity::NetDeflection.describe(), "net deflection");
    }
}
