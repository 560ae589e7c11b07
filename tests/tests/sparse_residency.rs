//! A sparse 2D-array image with a full mip chain: bind blocks at two levels
//! with `vkQueueBindSparse` (its semaphore gates the graphics-queue copy and
//! sampling), copy texels in, sample with `GL_ARB_sparse_texture2`, check the
//! resident values and the non-resident residency code, then unbind one block
//! and check it reads as non-resident.

use anyhow::{ensure, Context, Result};
use citystream_engine::buffer::{Buffer, BufferDesc};
use citystream_engine::commands::{CommandContext, Semaphore, SemaphoreWait};
use citystream_engine::gpu_allocator::MemoryLocation;
use citystream_engine::gpu_types::{ProbePoint, ProbeResult};
use citystream_engine::probe::SparseProbe;
use citystream_engine::sparse::{SparseBlockBind, SparseImage, SparseImageDesc, SparseMemoryChunk, TexelUpload};
use citystream_engine::vk;
use citystream_tests::{assert_no_validation_errors, validated_device};

const SIDE: u32 = 256;
const LAYERS: u32 = 2;

/// Texel pattern of level `mip` at (x, y): distinct per level and position.
fn texel(mip: u32, x: u32, y: u32) -> [u8; 4] {
    [(x * (1 << mip)) as u8, (y * (1 << mip)) as u8, 40 + 60 * mip as u8, 255]
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

#[test]
fn bind_copy_sample_unbind() -> Result<()> {
    let device = validated_device()?;
    let mips = 32 - SIDE.leading_zeros();
    let image = SparseImage::new(
        &device,
        SparseImageDesc {
            width: SIDE,
            height: SIDE,
            layers: LAYERS,
            mips,
            format: vk::Format::R8G8B8A8_UNORM,
        },
        "residency test image",
    )?;
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
    ensure!(
        image.mip_tail_first_lod() > 2,
        "level 2 must be bindable per block (mip tail starts at {})",
        image.mip_tail_first_lod()
    );

    let chunk = SparseMemoryChunk::new(&device, &image, 2, "residency test blocks")?;
    let block_size = image.block_size();
    let level0_block = SparseBlockBind {
        layer: 1,
        mip: 0,
        x: 1,
        y: 0,
        memory: chunk.block(0, block_size),
    };
    let level2_block = SparseBlockBind {
        layer: 1,
        mip: 2,
        x: 0,
        y: 0,
        memory: chunk.block(1, block_size),
    };
    ensure!(level0_block.memory.is_some() && level2_block.memory.is_some());
    let bound = Semaphore::new(&device, "blocks bound")?;
    let entries = image.bind(&[level0_block, level2_block], &[bound.raw()], vk::Fence::null())?;
    ensure!(entries == 2, "two separate blocks make two bind entries, got {entries}");

    // Upload the texels of both bound regions.
    let (r0_offset, r0_extent) = image.block_region(0, 1, 0)?;
    let (r2_offset, r2_extent) = image.block_region(2, 0, 0)?;
    let mut bytes = level_bytes(
        0,
        r0_offset.x as u32,
        r0_offset.y as u32,
        r0_extent.width,
        r0_extent.height,
    );
    let level2_start = bytes.len() as u64;
    bytes.extend(level_bytes(
        2,
        r2_offset.x as u32,
        r2_offset.y as u32,
        r2_extent.width,
        r2_extent.height,
    ));
    let mut staging = Buffer::new(
        &device,
        BufferDesc {
            size: bytes.len() as u64,
            usage: vk::BufferUsageFlags::TRANSFER_SRC,
            location: MemoryLocation::CpuToGpu,
        },
        "residency test staging",
    )?;
    staging.write(0, &bytes)?;
    let mut commands = CommandContext::new(&device, "residency test")?;
    let cmd = commands.begin()?;
    image.record_layout(cmd, vk::ImageLayout::UNDEFINED, vk::ImageLayout::TRANSFER_DST_OPTIMAL);
    image.record_copies(
        cmd,
        staging.raw(),
        &[
            TexelUpload {
                layer: 1,
                mip: 0,
                x: r0_offset.x as u32,
                y: r0_offset.y as u32,
                width: r0_extent.width,
                height: r0_extent.height,
                buffer_offset: 0,
            },
            TexelUpload {
                layer: 1,
                mip: 2,
                x: r2_offset.x as u32,
                y: r2_offset.y as u32,
                width: r2_extent.width,
                height: r2_extent.height,
                buffer_offset: level2_start,
            },
        ],
    )?;
    image.record_layout(
        cmd,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
    );
    // The copy must wait for the sparse bind on the same queue.
    commands.submit_and_wait(&[SemaphoreWait::binary(bound.raw(), vk::PipelineStageFlags2::COPY)])?;

    let first_resident_x = gw; // first texel of block 1 on level 0
    let last_x = SIDE - 1;
    let level2_side = SIDE >> 2;
    let points = vec![
        // Resident: inside and at both edges of the bound level-0 block.
        at(1, 0, first_resident_x, 0),
        at(1, 0, first_resident_x + 7, 5),
        at(1, 0, last_x, gh - 1),
        // Non-resident: the neighbouring block, the same block of layer 0, level 1.
        at(1, 0, first_resident_x - 1, 0),
        at(0, 0, first_resident_x, 0),
        at(1, 1, 5, 5),
        // Resident: level 2 (one block covers it).
        at(1, 2, 0, 0),
        at(1, 2, level2_side - 1, level2_side - 1),
        at(1, 2, 17, 33),
    ];
    let expected_resident = [true, true, true, false, false, false, true, true, true];
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

    // Unbind the level-0 block; level 2 stays.
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
        let still = expected_resident[i] && points[i].lod as u32 == 2;
        ensure!(
            (result.resident == 1) == still,
            "after unbind, probe {i} at {:?}: resident = {}, expected {still}",
            points[i],
            result.resident
        );
    }
    device.wait_idle()?;
    drop(probe);
    drop(commands);
    drop(image);
    drop(chunk);
    assert_no_validation_errors(&device)
}

#[test]
fn out_of_range_blocks_are_refused() -> Result<()> {
    let device = validated_device()?;
    let image = SparseImage::new(
        &device,
        SparseImageDesc {
            width: 256,
            height: 256,
            layers: 1,
            mips: 9,
            format: vk::Format::R8G8B8A8_UNORM,
        },
        "range test image",
    )?;
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
    let too_many_mips = SparseImage::new(
        &device,
        SparseImageDesc {
            width: 64,
            height: 64,
            layers: 1,
            mips: 8,
            format: vk::Format::R8G8B8A8_UNORM,
        },
        "bad mips",
    );
    ensure!(too_many_mips.is_err(), "64x64 has 7 levels; 8 must be refused");
    drop(image);
    assert_no_validation_errors(&device)
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
