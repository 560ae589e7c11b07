//! Sharded writes: `gen … --shard I/N` and `import … --shard I/N` write shard `I` of `N`
//! of a dataset into `OUT/shards/I/`, which `citystream merge OUT` joins
//! (`docs/SHARDS.md`). `OUT` is a directory or an `s3://bucket/prefix` URL.
//!
//! A shard is an ordinary dataset written by [`citystream_dataset::DatasetWriter`], with
//! its record ([`citystream_dataset::ShardRecord`]: job, index, count, totals) in the same write, so a shard
//! is atomic and resumable as every write is, and rerunning it replaces it. Into S3 it is
//! written in a local staging directory first (resumable there), every mip checked, then
//! uploaded: the write's files, then their pack's entity tag, then the manifest, and the
//! shard's older writes removed. While an S3 shard runs, `shards/I/shard.journal` says so
//! (`merge --status`); locally the write's own `resume.journal` does.

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use citystream_dataset::remote::{is_remote, lease_holder, Lease, ObjectBucket, RemoteOptions};
pub use citystream_dataset::MAX_SHARDS;
use citystream_dataset::{verify_dataset, Dataset, Scene, MANIFEST_FILE, PACK_FILE, SHARDS_DIR};

/// The journal an S3 shard keeps beside its files while it runs.
pub const S3_JOURNAL: &str = "shard.journal";
/// The file beside an S3 shard's pack holding the pack's size and entity tag as uploaded.
pub const PACK_TAG_FILE: &str = "textures.pack.etag";

/// Which shard a command writes: from `--shard I/N`, or `--shard-index-env NAME --shards N`.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ShardArgs {
    /// Write shard I of N (I from 0) into OUT/shards/I/ (OUT a directory or s3://bucket/prefix);
    /// `citystream merge OUT` joins the N shards into one dataset at OUT.
    #[arg(long, value_name = "I/N", conflicts_with = "shard_index_env")]
    pub shard: Option<String>,
    /// Read the shard index from this environment variable, as a batch scheduler sets it
    /// (JOB_COMPLETION_INDEX, AWS_BATCH_JOB_ARRAY_INDEX, SLURM_ARRAY_TASK_ID); with --shards.
    #[arg(long, value_name = "NAME", requires = "shards")]
    pub shard_index_env: Option<String>,
    /// How many shards, with --shard-index-env.
    #[arg(long, value_name = "N", requires = "shard_index_env")]
    pub shards: Option<u32>,
}

/// Refuses an `--out` URL for an ordinary write: only a shard is written into S3 (and
/// joined there by `merge`); an ordinary write goes to a local directory.
pub fn check_out(out: &Path, shard: Option<Shard>) -> Result<()> {
    let text = out.to_string_lossy();
    if shard.is_none() && citystream_dataset::looks_like_url(&text) {
        bail!(
            "--out {text} is a URL: a dataset is written to a local directory; to build one into S3, \
             write it with --shard I/N (--shard 0/1 for one process) and join the shards there with \
             `citystream merge {text}` (docs/SHARDS.md)"
        );
    }
    if shard.is_some() && citystream_dataset::looks_like_url(&text) && !is_remote(&text) {
        bail!("--out {text}: shards are written to a directory or an s3://bucket/prefix URL");
    }
    Ok(())
}

/// Shard `index` of `count`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    /// From 0.
    pub index: u32,
    /// At least 1.
    pub count: u32,
}

impl ShardArgs {
    /// The shard asked for, or `None` for an ordinary write.
    pub fn resolve(&self) -> Result<Option<Shard>> {
        let (index, count) = match (&self.shard, &self.shard_index_env, self.shards) {
            (Some(text), _, _) => {
                let (i, n) = text
                    .split_once('/')
                    .with_context(|| format!("--shard {text}: expected I/N, e.g. 0/4"))?;
                let parse = |what: &str, v: &str| {
                    v.trim()
                        .parse::<u64>()
                        .with_context(|| format!("--shard {text}: the {what} {v:?} is not a whole number"))
                };
                (parse("index", i)?, parse("count", n)?)
            }
            (None, Some(name), Some(count)) => {
                let value = std::env::var_os(name).with_context(|| {
                    format!("--shard-index-env {name}: the variable is not set (the scheduler sets it for array jobs)")
                })?;
                let value = value.to_str().with_context(|| {
                    format!("--shard-index-env {name}: its value {value:?} is not text (expected a whole number)")
                })?;
                let index = value
                    .trim()
                    .parse::<u64>()
                    .with_context(|| format!("--shard-index-env {name}: its value {value:?} is not a whole number"))?;
                (index, u64::from(count))
            }
            _ => return Ok(None),
        };
        if count == 0 {
            bail!("shard index {index} of {count}: the shard count must be at least 1");
        }
        if count > u64::from(MAX_SHARDS) {
            bail!("shard count {count}: at most {MAX_SHARDS} shards");
        }
        if index >= count {
            bail!(
                "shard index {index} of {count}: the index must be 0 to {} (indices count from 0)",
                count - 1
            );
        }
        // Both fit: count ≤ MAX_SHARDS and index < count.
        Ok(Some(Shard {
            index: index as u32,
            count: count as u32,
        }))
    }
}

impl Shard {
    /// Refuses more shards than `total` items of `what` to divide (a shard without any
    /// would be empty).
    pub fn check_divides(&self, total: usize, what: &str) -> Result<()> {
        if self.count as usize > total {
            bail!(
                "--shard {}/{}: {} shards of {total} {what}: at most one shard per {}",
                self.index,
                self.count,
                self.count,
                what.trim_end_matches('s')
            );
        }
        Ok(())
    }

    /// This shard's contiguous part of `total` items in order: `total·I/N .. total·(I+1)/N`.
    pub fn range(&self, total: usize) -> Range<usize> {
        let at = |i: u32| (total as u128 * u128::from(i) / u128::from(self.count)) as usize;
        at(self.index)..at(self.index + 1)
    }
}

/// A fingerprint of a laid-out scene, part of a shard's job: shards of one job divide the
/// same city, so a shard of another layout (another build, other options) is refused.
pub fn scene_fingerprint(scene: &Scene, textures: usize) -> u32 {
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(&(scene.meshes.len() as u64).to_le_bytes());
    hasher.update(&(textures as u64).to_le_bytes());
    hasher.update(&(scene.positions.len() as u64).to_le_bytes());
    for p in scene.positions.iter().step_by(97) {
        for v in p {
            hasher.update(&v.to_le_bytes());
        }
    }
    for m in scene.meshes.iter().step_by(31) {
        hasher.update(&m.texture.to_le_bytes());
    }
    hasher.finalize()
}

/// Where a shard is written and how it is published.
#[derive(Debug)]
pub struct ShardWrite {
    shard: Shard,
    /// The dataset directory the shard's writer writes.
    dir: PathBuf,
    /// Into S3: the bucket, the shard's key and the lease its journal is.
    bucket: Option<(ObjectBucket, String, Lease)>,
    quiet: bool,
}

impl ShardWrite {
    /// Starts shard `shard` of the output `out`: for a directory, the shard is written in
    /// `out/shards/I/`; for an S3 URL, in a staging directory under the system's temporary
    /// directory (named by `out` and `I`, so a rerun resumes it), and `shards/I/shard.journal`
    /// is taken as a lease saying that it runs: a second writer of the same shard is refused
    /// while this one renews it, and may take over once it has lapsed (a killed writer).
    pub fn begin(out: &Path, shard: Shard, command: &str, quiet: bool) -> Result<Self> {
        let location = out.to_string_lossy();
        let key = format!("{SHARDS_DIR}/{}", shard.index);
        if !is_remote(&location) {
            return Ok(Self {
                shard,
                dir: out.join(&key),
                bucket: None,
                quiet,
            });
        }
        let bucket = ObjectBucket::new(&location, &RemoteOptions::from_env()?)?;
        let name = format!("{:08x}-{}", crc32fast::hash(bucket.url().as_bytes()), shard.index);
        let dir = std::env::temp_dir().join("citystream-shards").join(name);
        let note = format!(
            "shard {} of {}; command {command}; staging {}",
            shard.index,
            shard.count,
            dir.display()
        );
        let lease = bucket
            .acquire_lease(&format!("{key}/{S3_JOURNAL}"), &lease_holder(), &note)
            .with_context(|| format!("starting shard {} of {}", shard.index, shard.count))?;
        Ok(Self {
            shard,
            dir,
            bucket: Some((bucket, key, lease)),
            quiet,
        })
    }

    /// The dataset directory the shard is written in.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// After the shard's write finished: nothing more for a directory; into S3, checks
    /// every mip of the staged shard, uploads it (its files, its pack's tag, then its
    /// manifest), removes its older writes and the journal, and the staging directory.
    pub fn publish(self) -> Result<()> {
        let Some((bucket, key, lease)) = self.bucket else {
            return Ok(());
        };
        let say = |line: String| {
            if !self.quiet {
                eprintln!("shard {}/{}: {line}", self.shard.index, self.shard.count);
            }
        };
        let staged = Dataset::open(&self.dir).with_context(|| format!("reopening {}", self.dir.display()))?;
        say(format!("checking every mip of {}", self.dir.display()));
        verify_dataset(&staged).with_context(|| format!("checking {}", self.dir.display()))?;
        let files = staged.files().clone();
        let write_name = files
            .data_dir()
            .file_name()
            .context("the staged write has no directory name")?
            .to_string_lossy()
            .into_owned();
        let write_key = format!("{key}/{write_name}");
        let mut names: Vec<String> = std::fs::read_dir(files.data_dir())
            .with_context(|| format!("listing {}", files.data_dir().display()))?
            .map(|e| e.map(|e| e.file_name().to_string_lossy().into_owned()))
            .collect::<std::io::Result<_>>()?;
        names.sort();
        for name in &names {
            lease.check()?;
            let path = files.data_dir().join(name);
            let mut last_tenth = 0;
            bucket.upload_file(&format!("{write_key}/{name}"), &path, &mut |done, total| {
                let tenth = done * 10 / total.max(1);
                if total >= 64 << 20 && tenth > last_tenth {
                    last_tenth = tenth;
                    say(format!("uploading {name}: {} of {} MB", done >> 20, total >> 20));
                }
            })?;
        }
        let pack = bucket.head(&format!("{write_key}/{PACK_FILE}"))?.with_context(|| {
            format!(
                "{}: the pack just uploaded is not there",
                bucket.url_of(&write_key).display()
            )
        })?;
        let e_tag = pack.e_tag.unwrap_or_default();
        bucket.put(
            &format!("{write_key}/{PACK_TAG_FILE}"),
            format!("{} {e_tag}\n", pack.size).into_bytes(),
        )?;
        // Still this shard's only writer: the switch, then the removal of earlier writes.
        lease.check()?;
        bucket.upload_file(
            &format!("{key}/{MANIFEST_FILE}"),
            &self.dir.join(MANIFEST_FILE),
            &mut |_, _| {},
        )?;
        lease.check()?;
        for (old, _) in bucket.list(&format!("{key}/"))? {
            let inside = old.strip_prefix(&format!("{key}/")).unwrap_or(&old);
            if inside.starts_with("write-") && !inside.starts_with(&format!("{write_name}/")) {
                bucket.delete(&old)?;
            }
        }
        bucket.release_lease(lease)?;
        say(format!(
            "uploaded to {} ({} MB of pack)",
            bucket.url_of(&key).display(),
            pack.size >> 20
        ));
        drop(staged);
        if let Err(e) = std::fs::remove_dir_all(&self.dir) {
            eprintln!(
                "warning: could not remove the staging directory {}: {e}",
                self.dir.display()
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_divide_the_items_in_order_without_gaps() {
        for total in [0usize, 1, 7, 25_858] {
            for count in 1..=9u32 {
                let mut next = 0;
                for index in 0..count {
                    let range = Shard { index, count }.range(total);
                    assert_eq!(range.start, next, "{total} in {count}");
                    assert!(range.len() <= total.div_ceil(count as usize));
                    next = range.end;
                }
                assert_eq!(next, total);
            }
        }
    }

    #[test]
    fn the_index_comes_from_the_argument_or_the_scheduler() {
        let args = |shard: Option<&str>, env: Option<&str>, shards: Option<u32>| ShardArgs {
            shard: shard.map(Into::into),
            shard_index_env: env.map(Into::into),
            shards,
        };
        assert_eq!(
            args(Some("2/4"), None, None).resolve().expect("2/4"),
            Some(Shard { index: 2, count: 4 })
        );
        assert_eq!(args(None, None, None).resolve().expect("none"), None);
        for bad in ["4/4", "1/0", "x/4", "2", "-1/4"] {
            let error = args(Some(bad), None, None).resolve().expect_err(bad).to_string();
            assert!(error.contains(bad) || error.contains("index"), "{bad}: {error}");
        }
        std::env::set_var("CITYSTREAM_TEST_SHARD_INDEX", "3");
        assert_eq!(
            args(None, Some("CITYSTREAM_TEST_SHARD_INDEX"), Some(5))
                .resolve()
                .expect("env"),
            Some(Shard { index: 3, count: 5 })
        );
        let error = args(None, Some("CITYSTREAM_TEST_SHARD_UNSET"), Some(5))
            .resolve()
            .expect_err("unset")
            .to_string();
        assert!(
            error.contains("CITYSTREAM_TEST_SHARD_UNSET") && error.contains("not set"),
            "{error}"
        );
    }

    #[test]
    fn a_shard_argument_out_of_range_says_which_part_is_wrong() {
        let resolve = |text: &str| {
            ShardArgs {
                shard: Some(text.into()),
                ..ShardArgs::default()
            }
            .resolve()
        };
        for (bad, expected) in [
            ("0/0", "the shard count must be at least 1"),
            ("0/4294967296", "at most 65536 shards"),
            ("0/1000000000", "at most 65536 shards"),
            ("4/4", "the index must be 0 to 3"),
            ("x/4", "the index \"x\" is not a whole number"),
        ] {
            let error = format!("{:#}", resolve(bad).expect_err(bad));
            assert!(error.contains(expected), "{bad}: {error}");
        }
        assert_eq!(
            resolve("65535/65536").expect("the most shards"),
            Some(Shard {
                index: 65_535,
                count: MAX_SHARDS
            })
        );
        let shard = Shard { index: 0, count: 300 };
        let error = format!("{:#}", shard.check_divides(254, "textures").expect_err("300 of 254"));
        assert!(
            error.contains("300 shards of 254 textures: at most one shard per texture"),
            "{error}"
        );
        shard.check_divides(300, "textures").expect("one each");
    }

    #[cfg(unix)]
    #[test]
    fn a_shard_index_variable_that_is_not_text_is_named_as_such() {
        use std::os::unix::ffi::OsStrExt;
        std::env::set_var(
            "CITYSTREAM_TEST_SHARD_BYTES",
            std::ffi::OsStr::from_bytes(&[0x33, 0xff]),
        );
        let error = ShardArgs {
            shard_index_env: Some("CITYSTREAM_TEST_SHARD_BYTES".into()),
            shards: Some(5),
            ..ShardArgs::default()
        }
        .resolve()
        .expect_err("not UTF-8")
        .to_string();
        assert!(error.contains("is not text"), "{error}");
    }
}
