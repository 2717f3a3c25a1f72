//! Reading a small text file (a config, a calibration) with a size limit, so a wrong path
//! (a disk image, `/dev/zero`) is refused instead of read into memory.

use std::path::Path;

/// Largest config or calibration file read, bytes (real ones are a few kB).
pub const MAX_CONFIG_BYTES: u64 = 16 << 20;

/// Opens a regular file for reading. A FIFO, a device or a folder is refused before it is
/// opened (opening a FIFO with no writer would block for ever; a device has no end).
pub fn open_regular(path: &Path) -> std::io::Result<std::fs::File> {
    let m = std::fs::metadata(path)?;
    if !m.is_file() {
        let kind = if m.is_dir() { "a folder" } else { "not a regular file (a FIFO, socket or device)" };
        return Err(std::io::Error::new(std::io::ErrorKind::InvalidInput, format!("{kind}, not a file to read")));
    }
    std::fs::File::open(path)
}

/// Reads a text file of at most [`MAX_CONFIG_BYTES`] (a regular file: see [`open_regular`]).
pub fn read_text_limited(path: &Path) -> std::io::Result<String> {
    use std::io::Read;
    let f = open_regular(path)?;
    let mut text = String::new();
    f.take(MAX_CONFIG_BYTES + 1).read_to_string(&mut text)?;
    if text.len() as u64 > MAX_CONFIG_BYTES {
        return Err(std::io::Error::other(format!("larger than {MAX_CONFIG_BYTES} bytes: not a config file")));
    }
    Ok(text)
}
