//! Calibration import: camera intrinsics from the files labs already have (OpenCV
//! FileStorage YAML or JSON).

use std::path::{Path, PathBuf};

use crate::camera::CameraIntrinsics;

/// Error reading a calibration file.
#[derive(Debug, thiserror::Error)]
#[error("calibration file {path}: {message}")]
pub struct CalibrationError {
    path: PathBuf,
    message: String,
}

/// Reads an OpenCV FileStorage YAML (`%YAML:1.0`, `!!opencv-matrix`) or JSON calibration
/// with `camera_matrix` and `distortion_coefficients` (and `image_width`/`image_height`
/// when present; 0 otherwise).
pub fn load_calibration(path: &Path) -> Result<CameraIntrinsics, CalibrationError> {
    let err = |m: String| CalibrationError { path: path.to_path_buf(), message: m };
    let text = super::read_text_limited(path).map_err(|e| err(format!("cannot read: {e}")))?;
    let is_json = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("json")) || text.trim_start().starts_with('{');
    parse_calibration(&text, is_json, path)
}

/// Parses calibration text (JSON when `is_json`, else OpenCV YAML); `path` names it in errors.
pub fn parse_calibration(text: &str, is_json: bool, path: &Path) -> Result<CameraIntrinsics, CalibrationError> {
    let err = |m: String| CalibrationError { path: path.to_path_buf(), message: m };
    let value: serde_json::Value = if is_json {
        serde_json::from_str(text).map_err(|e| err(format!("not valid JSON: {e}")))?
    } else {
        yaml_to_json(text).map_err(err)?
    };
    let matrix = |key: &str| -> Result<Vec<f64>, String> {
        let m = value.get(key).ok_or_else(|| format!("no `{key}`"))?;
        let data = if let Some(d) = m.get("data") { d } else { m };
        let mut out = Vec::new();
        flatten_numbers(data, &mut out).map_err(|e| format!("`{key}`: {e}"))?;
        Ok(out)
    };
    let k = matrix("camera_matrix").map_err(err)?;
    if k.len() != 9 {
        return Err(err(format!("`camera_matrix` must have 9 numbers (3x3), has {}", k.len())));
    }
    let d = matrix("distortion_coefficients").map_err(err)?;
    if d.len() < 4 || d.len() > 14 {
        return Err(err(format!("`distortion_coefficients` must have 4 or 5 numbers, has {}", d.len())));
    }
    if d.len() > 5 && d[5..].iter().any(|&x| x != 0.0) {
        return Err(err("only the k1, k2, p1, p2, k3 distortion model is supported; higher coefficients are non-zero".into()));
    }
    let mut dist = [0.0; 5];
    for (i, v) in d.iter().take(5).enumerate() {
        dist[i] = *v;
    }
    let dim = |key: &str| value.get(key).and_then(|v| v.as_u64()).unwrap_or(0) as u32;
    Ok(CameraIntrinsics { width: dim("image_width"), height: dim("image_height"), fx: k[0], fy: k[4], cx: k[2], cy: k[5], dist })
}

fn flatten_numbers(v: &serde_json::Value, out: &mut Vec<f64>) -> Result<(), String> {
    match v {
        serde_json::Value::Number(n) => out.push(n.as_f64().ok_or("not a number")?),
        serde_json::Value::Array(a) => {
            for x in a {
                flatten_numbers(x, out)?;
            }
        }
        _ => return Err("expected numbers".into()),
    }
    Ok(())
}

/// OpenCV FileStorage YAML → JSON value. OpenCV writes `%YAML:1.0` (not valid YAML 1.x
/// directive syntax) and custom `!!opencv-matrix` tags; both are handled here.
fn yaml_to_json(text: &str) -> Result<serde_json::Value, String> {
    let cleaned: String = text
        .lines()
        .filter(|l| !l.trim_start().starts_with("%YAML"))
        .map(|l| l.replace("!!opencv-matrix", "").replace("!!opencv-nd-matrix", ""))
        .collect::<Vec<_>>()
        .join("\n");
    let docs = yaml_rust2::YamlLoader::load_from_str(&cleaned).map_err(|e| format!("not valid YAML: {e}"))?;
    let doc = docs.into_iter().next().ok_or("empty YAML file")?;
    Ok(yaml_value(&doc))
}

fn yaml_value(y: &yaml_rust2::Yaml) -> serde_json::Value {
    use yaml_rust2::Yaml;
    match y {
        Yaml::Real(s) => s.parse::<f64>().map(serde_json::Value::from).unwrap_or(serde_json::Value::Null),
        Yaml::Integer(i) => serde_json::Value::from(*i),
        Yaml::String(s) => s.parse::<f64>().map(serde_json::Value::from).unwrap_or_else(|_| serde_json::Value::from(s.clone())),
        Yaml::Boolean(b) => serde_json::Value::from(*b),
        Yaml::Array(a) => serde_json::Value::Array(a.iter().map(yaml_value).collect()),
        Yaml::Hash(h) => {
            serde_json::Value::Object(h.iter().filter_map(|(k, v)| k.as_str().map(|k| (k.to_string(), yaml_value(v)))).collect())
        }
        _ => serde_json::Value::Null,
    }
}
