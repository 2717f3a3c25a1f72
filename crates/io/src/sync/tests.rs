//! The assembler's rules, on recorded and live timelines.

use super::*;
use std::sync::Arc;
use tagdeflect_core::frame::GrayImage;

fn f(camera: usize, t_ms: i64) -> Frame {
    Frame { camera, seq: 0, t_ns: 1_700_000_000_000_000_000 + t_ms * 1_000_000, image: Arc::new(GrayImage::new(1, 1)) }
}

fn run(frames: Vec<Frame>) -> Vec<Vec<usize>> {
    let mut a = FrameSetAssembler::new(3, 10.0);
    let mut out: Vec<FrameSet> = frames.into_iter().flat_map(|fr| a.push(fr)).collect();
    out.extend(a.flush());
    out.iter().map(|s| s.frames.iter().map(|f| f.camera).collect()).collect()
}

#[test]
fn groups_within_tolerance_and_closes_when_complete() {
    let sets = run(vec![f(0, 0), f(1, 3), f(2, 5), f(0, 100), f(1, 104), f(2, 98)]);
    assert_eq!(sets, vec![vec![0, 1, 2], vec![0, 1, 2]]);
}

#[test]
fn dropped_frame_makes_a_smaller_set_never_two_of_one_camera() {
    // camera 2 dropped its first frame; camera 0 comes twice close together.
    let sets = run(vec![f(0, 0), f(1, 2), f(0, 100), f(1, 101), f(2, 102), f(0, 200), f(0, 205)]);
    assert_eq!(sets, vec![vec![0, 1], vec![0, 1, 2], vec![0], vec![0]]);
}

#[test]
fn far_apart_frames_form_separate_sets_and_late_frames_are_counted() {
    let mut a = FrameSetAssembler::new(2, 10.0);
    assert!(a.push(f(0, 0)).is_empty());
    let s = a.push(f(1, 50));
    assert_eq!(s.len(), 1);
    assert_eq!(s[0].frames.len(), 1);
    assert!(a.push(f(0, 20)).is_empty()); // older than the open set's anchor - tolerance
    assert!(a.push(f(1, 0)).is_empty()); // not newer than the closed first set
    assert_eq!(a.late_frames(), 2);
    let set = a.flush().pop().unwrap();
    assert_eq!(set.seq, 1);
    assert_eq!(set.t_ns, f(1, 50).t_ns);
}

#[test]
fn poll_closes_a_stale_set_and_mean_time_is_used() {
    let mut a = FrameSetAssembler::new(3, 10.0);
    a.push(f(0, 0));
    a.push(f(1, 4));
    assert!(a.poll(std::time::Duration::from_secs(60)).is_empty());
    std::thread::sleep(std::time::Duration::from_millis(5));
    let set = a.poll(std::time::Duration::from_millis(1)).pop().unwrap();
    assert_eq!(set.t_ns, f(0, 2).t_ns);
    // A late frame of camera 2 does not start an earlier set.
    assert!(a.push(f(2, 3)).is_empty());
    assert_eq!(a.late_frames(), 1);
    // A frame just after the closed set's newest frame starts the next set.
    assert!(a.push(f(2, 5)).is_empty());
    assert_eq!(a.flush().pop().unwrap().frames.len(), 1);
}

#[test]
fn live_assembler_lets_a_lagging_camera_join_its_set() {
    let mut a = FrameSetAssembler::with_open_sets(3, 10.0, 3);
    let mut sets = Vec::new();
    // Camera 2 lags by more than a frame period behind cameras 0 and 1.
    for (c, t) in [(0, 0), (1, 1), (0, 100), (1, 101), (2, 2), (0, 200), (2, 99), (1, 199), (2, 201)] {
        sets.extend(a.push(f(c, t)));
    }
    let cams: Vec<Vec<usize>> = sets.iter().map(|s| s.frames.iter().map(|f| f.camera).collect()).collect();
    assert_eq!(cams, vec![vec![0, 1, 2], vec![0, 1, 2], vec![0, 1, 2]]);
    assert_eq!(a.late_frames(), 0);
}

#[test]
fn frame_set_times_never_go_back() {
    let mut a = FrameSetAssembler::new(3, 10.0);
    let mut times = Vec::new();
    // Cameras arrive out of order and late, some sets closed early.
    for (i, (c, t)) in [(0, 0), (2, 8), (1, 30), (0, 35), (2, 9), (1, 2), (2, 40), (0, 70), (1, 69), (2, 75)].into_iter().enumerate() {
        for s in a.push(f(c, t)) {
            times.push(s.t_ns);
        }
        if i == 3 {
            times.extend(a.flush().iter().map(|s| s.t_ns));
        }
    }
    times.extend(a.flush().iter().map(|s| s.t_ns));
    assert!(times.windows(2).all(|w| w[1] > w[0]), "{times:?}");
}

#[test]
fn frames_far_older_than_the_last_set_never_make_a_set_out_of_order() {
    // Times that jump back by 5 s (a device clock's glitch): late frames, never a set
    // older than one already closed (the process clock itself never goes back).
    let mut a = FrameSetAssembler::with_open_sets(2, 10.0, 3);
    let mut sets = Vec::new();
    for t in [0, 33, 66, 100, 133 - 5000, 166 - 5000, 200, 233] {
        sets.extend(a.push(f(0, t)));
        sets.extend(a.push(f(1, t + 1)));
    }
    sets.extend(a.flush());
    assert!(sets.windows(2).all(|w| w[1].t_ns > w[0].t_ns));
    assert_eq!(sets.len(), 6);
    assert_eq!(a.late_frames(), 4);
}

#[test]
fn extreme_times_do_not_overflow() {
    let mut a = FrameSetAssembler::with_open_sets(2, 10.0, 3);
    for t in [i64::MAX, i64::MIN, 0, i64::MAX - 1, i64::MIN + 1] {
        let fr = Frame { camera: 0, seq: 0, t_ns: t, image: Arc::new(GrayImage::new(1, 1)) };
        let _ = a.push(fr);
    }
    let _ = a.flush();
}

// Live timelines: frames at 30 fps whose arrival (process clock) is given, played into a live
// assembler polled every 5 ms (the graph's tick at the default tolerance), no wall clock.

const T0_NS: i64 = 1_700_000_000_000_000_000;
const MS_NS: i64 = 1_000_000;
const PERIOD_NS: i64 = 33_333_333;
const TICK_NS: i64 = 5 * MS_NS;

/// Frame `k` of `camera` (cameras 1 ms apart within a period).
fn frame_k(camera: usize, k: i64) -> Frame {
    Frame { camera, seq: k as u64, t_ns: T0_NS + k * PERIOD_NS + camera as i64 * MS_NS, image: Arc::new(GrayImage::new(1, 1)) }
}

/// A fixed, uneven jitter in `0..span_ms` ms.
fn jitter_ns(camera: usize, k: i64, span_ms: i64) -> i64 {
    ((k * 7919 + camera as i64 * 104_729) % (span_ms * 10)) * MS_NS / 10
}

/// `n` periods of `cameras`; `delay_ns(camera, k)` is when frame `k` arrives after its time
/// (`None`: it never does). Sorted by arrival.
fn timeline(cameras: usize, n: i64, delay_ns: impl Fn(usize, i64) -> Option<i64>) -> Vec<(i64, Frame)> {
    let mut out = Vec::new();
    for k in 0..n {
        for c in 0..cameras {
            if let Some(d) = delay_ns(c, k) {
                let fr = frame_k(c, k);
                out.push((fr.t_ns + d, fr));
            }
        }
    }
    out.sort_by_key(|(at, _)| *at);
    out
}

/// A set as it left: when, its time, its cameras, and when its first frame arrived.
struct Left {
    at_ns: i64,
    t_ns: i64,
    cameras: Vec<usize>,
    opened_ns: i64,
}

/// Plays `arrivals` into `a`, polled every tick with the base wait; `on_tick` sees the
/// assembler at each tick.
fn play(a: &mut FrameSetAssembler, arrivals: &[(i64, Frame)], mut on_tick: impl FnMut(i64, &FrameSetAssembler)) -> Vec<Left> {
    let wait = WaitRule::for_fps(Some(30.0)).base();
    let arrived: std::collections::HashMap<(usize, i64), i64> = arrivals.iter().map(|(at, f)| ((f.camera, f.t_ns), *at)).collect();
    let left = |at_ns: i64, s: FrameSet| Left {
        at_ns,
        t_ns: s.t_ns,
        cameras: s.frames.iter().map(|f| f.camera).collect(),
        opened_ns: s.frames.iter().map(|f| arrived[&(f.camera, f.t_ns)]).min().unwrap(),
    };
    let mut out = Vec::new();
    let (mut now, end) = (arrivals[0].0, arrivals.last().unwrap().0 + 2_000 * MS_NS);
    let mut next = 0;
    while now <= end {
        while next < arrivals.len() && arrivals[next].0 <= now {
            let (at, fr) = arrivals[next].clone();
            out.extend(a.push_at(fr, at).into_iter().map(|s| left(at, s)));
            next += 1;
        }
        out.extend(a.poll_at(now, wait).into_iter().map(|s| left(now, s)));
        on_tick(now, a);
        now += TICK_NS;
    }
    out.extend(a.flush().into_iter().map(|s| left(end, s)));
    out
}

fn live(cameras: usize) -> FrameSetAssembler {
    let names = (0..cameras).map(|c| format!("cam{c}")).collect();
    FrameSetAssembler::live(names, 10.0, WaitRule::for_fps(Some(30.0)))
}

#[test]
fn the_wait_rule_follows_the_fastest_camera() {
    let r = WaitRule::for_fps(Some(30.0));
    assert_eq!((r.base_ns, r.max_ns, r.margin_ns, r.forget_after_ns), (50 * MS_NS, 1_000 * MS_NS, 12_500_000, 2_000 * MS_NS));
    assert_eq!(r.open_sets(), 32);
    let r = WaitRule::for_fps(Some(1.0));
    assert_eq!((r.base_ns, r.max_ns, r.margin_ns), (1_000 * MS_NS, 3_000 * MS_NS, 250 * MS_NS));
    assert_eq!(WaitRule::for_fps(None).base_ns, 100 * MS_NS);
}

#[test]
fn a_camera_steadily_later_than_a_period_is_waited_for_and_every_set_is_whole() {
    // Camera 1's frames arrive 50–58 ms after their time (1.5 periods at 30 fps), camera 0's
    // 2–5 ms: the base wait (50 ms from the set's opening) alone ends about when camera 1's
    // frame comes, so whether it joins depends on the phase.
    let arrivals = timeline(2, 300, |c, k| Some(if c == 1 { 50 * MS_NS + jitter_ns(c, k, 8) } else { 2 * MS_NS + jitter_ns(c, k, 3) }));
    let mut a = live(2);
    let sets = play(&mut a, &arrivals, |_, _| {});
    // After a short learning time (MIN_DELAYS frames; 0.5 s given), every set is whole.
    let learnt: Vec<&Left> = sets.iter().filter(|s| s.t_ns >= frame_k(0, 15).t_ns).collect();
    let whole = learnt.iter().filter(|s| s.cameras == [0, 1]).count();
    assert_eq!((whole, learnt.len()), (285, 285), "whole sets from 0.5 s on (periods 15..300); late frames {:?}", a.late_by_camera());
    let delay_ns = a.arrival_delays().and_then(|d| d.steady_delay_ns(1, T0_NS + 10_000 * MS_NS)).unwrap();
    assert!((50 * MS_NS..=58 * MS_NS).contains(&delay_ns), "camera 1's learned delay {delay_ns} ns");
    // Each set left as soon as it was whole: with camera 1's frame.
    assert!(learnt.iter().all(|s| s.at_ns - s.t_ns <= 60 * MS_NS));
}

#[test]
fn a_two_second_hiccup_does_not_keep_the_wait_up() {
    // Camera 1 (steady 10–14 ms) has one frame 2 s late (k = 60), then stalls 2 s and hands
    // over 10 queued frames at once, 2 s late (k = 100..110; 110..160 lost); frame 250 is lost.
    let delay = |c: usize, k: i64| match (c, k) {
        (0, _) => Some(2 * MS_NS + jitter_ns(c, k, 3)),
        (1, 60) | (1, 100..110) => Some(2_000 * MS_NS),
        (1, 110..160) | (1, 250) => None,
        _ => Some(10 * MS_NS + jitter_ns(c, k, 4)),
    };
    let arrivals = timeline(2, 300, delay);
    let mut a = live(2);
    let mut raised = Vec::new();
    let sets = play(&mut a, &arrivals, |now, a| {
        let d = a.arrival_delays().and_then(|d| d.steady_delay_ns(1, now)).unwrap_or(0);
        if d > 100 * MS_NS {
            raised.push(now);
        }
    });
    // The one slow frame never moved the estimate; the burst raised it only while its frames
    // were among the last 32 (until about 28 frames after the stall: under a second).
    let burst_over = T0_NS + 160 * PERIOD_NS + 28 * PERIOD_NS + 200 * MS_NS;
    assert!(raised.iter().all(|&t| t > T0_NS + 100 * PERIOD_NS + 1_900 * MS_NS && t < burst_over), "raised at {raised:?}");
    assert!(!raised.is_empty(), "ten frames 2 s late among the last 32 raise the estimate");
    // The set whose camera-1 frame was lost at k = 250 left after the base wait, not the bound.
    let lost = sets.iter().find(|s| s.t_ns == frame_k(0, 250).t_ns).expect("set 250");
    assert_eq!(lost.cameras, [0]);
    assert!(lost.at_ns - lost.opened_ns <= 50 * MS_NS + TICK_NS, "set 250 waited {} ms", (lost.at_ns - lost.opened_ns) / MS_NS);
    // Every set after the burst is whole but that one.
    let after: Vec<&Left> = sets.iter().filter(|s| s.t_ns > frame_k(0, 170).t_ns).collect();
    assert_eq!(after.iter().filter(|s| s.cameras != [0, 1]).count(), 1);
}

#[test]
fn a_dead_camera_stalls_no_set_beyond_the_bound() {
    // Camera 1 steadily 300 ms late, dead from k = 150: sets wait for it at most its learned
    // delay (never past the 1 s bound), and after the forget time (2 s) the base wait again.
    let arrivals = timeline(2, 300, |c, k| match (c, k) {
        (0, _) => Some(2 * MS_NS),
        (_, 150..) => None,
        _ => Some(300 * MS_NS + jitter_ns(c, k, 5)),
    });
    let mut a = live(2);
    let sets = play(&mut a, &arrivals, |_, _| {});
    assert!(sets.iter().all(|s| s.at_ns - s.opened_ns <= 1_000 * MS_NS + TICK_NS));
    let waited_ms = |k: i64| sets.iter().find(|s| s.t_ns == frame_k(0, k).t_ns).map(|s| (s.at_ns - s.opened_ns) / MS_NS);
    // Just after its death: camera 1's delay + tolerance + margin (~328 ms).
    assert!(waited_ms(151).is_some_and(|w| (300..=345).contains(&w)), "{:?}", waited_ms(151));
    // Camera 1's last frame arrived at about k = 149 + 9 periods: forgotten 2 s later.
    let forgotten_k = 149 + 9 + 60 + 1;
    assert!((forgotten_k..300).all(|k| waited_ms(k).is_some_and(|w| w <= 55)), "{:?}", waited_ms(forgotten_k));
    // Whole sets while it lived, once learned.
    assert!(sets.iter().filter(|s| s.t_ns > T0_NS + 700 * MS_NS && s.t_ns < frame_k(0, 150).t_ns).all(|s| s.cameras == [0, 1]));
}

#[test]
fn a_camera_later_than_the_bound_is_not_waited_for() {
    // Camera 1 steadily 3 s late (the bound is 1 s): its frames miss their sets whatever the
    // wait, so sets wait only the base, not the bound.
    let arrivals = timeline(2, 200, |c, k| Some(if c == 1 { 3_000 * MS_NS + jitter_ns(c, k, 5) } else { 2 * MS_NS }));
    let mut a = live(2);
    let sets = play(&mut a, &arrivals, |_, _| {});
    assert!(sets.iter().all(|s| s.at_ns - s.opened_ns <= 50 * MS_NS + TICK_NS));
    assert!(a.late_by_camera()[1] > 150, "camera 1's frames are late: {:?}", a.late_by_camera());
}
