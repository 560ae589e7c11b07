//! The feedback pass's compacted entries as the loader's records.

use citystream_streaming::records::MeshMetaData;

use crate::gpu_types::{FeedbackEntry, FEEDBACK_MIP_ONE, FEEDBACK_WEIGHT_ONE};

/// Converts compacted feedback entries to the loader's records: the level
/// wanted is the finest whole level covering the fractional one; the weight
/// is back in units of W per visible fragment (`fragment_area` visible pixels
/// per feedback fragment, see [`crate::city::FeedbackView::fragment_area`]).
pub fn records_from_feedback(entries: &[FeedbackEntry], fragment_area: f32) -> Vec<MeshMetaData> {
    entries
        .iter()
        .map(|e| MeshMetaData {
            mip_level: (e.mip as f32 / FEEDBACK_MIP_ONE).floor() as u32,
            weight: (e.weight as f32 / FEEDBACK_WEIGHT_ONE * fragment_area).round() as u32,
            mesh_id: e.mesh_id,
        })
        .collect()
}

/// The compaction threshold in the feedback's fixed-point units for a τ in
/// W per visible fragment.
pub fn feedback_tau(tau: u32, fragment_area: f32) -> u32 {
    (tau as f32 * FEEDBACK_WEIGHT_ONE / fragment_area.max(1e-6)).floor() as u32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn feedback_weights_become_visible_fragment_weights() {
        // One feedback fragment covers a 4x4 block of visible pixels (area 16).
        // A weight of 10 W in fixed point (80) stands for 160 W of visible fragments.
        let entries = [FeedbackEntry {
            mip: 3 * 256 + 200, // level 3.78: the finest whole level covering it is 3
            weight: 80,
            mesh_id: 7,
        }];
        let records = records_from_feedback(&entries, 16.0);
        assert_eq!(
            records,
            vec![MeshMetaData {
                mip_level: 3,
                weight: 160,
                mesh_id: 7
            }]
        );
        // τ = 150 W per visible fragment is 150 * 8 / 16 = 75 in feedback fixed point:
        // the entry above (80) passes on the GPU and its record (160) on the host.
        assert_eq!(feedback_tau(150, 16.0), 75);
        assert_eq!(feedback_tau(150, 1.0), 1200);
        // A degenerate area never divides by zero.
        assert!(feedback_tau(150, 0.0) > 0);
    }
}
