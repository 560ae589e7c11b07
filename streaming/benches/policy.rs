//! Criterion benchmarks: one controller step, and sorting 1 M metadata
//! records by priority (the parallel sort of §3.3).

use std::hint::black_box;

use citystream_streaming::controller::{AdaptivePolicy, LoadPolicy, PolicyOptions};
use citystream_streaming::records::{sort_by_priority, MeshMetaData};
use citystream_streaming::rng::SplitMix64;
use criterion::{criterion_group, criterion_main, BatchSize, Criterion};

fn controller_step(c: &mut Criterion) {
    let mut policy = match AdaptivePolicy::new(&PolicyOptions::default()) {
        Ok(p) => p,
        Err(e) => panic!("default options are valid: {e}"),
    };
    // Fill every history window first so the step does its full work.
    let mut rng = SplitMix64::new(1);
    for _ in 0..1000 {
        policy.update(rng.range(3.0, 20.0));
    }
    let trace: Vec<f64> = (0..1024).map(|_| rng.range(3.0, 20.0)).collect();
    let mut i = 0;
    c.bench_function("controller_step", |b| {
        b.iter(|| {
            i = (i + 1) & 1023;
            black_box(policy.update(black_box(trace[i])))
        })
    });
}

fn sort_1m_records(c: &mut Criterion) {
    let mut rng = SplitMix64::new(2);
    let records: Vec<MeshMetaData> = (0..1_000_000u32)
        .map(|mesh_id| MeshMetaData {
            mip_level: (rng.next_u64() % 10) as u32,
            weight: (rng.next_u64() % 100_000) as u32,
            mesh_id,
        })
        .collect();
    let mut group = c.benchmark_group("records");
    group.sample_size(20);
    group.bench_function("sort_1m_by_priority", |b| {
        b.iter_batched_ref(
            || records.clone(),
            |r| sort_by_priority(black_box(r)),
            BatchSize::LargeInput,
        )
    });
    group.finish();
}

criterion_group!(benches, controller_step, sort_1m_records);
criterion_main!(benches);
