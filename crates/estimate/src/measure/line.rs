//! Stage 6, line: the feed line of a frame set from its cameras' health, its tags'
//! estimates and its gauges — the tags rounded for the feed, the net deflection, the UTM's
//! load and stroke at the set's time, the clock check.

use std::collections::{BTreeMap, HashMap};

use nalgebra::Vector3;
use tagdeflect_core::feed::{round_mm, FeedLine, FeedTag, GaugeReading};
use tagdeflect_core::frame::FrameSet;
use tagdeflect_core::rig::TagRole;

use super::estimate::{Estimates, NetInput, TagEstimate};
use super::pose::CameraPoses;
use super::Measurement;

/// The net deflection of a frame set.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct NetDeflection {
    /// Mean downward displacement of the midspan tags minus that of the support tags, mm
    /// (rounded for the feed).
    pub(super) value_mm: f64,
    /// Its 1 σ, mm.
    pub(super) sigma_mm: f64,
    /// Its rate, mm/s, when every tag has one.
    pub(super) rate_mm_per_s: Option<f64>,
}

impl Measurement {
    /// The feed line of a frame set.
    pub(super) fn line(
        &mut self,
        set: &FrameSet,
        cameras: CameraPoses,
        estimates: Estimates,
        gauges: BTreeMap<String, GaugeReading>,
    ) -> FeedLine {
        let tags: Vec<FeedTag> = estimates.tags.iter().map(feed_tag).collect();
        let inputs: Vec<&NetInput> = estimates.tags.iter().map(|t| &t.net).collect();
        let net = net_deflection(&self.up, &self.specimen_ids, &tags, &inputs);
        let (load, stroke) = match self.utm.interpolate(set.t_ns) {
            Some((l, s)) => (Some(l), s),
            None => (None, None),
        };
        self.stats.sets += 1;
        let mut line = FeedLine {
            seq: set.seq,
            t_ns: set.t_ns,
            load_kn: load,
            stroke_mm: stroke,
            tags,
            net_deflection_mm: net.map(|n| n.value_mm),
            net_deflection_sigma_mm: net.map(|n| round_mm(n.sigma_mm.max(1e-5))),
            net_deflection_rate_mm_per_min: net.and_then(|n| n.rate_mm_per_s).map(|r| (r * 60.0 * 1e6).round() / 1e6),
            partial_set: cameras.health.iter().any(|h| !h.frame) || estimates.partial,
            smoothed: false,
            reproj_px: estimates.reproj_px,
            cameras: cameras.health,
            utm: None,
            dropped_sets: None,
            latency_ms: None,
            mqtt_dropped: None,
            recording: None,
            recorder_dropped: None,
            gauges,
            clock_offset_ms: None,
            test: None,
            events: Vec::new(),
        };
        line.clock_offset_ms = self.gauges.clock_offset_ms(&line, &self.utm);
        line
    }
}

/// A tag's estimate as the feed gives it (rounded).
fn feed_tag(t: &TagEstimate) -> FeedTag {
    let (c, disp) = (t.centre_mm, t.disp_mm);
    FeedTag {
        id: t.id,
        pos_mm: [round_mm(c.x), round_mm(c.y), round_mm(c.z)],
        disp_mm: [round_mm(disp.x), round_mm(disp.y), round_mm(disp.z)],
        views: t.solution.views,
        sigma_mm: Some(t.sigma_mm.map(|s| round_mm(s.max(1e-5))).into()),
        disp_sigma_mm: Some(t.disp_sigma_mm.map(|s| round_mm(s.max(1e-5))).into()),
        reproj_px: Some((t.solution.rms_px * 1e3).round() / 1e3),
    }
}

/// Mean downward displacement of midspan tags minus that of support tags (from the feed's
/// rounded `disp_mm`), its 1 σ (the tags' displacement covariances `inputs[i]` of `tags[i]`,
/// tags independent) and its rate (when every tag has one); `None` without a midspan and a
/// support tag.
fn net_deflection(
    up: &Vector3<f64>,
    roles: &HashMap<u32, Option<TagRole>>,
    tags: &[FeedTag],
    inputs: &[&NetInput],
) -> Option<NetDeflection> {
    let down = |t: &FeedTag| -Vector3::from(t.disp_mm).dot(up);
    let mut value = 0.0;
    let mut var = 0.0;
    let mut rate = Some(0.0);
    for (role, sign) in [(TagRole::Midspan, 1.0), (TagRole::Support, -1.0)] {
        let members: Vec<(&FeedTag, &NetInput)> =
            tags.iter().zip(inputs).filter(|(t, _)| roles.get(&t.id).copied().flatten() == Some(role)).map(|(t, i)| (t, *i)).collect();
        if members.is_empty() {
            return None;
        }
        let w = sign / members.len() as f64;
        for (t, i) in members {
            value += w * down(t);
            var += w * w * (up.transpose() * i.cov * up)[(0, 0)];
            rate = rate.zip(i.rate).map(|(r, v)| r - w * v.dot(up));
        }
    }
    Some(NetDeflection { value_mm: round_mm(value), sigma_mm: var.max(0.0).sqrt(), rate_mm_per_s: rate })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix3;

    fn tag(id: u32, disp_z_mm: f64) -> FeedTag {
        FeedTag { id, pos_mm: [0.0; 3], disp_mm: [0.0, 0.0, disp_z_mm], views: 2, sigma_mm: None, disp_sigma_mm: None, reproj_px: None }
    }

    #[test]
    fn net_deflection_is_midspan_minus_supports_down() {
        let roles: HashMap<u32, Option<TagRole>> =
            [(0, Some(TagRole::Midspan)), (1, Some(TagRole::Support)), (2, Some(TagRole::Support)), (3, None)].into();
        let tags = [tag(0, -0.5), tag(1, -0.1), tag(2, -0.1), tag(3, -9.0)];
        let input = |rate_z: f64| NetInput { cov: Matrix3::identity() * 1e-4, rate: Some(Vector3::new(0.0, 0.0, rate_z)) };
        let inputs = [input(-0.01), input(0.0), input(0.0), input(0.0)];
        let refs: Vec<&NetInput> = inputs.iter().collect();
        let net = net_deflection(&Vector3::z(), &roles, &tags, &refs).unwrap();
        assert!((net.value_mm - 0.4).abs() < 1e-12, "{net:?}");
        // σ² = 1·1e-4 + 2·(½)²·1e-4.
        assert!((net.sigma_mm - 1.5e-4f64.sqrt()).abs() < 1e-12, "{net:?}");
        assert!((net.rate_mm_per_s.unwrap() - 0.01).abs() < 1e-12, "{net:?}");
        // Without a support tag there is none.
        assert_eq!(net_deflection(&Vector3::z(), &roles, &tags[..1], &refs[..1]), None);
    }
}
