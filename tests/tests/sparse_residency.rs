//! A sparse 2D-array image with a full mip chain: bind blocks at two levels
//! and the mip tail where the device has one (or `CITYSTREAM_FORCE_MIP_TAIL`
//! makes one) with `vkQueueBindSparse` (its semaphore gates the
//! graphics-queue copy and sampling), copy texels in, sample with
//! `GL_ARB_sparse_texture2`, check the resident values and the non-resident
//! residency code, then unbind one block and check it reads as non-resident.
//! And the opaque bind (how a GPU's tails are bound) on a whole image.

use std::sync::Arc;

use anyhow::{ensure, Context, Result};
use citystream_engine::commands::{CommandContext, Semaphore, SemaphoreWait};
use citystream_engine::device::Device;
use citystream_engine::gpu_types::{ProbePoint, ProbeResult};
use citystream_engine::probe::SparseProbe;
use citystream_engine::sparse::{
    bind_opaque_and_wait, SparseBlockBind, SparseImage, SparseImageDesc, SparseMemoryChunk, TailBlockBind, TexelUpload,
};
use citystream_engine::vk;
use citystream_tests::{
    assert_clean_after_dropping, assert_no_validation_errors, copy_into_new_sparse_image, validated_device,
};

const SIDE: u32 = 256;
const LAYERS: u32 = 2;

/// Texel pattern of level `mip` at (x, y): distinct per level and position.
fn texel(mip: u32, x: u32, y: u32) -> [u8; 4] {
    [
        (x * (1 << mip)) as u8,
        (y * (1 << mip)) as u8,
        (40 + 37 * mip) as u8,
        255,
    ]
}

fn level_bytes(mip: u32, x0: u32, y0: u32, w: u32, h: u32) -> Vec<u8> {
    let mut bytes = Vec::with_capacity((w * h * 4) as usize);
    for y in y0..y0 + h {
        for x in x0..x0 + w {
            bytes.extend_from_slice(&texel(mip, x, y));
        }
    }
    bytes
}

/// A probe at the centre of texel (x, y) of `mip` in `layer`.
fn at(layer: u32, mip: u32, x: u32, y: u32) -> ProbePoint {
    let side = (SIDE >> mip) as f32;
    ProbePoint {
        uv: [(x as f32 + 0.5) / side, (y as f32 + 0.5) / side],
        layer: layer as f32,
        lod: mip as f32,
    }
}

fn to_u8(result: &ProbeResult) -> [u8; 4] {
    result.value.map(|c| (c * 255.0).round() as u8)
}

/// A sparse RGBA8 image `side` texels square, of `layers` layers and `mips` levels.
fn rgba8_image(
    device: &Arc<Device>,
    side: u32,
    layers: u32,
    mips: u32,
    name: &str,
) -> citystream_engine::Result<SparseImage> {
    let desc = SparseImageDesc {
        width: side,
        height: side,
        layers,
        mips,
        format: vk::Format::R8G8B8A8_UNORM,
    };
    SparseImage::new(device, desc, name)
}

#[test]
fn bind_copy_sample_unbind() -> Result<()> {
    let device = validated_device()?;
    let mips = 32 - SIDE.leading_zeros();
    let image = rgba8_image(&device, SIDE, LAYERS, mips, "residency test image")?;
    let (gw, gh) = image.granularity();
    ensure!(
        gw > 0 && gh > 0 && image.block_size() > 0,
        "device reported no sparse granularity"
    );
    // The test needs level 0 to span at least two blocks across, so one
    // block can be resident next to a non-resident one.
    ensure!(
        SIDE >= 2 * gw,
        "granularity {gw}x{gh} too coarse for a {SIDE}-texel test image"
    );
    // A second level bound per block: level 2 where the device binds it so
    // (lavapipe), else the last level above the mip tail (a GPU: level 1).
    let tail = image.mip_tail();
    let has_tail = tail.first_lod < mips;
    let small = 2.min(tail.first_lod.saturating_sub(1));
    ensure!(
        small >= 1,
        "the mip tail starts at level {}: no small level to bind",
        tail.first_lod
    );
    let tail_blocks = image.tail_blocks();
    // Layer 1's tail (the image's, when single) is bound opaquely.
    let tail_layer = if tail.single { 0 } else { 1 };

    let chunk = SparseMemoryChunk::new(&device, &image, 2 + u64::from(tail_blocks), "residency test blocks")?;
    let block_size = image.block_size();
    let level0_block = SparseBlockBind {
        layer: 1,
        mip: 0,
        x: 1,
        y: 0,
        memory: chunk.block(0, block_size),
    };
    let small_block = SparseBlockBind {
        layer: 1,
        mip: small,
        x: 0,
        y: 0,
        memory: chunk.block(1, block_size),
    };
    ensure!(level0_block.memory.is_some() && small_block.memory.is_some());
    let tail_binds: Vec<_> = (0..tail_blocks)
        .map(|index| TailBlockBind {
            layer: tail_layer,
            index,
            memory: chunk.block(2 + u64::from(index), block_size),
        })
        .collect();
    let bound = Semaphore::new(&device, "blocks bound")?;
    let entries = image.bind_with_tail(
        &[level0_block, small_block],
        &tail_binds,
        &[bound.raw()],
        vk::Fence::null(),
    )?;
    ensure!(
        entries >= 2 + usize::from(has_tail),
        "two separate blocks and a tail make at least {} bind entries, got {entries}",
        2 + usize::from(has_tail)
    );
    if has_tail {
        let refused = image.bind(
            &[SparseBlockBind {
                mip: tail.first_lod,
                ..small_block
            }],
            &[],
            vk::Fence::null(),
        );
        ensure!(refused.is_err(), "a per-block bind of a tail level must be refused");
    }

    // Upload the texels of the bound regions: a level-0 block, the small
    // level's block and every level of the tail.
    let (r0_offset, r0_extent) = image.block_region(0, 1, 0)?;
    let (rs_offset, rs_extent) = image.block_region(small, 0, 0)?;
    let mut regions = vec![
        (
            0,
            r0_offset.x as u32,
            r0_offset.y as u32,
            r0_extent.width,
            r0_extent.height,
        ),
        (
            small,
            rs_offset.x as u32,
            rs_offset.y as u32,
            rs_extent.width,
            rs_extent.height,
        ),
    ];
    if has_tail {
        for mip in tail.first_lod..mips {
            let (w, h) = image.level_extent(mip);
            regions.push((mip, 0, 0, w, h));
        }
    }
    let mut bytes = Vec::new();
    let mut uploads = Vec::new();
    for &(mip, x, y, width, height) in &regions {
        uploads.push(TexelUpload {
            layer: 1,
            mip,
            x,
            y,
            width,
            height,
            buffer_offset: bytes.len() as u64,
        });
        bytes.extend(level_bytes(mip, x, y, width, height));
    }
    let mut commands = CommandContext::new(&device, "residency test")?;
    // The copy must wait for the sparse bind on the same queue.
    copy_into_new_sparse_image(
        &device,
        &mut commands,
        &image,
        &uploads,
        &bytes,
        &[SemaphoreWait::binary(bound.raw(), vk::PipelineStageFlags2::COPY)],
    )?;

    let first_resident_x = gw; // first texel of block 1 on level 0
    let last_x = SIDE - 1;
    let small_side = SIDE >> small;
    let mut points = vec![
        // Resident: inside and at both edges of the bound level-0 block.
        at(1, 0, first_resident_x, 0),
        at(1, 0, first_resident_x + 7, 5),
        at(1, 0, last_x, gh - 1),
        // Non-resident: the neighbouring block, the same block of layer 0.
        at(0, 0, first_resident_x, 0),
        at(1, 0, first_resident_x - 1, 0),
        // Resident: the small level's block.
        at(1, small, 0, 0),
        at(1, small, rs_extent.width - 1, rs_extent.height - 1),
        at(1, small, 17 % small_side, 33 % small_side),
    ];
    let mut expected_resident = vec![true, true, true, false, false, true, true, true];
    if small > 1 {
        // Level 1 has no bound block.
        points.push(at(1, 1, 5, 5));
        expected_resident.push(false);
    }
    if has_tail {
        for mip in tail.first_lod..mips {
            let (w, h) = image.level_extent(mip);
            points.push(at(1, mip, w - 1, h - 1));
            expected_resident.push(true);
        }
    }
    let probe = SparseProbe::new(&device, 64)?;
    let results = probe.run(&mut commands, image.view(), &points, &[])?;
    for (i, (result, point)) in results.iter().zip(&points).enumerate() {
        ensure!(
            (result.resident == 1) == expected_resident[i],
            "probe {i} at {point:?}: resident = {}, code {}, expected resident = {}",
            result.resident,
            result.raw_code,
            expected_resident[i]
        );
        if expected_resident[i] {
            let mip = point.lod as u32;
            let side = (SIDE >> mip) as f32;
            let (x, y) = ((point.uv[0] * side) as u32, (point.uv[1] * side) as u32);
            ensure!(
                to_u8(result) == texel(mip, x, y),
                "probe {i}: level {mip} texel ({x}, {y}) read {:?}, expected {:?}",
                to_u8(result),
                texel(mip, x, y)
            );
        }
    }

    // Unbind the level-0 block; the small level and the tail stay.
    let unbound = Semaphore::new(&device, "block unbound")?;
    image.bind(
        &[SparseBlockBind {
            memory: None,
            ..level0_block
        }],
        &[unbound.raw()],
        vk::Fence::null(),
    )?;
    let after = probe
        .run(
            &mut commands,
            image.view(),
            &points,
            &[SemaphoreWait::binary(
                unbound.raw(),
                vk::PipelineStageFlags2::COMPUTE_SHADER,
            )],
        )
        .context("probing after the unbind")?;
    for (i, result) in after.iter().enumerate() {
        let still = expected_resident[i] && points[i].lod as u32 != 0;
        ensure!(
            (result.resident == 1) == still,
            "after unbind, probe {i} at {:?}: resident = {}, expected {still}",
            points[i],
            result.resident
        );
    }
    device.wait_idle()?;
    assert_clean_after_dropping(&device, (probe, commands, image, chunk))
}

/// The opaque bind path (how mip tails are bound on a GPU), where lavapipe
/// can run it: a sparse image's whole memory bound opaquely, every level
/// copied in and sampled back resident and exact.
#[test]
fn an_opaquely_bound_sparse_image_samples_every_level() -> Result<()> {
    let device = validated_device()?;
    let side = 64u32;
    let mips = 32 - side.leading_zeros();
    let image = rgba8_image(&device, side, 1, mips, "opaque bind test image")?;
    let block_size = image.block_size();
    let bytes_bound = image.opaque_bytes().next_multiple_of(block_size);
    let chunk = SparseMemoryChunk::new(&device, &image, bytes_bound / block_size, "opaque bind test memory")?;
    let (memory, memory_offset) = chunk.block(0, block_size).context("the chunk's first block")?;
    // One range per block, as the cache binds a tail's blocks. (Lavapipe,
    // Mesa 25.0.7, made only the first block of a several-block range resident.)
    let binds: Vec<vk::SparseMemoryBind> = (0..bytes_bound / block_size)
        .map(|block| vk::SparseMemoryBind {
            resource_offset: block * block_size,
            size: block_size,
            memory,
            memory_offset: memory_offset + block * block_size,
            flags: vk::SparseMemoryBindFlags::empty(),
        })
        .collect();
    bind_opaque_and_wait(&device, &[(image.raw(), binds.as_slice())])?;

    let mut bytes = Vec::new();
    let mut uploads = Vec::new();
    for mip in 0..mips {
        let (w, h) = image.level_extent(mip);
        uploads.push(TexelUpload {
            layer: 0,
            mip,
            x: 0,
            y: 0,
            width: w,
            height: h,
            buffer_offset: bytes.len() as u64,
        });
        bytes.extend(level_bytes(mip, 0, 0, w, h));
    }
    let mut commands = CommandContext::new(&device, "opaque bind test")?;
    copy_into_new_sparse_image(&device, &mut commands, &image, &uploads, &bytes, &[])?;

    let side_at = |mip: u32| (side >> mip).max(1);
    let points: Vec<ProbePoint> = (0..mips)
        .flat_map(|mip| {
            let s = side_at(mip);
            [(0, 0), (s - 1, s - 1), (s / 2, s / 3)].map(|(x, y)| ProbePoint {
                uv: [(x as f32 + 0.5) / s as f32, (y as f32 + 0.5) / s as f32],
                layer: 0.0,
                lod: mip as f32,
            })
        })
        .collect();
    let probe = SparseProbe::new(&device, 64)?;
    let results = probe.run(&mut commands, image.view(), &points, &[])?;
    for (i, (result, point)) in results.iter().zip(&points).enumerate() {
        let mip = point.lod as u32;
        let s = side_at(mip) as f32;
        let (x, y) = ((point.uv[0] * s) as u32, (point.uv[1] * s) as u32);
        ensure!(
            result.resident == 1,
            "probe {i} at {point:?}: not resident after the opaque bind"
        );
        ensure!(
            to_u8(result) == texel(mip, x, y),
            "probe {i}: level {mip} texel ({x}, {y}) read {:?}, expected {:?}",
            to_u8(result),
            texel(mip, x, y)
        );
    }
    device.wait_idle()?;
    assert_clean_after_dropping(&device, (probe, commands, image, chunk))
}

#[test]
fn out_of_range_blocks_are_refused() -> Result<()> {
    let device = validated_device()?;
    let image = rgba8_image(&device, 256, 1, 9, "range test image")?;
    let (bw, _) = image.level_blocks(0);
    let error = image
        .bind(
            &[SparseBlockBind {
                layer: 0,
                mip: 0,
                x: bw,
                y: 0,
                memory: None,
            }],
            &[],
            vk::Fence::null(),
        )
        .expect_err("a block past the level edge must be refused");
    ensure!(error.to_string().contains("outside"), "unclear error: {error}");
    let too_many_mips = rgba8_image(&device, 64, 1, 8, "bad mips");
    ensure!(too_many_mips.is_err(), "64x64 has 7 levels; 8 must be refused");
    assert_clean_after_dropping(&device, image)
}

#[test]
fn granularity_spans_exactly_one_memory_block_for_every_cache_format() -> Result<()> {
    let device = validated_device()?;
    for (format, bytes_per_block, texels_per_block) in [
        (vk::Format::R8G8B8A8_UNORM, 4u64, 1u64),
        (vk::Format::BC1_RGB_UNORM_BLOCK, 8, 16),
    ] {
        let image = SparseImage::new(
            &device,
            SparseImageDesc {
                width: 1024,
                height: 1024,
                layers: 1,
                mips: 11,
                format,
            },
            "granularity test",
        )?;
        let (gw, gh) = image.granularity();
        let bytes = u64::from(gw) * u64::from(gh) * bytes_per_block / texels_per_block;
        ensure!(
            bytes == image.block_size(),
            "{format:?}: granularity {gw}x{gh} texels spans {bytes} bytes, the block is {}",
            image.block_size()
        );
    }
    assert_no_validation_errors(&device)
}
