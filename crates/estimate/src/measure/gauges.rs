//! Stage 5, gauges: the virtual gauges (`[[gauge]]`, [`crate::gauges`]) of a frame set from
//! its tags' estimates, and the clock check (`[clock_check]`, [`crate::clock_offset`]) that
//! reads the finished line.

use std::collections::BTreeMap;

use tagdeflect_core::feed::{FeedLine, GaugeReading};
use tagdeflect_core::utm_sample::UtmHistory;

use super::estimate::TagEstimate;
use super::MeasurementRig;
use crate::clock_offset::ClockCheck;
use crate::gauges::{GaugeKind, GaugeTag, Gauges};

/// The gauges and the clock check as the measurement uses them.
#[derive(Debug, Clone)]
pub(super) struct LineGauges {
    gauges: Gauges,
    /// The name of the first `net_deflection` gauge (the clock check's net deflection when
    /// the line has none of its own).
    net_gauge: Option<String>,
    clock: ClockCheck,
}

impl LineGauges {
    /// The gauges of `config` (`[[gauge]]`) and its clock check (`[clock_check]`, defaults
    /// when absent; it only answers when the feed has a net deflection and a UTM stroke).
    pub(super) fn new(config: &MeasurementRig) -> LineGauges {
        LineGauges {
            gauges: Gauges::new(&config.gauges, config.world.up, &config.specimen),
            net_gauge: config.gauges.iter().find(|g| g.kind == GaugeKind::NetDeflection).map(|g| g.name.clone()),
            clock: ClockCheck::new(config.clock_check.clone().unwrap_or_default()),
        }
    }

    /// The gauges' readings from the tags estimated in a frame set (tags seen for the first
    /// time become their own reference).
    pub(super) fn process(&mut self, tags: &[TagEstimate]) -> BTreeMap<String, GaugeReading> {
        if self.gauges.is_empty() {
            return BTreeMap::new();
        }
        let tags: Vec<GaugeTag> = tags.iter().map(gauge_tag).collect();
        self.gauges.evaluate(&tags)
    }

    /// The clock check's offset after a finished line (its `gauges` filled): it reads the
    /// line's net deflection (else its `net_deflection` gauge's), load and the UTM history.
    pub(super) fn clock_offset_ms(&mut self, line: &FeedLine, utm: &UtmHistory) -> Option<tagdeflect_core::feed::ValueSigma> {
        let net = line.net_deflection_mm.or_else(|| self.net_gauge.as_ref().and_then(|g| line.gauges.get(g)).map(|r| r.value));
        self.clock.update(line.t_ns, net, line.load_kn, utm)
    }
}

/// A tag as the gauges take it: its pose as reported (after any fusion, whose position
/// covariance replaces the solve's). The gauges use the covariance of the pixel noise: the
/// camera poses' part is common to all frame sets while the cameras are held still and
/// cancels from the displacements gauges measure.
fn gauge_tag(tag: &TagEstimate) -> GaugeTag {
    let mut covariance = tag.solution.noise_covariance;
    if let Some(c) = tag.fused_cov {
        covariance.fixed_view_mut::<3, 3>(3, 3).copy_from(&c);
        covariance.fixed_view_mut::<3, 3>(0, 3).fill(0.0);
        covariance.fixed_view_mut::<3, 3>(3, 0).fill(0.0);
    }
    GaugeTag { id: tag.id, pose: tag.pose, covariance }
}
