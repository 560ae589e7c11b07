//! One streaming cycle of the GPU cache: binds and staging before the
//! caller records its frame, copies and the table update inside it. Its
//! state is [`StagingCycle`]: the mips staged ([`PendingUploads`], pure),
//! the host-visible staging they go through ([`Staging`]) and the cycle
//! prepared; [`UploadStats`] counts what was uploaded and dropped.

use std::collections::VecDeque;
use std::ops::Range;
use std::sync::Arc;

use ash::vk;
use citystream_cache::Placement;
use citystream_streaming::bind_latency::BatchShape;

use super::table::same_place;
use super::{CycleReport, GpuTextureCache};
use crate::buffer::Buffer;
use crate::commands::{CommandContext, Recording, SemaphoreWait};
use crate::device::Device;
use crate::error::{EngineError, Result};
use crate::sparse::TexelUpload;
use crate::staging::StagingRing;

/// A mip staged for the next cycle: where it goes and where its bytes are.
#[derive(Clone, Debug)]
pub(super) struct PendingUpload {
    texture: u32,
    placement: Placement,
    upload: TexelUpload,
    image: u32,
    /// Its bytes in [`PendingUploads::bytes`].
    bytes: Range<usize>,
}

/// The mips staged in this cycle, and their bytes one after another.
#[derive(Clone, Debug, Default)]
pub(super) struct PendingUploads {
    uploads: Vec<PendingUpload>,
    bytes: Vec<u8>,
}

impl PendingUploads {
    /// Queues `upload` of `texture` at `placement` with its `bytes`.
    pub(super) fn push(&mut self, texture: u32, placement: Placement, upload: TexelUpload, bytes: &[u8]) {
        let start = self.bytes.len();
        self.bytes.extend_from_slice(bytes);
        self.uploads.push(PendingUpload {
            texture,
            placement,
            image: placement.image,
            upload,
            bytes: start..start + bytes.len(),
        });
    }

    /// Forgets the mips staged for a place in `evicted`: they must not be copied.
    pub(super) fn drop_evicted(&mut self, evicted: &[Placement]) {
        self.uploads
            .retain(|u| !evicted.iter().any(|gone| same_place(&u.placement, gone)));
    }

    /// The copies into cache image `image`, their bytes at `base` onwards
    /// in the buffer the cycle's bytes were staged to.
    pub(super) fn for_image(&self, image: usize, base: u64) -> Vec<TexelUpload> {
        self.uploads
            .iter()
            .filter(|u| u.image as usize == image)
            .map(|u| TexelUpload {
                buffer_offset: base + u.bytes.start as u64,
                ..u.upload
            })
            .collect()
    }

    pub(super) fn uploads(&self) -> &[PendingUpload] {
        &self.uploads
    }

    /// The staged bytes, one mip after another.
    pub(super) fn bytes(&self) -> &[u8] {
        &self.bytes
    }

    pub(super) fn is_empty(&self) -> bool {
        self.uploads.is_empty()
    }

    pub(super) fn clear(&mut self) {
        self.uploads.clear();
        self.bytes.clear();
    }
}

/// Host-visible staging: the ring, and one-off buffers for what the ring
/// has no room for, each released with the ticket of the submission that
/// reads it.
pub(super) struct Staging {
    ring: StagingRing,
    /// One-off staging buffers, each with the ticket after which it is free.
    retiring: VecDeque<(u64, Buffer)>,
}

impl Staging {
    pub(super) fn new(ring: StagingRing) -> Self {
        Self {
            ring,
            retiring: VecDeque::new(),
        }
    }

    /// Puts `bytes` into the staging ring for the submission `ticket` or,
    /// where the ring has no room, into a one-off buffer released with that
    /// ticket ([`GpuTextureCache::retire`]). Returns the buffer and the
    /// bytes' offset.
    pub(super) fn put(
        &mut self,
        device: &Arc<Device>,
        bytes: &[u8],
        ticket: u64,
        label: &str,
    ) -> Result<(vk::Buffer, u64)> {
        if let Some(range) = self.ring.push(bytes, 16, ticket)? {
            return Ok((self.ring.buffer(), range.offset));
        }
        let oversize = Buffer::staged(device, bytes, label)?;
        let raw = oversize.raw();
        self.retiring.push_back((ticket, oversize));
        Ok((raw, 0))
    }

    /// Releases what the submissions up to ticket `completed` read.
    pub(super) fn retire(&mut self, completed: u64) {
        self.ring.retire(completed);
        while self.retiring.front().is_some_and(|(ticket, _)| *ticket <= completed) {
            self.retiring.pop_front();
        }
    }

    /// Bytes of the ring.
    pub(super) fn capacity(&self) -> u64 {
        self.ring.capacity()
    }
}

/// Where a prepared cycle's upload bytes wait and what it did so far.
#[derive(Debug)]
pub(super) struct PreparedCycle {
    ticket: u64,
    /// Buffer and offset of the first upload byte, when there are uploads.
    source: Option<(vk::Buffer, u64)>,
    report: CycleReport,
}

/// A streaming cycle's state: what is staged, the staging it goes
/// through, and the cycle prepared but not yet recorded.
pub(super) struct StagingCycle {
    pub(super) pending: PendingUploads,
    pub(super) staging: Staging,
    /// The cycle prepared by `prepare_cycle`, waiting for `record_cycle`.
    prepared: Option<PreparedCycle>,
    /// The highest ticket handed to `prepare_cycle`.
    last_ticket: u64,
}

impl StagingCycle {
    pub(super) fn new(ring: StagingRing) -> Self {
        Self {
            pending: PendingUploads::default(),
            staging: Staging::new(ring),
            prepared: None,
            last_ticket: 0,
        }
    }
}

/// What was uploaded and dropped so far, for the statistics.
#[derive(Clone, Debug, Default)]
pub(super) struct UploadStats {
    /// Mip bytes per texture level that `drop_finest` released.
    dropped_bytes: u64,
    /// Per texture, bit m: level m was uploaded at least once.
    uploaded_levels: Vec<u32>,
    /// Bytes of the distinct (texture, level) pairs uploaded.
    unique_bytes: u64,
}

impl UploadStats {
    pub(super) fn new(textures: usize) -> Self {
        Self {
            uploaded_levels: vec![0; textures],
            ..Self::default()
        }
    }

    /// Level `mip` of `texture`, `bytes` long, was uploaded.
    pub(super) fn uploaded(&mut self, texture: u32, mip: u32, bytes: u64) {
        let uploaded = &mut self.uploaded_levels[texture as usize];
        if *uploaded & (1 << mip) == 0 {
            *uploaded |= 1 << mip;
            self.unique_bytes += bytes;
        }
    }

    /// A level of `bytes` was dropped.
    pub(super) fn dropped(&mut self, bytes: u64) {
        self.dropped_bytes += bytes;
    }

    pub(super) fn dropped_bytes(&self) -> u64 {
        self.dropped_bytes
    }

    pub(super) fn unique_bytes(&self) -> u64 {
        self.unique_bytes
    }
}

impl GpuTextureCache {
    /// Carries out a cycle in one submission and waits for it: for tools,
    /// tests and reference renders. Must not be interleaved with a
    /// [`prepare_cycle`](Self::prepare_cycle) whose commands are not yet
    /// submitted.
    pub fn finish_cycle(&mut self, commands: &mut CommandContext) -> Result<CycleReport> {
        self.finish_cycle_after(commands, None)
    }

    /// As [`finish_cycle`](Self::finish_cycle), with the unbinds waiting for
    /// `frames_before` (see [`prepare_cycle`](Self::prepare_cycle)), which
    /// must already be submitted.
    pub fn finish_cycle_after(
        &mut self,
        commands: &mut CommandContext,
        frames_before: Option<SemaphoreWait>,
    ) -> Result<CycleReport> {
        let ticket = self.prepare_cycle(frames_before)?;
        let cmd = commands.begin()?;
        let report = self.record_cycle(cmd)?;
        let waits: Vec<SemaphoreWait> = self.bind_wait().into_iter().collect();
        commands.submit_and_wait(&waits)?;
        // The fence covers every earlier submission on the queue too.
        self.retire(ticket);
        Ok(report)
    }

    /// First half of a cycle, before the caller records its frame: marks
    /// evicted textures not sampleable, allocates new memory chunks,
    /// submits all binds and unbinds in one `vkQueueBindSparse` and moves
    /// the staged bytes to host-visible staging. Returns the cycle's ticket,
    /// which names the submission that will carry its commands (see
    /// [`retire`](Self::retire)); `frames_before` is the GPU progress
    /// (semaphore and value) of the last submission that could still
    /// sample an evicted texture, which the unbinds wait for.
    pub fn prepare_cycle(&mut self, frames_before: Option<SemaphoreWait>) -> Result<u64> {
        if self.cycle.prepared.is_some() {
            return Err(EngineError::InvalidRequest(
                "a cache cycle was prepared twice without recording it".into(),
            ));
        }
        self.cycle.last_ticket += 1;
        let ticket = self.cycle.last_ticket;
        let batch = self.cache.take_batch();
        let mut report = CycleReport::default();

        // 1. Evicted textures stop being sampleable; the table copy that
        // says so is recorded before this frame's passes.
        for gone in &batch.invalidated {
            let Ok(texture) = u32::try_from(gone.key) else { continue };
            let Some(slot) = self.table.slot(texture) else {
                continue;
            };
            if slot.placement.is_some_and(|p| same_place(&p, gone)) {
                self.table.place(texture, None);
                report.textures_invalidated += 1;
                report.invalidated_textures.push(texture);
            }
        }
        // Mips staged for a place that was evicted in the same cycle must not be copied.
        self.cycle.pending.drop_evicted(&batch.invalidated);

        // 2. Memory for new pool chunks, and 3. one bind submission: unbinds
        // wait for the frames that may still sample (sparse images only).
        let applied = self
            .images
            .apply_batch(&self.device, &batch.new_chunks, &batch.ops, frames_before)?;
        report.bind_entries = applied.entries;
        report.bind_shape = BatchShape::of(&batch.ops);
        report.bind_seconds = applied.seconds;
        report.blocks_bound = applied.bound;
        report.blocks_unbound = applied.unbound;

        // 4. The bytes go to the staging ring (or, for a cycle larger than
        // the ring, a one-off buffer released with the ticket).
        let source = if self.cycle.pending.is_empty() {
            None
        } else {
            Some(self.cycle.staging.put(
                &self.device,
                self.cycle.pending.bytes(),
                ticket,
                "cache upload staging (oversize cycle)",
            )?)
        };
        self.cycle.prepared = Some(PreparedCycle { ticket, source, report });
        Ok(ticket)
    }

    /// Second half of a cycle: records into `cmd` the copies of the staged
    /// mips (after the layout change the copies need) and then the table
    /// update that publishes them and the evictions, with the barriers that
    /// order them against earlier and later frames. The submission carrying
    /// `cmd` must wait on [`bind_wait`](Self::bind_wait). Without a
    /// prepared cycle, records only pending table changes.
    pub fn record_cycle(&mut self, rec: Recording<'_>) -> Result<CycleReport> {
        let Some(prepared) = self.cycle.prepared.take() else {
            let ticket = self.cycle.last_ticket;
            self.record_table_update(rec, ticket)?;
            return Ok(CycleReport::default());
        };
        let mut report = prepared.report;
        if let Some((source, base)) = prepared.source {
            for index in 0..self.images.len() {
                let uploads = self.cycle.pending.for_image(index, base);
                if uploads.is_empty() {
                    continue;
                }
                let (sampled, copied) = (
                    vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                );
                self.images.record_layout(&self.device, index, rec, sampled, copied);
                self.images.record_copies(&self.device, index, rec, source, &uploads)?;
                self.images.record_layout(&self.device, index, rec, copied, sampled);
            }
            // The copies precede the table update in this command buffer,
            // so no frame sees a level as resident before its texels.
            for u in self.cycle.pending.uploads() {
                self.table.recorded(u.texture, &u.placement, u.upload.mip);
                self.stats.uploaded(u.texture, u.upload.mip, u.bytes.len() as u64);
                report.mips_uploaded += 1;
                report.bytes_uploaded += u.bytes.len() as u64;
            }
            for u in self.cycle.pending.uploads() {
                self.table.publish(u.texture);
            }
        }
        self.cycle.pending.clear();
        self.record_table_update(rec, prepared.ticket)?;
        Ok(report)
    }

    /// What the submission carrying [`record_cycle`](Self::record_cycle)'s
    /// commands must wait on: the last sparse bind batch, at the copy stage.
    pub fn bind_wait(&self) -> Option<SemaphoreWait> {
        self.images.bind_wait()
    }

    /// Releases staging space and one-off buffers of every cycle whose
    /// ticket is at most `completed` (their submissions have finished).
    pub fn retire(&mut self, completed: u64) {
        self.cycle.staging.retire(completed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The table tests' placement, moved to `layer` of `image`.
    fn placement(layer: u32, image: u32) -> Placement {
        Placement {
            layer,
            image,
            ..super::super::table::tests::placement()
        }
    }

    fn upload(mip: u32) -> TexelUpload {
        TexelUpload {
            layer: 0,
            mip,
            x: 0,
            y: 0,
            width: 4,
            height: 4,
            buffer_offset: 0,
        }
    }

    #[test]
    fn staged_mips_are_copied_per_image_from_their_bytes_offset() {
        let mut pending = PendingUploads::default();
        assert!(pending.is_empty());
        pending.push(1, placement(0, 0), upload(6), &[1; 16]);
        pending.push(2, placement(0, 1), upload(5), &[2; 64]);
        pending.push(3, placement(1, 0), upload(4), &[3; 256]);
        assert_eq!(pending.bytes().len(), 336);
        let offsets: Vec<(u32, u64)> = pending
            .for_image(0, 1000)
            .iter()
            .map(|u| (u.mip, u.buffer_offset))
            .collect();
        assert_eq!(offsets, vec![(6, 1000), (4, 1080)]);
        assert_eq!(pending.for_image(1, 0).len(), 1);
        assert!(pending.for_image(2, 0).is_empty());
        // An eviction of layer 1 of image 0 drops its mip; the bytes stay where they are.
        pending.drop_evicted(&[placement(1, 0)]);
        let textures: Vec<u32> = pending.uploads().iter().map(|u| u.texture).collect();
        assert_eq!(textures, vec![1, 2]);
        assert_eq!(pending.bytes()[80], 3);
        pending.clear();
        assert!(pending.is_empty() && pending.bytes().is_empty());
    }

    #[test]
    fn unique_bytes_count_each_texture_level_once() {
        let mut stats = UploadStats::new(4);
        stats.uploaded(3, 2, 100);
        stats.uploaded(3, 2, 100);
        stats.uploaded(3, 1, 400);
        stats.uploaded(0, 2, 100);
        assert_eq!(stats.unique_bytes(), 600);
        stats.dropped(400);
        stats.dropped(100);
        assert_eq!(stats.dropped_bytes(), 500);
    }
}
