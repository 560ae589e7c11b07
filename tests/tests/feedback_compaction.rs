//! Compaction (paper §3.3) on lavapipe: the GPU's dense output equals a CPU
//! filter of the same random per-mesh array, for 1, 1 K, 1 M and 5.7 M meshes
//! (the paper's Berlin texture count) at several fill ratios, and the array
//! is reset afterwards.

use anyhow::{ensure, Result};
use citystream_engine::commands::CommandContext;
use citystream_engine::feedback::FeedbackCompactor;
use citystream_engine::gpu_types::{FeedbackEntry, MeshFeedback, FEEDBACK_UNSEEN};
use citystream_engine::placeholder::SplitMix64;
use citystream_tests::{assert_clean_after_dropping, validated_device};

const TAU: u32 = 150;

fn random_feedback(count: u32, fill: f32, seed: u64) -> Vec<MeshFeedback> {
    let mut rng = SplitMix64::new(seed);
    (0..count)
        .map(|_| {
            if rng.next_f32() < fill {
                MeshFeedback {
                    min_mip: (rng.next_u64() % (12 * 256)) as u32,
                    // Around τ, so the filter cuts through the data.
                    weight: (rng.next_u64() % 400) as u32,
                }
            } else {
                MeshFeedback {
                    min_mip: FEEDBACK_UNSEEN,
                    weight: 0,
                }
            }
        })
        .collect()
}

fn cpu_filter(values: &[MeshFeedback], tau: u32) -> Vec<FeedbackEntry> {
    values
        .iter()
        .enumerate()
        .filter(|(_, m)| m.min_mip != FEEDBACK_UNSEEN && m.weight >= tau)
        .map(|(i, m)| FeedbackEntry {
            mip: m.min_mip,
            weight: m.weight,
            mesh_id: i as u32,
        })
        .collect()
}

fn run_case(count: u32, fill: f32, capacity: u32, seed: u64) -> Result<()> {
    let device = validated_device()?;
    let mut commands = CommandContext::new(&device, "compaction test")?;
    let compactor = FeedbackCompactor::new(&device, &mut commands, count, capacity)?;
    // Freshly created arrays are reset.
    let initial = compactor.download_mesh_feedback(&mut commands)?;
    ensure!(
        initial.iter().all(|m| m.min_mip == FEEDBACK_UNSEEN && m.weight == 0),
        "a new feedback array must start reset"
    );
    let values = random_feedback(count, fill, seed);
    compactor.upload_mesh_feedback(&mut commands, &values)?;
    let cmd = commands.begin()?;
    compactor.record_compact(cmd, TAU, 0)?;
    commands.submit_and_wait(&[])?;
    let result = compactor.read_back(0)?;

    let expected = cpu_filter(&values, TAU);
    let mut got = result.entries.clone();
    got.sort_unstable_by_key(|e| e.mesh_id);
    if expected.len() <= capacity as usize {
        ensure!(
            result.dropped == 0,
            "{count} meshes: {} dropped with room to spare",
            result.dropped
        );
        ensure!(
            got == expected,
            "{count} meshes at fill {fill}: GPU kept {} entries, CPU {}",
            got.len(),
            expected.len()
        );
    } else {
        ensure!(
            got.len() == capacity as usize,
            "a full dense array holds exactly its capacity"
        );
        ensure!(result.dropped as usize == expected.len() - capacity as usize);
        let expected_set: std::collections::HashSet<_> = expected.iter().collect();
        ensure!(
            got.iter().all(|e| expected_set.contains(e)),
            "overflowing entries must still be real ones"
        );
    }
    let after = compactor.download_mesh_feedback(&mut commands)?;
    ensure!(
        after.iter().all(|m| m.min_mip == FEEDBACK_UNSEEN && m.weight == 0),
        "compaction must reset the array for the next frame"
    );
    assert_clean_after_dropping(&device, (compactor, commands))
}

#[test]
fn compaction_of_one_mesh() -> Result<()> {
    run_case(1, 1.0, 1, 1)?;
    run_case(1, 0.0, 1, 2)
}

#[test]
fn compaction_of_1k_meshes_at_several_fill_ratios() -> Result<()> {
    for (i, fill) in [0.0, 0.1, 0.5, 1.0].into_iter().enumerate() {
        run_case(1024, fill, 1024, 10 + i as u64)?;
    }
    Ok(())
}

#[test]
fn compaction_of_1m_meshes() -> Result<()> {
    run_case(1 << 20, 0.05, 1 << 20, 20)?;
    run_case(1 << 20, 0.9, 1 << 20, 21)
}

#[test]
fn compaction_of_berlin_scale_5_7m_meshes() -> Result<()> {
    // 5.7 M meshes: 22 266 workgroups of 256 and a 45 MB per-mesh array.
    run_case(5_700_000, 0.02, 1 << 20, 30)
}

#[test]
fn compaction_overflow_is_counted_not_written_out_of_bounds() -> Result<()> {
    run_case(4096, 1.0, 100, 40)
}
