use super::*;
use tagdeflect_core::frame::GrayImage;

fn frame(seq: u64) -> Frame {
    Frame { camera: 0, seq, t_ns: 0, image: Arc::new(GrayImage::new(2, 2)) }
}

#[test]
fn full_channel_drops_and_reports_later() {
    let (tx, mut rx) = tokio::sync::mpsc::channel(2);
    let mut em = Emitter::new(0, tx, Arc::new(CaptureStats::default()));
    for s in 0..5 {
        em.frame(frame(s));
    }
    let snap = em.stats.snapshot();
    assert_eq!((snap.delivered, snap.dropped_full), (2, 3));
    assert!(matches!(rx.try_recv(), Ok(SourceEvent::Frame(f)) if f.seq == 0));
    assert!(matches!(rx.try_recv(), Ok(SourceEvent::Frame(f)) if f.seq == 1));
    em.lost("unplugged".into());
    em.frame(frame(5));
    assert!(matches!(rx.try_recv(), Ok(SourceEvent::Lost { camera: 0, .. })));
    assert!(matches!(rx.try_recv(), Ok(SourceEvent::Dropped { count: 3, why: DropReason::ChannelFull, .. })));
    // Frame 5 was dropped (channel full again): reported before the next delivered frame.
    em.frame(frame(6));
    assert!(matches!(rx.try_recv(), Ok(SourceEvent::Dropped { count: 1, why: DropReason::ChannelFull, .. })));
    assert!(matches!(rx.try_recv(), Ok(SourceEvent::Frame(f)) if f.seq == 6));
    drop(rx);
    em.frame(frame(7));
    assert!(em.is_closed());
}

/// A scripted device: plays its script, then times out.
struct Scripted(std::collections::VecDeque<Captured>);

impl CaptureSession for Scripted {
    fn next(&mut self, into: &mut GrayImage) -> Captured {
        if into.data.is_empty() {
            *into = GrayImage::new(2, 2);
        }
        self.0.pop_front().unwrap_or_else(|| {
            std::thread::sleep(Duration::from_millis(5));
            Captured::Timeout
        })
    }
}

fn img(t: i64) -> Captured {
    Captured::Image(t)
}

#[test]
fn capture_loop_reports_failure_reopens_and_keeps_counting() {
    let (tx, mut rx) = tokio::sync::mpsc::channel(64);
    let stats = Arc::new(CaptureStats::default());
    let mut em = Emitter::new(4, tx, stats.clone());
    let stop = Arc::new(AtomicBool::new(false));
    let first = Scripted(
        vec![
            img(1),
            Captured::Incomplete("missing packets".into()),
            img(2),
            Captured::Bad("short".into()),
            Captured::Failed("ENODEV".into()),
        ]
        .into(),
    );
    // The device stays away for two attempts, then comes back with two frames and stalls.
    let mut attempts = 0;
    let stop2 = stop.clone();
    let open = move || {
        attempts += 1;
        match attempts {
            1 | 2 => Err(format!("attempt {attempts}: no such device")),
            3 => Ok(Scripted(vec![img(10), img(11)].into())),
            _ => {
                stop2.store(true, Ordering::Relaxed);
                Err("stop here".into())
            }
        }
    };
    let timing =
        LoopTiming { stall: Duration::from_millis(100), backoff: Backoff::new(Duration::from_millis(10), Duration::from_millis(40)) };
    run_capture_loop(&mut em, "test:cam", Some(first), open, timing, &stop);
    let mut events = Vec::new();
    while let Ok(ev) = rx.try_recv() {
        events.push(ev);
    }
    let summary: Vec<String> = events
        .iter()
        .map(|e| match e {
            SourceEvent::Frame(f) => format!("frame{}@{}", f.seq, f.t_ns),
            SourceEvent::Lost { camera, reason } => format!("lost{camera}:{reason}"),
            SourceEvent::Reopened { camera } => format!("reopened{camera}"),
            SourceEvent::Dropped { count, why, .. } => format!("dropped{count}:{why:?}"),
        })
        .collect();
    println!("{summary:?}");
    assert_eq!(
        vec![
            "frame0@1",
            "dropped1:Incomplete",
            "frame1@2",
            "lost4:test:cam: ENODEV",
            "dropped1:BadBuffer",
            "reopened4",
            "frame2@10",
            "frame3@11",
        ],
        summary[..summary.len().min(8)]
    );
    assert_eq!(summary.len(), 9, "{summary:?}");
    assert!(summary[8].starts_with("lost4:test:cam: no complete frame for"), "{}", summary[8]);
    let s = stats.snapshot();
    assert_eq!((s.delivered, s.incomplete, s.bad_buffers, s.lost, s.reopened), (4, 1, 1, 2, 1));
}

#[test]
fn backoff_doubles_to_ten_seconds() {
    let mut b = Backoff::default();
    let d: Vec<u64> = (0..7).map(|_| b.next_delay().as_millis() as u64).collect();
    assert_eq!(d, vec![500, 1000, 2000, 4000, 8000, 10000, 10000]);
    b.reset();
    assert_eq!(b.next_delay(), Duration::from_millis(500));
}
