//! Fully resident textured-mesh rendering: vertex/index buffers, one RGBA8
//! texture array, one draw per mesh: the procedural placeholder city and
//! tests. The streaming city passes are in [`crate::city`].

use std::sync::Arc;

use ash::vk;
use glam::Mat4;
use gpu_allocator::MemoryLocation;

use crate::buffer::{Buffer, BufferDesc};
use crate::commands::{CommandContext, Recording};
use crate::device::Device;
use crate::error::{EngineError, Result};
use crate::gpu_types::{DrawPush, Vertex, BINDING_MESH_TEXTURES};
use crate::image::{transition, Image, ImageDesc};
use crate::pipeline::{DepthMode, DescriptorPool, DescriptorResource, Filtering, GraphicsDesc, Pipeline, Sampler};
use crate::shaders;
use crate::target::{RenderTarget, COLOR_FORMAT, DEPTH_FORMAT};

/// One mesh: a range of the index buffer drawn with one texture layer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeshRange {
    /// First index in the index buffer.
    pub first_index: u32,
    /// Number of indices (a multiple of 3), relative to `vertex_offset`.
    pub index_count: u32,
    /// Added to every index of the mesh.
    pub vertex_offset: u32,
    /// Texture-array layer.
    pub layer: u32,
    /// Multiplies the sampled colour (white leaves it unchanged).
    pub tint: [f32; 4],
}

/// Geometry of a scene on the CPU.
#[derive(Clone, Debug, Default)]
pub struct SceneGeometry {
    /// All vertices.
    pub vertices: Vec<Vertex>,
    /// All indices (u32).
    pub indices: Vec<u32>,
    /// Meshes as index ranges.
    pub meshes: Vec<MeshRange>,
}

impl SceneGeometry {
    /// Appends a mesh given its own vertices and indices (relative to them).
    pub fn push_mesh(&mut self, vertices: &[Vertex], indices: &[u32], layer: u32) {
        let vertex_offset = self.vertices.len() as u32;
        let first_index = self.indices.len() as u32;
        self.vertices.extend_from_slice(vertices);
        self.indices.extend_from_slice(indices);
        self.meshes.push(MeshRange {
            first_index,
            index_count: indices.len() as u32,
            vertex_offset,
            layer,
            tint: [1.0; 4],
        });
    }

    /// Checks indices and ranges, so a bad scene is an error, not a GPU fault.
    pub fn validate(&self) -> Result<()> {
        for (m, mesh) in self.meshes.iter().enumerate() {
            let end = u64::from(mesh.first_index) + u64::from(mesh.index_count);
            if end > self.indices.len() as u64 || mesh.index_count % 3 != 0 {
                return Err(EngineError::InvalidRequest(format!(
                    "mesh {m} covers indices {}..{end} of {} (or is not whole triangles)",
                    mesh.first_index,
                    self.indices.len()
                )));
            }
            let range = mesh.first_index as usize..end as usize;
            if let Some((i, &index)) = self.indices[range]
                .iter()
                .enumerate()
                .find(|(_, &v)| u64::from(v) + u64::from(mesh.vertex_offset) >= self.vertices.len() as u64)
            {
                return Err(EngineError::InvalidRequest(format!(
                    "mesh {m} index {i} refers to vertex {} + {index}, but the scene has {} vertices",
                    mesh.vertex_offset,
                    self.vertices.len()
                )));
            }
        }
        if let Some((v, _)) = self
            .vertices
            .iter()
            .enumerate()
            .find(|(_, v)| v.position.iter().chain(&v.uv).any(|c| !c.is_finite()))
        {
            return Err(EngineError::InvalidRequest(format!(
                "vertex {v} has a NaN or infinite coordinate"
            )));
        }
        Ok(())
    }
}

/// Square RGBA8 textures of one size, each with a full mip chain.
#[derive(Clone, Debug)]
pub struct TextureArrayData {
    /// Side length of level 0 (a power of two).
    pub size: u32,
    /// `layers[layer][mip]` = RGBA8 texels of that level.
    pub layers: Vec<Vec<Vec<u8>>>,
}

impl TextureArrayData {
    /// Builds layers from level-0 RGBA8 images by 2×2 box filtering.
    pub fn from_base_levels(size: u32, bases: Vec<Vec<u8>>) -> Result<Self> {
        if !size.is_power_of_two() {
            return Err(EngineError::InvalidRequest(format!(
                "texture size {size} is not a power of two"
            )));
        }
        let mut layers = Vec::with_capacity(bases.len());
        for (i, base) in bases.into_iter().enumerate() {
            if base.len() != (size * size * 4) as usize {
                return Err(EngineError::InvalidRequest(format!(
                    "texture {i} has {} bytes, a {size}x{size} RGBA8 level needs {}",
                    base.len(),
                    size * size * 4
                )));
            }
            let mut chain = vec![base];
            let mut side = size;
            while side > 1 {
                let previous = chain.last().map(Vec::as_slice).unwrap_or_default();
                chain.push(downsample_rgba(previous, side));
                side /= 2;
            }
            layers.push(chain);
        }
        Ok(Self { size, layers })
    }

    /// Mip count of the chain.
    pub fn mips(&self) -> u32 {
        32 - self.size.leading_zeros()
    }
}

/// 2×2 box filter of a square RGBA8 level of side `side`.
pub fn downsample_rgba(level: &[u8], side: u32) -> Vec<u8> {
    let half = (side / 2).max(1);
    let mut out = vec![0u8; (half * half * 4) as usize];
    for y in 0..half {
        for x in 0..half {
            for c in 0..4 {
                let at = |sx: u32, sy: u32| u32::from(level[((sy * side + sx) * 4 + c) as usize]);
                let (x0, y0) = (2 * x, 2 * y);
                let (x1, y1) = ((2 * x + 1).min(side - 1), (2 * y + 1).min(side - 1));
                let sum = at(x0, y0) + at(x1, y0) + at(x0, y1) + at(x1, y1);
                out[((y * half + x) * 4 + c) as usize] = ((sum + 2) / 4) as u8;
            }
        }
    }
    out
}

/// Renders a [`SceneGeometry`] with a resident texture array.
#[derive(Debug)]
pub struct MeshRenderer {
    device: Arc<Device>,
    pipeline: Pipeline,
    _pool: DescriptorPool,
    set: vk::DescriptorSet,
    _sampler: Sampler,
    _textures: Image,
    vertices: Buffer,
    indices: Buffer,
    meshes: Vec<MeshRange>,
}

impl MeshRenderer {
    /// Uploads geometry and textures and builds the pipeline.
    pub fn new(
        device: &Arc<Device>,
        commands: &mut CommandContext,
        geometry: &SceneGeometry,
        textures: &TextureArrayData,
        filtering: Filtering,
    ) -> Result<Self> {
        geometry.validate()?;
        if geometry.meshes.is_empty() || textures.layers.is_empty() {
            return Err(EngineError::InvalidRequest(
                "a scene needs at least one mesh and one texture".into(),
            ));
        }
        if let Some(mesh) = geometry
            .meshes
            .iter()
            .find(|m| m.layer as usize >= textures.layers.len())
        {
            return Err(EngineError::InvalidRequest(format!(
                "a mesh uses texture layer {}, but there are {} layers",
                mesh.layer,
                textures.layers.len()
            )));
        }
        let pipeline = Pipeline::graphics(
            device,
            &GraphicsDesc {
                vertex: shaders::MESH_VERT,
                fragment: shaders::MESH_FRAG,
                vertex_stride: std::mem::size_of::<Vertex>() as u32,
                attributes: Vertex::attributes(),
                color_format: COLOR_FORMAT,
                depth_format: DEPTH_FORMAT,
                cull_mode: vk::CullModeFlags::NONE,
                bindings: vec![(
                    BINDING_MESH_TEXTURES,
                    vk::DescriptorType::COMBINED_IMAGE_SAMPLER,
                    1,
                    vk::ShaderStageFlags::FRAGMENT,
                )],
                push_constant_size: std::mem::size_of::<DrawPush>() as u32,
                depth: DepthMode::TestAndWrite,
                color_write: true,
            },
            "mesh pipeline",
        )?;
        let (vertices, indices) = upload_geometry(
            device,
            commands,
            &geometry.vertices,
            &geometry.indices,
            vk::BufferUsageFlags::empty(),
            "scene",
        )?;
        let texture_image = upload_texture_array(device, commands, textures)?;
        let sampler = Sampler::new(device, filtering, "scene sampler")?;
        let pool = DescriptorPool::new(device, &pipeline, 1, "scene descriptors")?;
        let set = pool.allocate(
            &pipeline,
            &[(
                BINDING_MESH_TEXTURES,
                DescriptorResource::SampledImage(texture_image.view(), sampler.raw()),
            )],
        )?;
        Ok(Self {
            device: Arc::clone(device),
            pipeline,
            _pool: pool,
            set,
            _sampler: sampler,
            _textures: texture_image,
            vertices,
            indices,
            meshes: geometry.meshes.clone(),
        })
    }

    /// Records draws of every mesh inside the target's rendering.
    pub fn record(&self, rec: Recording<'_>, view_proj: Mat4, light: [f32; 4]) {
        let cmd = rec.raw();
        self.pipeline.bind(rec, self.set);
        // SAFETY: cmd is recording inside dynamic rendering; buffers are live.
        unsafe {
            self.device
                .raw
                .cmd_bind_vertex_buffers(cmd, 0, &[self.vertices.raw()], &[0]);
            self.device
                .raw
                .cmd_bind_index_buffer(cmd, self.indices.raw(), 0, vk::IndexType::UINT32);
        }
        for mesh in &self.meshes {
            let push = DrawPush {
                view_proj: view_proj.to_cols_array_2d(),
                light_dir_weight: light,
                tint: mesh.tint,
                layer: mesh.layer,
                ..Default::default()
            };
            self.pipeline.push(rec, &push);
            // SAFETY: the index range was validated against the buffers.
            unsafe {
                self.device.raw.cmd_draw_indexed(
                    cmd,
                    mesh.index_count,
                    1,
                    mesh.first_index,
                    mesh.vertex_offset as i32,
                    0,
                )
            };
        }
    }

    /// Renders one frame into `target` and waits for it; returns the pixels.
    pub fn render_once(
        &self,
        commands: &mut CommandContext,
        target: &RenderTarget,
        view_proj: Mat4,
        light: [f32; 4],
        clear: [f32; 4],
    ) -> Result<image::RgbaImage> {
        let cmd = commands.begin()?;
        target.begin(&self.device, cmd, clear);
        self.record(cmd, view_proj, light);
        target.end_and_copy(&self.device, cmd);
        commands.submit_and_wait(&[])?;
        target.read_pixels()
    }
}

/// Uploads a mesh's vertices and indices into device-local buffers named `NAME vertices`
/// and `NAME indices`, the index buffer also usable as `extra_index_usage` says.
pub(crate) fn upload_geometry<V: bytemuck::Pod>(
    device: &Arc<Device>,
    commands: &mut CommandContext,
    vertices: &[V],
    indices: &[u32],
    extra_index_usage: vk::BufferUsageFlags,
    name: &str,
) -> Result<(Buffer, Buffer)> {
    let vertex_buffer = upload_buffer(
        device,
        commands,
        bytemuck::cast_slice(vertices),
        vk::BufferUsageFlags::VERTEX_BUFFER,
        &format!("{name} vertices"),
    )?;
    let index_buffer = upload_buffer(
        device,
        commands,
        bytemuck::cast_slice(indices),
        vk::BufferUsageFlags::INDEX_BUFFER | extra_index_usage,
        &format!("{name} indices"),
    )?;
    Ok((vertex_buffer, index_buffer))
}

/// Creates a GPU-only buffer holding `bytes`, through a temporary staging buffer.
pub fn upload_buffer(
    device: &Arc<Device>,
    commands: &mut CommandContext,
    bytes: &[u8],
    usage: vk::BufferUsageFlags,
    name: &str,
) -> Result<Buffer> {
    let size = (bytes.len() as u64).max(4);
    let mut staging = Buffer::new(
        device,
        BufferDesc {
            size,
            usage: vk::BufferUsageFlags::TRANSFER_SRC,
            location: MemoryLocation::CpuToGpu,
        },
        &format!("{name} staging"),
    )?;
    staging.write(0, bytes)?;
    let buffer = Buffer::new(
        device,
        BufferDesc {
            size,
            usage: usage | vk::BufferUsageFlags::TRANSFER_DST,
            location: MemoryLocation::GpuOnly,
        },
        name,
    )?;
    let cmd = commands.begin()?;
    let region = vk::BufferCopy {
        src_offset: 0,
        dst_offset: 0,
        size,
    };
    // SAFETY: both buffers are live and large enough.
    unsafe {
        device
            .raw
            .cmd_copy_buffer(cmd.raw(), staging.raw(), buffer.raw(), &[region])
    };
    crate::image::memory_barrier(
        device,
        cmd,
        (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
        (vk::PipelineStageFlags2::ALL_COMMANDS, vk::AccessFlags2::MEMORY_READ),
    );
    commands.submit_and_wait(&[])?;
    Ok(buffer)
}

/// Creates a sampled RGBA8 texture array holding every level of `data`.
pub fn upload_texture_array(
    device: &Arc<Device>,
    commands: &mut CommandContext,
    data: &TextureArrayData,
) -> Result<Image> {
    let mips = data.mips();
    let layers = data.layers.len() as u32;
    let image = Image::new(
        device,
        ImageDesc {
            width: data.size,
            height: data.size,
            layers,
            mips,
            format: vk::Format::R8G8B8A8_UNORM,
            usage: vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
            view_type: vk::ImageViewType::TYPE_2D_ARRAY,
        },
        "scene textures",
    )?;
    let mut bytes = Vec::new();
    let mut regions = Vec::new();
    for (layer, chain) in data.layers.iter().enumerate() {
        if chain.len() != mips as usize {
            return Err(EngineError::InvalidRequest(format!(
                "texture layer {layer} has {} levels, expected {mips}",
                chain.len()
            )));
        }
        for (mip, level) in chain.iter().enumerate() {
            let side = (data.size >> mip).max(1);
            if level.len() != (side * side * 4) as usize {
                return Err(EngineError::InvalidRequest(format!(
                    "texture layer {layer} level {mip} has {} bytes, expected {}",
                    level.len(),
                    side * side * 4
                )));
            }
            regions.push(vk::BufferImageCopy {
                buffer_offset: bytes.len() as u64,
                buffer_row_length: 0,
                buffer_image_height: 0,
                image_subresource: vk::ImageSubresourceLayers {
                    aspect_mask: vk::ImageAspectFlags::COLOR,
                    mip_level: mip as u32,
                    base_array_layer: layer as u32,
                    layer_count: 1,
                },
                image_offset: vk::Offset3D::default(),
                image_extent: vk::Extent3D {
                    width: side,
                    height: side,
                    depth: 1,
                },
            });
            bytes.extend_from_slice(level);
        }
    }
    let staging = Buffer::staged(device, &bytes, "texture staging")?;
    let cmd = commands.begin()?;
    // The whole image from one layout to another.
    let image_transition = |from, to, src, dst| {
        transition(device, cmd, image.raw(), image.desc().full_range(), from, to, src, dst);
    };
    image_transition(
        vk::ImageLayout::UNDEFINED,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        (vk::PipelineStageFlags2::TOP_OF_PIPE, vk::AccessFlags2::NONE),
        (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
    );
    // SAFETY: image in TRANSFER_DST_OPTIMAL; regions lie inside buffer and image.
    unsafe {
        device.raw.cmd_copy_buffer_to_image(
            cmd.raw(),
            staging.raw(),
            image.raw(),
            vk::ImageLayout::TRANSFER_DST_OPTIMAL,
            &regions,
        )
    };
    image_transition(
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
        (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
        (
            vk::PipelineStageFlags2::FRAGMENT_SHADER,
            vk::AccessFlags2::SHADER_SAMPLED_READ,
        ),
    );
    commands.submit_and_wait(&[])?;
    Ok(image)
}
