//! Streaming policy (paper §3.4–3.5). Vulkan-free.
#![forbid(unsafe_code)]

pub mod atlas_tree;
#[cfg(feature = "bench")]
pub mod bench;
pub mod bind_latency;
pub mod clipmap;
pub mod controller;
pub mod dataset;
pub mod ground;
pub mod loader;
pub mod records;
#[cfg(feature = "remote")]
pub mod remote;
pub mod residency;
pub mod rng;
pub mod source;
pub mod states;
