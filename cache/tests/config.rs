//! Configuration: granularity conversion and validation errors.

mod common;

use citystream_cache::{
    CacheConfig, CacheError, ConfigError, DeviceLimits, Granularity, GranularityUnit, ImageConfig, ImageDesc,
    TexelFormat, TextureCache,
};

fn lavapipe_config(layer_size: u32, layer_count: u32) -> CacheConfig {
    let limits = DeviceLimits::lavapipe_reference();
    CacheConfig {
        images: vec![
            ImageConfig {
                format: TexelFormat::BC1,
                granularity: Granularity::texels(512, 256),
                layer_size,
                layer_count,
                mip_tail: None,
            },
            ImageConfig {
                format: TexelFormat::RGBA8,
                granularity: Granularity::texels(128, 128),
                layer_size,
                layer_count,
                mip_tail: None,
            },
        ],
        limits,
        memory_budget_bytes: 256 << 20,
        virtual_budget_bytes: 2 << 30,
        blocks_per_chunk: 64,
    }
}

/// [`lavapipe_config`] edited by `edit`, validated.
fn validate_edited(
    layer_size: u32,
    layer_count: u32,
    edit: impl FnOnce(&mut CacheConfig),
) -> Result<Vec<ImageDesc>, ConfigError> {
    let mut config = lavapipe_config(layer_size, layer_count);
    edit(&mut config);
    config.validate()
}

#[test]
fn bc1_granularity_reported_in_blocks_converts_to_texels() -> Result<(), ConfigError> {
    let block = DeviceLimits::lavapipe_reference().sparse_block_bytes;
    let unit = GranularityUnit::infer(&TexelFormat::BC1, 128, 64, block);
    assert_eq!(unit, Some(GranularityUnit::TexelBlocks));
    let bc1 = Granularity::from_device_report(&TexelFormat::BC1, 128, 64, GranularityUnit::TexelBlocks)?;
    assert_eq!(bc1, Granularity::texels(512, 256));
    // 128x64 blocks of 8 bytes fill exactly one 64 KiB sparse block.
    assert_eq!(TexelFormat::BC1.image_bytes(bc1.width, bc1.height), block);

    let rgba = Granularity::from_device_report(&TexelFormat::RGBA8, 128, 128, GranularityUnit::TexelBlocks)?;
    assert_eq!(rgba, Granularity::texels(128, 128));
    assert_eq!(
        GranularityUnit::infer(&TexelFormat::RGBA8, 128, 128, block),
        Some(GranularityUnit::Texels)
    );
    // A BC1 report already in texels: 512x256 texels are 64 KiB as texels.
    assert_eq!(
        GranularityUnit::infer(&TexelFormat::BC1, 512, 256, block),
        Some(GranularityUnit::Texels)
    );
    assert_eq!(GranularityUnit::infer(&TexelFormat::BC1, 64, 64, block), None);
    Ok(())
}

#[test]
fn bad_granularity_reports_are_errors() {
    let zero = Granularity::from_device_report(&TexelFormat::BC1, 0, 64, GranularityUnit::TexelBlocks);
    assert!(matches!(zero, Err(ConfigError::BadGranularity { format: "BC1", .. })));
    let odd = Granularity::from_device_report(&TexelFormat::RGBA8, 96, 128, GranularityUnit::Texels);
    assert!(matches!(odd, Err(ConfigError::BadGranularity { format: "RGBA8", .. })));
    // Texel granularity smaller than one BC block.
    let small = Granularity::from_device_report(&TexelFormat::BC1, 2, 2, GranularityUnit::Texels);
    assert!(matches!(small, Err(ConfigError::BadGranularity { .. })));
}

#[test]
fn virtual_size_counts_block_padded_mip_chain() -> Result<(), ConfigError> {
    let config = lavapipe_config(1024, 4);
    let descs = config.validate()?;
    // RGBA8, 128x128 blocks: levels 1024..1 need 64+16+4+1+1+1+1+1+1+1+1 blocks.
    assert_eq!(descs[1].mip_levels, 11);
    assert_eq!(descs[1].blocks_per_layer, 64 + 16 + 4 + 8);
    // BC1, 512x256 texel blocks: 2x4 + 1x2 + 1 per level below.
    assert_eq!(descs[0].blocks_per_layer, 8 + 2 + 9);
    assert_eq!(descs[1].virtual_bytes(), 4 * 92 * 65536);
    Ok(())
}

#[test]
fn virtual_budget_is_enforced() {
    // 4096² RGBA8 with 128² blocks: 1024+256+64+16+4+1*8 = 1372 blocks a
    // layer, 86 MiB; 64 layers are 5.4 GiB, over a 2 GiB budget.
    let config = lavapipe_config(4096, 64);
    match config.validate() {
        Err(ConfigError::VirtualBudgetExceeded {
            needed_bytes,
            budget_bytes,
            largest_image,
            ..
        }) => {
            assert_eq!(budget_bytes, 2 << 30);
            assert!(needed_bytes > budget_bytes);
            assert_eq!(largest_image, 1);
        }
        other => panic!("expected VirtualBudgetExceeded, got {other:?}"),
    }
    let config = lavapipe_config(4096, 8);
    assert!(config.validate().is_ok(), "8 layers of both formats fit in 2 GiB");
}

#[test]
fn device_limits_are_enforced() {
    assert!(matches!(
        validate_edited(1024, 4, |c| c.images[1].layer_count = 2049),
        Err(ConfigError::BadLayerCount {
            image: 1,
            layer_count: 2049,
            max_layers: 2048,
            ..
        })
    ));
    assert!(matches!(
        validate_edited(1024, 4, |c| c.images[0].layer_count = 0),
        Err(ConfigError::BadLayerCount { image: 0, .. })
    ));

    assert!(matches!(
        validate_edited(1024, 1, |c| c.limits.max_image_dimension_2d = 512),
        Err(ConfigError::BadLayerSize { layer_size: 1024, .. })
    ));
    assert!(matches!(
        validate_edited(1024, 1, |c| c.images[1].layer_size = 1000),
        Err(ConfigError::BadLayerSize {
            image: 1,
            layer_size: 1000,
            ..
        })
    ));
    assert!(matches!(
        validate_edited(1024, 1, |c| c.images[0].layer_size = 2),
        Err(ConfigError::BadLayerSize { image: 0, .. })
    ));
}

#[test]
fn budgets_and_images_are_checked() {
    assert!(matches!(
        validate_edited(1024, 1, |c| c.memory_budget_bytes = 1000),
        Err(ConfigError::MemoryBudgetTooSmall { budget_bytes: 1000, .. })
    ));
    assert!(matches!(
        validate_edited(1024, 1, |c| c.limits.sparse_block_bytes = 0),
        Err(ConfigError::ZeroBlockSize)
    ));
    assert!(matches!(
        validate_edited(1024, 1, |c| c.blocks_per_chunk = 0),
        Err(ConfigError::ZeroChunk)
    ));
    let mut config = lavapipe_config(1024, 1);
    config.images.clear();
    assert!(matches!(TextureCache::new(&config), Err(ConfigError::NoImages)));
}

#[test]
fn image_for_format_finds_the_right_image() -> Result<(), ConfigError> {
    let cache = TextureCache::new(&lavapipe_config(1024, 2))?;
    assert_eq!(cache.image_for_format(&TexelFormat::BC1), Some(0));
    assert_eq!(cache.image_for_format(&TexelFormat::RGBA8), Some(1));
    let bc7 = TexelFormat {
        name: "BC7",
        block_width: 4,
        block_height: 4,
        bytes_per_block: 16,
    };
    assert_eq!(cache.image_for_format(&bc7), None);
    assert_eq!(cache.images_for_format(&bc7), Vec::<u32>::new());
    let images: Vec<ImageDesc> = cache.images();
    assert_eq!(images.len(), 2);
    assert_eq!(images[0].layer_count, 2);
    Ok(())
}

#[test]
fn a_format_may_have_several_images() -> Result<(), ConfigError> {
    let mut config = lavapipe_config(1024, 2);
    config.images.push(config.images[0]);
    let cache = TextureCache::new(&config)?;
    assert_eq!(cache.image_for_format(&TexelFormat::BC1), Some(0));
    assert_eq!(cache.images_for_format(&TexelFormat::BC1), vec![0, 2]);
    assert_eq!(cache.images_for_format(&TexelFormat::RGBA8), vec![1]);
    Ok(())
}

#[test]
fn textures_of_a_format_fill_each_of_its_images_then_reuse_the_oldest_layer() -> Result<(), Box<dyn std::error::Error>>
{
    // Two BC1 images of one layer each; a 1024² texture fills a layer.
    let mut config = lavapipe_config(1024, 1);
    config.images.push(config.images[0]);
    let cache = TextureCache::new(&config)?;
    let bc1 = cache.images_for_format(&TexelFormat::BC1);
    let first = cache.try_insert_in(&bc1, 1, 1024, 1024)?;
    let second = cache.try_insert_in(&bc1, 2, 1024, 1024)?;
    assert_eq!(
        (first.image, second.image),
        (0, 2),
        "the second image takes what the first cannot"
    );
    assert!(matches!(
        cache.try_insert_in(&bc1, 3, 1024, 1024),
        Err(CacheError::NoLayer { image: 0, extent: 1024 })
    ));
    // The ring over both images reuses the oldest layer: texture 1's.
    let third = cache.insert_in(&bc1, 3, 1024, 1024)?;
    assert_eq!(third.image, 0);
    assert!(!cache.is_live(&first) && cache.is_live(&second) && cache.is_live(&third));
    let fourth = cache.insert_in(&bc1, 4, 1024, 1024)?;
    assert_eq!(fourth.image, 2);
    assert!(!cache.is_live(&second) && cache.is_live(&third));
    Ok(())
}
