//! Arbitrary damage to any dataset file never panics: opening, reading every mip and
//! verifying either succeed or return an error.

mod support;

use citystream_dataset::{
    verify, Dataset, DATASET_FILES as FILES, GEOMETRY_PACK_FILE, MANIFEST_FILE, PACK_FILE, TILES_FILE,
};
use proptest::prelude::*;
use support::{copy_dir, data_file, patch, write_fixture};

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn damaged_files_never_panic(
        file in 0usize..FILES.len(),
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..4),
        truncate in proptest::option::of(any::<prop::sample::Index>()),
        recompute_crc in any::<bool>(),
    ) {
        let source = write_fixture("fuzz-src");
        let dir = copy_dir(&source.dir, "fuzz");
        let name = FILES[file];
        let path = if name == MANIFEST_FILE { dir.join(name) } else { data_file(&dir, name) };
        patch(&path, |b| {
            for (index, value) in &flips {
                if !b.is_empty() {
                    let i = index.index(b.len());
                    b[i] ^= value | 1;
                }
            }
            if let Some(t) = &truncate {
                let keep = t.index(b.len() + 1);
                b.truncate(keep);
            }
            // Also reach the checks behind the table checksums.
            if recompute_crc && b.len() >= 80 && name == TILES_FILE {
                support::fix_tiles_crc(b);
            } else if name == GEOMETRY_PACK_FILE {
                // Its tiles' CRC-32s are in `geometry.crc`: fixed below.
            } else if recompute_crc && b.len() >= 44 && name == PACK_FILE {
                support::fix_pack_header_crc(b);
            } else if recompute_crc && b.len() >= 40 && name != MANIFEST_FILE {
                support::fix_table_crc(b);
            }
        });
        if recompute_crc && name == GEOMETRY_PACK_FILE {
            support::fix_geometry_crc(&dir);
        }
        if let Ok(dataset) = Dataset::open(&dir) {
            let mut buf = Vec::new();
            for (id, info) in dataset.textures.textures().iter().enumerate() {
                for level in 0..info.mip_count() {
                    let _ = dataset.textures.read_mip(id as u32, level, &mut buf);
                }
            }
        }
        let _ = verify(&dir);
    }
}
