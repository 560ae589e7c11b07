//! An opened dataset ([`Dataset`]): the files of the write its manifest names, read,
//! validated against each other and held open, locally or from a store.

use std::path::Path;
use std::sync::Arc;

use super::colormap::Colormap;
use super::error::DatasetError;
use super::files::{DatasetFiles, COLORMAP_FILE, SCENE_FILE};
use super::format::TextureInfo;
use super::format::FORMAT_VERSION;
use super::io_util;
use super::pack::TexturePack;
use super::scene::{self, Scene};
use super::store::{self, DatasetStore};

/// An opened dataset: the scene, the texture table with an open pack, and the colormap.
///
/// Threading: `Send + Sync`; see [`TexturePack`] for concurrent mip reads.
#[derive(Debug)]
pub struct Dataset {
    files: DatasetFiles,
    /// Where it was opened from (`None`: the local directory).
    store: Option<Arc<dyn DatasetStore>>,
    /// All meshes and geometry.
    pub scene: Scene,
    /// Texture metadata and mip reads.
    pub textures: TexturePack,
    /// Mean colour per texture.
    pub colormap: Colormap,
    scene_file_len: u64,
}

impl Dataset {
    /// Opens the dataset in `dir`: reads its manifest, then reads and validates `tiles.bin`,
    /// `geometry.pack` (every tile against `geometry.crc`), `textures.meta`, `textures.crc`, `colormap.bin` and the header of `textures.pack` of
    /// the write it names, and checks they agree (one write id, every mesh's texture exists,
    /// one colour per texture). Reads no mip data.
    ///
    /// A writer may replace the dataset meanwhile and remove the files just resolved; the
    /// open then starts again from the new manifest (a few times at most).
    pub fn open(dir: impl AsRef<Path>) -> Result<Self, DatasetError> {
        let dir = dir.as_ref();
        Self::open_resolved(|| DatasetFiles::resolve(dir), Self::open_files)
    }

    /// Resolves the manifest and opens the write it names; when the open fails because a
    /// writer replaced the dataset meanwhile (the manifest now names another write), starts
    /// again, three attempts at most.
    fn open_resolved(
        resolve: impl Fn() -> Result<DatasetFiles, DatasetError>,
        open: impl Fn(&DatasetFiles) -> Result<Self, DatasetError>,
    ) -> Result<Self, DatasetError> {
        let mut attempts = 0;
        loop {
            let files = resolve()?;
            match open(&files) {
                Ok(dataset) => return Ok(dataset),
                Err(e) => {
                    attempts += 1;
                    let replaced = resolve().is_ok_and(|now| now.write_id() != files.write_id());
                    if !replaced || attempts >= 3 {
                        return Err(e);
                    }
                }
            }
        }
    }

    /// [`Dataset::open`] of resolved files.
    pub fn open_files(files: &DatasetFiles) -> Result<Self, DatasetError> {
        Self::open_files_in(None, files)
    }

    /// Opens the dataset at `root` of `store` (a remote dataset: `root` is its URL): the
    /// manifest, then the files of the write it names, validated as [`Dataset::open`] does;
    /// mips are then read from the store by range. If the dataset is replaced meanwhile,
    /// the open starts again from the new manifest (a few times at most).
    pub fn open_store(store: Arc<dyn DatasetStore>, root: &Path) -> Result<Self, DatasetError> {
        Self::open_resolved(
            || DatasetFiles::resolve_in(store.as_ref(), root),
            |files| Self::open_files_in(Some(&store), files),
        )
    }

    fn open_files_in(store: Option<&Arc<dyn DatasetStore>>, files: &DatasetFiles) -> Result<Self, DatasetError> {
        let read_file = |path: &Path| store::read_file(store, path);
        let textures = TexturePack::open_files_in(store, files)?;
        let colormap_path = files.path(COLORMAP_FILE);
        let (colormap, write_id) =
            Colormap::decode_with_write_id(&colormap_path, &read_file(&colormap_path)?, files.version())?;
        files.check_write_id(&colormap_path, write_id)?;
        if colormap.len() != textures.textures().len() {
            return Err(DatasetError::Corrupt {
                path: colormap_path,
                offset: 24,
                what: format!("{} colours for {} textures", colormap.len(), textures.len()),
            });
        }
        let count = textures.len();
        if files.version() == FORMAT_VERSION {
            let (scene, scene_file_len) = crate::tiled::read_scene_files(files, read_file, count)?;
            return Ok(Self {
                files: files.clone(),
                store: store.cloned(),
                scene,
                textures,
                colormap,
                scene_file_len,
            });
        }
        // Versions 2 and 3, opened by the upgrade: one `scene.bin`.
        let scene_path = files.path(SCENE_FILE);
        let scene_bytes = read_file(&scene_path)?;
        let layout = if files.version() == io_util::VERSION_2 {
            scene::SceneLayout::V2
        } else {
            scene::SceneLayout::V3
        };
        let (scene, write_id) = Scene::decode_with(&scene_path, &scene_bytes, layout)?;
        files.check_write_id(&scene_path, write_id)?;
        if let Some((m, mesh)) = scene.meshes.iter().enumerate().find(|(_, m)| m.texture >= count) {
            return Err(DatasetError::Corrupt {
                path: scene_path,
                offset: scene.mesh_record_offset(layout, m) + 16,
                what: format!(
                    "mesh {m} uses texture {}, but the dataset has {count} textures",
                    mesh.texture
                ),
            });
        }
        Ok(Self {
            files: files.clone(),
            store: store.cloned(),
            scene,
            textures,
            colormap,
            scene_file_len: scene_bytes.len() as u64,
        })
    }

    /// Another file of the opened write's directory (beside the five of the format, e.g. an
    /// atlas tree's `atlas-tree.bin`), whole, from wherever the dataset was opened; `None`
    /// where the write has no such file.
    pub fn read_write_file(&self, name: &str) -> Result<Option<Vec<u8>>, DatasetError> {
        let path = self.files.path(name);
        if self.store.is_none() && !path.exists() {
            return Ok(None);
        }
        match store::read_file(self.store.as_ref(), &path) {
            Ok(bytes) => Ok(Some(bytes)),
            Err(DatasetError::Missing { .. }) => Ok(None),
            Err(e) => Err(e),
        }
    }

    /// Bytes of the scene's files as they were read (`tiles.bin` and `geometry.pack`;
    /// `scene.bin` for the older versions the upgrade opens).
    pub fn scene_file_len(&self) -> u64 {
        self.scene_file_len
    }

    /// The dataset directory.
    pub fn dir(&self) -> &Path {
        self.files.dir()
    }

    /// Where the opened write's files are.
    pub fn files(&self) -> &DatasetFiles {
        &self.files
    }

    /// Host bytes per texture of the opened metadata (texture record, index of its first mip
    /// checksum, colormap entry), excluding the scene geometry and the per-mip checksums
    /// ([`Dataset::metadata_bytes_per_mip`]).
    pub fn metadata_bytes_per_texture() -> usize {
        std::mem::size_of::<TextureInfo>() + std::mem::size_of::<u32>() + std::mem::size_of::<[u8; 4]>()
    }

    /// Host bytes per mip of the opened metadata: its CRC-32.
    pub fn metadata_bytes_per_mip() -> usize {
        std::mem::size_of::<u32>()
    }
}
