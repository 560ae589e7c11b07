//! The Vulkan `SparseBinder`: one bind per batch, adjacent blocks with
//! contiguous memory merged into one entry, a timeline value the copy waits
//! on, and clear errors for blocks or memory it does not know.

use std::sync::Arc;

use anyhow::{ensure, Result};
use citystream_cache::{BindError, BindOp, BlockKey, MemorySlot, SparseBinder};
use citystream_engine::binder::VulkanBinder;
use citystream_engine::commands::CommandContext;
use citystream_engine::gpu_types::ProbePoint;
use citystream_engine::probe::SparseProbe;
use citystream_engine::sparse::{SparseImage, SparseImageDesc, SparseMemoryChunk, TexelUpload};
use citystream_engine::vk;
use citystream_tests::{assert_clean_after_dropping, copy_into_new_sparse_image, validated_device};

fn key(x: u32) -> BlockKey {
    BlockKey {
        image: 0,
        layer: 0,
        mip: 0,
        x,
        y: 0,
    }
}

/// A one-level 1024 x 256 RGBA8 sparse image: four or more blocks across.
fn test_image(device: &Arc<citystream_engine::Device>, name: &str) -> Result<SparseImage> {
    let desc = SparseImageDesc {
        width: 1024,
        height: 256,
        layers: 1,
        mips: 1,
        format: vk::Format::R8G8B8A8_UNORM,
    };
    Ok(SparseImage::new(device, desc, name)?)
}

#[test]
fn batches_merge_bind_and_unbind() -> Result<()> {
    let device = validated_device()?;
    let probe_image = test_image(&device, "binder test image")?;
    let (blocks_across, _) = probe_image.level_blocks(0);
    ensure!(
        blocks_across >= 4,
        "need four blocks across level 0, got {blocks_across}"
    );
    let (gw, gh) = probe_image.granularity();
    let block_size = probe_image.block_size();
    let image = Arc::new(probe_image);
    let mut binder = VulkanBinder::new(&device, vec![Arc::clone(&image)])?;
    let chunk = binder.add_chunk(SparseMemoryChunk::new(&device, &image, 4, "binder test chunk")?)?;

    // Blocks 0..3 with consecutive memory: one merged entry.
    let batch: Vec<BindOp> = (0..3)
        .map(|x| BindOp::Bind {
            block: key(x),
            memory: MemorySlot {
                chunk,
                offset: u64::from(x) * block_size,
            },
        })
        .collect();
    let report = binder.submit(&batch)?;
    ensure!(
        report.blocks == 3 && report.entries == 1,
        "expected 3 blocks in 1 entry, got {report:?}"
    );
    ensure!(binder.last_signalled() == 1);

    // Fill the three blocks, waiting on the batch's timeline value.
    let width = 3 * gw;
    let bytes: Vec<u8> = (0..width * gh).flat_map(|i| [(i % 251) as u8, 7, 9, 255]).collect();
    let mut commands = CommandContext::new(&device, "binder test")?;
    copy_into_new_sparse_image(
        &device,
        &mut commands,
        &image,
        &[TexelUpload {
            layer: 0,
            mip: 0,
            x: 0,
            y: 0,
            width,
            height: gh,
            buffer_offset: 0,
        }],
        &bytes,
        &[binder.wait_for_last_batch(vk::PipelineStageFlags2::COPY)],
    )?;

    let probe = SparseProbe::new(&device, 16)?;
    let points: Vec<ProbePoint> = (0..4)
        .map(|b| ProbePoint {
            uv: [((b * gw) as f32 + 3.5) / 1024.0, 0.5 / 256.0],
            layer: 0.0,
            lod: 0.0,
        })
        .collect();
    let results = probe.run(&mut commands, image.view(), &points, &[])?;
    let resident: Vec<u32> = results.iter().map(|r| r.resident).collect();
    ensure!(resident == [1, 1, 1, 0], "residency after bind: {resident:?}");
    let expected_red = ((gw + 3) % 251) as f32 / 255.0;
    ensure!(
        (results[1].value[0] - expected_red).abs() < 1e-3,
        "block 1 read {:?}",
        results[1].value
    );

    // Unbind the middle block.
    let report = binder.submit(&[BindOp::Unbind { block: key(1) }])?;
    ensure!(report.blocks == 1 && report.entries == 1);
    let results = probe.run(
        &mut commands,
        image.view(),
        &points,
        &[binder.wait_for_last_batch(vk::PipelineStageFlags2::COMPUTE_SHADER)],
    )?;
    let resident: Vec<u32> = results.iter().map(|r| r.resident).collect();
    ensure!(resident == [1, 0, 1, 0], "residency after unbind: {resident:?}");

    // Errors name what is wrong.
    let unknown = binder.submit(&[BindOp::Unbind {
        block: BlockKey { image: 5, ..key(0) },
    }]);
    ensure!(matches!(unknown, Err(BindError::UnknownBlock { .. })), "{unknown:?}");
    let misaligned = binder.submit(&[BindOp::Bind {
        block: key(3),
        memory: MemorySlot { chunk, offset: 100 },
    }]);
    ensure!(
        matches!(&misaligned, Err(BindError::Rejected { reason, .. }) if reason.contains("block-aligned")),
        "{misaligned:?}"
    );
    let no_chunk = binder.submit(&[BindOp::Bind {
        block: key(3),
        memory: MemorySlot { chunk: 9, offset: 0 },
    }]);
    ensure!(matches!(no_chunk, Err(BindError::Rejected { .. })), "{no_chunk:?}");
    ensure!(binder.submit(&[])?.blocks == 0, "an empty batch costs nothing");

    device.wait_idle()?;
    assert_clean_after_dropping(&device, (probe, commands, binder, image))
}

#[test]
fn the_bind_checker_refuses_a_double_bind_and_a_copy_into_an_unbound_block() -> Result<()> {
    let device = validated_device()?;
    let image = Arc::new(test_image(&device, "bind check image")?);
    let block_size = image.block_size();
    let (gw, gh) = image.granularity();
    let mut binder = VulkanBinder::with_checks(&device, vec![Arc::clone(&image)], true)?;
    let chunk = binder.add_chunk(SparseMemoryChunk::new(&device, &image, 4, "bind check chunk")?)?;
    let at = |x: u32, slot: u64| BindOp::Bind {
        block: key(x),
        memory: MemorySlot {
            chunk,
            offset: slot * block_size,
        },
    };
    binder.submit(&[at(1, 0)])?;
    // The same block again, on other memory, without an unbind: refused before the driver sees it.
    let double = binder.submit(&[at(1, 1)]);
    ensure!(
        matches!(&double, Err(BindError::Rejected { reason, .. })
            if reason.contains("image 0 layer 0 level 0 block (1, 0)") && reason.contains("without an unbind")),
        "{double:?}"
    );
    ensure!(binder.last_signalled() == 1, "the refused batch was submitted");
    ensure!(binder.checked() == Some((1, 1)), "{:?}", binder.checked());
    // A copy covering block 1 passes; one reaching into block 2 (not bound) is refused.
    let copy = |x: u32, width: u32| TexelUpload {
        layer: 0,
        mip: 0,
        x,
        y: 0,
        width,
        height: gh,
        buffer_offset: 0,
    };
    binder.check_copy(0, &copy(gw, gw))?;
    let into_unbound = binder.check_copy(0, &copy(gw, gw + 1));
    ensure!(
        matches!(&into_unbound, Err(e) if e.to_string().contains("image 0 layer 0 level 0 block (2, 0), which is not bound")),
        "{into_unbound:?}"
    );
    // Unbinding it twice is refused too.
    binder.submit(&[BindOp::Unbind { block: key(1) }])?;
    let twice = binder.submit(&[BindOp::Unbind { block: key(1) }]);
    ensure!(
        matches!(&twice, Err(BindError::Rejected { reason, .. }) if reason.contains("is not bound")),
        "{twice:?}"
    );
    device.wait_idle()?;
    assert_clean_after_dropping(&device, (binder, image))
}
