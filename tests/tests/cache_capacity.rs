//! The cache's layers come from the textures, the budget and the device,
//! not from a constant: on a device that allows few layers per image (a
//! configured limit) the count still follows the budget, in more images of
//! the format; where the images' slots run out too, the streamer still
//! serves every texture by reusing layers.

use std::sync::Arc;

use anyhow::{ensure, Result};
use citystream_engine::stream::{StreamConfig, TextureStreamer};
use citystream_engine::texture_cache::ResidentCache;
use citystream_engine::Device;
use citystream_streaming::controller::{PolicyKind, PolicyOptions};
use citystream_streaming::source::MemorySource;
use citystream_tests::{assert_clean_after_dropping, validated_device};

const TEXTURES: u32 = 12;
const LAYER: u32 = 256;

fn streamer(device: &Arc<Device>, budget_bytes: u64, max_layers: Option<u32>) -> Result<TextureStreamer<MemorySource>> {
    let mut source = MemorySource::new();
    // One texture per layer: twelve layers place them all.
    for _ in 0..TEXTURES {
        source.push_bc1(LAYER, LAYER);
    }
    Ok(TextureStreamer::new(
        device,
        source,
        (0..TEXTURES).collect(),
        &vec![[0, 0, 0, 255]; TEXTURES as usize],
        PolicyKind::Baseline.build(&PolicyOptions::default())?,
        &StreamConfig {
            layer_size: LAYER,
            max_layers,
            memory_budget_bytes: budget_bytes,
            staging_bytes: 1 << 20,
            ..StreamConfig::default()
        },
    )?)
}

/// Layers of each BC1 image.
fn bc1_layers(streamer: &TextureStreamer<MemorySource>) -> Vec<u32> {
    let images = streamer.cache().packing().images();
    images
        .iter()
        .filter(|image| image.format.name == "BC1")
        .map(|image| image.layer_count)
        .collect()
}

#[test]
fn layers_follow_the_budget_whatever_the_layer_limit() -> Result<()> {
    let device = validated_device()?;
    let block = 64 << 10;
    // Enough budget for every texture: one layer each.
    let roomy = streamer(&device, 64 * block, None)?;
    ensure!(bc1_layers(&roomy) == [TEXTURES], "{:?} layers", bc1_layers(&roomy));
    drop(roomy);
    // A limit of 4 layers per image: the twelve layers in three images.
    let few = streamer(&device, 64 * block, Some(4))?;
    ensure!(
        bc1_layers(&few) == [4, 4, 4],
        "{:?} layers under a limit of 4",
        bc1_layers(&few)
    );
    drop(few);
    // Three blocks of budget can keep at most three layers live.
    let small = streamer(&device, 3 * block, Some(4))?;
    ensure!(
        bc1_layers(&small) == [3],
        "{:?} layers for a 3-block budget",
        bc1_layers(&small)
    );
    drop(small);
    // Nine blocks under a limit of 2: five images of two layers or fewer.
    let nine = streamer(&device, 9 * block, Some(2))?;
    ensure!(
        bc1_layers(&nine) == [2, 2, 2, 2, 1],
        "{:?} layers for a 9-block budget, 2 per image",
        bc1_layers(&nine)
    );
    assert_clean_after_dropping(&device, nine)
}

#[test]
fn textures_in_several_images_are_all_resident_at_once() -> Result<()> {
    let device = validated_device()?;
    let mut streamer = streamer(&device, 64 << 20, Some(4))?;
    let mut commands = citystream_engine::commands::CommandContext::new(&device, "capacity test")?;
    let coarsest = 6; // 4x4 of a 256² texture
    for texture in 0..TEXTURES {
        streamer.load_now(&[(texture, coarsest)], &mut commands)?;
    }
    for texture in 0..TEXTURES {
        ensure!(
            streamer.cache().resident_levels(texture) & (1 << coarsest) != 0,
            "texture {texture} is not resident"
        );
    }
    let evicted = streamer.residency_totals().evicted_layers;
    ensure!(evicted == 0, "{evicted} layers evicted with room for every texture");
    assert_clean_after_dropping(&device, streamer)
}

#[test]
fn textures_beyond_the_layers_are_served_by_evicting_layers_the_view_does_not_need() -> Result<()> {
    let device = validated_device()?;
    // One layer per image: the source has only BC1 textures, so BC1 gets
    // all eight image slots.
    let mut streamer = streamer(&device, 64 << 20, Some(1))?;
    ensure!(bc1_layers(&streamer) == [1; 8], "{:?} layers", bc1_layers(&streamer));
    ensure!(
        streamer.cache().packing().images().len() == 8,
        "images of other formats were made"
    );
    let mut commands = citystream_engine::commands::CommandContext::new(&device, "capacity test")?;
    // Load every texture's coarsest level, one after another: twelve
    // textures through eight layers.
    for texture in 0..TEXTURES {
        let coarsest = 6; // 4x4 of a 256² texture
        streamer.load_now(&[(texture, coarsest)], &mut commands)?;
        ensure!(
            streamer.cache().resident_levels(texture) & (1 << coarsest) != 0,
            "texture {texture} is not resident after its load"
        );
    }
    let evicted = streamer.residency_totals().evicted_layers;
    ensure!(
        evicted == u64::from(TEXTURES - 8),
        "{evicted} layers evicted for {TEXTURES} textures in 8 layers"
    );
    assert_clean_after_dropping(&device, streamer)
}
