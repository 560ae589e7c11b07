//! `citystream atlas`: packs a dataset's textures into square atlases (paper §3.1).
//!
//! Meshes are grouped by their centre into uniform grid regions, then by the closest of the
//! six global axis directions to their mean normal. Regions are walked in Z order (so that
//! consecutive regions are neighbours), orientation groups in order (+x, −x, +y, −y, +z, −z),
//! and each group's textures tallest and widest first; one shelf packer places them all into
//! `A × A` atlases, so an atlas a region leaves part empty is filled by the next region rather
//! than written mostly empty. Every texture sits at a multiple of its own width and height,
//! so its mips stay aligned in the atlas mips. UVs are rewritten into the atlas.
//!
//! `--packing regions` is the earlier packing, kept because the default city's published
//! figures were measured on it: a row packer per (region, texture height), each opening its
//! own atlases (on the `large` preset at 2048² it fills 21 % of each atlas).
//!
//! Memory stays bounded whatever the dataset size: atlases are composed in batches that fit
//! `--buffer-mb` and written to the pack before the next batch is composed.
//!
//! Level 0 of a BC1 atlas is a byte copy of the original blocks (rendering at full
//! resolution is identical); coarser levels copy every block that lies inside one texture's
//! own mip and re-encode only blocks where several textures (or empty space) meet. Textures
//! that cannot go into an atlas (larger than it, sampled with UVs outside `[0, 1]`, of another
//! format, or unused) are copied unchanged.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use citystream_dataset::{Dataset, DatasetWriter, Scene, TextureFormat};
use rayon::prelude::*;

use crate::city::check_texture_extent;
use crate::files::print_stdout;
use crate::texture::{decode_level, downsample};

/// Options of `citystream atlas`.
#[derive(Debug, clap::Args)]
pub struct AtlasArgs {
    /// Input dataset directory.
    pub input: PathBuf,
    /// Output dataset directory.
    #[arg(long, value_parser = crate::files::local_out)]
    pub out: PathBuf,
    /// Side of the square grid regions meshes are grouped by, metres.
    #[arg(long, default_value_t = 512.0)]
    pub region: f64,
    /// Atlas side in texels (a power of two, 4 to 16384).
    #[arg(long, default_value_t = 512)]
    pub atlas_extent: u32,
    /// How textures are placed: `shelves` (atlases shared by neighbouring regions) or
    /// `regions` (the earlier packing: separate atlases per region and texture height).
    #[arg(long, value_enum, default_value = "shelves")]
    pub packing: Packing,
    /// Memory for atlases composed but not yet written, MB (at least one atlas is
    /// composed at a time, whatever this says).
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u64).range(1..=1_048_576))]
    pub buffer_mb: u64,
    /// Do not print the summary.
    #[arg(long)]
    pub quiet: bool,
}

/// Where a texture went in an atlas.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Placement {
    pub atlas: usize,
    pub x: u32,
    pub y: u32,
}

/// Index (0..6) of the global axis direction closest to `n`: +x, −x, +y, −y, +z, −z.
pub fn closest_axis(n: [f32; 3]) -> usize {
    let (axis, _) = n.iter().enumerate().fold(
        (0, -1.0f32),
        |best, (a, v)| if v.abs() > best.1 { (a, v.abs()) } else { best },
    );
    axis * 2 + usize::from(n[axis] < 0.0)
}

/// How `citystream atlas` places textures (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Packing {
    /// One shelf packer over all regions in Z order.
    Shelves,
    /// A row packer per (region, texture height).
    Regions,
}

/// The earlier packing's row packer for textures of one height: a texture of width `w` is
/// placed at the first row position that is a multiple of `w` and has room.
#[derive(Debug)]
struct RowPacker {
    extent: u32,
    height: u32,
    /// Cursor of each row of the current atlas.
    rows: Vec<u32>,
    atlas: Option<usize>,
}

impl RowPacker {
    fn new(extent: u32, height: u32) -> Self {
        Self {
            extent,
            height,
            rows: Vec::new(),
            atlas: None,
        }
    }

    fn place(&mut self, width: u32, atlas_count: &mut usize) -> Placement {
        let atlas = match self.atlas {
            Some(a) => a,
            None => self.open(atlas_count),
        };
        for (r, cursor) in self.rows.iter_mut().enumerate() {
            let x = cursor.next_multiple_of(width);
            if x + width <= self.extent {
                *cursor = x + width;
                return Placement {
                    atlas,
                    x,
                    y: r as u32 * self.height,
                };
            }
        }
        if (self.rows.len() as u32 + 1) * self.height <= self.extent {
            self.rows.push(width);
            return Placement {
                atlas,
                x: 0,
                y: (self.rows.len() as u32 - 1) * self.height,
            };
        }
        let atlas = self.open(atlas_count);
        self.rows.push(width);
        Placement { atlas, x: 0, y: 0 }
    }

    fn open(&mut self, atlas_count: &mut usize) -> usize {
        self.rows.clear();
        self.atlas = Some(*atlas_count);
        *atlas_count += 1;
        *atlas_count - 1
    }
}

/// A row of one height in an atlas.
#[derive(Debug)]
struct Shelf {
    y: u32,
    height: u32,
    /// First free column.
    cursor: u32,
}

/// Shelf packer for power-of-two textures in `A × A` atlases: a texture of `w × h` goes to
/// the first shelf of height `h` with room at a multiple of `w`, else to a new shelf at the
/// first multiple of `h` below the others, else to a new atlas.
#[derive(Debug)]
struct ShelfPacker {
    extent: u32,
    shelves: Vec<Shelf>,
    /// First row below every shelf of the current atlas.
    bottom: u32,
    atlas: Option<usize>,
}

impl ShelfPacker {
    fn new(extent: u32) -> Self {
        Self {
            extent,
            shelves: Vec::new(),
            bottom: 0,
            atlas: None,
        }
    }

    fn place(&mut self, width: u32, height: u32, atlas_count: &mut usize) -> Placement {
        let atlas = match self.atlas {
            Some(a) => a,
            None => self.open(atlas_count),
        };
        for shelf in self.shelves.iter_mut().filter(|s| s.height == height) {
            let x = shelf.cursor.next_multiple_of(width);
            if x + width <= self.extent {
                shelf.cursor = x + width;
                return Placement { atlas, x, y: shelf.y };
            }
        }
        let y = self.bottom.next_multiple_of(height);
        if y + height <= self.extent {
            return self.new_shelf(atlas, y, width, height);
        }
        let atlas = self.open(atlas_count);
        self.new_shelf(atlas, 0, width, height)
    }

    fn new_shelf(&mut self, atlas: usize, y: u32, width: u32, height: u32) -> Placement {
        self.shelves.push(Shelf {
            y,
            height,
            cursor: width,
        });
        self.bottom = y + height;
        Placement { atlas, x: 0, y }
    }

    fn open(&mut self, atlas_count: &mut usize) -> usize {
        self.shelves.clear();
        self.bottom = 0;
        self.atlas = Some(*atlas_count);
        *atlas_count += 1;
        *atlas_count - 1
    }
}

/// Interleaves the bits of two region coordinates (offset to be non-negative): regions
/// sorted by this key are walked in Z order, neighbours mostly after one another.
fn z_order(x: i64, z: i64) -> u128 {
    let spread = |v: i64| {
        let v = (v as i128 - i128::from(i64::MIN)) as u128 & u128::from(u64::MAX);
        (0..64).fold(0u128, |acc, bit| acc | (((v >> bit) & 1) << (2 * bit)))
    };
    spread(x) | (spread(z) << 1)
}

/// Where every texture goes: the output of the packing, before any texel is touched.
#[derive(Debug)]
pub(crate) struct AtlasPlan {
    /// Per input texture: its place in an atlas, `None` when it is kept as it is.
    pub placements: Vec<Option<Placement>>,
    /// Per atlas: its member textures in id order.
    pub members: Vec<Vec<usize>>,
}

impl AtlasPlan {
    /// Atlases the plan fills.
    pub fn atlas_count(&self) -> usize {
        self.members.len()
    }

    /// Fraction of the atlases' texels that hold texture texels.
    pub fn fill_ratio(&self, sizes: &[[u32; 2]], extent: u32) -> f64 {
        let packed: u64 = sizes
            .iter()
            .zip(&self.placements)
            .filter(|(_, p)| p.is_some())
            .map(|(s, _)| u64::from(s[0]) * u64::from(s[1]))
            .sum();
        let capacity = self.atlas_count() as u64 * u64::from(extent) * u64::from(extent);
        if capacity > 0 {
            packed as f64 / capacity as f64
        } else {
            0.0
        }
    }
}

/// Plans the atlases of a scene whose textures have `sizes` (width, height); `eligible`
/// says which textures may go into an atlas at all (format, extent). A texture also stays
/// out when a mesh samples it outside `[0, 1]` or no mesh uses it.
pub(crate) fn plan_atlases(
    scene: &Scene,
    sizes: &[[u32; 2]],
    mut eligible: Vec<bool>,
    region: f64,
    extent: u32,
    packing: Packing,
) -> AtlasPlan {
    let count = sizes.len();
    let mut first_mesh: Vec<Option<usize>> = vec![None; count];
    for (m, mesh) in scene.meshes.iter().enumerate() {
        let t = mesh.texture as usize;
        first_mesh[t].get_or_insert(m);
        let range = mesh.first_vertex as usize..(mesh.first_vertex + mesh.vertex_count) as usize;
        if scene.uvs[range].iter().flatten().any(|v| !(0.0..=1.0).contains(v)) {
            eligible[t] = false;
        }
    }

    // Group: region (in Z order) then orientation, textures in id order.
    let mut groups: BTreeMap<(u128, i64, i64), [Vec<usize>; 6]> = BTreeMap::new();
    for t in 0..count {
        let Some(m) = first_mesh[t].filter(|_| eligible[t]) else {
            continue;
        };
        let mesh = &scene.meshes[m];
        let c = mesh.bounds.center();
        let region_of = |a: usize| ((scene.origin[a] + f64::from(c[a])) / region).floor() as i64;
        let range = mesh.first_vertex as usize..(mesh.first_vertex + mesh.vertex_count) as usize;
        let mut n = [0.0f32; 3];
        for v in &scene.normals[range] {
            for a in 0..3 {
                n[a] += v[a];
            }
        }
        let (rx, rz) = (region_of(0), region_of(2));
        groups.entry((z_order(rx, rz), rx, rz)).or_default()[closest_axis(n)].push(t);
    }
    let mut placements: Vec<Option<Placement>> = vec![None; count];
    let mut atlas_count = 0usize;
    match packing {
        Packing::Shelves => {
            let mut packer = ShelfPacker::new(extent);
            for orientations in groups.values() {
                for mut group in orientations.iter().cloned() {
                    // Tallest, then widest first inside a group keeps shelves dense; groups
                    // stay in axis order and regions in Z order.
                    group.sort_by_key(|&t| (std::cmp::Reverse(sizes[t][1]), std::cmp::Reverse(sizes[t][0])));
                    for t in group {
                        placements[t] = Some(packer.place(sizes[t][0], sizes[t][1], &mut atlas_count));
                    }
                }
            }
        }
        Packing::Regions => {
            // Regions in coordinate order, then texture height, then orientation.
            let mut by_height: BTreeMap<(i64, i64, u32), [Vec<usize>; 6]> = BTreeMap::new();
            for (&(_, rx, rz), orientations) in &groups {
                for (axis, group) in orientations.iter().enumerate() {
                    for &t in group {
                        by_height.entry((rx, rz, sizes[t][1])).or_default()[axis].push(t);
                    }
                }
            }
            for ((_, _, height), orientations) in &by_height {
                let mut packer = RowPacker::new(extent, *height);
                for mut group in orientations.iter().cloned() {
                    group.sort_by_key(|&t| std::cmp::Reverse(sizes[t][0]));
                    for t in group {
                        placements[t] = Some(packer.place(sizes[t][0], &mut atlas_count));
                    }
                }
            }
        }
    }
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); atlas_count];
    for (t, p) in placements.iter().enumerate() {
        if let Some(p) = p {
            members[p.atlas].push(t);
        }
    }
    AtlasPlan { placements, members }
}

/// Mip levels and chain bytes of one `extent²` atlas in `format`.
pub(crate) fn atlas_chain(extent: u32, format: TextureFormat) -> (u32, u64) {
    let levels = extent.trailing_zeros() + 1;
    let bytes = (0..levels)
        .map(|level| format.mip_bytes(extent >> level, extent >> level))
        .sum();
    (levels, bytes)
}

/// How many atlases to compose before writing them so that `buffer_mb` holds the batch and
/// every thread's working images (at least one atlas).
pub(crate) fn atlas_batch(extent: u32, format: TextureFormat, buffer_mb: u64) -> (usize, u64) {
    let (_, chain_bytes) = atlas_chain(extent, format);
    // Each thread composes one atlas at a time in RGBA (a level and the one above it);
    // every atlas of a batch holds its finished chain until the batch is written.
    let working = u64::from(extent) * u64::from(extent) * 4 * 2 * rayon::current_num_threads() as u64;
    let batch = ((buffer_mb << 20).saturating_sub(working) / chain_bytes.max(1)).max(1) as usize;
    (batch, working)
}

/// The scene with every placed texture's meshes pointed at their atlas (`new_id` maps every
/// input texture to its output id) and their UVs rewritten into it.
pub(crate) fn remap_scene(
    scene: &Scene,
    sizes: &[[u32; 2]],
    placements: &[Option<Placement>],
    new_id: &[u32],
    extent: u32,
) -> Result<Scene> {
    let mut out_scene = scene.clone();
    let mut remapped = vec![false; scene.uvs.len()];
    for mesh in &mut out_scene.meshes {
        let t = mesh.texture as usize;
        mesh.texture = new_id[t];
        let Some(p) = placements[t] else { continue };
        let (w, h, a) = (sizes[t][0] as f32, sizes[t][1] as f32, extent as f32);
        let range = mesh.first_vertex as usize..(mesh.first_vertex + mesh.vertex_count) as usize;
        let rewritten = out_scene.uvs[range.clone()]
            .iter_mut()
            .zip(&mut remapped[range.clone()]);
        for (v, (uv, done)) in rewritten.enumerate() {
            if std::mem::replace(done, true) {
                bail!(
                    "vertex {} is shared by two meshes; its texture coordinates cannot be rewritten twice",
                    range.start + v
                );
            }
            *uv = [(p.x as f32 + uv[0] * w) / a, (p.y as f32 + uv[1] * h) / a];
        }
    }
    Ok(out_scene)
}

/// Runs `citystream atlas`.
pub fn run(args: &AtlasArgs) -> Result<()> {
    let start = Instant::now();
    let extent = args.atlas_extent;
    check_texture_extent("--atlas-extent", extent)?;
    if !(args.region.is_finite() && args.region > 0.0) {
        bail!("--region {} must be a positive number of metres", args.region);
    }
    let dataset = Dataset::open(&args.input).with_context(|| format!("opening {}", args.input.display()))?;
    let scene = &dataset.scene;
    let infos = dataset.textures.textures();
    let count = infos.len();

    // The atlas format is the dataset's most common of BC1 / RGBA8.
    let bc1 = infos.iter().filter(|t| t.format() == TextureFormat::Bc1).count();
    let rgba = infos.iter().filter(|t| t.format() == TextureFormat::Rgba8).count();
    let format = if bc1 >= rgba {
        TextureFormat::Bc1
    } else {
        TextureFormat::Rgba8
    };
    let sizes: Vec<[u32; 2]> = infos.iter().map(|t| [t.width(), t.height()]).collect();
    let eligible = infos
        .iter()
        .map(|t| t.format() == format && t.width() <= extent && t.height() <= extent)
        .collect();
    let plan = plan_atlases(scene, &sizes, eligible, args.region, extent, args.packing);
    let members = &plan.members;

    // Compose atlases in parallel, a batch that fits the buffer at a time, and write each
    // batch before the next: memory does not grow with the dataset.
    let (levels, chain_bytes) = atlas_chain(extent, format);
    let (batch, working) = atlas_batch(extent, format, args.buffer_mb);
    let mut writer = DatasetWriter::create(&args.out)?;
    let mut peak_buffered = 0u64;
    for (index, chunk) in members.chunks(batch).enumerate() {
        let built: Vec<Result<(Vec<u8>, [u8; 4])>> = chunk
            .par_iter()
            .map(|textures| {
                let parts: Vec<AtlasPart> = textures
                    .iter()
                    .map(|&t| {
                        let info = &infos[t];
                        let p = plan.placements[t].context("atlas member without a placement")?;
                        Ok(AtlasPart {
                            x: p.x,
                            y: p.y,
                            width: info.width(),
                            height: info.height(),
                            mip_count: info.mip_count(),
                            format: info.format(),
                            colour: dataset.colormap.get(t as u32).unwrap_or([128, 128, 128, 255]),
                        })
                    })
                    .collect::<Result<_>>()?;
                compose_atlas(&parts, extent, levels, format, |part, level, buf| {
                    dataset.textures.read_mip(textures[part] as u32, level, buf)?;
                    Ok(())
                })
            })
            .collect();
        peak_buffered = peak_buffered.max(chunk.len() as u64 * chain_bytes + working);
        for atlas in built {
            let (chain, mean) = atlas?;
            writer.add_texture(format, extent, extent, levels, &chain, mean)?;
        }
        if !args.quiet && members.len() > batch {
            let done = (index * batch + chunk.len()).min(members.len());
            eprintln!(
                "atlas: {done}/{} atlases written ({:.0} s)",
                members.len(),
                start.elapsed().as_secs_f64()
            );
        }
    }
    let mut new_id: Vec<u32> = vec![0; count];
    let mut standalone = 0u32;
    let mut buf = Vec::new();
    for (t, (id, placement)) in new_id.iter_mut().zip(&plan.placements).enumerate() {
        match placement {
            Some(p) => *id = p.atlas as u32,
            None => {
                *id = copy_texture(&dataset, t as u32, &mut writer, &mut buf)?;
                standalone += 1;
            }
        }
    }

    let out_scene = remap_scene(scene, &sizes, &plan.placements, &new_id, extent)?;
    let summary = writer
        .finish(&out_scene)
        .with_context(|| format!("writing {}", args.out.display()))?;

    if args.quiet {
        return Ok(());
    }
    print_stdout(&format!(
        "atlas: {} textures -> {} atlases of {extent}x{extent} (fill ratio {:.1}%) + {standalone} textures kept as they are = {} textures; {:.1} MB pack, {:.2} s; atlases composed {batch} at a time, peak buffer {:.1} MB of {} MB\n",
        count,
        plan.atlas_count(),
        100.0 * plan.fill_ratio(&sizes, extent),
        summary.textures,
        summary.pack_bytes as f64 / 1e6,
        start.elapsed().as_secs_f64(),
        peak_buffered as f64 / f64::from(1 << 20),
        args.buffer_mb,
    ))
}

/// Copies texture `t` of `dataset` (every level, and its colormap colour) unchanged into
/// `writer`; returns its id there. `buf` is reused between calls.
pub fn copy_texture(dataset: &Dataset, t: u32, writer: &mut DatasetWriter, buf: &mut Vec<u8>) -> Result<u32> {
    let info = dataset.textures.info(t)?;
    let mut chain = Vec::with_capacity(info.chain_len() as usize);
    for level in 0..info.mip_count() {
        dataset.textures.read_mip(t, level, buf)?;
        chain.extend_from_slice(buf);
    }
    let colour = dataset.colormap.get(t).unwrap_or([128, 128, 128, 255]);
    Ok(writer.add_texture(
        info.format(),
        info.width(),
        info.height(),
        info.mip_count(),
        &chain,
        colour,
    )?)
}

/// One texture of an atlas: where it sits, its extent, levels, format and colormap colour.
#[derive(Clone, Copy, Debug)]
pub(crate) struct AtlasPart {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
    pub mip_count: u32,
    pub format: TextureFormat,
    pub colour: [u8; 4],
}

/// Composes one atlas of `parts`: its mip chain (full, finest first) and the area-weighted
/// mean colour of its textures. `read(part, level, buf)` fills `buf` with a part's stored
/// level.
pub(crate) fn compose_atlas(
    parts: &[AtlasPart],
    extent: u32,
    levels: u32,
    format: TextureFormat,
    read: impl Fn(usize, u32, &mut Vec<u8>) -> Result<()>,
) -> Result<(Vec<u8>, [u8; 4])> {
    let mut sum = [0u64; 4];
    let mut area = 0u64;
    for part in parts {
        let a = u64::from(part.width) * u64::from(part.height);
        for (total, channel) in sum.iter_mut().zip(part.colour) {
            *total += u64::from(channel) * a;
        }
        area += a;
    }
    let mean = sum.map(|s| (s / area.max(1)) as u8);

    let mut chain = Vec::new();
    let mut previous: Option<Vec<u8>> = None;
    let mut buf = Vec::new();
    let params = texpresso::Params {
        algorithm: texpresso::Algorithm::RangeFit,
        ..Default::default()
    };
    for level in 0..levels {
        let side = (extent >> level) as usize;
        // Empty space: the mean colour at level 0, the box filter of the level above below it.
        let mut rgba = match &previous {
            None => mean.repeat(side * side),
            Some(prev) => downsample(prev, side * 2, side * 2).0,
        };
        let blocks_per_row = side.div_ceil(4);
        // Blocks inside one part's own mip: their bytes are copied, not encoded.
        let mut copied = vec![false; blocks_per_row * blocks_per_row];
        let mut copies = Vec::new();
        for (index, part) in parts.iter().enumerate() {
            let (w, h) = (part.width >> level, part.height >> level);
            if w == 0 || h == 0 || level >= part.mip_count {
                continue;
            }
            read(index, level, &mut buf)?;
            let texels = decode_level(part.format, &buf, w, h);
            let (x0, y0) = ((part.x >> level) as usize, (part.y >> level) as usize);
            for row in 0..h as usize {
                let dst = ((y0 + row) * side + x0) * 4;
                let src = row * w as usize * 4;
                rgba[dst..dst + w as usize * 4].copy_from_slice(&texels[src..src + w as usize * 4]);
            }
            if format == TextureFormat::Bc1 && w >= 4 && h >= 4 {
                let (bx, by, bw, bh) = (x0 / 4, y0 / 4, (w / 4) as usize, (h / 4) as usize);
                for row in by..by + bh {
                    copied[row * blocks_per_row + bx..row * blocks_per_row + bx + bw].fill(true);
                }
                copies.push((bx, by, bw, bh, std::mem::take(&mut buf)));
            }
        }
        match format {
            TextureFormat::Bc1 => {
                let start = chain.len();
                chain.resize(start + format.mip_bytes(side as u32, side as u32) as usize, 0);
                let level_bytes = &mut chain[start..];
                if side < 4 {
                    texpresso::Format::Bc1.compress(&rgba, side, side, params, level_bytes);
                } else {
                    // Only the blocks no part covers are encoded (each block is encoded on
                    // its own, so this equals encoding the level whole).
                    for (block, _) in copied.iter().enumerate().filter(|(_, &c)| !c) {
                        let (bx, by) = (block % blocks_per_row * 4, block / blocks_per_row * 4);
                        let mut texels = [[0u8; 4]; 16];
                        for (i, texel) in texels.iter_mut().enumerate() {
                            let at = ((by + i / 4) * side + bx + i % 4) * 4;
                            texel.copy_from_slice(&rgba[at..at + 4]);
                        }
                        texpresso::Format::Bc1.compress_block_masked(
                            texels,
                            u32::MAX >> 16,
                            params,
                            &mut level_bytes[block * 8..block * 8 + 8],
                        );
                    }
                }
                // Blocks inside one texture's own mip: the original bytes, exactly.
                for (bx, by, bw, bh, bytes) in copies {
                    for row in 0..bh {
                        let dst = ((by + row) * blocks_per_row + bx) * 8;
                        level_bytes[dst..dst + bw * 8].copy_from_slice(&bytes[row * bw * 8..(row + 1) * bw * 8]);
                    }
                }
            }
            _ => chain.extend_from_slice(&rgba),
        }
        previous = Some(rgba);
    }
    Ok((chain, mean))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normals_map_to_the_closest_axis_direction() {
        assert_eq!(closest_axis([0.9, 0.1, -0.2]), 0);
        assert_eq!(closest_axis([-0.9, 0.1, 0.2]), 1);
        assert_eq!(closest_axis([0.0, 1.0, 0.0]), 2);
        assert_eq!(closest_axis([0.1, -0.7, 0.3]), 3);
        assert_eq!(closest_axis([0.0, 0.0, 1.0]), 4);
        assert_eq!(closest_axis([0.3, 0.2, -0.8]), 5);
    }

    #[test]
    fn shelf_packer_keeps_alignment_fills_shelves_then_opens_atlases() {
        let mut atlases = 0;
        let mut packer = ShelfPacker::new(16);
        let a = packer.place(8, 8, &mut atlases);
        let b = packer.place(4, 8, &mut atlases);
        let c = packer.place(8, 8, &mut atlases); // does not fit after 8+4 at an aligned x: next shelf
        let d = packer.place(4, 8, &mut atlases); // fills the gap in shelf 0
        let e = packer.place(16, 8, &mut atlases); // both shelves full: new atlas
        assert_eq!((a.atlas, a.x, a.y), (0, 0, 0));
        assert_eq!((b.atlas, b.x, b.y), (0, 8, 0));
        assert_eq!((c.atlas, c.x, c.y), (0, 0, 8));
        assert_eq!((d.atlas, d.x, d.y), (0, 12, 0));
        assert_eq!((e.atlas, e.x, e.y), (1, 0, 0));
        assert_eq!(atlases, 2);
        // Heights mix in one atlas, each shelf at a multiple of its height.
        let f = packer.place(4, 4, &mut atlases);
        let g = packer.place(2, 2, &mut atlases);
        let h = packer.place(4, 4, &mut atlases);
        assert_eq!((f.atlas, f.x, f.y), (1, 0, 8));
        assert_eq!((g.atlas, g.x, g.y), (1, 0, 12));
        assert_eq!((h.atlas, h.x, h.y), (1, 4, 8));
        assert_eq!(atlases, 2);
    }

    #[test]
    fn z_order_walks_neighbours_together() {
        let mut regions: Vec<(i64, i64)> = (-2..2).flat_map(|x| (-2..2).map(move |z| (x, z))).collect();
        regions.sort_by_key(|&(x, z)| z_order(x, z));
        // The first four are one 2x2 block.
        let block: Vec<_> = regions[..4].to_vec();
        assert!(
            block.iter().all(|&(x, z)| (-2..0).contains(&x) && (-2..0).contains(&z)),
            "{block:?}"
        );
        assert_eq!(z_order(i64::MIN, i64::MIN), 0);
        assert!(z_order(i64::MAX, i64::MAX) > z_order(0, 0));
    }
}
