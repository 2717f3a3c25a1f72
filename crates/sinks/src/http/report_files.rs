//! `GET /reports/{id}/{file}`: a stopped test's report files (`GET /reports/{id}`: which) (`TESTS/<id>/report/`), read-only,
//! for the page's link after a stop. Both path parts are hostile input: the test id must be one
//! folder name of the tests folder (letters, digits, `_`, `-`, `.`, not first; no separator),
//! the file one name of the report folder with a known extension; the folders on the way must
//! be real folders (not symbolic links), the file a regular file. The report's HTML is served
//! under a policy of its own: its inline style may apply, no script runs at all.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use axum::extract::State;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

use super::LiveView;

/// Largest report file served, bytes (a report's PDF is a few hundred KiB).
pub const MAX_REPORT_FILE: u64 = 64 * 1024 * 1024;

/// The report's own page runs no script and loads nothing but its own images.
const REPORT_CSP: &str = "default-src 'none'; style-src 'unsafe-inline'; img-src 'self' data:; frame-ancestors 'none'; base-uri 'none'";

/// The content type of a report file's extension; `None`: not served.
fn content_type(file: &str) -> Option<&'static str> {
    let ext = file.rsplit_once('.')?.1;
    Some(match ext {
        "html" => "text/html; charset=utf-8",
        "pdf" => "application/pdf",
        "json" => "application/json",
        "svg" => "image/svg+xml",
        "png" => "image/png",
        "csv" => "text/csv; charset=utf-8",
        _ => return None,
    })
}

/// One plain name: 1 to 128 letters, digits, `_`, `-`, `.`, not starting with `.`.
fn plain_name(s: &str) -> bool {
    !s.is_empty() && s.len() <= 128 && !s.starts_with('.') && s.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
}

/// The report file `file` of the test `id` under `tests`, or why not (404's text).
fn report_path(tests: &Path, id: &str, file: &str) -> Result<PathBuf, String> {
    if !plain_name(id) {
        return Err(format!("no test \"{}\": a test's id, as GET /api/tests names it", id.escape_debug()));
    }
    if !plain_name(file) || content_type(file).is_none() {
        return Err(format!("no report file \"{}\": report.html, report.pdf, report.json, …", file.escape_debug()));
    }
    let folder = tests.join(id);
    let report = folder.join("report");
    for dir in [&folder, &report] {
        if !std::fs::symlink_metadata(dir).is_ok_and(|m| m.is_dir()) {
            return Err(format!("test {id} has no report folder"));
        }
    }
    let path = report.join(file);
    match std::fs::symlink_metadata(&path) {
        Ok(m) if m.is_file() && m.len() <= MAX_REPORT_FILE => Ok(path),
        _ => Err(format!("test {id}'s report has no file {file}")),
    }
}

/// The report files of the test `id` under `tests` (none when its report was not made), or
/// why not (an id that names no test folder).
fn report_files(tests: &Path, id: &str) -> Result<Vec<String>, String> {
    let folder = tests.join(id);
    if !plain_name(id) || !std::fs::symlink_metadata(&folder).is_ok_and(|m| m.is_dir()) {
        return Err(format!("no test \"{}\" here", id.escape_debug()));
    }
    let mut files: Vec<String> = std::fs::read_dir(folder.join("report"))
        .map(|d| d.filter_map(|e| e.ok()).filter_map(|e| e.file_name().into_string().ok()).collect())
        .unwrap_or_default();
    files.retain(|f| report_path(tests, id, f).is_ok());
    files.sort();
    Ok(files)
}

/// `GET /reports/{id}`: `{"id", "files": [...]}`, the report files served (empty: no report),
/// so the page asks for report.json only when there is one.
pub(crate) async fn report_index(State(view): State<Arc<LiveView>>, axum::extract::Path(id): axum::extract::Path<String>) -> Response {
    let Some(api) = view.test_api.get() else {
        return (StatusCode::NOT_FOUND, "no tests here: configure [output] tests (or run with --tests DIR)").into_response();
    };
    let tests = api.tests_dir().to_path_buf();
    match tokio::task::spawn_blocking(move || report_files(&tests, &id).map(|f| (id, f))).await {
        Ok(Ok((id, files))) => axum::Json(serde_json::json!({"id": id, "files": files})).into_response(),
        Ok(Err(why)) => (StatusCode::NOT_FOUND, why).into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, format!("reading the report folder failed: {e}")).into_response(),
    }
}

/// `GET /reports/{id}/{file}`.
pub(crate) async fn report_file(
    State(view): State<Arc<LiveView>>,
    axum::extract::Path((id, file)): axum::extract::Path<(String, String)>,
) -> Response {
    let Some(api) = view.test_api.get() else {
        return (StatusCode::NOT_FOUND, "no tests here: configure [output] tests (or run with --tests DIR)").into_response();
    };
    let tests = api.tests_dir().to_path_buf();
    let read =
        move || report_path(&tests, &id, &file).and_then(|p| std::fs::read(&p).map_err(|e| format!("{file}: {e}")).map(|b| (b, file)));
    match tokio::task::spawn_blocking(read).await {
        Ok(Ok((bytes, file))) => {
            let mut resp = ([(header::CONTENT_TYPE, content_type(&file).unwrap_or("application/octet-stream"))], bytes).into_response();
            let hd = resp.headers_mut();
            hd.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
            hd.insert(header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(REPORT_CSP));
            resp
        }
        Ok(Err(why)) => (StatusCode::NOT_FOUND, why).into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, format!("reading the report failed: {e}")).into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_report_file_of_a_test_folder_is_served() {
        let dir = tempfile::tempdir().unwrap();
        let tests = dir.path().join("tests");
        let report = tests.join("20261206T100000Z-B1/report");
        std::fs::create_dir_all(&report).unwrap();
        std::fs::write(report.join("report.html"), "<p>ok</p>").unwrap();
        std::fs::write(report.join("notes.txt"), "not served").unwrap();
        std::fs::write(dir.path().join("secret.json"), "{}").unwrap();
        std::os::unix::fs::symlink(dir.path(), tests.join("link")).unwrap();
        assert_eq!(report_path(&tests, "20261206T100000Z-B1", "report.html").unwrap(), report.join("report.html"));
        assert_eq!(report_files(&tests, "20261206T100000Z-B1").unwrap(), ["report.html"]);
        assert!(report_files(&tests, "..").is_err() && report_files(&tests, "link").is_err());
        for (id, file) in [
            ("..", "report.html"),
            ("../tests/20261206T100000Z-B1", "report.html"),
            ("20261206T100000Z-B1", "../../secret.json"),
            ("20261206T100000Z-B1", "notes.txt"),
            ("20261206T100000Z-B1", ".hidden.json"),
            ("20261206T100000Z-B1", "report.pdf"),
            ("link", "secret.json"),
            ("%2e%2e", "report.html"),
            ("", "report.html"),
        ] {
            assert!(report_path(&tests, id, file).is_err(), "{id}/{file} served");
        }
    }
}
