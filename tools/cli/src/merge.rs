//! `citystream merge OUT`: joins the shards a sharded build wrote into `OUT/shards/I/`
//! (`gen … --shard I/N`, `import … --shard I/N`) into one dataset at `OUT`, a directory or
//! an `s3://bucket/prefix` URL (docs/SHARDS.md); `merge --status OUT` lists the shards.
//!
//! Every shard is checked before anything is written: all `N` present and complete (its
//! manifest names a write holding its record), one job (the record's job and count), its
//! record agreeing with its files, and its bytes undamaged: locally every mip against its
//! CRC-32; in S3 the pack's size and entity tag against those its shard recorded at upload
//! (S3 computes the tag from the bytes it stored, so no mip need be read here). A shard
//! missing, running, of another job or damaged is named and nothing is written.
//!
//! The write is atomic as every write ([`write`]): locally through the dataset writer, the
//! packs copied file to file in the kernel; in S3 the tables and scene put, the pack
//! composed in the store from the shards' packs, the manifest put last.

mod write;

use std::collections::BTreeMap;
use std::ops::Range;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use citystream_dataset::remote::{is_remote, lease_holder, open_dataset, ObjectBucket, RemoteOptions};
use citystream_dataset::{verify_dataset, Dataset, ShardRecord, MANIFEST_FILE, SHARDS_DIR, SHARD_RECORD_FILE};
use citystream_gen::shard::{PACK_TAG_FILE, S3_JOURNAL};

/// Options of `citystream merge`.
#[derive(Debug, clap::Args)]
pub struct MergeArgs {
    /// The sharded build's output: a directory or s3://bucket/prefix holding shards/0/ …
    /// shards/N-1/; the merged dataset is written there (beside shards/, which stays).
    pub out: PathBuf,
    /// List the shards done, running (journal present) and missing, and write nothing.
    #[arg(long)]
    pub status: bool,
    /// Do not print progress or the summary.
    #[arg(long)]
    pub quiet: bool,
}

/// Where the shards and the merged dataset are.
enum Place {
    Local(PathBuf),
    S3(ObjectBucket),
}

/// What one `shards/I/` holds.
struct Found {
    /// Its URL or directory, for messages.
    location: String,
    /// A complete shard: its record and its opened dataset.
    done: Option<(ShardRecord, Dataset)>,
    /// Why it is not complete (it has files but no readable shard).
    broken: Option<String>,
    /// A journal: a write of it is running (or was killed and can be resumed).
    journal: Option<String>,
}

/// Runs `citystream merge`.
pub fn run(args: &MergeArgs) -> Result<()> {
    let location = args.out.to_string_lossy().into_owned();
    let place = if is_remote(&location) {
        Place::S3(ObjectBucket::new(&location, &RemoteOptions::from_env()?)?)
    } else {
        Place::Local(args.out.clone())
    };
    if args.status {
        let found = find_shards(&place, &location, args.quiet)?;
        return print_status(&location, &found);
    }
    // Into S3, one merge at a time: a second would remove the first's files, which its
    // manifest may name (locally the dataset writer's lock does this).
    let lease = match &place {
        Place::S3(bucket) => Some(bucket.acquire_lease(MERGE_LEASE, &lease_holder(), "citystream merge")?),
        Place::Local(_) => None,
    };
    let merged = (|| {
        let found = find_shards(&place, &location, args.quiet)?;
        let shards = check_shards(&place, &location, found, args.quiet)?;
        write::merge(&place, &location, &shards, lease.as_ref(), args.quiet)
    })();
    if let (Place::S3(bucket), Some(lease)) = (&place, lease) {
        let released = bucket.release_lease(lease);
        merged?;
        return released.with_context(|| format!("releasing {location}/{MERGE_LEASE}"));
    }
    merged
}

/// The lease a merge into S3 holds at the output's prefix.
pub const MERGE_LEASE: &str = "merge.lease";

/// Every `shards/I/` of `place`, by index.
fn find_shards(place: &Place, location: &str, quiet: bool) -> Result<BTreeMap<u32, Found>> {
    let mut found = BTreeMap::new();
    match place {
        Place::Local(out) => {
            let dir = out.join(SHARDS_DIR);
            let entries = match std::fs::read_dir(&dir) {
                Ok(entries) => entries,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    bail!(
                        "{}: no shards (no {SHARDS_DIR}/ folder): write them with `--shard I/N --out {location}`",
                        dir.display()
                    )
                }
                Err(e) => return Err(e).with_context(|| format!("listing {}", dir.display())),
            };
            for entry in entries {
                let entry = entry.with_context(|| format!("listing {}", dir.display()))?;
                let Some(index) = entry.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) else {
                    continue;
                };
                let path = entry.path();
                let journal = std::fs::read_dir(&path)
                    .into_iter()
                    .flatten()
                    .flatten()
                    .map(|e| e.path().join("resume.journal"))
                    .find(|j| j.exists())
                    .map(|j| format!("{} present", j.display()));
                let mut shard = Found {
                    location: path.display().to_string(),
                    done: None,
                    broken: None,
                    journal,
                };
                if path.join(MANIFEST_FILE).exists() {
                    match Dataset::open(&path)
                        .map_err(anyhow::Error::from)
                        .and_then(|d| with_record(d, index))
                    {
                        Ok(done) => shard.done = Some(done),
                        Err(e) => shard.broken = Some(format!("{e:#}")),
                    }
                }
                found.insert(index, shard);
            }
        }
        Place::S3(bucket) => {
            let mut keys: BTreeMap<u32, Vec<String>> = BTreeMap::new();
            for (key, _) in bucket.list(&format!("{SHARDS_DIR}/"))? {
                let rest = key.strip_prefix(&format!("{SHARDS_DIR}/")).unwrap_or(&key);
                if let Some((index, inside)) = rest.split_once('/').and_then(|(i, r)| Some((i.parse().ok()?, r))) {
                    keys.entry(index).or_default().push(inside.to_owned());
                }
            }
            for (index, inside) in keys {
                let url = bucket.url_of(&format!("{SHARDS_DIR}/{index}")).display().to_string();
                let journal = inside
                    .iter()
                    .any(|k| k == S3_JOURNAL)
                    .then(|| format!("{url}/{S3_JOURNAL} present"));
                let mut shard = Found {
                    location: url.clone(),
                    done: None,
                    broken: None,
                    journal,
                };
                if inside.iter().any(|k| k == MANIFEST_FILE) {
                    if !quiet {
                        eprintln!("merge: reading shard {index} ({url})");
                    }
                    let opened = open_dataset(&url, &RemoteOptions::from_env()?)
                        .map_err(anyhow::Error::from)
                        .and_then(|d| with_record(d, index));
                    match opened {
                        Ok(done) => shard.done = Some(done),
                        Err(e) => shard.broken = Some(format!("{e:#}")),
                    }
                }
                found.insert(index, shard);
            }
        }
    }
    Ok(found)
}

/// `dataset` with its shard record, which must name shard `index`.
fn with_record(dataset: Dataset, index: u32) -> Result<(ShardRecord, Dataset)> {
    let path = dataset.files().path(SHARD_RECORD_FILE);
    let bytes = dataset
        .read_write_file(SHARD_RECORD_FILE)?
        .with_context(|| format!("{}: no shard record: a dataset, not a shard", path.display()))?;
    let record = ShardRecord::decode(&path, &bytes)?;
    if record.index != index {
        bail!(
            "{}: the record is of shard {}, in the folder of shard {index}",
            path.display(),
            record.index
        );
    }
    Ok((record, dataset))
}

/// The job and count most complete shards share (ties: the lowest index's).
fn reference_job(found: &BTreeMap<u32, Found>) -> Option<(String, u32)> {
    let mut votes: Vec<((String, u32), usize, u32)> = Vec::new();
    for (&index, shard) in found {
        if let Some((record, _)) = &shard.done {
            let key = (record.job.clone(), record.count);
            match votes.iter_mut().find(|(k, _, _)| *k == key) {
                Some(entry) => entry.1 += 1,
                None => votes.push((key, 1, index)),
            }
        }
    }
    votes.sort_by(|a, b| b.1.cmp(&a.1).then(a.2.cmp(&b.2)));
    votes.into_iter().next().map(|(key, _, _)| key)
}

fn print_status(location: &str, found: &BTreeMap<u32, Found>) -> Result<()> {
    let reference = reference_job(found);
    let count = reference
        .as_ref()
        .map(|(_, n)| *n)
        .unwrap_or_else(|| found.keys().next_back().map_or(0, |i| i + 1));
    let mut text = match &reference {
        Some((job, n)) => format!("{location}: {n} shards of job: {job}\n"),
        None => format!("{location}: no shard is complete yet, so the job and its shard count are unknown\n"),
    };
    let (mut done, mut running, mut missing, mut foreign) = (0u64, 0u64, 0u64, 0u64);
    let last = u64::from(count).max(found.keys().next_back().map_or(0, |i| u64::from(*i) + 1));
    // Shards with no folder are counted in runs, not named one by one: a job of many
    // shards with few written lists in bounded memory.
    let gap = |text: &mut String, from: u64, to: u64| {
        match to - from {
            0 => {}
            1 => text.push_str(&format!("  shard {from}/{count}: missing\n")),
            n => text.push_str(&format!(
                "  shards {from} to {} of {count}: missing ({n} shards)\n",
                to - 1
            )),
        }
        to - from
    };
    let mut next = 0u64;
    for (&index, shard) in found {
        missing += gap(&mut text, next, u64::from(index));
        next = u64::from(index) + 1;
        let state = match (&shard.done, &reference) {
            (Some((record, dataset)), Some((job, n))) if record.job == *job && record.count == *n => {
                done += 1;
                format!(
                    "done: {} textures, {} meshes, {:.1} MB pack",
                    record.textures,
                    dataset.scene.meshes.len(),
                    record.pack_bytes as f64 / 1e6
                )
            }
            (Some((record, _)), _) => {
                foreign += 1;
                format!("of another job ({} shards of: {})", record.count, record.job)
            }
            (None, _) if shard.journal.is_some() => {
                running += 1;
                "running".to_owned()
            }
            (None, _) => {
                missing += 1;
                match &shard.broken {
                    Some(why) => format!("incomplete or damaged: {why}"),
                    None => "missing (nothing written)".to_owned(),
                }
            }
        };
        let line = match &shard.journal {
            Some(journal) if shard.done.is_some() => format!("{state}; a rerun is running ({journal})"),
            Some(journal) if state == "running" => format!("running ({journal})"),
            _ => state,
        };
        text.push_str(&format!("  shard {index}/{count}: {line}\n"));
    }
    missing += gap(&mut text, next, last);
    text.push_str(&format!(
        "{done} done, {running} running, {missing} missing, {foreign} of another job\n"
    ));
    citystream_gen::files::print_stdout(&text)
}

/// The shards of the one job, in order, each checked (module docs); an error naming every
/// shard that is missing, running, foreign or damaged.
fn check_shards(
    place: &Place,
    location: &str,
    mut found: BTreeMap<u32, Found>,
    quiet: bool,
) -> Result<Vec<(ShardRecord, Dataset)>> {
    let Some((job, count)) = reference_job(&found) else {
        let states: Vec<String> = found
            .iter()
            .take(16)
            .map(|(index, shard)| match (&shard.journal, &shard.broken) {
                (Some(journal), _) => format!("\n  shard {index} is not complete: still running or killed ({journal})"),
                (None, Some(why)) => format!("\n  shard {index} is damaged or incomplete: {why}"),
                (None, None) => format!("\n  shard {index} holds no dataset"),
            })
            .collect();
        bail!(
            "{location}: no complete shard to merge{}{}",
            if found.is_empty() {
                String::new()
            } else {
                format!(
                    " ({} shard folders, none complete: see `citystream merge --status {location}`):",
                    found.len()
                )
            },
            states.concat()
        );
    };
    let mut problems = Vec::new();
    let mut shards = Vec::new();
    // Runs of shards with no folder, named as one problem each.
    let mut absent: Option<Range<u32>> = None;
    let name_absent = |problems: &mut Vec<String>, run: Option<Range<u32>>| match run {
        Some(run) if run.len() == 1 => problems.push(format!(
            "shard {} of {count} is missing: nothing in {location}/{SHARDS_DIR}/{}",
            run.start, run.start
        )),
        Some(run) => problems.push(format!(
            "shards {} to {} of {count} are missing ({} shards): nothing in {location}/{SHARDS_DIR}/ for them",
            run.start,
            run.end - 1,
            run.len()
        )),
        None => {}
    };
    for index in 0..count {
        let Some(shard) = found.remove(&index) else {
            absent = Some(absent.map_or(index..index + 1, |run| run.start..index + 1));
            continue;
        };
        name_absent(&mut problems, absent.take());
        let Some((record, dataset)) = shard.done else {
            problems.push(match (shard.broken, shard.journal) {
                (_, Some(journal)) => {
                    format!("shard {index} of {count} is not complete: still running or killed ({journal}); rerun it")
                }
                (Some(why), None) => format!("shard {index} of {count} is damaged or incomplete: {why}"),
                (None, None) => format!(
                    "shard {index} of {count} is missing: {} holds no dataset",
                    shard.location
                ),
            });
            continue;
        };
        if record.job != job || record.count != count {
            problems.push(format!(
                "shard {index} ({}) is of another job: {} shards of `{}`, where the others are {count} shards of `{job}`",
                shard.location, record.count, record.job
            ));
            continue;
        }
        match check_contents(place, &shard.location, &record, &dataset, index, count, quiet) {
            Ok(()) => shards.push((record, dataset)),
            Err(e) => problems.push(format!(
                "shard {index} of {count} ({}) is damaged: {e:#}",
                shard.location
            )),
        }
    }
    name_absent(&mut problems, absent.take());
    for (index, shard) in found {
        problems.push(format!(
            "{} is shard {index}, beyond the job's {count} shards (of another job?)",
            shard.location
        ));
    }
    if !problems.is_empty() {
        bail!(
            "merge refused, nothing written to {location}:\n  {}",
            problems.join("\n  ")
        );
    }
    Ok(shards)
}

/// The record against the files, and the bytes undamaged (module docs).
fn check_contents(
    place: &Place,
    location: &str,
    record: &ShardRecord,
    dataset: &Dataset,
    index: u32,
    count: u32,
    quiet: bool,
) -> Result<()> {
    if record.textures != dataset.textures.len()
        || record.meshes as usize != dataset.scene.meshes.len()
        || record.pack_bytes != dataset.textures.pack_len()
    {
        bail!(
            "its record says {} textures, {} meshes, {} pack bytes; its files hold {}, {}, {}",
            record.textures,
            record.meshes,
            record.pack_bytes,
            dataset.textures.len(),
            dataset.scene.meshes.len(),
            dataset.textures.pack_len()
        );
    }
    match place {
        Place::Local(_) => {
            if !quiet {
                eprintln!(
                    "merge: checking every mip of shard {index}/{count} ({:.1} MB)",
                    record.pack_bytes as f64 / 1e6
                );
            }
            verify_dataset(dataset)?;
        }
        Place::S3(bucket) => {
            let write_key = write_key(bucket, dataset)?;
            let tag_key = format!("{write_key}/{PACK_TAG_FILE}");
            let recorded = bucket
                .get(&tag_key)?
                .with_context(|| format!("{location}: no {PACK_TAG_FILE}: not uploaded by a shard"))?;
            let recorded = String::from_utf8_lossy(&recorded).trim().to_owned();
            let pack_key = format!("{write_key}/{}", citystream_dataset::PACK_FILE);
            let now = bucket
                .head(&pack_key)?
                .with_context(|| format!("{}: missing", bucket.url_of(&pack_key).display()))?;
            let stored = format!("{} {}", now.size, now.e_tag.unwrap_or_default());
            if stored != recorded {
                bail!(
                    "{}: size and entity tag {stored} are not those uploaded ({recorded}): the pack changed since",
                    bucket.url_of(&pack_key).display()
                );
            }
        }
    }
    Ok(())
}

/// The key of `dataset`'s write directory in `bucket`.
fn write_key(bucket: &ObjectBucket, dataset: &Dataset) -> Result<String> {
    let data_dir = dataset.files().data_dir().to_string_lossy().into_owned();
    let prefix = format!("{}/", bucket.url());
    data_dir
        .strip_prefix(&prefix)
        .map(str::to_owned)
        .with_context(|| format!("{data_dir} is not inside {}", bucket.url()))
}

/// Bytes this process read and wrote through system calls (`/proc/self/io`: files and
/// sockets alike), where the system tells.
fn process_io() -> Option<(u64, u64)> {
    let text = std::fs::read_to_string("/proc/self/io").ok()?;
    let field = |name: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.trim().parse::<u64>().ok())
    };
    Some((field("rchar:")?, field("wchar:")?))
}
