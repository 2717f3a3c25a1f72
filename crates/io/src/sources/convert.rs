//! Pixel-format conversion of captured buffers to the product's grey image (8-bit, with the
//! full-depth samples beside it for 10- to 16-bit layouts).
//!
//! Pure functions over byte slices: the live sources (V4L2, Aravis) hand in the bytes the
//! driver says are valid (`bytesused`, never the whole mapped buffer) and get a
//! [`GrayImage`] or a [`ConvertError`] — a short or malformed buffer is an error, never a
//! panic and never a half-filled image.

use tagdeflect_core::frame::GrayImage;

pub mod bayer;

pub use bayer::BayerPattern;

/// A raw pixel layout a camera can deliver.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelLayout {
    /// 8-bit grey (V4L2 `GREY`, GenICam `Mono8`).
    Gray8,
    /// 16-bit little-endian grey containers holding `bits` significant bits, LSB-aligned
    /// (V4L2 `Y16` is `bits = 16`, `Y10`/`Y12` are 10/12; GenICam `Mono16`, `Mono12`,
    /// `Mono10`). Kept at full depth ([`tagdeflect_core::frame::DeepPlane`]) beside an
    /// 8-bit plane rounded from it.
    Gray16Le {
        /// Significant bits per sample, 9..=16.
        bits: u8,
    },
    /// Packed YUV 4:2:2 `Y0 U Y1 V` (V4L2 `YUYV`): the luma bytes are kept.
    Yuyv,
    /// Motion-JPEG: each buffer is one JPEG image, decoded and converted to luma.
    Mjpeg,
    /// A colour sensor's raw 8-bit mosaic (V4L2 `RGGB`…, GenICam `BayerRG8`…): kept at full
    /// resolution, each site's gain equalised to a grey scene's ([`bayer`]: no demosaic), kept
    /// at 12 bits beside an 8-bit plane.
    Bayer8(BayerPattern),
}

impl PixelLayout {
    /// Bytes per pixel of an uncompressed layout (`None` for MJPEG).
    pub fn bytes_per_pixel(self) -> Option<usize> {
        match self {
            PixelLayout::Gray8 | PixelLayout::Bayer8(_) => Some(1),
            PixelLayout::Gray16Le { .. } | PixelLayout::Yuyv => Some(2),
            PixelLayout::Mjpeg => None,
        }
    }
}

/// Why a buffer could not be turned into an image.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ConvertError {
    /// Fewer bytes than the geometry needs.
    #[error("{layout:?} buffer of {width}x{height} (stride {stride}) needs {needed} bytes, got {got}")]
    Truncated {
        /// Pixel layout of the buffer.
        layout: PixelLayout,
        /// Image width in pixels.
        width: u32,
        /// Image height in pixels.
        height: u32,
        /// Bytes per row in the buffer.
        stride: usize,
        /// Bytes the geometry needs.
        needed: usize,
        /// Bytes available.
        got: usize,
    },
    /// A row stride shorter than one row of pixels, or a zero-sized image.
    #[error("bad geometry {width}x{height} with stride {stride} for {layout:?}")]
    Geometry {
        /// Pixel layout of the buffer.
        layout: PixelLayout,
        /// Image width in pixels.
        width: u32,
        /// Image height in pixels.
        height: u32,
        /// Bytes per row in the buffer.
        stride: usize,
    },
    /// The JPEG did not decode.
    #[error("MJPEG frame does not decode: {0}")]
    Jpeg(String),
    /// The decoded JPEG is not the configured size.
    #[error("MJPEG frame is {got_w}x{got_h}, expected {width}x{height}")]
    JpegSize {
        /// Expected width.
        width: u32,
        /// Expected height.
        height: u32,
        /// Decoded width.
        got_w: u32,
        /// Decoded height.
        got_h: u32,
    },
    /// A 16-bit layout with an impossible bit depth.
    #[error("unsupported bit depth {0} for a 16-bit grey container (9..=16)")]
    BitDepth(u8),
}

/// Converts one captured buffer to grey: 8-bit, plus the full-depth plane for
/// [`PixelLayout::Gray16Le`].
///
/// `data` is the valid part of the buffer (`bytesused`); `stride` is the bytes per row
/// (V4L2 `bytesperline`; 0 means tightly packed). Rows may be padded beyond the pixels, and
/// bytes after the last row are ignored. For MJPEG `stride` is ignored and the decoded size
/// must equal `width` × `height`.
pub fn to_gray8(layout: PixelLayout, width: u32, height: u32, stride: usize, data: &[u8]) -> Result<GrayImage, ConvertError> {
    let mut out = GrayImage::new(0, 0);
    to_gray8_into(layout, width, height, stride, data, &mut out)?;
    Ok(out)
}

/// [`to_gray8`] into `out`, reusing its buffer (a capture loop's recycled frame).
pub(crate) fn to_gray8_into(
    layout: PixelLayout,
    width: u32,
    height: u32,
    stride: usize,
    data: &[u8],
    out: &mut GrayImage,
) -> Result<(), ConvertError> {
    let bpp = match layout.bytes_per_pixel() {
        Some(b) => b,
        None => {
            *out = decode_mjpeg(width, height, data)?;
            return Ok(());
        }
    };
    let row_bytes = width as usize * bpp;
    let stride = if stride == 0 { row_bytes } else { stride };
    if width == 0 || height == 0 || stride < row_bytes {
        return Err(ConvertError::Geometry { layout, width, height, stride });
    }
    // The last row needs only its pixels, not its padding.
    let needed = stride * (height as usize - 1) + row_bytes;
    if data.len() < needed {
        return Err(ConvertError::Truncated { layout, width, height, stride, needed, got: data.len() });
    }
    let w = width as usize;
    out.width = width;
    out.height = height;
    if let PixelLayout::Gray16Le { bits } = layout {
        if !(9..=16).contains(&bits) {
            return Err(ConvertError::BitDepth(bits));
        }
        fill_deep(out, bits, w, data.chunks(stride).take(height as usize).map(|row| &row[..row_bytes]));
        return Ok(());
    }
    out.deep = None;
    out.data.resize(w * height as usize, 0);
    for (dst, row) in out.data.chunks_exact_mut(w).zip(data.chunks(stride)) {
        let row = &row[..row_bytes];
        match layout {
            PixelLayout::Gray8 | PixelLayout::Bayer8(_) => dst.copy_from_slice(row),
            PixelLayout::Yuyv => dst.iter_mut().zip(row.chunks_exact(2)).for_each(|(d, p)| *d = p[0]),
            PixelLayout::Gray16Le { .. } | PixelLayout::Mjpeg => {}
        }
    }
    if let PixelLayout::Bayer8(pattern) = layout {
        bayer::equalise(out, pattern);
    }
    Ok(())
}

/// Keeps 16-bit little-endian rows at full depth (`bits` significant, LSB-aligned; a value
/// above `2^bits − 1`, which a camera should not send, is clamped to it) and makes the 8-bit plane from them,
/// reusing `out`'s buffers.
fn fill_deep<'a>(out: &mut GrayImage, bits: u8, w: usize, rows: impl Iterator<Item = &'a [u8]>) {
    let deep = out.deep.get_or_insert_with(Default::default);
    deep.bits = bits;
    deep.data.clear();
    let max = ((1u32 << bits) - 1) as u16;
    for row in rows {
        deep.data.extend(row.chunks_exact(2).take(w).map(|p| u16::from_le_bytes([p[0], p[1]]).min(max)));
    }
    out.fill_8bit_from_deep();
}

/// Decodes one MJPEG frame. A frame must start with the start-of-image marker and end
/// (before any zero padding, which UVC cameras add) with the end-of-image marker: decoders
/// accept a JPEG cut short and fill the missing part, which must not reach the detector.
fn decode_mjpeg(width: u32, height: u32, data: &[u8]) -> Result<GrayImage, ConvertError> {
    let end = data.iter().rposition(|b| *b != 0).map_or(0, |i| i + 1);
    let data = &data[..end];
    if data.len() < 4 || data[..2] != [0xFF, 0xD8] {
        return Err(ConvertError::Jpeg(format!("no start-of-image marker ({} bytes)", data.len())));
    }
    if data[data.len() - 2..] != [0xFF, 0xD9] {
        return Err(ConvertError::Jpeg(format!("no end-of-image marker: frame cut short ({} bytes)", data.len())));
    }
    // The size from the header first: a corrupt frame that claims a huge image is refused
    // before anything is decoded or allocated.
    let reader = || image::ImageReader::with_format(std::io::Cursor::new(data), image::ImageFormat::Jpeg);
    let (got_w, got_h) = reader().into_dimensions().map_err(|e| ConvertError::Jpeg(e.to_string()))?;
    if (got_w, got_h) != (width, height) {
        return Err(ConvertError::JpegSize { width, height, got_w, got_h });
    }
    let img = reader().decode().map_err(|e| ConvertError::Jpeg(e.to_string()))?;
    let luma = img.to_luma8();
    if luma.width() != width || luma.height() != height {
        return Err(ConvertError::JpegSize { width, height, got_w: luma.width(), got_h: luma.height() });
    }
    Ok(GrayImage::from_8bit(width, height, luma.into_raw()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sixteen_bit_depths_keep_the_full_depth_beside_8_bits() {
        let px: u16 = 0x0ABC; // 12-bit value
        let data = px.to_le_bytes();
        let img = to_gray8(PixelLayout::Gray16Le { bits: 12 }, 1, 1, 0, &data).unwrap();
        assert_eq!(img.data, vec![0xAC], "the 8-bit plane is the nearest level");
        assert_eq!(img.deep.as_ref().map(|d| (d.bits, d.data.clone())), Some((12, vec![0x0ABC])));
        assert_eq!(img.level(0), 0x0ABC as f32 / 16.0);
        assert_eq!(to_gray8(PixelLayout::Gray16Le { bits: 16 }, 1, 1, 0, &data).unwrap().data, vec![0x0B]);
        let eight = to_gray8(PixelLayout::Gray8, 1, 1, 0, &[7]).unwrap();
        assert!(eight.deep.is_none(), "no full-depth copy of an 8-bit frame");
        assert!(matches!(to_gray8(PixelLayout::Gray16Le { bits: 8 }, 1, 1, 0, &data), Err(ConvertError::BitDepth(8))));
    }

    #[test]
    fn bad_stride_is_an_error() {
        let r = to_gray8(PixelLayout::Yuyv, 4, 2, 6, &[0; 64]);
        assert!(matches!(r, Err(ConvertError::Geometry { .. })), "{r:?}");
    }
}
