//! The streamer's descriptor set for a host's own pipelines: the layout, a
//! pool and the one set, written once (see `docs/EMBEDDING.md`, "Shaders").

use std::sync::Arc;

use ash::vk;

use crate::device::Device;
use crate::error::{Result, VkResultExt};
use crate::pipeline::{write_descriptor_set, DescriptorResource};

/// Everything `citystream_host.glsl` reaches, as one descriptor set a host
/// binds at the set index its shaders give `CITYSTREAM_SET`. Made by
/// [`TextureStreamer::create_descriptors`](super::TextureStreamer::create_descriptors);
/// put [`layout`](Self::layout) into your pipeline layout and bind
/// [`set`](Self::set). Drop it after the last frame that bound the set
/// completed and before the streamer (whose resources it names).
#[derive(Debug)]
pub struct StreamDescriptors {
    device: Arc<Device>,
    layout: vk::DescriptorSetLayout,
    pool: vk::DescriptorPool,
    set: vk::DescriptorSet,
}

impl StreamDescriptors {
    /// Creates the layout (every binding visible to `stages`), a pool for one
    /// set, and the set with `bindings` written.
    pub(crate) fn new(
        device: &Arc<Device>,
        bindings: &[(u32, vk::DescriptorType, DescriptorResource)],
        stages: vk::ShaderStageFlags,
    ) -> Result<Self> {
        let layout_bindings: Vec<_> = bindings
            .iter()
            .map(|(binding, ty, resource)| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(*binding)
                    .descriptor_type(*ty)
                    .descriptor_count(resource.count())
                    .stage_flags(stages)
            })
            .collect();
        let raw = device.raw();
        // SAFETY: valid create info on a live device.
        let layout = unsafe {
            raw.create_descriptor_set_layout(
                &vk::DescriptorSetLayoutCreateInfo::default().bindings(&layout_bindings),
                None,
            )
        }
        .vk("vkCreateDescriptorSetLayout")?;
        device.set_name(layout, "citystream host set layout");
        let sizes: Vec<_> = bindings
            .iter()
            .map(|(_, ty, resource)| vk::DescriptorPoolSize {
                ty: *ty,
                descriptor_count: resource.count(),
            })
            .collect();
        let pool_info = vk::DescriptorPoolCreateInfo::default().max_sets(1).pool_sizes(&sizes);
        // SAFETY: valid create info on a live device.
        let pool = match unsafe { raw.create_descriptor_pool(&pool_info, None) }.vk("vkCreateDescriptorPool") {
            Ok(pool) => pool,
            Err(error) => {
                // SAFETY: created above and not used by anything yet.
                unsafe { raw.destroy_descriptor_set_layout(layout, None) };
                return Err(error);
            }
        };
        device.set_name(pool, "citystream host descriptor pool");
        // From here on `Drop` destroys the pool and the layout.
        let mut descriptors = Self {
            device: Arc::clone(device),
            layout,
            pool,
            set: vk::DescriptorSet::null(),
        };
        let layouts = [layout];
        let allocate = vk::DescriptorSetAllocateInfo::default()
            .descriptor_pool(pool)
            .set_layouts(&layouts);
        // SAFETY: the pool has room for this one set of this layout.
        descriptors.set = unsafe { raw.allocate_descriptor_sets(&allocate) }.vk("vkAllocateDescriptorSets")?[0];
        let resources: Vec<(u32, DescriptorResource)> = bindings
            .iter()
            .map(|&(binding, _, resource)| (binding, resource))
            .collect();
        write_descriptor_set(device, descriptors.set, &resources);
        Ok(descriptors)
    }

    /// The set layout, for the host's pipeline layout.
    pub fn layout(&self) -> vk::DescriptorSetLayout {
        self.layout
    }

    /// The written set, for `vkCmdBindDescriptorSets`.
    pub fn set(&self) -> vk::DescriptorSet {
        self.set
    }
}

impl Drop for StreamDescriptors {
    fn drop(&mut self) {
        let raw = self.device.raw();
        // SAFETY: the owner drops this after the last frame that bound the set
        // completed; destroying the pool frees the set.
        unsafe {
            raw.destroy_descriptor_pool(self.pool, None);
            raw.destroy_descriptor_set_layout(self.layout, None);
        }
    }
}
