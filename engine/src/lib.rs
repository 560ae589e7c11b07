//! citystream's Vulkan engine: the device half of what `citystream-streaming`
//! decides, and the passes that render a streamed city.
//!
//! The embeddable module: [`stream`], whose [`stream::TextureStreamer`] runs
//! the paper's Algorithm 1 inside a host's frame loop with frames in flight
//! (see `docs/EMBEDDING.md`), over [`texture_cache`] (the GPU half of the
//! cache: sparse images per format, the per-texture table, the City
//! Colormap), [`binder`] (`vkQueueBindSparse` batches, checked against a CPU
//! shadow of the page tables where asked) and [`feedback`] (the per-mesh
//! feedback array, its compaction and read-back).
//!
//! The engine's own passes: [`city`] (depth pre-pass, feedback and visible
//! pass of a streamed city), [`cull`] (GPU culling of those passes: frustum and
//! depth-pyramid tests in two phases, draws compacted in mesh order), [`atlas_tree`] (the texture-atlas tree's visible
//! pass), [`ground`] (the flexible clipmap's tile array and ground pass),
//! [`scene`] and [`placeholder`] (fully resident meshes and the procedural
//! city), [`probe`] (what the GPU reads from a sparse image, for tests).
//!
//! One module per Vulkan concept under them: [`instance`] (loader, layers,
//! debug messenger), [`device`] (physical-device choice, logical device,
//! queue, allocator; or a host's own through [`Device::from_host`]),
//! [`buffer`] and [`image`] (resources that own their memory), [`sparse`]
//! (partially resident images and `vkQueueBindSparse`), [`commands`]
//! (submissions and semaphores), [`pipeline`] (pipelines and descriptors),
//! [`shaders`] (the SPIR-V compiled from `shaders/` and the GLSL include
//! directory), [`gpu_types`] (Rust mirrors of the GLSL structs), [`target`]
//! (off-screen colour + depth and read-back), `present` (feature `window`:
//! surface, swapchain and screenshots of presented frames), [`staging`]
//! (host-visible upload ring), [`timing`] (CPU and GPU frame timing).
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

/// `Debug` for the engine's owners of Vulkan objects: the type's name and the fields that
/// say what it is, the rest (handles' memory, tables, buffers) left out. A field may show
/// a value derived from the owner: `images = |s| s.images.len()`.
macro_rules! debug_fields {
    ($ty:ident { $($name:ident $(= |$s:ident| $value:expr)?),* $(,)? }) => {
        impl std::fmt::Debug for $ty {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.debug_struct(stringify!($ty))
                    $(.field(stringify!($name), &debug_fields!(@value self, $name $(, |$s| $value)?)))*
                    .finish_non_exhaustive()
            }
        }
    };
    (@value $owner:ident, $name:ident) => { $owner.$name };
    (@value $owner:ident, $name:ident, |$s:ident| $value:expr) => {{
        let $s = $owner;
        $value
    }};
}

pub mod atlas_tree;
pub mod binder;
pub mod buffer;
pub mod city;
pub mod commands;
pub mod cull;
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

pub use device::{Device, DeviceOptions, HostAllocator, HostDevice, SparseMode, TextureBacking};
pub use instance::{ValidationLog, ValidationMessage};
