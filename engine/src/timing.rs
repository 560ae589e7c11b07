//! Frame timing: CPU wall time per frame and GPU timestamp queries. The
//! adaptive controller consumes these as frame latency.

use std::sync::Arc;
use std::time::{Duration, Instant};

use ash::vk;

use crate::commands::Recording;
use crate::device::Device;
use crate::error::{Result, VkResultExt};

/// Measures CPU wall time between successive frames.
#[derive(Debug)]
pub struct CpuFrameClock {
    last: Instant,
}

impl Default for CpuFrameClock {
    fn default() -> Self {
        Self::new()
    }
}

impl CpuFrameClock {
    /// Starts the clock now.
    pub fn new() -> Self {
        Self { last: Instant::now() }
    }

    /// Time since the previous call (or since creation), and restarts.
    pub fn tick(&mut self) -> Duration {
        let now = Instant::now();
        let elapsed = now - self.last;
        self.last = now;
        elapsed
    }
}

/// GPU timestamps around a frame's commands, one pair per frame slot.
///
/// Threading: owned by the frame loop.
pub struct GpuTimer {
    device: Arc<Device>,
    pool: vk::QueryPool,
    period_ns: f64,
    slots: u32,
    valid_bits: u32,
}

debug_fields!(GpuTimer { slots });

impl GpuTimer {
    /// Creates a timer with `slots` frame slots (one per frame in flight).
    pub fn new(device: &Arc<Device>, slots: u32) -> Result<Self> {
        let info = vk::QueryPoolCreateInfo::default()
            .query_type(vk::QueryType::TIMESTAMP)
            .query_count(slots.max(1) * 2);
        // SAFETY: valid create info.
        let pool = unsafe { device.raw.create_query_pool(&info, None) }.vk("vkCreateQueryPool")?;
        device.set_name(pool, "frame timestamps");
        // SAFETY: physical belongs to the instance.
        let families = unsafe {
            device
                .instance_fns()
                .get_physical_device_queue_family_properties(device.physical())
        };
        let valid_bits = families
            .get(device.queue_family() as usize)
            .map_or(0, |f| f.timestamp_valid_bits);
        Ok(Self {
            device: Arc::clone(device),
            pool,
            period_ns: f64::from(device.properties().limits.timestamp_period),
            slots: slots.max(1),
            valid_bits,
        })
    }

    /// Whether the queue writes timestamps at all.
    pub fn supported(&self) -> bool {
        self.valid_bits > 0
    }

    /// Records the reset and the start timestamp of `slot` (outside rendering).
    pub fn begin(&self, rec: Recording<'_>, slot: u32) {
        let cmd = rec.raw();
        let first = (slot % self.slots) * 2;
        // SAFETY: cmd is recording outside a render pass; queries lie in the pool.
        unsafe {
            self.device.raw.cmd_reset_query_pool(cmd, self.pool, first, 2);
            self.device
                .raw
                .cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::TOP_OF_PIPE, self.pool, first);
        }
    }

    /// Records the end timestamp of `slot`.
    pub fn end(&self, rec: Recording<'_>, slot: u32) {
        let cmd = rec.raw();
        let first = (slot % self.slots) * 2;
        // SAFETY: cmd is recording; the query was reset by `begin` in the same buffer.
        unsafe {
            self.device
                .raw
                .cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::BOTTOM_OF_PIPE, self.pool, first + 1)
        };
    }

    /// GPU time of `slot` in milliseconds, once its submission completed;
    /// `None` when the queue has no timestamps.
    pub fn read_ms(&self, slot: u32) -> Result<Option<f64>> {
        if !self.supported() {
            return Ok(None);
        }
        let first = (slot % self.slots) * 2;
        let mut stamps = [0u64; 2];
        // SAFETY: the caller waited for the submission; results fit the array.
        unsafe {
            self.device
                .raw
                .get_query_pool_results(self.pool, first, &mut stamps, vk::QueryResultFlags::TYPE_64)
        }
        .vk("vkGetQueryPoolResults")?;
        let mask = if self.valid_bits >= 64 {
            u64::MAX
        } else {
            (1u64 << self.valid_bits) - 1
        };
        let ticks = (stamps[1] & mask).wrapping_sub(stamps[0] & mask) & mask;
        Ok(Some(ticks as f64 * self.period_ns / 1.0e6))
    }
}

impl Drop for GpuTimer {
    fn drop(&mut self) {
        // SAFETY: the owner drops after the frames that wrote it completed.
        unsafe { self.device.raw.destroy_query_pool(self.pool, None) };
    }
}
