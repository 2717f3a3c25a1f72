//! [`Recording::frames`]: a recording's frames in time order, read and decoded ahead on a
//! few threads — what `replay`, `bench` and `check` read a recording through.
//!
//! Decoding a PNG frame costs ~15 ms of CPU at 1080p; one reader thread caps a three-camera
//! replay at ~20 frame sets/s. Here `workers` threads take the next frames in turn (each
//! into its own recycled buffers, [`tagdeflect_core::frame::ImagePool`]) and at most `window` frames
//! are read ahead of the consumer, so memory stays bounded and frames come out in order.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::Instant;

use super::{FrameEntry, RecordedConfig, Recording, RecordingError};
use tagdeflect_core::frame::{Frame, ImagePool};

/// One frame as read: the frame, or why it could not be read (the entry names the file).
#[derive(Debug)]
pub struct ReadFrame {
    /// Index into [`Recording::frames`](Recording).
    pub index: usize,
    /// The frame, or the error naming its file.
    pub frame: Result<Frame, RecordingError>,
    /// Seconds spent reading and decoding it (on a worker thread).
    pub decode_s: f64,
}

struct Shared {
    rec: Recording<CameraList>,
    cameras: Vec<usize>,
    next: AtomicUsize,
    consumed: AtomicUsize,
    window: usize,
    stop: AtomicBool,
    done: Mutex<BTreeMap<usize, ReadFrame>>,
    changed: Condvar,
}

/// The iterator of [`Recording::frames`]; its threads end when it is dropped.
pub struct FrameReader {
    shared: Arc<Shared>,
    workers: Vec<JoinHandle<()>>,
    at: usize,
}

impl std::fmt::Debug for FrameReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameReader").field("at", &self.at).field("workers", &self.workers.len()).finish()
    }
}

/// A recording's cameras alone: what reading its frames needs of its config.
#[derive(Debug, Clone)]
pub struct CameraList(pub Vec<tagdeflect_core::camera_config::CameraConfig>);

impl RecordedConfig for CameraList {
    type Error = std::io::Error;
    fn load(path: &std::path::Path) -> Result<Self, Self::Error> {
        Err(std::io::Error::other(format!("{}: a camera list is built from a config, not read", path.display())))
    }
    fn cameras(&self) -> &[tagdeflect_core::camera_config::CameraConfig] {
        &self.0
    }
    fn to_toml_string(&self) -> String {
        String::new()
    }
}

impl<C: RecordedConfig> Recording<C> {
    /// This recording with only its cameras as config (what its frame readers hold).
    pub fn with_cameras_only(&self) -> Recording<CameraList> {
        Recording {
            dir: self.dir.clone(),
            config: CameraList(self.config.cameras().to_vec()),
            frames: self.frames.clone(),
            utm: Vec::new(),
            truth: Vec::new(),
            skipped_lines: Vec::new(),
        }
    }

    /// The frames in time order, decoded ahead on one thread per core (at most 4).
    pub fn frames(&self) -> FrameReader {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        self.frames_with(cores.clamp(1, 4))
    }

    /// The frames in time order, decoded ahead on `workers` threads.
    pub fn frames_with(&self, workers: usize) -> FrameReader {
        let workers = workers.max(1);
        let cameras =
            self.frames.iter().map(|e| self.config.camera_index(&e.camera).expect("checked when the recording is opened")).collect();
        let window = (2 * workers).max(2 * self.config.cameras().len()).max(4);
        let shared = Arc::new(Shared {
            rec: self.with_cameras_only(),
            cameras,
            next: AtomicUsize::new(0),
            consumed: AtomicUsize::new(0),
            window,
            stop: AtomicBool::new(false),
            done: Mutex::new(BTreeMap::new()),
            changed: Condvar::new(),
        });
        let handles = (0..workers)
            .map(|w| {
                let shared = shared.clone();
                std::thread::Builder::new()
                    .name(format!("frame-reader-{w}"))
                    .spawn(move || read_loop(&shared))
                    .expect("frame reader thread")
            })
            .collect();
        FrameReader { shared, workers: handles, at: 0 }
    }

    /// Reads entry `index` into a buffer of `pool` (`scratch` holds compressed bytes).
    pub fn read_frame(&self, index: usize, pool: &mut ImagePool, scratch: &mut Vec<u8>) -> Result<Frame, RecordingError> {
        let entry: &FrameEntry = &self.frames[index];
        let camera = self.config.camera_index(&entry.camera).expect("checked when the recording is opened");
        let image = pool.fill(|img| self.load_image_into(entry, img, scratch))?;
        Ok(Frame { camera, seq: entry.seq, t_ns: entry.t_ns, image })
    }
}

fn read_loop(shared: &Shared) {
    let mut pool = ImagePool::default();
    let mut scratch = Vec::new();
    loop {
        let i = shared.next.fetch_add(1, Ordering::SeqCst);
        if i >= shared.rec.frames.len() {
            return;
        }
        // Never more than `window` frames ahead of the consumer.
        {
            let mut g = shared.done.lock().expect("reader lock");
            while i >= shared.consumed.load(Ordering::SeqCst) + shared.window {
                if shared.stop.load(Ordering::SeqCst) {
                    return;
                }
                g = shared.changed.wait(g).expect("reader lock");
            }
        }
        if shared.stop.load(Ordering::SeqCst) {
            return;
        }
        let t = Instant::now();
        debug_assert_eq!(shared.cameras[i], shared.rec.config.camera_index(&shared.rec.frames[i].camera).unwrap_or(usize::MAX));
        let frame = shared.rec.read_frame(i, &mut pool, &mut scratch);
        let read = ReadFrame { index: i, frame, decode_s: t.elapsed().as_secs_f64() };
        shared.done.lock().expect("reader lock").insert(i, read);
        shared.changed.notify_all();
    }
}

impl Iterator for FrameReader {
    type Item = ReadFrame;

    fn next(&mut self) -> Option<ReadFrame> {
        if self.at >= self.shared.rec.frames.len() {
            return None;
        }
        let mut g = self.shared.done.lock().expect("reader lock");
        let item = loop {
            if let Some(x) = g.remove(&self.at) {
                break x;
            }
            g = self.shared.changed.wait(g).expect("reader lock");
        };
        drop(g);
        self.at += 1;
        self.shared.consumed.store(self.at, Ordering::SeqCst);
        self.shared.changed.notify_all();
        Some(item)
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = self.shared.rec.frames.len() - self.at;
        (left, Some(left))
    }
}

impl Drop for FrameReader {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        {
            let _g = self.shared.done.lock().expect("reader lock");
            self.shared.changed.notify_all();
        }
        for w in self.workers.drain(..) {
            let _ = w.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recording::RecordingWriter;
    use tagdeflect_core::camera_config::{CameraConfig, CameraSource};

    #[test]
    fn frames_come_in_order_bad_ones_named_and_reading_stops_when_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let camera = |name: &str| CameraConfig {
            name: name.into(),
            source: CameraSource::Sim,
            fps: None,
            width: 64,
            height: 48,
            fx: 60.0,
            fy: 60.0,
            cx: 31.5,
            cy: 23.5,
            dist: [0.0; 5],
            rvec: None,
            tvec_mm: None,
            full_depth: false,
        };
        let config = CameraList(vec![camera("left"), camera("right")]);
        let mut w = RecordingWriter::create(&dir.path().join("rec"), &config).unwrap();
        let names: Vec<String> = config.0.iter().map(|c| c.name.clone()).collect();
        for k in 0..20u64 {
            for (c, name) in names.iter().enumerate() {
                let mut img = tagdeflect_core::frame::GrayImage::new(64, 48);
                img.data[0] = (k * 2 + c as u64) as u8;
                w.write_frame(name, k, 1_000 + (k as i64) * 100 + c as i64, &img).unwrap();
            }
        }
        w.finish().unwrap();
        let rec_dir = dir.path().join("rec");
        // One frame file is corrupt.
        let rec = Recording::open_with(&rec_dir, config.clone()).unwrap();
        std::fs::write(rec_dir.join(&rec.frames[7].file), b"not an image").unwrap();
        for workers in [1, 3] {
            let got: Vec<ReadFrame> = rec.frames_with(workers).collect();
            assert_eq!(got.len(), 40);
            for (i, r) in got.iter().enumerate() {
                assert_eq!(r.index, i);
                match &r.frame {
                    Ok(f) => {
                        assert_ne!(i, 7);
                        assert_eq!(f.t_ns, rec.frames[i].t_ns);
                        assert_eq!(f.image.data[0] as usize, i);
                    }
                    Err(e) => {
                        assert_eq!(i, 7);
                        assert!(e.to_string().contains(&rec.frames[7].file), "{e}");
                    }
                }
            }
        }
        // Dropped early: the threads end.
        let mut r = rec.frames_with(2);
        assert!(r.next().is_some());
        drop(r);
    }
}
