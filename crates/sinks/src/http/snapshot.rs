//! Annotated camera snapshots (`/camera/NAME.jpg`): a frame downscaled to at most
//! [`THUMB_WIDTH`] pixels wide, the detected tags outlined and labelled (specimen tags in
//! orange `S<id>`, background tags in cyan `B<id>`), encoded as JPEG.
//!
//! Encoding runs on its own thread ([`spawn_encoder`]); the solver offers at most one frame
//! per camera per [`SNAPSHOT_INTERVAL`] through a bounded channel with `try_send`, so a slow
//! encoder loses snapshots, never time of the measurement.

use ab_glyph::{FontRef, PxScale};
use image::{ImageBuffer, Luma, Rgb, RgbImage};
use imageproc::drawing::{draw_line_segment_mut, draw_text_mut};
use std::sync::Arc;
use std::time::Duration;

use tagdeflect_core::frame::GrayImage;
use tagdeflect_core::observed::SeenTag;

/// Widest thumbnail, pixels (frames are shrunk by an integer factor to fit).
pub const THUMB_WIDTH: u32 = 480;
/// At most one snapshot per camera per this interval.
pub const SNAPSHOT_INTERVAL: Duration = Duration::from_secs(1);
/// JPEG quality of the snapshots.
pub const JPEG_QUALITY: u8 = 75;

/// Specimen tags' outline and label colour.
pub const SPECIMEN_COLOUR: [u8; 3] = [255, 140, 0];
/// Background tags' outline and label colour.
pub const BACKGROUND_COLOUR: [u8; 3] = [0, 200, 255];

static FONT: &[u8] = include_bytes!("assets/vendor/dejavu/DejaVuSansMono-Bold.ttf");

/// One frame to annotate.
pub struct SnapshotJob {
    /// Camera index in the config.
    pub camera: usize,
    /// Frame set number.
    pub seq: u64,
    /// Frame time, ns since the Unix epoch.
    pub t_ns: i64,
    /// The frame (shared with the pipeline; held only while encoding).
    pub image: Arc<GrayImage>,
    /// Tags detected in it.
    pub tags: Vec<SeenTag>,
}

/// An encoded snapshot.
#[derive(Clone, Debug)]
pub struct Snapshot {
    /// Frame set number.
    pub seq: u64,
    /// Frame time, ns since the Unix epoch.
    pub t_ns: i64,
    /// Thumbnail size, pixels.
    pub width: u32,
    /// Thumbnail height, pixels.
    pub height: u32,
    /// The JPEG file.
    pub jpeg: Arc<Vec<u8>>,
    /// When it was made.
    pub made: std::time::Instant,
}

/// Downscales, annotates and encodes one frame.
pub fn render(image: &GrayImage, tags: &[SeenTag]) -> Snapshot {
    let factor = image.width.div_ceil(THUMB_WIDTH).max(1);
    let (w, h) = ((image.width / factor).max(1), (image.height / factor).max(1));
    let gray: ImageBuffer<Luma<u8>, &[u8]> =
        ImageBuffer::from_raw(image.width, image.height, &image.data[..]).expect("frame buffer holds width × height bytes");
    let small = image::imageops::thumbnail(&gray, w, h);
    let mut rgb: RgbImage = ImageBuffer::from_fn(w, h, |x, y| {
        let v = small.get_pixel(x, y).0[0];
        Rgb([v, v, v])
    });
    let s = w as f64 / image.width as f64;
    // OpenCV pixel convention: centres at integers in both images.
    let map = |p: nalgebra::Point2<f64>| (((p.x + 0.5) * s - 0.5) as f32, ((p.y + 0.5) * s - 0.5) as f32);
    let font = FontRef::try_from_slice(FONT).expect("the embedded font parses");
    let scale = PxScale::from((h as f32 / 28.0).clamp(11.0, 18.0));
    for t in tags {
        let colour = Rgb(if t.specimen { SPECIMEN_COLOUR } else { BACKGROUND_COLOUR });
        let pts: Vec<(f32, f32)> = t.corners.iter().map(|c| map(*c)).collect();
        for i in 0..4 {
            let (a, b) = (pts[i], pts[(i + 1) % 4]);
            // Two pixels wide, readable on a small thumbnail.
            draw_line_segment_mut(&mut rgb, a, b, colour);
            draw_line_segment_mut(&mut rgb, (a.0 + 1.0, a.1), (b.0 + 1.0, b.1), colour);
        }
        let label = format!("{}{}", if t.specimen { 'S' } else { 'B' }, t.id);
        let x = pts.iter().map(|p| p.0).fold(f32::INFINITY, f32::min);
        let y = pts.iter().map(|p| p.1).fold(f32::INFINITY, f32::min) - scale.y - 1.0;
        draw_text_mut(&mut rgb, colour, x as i32, y.max(0.0) as i32, scale, &font, &label);
    }
    let mut jpeg = Vec::with_capacity((w * h / 4) as usize);
    let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, JPEG_QUALITY);
    enc.encode_image(&rgb).expect("encoding into memory cannot fail");
    Snapshot { seq: 0, t_ns: 0, width: w, height: h, jpeg: Arc::new(jpeg), made: std::time::Instant::now() }
}

/// Starts the encoder thread: it renders every job it receives and hands the result to
/// `done` (camera, snapshot). It ends when every sender is dropped.
pub fn spawn_encoder(
    rx: std::sync::mpsc::Receiver<SnapshotJob>,
    done: impl Fn(usize, Snapshot) + Send + 'static,
) -> std::io::Result<std::thread::JoinHandle<()>> {
    std::thread::Builder::new().name("snapshots".into()).spawn(move || {
        for job in rx {
            let mut snap = render(&job.image, &job.tags);
            drop(job.image);
            snap.seq = job.seq;
            snap.t_ns = job.t_ns;
            done(job.camera, snap);
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point2;
    use tagdeflect_core::tags::TagFamily;

    #[test]
    fn thumbnail_is_downscaled_jpeg_with_outlines_in_role_colours() {
        let mut img = GrayImage::new(1280, 960);
        img.data.iter_mut().for_each(|p| *p = 128);
        let square =
            |x: f64, y: f64| [Point2::new(x, y + 80.0), Point2::new(x + 80.0, y + 80.0), Point2::new(x + 80.0, y), Point2::new(x, y)];
        let tags = vec![
            SeenTag { family: TagFamily::Tag36h11, id: 3, specimen: true, corners: square(200.0, 200.0) },
            SeenTag { family: TagFamily::Tag25h9, id: 7, specimen: false, corners: square(800.0, 500.0) },
        ];
        let snap = render(&img, &tags);
        assert_eq!((snap.width, snap.height), (426, 320));
        assert_eq!(&snap.jpeg[..2], &[0xFF, 0xD8], "a JPEG file");
        let back = image::load_from_memory(&snap.jpeg).unwrap().to_rgb8();
        // The specimen outline's left edge at x ≈ (200.5 / 3) - 0.5 ≈ 66, y within the tag.
        let px = |x: u32, y: u32| back.get_pixel(x, y).0;
        let near = |c: [u8; 3], want: [u8; 3]| c.iter().zip(want).all(|(a, b)| (*a as i32 - b as i32).abs() < 60);
        let on_specimen = (64..70).any(|x| near(px(x, 90), SPECIMEN_COLOUR));
        let on_background = (264..270).any(|x| near(px(x, 190), BACKGROUND_COLOUR));
        assert!(on_specimen && on_background, "outlines in the role colours");
        assert!(near(px(150, 250), [128, 128, 128]), "the image itself is kept");
    }
}
