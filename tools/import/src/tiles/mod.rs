//! `citystream import TILESET_JSON`: an OGC 3D Tiles tileset (1.0 and 1.1) as a dataset,
//! from a directory or a URL ([`remote`]).
//!
//! The tile hierarchy is walked from `tileset.json`, following external tilesets (content
//! URIs ending in `.json`) and composing each tile's `transform` down the tree. Content is
//! read from b3dm (3D Tiles 1.0: feature and batch tables skipped, `RTC_CENTER` applied)
//! and glTF 2.0 (`.glb`, `.gltf`; 1.1 content, `CESIUM_RTC` applied), with glTF's y-up axis
//! turned to the tiles' z-up as the specification says; every triangle primitive becomes a
//! mesh and its textures go through the glTF import's path (BCn blocks kept, the rest
//! encoded), a texture shared by several tiles imported once.
//!
//! Which tiles: `--lod finest` (the default) takes the content of tiles that are not
//! refined further under `REPLACE` refinement and every tile's content under `ADD`;
//! `--lod all` keeps every level. Point clouds, instanced and composite tiles and
//! implicit tiling are not imported: they are counted and named in a warning
//! (`--strict` makes them an error).
//!
//! Coordinates: the tileset's Earth-centred coordinates (EPSG:4978) become a local
//! east-north-up frame at the centre of the imported geometry (up along the WGS 84
//! ellipsoid's normal there, as CesiumJS's `eastNorthUpToFixedFrame`), which the dataset
//! names as its CRS; positions stay in f64 until they are made relative to the dataset's
//! origin.
//!
//! Input is untrusted: tilesets that refer to themselves through external tilesets, URIs
//! that leave the tileset's directory, non-finite transforms or bounding volumes,
//! negative geometric errors and b3dm lengths that disagree with the file are refused,
//! naming the tile; file sizes, tile counts and nesting are bounded.

pub mod content;
pub mod geodesy;
pub mod remote;
pub mod tileset;
pub mod write;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use citystream_dataset::{Crs, DatasetWriter, Scene, ShardRecord, TextureFormat, SHARD_RECORD_FILE};
use rayon::prelude::*;
use serde_json::Value;

use citystream_gen::files::print_stdout;
use citystream_gen::shard::{Shard, ShardWrite};
use citystream_gen::texture::EncodedTexture;

use crate::encodings::EncodingCounts;
use crate::gltf::{
    bounds, read_gltf, relative_uri_path, scene_at, scene_origin, GltfContent, PendingMesh, MAX_IMPORTED_VERTICES,
};
use crate::transform::{mul, Mat4, IDENTITY};
use geodesy::{to_geodetic, EastNorthUp};
use tileset::{
    content_kind, content_uri_path, objects_within, Refine, TileJson, TilesetJson, UpAxis, MAX_CONTENTS,
    MAX_CONTENT_BYTES, MAX_DEPTH, MAX_HELD_TILESET_OBJECTS, MAX_TILES, MAX_TILESETS, MAX_TILESET_BYTES,
};

/// Distances from the Earth's centre (metres) a city's geometry lies between: the WGS 84
/// ellipsoid is 6,356.8 to 6,378.1 km, and city heights are within a few km of it.
const EARTH_SHELL_M: (f64, f64) = (6_300_000.0, 6_450_000.0);

/// Which tiles' content is imported.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Lod {
    /// The finest level: tiles not refined further (`REPLACE`), every tile under `ADD`.
    Finest,
    /// Every tile's content, all levels overlapping (for inspection).
    All,
}

/// A content file to import and the transform that places it in Earth-centred coordinates.
struct ContentRef {
    path: PathBuf,
    transform: Mat4,
    /// Its glTF's up axis (`asset.gltfUpAxis` of the tileset or the one above it; y).
    up: UpAxis,
    tile: String,
}

/// The walk over a tileset and its external tilesets.
struct Walk {
    /// The top tileset's directory: no URI may leave it.
    root_dir: PathBuf,
    lod: Lod,
    tiles: usize,
    tilesets: usize,
    /// Content entries listed (followed or not).
    content_entries: usize,
    contents: Vec<ContentRef>,
    /// Content not imported, by kind.
    skipped: BTreeMap<String, usize>,
    /// JSON objects of the tilesets parsed and held now (the chain of external tilesets
    /// being walked), against [`MAX_HELD_TILESET_OBJECTS`].
    held_objects: usize,
}

/// A tileset read into memory: what `import` writes as a dataset.
#[derive(Debug)]
pub struct ImportedTileset {
    /// Meshes in dataset form, in the local east-north-up frame.
    pub scene: Scene,
    /// Textures handed to the sink, in first-use order (their ids).
    pub textures: usize,
    /// How many of them keep their source's BC blocks as they are.
    pub kept_blocks: usize,
    /// The frame the scene's coordinates are in.
    pub frame: EastNorthUp,
    /// Content files imported.
    pub contents: usize,
    /// Tiles walked (external tilesets' included).
    pub tiles: usize,
    /// Content not imported, by kind, and how many of each.
    pub skipped: BTreeMap<String, usize>,
    /// A fingerprint of the contents walked (their paths in order, each file's bytes and
    /// those of its external buffers and images): part of a shard's job.
    pub contents_fingerprint: u32,
    /// Meshes and textures by the encoding they were stored in.
    pub encodings: EncodingCounts,
}

/// Whether `input` names a tileset rather than a glTF file: a `.json` file, or a URL whose
/// path is one (its query string, `?token=…`, and fragment aside).
pub fn is_tileset(input: &Path) -> bool {
    let location = input.to_string_lossy();
    let path = if citystream_dataset::remote::is_remote(&location) {
        Path::new(location.split(['?', '#']).next().unwrap_or(""))
    } else {
        input
    };
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("json"))
}

/// How [`load`] reads a tileset.
#[derive(Clone, Debug)]
pub struct LoadOptions {
    /// Texture encoding, and the largest side kept.
    pub format: TextureFormat,
    pub max_extent: u32,
    pub lod: Lod,
    /// Content that is not imported is an error (instead of a warning).
    pub strict: bool,
    /// Warnings and progress on standard error.
    pub report: bool,
    /// A UTM projection to place the city in; `None`: a local east-north-up frame.
    pub crs: Option<Crs>,
    /// Import only this shard's contiguous part of the contents (in the walk's order), in
    /// the frame and at the origin of the whole tileset (whose geometry is still read).
    pub part: Option<Shard>,
}

/// Reads the tileset `input` and its content. Each texture new to the import is handed to
/// `sink` as it is encoded (its id is the count handed before it), so that textures need
/// not all be held at once; the scene follows once every content is read.
pub fn load(
    input: &Path,
    options: &LoadOptions,
    sink: &mut dyn FnMut(&EncodedTexture) -> Result<()>,
) -> Result<ImportedTileset> {
    let LoadOptions {
        format,
        max_extent,
        lod,
        strict,
        report,
        ref crs,
        part,
    } = *options;
    let canonical = input
        .canonicalize()
        .with_context(|| format!("reading tileset {}", input.display()))?;
    let root_dir = canonical.parent().unwrap_or(Path::new("/")).to_path_buf();
    let mut walk = Walk {
        root_dir,
        lod,
        tiles: 0,
        tilesets: 0,
        content_entries: 0,
        contents: Vec::new(),
        skipped: BTreeMap::new(),
        held_objects: 0,
    };
    let top = Inherited {
        transform: IDENTITY,
        refine: Refine::Replace,
        up: UpAxis::Y,
        depth: 0,
    };
    walk.tileset(&canonical, top, &mut Vec::new())?;
    if strict && !walk.skipped.is_empty() {
        bail!("{}: {} (--strict)", input.display(), skipped_text(&walk.skipped));
    }
    if report && !walk.skipped.is_empty() {
        eprintln!(
            "warning: {}: {} (not imported; --strict makes this an error)",
            input.display(),
            skipped_text(&walk.skipped)
        );
    }
    if walk.contents.is_empty() {
        bail!(
            "{}: no b3dm or glTF content to import in {} tiles{}",
            input.display(),
            walk.tiles,
            if walk.skipped.is_empty() {
                String::new()
            } else {
                format!("; {}", skipped_text(&walk.skipped))
            }
        );
    }

    let started = Instant::now();
    let (mut textures, mut kept_blocks) = (0usize, 0usize);
    let mut texture_ids: HashMap<u128, usize> = HashMap::new();
    let mut vertices = 0usize;
    let count = walk.contents.len();
    // Each content file is read and parsed once, however many tiles list it: its listings
    // are placed from that one read, and the meshes keep the order the walk met them in.
    let mut files: Vec<&Path> = Vec::new();
    let mut listings_of: HashMap<&Path, Vec<usize>> = HashMap::new();
    for (n, content) in walk.contents.iter().enumerate() {
        let listings = listings_of.entry(content.path.as_path()).or_default();
        if listings.is_empty() {
            files.push(content.path.as_path());
        }
        listings.push(n);
    }
    if let Some(shard) = part {
        shard.check_divides(count, "contents")?;
    }
    let part = part.map(|shard| shard.range(count));
    let in_part = |listing: usize| part.as_ref().is_none_or(|range| range.contains(&listing));
    let mut placed: Vec<Vec<PendingMesh>> = Vec::new();
    placed.resize_with(count, Vec::new);
    let mut listings_done = 0usize;
    let mut encodings = EncodingCounts::default();
    // glTF content requiring extensions the import does not decode: by extensions, the
    // listings skipped and the first files.
    let mut undecoded: BTreeMap<String, (usize, Vec<String>)> = BTreeMap::new();
    // What every content file holds (its bytes, and its external buffers' and images'),
    // in the walk's order: part of a shard's job, so that shards of a
    // tileset whose files changed between them are not joined.
    let mut content_bytes = crc32fast::Hasher::new();
    for (n, path) in files.iter().enumerate() {
        let listings = &listings_of[path];
        let first = &walk.contents[listings[0]];
        let what = |i: usize| {
            let content = &walk.contents[i];
            format!("{} (tile {})", content.path.display(), content.tile)
        };
        let (mut read, centres) = match read_content(
            first,
            &walk.root_dir,
            MAX_IMPORTED_VERTICES - vertices,
            &mut content_bytes,
        )
        .with_context(|| what(listings[0]))?
        {
            Content::Read(read, centres) => (read, centres),
            Content::Undecoded(extensions) => {
                let names = extensions.join(", ");
                if strict {
                    bail!(
                        "{}: requires {names}, which citystream does not decode (--strict)",
                        what(listings[0])
                    );
                }
                let (count, examples) = undecoded.entry(names).or_default();
                *count += listings.len();
                if examples.len() < 3 {
                    examples.push(file_name(path));
                }
                listings_done += listings.len();
                continue;
            }
        };
        // Textures new to the import are encoded (in parallel); shared ones map to the first.
        // Content outside a shard's part is read for its geometry only (the frame and origin
        // are the whole tileset's).
        let wanted = listings.iter().any(|&l| in_part(l));
        let mut local_to_global = Vec::with_capacity(read.texture_count());
        let mut fresh = Vec::new();
        for k in (0..read.texture_count()).filter(|_| wanted) {
            let identity = read.texture_identity(k).with_context(|| what(listings[0]))?;
            let next = textures + fresh.len();
            let id = *texture_ids.entry(identity).or_insert_with(|| {
                fresh.push(k);
                next
            });
            local_to_global.push(id);
        }
        let encoded = fresh
            .par_iter()
            .map(|&k| read.encode_texture(k, format, max_extent))
            .collect::<Result<Vec<_>>>()
            .with_context(|| what(listings[0]))?;
        for (texture, origin) in &encoded {
            sink(texture).with_context(|| what(listings[0]))?;
            kept_blocks += usize::from(origin.kept_blocks);
            encodings.add_texture(origin.encoding);
        }
        textures += encoded.len();
        let mut first_meshes = std::mem::take(&mut read.meshes);
        for (i, &listing) in listings.iter().enumerate() {
            let mut meshes = if i == 0 {
                std::mem::take(&mut first_meshes)
            } else {
                let content = &walk.contents[listing];
                read.place(&content_root(content, centres), MAX_IMPORTED_VERTICES - vertices)
                    .with_context(|| what(listing))?
            };
            for mesh in &mut meshes {
                mesh.texture = local_to_global.get(mesh.texture).copied().unwrap_or(0);
                vertices += mesh.positions.len();
                encodings.add_mesh(mesh.encoding);
            }
            placed[listing] = meshes;
            listings_done += 1;
            if report && count >= 100 && listings_done.is_multiple_of((count / 20).max(1)) {
                eprintln!(
                    "import: {listings_done}/{count} contents ({}/{} files read), {} textures, {:.0} s",
                    n + 1,
                    files.len(),
                    textures,
                    started.elapsed().as_secs_f64()
                );
            }
        }
    }
    let mut fingerprint = crc32fast::Hasher::new();
    for content in &walk.contents {
        let relative = content.path.strip_prefix(&walk.root_dir).unwrap_or(&content.path);
        fingerprint.update(relative.to_string_lossy().as_bytes());
        fingerprint.update(&[0]);
    }
    fingerprint.update(&content_bytes.finalize().to_le_bytes());
    let listing_of_mesh: Vec<usize> = placed
        .iter()
        .enumerate()
        .flat_map(|(l, meshes)| std::iter::repeat_n(l, meshes.len()))
        .collect();
    let mut skipped = walk.skipped;
    for (extensions, (n, examples)) in undecoded {
        let kind = format!("glTF content requiring {extensions}");
        if report {
            let more = if n > examples.len() { ", …" } else { "" };
            eprintln!(
                "warning: {}: {n} glTF content listings skipped ({}{more}): they require {extensions}, which \
                 citystream does not decode (--strict makes this an error)",
                input.display(),
                examples.join(", ")
            );
        }
        *skipped.entry(kind).or_default() += n;
    }
    let mut meshes: Vec<PendingMesh> = placed.into_iter().flatten().collect();
    if meshes.is_empty() {
        bail!(
            "{}: the tileset's {count} contents hold no triangle meshes",
            input.display()
        );
    }

    let frame = local_frame(&meshes).with_context(|| format!("{}: placing the tileset", input.display()))?;
    let scene_crs = match crs {
        None => {
            for mesh in &mut meshes {
                for p in &mut mesh.positions {
                    let [e, n, u] = frame.local(*p);
                    *p = [e, u, -n];
                }
                for normal in &mut mesh.normals {
                    let [e, n, u] = frame.local_direction(normal.map(f64::from));
                    *normal = [e as f32, u as f32, -n as f32];
                }
            }
            enu_crs(&frame)?
        }
        Some(crs) => {
            project_utm(&mut meshes, &frame, crs).with_context(|| format!("{}: --crs {crs}", input.display()))?;
            crs.clone()
        }
    };
    let origin = scene_origin(&meshes);
    if part.is_some() {
        meshes = meshes
            .into_iter()
            .zip(&listing_of_mesh)
            .filter(|(_, &l)| in_part(l))
            .map(|(m, _)| m)
            .collect();
    }
    let mut scene = scene_at(&meshes, origin, input)?;
    scene.crs = Some(scene_crs);
    Ok(ImportedTileset {
        scene,
        textures,
        kept_blocks,
        frame,
        contents: count,
        tiles: walk.tiles,
        skipped,
        contents_fingerprint: fingerprint.finalize(),
        encodings,
    })
}

/// Writes the tileset `input` (a path, or an `http(s)://` or `s3://` URL: see [`remote`])
/// as the dataset `out` (see [`load`]).
pub fn import(input: &Path, out: &Path, options: &LoadOptions) -> Result<()> {
    let location = input.to_string_lossy();
    let shard = match options.part {
        Some(shard) => Some(ShardWrite::begin(
            out,
            shard,
            &format!("citystream import {location}"),
            !options.report,
        )?),
        None => None,
    };
    let out = shard.as_ref().map_or(out, |s| s.dir());
    let imported = import_fetched(input, &location, out, options);
    match shard {
        Some(shard) if imported.is_ok() => shard.publish(),
        _ => imported,
    }
}

fn import_fetched(input: &Path, location: &str, out: &Path, options: &LoadOptions) -> Result<()> {
    if !citystream_dataset::remote::is_remote(location) {
        return import_local(input, location, out, options);
    }
    // Beside the output, also when it is given with a trailing slash.
    let out_clean: PathBuf = out.components().collect();
    let mut scratch = out_clean.into_os_string();
    scratch.push(".tileset-download");
    let scratch = PathBuf::from(scratch);
    if scratch.exists() {
        remote::clear_stale_download(&scratch)?;
    }
    let imported = remote::fetch(location, &scratch).and_then(|local| {
        import_local(&local, location, out, options)
            .with_context(|| format!("importing {location} as fetched into {}", scratch.display()))
    });
    // The scratch copy goes whatever happened; a failure to remove it is only reported.
    if let Err(e) = std::fs::remove_dir_all(&scratch) {
        eprintln!("warning: could not remove {}: {e}", scratch.display());
    }
    imported
}

fn import_local(input: &Path, shown: &str, out: &Path, options: &LoadOptions) -> Result<()> {
    let start = Instant::now();
    // Textures go to the pack as they are encoded; the dataset appears only at `finish`.
    let mut writer = DatasetWriter::create(out)?;
    let imported = load(input, options, &mut |t| {
        writer.add_texture(t.format, t.width, t.height, t.mip_count, &t.chain, t.mean)?;
        Ok(())
    })?;
    if let Some(shard) = options.part {
        let job = format!(
            "citystream import {shown} --format {} --max-extent {} --lod {:?} --strict {} --crs {}, contents {} {:08x}",
            options.format.name(),
            options.max_extent,
            options.lod,
            options.strict,
            options.crs.as_ref().map_or("(local frame)", |c| c.as_str()),
            imported.contents,
            imported.contents_fingerprint
        )
        .replace(['\n', '\r'], " ");
        let record = ShardRecord {
            job,
            index: shard.index,
            count: shard.count,
            textures: writer.texture_count(),
            meshes: imported.scene.meshes.len() as u32,
            pack_bytes: writer.pack_len(),
        };
        writer.add_file(SHARD_RECORD_FILE, &record.encode()?)?;
    }
    let summary = writer
        .finish(&imported.scene)
        .with_context(|| format!("writing {}", out.display()))?;
    imported.encodings.write(out)?;
    let origin = to_geodetic(imported.frame.origin);
    print_stdout(&format!(
        "imported tileset {} into {}: {} tiles, {} contents, {} meshes, {} triangles, {} textures ({}), {:.1} MB pack, {:.2} s\nencodings: {}\nframe: east-north-up at {}\n",
        shown,
        out.display(),
        imported.tiles,
        imported.contents,
        summary.meshes,
        summary.triangles,
        summary.textures,
        imported.encodings.texture_note(imported.kept_blocks, options.format.name()),
        summary.pack_bytes as f64 / 1e6,
        start.elapsed().as_secs_f64(),
        imported.encodings.summary(),
        origin.map_or_else(|| "?".to_owned(), |g| format!(
            "latitude {:.7}°, longitude {:.7}°, height {:.3} m (WGS 84)",
            g.latitude.to_degrees(),
            g.longitude.to_degrees(),
            g.height
        ))
    ))
}

fn skipped_text(skipped: &BTreeMap<String, usize>) -> String {
    let list: Vec<String> = skipped.iter().map(|(kind, n)| format!("{n} {kind}")).collect();
    format!(
        "skipped content of kinds citystream does not import: {}",
        list.join(", ")
    )
}

/// What a tile takes from its ancestors: their composed transform, refinement and up axis, and
/// how deep it lies (external tilesets included).
#[derive(Clone, Copy)]
struct Inherited {
    transform: Mat4,
    refine: Refine,
    up: UpAxis,
    depth: usize,
}

impl Walk {
    fn tileset(&mut self, path: &Path, from: Inherited, chain: &mut Vec<PathBuf>) -> Result<()> {
        if let Some(at) = chain.iter().position(|p| p == path) {
            let cycle: Vec<String> = chain[at..]
                .iter()
                .chain(std::iter::once(&path.to_path_buf()))
                .map(|p| p.display().to_string())
                .collect();
            bail!(
                "external tilesets refer to each other in a cycle: {}",
                cycle.join(" -> ")
            );
        }
        self.tilesets += 1;
        if self.tilesets > MAX_TILESETS {
            bail!(
                "more than {MAX_TILESETS} external tilesets are read (at {})",
                path.display()
            );
        }
        let (tileset, objects) = read_tileset(path, MAX_HELD_TILESET_OBJECTS - self.held_objects)?;
        // The tilesets above this one stay parsed while it is walked: their objects count.
        self.held_objects += objects;
        let walked = self.walk_tileset(&tileset, path, from, chain);
        self.held_objects -= objects;
        walked
    }

    /// [`tileset`](Self::tileset) once `tileset` is parsed.
    fn walk_tileset(
        &mut self,
        tileset: &TilesetJson,
        path: &Path,
        from: Inherited,
        chain: &mut Vec<PathBuf>,
    ) -> Result<()> {
        let unsupported: Vec<&String> = tileset
            .extensions_required
            .iter()
            .filter(|e| e.as_str() != "3DTILES_content_gltf")
            .collect();
        if !unsupported.is_empty() {
            bail!(
                "{}: the tileset requires extensions citystream does not read: {unsupported:?}",
                path.display()
            );
        }
        let up = match tileset
            .asset
            .gltf_up_axis
            .as_deref()
            .map(str::to_ascii_uppercase)
            .as_deref()
        {
            None => from.up,
            Some("X") => UpAxis::X,
            Some("Y") => UpAxis::Y,
            Some("Z") => UpAxis::Z,
            Some(other) => bail!("{}: asset.gltfUpAxis {other:?} (X, Y or Z)", path.display()),
        };
        let dir = path.parent().unwrap_or(Path::new("/")).to_path_buf();
        chain.push(path.to_path_buf());
        let walked = self.tile(
            &tileset.root,
            &dir,
            Inherited { up, ..from },
            chain,
            &format!("{}#root", file_name(path)),
        );
        chain.pop();
        walked.with_context(|| format!("in tileset {}", path.display()))
    }

    fn tile(
        &mut self,
        tile: &TileJson,
        dir: &Path,
        from: Inherited,
        chain: &mut Vec<PathBuf>,
        name: &str,
    ) -> Result<()> {
        let Inherited {
            transform: parent,
            refine: inherited,
            up,
            depth,
        } = from;
        if depth > MAX_DEPTH {
            bail!("tile {name}: tiles nest deeper than {MAX_DEPTH} levels");
        }
        self.tiles += 1;
        if self.tiles > MAX_TILES {
            bail!("tile {name}: the tileset has more than {MAX_TILES} tiles");
        }
        check_tile(tile).with_context(|| format!("tile {name}"))?;
        let world = match &tile.transform {
            Some(t) => mul(&parent, &matrix(t).with_context(|| format!("tile {name}: transform"))?),
            None => parent,
        };
        if world.iter().flatten().any(|v| !v.is_finite()) {
            bail!("tile {name}: its transform composed with its ancestors' is not finite");
        }
        let refine = match tile.refine.as_deref().map(str::to_ascii_uppercase).as_deref() {
            None => inherited,
            Some("REPLACE") => Refine::Replace,
            Some("ADD") => Refine::Add,
            Some(other) => bail!("tile {name}: refine {other:?} (REPLACE or ADD)"),
        };
        // An implicitly tiled subtree's content URIs are templates (`{level}/{x}/{y}`):
        // counted, not followed.
        let implicit = tile.implicit_tiling.is_some();
        if implicit {
            *self.skipped.entry("implicitly tiled subtrees".to_owned()).or_default() += 1;
        }
        let below = Inherited {
            transform: world,
            refine,
            up,
            depth: depth + 1,
        };
        let keep = self.lod == Lod::All || refine == Refine::Add || tile.children.is_empty();
        let contents = tile.content.iter().chain(&tile.contents).filter(|_| !implicit);
        for content in contents {
            self.content_entries += 1;
            if self.content_entries > MAX_CONTENTS {
                bail!("tile {name}: the tileset lists more than {MAX_CONTENTS} contents");
            }
            let Some(uri) = content.uri.as_deref().or(content.url.as_deref()) else {
                bail!("tile {name}: content without a uri");
            };
            let path = self
                .resolve(dir, uri)
                .with_context(|| format!("tile {name}: content {uri:?}"))?;
            let kind = content_kind(&path);
            match kind.as_str() {
                "json" => self.tileset(&path, below, chain)?,
                "b3dm" | "glb" | "gltf" if keep => self.contents.push(ContentRef {
                    path,
                    transform: world,
                    up,
                    tile: name.to_owned(),
                }),
                "b3dm" | "glb" | "gltf" => {}
                "pnts" => *self.skipped.entry("point clouds (pnts)".to_owned()).or_default() += 1,
                "i3dm" => *self.skipped.entry("instanced models (i3dm)".to_owned()).or_default() += 1,
                "cmpt" => *self.skipped.entry("composite tiles (cmpt)".to_owned()).or_default() += 1,
                "subtree" => *self.skipped.entry("implicit tiling subtrees".to_owned()).or_default() += 1,
                _ => *self.skipped.entry(format!("unknown content (.{kind})")).or_default() += 1,
            }
        }
        for (i, child) in tile.children.iter().enumerate() {
            self.tile(child, dir, below, chain, &format!("{name}/{i}"))?;
        }
        Ok(())
    }

    /// A content URI as a file inside the top tileset's directory.
    fn resolve(&self, dir: &Path, uri: &str) -> Result<PathBuf> {
        let path = dir.join(content_uri_path(uri)?);
        let canonical = path
            .canonicalize()
            .with_context(|| format!("{} does not exist", path.display()))?;
        if !canonical.starts_with(&self.root_dir) {
            bail!(
                "{} lies outside the tileset's directory {}",
                canonical.display(),
                self.root_dir.display()
            );
        }
        Ok(canonical)
    }
}

fn file_name(path: &Path) -> String {
    path.file_name()
        .map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned())
}

fn read_bounded(path: &Path, limit: u64, what: &str) -> Result<Vec<u8>> {
    citystream_dataset::ensure_regular_file(path).with_context(|| format!("reading {}", path.display()))?;
    let len = std::fs::metadata(path)
        .with_context(|| format!("reading {}", path.display()))?
        .len();
    if len > limit {
        bail!("{}: a {what} of {len} bytes (at most {limit} are read)", path.display());
    }
    std::fs::read(path).with_context(|| format!("reading {}", path.display()))
}

/// Reads and parses the tileset `path` and counts its JSON objects, refused before it is
/// parsed where it holds more than `max_objects` (a parsed tile takes some 250 bytes, so
/// a file of empty tiles takes 80 times its size once parsed).
fn read_tileset(path: &Path, max_objects: usize) -> Result<(TilesetJson, usize)> {
    let bytes = read_bounded(path, MAX_TILESET_BYTES, "tileset")?;
    let objects = objects_within(&bytes, max_objects, &path.display())?;
    let tileset: TilesetJson =
        serde_json::from_slice(&bytes).with_context(|| format!("{}: not a 3D Tiles tileset", path.display()))?;
    if !matches!(tileset.asset.version.as_str(), "0.0" | "1.0" | "1.1") {
        bail!(
            "{}: 3D Tiles version {:?} (citystream reads 1.0 and 1.1)",
            path.display(),
            tileset.asset.version
        );
    }
    Ok((tileset, objects))
}

/// A tile's numbers: a finite, non-negative geometric error; bounding volumes of the
/// right length, finite, with non-negative extents.
fn check_tile(tile: &TileJson) -> Result<()> {
    if let Some(error) = tile.geometric_error {
        if !(error.is_finite() && error >= 0.0) {
            bail!("geometricError {error} (a finite, non-negative number)");
        }
    }
    if let Some(volume) = &tile.bounding_volume {
        let check = |name: &str, values: &Option<Vec<f64>>, len: usize| -> Result<()> {
            if let Some(values) = values {
                if values.len() != len || values.iter().any(|v| !v.is_finite()) {
                    bail!("boundingVolume.{name} must be {len} finite numbers, not {values:?}");
                }
            }
            Ok(())
        };
        check("box", &volume.oriented_box, 12)?;
        check("region", &volume.region, 6)?;
        check("sphere", &volume.sphere, 4)?;
        if let Some(sphere) = &volume.sphere {
            if sphere[3] < 0.0 {
                bail!("boundingVolume.sphere has a negative radius {}", sphere[3]);
            }
        }
        if let Some(region) = &volume.region {
            if region[4] > region[5] || region[1] > region[3] {
                bail!("boundingVolume.region {region:?} has its south above its north or its floor above its ceiling");
            }
        }
    }
    Ok(())
}

/// A 3D Tiles transform (16 numbers, column-major).
fn matrix(values: &[f64]) -> Result<Mat4> {
    if values.len() != 16 || values.iter().any(|v| !v.is_finite()) {
        bail!("16 finite numbers expected, found {values:?}");
    }
    Ok(std::array::from_fn(|c| std::array::from_fn(|r| values[c * 4 + r])))
}

fn translation(t: [f64; 3]) -> Mat4 {
    let mut m = IDENTITY;
    m[3] = [t[0], t[1], t[2], 1.0];
    m
}

/// An x-up glTF to the tiles' z-up (CesiumJS's `Axis.X_UP_TO_Z_UP`, a rotation about y by
/// −90°): (x, y, z) → (−z, y, x).
const X_UP_TO_Z_UP: Mat4 = [
    [0.0, 0.0, 1.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

/// glTF's y-up to the tiles' z-up: (x, y, z) → (x, −z, y).
const Y_UP_TO_Z_UP: Mat4 = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

/// The RTC centres a content file carries: its b3dm's and its glTF's `CESIUM_RTC`.
type RtcCentres = [Option<[f64; 3]>; 2];

/// Where a listing of a content file places its glTF: Cesium's order, the tile's
/// transform, the centres, then the axis correction (the glTF's own node transforms follow).
fn content_root(content: &ContentRef, centres: RtcCentres) -> Mat4 {
    let mut transform = content.transform;
    for center in centres.into_iter().flatten() {
        transform = mul(&transform, &translation(center));
    }
    match content.up {
        UpAxis::X => transform = mul(&transform, &X_UP_TO_Z_UP),
        UpAxis::Y => transform = mul(&transform, &Y_UP_TO_Z_UP),
        UpAxis::Z => {}
    }
    transform
}

/// A content file, read or not.
enum Content {
    /// Its glTF's primitives and its RTC centres (boxed: the other variant is small).
    Read(Box<GltfContent>, RtcCentres),
    /// Its glTF requires these extensions, which the import does not decode.
    Undecoded(Vec<String>),
}

/// One content file read: its glTF's primitives placed in Earth-centred coordinates (for
/// `content`, the first listing of the file), and its RTC centres (for the others).
fn read_content(
    content: &ContentRef,
    root_dir: &Path,
    vertex_budget: usize,
    fingerprint: &mut crc32fast::Hasher,
) -> Result<Content> {
    let bytes = read_bounded(&content.path, MAX_CONTENT_BYTES, "content file")?;
    fingerprint.update(&(bytes.len() as u64).to_le_bytes());
    fingerprint.update(&bytes);
    let (glb, batch_rtc) = if content_kind(&content.path) == "b3dm" {
        let batched = content::parse_b3dm(&bytes)?;
        (batched.glb, batched.rtc_center)
    } else {
        (&bytes[..], None)
    };
    let json = content::gltf_json(glb)?;
    let undecoded = content::undecoded_required(&json);
    if !undecoded.is_empty() {
        return Ok(Content::Undecoded(undecoded));
    }
    let gltf_rtc = content::cesium_rtc(&json)?;
    let centres = [batch_rtc, gltf_rtc];
    let transform = content_root(content, centres);
    let base = content.path.parent().unwrap_or(Path::new("/"));
    check_external_files(&json, base, root_dir, fingerprint)?;
    Ok(Content::Read(
        Box::new(read_gltf(glb, base, &content.path, &transform, vertex_budget)?),
        centres,
    ))
}

/// The files a glTF's buffers and images name (other than data URIs) lie inside the
/// tileset's directory `root_dir` and are at most [`MAX_CONTENT_BYTES`], before the glTF
/// reader opens them; their bytes go into `fingerprint`.
fn check_external_files(json: &Value, base: &Path, root_dir: &Path, fingerprint: &mut crc32fast::Hasher) -> Result<()> {
    for key in ["buffers", "images"] {
        let items = json.get(key).and_then(Value::as_array).into_iter().flatten();
        for (i, item) in items.enumerate() {
            let Some(uri) = item.get("uri").and_then(Value::as_str) else {
                continue;
            };
            if uri.starts_with("data:") {
                continue;
            }
            let what = || format!("glTF {key}[{i}] uri {uri:?}");
            let relative = relative_uri_path(uri)
                .with_context(|| format!("{}: not a relative path inside the tileset's directory", what()))?;
            let path = base.join(relative);
            let canonical = path
                .canonicalize()
                .with_context(|| format!("{}: {} does not exist", what(), path.display()))?;
            if !canonical.starts_with(root_dir) {
                bail!(
                    "{}: {} lies outside the tileset's directory {}",
                    what(),
                    canonical.display(),
                    root_dir.display()
                );
            }
            let meta = std::fs::metadata(&canonical).with_context(what)?;
            let len = meta.len();
            if len > MAX_CONTENT_BYTES {
                bail!("{}: {len} bytes (at most {MAX_CONTENT_BYTES} are read)", what());
            }
            // Its bytes, streamed (a fetched tileset's files all have the download's time,
            // so a modification time would differ between shards of the same files).
            fingerprint.update(uri.as_bytes());
            fingerprint.update(&len.to_le_bytes());
            let mut file = std::fs::File::open(&canonical).with_context(what)?;
            let mut chunk = vec![0u8; 1 << 16];
            loop {
                match std::io::Read::read(&mut file, &mut chunk).with_context(what)? {
                    0 => break,
                    n => fingerprint.update(&chunk[..n]),
                }
            }
        }
    }
    Ok(())
}

/// Projects Earth-centred `meshes` into the UTM projection `crs` names (x easting, y
/// ellipsoidal height, −z northing), each vertex through its geodetic position; normals
/// are turned by the grid's rotation from true north at `frame`'s origin (under a
/// hundredth of a degree across a city). WGS 84 coordinates are taken as ETRS89 for the
/// ETRS89 zones: in Europe they differ by under a metre (the plates' drift since 1989).
fn project_utm(meshes: &mut [PendingMesh], frame: &EastNorthUp, crs: &Crs) -> Result<()> {
    let Some((tm, _datum)) = crs.epsg_code().and_then(geodesy::utm_of_epsg) else {
        bail!(
            "a tileset can be projected into UTM (EPSG:32601-32660, 32701-32760, 25828-25838) or, without --crs, \
             kept in a local east-north-up frame; reprojecting into another CRS is not implemented"
        );
    };
    let centre = to_geodetic(frame.origin).context("the tileset's centre has no geodetic position")?;
    let [e0, n0] = tm.project(centre.latitude, centre.longitude);
    let [e1, n1] = tm.project(centre.latitude + 1e-7, centre.longitude);
    let length = (e1 - e0).hypot(n1 - n0);
    let north = [(e1 - e0) / length, (n1 - n0) / length];
    let east = [north[1], -north[0]];
    for mesh in meshes {
        for p in &mut mesh.positions {
            let g = to_geodetic(*p).with_context(|| format!("vertex {p:?} has no geodetic position"))?;
            let [e, n] = tm.project(g.latitude, g.longitude);
            *p = Crs::to_scene([e, n, g.height]);
        }
        for normal in &mut mesh.normals {
            let [de, dn, du] = frame.local_direction(normal.map(f64::from));
            let grid_e = de * east[0] + dn * north[0];
            let grid_n = de * east[1] + dn * north[1];
            *normal = [grid_e as f32, du as f32, -grid_n as f32];
        }
    }
    Ok(())
}

/// The east-north-up frame at the centre of the meshes' Earth-centred bounds.
fn local_frame(meshes: &[PendingMesh]) -> Result<EastNorthUp> {
    let (lo, hi) = bounds(meshes);
    let centre = [0, 1, 2].map(|a| 0.5 * (lo[a] + hi[a]));
    let radius = centre[0].hypot(centre[1]).hypot(centre[2]);
    if !(EARTH_SHELL_M.0..=EARTH_SHELL_M.1).contains(&radius) {
        bail!(
            "the content's Earth-centred bounds are centred {:.1} km from the Earth's centre, not near its surface \
             ({:.0} to {:.0} km): is the tileset really in EPSG:4978 (a root transform missing)?",
            radius / 1e3,
            EARTH_SHELL_M.0 / 1e3,
            EARTH_SHELL_M.1 / 1e3
        );
    }
    EastNorthUp::at(centre).with_context(|| {
        format!(
            "the content's Earth-centred bounds are centred at {centre:?}, where no east-north-up frame exists \
             (on the Earth's axis, or not finite): is it really in EPSG:4978?"
        )
    })
}

/// Marks the frame's Earth-centred origin in [`enu_crs`]'s text.
const ORIGIN_MARK: &str = "Topocentric origin at EPSG:4978 (";

/// The Earth-centred origin of a local east-north-up CRS written by this import, read
/// back from its text; `None` for any other CRS.
pub fn local_frame_origin(crs: &Crs) -> Option<[f64; 3]> {
    let text = crs.as_str();
    let start = text.find(ORIGIN_MARK)? + ORIGIN_MARK.len();
    let numbers = &text[start..start + text[start..].find(')')?];
    let values: Vec<f64> = numbers
        .split(',')
        .map(|v| v.trim().parse().ok())
        .collect::<Option<_>>()?;
    match values[..] {
        [x, y, z] if values.iter().all(|v| v.is_finite()) => Some([x, y, z]),
        _ => None,
    }
}

/// The dataset's CRS for `frame`: an engineering CRS naming the frame's origin.
fn enu_crs(frame: &EastNorthUp) -> Result<Crs> {
    let g = to_geodetic(frame.origin).context("the frame's origin has no geodetic position")?;
    let [x, y, z] = frame.origin;
    let text = format!(
        "ENGCRS[\"citystream local east-north-up at latitude {lat:.9}, longitude {lon:.9}, height {h:.4} m (WGS 84)\",\
         EDATUM[\"{ORIGIN_MARK}{x:.4}, {y:.4}, {z:.4})\"],\
         CS[Cartesian,3],\
         AXIS[\"easting (E)\",east,ORDER[1],LENGTHUNIT[\"metre\",1]],\
         AXIS[\"northing (N)\",north,ORDER[2],LENGTHUNIT[\"metre\",1]],\
         AXIS[\"ellipsoidal height (U)\",up,ORDER[3],LENGTHUNIT[\"metre\",1]]]",
        lat = g.latitude.to_degrees(),
        lon = g.longitude.to_degrees(),
        h = g.height,
    );
    Crs::parse(&text).map_err(|e| anyhow::anyhow!("the local frame's CRS: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_frame_origin_reads_back_from_the_crs_text() {
        let origin = geodesy::to_ecef(geodesy::Geodetic {
            latitude: 52.5f64.to_radians(),
            longitude: 13.4f64.to_radians(),
            height: 34.0,
        });
        let crs = enu_crs(&EastNorthUp::at(origin).expect("frame")).expect("crs");
        let back = local_frame_origin(&crs).expect("origin");
        for a in 0..3 {
            assert!((back[a] - origin[a]).abs() < 1e-4, "{back:?} vs {origin:?}");
        }
        assert_eq!(local_frame_origin(&Crs::epsg(25833)), None);
    }
}
