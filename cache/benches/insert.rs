//! Parallel insertion throughput: textures placed per second by 2 (and 1)
//! loader threads inserting a random mix of extents.

use std::hint::black_box;
use std::time::{Duration, Instant};

use citystream_cache::{CacheConfig, DeviceLimits, Granularity, ImageConfig, TexelFormat, TextureCache};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};

fn config() -> CacheConfig {
    CacheConfig {
        images: vec![ImageConfig {
            format: TexelFormat::RGBA8,
            granularity: Granularity::texels(128, 128),
            layer_size: 4096,
            layer_count: 64,
            mip_tail: None,
        }],
        limits: DeviceLimits::lavapipe_reference(),
        memory_budget_bytes: 1 << 30,
        virtual_budget_bytes: u64::MAX,
        blocks_per_chunk: 256,
    }
}

/// Extents 4..=512 per side, from a fixed xorshift sequence.
fn shapes(count: usize, seed: u64) -> Vec<(u32, u32)> {
    let mut state = seed | 1;
    (0..count)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let w = 2 + (state % 8) as u32;
            let h = 2 + ((state >> 8) % 8) as u32;
            (1 << w, 1 << h)
        })
        .collect()
}

fn insert_parallel(cache: &TextureCache, per_thread: &[Vec<(u32, u32)>]) -> Duration {
    let start = std::sync::Barrier::new(per_thread.len() + 1);
    std::thread::scope(|scope| {
        for (thread, shapes) in per_thread.iter().enumerate() {
            let start = &start;
            scope.spawn(move || {
                start.wait();
                for (index, &(w, h)) in shapes.iter().enumerate() {
                    let key = (thread as u64) << 32 | index as u64;
                    black_box(cache.insert(0, key, w, h).ok());
                }
            });
        }
        start.wait();
        let began = Instant::now();
        // Leaving the scope joins the threads.
        began
    })
    .elapsed()
}

fn bench_insert(c: &mut Criterion) {
    const BATCH: usize = 20_000;
    let mut group = c.benchmark_group("insert");
    for threads in [1usize, 2] {
        let per_thread: Vec<Vec<(u32, u32)>> = (0..threads)
            .map(|thread| shapes(BATCH / threads, 0x9e37_79b9_7f4a_7c15 + thread as u64))
            .collect();
        group.throughput(Throughput::Elements(BATCH as u64));
        group.bench_function(format!("{threads}_threads_{BATCH}_textures"), |b| {
            b.iter_custom(|iterations| {
                let mut total = Duration::ZERO;
                for _ in 0..iterations {
                    let cache = TextureCache::new(&config()).expect("valid bench config");
                    total += insert_parallel(&cache, &per_thread);
                }
                total
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench_insert);
criterion_main!(benches);
