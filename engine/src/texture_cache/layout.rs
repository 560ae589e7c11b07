//! How many images the cache has and how many layers each: from the formats
//! it holds, the textures each must place, the budget and the device's
//! limits. Pure: the sparse block size and layer footprint come in as
//! [`LayerProbe`]s, which the caller measures on the device. Also which
//! image holds which format ([`FormatImages`]).

use citystream_cache::{derive_image_layers, layers_to_place, ImageDemand};

use super::{CacheLayers, GpuCacheConfig, CACHE_FORMATS};
use crate::error::{EngineError, Result};
use crate::gpu_types::CACHE_IMAGE_SLOTS;

/// What one layer of a cache image costs, from a one-layer probe image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct LayerProbe {
    /// The sparse block size.
    pub(super) block_bytes: u64,
    /// Virtual bytes of one layer: its full mip chain in whole blocks.
    pub(super) virtual_bytes: u64,
    /// Blocks of a single mip tail (`SINGLE_MIPTAIL`) in an image of one layer: bound
    /// from the budget when the image is made and kept. 0 without one.
    pub(super) single_tail_blocks: u64,
    /// Whether a single tail grows with the layers (a synthetic one, forced on a device
    /// without tails: its blocks are the layers' own), or is one per image (a GPU's).
    pub(super) single_tail_per_layer: bool,
}

/// Indices into [`CACHE_FORMATS`] of the formats `config` holds, in that order.
pub(super) fn held_formats(config: &GpuCacheConfig) -> Result<Vec<usize>> {
    let held: Vec<usize> = (0..CACHE_FORMATS.len())
        .filter(|&index| config.formats.contains(&CACHE_FORMATS[index].0))
        .collect();
    if held.is_empty() {
        return Err(EngineError::InvalidRequest(format!(
            "the cache must hold at least one of {:?}; {:?} were asked for",
            CACHE_FORMATS.map(|(format, _, _)| format),
            config.formats
        )));
    }
    Ok(held)
}

/// Whether `layer_counts` (per format in [`CACHE_FORMATS`] order) place
/// every texture of derived layers at once: each format has at least the
/// layers its textures fill (`false` for fixed layers, whose textures are
/// not known).
pub(super) fn holds_every_texture(config: &GpuCacheConfig, layer_counts: &[Vec<u32>]) -> bool {
    let CacheLayers::Derived { extents, .. } = &config.layers else {
        return false;
    };
    extents.iter().zip(layer_counts).all(|(extents, counts)| {
        counts.iter().map(|&layers| u64::from(layers)).sum::<u64>() >= layers_to_place(config.layer_size, extents)
    })
}

/// Per format in [`CACHE_FORMATS`] order, the layer count of each of its
/// images (none for a format not held). `device_max_layers` is the device's
/// `maxImageArrayLayers`; `probe` measures a layer of the format at an index
/// of [`CACHE_FORMATS`] (called only for derived layers).
pub(super) fn plan_layer_counts(
    config: &GpuCacheConfig,
    held: &[usize],
    device_max_layers: u32,
    virtual_budget_bytes: u64,
    mut probe: impl FnMut(usize) -> Result<LayerProbe>,
) -> Result<Vec<Vec<u32>>> {
    let mut layer_counts: Vec<Vec<u32>> = vec![Vec::new(); CACHE_FORMATS.len()];
    match &config.layers {
        CacheLayers::Fixed(count) => {
            for &index in held {
                layer_counts[index] = vec![*count];
            }
        }
        CacheLayers::Derived { extents, max_layers } => {
            let max_layers = max_layers.map_or(device_max_layers, |m| m.min(device_max_layers));
            let probes = held.iter().map(|&index| probe(index)).collect::<Result<Vec<_>>>()?;
            let demands: Vec<ImageDemand> = held
                .iter()
                .zip(&probes)
                .map(|(&index, probe)| ImageDemand {
                    extents: extents.get(index).cloned().unwrap_or_default(),
                    layer_virtual_bytes: probe.virtual_bytes,
                })
                .collect();
            // The images share one block size (checked once they exist).
            let block_bytes = probes.first().map_or(1, |probe| probe.block_bytes.max(1));
            let budget_blocks = config.memory_budget_bytes / block_bytes;
            let derive = |images_per_format: &[u64]| {
                derive_image_layers(
                    config.layer_size,
                    &demands,
                    layer_budget_blocks(budget_blocks, &probes, images_per_format),
                    max_layers,
                    CACHE_IMAGE_SLOTS,
                    virtual_budget_bytes,
                )
            };
            // Single tails are bound from the budget once per image: the layers get
            // what they leave, counted again where a format takes more than one image.
            let mut derived = derive(&vec![1; held.len()]);
            let images: Vec<u64> = derived.iter().map(|counts| counts.len() as u64).collect();
            if images.iter().any(|&n| n > 1) {
                derived = derive(&images);
            }
            for (&index, counts) in held.iter().zip(derived) {
                layer_counts[index] = counts;
            }
        }
    };
    let image_count: usize = layer_counts.iter().map(Vec::len).sum();
    if image_count > CACHE_IMAGE_SLOTS as usize
        || held.iter().any(|&index| layer_counts[index].is_empty())
        || layer_counts.iter().flatten().any(|&layers| layers == 0)
    {
        return Err(EngineError::InvalidRequest(format!(
            "the cache needs 1 to {CACHE_IMAGE_SLOTS} images per format and {CACHE_IMAGE_SLOTS} in all, \
             each with at least one layer; {layer_counts:?} layers were asked for"
        )));
    }
    Ok(layer_counts)
}

/// The blocks of `budget_blocks` the layers may use once the single mip tails are bound:
/// one per image for a GPU's tails (`images_per_format` images of each probed format),
/// and, for synthetic tails that grow with the layers, a share per layer. At least 1.
fn layer_budget_blocks(budget_blocks: u64, probes: &[LayerProbe], images_per_format: &[u64]) -> u64 {
    let per_image: u64 = probes
        .iter()
        .zip(images_per_format)
        .filter(|(probe, _)| !probe.single_tail_per_layer)
        .map(|(probe, &images)| probe.single_tail_blocks * images)
        .sum();
    let per_layer = probes
        .iter()
        .filter(|probe| probe.single_tail_per_layer)
        .map(|probe| probe.single_tail_blocks)
        .max()
        .unwrap_or(0);
    (budget_blocks.saturating_sub(per_image) / (1 + per_layer)).max(1)
}

/// The images of `layer_counts` (per format in [`CACHE_FORMATS`] order) in
/// image order: `(format index, nth image of the format, layers)`.
pub(super) fn image_layouts(layer_counts: &[Vec<u32>]) -> Vec<(usize, usize, u32)> {
    layer_counts
        .iter()
        .enumerate()
        .flat_map(|(format, counts)| {
            counts
                .iter()
                .enumerate()
                .map(move |(nth, &layers)| (format, nth, layers))
        })
        .collect()
}

/// Which cache images hold which format: the images in [`image_layouts`]
/// order, each of one format of [`CACHE_FORMATS`].
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub(super) struct FormatImages {
    /// Per image, its format's index in [`CACHE_FORMATS`].
    image_formats: Vec<usize>,
    /// Per format in [`CACHE_FORMATS`], its images.
    format_images: Vec<Vec<u32>>,
}

impl FormatImages {
    /// Each image's format and each format's images, for `layouts`.
    pub(super) fn new(layouts: &[(usize, usize, u32)]) -> Self {
        let mut format_images = vec![Vec::new(); CACHE_FORMATS.len()];
        for (image, &(format, _, _)) in layouts.iter().enumerate() {
            format_images[format].push(image as u32);
        }
        Self {
            image_formats: layouts.iter().map(|&(format, _, _)| format).collect(),
            format_images,
        }
    }

    /// The images of the format at `format` in [`CACHE_FORMATS`], in index order.
    pub(super) fn of_format(&self, format: usize) -> &[u32] {
        &self.format_images[format]
    }

    /// The images holding textures of the same format as `image` (itself
    /// included), in index order; none for an image the cache does not have.
    pub(super) fn sharing(&self, image: u32) -> &[u32] {
        self.image_formats
            .get(image as usize)
            .map_or(&[], |&format| self.format_images[format].as_slice())
    }

    /// Per format in [`CACHE_FORMATS`] order, its index and images.
    pub(super) fn iter(&self) -> impl Iterator<Item = (usize, &[u32])> {
        self.format_images.iter().map(Vec::as_slice).enumerate()
    }
}

#[cfg(test)]
mod tests {
    use citystream_dataset::TextureFormat;

    use super::*;
    use crate::pipeline::Filtering;
    use crate::texture_cache::Eviction;

    const BLOCK: u64 = 64 * 1024;

    fn config(formats: &[TextureFormat], layers: CacheLayers, budget_blocks: u64) -> GpuCacheConfig {
        GpuCacheConfig {
            layer_size: 1024,
            layers,
            formats: formats.to_vec(),
            memory_budget_bytes: budget_blocks * BLOCK,
            virtual_budget_bytes: None,
            blocks_per_chunk: 16,
            texture_count: 1,
            filtering: Filtering::Nearest,
            staging_bytes: 1 << 20,
            eviction: Eviction::View,
        }
    }

    fn probe(_: usize) -> Result<LayerProbe> {
        Ok(LayerProbe {
            block_bytes: BLOCK,
            // A 1024² BC1 layer with its mip chain in whole 64 KiB blocks.
            virtual_bytes: 10 * BLOCK,
            single_tail_blocks: 0,
            single_tail_per_layer: false,
        })
    }

    #[test]
    fn derived_layers_leave_the_budget_single_tails_take() -> Result<()> {
        let tail = |blocks: u64, per_layer: bool| {
            move |_: usize| -> Result<LayerProbe> {
                Ok(LayerProbe {
                    single_tail_blocks: blocks,
                    single_tail_per_layer: per_layer,
                    ..probe(0)?
                })
            }
        };
        // 100 textures want 7 layers; a budget of 5 blocks keeps 5 live, one of them a
        // GPU's single tail: 4.
        let counts = plan_layer_counts(&bc1_derived(256, 100, None, 5), &[0], 2048, u64::MAX, tail(1, false))?;
        assert_eq!(counts[0], vec![4]);
        // At most 3 layers an image: 7 layers would take three images and three tails,
        // leaving 5 layers of 8 blocks (in two images).
        let counts = plan_layer_counts(&bc1_derived(256, 100, Some(3), 8), &[0], 2048, u64::MAX, tail(1, false))?;
        assert_eq!(counts[0], vec![3, 2]);
        // A synthetic tail of 2 blocks a layer: each layer costs 3 blocks of 12.
        let counts = plan_layer_counts(&bc1_derived(256, 100, None, 12), &[0], 2048, u64::MAX, tail(2, true))?;
        assert_eq!(counts[0], vec![4]);
        Ok(())
    }

    fn never_probed(index: usize) -> Result<LayerProbe> {
        panic!("fixed layers must not probe format {index}")
    }

    /// A BC1 cache deriving its layers for `textures` of `extent`, at most
    /// `max_layers` per image, within `budget_blocks`.
    fn bc1_derived(extent: u32, textures: u64, max_layers: Option<u32>, budget_blocks: u64) -> GpuCacheConfig {
        let extents = vec![vec![(extent, textures)], vec![], vec![], vec![]];
        config(
            &[TextureFormat::Bc1],
            CacheLayers::Derived { extents, max_layers },
            budget_blocks,
        )
    }

    #[test]
    fn fixed_layers_give_each_held_format_one_image_in_cache_format_order() -> Result<()> {
        let config = config(&[TextureFormat::Bc7, TextureFormat::Bc1], CacheLayers::Fixed(8), 100);
        let held = held_formats(&config)?;
        assert_eq!(held, vec![0, 3]);
        let counts = plan_layer_counts(&config, &held, 2048, u64::MAX, never_probed)?;
        assert_eq!(counts, vec![vec![8], vec![], vec![], vec![8]]);
        Ok(())
    }

    #[test]
    fn a_cache_holding_no_format_is_refused() {
        let config = config(&[], CacheLayers::Fixed(8), 100);
        assert!(matches!(held_formats(&config), Err(EngineError::InvalidRequest(_))));
    }

    #[test]
    fn derived_layers_place_every_texture_within_the_budget() -> Result<()> {
        // 256² textures pack 16 to a 1024² layer: 100 textures need 7 layers.
        let counts = plan_layer_counts(&bc1_derived(256, 100, None, 1000), &[0], 2048, u64::MAX, probe)?;
        assert_eq!(counts[0], vec![7]);
        // A budget of 3 blocks can keep at most 3 layers live.
        let tight = plan_layer_counts(&bc1_derived(256, 100, None, 3), &[0], 2048, u64::MAX, probe)?;
        assert_eq!(tight[0], vec![3]);
        Ok(())
    }

    #[test]
    fn a_format_needing_more_than_the_device_s_layers_gets_more_images() -> Result<()> {
        let counts = plan_layer_counts(&bc1_derived(1024, 10, None, 1000), &[0], 4, u64::MAX, probe)?;
        assert_eq!(counts[0].iter().sum::<u32>(), 10);
        assert!(
            counts[0].len() >= 3 && counts[0].iter().all(|&layers| layers <= 4),
            "{counts:?}"
        );
        // A lower limit than the device's applies the same way.
        let counts = plan_layer_counts(&bc1_derived(1024, 10, Some(5), 1000), &[0], 2048, u64::MAX, probe)?;
        assert_eq!(counts[0], vec![5, 5]);
        Ok(())
    }

    #[test]
    fn a_cache_holds_every_texture_only_with_the_layers_they_fill() -> Result<()> {
        // 100 textures of 256² need 7 layers of 1024².
        let roomy = bc1_derived(256, 100, None, 1000);
        let counts = plan_layer_counts(&roomy, &[0], 2048, u64::MAX, probe)?;
        assert!(holds_every_texture(&roomy, &counts));
        let tight = bc1_derived(256, 100, None, 3);
        let counts = plan_layer_counts(&tight, &[0], 2048, u64::MAX, probe)?;
        assert!(!holds_every_texture(&tight, &counts));
        let fixed = config(&[TextureFormat::Bc1], CacheLayers::Fixed(100), 1000);
        assert!(!holds_every_texture(&fixed, &[vec![100], vec![], vec![], vec![]]));
        Ok(())
    }

    #[test]
    fn an_image_of_zero_layers_is_refused() {
        let zero = config(&[TextureFormat::Bc1], CacheLayers::Fixed(0), 100);
        assert!(matches!(
            plan_layer_counts(&zero, &[0], 2048, u64::MAX, never_probed),
            Err(EngineError::InvalidRequest(_))
        ));
    }

    #[test]
    fn images_follow_cache_format_order_and_know_their_format() {
        let layouts = image_layouts(&[vec![2, 3], vec![], vec![5], vec![]]);
        assert_eq!(layouts, vec![(0, 0, 2), (0, 1, 3), (2, 0, 5)]);
        let formats = FormatImages::new(&layouts);
        assert_eq!(formats.of_format(0), &[0, 1]);
        assert_eq!(formats.of_format(1), &[] as &[u32]);
        assert_eq!(formats.of_format(2), &[2]);
        assert_eq!(formats.sharing(1), &[0, 1]);
        assert_eq!(formats.sharing(2), &[2]);
        assert_eq!(formats.sharing(3), &[] as &[u32], "no image 3");
        let listed: Vec<(usize, Vec<u32>)> = formats.iter().map(|(f, images)| (f, images.to_vec())).collect();
        assert_eq!(listed, vec![(0, vec![0, 1]), (1, vec![]), (2, vec![2]), (3, vec![])]);
    }
}
