//! A dataset written through the public writer reads back identically, mip by mip.

mod support;

use citystream_dataset::{verify, Dataset, DatasetError, TextureFormat, TexturePack, PACK_HEADER_BYTES};
use support::{mip_extent, write_fixture, TEXTURES};

#[test]
fn every_mip_reads_back_byte_identical_with_one_positioned_read() -> Result<(), DatasetError> {
    let fixture = write_fixture("roundtrip");
    let dataset = Dataset::open(&fixture.dir)?;
    assert_eq!(dataset.textures.len() as usize, TEXTURES.len());
    let mut buf = Vec::new();
    let mut previous_end = PACK_HEADER_BYTES;
    for (id, written) in fixture.textures.iter().enumerate() {
        let id = id as u32;
        let info = dataset.textures.info(id)?;
        assert_eq!(
            (info.format(), info.width(), info.height()),
            (written.format, written.width, written.height)
        );
        assert_eq!(info.mip_count() as usize, written.mips.len());
        // Chains are laid out back to back in id order, right after the header.
        assert_eq!(info.offset(), previous_end);
        previous_end = info.offset() + info.chain_len();
        for (level, expected) in written.mips.iter().enumerate() {
            let level = level as u32;
            let location = dataset.textures.read_mip(id, level, &mut buf)?;
            assert_eq!(&buf, expected, "texture {id} level {level}");
            assert_eq!(
                (location.width, location.height),
                mip_extent(written.width, written.height, level)
            );
            assert_eq!(location.len, expected.len() as u64);
            let mut exact = vec![0u8; expected.len()];
            dataset.textures.read_mip_into(id, level, &mut exact)?;
            assert_eq!(&exact, expected);
        }
        assert_eq!(dataset.colormap.get(id), Some(written.colour));
    }
    assert_eq!(previous_end, dataset.textures.pack_len());
    assert_eq!(dataset.scene, fixture.scene);
    assert_eq!(fixture.summary.pack_bytes, dataset.textures.pack_len());
    assert_eq!(fixture.summary.textures as usize, TEXTURES.len());
    Ok(())
}

#[test]
fn verify_passes_on_a_fresh_dataset_and_counts_every_mip() -> Result<(), DatasetError> {
    let fixture = write_fixture("verify-ok");
    let report = verify(&fixture.dir)?;
    let mips: u64 = TEXTURES.iter().map(|t| u64::from(t.3)).sum();
    let bytes: u64 = fixture
        .textures
        .iter()
        .flat_map(|t| &t.mips)
        .map(|m| m.len() as u64)
        .sum();
    assert_eq!(report.textures as usize, TEXTURES.len());
    assert_eq!(report.mips, mips);
    assert_eq!(report.bytes_read, bytes);
    assert_eq!(report.meshes as usize, fixture.scene.meshes.len());
    Ok(())
}

#[test]
fn mip_sizes_follow_the_block_rules() {
    // BC1 levels below 4x4 still take one 8-byte block; BC3/BC7 blocks are 16 bytes.
    assert_eq!(TextureFormat::Bc1.mip_bytes(4, 32), 8 * 8);
    assert_eq!(TextureFormat::Bc1.mip_bytes(2, 16), 4 * 8);
    assert_eq!(TextureFormat::Bc1.mip_bytes(1, 1), 8);
    assert_eq!(TextureFormat::Bc3.mip_bytes(8, 8), 4 * 16);
    assert_eq!(TextureFormat::Bc7.mip_bytes(2, 2), 16);
    assert_eq!(TextureFormat::Rgba8.mip_bytes(16, 8), 16 * 8 * 4);
    for format in TextureFormat::ALL {
        assert_eq!(TextureFormat::from_code(format.code()), Some(format));
        assert_eq!(TextureFormat::from_name(format.name()), Some(format));
    }
}

#[test]
fn metadata_is_small_per_texture() {
    // 12 bytes of texture record + 4 of checksum index + 4 of colormap per texture, and a
    // 4-byte CRC per mip: a 5.7 M-texture city of 512² textures (10 levels) needs about
    // 5.7 M × (20 + 40) B = 342 MB of host metadata.
    assert_eq!(Dataset::metadata_bytes_per_texture(), 20);
    assert_eq!(Dataset::metadata_bytes_per_mip(), 4);
    let fixture = write_fixture("metadata-bytes");
    let pack = TexturePack::open(&fixture.dir).expect("open");
    let mips: usize = pack.textures().iter().map(|t| t.mip_count() as usize).sum();
    assert_eq!(pack.metadata_bytes(), pack.textures().len() * 16 + mips * 4);
}

#[test]
fn out_of_range_requests_are_errors() -> Result<(), DatasetError> {
    let fixture = write_fixture("out-of-range");
    let pack = TexturePack::open(&fixture.dir)?;
    let mut buf = Vec::new();
    let count = pack.len();
    assert!(
        matches!(pack.read_mip(count, 0, &mut buf), Err(DatasetError::NoSuchTexture { texture, .. }) if texture == count)
    );
    assert!(matches!(
        pack.read_mip(0, 6, &mut buf),
        Err(DatasetError::NoSuchMip {
            level: 6,
            mip_count: 6,
            ..
        })
    ));
    let mut wrong = vec![0u8; 3];
    assert!(matches!(
        pack.read_mip_into(0, 0, &mut wrong),
        Err(DatasetError::InvalidInput(_))
    ));
    Ok(())
}

#[test]
fn concurrent_reads_from_one_pack_agree() -> Result<(), DatasetError> {
    let fixture = write_fixture("concurrent");
    let pack = TexturePack::open(&fixture.dir)?;
    std::thread::scope(|scope| {
        for _ in 0..4 {
            scope.spawn(|| {
                let mut buf = Vec::new();
                for (id, written) in fixture.textures.iter().enumerate() {
                    for (level, expected) in written.mips.iter().enumerate() {
                        pack.read_mip(id as u32, level as u32, &mut buf).expect("read mip");
                        assert_eq!(&buf, expected);
                    }
                }
            });
        }
    });
    Ok(())
}

#[test]
fn dataset_types_can_be_shared_across_loader_threads() {
    fn assert_send_sync<T: Send + Sync>() {}
    assert_send_sync::<Dataset>();
    assert_send_sync::<TexturePack>();
    assert_send_sync::<DatasetError>();
}
