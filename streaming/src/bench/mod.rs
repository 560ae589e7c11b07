//! Benchmark infrastructure, kept apart from the policy's core API: camera
//! paths (the standard benchmark path), the streaming simulator on a
//! modelled clock, and run statistics for reports. Hosts that embed the
//! streaming need none of it.

pub mod path;
pub mod sim;
pub mod stats;
