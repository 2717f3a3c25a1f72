//! The product's one clock, and the other clocks it reads.
//!
//! # Contract
//!
//! Every time in tagdeflect — frames of every camera, UTM samples, the feed — is `i64`
//! nanoseconds since the Unix epoch on **one process clock** ([`now_epoch_ns`]): the host's
//! CLOCK_MONOTONIC plus an offset to the epoch measured once at start. The monotonic clock
//! never steps, so intervals between stamps are exact whatever NTP or an operator does to
//! the wall clock, and load is paired with deflection on one time axis.
//!
//! The wall clock may still be stepped (NTP correcting a badly set clock, a manual change).
//! [`ProcessClock::check_step`] compares the two (the live pipeline calls it about once a
//! second): when they disagree by more than [`STEP_THRESHOLD_NS`] the step is logged and the
//! mapping follows the wall clock — at once for a step forwards; for a step backwards by
//! slewing at [`SLEW_PPM`] (the process clock runs 0.5 % slow until it has caught up), so
//! times never go back and the feed stays in `t_ns` order (SPEC). Everything stamped on this
//! clock moves together, so pairing load with frames is unaffected, and frame-set assembly
//! ([`crate::sync`]) never sees its input times step back.
//!
//! Device clocks are mapped onto the process clock: V4L2 drivers stamp buffers on
//! CLOCK_MONOTONIC ([`ProcessClock::monotonic_to_epoch`]), GigE Vision cameras on their own
//! tick counter ([`DeviceClockMap`]).
//!
//! Also here: the calling thread's CPU time ([`thread_cpu_s`], for benchmarks).
//!
//! This module and the FFI modules are the only places with `unsafe` (`clock_gettime`).
#![allow(unsafe_code)]

use std::sync::{Mutex, OnceLock};
use std::time::{SystemTime, UNIX_EPOCH};

/// Wall-clock disagreements above this (1 s) are treated as a step of the wall clock and
/// re-map the process clock. Smaller differences are left alone: every stamp is on the
/// process clock, so they cannot pair load with the wrong frame, and NTP's gradual slewing
/// moves CLOCK_MONOTONIC's rate along with the wall clock's.
pub(crate) const STEP_THRESHOLD_NS: i64 = 1_000_000_000;

/// How fast the process clock absorbs a backwards step of the wall clock: 5000 ppm (5 ms per
/// second; a 5 s step is absorbed in 1000 s). Intervals measured meanwhile are 0.5 % short —
/// far below what matters for pairing load and frames, which share this clock.
pub(crate) const SLEW_PPM: i64 = 5_000;

/// Nanoseconds since the Unix epoch on the host's realtime (wall) clock. Can step; stamp
/// nothing with it — use [`now_epoch_ns`].
pub(crate) fn wall_epoch_ns() -> i64 {
    match SystemTime::now().duration_since(UNIX_EPOCH) {
        Ok(d) => i64::try_from(d.as_nanos()).unwrap_or(i64::MAX),
        // A clock set before 1970: report it as negative time rather than panicking.
        Err(e) => -i64::try_from(e.duration().as_nanos()).unwrap_or(i64::MAX),
    }
}

fn clock_ns(id: libc::clockid_t) -> i64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime only writes the timespec we pass by valid mutable reference;
    // the clocks used here (MONOTONIC, THREAD_CPUTIME_ID) always exist on Linux.
    let rc = unsafe { libc::clock_gettime(id, &mut ts) };
    if rc != 0 {
        return 0;
    }
    // `time_t`/`c_long` are i64 on 64-bit Linux, i32 on some 32-bit targets.
    #[allow(clippy::useless_conversion)]
    let (s, ns) = (i64::from(ts.tv_sec), i64::from(ts.tv_nsec));
    s.saturating_mul(1_000_000_000).saturating_add(ns)
}

/// Nanoseconds on CLOCK_MONOTONIC (the clock V4L2 drivers stamp buffers with).
pub fn monotonic_ns() -> i64 {
    clock_ns(libc::CLOCK_MONOTONIC)
}

/// CPU time of the calling thread, seconds.
pub fn thread_cpu_s() -> f64 {
    clock_ns(libc::CLOCK_THREAD_CPUTIME_ID) as f64 * 1e-9
}

/// What the process clock reads its two clocks from (injectable for tests).
pub trait ClockSource: Send + Sync {
    /// A monotonic time, ns (never steps).
    fn monotonic_ns(&self) -> i64;
    /// The wall clock, ns since the epoch (may step).
    fn wall_ns(&self) -> i64;
}

/// The host's clocks.
#[derive(Debug, Default, Clone, Copy)]
pub struct HostClocks;

impl ClockSource for HostClocks {
    fn monotonic_ns(&self) -> i64 {
        monotonic_ns()
    }
    fn wall_ns(&self) -> i64 {
        wall_epoch_ns()
    }
}

/// A wall-clock step that [`ProcessClock::check_step`] found and corrected.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClockStep {
    /// How far the wall clock moved relative to the process clock (positive: forwards), ns.
    pub step_ns: i64,
}

/// The mapping `epoch = monotonic + offset(monotonic)`: `offset` at `since`, slewing down
/// towards `target` at [`SLEW_PPM`] (never up: forward steps are taken at once).
#[derive(Debug, Clone, Copy)]
struct Mapping {
    offset: i64,
    target: i64,
    since: i64,
}

impl Mapping {
    fn fixed(offset: i64, since: i64) -> Self {
        Self { offset, target: offset, since }
    }

    fn offset_at(&self, mono: i64) -> i64 {
        if self.target >= self.offset {
            return self.offset;
        }
        let slewed = i128::from(mono.saturating_sub(self.since).max(0)) * i128::from(SLEW_PPM) / 1_000_000;
        let slewed = i64::try_from(slewed).unwrap_or(i64::MAX);
        self.offset.saturating_sub(slewed).max(self.target)
    }
}

/// A monotonic clock mapped to epoch time (see the module doc): the offset is measured once
/// and follows the wall clock only when it is found stepped.
pub struct ProcessClock {
    source: Box<dyn ClockSource>,
    mapping: Mutex<Mapping>,
}

impl std::fmt::Debug for ProcessClock {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ProcessClock").field("mapping", &*self.lock()).finish()
    }
}

impl ProcessClock {
    /// A clock over `source`, its offset measured now.
    pub fn new(source: Box<dyn ClockSource>) -> Self {
        let offset = measure_offset(source.as_ref());
        let mono = source.monotonic_ns();
        Self { source, mapping: Mutex::new(Mapping::fixed(offset, mono)) }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Mapping> {
        self.mapping.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Now, ns since the epoch; never goes back.
    pub fn now_ns(&self) -> i64 {
        let mono = self.source.monotonic_ns();
        mono.saturating_add(self.lock().offset_at(mono))
    }

    /// The current mapping of the monotonic clock (V4L2 buffer stamps) to epoch time.
    pub fn monotonic_to_epoch(&self) -> MonotonicToEpoch {
        let mono = self.source.monotonic_ns();
        MonotonicToEpoch { offset_ns: self.lock().offset_at(mono) }
    }

    /// Compares the wall clock with the process clock; beyond [`STEP_THRESHOLD_NS`] the step
    /// is logged and returned, and the mapping follows it (forwards at once, backwards by
    /// slewing). A step found while an earlier one is still being slewed replaces its target.
    pub fn check_step(&self) -> Option<ClockStep> {
        let wall_offset = measure_offset(self.source.as_ref());
        let mono = self.source.monotonic_ns();
        let mut m = self.lock();
        let now_offset = m.offset_at(mono);
        let step = wall_offset.saturating_sub(now_offset);
        let pending = wall_offset.saturating_sub(m.target);
        if pending.abs() <= STEP_THRESHOLD_NS {
            return None;
        }
        if step > 0 {
            *m = Mapping::fixed(wall_offset, mono);
            tracing::warn!(
                step_ms = step as f64 / 1e6,
                "the wall clock stepped forwards by {:.1} ms: the process clock follows at once",
                step as f64 / 1e6
            );
        } else {
            *m = Mapping { offset: now_offset, target: wall_offset, since: mono };
            tracing::warn!(
                step_ms = step as f64 / 1e6,
                "the wall clock stepped back by {:.1} ms: the process clock slews to it at {} ppm (about {:.0} s), so times never go back",
                -step as f64 / 1e6,
                SLEW_PPM,
                (-step as f64 / 1e9) / (SLEW_PPM as f64 * 1e-6)
            );
        }
        Some(ClockStep { step_ns: step })
    }
}

/// The offset `wall − monotonic`: the wall clock read between two monotonic readings, the
/// tightest of a few such sandwiches kept and its monotonic midpoint used.
fn measure_offset(source: &dyn ClockSource) -> i64 {
    let mut best: Option<(i64, i64)> = None; // (width, offset)
    for _ in 0..5 {
        let m0 = source.monotonic_ns();
        let r = source.wall_ns();
        let m1 = source.monotonic_ns();
        let width = m1.saturating_sub(m0);
        let offset = r.saturating_sub(m0.saturating_add(width / 2));
        if best.is_none_or(|(w, _)| width < w) {
            best = Some((width, offset));
        }
    }
    best.map_or(0, |(_, o)| o)
}

/// The process's clock (host clocks).
pub fn process() -> &'static ProcessClock {
    static CLOCK: OnceLock<ProcessClock> = OnceLock::new();
    CLOCK.get_or_init(|| ProcessClock::new(Box::new(HostClocks)))
}

/// Now on the process clock, ns since the Unix epoch: what every frame, UTM sample and feed
/// line is stamped with.
pub fn now_epoch_ns() -> i64 {
    process().now_ns()
}

/// The offset between CLOCK_MONOTONIC and the Unix epoch: `epoch = monotonic + offset_ns`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MonotonicToEpoch {
    /// `epoch_ns − monotonic_ns`.
    pub offset_ns: i64,
}

impl MonotonicToEpoch {
    /// The process clock's current mapping.
    pub fn current() -> Self {
        process().monotonic_to_epoch()
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
/// mapped time strays further than `max_skew_ns` from the host's receive time (which is on
/// the process clock, so a wall-clock step re-anchors it too).
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
            Some(o) if device_ns.saturating_add(o).saturating_sub(receive_epoch_ns).saturating_abs() <= self.max_skew_ns => o,
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
    use std::sync::Arc;

    /// Clocks the test sets: the monotonic one advances, the wall one can be stepped.
    #[derive(Default)]
    struct Scripted {
        mono: AtomicI64,
        wall_minus_mono: AtomicI64,
    }
    impl ClockSource for Arc<Scripted> {
        fn monotonic_ns(&self) -> i64 {
            self.mono.load(Ordering::Relaxed)
        }
        fn wall_ns(&self) -> i64 {
            self.mono.load(Ordering::Relaxed) + self.wall_minus_mono.load(Ordering::Relaxed)
        }
    }

    use std::sync::atomic::{AtomicI64, Ordering};

    #[test]
    fn process_clock_follows_monotonic_and_remaps_on_a_wall_step_only() {
        let s = Arc::new(Scripted::default());
        s.mono.store(1_000, Ordering::Relaxed);
        s.wall_minus_mono.store(1_700_000_000_000_000_000, Ordering::Relaxed);
        let clock = ProcessClock::new(Box::new(s.clone()));
        assert_eq!(clock.now_ns(), 1_700_000_000_000_001_000);
        // 40 ms pass; the wall clock moves by 300 ms: no re-map, intervals exact.
        s.mono.fetch_add(40_000_000, Ordering::Relaxed);
        s.wall_minus_mono.fetch_add(300_000_000, Ordering::Relaxed);
        assert_eq!(clock.check_step(), None);
        assert_eq!(clock.now_ns(), 1_700_000_000_040_001_000);
        // The wall clock steps forwards by 5 s: followed at once.
        s.wall_minus_mono.fetch_add(5_000_000_000, Ordering::Relaxed);
        assert_eq!(clock.now_ns(), 1_700_000_000_040_001_000, "no change before the check");
        let step = clock.check_step().expect("a 5 s step is found");
        assert_eq!(step.step_ns, 5_300_000_000);
        assert_eq!(clock.now_ns(), 1_700_000_005_340_001_000);
        assert_eq!(clock.monotonic_to_epoch().to_epoch(s.mono.load(Ordering::Relaxed)), clock.now_ns());
        assert_eq!(clock.check_step(), None);
        // The wall clock steps back by 5 s: the process clock slews, never goes back, and has
        // caught up after 5 s / 5000 ppm = 1000 s.
        s.wall_minus_mono.fetch_sub(5_000_000_000, Ordering::Relaxed);
        let before = clock.now_ns();
        let step = clock.check_step().expect("a 5 s step back is found");
        assert_eq!(step.step_ns, -5_000_000_000);
        let mut last = before;
        for _ in 0..2100 {
            s.mono.fetch_add(500_000_000, Ordering::Relaxed);
            let _ = clock.check_step();
            let now = clock.now_ns();
            assert!(now > last, "time went back: {last} -> {now}");
            // Half a second of monotonic time is at least 0.4975 s of process time.
            assert!(now - last >= 497_500_000, "{}", now - last);
            last = now;
        }
        let wall = s.mono.load(Ordering::Relaxed) + s.wall_minus_mono.load(Ordering::Relaxed);
        assert!((clock.now_ns() - wall).abs() < 1_000, "not caught up: {} ns", clock.now_ns() - wall);
        assert_eq!(clock.check_step(), None);
    }

    #[test]
    fn host_process_clock_maps_now_to_the_wall_clock() {
        let err = (now_epoch_ns() - wall_epoch_ns()).abs();
        println!("process clock vs wall clock: {err} ns");
        assert!(err < 5_000_000, "the process clock is {err} ns away from the wall clock");
        let mapped = MonotonicToEpoch::current().to_epoch(monotonic_ns());
        assert!((mapped - now_epoch_ns()).abs() < 5_000_000);
        assert!(thread_cpu_s() > 0.0);
    }

    #[test]
    fn device_clock_anchors_and_reanchors() {
        let mut m = DeviceClockMap::new(1_000_000_000);
        assert_eq!(m.map(1_000, 5_000_000_000), 5_000_000_000);
        // 40 ms later on the device, received 41 ms later: keeps the device spacing.
        assert_eq!(m.map(40_001_000, 5_041_000_000), 5_040_000_000);
        // The device clock jumped (camera reset): re-anchored on the receive time.
        assert_eq!(m.map(7, 6_500_000_000), 6_500_000_000);
        // Extreme values saturate instead of overflowing.
        let _ = m.map(i64::MIN, i64::MAX);
        let _ = m.map(i64::MAX, i64::MIN);
    }
}
