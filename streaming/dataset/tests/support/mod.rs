//! Shared fixture for the dataset tests: a small dataset with every format, square and
//! rectangular extents, full and partial mip chains, written through the public writer.

#![allow(dead_code)] // reason: each test binary uses a different subset

use std::path::{Path, PathBuf};

use citystream_dataset::{
    Crs, DatasetFiles, DatasetWriter, Scene, TextureFormat, WriteSummary, GEOMETRY_CRC_FILE, GEOMETRY_PACK_FILE,
};

/// One texture of the fixture: what was written.
#[derive(Debug, Clone)]
pub struct WrittenTexture {
    pub format: TextureFormat,
    pub width: u32,
    pub height: u32,
    pub mips: Vec<Vec<u8>>,
    pub colour: [u8; 4],
}

#[derive(Debug)]
pub struct Fixture {
    pub dir: PathBuf,
    pub textures: Vec<WrittenTexture>,
    pub scene: Scene,
    pub summary: WriteSummary,
}

/// (format, width, height, mip count)
pub const TEXTURES: &[(TextureFormat, u32, u32, u32)] = &[
    (TextureFormat::Bc1, 4, 32, 6),
    (TextureFormat::Bc1, 64, 256, 9),
    (TextureFormat::Rgba8, 16, 8, 5),
    (TextureFormat::Bc1, 512, 512, 3),
    (TextureFormat::Bc3, 8, 8, 4),
    (TextureFormat::Rgba8, 1, 1, 1),
    (TextureFormat::Bc7, 4, 4, 3),
    (TextureFormat::Rgba8, 256, 4, 9),
];

/// A fresh empty directory for one test.
pub fn test_dir(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("dataset-tests").join(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create test dir");
    dir
}

/// Deterministic bytes, different for every (texture, level).
fn bytes(seed: u64, len: usize) -> Vec<u8> {
    let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    (0..len)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 24) as u8
        })
        .collect()
}

pub fn mip_extent(width: u32, height: u32, level: u32) -> (u32, u32) {
    ((width >> level).max(1), (height >> level).max(1))
}

/// The fixture's CRS: multi-line WKT of a length that is not a multiple of 4, so the CRS
/// record has padding.
pub const FIXTURE_CRS: &str = "PROJCRS[\"ETRS89 / UTM zone 33N\",\n  BASEGEOGCRS[\"ETRS89\"],\n  ID[\"EPSG\",25833]]";

/// A scene of one mesh per texture (quads and a triangle), far from the world origin, in
/// [`FIXTURE_CRS`].
pub fn fixture_scene(textures: u32) -> Scene {
    let mut scene = Scene::new([391_250.5, 34.25, -5_819_500.75]);
    scene.crs = Some(Crs::parse(FIXTURE_CRS).expect("fixture CRS"));
    for t in 0..textures {
        let x = t as f32 * 10.0;
        if t % 3 == 2 {
            scene
                .push_mesh(
                    t,
                    &[[x, 0.0, 0.0], [x + 4.0, 0.0, 0.0], [x + 2.0, 5.0, -1.0]],
                    &[[0.0, 0.0, 1.0]; 3],
                    &[[0.0, 1.0], [2.0, 1.0], [1.0, -1.0]],
                    &[0, 1, 2],
                )
                .expect("push triangle");
        } else {
            scene
                .push_mesh(
                    t,
                    &[[x, 0.0, 1.0], [x + 8.0, 0.0, 1.0], [x + 8.0, 12.0, 1.0], [x, 12.0, 1.0]],
                    &[[0.0, 0.0, 1.0]; 4],
                    &[[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]],
                    &[0, 1, 2, 0, 2, 3],
                )
                .expect("push quad");
        }
    }
    scene
}

/// Texture `t` of [`TEXTURES`] with its deterministic bytes and colour.
pub fn fixture_texture(t: usize) -> WrittenTexture {
    let (format, width, height, mip_count) = TEXTURES[t];
    let mips: Vec<Vec<u8>> = (0..mip_count)
        .map(|level| {
            let (w, h) = mip_extent(width, height, level);
            bytes((t as u64) << 8 | u64::from(level), format.mip_bytes(w, h) as usize)
        })
        .collect();
    WrittenTexture {
        format,
        width,
        height,
        mips,
        colour: [t as u8 * 30, 255 - t as u8, 7, 255],
    }
}

/// Appends `texture` to `writer`; returns its id.
pub fn add_fixture_texture(writer: &mut DatasetWriter, texture: &WrittenTexture) -> u32 {
    let chain: Vec<u8> = texture.mips.concat();
    writer
        .add_texture(
            texture.format,
            texture.width,
            texture.height,
            texture.mips.len() as u32,
            &chain,
            texture.colour,
        )
        .expect("add texture")
}

/// Writes the fixture dataset into a fresh directory `name`.
pub fn write_fixture(name: &str) -> Fixture {
    let dir = test_dir(name);
    let mut writer = DatasetWriter::create(&dir).expect("create writer");
    let mut textures = Vec::new();
    for t in 0..TEXTURES.len() {
        let texture = fixture_texture(t);
        assert_eq!(add_fixture_texture(&mut writer, &texture) as usize, t);
        textures.push(texture);
    }
    let scene = fixture_scene(TEXTURES.len() as u32);
    let summary = writer.finish(&scene).expect("finish");
    Fixture {
        dir,
        textures,
        scene,
        summary,
    }
}

/// Copies a dataset directory (the manifest and the write subdirectory).
pub fn copy_dir(from: &Path, name: &str) -> PathBuf {
    let to = test_dir(name);
    copy_tree(from, &to);
    to
}

fn copy_tree(from: &Path, to: &Path) {
    for entry in std::fs::read_dir(from).expect("read dir") {
        let entry = entry.expect("dir entry");
        let target = to.join(entry.file_name());
        if entry.file_type().expect("file type").is_dir() {
            std::fs::create_dir_all(&target).expect("create subdirectory");
            copy_tree(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).expect("copy file");
        }
    }
}

/// Path of one data file (`scene.bin`, ...) of the dataset in `dir`.
pub fn data_file(dir: &Path, name: &str) -> PathBuf {
    DatasetFiles::resolve(dir)
        .expect("resolve the dataset's manifest")
        .path(name)
}

/// Edits a file in place.
pub fn patch(path: &Path, edit: impl FnOnce(&mut Vec<u8>)) {
    let mut bytes = std::fs::read(path).expect("read file to patch");
    edit(&mut bytes);
    std::fs::write(path, bytes).expect("write patched file");
}

/// Recomputes the checksum of a table file (meta, colormap, crc: header bytes 0..32 and the
/// records) after a patch, so the test reaches the check behind the checksum.
pub fn fix_table_crc(bytes: &mut [u8]) {
    let crc = crc_of(&bytes[..32], &bytes[40..]);
    bytes[32..36].copy_from_slice(&crc.to_le_bytes());
}

/// Same for `tiles.bin` (bytes 0..44 and everything after byte 48).
pub fn fix_tiles_crc(bytes: &mut [u8]) {
    let crc = crc_of(&bytes[..44], &bytes[48..]);
    bytes[44..48].copy_from_slice(&crc.to_le_bytes());
}

/// Recomputes, in `geometry.crc` of the dataset in `dir`, the CRC-32 of its first tile's
/// blob (the whole `geometry.pack`: the fixture has one tile) and the table's checksum, so a
/// test reaches the checks behind them.
pub fn fix_geometry_crc(dir: &Path) {
    let pack = std::fs::read(data_file(dir, GEOMETRY_PACK_FILE)).expect("read geometry.pack");
    patch(&data_file(dir, GEOMETRY_CRC_FILE), |b| {
        b[40..44].copy_from_slice(&crc32fast::hash(&pack).to_le_bytes());
        fix_table_crc(b);
    });
}

/// Same for the header of `textures.pack` (bytes 0..40).
pub fn fix_pack_header_crc(bytes: &mut [u8]) {
    let crc = crc32fast::hash(&bytes[..40]);
    bytes[40..44].copy_from_slice(&crc.to_le_bytes());
}

fn crc_of(header: &[u8], body: &[u8]) -> u32 {
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(header);
    hasher.update(body);
    hasher.finalize()
}
