//! Sparse-image texture cache (paper §3.6). Vulkan-free.
#![forbid(unsafe_code)]

pub mod binder;

pub use binder::{BindError, BindOp, BindReport, BlockKey, MemorySlot, SparseBinder};
