//! What a host reads of the streamer to report on it, without reaching into
//! the cache: how far what is shown lags behind what the view asked for,
//! what a texture's table entry says, and the memory bound.

use citystream_streaming::source::MipSource;

use super::{source_failure, TextureStreamer};
use crate::error::Result;
use crate::gpu_types::{FeedbackEntry, TextureData, FEEDBACK_MIP_ONE, TEXTURE_SAMPLEABLE};

/// A frame's feedback against what the cache shows, over the meshes whose
/// weight reaches the loader's τ (those streaming serves).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ServedLevels {
    /// The weighted mean of displayed minus needed level (0 when everything
    /// needed is shown; `None` when no mesh reaches τ). A texture not yet
    /// sampleable counts as shown at its coarsest full-resolution level (the
    /// colormap).
    pub mip_deficit: Option<f64>,
    /// Distinct textures shown a whole level or more coarser than needed.
    pub pending_textures: usize,
}

impl<S: MipSource + 'static> TextureStreamer<S> {
    /// [`ServedLevels`] of compacted feedback `entries` (as
    /// [`latest_feedback`](Self::latest_feedback) gives them).
    pub fn served_levels(&self, entries: &[FeedbackEntry]) -> Result<ServedLevels> {
        let mesh_textures = self.loader.mesh_textures();
        let (mut weighted, mut total) = (0.0f64, 0.0f64);
        let mut pending: Vec<u32> = Vec::new();
        for entry in entries.iter().filter(|e| e.weight >= self.gpu_tau) {
            let Some(&texture) = mesh_textures.get(entry.mesh_id as usize) else {
                continue;
            };
            let needed = f64::from(entry.mip) / f64::from(FEEDBACK_MIP_ONE);
            let displayed = match self.cache.texture_data(texture) {
                Some(d) if d.state == TEXTURE_SAMPLEABLE => needed
                    .max(f64::from(d.lowest_mip))
                    .min(f64::from(d.mip_count.saturating_sub(1))),
                _ => {
                    let chain = self.loader.source().mip_chain(texture).map_err(source_failure)?;
                    f64::from(31 - chain.width.max(chain.height).max(1).leading_zeros())
                }
            };
            let weight = f64::from(entry.weight);
            weighted += weight * (displayed - needed).max(0.0);
            total += weight;
            if displayed - needed >= 1.0 {
                pending.push(texture);
            }
        }
        pending.sort_unstable();
        pending.dedup();
        Ok(ServedLevels {
            mip_deficit: (total > 0.0).then(|| weighted / total),
            pending_textures: pending.len(),
        })
    }

    /// The table entry the shaders read for `texture` (which levels are
    /// sampleable, and where); `None` outside the table.
    pub fn texture_data(&self, texture: u32) -> Option<TextureData> {
        self.cache.texture_data(texture).copied()
    }

    /// The array layers of each cache image, in binding order (images of
    /// BC1, RGBA8, BC3, BC7 textures, as the source has them).
    pub fn cache_layers(&self) -> Vec<u32> {
        self.cache
            .packing()
            .images()
            .iter()
            .map(|image| image.layer_count)
            .collect()
    }

    /// Device memory the cache holds for texels, which the memory budget
    /// limits: sparse blocks bound now, parked ones included, or with
    /// texture arrays every layer's full mip chain, bound from the start.
    pub fn bound_bytes(&self) -> u64 {
        self.cache.texel_memory_bytes()
    }

    /// How the cache holds textures (sparse images or texture arrays).
    pub fn texture_backing(&self) -> crate::device::TextureBacking {
        self.cache.backing()
    }
}
