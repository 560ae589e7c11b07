//! The loader over an in-memory source and sink: Algorithm 1's cycle.

use std::sync::Mutex;
use std::time::Duration;

use citystream_streaming::controller::Decision;
use citystream_streaming::loader::{Loader, LoaderError, LoaderOptions};
use citystream_streaming::records::{prepare, MeshMetaData};
use citystream_streaming::source::{
    pattern_byte, FaultKind, FaultPlan, FaultySource, MemorySink, MemorySource, MipSink, SinkError, StagedMip,
};
use citystream_streaming::states::TextureState;

/// A source of `count` BC1 textures of `side`² texels.
fn bc1_source(count: usize, side: u32) -> MemorySource {
    let mut src = MemorySource::new();
    for _ in 0..count {
        src.push_bc1(side, side);
    }
    src
}

fn rec(mesh_id: u32, weight: u32, mip_level: u32) -> MeshMetaData {
    MeshMetaData {
        mip_level,
        weight,
        mesh_id,
    }
}

fn unlimited() -> Decision {
    Decision::new(u64::MAX, 0.0)
}

fn options() -> LoaderOptions {
    LoaderOptions {
        load_time: Duration::from_secs(60),
        plan_chunk: 2,
        retry_backoff: Duration::from_micros(10),
        ..LoaderOptions::default()
    }
}

/// Two 16×16 BC1 textures (5 levels: 128, 32, 8, 8, 8 bytes; the 4×4 level
/// is 2), meshes 0 and 1 on texture 0, mesh 2 on texture 1.
fn two_textures() -> Result<Loader<MemorySource, MemorySink>, LoaderError> {
    let src = bc1_source(2, 16);
    Loader::new(src, MemorySink::new(), vec![0, 0, 1], 2, options())
}

#[test]
fn first_cycle_loads_the_4x4_level_then_one_level_per_cycle() -> Result<(), LoaderError> {
    let loader = two_textures()?;
    let records = prepare(vec![rec(0, 500, 0), rec(1, 400, 0), rec(2, 300, 1)], 150);
    // Cycle 1: both textures Initial → level 2 (4×4), one mip each even
    // though texture 0 has two records.
    let r = loader.run_cycle(&records, unlimited()).expect("idle");
    assert_eq!((r.planned_mips, r.loaded_mips, r.loaded_bytes), (2, 2, 16));
    let mut staged = loader.sink().take_staged();
    staged.sort_by_key(|m| m.texture);
    assert_eq!(
        staged.iter().map(|m| (m.texture, m.level)).collect::<Vec<_>>(),
        vec![(0, 2), (1, 2)]
    );
    // Exactly the mip's bytes, as stored.
    for m in &staged {
        assert!(m
            .bytes
            .iter()
            .enumerate()
            .all(|(o, &b)| b == pattern_byte(m.texture, m.level, o)));
    }
    // Cycle 2: level 1 for both (sampled 0 and 1 are below 2).
    loader.run_cycle(&records, unlimited());
    // Cycle 3: texture 0 → level 0 (Final); texture 1 wants 1, has 1: nothing.
    let r = loader.run_cycle(&records, unlimited()).expect("idle");
    assert_eq!(r.loaded_mips, 1);
    let s0 = loader.states().get(0).expect("in range");
    let s1 = loader.states().get(1).expect("in range");
    assert_eq!((s0.state, s0.mip_level), (TextureState::Final, 0));
    assert_eq!((s1.state, s1.mip_level), (TextureState::Active, 1));
    // Cycle 4: nothing left to do.
    assert_eq!(loader.run_cycle(&records, unlimited()).map(|r| r.planned_mips), Some(0));
    assert_eq!(loader.totals().loaded_mips, 5);
    assert_eq!(loader.sink().cycles(), 4);
    Ok(())
}

#[test]
fn bias_holds_back_refinement() -> Result<(), LoaderError> {
    let loader = two_textures()?;
    let records = vec![rec(2, 300, 0)];
    let biased = Decision::new(u64::MAX, 1.5);
    loader.run_cycle(&records, biased); // → level 2
                                        // 0 + 1.5 < 2 → level 1; then 0 + 1.5 < 1 is false → stays at 1.
    loader.run_cycle(&records, biased);
    let r = loader.run_cycle(&records, biased).expect("idle");
    assert_eq!(r.planned_mips, 0);
    assert_eq!(loader.states().get(1).expect("in range").mip_level, 1);
    Ok(())
}

#[test]
fn batch_stops_once_it_exceeds_the_load_size() -> Result<(), LoaderError> {
    // Ten 64×64 textures at level 0 wanted; the first cycle loads the 4×4
    // levels (8 B each). With s = 20 B: 0, 8, 16 ≤ 20 → a third mip is
    // still taken (24 B), then 24 > 20 stops the batch.
    let src = bc1_source(10, 64);
    let loader = Loader::new(src, MemorySink::new(), (0..10).collect(), 10, options())?;
    let records: Vec<_> = (0..10).map(|i| rec(i, 1000 - i, 0)).collect();
    let s = Decision::new(20, 0.0);
    let r = loader.run_cycle(&records, s).expect("idle");
    assert_eq!((r.loaded_mips, r.loaded_bytes), (3, 24));
    // Highest weights first.
    let mut got: Vec<u32> = loader.sink().take_staged().iter().map(|m| m.texture).collect();
    got.sort_unstable();
    assert_eq!(got, vec![0, 1, 2]);
    Ok(())
}

#[test]
fn io_errors_fail_the_texture_and_streaming_continues() -> Result<(), LoaderError> {
    let mut src = bc1_source(3, 16);
    src.remove_mip(0, 2); // missing data
    src.truncate_mip(1, 2, 3); // short read
    let loader = Loader::new(src, MemorySink::new(), vec![0, 1, 2, 7], 3, options());
    assert_eq!(
        loader.err(),
        Some(LoaderError::MeshTable {
            mesh: 3,
            texture: 7,
            textures: 3
        })
    );
    let mut src = bc1_source(3, 16);
    src.remove_mip(0, 2);
    src.truncate_mip(1, 2, 3);
    let loader = Loader::new(src, MemorySink::new(), vec![0, 1, 2], 3, options())?;
    let records = vec![rec(0, 900, 0), rec(1, 800, 0), rec(2, 700, 0), rec(99, 600, 0)];
    let r = loader.run_cycle(&records, unlimited()).expect("idle");
    assert_eq!((r.loaded_mips, r.failed, r.bad_records), (1, 2, 1));
    assert_eq!(loader.states().get(0).expect("in range").state, TextureState::Failed);
    assert_eq!(loader.states().get(1).expect("in range").state, TextureState::Failed);
    let failures = loader.failures();
    assert_eq!(failures.len(), 2);
    let reasons: Vec<&str> = failures.iter().map(|f| f.reason.as_str()).collect();
    assert!(reasons.iter().any(|r| r.contains("mip data missing")), "{reasons:?}");
    assert!(reasons.iter().any(|r| r.contains("short read")), "{reasons:?}");
    // Each was read three times before the texture was given up.
    assert!(reasons.iter().all(|r| r.ends_with("(after 3 attempts)")), "{reasons:?}");
    assert_eq!(loader.totals().read_retries, 4);
    // Failed textures are not retried; the good one keeps refining.
    let r = loader.run_cycle(&records, unlimited()).expect("idle");
    assert_eq!((r.loaded_mips, r.failed), (1, 0));
    assert_eq!(loader.totals().failed, 2);
    Ok(())
}

#[test]
fn invalidated_textures_are_unloaded_then_reloaded() -> Result<(), LoaderError> {
    let loader = two_textures()?;
    let records = vec![rec(2, 300, 0)];
    loader.run_cycle(&records, unlimited());
    loader.run_cycle(&records, unlimited());
    assert!(loader.states().invalidate(1).expect("in range"));
    assert_eq!(loader.states().get(1).expect("in range").state, TextureState::Final);
    loader.sink().take_staged();
    // Next cycle: UnloadTextures first, then the texture starts over at 4×4.
    let r = loader.run_cycle(&records, unlimited()).expect("idle");
    assert_eq!(r.unloaded, 1);
    assert_eq!(loader.sink().unloaded(), vec![1]);
    let staged = loader.sink().take_staged();
    assert_eq!(
        staged.iter().map(|m| (m.texture, m.level)).collect::<Vec<_>>(),
        vec![(1, 2)]
    );
    Ok(())
}

#[test]
fn load_time_limit_defers_and_keeps_state() -> Result<(), LoaderError> {
    let src = bc1_source(1, 16);
    let opts = LoaderOptions {
        load_time: Duration::ZERO,
        plan_chunk: 16,
        ..LoaderOptions::default()
    };
    let loader = Loader::new(src, MemorySink::new(), vec![0], 1, opts)?;
    let r = loader.run_cycle(&[rec(0, 500, 0)], unlimited()).expect("idle");
    assert_eq!((r.planned_mips, r.loaded_mips, r.deferred_by_time), (1, 0, 1));
    assert_eq!(loader.states().get(0).expect("in range").state, TextureState::Initial);
    Ok(())
}

/// Keeps each mip's modelled completion.
#[derive(Debug, Default)]
struct TimedSink {
    staged: Mutex<Vec<(u32, u32, Duration)>>,
}

impl MipSink for TimedSink {
    fn stage(&self, mip: StagedMip) -> Result<(), SinkError> {
        Err(SinkError {
            texture: mip.texture,
            level: mip.level,
            reason: "a modelled disk stages with stage_after".into(),
            invalidated: false,
        })
    }
    fn stage_after(&self, mip: StagedMip, done: Duration) -> Result<(), SinkError> {
        self.staged
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push((mip.texture, mip.level, done));
        Ok(())
    }
    fn unload(&self, _texture: u32) {}
}

#[test]
fn a_modelled_disk_times_each_read_and_limits_the_cycle_by_modelled_time() -> Result<(), LoaderError> {
    use citystream_streaming::disk_model::DiskModel;
    // 16 textures of 64² BC1: their 4×4 levels (8 bytes each) in the first cycle. One
    // lane at 8,000 bytes/s and 1 ms a request: each read takes 2 ms, one after another.
    let disk = DiskModel {
        bytes_per_s: 8_000,
        request_latency: Duration::from_millis(1),
        queue_depth: 1,
    };
    let opts = LoaderOptions {
        // Reads starting after 9 ms of modelled time wait for a later cycle: 5 start in
        // time (at 0, 2, 4, 6 and 8 ms).
        load_time: Duration::from_millis(9),
        disk: Some(disk),
        plan_chunk: 16,
        ..LoaderOptions::default()
    };
    let loader = Loader::new(bc1_source(16, 64), TimedSink::default(), (0..16).collect(), 16, opts)?;
    // Heaviest first: the order the reads are issued in.
    let records = prepare((0..16).map(|t| rec(t, 1000 - t, 0)).collect(), 150);
    let r = loader.run_cycle(&records, unlimited()).expect("idle");
    assert_eq!((r.planned_mips, r.loaded_mips, r.deferred_by_time), (16, 5, 11));
    assert_eq!(r.modelled_read_time, Duration::from_millis(10));
    let mut staged = loader
        .sink()
        .staged
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .clone();
    staged.sort();
    let expected: Vec<(u32, u32, Duration)> = (0..5)
        .map(|t| (t, 4, Duration::from_millis(2 * u64::from(t) + 2)))
        .collect();
    assert_eq!(staged, expected);
    // Deferred textures stay as they were, for the next cycle.
    assert_eq!(loader.states().get(5).expect("in range").state, TextureState::Initial);
    Ok(())
}

/// A sink whose first `stage` blocks until released, to hold a cycle open.
#[derive(Debug)]
struct GateSink {
    gate: Mutex<Option<crossbeam::channel::Receiver<()>>>,
    inner: MemorySink,
}

impl MipSink for GateSink {
    fn stage(&self, mip: StagedMip) -> Result<(), SinkError> {
        let rx = self
            .gate
            .lock()
            .map_err(|_| SinkError {
                texture: mip.texture,
                level: mip.level,
                reason: "poisoned".into(),
                invalidated: false,
            })?
            .take();
        if let Some(rx) = rx {
            let _ = rx.recv_timeout(Duration::from_secs(10));
        }
        self.inner.stage(mip)
    }
    fn unload(&self, texture: u32) {
        self.inner.unload(texture);
    }
}

#[test]
fn only_one_cycle_at_a_time() -> Result<(), LoaderError> {
    let (tx, rx) = crossbeam::channel::bounded(1);
    let src = bc1_source(1, 16);
    let sink = GateSink {
        gate: Mutex::new(Some(rx)),
        inner: MemorySink::new(),
    };
    let loader = Loader::new(src, sink, vec![0], 1, options())?;
    assert!(loader.try_spawn(vec![rec(0, 500, 0)], unlimited()));
    // The spawned cycle is held in `stage`; the flag refuses a second one.
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while !loader.is_streaming() && std::time::Instant::now() < deadline {
        std::thread::yield_now();
    }
    assert!(!loader.try_spawn(vec![rec(0, 500, 0)], unlimited()));
    assert!(loader.run_cycle(&[rec(0, 500, 0)], unlimited()).is_none());
    tx.send(()).expect("cycle waiting");
    let report = loader
        .recv_report_timeout(Duration::from_secs(10))
        .expect("cycle finishes");
    assert_eq!(report.loaded_mips, 1);
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while loader.is_streaming() && std::time::Instant::now() < deadline {
        std::thread::yield_now();
    }
    assert!(!loader.is_streaming());
    assert!(loader.try_spawn(vec![rec(0, 500, 0)], unlimited()));
    assert!(loader.recv_report_timeout(Duration::from_secs(10)).is_some());
    Ok(())
}

/// A sink that refuses texture 0 as invalidated and texture 1 as broken.
#[derive(Debug, Default)]
struct RefusingSink {
    inner: MemorySink,
}

impl MipSink for RefusingSink {
    fn stage(&self, mip: StagedMip) -> Result<(), SinkError> {
        match mip.texture {
            0 | 1 => Err(SinkError {
                texture: mip.texture,
                level: mip.level,
                reason: if mip.texture == 0 {
                    "region reused"
                } else {
                    "upload failed"
                }
                .into(),
                invalidated: mip.texture == 0,
            }),
            _ => self.inner.stage(mip),
        }
    }
    fn unload(&self, texture: u32) {
        self.inner.unload(texture);
    }
}

#[test]
fn sink_refusals_invalidate_or_fail() -> Result<(), LoaderError> {
    let src = bc1_source(3, 16);
    let states = std::sync::Arc::new(citystream_streaming::states::TextureStates::new(3));
    let loader = Loader::with_states(src, RefusingSink::default(), vec![0, 1, 2], states.clone(), options())?;
    assert!(std::sync::Arc::ptr_eq(&states, &loader.states_handle()));
    let records = vec![rec(0, 900, 0), rec(1, 800, 0), rec(2, 700, 0)];
    let r = loader.run_cycle(&records, unlimited()).expect("idle");
    assert_eq!((r.loaded_mips, r.invalidated_while_loading, r.failed), (1, 1, 1));
    let s0 = loader.states().get(0).expect("in range");
    assert_eq!((s0.state, s0.invalidated), (TextureState::Final, true));
    assert_eq!(loader.states().get(1).expect("in range").state, TextureState::Failed);
    assert_eq!(loader.failures().len(), 1);
    assert!(loader.failures()[0].reason.contains("upload failed"));
    // Next cycle unloads texture 0 and tries it again from the 4×4 level.
    let r = loader.run_cycle(&records, unlimited()).expect("idle");
    assert_eq!(r.unloaded, 1);
    assert_eq!(loader.sink().inner.unloaded(), vec![0]);
    Ok(())
}

/// Forty 16×16 textures, one mesh each, loaded to their base level.
fn load_all_through(plan: FaultPlan) -> Result<Loader<FaultySource<MemorySource>, MemorySink>, LoaderError> {
    let src = bc1_source(40, 16);
    let source = FaultySource::new(src, Some(plan), "textures.pack");
    let loader = Loader::new(source, MemorySink::new(), (0..40).collect(), 40, options())?;
    let records: Vec<MeshMetaData> = (0..40).map(|mesh| rec(mesh, 500, 0)).collect();
    for _ in 0..4 {
        loader.run_cycle(&records, unlimited());
    }
    Ok(loader)
}

#[test]
fn failed_reads_are_retried_and_recover_below_the_attempt_limit() -> Result<(), LoaderError> {
    for kind in [FaultKind::Error, FaultKind::ShortRead] {
        // Every third mip fails twice, and the third read succeeds.
        let loader = load_all_through(FaultPlan {
            every: 3,
            times: 2,
            kind,
        })?;
        let injected = loader.source().injected_failures();
        assert!(injected >= 20, "{injected} failures injected");
        let totals = loader.totals();
        assert_eq!((totals.failed, totals.read_retries), (0, injected));
        assert!(loader.failures().is_empty());
        // Every texture reached its base level with the right bytes.
        assert_eq!(loader.states().census(), [0, 0, 40, 0]);
        for mip in loader.sink().take_staged() {
            assert!(mip
                .bytes
                .iter()
                .enumerate()
                .all(|(o, &b)| b == pattern_byte(mip.texture, mip.level, o)));
        }
    }
    Ok(())
}

#[test]
fn reads_failing_every_attempt_fail_their_texture_and_name_the_file() -> Result<(), LoaderError> {
    let loader = load_all_through(FaultPlan {
        every: 3,
        times: 3,
        kind: FaultKind::Error,
    })?;
    let totals = loader.totals();
    let failed = loader.states().census()[3] as u64;
    assert!(failed > 0 && totals.failed == failed, "{totals:?}, {failed} failed");
    // Two retries per failed texture, nothing else retried.
    assert_eq!(totals.read_retries, 2 * failed);
    let failures = loader.failures();
    assert!(failures
        .iter()
        .all(|f| f.reason.contains("textures.pack") && f.reason.ends_with("(after 3 attempts)")));
    // A failed texture is never read again, and stays failed when its
    // cache region is reused.
    let first = failures[0].texture;
    assert!(!loader.states().invalidate(first).expect("in range"));
    assert_eq!(
        loader.states().get(first).expect("in range").state,
        TextureState::Failed
    );
    Ok(())
}

/// A source that records the prefetch hints it is given.
struct HintedSource {
    inner: MemorySource,
    hints: Mutex<Vec<Vec<(u32, u32)>>>,
}

impl citystream_streaming::source::MipSource for HintedSource {
    fn texture_count(&self) -> u32 {
        self.inner.texture_count()
    }
    fn texture_format(
        &self,
        texture: u32,
    ) -> Result<citystream_dataset::TextureFormat, citystream_streaming::source::SourceError> {
        self.inner.texture_format(texture)
    }
    fn mip_chain(
        &self,
        texture: u32,
    ) -> Result<citystream_streaming::states::MipChain, citystream_streaming::source::SourceError> {
        self.inner.mip_chain(texture)
    }
    fn mip_len(&self, texture: u32, level: u32) -> Result<u64, citystream_streaming::source::SourceError> {
        self.inner.mip_len(texture, level)
    }
    fn read_mip(
        &self,
        texture: u32,
        level: u32,
        buf: &mut [u8],
    ) -> Result<(), citystream_streaming::source::SourceError> {
        self.inner.read_mip(texture, level, buf)
    }
    fn prefetch(&self, mips: &[(u32, u32)]) {
        self.hints.lock().expect("hints").push(mips.to_vec());
    }
}

#[test]
fn prefetch_hints_the_cycle_in_priority_order_then_the_finer_levels_the_records_need_breadth_first(
) -> Result<(), LoaderError> {
    let inner = bc1_source(2, 16);
    let source = HintedSource {
        inner,
        hints: Mutex::new(Vec::new()),
    };
    let loader = Loader::new(source, MemorySink::new(), vec![0, 1], 2, options())?;
    // Texture 1 (heavier) needs level 0, texture 0 level 1.
    let records = prepare(vec![rec(0, 300, 1), rec(1, 500, 0)], 150);
    loader.run_cycle(&records, unlimited()).expect("idle");
    loader.run_cycle(&records, unlimited()).expect("idle");
    let hints = loader.source().hints.lock().expect("hints").clone();
    assert_eq!(hints.len(), 2);
    // Cycle 1 loads both 4×4 levels (2), heavier first; then the levels still to come,
    // the next cycle's of both before the one after: texture 1 down to 0, texture 0 down to
    // 1, nothing beyond what the records need.
    assert_eq!(hints[0], vec![(1, 2), (0, 2), (1, 1), (0, 1), (1, 0)]);
    assert_eq!(hints[1], vec![(1, 1), (0, 1), (1, 0)]);
    // Hints change nothing else: one level per texture per cycle, as without them.
    let mut staged: Vec<(u32, u32)> = loader
        .sink()
        .take_staged()
        .iter()
        .map(|m| (m.texture, m.level))
        .collect();
    staged.sort_unstable();
    assert_eq!(staged, vec![(0, 1), (0, 2), (1, 1), (1, 2)]);
    Ok(())
}
