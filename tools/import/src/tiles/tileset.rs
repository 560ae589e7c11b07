//! The `tileset.json` of 3D Tiles as read here: its schema, the bounds every read of it
//! keeps, and the reading of its content URIs, shared by the local and the remote walk.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::Deserialize;
use serde_json::Value;

use crate::gltf::relative_uri_path;

/// Most JSON objects of the tilesets held parsed at once (a tileset and the external
/// ones below it being walked): some 400 MB at the worst.
pub const MAX_HELD_TILESET_OBJECTS: usize = 1_500_000;

/// Largest `tileset.json` read (external ones too).
pub const MAX_TILESET_BYTES: u64 = 64 << 20;
/// Largest content file read.
pub const MAX_CONTENT_BYTES: u64 = 1 << 30;
/// Most tiles a tileset may have, external tilesets included.
pub const MAX_TILES: usize = 4_000_000;
/// Most external tilesets read (one referred to twice counts twice).
pub const MAX_TILESETS: usize = 100_000;
/// Most content entries the tiles list, external tilesets' included.
pub const MAX_CONTENTS: usize = 4_000_000;
/// Deepest tile nesting, across external tilesets.
pub const MAX_DEPTH: usize = 256;
/// The axis a tileset's glTF content points up (`asset.gltfUpAxis`, before 3D Tiles 1.0;
/// y since). An external tileset that does not say inherits the one above it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum UpAxis {
    X,
    Y,
    Z,
}

/// How a tile's children refine it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Refine {
    Replace,
    Add,
}

#[derive(Deserialize)]
pub(crate) struct TilesetJson {
    pub(crate) asset: AssetJson,
    pub(crate) root: TileJson,
    #[serde(default, rename = "extensionsRequired")]
    pub(crate) extensions_required: Vec<String>,
}

#[derive(Deserialize)]
pub(crate) struct AssetJson {
    pub(crate) version: String,
    #[serde(default, rename = "gltfUpAxis")]
    pub(crate) gltf_up_axis: Option<String>,
}

#[derive(Deserialize)]
pub(crate) struct TileJson {
    #[serde(default, rename = "boundingVolume")]
    pub(crate) bounding_volume: Option<BoundingVolumeJson>,
    #[serde(default, rename = "geometricError")]
    pub(crate) geometric_error: Option<f64>,
    #[serde(default)]
    pub(crate) refine: Option<String>,
    #[serde(default)]
    pub(crate) transform: Option<Vec<f64>>,
    #[serde(default)]
    pub(crate) content: Option<ContentJson>,
    #[serde(default)]
    pub(crate) contents: Vec<ContentJson>,
    #[serde(default)]
    pub(crate) children: Vec<TileJson>,
    #[serde(default, rename = "implicitTiling")]
    pub(crate) implicit_tiling: Option<Value>,
}

#[derive(Deserialize)]
pub(crate) struct BoundingVolumeJson {
    #[serde(default, rename = "box")]
    pub(crate) oriented_box: Option<Vec<f64>>,
    #[serde(default)]
    pub(crate) region: Option<Vec<f64>>,
    #[serde(default)]
    pub(crate) sphere: Option<Vec<f64>>,
}

#[derive(Deserialize)]
pub(crate) struct ContentJson {
    #[serde(default)]
    pub(crate) uri: Option<String>,
    /// The name 3D Tiles used before 1.0.
    #[serde(default)]
    pub(crate) url: Option<String>,
}

/// A tile's content URI as a relative path, decoded, its query and fragment aside: the one
/// reading of content URIs for local and remote tilesets alike.
pub(crate) fn content_uri_path(uri: &str) -> Result<PathBuf> {
    let not_relative = "not a relative path (citystream imports a tileset's files from its own directory)";
    if uri.starts_with("data:") {
        bail!(not_relative);
    }
    relative_uri_path(uri.split(['?', '#']).next().unwrap_or("")).context(not_relative)
}

/// A content file's kind by its extension, lower case.
pub(crate) fn content_kind(path: &Path) -> String {
    path.extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default()
}

/// The JSON objects of tileset `bytes` (named `what`), refused where more than
/// `max_objects` remain of [`MAX_HELD_TILESET_OBJECTS`].
pub(crate) fn objects_within(bytes: &[u8], max_objects: usize, what: &dyn std::fmt::Display) -> Result<usize> {
    let objects = json_objects(bytes);
    if objects > max_objects {
        bail!(
            "{what}: {objects} JSON objects, more than the {max_objects} still allowed (at most \
             {MAX_HELD_TILESET_OBJECTS} are held at once, over the external tilesets being read)"
        );
    }
    Ok(objects)
}

/// The JSON objects in `bytes` (its `{` outside strings), counted without parsing: an
/// upper bound on what a tileset file holds, for bounding its parse.
pub(crate) fn json_objects(bytes: &[u8]) -> usize {
    let (mut objects, mut in_string, mut escaped) = (0usize, false, false);
    for &b in bytes {
        if in_string {
            match (escaped, b) {
                (true, _) => escaped = false,
                (false, b'\\') => escaped = true,
                (false, b'"') => in_string = false,
                _ => {}
            }
        } else if b == b'"' {
            in_string = true;
        } else if b == b'{' {
            objects += 1;
        }
    }
    objects
}
