//! Residency probe: samples a sparse 2D-array image at given points and
//! levels with `sparseTextureLodARB` and returns values and residency codes.
//! Used by tests and diagnostics to see what the GPU actually reads.

use std::sync::Arc;

use ash::vk;
use gpu_allocator::MemoryLocation;

use crate::buffer::{Buffer, BufferDesc};
use crate::commands::{CommandContext, SemaphoreWait};
use crate::device::Device;
use crate::error::{EngineError, Result};
use crate::gpu_types::{
    ProbePoint, ProbeResult, TextureProbePoint, BINDING_CACHE_IMAGES, BINDING_COLORMAP, BINDING_PROBE_POINTS,
    BINDING_PROBE_RESULTS, BINDING_PROBE_TEXTURE, BINDING_TEXTURE_DATA, BINDING_TEXTURE_PROBE_POINTS,
    BINDING_TEXTURE_PROBE_RESULTS, CACHE_IMAGE_SLOTS,
};
use crate::image::memory_barrier;
use crate::pipeline::{DescriptorPool, DescriptorResource, Filtering, Pipeline, Sampler};
use crate::shaders;
use crate::texture_cache::GpuTextureCache;

const WORKGROUP: u32 = 64;

/// A compute pipeline that samples a sparse image and reports residency.
#[derive(Debug)]
pub struct SparseProbe {
    device: Arc<Device>,
    pipeline: Pipeline,
    sampler: Sampler,
    capacity: usize,
}

impl SparseProbe {
    /// Creates the probe pipeline for up to `capacity` points per run.
    pub fn new(device: &Arc<Device>, capacity: usize) -> Result<Self> {
        let pipeline = Pipeline::compute(
            device,
            &shaders::SPARSE_PROBE_COMP,
            &[
                (
                    BINDING_PROBE_TEXTURE,
                    vk::DescriptorType::COMBINED_IMAGE_SAMPLER,
                    1,
                    vk::ShaderStageFlags::COMPUTE,
                ),
                (
                    BINDING_PROBE_POINTS,
                    vk::DescriptorType::STORAGE_BUFFER,
                    1,
                    vk::ShaderStageFlags::COMPUTE,
                ),
                (
                    BINDING_PROBE_RESULTS,
                    vk::DescriptorType::STORAGE_BUFFER,
                    1,
                    vk::ShaderStageFlags::COMPUTE,
                ),
            ],
            0,
            "sparse probe",
        )?;
        let sampler = Sampler::new(device, Filtering::Nearest, "sparse probe sampler")?;
        Ok(Self {
            device: Arc::clone(device),
            pipeline,
            sampler,
            capacity: capacity.max(1),
        })
    }

    /// Samples `view` (in SHADER_READ_ONLY_OPTIMAL) at `points`, after
    /// waiting on `waits`, and returns one result per point.
    pub fn run(
        &self,
        commands: &mut CommandContext,
        view: vk::ImageView,
        points: &[ProbePoint],
        waits: &[SemaphoreWait],
    ) -> Result<Vec<ProbeResult>> {
        if points.is_empty() || points.len() > self.capacity {
            return Err(EngineError::InvalidRequest(format!(
                "probe run with {} points; allowed 1..={}",
                points.len(),
                self.capacity
            )));
        }
        let sampled = [(
            BINDING_PROBE_TEXTURE,
            DescriptorResource::SampledImage(view, self.sampler.raw()),
        )];
        dispatch_probe(
            &self.device,
            &self.pipeline,
            commands,
            points,
            (BINDING_PROBE_POINTS, BINDING_PROBE_RESULTS),
            &sampled,
            waits,
        )
    }
}

/// Samples dataset textures through a [`GpuTextureCache`] exactly as the
/// renderer does (table, UV transform, LOD clamp, residency, colormap
/// fallback) at explicit points; `ProbeResult::resident` is 1 where the
/// value came from the cache and 0 where it is the colormap colour.
#[derive(Debug)]
pub struct TextureProbe {
    device: Arc<Device>,
    pipeline: Pipeline,
}

impl TextureProbe {
    /// Creates the probe pipeline.
    pub fn new(device: &Arc<Device>) -> Result<Self> {
        let compute = vk::ShaderStageFlags::COMPUTE;
        let pipeline = Pipeline::compute(
            device,
            &shaders::for_backing(device, shaders::TEXTURE_PROBE_COMP, shaders::TEXTURE_PROBE_COMP_ARRAYS),
            &[
                (
                    BINDING_CACHE_IMAGES,
                    vk::DescriptorType::COMBINED_IMAGE_SAMPLER,
                    CACHE_IMAGE_SLOTS,
                    compute,
                ),
                (BINDING_TEXTURE_DATA, vk::DescriptorType::STORAGE_BUFFER, 1, compute),
                (BINDING_COLORMAP, vk::DescriptorType::STORAGE_BUFFER, 1, compute),
                (
                    BINDING_TEXTURE_PROBE_POINTS,
                    vk::DescriptorType::STORAGE_BUFFER,
                    1,
                    compute,
                ),
                (
                    BINDING_TEXTURE_PROBE_RESULTS,
                    vk::DescriptorType::STORAGE_BUFFER,
                    1,
                    compute,
                ),
            ],
            0,
            "texture probe",
        )?;
        Ok(Self {
            device: Arc::clone(device),
            pipeline,
        })
    }

    /// Samples `points` through `cache` and returns one result per point.
    pub fn run(
        &self,
        commands: &mut CommandContext,
        cache: &GpuTextureCache,
        points: &[TextureProbePoint],
    ) -> Result<Vec<ProbeResult>> {
        if points.is_empty() {
            return Err(EngineError::InvalidRequest("texture probe run with no points".into()));
        }
        dispatch_probe(
            &self.device,
            &self.pipeline,
            commands,
            points,
            (BINDING_TEXTURE_PROBE_POINTS, BINDING_TEXTURE_PROBE_RESULTS),
            &cache.descriptors(),
            &[],
        )
    }
}

/// Uploads `points`, binds them and `resources` to `pipeline`, dispatches one
/// invocation per point after `waits`, and reads one [`ProbeResult`] each.
/// The temporary buffers and pool drop after the submission's wait.
fn dispatch_probe<P: bytemuck::Pod>(
    device: &Arc<Device>,
    pipeline: &Pipeline,
    commands: &mut CommandContext,
    points: &[P],
    (points_binding, results_binding): (u32, u32),
    resources: &[(u32, DescriptorResource)],
    waits: &[SemaphoreWait],
) -> Result<Vec<ProbeResult>> {
    let mut point_buffer = Buffer::new(
        device,
        BufferDesc {
            size: std::mem::size_of_val(points) as u64,
            usage: vk::BufferUsageFlags::STORAGE_BUFFER,
            location: MemoryLocation::CpuToGpu,
        },
        "probe points",
    )?;
    point_buffer.write(0, points)?;
    let result_buffer = Buffer::new(
        device,
        BufferDesc {
            size: (points.len() * std::mem::size_of::<ProbeResult>()) as u64,
            usage: vk::BufferUsageFlags::STORAGE_BUFFER,
            location: MemoryLocation::GpuToCpu,
        },
        "probe results",
    )?;
    let pool = DescriptorPool::new(device, pipeline, 1, "probe descriptors")?;
    let mut all = resources.to_vec();
    all.push((points_binding, DescriptorResource::StorageBuffer(point_buffer.raw())));
    all.push((results_binding, DescriptorResource::StorageBuffer(result_buffer.raw())));
    let set = pool.allocate(pipeline, &all)?;
    let cmd = commands.begin()?;
    memory_barrier(
        device,
        cmd,
        (vk::PipelineStageFlags2::ALL_COMMANDS, vk::AccessFlags2::MEMORY_WRITE),
        (vk::PipelineStageFlags2::COMPUTE_SHADER, vk::AccessFlags2::SHADER_READ),
    );
    pipeline.bind(cmd, set);
    // SAFETY: cmd is recording; the pipeline and set are bound.
    unsafe {
        device
            .raw()
            .cmd_dispatch(cmd.raw(), (points.len() as u32).div_ceil(WORKGROUP), 1, 1)
    };
    memory_barrier(
        device,
        cmd,
        (vk::PipelineStageFlags2::COMPUTE_SHADER, vk::AccessFlags2::SHADER_WRITE),
        (vk::PipelineStageFlags2::HOST, vk::AccessFlags2::HOST_READ),
    );
    commands.submit_and_wait(waits)?;
    result_buffer.read::<ProbeResult>(0, points.len())
}
