//! Fuzz harnesses for every parser of untrusted input: dataset files, camera paths, glTF/GLB
//! import, KTX2/DDS/PNG texture input and ground patch sets.
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

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use citystream_dataset::{
    verify, Dataset, DatasetFiles, DatasetWriter, Scene, TextureFormat, CHECKSUM_FILE, COLORMAP_FILE, MANIFEST_FILE,
    META_FILE, PACK_FILE, SCENE_FILE,
};
use citystream_streaming::bench::path::{standard_path, CameraPath};
use citystream_streaming::rng::SplitMix64;

/// The parsers a harness drives.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Target {
    /// `Dataset::open`, every mip read and `verify`, one mutated file at a time.
    Dataset,
    /// `CameraPath::from_json` and sampling of what parses.
    Path,
    /// glTF and GLB import (`import::load_slice`) without writing a dataset.
    Gltf,
    /// KTX2, DDS and PNG decoding (`decode_image_bytes`).
    Texture,
    /// Ground patch sets: `patches.json` and the PNG headers `PatchSet::open` reads, then
    /// the images decoded as the flythrough decodes them where their listed size is small.
    Patches,
    /// A remote store's HTTP client against a scripted loopback server whose every answer
    /// is the input (status line, headers, lengths, ranges, body): a file's length (HEAD)
    /// and a 32-byte range read.
    Remote,
    /// 3D Tiles import (`tiles::load`, every level) of a small tileset with an external
    /// tileset, b3dm and glb content, one mutated file at a time, without writing a dataset.
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

#[derive(Debug)]
struct Seed {
    /// What the bytes are: a dataset file name, or a file name whose extension says the kind.
    name: String,
    bytes: Vec<u8>,
}

/// What one input did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// The parser accepted it (and everything downstream ran).
    Accepted,
    /// The parser returned an error.
    Rejected,
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
        let outcome = if std::fs::write(&path, bytes).is_err() {
            Outcome::Rejected
        } else {
            match crate::patches::PatchSet::open(&dir) {
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
        };
        // Restore the set's own file for the next input.
        if let Some(original) = self.seeds.iter().find(|s| s.name == name) {
            let _ = std::fs::write(&path, &original.bytes);
        }
        outcome
    }

    fn run_tileset(&self, name: &str, bytes: &[u8]) -> Outcome {
        let dir = self.work.join("tileset");
        let path = dir.join(name);
        let outcome = if std::fs::write(&path, bytes).is_err() {
            Outcome::Rejected
        } else {
            // RGBA8 and a small extent: the harness is about parsing, not encoding.
            let tileset = dir.join("tileset.json");
            let options = crate::tiles::LoadOptions {
                format: TextureFormat::Rgba8,
                max_extent: 64,
                lod: crate::tiles::Lod::All,
                strict: false,
                report: false,
                crs: None,
            };
            match crate::tiles::load(&tileset, &options, &mut |_| Ok(())) {
                Ok(_) => Outcome::Accepted,
                Err(_) => Outcome::Rejected,
            }
        };
        // Restore the tileset's own file for the next input.
        if let Some(original) = self.seeds.iter().find(|s| s.name == name) {
            let _ = std::fs::write(&path, &original.bytes);
        }
        outcome
    }

    fn dataset_dir(&self) -> PathBuf {
        self.work.join("dataset")
    }

    fn run_dataset(&self, name: &str, bytes: &[u8]) -> Outcome {
        let dir = self.dataset_dir();
        let path = dataset_file_path(&dir, name);
        let write = std::fs::write(&path, bytes);
        let outcome = if write.is_err() {
            Outcome::Rejected
        } else {
            match Dataset::open(&dir) {
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
            }
        };
        // Restore the dataset's own file (the first seed of that name) for the next input.
        if let Some(original) = self.seeds.iter().find(|s| s.name == name) {
            let _ = std::fs::write(&path, &original.bytes);
        }
        outcome
    }

    fn run_gltf(&self, name: &str, bytes: &[u8]) -> Outcome {
        let base = self.work.join("gltf");
        // RGBA8 and a small extent: the harness is about parsing, not encoding.
        match crate::import::load_slice(bytes, &base, Path::new(name), TextureFormat::Rgba8, 64) {
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
    // Both readers of texture files: block sources kept as they are by `import`, and the
    // decoder every other image goes through.
    let kept = crate::import::block_source(bytes);
    match crate::gen::library::decode_image_bytes(bytes) {
        Ok(_) => Outcome::Accepted,
        Err(_) if matches!(kept, Ok(Some(_))) => Outcome::Accepted,
        Err(_) => Outcome::Rejected,
    }
}

fn below(rng: &mut SplitMix64, n: usize) -> usize {
    (rng.next_u64() % n.max(1) as u64) as usize
}

/// Values that break careless arithmetic, as little-endian 4- and 8-byte fields.
const EXTREME_U32: [u32; 9] = [
    0,
    1,
    u32::MAX,
    0x8000_0000,
    0x7fff_ffff,
    0x7fc0_0000, // f32 NaN
    0x7f80_0000, // f32 +inf
    0xff80_0000, // f32 -inf
    0x7149_f2ca, // f32 1e30
];
const EXTREME_U64: [u64; 6] = [
    0,
    u64::MAX,
    1 << 32,
    1 << 63,
    0x7ff8_0000_0000_0000, // f64 NaN
    0x7ff0_0000_0000_0000, // f64 +inf
];
const EXTREME_NUMBERS: [&str; 14] = [
    "0",
    "-0",
    "-1",
    "1e308",
    "-1e308",
    "1e999",
    "NaN",
    "Infinity",
    "4294967296",
    "18446744073709551616",
    "2147483648",
    "1e-320",
    "0.5",
    "99999999999999999999999999999",
];

/// One to four mutations of `original`; `donor` provides spliced bytes, `uris` the URI
/// shapes (none: no URI mutation, and the same inputs as before it existed).
fn mutate(rng: &mut SplitMix64, original: &[u8], donor: &[u8], text: bool, uris: &[UriShape]) -> Vec<u8> {
    let mut b = original.to_vec();
    let count = 1 + below(rng, 4);
    for _ in 0..count {
        let kinds = if text { 10 } else { 8 } + usize::from(!uris.is_empty());
        let kind = below(rng, kinds);
        // Binary inputs skip the two text mutations (8, 9).
        let kind = if !text && kind >= 8 { kind + 2 } else { kind };
        match kind {
            0 if !b.is_empty() => {
                let i = below(rng, b.len());
                b[i] ^= 1 << below(rng, 8);
            }
            1 if !b.is_empty() => {
                let i = below(rng, b.len());
                b[i] = [0u8, 0xff, 0x7f, 0x80, b'0', b'"'][below(rng, 6)];
            }
            2 if b.len() >= 4 => {
                // Aligned fields: headers are made of them.
                let i = below(rng, b.len() / 4) * 4;
                let v = EXTREME_U32[below(rng, EXTREME_U32.len())];
                b[i..i + 4].copy_from_slice(&v.to_le_bytes());
            }
            3 if b.len() >= 8 => {
                let i = below(rng, b.len() / 8) * 8;
                let v = EXTREME_U64[below(rng, EXTREME_U64.len())];
                b[i..i + 8].copy_from_slice(&v.to_le_bytes());
            }
            4 => {
                let keep = below(rng, b.len() + 1);
                b.truncate(keep);
            }
            5 if !donor.is_empty() => {
                // Splice: a run of the donor over a run of the input.
                let from = below(rng, donor.len());
                let len = 1 + below(rng, (donor.len() - from).min(256));
                let at = below(rng, b.len() + 1);
                let end = (at + len).min(b.len());
                b.splice(at..end, donor[from..from + len].iter().copied());
            }
            6 if !b.is_empty() => {
                let at = below(rng, b.len());
                let len = 1 + below(rng, (b.len() - at).min(64));
                if below(rng, 2) == 0 {
                    b.drain(at..at + len);
                } else {
                    let copy: Vec<u8> = b[at..at + len].to_vec();
                    b.splice(at..at, copy);
                }
            }
            7 => {
                let extra: Vec<u8> = (0..1 + below(rng, 32)).map(|_| rng.next_u64() as u8).collect();
                let at = below(rng, b.len() + 1);
                b.splice(at..at, extra);
            }
            8 => replace_number(rng, &mut b),
            9 if !b.is_empty() => {
                // Remove a structural character of JSON.
                let positions: Vec<usize> = b
                    .iter()
                    .enumerate()
                    .filter(|(_, c)| b"{}[],:\"".contains(c))
                    .map(|(i, _)| i)
                    .collect();
                if !positions.is_empty() {
                    b.remove(positions[below(rng, positions.len())]);
                }
            }
            10 if !uris.is_empty() => {
                let shape = &uris[below(rng, uris.len())];
                let site = rng.next_u64() as usize;
                put_uri(&mut b, site, shape);
            }
            _ => {}
        }
    }
    b
}

/// Replaces one number token of JSON text with an extreme one.
fn replace_number(rng: &mut SplitMix64, b: &mut Vec<u8>) {
    let is_number_byte = |c: u8| c.is_ascii_digit() || b"-+.eE".contains(&c);
    let starts: Vec<usize> = (0..b.len())
        .filter(|&i| b[i].is_ascii_digit() && (i == 0 || !is_number_byte(b[i - 1])))
        .collect();
    if starts.is_empty() {
        return;
    }
    let start = starts[below(rng, starts.len())];
    let start = if start > 0 && b[start - 1] == b'-' {
        start - 1
    } else {
        start
    };
    let mut end = start + 1;
    while end < b.len() && is_number_byte(b[end]) {
        end += 1;
    }
    let replacement = EXTREME_NUMBERS[below(rng, EXTREME_NUMBERS.len())];
    b.splice(start..end, replacement.bytes());
}

/// A URI a glTF buffer or image or a tile's content is given in place of its own and, for
/// some data URIs, the `byteLength` its object then declares.
#[derive(Clone, Debug)]
struct UriShape {
    uri: String,
    byte_length: Option<&'static str>,
}

/// URI shapes that broke the import or that a resolver must refuse or keep inside: schemes
/// (`file:` of a device, of a file outside, of a name a decoy has), escapes that are not
/// UTF-8 or decode to a separator, paths outside or absolute, drive letters and UNC names,
/// queries and fragments, data URIs (valid, truncated, bad base64, a declared length far
/// beyond their bytes), empty, very long, NUL and control characters, U+FFFD, and names of
/// the tileset's own files (cycles). [`write_uri_decoys`] makes the naive readings exist.
fn uri_shapes() -> Vec<UriShape> {
    let fixed = [
        "file:/dev/zero",
        "file:///dev/zero",
        "FILE:/dev/zero",
        "file:/etc/passwd",
        "file:///etc/passwd",
        "file:/citystream-fuzz/outside.bin",
        "file:x.bin",
        "file:",
        "file://",
        "%FF.bin",
        "%C3%28.bin",
        "%EF%BF%BD.bin",
        "%2F..%2Fx.bin",
        "%2e%2e/outside.bin",
        "..%2Foutside.bin",
        "%00.bin",
        "%",
        "a%2",
        "../outside.bin",
        "../../outside.bin",
        "escape.bin",
        "zero.bin",
        "/abs/path.bin",
        "/dev/zero",
        "//server/share/x.bin",
        "\\\\server\\share\\x.bin",
        "C:\\x.bin",
        "C:/x.bin",
        "c:x.bin",
        "http://example.com/a.glb",
        "https://example.com/a.glb?token=abc",
        "a.glb?token=abc#frag",
        "a.glb#frag",
        "?",
        "#",
        "",
        ".",
        "..",
        "./",
        "sub/../a.glb",
        "a.glb",
        "tileset.json",
        "ext.json",
        "BoxTextured0.bin",
        "CesiumLogoFlat.png",
        "c.bin",
        "c.png",
        "a\0.bin",
        "a\u{1}.bin",
        "a\n.bin",
        "\t",
        "a\u{7f}.bin",
        "\u{fffd}.bin",
        "data:",
        "data:,",
        "data:,not base64",
        "data:;base64,",
        "data:application/octet-stream;base64,!!!!",
        "data:application/octet-stream;base64,A",
        "data:application/octet-stream;base64,====",
    ];
    let mut shapes: Vec<UriShape> = fixed
        .into_iter()
        .map(|uri| UriShape {
            uri: uri.to_owned(),
            byte_length: None,
        })
        .collect();
    let buffer = format!(
        "data:application/octet-stream;base64,{}",
        base64(&quad_buffer(1.0, 2.0).bytes)
    );
    let png = format!(
        "data:image/png;base64,{}",
        base64(&crate::tiles::write::gradient_png(4, 4, 3))
    );
    let generated = [
        buffer.clone(),
        png.clone(),
        // Truncated within a base64 quantum, and by half.
        buffer[..buffer.len() - 7].to_owned(),
        png[..png.len() / 2].to_owned(),
        format!("data:application/octet-stream;base64,{}", "A".repeat(1 << 16)),
        format!("{}.bin", "x".repeat(5000)),
        format!("{}x.bin", "a/".repeat(2100)),
        format!("{}a.glb", "./".repeat(2100)),
        format!("{}outside.bin", "../".repeat(64)),
    ];
    shapes.extend(generated.into_iter().map(|uri| UriShape { uri, byte_length: None }));
    for length in ["4294967296", "18446744073709551615", "9007199254740993", "2147483647"] {
        shapes.push(UriShape {
            uri: buffer.clone(),
            byte_length: Some(length),
        });
    }
    shapes
}

/// Files in `dir` (and `../outside.bin`), each holding `bytes`, that make the naive readings
/// of some URI shapes exist: a `file:` or `http:` URI taken as a relative path, the name
/// `%FF` once decoded to (U+FFFD), a drive letter, a query taken literally; and links to a
/// device and to the file outside. Without them an import that reads such a path instead
/// of refusing the URI would stop at "missing file", and the escape would go unexercised.
fn write_uri_decoys(dir: &Path, bytes: &[u8]) -> Result<()> {
    for name in [
        "file:/dev/zero",
        "file:/etc/passwd",
        "file:/citystream-fuzz/outside.bin",
        "file:x.bin",
        "http:/example.com/a.glb",
        "https:/example.com/a.glb?token=abc",
        "C:\\x.bin",
        "c:x.bin",
        "\u{fffd}.bin",
        "a.glb?token=abc#frag",
    ] {
        let path = dir.join(name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
        }
        std::fs::write(&path, bytes).with_context(|| format!("writing the decoy {}", path.display()))?;
    }
    let outside = dir
        .parent()
        .context("a harness directory has a parent")?
        .join("outside.bin");
    std::fs::write(&outside, bytes).with_context(|| format!("writing {}", outside.display()))?;
    for (link, target) in [("zero.bin", "/dev/zero"), ("escape.bin", "../outside.bin")] {
        std::os::unix::fs::symlink(target, dir.join(link)).with_context(|| format!("linking {link}"))?;
    }
    Ok(())
}

/// Where a URI goes in glTF or tileset JSON: the string of a `"uri"` key, or, in a document
/// without one (a GLB's), the first object of `"buffers"` and of `"images"`.
#[derive(Clone, Debug, PartialEq, Eq)]
enum UriSite {
    /// The string token, quotes included.
    Value(Range<usize>),
    /// Just inside the object's `{`.
    Object(usize),
}

fn uri_sites(json: &[u8]) -> Vec<UriSite> {
    let value_of = |key_end: usize| {
        let i = skip_whitespace(json, key_end);
        (json.get(i) == Some(&b':')).then(|| skip_whitespace(json, i + 1))
    };
    let mut sites = Vec::new();
    for at in find_all(json, b"\"uri\"") {
        let Some(i) = value_of(at + 5).filter(|&i| json.get(i) == Some(&b'"')) else {
            continue;
        };
        let mut j = i + 1;
        while j < json.len() && json[j] != b'"' {
            j += if json[j] == b'\\' { 2 } else { 1 };
        }
        if j < json.len() {
            sites.push(UriSite::Value(i..j + 1));
        }
    }
    if sites.is_empty() {
        for key in [&b"\"buffers\""[..], b"\"images\""] {
            for at in find_all(json, key) {
                let Some(i) = value_of(at + key.len()).filter(|&i| json.get(i) == Some(&b'[')) else {
                    continue;
                };
                let i = skip_whitespace(json, i + 1);
                if json.get(i) == Some(&b'{') {
                    sites.push(UriSite::Object(i + 1));
                }
            }
        }
    }
    sites
}

fn find_all(hay: &[u8], needle: &[u8]) -> Vec<usize> {
    hay.windows(needle.len())
        .enumerate()
        .filter(|(_, w)| *w == needle)
        .map(|(i, _)| i)
        .collect()
}

fn skip_whitespace(b: &[u8], mut i: usize) -> usize {
    while b.get(i).is_some_and(u8::is_ascii_whitespace) {
        i += 1;
    }
    i
}

/// Puts `shape` at the URI site `site` (modulo their count) of JSON text, or of the JSON
/// chunk of a GLB (a b3dm's too) whose chunk and file lengths are then kept consistent, so
/// that the shape reaches the resolver rather than the header checks.
fn put_uri(b: &mut Vec<u8>, site: usize, shape: &UriShape) {
    let Some(embedded) = embedded_json(b) else {
        put_uri_in_json(b, site, shape);
        return;
    };
    let mut json = b[embedded.json.clone()].to_vec();
    put_uri_in_json(&mut json, site, shape);
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let grown = json.len() as i64 - embedded.json.len() as i64;
    b.splice(embedded.json, json);
    for at in embedded.lengths {
        let old = u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]]);
        if let Ok(new) = u32::try_from(i64::from(old) + grown) {
            b[at..at + 4].copy_from_slice(&new.to_le_bytes());
        }
    }
}

/// The JSON chunk of a GLB or of the GLB inside a b3dm, and the offsets of the lengths that
/// cover it (the chunk's, the GLB's, the b3dm's).
struct EmbeddedJson {
    json: Range<usize>,
    lengths: Vec<usize>,
}

fn embedded_json(b: &[u8]) -> Option<EmbeddedJson> {
    let u32_at = |i: usize| {
        b.get(i..i + 4)
            .and_then(|s| <[u8; 4]>::try_from(s).ok())
            .map(|s| u32::from_le_bytes(s) as usize)
    };
    let (glb, mut lengths) = if b.starts_with(b"b3dm") {
        // Feature table and batch table, JSON and binary, before the GLB.
        let tables: usize = [12, 16, 20, 24].into_iter().map(u32_at).sum::<Option<usize>>()?;
        (28 + tables, vec![8])
    } else {
        (0, Vec::new())
    };
    if b.get(glb..glb + 4)? != b"glTF" || b.get(glb + 16..glb + 20)? != b"JSON" {
        return None;
    }
    let start = glb + 20;
    let end = start + u32_at(glb + 12)?;
    if end > b.len() {
        return None;
    }
    lengths.extend([glb + 8, glb + 12]);
    Some(EmbeddedJson {
        json: start..end,
        lengths,
    })
}

fn put_uri_in_json(json: &mut Vec<u8>, site: usize, shape: &UriShape) {
    let sites = uri_sites(json);
    if sites.is_empty() {
        return;
    }
    let quoted = serde_json::Value::from(shape.uri.as_str()).to_string();
    let at = match &sites[site % sites.len()] {
        UriSite::Value(range) => {
            json.splice(range.clone(), quoted.bytes());
            range.start
        }
        UriSite::Object(at) => {
            json.splice(*at..*at, format!("\"uri\":{quoted},").bytes());
            *at
        }
    };
    if let Some(length) = shape.byte_length {
        set_byte_length(json, at, length);
    }
}

/// Sets the `byteLength` of the object around `at` (naively: between the nearest braces).
fn set_byte_length(json: &mut Vec<u8>, at: usize, value: &str) {
    let Some(open) = json[..at].iter().rposition(|&c| c == b'{') else {
        return;
    };
    let close = json[at..]
        .iter()
        .position(|&c| c == b'}')
        .map_or(json.len(), |p| at + p);
    let key = b"\"byteLength\"";
    let Some(k) = find_all(&json[open..close], key).first().map(|p| open + p) else {
        return;
    };
    let i = skip_whitespace(json, k + key.len());
    if json.get(i) != Some(&b':') {
        return;
    }
    let i = skip_whitespace(json, i + 1);
    let len = json[i..]
        .iter()
        .take_while(|c| c.is_ascii_digit() || b"-+.eE".contains(c))
        .count();
    json.splice(i..i + len, value.bytes());
}

fn dataset_file_path(dir: &Path, name: &str) -> PathBuf {
    if name == MANIFEST_FILE {
        dir.join(name)
    } else {
        // Resolved once per seed set: the fixture's manifest is restored after every input.
        DatasetFiles::resolve(dir).map_or_else(|_| dir.join(name), |files| files.path(name))
    }
}

/// Recomputes the checksum of a dataset file (layout of `docs/DATASET.md`), so that mutated
/// fields reach the checks behind it.
fn fix_dataset_checksum(name: &str, b: &mut [u8]) {
    let crc_of = |parts: &[&[u8]]| {
        let mut hasher = crc32fast::Hasher::new();
        for part in parts {
            hasher.update(part);
        }
        hasher.finalize()
    };
    let (covered_to, crc_at, body_from) = match name {
        SCENE_FILE => (96, 96, 104),
        PACK_FILE => (40, 40, usize::MAX),
        MANIFEST_FILE => (24, 24, usize::MAX),
        _ => (32, 32, 40),
    };
    if b.len() < crc_at + 4 || (body_from != usize::MAX && b.len() < body_from) {
        return;
    }
    let crc = if body_from == usize::MAX {
        crc_of(&[&b[..covered_to]])
    } else {
        crc_of(&[&b[..covered_to], &b[body_from..]])
    };
    b[crc_at..crc_at + 4].copy_from_slice(&crc.to_le_bytes());
}

/// A loopback HTTP server that answers every request with the current input and closes the
/// connection, and a remote store reading from it.
#[derive(Debug)]
struct ScriptedServer {
    answer: std::sync::Arc<std::sync::Mutex<Vec<u8>>>,
    url: String,
    /// Replaced after an input that waited out the timeout: a store that saw its server go
    /// silent fails later reads at once, which would hide every later input's answer.
    store: std::sync::Mutex<citystream_dataset::remote::RemoteStore>,
}

/// The scripted server's store: no retries (every answer is the same input), a short timeout
/// for answers that promise more than they send (the server closes at once anyway).
fn scripted_store(url: &str) -> Result<citystream_dataset::remote::RemoteStore> {
    let options = citystream_dataset::remote::RemoteOptions {
        retries: 0,
        timeout: SCRIPTED_TIMEOUT,
        connect_timeout: SCRIPTED_TIMEOUT,
        ..Default::default()
    };
    Ok(citystream_dataset::remote::RemoteStore::new(url, &options)?)
}

const SCRIPTED_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(2);

impl ScriptedServer {
    fn start() -> Result<Self> {
        use std::io::{Read, Write};
        let listener = std::net::TcpListener::bind("127.0.0.1:0")?;
        let url = format!("http://{}/city/", listener.local_addr()?);
        let answer = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let served = std::sync::Arc::clone(&answer);
        std::thread::Builder::new().name("fuzz-http".into()).spawn(move || {
            for mut stream in listener.incoming().flatten() {
                // The request (small) in one read; its content does not matter.
                let mut request = [0u8; 4096];
                let _ = stream.read(&mut request);
                let bytes = served.lock().map(|a| a.clone()).unwrap_or_default();
                let _ = stream.write_all(&bytes);
                let _ = stream.shutdown(std::net::Shutdown::Both);
            }
        })?;
        let store = std::sync::Mutex::new(scripted_store(&url)?);
        Ok(Self { answer, url, store })
    }

    fn run(&self, bytes: &[u8]) -> Outcome {
        use citystream_dataset::DatasetStore;
        if let Ok(mut answer) = self.answer.lock() {
            *answer = bytes.to_vec();
        }
        let Ok(mut store) = self.store.lock() else {
            return Outcome::Rejected;
        };
        let started = std::time::Instant::now();
        let path = store.root().join("file.bin");
        let _ = store.len(&path);
        let mut buf = [0u8; 32];
        let outcome = match store.read_at(&path, 0, &mut buf) {
            Ok(()) => Outcome::Accepted,
            Err(_) => Outcome::Rejected,
        };
        if started.elapsed() >= SCRIPTED_TIMEOUT {
            if let Ok(fresh) = scripted_store(&self.url) {
                *store = fresh;
            }
        }
        outcome
    }
}

/// Answers a server may give to a length (HEAD) and a 32-byte range request: partial content
/// with its range, and ones the client refuses (`refused-…`): the whole file for a range, a
/// redirect to another origin, errors, a body without a length.
fn remote_seeds() -> Vec<Seed> {
    let body: Vec<u8> = (0..32u8).collect();
    let answer = |head: &str, body: &[u8]| {
        let mut bytes = head.replace('\n', "\r\n").into_bytes();
        bytes.extend_from_slice(body);
        bytes
    };
    let seeds = [
        (
            "partial.http",
            answer(
                "HTTP/1.1 206 Partial Content\nContent-Range: bytes 0-31/4096\nContent-Length: 32\nAccept-Ranges: bytes\n\n",
                &body,
            ),
        ),
        ("refused-whole-file-for-a-range.http", answer("HTTP/1.1 200 OK\nContent-Length: 32\n\n", &body)),
        (
            "refused-redirect-elsewhere.http",
            answer("HTTP/1.1 302 Found\nLocation: http://127.0.0.1:9/city/file.bin\nContent-Length: 0\n\n", &[]),
        ),
        ("refused-unavailable.http", answer("HTTP/1.1 503 Service Unavailable\nContent-Length: 0\n\n", &[])),
        ("refused-missing.http", answer("HTTP/1.1 404 Not Found\nContent-Length: 9\n\n", b"not found")),
        (
            "refused-chunked-without-length.http",
            answer(
                "HTTP/1.1 206 Partial Content\nContent-Range: bytes 0-31/32\nTransfer-Encoding: chunked\n\n",
                b"20\r\n\x00\x01\x02\x03\x04\x05\x06\x07\x08\x09\x0a\x0b\x0c\x0d\x0e\x0f\x10\x11\x12\x13\x14\x15\x16\x17\x18\x19\x1a\x1b\x1c\x1d\x1e\x1f\r\n0\r\n\r\n",
            ),
        ),
    ];
    seeds
        .into_iter()
        .map(|(name, bytes)| Seed {
            name: name.to_owned(),
            bytes,
        })
        .collect()
}

/// A tileset at Berlin written to `work/tileset` (`tileset.json` with a transform, REPLACE
/// refinement and an external `ext.json` under ADD; a glb with CESIUM_RTC and node
/// transforms, a b3dm with RTC_CENTER and a batch table, a glTF with an external buffer and
/// image), with the URI decoys: each file but the glTF's buffer and image is a seed.
fn tileset_seeds(work: &Path) -> Result<Vec<Seed>> {
    use crate::tiles::write;
    use serde_json::json;
    let dir = work.join("tileset");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    // East-north-up at 52.5 N, 13.4 E on the ellipsoid, as a column-major transform.
    let (lat, lon) = (52.5f64.to_radians(), 13.4f64.to_radians());
    let origin = crate::tiles::geodesy::to_ecef(crate::tiles::geodesy::Geodetic {
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
                              {"boundingVolume": volume, "geometricError": 0.0, "content": {"uri": "c.gltf"}}]}
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
    ];
    for seed in &seeds {
        std::fs::write(dir.join(&seed.name), &seed.bytes).with_context(|| format!("writing {}", seed.name))?;
    }
    Ok(seeds)
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
    let record =
        |id: u64, file: &str, (width, height): (u32, u32), min: [f64; 2], arrival_s: f64| crate::patches::PatchRecord {
            id,
            file: file.to_owned(),
            width,
            height,
            min,
            max: [min[0] + f64::from(width) * 2.0, min[1] + f64::from(height) * 2.0],
            metres_per_texel: 2.0,
            arrival_s,
        };
    let set = crate::patches::PatchSet {
        format: "citystream-patches".into(),
        version: crate::patches::PATCHES_VERSION,
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
    std::fs::write(dir.join(crate::patches::PATCHES_FILE), &json)?;
    seeds.push(Seed {
        name: crate::patches::PATCHES_FILE.to_owned(),
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
    for name in [SCENE_FILE, META_FILE, PACK_FILE, COLORMAP_FILE, CHECKSUM_FILE] {
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
    for name in [SCENE_FILE, PACK_FILE] {
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
    let samples = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/gltf");
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
    ])
}

use image::ImageEncoder;

/// A KTX2 file of `levels` (finest first): header, level index, a 4-byte data format
/// descriptor, then the levels in order. The minimal writer behind the fuzz seeds and the
/// tests' KTX2 files.
pub fn ktx2_file(vk_format: u32, width: u32, height: u32, levels: &[Vec<u8>]) -> Vec<u8> {
    let mut f = vec![0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A];
    for v in [vk_format, 1, width, height, 0, 0, 1, levels.len() as u32, 0] {
        f.extend_from_slice(&v.to_le_bytes());
    }
    let dfd_offset = 80 + 24 * levels.len();
    for v in [dfd_offset as u32, 4, 0, 0] {
        f.extend_from_slice(&v.to_le_bytes());
    }
    // No supercompression global data.
    f.extend_from_slice(&[0u8; 16]);
    let mut offset = (dfd_offset + 4) as u64;
    for level in levels {
        for v in [offset, level.len() as u64, level.len() as u64] {
            f.extend_from_slice(&v.to_le_bytes());
        }
        offset += level.len() as u64;
    }
    f.extend_from_slice(&4u32.to_le_bytes());
    for level in levels {
        f.extend_from_slice(level);
    }
    f
}

/// A DDS file of `levels` (finest first) with the FourCC `four_cc`; `DX10` adds the extended
/// header naming `dxgi_format` (ignored otherwise). The minimal writer behind the fuzz seeds
/// and the tests' DDS files.
pub fn dds_file(four_cc: &[u8; 4], dxgi_format: u32, width: u32, height: u32, levels: &[Vec<u8>]) -> Vec<u8> {
    const DDSD_MIPMAPCOUNT: u32 = 0x2_0000;
    const CAPS_MIPMAP: u32 = 0x40_0008;
    let mipmapped = levels.len() > 1;
    let flags = 0x1007 | if mipmapped { DDSD_MIPMAPCOUNT } else { 0 };
    let mut dds = b"DDS ".to_vec();
    // size, flags (caps|height|width|pixelformat[|mipmapcount]), height, width, linear size,
    // depth, mip count
    let linear_size = levels.first().map_or(0, Vec::len) as u32;
    for v in [124u32, flags, height, width, linear_size, 0, levels.len() as u32] {
        dds.extend_from_slice(&v.to_le_bytes());
    }
    dds.extend_from_slice(&[0u8; 44]);
    for v in [32u32, 0x4] {
        dds.extend_from_slice(&v.to_le_bytes());
    }
    dds.extend_from_slice(four_cc);
    dds.extend_from_slice(&[0u8; 20]);
    let caps = 0x1000 | if mipmapped { CAPS_MIPMAP } else { 0 };
    dds.extend_from_slice(&caps.to_le_bytes());
    dds.extend_from_slice(&[0u8; 16]);
    if four_cc == b"DX10" {
        // DXGI format, dimension (TEXTURE2D), misc flags, array size, misc flags 2.
        for v in [dxgi_format, 3, 0, 1, 0] {
            dds.extend_from_slice(&v.to_le_bytes());
        }
    }
    for level in levels {
        dds.extend_from_slice(level);
    }
    dds
}

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
    fn uri_shapes_go_inside_glb_and_b3dm_with_their_lengths_kept() {
        use crate::tiles::{content, write};
        let u32_at = |b: &[u8], at: usize| u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"));
        let (gltf, bin) = write::textured_quad(
            [[0.0; 3], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]],
            &write::gradient_png(4, 4, 1),
            serde_json::json!({}),
            None,
        );
        let glb = write::glb(&gltf, &bin);
        let b3dm = write::b3dm(&glb, &serde_json::json!({"BATCH_LENGTH": 0}), None, &[]);
        let shape = UriShape {
            uri: "file:/dev/zero\u{0}".into(),
            byte_length: None,
        };
        for mut b in [glb, b3dm] {
            // A GLB's JSON has no URI: site 0 is the first buffer's object.
            put_uri(&mut b, 0, &shape);
            let glb = if b.starts_with(b"b3dm") {
                assert_eq!(u32_at(&b, 8) as usize, b.len(), "b3dm byteLength");
                content::parse_b3dm(&b).expect("b3dm").glb
            } else {
                &b[..]
            };
            assert_eq!(u32_at(glb, 8) as usize, glb.len(), "GLB length");
            assert_eq!(u32_at(glb, 12) % 4, 0, "JSON chunk padded");
            let json = content::gltf_json(glb).expect("GLB JSON");
            assert_eq!(json["buffers"][0]["uri"], serde_json::json!(shape.uri));
            assert_eq!(json["images"][0]["bufferView"], serde_json::json!(3));
        }
    }

    #[test]
    fn uri_shapes_replace_uris_and_declared_lengths() {
        let text = br#"{"buffers": [ {"byteLength": 840, "uri": "a.bin"}, {"uri": "b\"q.bin", "byteLength": 8} ],
            "images": [{"uri": "c.png"}]}"#;
        assert_eq!(uri_sites(text).len(), 3);
        let huge = UriShape {
            uri: "data:application/octet-stream;base64,AAAA".into(),
            byte_length: Some("18446744073709551615"),
        };
        for (site, pointer) in [(0, "/buffers/0"), (1, "/buffers/1")] {
            let mut b = text.to_vec();
            put_uri(&mut b, site, &huge);
            let json: serde_json::Value = serde_json::from_slice(&b).expect("still JSON");
            assert_eq!(
                json.pointer(&format!("{pointer}/uri")),
                Some(&serde_json::json!(huge.uri))
            );
            assert_eq!(
                json.pointer(&format!("{pointer}/byteLength")),
                Some(&serde_json::json!(u64::MAX))
            );
        }
        // NUL and control characters go in escaped: the JSON stays valid and carries them.
        let control = UriShape {
            uri: "a\u{0}\u{1}\n\u{fffd}.bin".into(),
            byte_length: None,
        };
        let mut b = text.to_vec();
        put_uri(&mut b, 2, &control);
        let json: serde_json::Value = serde_json::from_slice(&b).expect("still JSON");
        assert_eq!(json["images"][0]["uri"], serde_json::json!(control.uri));
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
    fn number_tokens_are_replaced_whole() {
        let mut rng = SplitMix64::new(1);
        let mut text = br#"{"t": -12.5e3, "x": [1, 2]}"#.to_vec();
        replace_number(&mut rng, &mut text);
        let text = String::from_utf8(text).expect("utf-8");
        assert!(!text.contains("12.5e3") || !text.contains("[1, 2]"), "{text}");
        assert!(text.starts_with("{\"t\": "), "{text}");
    }

    #[test]
    fn base64_matches_the_standard_alphabet() {
        assert_eq!(base64(b"Man"), "TWFu");
        assert_eq!(base64(b"Ma"), "TWE=");
        assert_eq!(base64(b"M"), "TQ==");
    }
}
