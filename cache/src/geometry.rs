//! Pure layer geometry: regions, mip rectangles, UV transforms and the
//! sparse blocks a rectangle touches. All sizes are powers of two, so every
//! mip of a region stays aligned to the same fraction of its layer.

use crate::format::{Granularity, TexelFormat};

/// Width or height of mip level `mip` of a `size`-texel level 0.
pub fn level_size(size: u32, mip: u32) -> u32 {
    size.checked_shr(mip).unwrap_or(0).max(1)
}

/// Sparse blocks covering a square `size`×`size` mip level.
pub fn blocks_in_level(size: u32, granularity: &Granularity) -> u64 {
    u64::from(size.div_ceil(granularity.width)) * u64::from(size.div_ceil(granularity.height))
}

/// Texel origin of square region `region` of extent `extent` in a layer of
/// `layer_size`, filling left to right, then top to bottom.
pub fn region_origin(layer_size: u32, extent: u32, region: u32) -> (u32, u32) {
    let per_row = (layer_size / extent.max(1)).max(1);
    (
        (region % per_row).saturating_mul(extent),
        (region / per_row).saturating_mul(extent),
    )
}

/// Number of mips of a `width`×`height` texture the cache can hold: the
/// levels whose both sides are still whole texel blocks. Beyond them a
/// compressed mip could not be copied into its region block-aligned, and
/// the region's UV transform would no longer address whole texels.
/// Zero when level 0 itself is smaller than a texel block.
pub fn cacheable_mip_count(format: &TexelFormat, width: u32, height: u32) -> u32 {
    if width < format.block_width || height < format.block_height {
        return 0;
    }
    let wide = (width / format.block_width).max(1).ilog2();
    let high = (height / format.block_height).max(1).ilog2();
    wide.min(high) + 1
}

/// A rectangle of texels inside one mip level of a layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct TexelRect {
    /// Mip level of the sparse image.
    pub mip: u32,
    /// Left edge in texels of that level.
    pub x: u32,
    /// Top edge in texels of that level.
    pub y: u32,
    /// Width in texels.
    pub width: u32,
    /// Height in texels.
    pub height: u32,
}

impl TexelRect {
    /// The rectangle of mip `mip` of a `width`×`height` texture whose level
    /// 0 starts at (`origin_x`, `origin_y`).
    pub fn of_mip(origin_x: u32, origin_y: u32, width: u32, height: u32, mip: u32) -> Self {
        TexelRect {
            mip,
            x: origin_x.checked_shr(mip).unwrap_or(0),
            y: origin_y.checked_shr(mip).unwrap_or(0),
            width: level_size(width, mip),
            height: level_size(height, mip),
        }
    }

    /// Whether two rectangles of the same level share a texel.
    pub fn overlaps(&self, other: &TexelRect) -> bool {
        let end = |start: u32, size: u32| u64::from(start) + u64::from(size);
        self.mip == other.mip
            && u64::from(self.x) < end(other.x, other.width)
            && u64::from(other.x) < end(self.x, self.width)
            && u64::from(self.y) < end(other.y, other.height)
            && u64::from(other.y) < end(self.y, self.height)
    }

    /// The inclusive-exclusive range of sparse block columns and rows the
    /// rectangle touches: `(x0, y0, x1, y1)`.
    pub fn block_range(&self, granularity: &Granularity) -> (u32, u32, u32, u32) {
        if self.width == 0 || self.height == 0 {
            return (0, 0, 0, 0);
        }
        // Last texel in u64 so rectangles at the edge of u32 cannot overflow.
        let last = |start: u32, size: u32, block: u32| {
            ((u64::from(start) + u64::from(size) - 1) / u64::from(block.max(1))) as u32
        };
        (
            self.x / granularity.width.max(1),
            self.y / granularity.height.max(1),
            last(self.x, self.width, granularity.width).saturating_add(1),
            last(self.y, self.height, granularity.height).saturating_add(1),
        )
    }
}

/// Maps a texture's own UV in \[0, 1\]² to the UV of its layer:
/// `layer_uv = uv * scale + offset`. Valid at every cacheable mip, because a
/// region's origin and the texture's size shrink by the same power of two as
/// the layer's level.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UvTransform {
    /// Texture size over layer size, per axis.
    pub scale: [f32; 2],
    /// Region origin over layer size, per axis.
    pub offset: [f32; 2],
}

impl UvTransform {
    /// The transform for a `width`×`height` texture at (`origin_x`,
    /// `origin_y`) in a layer of `layer_size`. Exact in `f32`: every value
    /// is an integer below 2^15 divided by a power of two.
    pub fn new(layer_size: u32, origin_x: u32, origin_y: u32, width: u32, height: u32) -> Self {
        let size = layer_size.max(1) as f32;
        UvTransform {
            scale: [width as f32 / size, height as f32 / size],
            offset: [origin_x as f32 / size, origin_y as f32 / size],
        }
    }

    /// Applies the transform to a texture UV.
    pub fn apply(&self, uv: [f32; 2]) -> [f32; 2] {
        [
            uv[0] * self.scale[0] + self.offset[0],
            uv[1] * self.scale[1] + self.offset[1],
        ]
    }
}
