//! The merged dataset written: locally through the dataset writer (atomic as every write,
//! the shards' packs copied file to file in the kernel), in S3 object by object with the
//! manifest last (readers see the old dataset or the new one) and the pack composed inside
//! the store from the shards' packs.

use std::time::Instant;

use anyhow::{bail, Context, Result};
use citystream_dataset::remote::{open_dataset, Lease, RemoteOptions, Segment};
use citystream_dataset::{
    fresh_write_id, manifest_bytes, write_dir_name, Dataset, DatasetWriter, JoinedTables, ShardRecord, MANIFEST_FILE,
    PACK_FILE,
};

use super::{process_io, write_key, Place};

/// Writes the merged dataset of `shards` (checked, in order) at `place`.
/// Into S3, `lease` is the merge's (checked before the switch and the removals).
pub(super) fn merge(
    place: &Place,
    location: &str,
    shards: &[(ShardRecord, Dataset)],
    lease: Option<&Lease>,
    quiet: bool,
) -> Result<()> {
    let start = Instant::now();
    let say = |line: String| {
        if !quiet {
            eprintln!("merge: {line}");
        }
    };
    let summary = match place {
        Place::Local(out) => {
            let mut writer = DatasetWriter::create(out).with_context(|| format!("writing {}", out.display()))?;
            let mut scene = shards[0].1.scene.clone();
            let mut copied = 0u64;
            for (k, (_, shard)) in shards.iter().enumerate() {
                let offset = writer.texture_count();
                copied += writer
                    .append_pack_of(shard)
                    .with_context(|| format!("joining {}", shard.dir().display()))?;
                if k > 0 {
                    scene
                        .append(&shard.scene, offset)
                        .with_context(|| format!("joining the scene of {}", shard.dir().display()))?;
                }
                say(format!(
                    "joined shard {k}/{} ({:.1} MB of pack copied so far)",
                    shards.len(),
                    copied as f64 / 1e6
                ));
            }
            say("writing the scene and tables, checking the dataset reads back".into());
            let written = writer
                .finish(&scene)
                .with_context(|| format!("writing {}", out.display()))?;
            format!(
                "merged {} shards into {location}: {} textures, {} meshes, {:.1} MB pack ({:.1} MB copied file to file), {:.2} s",
                shards.len(),
                written.textures,
                written.meshes,
                written.pack_bytes as f64 / 1e6,
                copied as f64 / 1e6,
                start.elapsed().as_secs_f64()
            )
        }
        Place::S3(bucket) => {
            let mut joined = JoinedTables::new();
            let mut segments = vec![Segment::Bytes(Vec::new())];
            for (k, (_, shard)) in shards.iter().enumerate() {
                let body = joined
                    .push(shard)
                    .with_context(|| format!("joining shard {k} ({})", shard.dir().display()))?;
                segments.push(Segment::Copy {
                    key: format!("{}/{PACK_FILE}", write_key(bucket, shard)?),
                    range: body,
                });
            }
            let write_id = fresh_write_id();
            let write = write_dir_name(write_id);
            segments[0] = Segment::Bytes(joined.pack_header(write_id));
            let files = joined.encode(&bucket.url_of(&write), write_id)?;
            for (name, bytes) in files {
                say(format!("putting {write}/{name} ({:.1} MB)", bytes.len() as f64 / 1e6));
                bucket.put(&format!("{write}/{name}"), bytes)?;
            }
            say(format!(
                "composing {write}/{PACK_FILE} ({:.1} MB) in the store from the shards' packs",
                joined.pack_len() as f64 / 1e6
            ));
            let pack_key = format!("{write}/{PACK_FILE}");
            let mut last_tenth = 0;
            let report = bucket.compose(&pack_key, &segments, &mut |done, total| {
                let tenth = done * 10 / total.max(1);
                if tenth > last_tenth {
                    last_tenth = tenth;
                    say(format!("composed {done} of {total} parts"));
                }
            })?;
            let stored = bucket
                .head(&pack_key)?
                .with_context(|| format!("{}: the composed pack is not there", bucket.url_of(&pack_key).display()))?;
            if stored.size != joined.pack_len() {
                bail!(
                    "{}: the composed pack is {} bytes, not {}; the dataset was left as it was",
                    bucket.url_of(&pack_key).display(),
                    stored.size,
                    joined.pack_len()
                );
            }
            // The switch: readers see the old dataset or this one.
            if let Some(lease) = lease {
                lease.check()?;
            }
            bucket.put(MANIFEST_FILE, manifest_bytes(write_id))?;
            let merged = open_dataset(location, &RemoteOptions::from_env()?)
                .with_context(|| format!("reopening the merged dataset {location}"))?;
            if merged.files().write_id() != write_id {
                bail!("{location}: another write replaced the merged dataset while it was written");
            }
            // Earlier writes (and what a killed merge left) go; the shards stay, and so
            // does whatever write the live manifest names (read again: never a write a
            // reader can be sent to).
            if let Some(lease) = lease {
                lease.check()?;
            }
            let live = open_dataset(location, &RemoteOptions::from_env()?)
                .map(|d| write_dir_name(d.files().write_id()))
                .with_context(|| format!("reading {location}'s manifest before removing earlier writes"))?;
            let old = bucket.list("")?.into_iter().filter(|(k, _)| {
                k.starts_with("write-") && !k.starts_with(&format!("{write}/")) && !k.starts_with(&format!("{live}/"))
            });
            for (key, _) in old {
                bucket.delete(&key)?;
            }
            format!(
                "merged {} shards into {location}: {} textures, {} meshes, {:.1} MB pack in {} parts, {} copied in the store ({:.1} MB), \
                 {:.3} MB uploaded by this process of which {:.3} MB read from the shards' packs; object data through this process: \
                 {:.3} MB sent, {:.3} MB received (besides the shards' scenes and tables read to join them); {:.2} s",
                shards.len(),
                merged.textures.len(),
                merged.scene.meshes.len(),
                joined.pack_len() as f64 / 1e6,
                report.parts,
                report.copied_parts,
                report.copied_bytes as f64 / 1e6,
                report.uploaded_bytes as f64 / 1e6,
                report.read_bytes as f64 / 1e6,
                bucket.bytes_sent() as f64 / 1e6,
                bucket.bytes_received() as f64 / 1e6,
                start.elapsed().as_secs_f64()
            )
        }
    };
    if quiet {
        return Ok(());
    }
    let io = match (place, process_io()) {
        (Place::Local(_), Some((r, w))) => format!(
            " (its system calls read {:.1} MB and wrote {:.1} MB, /proc/self/io, which counts copy_file_range's bytes though they stay in the kernel)",
            r as f64 / 1e6,
            w as f64 / 1e6
        ),
        _ => String::new(),
    };
    citystream_gen::files::print_stdout(&format!("{summary}{io}\n"))
}
