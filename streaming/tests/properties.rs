//! Invariants of the controller, the states, the records and the planner
//! under arbitrary input.

use citystream_streaming::bind_latency::{BatchShape, BindLatencyPreset};
use citystream_streaming::controller::Decision;
use citystream_streaming::controller::{
    AdaptivePolicy, HeadroomPolicy, LoadPolicy, PolicyKind, PolicyOptions, PredictivePolicy, BYTES_PER_MB,
    MAX_FRAME_LATENCY_MS,
};
use citystream_streaming::loader::plan_cycle;
use citystream_streaming::records::{prepare, MeshMetaData};
use citystream_streaming::source::MemorySource;
use citystream_streaming::states::{next_load, TextureState, TextureStates, TextureStatus};
use proptest::prelude::*;

/// Frame latencies including every hard case: non-finite, negative, zero, tiny and huge.
fn latency() -> impl Strategy<Value = f64> {
    prop_oneof![
        4 => 0.0f64..50.0,
        1 => Just(0.0),
        1 => Just(1e-9),
        1 => Just(1e4),
        1 => Just(1000.0),
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
        1 => Just(f64::NEG_INFINITY),
        1 => -10.0f64..0.0,
        1 => 1e4f64..1e12,
    ]
}

fn options() -> impl Strategy<Value = PolicyOptions> {
    (0.01f64..200.0, 0.0f64..16.0, 0.5f64..256.0).prop_map(|(alpha_ms, beta, s_max_mb)| PolicyOptions {
        alpha_ms,
        beta,
        s_max_mb,
        ..PolicyOptions::default()
    })
}

proptest! {
    #[test]
    fn controller_outputs_stay_in_range(o in options(), frames in prop::collection::vec(latency(), 1..400)) {
        let mut p = AdaptivePolicy::new(&o).expect("generated options are valid");
        let s_min = o.s_min_bytes;
        let s_max = (o.s_max_mb * BYTES_PER_MB).round() as u64;
        for &ms in &frames {
            let d = p.update(ms);
            let t = p.telemetry();
            prop_assert!((s_min..=s_max).contains(&d.load_size_bytes), "{d:?} {t:?}");
            prop_assert!(d.mip_bias >= 0.0 && d.mip_bias <= o.beta, "{d:?}");
            prop_assert!((0.0..=1.0).contains(&t.load_factor));
            for v in [t.frame_ms, t.tw_ms, t.tm_ms, t.twa_ms, t.tb_ms, t.tbl_ms, t.tbu_ms, t.load_size_mb] {
                prop_assert!(v.is_finite() && v >= 0.0, "{t:?}");
            }
            // Eq. 5: t_w never drops below the frame it just saw; Eq. 7:
            // the edges bracket t_w.
            prop_assert!(t.tw_ms >= t.frame_ms);
            prop_assert!(t.tw_ms <= MAX_FRAME_LATENCY_MS);
            prop_assert!(t.tbl_ms <= t.tw_ms * (1.0 + 1e-12) && t.tw_ms <= t.tbu_ms * (1.0 + 1e-12), "{t:?}");
        }
    }

    #[test]
    fn every_policy_is_finite(kind in prop_oneof![Just(PolicyKind::Adaptive), Just(PolicyKind::Headroom), Just(PolicyKind::Baseline), Just(PolicyKind::Fixed)],
                              frames in prop::collection::vec(latency(), 1..100)) {
        let mut p = kind.build(&PolicyOptions::default()).expect("defaults are valid");
        for &ms in &frames {
            let d = p.update(ms);
            prop_assert!(d.mip_bias.is_finite());
            prop_assert!(d.load_size_bytes >= 65_536 && d.load_size_bytes <= 64 << 20);
        }
    }

    #[test]
    fn headroom_outputs_stay_in_range(o in options(),
                                      frames in prop::collection::vec((latency(), 0u64..(256 << 20)), 1..400)) {
        let mut p = HeadroomPolicy::new(&o).expect("generated options are valid");
        let s_min = o.s_min_bytes;
        let s_max = (o.s_max_mb * BYTES_PER_MB).round() as u64;
        for &(ms, loaded) in &frames {
            p.observe_load(loaded);
            let d = p.update(ms);
            let t = p.telemetry();
            prop_assert!((s_min..=s_max).contains(&d.load_size_bytes), "{d:?} {t:?}");
            prop_assert!(d.mip_bias >= 0.0 && d.mip_bias <= o.beta, "{d:?}");
            prop_assert!((0.0..=1.0).contains(&t.load_factor));
            for v in [t.frame_ms, t.tw_ms, t.tm_ms, t.twa_ms, t.tb_ms, t.load_size_mb] {
                prop_assert!(v.is_finite() && v >= 0.0, "{t:?}");
            }
        }
    }

    #[test]
    fn next_load_refines_one_level_towards_the_biased_target(
        level in 1u32..12, sampled in 0u32..12, bias in 0.0f64..8.0) {
        let s = TextureStatus { state: TextureState::Active, mip_level: level, invalidated: false };
        let next = next_load(s, sampled, bias, || Ok::<u32, ()>(0)).expect("no header read");
        match next {
            Some((l, to)) => {
                prop_assert_eq!(l, level - 1);
                prop_assert!(f64::from(sampled) + bias < f64::from(level));
                prop_assert_eq!(to.state == TextureState::Final, l == 0);
            }
            None => prop_assert!(f64::from(sampled) + bias >= f64::from(level)),
        }
    }

    #[test]
    fn prepare_filters_and_sorts(raw in prop::collection::vec((0u32..10, 0u32..400, 0u32..50), 0..300), tau in 0u32..400) {
        let records: Vec<MeshMetaData> = raw.iter().map(|&(m, w, id)| MeshMetaData { mip_level: m, weight: w, mesh_id: id }).collect();
        let out = prepare(records.clone(), tau);
        let mut kept: Vec<_> = records.iter().copied().filter(|r| r.weight >= tau).collect();
        prop_assert_eq!(out.len(), kept.len());
        prop_assert!(out.windows(2).all(|w| w[0].weight >= w[1].weight));
        let mut sorted = out.clone();
        sorted.sort_by_key(|r| (r.mesh_id, r.weight, r.mip_level));
        kept.sort_by_key(|r| (r.mesh_id, r.weight, r.mip_level));
        prop_assert_eq!(sorted, kept);
    }

    #[test]
    fn plan_takes_one_mip_per_texture_within_the_budget(
        weights in prop::collection::vec((0u32..1000, 0u32..6), 1..60), budget in 1u64..4000) {
        let mut src = MemorySource::new();
        for i in 0..20u32 {
            src.push_bc1(8 << (i % 5), 8 << (i % 5));
        }
        let states = TextureStates::new(20);
        let mesh_textures: Vec<u32> = (0..60).map(|m| m % 20).collect();
        let records: Vec<MeshMetaData> = weights.iter().enumerate()
            .map(|(i, &(w, m))| MeshMetaData { mip_level: m, weight: w, mesh_id: i as u32 }).collect();
        let records = prepare(records, 0);
        let decision = Decision::new(budget, 0.0);
        for _ in 0..4 {
            let plan = plan_cycle(&states, &mesh_textures, &records, decision, &src, 7, None);
            let mut textures: Vec<u32> = plan.items.iter().map(|i| i.texture).collect();
            textures.sort_unstable();
            let n = textures.len();
            textures.dedup();
            prop_assert_eq!(n, textures.len(), "one mip per texture per cycle");
            // Algorithm 1 checks `batch > s` before each load: everything but
            // the last item fits within s.
            let before_last: u64 = plan.items.iter().rev().skip(1).map(|i| i.bytes).sum();
            prop_assert!(before_last <= budget);
            prop_assert_eq!(plan.bytes, plan.items.iter().map(|i| i.bytes).sum::<u64>());
            for item in &plan.items {
                prop_assert!(states.try_transition(item.texture, item.from, item.to).expect("in range"));
            }
        }
    }
}

/// Frame `i`'s time in the million-frame trace: 4 to 8 ms, fluctuating, with a 1000 ms
/// spike every 10⁵ frames (the last at frame 999 999).
fn spiky_frame_ms(i: u64) -> f64 {
    if i % 100_000 == 99_999 {
        1000.0
    } else {
        4.0 + (i.wrapping_mul(2_654_435_761) % 1000) as f64 / 250.0
    }
}

/// The batch reported in frame `i` of the long runs: 0 to 1,023 blocks bound.
fn long_run_batch(i: u64) -> BatchShape {
    let blocks = i.wrapping_mul(2_654_435_761) % 1_024;
    BatchShape {
        bound: blocks,
        unbound: blocks / 3,
        bind_runs: blocks.div_ceil(16),
        unbind_runs: blocks.div_ceil(48),
    }
}

/// A predictive controller fed frames `frames` of the long run; its last decision.
fn predictive_over(bind_cost: Option<BindLatencyPreset>, frames: std::ops::Range<u64>) -> (PredictivePolicy, Decision) {
    let options = PolicyOptions {
        bind_cost,
        ..PolicyOptions::default()
    };
    let mut p = PredictivePolicy::new(&options).expect("defaults are valid");
    let mut last = p.decision();
    for i in frames {
        let shape = long_run_batch(i);
        p.observe_batch(shape, shape.bound * 65_536);
        last = p.update(spiky_frame_ms(i % 1_000_000));
        assert!(
            last.mip_bias.is_finite() && (0.0..=8.0).contains(&last.mip_bias),
            "{bind_cost:?}, frame {i}: bias {}",
            last.mip_bias
        );
        assert!(last.load_size_bytes <= 64 << 20, "{bind_cost:?}, frame {i}: {last:?}");
    }
    (p, last)
}

#[test]
fn ten_million_frames_of_the_predictive_controller_stay_finite_and_do_not_drift() {
    // 10⁷ frames of the spiky trace (a 1000 ms frame every 10⁵), each with a batch of 0 to
    // 1,023 blocks: with a device's fitted bind cost and with the cost learned online. No
    // NaN, nothing out of range, and the last decision is the one a controller fed only
    // the last 10⁶ frames reaches: nothing accumulated over the run moved it.
    const FRAMES: u64 = 10_000_000;
    for bind_cost in [Some(BindLatencyPreset::Desktop), None] {
        let (long, decided) = predictive_over(bind_cost, 0..FRAMES);
        let t = long.telemetry();
        assert_eq!(t.frames, FRAMES, "{bind_cost:?}");
        assert!(t.tw_ms.is_finite() && t.twa_ms.is_finite(), "{bind_cost:?}: {t:?}");
        let (_, fresh) = predictive_over(bind_cost, FRAMES - 1_000_000..FRAMES);
        eprintln!("{bind_cost:?}: after 10^7 frames {decided:?}, after the last 10^6 {fresh:?}");
        let ratio = decided.load_size_bytes as f64 / fresh.load_size_bytes.max(1) as f64;
        assert!(
            (0.9..=1.1).contains(&ratio) && (decided.mip_bias - fresh.mip_bias).abs() < 0.1,
            "{bind_cost:?}: {decided:?} after 10^7 frames, {fresh:?} after the last 10^6"
        );
    }
}

#[test]
fn a_million_frames_stay_finite_and_in_range() {
    // 10⁶ frames of a fluctuating trace with a 1000 ms spike every 10⁵
    // frames: no drift, no NaN, ranges hold at the end.
    let mut p = AdaptivePolicy::new(&PolicyOptions::default()).expect("defaults are valid");
    let mut max_s = 0;
    for i in 0u64..1_000_000 {
        let ms = spiky_frame_ms(i);
        let d = p.update(ms);
        max_s = max_s.max(d.load_size_bytes);
        assert!(d.mip_bias.is_finite() && (0.0..=8.0).contains(&d.mip_bias));
    }
    let t = p.telemetry();
    assert_eq!(t.frames, 1_000_000);
    assert!(t.tw_ms.is_finite() && t.twa_ms.is_finite() && t.tbu_ms.is_finite());
    assert!(max_s <= 64 << 20 && max_s > 65_536, "{max_s}");
    // After the last spike (frame 999 999) the load factor collapsed.
    assert_eq!(t.load_factor, 0.0);
}

#[test]
fn a_million_frames_of_the_headroom_controller_stay_finite_and_in_range() {
    // The same trace, with loads reported: no drift, no NaN, ranges hold, and the last
    // spike cut the load size.
    let mut p = HeadroomPolicy::new(&PolicyOptions::default()).expect("defaults are valid");
    let mut max_s = 0;
    let mut before_last_spike = 0;
    for i in 0u64..1_000_000 {
        let ms = spiky_frame_ms(i);
        p.observe_load(i.wrapping_mul(40_503) % (8 << 20));
        if i == 999_999 {
            before_last_spike = p.decision().load_size_bytes;
        }
        let d = p.update(ms);
        max_s = max_s.max(d.load_size_bytes);
        assert!(d.mip_bias.is_finite() && (0.0..=8.0).contains(&d.mip_bias));
    }
    let t = p.telemetry();
    assert_eq!(t.frames, 1_000_000);
    assert!(t.tw_ms.is_finite() && t.twa_ms.is_finite());
    assert!(max_s <= 64 << 20 && max_s > 65_536, "{max_s}");
    assert!(
        p.decision().load_size_bytes * 8 <= before_last_spike,
        "{} bytes after the spike, {before_last_spike} before",
        p.decision().load_size_bytes
    );
}
