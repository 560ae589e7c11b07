//! The order a cycle takes its mips in: by error removed per byte, within a block
//! budget, and the view's records before the prefetch's.

use citystream_streaming::controller::{BlockBudget, Decision};
use citystream_streaming::loader::{
    error_per_byte, plan_cycle_with, CyclePlan, CycleRequest, Loader, LoaderOptions, PlanOrder,
};
use citystream_streaming::records::MeshMetaData;
use citystream_streaming::source::{MemorySink, MemorySource};
use citystream_streaming::states::TextureStates;

fn rec(mesh_id: u32, weight: u32, mip_level: u32) -> MeshMetaData {
    MeshMetaData {
        mip_level,
        weight,
        mesh_id,
    }
}

/// Four BC1 textures whose next loads are known (bytes of a BC1 level: 8 per 4×4 block):
///
/// | texture | extent | resident | wants | next level, bytes | meshes, weights |
/// | --- | --- | --- | --- | --- | --- |
/// | 0 | 256² | level 1 | 0 | 0, 32,768 | mesh 0: 1,000 |
/// | 1 | 64² | nothing | 0 | 4×4 (level 4), 8 | mesh 1: 100 |
/// | 2 | 256² | level 3 | 0 | 2, 2,048 | mesh 2: 300 |
/// | 3 | 64² | level 2 | 0 | 1, 512 | meshes 3 and 4: 200 each |
fn hand_made() -> Loader<MemorySource, MemorySink> {
    let mut src = MemorySource::new();
    for side in [256, 64, 256, 64] {
        src.push_bc1(side, side);
    }
    let loader = Loader::new(src, MemorySink::new(), vec![0, 1, 2, 3, 3], 4, LoaderOptions::default()).expect("valid");
    for (texture, level) in [(0, 1), (2, 3), (3, 2)] {
        assert!(loader
            .states()
            .settle(texture, TextureStates::resident_status(Some(level)))
            .expect("in range"));
    }
    loader
}

/// The view's records, by descending weight as `records::prepare` sorts them.
fn view() -> Vec<MeshMetaData> {
    vec![
        rec(0, 1000, 0),
        rec(2, 300, 0),
        rec(3, 200, 0),
        rec(4, 200, 0),
        rec(1, 100, 0),
    ]
}

fn plan(
    loader: &Loader<MemorySource, MemorySink>,
    order: PlanOrder,
    records: &[MeshMetaData],
    prefetch: &[MeshMetaData],
    decision: Decision,
) -> CyclePlan {
    let request = CycleRequest {
        records,
        prefetch,
        order,
        plan_chunk: 2,
    };
    plan_cycle_with(
        loader.states(),
        loader.mesh_textures(),
        &request,
        decision,
        loader.source(),
        None,
    )
}

fn textures(plan: &CyclePlan) -> Vec<u32> {
    plan.items.iter().map(|item| item.texture).collect()
}

#[test]
fn error_per_byte_takes_the_cheapest_error_first() {
    let loader = hand_made();
    // Error removed per byte: texture 1, a first load, 100 · 2 / 8 = 25; texture 3, both
    // meshes' weights, 400 / 512 = 0.78; texture 2, 300 / 2,048 = 0.15; texture 0,
    // 1,000 / 32,768 = 0.03. The weight order is the reverse but for texture 3 (max 200).
    assert_eq!(error_per_byte(100, true, 8), 25.0);
    assert_eq!(error_per_byte(400, false, 512), 400.0 / 512.0);
    let by_error = plan(
        &loader,
        PlanOrder::ErrorPerByte,
        &view(),
        &[],
        Decision::new(u64::MAX, 0.0),
    );
    assert_eq!(textures(&by_error), vec![1, 3, 2, 0]);
    assert_eq!(
        by_error.items.iter().map(|i| (i.level, i.bytes)).collect::<Vec<_>>(),
        vec![(4, 8), (1, 512), (2, 2048), (0, 32768)]
    );
    let by_weight = plan(&loader, PlanOrder::Weight, &view(), &[], Decision::new(u64::MAX, 0.0));
    assert_eq!(textures(&by_weight), vec![0, 2, 3, 1]);

    // A short budget: 2,560 bytes. Algorithm 1 stops once the batch exceeds it. By error
    // per byte it buys three textures' next levels (8 + 512 + 2,048 bytes); by weight one
    // level of texture 0 alone (32,768 bytes).
    let short = Decision::new(2560, 0.0);
    let by_error = plan(&loader, PlanOrder::ErrorPerByte, &view(), &[], short);
    assert_eq!((textures(&by_error), by_error.bytes), (vec![1, 3, 2], 2568));
    let by_weight = plan(&loader, PlanOrder::Weight, &view(), &[], short);
    assert_eq!(textures(&by_weight), vec![0]);
}

#[test]
fn under_a_block_budget_a_level_costs_its_whole_blocks_and_smaller_ones_share_blocks() {
    let loader = hand_made();
    // Blocks of 512 bytes: texture 3's level takes one block, texture 2's four, texture
    // 0's sixty-four; texture 1's 8-byte first load is smaller than a block and shares one
    // (its bytes' share of a block ranks it as without a budget). 6 blocks: 1 + 4 + 1.
    let budget = BlockBudget {
        blocks: 10,
        block_bytes: 512,
    };
    let decision = Decision {
        block_budget: Some(budget),
        ..Decision::new(u64::MAX, 0.0)
    };
    let p = plan(&loader, PlanOrder::ErrorPerByte, &view(), &[], decision);
    assert_eq!(textures(&p), vec![1, 3, 2]);
    assert_eq!((p.blocks, p.over_block_budget), (6, 1));
    // Small levels share blocks: a budget of one block takes the 8-byte level and, being
    // the cycle's first, nothing else fits beside texture 3's whole block.
    let one = Decision {
        block_budget: Some(BlockBudget { blocks: 1, ..budget }),
        ..Decision::new(u64::MAX, 0.0)
    };
    let p = plan(&loader, PlanOrder::ErrorPerByte, &view(), &[], one);
    assert_eq!((textures(&p), p.blocks, p.shared_bytes), (vec![1], 1, 8));
    // In the paper's order the first mip is always taken, whatever it costs (a cycle
    // makes progress); the rest only where their blocks fit what is left.
    let p = plan(&loader, PlanOrder::Weight, &view(), &[], decision);
    assert_eq!(textures(&p), vec![0]);
    assert_eq!((p.blocks, p.over_block_budget), (64, 3));
}

#[test]
fn prefetch_requests_never_displace_the_views_within_a_cycle() {
    let loader = hand_made();
    // The view asks for textures 0 and 2 only, lightly; the prefetch, heavily, for all
    // four. Whatever the order, every one of the view's mips comes before any prefetch
    // one, and a texture both name is the view's.
    let view = [rec(0, 160, 0), rec(2, 150, 0)];
    let prefetch = [
        rec(1, 60_000, 0),
        rec(3, 50_000, 0),
        rec(0, 70_000, 0),
        rec(2, 40_000, 0),
    ];
    for order in [PlanOrder::Weight, PlanOrder::ErrorPerByte] {
        let all = plan(&loader, order, &view, &prefetch, Decision::new(u64::MAX, 0.0));
        assert_eq!(
            textures(&all)[..2]
                .iter()
                .copied()
                .collect::<std::collections::BTreeSet<_>>(),
            [0, 2].into()
        );
        assert_eq!(all.items.len(), 4, "{order:?}");
        assert_eq!(all.prefetched, 2, "{order:?}");
        // A budget that the view's needs fill: no prefetch mip at all.
        let short = Decision::new(32768 + 2048 - 1, 0.0);
        let p = plan(&loader, order, &view, &prefetch, short);
        assert_eq!(p.prefetched, 0, "{order:?}: {:?}", textures(&p));
        let mut got = textures(&p);
        got.sort_unstable();
        assert_eq!(got, vec![0, 2], "{order:?}");
        // A block budget the view fills: the same.
        let blocks = Decision {
            block_budget: Some(BlockBudget {
                blocks: 68,
                block_bytes: 512,
            }),
            ..Decision::new(u64::MAX, 0.0)
        };
        let p = plan(&loader, order, &view, &prefetch, blocks);
        assert_eq!((p.prefetched, p.blocks), (0, 68), "{order:?}: {:?}", textures(&p));
    }
}

#[test]
fn a_cycle_of_the_loader_follows_its_order_option() {
    let mut src = MemorySource::new();
    for side in [256, 64, 256, 64] {
        src.push_bc1(side, side);
    }
    let options = LoaderOptions {
        order: PlanOrder::ErrorPerByte,
        ..LoaderOptions::default()
    };
    let loader = Loader::new(src, MemorySink::new(), vec![0, 1, 2, 3, 3], 4, options).expect("valid");
    // All four Initial: first loads of 8 bytes each, ranked by summed weight (texture 0's
    // 1,000, texture 3's 400, texture 2's 300, texture 1's 100); s = 16 bytes takes three.
    let report = loader
        .run_cycle_with(&view(), &[rec(1, 9000, 0)], Decision::new(16, 0.0))
        .expect("idle");
    assert_eq!((report.planned_mips, report.prefetched_mips), (3, 0));
    let mut staged: Vec<u32> = loader.sink().take_staged().iter().map(|m| m.texture).collect();
    staged.sort_unstable();
    assert_eq!(staged, vec![0, 2, 3]);
}
