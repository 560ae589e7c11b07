//! Host-visible staging ring for uploads: the loader writes mip bytes here,
//! copy commands read them, and space returns once the submission that read
//! it has completed.

use std::collections::VecDeque;
use std::sync::Arc;

use ash::vk;
use gpu_allocator::MemoryLocation;

use crate::buffer::{Buffer, BufferDesc};
use crate::device::Device;
use crate::error::Result;

/// A byte range handed out by the ring.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RingRange {
    /// Offset in the ring buffer.
    pub offset: u64,
    /// Size in bytes.
    pub size: u64,
}

/// The ring's bookkeeping, separate from Vulkan so it can be tested alone.
///
/// Allocations are tagged with a ticket (a submission number that only
/// grows); `retire(t)` frees every allocation whose ticket is `<= t`.
#[derive(Debug)]
pub struct RingAllocator {
    capacity: u64,
    head: u64,
    used: u64,
    /// (start, consumed bytes including wrap padding, ticket), oldest first.
    live: VecDeque<(u64, u64, u64)>,
}

impl RingAllocator {
    /// A ring of `capacity` bytes.
    pub fn new(capacity: u64) -> Self {
        Self {
            capacity,
            head: 0,
            used: 0,
            live: VecDeque::new(),
        }
    }

    /// Bytes currently handed out (including wrap padding).
    pub fn used(&self) -> u64 {
        self.used
    }

    /// Capacity in bytes.
    pub fn capacity(&self) -> u64 {
        self.capacity
    }

    /// Hands out `size` bytes aligned to `align` (a power of two), or `None`
    /// when the ring has no room until older tickets retire.
    pub fn alloc(&mut self, size: u64, align: u64, ticket: u64) -> Option<RingRange> {
        let align = align.max(1);
        if size == 0 || size > self.capacity || !align.is_power_of_two() {
            return None;
        }
        let tail = self.live.front().map_or(self.head, |&(start, _, _)| start);
        if self.used > 0 && self.head == tail {
            return None; // full
        }
        let aligned = self.head.checked_add(align - 1)? & !(align - 1);
        // Free space is [head, capacity) + [0, tail) when head >= tail, else [head, tail).
        let limit = if self.head >= tail { self.capacity } else { tail };
        if aligned.checked_add(size)? <= limit {
            self.live.push_back((self.head, aligned + size - self.head, ticket));
            self.used += aligned + size - self.head;
            self.head = aligned + size;
            return Some(RingRange { offset: aligned, size });
        }
        if self.head >= tail && size <= tail {
            // Wrap: the rest of the buffer is padding, the range starts at zero.
            let consumed = self.capacity - self.head + size;
            self.live.push_back((self.head, consumed, ticket));
            self.used += consumed;
            self.head = size;
            return Some(RingRange { offset: 0, size });
        }
        None
    }

    /// Frees every allocation whose ticket is `<= completed`.
    pub fn retire(&mut self, completed: u64) {
        while let Some(&(_, consumed, ticket)) = self.live.front() {
            if ticket > completed {
                break;
            }
            self.live.pop_front();
            self.used -= consumed;
        }
        if self.live.is_empty() {
            self.head = 0;
            self.used = 0;
        }
    }
}

/// A host-visible upload buffer managed as a ring.
#[derive(Debug)]
pub struct StagingRing {
    buffer: Buffer,
    ring: RingAllocator,
}

impl StagingRing {
    /// Creates a ring of `capacity` bytes.
    pub fn new(device: &Arc<Device>, capacity: u64) -> Result<Self> {
        let buffer = Buffer::new(
            device,
            BufferDesc {
                size: capacity,
                usage: vk::BufferUsageFlags::TRANSFER_SRC,
                location: MemoryLocation::CpuToGpu,
            },
            "staging ring",
        )?;
        Ok(Self {
            buffer,
            ring: RingAllocator::new(capacity),
        })
    }

    /// Bytes the ring holds.
    pub fn capacity(&self) -> u64 {
        self.ring.capacity()
    }

    /// Copies `bytes` into the ring for the submission `ticket`; `None` when full.
    pub fn push(&mut self, bytes: &[u8], align: u64, ticket: u64) -> Result<Option<RingRange>> {
        let Some(range) = self.ring.alloc(bytes.len() as u64, align, ticket) else {
            return Ok(None);
        };
        self.buffer.write(range.offset, bytes)?;
        Ok(Some(range))
    }

    /// Frees the space of submissions up to `completed`.
    pub fn retire(&mut self, completed: u64) {
        self.ring.retire(completed);
    }

    /// The buffer copies read from.
    pub fn buffer(&self) -> vk::Buffer {
        self.buffer.raw()
    }

    /// Bytes in use.
    pub fn used(&self) -> u64 {
        self.ring.used()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn allocations_never_overlap_and_space_returns() {
        let mut ring = RingAllocator::new(1024);
        let a = ring.alloc(300, 16, 1).expect("room");
        let b = ring.alloc(300, 16, 1).expect("room");
        let c = ring.alloc(300, 16, 2).expect("room");
        assert_eq!(a.offset, 0);
        assert_eq!(b.offset, 304, "300 rounded up to the 16-byte alignment");
        assert_eq!(c.offset, 608);
        let ranges = [a, b, c];
        for (i, x) in ranges.iter().enumerate() {
            assert_eq!(x.offset % 16, 0);
            assert!(x.offset + x.size <= 1024);
            for y in &ranges[i + 1..] {
                assert!(
                    x.offset + x.size <= y.offset || y.offset + y.size <= x.offset,
                    "{x:?} overlaps {y:?}"
                );
            }
        }
        assert!(ring.alloc(300, 16, 3).is_none(), "ring is full until ticket 1 retires");
        ring.retire(1);
        let d = ring.alloc(300, 16, 3).expect("space of ticket 1 came back");
        assert_eq!(d.offset, 0, "wraps to the start");
        assert!(
            ring.alloc(400, 16, 4).is_none(),
            "only 308 bytes before ticket 2's range"
        );
        ring.retire(3);
        assert_eq!(ring.used(), 0);
    }

    #[test]
    fn oversize_and_zero_requests_are_refused() {
        let mut ring = RingAllocator::new(64);
        assert!(ring.alloc(65, 1, 0).is_none());
        assert!(ring.alloc(0, 1, 0).is_none());
        assert!(ring.alloc(8, 3, 0).is_none(), "alignment must be a power of two");
    }
}
