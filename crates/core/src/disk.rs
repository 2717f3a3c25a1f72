//! Free space on a filesystem (`statvfs`), for guards that stop a bulky output (a test's
//! frames) before the disk is too full for the lines.

use std::io;
use std::path::Path;

/// Bytes an unprivileged writer may still use on the filesystem holding `path`
/// (`f_bavail × f_frsize`).
pub fn free_bytes(path: &Path) -> io::Result<u64> {
    let st = rustix::fs::statvfs(path)?;
    Ok(st.f_bavail.saturating_mul(st.f_frsize))
}

#[cfg(test)]
mod tests {
    #[test]
    fn free_space_is_read_and_a_missing_path_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let before = super::free_bytes(dir.path()).unwrap();
        assert!(before > 0);
        assert!(super::free_bytes(&dir.path().join("absent")).is_err());
    }
}
