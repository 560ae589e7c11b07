//! `citystream import`: a glTF 2.0 scene (`.gltf` with external or embedded resources, or
//! `.glb`) as a dataset.
//!
//! Every triangle primitive becomes one mesh; its texture is the material's base-colour
//! texture (multiplied by the base-colour factor), or a 4×4 texture of the factor when it has
//! none. Primitives sharing image and factor share a texture. Node transforms are applied
//! in f64 and positions stored relative to the scene centre. UVs are kept as they are, also
//! outside `[0, 1]` (the engine samples with repeat addressing), through the base-colour
//! texture's `KHR_texture_transform`. Geometry may be Draco-compressed, meshopt-compressed or
//! quantized ([`crate::decode`], [`crate::primitive`]). Images may be PNG, JPEG, DDS
//! (`MSFT_texture_dds`) or KTX2 (RGBA8 and BC levels, or Basis Universal under
//! `KHR_texture_basisu`, transcoded by [`crate::basis`]); the first source that reads is used.
//! A file that requires an extension outside [`DECODED_EXTENSIONS`] is refused naming it. Sides that are not powers of two are resized up to the next power
//! of two; sides above `--max-extent` are downscaled with a warning.
//!
//! KTX2 and DDS sources stored as BC1, BC3 or BC7 blocks with power-of-two sides and no
//! tint (base-colour factor 1) keep their blocks and stored levels as they are, whatever
//! `--format` says (re-encoding would only lose quality, and BC3/BC7 their alpha); levels
//! finer than `--max-extent` are dropped. Everything else is decoded and encoded in
//! `--format`. Images decode up to 16384 texels a side; larger ones are refused by extent.
//!
//! Input is untrusted: references the `gltf` crate would follow unchecked (accessor indices,
//! image sources, buffer-view strides, element counts, the GLB length) are checked first, so
//! no file makes the import panic (`fuzz --target gltf`).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use citystream_dataset::{Scene, TextureFormat};
use image::imageops::FilterType;
use image::RgbaImage;
use rayon::prelude::*;

use citystream_gen::library::decode_image_bytes;
use citystream_gen::texture::{decode_level, encode_chain, mean_colour, EncodedTexture};

use crate::basis::{is_basis, BasisTexture};
use crate::blocks::block_source;
use crate::decode::{draco, meshopt};
use crate::encodings::EncodingCounts;
pub(crate) use crate::primitive::PendingMesh;
use crate::primitive::{read_primitive, Buffers, DecodedViews, UvTransform};
use crate::transform::{mul, Mat4, IDENTITY};

/// Extensions a glTF may require that the import decodes (or, for `KHR_materials_unlit`
/// and `CESIUM_RTC`, whose meaning it keeps); content requiring any other is not imported.
pub const DECODED_EXTENSIONS: [&str; 7] = [
    "KHR_draco_mesh_compression",
    "EXT_meshopt_compression",
    "KHR_mesh_quantization",
    "KHR_texture_basisu",
    "KHR_texture_transform",
    "KHR_materials_unlit",
    "CESIUM_RTC",
];

/// The extensions of `required` (a glTF's `extensionsRequired`) the import does not decode.
pub fn undecoded_extensions<'a>(required: impl IntoIterator<Item = &'a str>) -> Vec<String> {
    required
        .into_iter()
        .filter(|e| !DECODED_EXTENSIONS.contains(e) && *e != "MSFT_texture_dds")
        .map(str::to_owned)
        .collect()
}

/// Most node instances an import places (a node reached through several
/// shared parents counts once per path).
pub const MAX_NODE_INSTANCES: usize = 1_000_000;
/// Most vertices an import holds once instances are placed (about 1 GB of
/// pending geometry).
pub const MAX_IMPORTED_VERTICES: usize = 20_000_000;

/// What a mesh's texture is made of: an image (by glTF image index) tinted by a factor.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
struct TextureKey {
    /// Candidate glTF image indices in order of preference (extension sources first).
    images: [Option<usize>; 3],
    factor: [u8; 4],
}

/// A glTF scene read into memory: what `import` writes as a dataset.
#[derive(Debug)]
pub struct ImportedScene {
    /// Meshes in dataset form, origin at the centre of the model.
    pub scene: Scene,
    /// One encoded texture per distinct (image, factor) pair, in first-use order.
    pub textures: Vec<EncodedTexture>,
    /// How many of them keep their source's BC1/BC3/BC7 blocks as they are.
    pub kept_blocks: usize,
    /// Meshes and textures by the encoding they were stored in.
    pub encodings: EncodingCounts,
}

/// Where an imported texture came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct TextureOrigin {
    /// Its source's encoding, as [`EncodingCounts`] names it.
    pub(crate) encoding: &'static str,
    /// Whether the source's BC blocks were kept as they are.
    pub(crate) kept_blocks: bool,
}

/// Reads the glTF or GLB file `input` (external files relative to its directory) and
/// encodes its textures in `format`, at most `max_extent` on a side.
pub fn load(input: &Path, format: TextureFormat, max_extent: u32) -> Result<ImportedScene> {
    let bytes = citystream_dataset::ensure_regular_file(input)
        .and_then(|()| std::fs::read(input))
        .with_context(|| format!("reading {}", input.display()))?;
    load_slice(
        &bytes,
        input.parent().unwrap_or(Path::new(".")),
        input,
        format,
        max_extent,
    )
}

/// [`load`] of glTF or GLB bytes; external files are looked up in `base`, errors name
/// `input`. Every failure is an error, whatever the bytes (the fuzz harness feeds it
/// mutated files).
pub fn load_slice(
    bytes: &[u8],
    base: &Path,
    input: &Path,
    format: TextureFormat,
    max_extent: u32,
) -> Result<ImportedScene> {
    let content = read_gltf(bytes, base, input, &IDENTITY, MAX_IMPORTED_VERTICES)?;
    if content.meshes.is_empty() {
        bail!("{}: no triangle meshes to import", input.display());
    }
    // Textures: decode and encode in parallel, in first-use order.
    let textures = (0..content.texture_count())
        .into_par_iter()
        .map(|k| content.encode_texture(k, format, max_extent))
        .collect::<Result<Vec<_>>>()?;
    let kept_blocks = textures.iter().filter(|(_, origin)| origin.kept_blocks).count();
    let mut encodings = EncodingCounts::default();
    for (_, origin) in &textures {
        encodings.add_texture(origin.encoding);
    }
    for mesh in &content.meshes {
        encodings.add_mesh(mesh.encoding);
    }
    let textures = textures.into_iter().map(|(texture, _)| texture).collect();
    let scene = centred_scene(&content.meshes, input)?;
    Ok(ImportedScene {
        scene,
        textures,
        kept_blocks,
        encodings,
    })
}

/// The triangle primitives of one glTF document, placed in f64 by a root transform and
/// the node transforms, and what their textures are made of.
pub(crate) struct GltfContent {
    document: gltf::Document,
    buffers: Vec<gltf::buffer::Data>,
    base: PathBuf,
    input: PathBuf,
    keys: Vec<TextureKey>,
    /// Buffer views that hold decoded geometry.
    decoded: DecodedViews,
    /// Every triangle primitive; `texture` indexes the document's textures.
    pub(crate) meshes: Vec<PendingMesh>,
}

/// Reads glTF or GLB `bytes` (external files in `base`, errors naming `input`): every
/// triangle primitive placed by `root` × its node's transform, at most `vertex_budget`
/// vertices in all. Checks what the `gltf` crate would panic on first.
pub(crate) fn read_gltf(
    bytes: &[u8],
    base: &Path,
    input: &Path,
    root_transform: &Mat4,
    vertex_budget: usize,
) -> Result<GltfContent> {
    let invalid = |e: gltf::Error| anyhow!("{}: not a valid glTF 2.0 file: {e}", input.display());
    if bytes.starts_with(b"glTF") {
        // The `gltf` crate subtracts the 12-byte header from the declared length unchecked.
        let declared = bytes.get(8..12).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]));
        if !declared.is_some_and(|len| (12..=bytes.len() as u64).contains(&u64::from(len))) {
            bail!(
                "{}: GLB header declares {declared:?} bytes; a GLB is at least its 12-byte header and at most the file's {} bytes",
                input.display(),
                bytes.len()
            );
        }
    }
    // The `gltf` crate's own validation indexes accessors unchecked (a POSITION attribute
    // naming a missing accessor panics inside it), so references are checked first.
    let unchecked = gltf::Gltf::from_slice_without_validation(bytes).map_err(invalid)?;
    let mut root = unchecked.document.into_json();
    check_references(&root).with_context(|| input.display().to_string())?;
    let undecoded = undecoded_extensions(root.extensions_required.iter().map(String::as_str));
    if !undecoded.is_empty() {
        bail!(
            "{}: the glTF requires {}, which citystream does not decode",
            input.display(),
            undecoded.join(", ")
        );
    }
    // Checked above; the `gltf` crate refuses extensions it does not know itself.
    root.extensions_required.clear();
    use_extension_sources(&mut root);
    let mut buffers = load_buffers(&root, unchecked.blob.as_deref(), base, input)?;
    let decoded = DecodedViews {
        meshopt: meshopt::decode_views(&root, &mut buffers).with_context(|| input.display().to_string())?,
        draco: draco::decode_primitives(&mut root, &mut buffers).with_context(|| input.display().to_string())?,
    };
    let buffers: Vec<gltf::buffer::Data> = buffers.into_iter().map(gltf::buffer::Data).collect();
    let document = gltf::Document::from_json(root).map_err(invalid)?;

    let mut keys: Vec<TextureKey> = Vec::new();
    let meshes = place_scene(
        &document,
        &buffers,
        &decoded,
        input,
        root_transform,
        vertex_budget,
        &mut keys,
    )?;

    Ok(GltfContent {
        document,
        buffers,
        base: base.to_path_buf(),
        input: input.to_path_buf(),
        keys,
        decoded,
        meshes,
    })
}

/// A texture that names its image only through an extension (`KHR_texture_basisu`,
/// `MSFT_texture_dds` without a fallback `source`) gets that image as its `source`, which the
/// `gltf` crate requires; extension sources that name no image are left to fail validation.
fn use_extension_sources(root: &mut gltf::json::Root) {
    let images = root.images.len();
    for texture in &mut root.textures {
        if texture.source.value() < images {
            continue;
        }
        let others = texture.extensions.as_ref().map(|e| &e.others);
        let from_extension = ["KHR_texture_basisu", "MSFT_texture_dds"].iter().find_map(|name| {
            let source = others?.get(*name)?.get("source")?.as_u64()?;
            usize::try_from(source).ok().filter(|&s| s < images)
        });
        if let Some(source) = from_extension {
            texture.source = gltf::json::Index::new(source as u32);
        }
    }
}

/// Every triangle primitive of `document`'s default scene placed by `root` × its node's
/// transform, at most `vertex_budget` vertices in all; each primitive's texture indexes
/// `keys`, where textures met for the first time are appended.
fn place_scene(
    document: &gltf::Document,
    buffers: &[gltf::buffer::Data],
    decoded: &DecodedViews,
    input: &Path,
    root: &Mat4,
    vertex_budget: usize,
    keys: &mut Vec<TextureKey>,
) -> Result<Vec<PendingMesh>> {
    let mut key_ids: HashMap<TextureKey, usize> = keys.iter().enumerate().map(|(i, k)| (*k, i)).collect();
    let buffers = Buffers { data: buffers, decoded };
    let mut meshes = Vec::new();
    let scene = document.default_scene().or_else(|| document.scenes().next());
    let roots: Vec<gltf::Node> = match &scene {
        Some(s) => s.nodes().collect(),
        None => bail!("{}: the glTF has no scene", input.display()),
    };
    let mut stack: Vec<(gltf::Node, Mat4, usize)> = roots.into_iter().map(|n| (n, *root, 0)).collect();
    // Nodes listed as children of several parents are instanced once per
    // path (glTF requires trees, some exporters share); the caps keep a
    // graph with exponentially many paths from exhausting memory.
    let (mut visits, mut vertices) = (0usize, 0usize);
    while let Some((node, parent, depth)) = stack.pop() {
        if depth > 256 {
            bail!("{}: node hierarchy deeper than 256 levels (a cycle?)", input.display());
        }
        visits += 1;
        if visits > MAX_NODE_INSTANCES {
            bail!(
                "{}: the node graph places more than {MAX_NODE_INSTANCES} node instances (node {} is reached \
                 again through shared children); glTF node hierarchies must be trees",
                input.display(),
                node.index()
            );
        }
        let local = node.transform().matrix().map(|c| c.map(f64::from));
        let world = mul(&parent, &local);
        if let Some(mesh) = node.mesh() {
            for primitive in mesh.primitives() {
                let what = format!(
                    "{}: mesh {} ({:?}) primitive {}",
                    input.display(),
                    mesh.index(),
                    mesh.name().unwrap_or(""),
                    primitive.index()
                );
                use gltf::mesh::Mode;
                if !matches!(
                    primitive.mode(),
                    Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
                ) {
                    eprintln!(
                        "warning: {what}: mode {:?} skipped (only triangles are imported)",
                        primitive.mode()
                    );
                    continue;
                }
                let key = texture_key(&primitive);
                let texture = *key_ids.entry(key).or_insert_with(|| {
                    keys.push(key);
                    keys.len() - 1
                });
                let uv = match primitive.material().pbr_metallic_roughness().base_color_texture() {
                    Some(info) => UvTransform::of(&info).with_context(|| what.clone())?,
                    None => (None, 0),
                };
                let mesh = read_primitive(&primitive, &buffers, &world, uv, texture).with_context(|| what.clone())?;
                vertices += mesh.positions.len();
                if vertices > vertex_budget {
                    bail!(
                        "{what}: the scene has more than {MAX_IMPORTED_VERTICES} vertices once its instances are \
                         placed; split it or share fewer nodes"
                    );
                }
                meshes.push(mesh);
            }
        }
        stack.extend(node.children().map(|c| (c, world, depth + 1)));
    }
    Ok(meshes)
}

impl GltfContent {
    /// The document's primitives placed again, by `root` instead of the root it was read
    /// with (a content listed by several tiles is read once), at most `vertex_budget`
    /// vertices; their textures index the same [`texture_count`](Self::texture_count).
    pub(crate) fn place(&self, root: &Mat4, vertex_budget: usize) -> Result<Vec<PendingMesh>> {
        let mut keys = self.keys.clone();
        let meshes = place_scene(
            &self.document,
            &self.buffers,
            &self.decoded,
            &self.input,
            root,
            vertex_budget,
            &mut keys,
        )?;
        debug_assert_eq!(keys.len(), self.keys.len(), "the same scene meets the same textures");
        Ok(meshes)
    }

    /// Distinct (image, factor) textures the meshes use.
    pub(crate) fn texture_count(&self) -> usize {
        self.keys.len()
    }

    /// What texture `k` is made of, as bytes that are equal exactly when two textures are
    /// the same (for sharing one across documents): its candidate images' bytes and the
    /// factor, hashed to 128 bits.
    pub(crate) fn texture_identity(&self, k: usize) -> Result<u128> {
        use std::hash::{Hash, Hasher};
        let key = &self.keys[k];
        let mut halves = [0u64; 2];
        for (seed, half) in halves.iter_mut().enumerate() {
            let mut hasher = std::collections::hash_map::DefaultHasher::new();
            seed.hash(&mut hasher);
            key.factor.hash(&mut hasher);
            for index in key.images {
                match index {
                    Some(index) => image_bytes(&self.document, &self.buffers, &self.base, index)
                        .with_context(|| self.input.display().to_string())?
                        .hash(&mut hasher),
                    None => 0u8.hash(&mut hasher),
                }
            }
            *half = hasher.finish();
        }
        Ok((u128::from(halves[0]) << 64) | u128::from(halves[1]))
    }

    /// Texture `k` encoded in `format` at most `max_extent` a side, and where it came from.
    /// A Basis Universal source is transcoded block by block where it can be kept as shipped
    /// (untinted, power-of-two sides), and decoded and encoded otherwise.
    pub(crate) fn encode_texture(
        &self,
        k: usize,
        format: TextureFormat,
        max_extent: u32,
    ) -> Result<(EncodedTexture, TextureOrigin)> {
        let key = &self.keys[k];
        let max_log2 = max_extent.trailing_zeros();
        let source = key.images.iter().flatten().find_map(|&index| {
            Some((
                index,
                image_bytes(&self.document, &self.buffers, &self.base, index).ok()?,
            ))
        });
        let encoding = source.as_ref().map_or("factor", |(_, bytes)| image_kind(bytes));
        if let Some((index, bytes)) = source.as_ref().filter(|(_, bytes)| is_basis(bytes)) {
            let what = || format!("{}: image {index}", self.input.display());
            let basis = BasisTexture::open(bytes).with_context(what)?;
            // Held until the texture is encoded: the transcodes running in parallel share
            // one bound.
            let _room = basis.reserve().with_context(what)?;
            let origin = TextureOrigin {
                encoding: basis.codec.name(),
                kept_blocks: false,
            };
            if key.factor == [255; 4] {
                if let Some(texture) = basis.blocks(format, max_log2).with_context(what)? {
                    return Ok((texture, origin));
                }
            }
            let image = tint(basis.rgba().with_context(what)?, key.factor);
            let image = fit_power_of_two(image, max_log2, &self.input);
            let (w, h) = image.dimensions();
            return Ok((encode_chain(image.into_raw(), w, h, format)?, origin));
        }
        if let Some(kept) = kept_blocks(&self.document, &self.buffers, &self.base, key, max_log2) {
            let origin = TextureOrigin {
                encoding,
                kept_blocks: true,
            };
            return Ok((kept, origin));
        }
        let image = texture_image(&self.document, &self.buffers, &self.base, key, &self.input)?;
        let image = fit_power_of_two(image, max_log2, &self.input);
        let (w, h) = image.dimensions();
        let origin = TextureOrigin {
            encoding,
            kept_blocks: false,
        };
        Ok((encode_chain(image.into_raw(), w, h, format)?, origin))
    }
}

/// The lowest and highest coordinates of `meshes`' positions (infinite when there are none).
pub(crate) fn bounds(meshes: &[PendingMesh]) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in meshes.iter().flat_map(|m| &m.positions) {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    (lo, hi)
}

/// `meshes` as a scene whose origin is the centre of their bounds (rounded to metres), so
/// that f32 positions relative to it stay precise; checked as a dataset's scene is.
pub(crate) fn centred_scene(meshes: &[PendingMesh], input: &Path) -> Result<Scene> {
    scene_at(meshes, scene_origin(meshes), input)
}

/// The centre of `meshes`' bounds rounded to metres: the origin [`centred_scene`] gives them.
pub(crate) fn scene_origin(meshes: &[PendingMesh]) -> [f64; 3] {
    // Origin at the centre of the world-space bounds keeps f32 positions precise.
    let (lo, hi) = bounds(meshes);
    [0, 1, 2].map(|a| {
        if lo[a].is_finite() {
            (0.5 * (lo[a] + hi[a])).round()
        } else {
            0.0
        }
    })
}

/// `meshes` as a scene at `origin` (a shard's meshes at the whole tileset's origin).
pub(crate) fn scene_at(meshes: &[PendingMesh], origin: [f64; 3], input: &Path) -> Result<Scene> {
    let mut scene = Scene::new(origin);
    for m in meshes {
        let positions: Vec<[f32; 3]> = m
            .positions
            .iter()
            .map(|p| [0, 1, 2].map(|a| (p[a] - origin[a]) as f32))
            .collect();
        scene.push_mesh(m.texture as u32, &positions, &m.normals, &m.uvs, &m.indices)?;
    }
    scene
        .validate(input)
        .with_context(|| format!("{}: the imported scene", input.display()))?;
    Ok(scene)
}

/// Fails where the `gltf` crate would panic: a mesh primitive referring to an accessor that
/// does not exist, an image without a source or a buffer-view image without a MIME type.
fn check_references(root: &gltf::json::Root) -> Result<()> {
    for (i, image) in root.images.iter().enumerate() {
        match (&image.buffer_view, &image.uri, &image.mime_type) {
            (Some(_), _, None) => bail!("image {i} lies in a buffer view but names no mimeType"),
            (None, None, _) => bail!("image {i} has neither a uri nor a bufferView"),
            _ => {}
        }
    }
    let count = root.accessors.len();
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, primitive) in mesh.primitives.iter().enumerate() {
            let targets = primitive.targets.iter().flatten();
            let references = primitive
                .attributes
                .values()
                .chain(&primitive.indices)
                .chain(targets.flat_map(|t| t.positions.iter().chain(&t.normals).chain(&t.tangents)));
            for accessor in references {
                if accessor.value() >= count {
                    bail!(
                        "mesh {m} primitive {p} refers to accessor {}, but the file has {count} accessors",
                        accessor.value()
                    );
                }
            }
        }
    }
    Ok(())
}

fn texture_key(primitive: &gltf::Primitive) -> TextureKey {
    let pbr = primitive.material().pbr_metallic_roughness();
    let factor = pbr
        .base_color_factor()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
    let mut images = [None; 3];
    if let Some(info) = pbr.base_color_texture() {
        let texture = info.texture();
        let ext_source = |name: &str| {
            texture
                .extension_value(name)
                .and_then(|v| v.get("source"))
                .and_then(|s| s.as_u64())
                .map(|s| s as usize)
        };
        images = [
            ext_source("MSFT_texture_dds"),
            ext_source("KHR_texture_basisu"),
            Some(texture.source().index()),
        ];
    }
    TextureKey { images, factor }
}

/// The bytes of every buffer of `document`, each read by our own code (never by a reader
/// that interprets URI schemes or decodes paths itself): the GLB's binary chunk, a data URI,
/// or a regular file beside the input, named by a relative URI, of which the declared
/// `byteLength` is read (so a file is never read past what the document asks for).
fn load_buffers(root: &gltf::json::Root, blob: Option<&[u8]>, base: &Path, input: &Path) -> Result<Vec<Vec<u8>>> {
    use std::io::Read;
    let fallback = meshopt::fallback_lengths(root).with_context(|| input.display().to_string())?;
    let mut buffers = Vec::with_capacity(root.buffers.len());
    for (index, buffer) in root.buffers.iter().enumerate() {
        let length = usize::try_from(buffer.byte_length.0).unwrap_or(usize::MAX);
        let what = || format!("{}: buffer {index}", input.display());
        let mut bytes = match (&buffer.uri, fallback[index]) {
            // Zeros that the meshopt views decode over (bounded by `fallback_lengths`).
            (None, Some(_)) => vec![0; length],
            (None, None) => blob
                .with_context(|| format!("{} is the GLB's binary chunk, which the file lacks", what()))?
                .to_vec(),
            (Some(uri), _) => {
                if let Some(data) = uri.strip_prefix("data:") {
                    let (_, payload) = data
                        .split_once(";base64,")
                        .with_context(|| format!("{}: a data URI that is not base64", what()))?;
                    base64_decode(payload).with_context(|| format!("{}: invalid base64 data URI", what()))?
                } else {
                    let path = base.join(relative_uri_path(uri).with_context(what)?);
                    if !path.is_file() {
                        bail!("{} refers to missing file {}", what(), path.display());
                    }
                    citystream_dataset::ensure_regular_file(&path).with_context(what)?;
                    let mut file = std::fs::File::open(&path)
                        .with_context(|| format!("{}: opening {}", what(), path.display()))?;
                    let mut bytes = Vec::new();
                    file.by_ref()
                        .take(length as u64)
                        .read_to_end(&mut bytes)
                        .with_context(|| format!("{}: reading {}", what(), path.display()))?;
                    bytes
                }
            }
        };
        if bytes.len() < length {
            bail!(
                "{}: {} bytes, shorter than its byteLength {length}",
                what(),
                bytes.len()
            );
        }
        // As glTF readers do: buffers padded to four bytes.
        while bytes.len() % 4 != 0 {
            bytes.push(0);
        }
        buffers.push(bytes);
    }
    Ok(buffers)
}

/// Raw bytes of a glTF image: a buffer view, an external file, or a data URI.
fn image_bytes(
    document: &gltf::Document,
    buffers: &[gltf::buffer::Data],
    base: &Path,
    index: usize,
) -> Result<Vec<u8>> {
    let image = document
        .images()
        .nth(index)
        .with_context(|| format!("image {index} does not exist"))?;
    match image.source() {
        gltf::image::Source::View { view, .. } => {
            let buffer = buffers
                .get(view.buffer().index())
                .context("buffer view refers to a missing buffer")?;
            let range = view.offset()..view.offset() + view.length();
            Ok(buffer
                .0
                .get(range.clone())
                .with_context(|| format!("image {index}: buffer view bytes {range:?} out of range"))?
                .to_vec())
        }
        gltf::image::Source::Uri { uri, .. } => {
            if let Some(data) = uri.strip_prefix("data:") {
                let (_, payload) = data
                    .split_once(";base64,")
                    .with_context(|| format!("image {index}: unsupported data URI"))?;
                base64_decode(payload).with_context(|| format!("image {index}: invalid base64 data URI"))
            } else {
                let path = base.join(relative_uri_path(uri).with_context(|| format!("image {index}"))?);
                citystream_dataset::ensure_regular_file(&path)
                    .and_then(|()| std::fs::read(&path))
                    .with_context(|| format!("image {index}: reading {}", path.display()))
            }
        }
    }
}

/// `uri` (a glTF buffer's or image's, a tileset's content) as a relative path, decoded:
/// refused when it names a scheme (`file:`, `http:`: ours are files beside the input, and no
/// reader is handed a URI to interpret), is absolute, or does not decode to UTF-8. `data:`
/// URIs are the caller's to decode. The caller joins the path to its base directory and
/// keeps it inside where it must.
pub(crate) fn relative_uri_path(uri: &str) -> Result<PathBuf> {
    if has_scheme(uri) {
        bail!("{uri:?} names a scheme; only relative paths (and data: URIs) are read");
    }
    if uri.is_empty() || uri.starts_with(['/', '\\']) {
        bail!("{uri:?} is not a relative path");
    }
    let decoded = percent_decode(uri)?;
    if decoded.starts_with(['/', '\\']) || has_scheme(&decoded) {
        bail!("{uri:?} decodes to {decoded:?}, not a relative path");
    }
    Ok(PathBuf::from(decoded))
}

/// Whether `uri` begins with a URI scheme (RFC 3986: a letter, then letters, digits, `+`,
/// `-` or `.`, then `:`), as `file:/x`, `http://x` or `c:x` do.
fn has_scheme(uri: &str) -> bool {
    let Some((scheme, _)) = uri.split_once(':') else {
        return false;
    };
    let mut chars = scheme.chars();
    chars.next().is_some_and(|c| c.is_ascii_alphabetic())
        && chars.all(|c| c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.'))
}

/// Percent-decodes `s`; refused where the bytes it names are not UTF-8 (`%FF`).
pub(crate) fn percent_decode(s: &str) -> Result<String> {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = |b: u8| (b as char).to_digit(16);
        if bytes[i] == b'%' && i + 2 < bytes.len() {
            if let (Some(h), Some(l)) = (hex(bytes[i + 1]), hex(bytes[i + 2])) {
                out.push((h * 16 + l) as u8);
                i += 3;
                continue;
            }
        }
        out.push(bytes[i]);
        i += 1;
    }
    String::from_utf8(out).map_err(|_| anyhow!("{s:?} does not percent-decode to UTF-8"))
}

fn base64_decode(s: &str) -> Result<Vec<u8>> {
    let value = |c: u8| -> Option<u32> {
        Some(match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' | b'-' => 62,
            b'/' | b'_' => 63,
            _ => return None,
        } as u32)
    };
    let mut out = Vec::with_capacity(s.len() * 3 / 4);
    let (mut acc, mut bits) = (0u32, 0u32);
    for c in s.bytes().filter(|c| !c.is_ascii_whitespace() && *c != b'=') {
        acc = (acc << 6) | value(c).with_context(|| format!("byte {c:#x} is not base64"))?;
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    Ok(out)
}

/// The texture of `key` with its source's blocks as they are, when its preferred source is
/// a BC1/BC3/BC7 KTX2 or DDS file of power-of-two sides that is not tinted: re-encoding
/// would only lose quality (and BC3/BC7 alpha). `None` sends the texture down the decoding
/// path, which also reports sources that cannot be read.
fn kept_blocks(
    document: &gltf::Document,
    buffers: &[gltf::buffer::Data],
    base: &Path,
    key: &TextureKey,
    max_log2: u32,
) -> Option<EncodedTexture> {
    if key.factor != [255; 4] {
        return None;
    }
    let bytes = key
        .images
        .iter()
        .flatten()
        .find_map(|&index| image_bytes(document, buffers, base, index).ok())?;
    let source = block_source(&bytes).ok().flatten()?;
    // Drop levels finer than the maximum extent; a BC level must stay at least one block.
    let first = source
        .width
        .max(source.height)
        .trailing_zeros()
        .saturating_sub(max_log2);
    let (width, height) = (source.width >> first, source.height >> first);
    if first as usize >= source.levels.len() || width < 4 || height < 4 {
        return None;
    }
    let levels = &source.levels[first as usize..];
    let mean = mean_colour(&decode_level(source.format, &levels[0], width, height));
    Some(EncodedTexture {
        format: source.format,
        width,
        height,
        mip_count: levels.len() as u32,
        chain: levels.concat(),
        mean,
    })
}

fn texture_image(
    document: &gltf::Document,
    buffers: &[gltf::buffer::Data],
    base: &Path,
    key: &TextureKey,
    input: &Path,
) -> Result<RgbaImage> {
    let mut errors = Vec::new();
    let mut image = None;
    for index in key.images.iter().flatten() {
        match image_bytes(document, buffers, base, *index).and_then(|b| decode_image_bytes(&b)) {
            Ok(decoded) => {
                image = Some(decoded);
                break;
            }
            Err(e) => errors.push(format!("image {index}: {e:#}")),
        }
    }
    let mut image = match image {
        Some(image) => image,
        None if key.images.iter().all(Option::is_none) => RgbaImage::from_pixel(4, 4, image::Rgba(key.factor)),
        None => bail!(
            "{}: no source of a texture could be decoded: {}",
            input.display(),
            errors.join("; ")
        ),
    };
    if key.images.iter().any(Option::is_some) {
        image = tint(image, key.factor);
    }
    Ok(image)
}

/// `image` multiplied by the base-colour factor.
fn tint(mut image: RgbaImage, factor: [u8; 4]) -> RgbaImage {
    if factor != [255; 4] {
        let factor = factor.map(u32::from);
        for p in image.pixels_mut() {
            for c in 0..4 {
                p[c] = ((u32::from(p[c]) * factor[c] + 127) / 255) as u8;
            }
        }
    }
    image
}

/// What kind of image `bytes` is, by its signature, as [`EncodingCounts`] names it.
fn image_kind(bytes: &[u8]) -> &'static str {
    if bytes.starts_with(b"\x89PNG") {
        "png"
    } else if bytes.starts_with(&[0xFF, 0xD8]) {
        "jpeg"
    } else if bytes.starts_with(b"DDS ") {
        "dds"
    } else if bytes.starts_with(&[0xAB, 0x4B, 0x54, 0x58]) {
        "ktx2"
    } else {
        "other"
    }
}

/// Resizes up to powers of two (at least 4 per side, one BC block), and down to `max_log2`.
fn fit_power_of_two(image: RgbaImage, max_log2: u32, input: &Path) -> RgbaImage {
    let (w, h) = image.dimensions();
    let up = |n: u32| n.max(4).next_power_of_two();
    let max = 1u32 << max_log2;
    let (tw, th) = (up(w).min(max), up(h).min(max));
    if up(w) > max || up(h) > max {
        eprintln!(
            "warning: {}: a {w}x{h} texture is downscaled to {tw}x{th} (--max-extent {max})",
            input.display()
        );
    }
    if (tw, th) == (w, h) {
        image
    } else {
        image::imageops::resize(&image, tw, th, FilterType::Triangle)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture(name: &str) -> Vec<u8> {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../test-data/encoded-tilesets/fuzz")
            .join(name);
        std::fs::read(&path).expect("fixture")
    }

    /// Every vertex of `content`, placed.
    fn corners(content: &GltfContent) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in content.meshes.iter().flat_map(|m| &m.positions) {
            for c in 0..3 {
                lo[c] = lo[c].min(p[c]);
                hi[c] = hi[c].max(p[c]);
            }
        }
        (lo, hi)
    }

    /// One byte of the binary chunk changed at a time (the JSON, and so the accessors'
    /// bounds and the nodes' transforms, kept): every mutant read without an error has its
    /// vertices within the original's box, widened by 1 % of its extent. Before positions
    /// were checked against the accessors' bounds, mutants of both files read with
    /// buildings hundreds of kilometres wide.
    #[test]
    fn damaged_compressed_geometry_never_reads_outside_the_accessors_bounds() {
        for file in ["draco-etc1s.glb", "meshopt-etc1s.glb"] {
            let good = fixture(file);
            let read = |bytes: &[u8]| read_gltf(bytes, Path::new("."), Path::new(file), &IDENTITY, 1 << 20);
            let (lo, hi) = corners(&read(&good).expect(file));
            let slack: f64 = (0..3).map(|c| hi[c] - lo[c]).fold(0.0, f64::max) * 0.01;
            let json_len = u32::from_le_bytes(good[12..16].try_into().expect("4 bytes")) as usize;
            let bin = 20 + json_len + 8;
            let (mut refused, mut read_ok) = (0, 0);
            for at in bin..good.len() {
                for mask in [0x01u8, 0x80, 0xFF] {
                    let mut bytes = good.clone();
                    bytes[at] ^= mask;
                    let Ok(content) = read(&bytes) else {
                        refused += 1;
                        continue;
                    };
                    read_ok += 1;
                    let (l, h) = corners(&content);
                    let inside = (0..3).all(|c| l[c] >= lo[c] - slack && h[c] <= hi[c] + slack);
                    assert!(
                        inside,
                        "{file}: byte {at} ^ {mask:#04x} reads with vertices from {l:?} to {h:?}, the file's are {lo:?} to {hi:?}"
                    );
                }
            }
            assert!(refused > 0 && read_ok > 0, "{file}: {refused} refused, {read_ok} read");
        }
    }
}
