//! The culling shader's inputs the host computes, Vulkan-free: each mesh's and each
//! chunk's box, the storage windows the bounds and the city's indices are seen
//! through, and the flag predicate that puts a mesh in a list.

use ash::vk;

use crate::error::{EngineError, Result};
use crate::gpu_types::{MeshBounds, CULL_IN_FRUSTUM, CULL_PREVIOUS, CULL_UNOCCLUDED, CULL_WINDOWS};
use crate::pipeline::DescriptorResource;

use super::CULL_CHUNK;

/// A view's lists.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum CullList {
    /// In the frustum and unoccluded last frame: drawn before the pyramid is built.
    Early = 0,
    /// In the frustum, unoccluded now, not drawn early.
    Late = 1,
    /// In the frustum and unoccluded now (the feedback pass after the pre-pass).
    Unoccluded = 2,
}

impl CullList {
    pub(crate) const ALL: [CullList; 3] = [CullList::Early, CullList::Late, CullList::Unoccluded];

    /// (mask, want) of the flags of a listed mesh.
    pub(crate) fn predicate(self) -> (u32, u32) {
        match self {
            CullList::Early => (CULL_PREVIOUS | CULL_IN_FRUSTUM, CULL_PREVIOUS | CULL_IN_FRUSTUM),
            CullList::Late => (
                CULL_PREVIOUS | CULL_IN_FRUSTUM | CULL_UNOCCLUDED,
                CULL_IN_FRUSTUM | CULL_UNOCCLUDED,
            ),
            CullList::Unoccluded => (CULL_IN_FRUSTUM | CULL_UNOCCLUDED, CULL_IN_FRUSTUM | CULL_UNOCCLUDED),
        }
    }
}

/// A buffer of `size` bytes seen through [`CULL_WINDOWS`] windows of `2^shift` elements.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct StorageWindows {
    size: u64,
    window_bytes: u64,
    /// log2 of the elements a window holds (the shader splits element indices by it).
    pub(super) shift: u32,
}

/// Testing aid: a smaller window than the device allows (bytes), so that a small city
/// exercises several windows.
pub const WINDOW_BYTES_ENV: &str = "CITYSTREAM_CULL_WINDOW_BYTES";

impl StorageWindows {
    /// Windows of `element`-byte elements (a power of two) over `size` bytes, each at most
    /// `max_range` bytes (the device's `maxStorageBufferRange`) and at least `alignment`
    /// (its `minStorageBufferOffsetAlignment`). `what` names the buffer in the error when
    /// [`CULL_WINDOWS`] windows do not hold it.
    pub(crate) fn new(size: u64, element: u64, max_range: u64, alignment: u64, what: &str) -> Result<Self> {
        // The largest power of two in range: window offsets stay aligned and element
        // indices split by a shift.
        let window_bytes = (1u64 << (63 - max_range.max(1).leading_zeros()))
            .max(element)
            .max(alignment.next_power_of_two());
        let windows = size.div_ceil(window_bytes);
        if windows > u64::from(CULL_WINDOWS) {
            return Err(EngineError::InvalidRequest(format!(
                "culling {what} of {size} bytes needs {windows} storage windows of {window_bytes} bytes \
                 (the device's maxStorageBufferRange is {max_range}); at most {CULL_WINDOWS} are supported"
            )));
        }
        Ok(Self {
            size: size.max(element),
            window_bytes,
            shift: (window_bytes / element).trailing_zeros(),
        })
    }

    pub(crate) fn resource(&self, buffer: vk::Buffer) -> DescriptorResource {
        DescriptorResource::StorageBufferWindows {
            buffer,
            size: self.size,
            window: self.window_bytes,
            count: CULL_WINDOWS,
        }
    }
}

/// A box holding nothing: every point widens it.
const EMPTY_BOUNDS: MeshBounds = MeshBounds {
    low: [f32::MAX, f32::MAX, f32::MAX, 0.0],
    high: [f32::MIN, f32::MIN, f32::MIN, 0.0],
};

/// World-space bounds of each mesh's drawn vertices; non-finite positions make the mesh
/// unbounded (never culled) rather than wrongly culled.
pub(crate) fn mesh_bounds(positions: impl Iterator<Item = (u32, [f32; 3])>, mesh_count: usize) -> Vec<MeshBounds> {
    let mut bounds = vec![EMPTY_BOUNDS; mesh_count];
    for (mesh, p) in positions {
        let Some(b) = bounds.get_mut(mesh as usize) else {
            continue;
        };
        if p.iter().any(|c| !c.is_finite()) {
            b.low[3] = 1.0;
            continue;
        }
        for (axis, &c) in p.iter().enumerate() {
            b.low[axis] = b.low[axis].min(c);
            b.high[axis] = b.high[axis].max(c);
        }
    }
    bounds
}

/// The union of each chunk of [`CULL_CHUNK`] meshes' boxes; unbounded when one of them is.
pub(crate) fn chunk_bounds(bounds: &[MeshBounds]) -> Vec<MeshBounds> {
    bounds
        .chunks(CULL_CHUNK as usize)
        .map(|chunk| {
            chunk.iter().fold(EMPTY_BOUNDS, |mut union, b| {
                if b.low[3] != 0.0 {
                    union.low[3] = 1.0;
                }
                for axis in 0..3 {
                    union.low[axis] = union.low[axis].min(b.low[axis]);
                    union.high[axis] = union.high[axis].max(b.high[axis]);
                }
                union
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn storage_windows_fit_the_device_range_and_refuse_what_eight_do_not_hold() -> Result<()> {
        // lavapipe: 128 MiB; 7.7 M meshes of 32-byte bounds need two windows.
        let w = StorageWindows::new(7_685_318 * 32, 32, 1 << 27, 16, "bounds")?;
        assert_eq!((w.window_bytes, w.shift), (1 << 27, 22));
        // A range that is no power of two rounds down; the shift counts elements.
        let w = StorageWindows::new(1000, 4, 300, 16, "indices")?;
        assert_eq!((w.window_bytes, w.shift), (256, 6));
        let windows: Vec<_> = crate::pipeline::storage_windows(w.size, w.window_bytes, CULL_WINDOWS).collect();
        assert_eq!(&windows[..5], &[(0, 256), (256, 256), (512, 256), (768, 232), (0, 256)]);
        // Nine windows' worth is refused, naming the buffer.
        let err = StorageWindows::new(9 * 256, 4, 256, 16, "the city's index buffer").expect_err("too large");
        assert!(err.to_string().contains("the city's index buffer"), "{err}");
        // An empty buffer still binds one element's worth.
        assert_eq!(StorageWindows::new(0, 32, 1 << 27, 16, "bounds")?.size, 32);
        Ok(())
    }

    #[test]
    fn bounds_cover_each_meshs_positions_and_leave_non_finite_meshes_unbounded() {
        let positions = [
            (0, [1.0, 2.0, 3.0]),
            (0, [-1.0, 5.0, 0.0]),
            (1, [0.0, f32::NAN, 0.0]),
            (1, [4.0, 4.0, 4.0]),
            (7, [9.0, 9.0, 9.0]),
        ];
        let bounds = mesh_bounds(positions.into_iter(), 3);
        assert_eq!(bounds[0].low, [-1.0, 2.0, 0.0, 0.0]);
        assert_eq!(bounds[0].high, [1.0, 5.0, 3.0, 0.0]);
        assert_eq!(bounds[1].low[3], 1.0, "a NaN position makes the mesh unbounded");
        // A mesh with no vertex has an empty box; its index count (0) keeps it undrawn.
        assert!(bounds[2].low[0] > bounds[2].high[0]);
    }

    #[test]
    fn chunk_bounds_hold_their_meshes_and_inherit_unboundedness() {
        let boxed = |low: [f32; 3], high: [f32; 3]| MeshBounds {
            low: [low[0], low[1], low[2], 0.0],
            high: [high[0], high[1], high[2], 0.0],
        };
        let mut bounds = vec![boxed([0.0; 3], [1.0; 3]); CULL_CHUNK as usize + 2];
        bounds[3] = boxed([-5.0, 0.0, 0.0], [0.0, 9.0, 0.0]);
        bounds[CULL_CHUNK as usize + 1].low[3] = 1.0;
        let chunks = chunk_bounds(&bounds);
        assert_eq!(chunks.len(), 2);
        assert_eq!(chunks[0].low, [-5.0, 0.0, 0.0, 0.0]);
        assert_eq!(chunks[0].high, [1.0, 9.0, 1.0, 0.0]);
        assert_eq!(chunks[1].low[3], 1.0, "an unbounded mesh makes its chunk unbounded");
        let header = include_str!("../../../shaders/include/citystream.glsl");
        assert!(header.contains(&format!("#define CULL_CHUNK {CULL_CHUNK}u")));
    }

    #[test]
    fn lists_partition_the_unoccluded_meshes_into_early_and_late() {
        // Every combination of the three flags: early + late covers the unoccluded
        // meshes exactly once, whatever was visible last frame.
        for flags in 0..8u32 {
            let listed = |list: CullList| {
                let (mask, want) = list.predicate();
                flags & mask == want
            };
            let in_frustum = flags & CULL_IN_FRUSTUM != 0;
            let unoccluded = in_frustum && flags & CULL_UNOCCLUDED != 0;
            assert_eq!(listed(CullList::Unoccluded), unoccluded, "flags {flags:03b}");
            assert!(
                !(listed(CullList::Early) && listed(CullList::Late)),
                "flags {flags:03b}"
            );
            if unoccluded {
                assert!(listed(CullList::Early) || listed(CullList::Late), "flags {flags:03b}");
            }
            assert!(!listed(CullList::Early) || in_frustum);
        }
    }
}
