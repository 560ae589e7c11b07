//! Procedural texture content, mip chains and block compression.
//!
//! Level 0 is synthesised texel by texel from a `TextureSpec`; every further level is a
//! 2×2 box filter of the previous one, so small levels really are averages of the large ones
//! (window grids and brick courses blur away), which is what makes per-level image error
//! meaningful to the streamer.

use anyhow::Result;
use citystream_dataset::TextureFormat;

use crate::layout::{Content, FacadeStyle, TextureSpec, WallMaterial};
use crate::rng::{hash2, value_noise};

/// One encoded texture: its mip chain (finest first, back to back) and mean colour.
#[derive(Debug)]
pub struct EncodedTexture {
    pub format: TextureFormat,
    pub width: u32,
    pub height: u32,
    pub mip_count: u32,
    pub chain: Vec<u8>,
    pub mean: [u8; 4],
}

/// RGBA8 level 0 of `spec`, rows top to bottom.
pub fn synthesize(spec: &TextureSpec) -> Vec<u8> {
    let (w, h) = (1usize << spec.width_log2, 1usize << spec.height_log2);
    let mut out = vec![0u8; w * h * 4];
    let seed = spec.seed as u32 ^ (spec.seed >> 32) as u32;
    // Metres per texel along u and v.
    let mx = spec.size_m[0] / w as f32;
    let my = spec.size_m[1] / h as f32;
    for (j, row) in out.chunks_exact_mut(w * 4).enumerate() {
        for (i, px) in row.chunks_exact_mut(4).enumerate() {
            let u_m = (i as f32 + 0.5) * mx;
            let v_m = (j as f32 + 0.5) * my;
            let c = match &spec.content {
                Content::Facade(style) => facade(style, i, j, u_m, spec.size_m[1] - v_m, mx, seed),
                Content::Roof { base, parapet } => roof(*base, *parapet, u_m, v_m, spec.size_m, mx.max(my), seed),
                Content::Grass => grass(u_m, v_m, seed),
                Content::Plaza { base } => plaza(*base, u_m, v_m, mx.max(my), seed),
                Content::Street { along_u } => {
                    let (along, across, width) = if *along_u {
                        (u_m, v_m, spec.size_m[1])
                    } else {
                        (v_m, u_m, spec.size_m[0])
                    };
                    street(along, across, width, mx.max(my), seed)
                }
            };
            px[0] = to_u8(c[0]);
            px[1] = to_u8(c[1]);
            px[2] = to_u8(c[2]);
            px[3] = 255;
        }
    }
    out
}

fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

fn scale(c: [f32; 3], k: f32) -> [f32; 3] {
    [c[0] * k, c[1] * k, c[2] * k]
}

fn lerp(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

/// `u_m` along the wall segment, `y_m` height above the segment's bottom edge, `texel_m` metres per texel.
fn facade(style: &FacadeStyle, i: usize, j: usize, u_m: f32, y_m: f32, texel_m: f32, seed: u32) -> [f32; 3] {
    let x = u_m + style.along_offset;
    let y = y_m + style.base_height;
    let grime = 0.92 + 0.08 * value_noise(x * 0.3, y * 0.3, seed);
    let wall = match style.material {
        WallMaterial::Brick => {
            // Courses in texel space so the pattern exists at level 0 whatever the density.
            let course = j / 3;
            let shift = (course % 2) * 3;
            if j % 3 == 2 || (i + shift) % 6 == 5 {
                [0.72, 0.7, 0.66]
            } else {
                let brick = hash2(((i + shift) / 6) as i32, course as i32, seed);
                scale(style.wall, 0.85 + 0.3 * brick)
            }
        }
        WallMaterial::Plaster => scale(style.wall, 0.94 + 0.1 * hash2(i as i32, j as i32, seed)),
        WallMaterial::Concrete => {
            let panel = 3.0;
            let line = (x % panel < texel_m) || (y % panel < texel_m);
            scale(
                style.wall,
                if line {
                    0.75
                } else {
                    0.95 + 0.1 * hash2(i as i32, j as i32, seed)
                },
            )
        }
        WallMaterial::Glass => {
            let mullion = (x % 1.5 < texel_m.max(0.1)) || (y % style.floor_height < texel_m.max(0.15));
            if mullion {
                style.frame
            } else {
                let pane = hash2((x / 1.5) as i32, (y / style.floor_height) as i32, seed);
                let sky = (y * 0.01).min(0.3);
                scale(lerp(style.wall, [0.7, 0.8, 0.9], sky), 0.8 + 0.4 * pane)
            }
        }
    };
    if matches!(style.material, WallMaterial::Glass) {
        return scale(wall, grime);
    }
    let floor = (y / style.floor_height).floor();
    let fy = y / style.floor_height - floor;
    let column = (x / style.window_spacing).floor();
    let fx = x / style.window_spacing - column;
    let frame = (0.08f32).max(texel_m * 0.5) / style.window_spacing;
    let (x0, x1, y0, y1) = if floor == 0.0 && style.shop_floor {
        (0.08, 0.92, 0.08, 0.8)
    } else {
        let half = style.window_width / 2.0;
        (0.5 - half, 0.5 + half, 0.3, 0.3 + style.window_height)
    };
    let frame_y = (0.08f32).max(texel_m * 0.5) / style.floor_height;
    let in_window = fx >= x0 && fx <= x1 && fy >= y0 && fy <= y1;
    let colour = if in_window {
        let inner = fx >= x0 + frame && fx <= x1 - frame && fy >= y0 + frame_y && fy <= y1 - frame_y;
        if inner {
            let lit = hash2(column as i32, floor as i32, seed ^ 0x51);
            let reflection = 1.0 - (fy - y0) / (y1 - y0).max(1e-3);
            let glass = lerp(style.glass, [0.55, 0.62, 0.7], 0.35 * reflection);
            if lit > 0.85 {
                [0.95, 0.85, 0.55]
            } else {
                scale(glass, 0.8 + 0.4 * lit)
            }
        } else {
            style.frame
        }
    } else {
        wall
    };
    // Darker near the ground, lighter at the cornice line of each floor.
    let ground_dirt = 0.8 + 0.2 * (y / 2.5).min(1.0);
    scale(colour, grime * ground_dirt)
}

fn roof(base: [f32; 3], parapet: [f32; 3], u_m: f32, v_m: f32, size: [f32; 2], texel_m: f32, seed: u32) -> [f32; 3] {
    let edge = 0.6f32.max(texel_m);
    if u_m < edge || v_m < edge || size[0] - u_m < edge || size[1] - v_m < edge {
        return parapet;
    }
    // A few rooftop units: boxes on a coarse grid with their own shade.
    let cell = 6.0;
    let (cx, cy) = ((u_m / cell).floor(), (v_m / cell).floor());
    let h = hash2(cx as i32, cy as i32, seed ^ 0x77);
    if h > 0.8 {
        let (fx, fy) = (u_m / cell - cx, v_m / cell - cy);
        if (0.2..0.7).contains(&fx) && (0.25..0.75).contains(&fy) {
            return scale(parapet, 0.8 + 0.4 * h);
        }
        if (0.2..0.75).contains(&fx) && (0.75..0.9).contains(&fy) {
            return scale(base, 0.6);
        }
    }
    let gravel = hash2((u_m * 8.0) as i32, (v_m * 8.0) as i32, seed);
    scale(
        base,
        0.85 + 0.3 * gravel * (0.7 + 0.3 * value_noise(u_m * 0.2, v_m * 0.2, seed)),
    )
}

fn grass(u_m: f32, v_m: f32, seed: u32) -> [f32; 3] {
    let n = 0.6 * value_noise(u_m * 0.15, v_m * 0.15, seed) + 0.4 * value_noise(u_m * 0.8, v_m * 0.8, seed ^ 3);
    let tree_cell = 9.0;
    let (cx, cy) = ((u_m / tree_cell).floor(), (v_m / tree_cell).floor());
    if hash2(cx as i32, cy as i32, seed ^ 0x1ee) > 0.55 {
        let (dx, dy) = (u_m / tree_cell - cx - 0.5, v_m / tree_cell - cy - 0.5);
        let r2 = dx * dx + dy * dy;
        if r2 < 0.12 {
            return scale([0.12, 0.3, 0.1], 0.7 + 0.6 * (0.12 - r2) / 0.12);
        }
    }
    lerp([0.25, 0.42, 0.16], [0.42, 0.55, 0.22], n)
}

fn plaza(base: [f32; 3], u_m: f32, v_m: f32, texel_m: f32, seed: u32) -> [f32; 3] {
    let tile = 2.0;
    let joint = 0.06f32.max(texel_m * 0.5);
    if u_m % tile < joint || v_m % tile < joint {
        return scale(base, 0.7);
    }
    scale(base, 0.9 + 0.2 * hash2((u_m / tile) as i32, (v_m / tile) as i32, seed))
}

fn street(along: f32, across: f32, width: f32, texel_m: f32, seed: u32) -> [f32; 3] {
    let kerb = 0.4f32.max(texel_m);
    if across < kerb || width - across < kerb {
        return [0.62, 0.62, 0.6];
    }
    let centre = (across - width / 2.0).abs();
    if centre < 0.08f32.max(texel_m * 0.5) && along % 6.0 < 3.0 {
        return [0.92, 0.92, 0.88];
    }
    let grain = hash2((along * 10.0) as i32, (across * 10.0) as i32, seed);
    scale([0.22, 0.22, 0.23], 0.85 + 0.3 * grain)
}

/// Box-filters one level to the next (each side halves, stopping at 1).
pub fn downsample(src: &[u8], w: usize, h: usize) -> (Vec<u8>, usize, usize) {
    let (nw, nh) = ((w / 2).max(1), (h / 2).max(1));
    let (sx, sy) = (if w > 1 { 2 } else { 1 }, if h > 1 { 2 } else { 1 });
    let mut out = vec![0u8; nw * nh * 4];
    for y in 0..nh {
        for x in 0..nw {
            for c in 0..4 {
                let mut sum = 0u32;
                for dy in 0..sy {
                    for dx in 0..sx {
                        sum += u32::from(src[((y * sy + dy) * w + x * sx + dx) * 4 + c]);
                    }
                }
                let n = (sx * sy) as u32;
                out[(y * nw + x) * 4 + c] = ((sum + n / 2) / n) as u8;
            }
        }
    }
    (out, nw, nh)
}

/// Mean colour of an RGBA8 image (the City Colormap entry).
pub fn mean_colour(rgba: &[u8]) -> [u8; 4] {
    let mut sum = [0u64; 4];
    for px in rgba.chunks_exact(4) {
        for c in 0..4 {
            sum[c] += u64::from(px[c]);
        }
    }
    let n = (rgba.len() / 4).max(1) as u64;
    sum.map(|s| ((s + n / 2) / n) as u8)
}

/// One RGBA8 level as BC7 (alpha kept). The encoder takes whole 4×4
/// blocks, so levels below 4 texels a side are padded by repeating their
/// last row and column, as a sampler clamping at the edge would read them.
fn encode_bc7(rgba: &[u8], width: usize, height: usize) -> Vec<u8> {
    let (padded_w, padded_h) = (width.next_multiple_of(4), height.next_multiple_of(4));
    let mut padded = vec![0u8; padded_w * padded_h * 4];
    for y in 0..padded_h {
        for x in 0..padded_w {
            let from = (y.min(height - 1) * width + x.min(width - 1)) * 4;
            let to = (y * padded_w + x) * 4;
            padded[to..to + 4].copy_from_slice(&rgba[from..from + 4]);
        }
    }
    let surface = intel_tex_2::RgbaSurface {
        data: &padded,
        width: padded_w as u32,
        height: padded_h as u32,
        stride: padded_w as u32 * 4,
    };
    intel_tex_2::bc7::compress_blocks(&intel_tex_2::bc7::alpha_ultra_fast_settings(), &surface)
}

/// Builds the full mip chain of an RGBA8 level 0 and encodes every level in `format`.
pub fn encode_chain(level0: Vec<u8>, width: u32, height: u32, format: TextureFormat) -> Result<EncodedTexture> {
    let encoder = match format {
        TextureFormat::Rgba8 | TextureFormat::Bc7 => None,
        TextureFormat::Bc1 => Some(texpresso::Format::Bc1),
        TextureFormat::Bc3 => Some(texpresso::Format::Bc3),
    };
    let mean = mean_colour(&level0);
    let mip_count = width.trailing_zeros().max(height.trailing_zeros()) + 1;
    let mut chain = Vec::new();
    let (mut level, mut w, mut h) = (level0, width as usize, height as usize);
    for l in 0..mip_count {
        match encoder {
            None if format == TextureFormat::Bc7 => chain.extend_from_slice(&encode_bc7(&level, w, h)),
            None => chain.extend_from_slice(&level),
            Some(encoder) => {
                let start = chain.len();
                chain.resize(start + format.mip_bytes(w as u32, h as u32) as usize, 0);
                // Range fit: several times faster than cluster fit, and the procedural
                // content has few colours per block, so the quality loss is small.
                let params = texpresso::Params {
                    algorithm: texpresso::Algorithm::RangeFit,
                    ..Default::default()
                };
                encoder.compress(&level, w, h, params, &mut chain[start..]);
            }
        }
        if l + 1 < mip_count {
            (level, w, h) = downsample(&level, w, h);
        }
    }
    Ok(EncodedTexture {
        format,
        width,
        height,
        mip_count,
        chain,
        mean,
    })
}

/// One stored level of `width`×`height` texels in `format`, as RGBA8 rows (block formats
/// decoded; `data` must hold the level's [`TextureFormat::mip_bytes`]).
pub fn decode_level(format: TextureFormat, data: &[u8], width: u32, height: u32) -> Vec<u8> {
    let (w, h) = (width as usize, height as usize);
    let mut out = vec![0u8; w * h * 4];
    match format {
        TextureFormat::Rgba8 => out.copy_from_slice(&data[..w * h * 4]),
        TextureFormat::Bc1 => texpresso::Format::Bc1.decompress(data, w, h, &mut out),
        TextureFormat::Bc3 => texpresso::Format::Bc3.decompress(data, w, h, &mut out),
        TextureFormat::Bc7 => {
            let blocks_wide = w.div_ceil(4);
            let mut texels = [0u8; 64];
            for (b, block) in data.chunks_exact(16).take(blocks_wide * h.div_ceil(4)).enumerate() {
                bcdec_rs::bc7(block, &mut texels, 16);
                let (bx, by) = (b % blocks_wide * 4, b / blocks_wide * 4);
                // Blocks overhang levels below 4 texels a side: keep the texels inside.
                for y in 0..4.min(h - by) {
                    for x in 0..4.min(w - bx) {
                        let to = ((by + y) * w + bx + x) * 4;
                        out[to..to + 4].copy_from_slice(&texels[(y * 4 + x) * 4..(y * 4 + x) * 4 + 4]);
                    }
                }
            }
        }
    }
    out
}

/// Synthesises and encodes one texture.
pub fn generate(spec: &TextureSpec, format: TextureFormat) -> Result<EncodedTexture> {
    let level0 = synthesize(spec);
    encode_chain(level0, 1 << spec.width_log2, 1 << spec.height_log2, format)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn downsample_averages_and_handles_thin_levels() {
        // 2x2 -> 1x1: mean of four texels (rounded).
        let src = [10, 0, 0, 255, 20, 0, 0, 255, 30, 0, 0, 255, 41, 0, 0, 255];
        let (out, w, h) = downsample(&src, 2, 2);
        assert_eq!((w, h), (2 / 2, 2 / 2));
        assert_eq!(out[0], 25);
        // 1x4 -> 1x2 averages vertical pairs only.
        let src = [0, 0, 0, 0, 100, 0, 0, 0, 50, 0, 0, 0, 50, 0, 0, 0];
        let (out, w, h) = downsample(&src, 1, 4);
        assert_eq!((w, h), (1, 2));
        assert_eq!((out[0], out[4]), (50, 50));
    }

    #[test]
    fn chain_lengths_match_the_format() {
        for format in [TextureFormat::Bc1, TextureFormat::Rgba8] {
            let level0: Vec<u8> = (0..8 * 32 * 4).map(|i| (i * 7 % 251) as u8).collect();
            let t = encode_chain(level0, 8, 32, format).expect("encodable format");
            assert_eq!(t.mip_count, 6);
            let expected: u64 = (0..6).map(|l| format.mip_bytes((8u32 >> l).max(1), 32 >> l)).sum();
            assert_eq!(t.chain.len() as u64, expected);
        }
    }
}
