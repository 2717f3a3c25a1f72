//! `tagdeflect cameras`: the cameras this machine sees, with what to write in a config.

use anyhow::Result;
use tagdeflect_io::sources::list;

/// Prints every V4L2 capture device (by its `/dev/v4l/by-id` path when it has one) with its
/// formats, sizes and frame rates, then every Aravis device by id.
#[cfg_attr(not(feature = "aravis"), allow(unused_variables))]
pub fn list(with_fake: bool) -> Result<()> {
    let v4l2 = list::v4l2_devices();
    println!("V4L2 capture devices: {}", v4l2.len());
    for d in &v4l2 {
        let source = d.by_id.first().unwrap_or(&d.node);
        println!("  {} ({})", d.card, d.node.display());
        println!("    source = \"v4l2:{}\"", source.display());
        if d.by_id.is_empty() {
            println!("    (no /dev/v4l/by-id link: the /dev/videoN number may change when the camera is replugged)");
        }
        for f in &d.formats {
            println!("    {} {}", f.fourcc, f.description);
            for (size, rates) in &f.sizes {
                if rates.is_empty() {
                    println!("      {size}");
                } else {
                    println!("      {size}: {}", rates.join(", "));
                }
            }
        }
    }
    #[cfg(feature = "aravis")]
    {
        let aravis = list::aravis_devices(with_fake);
        println!("GigE Vision / USB3 Vision devices (Aravis): {}", aravis.len());
        for d in &aravis {
            println!("  {} {} serial {} at {} ({})", d.vendor, d.model, d.serial, d.address, d.protocol);
            println!("    source = \"aravis:{}\"", d.id);
        }
    }
    #[cfg(not(feature = "aravis"))]
    println!("GigE Vision / USB3 Vision devices: not listed (this build has no `aravis` feature)");
    Ok(())
}
