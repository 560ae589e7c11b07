//! The default city: what `flythrough` and `make run` stream when no
//! dataset is named.
//!
//! It is the `small` generated city (seed 1) packed into 2048×2048 BC1
//! atlases, the analogue of the paper's Table 3 dataset, Berlin (atlas).
//! The atlases are larger than the paper's 512×512 because the default view
//! is 640×360, 1/36 of the paper's 3840×2160 framebuffer: at that size a
//! view needs, relative to each atlas's base level, about the mip levels a
//! 4K view needs of 512×512 atlases, so a baseline cycle binds hundreds of
//! sparse blocks, as it does in the paper.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use citystream_dataset::{upgrade, DatasetError, DatasetFiles};

use crate::atlas::AtlasArgs;
use crate::city::{GenArgs, Preset};

/// Where the default city is created, relative to the working directory.
pub const DEFAULT_CITY_DIR: &str = "data/city";

/// Atlas side of the default city, in texels.
pub const DEFAULT_CITY_ATLAS_EXTENT: u32 = 2048;

/// True when `dir` holds a finished dataset (its manifest names a write: the manifest is
/// renamed into place only once the write is complete).
pub fn is_dataset(dir: &Path) -> bool {
    DatasetFiles::resolve(dir).is_ok()
}

/// Upgrades a dataset the tools created in an earlier format version (the default city, the
/// benchmark cities): ours to rewrite, and cheaper than rebuilding. Returns whether it did.
pub fn upgrade_if_old(dir: &Path, quiet: bool) -> Result<bool> {
    if !matches!(DatasetFiles::resolve(dir), Err(DatasetError::NeedsUpgrade { .. })) {
        return Ok(false);
    }
    if !quiet {
        eprintln!(
            "upgrading {} to the current dataset format (`citystream upgrade`)",
            dir.display()
        );
    }
    upgrade(dir, None).with_context(|| format!("upgrading {}", dir.display()))?;
    Ok(true)
}

/// The per-mesh-texture city the atlases of `dir` are made from.
pub fn source_dir(dir: &Path) -> PathBuf {
    let name = dir
        .file_name()
        .map_or_else(|| "city".into(), |n| n.to_string_lossy().into_owned());
    dir.with_file_name(format!("{name}-per-mesh"))
}

/// Creates the default city in `dir` unless a dataset is already there.
/// Returns whether it generated one. Progress goes to stderr unless `quiet`.
///
/// Each dataset is built in a private directory next to its destination and
/// renamed into place when complete, so runs started at the same time never
/// write into one directory or read a half-written city.
pub fn ensure_default_city(dir: &Path, quiet: bool) -> Result<bool> {
    if is_dataset(dir) || upgrade_if_old(dir, quiet)? {
        return Ok(false);
    }
    let started = std::time::Instant::now();
    let source = source_dir(dir);
    if !quiet {
        eprintln!(
            "creating the default city in {} (first run): `citystream gen --preset small --seed 1 --out {}`, \
             then `citystream atlas --atlas-extent {DEFAULT_CITY_ATLAS_EXTENT}`",
            dir.display(),
            source.display()
        );
    }
    if !is_dataset(&source) && !upgrade_if_old(&source, quiet)? {
        build_then_move(&source, |partial| {
            crate::command::run(&GenArgs {
                // The summaries would name the private build directories.
                quiet: true,
                ..GenArgs::new(Preset::Small, 1, partial.to_path_buf())
            })
            .with_context(|| format!("generating the default city's textures for {}", source.display()))
        })?;
    }
    build_then_move(dir, |partial| {
        crate::atlas::run(&AtlasArgs {
            input: source.clone(),
            out: partial.to_path_buf(),
            region: 512.0,
            atlas_extent: DEFAULT_CITY_ATLAS_EXTENT,
            // The default city's published figures were measured on this packing.
            packing: crate::atlas::Packing::Regions,
            buffer_mb: 256,
            quiet: true,
        })
        .with_context(|| format!("packing the default city's atlases for {}", dir.display()))
    })?;
    if !quiet {
        eprintln!(
            "default city ready in {:.1} s: {} (`citystream info {}` describes it)",
            started.elapsed().as_secs_f64(),
            dir.display(),
            dir.display()
        );
    }
    Ok(true)
}

/// Runs `build` into a private directory next to `dir`, then renames the
/// result to `dir`. A dataset another run completed meanwhile is kept; a
/// `dir` that holds files but no dataset is an error, never overwritten.
pub fn build_then_move(dir: &Path, build: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let name = dir
        .file_name()
        .with_context(|| format!("{} does not name a directory", dir.display()))?
        .to_string_lossy()
        .into_owned();
    if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    }
    // Private to this call: threads of one process (a test binary's tests) build at once too.
    static BUILDS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let build_index = BUILDS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let partial = dir.with_file_name(format!(".{name}.partial-{}-{build_index}", std::process::id()));
    let _ = std::fs::remove_dir_all(&partial);
    if let Err(e) = build(&partial) {
        let _ = std::fs::remove_dir_all(&partial);
        return Err(e);
    }
    if is_dataset(dir) {
        // Another run finished first; its dataset has the same content.
        let _ = std::fs::remove_dir_all(&partial);
        return Ok(());
    }
    // An empty directory (for example one a user created) may be replaced.
    if dir.is_dir() && std::fs::read_dir(dir).is_ok_and(|mut entries| entries.next().is_none()) {
        let _ = std::fs::remove_dir(dir);
    }
    match std::fs::rename(&partial, dir) {
        Ok(()) => Ok(()),
        Err(_) if is_dataset(dir) => {
            let _ = std::fs::remove_dir_all(&partial);
            Ok(())
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&partial);
            Err(e).with_context(|| {
                format!(
                    "moving the new dataset to {}: it exists but holds no complete dataset; \
                     remove it or name another dataset with --dataset",
                    dir.display()
                )
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use citystream_dataset::MANIFEST_FILE;

    fn empty_dataset(dir: &Path) -> Result<()> {
        use citystream_dataset::{DatasetWriter, Scene};
        DatasetWriter::create(dir)?.finish(&Scene::new([0.0; 3]))?;
        Ok(())
    }

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("citystream-default-city-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn a_finished_build_is_moved_into_place_and_a_failed_one_leaves_nothing() {
        let root = scratch("move");
        let dir = root.join("city");
        let fail = build_then_move(&dir, |partial| {
            std::fs::create_dir_all(partial)?;
            std::fs::write(partial.join(MANIFEST_FILE), b"half")?;
            anyhow::bail!("interrupted")
        });
        assert!(fail.is_err());
        assert!(!dir.exists());
        assert_eq!(
            std::fs::read_dir(&root).expect("root").count(),
            0,
            "no partial directory left"
        );

        build_then_move(&dir, empty_dataset).expect("moved");
        assert!(is_dataset(&dir));
        let _ = std::fs::remove_dir_all(&root);
    }

    /// Tests of one binary create the default city from several threads of one process at
    /// once: each builds in its own directory, one moves its dataset into place, and the
    /// others keep it (they once shared a directory named after the process and failed).
    #[test]
    fn threads_of_one_process_building_at_once_all_succeed() {
        let root = scratch("threads");
        let dir = root.join("city");
        let slow_dataset = |partial: &Path| {
            empty_dataset(partial)?;
            std::thread::sleep(std::time::Duration::from_millis(50));
            Ok(())
        };
        std::thread::scope(|scope| {
            let builds: Vec<_> = (0..4)
                .map(|_| scope.spawn(|| build_then_move(&dir, slow_dataset)))
                .collect();
            for build in builds {
                build.join().expect("thread").expect("built or kept");
            }
        });
        assert!(is_dataset(&dir));
        assert_eq!(
            std::fs::read_dir(&root).expect("root").count(),
            1,
            "no partial directory left"
        );
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn datasets_of_an_earlier_format_are_upgraded_in_place_once() {
        let root = scratch("upgrade");
        let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("../test-data/v1-tiny");
        std::fs::create_dir_all(&root).expect("dir");
        for entry in std::fs::read_dir(&fixture).expect("fixture") {
            let entry = entry.expect("entry");
            std::fs::copy(entry.path(), root.join(entry.file_name())).expect("copy");
        }
        assert!(!is_dataset(&root));
        assert!(upgrade_if_old(&root, true).expect("upgrade"));
        assert!(is_dataset(&root));
        assert!(!upgrade_if_old(&root, true).expect("nothing to do"));
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn files_that_are_not_a_dataset_are_never_replaced() {
        let root = scratch("keep");
        let dir = root.join("city");
        std::fs::create_dir_all(&dir).expect("dir");
        std::fs::write(dir.join("notes.txt"), b"mine").expect("file");
        let err = build_then_move(&dir, empty_dataset).expect_err("refused");
        assert!(format!("{err:#}").contains("holds no complete dataset"), "{err:#}");
        assert_eq!(std::fs::read(dir.join("notes.txt")).expect("kept"), b"mine");
        assert_eq!(
            std::fs::read_dir(&root).expect("root").count(),
            1,
            "no partial directory left"
        );
        let _ = std::fs::remove_dir_all(&root);
    }
}
