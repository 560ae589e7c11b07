//! `embed_host`: a renderer that is not citystream's, streaming its
//! textures through citystream. It creates its own Vulkan instance and
//! device, its own pipelines, meshes and descriptor sets, and uses only the
//! engine's public API for the rest: `Device::from_host` over its handles,
//! `TextureStreamer` for Algorithm 1, and `citystream_host.glsl` in its
//! own fragment shaders. docs/EMBEDDING.md walks through it.
//!
//! ```text
//! cargo run --release -p citystream-engine --example embed_host [DATASET_DIR] [--out FILE.png] [--reference] [--sparse auto|on|off]
//! ```
//! Without a dataset it streams procedural textures from a `MipSource`
//! implemented below; with one it streams that dataset. It writes its last
//! frame as a PNG (`embed_host.png` in the working directory unless told
//! otherwise). `--reference` loads every texture fully before one frame
//! (the image streaming must converge to). `--sparse` chooses the texture
//! backing (docs/STRATEGIES.md): `auto` (sparse where the device has it, texture
//! arrays otherwise), `on` or `off`. `CITYSTREAM_VALIDATION=1` turns
//! on validation, `CITYSTREAM_VALIDATION=sync` synchronization validation
//! too; any message makes it exit non-zero.

use std::ffi::{c_void, CStr};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use anyhow::{bail, Context, Result};
use ash::vk;
use citystream_dataset::Dataset;
use citystream_engine::buffer::{Buffer, BufferDesc};
use citystream_engine::city::Camera;
use citystream_engine::commands::Recording;
use citystream_engine::device::{check_physical_device, required_features, TextureBacking};
use citystream_engine::gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};
use citystream_engine::gpu_allocator::MemoryLocation;
use citystream_engine::stream::{StreamConfig, StreamDescriptors, TextureStreamer};
use citystream_engine::target::{RenderTarget, COLOR_FORMAT, DEPTH_FORMAT};
use citystream_engine::{Device, HostAllocator, HostDevice};
use citystream_streaming::controller::{PolicyKind, PolicyOptions};
// Everything a MipSource's signatures name, from one module.
use citystream_streaming::source::{DatasetSource, MipChain, MipSource, SourceError, TextureFormat};
use glam::{DVec3, Mat4, Vec3};

const WIDTH: u32 = 320;
const HEIGHT: u32 = 200;
const FRAMES: u64 = 72;
const FRAMES_IN_FLIGHT: u32 = 2;

const VERT: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/embed_host_host_vert.spv"));
const FEEDBACK_FRAG: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/embed_host_host_feedback_frag.spv"));
const VISIBLE_FRAG: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/embed_host_host_visible_frag.spv"));
/// The visible pass for the texture-array backing: compiled with `CITYSTREAM_NO_SPARSE`.
const VISIBLE_FRAG_ARRAYS: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/embed_host_host_visible_frag_arrays.spv"));

// ---- The host's mip source: procedural façades --------------------------

/// `count` RGBA8 textures of `SIDE`² texels, bricks in a hue per texture;
/// every level is the level-0 pattern point-sampled, so levels agree.
struct Facades {
    count: u32,
}

impl Facades {
    const SIDE: u32 = 256;

    fn texel(texture: u32, x: u32, y: u32) -> [u8; 4] {
        let row = y / 16;
        let brick = (x + (row % 2) * 16) / 32;
        let mortar = y.is_multiple_of(16) || (x + (row % 2) * 16).is_multiple_of(32);
        let hue = (texture * 47 % 360) as f32;
        let shade = if mortar {
            0.35
        } else {
            0.75 + 0.2 * ((brick * 7 + row * 3) % 5) as f32 / 4.0
        };
        let (r, g, b) = hue_rgb(hue);
        [
            (r * shade * 255.0) as u8,
            (g * shade * 255.0) as u8,
            (b * shade * 255.0) as u8,
            255,
        ]
    }
}

fn hue_rgb(hue: f32) -> (f32, f32, f32) {
    let h = hue / 60.0;
    let x = 1.0 - (h % 2.0 - 1.0).abs();
    match h as u32 {
        0 => (1.0, x, 0.3),
        1 => (x, 1.0, 0.3),
        2 => (0.3, 1.0, x),
        3 => (0.3, x, 1.0),
        4 => (x, 0.3, 1.0),
        _ => (1.0, 0.3, x),
    }
}

impl MipSource for Facades {
    fn texture_count(&self) -> u32 {
        self.count
    }

    fn texture_format(&self, texture: u32) -> Result<TextureFormat, SourceError> {
        self.mip_chain(texture).map(|_| TextureFormat::Rgba8)
    }

    fn mip_chain(&self, texture: u32) -> Result<MipChain, SourceError> {
        if texture >= self.count {
            return Err(SourceError::UnknownTexture { texture });
        }
        Ok(MipChain {
            width: Self::SIDE,
            height: Self::SIDE,
            // Down to 4×4, the coarsest level the loader starts from.
            mip_count: Self::SIDE.ilog2() - 1,
        })
    }

    fn mip_len(&self, texture: u32, level: u32) -> Result<u64, SourceError> {
        let chain = self.mip_chain(texture)?;
        if level >= chain.mip_count {
            return Err(SourceError::UnknownLevel {
                texture,
                level,
                mip_count: chain.mip_count,
            });
        }
        let side = u64::from(Self::SIDE >> level);
        Ok(side * side * 4)
    }

    fn read_mip(&self, texture: u32, level: u32, buf: &mut [u8]) -> Result<(), SourceError> {
        self.check_buffer_len(texture, level, buf)?;
        let side = Self::SIDE >> level;
        for (i, texel) in buf.chunks_exact_mut(4).enumerate() {
            let (x, y) = (i as u32 % side, i as u32 / side);
            texel.copy_from_slice(&Self::texel(texture, x << level, y << level));
        }
        Ok(())
    }
}

// ---- The host's scene ----------------------------------------------------

/// The host's vertex: position, texture coordinate, mesh id.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct HostVertex {
    position: [f32; 3],
    uv: [f32; 2],
    mesh: u32,
}

/// What the host's shaders know of a mesh (set 0, binding 0).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct HostMesh {
    texture: u32,
    width: u32,
    height: u32,
    pad: u32,
}

struct Scene {
    vertices: Vec<HostVertex>,
    meshes: Vec<HostMesh>,
    colormap: Vec<[u8; 4]>,
    /// Camera at the start and at the end of the run.
    path: (Camera, Camera),
    /// Distance of the thickest fog.
    fog_distance: f32,
    /// Distance within which streaming weighs fragments more (w_d).
    foreground_distance: f32,
}

/// A street of façades, both sides, one texture each.
fn street(textures: u32) -> Scene {
    let mut vertices = Vec::new();
    let mut meshes = Vec::new();
    for t in 0..textures {
        let side = if t % 2 == 0 { -1.0 } else { 1.0 };
        let z0 = -((t / 2) as f32) * 24.0;
        let x = side * 12.0;
        let corners = [(z0, 0.0), (z0 - 22.0, 0.0), (z0 - 22.0, 18.0), (z0, 18.0)];
        let uv = [[0.0, 1.0], [2.0, 1.0], [2.0, 0.0], [0.0, 0.0]];
        for i in [0, 1, 2, 0, 2, 3] {
            let (z, y) = corners[i];
            vertices.push(HostVertex {
                position: [x, y, z],
                uv: uv[i],
                mesh: t,
            });
        }
        meshes.push(HostMesh {
            texture: t,
            width: Facades::SIDE,
            height: Facades::SIDE,
            pad: 0,
        });
    }
    let colormap = (0..textures)
        .map(|t| {
            let (r, g, b) = hue_rgb((t * 47 % 360) as f32);
            [(r * 170.0) as u8, (g * 170.0) as u8, (b * 170.0) as u8, 255]
        })
        .collect();
    let camera = |z: f32| Camera {
        eye: DVec3::new(0.0, 4.0, f64::from(z)),
        target: DVec3::new(0.0, 6.0, f64::from(z) - 40.0),
        fov_y: 60f32.to_radians(),
        near: 0.1,
    };
    Scene {
        vertices,
        meshes,
        colormap,
        path: (camera(20.0), camera(-10.0)),
        fog_distance: 400.0,
        foreground_distance: 60.0,
    }
}

/// A dataset's meshes as host geometry (one vertex per index), viewed
/// from above one corner of its bounds.
fn dataset_scene(dataset: &Dataset) -> Result<Scene> {
    let scene = &dataset.scene;
    let mut vertices = Vec::new();
    let mut meshes = Vec::new();
    for (id, mesh) in scene.meshes.iter().enumerate() {
        let info = dataset.textures.info(mesh.texture)?;
        // This host draws in the scene's frame: a mesh at a local origin moves there.
        let offset = scene.offset_of(mesh);
        let first = mesh.first_index as usize;
        let indices = scene
            .indices
            .get(first..first + mesh.index_count as usize)
            .with_context(|| format!("mesh {id} indexes outside the dataset"))?;
        for &index in indices {
            let v = (mesh.first_vertex + index) as usize;
            let (Some(p), Some(uv)) = (scene.positions.get(v), scene.uvs.get(v)) else {
                bail!("mesh {id} refers to vertex {v}, outside the dataset");
            };
            vertices.push(HostVertex {
                position: std::array::from_fn(|a| (offset[a] + f64::from(p[a])) as f32),
                uv: *uv,
                mesh: id as u32,
            });
        }
        meshes.push(HostMesh {
            texture: mesh.texture,
            width: info.width(),
            height: info.height(),
            pad: 0,
        });
    }
    let (min, max) = (Vec3::from(scene.bounds.min), Vec3::from(scene.bounds.max));
    let extent = (max - min).max_element().max(1.0);
    let centre = (min + max) * 0.5;
    let camera = |t: f32| Camera {
        eye: (centre + Vec3::new(extent * (0.6 - 0.2 * t), extent * 0.35, extent * 0.6)).as_dvec3(),
        target: centre.as_dvec3(),
        fov_y: 60f32.to_radians(),
        near: extent * 1e-3,
    };
    Ok(Scene {
        vertices,
        meshes,
        colormap: dataset.colormap.colours().to_vec(),
        path: (camera(0.0), camera(1.0)),
        fog_distance: extent * 4.0,
        foreground_distance: 200.0,
    })
}

// ---- The host's Vulkan objects -------------------------------------------

static VALIDATION_MESSAGES: AtomicUsize = AtomicUsize::new(0);

unsafe extern "system" fn on_validation_message(
    _severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    _types: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    _user: *mut c_void,
) -> vk::Bool32 {
    VALIDATION_MESSAGES.fetch_add(1, Ordering::SeqCst);
    // SAFETY: the layer passes valid callback data for the duration of the call.
    let message = unsafe { data.as_ref() }
        .and_then(|d| (!d.p_message.is_null()).then(|| unsafe { CStr::from_ptr(d.p_message) }))
        .map(|m| m.to_string_lossy().into_owned())
        .unwrap_or_default();
    eprintln!("[validation] {message}");
    vk::FALSE
}

/// The host's instance and device, made the way any Vulkan renderer makes them.
struct HostVulkan {
    entry: ash::Entry,
    instance: ash::Instance,
    messenger: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    physical: vk::PhysicalDevice,
    device: ash::Device,
    queue_family: u32,
    /// The texture backing the device was created with the features of.
    backing: TextureBacking,
}

impl HostVulkan {
    /// `backing`: the one to take, or `None` for sparse where a device has it and
    /// texture arrays otherwise.
    fn new(validation: &str, backing: Option<TextureBacking>) -> Result<Self> {
        // SAFETY: loads the system Vulkan loader.
        let entry = unsafe { ash::Entry::load() }.context("loading Vulkan")?;
        let validate = matches!(validation, "1" | "sync");
        let layers = [c"VK_LAYER_KHRONOS_validation".as_ptr()];
        let mut extensions = Vec::new();
        if validate {
            extensions.push(ash::ext::debug_utils::NAME.as_ptr());
        }
        if validation == "sync" {
            extensions.push(ash::ext::validation_features::NAME.as_ptr());
        }
        let app = vk::ApplicationInfo::default()
            .application_name(c"embed_host")
            .api_version(vk::API_VERSION_1_3);
        let enables = [vk::ValidationFeatureEnableEXT::SYNCHRONIZATION_VALIDATION];
        let mut features = vk::ValidationFeaturesEXT::default().enabled_validation_features(&enables);
        let mut info = vk::InstanceCreateInfo::default()
            .application_info(&app)
            .enabled_extension_names(&extensions);
        if validate {
            info = info.enabled_layer_names(&layers);
        }
        if validation == "sync" {
            info = info.push_next(&mut features);
        }
        // SAFETY: every pointer in `info` is alive for the call.
        let instance = unsafe { entry.create_instance(&info, None) }.context("creating the host's instance")?;
        let messenger = if validate {
            let loader = ash::ext::debug_utils::Instance::new(&entry, &instance);
            let info = vk::DebugUtilsMessengerCreateInfoEXT::default()
                .message_severity(
                    vk::DebugUtilsMessageSeverityFlagsEXT::ERROR | vk::DebugUtilsMessageSeverityFlagsEXT::WARNING,
                )
                .message_type(vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION)
                .pfn_user_callback(Some(on_validation_message));
            // SAFETY: the callback is a plain function; the messenger is destroyed in Drop.
            let messenger = unsafe { loader.create_debug_utils_messenger(&info, None) }?;
            Some((loader, messenger))
        } else {
            None
        };
        // The first physical device that has what citystream needs, sparse
        // residency first.
        // SAFETY: plain enumeration on a live instance.
        let physicals = unsafe { instance.enumerate_physical_devices() }?;
        let wanted = match backing {
            Some(backing) => vec![backing],
            None => vec![TextureBacking::Sparse, TextureBacking::Arrays],
        };
        let (physical, queue_family, backing) = wanted
            .iter()
            .find_map(|&backing| {
                physicals
                    .iter()
                    .find_map(|&p| match check_physical_device(&instance, p, backing) {
                        (missing, Some(family)) if missing.is_empty() => Some((p, family, backing)),
                        _ => None,
                    })
            })
            .with_context(|| format!("no Vulkan device has what citystream needs for {wanted:?} (BC, Vulkan 1.3)"))?;
        // The host's own features would be merged into these.
        let required = required_features(backing);
        let mut vk12 = required.vulkan12;
        let mut vk13 = required.vulkan13;
        let priorities = [1.0];
        let queues = [vk::DeviceQueueCreateInfo::default()
            .queue_family_index(queue_family)
            .queue_priorities(&priorities)];
        let info = vk::DeviceCreateInfo::default()
            .queue_create_infos(&queues)
            .enabled_features(&required.core)
            .push_next(&mut vk12)
            .push_next(&mut vk13);
        // SAFETY: `physical` came from this instance; `info` is alive for the call.
        let device = unsafe { instance.create_device(physical, &info, None) }.context("creating the host's device")?;
        Ok(Self {
            entry,
            instance,
            messenger,
            physical,
            device,
            queue_family,
            backing,
        })
    }
}

impl Drop for HostVulkan {
    fn drop(&mut self) {
        // SAFETY: the engine's Device and everything on it were dropped first
        // (see `run`), so nothing uses the device any more.
        unsafe {
            let _ = self.device.device_wait_idle();
            self.device.destroy_device(None);
            if let Some((loader, messenger)) = self.messenger.take() {
                loader.destroy_debug_utils_messenger(messenger, None);
            }
            self.instance.destroy_instance(None);
        }
    }
}

/// The host's two pipelines and their layout; set 0 is the host's own (its
/// mesh table), set 1 the streamer's.
struct HostPipelines {
    device: ash::Device,
    host_set_layout: vk::DescriptorSetLayout,
    layout: vk::PipelineLayout,
    pool: vk::DescriptorPool,
    sets: [vk::DescriptorSet; 2],
    feedback: vk::Pipeline,
    visible: vk::Pipeline,
}

impl HostPipelines {
    fn new(
        device: &ash::Device,
        host_meshes: vk::Buffer,
        streamed: &StreamDescriptors,
        backing: TextureBacking,
    ) -> Result<Self> {
        let fragment = vk::ShaderStageFlags::FRAGMENT;
        let host_bindings = [vk::DescriptorSetLayoutBinding::default()
            .binding(0)
            .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
            .descriptor_count(1)
            .stage_flags(fragment)];
        // SAFETY (this block and the ones below): every create info points at
        // live data for the call; handles come from `device`.
        let host_set_layout = unsafe {
            device.create_descriptor_set_layout(
                &vk::DescriptorSetLayoutCreateInfo::default().bindings(&host_bindings),
                None,
            )?
        };
        let set_layouts = [host_set_layout, streamed.layout()];
        let push = [vk::PushConstantRange::default()
            .stage_flags(vk::ShaderStageFlags::VERTEX | fragment)
            .size(80)];
        let layout = unsafe {
            device.create_pipeline_layout(
                &vk::PipelineLayoutCreateInfo::default()
                    .set_layouts(&set_layouts)
                    .push_constant_ranges(&push),
                None,
            )?
        };
        let sizes = [vk::DescriptorPoolSize::default()
            .ty(vk::DescriptorType::STORAGE_BUFFER)
            .descriptor_count(1)];
        let pool = unsafe {
            device.create_descriptor_pool(
                &vk::DescriptorPoolCreateInfo::default().max_sets(1).pool_sizes(&sizes),
                None,
            )?
        };
        let host_set = unsafe {
            device.allocate_descriptor_sets(
                &vk::DescriptorSetAllocateInfo::default()
                    .descriptor_pool(pool)
                    .set_layouts(&[host_set_layout]),
            )?
        }[0];
        let mesh_table = [vk::DescriptorBufferInfo::default()
            .buffer(host_meshes)
            .range(vk::WHOLE_SIZE)];
        let write = vk::WriteDescriptorSet::default()
            .dst_set(host_set)
            .dst_binding(0)
            .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
            .buffer_info(&mesh_table);
        unsafe { device.update_descriptor_sets(&[write], &[]) };
        let feedback = graphics_pipeline(device, layout, FEEDBACK_FRAG)?;
        // Sampling sparse images needs shaderResourceResidency; texture arrays do not.
        let visible_frag = match backing {
            TextureBacking::Sparse => VISIBLE_FRAG,
            TextureBacking::Arrays => VISIBLE_FRAG_ARRAYS,
        };
        let visible = graphics_pipeline(device, layout, visible_frag)?;
        Ok(Self {
            device: device.clone(),
            host_set_layout,
            layout,
            pool,
            sets: [host_set, streamed.set()],
            feedback,
            visible,
        })
    }

    fn draw(&self, cmd: vk::CommandBuffer, pipeline: vk::Pipeline, push: &[f32; 20], vertices: &Buffer, count: u32) {
        // SAFETY: cmd is recording inside rendering; every handle is alive.
        unsafe {
            self.device
                .cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, pipeline);
            self.device
                .cmd_bind_descriptor_sets(cmd, vk::PipelineBindPoint::GRAPHICS, self.layout, 0, &self.sets, &[]);
            self.device.cmd_push_constants(
                cmd,
                self.layout,
                vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT,
                0,
                bytemuck::cast_slice(push),
            );
            self.device.cmd_bind_vertex_buffers(cmd, 0, &[vertices.raw()], &[0]);
            self.device.cmd_draw(cmd, count, 1, 0, 0);
        }
    }
}

impl Drop for HostPipelines {
    fn drop(&mut self) {
        // SAFETY: the owner waited for the GPU before dropping.
        unsafe {
            self.device.destroy_pipeline(self.feedback, None);
            self.device.destroy_pipeline(self.visible, None);
            self.device.destroy_descriptor_pool(self.pool, None);
            self.device.destroy_pipeline_layout(self.layout, None);
            self.device.destroy_descriptor_set_layout(self.host_set_layout, None);
        }
    }
}

fn graphics_pipeline(device: &ash::Device, layout: vk::PipelineLayout, fragment: &[u8]) -> Result<vk::Pipeline> {
    let module = |bytes: &[u8]| -> Result<vk::ShaderModule> {
        let words = ash::util::read_spv(&mut std::io::Cursor::new(bytes))?;
        // SAFETY: valid SPIR-V compiled and checked by the build script.
        Ok(unsafe { device.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&words), None)? })
    };
    let (vert, frag) = (module(VERT)?, module(fragment)?);
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
    let bindings = [vk::VertexInputBindingDescription::default()
        .stride(std::mem::size_of::<HostVertex>() as u32)
        .input_rate(vk::VertexInputRate::VERTEX)];
    let attributes = [
        vk::VertexInputAttributeDescription::default()
            .location(0)
            .format(vk::Format::R32G32B32_SFLOAT)
            .offset(0),
        vk::VertexInputAttributeDescription::default()
            .location(1)
            .format(vk::Format::R32G32_SFLOAT)
            .offset(12),
        vk::VertexInputAttributeDescription::default()
            .location(2)
            .format(vk::Format::R32_UINT)
            .offset(20),
    ];
    let vertex_input = vk::PipelineVertexInputStateCreateInfo::default()
        .vertex_binding_descriptions(&bindings)
        .vertex_attribute_descriptions(&attributes);
    let assembly = vk::PipelineInputAssemblyStateCreateInfo::default().topology(vk::PrimitiveTopology::TRIANGLE_LIST);
    let viewport = vk::PipelineViewportStateCreateInfo::default()
        .viewport_count(1)
        .scissor_count(1);
    let raster = vk::PipelineRasterizationStateCreateInfo::default()
        .polygon_mode(vk::PolygonMode::FILL)
        .cull_mode(vk::CullModeFlags::NONE)
        .line_width(1.0);
    let multisample =
        vk::PipelineMultisampleStateCreateInfo::default().rasterization_samples(vk::SampleCountFlags::TYPE_1);
    let depth = vk::PipelineDepthStencilStateCreateInfo::default()
        .depth_test_enable(true)
        .depth_write_enable(true)
        // The engine's camera and targets use reversed depth (cleared to 0, nearer is greater).
        .depth_compare_op(vk::CompareOp::GREATER);
    let blend_attachments =
        [vk::PipelineColorBlendAttachmentState::default().color_write_mask(vk::ColorComponentFlags::RGBA)];
    let blend = vk::PipelineColorBlendStateCreateInfo::default().attachments(&blend_attachments);
    let dynamic_states = [vk::DynamicState::VIEWPORT, vk::DynamicState::SCISSOR];
    let dynamic = vk::PipelineDynamicStateCreateInfo::default().dynamic_states(&dynamic_states);
    let formats = [COLOR_FORMAT];
    let mut rendering = vk::PipelineRenderingCreateInfo::default()
        .color_attachment_formats(&formats)
        .depth_attachment_format(DEPTH_FORMAT);
    let info = vk::GraphicsPipelineCreateInfo::default()
        .stages(&stages)
        .vertex_input_state(&vertex_input)
        .input_assembly_state(&assembly)
        .viewport_state(&viewport)
        .rasterization_state(&raster)
        .multisample_state(&multisample)
        .depth_stencil_state(&depth)
        .color_blend_state(&blend)
        .dynamic_state(&dynamic)
        .layout(layout)
        .push_next(&mut rendering);
    // SAFETY: `info` points at live data; the modules are destroyed after creation.
    let pipeline = unsafe { device.create_graphics_pipelines(vk::PipelineCache::null(), &[info], None) };
    unsafe {
        device.destroy_shader_module(vert, None);
        device.destroy_shader_module(frag, None);
    }
    let pipelines = pipeline.map_err(|(_, e)| e)?;
    Ok(pipelines[0])
}

/// One command pool and buffer per frame in flight.
struct FrameCommands {
    device: ash::Device,
    pools: Vec<(vk::CommandPool, vk::CommandBuffer)>,
}

impl FrameCommands {
    fn new(device: &ash::Device, family: u32, count: u32) -> Result<Self> {
        let mut pools = Vec::new();
        for _ in 0..count {
            // SAFETY: valid create infos on a live device.
            let pool = unsafe {
                device.create_command_pool(&vk::CommandPoolCreateInfo::default().queue_family_index(family), None)?
            };
            let cmd = unsafe {
                device.allocate_command_buffers(
                    &vk::CommandBufferAllocateInfo::default()
                        .command_pool(pool)
                        .level(vk::CommandBufferLevel::PRIMARY)
                        .command_buffer_count(1),
                )?[0]
            };
            pools.push((pool, cmd));
        }
        Ok(Self {
            device: device.clone(),
            pools,
        })
    }

    /// Resets and begins slot `slot`'s buffer: the streamer's `begin_frame`
    /// already waited until the frame that last used it completed.
    fn begin(&self, slot: u32) -> Result<vk::CommandBuffer> {
        let (pool, cmd) = self.pools[slot as usize];
        // SAFETY: the slot's previous submission completed (see above).
        unsafe {
            self.device
                .reset_command_pool(pool, vk::CommandPoolResetFlags::empty())?;
            self.device.begin_command_buffer(
                cmd,
                &vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
            )?;
        }
        Ok(cmd)
    }
}

impl Drop for FrameCommands {
    fn drop(&mut self) {
        for &(pool, _) in &self.pools {
            // SAFETY: the owner waited for the GPU before dropping.
            unsafe { self.device.destroy_command_pool(pool, None) };
        }
    }
}

// ---- The frame loop -------------------------------------------------------

struct Options {
    dataset: Option<PathBuf>,
    out: PathBuf,
    reference: bool,
    validation: String,
    /// `--sparse`: `None` for `auto`.
    backing: Option<TextureBacking>,
}

fn parse_args() -> Result<Options> {
    let mut options = Options {
        dataset: None,
        out: PathBuf::from("embed_host.png"),
        reference: false,
        validation: std::env::var("CITYSTREAM_VALIDATION").unwrap_or_default(),
        backing: None,
    };
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--out" => options.out = args.next().context("--out needs a file name")?.into(),
            "--reference" => options.reference = true,
            "--sparse" => {
                options.backing = match args.next().as_deref() {
                    Some("auto") => None,
                    Some("on") => Some(TextureBacking::Sparse),
                    Some("off") => Some(TextureBacking::Arrays),
                    other => bail!("--sparse takes auto, on or off, not {other:?}"),
                }
            }
            "-h" | "--help" => {
                println!("usage: embed_host [DATASET_DIR] [--out FILE.png] [--reference] [--sparse auto|on|off]");
                std::process::exit(0);
            }
            flag if flag.starts_with('-') => bail!("unknown option {flag:?} (try --help)"),
            dir => options.dataset = Some(dir.into()),
        }
    }
    Ok(options)
}

fn main() -> Result<()> {
    let options = parse_args()?;
    run(&options)?;
    println!("wrote {}", options.out.display());
    Ok(())
}

fn run(options: &Options) -> Result<()> {
    let host = HostVulkan::new(&options.validation, options.backing)?;
    {
        // The host shares its allocator with the engine.
        let allocator = Arc::new(Mutex::new(Allocator::new(&AllocatorCreateDesc {
            instance: host.instance.clone(),
            device: host.device.clone(),
            physical_device: host.physical,
            debug_settings: Default::default(),
            buffer_device_address: false,
            allocation_sizes: Default::default(),
        })?));
        // SAFETY: the handles are the host's live objects, created with
        // `required_features` and a queue of `queue_family`; this thread is
        // the only one that submits.
        let device = Arc::new(unsafe {
            Device::from_host(HostDevice {
                entry: host.entry.clone(),
                instance: host.instance.handle(),
                physical_device: host.physical,
                device: host.device.handle(),
                queue: host.device.get_device_queue(host.queue_family, 0),
                queue_family: host.queue_family,
                allocator: HostAllocator::Shared(Arc::clone(&allocator)),
                debug_utils: host.messenger.is_some(),
                backing: host.backing,
            })
        }?);
        match &options.dataset {
            Some(dir) => {
                let dataset = Arc::new(Dataset::open(dir).with_context(|| format!("opening {}", dir.display()))?);
                let scene = dataset_scene(&dataset)?;
                render(&host, &device, DatasetSource::new(dataset), scene, options)?;
            }
            None => {
                let textures = 16;
                render(&host, &device, Facades { count: textures }, street(textures), options)?;
            }
        }
        drop(device);
        drop(allocator);
    }
    let messages = VALIDATION_MESSAGES.load(Ordering::SeqCst);
    drop(host);
    if messages > 0 {
        bail!("{messages} validation message(s)");
    }
    Ok(())
}

fn render<S: MipSource + 'static>(
    host: &HostVulkan,
    device: &Arc<Device>,
    source: S,
    scene: Scene,
    options: &Options,
) -> Result<()> {
    let raw = &host.device;
    let target = RenderTarget::new(device, WIDTH, HEIGHT)?;
    let feedback_target = RenderTarget::new(device, WIDTH / 4, HEIGHT / 4)?;
    let mesh_textures: Vec<u32> = scene.meshes.iter().map(|m| m.texture).collect();
    let mut streamer = TextureStreamer::new(
        device,
        source,
        mesh_textures,
        &scene.colormap,
        PolicyKind::Adaptive.build(&PolicyOptions::default())?,
        &StreamConfig {
            frames_in_flight: FRAMES_IN_FLIGHT,
            layer_size: 2048,
            memory_budget_bytes: 256 << 20,
            fragment_area: 16.0,
            deterministic: true,
            ..StreamConfig::default()
        },
    )?;
    let host_buffer = |bytes: &[u8], usage: vk::BufferUsageFlags, name: &str| -> Result<Buffer> {
        let mut buffer = Buffer::new(
            device,
            BufferDesc {
                size: bytes.len().max(4) as u64,
                usage,
                location: MemoryLocation::CpuToGpu,
            },
            name,
        )?;
        buffer.write(0, bytes)?;
        Ok(buffer)
    };
    let vertices = host_buffer(
        bytemuck::cast_slice(&scene.vertices),
        vk::BufferUsageFlags::VERTEX_BUFFER,
        "host vertices",
    )?;
    let meshes = host_buffer(
        bytemuck::cast_slice(&scene.meshes),
        vk::BufferUsageFlags::STORAGE_BUFFER,
        "host meshes",
    )?;
    // The streamer's bindings as one set, read by the host's fragment shaders.
    let streamed = streamer.create_descriptors(vk::ShaderStageFlags::FRAGMENT)?;
    let pipelines = HostPipelines::new(raw, meshes.raw(), &streamed, host.backing)?;
    let commands = FrameCommands::new(raw, host.queue_family, FRAMES_IN_FLIGHT)?;
    // Dropped first, on success and on error alike: nothing above is
    // destroyed while a submitted frame may still use it.
    let _wait_before_teardown = WaitIdleOnDrop(Arc::clone(device));
    let vertex_count = scene.vertices.len() as u32;

    if options.reference {
        // Everything at full resolution, then one frame.
        let all: Vec<(u32, u32)> = scene.meshes.iter().map(|m| (m.texture, 0)).collect();
        let mut setup = citystream_engine::commands::CommandContext::new(device, "reference load")?;
        streamer.load_now(&all, &mut setup)?;
    }
    let frames = if options.reference { 1 } else { FRAMES };
    let mut last = 0;
    for frame in 0..frames {
        // Dolly down the street for two thirds of the run, then hold still.
        let t = (frame as f32 / (FRAMES as f32 * 2.0 / 3.0)).min(1.0);
        let t = if options.reference { 1.0 } else { t };
        let (from, to) = scene.path;
        let camera = Camera {
            eye: from.eye.lerp(to.eye, f64::from(t)),
            target: from.target.lerp(to.target, f64::from(t)),
            ..from
        };
        let mut begun = streamer.begin_frame()?;
        let cmd = commands.begin(begun.slot())?;
        // SAFETY: `cmd` was just begun on the engine's device; it stays recording, on this
        // thread, until `end_command_buffer` below, after the last use of `rec`.
        let rec = unsafe { Recording::from_raw(cmd) };
        streamer.record_uploads(&mut begun, rec)?;
        // Both passes' push constants: this frame's camera, the scene's distances and a
        // level-of-detail offset.
        let push_with_lod_offset = |lod_offset: f32| {
            push(
                camera.view_projection(WIDTH as f32 / HEIGHT as f32, 0.0),
                lod_offset,
                scene.foreground_distance,
                scene.fog_distance,
            )
        };
        // The host's feedback pass, a quarter of the resolution per axis.
        let feedback_push = push_with_lod_offset(2.0);
        feedback_target.begin(device, rec, [0.0; 4]);
        pipelines.draw(cmd, pipelines.feedback, &feedback_push, &vertices, vertex_count);
        // SAFETY: rendering was begun by `feedback_target.begin` in this buffer.
        unsafe { raw.cmd_end_rendering(cmd) };
        streamer.record_feedback_resolve(&mut begun, rec)?;
        // The host's visible pass.
        let visible_push = push_with_lod_offset(0.0);
        target.begin(device, rec, [0.55, 0.7, 0.9, 1.0]);
        pipelines.draw(cmd, pipelines.visible, &visible_push, &vertices, vertex_count);
        target.end_and_copy(device, rec);
        // SAFETY: cmd is recording.
        unsafe { raw.end_command_buffer(cmd) }?;
        // The host's measured frame latency would go here; a fixed 8 ms keeps
        // the run reproducible.
        last = begun.index();
        let submit = streamer.end_frame(begun, 8.0)?;
        let waits = submit.wait_infos();
        let signals = [submit.signal_info()];
        let buffers = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd)];
        let info = vk::SubmitInfo2::default()
            .wait_semaphore_infos(&waits)
            .command_buffer_infos(&buffers)
            .signal_semaphore_infos(&signals);
        {
            // The engine submits to the same queue: take its lock.
            let queue = device.queue();
            // SAFETY: the queue is locked; every handle in `info` is alive.
            unsafe { raw.queue_submit2(*queue, &[info], vk::Fence::null()) }?;
        }
    }
    streamer.wait_for_frame(last)?;
    let pixels = target.read_pixels()?;
    pixels
        .save(&options.out)
        .with_context(|| format!("writing {}", options.out.display()))?;
    Ok(())
}

/// Waits for the GPU when dropped.
struct WaitIdleOnDrop(Arc<Device>);

impl Drop for WaitIdleOnDrop {
    fn drop(&mut self) {
        // Device loss leaves nothing better to do than tear down anyway.
        let _ = self.0.wait_idle();
    }
}

/// The host's push constants: view-projection, then (log2 of the visible
/// resolution over the pass's, per axis; foreground distance; fog distance; 0).
fn push(view_proj: Mat4, lod_offset: f32, foreground: f32, fog: f32) -> [f32; 20] {
    let mut values = [0.0; 20];
    values[..16].copy_from_slice(&view_proj.to_cols_array());
    values[16] = lod_offset;
    values[17] = foreground;
    values[18] = fog;
    values
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The example as `make test` runs it: synchronization validation on,
    /// no message; after streaming, the image matches the fully resident one.
    #[test]
    fn streams_to_the_fully_resident_image_without_validation_messages() -> Result<()> {
        streams_to_the_fully_resident_image(Some(TextureBacking::Sparse))
    }

    /// The same host on texture arrays: its device without the sparse features, its
    /// visible shader without sparse sampling.
    #[test]
    fn streams_into_texture_arrays_as_well() -> Result<()> {
        streams_to_the_fully_resident_image(Some(TextureBacking::Arrays))
    }

    fn streams_to_the_fully_resident_image(backing: Option<TextureBacking>) -> Result<()> {
        let name = format!("embed_host_test_{}_{backing:?}", std::process::id());
        let dir = std::env::temp_dir().join(name);
        std::fs::create_dir_all(&dir)?;
        let streamed = dir.join("streamed.png");
        let reference = dir.join("reference.png");
        for (out, reference_run) in [(&streamed, false), (&reference, true)] {
            run(&Options {
                dataset: None,
                out: out.clone(),
                reference: reference_run,
                validation: "sync".into(),
                backing,
            })?;
        }
        let (a, b) = (image::open(&streamed)?.to_rgba8(), image::open(&reference)?.to_rgba8());
        let close = a
            .pixels()
            .zip(b.pixels())
            .filter(|(p, q)| p.0.iter().zip(q.0).all(|(x, y)| x.abs_diff(y) <= 3))
            .count();
        let total = (WIDTH * HEIGHT) as usize;
        // A handful of pixels at texture-region edges may filter differently.
        if close * 1000 < total * 995 {
            bail!(
                "only {close} of {total} pixels match the fully resident image ({} vs {})",
                streamed.display(),
                reference.display()
            );
        }
        // The street is textured, not just the colormap: bricks differ from mortar.
        let distinct: std::collections::HashSet<[u8; 4]> = a.pixels().map(|p| p.0).collect();
        if distinct.len() < 64 {
            bail!("the streamed image has only {} distinct colours", distinct.len());
        }
        std::fs::remove_dir_all(&dir)?;
        Ok(())
    }
}
