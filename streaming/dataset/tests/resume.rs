//! Resumable writes (`DatasetWriter::create_resumable`): a write interrupted after a
//! checkpoint continues there, and gives the same dataset as one uninterrupted write.

mod support;

use std::path::{Path, PathBuf};

use citystream_dataset::{Dataset, DatasetError, DatasetWriter, PACK_HEADER_BYTES};
use support::{add_fixture_texture, fixture_scene, fixture_texture, test_dir, write_fixture, TEXTURES};

const JOB: &str = "fixture, seed 1";

/// Write subdirectories in `dir` (the dataset's and any left by unfinished writes).
fn write_dirs(dir: &Path) -> Vec<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(dir)
        .expect("read dir")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_dir() && p.file_name().is_some_and(|n| n.to_string_lossy().starts_with("write-")))
        .collect();
    dirs.sort();
    dirs
}

/// Appends fixture textures `range` to a resumable writer of `dir`, checkpointing after
/// those below `checkpoint_at`, and drops it unfinished (as an error would).
fn interrupted_write(dir: &Path, job: &str, range: std::ops::Range<usize>, checkpoint_at: usize) -> u32 {
    let mut writer = DatasetWriter::create_resumable(dir, job).expect("create resumable");
    let start = writer.texture_count();
    for t in range {
        if t < start as usize {
            continue;
        }
        add_fixture_texture(&mut writer, &fixture_texture(t));
        if t + 1 == checkpoint_at {
            writer.checkpoint().expect("checkpoint");
        }
    }
    start
}

/// Finishes a resumable write of the whole fixture; returns where it resumed.
fn finish_write(dir: &Path, job: &str) -> u32 {
    let mut writer = DatasetWriter::create_resumable(dir, job).expect("create resumable");
    let start = writer.texture_count();
    for t in start as usize..TEXTURES.len() {
        add_fixture_texture(&mut writer, &fixture_texture(t));
    }
    writer.finish(&fixture_scene(TEXTURES.len() as u32)).expect("finish");
    start
}

/// Every mip, colour and the scene equal the uninterrupted fixture's.
fn assert_same_as_fixture(dir: &Path) -> Result<(), DatasetError> {
    let expected = write_fixture(&format!(
        "{}-reference",
        dir.file_name().expect("test dir name").to_string_lossy()
    ));
    let (a, b) = (Dataset::open(dir)?, Dataset::open(&expected.dir)?);
    assert_eq!(a.textures.len(), b.textures.len());
    assert_eq!(a.textures.pack_len(), b.textures.pack_len());
    let (mut x, mut y) = (Vec::new(), Vec::new());
    for t in 0..a.textures.len() {
        for level in 0..a.textures.info(t)?.mip_count() {
            a.textures.read_mip(t, level, &mut x)?;
            b.textures.read_mip(t, level, &mut y)?;
            assert_eq!(x, y, "texture {t} level {level}");
        }
        assert_eq!(a.colormap.get(t), b.colormap.get(t));
    }
    assert_eq!(a.scene, b.scene);
    citystream_dataset::verify(dir)?;
    Ok(())
}

#[test]
fn an_interrupted_write_resumes_after_its_last_checkpoint() -> Result<(), DatasetError> {
    let dir = test_dir("resume-after-checkpoint");
    // Textures 0..3 checkpointed, 3 and 4 appended after it and lost with the writer.
    assert_eq!(interrupted_write(&dir, JOB, 0..5, 3), 0);
    assert_eq!(write_dirs(&dir).len(), 1, "the unfinished write is kept");
    assert!(Dataset::open(&dir).is_err(), "no dataset before the write finishes");
    // A second interruption resumes at 3 and checkpoints up to 6.
    assert_eq!(interrupted_write(&dir, JOB, 0..7, 6), 3);
    assert_eq!(finish_write(&dir, JOB), 6);
    assert_eq!(write_dirs(&dir).len(), 1);
    assert!(
        !write_dirs(&dir)[0].join("resume.journal").exists(),
        "the journal goes at the end"
    );
    assert_same_as_fixture(&dir)
}

#[test]
fn another_job_or_a_plain_writer_starts_over() -> Result<(), DatasetError> {
    let dir = test_dir("resume-other-job");
    interrupted_write(&dir, JOB, 0..4, 4);
    assert_eq!(
        interrupted_write(&dir, "fixture, seed 2", 0..2, 2),
        0,
        "another job does not resume"
    );
    assert_eq!(write_dirs(&dir).len(), 1, "the other job's write was removed");
    assert_eq!(finish_write(&dir, JOB), 0, "the first job's progress is gone");
    assert_same_as_fixture(&dir)?;

    let dir = test_dir("resume-plain-writer");
    interrupted_write(&dir, JOB, 0..4, 4);
    let mut plain = DatasetWriter::create(&dir)?;
    assert_eq!(plain.texture_count(), 0);
    assert!(!plain.resumed());
    for t in 0..TEXTURES.len() {
        add_fixture_texture(&mut plain, &fixture_texture(t));
    }
    plain.finish(&fixture_scene(TEXTURES.len() as u32))?;
    assert_eq!(
        write_dirs(&dir).len(),
        1,
        "a plain writer removes the resumable leftover"
    );
    assert_same_as_fixture(&dir)
}

#[test]
fn a_torn_journal_record_or_extra_pack_bytes_are_cut_off() -> Result<(), DatasetError> {
    let dir = test_dir("resume-torn");
    interrupted_write(&dir, JOB, 0..5, 2);
    let write = write_dirs(&dir).pop().expect("unfinished write");
    // A record cut short by a crash, and its textures' bytes half written.
    let journal = write.join("resume.journal");
    let mut bytes = std::fs::read(&journal).expect("journal");
    let whole = bytes.len();
    bytes.extend_from_slice(&200u32.to_le_bytes());
    bytes.extend_from_slice(&[7u8; 57]);
    std::fs::write(&journal, &bytes).expect("write journal");
    let mut writer = DatasetWriter::create_resumable(&dir, JOB)?;
    assert!(writer.resumed());
    assert_eq!(writer.texture_count(), 2);
    assert_eq!(std::fs::metadata(&journal).expect("journal").len(), whole as u64);
    for t in 2..TEXTURES.len() {
        add_fixture_texture(&mut writer, &fixture_texture(t));
    }
    writer.finish(&fixture_scene(TEXTURES.len() as u32))?;
    assert_same_as_fixture(&dir)
}

#[test]
fn a_pack_shorter_than_its_journal_is_not_resumed() -> Result<(), DatasetError> {
    let dir = test_dir("resume-short-pack");
    interrupted_write(&dir, JOB, 0..3, 3);
    let write = write_dirs(&dir).pop().expect("unfinished write");
    let pack = std::fs::OpenOptions::new()
        .write(true)
        .open(write.join("textures.pack"))
        .expect("pack");
    pack.set_len(PACK_HEADER_BYTES + 10).expect("truncate");
    assert_eq!(finish_write(&dir, JOB), 0, "a damaged write starts over");
    assert_same_as_fixture(&dir)
}

#[test]
fn resuming_replaces_an_existing_dataset_only_at_the_end() -> Result<(), DatasetError> {
    let dir = test_dir("resume-replace");
    let mut old = DatasetWriter::create(&dir)?;
    for t in 0..2 {
        add_fixture_texture(&mut old, &fixture_texture(t));
    }
    old.finish(&fixture_scene(2))?;
    interrupted_write(&dir, JOB, 0..4, 4);
    // The old dataset is still the directory's while the write is unfinished.
    assert_eq!(Dataset::open(&dir)?.textures.len(), 2);
    assert_eq!(write_dirs(&dir).len(), 2);
    assert_eq!(finish_write(&dir, JOB), 4);
    assert_eq!(write_dirs(&dir).len(), 1, "the old write is removed after the switch");
    assert_same_as_fixture(&dir)
}
