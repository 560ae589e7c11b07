//! The per-texture table the shaders read: entries written from the host
//! state, changed entries copied into the device-local table in queue order.

use ash::vk;
use citystream_cache::Placement;

use super::{stage_bytes, GpuTextureCache};
use crate::commands::Recording;
use crate::error::Result;
use crate::gpu_types::{TextureData, TEXTURE_NOT_SAMPLEABLE, TEXTURE_SAMPLEABLE};
use crate::image::memory_barrier;

impl GpuTextureCache {
    pub(super) fn mark_dirty(&mut self, texture: u32) {
        if let Some(flag) = self.dirty_flags.get_mut(texture as usize) {
            if !*flag {
                *flag = true;
                self.dirty.push(texture);
            }
        }
    }

    /// Records the copy of every changed table entry (runs of adjacent
    /// textures merged) from staging into the device-local table.
    pub(super) fn record_table_update(&mut self, rec: Recording<'_>, ticket: u64) -> Result<()> {
        let cmd = rec.raw();
        if self.dirty.is_empty() {
            return Ok(());
        }
        let mut dirty = std::mem::take(&mut self.dirty);
        dirty.sort_unstable();
        for &texture in &dirty {
            self.dirty_flags[texture as usize] = false;
        }
        let entry = std::mem::size_of::<TextureData>() as u64;
        // Runs of consecutive texture ids: (first id, count).
        let mut runs: Vec<(u32, u32)> = Vec::new();
        for &texture in &dirty {
            match runs.last_mut() {
                Some((first, count)) if *first + *count == texture => *count += 1,
                _ => runs.push((texture, 1)),
            }
        }
        let mut bytes: Vec<u8> = Vec::with_capacity(dirty.len() * entry as usize);
        for &(first, count) in &runs {
            bytes.extend_from_slice(bytemuck::cast_slice(
                &self.table[first as usize..(first + count) as usize],
            ));
        }
        let (source, base) = stage_bytes(
            &self.device,
            &mut self.staging,
            &mut self.retiring,
            &bytes,
            ticket,
            "texture table staging (oversize update)",
        )?;
        let mut offset = base;
        let regions: Vec<vk::BufferCopy> = runs
            .iter()
            .map(|&(first, count)| {
                let region = vk::BufferCopy {
                    src_offset: offset,
                    dst_offset: u64::from(first) * entry,
                    size: u64::from(count) * entry,
                };
                offset += region.size;
                region
            })
            .collect();
        let shader_stages = vk::PipelineStageFlags2::VERTEX_SHADER
            | vk::PipelineStageFlags2::FRAGMENT_SHADER
            | vk::PipelineStageFlags2::COMPUTE_SHADER;
        // Earlier frames' reads of the table finish before it changes.
        memory_barrier(
            &self.device,
            rec,
            (shader_stages, vk::AccessFlags2::SHADER_STORAGE_READ),
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
        );
        // SAFETY: cmd is recording outside rendering; the regions lie inside
        // the staging source and the table (ids come from the table's range).
        unsafe {
            self.device
                .raw()
                .cmd_copy_buffer(cmd, source, self.table_buffer.raw(), &regions)
        };
        memory_barrier(
            &self.device,
            rec,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
            (shader_stages, vk::AccessFlags2::SHADER_STORAGE_READ),
        );
        Ok(())
    }

    /// Writes a texture's table entry from its host state. The coarsest
    /// resident level bounds sampling (the loader starts at the 4×4 level, so
    /// coarser levels of uncompressed textures are never loaded), and the
    /// finest level such that it and every level up to that one are resident
    /// is the finest sampled.
    pub(super) fn publish(&mut self, texture: u32) {
        self.mark_dirty(texture);
        let slot = self.slots[texture as usize];
        let entry = &mut self.table[texture as usize];
        *entry = table_entry(*entry, slot.placement.as_ref(), slot.resident);
    }
}

/// The entry for a texture at `placement` whose levels `resident` holds
/// (bit m: level m). Without a place or a resident level in its chain the
/// entry is `previous` marked not sampleable.
fn table_entry(previous: TextureData, placement: Option<&Placement>, resident: u32) -> TextureData {
    let not_sampleable = TextureData {
        state: TEXTURE_NOT_SAMPLEABLE,
        ..previous
    };
    let Some(placement) = placement else {
        return not_sampleable;
    };
    let resident = resident & ((1u64 << placement.mip_count.min(32)) - 1) as u32;
    if resident == 0 {
        return not_sampleable;
    }
    let coarsest = 31 - resident.leading_zeros();
    let mut lowest = coarsest;
    while lowest > 0 && resident & (1 << (lowest - 1)) != 0 {
        lowest -= 1;
    }
    TextureData {
        uv_transform: [
            placement.uv.scale[0],
            placement.uv.scale[1],
            placement.uv.offset[0],
            placement.uv.offset[1],
        ],
        image: placement.image,
        layer: placement.layer,
        lowest_mip: lowest,
        state: TEXTURE_SAMPLEABLE,
        mip_count: coarsest + 1,
        ..TextureData::default()
    }
}

#[cfg(test)]
mod tests {
    use citystream_cache::{TexelFormat, UvTransform};

    use super::*;

    /// A 256² BC1 texture in region 1 of layer 3 of image 2, 9 levels.
    fn placement() -> Placement {
        Placement {
            key: 7,
            image: 2,
            format: TexelFormat::BC1,
            layer: 3,
            region: 1,
            assignment: 1,
            width: 256,
            height: 256,
            extent: 256,
            origin_x: 256,
            origin_y: 0,
            layer_size: 1024,
            mip_count: 9,
            uv: UvTransform {
                scale: [0.25, 0.25],
                offset: [0.25, 0.0],
            },
        }
    }

    #[test]
    fn an_entry_samples_the_finest_level_of_the_unbroken_run_up_to_the_coarsest() {
        // Levels 8, 7, 6 and 4: level 5 is missing, so 6 is the finest sampled.
        let entry = table_entry(TextureData::default(), Some(&placement()), 0b1_1101_0000);
        assert_eq!(entry.state, TEXTURE_SAMPLEABLE);
        assert_eq!((entry.lowest_mip, entry.mip_count), (6, 9));
        assert_eq!((entry.image, entry.layer), (2, 3));
        assert_eq!(entry.uv_transform, [0.25, 0.25, 0.25, 0.0]);
        let full = table_entry(TextureData::default(), Some(&placement()), 0b1_1111_1111);
        assert_eq!((full.lowest_mip, full.mip_count), (0, 9));
    }

    #[test]
    fn an_entry_without_a_place_or_a_level_of_its_chain_is_not_sampleable() {
        let previous = table_entry(TextureData::default(), Some(&placement()), 0b1_0000_0000);
        assert_eq!(previous.state, TEXTURE_SAMPLEABLE);
        let gone = table_entry(previous, None, 0b1_0000_0000);
        assert_eq!(gone.state, TEXTURE_NOT_SAMPLEABLE);
        assert_eq!(gone.layer, previous.layer, "the rest of the entry stays");
        // Bits beyond the placement's chain are not levels of it.
        let beyond = table_entry(TextureData::default(), Some(&placement()), 1 << 9);
        assert_eq!(beyond.state, TEXTURE_NOT_SAMPLEABLE);
        assert_eq!(
            table_entry(TextureData::default(), Some(&placement()), 0).state,
            TEXTURE_NOT_SAMPLEABLE
        );
    }
}
