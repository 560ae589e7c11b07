//! How many of an import's meshes and textures came from each encoding, kept beside the
//! dataset (`import-encodings.json` in its write directory, as an atlas tree keeps its file)
//! so that `citystream info` can report it.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};
use citystream_dataset::{Dataset, DatasetFiles};
use serde::{Deserialize, Serialize};

use crate::primitive::MeshEncoding;

/// The file beside the dataset's own.
pub const FILE: &str = "import-encodings.json";

/// Meshes and textures of an import by the encoding they were stored in.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct EncodingCounts {
    /// `plain`, `quantized`, `meshopt`, `meshopt+quantized`, `draco`.
    pub meshes: BTreeMap<String, u64>,
    /// `png`, `jpeg`, `dds`, `ktx2` (BC or RGBA8 levels), `ktx2-etc1s`, `ktx2-uastc`,
    /// `ktx2-uastc-zstd`, `factor` (a material colour without an image), `other`.
    pub textures: BTreeMap<String, u64>,
}

impl EncodingCounts {
    pub(crate) fn add_mesh(&mut self, encoding: MeshEncoding) {
        *self.meshes.entry(encoding.name().to_owned()).or_default() += 1;
    }

    pub(crate) fn add_texture(&mut self, encoding: &str) {
        *self.textures.entry(encoding.to_owned()).or_default() += 1;
    }

    /// One line: `meshes plain 4, draco 2; textures png 1, ktx2-uastc 1`.
    pub fn summary(&self) -> String {
        let list = |counts: &BTreeMap<String, u64>| {
            counts
                .iter()
                .map(|(name, n)| format!("{name} {n}"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        format!("meshes {}; textures {}", list(&self.meshes), list(&self.textures))
    }

    /// How the import's textures were made, for its summary: `kept` with their KTX2/DDS
    /// blocks kept, those transcoded from Basis Universal (when there are any), the others
    /// encoded as `format`.
    pub fn texture_note(&self, kept: usize, format: &str) -> String {
        let basis: u64 = self
            .textures
            .iter()
            .filter(|(name, _)| name.starts_with("ktx2-"))
            .map(|(_, n)| n)
            .sum();
        let transcoded = if basis > 0 {
            format!(", {basis} transcoded from Basis Universal into {format}")
        } else {
            String::new()
        };
        format!("{kept} with their KTX2/DDS blocks kept{transcoded}, the others encoded as {format}")
    }

    /// Writes the counts beside the dataset just written to `dir`.
    pub fn write(&self, dir: &Path) -> Result<()> {
        let files = DatasetFiles::resolve(dir).with_context(|| format!("reopening {}", dir.display()))?;
        let path = files.path(FILE);
        let text = serde_json::to_vec_pretty(self)?;
        citystream_gen::files::write_atomically(&path, &text).with_context(|| format!("writing {}", path.display()))
    }

    /// The counts an import wrote beside `dataset`; `None` for a dataset not imported (or
    /// imported before the counts were kept).
    pub fn read(dataset: &Dataset) -> Result<Option<Self>> {
        let Some(bytes) = dataset.read_write_file(FILE)? else {
            return Ok(None);
        };
        let counts = serde_json::from_slice(&bytes).with_context(|| {
            format!(
                "{}: not the import's encoding counts",
                dataset.files().path(FILE).display()
            )
        })?;
        Ok(Some(counts))
    }
}
