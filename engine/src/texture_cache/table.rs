//! The per-texture table the shaders read: [`TextureTable`], the host
//! state (each texture's place and levels) and the entries written from it,
//! is Vulkan-free; the changed entries are copied into the device-local
//! table in queue order.

use ash::vk;
use citystream_cache::Placement;

use super::GpuTextureCache;
use crate::commands::Recording;
use crate::error::Result;
use crate::gpu_types::{TextureData, TEXTURE_NOT_SAMPLEABLE, TEXTURE_SAMPLEABLE};
use crate::image::memory_barrier;

/// Per-texture host state behind the GPU table.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct TextureSlot {
    pub(super) placement: Option<Placement>,
    /// Bit m set: mip m is resident (copied and not evicted).
    pub(super) resident: u32,
    /// Bit m set: mip m is staged in this cycle, not yet recorded.
    pub(super) pending: u32,
}

/// The host side of the table: each texture's place and levels, the
/// entries the shaders will read, and which entries changed since the last
/// copy to the device.
#[derive(Debug)]
pub(super) struct TextureTable {
    slots: Vec<TextureSlot>,
    entries: Vec<TextureData>,
    /// Per texture, the finest level its entry ever let the shaders sample
    /// (`u32::MAX`: never sampleable): a texture now coarser than this lost
    /// levels to the budget.
    finest_published: Vec<u32>,
    /// Textures whose entry changed since the last table copy.
    dirty: Vec<u32>,
    dirty_flags: Vec<bool>,
}

impl TextureTable {
    /// A table of `textures` entries, none placed or sampleable.
    pub(super) fn new(textures: usize) -> Self {
        Self {
            slots: vec![TextureSlot::default(); textures],
            entries: vec![TextureData::default(); textures],
            finest_published: vec![u32::MAX; textures],
            dirty: Vec::new(),
            dirty_flags: vec![false; textures],
        }
    }

    /// Every entry, in texture id order.
    pub(super) fn entries(&self) -> &[TextureData] {
        &self.entries
    }

    /// The entry the shaders see for `texture`.
    pub(super) fn entry(&self, texture: u32) -> Option<&TextureData> {
        self.entries.get(texture as usize)
    }

    /// Every texture's host state, in id order.
    pub(super) fn slots(&self) -> &[TextureSlot] {
        &self.slots
    }

    /// `texture`'s host state (`None` outside the table).
    pub(super) fn slot(&self, texture: u32) -> Option<TextureSlot> {
        self.slots.get(texture as usize).copied()
    }

    /// `texture`'s host state, which must be in the table.
    pub(super) fn slot_mut(&mut self, texture: u32) -> &mut TextureSlot {
        &mut self.slots[texture as usize]
    }

    pub(super) fn mark_dirty(&mut self, texture: u32) {
        if let Some(flag) = self.dirty_flags.get_mut(texture as usize) {
            if !*flag {
                *flag = true;
                self.dirty.push(texture);
            }
        }
    }

    /// Moves `texture` to `placement` (or none): no level is resident or
    /// staged there yet, so its entry stops being sampleable.
    pub(super) fn place(&mut self, texture: u32, placement: Option<Placement>) {
        let slot = &mut self.slots[texture as usize];
        slot.placement = placement;
        slot.resident = 0;
        slot.pending = 0;
        self.entries[texture as usize].state = TEXTURE_NOT_SAMPLEABLE;
        self.mark_dirty(texture);
    }

    /// Level `mip` of `texture`, staged for `placement`, was recorded: it is
    /// resident if the texture is still there. The texture has nothing staged
    /// any more.
    pub(super) fn recorded(&mut self, texture: u32, placement: &Placement, mip: u32) {
        let slot = &mut self.slots[texture as usize];
        if slot.placement.is_some_and(|p| same_place(&p, placement)) {
            slot.resident |= 1 << mip;
        }
        slot.pending = 0;
    }

    /// Writes a texture's entry from its host state. The coarsest resident
    /// level bounds sampling (the loader starts at the 4×4 level, so coarser
    /// levels of uncompressed textures are never loaded), and the finest
    /// level such that it and every level up to that one are resident is the
    /// finest sampled.
    pub(super) fn publish(&mut self, texture: u32) {
        self.mark_dirty(texture);
        let slot = self.slots[texture as usize];
        let entry = &mut self.entries[texture as usize];
        *entry = table_entry(*entry, slot.placement.as_ref(), slot.resident);
        if entry.state == TEXTURE_SAMPLEABLE {
            let finest = &mut self.finest_published[texture as usize];
            *finest = (*finest).min(entry.lowest_mip);
        }
    }

    /// The finest level `texture`'s entry ever let the shaders sample; `None` if it never
    /// was sampleable (or is outside the table).
    pub(super) fn finest_published(&self, texture: u32) -> Option<u32> {
        self.finest_published
            .get(texture as usize)
            .copied()
            .filter(|&level| level != u32::MAX)
    }

    /// Takes the changed entries; `None` when nothing changed.
    pub(super) fn take_dirty(&mut self) -> Option<ChangedEntries> {
        if self.dirty.is_empty() {
            return None;
        }
        let mut dirty = std::mem::take(&mut self.dirty);
        dirty.sort_unstable();
        for &texture in &dirty {
            self.dirty_flags[texture as usize] = false;
        }
        let mut runs: Vec<(u32, u32)> = Vec::new();
        for &texture in &dirty {
            match runs.last_mut() {
                Some((first, count)) if *first + *count == texture => *count += 1,
                _ => runs.push((texture, 1)),
            }
        }
        let mut bytes: Vec<u8> = Vec::with_capacity(dirty.len() * std::mem::size_of::<TextureData>());
        for &(first, count) in &runs {
            bytes.extend_from_slice(bytemuck::cast_slice(
                &self.entries[first as usize..(first + count) as usize],
            ));
        }
        Some(ChangedEntries { runs, bytes })
    }
}

/// Table entries changed since the last copy.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct ChangedEntries {
    /// Runs of consecutive texture ids, `(first id, count)`, in id order.
    pub(super) runs: Vec<(u32, u32)>,
    /// The runs' entries as bytes, one run after another.
    pub(super) bytes: Vec<u8>,
}

/// Whether two placements are the same place of the same texture.
pub(super) fn same_place(a: &Placement, b: &Placement) -> bool {
    a.image == b.image && a.layer == b.layer && a.region == b.region && a.assignment == b.assignment
}

impl GpuTextureCache {
    /// Records the copy of every changed table entry (runs of adjacent
    /// textures merged) from staging into the device-local table.
    pub(super) fn record_table_update(&mut self, rec: Recording<'_>, ticket: u64) -> Result<()> {
        let cmd = rec.raw();
        let Some(ChangedEntries { runs, bytes }) = self.table.take_dirty() else {
            return Ok(());
        };
        let entry = std::mem::size_of::<TextureData>() as u64;
        let (source, base) =
            self.cycle
                .staging
                .put(&self.device, &bytes, ticket, "texture table staging (oversize update)")?;
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
pub(super) mod tests {
    use citystream_cache::{TexelFormat, UvTransform};

    use super::*;

    /// A 256² BC1 texture in region 1 of layer 3 of image 2, 9 levels.
    pub(in crate::texture_cache) fn placement() -> Placement {
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

    #[test]
    fn changed_entries_are_taken_once_in_runs_of_adjacent_ids() {
        let mut table = TextureTable::new(10);
        assert!(table.take_dirty().is_none(), "nothing changed yet");
        for texture in [7, 2, 3, 2, 9, 8] {
            table.mark_dirty(texture);
        }
        table.mark_dirty(10); // outside the table: ignored
        let changed = table.take_dirty().expect("changes");
        assert_eq!(changed.runs, vec![(2, 2), (7, 3)]);
        assert_eq!(changed.bytes.len(), 5 * std::mem::size_of::<TextureData>());
        assert!(table.take_dirty().is_none(), "taken");
        table.mark_dirty(3);
        assert_eq!(table.take_dirty().map(|changed| changed.runs), Some(vec![(3, 1)]));
    }

    #[test]
    fn a_new_place_empties_the_levels_until_recorded_copies_publish_them() {
        let mut table = TextureTable::new(8);
        let here = placement();
        table.place(7, Some(here));
        table.slot_mut(7).pending |= 1 << 8;
        table.recorded(7, &here, 8);
        table.publish(7);
        let slot = table.slot(7).expect("in the table");
        assert_eq!((slot.resident, slot.pending), (1 << 8, 0));
        assert_eq!(
            table.entry(7).map(|e| (e.state, e.lowest_mip)),
            Some((TEXTURE_SAMPLEABLE, 8))
        );
        let changed = table.take_dirty().expect("changes");
        assert_eq!(changed.bytes, bytemuck::bytes_of(&table.entries()[7]));
        // A copy recorded for a place the texture has left is not resident.
        let elsewhere = Placement { layer: 4, ..here };
        table.place(7, Some(elsewhere));
        table.recorded(7, &here, 7);
        assert_eq!(table.slot(7).map(|s| s.resident), Some(0));
        assert_eq!(table.entry(7).map(|e| e.state), Some(TEXTURE_NOT_SAMPLEABLE));
        table.place(7, None);
        assert!(table.slot(7).is_some_and(|s| s.placement.is_none()));
        assert!(table.slot(8).is_none());
    }
}
