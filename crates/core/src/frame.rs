//! Frames and frame sets: what sources produce and the sync stage groups.

use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// An 8-bit grayscale image, row-major, `stride == width`, with the camera's full-depth
/// samples beside it when the camera gives more than 8 bits ([`DeepPlane`]): detection reads
/// the 8-bit plane, the edge fit the full-depth one ([`GrayImage::level`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GrayImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height` bytes, row after row.
    pub data: Vec<u8>,
    /// The full-depth samples when the image has more than 8 significant bits (`None` for an
    /// 8-bit camera: nothing is copied).
    pub deep: Option<DeepPlane>,
}

/// The full-depth samples of an image deeper than 8 bits: `width * height` values, row after
/// row, LSB-aligned (`0 ..= 2^bits − 1`, as V4L2 `Y10`/`Y12`/`Y16` and GenICam
/// `Mono10`/`Mono12`/`Mono16` deliver them).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct DeepPlane {
    /// Significant bits per sample, 9 to 16.
    pub bits: u8,
    /// The samples.
    pub data: Vec<u16>,
}

impl DeepPlane {
    /// The 8-bit level of a sample: `v / 2^(bits − 8)`, rounded to the nearest grey level.
    #[inline]
    pub fn to_8bit(bits: u8, v: u16) -> u8 {
        let shift = u32::from(bits.saturating_sub(8));
        let half = (1u32 << shift) >> 1;
        ((u32::from(v) + half) >> shift).min(255) as u8
    }
}

impl GrayImage {
    /// A black image.
    pub fn new(width: u32, height: u32) -> Self {
        Self { width, height, data: vec![0; width as usize * height as usize], deep: None }
    }

    /// An 8-bit image of `data` (`width * height` bytes).
    pub fn from_8bit(width: u32, height: u32, data: Vec<u8>) -> Self {
        Self { width, height, data, deep: None }
    }

    /// Makes the 8-bit plane from the full-depth one ([`DeepPlane::to_8bit`]), reusing
    /// `data`'s buffer; `deep` must hold `width * height` samples.
    pub fn fill_8bit_from_deep(&mut self) {
        if let Some(deep) = &self.deep {
            let bits = deep.bits;
            self.data.clear();
            self.data.extend(deep.data.iter().map(|&v| DeepPlane::to_8bit(bits, v)));
        }
    }

    /// Significant bits per sample: the full-depth plane's, else 8.
    pub fn bits(&self) -> u8 {
        self.deep.as_ref().map_or(8, |d| d.bits)
    }

    /// The grey level of pixel `index` (row-major) on the 8-bit scale (0–255) at the image's
    /// full depth: the full-depth sample divided by `2^(bits − 8)` when there is one, else
    /// the 8-bit value. What the edge fit reads.
    #[inline]
    pub fn level(&self, index: usize) -> f32 {
        match &self.deep {
            Some(d) => f32::from(d.data[index]) / (1u32 << d.bits.saturating_sub(8)) as f32,
            None => f32::from(self.data[index]),
        }
    }

    /// Pixel at integer coordinates (no bounds check beyond the slice's).
    #[inline]
    pub fn get(&self, x: u32, y: u32) -> u8 {
        self.data[y as usize * self.width as usize + x as usize]
    }

    /// Bilinear sample at OpenCV pixel coordinates (centres at integers); clamps at the border.
    pub fn sample(&self, x: f64, y: f64) -> f64 {
        let xm = (self.width - 1) as f64;
        let ym = (self.height - 1) as f64;
        let x = x.clamp(0.0, xm);
        let y = y.clamp(0.0, ym);
        let x0 = x.floor() as u32;
        let y0 = y.floor() as u32;
        let x1 = (x0 + 1).min(self.width - 1);
        let y1 = (y0 + 1).min(self.height - 1);
        let fx = x - x0 as f64;
        let fy = y - y0 as f64;
        let a = self.get(x0, y0) as f64 * (1.0 - fx) + self.get(x1, y0) as f64 * fx;
        let b = self.get(x0, y1) as f64 * (1.0 - fx) + self.get(x1, y1) as f64 * fx;
        a * (1.0 - fy) + b * fy
    }
}

/// One captured frame of one camera.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Index of the camera in the config's camera list.
    pub camera: usize,
    /// That camera's frame counter.
    pub seq: u64,
    /// Capture time, ns since the Unix epoch.
    pub t_ns: i64,
    /// The image (shared: recorders and the detector read the same buffer).
    pub image: Arc<GrayImage>,
}

/// Frames of different cameras taken at (nearly) the same time; at most one per camera.
#[derive(Debug, Clone)]
pub struct FrameSet {
    /// Frame-set number from 0.
    pub seq: u64,
    /// Mean capture time of the frames, ns since the Unix epoch.
    pub t_ns: i64,
    /// The frames, at most one per camera, ordered by camera index.
    pub frames: Vec<Frame>,
}

impl FrameSet {
    /// Builds a set from frames of distinct cameras; `t_ns` is their mean time.
    pub fn new(seq: u64, mut frames: Vec<Frame>) -> Self {
        frames.sort_by_key(|f| f.camera);
        let t_ns = if frames.is_empty() {
            0
        } else {
            let base = i128::from(frames[0].t_ns);
            let sum: i128 = frames.iter().map(|f| i128::from(f.t_ns) - base).sum();
            // The mean of i64 values is an i64.
            (base + sum / frames.len() as i128) as i64
        };
        Self { seq, t_ns, frames }
    }
}

/// Recycles frame buffers: a source fills the first buffer nobody else holds any more
/// (the pipeline dropped its last `Arc`), so a steady stream allocates no new frames. The
/// pool grows to the number of frames in flight (bounded by the pipeline's queues).
#[derive(Debug, Default)]
pub struct ImagePool {
    slots: Vec<Arc<GrayImage>>,
}

impl ImagePool {
    /// Fills a free buffer with `fill` and returns it shared; on error the buffer stays
    /// in the pool.
    pub fn fill<E>(&mut self, fill: impl FnOnce(&mut GrayImage) -> Result<(), E>) -> Result<Arc<GrayImage>, E> {
        let i = match self.slots.iter_mut().position(|a| Arc::get_mut(a).is_some()) {
            Some(i) => i,
            None => {
                self.slots.push(Arc::new(GrayImage::new(0, 0)));
                self.slots.len() - 1
            }
        };
        fill(Arc::get_mut(&mut self.slots[i]).expect("no other holder"))?;
        Ok(self.slots[i].clone())
    }

    /// Buffers in the pool (free or in flight).
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    /// Whether the pool has no buffer yet.
    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }
}

/// How a recorder writes frames (SPEC allows both; the reader takes either).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum FrameFormat {
    /// 8-bit grey PNG, fast compression: about half the disk, but ~10 ms of CPU per
    /// 1080p frame to write and ~15 ms to read.
    #[default]
    Png,
    /// Binary PGM (P5): raw pixels behind a short header; costs no CPU, takes
    /// width × height bytes per frame (≈ 187 MB/s for three 1080p cameras at 30 fps).
    Pgm,
}

impl FrameFormat {
    /// The file extension (without the dot).
    pub fn extension(self) -> &'static str {
        match self {
            FrameFormat::Png => "png",
            FrameFormat::Pgm => "pgm",
        }
    }

    /// Encodes an image in this format: at 16 bits when it has a full-depth plane (PNG:
    /// samples scaled to the 16-bit range with an `sBIT` chunk giving the significant bits;
    /// PGM: maxval `2^bits − 1`, big-endian samples), else at 8 bits.
    pub fn encode(self, img: &GrayImage) -> Result<Vec<u8>, png::EncodingError> {
        match self {
            FrameFormat::Png => encode_png(img),
            FrameFormat::Pgm if img.deep.is_some() => Ok(encode_pgm16(img)),
            FrameFormat::Pgm => {
                let header = format!("P5\n{} {}\n255\n", img.width, img.height);
                let mut out = Vec::with_capacity(header.len() + img.data.len());
                out.extend_from_slice(header.as_bytes());
                out.extend_from_slice(&img.data);
                Ok(out)
            }
        }
    }
}

/// Encodes an image as a grey PNG (fast compression): 8-bit, or 16-bit with an `sBIT`
/// chunk when it has a full-depth plane.
pub fn encode_png(img: &GrayImage) -> Result<Vec<u8>, png::EncodingError> {
    if let Some(deep) = &img.deep {
        return encode_png16(img.width, img.height, deep);
    }
    let mut out = Vec::with_capacity(img.data.len() / 2);
    {
        let mut enc = png::Encoder::new(&mut out, img.width, img.height);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_compression(png::Compression::Fast);
        let mut w = enc.write_header()?;
        w.write_image_data(&img.data)?;
    }
    Ok(out)
}

/// A 16-bit grey PNG of `deep`: each sample shifted into the high bits (the PNG rule for
/// fewer significant bits than the sample depth) and `sBIT` = `deep.bits`.
fn encode_png16(width: u32, height: u32, deep: &DeepPlane) -> Result<Vec<u8>, png::EncodingError> {
    let shift = 16 - u32::from(deep.bits.clamp(1, 16));
    let bytes: Vec<u8> = deep.data.iter().flat_map(|&v| (v << shift).to_be_bytes()).collect();
    let mut out = Vec::with_capacity(bytes.len() / 2);
    {
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Sixteen);
        enc.set_compression(png::Compression::Fast);
        let mut w = enc.write_header()?;
        w.write_chunk(png::chunk::sBIT, &[deep.bits])?;
        w.write_image_data(&bytes)?;
    }
    Ok(out)
}

/// A binary 16-bit PGM of the full-depth plane: maxval `2^bits − 1`, big-endian samples.
fn encode_pgm16(img: &GrayImage) -> Vec<u8> {
    let deep = img.deep.as_ref().expect("called with a full-depth plane");
    let maxval = (1u32 << deep.bits) - 1;
    let header = format!("P5\n{} {}\n{maxval}\n", img.width, img.height);
    let mut out = Vec::with_capacity(header.len() + 2 * deep.data.len());
    out.extend_from_slice(header.as_bytes());
    out.extend(deep.data.iter().flat_map(|v| v.to_be_bytes()));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_level_reads_the_full_depth_on_the_8bit_scale() {
        let mut img = GrayImage::new(3, 1);
        assert_eq!((img.level(0), img.bits()), (0.0, 8));
        img.deep = Some(DeepPlane { bits: 12, data: vec![0x0ABC, 4095, 8] });
        img.fill_8bit_from_deep();
        assert_eq!(img.data, vec![0xAC, 255, 1], "rounded to the nearest 8-bit level");
        assert_eq!((img.level(0), img.level(2), img.bits()), (0x0ABC as f32 / 16.0, 0.5, 12));
    }

    #[test]
    fn pool_reuses_buffers_once_released() {
        let mut pool = ImagePool::default();
        let fill = |v: u8| {
            move |img: &mut GrayImage| -> Result<(), ()> {
                img.width = 4;
                img.height = 1;
                img.data.resize(4, 0);
                img.data.fill(v);
                Ok(())
            }
        };
        let a = pool.fill(fill(1)).unwrap();
        let b = pool.fill(fill(2)).unwrap();
        assert_eq!((a.data[0], b.data[0], pool.len()), (1, 2, 2), "held buffers are not overwritten");
        let ptr = a.data.as_ptr();
        drop(a);
        let c = pool.fill(fill(3)).unwrap();
        assert_eq!((c.data[0], b.data[0], pool.len()), (3, 2, 2));
        assert_eq!(c.data.as_ptr(), ptr, "the released buffer is reused");
        assert!(pool.fill(|_| Err::<(), _>("bad")).is_err());
        assert_eq!(pool.len(), 3);
    }
}
