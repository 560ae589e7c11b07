//! Mesh visibility metadata records (paper §3.2–3.3): the τ cutoff and the
//! parallel sort by descending weight.

use rayon::slice::ParallelSliceMut;

/// One compacted `MeshMetaData` element as the GPU writes it (12 bytes,
/// `repr(C)`, three little-endian `u32`s in this order).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct MeshMetaData {
    /// The finest mip level any fragment of the mesh wants (under `A_m`
    /// anisotropy); 0 is the base level.
    pub mip_level: u32,
    /// Sum of per-fragment weights `W` (Eq. 1–3).
    pub weight: u32,
    /// The mesh; its texture comes from the mesh → texture table.
    pub mesh_id: u32,
}

/// Table 2: mesh weight cutoff threshold τ.
pub const DEFAULT_WEIGHT_CUTOFF: u32 = 150;

/// Drop records whose weight is below `tau` ("small meshes with weights
/// less than the defined threshold τ will not be copied"); order is kept.
pub fn filter_by_weight(records: &mut Vec<MeshMetaData>, tau: u32) {
    records.retain(|r| r.weight >= tau);
}

/// Sort by descending weight, in parallel on the rayon pool. Ties are
/// broken by ascending mesh id and then mip level so that the order (and so
/// a streaming cycle) is the same on every run.
pub fn sort_by_priority(records: &mut [MeshMetaData]) {
    records.par_sort_unstable_by_key(priority_key);
}

/// Sort key: weight descending, mesh id ascending, mip level ascending.
fn priority_key(r: &MeshMetaData) -> (std::cmp::Reverse<u32>, u32, u32) {
    (std::cmp::Reverse(r.weight), r.mesh_id, r.mip_level)
}

/// `RetrieveMetadata` + `SortArray` of Algorithm 1 on the CPU side: τ
/// filter, then the parallel sort.
pub fn prepare(mut records: Vec<MeshMetaData>, tau: u32) -> Vec<MeshMetaData> {
    filter_by_weight(&mut records, tau);
    sort_by_priority(&mut records);
    records
}

/// A record, for tests across the crate.
#[cfg(test)]
pub(crate) fn rec(mesh_id: u32, weight: u32, mip_level: u32) -> MeshMetaData {
    MeshMetaData {
        mip_level,
        weight,
        mesh_id,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filters_below_tau_and_sorts_descending() {
        let out = prepare(
            vec![
                rec(1, 149, 0),
                rec(2, 150, 3),
                rec(3, 900, 1),
                rec(4, 150, 2),
                rec(0, 10_000, 5),
            ],
            150,
        );
        let ids: Vec<u32> = out.iter().map(|r| r.mesh_id).collect();
        // 149 dropped; ties at 150 in mesh-id order.
        assert_eq!(ids, vec![0, 3, 2, 4]);
    }

    #[test]
    fn layout_is_three_u32() {
        assert_eq!(std::mem::size_of::<MeshMetaData>(), 12);
    }
}
