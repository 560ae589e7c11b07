//! Pool of sparse-block memory slots over device-memory chunks.
//!
//! Vulkan-free: a slot is a chunk index and a byte offset. The engine backs
//! each chunk it is told about ([`ChunkInfo`]) with one device allocation
//! and never frees it while the cache lives; slots freed by eviction are
//! handed out again instead of returning memory to the driver.

use crate::binder::MemorySlot;

/// A chunk the pool created; the engine must allocate `bytes` of device
/// memory for it before submitting any bind that refers to it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ChunkInfo {
    /// Chunk index ([`MemorySlot::chunk`]).
    pub chunk: u32,
    /// Size of the chunk in bytes (whole sparse blocks).
    pub bytes: u64,
}

/// Fixed-size block slots carved from chunks, created on demand up to a
/// slot limit and reused after [`BlockPool::free`].
///
/// Threading: not synchronised; the cache owns it behind its shared lock.
#[derive(Debug)]
pub struct BlockPool {
    block_bytes: u64,
    blocks_per_chunk: u32,
    max_slots: u64,
    created_slots: u64,
    chunks: u32,
    free: Vec<MemorySlot>,
}

impl BlockPool {
    /// A pool of at most `max_slots` slots of `block_bytes` each, created
    /// `blocks_per_chunk` at a time (the last chunk may be smaller).
    pub fn new(block_bytes: u64, blocks_per_chunk: u32, max_slots: u64) -> Self {
        BlockPool {
            block_bytes,
            blocks_per_chunk: blocks_per_chunk.max(1),
            max_slots,
            created_slots: 0,
            chunks: 0,
            free: Vec::new(),
        }
    }

    /// Slots that can be handed out now: free ones plus those not yet
    /// created.
    pub fn available(&self) -> u64 {
        self.free.len() as u64 + (self.max_slots - self.created_slots)
    }

    /// Slots handed out and not freed.
    pub fn in_use(&self) -> u64 {
        self.created_slots - self.free.len() as u64
    }

    /// Chunks created so far.
    pub fn chunk_count(&self) -> u32 {
        self.chunks
    }

    /// Hands out a slot, creating a chunk if no freed slot is left (its
    /// description is pushed to `new_chunks`). `None` when the limit is
    /// reached.
    pub fn allocate(&mut self, new_chunks: &mut Vec<ChunkInfo>) -> Option<MemorySlot> {
        if let Some(slot) = self.free.pop() {
            return Some(slot);
        }
        let remaining = self.max_slots - self.created_slots;
        if remaining == 0 {
            return None;
        }
        let slots = remaining.min(u64::from(self.blocks_per_chunk));
        let chunk = self.chunks;
        self.chunks = self.chunks.checked_add(1)?;
        self.created_slots += slots;
        new_chunks.push(ChunkInfo {
            chunk,
            bytes: slots * self.block_bytes,
        });
        // Highest offsets first on the free list so the chunk fills from 0.
        self.free.extend((1..slots).rev().map(|index| MemorySlot {
            chunk,
            offset: index * self.block_bytes,
        }));
        Some(MemorySlot { chunk, offset: 0 })
    }

    /// Returns a slot for reuse.
    pub fn free(&mut self, slot: MemorySlot) {
        self.free.push(slot);
    }
}
