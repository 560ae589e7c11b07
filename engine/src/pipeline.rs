//! Shader modules, descriptor layouts and pools, graphics and compute pipelines.

use std::sync::Arc;

use ash::vk;

use crate::commands::Recording;
use crate::device::Device;
use crate::error::{EngineError, Result, VkResultExt};
use crate::gpu_types::CACHE_IMAGE_SLOTS;
use crate::shaders::ShaderSource;

/// Creates a shader module from embedded SPIR-V. The module is only needed
/// while a pipeline is created; the caller destroys it right after.
fn create_module(device: &Device, shader: &ShaderSource) -> Result<vk::ShaderModule> {
    let code = ash::util::read_spv(&mut std::io::Cursor::new(shader.spirv)).map_err(|source| EngineError::Shader {
        name: shader.name,
        source,
    })?;
    let info = vk::ShaderModuleCreateInfo::default().code(&code);
    // SAFETY: code is valid SPIR-V (checked by spirv-val at build time).
    let module = unsafe { device.raw.create_shader_module(&info, None) }.vk("vkCreateShaderModule")?;
    device.set_name(module, shader.name);
    Ok(module)
}

/// Destroys shader modules when dropped, so pipeline creation can bail out early.
struct ModuleGuard<'a> {
    device: &'a Device,
    modules: Vec<vk::ShaderModule>,
}

impl Drop for ModuleGuard<'_> {
    fn drop(&mut self) {
        for &m in &self.modules {
            // SAFETY: modules are not referenced after pipeline creation.
            unsafe { self.device.raw.destroy_shader_module(m, None) };
        }
    }
}

/// Descriptor bindings of one set: (binding number, type, count, stages).
pub type BindingSpec = (u32, vk::DescriptorType, u32, vk::ShaderStageFlags);

/// A pipeline with its layout and descriptor-set layout (set 0).
pub struct Pipeline {
    device: Arc<Device>,
    raw: vk::Pipeline,
    layout: vk::PipelineLayout,
    set_layout: vk::DescriptorSetLayout,
    bind_point: vk::PipelineBindPoint,
    bindings: Vec<BindingSpec>,
}

debug_fields!(Pipeline { bind_point });

/// Fixed-function choices of a graphics pipeline.
#[derive(Clone, Debug)]
pub struct GraphicsDesc {
    /// Vertex shader.
    pub vertex: ShaderSource,
    /// Fragment shader.
    pub fragment: ShaderSource,
    /// Vertex stride in bytes.
    pub vertex_stride: u32,
    /// Vertex attributes (location, format, offset).
    pub attributes: Vec<(u32, vk::Format, u32)>,
    /// Colour attachment format.
    pub color_format: vk::Format,
    /// Depth attachment format.
    pub depth_format: vk::Format,
    /// Face culling.
    pub cull_mode: vk::CullModeFlags,
    /// Descriptor set 0.
    pub bindings: Vec<BindingSpec>,
    /// Push-constant bytes visible to vertex and fragment stages.
    pub push_constant_size: u32,
    /// Depth test and writes.
    pub depth: DepthMode,
    /// Whether the colour attachment is written.
    pub color_write: bool,
}

/// How a graphics pipeline uses the depth buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthMode {
    /// Test with GREATER and write: ordinary opaque rendering under reversed depth (nearer
    /// is greater; strict, so that of two surfaces at one depth the first drawn stays).
    TestAndWrite,
    /// Test with GREATER_OR_EQUAL against a depth pre-pass, no writes: only the
    /// nearest surface's fragments run.
    EqualAfterPrepass,
}

impl Pipeline {
    fn layouts(
        device: &Arc<Device>,
        bindings: &[BindingSpec],
        push_size: u32,
        push_stages: vk::ShaderStageFlags,
    ) -> Result<(vk::DescriptorSetLayout, vk::PipelineLayout)> {
        let vk_bindings: Vec<_> = bindings
            .iter()
            .map(|&(binding, ty, count, stages)| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(binding)
                    .descriptor_type(ty)
                    .descriptor_count(count)
                    .stage_flags(stages)
            })
            .collect();
        let info = vk::DescriptorSetLayoutCreateInfo::default().bindings(&vk_bindings);
        // SAFETY: valid create info.
        let set_layout =
            unsafe { device.raw.create_descriptor_set_layout(&info, None) }.vk("vkCreateDescriptorSetLayout")?;
        let set_layouts = [set_layout];
        let ranges = [vk::PushConstantRange {
            stage_flags: push_stages,
            offset: 0,
            size: push_size,
        }];
        let mut info = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
        if push_size > 0 {
            info = info.push_constant_ranges(&ranges);
        }
        // SAFETY: valid create info referencing a live set layout.
        match unsafe { device.raw.create_pipeline_layout(&info, None) } {
            Ok(layout) => Ok((set_layout, layout)),
            Err(result) => {
                // SAFETY: the set layout is unused.
                unsafe { device.raw.destroy_descriptor_set_layout(set_layout, None) };
                Err(EngineError::Vulkan {
                    call: "vkCreatePipelineLayout",
                    result,
                })
            }
        }
    }

    /// Creates a graphics pipeline for dynamic rendering.
    pub fn graphics(device: &Arc<Device>, desc: &GraphicsDesc, name: &str) -> Result<Self> {
        let (set_layout, layout) = Self::layouts(
            device,
            &desc.bindings,
            desc.push_constant_size,
            vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT,
        )?;
        // Owns the layouts from here, so any error below cleans up.
        let mut pipeline = Self {
            device: Arc::clone(device),
            raw: vk::Pipeline::null(),
            layout,
            set_layout,
            bind_point: vk::PipelineBindPoint::GRAPHICS,
            bindings: desc.bindings.clone(),
        };
        let mut guard = ModuleGuard {
            device,
            modules: Vec::new(),
        };
        let vert = create_module(device, &desc.vertex)?;
        guard.modules.push(vert);
        let frag = create_module(device, &desc.fragment)?;
        guard.modules.push(frag);
        let stages = [
            vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::VERTEX)
                .module(vert)
                .name(c"main"),
            vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::FRAGMENT)
                .module(frag)
                .name(c"main"),
        ];
        let vertex_bindings = [vk::VertexInputBindingDescription {
            binding: 0,
            stride: desc.vertex_stride,
            input_rate: vk::VertexInputRate::VERTEX,
        }];
        let attributes: Vec<_> = desc
            .attributes
            .iter()
            .map(|&(location, format, offset)| vk::VertexInputAttributeDescription {
                location,
                binding: 0,
                format,
                offset,
            })
            .collect();
        // A pass without attributes makes its vertices from gl_VertexIndex: no buffer binding.
        let used_bindings = if attributes.is_empty() {
            &[][..]
        } else {
            &vertex_bindings[..]
        };
        let vertex_input = vk::PipelineVertexInputStateCreateInfo::default()
            .vertex_binding_descriptions(used_bindings)
            .vertex_attribute_descriptions(&attributes);
        let input_assembly =
            vk::PipelineInputAssemblyStateCreateInfo::default().topology(vk::PrimitiveTopology::TRIANGLE_LIST);
        let viewport = vk::PipelineViewportStateCreateInfo::default()
            .viewport_count(1)
            .scissor_count(1);
        let raster = vk::PipelineRasterizationStateCreateInfo::default()
            .polygon_mode(vk::PolygonMode::FILL)
            .cull_mode(desc.cull_mode)
            .front_face(vk::FrontFace::COUNTER_CLOCKWISE)
            .line_width(1.0);
        let multisample =
            vk::PipelineMultisampleStateCreateInfo::default().rasterization_samples(vk::SampleCountFlags::TYPE_1);
        let (compare, write) = match desc.depth {
            DepthMode::TestAndWrite => (vk::CompareOp::GREATER, true),
            DepthMode::EqualAfterPrepass => (vk::CompareOp::GREATER_OR_EQUAL, false),
        };
        let depth = vk::PipelineDepthStencilStateCreateInfo::default()
            .depth_test_enable(true)
            .depth_write_enable(write)
            .depth_compare_op(compare);
        let write_mask = if desc.color_write {
            vk::ColorComponentFlags::RGBA
        } else {
            vk::ColorComponentFlags::empty()
        };
        let blend_attachments = [vk::PipelineColorBlendAttachmentState::default().color_write_mask(write_mask)];
        let blend = vk::PipelineColorBlendStateCreateInfo::default().attachments(&blend_attachments);
        let dynamic_states = [vk::DynamicState::VIEWPORT, vk::DynamicState::SCISSOR];
        let dynamic = vk::PipelineDynamicStateCreateInfo::default().dynamic_states(&dynamic_states);
        let color_formats = [desc.color_format];
        let mut rendering = vk::PipelineRenderingCreateInfo::default()
            .color_attachment_formats(&color_formats)
            .depth_attachment_format(desc.depth_format);
        let info = vk::GraphicsPipelineCreateInfo::default()
            .stages(&stages)
            .vertex_input_state(&vertex_input)
            .input_assembly_state(&input_assembly)
            .viewport_state(&viewport)
            .rasterization_state(&raster)
            .multisample_state(&multisample)
            .depth_stencil_state(&depth)
            .color_blend_state(&blend)
            .dynamic_state(&dynamic)
            .layout(layout)
            .push_next(&mut rendering);
        // SAFETY: every referenced object is live for this call.
        let created = unsafe {
            device
                .raw
                .create_graphics_pipelines(vk::PipelineCache::null(), &[info], None)
        };
        pipeline.raw = created.map_err(|(_, result)| EngineError::Vulkan {
            call: "vkCreateGraphicsPipelines",
            result,
        })?[0];
        device.set_name(pipeline.raw, name);
        Ok(pipeline)
    }

    /// Creates a compute pipeline.
    pub fn compute(
        device: &Arc<Device>,
        shader: &ShaderSource,
        bindings: &[BindingSpec],
        push_constant_size: u32,
        name: &str,
    ) -> Result<Self> {
        let (set_layout, layout) = Self::layouts(device, bindings, push_constant_size, vk::ShaderStageFlags::COMPUTE)?;
        let mut pipeline = Self {
            device: Arc::clone(device),
            raw: vk::Pipeline::null(),
            layout,
            set_layout,
            bind_point: vk::PipelineBindPoint::COMPUTE,
            bindings: bindings.to_vec(),
        };
        let module = create_module(device, shader)?;
        let _guard = ModuleGuard {
            device,
            modules: vec![module],
        };
        let stage = vk::PipelineShaderStageCreateInfo::default()
            .stage(vk::ShaderStageFlags::COMPUTE)
            .module(module)
            .name(c"main");
        let info = vk::ComputePipelineCreateInfo::default().stage(stage).layout(layout);
        // SAFETY: every referenced object is live for this call.
        let created = unsafe {
            device
                .raw
                .create_compute_pipelines(vk::PipelineCache::null(), &[info], None)
        };
        pipeline.raw = created.map_err(|(_, result)| EngineError::Vulkan {
            call: "vkCreateComputePipelines",
            result,
        })?[0];
        device.set_name(pipeline.raw, name);
        Ok(pipeline)
    }

    /// The raw pipeline.
    pub fn raw(&self) -> vk::Pipeline {
        self.raw
    }

    /// The pipeline layout.
    pub fn layout(&self) -> vk::PipelineLayout {
        self.layout
    }

    /// The layout of descriptor set 0.
    pub fn set_layout(&self) -> vk::DescriptorSetLayout {
        self.set_layout
    }

    /// Graphics or compute.
    pub fn bind_point(&self) -> vk::PipelineBindPoint {
        self.bind_point
    }

    /// The bindings of set 0.
    pub fn bindings(&self) -> &[BindingSpec] {
        &self.bindings
    }

    /// Binds the pipeline and `set` as set 0.
    pub(crate) fn bind(&self, rec: Recording<'_>, set: vk::DescriptorSet) {
        let cmd = rec.raw();
        // SAFETY: cmd is recording; pipeline and set are live and compatible.
        unsafe {
            self.device.raw.cmd_bind_pipeline(cmd, self.bind_point, self.raw);
            self.device
                .raw
                .cmd_bind_descriptor_sets(cmd, self.bind_point, self.layout, 0, &[set], &[]);
        }
    }

    /// Dispatches at least `invocations` invocations of this compute pipeline's
    /// `workgroup_size`-wide workgroups, as many rows of workgroups as the device's
    /// `maxComputeWorkGroupCount[0]` requires: the shader's flat index is
    /// `gl_GlobalInvocationID.x + gl_GlobalInvocationID.y * gl_NumWorkGroups.x * workgroup_size`,
    /// and it bounds-checks it (the last row is padded).
    pub(crate) fn dispatch_flat(&self, rec: Recording<'_>, invocations: u32, workgroup_size: u32) {
        let cmd = rec.raw();
        let groups = invocations.div_ceil(workgroup_size).max(1);
        let row = self.device.properties().limits.max_compute_work_group_count[0].max(1);
        let (x, y) = if groups <= row {
            (groups, 1)
        } else {
            (row, groups.div_ceil(row))
        };
        // SAFETY: cmd is recording outside rendering with this pipeline bound; the shader
        // bounds-checks its flat index.
        unsafe { self.device.raw.cmd_dispatch(cmd, x, y, 1) };
    }

    /// Pushes constants to every stage of the layout.
    pub(crate) fn push<T: bytemuck::Pod>(&self, rec: Recording<'_>, value: &T) {
        let cmd = rec.raw();
        let stages = match self.bind_point {
            vk::PipelineBindPoint::COMPUTE => vk::ShaderStageFlags::COMPUTE,
            _ => vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT,
        };
        // SAFETY: cmd is recording; the range lies within the layout's push range.
        unsafe {
            self.device
                .raw
                .cmd_push_constants(cmd, self.layout, stages, 0, bytemuck::bytes_of(value))
        };
    }
}

impl Drop for Pipeline {
    fn drop(&mut self) {
        // SAFETY: the owner drops only after the GPU finished with the pipeline.
        unsafe {
            if self.raw != vk::Pipeline::null() {
                self.device.raw.destroy_pipeline(self.raw, None);
            }
            self.device.raw.destroy_pipeline_layout(self.layout, None);
            self.device.raw.destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}

/// A descriptor pool sized for a few sets of one pipeline's layout.
pub struct DescriptorPool {
    device: Arc<Device>,
    raw: vk::DescriptorPool,
}

debug_fields!(DescriptorPool { raw });

/// What one descriptor write points at.
#[derive(Clone, Copy, Debug)]
pub enum DescriptorResource {
    /// A storage buffer range (whole buffer).
    StorageBuffer(vk::Buffer),
    /// An array binding of storage buffers that views one buffer of `size` bytes through
    /// windows of `window` bytes (a power of two no larger than the device's
    /// `maxStorageBufferRange`): element `k` is bytes `k * window ..` of it, so a shader
    /// reaches a buffer larger than one binding may address. Elements past the end repeat
    /// the first window.
    StorageBufferWindows {
        buffer: vk::Buffer,
        size: u64,
        window: u64,
        count: u32,
    },
    /// A uniform buffer (whole buffer).
    UniformBuffer(vk::Buffer),
    /// A combined image sampler in SHADER_READ_ONLY_OPTIMAL.
    SampledImage(vk::ImageView, vk::Sampler),
    /// An array binding of combined image samplers in
    /// SHADER_READ_ONLY_OPTIMAL, one view per element, one sampler for all.
    SampledImageArray([vk::ImageView; CACHE_IMAGE_SLOTS as usize], vk::Sampler),
}

impl DescriptorResource {
    /// The descriptor type a binding of this resource has.
    pub fn descriptor_type(&self) -> vk::DescriptorType {
        match self {
            DescriptorResource::StorageBuffer(_) | DescriptorResource::StorageBufferWindows { .. } => {
                vk::DescriptorType::STORAGE_BUFFER
            }
            DescriptorResource::UniformBuffer(_) => vk::DescriptorType::UNIFORM_BUFFER,
            DescriptorResource::SampledImage(..) | DescriptorResource::SampledImageArray(..) => {
                vk::DescriptorType::COMBINED_IMAGE_SAMPLER
            }
        }
    }

    /// Descriptors in the binding (its `descriptorCount`).
    pub fn count(&self) -> u32 {
        match self {
            DescriptorResource::SampledImageArray(views, _) => views.len() as u32,
            _ => 1,
        }
    }
}

impl DescriptorPool {
    /// Creates a pool for `sets` sets of `pipeline`'s set-0 layout.
    pub fn new(device: &Arc<Device>, pipeline: &Pipeline, sets: u32, name: &str) -> Result<Self> {
        let sizes: Vec<_> = pipeline
            .bindings()
            .iter()
            .map(|&(_, ty, count, _)| vk::DescriptorPoolSize {
                ty,
                descriptor_count: count * sets,
            })
            .collect();
        let info = vk::DescriptorPoolCreateInfo::default()
            .max_sets(sets)
            .pool_sizes(&sizes);
        // SAFETY: valid create info.
        let raw = unsafe { device.raw.create_descriptor_pool(&info, None) }.vk("vkCreateDescriptorPool")?;
        device.set_name(raw, name);
        Ok(Self {
            device: Arc::clone(device),
            raw,
        })
    }

    /// Allocates a set for `pipeline` and writes `resources` (binding, resource).
    pub fn allocate(&self, pipeline: &Pipeline, resources: &[(u32, DescriptorResource)]) -> Result<vk::DescriptorSet> {
        let layouts = [pipeline.set_layout()];
        let info = vk::DescriptorSetAllocateInfo::default()
            .descriptor_pool(self.raw)
            .set_layouts(&layouts);
        // SAFETY: pool and layout are live.
        let set = unsafe { self.device.raw.allocate_descriptor_sets(&info) }.vk("vkAllocateDescriptorSets")?[0];
        self.write(set, resources);
        Ok(set)
    }

    /// Writes `resources` into `set`. The set must not be in use by the GPU.
    pub fn write(&self, set: vk::DescriptorSet, resources: &[(u32, DescriptorResource)]) {
        write_descriptor_set(&self.device, set, resources);
    }
}

/// (offset, range) of each of `count` windows of `window` bytes over a buffer of `size`
/// bytes; windows past the end repeat the first.
pub(crate) fn storage_windows(size: u64, window: u64, count: u32) -> impl Iterator<Item = (u64, u64)> {
    (0..u64::from(count)).map(move |k| {
        let offset = k.checked_mul(window).filter(|&o| o < size).unwrap_or(0);
        (offset, window.min(size - offset).max(1))
    })
}

/// Writes `resources` (binding, resource) into `set`, which must come from a
/// live pool of `device` with a layout that has those bindings, and must not
/// be in use by the GPU.
pub(crate) fn write_descriptor_set(device: &Device, set: vk::DescriptorSet, resources: &[(u32, DescriptorResource)]) {
    let buffer_infos: Vec<Vec<vk::DescriptorBufferInfo>> = resources
        .iter()
        .map(|(_, r)| match *r {
            DescriptorResource::StorageBuffer(b) | DescriptorResource::UniformBuffer(b) => {
                vec![vk::DescriptorBufferInfo {
                    buffer: b,
                    offset: 0,
                    range: vk::WHOLE_SIZE,
                }]
            }
            DescriptorResource::StorageBufferWindows {
                buffer,
                size,
                window,
                count,
            } => storage_windows(size, window, count)
                .map(|(offset, range)| vk::DescriptorBufferInfo { buffer, offset, range })
                .collect(),
            _ => Vec::new(),
        })
        .collect();
    let sampled = |sampler, image_view| vk::DescriptorImageInfo {
        sampler,
        image_view,
        image_layout: vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
    };
    let image_infos: Vec<Vec<vk::DescriptorImageInfo>> = resources
        .iter()
        .map(|(_, r)| match *r {
            DescriptorResource::SampledImage(view, sampler) => vec![sampled(sampler, view)],
            DescriptorResource::SampledImageArray(views, sampler) => {
                views.iter().map(|&view| sampled(sampler, view)).collect()
            }
            _ => Vec::new(),
        })
        .collect();
    let writes: Vec<_> = resources
        .iter()
        .enumerate()
        .map(|(i, (binding, r))| {
            let write = vk::WriteDescriptorSet::default()
                .dst_set(set)
                .dst_binding(*binding)
                .descriptor_type(r.descriptor_type());
            match r {
                DescriptorResource::StorageBuffer(_)
                | DescriptorResource::UniformBuffer(_)
                | DescriptorResource::StorageBufferWindows { .. } => write.buffer_info(&buffer_infos[i]),
                DescriptorResource::SampledImage(..) | DescriptorResource::SampledImageArray(..) => {
                    write.image_info(&image_infos[i])
                }
            }
        })
        .collect();
    // SAFETY: every write refers to live objects; the set is not in use.
    unsafe { device.raw.update_descriptor_sets(&writes, &[]) };
}

impl Drop for DescriptorPool {
    fn drop(&mut self) {
        // SAFETY: the owner drops only after the GPU finished with its sets.
        unsafe { self.device.raw.destroy_descriptor_pool(self.raw, None) };
    }
}

/// A sampler owned by Rust.
pub struct Sampler {
    device: Arc<Device>,
    raw: vk::Sampler,
}

debug_fields!(Sampler { raw });

/// Sampler filtering choice.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Filtering {
    /// Nearest texel, nearest mip: exact texel reads for tests and probes.
    Nearest,
    /// Trilinear with the given maximum anisotropy (1 = off).
    Trilinear { max_anisotropy: u32 },
    /// Bilinear within a level, nearest level: the city shaders blend two
    /// levels themselves (see `city_texture.glsl`).
    BilinearNearestLevel,
}

impl Sampler {
    /// Creates a sampler with repeat addressing.
    pub fn new(device: &Arc<Device>, filtering: Filtering, name: &str) -> Result<Self> {
        let mut info = vk::SamplerCreateInfo::default()
            .address_mode_u(vk::SamplerAddressMode::REPEAT)
            .address_mode_v(vk::SamplerAddressMode::REPEAT)
            .address_mode_w(vk::SamplerAddressMode::CLAMP_TO_EDGE)
            .min_lod(0.0)
            .max_lod(vk::LOD_CLAMP_NONE);
        info = match filtering {
            Filtering::Nearest => info
                .mag_filter(vk::Filter::NEAREST)
                .min_filter(vk::Filter::NEAREST)
                .mipmap_mode(vk::SamplerMipmapMode::NEAREST),
            Filtering::BilinearNearestLevel => info
                .mag_filter(vk::Filter::LINEAR)
                .min_filter(vk::Filter::LINEAR)
                .mipmap_mode(vk::SamplerMipmapMode::NEAREST),
            Filtering::Trilinear { max_anisotropy } => {
                let limit = device.properties().limits.max_sampler_anisotropy;
                let aniso = (max_anisotropy as f32).min(limit);
                info.mag_filter(vk::Filter::LINEAR)
                    .min_filter(vk::Filter::LINEAR)
                    .mipmap_mode(vk::SamplerMipmapMode::LINEAR)
                    .anisotropy_enable(aniso > 1.0)
                    .max_anisotropy(aniso.max(1.0))
            }
        };
        // SAFETY: valid create info.
        let raw = unsafe { device.raw.create_sampler(&info, None) }.vk("vkCreateSampler")?;
        device.set_name(raw, name);
        Ok(Self {
            device: Arc::clone(device),
            raw,
        })
    }

    /// The raw handle.
    pub fn raw(&self) -> vk::Sampler {
        self.raw
    }
}

impl Drop for Sampler {
    fn drop(&mut self) {
        // SAFETY: the owner drops only after the GPU finished with it.
        unsafe { self.device.raw.destroy_sampler(self.raw, None) };
    }
}
