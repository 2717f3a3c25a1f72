//! The memory a feed takes once read for the report, and the report's own, measured by this
//! process itself: a counting allocator (this test binary's only test, so nothing else
//! allocates meanwhile) tells the bytes the read feed holds, the peak while reading and the
//! peak while the report is built and written, by both routes: the feed read without the rig
//! (`Feed::read`, as `export`) and read for it (`Feed::read_runs_for`, the route of every
//! report, the daemon's at a test's stop included). A long test's report must fit the unit's
//! `MemoryMax=2G`: what a line costs here times a 9-hour test at 30 frame sets/s (972 000
//! lines) is the figure in docs/operations.md.

// The counting allocator is the one unsafe part: it forwards every call to the system's.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;
use std::sync::atomic::{AtomicUsize, Ordering};

use tagdeflect_core::feed::{CameraHealth, FeedLine, FeedTag, GaugeReading, TestRef};
use tagdeflect_report::{Feed, ReadOptions, ReportConfig, Standard, TestRig};

struct Counting;

static HELD: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: every call is forwarded unchanged to `System`, which upholds GlobalAlloc's contract;
// the counters only observe the sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's layout, as GlobalAlloc::alloc requires, passed on.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = HELD.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `alloc` above (System's) with this layout.
        unsafe { System.dealloc(ptr, layout) };
        HELD.fetch_sub(layout.size(), Ordering::Relaxed);
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// A line as a three-camera rig writes it: 9 tags with σ, 3 cameras, 4 gauges, a test; a
/// beam loaded to its peak and softening over `lines` lines (as `scripts/long_feed.py`).
fn rig_line(seq: u64, lines: u64) -> FeedLine {
    let d = 3.2 * seq as f64 / (lines - 1) as f64;
    let p = if d < 0.06 { 45.0 * d / 0.06 } else { 15.0 + 30.0 * (-(d - 0.06) / 0.4).exp() };
    let wobble = |k: u32| 1.0 + 0.2 * (0.37 * seq as f64 + 1.3 * k as f64).sin();
    let tags = (0..9)
        .map(|id| FeedTag {
            id,
            pos_mm: [100.0 * id as f64, 0.5, 1500.0],
            disp_mm: [1e-4 * (seq as f64).sin(), 2e-4, if id == 1 { -d } else { 0.0 }],
            views: 2,
            sigma_mm: Some([0.004 * wobble(3 * id), 0.005 * wobble(3 * id + 1), 0.002 * wobble(3 * id + 2)]),
            disp_sigma_mm: None,
            reproj_px: Some(0.12),
        })
        .collect();
    let cameras = ["cam-left", "cam-middle", "cam-right"]
        .iter()
        .map(|n| CameraHealth {
            name: n.to_string(),
            frame: true,
            background_tags: 4,
            specimen_tags: 6,
            pose_reproj_px: Some(0.2),
            posed: true,
            drift_deg: Some(0.0),
            drift_mm: Some(0.0),
            pose_age_sets: Some(0),
            dropped_frames: Some(0),
            ..Default::default()
        })
        .collect();
    let gauges = ["net_deflection", "cmod", "rotation_left", "rotation_right"]
        .iter()
        .map(|g| (g.to_string(), GaugeReading { value: d, sigma: 0.003 * wobble(40), unit: "mm".into() }))
        .collect();
    FeedLine {
        seq,
        t_ns: 1_780_000_000_000_000_000 + seq as i64 * 33_333_333,
        load_kn: Some(p),
        stroke_mm: Some(1.3 * d),
        tags,
        net_deflection_mm: Some(d),
        net_deflection_sigma_mm: Some(0.004),
        reproj_px: Some(0.15),
        cameras,
        utm: Some("ok".into()),
        dropped_sets: Some(0),
        latency_ms: Some(42.0),
        gauges,
        recording: Some("ok".into()),
        test: Some(TestRef { id: "2026-12-06T16-00-00Z-B12".into(), specimen: "B12".into(), zeroing: false }),
        ..Default::default()
    }
}

/// The three-camera rig of `config/three-camera.toml`: tags 0 and 2 on the supports, 1 at
/// mid-span, a 150 × 150 × 450 mm beam.
fn rig() -> TestRig {
    let specimen = serde_json::from_value(serde_json::json!({
        "family": "tag36h11", "size_mm": 30.0,
        "tag": [{"id": 0, "role": "support"}, {"id": 1, "role": "midspan"}, {"id": 2, "role": "support"}],
        "beam": {"width_mm": 150.0, "depth_mm": 150.0, "span_mm": 450.0},
    }))
    .unwrap();
    TestRig { world: Default::default(), specimen, gauges: Vec::new() }
}

/// Bytes a line the read feed may hold: ~1.3 × the 105 B measured (2026-12-06; 2 220 B
/// before the columns, 3 803 B as parsed; docs/performance.md).
const HELD_BOUND: f64 = 140.0;
/// Bytes a line at the peak of building the report, the feed included: ~1.3 × the 398 B
/// measured (the tags read again: each tag's σ along `world.up` and each line's role σ; the
/// curve's own columns).
const BUILD_BOUND: f64 = 520.0;
/// The same two read for the rig, the route every report takes (`Feed::read_runs_for`): the
/// tags' figures gathered while reading (each tag's σ along `world.up`, each line's role σ) are
/// held with the feed until the report takes them. ~1.3 × the 185 B and 398 B measured
/// (2026-12-07; the build's peak is the same by either route: the figures are held from the
/// read instead of gathered during the build).
const HELD_BOUND_RIG: f64 = 240.0;
const BUILD_BOUND_RIG: f64 = 520.0;

const LINES: u64 = 20_000;

/// Bytes (held, peak) since `f` began, the allocator's peak reset first.
fn counted<T>(f: impl FnOnce() -> T) -> (T, usize, usize) {
    let base = HELD.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let v = f();
    (v, HELD.load(Ordering::Relaxed).saturating_sub(base), PEAK.load(Ordering::Relaxed) - base)
}

/// What one route costs, bytes: the read feed held, the peak while reading, the peak while
/// building the report above the feed, the peak while writing it above that.
struct Route {
    held: usize,
    read_peak: usize,
    build_peak: usize,
    write_peak: usize,
}

impl Route {
    fn per_line(b: usize) -> f64 {
        b as f64 / LINES as f64
    }

    fn say(&self, name: &str) {
        let pl = Self::per_line;
        eprintln!(
            "{name}: held for the report {:.0} B a line, peak while reading {:.0} B a line; building the report: \
             peak {:.0} B a line above the feed; writing it: peak {:.0} B a line above that; a 9-hour test at \
             30 sets/s (972 000 lines): {:.3} GB held, {:.3} GB at the peak of building",
            pl(self.held),
            pl(self.read_peak),
            pl(self.build_peak),
            pl(self.write_peak),
            pl(self.held) * 972_000.0 / 1e9,
            pl(self.held + self.build_peak) * 972_000.0 / 1e9,
        );
    }
}

/// Reads the feed at `path` (for the rig, or without it as `export` does), builds and writes
/// its report (no PDF: Chromium is another process) into `out`, counting each step.
fn route(path: &std::path::Path, for_rig: bool, out: &std::path::Path) -> Route {
    let mut opts = ReportConfig::new(Standard::AstmC1609, out.to_path_buf());
    opts.pdf = false;
    let rig = rig();
    let read = ReadOptions { limits: opts.limits(), allow_restarts: false };
    let (feed, held, read_peak) = counted(|| Feed::read_runs_for(path, &read, for_rig.then_some(&rig)).unwrap().remove(0));
    assert_eq!(feed.len() as u64, LINES);
    let (report, _, build_peak) = counted(|| tagdeflect_report::build(&feed, None, &rig, std::path::Path::new("rig.toml"), &opts).unwrap());
    let (_, _, write_peak) = counted(|| tagdeflect_report::write(&report, &feed, out).unwrap());
    // The cameras are counted, not held; the report's numbers come out of the columns.
    assert_eq!(feed.summary.cameras.len(), 3);
    assert_eq!(feed.columns.gauges.len(), 4);
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    assert_eq!(json["qc"]["lines"], LINES, "{}", json["qc"]);
    assert_eq!(json["qc"]["tags"].as_array().map(Vec::len), Some(9), "every tag's figures: {}", json["qc"]["tags"]);
    let csv = std::fs::read_to_string(out.join("curve.csv")).unwrap();
    assert_eq!(csv.lines().count() as u64, LINES + 1, "a row per line and the header");
    Route { held, read_peak, build_peak, write_peak }
}

#[test]
fn a_long_feed_read_for_the_report_holds_its_numbers_not_its_lines() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("feed.jsonl");
    let mut f = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
    let mut text_bytes = 0;
    for seq in 0..LINES {
        let s = serde_json::to_string(&rig_line(seq, LINES)).unwrap();
        text_bytes += s.len() + 1;
        writeln!(f, "{s}").unwrap();
    }
    f.flush().unwrap();
    drop(f);

    // What the lines take as the measurement's own type, parsed and held as they are.
    let (parsed, as_parsed, _) =
        counted(|| std::fs::read_to_string(&path).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect::<Vec<FeedLine>>());
    drop(parsed);
    let per_line = Route::per_line;
    eprintln!(
        "{LINES} lines of a 3-camera, 9-tag, 4-gauge rig ({:.0} B of text a line): held as parsed {:.0} B a line \
         (a 9-hour test: {:.2} GB)",
        per_line(text_bytes),
        per_line(as_parsed),
        per_line(as_parsed) * 972_000.0 / 1e9
    );

    // Without the rig (`Feed::read`, as `export` reads; a report of it reads the tags again).
    let plain = route(&path, false, &dir.path().join("report"));
    plain.say("read without the rig");
    // For the rig: the route of `report FEED`, `report DIR`, `--series` and the daemon's
    // report at a test's stop (the tags' figures gathered in the one read).
    let for_rig = route(&path, true, &dir.path().join("report-rig"));
    for_rig.say("read for the rig");
    let same = |name: &str| std::fs::read(dir.path().join("report").join(name)).unwrap();
    let same_rig = |name: &str| std::fs::read(dir.path().join("report-rig").join(name)).unwrap();
    assert!(same("curve.csv") == same_rig("curve.csv"), "curve.csv the same by either route");

    // Bounds ~1.3 × the figures measured (the constants above).
    assert!(plain.held as f64 <= 0.05 * as_parsed as f64, "held {} B vs {as_parsed} B as parsed", plain.held);
    assert!(per_line(plain.held) <= HELD_BOUND, "{:.0} B a line", per_line(plain.held));
    assert!(
        per_line(plain.held + plain.build_peak) <= BUILD_BOUND,
        "{:.0} B a line at the peak of building",
        per_line(plain.held + plain.build_peak)
    );
    assert!(per_line(for_rig.held) <= HELD_BOUND_RIG, "for the rig: {:.0} B a line", per_line(for_rig.held));
    assert!(
        per_line(for_rig.held + for_rig.build_peak) <= BUILD_BOUND_RIG,
        "for the rig: {:.0} B a line at the peak of building",
        per_line(for_rig.held + for_rig.build_peak)
    );
    // Reading streams: the peak is the held lines plus the growing columns' spare room.
    for (name, r) in [("without the rig", &plain), ("for the rig", &for_rig)] {
        assert!(r.read_peak as f64 <= 2.2 * r.held as f64, "{name}: peak {} B vs held {} B", r.read_peak, r.held);
    }
}
