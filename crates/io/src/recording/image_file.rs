//! Frame files: 8- or 16-bit grey PNG or binary PGM (P5) read into a recycled image, their
//! size and depth checked against the camera's before anything is allocated. A 16-bit frame
//! keeps its full depth ([`tagdeflect_core::frame::DeepPlane`]: the significant bits from a
//! PNG's `sBIT` chunk, else 16; from a PGM's maxval) beside an 8-bit plane rounded from it.

use std::io::Read;
use std::path::Path;

use tagdeflect_core::frame::{DeepPlane, GrayImage};

use super::{io_err, RecordingError};

/// Why bytes are not an 8-bit grey frame.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// Neither a PNG nor a binary PGM.
    #[error("not a PNG or binary PGM (P5) image")]
    NotAnImage,
    /// The PGM header cannot be read.
    #[error("corrupt PGM header")]
    CorruptPgmHeader,
    /// The PGM's maxval is not 1 to 65535.
    #[error("PGM maxval {0}: frames must be 8- or 16-bit grey (maxval 1 to 65535)")]
    PgmMaxval(u32),
    /// The PGM ends before its pixels do.
    #[error("truncated PGM: {got} of {want} pixel bytes")]
    TruncatedPgm {
        /// Pixel bytes there.
        got: usize,
        /// Pixel bytes the header says.
        want: usize,
    },
    /// The PNG cannot be decoded.
    #[error("corrupt PNG: {0}")]
    CorruptPng(png::DecodingError),
    /// The PNG's pixels cannot be decoded.
    #[error("corrupt PNG data: {0}")]
    CorruptPngData(png::DecodingError),
    /// The PNG is not 8- or 16-bit grey.
    #[error("PNG is {color:?} {depth:?}: frames must be 8- or 16-bit grayscale")]
    NotGrey {
        /// Its colour type.
        color: png::ColorType,
        /// Its bit depth.
        depth: png::BitDepth,
    },
    /// The PNG is larger than any frame.
    #[error("PNG header says {width}x{height}: more than {MAX_IMAGE_PIXELS} pixels")]
    PngTooLarge {
        /// Its width, px.
        width: u32,
        /// Its height, px.
        height: u32,
    },
    /// The PNG's rows are not 8- or 16-bit grey.
    #[error("PNG row layout is not 8- or 16-bit grey")]
    PngRowLayout,
    /// The image is not the camera's size.
    #[error("image is {width}x{height} but camera is {camera_width}x{camera_height} (from its header)")]
    OtherSize {
        /// Its width, px.
        width: u32,
        /// Its height, px.
        height: u32,
        /// The camera's width, px.
        camera_width: u32,
        /// The camera's height, px.
        camera_height: u32,
    },
    /// The header's size is empty or too large.
    #[error("header says {width}x{height}")]
    BadSize {
        /// Its width, px.
        width: u32,
        /// Its height, px.
        height: u32,
    },
}

/// Largest image accepted without a known camera size (pixels): 256 Mpx.
pub(crate) const MAX_IMAGE_PIXELS: u64 = 1 << 28;
/// Largest image file read (bytes): 512 MiB.
pub(crate) const MAX_IMAGE_FILE_BYTES: u64 = 1 << 29;

/// Reads an 8- or 16-bit grey PNG or binary PGM (P5) into `img`, reusing its buffers;
/// at most [`MAX_IMAGE_PIXELS`] pixels and [`MAX_IMAGE_FILE_BYTES`] bytes.
pub fn read_gray_into(path: &Path, img: &mut GrayImage, scratch: &mut Vec<u8>) -> Result<(), RecordingError> {
    read_gray_into_checked(path, img, scratch, None)
}

/// [`read_gray_into`], checking the size in the header against `expect` (the camera's
/// width and height) *before* anything is allocated: a corrupt header that claims a huge
/// image is an error naming the file, never an allocation.
///
/// A PGM's pixels are read from the file straight into `img` (no intermediate copy); a
/// PNG is read whole into `scratch` (kept by the caller between frames) and decoded into
/// `img`, so a steady replay allocates nothing per frame.
pub(crate) fn read_gray_into_checked(
    path: &Path,
    img: &mut GrayImage,
    scratch: &mut Vec<u8>,
    expect: Option<(u32, u32)>,
) -> Result<(), RecordingError> {
    let bad = |m: String| RecordingError::BadImage { path: path.to_path_buf(), message: m };
    let mut file = tagdeflect_core::text_file::open_regular(path).map_err(io_err(path))?;
    let file_len = file.metadata().map_err(io_err(path))?.len();
    // A frame file is at most its pixels plus headers (PNG: plus incompressible overhead).
    let max_file = expect.map_or(MAX_IMAGE_FILE_BYTES, |(w, h)| (w as u64 * h as u64 * 2 + (1 << 20)).min(MAX_IMAGE_FILE_BYTES));
    if file_len > max_file {
        return Err(bad(format!("file is {file_len} bytes, more than any frame of this size can be (at most {max_file})")));
    }
    let check_size = |w: u32, h: u32| -> Result<(), RecordingError> {
        match expect {
            Some((ew, eh)) if (w, h) != (ew, eh) => {
                Err(bad(format!("image is {w}x{h} but camera is {ew}x{eh} (from its header; nothing read)")))
            }
            None if w as u64 * h as u64 > MAX_IMAGE_PIXELS => Err(bad(format!("header says {w}x{h}: more than {MAX_IMAGE_PIXELS} pixels"))),
            _ if w == 0 || h == 0 => Err(bad(format!("header says {w}x{h}: an empty image"))),
            _ => Ok(()),
        }
    };
    // Enough for any PGM header and the PNG signature.
    let mut head = [0u8; 512];
    let mut got = 0;
    while got < head.len() {
        match file.read(&mut head[got..]).map_err(io_err(path))? {
            0 => break,
            n => got += n,
        }
    }
    let head = &head[..got];
    if head.starts_with(b"P5") {
        let (w, h, maxval, data_start) = parse_pgm_header(head).map_err(|e| bad(e.to_string()))?;
        check_size(w, h)?;
        let n = w as usize * h as usize * pgm_sample_bytes(maxval);
        img.width = w;
        img.height = h;
        img.data.resize(n, 0);
        let in_head = (head.len() - data_start).min(n);
        img.data[..in_head].copy_from_slice(&head[data_start..data_start + in_head]);
        let mut filled = in_head;
        while filled < n {
            match file.read(&mut img.data[filled..]).map_err(io_err(path))? {
                0 => return Err(bad(format!("truncated PGM: {filled} of {n} pixel bytes"))),
                k => filled += k,
            }
        }
        pgm_to_planes(img, maxval);
        Ok(())
    } else if head.starts_with(b"\x89PNG") {
        // The size is in the IHDR chunk at bytes 16..24: checked before the file is read.
        if head.len() >= 26 && &head[12..16] == b"IHDR" {
            let be = |b: &[u8]| u32::from_be_bytes([b[0], b[1], b[2], b[3]]);
            check_size(be(&head[16..20]), be(&head[20..24]))?;
            // Depth and colour type (bytes 24, 25): grey (0) at 8 or 16 bits only.
            if head[25] != 0 || !matches!(head[24], 8 | 16) {
                return Err(bad(format!(
                    "PNG header says colour type {} at {} bits: frames must be 8- or 16-bit grayscale (nothing decoded)",
                    head[25], head[24]
                )));
            }
        }
        scratch.clear();
        scratch.extend_from_slice(head);
        (&mut file).take(max_file).read_to_end(scratch).map_err(io_err(path))?;
        decode_png(scratch, img).map_err(|e| bad(e.to_string()))?;
        check_size(img.width, img.height)
    } else {
        Err(bad(ImageError::NotAnImage.to_string()))
    }
}

/// Decodes an in-memory 8- or 16-bit grey PNG or binary PGM (what [`read_gray_into_checked`] reads
/// from a file), with the same size checks; used by the fuzz targets.
pub fn decode_gray_bytes(bytes: &[u8], img: &mut GrayImage, expect: Option<(u32, u32)>) -> Result<(), ImageError> {
    let check = |w: u32, h: u32| match expect {
        Some(e) if (w, h) != e => Err(ImageError::OtherSize { width: w, height: h, camera_width: e.0, camera_height: e.1 }),
        _ if w as u64 * h as u64 > MAX_IMAGE_PIXELS || w == 0 || h == 0 => Err(ImageError::BadSize { width: w, height: h }),
        _ => Ok(()),
    };
    if bytes.starts_with(b"P5") {
        let head = &bytes[..bytes.len().min(512)];
        let (w, h, maxval, start) = parse_pgm_header(head)?;
        check(w, h)?;
        let n = w as usize * h as usize * pgm_sample_bytes(maxval);
        let data =
            bytes.get(start..start + n).ok_or_else(|| ImageError::TruncatedPgm { got: bytes.len() - start.min(bytes.len()), want: n })?;
        img.width = w;
        img.height = h;
        img.data.clear();
        img.data.extend_from_slice(data);
        pgm_to_planes(img, maxval);
        Ok(())
    } else if bytes.starts_with(b"\x89PNG") {
        if bytes.len() >= 24 && &bytes[12..16] == b"IHDR" {
            let be = |b: &[u8]| u32::from_be_bytes([b[0], b[1], b[2], b[3]]);
            check(be(&bytes[16..20]), be(&bytes[20..24]))?;
        }
        decode_png(bytes, img)?;
        check(img.width, img.height)
    } else {
        Err(ImageError::NotAnImage)
    }
}

fn decode_png(bytes: &[u8], img: &mut GrayImage) -> Result<(), ImageError> {
    // The decoder's own memory limit: the image itself plus slack.
    let decoder = png::Decoder::new_with_limits(bytes, png::Limits { bytes: (MAX_IMAGE_PIXELS as usize) + (1 << 20) });
    let mut reader = decoder.read_info().map_err(ImageError::CorruptPng)?;
    let info = reader.info();
    let sixteen = match (info.color_type, info.bit_depth) {
        (png::ColorType::Grayscale, png::BitDepth::Eight) => false,
        (png::ColorType::Grayscale, png::BitDepth::Sixteen) => true,
        (color, depth) => return Err(ImageError::NotGrey { color, depth }),
    };
    // Significant bits of a 16-bit PNG: its sBIT chunk (checked 1..=16 by the decoder), else 16.
    let sbit = info.sbit.as_ref().and_then(|b| b.first().copied()).unwrap_or(16);
    let (w, h) = (info.width, info.height);
    if w as u64 * h as u64 > MAX_IMAGE_PIXELS {
        return Err(ImageError::PngTooLarge { width: w, height: h });
    }
    let n = w as usize * h as usize;
    img.width = w;
    img.height = h;
    img.data.resize(if sixteen { 2 * n } else { n }, 0);
    if reader.output_buffer_size() != img.data.len() {
        return Err(ImageError::PngRowLayout);
    }
    reader.next_frame(&mut img.data).map_err(ImageError::CorruptPngData)?;
    if sixteen {
        // PNG keeps fewer significant bits in the high bits of each sample.
        samples_to_planes(img, sbit.clamp(1, 16), 16 - u32::from(sbit.clamp(1, 16)));
    } else {
        img.deep = None;
    }
    Ok(())
}

/// Bytes per sample of a PGM of `maxval`.
fn pgm_sample_bytes(maxval: u32) -> usize {
    if maxval > 255 {
        2
    } else {
        1
    }
}

/// Turns a PGM's pixels (in `img.data`) into the image's planes: 8-bit as they are, 16-bit
/// (big-endian, `0 ..= maxval`) at full depth with `bits` = the bits `maxval` needs.
fn pgm_to_planes(img: &mut GrayImage, maxval: u32) {
    if maxval > 255 {
        samples_to_planes(img, (32 - maxval.leading_zeros()) as u8, 0);
    } else {
        img.deep = None;
    }
}

/// Moves big-endian 16-bit samples (in `img.data`, shifted left by `shift`) into the
/// full-depth plane with `bits` significant bits, and rounds the 8-bit plane from them;
/// both buffers are reused. Of 8 or fewer significant bits, the image is 8-bit.
fn samples_to_planes(img: &mut GrayImage, bits: u8, shift: u32) {
    let deep = img.deep.get_or_insert_with(DeepPlane::default);
    deep.bits = bits.max(9);
    deep.data.clear();
    // Fewer than 9 significant bits are widened to 9 (one bit of zeros), then rounded back;
    // a PGM sample above its maxval is clamped to the depth's largest value.
    let widen = u32::from(deep.bits - bits);
    let max = (1u32 << deep.bits) - 1;
    deep.data.extend(img.data.chunks_exact(2).map(|b| (((u16::from_be_bytes([b[0], b[1]]) >> shift) as u32) << widen).min(max) as u16));
    img.fill_8bit_from_deep();
    if bits <= 8 {
        img.deep = None;
    }
}

/// Parses a binary PGM header: width, height, maxval and the offset of the first pixel byte.
/// Header: "P5" whitespace width whitespace height whitespace maxval single-whitespace
/// data; '#' comments allowed between tokens.
fn parse_pgm_header(bytes: &[u8]) -> Result<(u32, u32, u32, usize), ImageError> {
    let mut pos = 2;
    let mut fields = [0u32; 3];
    for field in fields.iter_mut() {
        loop {
            while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
                pos += 1;
            }
            if pos < bytes.len() && bytes[pos] == b'#' {
                while pos < bytes.len() && bytes[pos] != b'\n' {
                    pos += 1;
                }
            } else {
                break;
            }
        }
        let start = pos;
        while pos < bytes.len() && bytes[pos].is_ascii_digit() {
            pos += 1;
        }
        let s = std::str::from_utf8(&bytes[start..pos]).unwrap_or("");
        *field = s.parse().map_err(|_| ImageError::CorruptPgmHeader)?;
    }
    if pos >= bytes.len() || !bytes[pos].is_ascii_whitespace() {
        return Err(ImageError::CorruptPgmHeader);
    }
    let [w, h, maxval] = fields;
    if maxval == 0 || maxval > 65535 {
        return Err(ImageError::PgmMaxval(maxval));
    }
    Ok((w, h, maxval, pos + 1))
}
