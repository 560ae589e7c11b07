//! One streaming cycle of the GPU cache: binds and staging before the
//! caller records its frame, copies and the table update inside it.

use ash::vk;

use super::{same_place, stage_bytes, CycleReport, GpuTextureCache, PreparedCycle};
use crate::commands::{CommandContext, Recording, SemaphoreWait};
use crate::error::{EngineError, Result};
use crate::gpu_types::TEXTURE_NOT_SAMPLEABLE;
use crate::sparse::TexelUpload;

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
        if self.prepared.is_some() {
            return Err(EngineError::InvalidRequest(
                "a cache cycle was prepared twice without recording it".into(),
            ));
        }
        self.last_ticket += 1;
        let ticket = self.last_ticket;
        let batch = self.cache.take_batch();
        let mut report = CycleReport::default();

        // 1. Evicted textures stop being sampleable; the table copy that
        // says so is recorded before this frame's passes.
        for gone in &batch.invalidated {
            let Ok(texture) = u32::try_from(gone.key) else { continue };
            let Some(slot) = self.slots.get_mut(texture as usize) else {
                continue;
            };
            if slot.placement.is_some_and(|p| same_place(&p, gone)) {
                slot.placement = None;
                slot.resident = 0;
                slot.pending = 0;
                self.table[texture as usize].state = TEXTURE_NOT_SAMPLEABLE;
                self.mark_dirty(texture);
                report.textures_invalidated += 1;
                report.invalidated_textures.push(texture);
            }
        }
        // Mips staged for a place that was evicted in the same cycle must not be copied.
        self.uploads
            .retain(|u| !batch.invalidated.iter().any(|gone| same_place(&u.placement, gone)));

        // 2. Memory for new pool chunks, and 3. one bind submission: unbinds
        // wait for the frames that may still sample (sparse images only).
        let applied = self
            .images
            .apply_batch(&self.device, &batch.new_chunks, &batch.ops, frames_before)?;
        report.bind_entries = applied.entries;
        report.bind_seconds = applied.seconds;
        report.blocks_bound = applied.bound;
        report.blocks_unbound = applied.unbound;

        // 4. The bytes go to the staging ring (or, for a cycle larger than
        // the ring, a one-off buffer released with the ticket).
        let source = if self.uploads.is_empty() {
            None
        } else {
            Some(stage_bytes(
                &self.device,
                &mut self.staging,
                &mut self.retiring,
                &self.upload_bytes,
                ticket,
                "cache upload staging (oversize cycle)",
            )?)
        };
        self.prepared = Some(PreparedCycle { ticket, source, report });
        Ok(ticket)
    }

    /// Second half of a cycle: records into `cmd` the copies of the staged
    /// mips (after the layout change the copies need) and then the table
    /// update that publishes them and the evictions, with the barriers that
    /// order them against earlier and later frames. The submission carrying
    /// `cmd` must wait on [`bind_wait`](Self::bind_wait). Without a
    /// prepared cycle, records only pending table changes.
    pub fn record_cycle(&mut self, rec: Recording<'_>) -> Result<CycleReport> {
        let Some(prepared) = self.prepared.take() else {
            let ticket = self.last_ticket;
            self.record_table_update(rec, ticket)?;
            return Ok(CycleReport::default());
        };
        let mut report = prepared.report;
        if let Some((source, base)) = prepared.source {
            for index in 0..self.images.len() {
                let uploads: Vec<TexelUpload> = self
                    .uploads
                    .iter()
                    .filter(|u| u.image as usize == index)
                    .map(|u| TexelUpload {
                        buffer_offset: base + u.bytes.start as u64,
                        ..u.upload
                    })
                    .collect();
                if uploads.is_empty() {
                    continue;
                }
                self.images.record_layout(
                    &self.device,
                    index,
                    rec,
                    vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                );
                self.images.record_copies(&self.device, index, rec, source, &uploads)?;
                self.images.record_layout(
                    &self.device,
                    index,
                    rec,
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                    vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
                );
            }
            // The copies precede the table update in this command buffer,
            // so no frame sees a level as resident before its texels.
            for u in &self.uploads {
                let slot = &mut self.slots[u.texture as usize];
                if slot.placement.is_some_and(|p| same_place(&p, &u.placement)) {
                    slot.resident |= 1 << u.upload.mip;
                }
                slot.pending = 0;
                let uploaded = &mut self.uploaded_levels[u.texture as usize];
                if *uploaded & (1 << u.upload.mip) == 0 {
                    *uploaded |= 1 << u.upload.mip;
                    self.unique_bytes_uploaded += u.bytes.len() as u64;
                }
                report.mips_uploaded += 1;
                report.bytes_uploaded += u.bytes.len() as u64;
            }
            let touched: Vec<u32> = self.uploads.iter().map(|u| u.texture).collect();
            for texture in touched {
                self.publish(texture);
            }
        }
        self.uploads.clear();
        self.upload_bytes.clear();
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
        self.staging.retire(completed);
        while self.retiring.front().is_some_and(|(ticket, _)| *ticket <= completed) {
            self.retiring.pop_front();
        }
    }
}
