//! How long a live frame set waits for its missing cameras: each camera's arrival delay is
//! learned, and a set waits for a missing camera as long as that camera's frames steadily take
//! to arrive, within a bound (the rule is stated in the module doc of [`super`]).

use std::collections::VecDeque;
use std::time::Duration;

/// Arrival delays kept per camera: the window of the estimate.
pub const DELAY_WINDOW: usize = 32;
/// Delays a camera needs in its window before its estimate counts.
pub const MIN_DELAYS: usize = 8;
/// The shortest bound on a set's wait.
pub const MIN_MAX_WAIT: Duration = Duration::from_secs(1);

/// The numbers of the wait rule, all in ns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WaitRule {
    /// The wait without a learned delay, counted from when the set opened: a frame period of
    /// the fastest camera, at least 50 ms (0.1 s when no camera states its rate).
    pub base_ns: i64,
    /// The most a set waits, counted from when it opened: the larger of 1 s and three base waits.
    pub max_ns: i64,
    /// Added to a camera's learned delay: a quarter of the base wait.
    pub margin_ns: i64,
    /// A camera that sent nothing for this long stops counting and learns again when it
    /// sends: twice the bound.
    pub forget_after_ns: i64,
    /// The frame period of the fastest camera (1/120 s when no camera states its rate).
    pub period_ns: i64,
}

impl WaitRule {
    /// The rule for a rig whose fastest camera runs at `max_fps` (`None`: no rate stated).
    pub fn for_fps(max_fps: Option<f64>) -> Self {
        let period_s = max_fps.filter(|f| f.is_finite() && *f > 0.0).map(|f| 1.0 / f);
        let base_ns = secs_to_ns(period_s.map_or(0.1, |p| p.max(0.05)));
        let max_ns = base_ns.saturating_mul(3).max(MIN_MAX_WAIT.as_nanos() as i64);
        Self {
            base_ns,
            max_ns,
            margin_ns: base_ns / 4,
            forget_after_ns: max_ns.saturating_mul(2),
            period_ns: secs_to_ns(period_s.unwrap_or(1.0 / 120.0)).max(1),
        }
    }

    /// The base wait, for [`super::FrameSetAssembler::poll`].
    pub fn base(&self) -> Duration {
        Duration::from_nanos(self.base_ns.max(0) as u64)
    }

    /// Sets a live assembler may hold open: enough for the longest wait.
    pub fn open_sets(&self) -> usize {
        usize::try_from(self.max_ns / self.period_ns).unwrap_or(usize::MAX).saturating_add(2).min(10_000)
    }
}

fn secs_to_ns(s: f64) -> i64 {
    (s * 1e9).round().clamp(0.0, i64::MAX as f64) as i64
}

/// One camera's recent arrival delays.
#[derive(Debug, Default)]
struct CameraDelays {
    delays_ns: VecDeque<i64>,
    last_arrival_ns: Option<i64>,
    /// The 90th percentile of the window, once it holds [`MIN_DELAYS`].
    steady_ns: Option<i64>,
    /// Logged as beyond the bound (until it comes back under it).
    beyond_bound: bool,
}

impl CameraDelays {
    fn record(&mut self, delay_ns: i64, arrival_ns: i64, forget_after_ns: i64) {
        if self.last_arrival_ns.is_some_and(|l| arrival_ns.saturating_sub(l) > forget_after_ns) {
            // Silent for longer than the rule remembers: learn again.
            self.delays_ns.clear();
            self.steady_ns = None;
        }
        self.last_arrival_ns = Some(self.last_arrival_ns.map_or(arrival_ns, |l| l.max(arrival_ns)));
        if self.delays_ns.len() == DELAY_WINDOW {
            self.delays_ns.pop_front();
        }
        self.delays_ns.push_back(delay_ns);
        if self.delays_ns.len() >= MIN_DELAYS {
            let mut sorted: Vec<i64> = self.delays_ns.iter().copied().collect();
            sorted.sort_unstable();
            self.steady_ns = Some(sorted[(sorted.len() - 1) * 9 / 10]);
        }
    }

    /// The steady delay, if the camera counts at `now_ns`.
    fn counted(&self, now_ns: i64, forget_after_ns: i64) -> Option<i64> {
        let recent = self.last_arrival_ns.is_some_and(|l| now_ns.saturating_sub(l) <= forget_after_ns);
        self.steady_ns.filter(|_| recent)
    }
}

/// Every camera's learned arrival delay (arrival on the process clock minus the frame's
/// `t_ns`) and the set deadlines it gives.
#[derive(Debug)]
pub struct ArrivalDelays {
    rule: WaitRule,
    names: Vec<String>,
    cameras: Vec<CameraDelays>,
    /// The learned wait last logged, ns past a set's time (the base wait at first).
    logged_wait_ns: i64,
    /// When it was logged (process clock ns).
    logged_at_ns: Option<i64>,
}

/// The learned wait is logged at most this often (its latest value is in every feed line).
const LOG_EVERY_NS: i64 = 60_000_000_000;

impl ArrivalDelays {
    /// Nothing learned yet, for cameras named `names` (in `[[cameras]]` order).
    pub fn new(names: Vec<String>, rule: WaitRule) -> Self {
        let cameras = names.iter().map(|_| CameraDelays::default()).collect();
        Self { rule, names, cameras, logged_wait_ns: rule.base_ns, logged_at_ns: None }
    }

    /// The rule in use.
    pub fn rule(&self) -> &WaitRule {
        &self.rule
    }

    /// Notes that `camera`'s frame stamped `t_ns` arrived at `arrival_ns` (process clock).
    pub fn record(&mut self, camera: usize, t_ns: i64, arrival_ns: i64) {
        let rule = self.rule;
        let Some(c) = self.cameras.get_mut(camera) else { return };
        c.record(arrival_ns.saturating_sub(t_ns), arrival_ns, rule.forget_after_ns);
        self.log_changes(camera, arrival_ns);
    }

    /// `camera`'s steady arrival delay at `now_ns`, ns: `None` while it is learned, or once
    /// the camera has sent nothing for the rule's forget time.
    pub fn steady_delay_ns(&self, camera: usize, now_ns: i64) -> Option<i64> {
        self.cameras.get(camera).and_then(|c| c.counted(now_ns, self.rule.forget_after_ns))
    }

    /// When a set anchored at `anchor_ns` and opened at `opened_ns` is closed without its
    /// `missing` cameras: after `base_ns` from its opening, and after each counted missing
    /// camera's steady delay plus the margin past its anchor (and tolerance), at most the
    /// bound (or `base_ns`, if longer) after its opening. A camera steadily later than the
    /// bound is not waited for (its frames would miss the set all the same).
    pub fn deadline_ns(
        &self,
        anchor_ns: i64,
        opened_ns: i64,
        base_ns: i64,
        tolerance_ns: i64,
        missing: impl Iterator<Item = usize>,
        now_ns: i64,
    ) -> i64 {
        let base = opened_ns.saturating_add(base_ns);
        let cap = opened_ns.saturating_add(base_ns.max(self.rule.max_ns));
        let past_anchor = anchor_ns.saturating_add(tolerance_ns).saturating_add(self.rule.margin_ns);
        let within = |d: &i64| d.saturating_add(self.rule.margin_ns) <= self.rule.max_ns;
        let learned = missing.filter_map(|c| self.steady_delay_ns(c, now_ns)).filter(within).map(|d| past_anchor.saturating_add(d)).max();
        learned.map_or(base, |l| l.max(base).min(cap))
    }

    /// The slowest counted camera within the bound and its steady delay plus the margin, ns.
    fn slowest(&self, now_ns: i64) -> Option<(usize, i64)> {
        (0..self.cameras.len())
            .filter_map(|c| self.steady_delay_ns(c, now_ns).map(|d| (c, d.saturating_add(self.rule.margin_ns))))
            .filter(|&(_, w)| w <= self.rule.max_ns)
            .max_by_key(|&(_, w)| w)
    }

    /// Logs the learned wait when it moved by more than the margin (at most once a minute),
    /// and a camera whose frames arrive later than the bound (once, until it comes back under
    /// three quarters of it).
    fn log_changes(&mut self, camera: usize, now_ns: i64) {
        let ms = |ns: i64| ns as f64 / 1e6;
        let (max_ns, margin_ns) = (self.rule.max_ns, self.rule.margin_ns);
        let wait_ns = self.slowest(now_ns).map_or(self.rule.base_ns, |(_, w)| w.clamp(self.rule.base_ns, max_ns.max(self.rule.base_ns)));
        let quiet = self.logged_at_ns.is_some_and(|t| now_ns.saturating_sub(t) < LOG_EVERY_NS);
        if (wait_ns - self.logged_wait_ns).abs() > margin_ns && !quiet {
            (self.logged_wait_ns, self.logged_at_ns) = (wait_ns, Some(now_ns));
            match self.slowest(now_ns) {
                Some((c, _)) if wait_ns > self.rule.base_ns => tracing::info!(
                    camera = %self.names[c],
                    delay_ms = ms(self.steady_delay_ns(c, now_ns).unwrap_or(0)),
                    wait_ms = ms(wait_ns),
                    "frame sets now wait up to {:.0} ms past their time for camera {} (its frames arrive {:.0} ms after their time)",
                    ms(wait_ns),
                    self.names[c],
                    ms(self.steady_delay_ns(c, now_ns).unwrap_or(0))
                ),
                _ => tracing::info!(wait_ms = ms(self.rule.base_ns), "frame sets wait the base {:.0} ms again", ms(self.rule.base_ns)),
            }
        }
        let steady = self.steady_delay_ns(camera, now_ns);
        let c = &mut self.cameras[camera];
        let beyond = steady.is_some_and(|d| d.saturating_add(margin_ns) > max_ns);
        let back_under = steady.is_none_or(|d| d.saturating_add(margin_ns) < max_ns / 4 * 3);
        if beyond && !c.beyond_bound {
            tracing::warn!(
                camera = %self.names[camera],
                delay_ms = ms(steady.unwrap_or(0)),
                bound_ms = ms(max_ns),
                "camera {}'s frames arrive {:.0} ms after their time, beyond the {:.0} ms a frame set may wait: sets do not wait for it and most of its frames are dropped as late",
                self.names[camera],
                ms(steady.unwrap_or(0)),
                ms(max_ns)
            );
        }
        c.beyond_bound = beyond || (c.beyond_bound && !back_under);
    }
}
