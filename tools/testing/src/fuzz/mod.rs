//! Fuzz harnesses for every parser of untrusted input: dataset files, camera paths, glTF/GLB
//! import (Draco, meshopt and quantized geometry included), KTX2/DDS/PNG texture input
//! (Basis Universal transcoding included) and ground patch sets.
//!
//! Coverage-guided fuzzers for Rust (`cargo fuzz`, libFuzzer) need a nightly compiler and
//! AFL++ needs its own compiler toolchain, neither of which this project's stable toolchain
//! and package registries provide. So each harness is a seeded in-process mutator over valid
//! seeds: bit flips, extreme bytes and fields (0, all ones, NaN, ±inf, 2^31, huge floats),
//! truncations, extensions, deletions, duplications and splices between seeds; for text
//! formats also number tokens replaced by extreme ones and structural characters removed; for
//! glTF and tilesets URIs replaced by shapes a resolver must refuse or keep inside (with
//! decoy files that make their naive readings exist); for binary dataset files checksums
//! recomputed half of the time so that the checks behind them are reached. The same seed
//! gives the same inputs. The `fuzz` binary runs a harness and
//! checks that no input panics, hangs or allocates beyond a bound.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use citystream_dataset::{
    verify, Dataset, DatasetFiles, DatasetWriter, Scene, TextureFormat, DATASET_FILES, MANIFEST_FILE, PACK_FILE,
    TILES_FILE,
};
use citystream_gen::image_files::{dds_file, ktx2_file};
use citystream_streaming::bench::path::{standard_path, CameraPath};
use citystream_streaming::rng::SplitMix64;

mod input;
mod mutate;
mod scripted;
mod uri;

pub use input::Outcome;
use input::Seed;
use mutate::{below, fix_dataset_checksum, mutate};
use scripted::{remote_seeds, ScriptedServer};
#[cfg(test)]
use uri::{put_uri, uri_sites};
use uri::{uri_shapes, write_uri_decoys, UriShape};

/// The parsers a harness drives.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Target {
    /// `Dataset::open`, every mip read and `verify`, one mutated file at a time.
    Dataset,
    /// `CameraPath::from_json` and sampling of what parses.
    Path,
    /// glTF and GLB import (`citystream_import::gltf::load_slice`, Draco and meshopt content
    /// included) without writing a dataset.
    Gltf,
    /// KTX2, DDS and PNG decoding (`decode_image_bytes`), and Basis Universal KTX2
    /// (ETC1S, UASTC, UASTC+zstd) transcoded to BC7, BC1 and RGBA8.
    Texture,
    /// Ground patch sets: `patches.json` and the PNG headers `PatchSet::open` reads, then
    /// the images decoded as the flythrough decodes them where their listed size is small.
    Patches,
    /// A remote store's HTTP client against a scripted loopback server whose every answer
    /// is the input (status line, headers, lengths, ranges, body): a file's length (HEAD)
    /// and a 32-byte range read.
    Remote,
    /// 3D Tiles import (`tiles::load`, every level) of a small tileset with an external
    /// tileset, b3dm and glb content (Draco and meshopt glbs with Basis textures among them),
    /// one mutated file at a time, without writing a dataset.
    Tileset,
}

impl Target {
    /// Every target.
    pub const ALL: [Target; 7] = [
        Target::Dataset,
        Target::Path,
        Target::Gltf,
        Target::Texture,
        Target::Patches,
        Target::Remote,
        Target::Tileset,
    ];

    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Target::Dataset => "dataset",
            Target::Path => "path",
            Target::Gltf => "gltf",
            Target::Texture => "texture",
            Target::Patches => "patches",
            Target::Remote => "remote",
            Target::Tileset => "tileset",
        }
    }
}

/// One harness: valid seeds and a way to run one (mutated) input.
#[derive(Debug)]
pub struct Harness {
    target: Target,
    seeds: Vec<Seed>,
    work: PathBuf,
    /// The remote harness's server and store.
    remote: Option<ScriptedServer>,
    /// What the URI mutation puts in place of a URI (glTF and tileset harnesses only).
    uri_shapes: Vec<UriShape>,
}

impl Harness {
    /// Builds the seeds of `target` in `work` (a scratch directory it owns).
    pub fn new(target: Target, work: &Path) -> Result<Self> {
        let _ = std::fs::remove_dir_all(work);
        std::fs::create_dir_all(work).with_context(|| format!("creating {}", work.display()))?;
        let seeds = match target {
            Target::Dataset => dataset_seeds(work)?,
            Target::Path => path_seeds()?,
            Target::Gltf => gltf_seeds(work)?,
            Target::Texture => texture_seeds()?,
            Target::Patches => patches_seeds(work)?,
            Target::Remote => remote_seeds(),
            Target::Tileset => tileset_seeds(work)?,
        };
        let remote = match target {
            Target::Remote => Some(ScriptedServer::start()?),
            _ => None,
        };
        let uri_shapes = match target {
            Target::Gltf | Target::Tileset => uri_shapes(),
            _ => Vec::new(),
        };
        Ok(Self {
            target,
            seeds,
            work: work.to_path_buf(),
            remote,
            uri_shapes,
        })
    }

    /// The target.
    pub fn target(&self) -> Target {
        self.target
    }

    /// The `index`-th input of the stream `seed`: a mutation of one of the seeds, with the name
    /// of the seed it came from.
    pub fn input(&self, seed: u64, index: u64) -> (usize, Vec<u8>) {
        let mut rng = SplitMix64::stream(seed, index);
        let which = below(&mut rng, self.seeds.len());
        let original = &self.seeds[which];
        let donor = &self.seeds[below(&mut rng, self.seeds.len())].bytes;
        let text =
            matches!(self.target, Target::Path) || original.name.ends_with(".gltf") || original.name.ends_with(".json");
        let mut bytes = mutate(&mut rng, &original.bytes, donor, text, &self.uri_shapes);
        if self.target == Target::Dataset && rng.next_u64().is_multiple_of(2) {
            fix_dataset_checksum(&original.name, &mut bytes);
        }
        (which, bytes)
    }

    /// Runs one input through the parser and everything that consumes what it returns.
    /// Errors are fine; a panic propagates to the caller.
    pub fn run(&self, seed_index: usize, bytes: &[u8]) -> Outcome {
        let name = &self.seeds[seed_index].name;
        match self.target {
            Target::Dataset => self.run_dataset(name, bytes),
            Target::Path => run_path(bytes),
            Target::Gltf => self.run_gltf(name, bytes),
            Target::Texture => run_texture(bytes),
            Target::Patches => self.run_patches(name, bytes),
            Target::Tileset => self.run_tileset(name, bytes),
            Target::Remote => match &self.remote {
                Some(server) => server.run(bytes),
                None => Outcome::Rejected,
            },
        }
    }

    fn run_patches(&self, name: &str, bytes: &[u8]) -> Outcome {
        let dir = self.work.join("patches");
        let path = dir.join(name);
        self.in_place(name, &path, bytes, || {
            match citystream_gen::patches::PatchSet::open(&dir) {
                Ok(set) => {
                    let _ = set.crs();
                    // What the flythrough decodes, where the set's listed sizes (checked
                    // against the headers) stay small: it refuses larger sets by budget.
                    for record in set
                        .patches
                        .iter()
                        .filter(|r| u64::from(r.width) * u64::from(r.height) <= 1 << 16)
                    {
                        if let Ok(image) = image::open(dir.join(&record.file)) {
                            let rgba = image.to_rgba8();
                            let _ = citystream_streaming::ground::PatchImage::from_rgba8(
                                rgba.width(),
                                rgba.height(),
                                rgba.as_raw(),
                            );
                        }
                    }
                    Outcome::Accepted
                }
                Err(_) => Outcome::Rejected,
            }
        })
    }

    /// Writes `bytes` over the seed file `name` at `path` and runs `parse` on what is there
    /// then (a write that fails is a rejection); afterwards restores the seed's own file (its
    /// first seed of that name) for the next input.
    fn in_place(&self, name: &str, path: &Path, bytes: &[u8], parse: impl FnOnce() -> Outcome) -> Outcome {
        let outcome = if std::fs::write(path, bytes).is_err() {
            Outcome::Rejected
        } else {
            parse()
        };
        if let Some(original) = self.seeds.iter().find(|s| s.name == name) {
            let _ = std::fs::write(path, &original.bytes);
        }
        outcome
    }

    fn run_tileset(&self, name: &str, bytes: &[u8]) -> Outcome {
        let dir = self.work.join("tileset");
        let path = dir.join(name);
        self.in_place(name, &path, bytes, || {
            // RGBA8 and a small extent: the harness is about parsing, not encoding.
            let tileset = dir.join("tileset.json");
            let options = citystream_import::tiles::LoadOptions {
                format: TextureFormat::Rgba8,
                max_extent: 64,
                lod: citystream_import::tiles::Lod::All,
                strict: false,
                report: false,
                crs: None,
                part: None,
            };
            match citystream_import::tiles::load(&tileset, &options, &mut |_| Ok(())) {
                Ok(_) => Outcome::Accepted,
                Err(_) => Outcome::Rejected,
            }
        })
    }

    fn dataset_dir(&self) -> PathBuf {
        self.work.join("dataset")
    }

    fn run_dataset(&self, name: &str, bytes: &[u8]) -> Outcome {
        let dir = self.dataset_dir();
        let path = dataset_file_path(&dir, name);
        self.in_place(name, &path, bytes, || match Dataset::open(&dir) {
            Ok(dataset) => {
                let mut buf = Vec::new();
                for (id, info) in dataset.textures.textures().iter().enumerate() {
                    for level in 0..info.mip_count() {
                        let _ = dataset.textures.read_mip(id as u32, level, &mut buf);
                    }
                }
                match verify(&dir) {
                    Ok(_) => Outcome::Accepted,
                    Err(_) => Outcome::Rejected,
                }
            }
            Err(_) => Outcome::Rejected,
        })
    }

    fn run_gltf(&self, name: &str, bytes: &[u8]) -> Outcome {
        let base = self.work.join("gltf");
        // RGBA8 and a small extent: the harness is about parsing, not encoding.
        match citystream_import::gltf::load_slice(bytes, &base, Path::new(name), TextureFormat::Rgba8, 64) {
            Ok(_) => Outcome::Accepted,
            Err(_) => Outcome::Rejected,
        }
    }

    /// Names of the seeds, for the report.
    pub fn seed_names(&self) -> Vec<&str> {
        self.seeds.iter().map(|s| s.name.as_str()).collect()
    }
}

fn run_path(bytes: &[u8]) -> Outcome {
    // `CameraPath::load` refuses text that is not UTF-8 the same way.
    let Ok(text) = std::str::from_utf8(bytes) else {
        return Outcome::Rejected;
    };
    match CameraPath::from_json(text) {
        Ok(path) => {
            let end = path.duration_s();
            for t in [0.0, end / 3.0, end * 0.999, end, end + 1.0, -1.0] {
                let pose = path.sample(t);
                assert!(
                    pose.position.iter().chain(&pose.look_at).all(|v| v.is_finite()),
                    "a parsed path gave a non-finite pose at t = {t}: {pose:?}"
                );
            }
            let _ = path.pauses();
            let _ = path.jumps();
            Outcome::Accepted
        }
        Err(_) => Outcome::Rejected,
    }
}

fn run_texture(bytes: &[u8]) -> Outcome {
    // Basis Universal KTX2: transcoded as `import` transcodes it, into blocks (all levels,
    // and from the second level on) and to RGBA8.
    if citystream_import::basis::is_basis(bytes) {
        let Ok(texture) = citystream_import::basis::BasisTexture::open(bytes) else {
            return Outcome::Rejected;
        };
        let Ok(_room) = texture.reserve() else {
            return Outcome::Rejected;
        };
        let blocks = [(TextureFormat::Bc7, 14), (TextureFormat::Bc1, 5)]
            .iter()
            .map(|&(format, max_log2)| texture.blocks(format, max_log2))
            .collect::<Result<Vec<_>, _>>();
        return match (blocks, texture.rgba()) {
            (Ok(_), Ok(_)) => Outcome::Accepted,
            _ => Outcome::Rejected,
        };
    }
    // Both readers of texture files: block sources kept as they are by `import`, and the
    // decoder every other image goes through.
    let kept = citystream_import::blocks::block_source(bytes);
    match citystream_gen::library::decode_image_bytes(bytes) {
        Ok(_) => Outcome::Accepted,
        Err(_) if matches!(kept, Ok(Some(_))) => Outcome::Accepted,
        Err(_) => Outcome::Rejected,
    }
}

fn dataset_file_path(dir: &Path, name: &str) -> PathBuf {
    if name == MANIFEST_FILE {
        dir.join(name)
    } else {
        // Resolved once per seed set: the fixture's manifest is restored after every input.
        DatasetFiles::resolve(dir).map_or_else(|_| dir.join(name), |files| files.path(name))
    }
}

/// A tileset at Berlin written to `work/tileset` (`tileset.json` with a transform, REPLACE
/// refinement and an external `ext.json` under ADD; a glb with CESIUM_RTC and node
/// transforms, a b3dm with RTC_CENTER and a batch table, a glTF with an external buffer and
/// image, a Draco and a meshopt glb with ETC1S textures), with the URI decoys: each file but
/// the glTF's buffer and image is a seed.
fn tileset_seeds(work: &Path) -> Result<Vec<Seed>> {
    use citystream_import::tiles::write;
    use serde_json::json;
    let dir = work.join("tileset");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    // East-north-up at 52.5 N, 13.4 E on the ellipsoid, as a column-major transform.
    let (lat, lon) = (52.5f64.to_radians(), 13.4f64.to_radians());
    let origin = citystream_import::tiles::geodesy::to_ecef(citystream_import::tiles::geodesy::Geodetic {
        latitude: lat,
        longitude: lon,
        height: 34.0,
    });
    let (sl, cl, so, co) = (lat.sin(), lat.cos(), lon.sin(), lon.cos());
    let enu = [
        -so,
        co,
        0.0,
        0.0,
        -sl * co,
        -sl * so,
        cl,
        0.0,
        cl * co,
        cl * so,
        sl,
        0.0,
        origin[0],
        origin[1],
        origin[2],
        1.0,
    ];
    let quad = [[0.0f32, 0.0, 0.0], [4.0, 0.0, 0.0], [4.0, 3.0, 0.0], [0.0, 3.0, 0.0]];
    let (gltf, bin) = write::textured_quad(
        quad,
        &write::gradient_png(8, 4, 1),
        json!({"translation": [1.0, 0.0, -2.0], "scale": [2.0, 2.0, 2.0]}),
        Some(json!({"CESIUM_RTC": {"center": [1.0, 2.0, 3.0]}})),
    );
    let glb = write::glb(&gltf, &bin);
    let (gltf, bin) = write::textured_quad(quad, &write::gradient_png(4, 8, 2), json!({}), None);
    let b3dm = write::b3dm(
        &write::glb(&gltf, &bin),
        &json!({"BATCH_LENGTH": 1, "RTC_CENTER": [10.0, 0.0, 0.0]}),
        Some(&json!({"height": [3.0]})),
        &[],
    );
    // A glTF whose buffer and image are files beside it: URIs for the URI mutation to replace
    // (a GLB's JSON has none), resolved by the tileset's checks and then by the reader.
    let png = write::gradient_png(4, 4, 3);
    let (mut c_gltf, c_bin) = write::textured_quad(quad, &png, json!({}), None);
    c_gltf["buffers"][0]["uri"] = json!("c.bin");
    c_gltf["images"] = json!([{"uri": "c.png"}]);
    std::fs::write(dir.join("c.bin"), &c_bin)?;
    std::fs::write(dir.join("c.png"), &png)?;
    write_uri_decoys(&dir, &c_bin)?;
    let volume = json!({"sphere": [0.0, 0.0, 0.0, 100.0]});
    let external = json!({
        "asset": {"version": "1.1"},
        "geometricError": 10.0,
        "root": {"boundingVolume": volume, "geometricError": 5.0, "refine": "ADD", "content": {"uri": "a.glb"},
                 "children": [{"boundingVolume": volume, "geometricError": 0.0, "content": {"uri": "b.b3dm"}},
                              {"boundingVolume": volume, "geometricError": 0.0, "content": {"uri": "c.gltf"}},
                              {"boundingVolume": volume, "geometricError": 0.0, "content": {"uri": "d.glb"}},
                              {"boundingVolume": volume, "geometricError": 0.0, "content": {"uri": "m.glb"}}]}
    });
    let tileset = json!({
        "asset": {"version": "1.0"},
        "geometricError": 100.0,
        "root": {
            "boundingVolume": {"region": [0.23, 0.91, 0.24, 0.92, 0.0, 100.0]},
            "geometricError": 50.0,
            "refine": "REPLACE",
            "transform": enu,
            "content": {"uri": "b.b3dm"},
            "children": [
                {"boundingVolume": volume, "geometricError": 1.0, "transform": [1,0,0,0, 0,1,0,0, 0,0,1,0, 20,0,0,1],
                 "content": {"uri": "a.glb"}},
                {"boundingVolume": volume, "geometricError": 1.0, "content": {"uri": "ext.json"}}
            ]
        }
    });
    let seeds = vec![
        Seed {
            name: "tileset.json".into(),
            bytes: serde_json::to_vec_pretty(&tileset)?,
        },
        Seed {
            name: "ext.json".into(),
            bytes: serde_json::to_vec_pretty(&external)?,
        },
        Seed {
            name: "a.glb".into(),
            bytes: glb,
        },
        Seed {
            name: "b.b3dm".into(),
            bytes: b3dm,
        },
        Seed {
            name: "c.gltf".into(),
            bytes: serde_json::to_vec_pretty(&c_gltf)?,
        },
        Seed {
            name: "d.glb".into(),
            bytes: encoded_seed("draco-etc1s.glb")?,
        },
        Seed {
            name: "m.glb".into(),
            bytes: encoded_seed("meshopt-etc1s.glb")?,
        },
    ];
    for seed in &seeds {
        std::fs::write(dir.join(&seed.name), &seed.bytes).with_context(|| format!("writing {}", seed.name))?;
    }
    Ok(seeds)
}

/// The fuzz seeds of `tools/test-data/encoded-tilesets/fuzz` (made by the ecosystem's own
/// tools: `tools/scripts/make-encoded-tilesets.sh`): Draco and meshopt glbs with ETC1S
/// textures, and ETC1S, UASTC and UASTC+zstd KTX2 files.
fn encoded_seed(file: &str) -> Result<Vec<u8>> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../test-data/encoded-tilesets/fuzz")
        .join(file);
    std::fs::read(&path).with_context(|| format!("reading {}", path.display()))
}

/// A patch set of three patches over two PNGs (one listed twice), written to `work/patches`;
/// its `patches.json` and both PNGs are the seeds.
fn patches_seeds(work: &Path) -> Result<Vec<Seed>> {
    let dir = work.join("patches");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut seeds = Vec::new();
    for (file, width, height) in [("patch_0000.png", 8u32, 8u32), ("patch_0001.png", 16, 4)] {
        let image = image::RgbaImage::from_fn(width, height, |x, y| image::Rgba([x as u8 * 16, y as u8 * 16, 99, 255]));
        let mut png = Vec::new();
        image::DynamicImage::ImageRgba8(image)
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
        std::fs::write(dir.join(file), &png)?;
        seeds.push(Seed {
            name: file.to_owned(),
            bytes: png,
        });
    }
    let record = |id: u64, file: &str, (width, height): (u32, u32), min: [f64; 2], arrival_s: f64| {
        citystream_gen::patches::PatchRecord {
            id,
            file: file.to_owned(),
            width,
            height,
            min,
            max: [min[0] + f64::from(width) * 2.0, min[1] + f64::from(height) * 2.0],
            metres_per_texel: 2.0,
            arrival_s,
        }
    };
    let set = citystream_gen::patches::PatchSet {
        format: "citystream-patches".into(),
        version: citystream_gen::patches::PATCHES_VERSION,
        source_image: "source.png".into(),
        source_size: [64, 64],
        source_crc32: 0x1234_5678,
        dataset: "city".into(),
        origin: [391_250.0, 34.0, -5_819_500.0],
        crs: Some("EPSG:25833".into()),
        extent_min: [-64.0, -64.0],
        extent_max: [64.0, 64.0],
        duration_s: 60.0,
        seed: 1,
        patches: vec![
            record(0, "patch_0000.png", (8, 8), [-64.0, -64.0], 0.0),
            record(1, "patch_0001.png", (16, 4), [-10.0, 5.0], 12.5),
            record(2, "patch_0000.png", (8, 8), [20.0, -30.0], 59.0),
        ],
    };
    let json = serde_json::to_vec_pretty(&set)?;
    std::fs::write(dir.join(citystream_gen::patches::PATCHES_FILE), &json)?;
    seeds.push(Seed {
        name: citystream_gen::patches::PATCHES_FILE.to_owned(),
        bytes: json,
    });
    Ok(seeds)
}

/// A small dataset with every format, rectangular and partial chains, a second write to
/// splice files from, and each of its six files as a seed.
fn dataset_seeds(work: &Path) -> Result<Vec<Seed>> {
    let dir = work.join("dataset");
    let other = work.join("dataset-other-write");
    for target in [&dir, &other] {
        let mut writer = DatasetWriter::create(target)?;
        let textures: [(TextureFormat, u32, u32, u32); 5] = [
            (TextureFormat::Rgba8, 8, 8, 4),
            (TextureFormat::Bc1, 16, 4, 5),
            (TextureFormat::Bc3, 8, 8, 2),
            (TextureFormat::Bc7, 4, 4, 3),
            (TextureFormat::Bc1, 32, 32, 6),
        ];
        let mut scene = Scene::new([391_000.0, 35.0, 5_819_000.0]);
        for (t, &(format, w, h, mips)) in textures.iter().enumerate() {
            let len: u64 = (0..mips)
                .map(|l| format.mip_bytes((w >> l).max(1), (h >> l).max(1)))
                .sum();
            let chain: Vec<u8> = (0..len)
                .map(|i| (i as u8).wrapping_mul(31).wrapping_add(t as u8))
                .collect();
            writer.add_texture(format, w, h, mips, &chain, [t as u8 * 40, 90, 200, 255])?;
            let x = t as f32 * 10.0;
            scene.push_mesh(
                t as u32,
                &[[x, 0.0, 0.0], [x + 8.0, 0.0, 0.0], [x + 8.0, 12.0, 0.0], [x, 12.0, 0.0]],
                &[[0.0, 0.0, 1.0]; 4],
                &[[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]],
                &[0, 1, 2, 0, 2, 3],
            )?;
        }
        writer.finish(&scene)?;
    }
    let files = DatasetFiles::resolve(&dir)?;
    let mut seeds = Vec::new();
    for name in DATASET_FILES.into_iter().filter(|&n| n != MANIFEST_FILE) {
        seeds.push(Seed {
            name: name.into(),
            bytes: std::fs::read(files.path(name))?,
        });
    }
    seeds.push(Seed {
        name: MANIFEST_FILE.into(),
        bytes: std::fs::read(dir.join(MANIFEST_FILE))?,
    });
    // Files of the other write are donors only through splices of same-named seeds: add them
    // as seeds of their own name so a whole file of another write is also tried.
    let other_files = DatasetFiles::resolve(&other)?;
    for name in [TILES_FILE, PACK_FILE] {
        seeds.push(Seed {
            name: name.into(),
            bytes: std::fs::read(other_files.path(name))?,
        });
    }
    Ok(seeds)
}

fn path_seeds() -> Result<Vec<Seed>> {
    let mut scene = Scene::new([0.0; 3]);
    for (i, x) in [-300.0f32, 0.0, 250.0].into_iter().enumerate() {
        scene.push_mesh(
            i as u32,
            &[
                [x, 0.0, -200.0],
                [x + 50.0, 0.0, -200.0],
                [x + 50.0, 40.0, 200.0],
                [x, 40.0, 200.0],
            ],
            &[[0.0, 1.0, 0.0]; 4],
            &[[0.0; 2]; 4],
            &[0, 1, 2, 0, 2, 3],
        )?;
    }
    let standard = standard_path(&scene, 60.0)?.to_json()?;
    let handwritten = r#"{ "version": 1, "description": "two runs",
  "keyframes": [
    { "t": 0.0, "position": [0, 50, -100], "look_at": [0, 10, 0] },
    { "t": 6.0, "position": [40, 80, -20], "look_at": [40, 10, 40], "hold_s": 2.0 },
    { "t": 14.0, "position": [-50, 80, 0], "look_at": [0, 10, 0], "jump": true },
    { "t": 20.5, "position": [-50, 30, 90], "look_at": [0, 0, 0] }
  ] }"#;
    Ok(vec![
        Seed {
            name: "standard.json".into(),
            bytes: standard.into_bytes(),
        },
        Seed {
            name: "handwritten.json".into(),
            bytes: handwritten.as_bytes().to_vec(),
        },
    ])
}

/// The Khronos BoxTextured sample as `.gltf` (external buffer and PNG, copied into the
/// harness's base directory, with the URI decoys) and `.glb`, and a two-node quad with a
/// data-URI buffer.
fn gltf_seeds(work: &Path) -> Result<Vec<Seed>> {
    let samples = Path::new(env!("CARGO_MANIFEST_DIR")).join("../test-data/gltf");
    let base = work.join("gltf");
    std::fs::create_dir_all(&base)?;
    for file in ["BoxTextured0.bin", "CesiumLogoFlat.png"] {
        std::fs::copy(samples.join("BoxTextured").join(file), base.join(file))
            .with_context(|| format!("copying the glTF sample {file}"))?;
    }
    write_uri_decoys(&base, &std::fs::read(base.join("BoxTextured0.bin"))?)?;
    let read = |path: PathBuf| std::fs::read(&path).with_context(|| format!("reading {}", path.display()));
    let quad_data = quad_buffer(1.0, 2.0);
    let data_uri = format!("data:application/octet-stream;base64,{}", base64(&quad_data.bytes));
    let sin_45_degrees = std::f32::consts::FRAC_1_SQRT_2;
    let quad = serde_json::json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [
            {"translation": [391000.0, 0.0, 5819000.0], "children": [1, 2]},
            {"mesh": 0, "rotation": [0.0, sin_45_degrees, 0.0, sin_45_degrees], "scale": [2.0, 2.0, 2.0]},
            {"mesh": 0, "matrix": [1,0,0,0, 0,1,0,0, 0,0,1,0, 5,0,0,1]}
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2,
                                    "material": 0, "mode": 4}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.8, 1.0, 1.0]}}],
        "buffers": [{"uri": data_uri, "byteLength": quad_data.bytes.len()}],
        "bufferViews": quad_data.buffer_views,
        "accessors": quad_data.accessors
    });
    Ok(vec![
        Seed {
            name: "BoxTextured.gltf".into(),
            bytes: read(samples.join("BoxTextured/BoxTextured.gltf"))?,
        },
        Seed {
            name: "BoxTextured.glb".into(),
            bytes: read(samples.join("BoxTextured-Binary/BoxTextured.glb"))?,
        },
        Seed {
            name: "quad.gltf".into(),
            bytes: serde_json::to_vec_pretty(&quad)?,
        },
        Seed {
            name: "draco-etc1s.glb".into(),
            bytes: encoded_seed("draco-etc1s.glb")?,
        },
        Seed {
            name: "meshopt-etc1s.glb".into(),
            bytes: encoded_seed("meshopt-etc1s.glb")?,
        },
    ])
}

/// One square quad in the xy plane as a glTF buffer, with what describes it.
#[derive(Debug)]
pub struct QuadBuffer {
    /// Positions (48 bytes), UVs (32), u16 indices (12).
    pub bytes: Vec<u8>,
    /// The three buffer views over buffer 0.
    pub buffer_views: serde_json::Value,
    /// Accessors 0 (POSITION, with min and max), 1 (TEXCOORD_0), 2 (indices).
    pub accessors: serde_json::Value,
}

/// A quad of `side` metres with UVs from 0 to `uv_max` (beyond 1 they repeat): the glTF
/// buffer behind the fuzz seed and the tests' glTF files.
pub fn quad_buffer(side: f32, uv_max: f32) -> QuadBuffer {
    let positions: [[f32; 3]; 4] = [[0.0, 0.0, 0.0], [side, 0.0, 0.0], [side, side, 0.0], [0.0, side, 0.0]];
    let uvs: [[f32; 2]; 4] = [[0.0, uv_max], [uv_max, uv_max], [uv_max, 0.0], [0.0, 0.0]];
    let mut bytes = Vec::new();
    for v in positions.iter().flatten().chain(uvs.iter().flatten()) {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    for i in [0u16, 1, 2, 0, 2, 3] {
        bytes.extend_from_slice(&i.to_le_bytes());
    }
    QuadBuffer {
        bytes,
        buffer_views: serde_json::json!([
            {"buffer": 0, "byteOffset": 0, "byteLength": 48},
            {"buffer": 0, "byteOffset": 48, "byteLength": 32},
            {"buffer": 0, "byteOffset": 80, "byteLength": 12}
        ]),
        accessors: serde_json::json!([
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [0.0, 0.0, 0.0], "max": [side, side, 0.0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"}
        ]),
    }
}

fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for chunk in bytes.chunks(3) {
        let n = chunk.iter().fold(0u32, |acc, &b| (acc << 8) | u32::from(b)) << (8 * (3 - chunk.len()));
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(ALPHABET[((n >> (18 - 6 * k)) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// KTX2 (RGBA8, BC1, BC3), DDS (DXT1, DXT5) and PNG files.
fn texture_seeds() -> Result<Vec<Seed>> {
    let mut bc1 = [0u8; 8];
    let mut bc3 = [0u8; 16];
    let texels: [[u8; 4]; 16] = std::array::from_fn(|i| [i as u8 * 16, 200, 40, 255 - i as u8]);
    texpresso::Format::Bc1.compress_block_masked(texels, 0xffff, texpresso::Params::default(), &mut bc1);
    texpresso::Format::Bc3.compress_block_masked(texels, 0xffff, texpresso::Params::default(), &mut bc3);
    let rgba: Vec<u8> = (0..8 * 4 * 4).map(|i| (i * 7) as u8).collect();
    let mut png = Vec::new();
    image::codecs::png::PngEncoder::new(&mut png)
        .write_image(&rgba, 8, 4, image::ExtendedColorType::Rgba8)
        .context("encoding the PNG seed")?;
    Ok(vec![
        Seed {
            name: "rgba8.ktx2".into(),
            bytes: ktx2_file(37, 8, 4, &[rgba]),
        },
        Seed {
            name: "bc1.ktx2".into(),
            bytes: ktx2_file(131, 4, 4, &[bc1.to_vec()]),
        },
        Seed {
            name: "bc3.ktx2".into(),
            bytes: ktx2_file(137, 4, 4, &[bc3.to_vec()]),
        },
        Seed {
            name: "dxt1.dds".into(),
            bytes: dds_file(b"DXT1", 0, 4, 4, &[bc1.to_vec()]),
        },
        Seed {
            name: "dxt5.dds".into(),
            bytes: dds_file(b"DXT5", 0, 4, 4, &[bc3.to_vec()]),
        },
        Seed {
            name: "bc7-dx10.dds".into(),
            bytes: dds_file(
                b"DX10",
                98,
                8,
                8,
                &[
                    [0x40; 64].to_vec(),
                    [0x40; 16].to_vec(),
                    [0x40; 16].to_vec(),
                    [0x40; 16].to_vec(),
                ],
            ),
        },
        Seed {
            name: "small.png".into(),
            bytes: png,
        },
        Seed {
            name: "roof-etc1s.ktx2".into(),
            bytes: encoded_seed("roof-etc1s.ktx2")?,
        },
        Seed {
            name: "roof-uastc.ktx2".into(),
            bytes: encoded_seed("roof-uastc.ktx2")?,
        },
        Seed {
            name: "roof-uastc-zstd.ktx2".into(),
            bytes: encoded_seed("roof-uastc-zstd.ktx2")?,
        },
    ])
}

use image::ImageEncoder;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_are_accepted_and_inputs_are_reproducible() {
        for target in Target::ALL {
            let work =
                std::env::temp_dir().join(format!("citystream-fuzz-unit-{}-{}", target.name(), std::process::id()));
            let harness = Harness::new(target, &work).expect("harness");
            for (i, seed) in harness.seeds.iter().enumerate() {
                // A dataset file of the other write is refused in place of the dataset's own;
                // a remote answer named `refused-…` is one the client must refuse.
                let from_other_write = harness.seeds[..i].iter().any(|s| s.name == seed.name);
                let expected = if from_other_write || seed.name.starts_with("refused-") {
                    Outcome::Rejected
                } else {
                    Outcome::Accepted
                };
                assert_eq!(
                    harness.run(i, &seed.bytes),
                    expected,
                    "{}: seed {}",
                    target.name(),
                    seed.name
                );
            }
            assert_eq!(harness.input(7, 3), harness.input(7, 3));
            assert_ne!(harness.input(7, 3), harness.input(7, 4));
            let _ = std::fs::remove_dir_all(&work);
        }
    }

    #[test]
    fn uri_shapes_meet_their_decoys_and_never_panic() {
        // Every shape at every URI site of the seeds with external files, run once. Shapes
        // naming a device are left to the `fuzz` binary, whose watchdog stops a read
        // without end (a unit test has none).
        for target in [Target::Gltf, Target::Tileset] {
            let work =
                std::env::temp_dir().join(format!("citystream-fuzz-uris-{}-{}", target.name(), std::process::id()));
            let harness = Harness::new(target, &work).expect("harness");
            let dir = work.join(target.name());
            for decoy in [
                "file:/dev/zero",
                "file:/etc/passwd",
                "\u{fffd}.bin",
                "C:\\x.bin",
                "../outside.bin",
            ] {
                assert!(dir.join(decoy).is_file(), "{}: decoy {decoy}", target.name());
            }
            assert!(dir.join("escape.bin").is_file() && !dir.join("zero.bin").is_file());
            for (i, seed) in harness.seeds.iter().enumerate() {
                if !["BoxTextured.gltf", "c.gltf", "tileset.json"].contains(&seed.name.as_str()) {
                    continue;
                }
                let sites = uri_sites(&seed.bytes).len();
                assert!(sites >= 2, "{}", seed.name);
                for shape in harness.uri_shapes.iter().filter(|s| !s.uri.contains("zero")) {
                    for site in 0..sites {
                        let mut bytes = seed.bytes.clone();
                        put_uri(&mut bytes, site, shape);
                        let outcome = harness.run(i, &bytes);
                        // A URI with a scheme is refused even where a decoy has its name.
                        if shape.uri.starts_with("file:") || shape.uri.contains("://") {
                            assert_eq!(outcome, Outcome::Rejected, "{} site {site}: {:?}", seed.name, shape.uri);
                        }
                    }
                }
            }
            let _ = std::fs::remove_dir_all(&work);
        }
    }

    #[test]
    fn base64_matches_the_standard_alphabet() {
        assert_eq!(base64(b"Man"), "TWFu");
        assert_eq!(base64(b"Ma"), "TWE=");
        assert_eq!(base64(b"M"), "TQ==");
    }
}
