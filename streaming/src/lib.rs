//! Streaming policy (paper §3.4–3.5). Vulkan-free.
#![forbid(unsafe_code)]
