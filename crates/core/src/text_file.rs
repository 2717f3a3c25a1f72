//! Reading a small text file (a config, a calibration) with a size limit, so a wrong path
//! (a disk image, `/dev/zero`) is refused instead of read into memory.

use std::path::Path;

/// Largest config or calibration file read, bytes (real ones are a few kB).
pub const MAX_CONFIG_BYTES: u64 = 16 << 20;

/// Reads a text file of at most [`MAX_CONFIG_BYTES`].
pub fn read_text_limited(path: &Path) -> std::io::Result<String> {
    use std::io::Read;
    let f = std::fs::File::open(path)?;
    let mut text = String::new();
    f.take(MAX_CONFIG_BYTES + 1).read_to_string(&mut text)?;
    if text.len() as u64 > MAX_CONFIG_BYTES {
        return Err(std::io::Error::other(format!("larger than {MAX_CONFIG_BYTES} bytes: not a config file")));
    }
    Ok(text)
}
