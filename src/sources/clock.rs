//! Clocks of live capture: the host's Unix-epoch clock, CLOCK_MONOTONIC, and the mapping of
//! device timestamps onto the product's one clock (ns since the Unix epoch, SPEC "Time").
//!
//! Drivers stamp buffers on their own clocks: V4L2 drivers mostly on CLOCK_MONOTONIC, GigE
//! Vision cameras on a free-running tick counter. Each source maps its clock to the epoch once,
//! with an offset measured when the source is opened ([`MonotonicToEpoch::measure`]), so that
//! the relative timing of frames keeps the driver's precision while all cameras, the UTM and
//! the feed share one time axis.

use std::time::{SystemTime, UNIX_EPOCH};

/// Nanoseconds since the Unix epoch on the host's realtime clock.
pub fn now_epoch_ns() -> i64 {
    match SystemTime::now().duration_since(UNIX_EPOCH) {
        Ok(d) => d.as_nanos() as i64,
        // A clock set before 1970: report it as negative time rather than panicking.
        Err(e) => -(e.duration().as_nanos() as i64),
    }
}

/// Nanoseconds on CLOCK_MONOTONIC (the clock V4L2 drivers stamp buffers with).
// `time_t`/`c_long` are i64 on 64-bit Linux, i32 on some 32-bit targets.
#[allow(clippy::useless_conversion)]
pub fn monotonic_ns() -> i64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime only writes the timespec we pass by valid mutable reference;
    // CLOCK_MONOTONIC is always supported on Linux, so the call cannot fail.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    if rc != 0 {
        return 0;
    }
    i64::from(ts.tv_sec) * 1_000_000_000 + i64::from(ts.tv_nsec)
}

/// The offset between CLOCK_MONOTONIC and the Unix epoch: `epoch = monotonic + offset_ns`.
///
/// Measured once per opened device; the realtime clock may later be stepped (NTP), the
/// monotonic clock is not, so frame intervals stay exact and all cameras opened at the same
/// time share the same offset to within the measurement error (a few µs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MonotonicToEpoch {
    /// `epoch_ns − monotonic_ns`.
    pub offset_ns: i64,
}

impl MonotonicToEpoch {
    /// Measures the offset: the realtime clock is read between two monotonic readings, the
    /// tightest of a few such sandwiches is kept and its monotonic midpoint used.
    pub fn measure() -> Self {
        let mut best: Option<(i64, i64)> = None; // (width, offset)
        for _ in 0..5 {
            let m0 = monotonic_ns();
            let r = now_epoch_ns();
            let m1 = monotonic_ns();
            let width = m1 - m0;
            let offset = r - (m0 + width / 2);
            if best.is_none_or(|(w, _)| width < w) {
                best = Some((width, offset));
            }
        }
        Self { offset_ns: best.map_or(0, |(_, o)| o) }
    }

    /// A mapping with a known offset (fixtures, tests).
    pub fn from_offset(offset_ns: i64) -> Self {
        Self { offset_ns }
    }

    /// Maps a CLOCK_MONOTONIC time in ns to ns since the epoch.
    pub fn to_epoch(self, monotonic_ns: i64) -> i64 {
        monotonic_ns.saturating_add(self.offset_ns)
    }
}

/// Maps a device clock with an arbitrary zero (a camera's tick counter) to the epoch from
/// the first timestamp it sees: `epoch = device − first_device + first_receive`.
///
/// Used when a source offers no host-side timestamp. The mapping absorbs the transport
/// latency of the first frame into the offset (so times are late by that latency, constant
/// over the run) and does not correct drift between the device oscillator and the host clock
/// (typically < 50 ppm: < 0.2 s per hour); [`DeviceClockMap::map`] re-anchors when the
/// mapped time strays further than `max_skew_ns` from the host's receive time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DeviceClockMap {
    offset_ns: Option<i64>,
    max_skew_ns: i64,
}

impl DeviceClockMap {
    /// A mapping that anchors on its first timestamp and re-anchors beyond `max_skew_ns`.
    pub fn new(max_skew_ns: i64) -> Self {
        Self { offset_ns: None, max_skew_ns: max_skew_ns.max(1) }
    }

    /// Maps a device timestamp (ns on the device's clock) received at `receive_epoch_ns`.
    pub fn map(&mut self, device_ns: i64, receive_epoch_ns: i64) -> i64 {
        let offset = match self.offset_ns {
            Some(o) if (device_ns.saturating_add(o) - receive_epoch_ns).abs() <= self.max_skew_ns => o,
            _ => {
                let o = receive_epoch_ns.saturating_sub(device_ns);
                self.offset_ns = Some(o);
                o
            }
        };
        device_ns.saturating_add(offset)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn measured_offset_maps_now_to_now() {
        let map = MonotonicToEpoch::measure();
        let mapped = map.to_epoch(monotonic_ns());
        let now = now_epoch_ns();
        let err = (mapped - now).abs();
        println!("monotonic→epoch mapping error: {err} ns");
        assert!(err < 5_000_000, "monotonic mapped to epoch is {err} ns away from the realtime clock");
    }

    #[test]
    fn device_clock_anchors_and_reanchors() {
        let mut m = DeviceClockMap::new(1_000_000_000);
        assert_eq!(m.map(1_000, 5_000_000_000), 5_000_000_000);
        // 40 ms later on the device, received 41 ms later: keeps the device spacing.
        assert_eq!(m.map(40_001_000, 5_041_000_000), 5_040_000_000);
        // The device clock jumped (camera reset): re-anchored on the receive time.
        assert_eq!(m.map(7, 6_500_000_000), 6_500_000_000);
    }
}
