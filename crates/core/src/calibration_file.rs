//! Calibration import: camera intrinsics from the files labs already have: OpenCV
//! FileStorage YAML or JSON, ROS `camera_info` YAML (`plumb_bob`, also the message form with
//! `K`/`D`), and Kalibr `camchain.yaml` / camera YAML (`pinhole` + `radtan`). A camchain with
//! several cameras takes a selector: `calibration = "camchain.yaml#cam1"`.

use std::path::{Path, PathBuf};

use crate::camera::CameraIntrinsics;

/// Error reading a calibration file.
#[derive(Debug, thiserror::Error)]
#[error("calibration file {path}: {fault}")]
pub struct CalibrationError {
    path: PathBuf,
    fault: CalibrationFault,
}

/// What is wrong with a calibration file's text.
#[derive(Debug, thiserror::Error)]
enum CalibrationFault {
    #[error("cannot read: {0}")]
    Unreadable(std::io::Error),
    #[error("not valid JSON: {0}")]
    Json(serde_json::Error),
    #[error("not valid YAML: {0}")]
    Yaml(yaml_rust2::ScanError),
    #[error("empty YAML file")]
    EmptyYaml,
    #[error("a `#camN` selector applies to a Kalibr camchain only")]
    SelectorWithoutCamchain,
    #[error("no `{key}`")]
    Missing { key: &'static str },
    #[error("`{key}`: {fault}")]
    Numbers { key: &'static str, fault: NumberFault },
    #[error("`{key}` must have 9 numbers (3x3), has {len}")]
    MatrixSize { key: &'static str, len: usize },
    #[error("`distortion_coefficients` must have 4 or 5 numbers, has {len}")]
    DistortionCount { len: usize },
    #[error("only the k1, k2, p1, p2, k3 distortion model is supported; higher coefficients are non-zero")]
    HigherDistortion,
    #[error("no camera `{selector}` in this camchain (it has {cameras})")]
    NoSuchCamera { selector: String, cameras: String },
    #[error("Kalibr camchain with cameras {cameras}: select one with `calibration = \"FILE#{first}\"`")]
    CamchainNeedsSelector { cameras: String, first: String },
    #[error(
        "{camera}: Kalibr camera model {model} is not supported: tagdeflect uses pinhole-radtan (OpenCV k1 k2 p1 p2 k3); \
         recalibrate with pinhole-radtan in Kalibr or with `tagdeflect calibrate`"
    )]
    KalibrModel { camera: String, model: String },
    #[error("{camera}: no `{key}`")]
    KalibrMissing { camera: String, key: &'static str },
    #[error("{camera}: `intrinsics` must be [fu, fv, pu, pv], has {len} numbers")]
    KalibrIntrinsics { camera: String, len: usize },
    #[error("{camera}: radtan `distortion_coeffs` must be [k1, k2, r1, r2], has {len} numbers")]
    KalibrRadtan { camera: String, len: usize },
    #[error("{camera}: `resolution` must be [width, height]")]
    KalibrResolution { camera: String },
    #[error("ROS camera_info distortion_model `{model}` is not supported: tagdeflect uses plumb_bob (k1 k2 p1 p2 k3)")]
    RosModel { model: String },
    #[error("no `{key}` (or `{alt}`)")]
    RosMissing { key: &'static str, alt: &'static str },
    #[error("`{key}`: {model} coefficients k4..k6 are non-zero; only k1 k2 p1 p2 k3 are supported")]
    RosHigherDistortion { key: &'static str, model: String },
    #[error("`{key}` must have 5 numbers (k1 k2 p1 p2 k3), has {len}")]
    RosDistortionCount { key: &'static str, len: usize },
}

/// What is wrong with a list of numbers.
#[derive(Debug, thiserror::Error)]
enum NumberFault {
    #[error("not a number")]
    NotANumber,
    #[error("expected numbers")]
    ExpectedNumbers,
}

type Fault = CalibrationFault;
type Json = serde_json::Value;

/// Reads an OpenCV FileStorage YAML (`%YAML:1.0`, `!!opencv-matrix`) or JSON calibration
/// with `camera_matrix` and `distortion_coefficients` (and `image_width`/`image_height`
/// when present; 0 otherwise).
pub fn load_calibration(path: &Path) -> Result<CameraIntrinsics, CalibrationError> {
    // `file.yaml#cam1` selects one camera of a Kalibr camchain.
    let (path, selector) = split_selector(path);
    let text =
        crate::text_file::read_text_limited(&path).map_err(|e| CalibrationError { path: path.clone(), fault: Fault::Unreadable(e) })?;
    let is_json = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("json")) || text.trim_start().starts_with('{');
    parse_selected(&text, is_json, &path, selector.as_deref())
}

/// Parses calibration text (JSON when `is_json`, else OpenCV YAML, Kalibr camchain or ROS
/// camera_info); `path` names it in errors.
pub fn parse_calibration(text: &str, is_json: bool, path: &Path) -> Result<CameraIntrinsics, CalibrationError> {
    parse_selected(text, is_json, path, None)
}

/// [`parse_calibration`] with a `#camN` selector for a Kalibr camchain.
fn parse_selected(text: &str, is_json: bool, path: &Path, selector: Option<&str>) -> Result<CameraIntrinsics, CalibrationError> {
    parse_value(text, is_json)
        .and_then(|value| intrinsics_of(&value, selector))
        .map_err(|fault| CalibrationError { path: path.to_path_buf(), fault })
}

/// The file's text as one JSON value (YAML converted).
fn parse_value(text: &str, is_json: bool) -> Result<Json, Fault> {
    if is_json {
        serde_json::from_str(text).map_err(Fault::Json)
    } else {
        yaml_to_json(text)
    }
}

/// The intrinsics of a Kalibr, ROS or OpenCV calibration.
fn intrinsics_of(value: &Json, selector: Option<&str>) -> Result<CameraIntrinsics, Fault> {
    if let Some(k) = kalibr_or_ros(value, selector)? {
        return Ok(k);
    }
    if selector.is_some() {
        return Err(Fault::SelectorWithoutCamchain);
    }
    opencv_intrinsics(value)
}

/// OpenCV FileStorage: `camera_matrix`, `distortion_coefficients`, `image_width`/`image_height`.
fn opencv_intrinsics(value: &Json) -> Result<CameraIntrinsics, Fault> {
    let k = opencv_matrix(value, "camera_matrix")?;
    if k.len() != 9 {
        return Err(Fault::MatrixSize { key: "camera_matrix", len: k.len() });
    }
    let dist = opencv_distortion(value)?;
    let dim = |key: &str| value.get(key).and_then(|v| v.as_u64()).unwrap_or(0) as u32;
    Ok(CameraIntrinsics { width: dim("image_width"), height: dim("image_height"), fx: k[0], fy: k[4], cx: k[2], cy: k[5], dist })
}

/// The numbers of an OpenCV matrix (`data` of an `!!opencv-matrix`, or a plain list).
fn opencv_matrix(value: &Json, key: &'static str) -> Result<Vec<f64>, Fault> {
    numbers(value.get(key).ok_or(Fault::Missing { key })?, key)
}

/// `distortion_coefficients`: k1, k2, p1, p2[, k3]; higher ones only when zero.
fn opencv_distortion(value: &Json) -> Result<[f64; 5], Fault> {
    let d = opencv_matrix(value, "distortion_coefficients")?;
    if d.len() < 4 || d.len() > 14 {
        return Err(Fault::DistortionCount { len: d.len() });
    }
    if d.len() > 5 && d[5..].iter().any(|&x| x != 0.0) {
        return Err(Fault::HigherDistortion);
    }
    Ok(first_five(&d))
}

/// The first five coefficients (k1 k2 p1 p2 k3), zeros for those missing.
fn first_five(d: &[f64]) -> [f64; 5] {
    let mut dist = [0.0; 5];
    for (i, x) in d.iter().take(5).enumerate() {
        dist[i] = *x;
    }
    dist
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

/// The numbers of `v` (its `data` when it has one), flattened; `key` names it in errors.
fn numbers(v: &Json, key: &'static str) -> Result<Vec<f64>, Fault> {
    let mut out = Vec::new();
    let data = v.get("data").unwrap_or(v);
    flatten_numbers(data, &mut out).map_err(|fault| Fault::Numbers { key, fault })?;
    Ok(out)
}

/// Kalibr (camchain or single camera) and ROS `camera_info` files; `Ok(None)` for other files.
fn kalibr_or_ros(value: &Json, selector: Option<&str>) -> Result<Option<CameraIntrinsics>, Fault> {
    let Some(obj) = value.as_object() else { return Ok(None) };
    if let Some((name, cam)) = kalibr_camera_of(value, obj, selector)? {
        return kalibr_camera(name, cam).map(Some);
    }
    if let Some(model) = obj.get("distortion_model").and_then(|m| m.as_str()) {
        return ros_camera_info(value, model).map(Some);
    }
    Ok(None)
}

/// The Kalibr camera of a file: a top-level `camera_model`, or one of cam0, cam1, ... each
/// holding one (the selected one, or the only one); `Ok(None)` when the file is not Kalibr's.
fn kalibr_camera_of<'a>(
    value: &'a Json,
    obj: &'a serde_json::Map<String, Json>,
    selector: Option<&str>,
) -> Result<Option<(&'a str, &'a Json)>, Fault> {
    if obj.contains_key("camera_model") {
        return Ok(Some(("camera", value)));
    }
    let cams: Vec<(&String, &Json)> = obj.iter().filter(|(_, v)| v.get("camera_model").is_some()).collect();
    if cams.is_empty() {
        return Ok(None);
    }
    let names = || cams.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>().join(", ");
    match selector {
        Some(sel) => match cams.iter().find(|(n, _)| n.as_str() == sel) {
            Some((n, c)) => Ok(Some((n.as_str(), *c))),
            None => Err(Fault::NoSuchCamera { selector: sel.to_string(), cameras: names() }),
        },
        None if cams.len() == 1 => Ok(Some((cams[0].0.as_str(), cams[0].1))),
        None => Err(Fault::CamchainNeedsSelector { cameras: names(), first: cams[0].0.clone() }),
    }
}

/// A Kalibr camera (`pinhole` with `radtan` or no distortion).
fn kalibr_camera(name: &str, cam: &Json) -> Result<CameraIntrinsics, Fault> {
    let camera_model = cam.get("camera_model").and_then(|v| v.as_str()).unwrap_or("?");
    let dist_model = cam.get("distortion_model").and_then(|v| v.as_str()).unwrap_or("none");
    let short = match dist_model {
        "equidistant" => "equi",
        other => other,
    };
    if camera_model != "pinhole" || !(dist_model == "radtan" || dist_model == "none") {
        return Err(Fault::KalibrModel { camera: name.to_string(), model: format!("{camera_model}-{short}") });
    }
    let i = numbers(kalibr_field(name, cam, "intrinsics")?, "intrinsics")?;
    if i.len() != 4 {
        return Err(Fault::KalibrIntrinsics { camera: name.to_string(), len: i.len() });
    }
    let dist = if dist_model == "radtan" { kalibr_radtan(name, cam)? } else { [0.0; 5] };
    let (w, h) = kalibr_resolution(name, cam)?;
    Ok(CameraIntrinsics { width: w, height: h, fx: i[0], fy: i[1], cx: i[2], cy: i[3], dist })
}

/// A field a Kalibr camera must have.
fn kalibr_field<'a>(name: &str, cam: &'a Json, key: &'static str) -> Result<&'a Json, Fault> {
    cam.get(key).ok_or(Fault::KalibrMissing { camera: name.to_string(), key })
}

/// Kalibr's radtan `distortion_coeffs` [k1, k2, r1, r2] as OpenCV's five (k3 = 0).
fn kalibr_radtan(name: &str, cam: &Json) -> Result<[f64; 5], Fault> {
    let d = numbers(kalibr_field(name, cam, "distortion_coeffs")?, "distortion_coeffs")?;
    if d.len() != 4 {
        return Err(Fault::KalibrRadtan { camera: name.to_string(), len: d.len() });
    }
    Ok(first_five(&d))
}

/// Kalibr's `resolution` [width, height]; (0, 0) when absent.
fn kalibr_resolution(name: &str, cam: &Json) -> Result<(u32, u32), Fault> {
    match cam.get("resolution").map(|r| numbers(r, "resolution")).transpose()? {
        Some(r) if r.len() == 2 => Ok((r[0] as u32, r[1] as u32)),
        Some(_) => Err(Fault::KalibrResolution { camera: name.to_string() }),
        None => Ok((0, 0)),
    }
}

/// A ROS `camera_info` (`plumb_bob` or `rational_polynomial` with k4..k6 zero): the
/// calibration-file form (camera_matrix, distortion_coefficients) or the message form (K, D;
/// ROS 2: k, d).
fn ros_camera_info(v: &Json, model: &str) -> Result<CameraIntrinsics, Fault> {
    if model != "plumb_bob" && model != "rational_polynomial" {
        return Err(Fault::RosModel { model: model.to_string() });
    }
    let (kk, kv) = ros_field(v, ["camera_matrix", "K", "k"])?;
    let k = numbers(kv, kk)?;
    if k.len() != 9 {
        return Err(Fault::MatrixSize { key: kk, len: k.len() });
    }
    let dist = ros_distortion(v, model)?;
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

/// The first of `keys` that `v` has, with its value; the error names the first two.
fn ros_field<'a>(v: &'a Json, keys: [&'static str; 3]) -> Result<(&'static str, &'a Json), Fault> {
    keys.iter().find_map(|k| v.get(*k).map(|x| (*k, x))).ok_or(Fault::RosMissing { key: keys[0], alt: keys[1] })
}

/// ROS distortion: k1 k2 p1 p2 k3 (none at all is no distortion); k4..k6 only when zero.
fn ros_distortion(v: &Json, model: &str) -> Result<[f64; 5], Fault> {
    let (dk, dv) = ros_field(v, ["distortion_coefficients", "D", "d"])?;
    let d = numbers(dv, dk)?;
    if d.len() > 5 && d[5..].iter().any(|&x| x != 0.0) {
        return Err(Fault::RosHigherDistortion { key: dk, model: model.to_string() });
    }
    if d.len() < 4 && !d.is_empty() {
        return Err(Fault::RosDistortionCount { key: dk, len: d.len() });
    }
    Ok(first_five(&d))
}

/// Appends the numbers of a number or (nested) list of numbers.
fn flatten_numbers(v: &Json, out: &mut Vec<f64>) -> Result<(), NumberFault> {
    match v {
        serde_json::Value::Number(n) => out.push(n.as_f64().ok_or(NumberFault::NotANumber)?),
        serde_json::Value::Array(a) => {
            for x in a {
                flatten_numbers(x, out)?;
            }
        }
        _ => return Err(NumberFault::ExpectedNumbers),
    }
    Ok(())
}

/// OpenCV FileStorage YAML → JSON value. OpenCV writes `%YAML:1.0` (not valid YAML 1.x
/// directive syntax) and custom `!!opencv-matrix` tags; both are handled here.
fn yaml_to_json(text: &str) -> Result<Json, Fault> {
    let cleaned: String = text
        .lines()
        .filter(|l| !l.trim_start().starts_with("%YAML"))
        .map(|l| l.replace("!!opencv-matrix", "").replace("!!opencv-nd-matrix", ""))
        .collect::<Vec<_>>()
        .join("\n");
    let docs = yaml_rust2::YamlLoader::load_from_str(&cleaned).map_err(Fault::Yaml)?;
    let doc = docs.into_iter().next().ok_or(Fault::EmptyYaml)?;
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Every coefficient is read with its own sign and place (k1, k2, p1, p2, k3), from
    /// OpenCV's YAML (`!!opencv-matrix`) and from JSON with plain lists: a sign lost where a
    /// file is read would bend every measurement (the injected regression
    /// `scripts/regressions/calibration-k1-sign.patch`).
    #[test]
    fn distortion_coefficients_are_read_with_their_signs() {
        let dist = [-0.21, 0.05, 0.001, -0.002, 0.01];
        let yaml = "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 500., 0., 320., 0., 501., 240., 0., 0., 1. ]\ndistortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ -0.21, 0.05, 0.001, -0.002, 0.01 ]\n";
        let json = r#"{"image_width": 640, "image_height": 480, "camera_matrix": [500, 0, 320, 0, 501, 240, 0, 0, 1],
                       "distortion_coefficients": [-0.21, 0.05, 0.001, -0.002, 0.01]}"#;
        for (text, is_json) in [(yaml, false), (json, true)] {
            let k = parse_calibration(text, is_json, Path::new("cam.yaml")).unwrap();
            assert_eq!(k.dist, dist, "json {is_json}");
            assert_eq!((k.fx, k.fy, k.cx, k.cy, k.width, k.height), (500.0, 501.0, 320.0, 240.0, 640, 480));
        }
    }
}
