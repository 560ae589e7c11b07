//! The sparse texture cache on lavapipe (paper §3.6): a few hundred textures
//! of mixed extents and both formats, several mips each, sampled through the
//! engine's own sampling code at every loaded mip and compared with the
//! source texels; LOD clamping to the finest resident level; repeated UVs;
//! then a ring eviction after which the evicted textures fall back to the
//! City Colormap and the others still read correctly.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;

use anyhow::{ensure, Result};
use citystream_cache::geometry::cacheable_mip_count;
use citystream_cache::TexelFormat;
use citystream_dataset::TextureFormat;
use citystream_engine::commands::CommandContext;
use citystream_engine::device::TextureBacking;
use citystream_engine::gpu_types::{ProbeResult, TextureProbePoint};
use citystream_engine::pipeline::Filtering;
use citystream_engine::placeholder::SplitMix64;
use citystream_engine::probe::TextureProbe;
use citystream_engine::texture_cache::{
    CacheLayers, Eviction, GpuCacheConfig, GpuTextureCache, ResidentCache, StageOutcome,
};
use citystream_engine::Device;
use citystream_tests::{
    assert_clean_after_dropping, bc1_texel, test_cache_config, validated_array_device, validated_device,
};

const EXTENTS: [u32; 6] = [4, 8, 16, 32, 64, 128];
const LAYER_SIZE: u32 = 256;
const LAYERS: u32 = 16;

struct SourceTexture {
    format: TextureFormat,
    width: u32,
    height: u32,
    /// Random bytes per level, level 0 first.
    levels: Vec<Vec<u8>>,
}

impl SourceTexture {
    fn random(rng: &mut SplitMix64, format: TextureFormat, width: u32, height: u32) -> Self {
        // The levels the cache holds: both sides at least one texel block.
        let texel_format = match format {
            TextureFormat::Bc1 => TexelFormat::BC1,
            TextureFormat::Bc3 => TexelFormat::BC3,
            TextureFormat::Bc7 => TexelFormat::BC7,
            TextureFormat::Rgba8 => TexelFormat::RGBA8,
        };
        let count = cacheable_mip_count(&texel_format, width, height);
        let levels = (0..count)
            .map(|m| {
                let bytes = format.mip_bytes(width >> m, height >> m) as usize;
                let mut level: Vec<u8> = (0..bytes).map(|_| rng.next_u64() as u8).collect();
                if format == TextureFormat::Bc7 {
                    // A first byte of 0 is BC7's reserved mode 8.
                    for block in level.chunks_mut(16) {
                        block[0] |= 1 << (block[1] % 8);
                    }
                }
                level
            })
            .collect();
        Self {
            format,
            width,
            height,
            levels,
        }
    }

    fn level_extent(&self, mip: u32) -> (u32, u32) {
        ((self.width >> mip).max(1), (self.height >> mip).max(1))
    }

    fn texel(&self, mip: u32, x: u32, y: u32) -> [u8; 4] {
        let (w, _) = self.level_extent(mip);
        let level = &self.levels[mip as usize];
        match self.format {
            TextureFormat::Bc1 => bc1_texel(level, w, x, y),
            TextureFormat::Bc3 | TextureFormat::Bc7 => {
                let blocks_per_row = w.div_ceil(4) as usize;
                let at = ((y / 4) as usize * blocks_per_row + (x / 4) as usize) * 16;
                let mut texels = [0u8; 64];
                if self.format == TextureFormat::Bc3 {
                    bcdec_rs::bc3(&level[at..at + 16], &mut texels, 16);
                } else {
                    bcdec_rs::bc7(&level[at..at + 16], &mut texels, 16);
                }
                let i = (((y % 4) * 4 + x % 4) * 4) as usize;
                [texels[i], texels[i + 1], texels[i + 2], texels[i + 3]]
            }
            TextureFormat::Rgba8 => {
                let at = ((y * w + x) * 4) as usize;
                [level[at], level[at + 1], level[at + 2], level[at + 3]]
            }
        }
    }
}

fn to_u8(result: &ProbeResult) -> [u8; 4] {
    result.value.map(|c| (c * 255.0).round() as u8)
}

fn close(a: [u8; 4], b: [u8; 4], tolerance: u8) -> bool {
    a.iter().zip(&b).all(|(x, y)| x.abs_diff(*y) <= tolerance)
}

/// Probe points for `texture`: a few texels of each level in `levels`,
/// sampled at `lod`, plus a repeated-UV copy of one of them.
fn points_for(
    texture: u32,
    source: &SourceTexture,
    level: u32,
    lod: f32,
    rng: &mut SplitMix64,
) -> Vec<(TextureProbePoint, u32, u32)> {
    let (w, h) = source.level_extent(level);
    let mut texels = vec![(0, 0), (w - 1, h - 1)];
    for _ in 0..2 {
        texels.push((
            (rng.next_u64() % u64::from(w)) as u32,
            (rng.next_u64() % u64::from(h)) as u32,
        ));
    }
    let mut points: Vec<(TextureProbePoint, u32, u32)> = texels
        .iter()
        .map(|&(x, y)| {
            (
                TextureProbePoint {
                    uv: [(x as f32 + 0.5) / w as f32, (y as f32 + 0.5) / h as f32],
                    lod,
                    texture,
                },
                x,
                y,
            )
        })
        .collect();
    let (first, x, y) = points[2];
    points.push((
        TextureProbePoint {
            uv: [first.uv[0] + 1.0, first.uv[1] - 2.0],
            ..first
        },
        x,
        y,
    ));
    points
}

#[test]
fn cache_samples_every_texture_at_every_loaded_mip_and_survives_eviction() -> Result<()> {
    cache_samples_every_texture_at_every_loaded_mip_and_survives_eviction_on(validated_device()?)
}

/// With texture arrays (no sparse residency) the cache reads back the same.
#[test]
fn cache_samples_every_texture_at_every_loaded_mip_and_survives_eviction_with_texture_arrays() -> Result<()> {
    cache_samples_every_texture_at_every_loaded_mip_and_survives_eviction_on(validated_array_device()?)
}

fn cache_samples_every_texture_at_every_loaded_mip_and_survives_eviction_on(device: Arc<Device>) -> Result<()> {
    let mut rng = SplitMix64::new(2024);
    let mut sources = Vec::new();
    // 20 textures of each extent class and format; rectangular ones too.
    for format in [TextureFormat::Bc1, TextureFormat::Rgba8] {
        for &extent in &EXTENTS {
            for i in 0..20u32 {
                let other = EXTENTS[(rng.next_u64() % EXTENTS.len() as u64) as usize].min(extent);
                let (w, h) = if i % 2 == 0 { (extent, other) } else { (other, extent) };
                sources.push(SourceTexture::random(&mut rng, format, w, h));
            }
        }
    }
    let first_phase = sources.len() as u32;
    // Extra 128-texel textures that overflow the ring later.
    for _ in 0..24 {
        sources.push(SourceTexture::random(&mut rng, TextureFormat::Rgba8, 128, 128));
    }
    let colormap: Vec<[u8; 4]> = (0..sources.len())
        .map(|_| [rng.next_u64() as u8, 90, 200, 255])
        .collect();

    let mut commands = CommandContext::new(&device, "cache test")?;
    let mut cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &GpuCacheConfig {
            layer_size: LAYER_SIZE,
            layers: CacheLayers::Fixed(LAYERS),
            formats: vec![TextureFormat::Bc1, TextureFormat::Rgba8],
            eviction: Eviction::Ring,
            memory_budget_bytes: 256 << 20,
            virtual_budget_bytes: None,
            blocks_per_chunk: 64,
            texture_count: sources.len() as u32,
            filtering: Filtering::Nearest,
            // A small ring: the first cycle's uploads do not fit and take the one-off buffer.
            staging_bytes: 64 * 1024,
        },
        &colormap,
    )?;

    // Phase 1: every texture, coarsest mip first as the loader does; every
    // fifth texture stops two levels above its base to exercise LOD clamping.
    let mut finest_loaded = HashMap::new();
    for (t, source) in sources.iter().enumerate().take(first_phase as usize) {
        let levels = source.levels.len() as u32;
        let finest = if t % 5 == 0 { 2.min(levels - 1) } else { 0 };
        for mip in (finest..levels).rev() {
            let outcome = cache.stage(
                t as u32,
                source.format,
                source.width,
                source.height,
                mip,
                &source.levels[mip as usize],
            )?;
            ensure!(
                matches!(outcome, StageOutcome::Staged { .. }),
                "texture {t} mip {mip}: {outcome:?}"
            );
        }
        finest_loaded.insert(t as u32, finest);
    }
    for t in first_phase..sources.len() as u32 {
        finest_loaded.insert(t, 0);
    }
    let report = cache.finish_cycle(&mut commands)?;
    ensure!(
        report.textures_invalidated == 0 && report.blocks_unbound == 0,
        "no eviction expected yet: {report:?}"
    );
    match device.texture_backing() {
        TextureBacking::Sparse => ensure!(report.blocks_bound > 0 && report.bind_entries <= report.blocks_bound),
        // Fully bound layers: nothing to bind, no bind to pay for.
        TextureBacking::Arrays => {
            ensure!(report.blocks_bound == 0 && report.bind_entries == 0, "{report:?}");
            // The block accounting still counts the blocks the loaded levels cover,
            // within every layer's (docs/STRATEGIES.md).
            let used = cache.budget_use();
            ensure!(
                used.live_blocks > 0 && used.live_blocks <= used.budget_blocks,
                "{used:?}"
            );
        }
    }

    let probe = TextureProbe::new(&device)?;
    let check_all = |cache: &GpuTextureCache,
                     textures: &[u32],
                     rng: &mut SplitMix64,
                     commands: &mut CommandContext|
     -> Result<usize> {
        let mut points = Vec::new();
        let mut expected = Vec::new();
        for &t in textures {
            let source = &sources[t as usize];
            let finest = finest_loaded[&t];
            let entry = cache.texture_data(t).expect("texture in table");
            ensure!(
                entry.lowest_mip == finest,
                "texture {t}: lowest mip {} != {finest}",
                entry.lowest_mip
            );
            for level in finest..source.levels.len() as u32 {
                for (point, x, y) in points_for(t, source, level, level as f32, rng) {
                    points.push(point);
                    expected.push((t, level, source.texel(level, x, y)));
                }
            }
            if finest > 0 {
                // Asking for level 0 reads the finest resident level instead.
                for (mut point, x, y) in points_for(t, source, finest, 0.0, rng) {
                    point.lod = 0.0;
                    points.push(point);
                    expected.push((t, finest, source.texel(finest, x, y)));
                }
            }
        }
        let results = probe.run(commands, cache, &points)?;
        for (i, result) in results.iter().enumerate() {
            let (t, level, want) = expected[i];
            let tolerance = if sources[t as usize].format == TextureFormat::Bc1 {
                3
            } else {
                0
            };
            ensure!(
                result.resident == 1,
                "texture {t} level {level}: fell back to the colormap at {:?}",
                points[i]
            );
            ensure!(
                close(to_u8(result), want, tolerance),
                "texture {t} ({:?} {}x{}) level {level} at uv {:?}: read {:?}, expected {want:?}",
                sources[t as usize].format,
                sources[t as usize].width,
                sources[t as usize].height,
                points[i].uv,
                to_u8(result)
            );
        }
        Ok(results.len())
    };
    let all_first: Vec<u32> = (0..first_phase).collect();
    let checked = check_all(&cache, &all_first, &mut rng, &mut commands)?;
    ensure!(checked > 5 * first_phase as usize, "too few probes: {checked}");

    // Phase 2: more 128-texel textures than the free layers hold: the ring
    // reuses the oldest layer, whose textures must then fall back.
    for t in first_phase..sources.len() as u32 {
        let source = &sources[t as usize];
        for mip in (0..source.levels.len() as u32).rev() {
            cache.stage(
                t,
                source.format,
                source.width,
                source.height,
                mip,
                &source.levels[mip as usize],
            )?;
        }
    }
    let report = cache.finish_cycle(&mut commands)?;
    ensure!(
        report.textures_invalidated > 0,
        "the ring must have evicted a layer: {report:?}"
    );
    let invalidated: HashSet<u32> = (0..sources.len() as u32)
        .filter(|&t| cache.texture_data(t).is_some_and(|d| d.state == 0))
        .collect();
    ensure!(invalidated.len() == report.textures_invalidated as usize);
    let evicted: Vec<u32> = invalidated.iter().copied().collect();
    let probes: Vec<TextureProbePoint> = evicted
        .iter()
        .map(|&t| TextureProbePoint {
            uv: [0.5, 0.5],
            lod: 0.0,
            texture: t,
        })
        .collect();
    let results = probe.run(&mut commands, &cache, &probes)?;
    for (result, &t) in results.iter().zip(&evicted) {
        ensure!(
            result.resident == 0,
            "evicted texture {t} was still sampled from the cache"
        );
        ensure!(
            to_u8(result) == colormap[t as usize],
            "evicted texture {t} must show its colormap colour"
        );
    }
    let survivors: Vec<u32> = (0..sources.len() as u32).filter(|t| !invalidated.contains(t)).collect();
    check_all(&cache, &survivors, &mut rng, &mut commands)?;

    let utilisation = cache.utilisation();
    ensure!(utilisation.texture_bytes > 0 && utilisation.bound_bytes >= utilisation.texture_bytes / 2);
    device.wait_idle()?;
    assert_clean_after_dropping(&device, (probe, cache, commands))
}

/// One BC1 block of a single opaque colour (RGB565 endpoints equal).
fn bc1_solid(rgb565: u16) -> [u8; 8] {
    let [lo, hi] = rgb565.to_le_bytes();
    [lo, hi, lo, hi, 0, 0, 0, 0]
}

#[test]
fn filtered_sampling_blends_levels_and_never_bleeds_into_neighbours() -> Result<()> {
    filtered_sampling_blends_levels_and_never_bleeds_into_neighbours_on(validated_device()?)
}

/// With texture arrays (no sparse residency) the cache reads back the same.
#[test]
fn filtered_sampling_blends_levels_and_never_bleeds_into_neighbours_with_texture_arrays() -> Result<()> {
    filtered_sampling_blends_levels_and_never_bleeds_into_neighbours_on(validated_array_device()?)
}

fn filtered_sampling_blends_levels_and_never_bleeds_into_neighbours_on(device: Arc<Device>) -> Result<()> {
    // Two 64x64 textures side by side in one layer, every level a solid colour
    // that differs between levels and between the textures. Bilinear sampling
    // inside a level returns exactly that colour, so any bleed across the
    // region edge or wrong residency shows.
    let mut commands = CommandContext::new(&device, "filtering test")?;
    let mut cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &GpuCacheConfig {
            layer_size: 128,
            memory_budget_bytes: 64 << 20,
            filtering: Filtering::BilinearNearestLevel,
            ..test_cache_config(&[TextureFormat::Bc1, TextureFormat::Rgba8], 4)
        },
        &[[0, 0, 0, 255]; 4],
    )?;
    let rgba_colour = |t: u32, level: u32| {
        [
            (40 * level) as u8,
            if t == 0 { 200 } else { 20 },
            (10 + 30 * t) as u8,
            255,
        ]
    };
    // RGB565 colours that expand exactly to 8 bits: red channel steps of 8 per level.
    let bc1_colour = |t: u32, level: u32| -> (u16, [u8; 4]) {
        let r5 = (4 * level) as u16;
        let g6 = if t == 2 { 60 } else { 4 };
        let c = (r5 << 11) | (g6 << 5) | 8;
        let expand = |v: u16, bits: u32| -> u8 { ((v << (8 - bits)) | (v >> (2 * bits - 8))) as u8 };
        (c, [expand(r5, 5), expand(g6, 6), expand(8, 5), 255])
    };
    for t in 0..2u32 {
        for level in (0..7u32).rev() {
            let side = 64 >> level;
            let bytes: Vec<u8> = (0..side * side).flat_map(|_| rgba_colour(t, level)).collect();
            cache.stage(t, TextureFormat::Rgba8, 64, 64, level, &bytes)?;
        }
    }
    for t in 2..4u32 {
        for level in (0..5u32).rev() {
            let blocks = ((64 >> level) / 4) * ((64 >> level) / 4);
            let bytes: Vec<u8> = (0..blocks).flat_map(|_| bc1_solid(bc1_colour(t, level).0)).collect();
            cache.stage(t, TextureFormat::Bc1, 64, 64, level, &bytes)?;
        }
    }
    cache.finish_cycle(&mut commands)?;
    ensure!(
        cache.texture_data(0).map(|d| d.layer) == cache.texture_data(1).map(|d| d.layer),
        "the two RGBA8 textures must share a layer for the bleed check"
    );

    let probe = TextureProbe::new(&device)?;
    let mut points = Vec::new();
    let mut expected = Vec::new();
    for t in 0..4u32 {
        let levels = if t < 2 { 7 } else { 5 };
        for lod in [0.0f32, 1.0, 1.25, 2.0, 2.5, 3.75] {
            if lod > (levels - 1) as f32 {
                continue;
            }
            // Edges and corners of the region, where a bleed would show, and repeats.
            for uv in [
                [0.001, 0.5],
                [0.999, 0.5],
                [0.5, 0.001],
                [0.5, 0.999],
                [0.999, 0.999],
                [1.75, -0.25],
            ] {
                points.push(TextureProbePoint { uv, lod, texture: t });
                let colour = |level: u32| {
                    if t < 2 {
                        rgba_colour(t, level)
                    } else {
                        bc1_colour(t, level).1
                    }
                };
                let fine = lod.floor() as u32;
                let blend = lod - fine as f32;
                let (a, b) = (colour(fine), colour((fine + 1).min(levels - 1)));
                expected.push(
                    [0, 1, 2, 3].map(|i| ((1.0 - blend) * f32::from(a[i]) + blend * f32::from(b[i])).round() as u8),
                );
            }
        }
    }
    let results = probe.run(&mut commands, &cache, &points)?;
    for (i, result) in results.iter().enumerate() {
        ensure!(result.resident == 1, "{:?}: fell back to the colormap", points[i]);
        ensure!(
            close(to_u8(result), expected[i], 2),
            "{:?}: read {:?}, expected {:?}",
            points[i],
            to_u8(result),
            expected[i]
        );
    }
    assert_clean_after_dropping(&device, (probe, cache, commands))
}

#[test]
fn levels_coarser_than_the_first_loaded_one_are_never_needed() -> Result<()> {
    // The loader starts at the 4x4 level; an RGBA8 64x64 texture also has
    // 2x2 and 1x1 levels that are never loaded. It must still be sampleable,
    // with far views clamped to the 4x4 level.
    let device = validated_device()?;
    let mut commands = CommandContext::new(&device, "coarse clamp test")?;
    let mut cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &GpuCacheConfig {
            layer_size: 128,
            layers: CacheLayers::Fixed(1),
            staging_bytes: 1 << 20,
            ..test_cache_config(&[TextureFormat::Bc1, TextureFormat::Rgba8], 1)
        },
        &[[9, 9, 9, 255]],
    )?;
    let colour = |level: u32| [(50 * level) as u8, 100, 200, 255];
    for level in (0..5u32).rev() {
        let side = 64 >> level;
        let bytes: Vec<u8> = (0..side * side).flat_map(|_| colour(level)).collect();
        cache.stage(0, TextureFormat::Rgba8, 64, 64, level, &bytes)?;
    }
    cache.finish_cycle(&mut commands)?;
    let entry = *cache.texture_data(0).expect("texture 0");
    ensure!(
        entry.state == 1 && entry.lowest_mip == 0 && entry.mip_count == 5,
        "{entry:?}"
    );
    let probe = TextureProbe::new(&device)?;
    let points: Vec<TextureProbePoint> = [0.0f32, 4.0, 6.0]
        .iter()
        .map(|&lod| TextureProbePoint {
            uv: [0.3, 0.6],
            lod,
            texture: 0,
        })
        .collect();
    let results = probe.run(&mut commands, &cache, &points)?;
    let read: Vec<[u8; 4]> = results.iter().map(to_u8).collect();
    ensure!(results.iter().all(|r| r.resident == 1), "{results:?}");
    ensure!(read == vec![colour(0), colour(4), colour(4)], "{read:?}");
    assert_clean_after_dropping(&device, (probe, cache, commands))
}

#[test]
fn a_level_of_a_layer_evicted_in_the_same_cycle_is_not_dropped_again() -> Result<()> {
    // View eviction may evict a layer and then, in the same cycle, look for levels to drop
    // among textures whose table still shows them resident: those are gone already.
    let device = validated_device()?;
    let mut commands = CommandContext::new(&device, "evict then drop test")?;
    let mut cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &GpuCacheConfig {
            layer_size: 128,
            eviction: Eviction::View,
            staging_bytes: 1 << 20,
            ..test_cache_config(&[TextureFormat::Bc1, TextureFormat::Rgba8], 2)
        },
        &[[9, 9, 9, 255], [9, 9, 9, 255]],
    )?;
    for texture in 0..2 {
        for level in (0..5u32).rev() {
            let side = 64 >> level;
            let bytes = vec![texture as u8 * 100; (side * side * 4) as usize];
            cache.stage(texture, TextureFormat::Rgba8, 64, 64, level, &bytes)?;
        }
    }
    cache.finish_cycle(&mut commands)?;
    let data = *cache.texture_data(0).expect("texture 0");
    cache.evict_layer(data.image, data.layer)?;
    ensure!(
        cache.drop_finest(0)?.is_none(),
        "a level of an evicted layer was dropped"
    );
    let report = cache.finish_cycle(&mut commands)?;
    ensure!(report.invalidated_textures.contains(&0), "{report:?}");
    ensure!(
        cache.texture_data(0).is_some_and(|d| d.state == 0),
        "texture 0 still sampleable"
    );
    assert_clean_after_dropping(&device, (cache, commands))
}

/// Stages every cacheable level of every source texture, coarsest first,
/// and finishes the cycle; every mip must be staged.
fn stage_every_level(
    cache: &mut GpuTextureCache,
    commands: &mut CommandContext,
    sources: &[SourceTexture],
) -> Result<citystream_engine::texture_cache::CycleReport> {
    for (t, source) in sources.iter().enumerate() {
        for mip in (0..source.levels.len() as u32).rev() {
            let outcome = cache.stage(
                t as u32,
                source.format,
                source.width,
                source.height,
                mip,
                &source.levels[mip as usize],
            )?;
            ensure!(
                matches!(outcome, StageOutcome::Staged { .. }),
                "texture {t} mip {mip}: {outcome:?}"
            );
        }
    }
    Ok(cache.finish_cycle(commands)?)
}

/// Samples a few texels of every level of every source texture through the
/// cache and compares them with the source (BC1 and BC3 colours may round
/// apart by 3; RGBA8 and BC7 decode exactly).
fn read_back_every_level(
    device: &std::sync::Arc<citystream_engine::Device>,
    cache: &GpuTextureCache,
    commands: &mut CommandContext,
    sources: &[SourceTexture],
    rng: &mut SplitMix64,
) -> Result<()> {
    let probe = TextureProbe::new(device)?;
    let mut points = Vec::new();
    let mut expected = Vec::new();
    for (t, source) in sources.iter().enumerate() {
        for level in 0..source.levels.len() as u32 {
            for (point, x, y) in points_for(t as u32, source, level, level as f32, rng) {
                points.push(point);
                expected.push((t, level, source.texel(level, x, y)));
            }
        }
    }
    let results = probe.run(commands, cache, &points)?;
    for (i, result) in results.iter().enumerate() {
        let (t, level, want) = expected[i];
        let tolerance = match sources[t].format {
            TextureFormat::Bc1 | TextureFormat::Bc3 => 3,
            TextureFormat::Rgba8 | TextureFormat::Bc7 => 0,
        };
        ensure!(
            result.resident == 1 && close(to_u8(result), want, tolerance),
            "texture {t} ({:?}, image {:?}) level {level} at {:?}: read {:?} (resident {}), expected {want:?}",
            sources[t].format,
            cache.texture_data(t as u32).map(|e| e.image),
            points[i].uv,
            to_u8(result),
            result.resident
        );
    }
    Ok(())
}

#[test]
fn a_format_spread_over_several_images_reads_back_from_each() -> Result<()> {
    let device = validated_device()?;
    let mut rng = SplitMix64::new(77);
    // One texture per layer; a limit of three layers per image spreads ten
    // BC1 textures over four images and four RGBA8 ones over two.
    let mut sources: Vec<SourceTexture> = (0..10)
        .map(|_| SourceTexture::random(&mut rng, TextureFormat::Bc1, LAYER_SIZE, LAYER_SIZE))
        .collect();
    sources.extend((0..4).map(|_| SourceTexture::random(&mut rng, TextureFormat::Rgba8, LAYER_SIZE, LAYER_SIZE)));
    let mut commands = CommandContext::new(&device, "multi-image cache test")?;
    let mut cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &GpuCacheConfig {
            layer_size: LAYER_SIZE,
            layers: CacheLayers::Derived {
                extents: vec![vec![(LAYER_SIZE, 10)], vec![(LAYER_SIZE, 4)]],
                max_layers: Some(3),
            },
            formats: vec![TextureFormat::Bc1, TextureFormat::Rgba8],
            eviction: Eviction::View,
            memory_budget_bytes: 256 << 20,
            virtual_budget_bytes: None,
            blocks_per_chunk: 64,
            texture_count: sources.len() as u32,
            filtering: Filtering::Nearest,
            staging_bytes: 1 << 20,
        },
        &vec![[0, 0, 0, 255]; sources.len()],
    )?;
    let layers: Vec<(&str, u32)> = cache
        .packing()
        .images()
        .iter()
        .map(|image| (image.format.name, image.layer_count))
        .collect();
    ensure!(
        layers
            == [
                ("BC1", 3),
                ("BC1", 3),
                ("BC1", 2),
                ("BC1", 2),
                ("RGBA8", 2),
                ("RGBA8", 2)
            ],
        "images and layers: {layers:?}"
    );
    let report = stage_every_level(&mut cache, &mut commands, &sources)?;
    ensure!(report.textures_invalidated == 0, "nothing evicted: {report:?}");
    let used: HashSet<u32> = (0..sources.len() as u32)
        .filter_map(|t| cache.texture_data(t).map(|entry| entry.image))
        .collect();
    ensure!(used.len() == 6, "textures placed in images {used:?}");
    read_back_every_level(&device, &cache, &mut commands, &sources, &mut rng)?;
    assert_clean_after_dropping(&device, cache)
}

#[test]
fn bc3_and_bc7_textures_are_cached_and_sampled() -> Result<()> {
    bc3_and_bc7_textures_are_cached_and_sampled_on(validated_device()?)
}

/// With texture arrays (no sparse residency) the cache reads back the same.
#[test]
fn bc3_and_bc7_textures_are_cached_and_sampled_with_texture_arrays() -> Result<()> {
    bc3_and_bc7_textures_are_cached_and_sampled_on(validated_array_device()?)
}

fn bc3_and_bc7_textures_are_cached_and_sampled_on(device: Arc<Device>) -> Result<()> {
    let mut rng = SplitMix64::new(3_7);
    let mut sources = Vec::new();
    for format in [TextureFormat::Bc3, TextureFormat::Bc7] {
        for (w, h) in [(LAYER_SIZE, LAYER_SIZE), (64, 128), (16, 16)] {
            sources.push(SourceTexture::random(&mut rng, format, w, h));
        }
    }
    let mut commands = CommandContext::new(&device, "BC3 and BC7 cache test")?;
    let mut cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &GpuCacheConfig {
            layer_size: LAYER_SIZE,
            layers: CacheLayers::Fixed(4),
            eviction: Eviction::View,
            memory_budget_bytes: 64 << 20,
            blocks_per_chunk: 64,
            staging_bytes: 1 << 20,
            ..test_cache_config(&[TextureFormat::Bc3, TextureFormat::Bc7], sources.len() as u32)
        },
        &vec![[0, 0, 0, 255]; sources.len()],
    )?;
    // Only the formats asked for get images.
    let formats: Vec<&str> = cache.packing().images().iter().map(|i| i.format.name).collect();
    ensure!(formats == ["BC3", "BC7"], "images of {formats:?}");
    stage_every_level(&mut cache, &mut commands, &sources)?;
    // A format the cache was not made for is refused with a typed error.
    let refused = cache.stage(0, TextureFormat::Bc1, 16, 16, 0, &[0; 128]);
    ensure!(refused.is_err(), "BC1 staged into a BC3/BC7 cache: {refused:?}");
    read_back_every_level(&device, &cache, &mut commands, &sources, &mut rng)?;
    assert_clean_after_dropping(&device, cache)
}

/// The cache reports the mip tail it binds, per format: where it starts,
/// its bytes, single or per layer, and the bytes held, which follow the
/// layers whose textures use tail levels (per layer) or stay put (single).
/// Without a tail (lavapipe) it reports none; under
/// `CITYSTREAM_FORCE_MIP_TAIL` the forced one.
#[test]
fn the_cache_reports_the_mip_tail_it_binds() -> Result<()> {
    let device = validated_device()?;
    let forced = citystream_engine::sparse::forced_mip_tail()?;
    let mut rng = SplitMix64::new(5);
    // Two 64² RGBA8 textures in one layer of 256²: levels 0..6, so levels
    // from 3 on are in a forced tail from 3.
    let sources: Vec<SourceTexture> = (0..2)
        .map(|_| SourceTexture::random(&mut rng, TextureFormat::Rgba8, 64, 64))
        .collect();
    let mut commands = CommandContext::new(&device, "tail report test")?;
    let colormap = vec![[255u8; 4]; sources.len()];
    let mut cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &test_cache_config(&[TextureFormat::Rgba8], sources.len() as u32),
        &colormap,
    )?;
    let before = cache.format_tails();
    ensure!(before.len() == 1 && before[0].format == "RGBA8", "{before:?}");
    let tail = &before[0];
    match forced {
        None => ensure!(
            tail.first_level.is_none() && tail.bytes_per_tail == 0 && tail.held_bytes == 0,
            "lavapipe has no tail: {tail:?}"
        ),
        Some(forced) => {
            ensure!(
                tail.first_level == Some(forced.first_lod) && tail.single == forced.single && tail.synthetic,
                "the forced tail {forced:?} reported as {tail:?}"
            );
            // A single tail is bound with the images; per-layer tails not yet.
            let held_at_start = if forced.single { tail.bytes_per_tail } else { 0 };
            ensure!(tail.held_bytes == held_at_start, "{tail:?}");
        }
    }
    stage_every_level(&mut cache, &mut commands, &sources)?;
    read_back_every_level(&device, &cache, &mut commands, &sources, &mut rng)?;
    let after = &cache.format_tails()[0];
    // Both textures share one layer, so one layer tail, or the single tail.
    let held = if after.first_level.is_some() {
        after.bytes_per_tail
    } else {
        0
    };
    ensure!(after.held_bytes == held, "after loading: {after:?}");
    ensure!(
        cache.utilisation().tail_bytes == held,
        "utilisation {:?} against {after:?}",
        cache.utilisation()
    );
    assert_clean_after_dropping(&device, cache)
}
