//! Every kind of damaged dataset gives a typed error naming the file and the offset or index
//! at fault, and nothing panics.

mod support;

use std::path::Path;

use citystream_dataset::{
    verify, Dataset, DatasetError, DatasetWriter, Scene, TextureFormat, TexturePack, CHECKSUM_FILE, COLORMAP_FILE,
    DATASET_FILES, FORMAT_VERSION, GEOMETRY_CRC_FILE, GEOMETRY_PACK_FILE, MANIFEST_FILE, MAX_CRS_BYTES, META_FILE,
    PACK_FILE, TILES_FILE,
};
use support::{
    copy_dir, data_file, fix_geometry_crc, fix_pack_header_crc, fix_table_crc, fix_tiles_crc, patch, test_dir,
    write_fixture, TEXTURES,
};

/// The data files of a write, every one the format's (the manifest is beside them).
fn data_files() -> impl Iterator<Item = &'static str> {
    DATASET_FILES.into_iter().filter(|&f| f != MANIFEST_FILE)
}

/// Byte offset of texture `i`'s record in `textures.meta`.
fn record(i: usize) -> usize {
    40 + 10 * i
}

fn open_err(dir: &Path) -> DatasetError {
    match Dataset::open(dir) {
        Ok(_) => panic!("{} opened although it is damaged", dir.display()),
        Err(e) => e,
    }
}

fn damaged(name: &str, file: &str, edit: impl FnOnce(&mut Vec<u8>)) -> std::path::PathBuf {
    let fixture = write_fixture(&format!("{name}-src"));
    let dir = copy_dir(&fixture.dir, name);
    patch(&data_file(&dir, file), edit);
    dir
}

fn assert_names(err: &DatasetError, file: &str, needles: &[&str]) {
    let message = err.to_string();
    assert!(message.contains(file), "error does not name {file}: {message}");
    for needle in needles {
        assert!(message.contains(needle), "error lacks {needle:?}: {message}");
    }
}

#[test]
fn missing_files_are_named() {
    for file in data_files() {
        let fixture = write_fixture(&format!("missing-{file}"));
        std::fs::remove_file(data_file(&fixture.dir, file)).expect("remove");
        let err = open_err(&fixture.dir);
        assert!(
            matches!(err, DatasetError::Missing { ref path } if path.ends_with(file)),
            "{err}"
        );
        assert_names(&err, file, &["missing"]);
    }
    let fixture = write_fixture("missing-manifest");
    std::fs::remove_file(fixture.dir.join(MANIFEST_FILE)).expect("remove");
    let err = open_err(&fixture.dir);
    assert!(matches!(err, DatasetError::Missing { .. }), "{err}");
    assert_names(&err, MANIFEST_FILE, &["missing"]);
}

#[test]
fn wrong_magic_is_reported_for_each_file() {
    // `geometry.pack` has no header: its tiles' blobs are checked against `geometry.crc`.
    for file in [TILES_FILE, GEOMETRY_CRC_FILE, META_FILE, PACK_FILE, COLORMAP_FILE] {
        let dir = damaged(&format!("magic-{file}"), file, |b| b[0..8].copy_from_slice(b"NOTADATA"));
        let err = open_err(&dir);
        assert!(matches!(err, DatasetError::BadMagic { .. }), "{file}: {err}");
        assert_names(&err, file, &["NOTADATA", "offset 0"]);
    }
}

#[test]
fn unsupported_version_is_reported() {
    let dir = damaged("version", META_FILE, |b| b[8..12].copy_from_slice(&7u32.to_le_bytes()));
    let err = open_err(&dir);
    assert!(
        matches!(
            err,
            DatasetError::UnsupportedVersion {
                found: 7,
                supported: FORMAT_VERSION,
                ..
            }
        ),
        "{err}"
    );
    assert_names(&err, META_FILE, &["version 7"]);
}

#[test]
fn truncated_pack_fails_at_open_and_in_verify() {
    let dir = damaged("truncated-pack", PACK_FILE, |b| b.truncate(b.len() - 100));
    let err = open_err(&dir);
    assert!(matches!(err, DatasetError::Truncated { .. }), "{err}");
    assert_names(&err, PACK_FILE, &["truncated"]);
    let err = verify(&dir).expect_err("verify of truncated pack");
    assert_names(&err, PACK_FILE, &[]);

    let dir = damaged("truncated-pack-header", PACK_FILE, |b| b.truncate(20));
    let err = open_err(&dir);
    assert!(
        matches!(
            err,
            DatasetError::Truncated {
                end: 64,
                file_len: 20,
                ..
            }
        ),
        "{err}"
    );
}

#[test]
fn pack_shrinking_after_open_gives_a_truncation_error_on_read() -> Result<(), DatasetError> {
    let fixture = write_fixture("shrink-after-open");
    let pack = TexturePack::open(&fixture.dir)?;
    let last = pack.len() - 1;
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(data_file(&fixture.dir, PACK_FILE))
        .expect("open pack");
    file.set_len(pack.pack_len() - 1).expect("truncate");
    let mut buf = Vec::new();
    // The last level of the last texture holds the pack's final byte.
    let level = pack.textures()[last as usize].mip_count() - 1;
    let location = pack.mip_location(last, level)?;
    let err = pack.read_mip(last, level, &mut buf).expect_err("read past the end");
    assert!(
        matches!(err, DatasetError::Truncated { offset, .. } if offset == location.offset),
        "{err}"
    );
    assert_names(&err, PACK_FILE, &[&location.offset.to_string()]);
    // Earlier mips are still readable.
    pack.read_mip(last, 0, &mut buf)?;
    Ok(())
}

#[test]
fn corrupt_table_bytes_fail_the_checksum() {
    let dir = damaged("meta-checksum", META_FILE, |b| b[record(1)] ^= 0x40);
    let err = open_err(&dir);
    assert!(matches!(err, DatasetError::Checksum { .. }), "{err}");
    assert_names(&err, META_FILE, &["checksum"]);

    // A byte of a tile's geometry: its CRC-32 in `geometry.crc` names the tile.
    let dir = damaged("geometry-checksum", GEOMETRY_PACK_FILE, |b| {
        let n = b.len();
        b[n - 1] ^= 1;
    });
    let err = open_err(&dir);
    assert!(matches!(err, DatasetError::Checksum { .. }), "{err}");
    assert_names(&err, GEOMETRY_PACK_FILE, &["tile 0's geometry"]);
    let dir = damaged("tiles-checksum", TILES_FILE, |b| {
        let n = b.len();
        b[n - 1] ^= 1;
    });
    let err = open_err(&dir);
    assert!(matches!(err, DatasetError::Checksum { .. }), "{err}");
    assert_names(&err, TILES_FILE, &["tile table"]);
}

#[test]
fn offset_past_the_end_names_texture_and_record() {
    let dir = damaged("offset-past-end", META_FILE, |b| {
        let r = record(3);
        b[r..r + 6].copy_from_slice(&[0, 0, 0, 0, 1, 0]); // 2^32: far past the end
        fix_table_crc(b);
    });
    let err = open_err(&dir);
    assert!(
        matches!(err, DatasetError::Corrupt { offset, .. } if offset == record(3) as u64),
        "{err}"
    );
    assert_names(&err, META_FILE, &["texture 3", "4294967296", "outside"]);
    let err = verify(&dir).expect_err("verify");
    assert_names(&err, META_FILE, &["texture 3"]);
}

#[test]
fn offset_inside_the_header_is_rejected() {
    let dir = damaged("offset-in-header", META_FILE, |b| {
        let r = record(0);
        b[r..r + 6].copy_from_slice(&[8, 0, 0, 0, 0, 0]);
        fix_table_crc(b);
    });
    assert_names(&open_err(&dir), META_FILE, &["texture 0", "outside"]);
}

#[test]
fn overlapping_chains_are_found_by_verify() {
    // Point texture 2 at texture 1's chain (valid on its own, but overlapping).
    let fixture = write_fixture("overlap-src");
    let pack = TexturePack::open(&fixture.dir).expect("open");
    let offset_1 = pack.textures()[1].offset();
    drop(pack);
    let dir = copy_dir(&fixture.dir, "overlap");
    patch(&data_file(&dir, META_FILE), |b| {
        let r = record(2);
        b[r..r + 6].copy_from_slice(&offset_1.to_le_bytes()[..6]);
        fix_table_crc(b);
    });
    Dataset::open(&dir).expect("each record on its own is in range");
    let err = verify(&dir).expect_err("verify overlap");
    assert!(matches!(err, DatasetError::Corrupt { .. }), "{err}");
    assert_names(&err, META_FILE, &["inside texture"]);
}

#[test]
fn flipped_mip_byte_fails_the_texture_checksum_in_verify() {
    let fixture = write_fixture("flipped-src");
    let pack = TexturePack::open(&fixture.dir).expect("open");
    let location = pack.mip_location(1, 4).expect("mip");
    drop(pack);
    let dir = copy_dir(&fixture.dir, "flipped");
    patch(&data_file(&dir, PACK_FILE), |b| b[location.offset as usize + 3] ^= 0xff);
    let dataset = Dataset::open(&dir).expect("open does not read mip data");
    // Every read checks the mip's own checksum, not only `verify`.
    let mut buf = Vec::new();
    let err = dataset
        .textures
        .read_mip(1, 4, &mut buf)
        .expect_err("read of the damaged mip");
    assert!(
        matches!(err, DatasetError::Checksum { offset, .. } if offset == location.offset),
        "{err}"
    );
    assert_names(&err, PACK_FILE, &["texture 1 level 4"]);
    let mut exact = vec![0u8; location.len as usize];
    assert!(dataset.textures.read_mip_into(1, 4, &mut exact).is_err());
    dataset
        .textures
        .read_mip(1, 3, &mut buf)
        .expect("the other levels are intact");
    let err = verify(&dir).expect_err("verify");
    assert!(matches!(err, DatasetError::Checksum { .. }), "{err}");
    assert_names(&err, PACK_FILE, &["texture 1 level 4"]);
}

#[test]
fn zero_and_absurd_texture_sizes_are_rejected() {
    let cases: [(&str, usize, u8, &str); 5] = [
        ("zero-mips", 7, 0, "mip count 0"),
        ("too-many-mips", 7, 11, "mip count 11"),
        ("absurd-extent", 6, 0xff, "exceeds the maximum"),
        ("bc1-below-block", 6, 0x11, "smaller than one 4x4 block"),
        ("unknown-format", 8, 9, "unknown texture format code 9"),
    ];
    for (name, byte, value, needle) in cases {
        let dir = damaged(name, META_FILE, |b| {
            b[record(1) + byte] = value;
            fix_table_crc(b);
        });
        let err = open_err(&dir);
        assert!(
            matches!(err, DatasetError::Corrupt { offset, .. } if offset == record(1) as u64),
            "{name}: {err}"
        );
        assert_names(&err, META_FILE, &["texture 1", needle]);
    }
}

#[test]
fn count_mismatches_between_files_are_reported() {
    let dir = damaged("pack-count", PACK_FILE, |b| {
        b[24..32].copy_from_slice(&3u64.to_le_bytes());
        fix_pack_header_crc(b);
    });
    assert_names(&open_err(&dir), PACK_FILE, &["3 textures"]);

    let dir = damaged("colormap-count", COLORMAP_FILE, |b| {
        b.truncate(b.len() - 4);
        b[24..32].copy_from_slice(&(TEXTURES.len() as u64 - 1).to_le_bytes());
        fix_table_crc(b);
    });
    assert_names(&open_err(&dir), COLORMAP_FILE, &["colours for"]);

    let dir = damaged("meta-absurd-count", META_FILE, |b| {
        b[24..32].copy_from_slice(&u64::MAX.to_le_bytes())
    });
    assert!(matches!(open_err(&dir), DatasetError::Corrupt { offset: 24, .. }));

    let dir = damaged("crc-count", CHECKSUM_FILE, |b| {
        b.truncate(b.len() - 4);
        let count = u64::from_le_bytes(b[24..32].try_into().expect("8 bytes")) - 1;
        b[24..32].copy_from_slice(&count.to_le_bytes());
        fix_table_crc(b);
    });
    assert_names(&open_err(&dir), CHECKSUM_FILE, &["mip checksums"]);
}

/// Writes `word` at byte `at` of a copy of the fixture's `geometry.pack` (its tile's CRC-32
/// recomputed, so the check behind it is reached) and expects a `Corrupt` error naming
/// `needle`.
fn assert_geometry_word_refused(name: &str, at: usize, word: [u8; 4], needle: &str) {
    let dir = damaged(name, GEOMETRY_PACK_FILE, |b| b[at..at + 4].copy_from_slice(&word));
    fix_geometry_crc(&dir);
    let err = open_err(&dir);
    assert!(
        matches!(err, DatasetError::Corrupt { offset, .. } if offset == at as u64),
        "{name}: {err}"
    );
    assert_names(&err, GEOMETRY_PACK_FILE, &["tile 0's geometry", needle]);
}

/// Byte offsets of the sections of the fixture's one tile in `geometry.pack` (its meshes lie
/// within a few tens of metres: one leaf tile, which lists them in their order).
struct GeometryLayout {
    meshes: usize,
    positions: usize,
    normals: usize,
    uvs: usize,
    indices: usize,
}

fn geometry_layout(scene: &Scene) -> GeometryLayout {
    let meshes = 16;
    let positions = meshes + 20 * scene.meshes.len();
    let normals = positions + 12 * scene.positions.len();
    let uvs = normals + 12 * scene.positions.len();
    let indices = uvs + 8 * scene.positions.len();
    GeometryLayout {
        meshes,
        positions,
        normals,
        uvs,
        indices,
    }
}

/// `tiles.bin`'s header bytes and where the fixture's one tile record starts.
const TILES_HEADER_BYTES: usize = 80;

fn tile_record_at(scene: &Scene) -> usize {
    TILES_HEADER_BYTES + scene.crs.as_ref().map_or(0, |c| c.as_str().len().next_multiple_of(8))
}

/// Writes `word` at byte `at` of a copy of the fixture's `tiles.bin` (checksum recomputed)
/// and expects a `Corrupt` error at `at` naming `needle`.
fn assert_tiles_word_refused(name: &str, at: usize, word: &[u8], needle: &str) {
    let dir = damaged(name, TILES_FILE, |b| {
        b[at..at + word.len()].copy_from_slice(word);
        fix_tiles_crc(b);
    });
    let err = open_err(&dir);
    assert!(matches!(err, DatasetError::Corrupt { .. }), "{name}: {err}");
    assert_names(&err, TILES_FILE, &[needle]);
}

#[test]
fn index_out_of_range_names_mesh_index_and_offset() {
    let scene = write_fixture("index-layout").scene;
    // Mesh 0 is a quad (4 vertices); make its second index 4.
    let at = geometry_layout(&scene).indices + 4;
    assert_geometry_word_refused(
        "index-range",
        at,
        4u32.to_le_bytes(),
        "mesh 0: index 4 beyond its 4 vertices",
    );
}

#[test]
fn non_finite_attributes_are_rejected() {
    let scene = write_fixture("nan-layout").scene;
    let layout = geometry_layout(&scene);
    let cases = [
        (
            "nan-position",
            layout.positions + 12 * 5 + 4,
            f32::NAN,
            "a position NaN",
        ),
        ("inf-normal", layout.normals + 12 * 2, f32::INFINITY, "a normal inf"),
        (
            "inf-uv",
            layout.uvs + 8 * 3 + 4,
            f32::NEG_INFINITY,
            "a texture coordinate -inf",
        ),
    ];
    for (name, at, value, needle) in cases {
        assert_geometry_word_refused(name, at, value.to_le_bytes(), needle);
    }
    // A tile's bounds, in `tiles.bin`.
    let record = tile_record_at(&scene);
    assert_tiles_word_refused("nan-bounds", record + 28, &f32::NAN.to_le_bytes(), "tile 0: bounds");
}

#[test]
fn mesh_ranges_and_texture_ids_are_checked() {
    let scene = write_fixture("mesh-layout").scene;
    let layout = geometry_layout(&scene);
    let cases: [(&str, usize, usize, u32, &str); 4] = [
        ("vertex-range", 4, 0, 1_000, "mesh 1: vertices"),
        ("index-range-mesh", 12, 8, 999, "mesh 1: indices"),
        ("partial-triangle", 12, 8, 5, "not whole triangles"),
        ("missing-texture", 16, 16, 500, "mesh 1: texture 500 outside"),
    ];
    for (name, field, named_at, value, needle) in cases {
        let at = layout.meshes + 20 + field;
        let dir = damaged(name, GEOMETRY_PACK_FILE, |b| {
            b[at..at + 4].copy_from_slice(&value.to_le_bytes())
        });
        fix_geometry_crc(&dir);
        let err = open_err(&dir);
        assert!(
            matches!(err, DatasetError::Corrupt { offset, .. } if offset == (layout.meshes + 20 + named_at) as u64),
            "{name}: {err}"
        );
        assert_names(&err, GEOMETRY_PACK_FILE, &[needle]);
    }
}

#[test]
fn geometry_counts_that_disagree_with_the_file_sizes_are_truncation() {
    // A tile's blob shorter than its counts say (its CRC-32 recomputed, its record's length
    // moved with it): truncation, naming the tile.
    let fixture = write_fixture("geometry-count-src");
    let dir = copy_dir(&fixture.dir, "geometry-count");
    patch(&data_file(&dir, GEOMETRY_PACK_FILE), |b| {
        b.truncate(b.len() - 4);
    });
    fix_geometry_crc(&dir);
    let record = tile_record_at(&fixture.scene);
    patch(&data_file(&dir, TILES_FILE), |b| {
        let len = u64::from_le_bytes(b[record + 72..record + 80].try_into().expect("8 bytes"));
        b[record + 72..record + 80].copy_from_slice(&(len - 4).to_le_bytes());
        fix_tiles_crc(b);
    });
    let err = open_err(&dir);
    assert!(matches!(err, DatasetError::Truncated { .. }), "{err}");
    assert_names(&err, GEOMETRY_PACK_FILE, &["tile 0's geometry"]);
    // A mesh count no file could hold.
    let dir = damaged("tiles-absurd-count", TILES_FILE, |b| {
        b[72..80].copy_from_slice(&u64::MAX.to_le_bytes());
        fix_tiles_crc(b);
    });
    assert!(matches!(open_err(&dir), DatasetError::Corrupt { offset: 72, .. }));
}

#[test]
fn writer_rejects_inconsistent_input() {
    let dir = support::test_dir("writer-input");
    let mut writer = DatasetWriter::create(&dir).expect("create");
    let too_short = vec![0u8; 10];
    let cases = [
        writer.add_texture(TextureFormat::Bc1, 8, 8, 4, &too_short, [0; 4]),
        writer.add_texture(TextureFormat::Bc1, 12, 8, 1, &too_short, [0; 4]),
        writer.add_texture(TextureFormat::Bc1, 2, 2, 1, &[0u8; 8], [0; 4]),
        writer.add_texture(TextureFormat::Rgba8, 4, 4, 0, &[], [0; 4]),
        writer.add_texture(TextureFormat::Rgba8, 1 << 15, 4, 1, &[], [0; 4]),
    ];
    for result in cases {
        assert!(matches!(result, Err(DatasetError::InvalidInput(_))), "{result:?}");
    }
    assert_eq!(writer.texture_count(), 0);
    // A scene referring to a texture that was never written is refused.
    let scene = support::fixture_scene(1);
    assert!(matches!(writer.finish(&scene), Err(DatasetError::InvalidInput(_))));
}

#[test]
fn empty_dataset_round_trips() -> Result<(), DatasetError> {
    let dir = support::test_dir("empty");
    DatasetWriter::create(&dir)?.finish(&Scene::new([0.0; 3]))?;
    let dataset = Dataset::open(&dir)?;
    assert!(dataset.textures.is_empty());
    assert!(dataset.scene.meshes.is_empty());
    assert_eq!(verify(&dir)?.mips, 0);
    Ok(())
}

#[cfg(unix)]
#[test]
fn files_that_are_not_regular_files_are_refused_without_blocking() {
    // A FIFO would block a plain read until a writer appears; a directory
    // cannot be read at all.
    for (file, kind) in [(META_FILE, "fifo"), (PACK_FILE, "fifo"), (TILES_FILE, "dir")] {
        let fixture = write_fixture(&format!("not-a-file-{kind}-src"));
        let dir = copy_dir(&fixture.dir, &format!("not-a-file-{kind}-{file}"));
        let path = data_file(&dir, file);
        std::fs::remove_file(&path).expect("remove");
        if kind == "dir" {
            std::fs::create_dir(&path).expect("mkdir");
        } else {
            let made = std::process::Command::new("mkfifo")
                .arg(&path)
                .status()
                .expect("mkfifo runs");
            assert!(made.success(), "mkfifo failed");
        }
        let err = open_err(&dir);
        assert_names(&err, file, &["not a regular file"]);
    }
}

#[test]
fn any_flipped_tile_table_header_bit_is_refused() {
    // The header (counts, write id, the scene's origin) and the CRS record are under the
    // tile table's checksum: a flipped bound once made the flythrough render only sky.
    let fixture = write_fixture("tiles-header-src");
    let path = data_file(&fixture.dir, TILES_FILE);
    let original = std::fs::read(&path).expect("read tiles.bin");
    let dir = copy_dir(&fixture.dir, "tiles-header");
    let target = data_file(&dir, TILES_FILE);
    for byte in 16..tile_record_at(&fixture.scene) {
        for bit in [0u8, 3, 7] {
            let mut bytes = original.clone();
            bytes[byte] ^= 1 << bit;
            std::fs::write(&target, &bytes).expect("write");
            let err = open_err(&dir);
            assert_names(&err, TILES_FILE, &[]);
        }
    }
}

#[test]
fn tile_bounds_that_do_not_hold_the_vertices_are_refused() {
    // With the checksum recomputed, bounds that leave a vertex out or are not a box still
    // fail their own checks.
    let scene = write_fixture("bounds-layout").scene;
    let record = tile_record_at(&scene);
    let cases: [(&str, usize, f32, &str); 3] = [
        ("tile-max-shrunk", record + 36, -1e7, "tile 0: bounds"),
        ("tile-min-inf", record + 24, f32::NEG_INFINITY, "tile 0: bounds"),
        ("tile-min-raised", record + 28, 1.0, "outside the tile's bounds"),
    ];
    for (name, at, value, needle) in cases {
        let dir = damaged(name, TILES_FILE, |b| {
            b[at..at + 4].copy_from_slice(&value.to_le_bytes());
            fix_tiles_crc(b);
        });
        let err = open_err(&dir);
        assert!(matches!(err, DatasetError::Corrupt { .. }), "{name}: {err}");
        assert!(err.to_string().contains(needle), "{name}: {err}");
    }
}

#[test]
fn files_of_another_write_are_refused() {
    // Two writes of the same content differ only in their write ids: a file copied from one
    // into the other is named as coming from another write.
    let a = write_fixture("mixed-a");
    let b = write_fixture("mixed-b");
    // `geometry.pack` carries no write id: its tiles' CRC-32s in `geometry.crc` do.
    for file in data_files().filter(|&f| f != GEOMETRY_PACK_FILE) {
        let dir = copy_dir(&a.dir, &format!("mixed-{file}"));
        std::fs::copy(data_file(&b.dir, file), data_file(&dir, file)).expect("copy");
        let err = open_err(&dir);
        assert!(matches!(err, DatasetError::MixedWrites { .. }), "{file}: {err}");
        assert_names(&err, file, &["different writes"]);
    }
}

#[test]
fn damaged_manifests_are_refused() {
    let fixture = write_fixture("manifest-src");
    for (name, edit) in [
        ("manifest-flip", (|b: &mut Vec<u8>| b[17] ^= 4) as fn(&mut Vec<u8>)),
        ("manifest-short", |b| b.truncate(20)),
        ("manifest-magic", |b| b[0..8].copy_from_slice(b"NOTADATA")),
    ] {
        let dir = copy_dir(&fixture.dir, name);
        patch(&dir.join(MANIFEST_FILE), edit);
        let err = open_err(&dir);
        assert_names(&err, MANIFEST_FILE, &[]);
    }
}

#[test]
fn the_crs_round_trips_and_a_damaged_crs_record_is_refused() {
    let fixture = write_fixture("crs-src");
    let opened = Dataset::open(&fixture.dir).expect("open");
    let crs = opened.scene.crs.as_ref().expect("the fixture has a CRS");
    assert_eq!(crs.as_str(), support::FIXTURE_CRS);
    assert_eq!(crs.epsg_code(), Some(25833));
    let text_at = TILES_HEADER_BYTES;
    let text_len = support::FIXTURE_CRS.len();
    assert_ne!(text_len % 8, 0, "the fixture exercises the padding");
    let records_at = tile_record_at(&fixture.scene);
    type Edit = Box<dyn Fn(&mut Vec<u8>)>;
    let cases: [(&str, Edit, &str, u64); 5] = [
        (
            "crs-too-long",
            Box::new(|b| b[40..44].copy_from_slice(&(MAX_CRS_BYTES as u32 + 1).to_le_bytes())),
            "at most",
            40,
        ),
        (
            "crs-not-utf8",
            Box::new(move |b| b[text_at + 3] = 0xff),
            "not UTF-8",
            text_at as u64,
        ),
        (
            "crs-not-wkt",
            Box::new(move |b| b[text_at] = b'1'),
            "CRS: not a CRS",
            text_at as u64,
        ),
        (
            "crs-padding",
            Box::new(move |b| b[text_at + text_len] = 1),
            "padding",
            (text_at + text_len) as u64,
        ),
        (
            "crs-epsg-zero",
            Box::new(move |b| {
                // Rewrites the record as `EPSG:0`, keeping its length with padding.
                let text = b"EPSG:0";
                b[40..44].copy_from_slice(&(text.len() as u32).to_le_bytes());
                b[text_at..text_at + text.len()].copy_from_slice(text);
                let padded = text.len().next_multiple_of(8);
                b[text_at + text.len()..text_at + padded].fill(0);
                b.drain(text_at + padded..records_at);
            }),
            "EPSG code",
            text_at as u64,
        ),
    ];
    for (name, edit, needle, offset) in cases {
        let dir = damaged(name, TILES_FILE, |b| {
            edit(b);
            fix_tiles_crc(b);
        });
        let err = open_err(&dir);
        assert!(
            matches!(err, DatasetError::Corrupt { offset: at, .. } if at == offset),
            "{name}: {err}"
        );
        assert_names(&err, TILES_FILE, &[needle]);
    }
    // A length that moves the records is a size mismatch.
    let dir = damaged("crs-length", TILES_FILE, |b| {
        b[40..44].copy_from_slice(&(text_len as u32 + 8).to_le_bytes());
        fix_tiles_crc(b);
    });
    assert!(matches!(open_err(&dir), DatasetError::Truncated { .. }));
}

#[test]
fn a_file_added_to_a_write_cannot_take_a_format_file_or_leave_the_directory() -> Result<(), DatasetError> {
    let mut writer = DatasetWriter::create(&test_dir("add-file-names"))?;
    let refused = DATASET_FILES
        .iter()
        .copied()
        .chain(["scene.bin", "resume.journal", "", ".hidden", "a/b", "a\\b"]);
    for name in refused {
        assert!(
            matches!(writer.add_file(name, b"x"), Err(DatasetError::InvalidInput(_))),
            "{name:?} must be refused"
        );
    }
    writer.add_file("shard.record", b"x")
}
