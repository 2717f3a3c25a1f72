//! The pixel renderer of synthetic camera images, shared by the simulated rig
//! (`tagdeflect_sim`, which traces its scene through it) and the calibration's test images
//! (`tagdeflect_calibrate::render`, targets with ground truth): each camera's exact
//! undistorted rays through every pixel corner ([`CornerRays`], on the simulator's own lens
//! model, [`lens`]), area integration of mixed pixels ([`render_rect`]), the optics before
//! the pixels ([`Optics`]: a Gaussian, a defocus disk, an astigmatic blur, the pixel's fill
//! factor), motion blur, the camera's processing after the pixels ([`formation`]: a discrete
//! Gaussian, a 3×3 sharpening kernel, a colour sensor's demosaic, JPEG), sensor noise and the
//! sensor's bit depth, kept at full depth beside an 8-bit plane when deeper ([`quantize_bits`]).
//!
//! Its own crate so that the calibration does not stand on the simulator: both stand on it.

pub mod formation;
pub mod lens;
mod optics;
mod pixels;

pub use optics::{Astigmatism, Optics, OpticsSpec};
pub use pixels::{blur, gaussian_kernel, motion_blur, quantize, quantize_bits, render_rect, CornerRays, Flat, Hit, Keep, PixelRect};
