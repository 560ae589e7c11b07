//! The seam between the cache's block accounting and whoever binds memory.
//!
//! The cache decides *which* blocks must be bound or unbound in a streaming
//! cycle and hands them over as one batch; an implementation (the Vulkan
//! binder in `engine/`, an in-memory fake in tests, or the bind-latency model
//! in `streaming/` wrapping either) carries the batch out.

/// One sparse block of one cached sparse image, in block-grid coordinates of
/// a mip level of an array layer; or, with `mip` = [`BlockKey::TAIL_LEVEL`],
/// block `x` of a layer's mip tail (`y` 0; layer 0 for a single tail), which
/// a binder binds opaquely at the tail's offset.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BlockKey {
    /// Which cached sparse image (one per texture format in use).
    pub image: u32,
    /// Array layer.
    pub layer: u32,
    /// Mip level of the sparse image.
    pub mip: u32,
    /// Block column within the level (in units of the sparse granularity).
    pub x: u32,
    /// Block row within the level (in units of the sparse granularity).
    pub y: u32,
}

impl BlockKey {
    /// The `mip` of a key that stands for a block of a mip tail.
    pub const TAIL_LEVEL: u32 = u32::MAX;

    /// Block `index` of the mip tail of `layer` of `image`.
    pub fn tail(image: u32, layer: u32, index: u32) -> Self {
        BlockKey {
            image,
            layer,
            mip: Self::TAIL_LEVEL,
            x: index,
            y: 0,
        }
    }

    /// Whether this key is a block of a mip tail.
    pub fn is_tail(&self) -> bool {
        self.mip == Self::TAIL_LEVEL
    }
}

/// Where a block's backing memory lives: a chunk of the block pool and a
/// byte offset inside it (a multiple of the block size).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct MemorySlot {
    /// Index of the device-memory chunk in the pool.
    pub chunk: u32,
    /// Byte offset inside the chunk.
    pub offset: u64,
}

/// One operation of a bind batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BindOp {
    /// Back `block` with the memory at `memory`.
    Bind { block: BlockKey, memory: MemorySlot },
    /// Make `block` non-resident again.
    Unbind { block: BlockKey },
}

impl BindOp {
    /// The block this operation touches.
    pub fn block(&self) -> BlockKey {
        match *self {
            BindOp::Bind { block, .. } | BindOp::Unbind { block } => block,
        }
    }
}

/// What a binder reports after carrying out a batch.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BindReport {
    /// Blocks bound or unbound.
    pub blocks: u32,
    /// Bind entries actually submitted after merging adjacent blocks.
    pub entries: u32,
    /// Time the binding took, in seconds, as measured (real binder) or
    /// modelled (latency model). Zero where nothing was measured.
    pub seconds: f64,
}

/// Error from a binder.
#[derive(Debug, thiserror::Error)]
pub enum BindError {
    /// The backing API rejected the batch.
    #[error("sparse bind of {blocks} blocks failed: {reason}")]
    Rejected { blocks: u32, reason: String },
    /// A block refers to an image, layer or level the binder does not know.
    #[error("block {block:?} lies outside every image the binder knows")]
    UnknownBlock { block: BlockKey },
}

/// Carries out one batch of sparse bind/unbind operations per streaming cycle.
///
/// Threading: called from one thread at a time (the streaming task owns the
/// binder while it runs); implementations need `Send` so the task can run on
/// a worker thread.
pub trait SparseBinder: Send {
    /// Bind and unbind the given blocks as one submission. An empty batch is
    /// allowed and must cost nothing.
    fn submit(&mut self, batch: &[BindOp]) -> Result<BindReport, BindError>;
}
