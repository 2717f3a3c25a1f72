//! Where methods are found: a lab's own files in `<tests>/methods/NAME.toml` (which win over a
//! shipped method of the same name), else the shipped ones; and their reviews,
//! `<tests>/methods/NAME.review.json`, each naming the SHA-256 of the file it reviewed (a file
//! changed since voids its review).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::Digest;

use super::{valid_name, Method, MethodRef, MethodReview, SHIPPED};
use crate::Problem;

/// A method as found, with its file's text and hash and its review when still valid.
#[derive(Debug, Clone)]
pub struct Loaded {
    /// The method.
    pub method: Method,
    /// Its file's text as used.
    pub text: String,
    /// SHA-256 (hex) of `text`.
    pub sha256: String,
    /// The lab's file, or `None` for a shipped method.
    pub path: Option<PathBuf>,
    /// The review of this very file, if there is one.
    pub review: Option<MethodReview>,
}

impl Loaded {
    /// What `test.json` records.
    pub fn reference(&self) -> MethodRef {
        MethodRef {
            name: self.method.name.clone(),
            version: self.method.version,
            standard: self.method.standard.clone(),
            sha256: self.sha256.clone(),
            review: self.review.clone(),
        }
    }

    /// Where the method comes from: its file, or `built-in`.
    pub fn origin(&self) -> String {
        self.path.as_ref().map_or_else(|| "built-in".to_string(), |p| p.display().to_string())
    }
}

/// `<tests>/methods/NAME.review.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReviewFile {
    /// The method's name.
    pub name: String,
    /// Its version as reviewed.
    pub version: u32,
    /// SHA-256 (hex) of the method file reviewed.
    pub sha256: String,
    /// Who, when, what it means.
    #[serde(flatten)]
    pub review: MethodReview,
}

/// Why a method cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum MethodError {
    /// No such method.
    #[error("no method \"{name}\" (shipped: {shipped}; a lab's own in {dir})")]
    NotFound {
        /// The name asked for.
        name: String,
        /// The shipped methods' names.
        shipped: String,
        /// The lab's folder of methods.
        dir: String,
    },
    /// A file that cannot be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// A method file that does not pass its checks; `text` lets the caller locate the key.
    #[error("{origin}: {problem}")]
    Bad {
        /// The file (or `built-in NAME`).
        origin: String,
        /// Its text.
        text: String,
        /// What is wrong, keyed by the file's key.
        problem: Problem,
    },
}

/// The lab's folder of methods and reviews.
pub fn methods_dir(tests: &Path) -> PathBuf {
    tests.join("methods")
}

/// SHA-256 (hex) of bytes.
pub fn sha256_hex(bytes: &[u8]) -> String {
    sha2::Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// The method `name`: the lab's file, else the shipped one; with its review when valid.
pub fn find(tests: &Path, name: &str) -> Result<Loaded, MethodError> {
    let not_found = || MethodError::NotFound {
        name: name.escape_debug().to_string(),
        shipped: SHIPPED.iter().map(|s| s.0).collect::<Vec<_>>().join(", "),
        dir: methods_dir(tests).display().to_string(),
    };
    valid_name(name).map_err(|_| not_found())?;
    let path = methods_dir(tests).join(format!("{name}.toml"));
    let (text, origin, path) = match std::fs::read_to_string(&path) {
        Ok(t) => (t, path.display().to_string(), Some(path)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let (_, t) = SHIPPED.iter().find(|s| s.0 == name).ok_or_else(not_found)?;
            (t.to_string(), format!("built-in {name}"), None)
        }
        Err(e) => return Err(MethodError::Io { path: path.display().to_string(), source: e }),
    };
    let method = Method::parse(&text).map_err(|problem| MethodError::Bad { origin: origin.clone(), text: text.clone(), problem })?;
    if method.name != name {
        let problem = Problem::new("name", format!("\"{}\": a method file's name is its file's (\"{name}\")", method.name));
        return Err(MethodError::Bad { origin, text, problem });
    }
    let sha256 = sha256_hex(text.as_bytes());
    let review = read_review(tests, name)?.filter(|r| r.sha256 == sha256).map(|r| r.review);
    Ok(Loaded { method, text, sha256, path, review })
}

/// Every method: the shipped ones and the lab's (a lab's file of a shipped name once).
pub fn list(tests: &Path) -> Vec<Result<Loaded, MethodError>> {
    let mut names: Vec<String> = SHIPPED.iter().map(|s| s.0.to_string()).collect();
    if let Ok(entries) = std::fs::read_dir(methods_dir(tests)) {
        let mut own: Vec<String> = entries
            .flatten()
            .filter_map(|e| e.file_name().to_str().and_then(|n| n.strip_suffix(".toml")).map(str::to_string))
            .filter(|n| !names.contains(n))
            .collect();
        own.sort();
        names.extend(own);
    }
    names.iter().map(|n| find(tests, n)).collect()
}

/// The review file of `name`, if there is one (whatever file it reviewed).
pub fn read_review(tests: &Path, name: &str) -> Result<Option<ReviewFile>, MethodError> {
    let path = methods_dir(tests).join(format!("{name}.review.json"));
    let io = |e| MethodError::Io { path: path.display().to_string(), source: e };
    match std::fs::read_to_string(&path) {
        Ok(text) => serde_json::from_str(&text).map(Some).map_err(|e| io(std::io::Error::new(std::io::ErrorKind::InvalidData, e))),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(io(e)),
    }
}

/// Writes the review of the method `name` as it is now (`<tests>/methods/NAME.review.json`).
pub fn review(tests: &Path, name: &str, review: MethodReview) -> Result<ReviewFile, MethodError> {
    let m = find(tests, name)?;
    let file = ReviewFile { name: name.to_string(), version: m.method.version, sha256: m.sha256, review };
    let dir = methods_dir(tests);
    let path = dir.join(format!("{name}.review.json"));
    let io = |e| MethodError::Io { path: path.display().to_string(), source: e };
    std::fs::create_dir_all(&dir).map_err(io)?;
    let text = serde_json::to_string_pretty(&file).map_err(|e| io(std::io::Error::other(e)))?;
    let tmp = path.with_extension("json.tmp");
    std::fs::write(&tmp, text + "\n").and_then(|()| std::fs::rename(&tmp, &path)).map_err(io)?;
    Ok(file)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reviewed() -> MethodReview {
        MethodReview { by: "A. Reviewer".into(), at: "2026-12-06T10:00:00Z".into(), meaning: "checked against the standard".into() }
    }

    #[test]
    fn a_review_holds_for_the_file_it_reviewed_and_a_changed_file_voids_it() {
        let dir = tempfile::tempdir().unwrap();
        let m = find(dir.path(), "C1609-19").unwrap();
        assert!(m.path.is_none() && m.review.is_none(), "shipped, not reviewed");
        review(dir.path(), "C1609-19", reviewed()).unwrap();
        let m = find(dir.path(), "C1609-19").unwrap();
        assert_eq!(m.reference().review, Some(reviewed()));
        // The lab's own copy of the method, changed: the review no longer holds.
        let changed = SHIPPED[0].1.replace("max_start_load_kn = 2.0", "max_start_load_kn = 3.0");
        std::fs::write(methods_dir(dir.path()).join("C1609-19.toml"), changed).unwrap();
        let m = find(dir.path(), "C1609-19").unwrap();
        assert_eq!(m.method.max_start_load_kn, 3.0);
        assert!(m.review.is_none(), "a changed file voids the review");
        assert!(matches!(find(dir.path(), "C9999"), Err(MethodError::NotFound { .. })));
        assert_eq!(list(dir.path()).iter().filter(|m| m.is_ok()).count(), 3);
    }
}
