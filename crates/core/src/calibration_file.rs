//! Calibration import: camera intrinsics from the files labs already have: OpenCV
//! FileStorage YAML or JSON, ROS `camera_info` YAML (`plumb_bob`, also the message form with
//! `K`/`D`), and Kalibr `camchain.yaml` / camera YAML (`pinhole` + `radtan`). A camchain with
//! several cameras takes a selector: `calibration = "camchain.yaml#cam1"`.

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
    // `file.yaml#cam1` selects one camera of a Kalibr camchain.
    let (path, selector) = split_selector(path);
    let path = path.as_path();
    let err = |m: String| CalibrationError { path: path.to_path_buf(), message: m };
    let text = crate::text_file::read_text_limited(path).map_err(|e| err(format!("cannot read: {e}")))?;
    let is_json = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("json")) || text.trim_start().starts_with('{');
    parse_selected(&text, is_json, path, selector.as_deref())
}

/// Parses calibration text (JSON when `is_json`, else OpenCV YAML, Kalibr camchain or ROS
/// camera_info); `path` names it in errors.
pub fn parse_calibration(text: &str, is_json: bool, path: &Path) -> Result<CameraIntrinsics, CalibrationError> {
    parse_selected(text, is_json, path, None)
}

/// [`parse_calibration`] with a `#camN` selector for a Kalibr camchain.
fn parse_selected(text: &str, is_json: bool, path: &Path, selector: Option<&str>) -> Result<CameraIntrinsics, CalibrationError> {
    let err = |m: String| CalibrationError { path: path.to_path_buf(), message: m };
    let value: serde_json::Value = if is_json {
        serde_json::from_str(text).map_err(|e| err(format!("not valid JSON: {e}")))?
    } else {
        yaml_to_json(text).map_err(err)?
    };
    if let Some(k) = kalibr_or_ros(&value, selector).map_err(err)? {
        return Ok(k);
    }
    if selector.is_some() {
        return Err(err("a `#camN` selector applies to a Kalibr camchain only".into()));
    }
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

/// The file a `calibration` value names: `file.yaml#cam1` (a camera of a Kalibr camchain)
/// is `file.yaml`, when `file.yaml#cam1` itself does not exist.
pub fn calibration_file_path(path: &Path) -> PathBuf {
    split_selector(path).0
}

/// Splits `file#sel` when `file#sel` itself does not exist.
fn split_selector(path: &Path) -> (PathBuf, Option<String>) {
    if path.exists() {
        return (path.to_path_buf(), None);
    }
    let s = path.to_string_lossy();
    match s.rsplit_once('#') {
        Some((file, sel)) if !sel.is_empty() && !sel.contains('/') => (PathBuf::from(file), Some(sel.to_string())),
        _ => (path.to_path_buf(), None),
    }
}

fn numbers(v: &serde_json::Value, key: &str) -> Result<Vec<f64>, String> {
    let mut out = Vec::new();
    let data = v.get("data").unwrap_or(v);
    flatten_numbers(data, &mut out).map_err(|e| format!("`{key}`: {e}"))?;
    Ok(out)
}

/// Kalibr (camchain or single camera) and ROS `camera_info` files; `Ok(None)` for other files.
fn kalibr_or_ros(value: &serde_json::Value, selector: Option<&str>) -> Result<Option<CameraIntrinsics>, String> {
    let Some(obj) = value.as_object() else { return Ok(None) };
    // Kalibr: top-level `camera_model`, or cam0, cam1, ... each holding one.
    let cams: Vec<(&String, &serde_json::Value)> = obj.iter().filter(|(_, v)| v.get("camera_model").is_some()).collect();
    if obj.contains_key("camera_model") || !cams.is_empty() {
        let (name, cam) = if obj.contains_key("camera_model") {
            ("camera", value)
        } else {
            let names: Vec<&str> = cams.iter().map(|(n, _)| n.as_str()).collect();
            match selector {
                Some(sel) => {
                    let c = cams
                        .iter()
                        .find(|(n, _)| n.as_str() == sel)
                        .ok_or_else(|| format!("no camera `{sel}` in this camchain (it has {})", names.join(", ")))?;
                    (c.0.as_str(), c.1)
                }
                None if cams.len() == 1 => (cams[0].0.as_str(), cams[0].1),
                None => {
                    return Err(format!(
                        "Kalibr camchain with cameras {}: select one with `calibration = \"FILE#{}\"`",
                        names.join(", "),
                        names[0]
                    ))
                }
            }
        };
        return kalibr_camera(name, cam).map(Some);
    }
    if let Some(model) = obj.get("distortion_model").and_then(|m| m.as_str()) {
        return ros_camera_info(value, model).map(Some);
    }
    Ok(None)
}

fn kalibr_camera(name: &str, cam: &serde_json::Value) -> Result<CameraIntrinsics, String> {
    let camera_model = cam.get("camera_model").and_then(|v| v.as_str()).unwrap_or("?");
    let dist_model = cam.get("distortion_model").and_then(|v| v.as_str()).unwrap_or("none");
    let short = match dist_model {
        "equidistant" => "equi",
        other => other,
    };
    let model = format!("{camera_model}-{short}");
    if camera_model != "pinhole" || !(dist_model == "radtan" || dist_model == "none") {
        return Err(format!(
            "{name}: Kalibr camera model {model} is not supported: tagdeflect uses pinhole-radtan (OpenCV k1 k2 p1 p2 k3); \
             recalibrate with pinhole-radtan in Kalibr or with `tagdeflect calibrate`"
        ));
    }
    let i = numbers(cam.get("intrinsics").ok_or(format!("{name}: no `intrinsics`"))?, "intrinsics")?;
    if i.len() != 4 {
        return Err(format!("{name}: `intrinsics` must be [fu, fv, pu, pv], has {} numbers", i.len()));
    }
    let mut dist = [0.0; 5];
    if dist_model == "radtan" {
        let d = numbers(cam.get("distortion_coeffs").ok_or(format!("{name}: no `distortion_coeffs`"))?, "distortion_coeffs")?;
        if d.len() != 4 {
            return Err(format!("{name}: radtan `distortion_coeffs` must be [k1, k2, r1, r2], has {} numbers", d.len()));
        }
        dist[..4].copy_from_slice(&d);
    }
    let (w, h) = match cam.get("resolution").map(|r| numbers(r, "resolution")).transpose()? {
        Some(r) if r.len() == 2 => (r[0] as u32, r[1] as u32),
        Some(_) => return Err(format!("{name}: `resolution` must be [width, height]")),
        None => (0, 0),
    };
    Ok(CameraIntrinsics { width: w, height: h, fx: i[0], fy: i[1], cx: i[2], cy: i[3], dist })
}

fn ros_camera_info(v: &serde_json::Value, model: &str) -> Result<CameraIntrinsics, String> {
    if model != "plumb_bob" && model != "rational_polynomial" {
        return Err(format!("ROS camera_info distortion_model `{model}` is not supported: tagdeflect uses plumb_bob (k1 k2 p1 p2 k3)"));
    }
    // The calibration-file form (camera_matrix, distortion_coefficients) or the message
    // form (K, D; ROS 2: k, d).
    let get =
        |keys: &[&'static str]| -> Option<(&'static str, &serde_json::Value)> { keys.iter().find_map(|k| v.get(*k).map(|x| (*k, x))) };
    let (kk, kv) = get(&["camera_matrix", "K", "k"]).ok_or("no `camera_matrix` (or `K`)")?;
    let k = numbers(kv, kk)?;
    if k.len() != 9 {
        return Err(format!("`{kk}` must have 9 numbers (3x3), has {}", k.len()));
    }
    let (dk, dv) = get(&["distortion_coefficients", "D", "d"]).ok_or("no `distortion_coefficients` (or `D`)")?;
    let d = numbers(dv, dk)?;
    if d.len() > 5 && d[5..].iter().any(|&x| x != 0.0) {
        return Err(format!("`{dk}`: {model} coefficients k4..k6 are non-zero; only k1 k2 p1 p2 k3 are supported"));
    }
    if d.len() < 4 && !d.is_empty() {
        return Err(format!("`{dk}` must have 5 numbers (k1 k2 p1 p2 k3), has {}", d.len()));
    }
    let mut dist = [0.0; 5];
    for (i, x) in d.iter().take(5).enumerate() {
        dist[i] = *x;
    }
    let dim = |keys: &[&str]| keys.iter().find_map(|k| v.get(*k).and_then(|x| x.as_u64())).unwrap_or(0) as u32;
    Ok(CameraIntrinsics {
        width: dim(&["image_width", "width"]),
        height: dim(&["image_height", "height"]),
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
        dist,
    })
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
