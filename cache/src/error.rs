//! Typed errors of the cache.

/// A cache configuration the device or the budgets cannot hold.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ConfigError {
    /// A texel format description is unusable.
    #[error("texel format {format}: {reason}")]
    BadFormat {
        /// Format name.
        format: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// A sparse granularity is unusable for its format.
    #[error("sparse granularity for {format}: {reason}")]
    BadGranularity {
        /// Format name.
        format: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// The configuration lists no image.
    #[error("cache configuration lists no sparse image")]
    NoImages,
    /// A layer size is not a power of two, too small for the format or
    /// larger than the device or the cache supports.
    #[error("image {image} ({format}): layer size {layer_size}: {reason}")]
    BadLayerSize {
        /// Image index in the configuration.
        image: usize,
        /// Format name.
        format: &'static str,
        /// The configured layer size in texels.
        layer_size: u32,
        /// What is wrong.
        reason: String,
    },
    /// A layer count is zero or beyond `maxImageArrayLayers`.
    #[error("image {image} ({format}): layer count {layer_count} outside 1..={max_layers}")]
    BadLayerCount {
        /// Image index in the configuration.
        image: usize,
        /// Format name.
        format: &'static str,
        /// The configured count.
        layer_count: u32,
        /// The device's `maxImageArrayLayers`.
        max_layers: u32,
    },
    /// The sparse block size is zero.
    #[error("sparse block size must be non-zero")]
    ZeroBlockSize,
    /// The memory budget cannot hold a single block.
    #[error("memory budget {budget_bytes} B is smaller than one sparse block of {block_bytes} B")]
    MemoryBudgetTooSmall {
        /// Configured budget.
        budget_bytes: u64,
        /// Sparse block size.
        block_bytes: u64,
    },
    /// Pool chunks must hold at least one block.
    #[error("pool chunks must hold at least one block")]
    ZeroChunk,
    /// An image whose mip tail the cache cannot serve.
    #[error("image {image} ({format}) cannot be served sparse: {reason}")]
    UnservedMipTail {
        /// Image index in the configuration.
        image: usize,
        /// Format name.
        format: &'static str,
        /// Why.
        reason: String,
    },
    /// The single mip tails, bound for the cache's whole life, leave no
    /// budget for anything else.
    #[error(
        "the images' single mip tails take {tail_bytes} B, which leaves nothing of the memory budget of \
         {budget_bytes} B: raise the budget"
    )]
    TailsOverBudget {
        /// Bytes of all single tails.
        tail_bytes: u64,
        /// The configured budget.
        budget_bytes: u64,
    },
    /// The images' sparse address space exceeds the virtual address budget.
    #[error(
        "sparse images need {needed_bytes} B of virtual address space (image {largest_image} alone {largest_bytes} B), \
         over the budget of {budget_bytes} B: lower the layer size or count"
    )]
    VirtualBudgetExceeded {
        /// Sum over images of layers × block-padded full mip chain.
        needed_bytes: u64,
        /// The configured budget.
        budget_bytes: u64,
        /// Image needing the most address space.
        largest_image: usize,
        /// Its need in bytes.
        largest_bytes: u64,
    },
}

/// An error from a cache operation.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CacheError {
    /// No image has this index.
    #[error("no cached sparse image with index {image} (the cache has {images})")]
    UnknownImage {
        /// Requested index.
        image: u32,
        /// Number of images.
        images: usize,
    },
    /// A texture extent the image cannot hold.
    #[error("texture {width}x{height} in image {image} ({format}): {reason}")]
    BadExtent {
        /// Image index.
        image: u32,
        /// Format name.
        format: &'static str,
        /// Texture width in texels.
        width: u32,
        /// Texture height in texels.
        height: u32,
        /// What is wrong.
        reason: String,
    },
    /// A mip level the texture does not have in the cache.
    #[error("texture {width}x{height} ({format}) has cacheable mips 0..{mip_count}; mip {mip} requested")]
    BadMip {
        /// Format name.
        format: &'static str,
        /// Texture width.
        width: u32,
        /// Texture height.
        height: u32,
        /// Requested mip.
        mip: u32,
        /// Number of cacheable mips.
        mip_count: u32,
    },
    /// The placement's layer was evicted: the texture is invalidated and
    /// must be inserted again.
    #[error("texture {key} was invalidated (image {image}, layer {layer} evicted)")]
    Invalidated {
        /// The caller's texture key.
        key: u64,
        /// Image index.
        image: u32,
        /// Layer index.
        layer: u32,
    },
    /// The memory budget cannot hold the blocks this mip needs even after
    /// evicting every other layer.
    #[error("mip needs {needed_blocks} new sparse blocks but the memory budget holds {budget_blocks}")]
    OverBudget {
        /// Blocks the request needs newly bound.
        needed_blocks: u64,
        /// Blocks the budget holds.
        budget_blocks: u64,
    },
    /// Without evicting, the memory budget has too few free blocks for this
    /// mip ([`crate::TextureCache::try_stage_mip`]); the caller frees room
    /// by dropping levels it values less, or declines the mip.
    #[error("mip needs {needed_blocks} new sparse blocks but only {free_blocks} of the budget are free")]
    NoRoom {
        /// Blocks the request needs newly bound.
        needed_blocks: u64,
        /// Blocks of the budget not bound now.
        free_blocks: u64,
    },
    /// [`crate::TextureCache::try_insert`]: the texture needs a new layer
    /// and every layer of the image is live.
    #[error("image {image} has no free layer for a texture of extent {extent}")]
    NoLayer {
        /// Image index.
        image: u32,
        /// The texture's extent.
        extent: u32,
    },
    /// [`crate::TextureCache::evict_layer`] named a layer that holds no
    /// assignment.
    #[error("layer {layer} of image {image} is not live")]
    LayerNotLive {
        /// Image index.
        image: u32,
        /// Layer index.
        layer: u32,
    },
    /// A level was to be dropped that the texture does not hold.
    #[error("texture {key} holds no staged mip {mip} to drop")]
    NotStaged {
        /// The caller's texture key.
        key: u64,
        /// The level asked for.
        mip: u32,
    },
    /// Enough blocks are within budget but their memory still backs blocks
    /// waiting to be unbound by the next batch; retry after
    /// [`crate::TextureCache::take_batch`].
    #[error("{needed_blocks} blocks needed, {free_blocks} free now; the rest waits for the next unbind batch")]
    MemoryPending {
        /// Blocks the request needs newly bound.
        needed_blocks: u64,
        /// Memory slots free right now.
        free_blocks: u64,
    },
}
