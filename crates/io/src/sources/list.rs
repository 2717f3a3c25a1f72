//! The cameras this machine can see (`tagdeflect cameras`): V4L2 devices by their stable
//! `/dev/v4l/by-id` paths (the path a config should use: `/dev/videoN` numbers change when a
//! camera is replugged) with their formats, sizes and frame rates, and Aravis devices by id.

use std::path::{Path, PathBuf};

/// One V4L2 capture device.
#[derive(Debug, Clone, PartialEq)]
pub struct V4l2Device {
    /// `/dev/videoN`.
    pub node: PathBuf,
    /// Its `/dev/v4l/by-id/...` links (what a config's `source = "v4l2:..."` should name).
    pub by_id: Vec<PathBuf>,
    /// The driver's name of the card.
    pub card: String,
    /// Pixel formats: FourCC, description, and the sizes with their frame rates.
    pub formats: Vec<V4l2Format>,
}

/// A pixel format of a V4L2 device.
#[derive(Debug, Clone, PartialEq)]
pub struct V4l2Format {
    /// FourCC, e.g. `GREY`, `YUYV`.
    pub fourcc: String,
    /// The driver's description.
    pub description: String,
    /// `WIDTHxHEIGHT` (or a stepwise range) with the frame intervals the device offers.
    pub sizes: Vec<(String, Vec<String>)>,
}

/// Every V4L2 capture device under `/dev` (nodes that are no capture device — metadata nodes
/// of UVC cameras — are left out).
pub fn v4l2_devices() -> Vec<V4l2Device> {
    v4l2_devices_in(Path::new("/dev"))
}

fn v4l2_devices_in(dev: &Path) -> Vec<V4l2Device> {
    use v4l::video::Capture;
    let by_id_dir = dev.join("v4l/by-id");
    let links: Vec<(PathBuf, PathBuf)> = std::fs::read_dir(&by_id_dir)
        .map(|d| d.filter_map(|e| e.ok()).filter_map(|e| std::fs::canonicalize(e.path()).ok().map(|t| (e.path(), t))).collect())
        .unwrap_or_default();
    let mut nodes: Vec<PathBuf> = std::fs::read_dir(dev)
        .map(|d| {
            d.filter_map(|e| e.ok())
                .map(|e| e.path())
                .filter(|p| {
                    p.file_name()
                        .and_then(|n| n.to_str())
                        .is_some_and(|n| n.starts_with("video") && n[5..].chars().all(|c| c.is_ascii_digit()))
                })
                .collect()
        })
        .unwrap_or_default();
    nodes.sort();
    let mut out = Vec::new();
    for node in nodes {
        let Ok(device) = v4l::Device::with_path(&node) else { continue };
        let Ok(caps) = device.query_caps() else { continue };
        if !caps.capabilities.contains(v4l::capability::Flags::VIDEO_CAPTURE) {
            continue;
        }
        let formats = device
            .enum_formats()
            .unwrap_or_default()
            .into_iter()
            .map(|f| {
                let sizes = device
                    .enum_framesizes(f.fourcc)
                    .unwrap_or_default()
                    .into_iter()
                    .flat_map(|s| s.size.to_discrete())
                    .map(|d| {
                        let rates = device
                            .enum_frameintervals(f.fourcc, d.width, d.height)
                            .unwrap_or_default()
                            .into_iter()
                            .map(|i| i.interval.to_string())
                            .collect();
                        (format!("{}x{}", d.width, d.height), rates)
                    })
                    .collect();
                V4l2Format { fourcc: f.fourcc.str().unwrap_or("????").to_string(), description: f.description, sizes }
            })
            .collect();
        let canonical = std::fs::canonicalize(&node).unwrap_or_else(|_| node.clone());
        let by_id = links.iter().filter(|(_, t)| *t == canonical).map(|(l, _)| l.clone()).collect();
        out.push(V4l2Device { node, by_id, card: caps.card, formats });
    }
    out
}

/// One Aravis (GigE Vision / USB3 Vision) device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AravisDevice {
    /// The id a config names (`source = "aravis:<id>"`).
    pub id: String,
    /// Vendor, model, serial and address as Aravis reports them (empty when unknown).
    pub vendor: String,
    /// Model.
    pub model: String,
    /// Serial number.
    pub serial: String,
    /// Network or USB address.
    pub address: String,
    /// Interface (`GigEVision`, `USB3Vision`, `Fake`).
    pub protocol: String,
}

/// Every Aravis device found by discovery (`with_fake`: Aravis's in-process fake camera too —
/// for a demonstration and the tests).
#[cfg(feature = "aravis")]
pub fn aravis_devices(with_fake: bool) -> Vec<AravisDevice> {
    if with_fake {
        super::aravis::enable_fake_interface();
    }
    super::aravis::list_devices()
}
