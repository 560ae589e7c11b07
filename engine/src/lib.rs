//! citystream's Vulkan engine.
//!
//! [`stream`] is the embeddable streaming module: [`stream::TextureStreamer`]
//! runs the paper's Algorithm 1 inside a host's frame loop with frames in
//! flight (see `docs/EMBEDDING.md`). Around it, one module per Vulkan
//! concept: [`instance`] (loader, layers, debug messenger), [`device`]
//! (physical-device choice, logical device, queue, allocator; or a host's
//! own through [`Device::from_host`]), [`buffer`] and [`image`] (resources
//! that own their memory), [`sparse`] (partially resident images and
//! `vkQueueBindSparse`), [`commands`] (submissions), [`pipeline`] (shaders,
//! pipelines, descriptors), [`target`] (off-screen colour + depth and
//! read-back), `present` (feature `window`: surface, swapchain and
//! screenshots of presented frames), [`staging`] (host-visible upload ring), [`timing`] (CPU and
//! GPU frame timing), [`texture_cache`] and [`feedback`] (the GPU halves of
//! the cache and of the feedback), [`city`] (the engine's own city passes),
//! [`atlas_tree`] (the visible pass of the texture-atlas tree strategy).
//!
//! Ownership contract: every Vulkan handle has exactly one owner, a Rust value
//! whose `Drop` destroys it. Resources hold an `Arc<Device>`, so the device
//! outlives them. Dropping a resource the GPU may still use is the owner's
//! bug: owners drop only after the last submission that used it completed
//! (the streamer releases staging space and buffers by frame timeline value).
//!
//! All `unsafe` code of citystream lives in this crate, each block with a
//! `// SAFETY:` line.
#![warn(unsafe_op_in_unsafe_fn)]

pub mod atlas_tree;
pub mod binder;
pub mod buffer;
pub mod city;
pub mod commands;
pub mod device;
pub mod error;
pub mod feedback;
pub mod gpu_types;
pub mod ground;
pub mod image;
pub mod instance;
mod memory;
pub mod pipeline;
pub mod placeholder;
#[cfg(feature = "window")]
pub mod present;
pub mod probe;
pub mod scene;
pub mod shaders;
pub mod sparse;
pub mod staging;
pub mod stream;
pub mod target;
pub mod texture_cache;
pub mod timing;

pub use ash;
pub use ash::vk;
pub use error::{EngineError, Result};
pub use gpu_allocator;

pub use device::{Device, DeviceOptions, HostAllocator, HostDevice};
pub use instance::{ValidationLog, ValidationMessage};
