//! `replay --smooth`: each line leaves a fixed-lag RTS smoother over the temporal estimate
//! (`tagdeflect_estimate::smooth`) `lag` frame sets later. The one wiring of the smoother, used
//! by the graph's solver and by the in-process replay alike.

use tagdeflect_core::feed::FeedLine;
use tagdeflect_estimate::measure::Measurement;
use tagdeflect_estimate::smooth::FixedLag;

/// A measurement's lines, smoothed with `lag` frame sets after them.
pub(crate) struct Smoothing {
    smoother: FixedLag,
}

impl Smoothing {
    /// Makes `measure` keep the steps the smoother needs and starts the smoother.
    pub(crate) fn attach(measure: &mut Measurement, lag_sets: usize) -> Self {
        measure.keep_steps();
        Self { smoother: measure.smoother(lag_sets) }
    }

    /// Takes the line `measure` just made; gives the line `lag` sets before it, smoothed.
    pub(crate) fn push(&mut self, line: FeedLine, measure: &Measurement) -> Option<FeedLine> {
        self.smoother.push(line, measure.last_steps().to_vec())
    }

    /// The lines still held, smoothed with what there is.
    pub(crate) fn finish(&mut self) -> Vec<FeedLine> {
        self.smoother.finish()
    }
}
