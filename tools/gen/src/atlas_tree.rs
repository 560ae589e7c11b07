//! `citystream atlas-tree`: builds a texture-atlas tree (Buchholz & Döllner §5) from a
//! dataset; the format and the run-time algorithms are in
//! `citystream_streaming::atlas_tree`.
//!
//! 1. The root holds every triangle. A node tries to pack, for each original texture its
//!    triangles use, the area that avoids magnification from the leaf distance `d_min` on
//!    (§5.2: per triangle, the world length of one texture repetition times the texels per
//!    metre needed at `d_min`, times the node's texture-coordinate range, plus a border;
//!    never more than the texture's own texels) into one `N × N` atlas. If they do not fit,
//!    the node splits in four (§5.3: triangles sorted by their centre's x, cut where the
//!    world area halves, each half likewise along z) and its children try again. A node that
//!    cannot split further (one triangle, or all at one centre) scales its areas down to fit
//!    (counted in the summary: those texels are magnified at `d_min`).
//! 2. Leaves compose their atlas from the original textures (the mip level whose size is
//!    nearest above what the area needs, bilinear, repeating); `min_distance` is `d_min`
//!    (`--distances paper`, the default) or, with `--distances full-density`, `d_min` times
//!    the largest shortfall of an area (an original with fewer texels than `d_min` needs,
//!    or an area scaled down to fit): from there on the atlas has every texel the view
//!    needs, so no ancestor shows less than the originals would.
//! 3. Inner nodes, bottom up: the children's atlases side by side in a `2N × 2N` image (a
//!    quadrant per child, empty ones the mean colour), box-filtered to `N × N`;
//!    `min_distance` is twice the children's largest.
//! 4. Every vertex gets its coordinates in the root atlas; node `k` levels down samples its
//!    own atlas at `root_uv · 2^k − offset`.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use citystream_dataset::{Aabb, Dataset, DatasetWriter, Scene, TextureFormat};
use citystream_streaming::atlas_tree::{
    texels_per_metre_at_unit_distance, world_length_of_texture_axes, AtlasTree, TreeNode, TreeParams, NO_PARENT,
    TREE_FILE,
};
use rayon::prelude::*;

use crate::files::{print_stdout, write_atomically};
use crate::texture::{decode_level, downsample, mean_colour};

/// Options of `citystream atlas-tree`.
#[derive(Debug, clap::Args)]
pub struct AtlasTreeArgs {
    /// Input dataset directory (generated or imported).
    pub dataset: PathBuf,
    /// Output directory: a dataset (the nodes' atlases, then the original textures; the
    /// leaves' meshes) plus `atlas-tree.bin`.
    #[arg(long, value_parser = crate::files::local_out)]
    pub out: PathBuf,
    /// Side of every node's atlas in texels (a power of two, 64 to 8192).
    #[arg(long, default_value_t = 512)]
    pub atlas_extent: u32,
    /// Texels per screen pixel the atlases guarantee at their node's distance.
    #[arg(long, default_value_t = 1.0)]
    pub texel_per_pixel: f32,
    /// Screen height the distances are computed for, pixels (the flythrough rescales
    /// them for its own).
    #[arg(long, default_value_t = 1080)]
    pub screen_height: u32,
    /// The leaves' distance `d_min`, metres: nearer than this, original textures are drawn.
    /// Default: the scene's diagonal / 150 (the paper's Berlin model used / 151).
    #[arg(long)]
    pub min_distance: Option<f32>,
    /// How leaves' distances are set: `paper` (default: `d_min` for every leaf, as Buchholz
    /// & Döllner; where an original is coarser than `d_min` needs, the ancestors of its leaf
    /// magnify it) or `full-density` (where the leaf's atlas has every texel the view needs:
    /// no ancestor shows less than the originals, at the cost of drawing and paging more
    /// nodes; see docs/ATLAS_TREE.md for both measured).
    #[arg(long, value_enum, default_value_t = LeafDistances::Paper)]
    pub distances: LeafDistances,
    /// Memory for atlases composed but not yet written, MB (at least one atlas is
    /// composed at a time, whatever this says).
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u64).range(1..=1_048_576))]
    pub buffer_mb: u64,
    /// Do not print progress and the summary.
    #[arg(long)]
    pub quiet: bool,
}

/// `--distances`: how a leaf's `min_distance` is set.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LeafDistances {
    /// Where the leaf's atlas has every texel the view needs.
    FullDensity,
    /// `d_min`, as the paper.
    Paper,
}

/// The flythrough's vertical field of view, which the distances assume.
pub const FOV_Y_DEGREES: f32 = 60.0;
/// Texels of border around each texture's area in an atlas (keeps neighbours apart in the
/// coarser levels; one BC1 block).
const BORDER: u32 = 4;
/// Depth at which splitting stops whatever fits, for `extent`² atlases: a vertex's f32
/// root-atlas coordinates, scaled by `2^depth` for its node, must still place it within a
/// quarter texel (`2^(depth − 24) · extent <= 1/4`); never beyond 16.
fn max_depth(extent: u32) -> u32 {
    22u32.saturating_sub(extent.trailing_zeros()).min(16)
}

/// One triangle of the input.
#[derive(Clone, Copy, Debug)]
struct Triangle {
    /// Scene vertex indices.
    vertices: [u32; 3],
    texture: u32,
    centre: [f32; 2],
    area: f32,
    /// World metres of one texture repetition along u and v (§5.2.1).
    repeat_m: Option<(f64, f64)>,
}

/// Where one texture's area lies in a leaf atlas.
#[derive(Clone, Copy, Debug)]
struct Area {
    texture: u32,
    /// Texture-coordinate range the area covers (before the border).
    uv_min: [f32; 2],
    uv_max: [f32; 2],
    /// Texels the node's triangles need at `d_min` (u, v), before the caps: the original's
    /// own texels and the atlas's.
    needed: [f64; 2],
    /// Inner size in texels (without the border), and where the whole area starts.
    width: u32,
    height: u32,
    x: u32,
    y: u32,
}

/// A node while building.
struct BuildNode {
    triangles: Vec<u32>,
    parent: u32,
    level: u32,
    /// Offset of the node's square in the root atlas (units of the root atlas).
    offset: [f64; 2],
    children: Vec<u32>,
    /// Where each child sits: quadrant column and row.
    quadrant: [u32; 2],
    areas: Vec<Area>,
    bounds: Aabb,
}

/// What a build did.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub struct TreeSummary {
    pub nodes: u32,
    pub leaves: u32,
    pub depth: u32,
    pub triangles: u64,
    pub leaf_min_distance_m: f32,
    pub root_min_distance_m: f32,
    /// Leaves whose areas had to be scaled down to fit (magnified at `d_min`).
    pub leaves_scaled_down: u32,
    pub seconds: f64,
}

/// Runs `citystream atlas-tree`.
pub fn run(args: &AtlasTreeArgs) -> Result<()> {
    let summary = build(args)?;
    if !args.quiet {
        print_stdout(&format!(
            "atlas-tree: {} nodes ({} leaves, depth {}), {} triangles, atlases {}x{}, d_min {:.1} m, root distance {:.1} m{}; {:.1} s\n",
            summary.nodes,
            summary.leaves,
            summary.depth,
            summary.triangles,
            args.atlas_extent,
            args.atlas_extent,
            summary.leaf_min_distance_m,
            summary.root_min_distance_m,
            if summary.leaves_scaled_down > 0 {
                format!(
                    "; {} leaves scaled down to fit (magnified nearer than their distance)",
                    summary.leaves_scaled_down
                )
            } else {
                String::new()
            },
            summary.seconds
        ))?;
    }
    Ok(())
}

/// Builds the tree `args` describe; returns what it did.
pub fn build(args: &AtlasTreeArgs) -> Result<TreeSummary> {
    let start = Instant::now();
    let extent = args.atlas_extent;
    if !extent.is_power_of_two() || !(64..=8192).contains(&extent) {
        bail!("--atlas-extent {extent} must be a power of two from 64 to 8192");
    }
    if !(args.texel_per_pixel.is_finite() && args.texel_per_pixel > 0.0 && args.texel_per_pixel <= 16.0) {
        bail!("--texel-per-pixel {} must be in (0, 16]", args.texel_per_pixel);
    }
    if !(1..=16384).contains(&args.screen_height) {
        bail!("--screen-height {} must be 1 to 16384 pixels", args.screen_height);
    }
    let dataset = Dataset::open(&args.dataset).with_context(|| format!("opening {}", args.dataset.display()))?;
    let scene = &dataset.scene;
    if scene.meshes.is_empty() {
        bail!("{} has no meshes: nothing to build a tree of", args.dataset.display());
    }
    // The tree merges triangles of many meshes into one frame: the scene's.
    if !scene.local_origins.is_empty() {
        bail!(
            "{} has meshes at {} local origins (a scene too large for one f32 frame); atlas trees are built of scenes in one frame",
            args.dataset.display(),
            scene.local_origins.len()
        );
    }
    let diagonal = {
        let b = &scene.bounds;
        (0..3)
            .map(|a| f64::from(b.max[a] - b.min[a]).powi(2))
            .sum::<f64>()
            .sqrt() as f32
    };
    let d_min = match args.min_distance {
        Some(d) if d.is_finite() && d > 0.0 => d,
        Some(d) => bail!("--min-distance {d} must be a positive number of metres"),
        None => (diagonal / 150.0).max(1.0),
    };
    let params = TreeParams {
        atlas_extent: extent,
        screen_height: args.screen_height,
        fov_y: FOV_Y_DEGREES.to_radians(),
        texel_per_pixel: args.texel_per_pixel,
        leaf_min_distance: d_min,
    };
    // Texels per metre a surface needs at d_min.
    let needed_per_metre =
        texels_per_metre_at_unit_distance(params.screen_height as f32, params.fov_y, params.texel_per_pixel)
            / f64::from(d_min);

    let triangles = collect_triangles(scene)?;
    let infos = dataset.textures.textures();

    // 1. Top-down, breadth first (children contiguous, after their parent).
    let mut nodes: Vec<BuildNode> = vec![BuildNode {
        triangles: (0..triangles.len() as u32).collect(),
        parent: NO_PARENT,
        level: 0,
        offset: [0.0, 0.0],
        children: Vec::new(),
        quadrant: [0, 0],
        areas: Vec::new(),
        bounds: scene.bounds,
    }];
    let mut scaled_down = 0u32;
    let mut next = 0usize;
    while next < nodes.len() {
        let index = next;
        next += 1;
        let level = nodes[index].level;
        let mut areas = required_areas(
            &nodes[index].triangles,
            &triangles,
            scene,
            infos,
            needed_per_metre,
            extent,
        );
        if pack(&mut areas, extent) {
            nodes[index].areas = areas;
            continue;
        }
        let groups = if level < max_depth(extent) {
            split(&nodes[index].triangles, &triangles)
        } else {
            Vec::new()
        };
        if groups.iter().filter(|(_, g)| !g.is_empty()).count() < 2 {
            // Cannot split: shrink every area until they fit.
            let mut factor = 0.9f64;
            loop {
                let mut shrunk = areas.clone();
                for a in &mut shrunk {
                    a.width = round_up4(((f64::from(a.width) * factor) as u32).max(4));
                    a.height = round_up4(((f64::from(a.height) * factor) as u32).max(4));
                }
                if pack(&mut shrunk, extent) {
                    nodes[index].areas = shrunk;
                    break;
                }
                if factor < 1e-3 {
                    bail!(
                        "node {index}: {} textures do not fit a {extent}x{extent} atlas even at 4x4 texels each; use a larger --atlas-extent",
                        areas.len()
                    );
                }
                factor *= 0.9;
            }
            scaled_down += 1;
            continue;
        }
        let parent_offset = nodes[index].offset;
        let child_size = 1.0 / f64::from(1u32 << (level + 1));
        for (quadrant, group) in groups.into_iter().filter(|(_, g)| !g.is_empty()) {
            let child = nodes.len() as u32;
            nodes[index].children.push(child);
            let bounds = triangle_bounds(&group, &triangles, scene);
            nodes.push(BuildNode {
                triangles: group,
                parent: index as u32,
                level: level + 1,
                offset: [
                    parent_offset[0] + f64::from(quadrant[0]) * child_size,
                    parent_offset[1] + f64::from(quadrant[1]) * child_size,
                ],
                children: Vec::new(),
                quadrant,
                areas: Vec::new(),
                bounds,
            });
        }
        // Inner nodes keep no triangles: their leaves do.
        nodes[index].triangles = Vec::new();
        if !args.quiet && nodes.len().is_multiple_of(64) {
            eprintln!(
                "atlas-tree: {} nodes so far ({:.0} s)",
                nodes.len(),
                start.elapsed().as_secs_f64()
            );
        }
    }
    let leaf_count = nodes.iter().filter(|n| n.children.is_empty()).count();
    if !args.quiet {
        eprintln!(
            "atlas-tree: {} nodes ({leaf_count} leaves); composing atlases ({:.1} s)",
            nodes.len(),
            start.elapsed().as_secs_f64()
        );
    }

    // 2–3. Atlases in post-order (children before their parent), so only the children
    // awaiting their parent are held (half size: all a parent needs of them), and each
    // atlas is written as soon as it is encoded: memory stays bounded by the depth and the
    // batch, whatever the city's size. Texture ids follow the writing order.
    let format = atlas_format(infos);
    let levels = extent.trailing_zeros() + 1;
    let mut writer = DatasetWriter::create(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let mut atlas_id = vec![0u32; nodes.len()];
    let mut min_distance = vec![d_min; nodes.len()];
    let mut halves: BTreeMap<usize, Vec<u8>> = BTreeMap::new();
    let order = post_order(&nodes);
    // A batch's RGBA atlases and their chains fit --buffer-mb; one at least.
    let per_atlas = u64::from(extent) * u64::from(extent) * 4 * 2;
    let batch = ((args.buffer_mb << 20) / per_atlas).clamp(1, rayon::current_num_threads() as u64 * 8) as usize;
    for (done, chunk) in order.chunks(batch).enumerate() {
        // Leaves in parallel; inner nodes in order (their children are earlier).
        let leaves: Vec<Result<Vec<u8>>> = chunk
            .par_iter()
            .map(|&i| {
                if nodes[i].children.is_empty() {
                    compose_leaf(&dataset, &nodes[i].areas, extent)
                } else {
                    Ok(Vec::new())
                }
            })
            .collect();
        let mut composed: Vec<Vec<u8>> = Vec::with_capacity(chunk.len());
        for (&i, leaf) in chunk.iter().zip(leaves) {
            let rgba = if nodes[i].children.is_empty() {
                min_distance[i] = match args.distances {
                    LeafDistances::FullDensity => full_density_distance(d_min, &nodes[i].areas),
                    LeafDistances::Paper => d_min,
                };
                leaf?
            } else {
                min_distance[i] = 2.0
                    * nodes[i]
                        .children
                        .iter()
                        .map(|&c| min_distance[c as usize])
                        .fold(0.0, f32::max);
                let children: Vec<([u32; 2], Vec<u8>)> = nodes[i]
                    .children
                    .iter()
                    .map(|&c| {
                        let half = halves
                            .remove(&(c as usize))
                            .context("a child's atlas was not composed")?;
                        Ok((nodes[c as usize].quadrant, half))
                    })
                    .collect::<Result<_>>()?;
                compose_inner(&children, extent)
            };
            if nodes[i].parent != NO_PARENT {
                halves.insert(i, downsample(&rgba, extent as usize, extent as usize).0);
            }
            composed.push(rgba);
        }
        let chains: Vec<(Vec<u8>, [u8; 4])> = composed
            .par_iter()
            .map(|rgba| encode_chain(rgba, extent, format))
            .collect();
        for (&i, (chain, mean)) in chunk.iter().zip(chains) {
            atlas_id[i] = writer.add_texture(format, extent, extent, levels, &chain, mean)?;
        }
        let written = (done * batch + chunk.len()).min(order.len());
        if !args.quiet && (written == order.len() || (done + 1).is_multiple_of(8)) {
            eprintln!(
                "atlas-tree: {written}/{} atlases written ({:.1} s)",
                order.len(),
                start.elapsed().as_secs_f64()
            );
        }
    }

    // 4. The originals after the atlases; the leaves' meshes, one per (leaf, texture), with
    // root-atlas coordinates per vertex.
    let original_base = nodes.len() as u32;
    let mut buf = Vec::new();
    for t in 0..infos.len() as u32 {
        crate::atlas::copy_texture(&dataset, t, &mut writer, &mut buf)?;
    }
    let mut out_scene = Scene {
        crs: scene.crs.clone(),
        ..Scene::new(scene.origin)
    };
    let mut atlas_uvs: Vec<[f32; 2]> = Vec::new();
    let mut tree_nodes: Vec<TreeNode> = Vec::with_capacity(nodes.len());
    for (i, node) in nodes.iter().enumerate() {
        let first_mesh = out_scene.meshes.len() as u32;
        if node.children.is_empty() {
            let by_texture = node
                .areas
                .iter()
                .map(|a| (a.texture, *a))
                .collect::<BTreeMap<u32, Area>>();
            let mut per_texture: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
            for &t in &node.triangles {
                per_texture.entry(triangles[t as usize].texture).or_default().push(t);
            }
            let scale = f64::from(1u32 << node.level);
            for (texture, group) in per_texture {
                let area = by_texture.get(&texture).context("a texture without an atlas area")?;
                let mut remap: BTreeMap<u32, u32> = BTreeMap::new();
                let (mut positions, mut normals, mut uvs, mut indices) =
                    (Vec::new(), Vec::new(), Vec::new(), Vec::new());
                for &t in &group {
                    for &v in &triangles[t as usize].vertices {
                        let local = *remap.entry(v).or_insert_with(|| {
                            let uv = scene.uvs[v as usize];
                            positions.push(scene.positions[v as usize]);
                            normals.push(scene.normals[v as usize]);
                            uvs.push(uv);
                            let leaf = leaf_uv(area, uv, extent);
                            atlas_uvs.push([
                                (node.offset[0] + f64::from(leaf[0]) / scale) as f32,
                                (node.offset[1] + f64::from(leaf[1]) / scale) as f32,
                            ]);
                            (positions.len() - 1) as u32
                        });
                        indices.push(local);
                    }
                }
                out_scene.push_mesh(original_base + texture, &positions, &normals, &uvs, &indices)?;
            }
        }
        let mesh_count = out_scene.meshes.len() as u32 - first_mesh;
        let scale = (1u64 << node.level) as f32;
        tree_nodes.push(TreeNode {
            bounds: node.bounds,
            min_distance: min_distance[i],
            parent: node.parent,
            first_child: node.children.first().copied().unwrap_or(0),
            child_count: node.children.len() as u32,
            atlas: atlas_id[i],
            uv_scale: scale,
            uv_offset: [
                (node.offset[0] * f64::from(scale)) as f32,
                (node.offset[1] * f64::from(scale)) as f32,
            ],
            first_mesh: if mesh_count > 0 { first_mesh } else { 0 },
            mesh_count,
        });
    }
    writer
        .finish(&out_scene)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let tree = AtlasTree {
        params,
        nodes: tree_nodes,
        atlas_uvs,
    };
    let written = Dataset::open(&args.out).with_context(|| format!("reopening {}", args.out.display()))?;
    let path = written.files().path(TREE_FILE);
    write_atomically(&path, &tree.encode(written.files().write_id()))?;
    // Read back through the checks every reader applies.
    let tree = AtlasTree::open(&written).with_context(|| format!("checking {}", path.display()))?;
    Ok(TreeSummary {
        nodes: tree.nodes.len() as u32,
        leaves: leaf_count as u32,
        depth: tree.depth(),
        triangles: triangles.len() as u64,
        leaf_min_distance_m: d_min,
        root_min_distance_m: tree.nodes[0].min_distance,
        leaves_scaled_down: scaled_down,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The atlas tree of `dataset`, if it is one (its write directory holds `atlas-tree.bin`,
/// locally or remotely), checked against it.
pub fn open_if_tree(dataset: &Dataset) -> Result<Option<AtlasTree>> {
    let path = dataset.files().path(TREE_FILE);
    AtlasTree::open_if_any(dataset).with_context(|| format!("checking {}", path.display()))
}

/// The atlas tree of `dataset` (opened from `location`), or an error saying it is none
/// and how to build one: for commands that need a tree (`flythrough --strategy atlas-tree`,
/// `bench --scenario strategies`).
pub fn open_tree(dataset: &Dataset, location: &std::path::Path) -> Result<AtlasTree> {
    match open_if_tree(dataset)? {
        Some(tree) => Ok(tree),
        None => bail!(
            "{} is not a texture-atlas tree (no {TREE_FILE}); build one with `citystream atlas-tree {} --out DIR` \
             and pass DIR to --dataset",
            location.display(),
            location.display()
        ),
    }
}

/// What `info` reports of a tree.
#[derive(Debug, Clone, serde::Serialize)]
pub struct TreeInfo {
    pub nodes: u32,
    pub leaves: u32,
    pub depth: u32,
    pub atlas_extent: u32,
    pub screen_height: u32,
    pub texel_per_pixel: f32,
    pub leaf_min_distance_m: f32,
    pub root_min_distance_m: f32,
}

impl TreeInfo {
    /// The totals of `tree`.
    pub fn of(tree: &AtlasTree) -> Self {
        Self {
            nodes: tree.nodes.len() as u32,
            leaves: tree.nodes.iter().filter(|n| n.is_leaf()).count() as u32,
            depth: tree.depth(),
            atlas_extent: tree.params.atlas_extent,
            screen_height: tree.params.screen_height,
            texel_per_pixel: tree.params.texel_per_pixel,
            leaf_min_distance_m: tree.params.leaf_min_distance,
            root_min_distance_m: tree.nodes.first().map_or(0.0, |n| n.min_distance),
        }
    }
}

/// Every triangle of the scene, with what the build needs of it.
fn collect_triangles(scene: &Scene) -> Result<Vec<Triangle>> {
    let mut out = Vec::with_capacity(scene.triangle_count() as usize);
    for mesh in &scene.meshes {
        let indices = &scene.indices[mesh.first_index as usize..(mesh.first_index + mesh.index_count) as usize];
        for tri in indices.chunks_exact(3) {
            let vertices = [0, 1, 2].map(|k| mesh.first_vertex + tri[k]);
            let p = vertices.map(|v| scene.positions[v as usize]);
            let uv = vertices.map(|v| scene.uvs[v as usize]);
            let e1 = [0, 1, 2].map(|a| f64::from(p[1][a] - p[0][a]));
            let e2 = [0, 1, 2].map(|a| f64::from(p[2][a] - p[0][a]));
            let cross = [
                e1[1] * e2[2] - e1[2] * e2[1],
                e1[2] * e2[0] - e1[0] * e2[2],
                e1[0] * e2[1] - e1[1] * e2[0],
            ];
            let area = 0.5 * (cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]).sqrt();
            out.push(Triangle {
                vertices,
                texture: mesh.texture,
                centre: [(p[0][0] + p[1][0] + p[2][0]) / 3.0, (p[0][2] + p[1][2] + p[2][2]) / 3.0],
                area: area as f32,
                repeat_m: world_length_of_texture_axes(p, uv),
            });
        }
    }
    if out.len() > u32::MAX as usize {
        bail!("more than 2^32 - 1 triangles");
    }
    Ok(out)
}

/// A leaf's `min_distance`: the distance from which its atlas has every texel the view
/// needs, `d_min` times the largest shortfall of an area (capped by its original's own
/// texels, or scaled down to fit). Nearer, the originals are drawn, so a leaf atlas never
/// shows less than they would; and since each level up halves the texels and doubles the
/// distance, no ancestor does either.
fn full_density_distance(d_min: f32, areas: &[Area]) -> f32 {
    let shortfall = areas
        .iter()
        .flat_map(|a| {
            [
                a.needed[0] / f64::from(a.width.max(1)),
                a.needed[1] / f64::from(a.height.max(1)),
            ]
        })
        .fold(1.0f64, f64::max);
    (f64::from(d_min) * shortfall) as f32
}

fn round_up4(v: u32) -> u32 {
    v.div_ceil(4) * 4
}

/// What a node's triangles need of one texture: texels per repetition (u, v), and the
/// texture-coordinate range they use (min, max).
type TextureNeeds = ([f64; 2], [f32; 2], [f32; 2]);

/// §5.2: each texture's area in a node's atlas (unplaced).
fn required_areas(
    members: &[u32],
    triangles: &[Triangle],
    scene: &Scene,
    infos: &[citystream_dataset::TextureInfo],
    needed_per_metre: f64,
    extent: u32,
) -> Vec<Area> {
    // texture -> (texels per repetition u, v; uv range)
    let mut by_texture: BTreeMap<u32, TextureNeeds> = BTreeMap::new();
    for &t in members {
        let tri = &triangles[t as usize];
        let entry = by_texture
            .entry(tri.texture)
            .or_insert(([1.0, 1.0], [f32::INFINITY; 2], [f32::NEG_INFINITY; 2]));
        if let Some((su, sv)) = tri.repeat_m {
            entry.0[0] = entry.0[0].max(su * needed_per_metre);
            entry.0[1] = entry.0[1].max(sv * needed_per_metre);
        }
        for v in tri.vertices {
            let uv = scene.uvs[v as usize];
            for (a, c) in uv.into_iter().enumerate() {
                entry.1[a] = entry.1[a].min(c);
                entry.2[a] = entry.2[a].max(c);
            }
        }
    }
    by_texture
        .into_iter()
        .map(|(texture, (per_repeat, uv_min, uv_max))| {
            let info = &infos[texture as usize];
            let own = [f64::from(info.width()), f64::from(info.height())];
            let range = [0, 1].map(|a| f64::from((uv_max[a] - uv_min[a]).max(0.0)));
            let size = [0, 1].map(|a| {
                // Never finer than the texture itself, never more than the atlas holds.
                let texels = (per_repeat[a].min(own[a]) * range[a]).ceil().max(1.0);
                round_up4((texels as u32).min(extent - 2 * BORDER))
            });
            Area {
                texture,
                uv_min,
                uv_max,
                needed: [0, 1].map(|a| (per_repeat[a] * range[a]).max(1.0)),
                width: size[0],
                height: size[1],
                x: 0,
                y: 0,
            }
        })
        .collect()
}

/// Shelf packing of the areas (with their borders) into one `extent²` atlas, tallest first;
/// false if they do not fit.
fn pack(areas: &mut [Area], extent: u32) -> bool {
    let mut order: Vec<usize> = (0..areas.len()).collect();
    order.sort_by_key(|&i| (std::cmp::Reverse(areas[i].height), std::cmp::Reverse(areas[i].width)));
    let (mut x, mut y, mut shelf) = (0u32, 0u32, 0u32);
    for i in order {
        let (w, h) = (areas[i].width + 2 * BORDER, areas[i].height + 2 * BORDER);
        if w > extent || h > extent {
            return false;
        }
        if x + w > extent {
            y += shelf;
            x = 0;
            shelf = 0;
        }
        if y + h > extent {
            return false;
        }
        areas[i].x = x;
        areas[i].y = y;
        x += w;
        shelf = shelf.max(h);
    }
    true
}

/// §5.3: four groups (x halves by area, each cut in z halves by area), with their
/// quadrant (column from x, row from z).
fn split(members: &[u32], triangles: &[Triangle]) -> Vec<([u32; 2], Vec<u32>)> {
    let halve = |mut group: Vec<u32>, axis: usize| -> (Vec<u32>, Vec<u32>) {
        group.sort_by(|&a, &b| triangles[a as usize].centre[axis].total_cmp(&triangles[b as usize].centre[axis]));
        let total: f64 = group.iter().map(|&t| f64::from(triangles[t as usize].area)).sum();
        let mut sum = 0.0;
        let mut cut = group.len();
        for (k, &t) in group.iter().enumerate() {
            let next = sum + f64::from(triangles[t as usize].area);
            // Cut where the running area comes closest to half.
            if next >= total / 2.0 {
                cut = if (next - total / 2.0) < (total / 2.0 - sum) {
                    k + 1
                } else {
                    k
                };
                break;
            }
            sum = next;
        }
        // Both sides non-empty where there are two triangles or more.
        let cut = if group.len() >= 2 {
            cut.clamp(1, group.len() - 1)
        } else {
            group.len()
        };
        let right = group.split_off(cut);
        (group, right)
    };
    let (low_x, high_x) = halve(members.to_vec(), 0);
    let (a, b) = halve(low_x, 1);
    let (c, d) = halve(high_x, 1);
    vec![([0, 0], a), ([0, 1], b), ([1, 0], c), ([1, 1], d)]
}

fn triangle_bounds(members: &[u32], triangles: &[Triangle], scene: &Scene) -> Aabb {
    let mut b = Aabb::EMPTY;
    for &t in members {
        for v in triangles[t as usize].vertices {
            for (a, c) in scene.positions[v as usize].into_iter().enumerate() {
                b.min[a] = b.min[a].min(c);
                b.max[a] = b.max[a].max(c);
            }
        }
    }
    b
}

/// The atlas format: the dataset's most common of BC1 / RGBA8.
fn atlas_format(infos: &[citystream_dataset::TextureInfo]) -> TextureFormat {
    let bc1 = infos.iter().filter(|t| t.format() == TextureFormat::Bc1).count();
    if bc1 * 2 >= infos.len() {
        TextureFormat::Bc1
    } else {
        TextureFormat::Rgba8
    }
}

/// A vertex's coordinates in its leaf's atlas (0..1).
fn leaf_uv(area: &Area, uv: [f32; 2], extent: u32) -> [f32; 2] {
    let inner = [area.width as f32, area.height as f32];
    let origin = [(area.x + BORDER) as f32, (area.y + BORDER) as f32];
    [0, 1].map(|a| {
        let range = (area.uv_max[a] - area.uv_min[a]).max(f32::MIN_POSITIVE);
        (origin[a] + (uv[a] - area.uv_min[a]) / range * inner[a]) / extent as f32
    })
}

/// A leaf's atlas, RGBA: each area sampled from its texture (repeating), borders
/// continuing the texture, empty space the mean colour of the areas.
fn compose_leaf(dataset: &Dataset, areas: &[Area], extent: u32) -> Result<Vec<u8>> {
    let side = extent as usize;
    let mut colours = Vec::new();
    let mut out = Vec::new();
    let mut buf = Vec::new();
    let mut images: Vec<(usize, Vec<u8>, u32, u32)> = Vec::new();
    for (k, area) in areas.iter().enumerate() {
        let info = dataset.textures.info(area.texture)?;
        // The coarsest level still at least as fine as the area needs.
        let range = [0, 1].map(|a| f64::from((area.uv_max[a] - area.uv_min[a]).max(1e-6)));
        let needed = [f64::from(area.width) / range[0], f64::from(area.height) / range[1]];
        let mut level = 0;
        while level + 1 < info.mip_count() {
            let (w, h) = info.mip_extent(level + 1);
            if f64::from(w) < needed[0] || f64::from(h) < needed[1] {
                break;
            }
            level += 1;
        }
        dataset.textures.read_mip(area.texture, level, &mut buf)?;
        let (w, h) = info.mip_extent(level);
        let rgba = decode_level(info.format(), &buf, w, h);
        colours.push(mean_colour(&rgba));
        images.push((k, rgba, w, h));
    }
    let mean = if colours.is_empty() {
        [128, 128, 128, 255]
    } else {
        [0, 1, 2, 3].map(|c| (colours.iter().map(|col| u32::from(col[c])).sum::<u32>() / colours.len() as u32) as u8)
    };
    out.resize(side * side * 4, 0);
    for texel in out.chunks_exact_mut(4) {
        texel.copy_from_slice(&mean);
    }
    for (k, rgba, w, h) in images {
        let area = &areas[k];
        let (inner_w, inner_h) = (area.width as f32, area.height as f32);
        let (ox, oy) = (area.x + BORDER, area.y + BORDER);
        for y in area.y..area.y + area.height + 2 * BORDER {
            for x in area.x..area.x + area.width + 2 * BORDER {
                // Texture coordinates continue linearly into the border.
                let u = area.uv_min[0] + ((x as f32 + 0.5 - ox as f32) / inner_w) * (area.uv_max[0] - area.uv_min[0]);
                let v = area.uv_min[1] + ((y as f32 + 0.5 - oy as f32) / inner_h) * (area.uv_max[1] - area.uv_min[1]);
                let texel = bilinear_repeat(&rgba, w, h, u, v);
                let at = (y as usize * side + x as usize) * 4;
                out[at..at + 4].copy_from_slice(&texel);
            }
        }
    }
    Ok(out)
}

/// Bilinear sample of an RGBA image at `(u, v)`, repeating.
fn bilinear_repeat(rgba: &[u8], w: u32, h: u32, u: f32, v: f32) -> [u8; 4] {
    let (fx, fy) = (u * w as f32 - 0.5, v * h as f32 - 0.5);
    let (x0, y0) = (fx.floor(), fy.floor());
    let (tx, ty) = (fx - x0, fy - y0);
    let wrap = |i: f32, n: u32| (i as i64).rem_euclid(i64::from(n)) as usize;
    let texel = |x: f32, y: f32| {
        let at = (wrap(y, h) * w as usize + wrap(x, w)) * 4;
        [0, 1, 2, 3].map(|c| f32::from(rgba[at + c]))
    };
    let (a, b, c, d) = (
        texel(x0, y0),
        texel(x0 + 1.0, y0),
        texel(x0, y0 + 1.0),
        texel(x0 + 1.0, y0 + 1.0),
    );
    [0, 1, 2, 3].map(|k| {
        let top = a[k] + (b[k] - a[k]) * tx;
        let bottom = c[k] + (d[k] - c[k]) * tx;
        (top + (bottom - top) * ty).round().clamp(0.0, 255.0) as u8
    })
}

/// An inner node's atlas: its children's atlases at half size (`(quadrant, image)`),
/// side by side; empty quadrants the children's mean colour.
fn compose_inner(children: &[([u32; 2], Vec<u8>)], extent: u32) -> Vec<u8> {
    let side = extent as usize;
    let half = side / 2;
    let mean = {
        let colours: Vec<[u8; 4]> = children.iter().map(|(_, img)| mean_colour(img)).collect();
        [0, 1, 2, 3]
            .map(|c| (colours.iter().map(|col| u32::from(col[c])).sum::<u32>() / colours.len().max(1) as u32) as u8)
    };
    let mut combined = vec![0u8; side * side * 4];
    for texel in combined.chunks_exact_mut(4) {
        texel.copy_from_slice(&mean);
    }
    for (quadrant, img) in children {
        let (qx, qy) = (quadrant[0] as usize * half, quadrant[1] as usize * half);
        for row in 0..half {
            let dst = ((qy + row) * side + qx) * 4;
            combined[dst..dst + half * 4].copy_from_slice(&img[row * half * 4..(row + 1) * half * 4]);
        }
    }
    combined
}

/// Node indices with every node after its children (depth first).
fn post_order(nodes: &[BuildNode]) -> Vec<usize> {
    let mut out = Vec::with_capacity(nodes.len());
    let mut stack = vec![(0usize, false)];
    while let Some((n, expanded)) = stack.pop() {
        if expanded || nodes[n].children.is_empty() {
            out.push(n);
        } else {
            stack.push((n, true));
            stack.extend(nodes[n].children.iter().rev().map(|&c| (c as usize, false)));
        }
    }
    out
}

/// A full mip chain of an RGBA atlas in `format`, and its mean colour.
fn encode_chain(rgba: &[u8], extent: u32, format: TextureFormat) -> (Vec<u8>, [u8; 4]) {
    let mean = mean_colour(rgba);
    let mut chain = Vec::new();
    let mut level = rgba.to_vec();
    let mut side = extent as usize;
    loop {
        match format {
            TextureFormat::Bc1 => {
                let start = chain.len();
                chain.resize(start + format.mip_bytes(side as u32, side as u32) as usize, 0);
                let params = texpresso::Params {
                    algorithm: texpresso::Algorithm::RangeFit,
                    ..Default::default()
                };
                texpresso::Format::Bc1.compress(&level, side, side, params, &mut chain[start..]);
            }
            _ => chain.extend_from_slice(&level),
        }
        if side == 1 {
            break;
        }
        level = downsample(&level, side, side).0;
        side /= 2;
    }
    (chain, mean)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atlas_tree_shelf_packing_fits_or_refuses() {
        let area = |w, h| Area {
            texture: 0,
            uv_min: [0.0; 2],
            uv_max: [1.0; 2],
            needed: [f64::from(w), f64::from(h)],
            width: w,
            height: h,
            x: 0,
            y: 0,
        };
        // Full density from d_min when every area has what it needs; a quarter of the
        // texels along u moves it four times as far.
        assert_eq!(full_density_distance(10.0, &[area(24, 24)]), 10.0);
        let short = Area {
            needed: [96.0, 24.0],
            ..area(24, 24)
        };
        assert_eq!(full_density_distance(10.0, &[area(24, 24), short]), 40.0);
        // Four 24x24 areas (32x32 with borders) fill 64x64 exactly; a fifth does not fit.
        let mut four = vec![area(24, 24); 4];
        assert!(pack(&mut four, 64));
        let mut places: Vec<(u32, u32)> = four.iter().map(|a| (a.x, a.y)).collect();
        places.sort_unstable();
        assert_eq!(places, vec![(0, 0), (0, 32), (32, 0), (32, 32)]);
        let mut five = vec![area(24, 24); 5];
        assert!(!pack(&mut five, 64));
        assert!(!pack(&mut [area(60, 4)], 64));
    }
}
