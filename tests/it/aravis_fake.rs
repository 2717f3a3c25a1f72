//! Aravis cameras tested for real against Aravis's own simulators:
//! (a) the in-process fake camera (Aravis's "Fake" interface, device `Fake_1`);
//! (b) the GigE Vision fake camera `arv-fake-gv-camera-0.8` on a loopback address;
//! (c) the same with its GVSP packet-loss option: incomplete frames are counted, never delivered.
//!
//! `arv-fake-gv-camera-0.8` comes with Debian's `aravis-tools` (installed by the setup
//! script). Each GigE test runs its own fake camera on 127.0.0.1, one at a time (a file
//! lock), and kills it when done (a Drop guard, also on failure).

use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tagdeflect::config::CameraConfig;
use tagdeflect_core::clock::now_epoch_ns;
use tagdeflect_core::frame::Frame;
use tagdeflect_io::sources::aravis::{spawn, AravisOptions};
use tagdeflect_io::sources::{spawn_camera, DropReason, LiveCamera, SourceError, SourceEvent};
use tokio::sync::mpsc::Receiver;

const FAKE_GV: &str = "arv-fake-gv-camera-0.8";

fn camera_cfg(source: &str, width: u32, height: u32, fps: f64) -> CameraConfig {
    let text = format!(
        "name = \"cam\"\nsource = \"{source}\"\nfps = {fps}\nwidth = {width}\nheight = {height}\n\
         fx = 500.0\nfy = 500.0\ncx = {}\ncy = {}\n",
        (width as f64 - 1.0) / 2.0,
        (height as f64 - 1.0) / 2.0
    );
    toml::from_str(&text).expect("test camera config")
}

/// The fake GigE camera can only listen on 127.0.0.1 (an address of an interface) and on the
/// fixed GVCP port 3956, so at most one runs at a time on the machine: every user takes an
/// exclusive `flock` on this file first (other test binaries may share it).
const FAKE_GV_LOCK: &str = "/tmp/tagdeflect-arv-fake-gv-camera.lock";

/// A running `arv-fake-gv-camera-0.8` on 127.0.0.1, killed on drop (the lock is released then).
struct FakeGvCamera {
    child: Child,
    address: String,
    _lock: std::fs::File,
}

impl FakeGvCamera {
    fn start(serial: &str, lost_per_thousand: Option<u32>) -> Self {
        use std::os::fd::AsRawFd;
        let lock = std::fs::OpenOptions::new().create(true).truncate(false).write(true).open(FAKE_GV_LOCK).expect("lock file");
        // SAFETY: flock on a file descriptor we own; blocks until other users are done.
        let rc = unsafe { libc::flock(lock.as_raw_fd(), libc::LOCK_EX) };
        assert_eq!(rc, 0, "cannot lock {FAKE_GV_LOCK}");
        let address = "127.0.0.1";
        let child = spawn_fake_gv(address, serial, lost_per_thousand);
        Self { child, address: address.to_string(), _lock: lock }
    }

    /// Kills the camera process (as if its cable were pulled), keeping the lock.
    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Starts the camera process again (as if plugged back in).
    fn restart(&mut self, serial: &str) {
        self.kill();
        self.child = spawn_fake_gv(&self.address, serial, None);
    }
}

fn spawn_fake_gv(address: &str, serial: &str, lost_per_thousand: Option<u32>) -> Child {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let mut cmd = Command::new(FAKE_GV);
        cmd.args(["-i", address, "-s", serial]).stdin(Stdio::null()).stdout(Stdio::null()).stderr(Stdio::null());
        if let Some(r) = lost_per_thousand {
            cmd.args(["-r", &r.to_string()]);
        }
        let mut child =
            cmd.spawn().unwrap_or_else(|e| panic!("cannot run {FAKE_GV} ({e}): install Debian's aravis-tools (run scripts/setup.sh)"));
        std::thread::sleep(Duration::from_millis(300));
        match child.try_wait() {
            Ok(None) => return child,
            // "Failed to start camera": the port is still taken (a camera not using the lock).
            _ if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(500)),
            other => panic!("{FAKE_GV} -i {address} exits at once ({other:?}): is UDP port 3956 on 127.0.0.1 taken?"),
        }
    }
}

impl Drop for FakeGvCamera {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Opens a camera, retrying while the fake GigE camera process starts up.
fn open_with_retry(
    cfg: &CameraConfig,
    id: &str,
    opts: AravisOptions,
    tx: tokio::sync::mpsc::Sender<SourceEvent>,
    stop: &Arc<AtomicBool>,
) -> LiveCamera {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        match spawn(0, cfg, id, opts.clone(), tx.clone(), stop.clone()) {
            Ok(cam) => return cam,
            Err(e) if Instant::now() < deadline => {
                eprintln!("not yet: {e}");
                std::thread::sleep(Duration::from_millis(300));
            }
            Err(e) => panic!("camera {id} never opened: {e}"),
        }
    }
}

#[derive(Default, Debug)]
struct Collected {
    frames: Vec<Frame>,
    dropped: Vec<(u64, DropReason)>,
    lost: usize,
}

/// Receives events until `n` frames arrived or `timeout` passed.
fn collect(rx: &mut Receiver<SourceEvent>, n: usize, timeout: Duration) -> Collected {
    let deadline = Instant::now() + timeout;
    let mut c = Collected::default();
    while c.frames.len() < n && Instant::now() < deadline {
        match rx.try_recv() {
            Ok(SourceEvent::Frame(f)) => c.frames.push(f),
            Ok(SourceEvent::Dropped { count, why, .. }) => c.dropped.push((count, why)),
            Ok(SourceEvent::Lost { reason, .. }) => {
                eprintln!("lost: {reason}");
                c.lost += 1;
            }
            Ok(SourceEvent::Reopened { .. }) => {}
            Err(_) => std::thread::sleep(Duration::from_millis(5)),
        }
    }
    c
}

/// Checks size, per-camera order and clock of delivered frames.
fn check_frames(frames: &[Frame], width: u32, height: u32, started_ns: i64) {
    let now = now_epoch_ns();
    for f in frames {
        assert_eq!((f.image.width, f.image.height, f.image.data.len()), (width, height, (width * height) as usize));
        assert!(
            f.t_ns >= started_ns - 1_000_000_000 && f.t_ns <= now,
            "frame time {} not within the test's run [{started_ns}, {now}]",
            f.t_ns
        );
    }
    for w in frames.windows(2) {
        assert!(w[1].seq > w[0].seq, "seq not increasing: {} then {}", w[0].seq, w[1].seq);
        assert!(w[1].t_ns > w[0].t_ns, "time not increasing: {} then {}", w[0].t_ns, w[1].t_ns);
    }
}

/// Aravis's fake cameras fill Mono8 frames with a diagonal ramp: a pixel's value depends only
/// on `x + y` (and the frame number). A frame with a missing or stale packet breaks that.
fn is_diagonal_ramp(f: &Frame) -> bool {
    let (w, h) = (f.image.width as usize, f.image.height as usize);
    let d = &f.image.data;
    (1..h).all(|y| (0..w - 1).all(|x| d[y * w + x] == d[(y - 1) * w + x + 1]))
}

fn stop_and_join(cam: LiveCamera, stop: &AtomicBool) -> Duration {
    stop.store(true, Ordering::Relaxed);
    let t = Instant::now();
    cam.join();
    t.elapsed()
}

#[test]
fn in_process_fake_camera_streams_checked_frames() {
    let cfg = camera_cfg("aravis:Fake_1", 320, 240, 20.0);
    let (tx, mut rx) = tokio::sync::mpsc::channel(32);
    let stop = Arc::new(AtomicBool::new(false));
    let started = now_epoch_ns();
    // Through the public dispatcher, as the pipeline calls it.
    let cam = spawn_camera(0, &cfg, tx, stop.clone()).expect("in-process fake camera opens");
    let c = collect(&mut rx, 6, Duration::from_secs(5));
    let stats = cam.stats.snapshot();
    let stop_took = stop_and_join(cam, &stop);
    println!("in-process fake: {} frames, stats {stats:?}, stopped in {stop_took:?}", c.frames.len());
    assert!(c.frames.len() >= 6, "only {} frames in 5 s", c.frames.len());
    check_frames(&c.frames, 320, 240, started);
    assert!(c.frames.iter().all(is_diagonal_ramp), "a delivered frame is not the fake camera's ramp");
    let ts: Vec<i64> = c.frames.iter().map(|f| f.t_ns).collect();
    let mean_dt = (ts[ts.len() - 1] - ts[0]) as f64 / (ts.len() - 1) as f64 / 1e6;
    println!("mean frame interval {mean_dt:.1} ms (requested 50 ms)");
    assert!(mean_dt > 10.0 && mean_dt < 200.0, "frame interval {mean_dt} ms");
    assert_eq!(c.lost, 0);
}

/// With `full_depth` the fake camera streams Mono16 (it offers Mono8 and Mono16): every
/// frame keeps its 16-bit samples beside the 8-bit plane rounded from them, and the
/// full-depth samples are the camera's ramp.
#[test]
fn in_process_fake_camera_in_mono16_keeps_the_full_depth() {
    let mut cfg = camera_cfg("aravis:Fake_1", 160, 120, 20.0);
    cfg.full_depth = true;
    let (tx, mut rx) = tokio::sync::mpsc::channel(32);
    let stop = Arc::new(AtomicBool::new(false));
    let started = now_epoch_ns();
    let cam = spawn_camera(0, &cfg, tx, stop.clone()).expect("in-process fake camera opens");
    let c = collect(&mut rx, 4, Duration::from_secs(10));
    stop_and_join(cam, &stop);
    assert!(c.frames.len() >= 4, "only {} frames in 10 s", c.frames.len());
    check_frames(&c.frames, 160, 120, started);
    for f in &c.frames {
        let deep = f.image.deep.as_ref().expect("a Mono16 frame keeps its full depth");
        assert_eq!((deep.bits, deep.data.len()), (16, 160 * 120));
        let rounded: Vec<u8> = deep.data.iter().map(|&v| tagdeflect_core::frame::DeepPlane::to_8bit(16, v)).collect();
        assert!(rounded == f.image.data, "the 8-bit plane is not the full depth rounded");
        let (w, d) = (160usize, &deep.data);
        assert!((1..120).all(|y| (0..w - 1).all(|x| d[y * w + x] == d[(y - 1) * w + x + 1])), "not the fake camera's ramp");
        let distinct: std::collections::BTreeSet<u16> = d.iter().copied().collect();
        let low_bits_used = d.iter().any(|v| v & 0xff != 0);
        println!(
            "Mono16 frame {}: {} distinct values, {}..={}, low byte used: {low_bits_used}",
            f.seq,
            distinct.len(),
            d.iter().min().unwrap(),
            d.iter().max().unwrap()
        );
        assert!(distinct.len() > 100, "a 16-bit ramp has many levels: {}", distinct.len());
    }
    // Without `full_depth` the same camera gives Mono8: no full-depth copy.
    let cfg8 = camera_cfg("aravis:Fake_1", 160, 120, 20.0);
    let (tx, mut rx) = tokio::sync::mpsc::channel(32);
    let stop = Arc::new(AtomicBool::new(false));
    let cam = spawn_camera(0, &cfg8, tx, stop.clone()).expect("in-process fake camera opens");
    let c = collect(&mut rx, 2, Duration::from_secs(10));
    stop_and_join(cam, &stop);
    assert!(c.frames.len() >= 2 && c.frames.iter().all(|f| f.image.deep.is_none()), "Mono8 frames carry no full-depth plane");
}

#[test]
fn a_full_channel_drops_frames_and_counts_them() {
    let cfg = camera_cfg("aravis:Fake_1", 64, 48, 50.0);
    let (tx, mut rx) = tokio::sync::mpsc::channel(2);
    let stop = Arc::new(AtomicBool::new(false));
    let cam = spawn(0, &cfg, "Fake_1", AravisOptions::default(), tx, stop.clone()).expect("fake camera opens");
    // Nobody reads: the capture thread must not block, and what it captures meanwhile is
    // counted as dropped (waited for, however slow the machine).
    let deadline = Instant::now() + Duration::from_secs(30);
    while cam.stats.snapshot().dropped_full < 5 {
        assert!(Instant::now() < deadline, "no frame counted as dropped on a full channel in 30 s: {:?}", cam.stats.snapshot());
        std::thread::sleep(Duration::from_millis(20));
    }
    let before = cam.stats.snapshot();
    let c = collect(&mut rx, 4, Duration::from_secs(3));
    let after = cam.stats.snapshot();
    stop_and_join(cam, &stop);
    println!("full channel: before reading {before:?}; after {after:?}; drop reports {:?}", c.dropped);
    assert_eq!(before.delivered, 2, "the channel holds 2");
    assert!(before.dropped_full >= 5, "frames captured while the channel was full were not counted: {before:?}");
    let reported: u64 = c.dropped.iter().filter(|(_, w)| *w == DropReason::ChannelFull).map(|(n, _)| n).sum();
    assert!(reported >= before.dropped_full, "drops reported {reported} < counted {}", before.dropped_full);
    // seq gaps show the dropped frames.
    assert!(c.frames.windows(2).any(|w| w[1].seq > w[0].seq + 1) || c.frames.first().is_some_and(|f| f.seq > 1));
}

#[test]
fn dispatcher_errors_name_the_camera_and_source() {
    let (tx, _rx) = tokio::sync::mpsc::channel(2);
    let stop = Arc::new(AtomicBool::new(false));
    let err = spawn_camera(3, &camera_cfg("sim", 64, 48, 10.0), tx.clone(), stop.clone()).err();
    assert!(matches!(err, Some(SourceError::Sim { camera: 3, .. })), "{err:?}");
    // An unknown source is a config error now (caught when the config is read, before any
    // source starts): see tests/it/config.rs.
    let text = "name = \"cam\"\nsource = \"usb:/dev/foo\"\nwidth = 64\nheight = 48\nfx = 500.0\nfy = 500.0\ncx = 31.5\ncy = 23.5\n";
    let err = toml::from_str::<CameraConfig>(text).err().map(|e| e.to_string()).unwrap_or_default();
    assert!(err.contains("usb:/dev/foo") && err.contains("not a camera source"), "{err}");
    let err = spawn_camera(2, &camera_cfg("aravis:No-Such-Camera-42", 64, 48, 10.0), tx.clone(), stop.clone()).err();
    let msg = err.map(|e| e.to_string()).unwrap_or_default();
    println!("{msg}");
    assert!(msg.contains("No-Such-Camera-42") && msg.contains("camera 2"), "{msg}");
    let err = spawn_camera(0, &camera_cfg("v4l2:/dev/video-none", 64, 48, 10.0), tx, stop).err();
    let msg = err.map(|e| e.to_string()).unwrap_or_default();
    println!("{msg}");
    assert!(msg.contains("/dev/video-none"), "{msg}");
    // A size the camera cannot give is refused at open, not discovered frame by frame.
    let (tx, _rx) = tokio::sync::mpsc::channel(2);
    let stop = Arc::new(AtomicBool::new(false));
    let msg = match spawn(0, &camera_cfg("aravis:Fake_1", 9000, 9000, 10.0), "Fake_1", AravisOptions::default(), tx, stop.clone()) {
        Ok(cam) => {
            stop_and_join(cam, &stop);
            String::from("opened")
        }
        Err(e) => e.to_string(),
    };
    println!("{msg}");
    assert!(msg.contains("9000"), "{msg}");
}

#[test]
fn gige_fake_camera_on_loopback_streams_checked_frames() {
    let fake = FakeGvCamera::start("TDGV02", None);
    let cfg = camera_cfg(&format!("aravis:{}", fake.address), 256, 192, 20.0);
    let (tx, mut rx) = tokio::sync::mpsc::channel(32);
    let stop = Arc::new(AtomicBool::new(false));
    let started = now_epoch_ns();
    let cam = open_with_retry(&cfg, &fake.address, AravisOptions::default(), tx, &stop);
    let c = collect(&mut rx, 8, Duration::from_secs(6));
    let stats = cam.stats.snapshot();
    stop_and_join(cam, &stop);
    drop(fake);
    println!("GigE fake: {} frames, stats {stats:?}", c.frames.len());
    assert!(c.frames.len() >= 8, "only {} frames from the GigE fake camera", c.frames.len());
    check_frames(&c.frames, 256, 192, started);
    assert!(c.frames.iter().all(is_diagonal_ramp), "a delivered frame is not the fake camera's ramp");
    assert_eq!(c.lost, 0);
}

#[test]
fn gige_packet_loss_is_counted_and_never_delivered() {
    // 30 ‰ of the GVSP packets lost; resend off, so frames missing packets stay incomplete.
    let fake = FakeGvCamera::start("TDGV03", Some(30));
    let cfg = camera_cfg(&format!("aravis:{}", fake.address), 512, 256, 25.0);
    let (tx, mut rx) = tokio::sync::mpsc::channel(64);
    let stop = Arc::new(AtomicBool::new(false));
    let opts = AravisOptions { packet_resend: false, stall_timeout: Some(Duration::from_secs(30)), ..AravisOptions::default() };
    let cam = open_with_retry(&cfg, &fake.address, opts, tx, &stop);
    // Until both kinds were seen (measured: 9 complete, 89 incomplete in 4 s), so that the
    // check of the delivered frames below is over frames, not over none.
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut c = Collected::default();
    let incomplete_seen = |c: &Collected| c.dropped.iter().any(|(_, w)| *w == DropReason::Incomplete);
    while Instant::now() < deadline && !(c.frames.len() >= 3 && incomplete_seen(&c)) {
        let more = collect(&mut rx, usize::MAX, Duration::from_millis(200));
        c.frames.extend(more.frames);
        c.dropped.extend(more.dropped);
        c.lost += more.lost;
    }
    let stats = cam.stats.snapshot();
    stop_and_join(cam, &stop);
    drop(fake);
    let incomplete: u64 = c.dropped.iter().filter(|(_, w)| *w == DropReason::Incomplete).map(|(n, _)| n).sum();
    println!(
        "GigE fake with 3 % packet loss: {} complete frames delivered, {incomplete} incomplete reported, stats {stats:?}",
        c.frames.len()
    );
    assert!(stats.incomplete > 0, "no incomplete frame counted with 3 % packet loss: {stats:?}");
    assert!(incomplete > 0, "incomplete frames were not reported as Dropped events");
    assert!(c.frames.len() >= 3, "only {} complete frames delivered in 60 s", c.frames.len());
    assert!(c.frames.iter().all(is_diagonal_ramp), "a frame with missing packets was delivered");
    for f in &c.frames {
        assert_eq!((f.image.width, f.image.height), (512, 256));
    }
}

#[test]
fn gige_packet_loss_with_resend_delivers_only_complete_frames() {
    let fake = FakeGvCamera::start("TDGV04", Some(30));
    let cfg = camera_cfg(&format!("aravis:{}", fake.address), 512, 256, 25.0);
    let (tx, mut rx) = tokio::sync::mpsc::channel(64);
    let stop = Arc::new(AtomicBool::new(false));
    let opts = AravisOptions { stall_timeout: Some(Duration::from_secs(30)), ..AravisOptions::default() };
    let cam = open_with_retry(&cfg, &fake.address, opts, tx, &stop);
    let c = collect(&mut rx, 20, Duration::from_secs(5));
    let stats = cam.stats.snapshot();
    stop_and_join(cam, &stop);
    drop(fake);
    println!("GigE fake with 3 % packet loss and resend: {} frames delivered, stats {stats:?}", c.frames.len());
    assert!(c.frames.iter().all(is_diagonal_ramp), "a frame with missing packets was delivered");
    assert!(!c.frames.is_empty(), "no frame delivered with packet resend on");
}

#[test]
fn gige_camera_unplugged_is_reported_and_reopened() {
    let mut fake = FakeGvCamera::start("TDGV05", None);
    let cfg = camera_cfg(&format!("aravis:{}", fake.address), 128, 96, 25.0);
    let (tx, mut rx) = tokio::sync::mpsc::channel(64);
    let stop = Arc::new(AtomicBool::new(false));
    let opts = AravisOptions { stall_timeout: Some(Duration::from_secs(1)), ..AravisOptions::default() };
    let cam = open_with_retry(&cfg, &fake.address, opts, tx, &stop);
    let before = collect(&mut rx, 3, Duration::from_secs(5));
    assert!(before.frames.len() >= 3, "no frames before the unplug");
    fake.kill();
    // Lost within the stall timeout (plus a pop timeout), no frames meanwhile.
    let t_kill = Instant::now();
    let mut lost_after = None;
    while lost_after.is_none() && t_kill.elapsed() < Duration::from_secs(5) {
        match rx.try_recv() {
            Ok(SourceEvent::Lost { reason, .. }) => {
                println!("lost after {:?}: {reason}", t_kill.elapsed());
                lost_after = Some(t_kill.elapsed());
            }
            Ok(_) => {}
            Err(_) => std::thread::sleep(Duration::from_millis(10)),
        }
    }
    assert!(lost_after.is_some(), "the unplugged camera was not reported lost");
    fake.restart("TDGV05");
    let t_back = Instant::now();
    let mut reopened = false;
    let mut frames_after = 0;
    while frames_after < 3 && t_back.elapsed() < Duration::from_secs(15) {
        match rx.try_recv() {
            Ok(SourceEvent::Reopened { .. }) => {
                println!("reopened {:?} after the restart", t_back.elapsed());
                reopened = true;
            }
            Ok(SourceEvent::Frame(f)) => {
                assert!(reopened, "a frame arrived before Reopened");
                assert!(f.seq >= before.frames.last().map_or(0, |l| l.seq + 1), "seq went back after reopening");
                frames_after += 1;
            }
            Ok(_) => {}
            Err(_) => std::thread::sleep(Duration::from_millis(10)),
        }
    }
    let stats = cam.stats.snapshot();
    stop_and_join(cam, &stop);
    drop(fake);
    println!("unplug/replug: stats {stats:?}");
    assert!(reopened && frames_after >= 3, "camera not back: reopened {reopened}, {frames_after} frames");
    assert_eq!((stats.lost, stats.reopened), (1, 1));
}

#[test]
fn two_in_process_fake_cameras_stream_side_by_side() {
    // What an end-to-end run with several `aravis:Fake_1` cameras relies on.
    let (tx, mut rx) = tokio::sync::mpsc::channel(64);
    let stop = Arc::new(AtomicBool::new(false));
    let a = spawn_camera(0, &camera_cfg("aravis:Fake_1", 160, 120, 20.0), tx.clone(), stop.clone()).expect("first fake camera");
    let b = spawn_camera(1, &camera_cfg("aravis:Fake_1", 200, 100, 20.0), tx, stop.clone()).expect("second fake camera");
    let c = collect(&mut rx, 12, Duration::from_secs(5));
    stop.store(true, Ordering::Relaxed);
    a.join();
    b.join();
    let n0 = c.frames.iter().filter(|f| f.camera == 0).count();
    let n1 = c.frames.iter().filter(|f| f.camera == 1).count();
    println!("two fake cameras: {n0} + {n1} frames");
    assert!(n0 >= 3 && n1 >= 3, "frames per camera: {n0}, {n1}");
    for f in &c.frames {
        let want = if f.camera == 0 { (160, 120) } else { (200, 100) };
        assert_eq!((f.image.width, f.image.height), want);
    }
}

/// `tagdeflect cameras` lists what a config can name: here Aravis's in-process fake camera
/// (with `--with-fake`), with the `source = ...` line to write; without it, not.
#[test]
fn cameras_lists_the_fake_camera_with_its_source_line() {
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_tagdeflect")).args(["cameras", "--with-fake"]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("V4L2 capture devices:"), "{text}");
    assert!(text.contains("source = \"aravis:Fake_1\"") || text.contains("source = \"aravis:Aravis-Fake"), "{text}");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_tagdeflect")).arg("cameras").output().unwrap();
    assert!(o.status.success());
    assert!(!String::from_utf8_lossy(&o.stdout).contains("Fake"), "the fake camera only when asked for");
}
