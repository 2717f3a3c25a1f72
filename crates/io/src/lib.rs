//! What comes in: camera sources (V4L2, Aravis, a recording played at its pace), frame-set
//! assembly ([`sync`]), the testing machine over Modbus TCP ([`utm`]), and recordings on disk
//! ([`recording`]) — written by the recorder, read by replay. [`modbus_server`] is the one
//! read-side Modbus TCP server the workspace's servers (the control output, the simulated UTM
//! and machine) are built on.
//!
//! Each owns its config section: `[sync]` ([`sync::SyncConfig`]) and `[utm]`
//! ([`utm::UtmConfig`]); cameras are described by `tagdeflect_core::camera_config`.

pub mod modbus_server;
pub mod recording;
pub mod sources;
pub mod sync;
pub mod utm;
