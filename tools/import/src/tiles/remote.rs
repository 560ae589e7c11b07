//! Tilesets behind an HTTP server or in S3 (`http(s)://…/tileset.json`, `s3://…`): every
//! file the tileset refers to (its external tilesets, content, and the files a glTF's
//! buffers and images name) is fetched through the remote dataset store into a scratch
//! directory with the same layout, which is then imported as a local tileset, so a URL
//! gives exactly the dataset its files give on disk. Every level is fetched whatever
//! `--lod` says; content that is not imported (point clouds and the like) is not
//! fetched, only counted.

use std::collections::HashSet;
use std::path::{Component, Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use citystream_dataset::remote::{RemoteOptions, RemoteStore};
use citystream_dataset::DatasetStore;
use serde_json::Value;

use super::content;
use super::tileset::{
    content_kind, content_uri_path, objects_within, TileJson, TilesetJson, MAX_CONTENT_BYTES, MAX_HELD_TILESET_OBJECTS,
    MAX_TILESETS, MAX_TILESET_BYTES,
};

/// Most files fetched for one tileset.
const MAX_FILES: usize = 4_000_000;

/// The file naming the process that fetches into a scratch directory.
const DOWNLOAD_MARKER: &str = ".citystream-tileset-download";

/// Clears `scratch`, a download directory an earlier import left, where it is provably
/// one (it holds the marker [`fetch`] writes) and the process that wrote it is gone (killed
/// before it could remove it). Refused otherwise: a directory of someone else's is not
/// deleted, and one a running import fetches into is not touched.
pub fn clear_stale_download(scratch: &Path) -> Result<()> {
    let marker = scratch.join(DOWNLOAD_MARKER);
    let owner = std::fs::read_to_string(&marker)
        .ok()
        .and_then(|text| text.trim().parse::<u32>().ok());
    let Some(pid) = owner else {
        bail!(
            "{} exists and is not an import's download directory (no {DOWNLOAD_MARKER}): remove it, the import \
             fetches the tileset there",
            scratch.display()
        );
    };
    if process_alive(pid) {
        bail!(
            "{} is where a running import (process {pid}) fetches the tileset; wait for it, or remove the \
             directory if that process is not an import",
            scratch.display()
        );
    }
    eprintln!(
        "removing {}, left by an import (process {pid}) that did not finish",
        scratch.display()
    );
    std::fs::remove_dir_all(scratch).with_context(|| format!("removing {}", scratch.display()))
}

/// Whether process `pid` exists (on Linux, its /proc entry; elsewhere it is taken to,
/// which only ever refuses to clear a directory).
fn process_alive(pid: u32) -> bool {
    if pid == std::process::id() {
        return true;
    }
    if cfg!(target_os = "linux") {
        Path::new("/proc").join(pid.to_string()).exists()
    } else {
        true
    }
}

/// Fetches the tileset at `url` and what it refers to into `scratch` (created; must not
/// exist); returns the local path of the top tileset.
pub fn fetch(url: &str, scratch: &Path) -> Result<PathBuf> {
    // A query string (`?token=…`) goes with every request; the path names the files.
    let (path_url, query) = match url.split_once('?') {
        Some((path, query)) => (path, format!("?{query}")),
        None => (url, String::new()),
    };
    let Some((dir_url, file)) = path_url.rsplit_once('/').filter(|(_, f)| !f.is_empty()) else {
        bail!("{url}: expected the URL of a tileset JSON (…/tileset.json)");
    };
    let store: Arc<dyn DatasetStore> = Arc::new(
        RemoteStore::new(&format!("{dir_url}/{query}"), &RemoteOptions::from_env()?)
            .with_context(|| format!("opening {url}"))?,
    );
    let root = PathBuf::from(dir_url);
    std::fs::create_dir(scratch).with_context(|| format!("creating the scratch directory {}", scratch.display()))?;
    // Whose it is: a later import may clear it if this process dies before removing it.
    std::fs::write(scratch.join(DOWNLOAD_MARKER), std::process::id().to_string())
        .with_context(|| format!("writing {}", scratch.join(DOWNLOAD_MARKER).display()))?;
    let mut fetcher = Fetcher {
        store,
        root,
        scratch: scratch.to_path_buf(),
        fetched: HashSet::new(),
    };
    let top = PathBuf::from(file);
    let mut tilesets = vec![top.clone()];
    let mut read = 0usize;
    while let Some(relative) = tilesets.pop() {
        if !fetcher.fetched.insert(relative.clone()) {
            continue;
        }
        read += 1;
        if read > MAX_TILESETS {
            bail!("{url}: more than {MAX_TILESETS} external tilesets");
        }
        let bytes = fetcher.get(&relative, MAX_TILESET_BYTES)?;
        objects_within(&bytes, MAX_HELD_TILESET_OBJECTS, &fetcher.url(&relative))?;
        let tileset: TilesetJson = serde_json::from_slice(&bytes)
            .with_context(|| format!("{}: not a 3D Tiles tileset", fetcher.url(&relative)))?;
        let dir = relative.parent().unwrap_or(Path::new("")).to_path_buf();
        let mut stack: Vec<&TileJson> = vec![&tileset.root];
        while let Some(tile) = stack.pop() {
            stack.extend(&tile.children);
            // Implicit tiling's content URIs are templates: the import counts them only.
            if tile.implicit_tiling.is_some() {
                continue;
            }
            for uri in tile
                .content
                .iter()
                .chain(&tile.contents)
                .filter_map(|c| c.uri.as_deref().or(c.url.as_deref()))
            {
                let path =
                    normalise(&dir, uri).with_context(|| format!("{}: content {uri:?}", fetcher.url(&relative)))?;
                match content_kind(&path).as_str() {
                    "json" => tilesets.push(path),
                    "b3dm" | "glb" | "gltf" => fetcher.content(&path)?,
                    // Counted by the import, never parsed: an empty stand-in will do.
                    _ => fetcher.placeholder(&path)?,
                }
            }
        }
    }
    Ok(scratch.join(top))
}

struct Fetcher {
    store: Arc<dyn DatasetStore>,
    /// The top tileset's directory URL.
    root: PathBuf,
    scratch: PathBuf,
    fetched: HashSet<PathBuf>,
}

impl Fetcher {
    fn url(&self, relative: &Path) -> String {
        self.root.join(relative).display().to_string()
    }

    /// The file at `relative` (at most `limit` bytes), also written into the scratch copy.
    fn get(&self, relative: &Path, limit: u64) -> Result<Vec<u8>> {
        if self.fetched.len() > MAX_FILES {
            bail!("the tileset refers to more than {MAX_FILES} files");
        }
        let remote = self.root.join(relative);
        let len = self
            .store
            .len(&remote)
            .with_context(|| format!("fetching {}", self.url(relative)))?;
        if len > limit {
            bail!("{}: {len} bytes (at most {limit} are read)", self.url(relative));
        }
        // `read_all` would ask for the length a second time.
        let mut bytes = vec![0; len as usize];
        if len > 0 {
            self.store
                .read_at(&remote, 0, &mut bytes)
                .with_context(|| format!("fetching {}", self.url(relative)))?;
        }
        let local = self.scratch.join(relative);
        if let Some(parent) = local.parent() {
            std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
        }
        std::fs::write(&local, &bytes).with_context(|| format!("writing {}", local.display()))?;
        Ok(bytes)
    }

    /// A content file and the external files its glTF names.
    fn content(&mut self, relative: &Path) -> Result<()> {
        if !self.fetched.insert(relative.to_path_buf()) {
            return Ok(());
        }
        let bytes = self.get(relative, MAX_CONTENT_BYTES)?;
        let what = || self.url(relative);
        let glb = if content_kind(relative) == "b3dm" {
            content::parse_b3dm(&bytes).with_context(what)?.glb
        } else {
            &bytes[..]
        };
        let json = content::gltf_json(glb).with_context(what)?;
        let dir = relative.parent().unwrap_or(Path::new("")).to_path_buf();
        let mut external = Vec::new();
        for key in ["buffers", "images"] {
            for item in json.get(key).and_then(Value::as_array).into_iter().flatten() {
                if let Some(uri) = item
                    .get("uri")
                    .and_then(Value::as_str)
                    .filter(|u| !u.starts_with("data:"))
                {
                    external.push(normalise(&dir, uri).with_context(|| format!("{}: {key} uri {uri:?}", what()))?);
                }
            }
        }
        for path in external {
            if self.fetched.insert(path.clone()) {
                self.get(&path, MAX_CONTENT_BYTES)?;
            }
        }
        Ok(())
    }

    fn placeholder(&mut self, relative: &Path) -> Result<()> {
        if self.fetched.insert(relative.to_path_buf()) {
            let local = self.scratch.join(relative);
            if let Some(parent) = local.parent() {
                std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
            }
            std::fs::write(&local, b"").with_context(|| format!("writing {}", local.display()))?;
        }
        Ok(())
    }
}

/// `uri` relative to `dir` (both inside the tileset's directory) as a clean relative
/// path: no scheme, no absolute path, no `..` above the tileset's directory.
fn normalise(dir: &Path, uri: &str) -> Result<PathBuf> {
    let decoded = content_uri_path(uri)?.display().to_string();
    let mut parts: Vec<std::ffi::OsString> = Vec::new();
    for component in dir.join(&decoded).components() {
        match component {
            Component::Normal(part) => parts.push(part.to_os_string()),
            Component::CurDir => {}
            Component::ParentDir => {
                if parts.pop().is_none() {
                    bail!("{decoded} leads outside the tileset's directory");
                }
            }
            Component::RootDir | Component::Prefix(_) => bail!("{decoded} is not a relative path"),
        }
    }
    if parts.is_empty() {
        bail!("{decoded:?} names no file");
    }
    Ok(parts.iter().collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uris_stay_inside_the_tileset_directory() {
        let dir = Path::new("ext/sub");
        assert_eq!(normalise(dir, "../a.glb").expect("inside"), PathBuf::from("ext/a.glb"));
        assert_eq!(
            normalise(dir, "./b%20c.b3dm?v=2").expect("inside"),
            PathBuf::from("ext/sub/b c.b3dm")
        );
        for bad in [
            "../../../x.glb",
            "/etc/passwd",
            "https://elsewhere/a.glb",
            "data:,x",
            "",
        ] {
            assert!(normalise(dir, bad).is_err(), "{bad}");
        }
        assert!(normalise(Path::new(""), "..").is_err());
    }
}
