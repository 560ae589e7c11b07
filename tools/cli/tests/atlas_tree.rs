//! `citystream atlas-tree`: trees built from a generated city cover every triangle exactly
//! once at every cut the traversal makes, hold the texel-per-pixel bound at their leaves'
//! distance, and bad input is refused clearly. (`cargo test atlas_tree` also runs the
//! streaming crate's traversal, paging-order and distance tests.)

mod cli_support;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use citystream_dataset::{Dataset, Scene};
use citystream_gen::atlas_tree::TreeSummary;
use citystream_streaming::atlas_tree::{
    texels_per_metre_at_unit_distance, world_length_of_texture_axes, AtlasTree, Block, DrawWith, TreeView, TREE_FILE,
};
use citystream_testing::tool_tests::full_density_tree;
use cli_support::{citystream, citystream_into, fresh_dir, stderr, tiny_city_at};

/// A tiny generated city and its tree (`extent`² atlases), in `name`'s own directory.
fn tiny_tree(name: &str, extent: u32) -> (PathBuf, PathBuf, TreeSummary) {
    let dir = fresh_dir("atlas_tree", name);
    let city = tiny_city_at(dir.join("city"));
    let tree = dir.join("tree");
    let summary = full_density_tree(&city, &tree, extent);
    (city, tree, summary)
}

/// Every triangle as its three corner positions (bit patterns, rotated to start at the
/// smallest), counted.
fn triangles(scene: &Scene) -> BTreeMap<[[u32; 3]; 3], u32> {
    let mut out = BTreeMap::new();
    for mesh in &scene.meshes {
        let indices = &scene.indices[mesh.first_index as usize..(mesh.first_index + mesh.index_count) as usize];
        for tri in indices.chunks_exact(3) {
            let corners = [0, 1, 2].map(|k| scene.positions[(mesh.first_vertex + tri[k]) as usize].map(f32::to_bits));
            let first = (0..3).min_by_key(|&k| corners[k]).unwrap_or(0);
            *out.entry([0, 1, 2].map(|k| corners[(first + k) % 3])).or_insert(0) += 1;
        }
    }
    out
}

const EVERYWHERE: [[f32; 4]; 6] = [[0.0, 0.0, 0.0, 1.0]; 6];

#[test]
fn atlas_tree_covers_every_triangle_exactly_once_at_each_cut() {
    let (city, tree_dir, summary) = tiny_tree("cover", 128);
    let source = Dataset::open(&city).expect("city");
    let dataset = Dataset::open(&tree_dir).expect("tree dataset");
    let tree = AtlasTree::open(&dataset).expect("tree");
    assert!(summary.depth >= 3 && summary.leaves >= 16, "{summary:?}");
    // The leaves hold the city's triangles: the same ones, each once.
    assert_eq!(triangles(&dataset.scene), triangles(&source.scene));

    // Structure: children follow their parent, distances double upwards.
    for (i, node) in tree.nodes.iter().enumerate() {
        for c in node.children() {
            assert_eq!(tree.nodes[c as usize].parent, i as u32);
        }
        if !node.is_leaf() {
            let children = node
                .children()
                .map(|c| tree.nodes[c as usize].min_distance)
                .fold(0.0, f32::max);
            assert_eq!(node.min_distance, 2.0 * children, "node {i}");
        } else {
            // From d_min on, later where an original has fewer texels than d_min needs.
            assert!(node.min_distance >= tree.params.leaf_min_distance, "leaf {i}");
            assert_eq!(tree.draw_distance(i as u32), tree.params.leaf_min_distance, "leaf {i}");
        }
    }

    // Cuts from many eyes (over the city, far above, far off to the side, inside a
    // building's box), everything resident or only some: each mesh drawn exactly once.
    let b = dataset.scene.bounds;
    let centre = [0, 1, 2].map(|a| (b.min[a] + b.max[a]) / 2.0);
    let span = (b.max[0] - b.min[0]).max(b.max[2] - b.min[2]);
    let eyes = [
        [centre[0], b.max[1] + 2.0, centre[2]],
        [b.min[0], 1.7, b.min[2]],
        [centre[0], span * 4.0, centre[2]],
        [b.max[0] + span, 30.0, centre[2]],
        [centre[0] + span / 7.0, 5.0, centre[2] - span / 5.0],
    ];
    let mut atlas_draws = 0;
    let mut original_draws = 0;
    for eye in eyes {
        let view = TreeView {
            eye,
            planes: EVERYWHERE,
            screen_height: 1080.0,
            fov_y: 60f32.to_radians(),
            texel_per_pixel: 1.0,
        };
        let residencies: [&dyn Fn(Block) -> bool; 3] =
            [&|_| true, &|b| matches!(b, Block::Atlas(n) if n % 3 != 1), &|b| {
                matches!(b, Block::Atlas(0))
            }];
        for (r, resident) in residencies.iter().enumerate() {
            let cut = tree.select(&view, resident);
            let mut drawn = vec![0u32; dataset.scene.meshes.len()];
            for &(node, with) in &cut.draws {
                match with {
                    DrawWith::Originals => original_draws += 1,
                    DrawWith::Atlas(atlas) => {
                        atlas_draws += 1;
                        // The atlas drawing a node is its own or an ancestor's.
                        let mut n = node;
                        while n != atlas {
                            n = tree.nodes[n as usize].parent;
                            assert_ne!(n, u32::MAX, "atlas {atlas} is not above node {node}");
                        }
                    }
                }
                for leaf in tree.leaves_under(node) {
                    let leaf = &tree.nodes[leaf as usize];
                    for m in leaf.first_mesh..leaf.first_mesh + leaf.mesh_count {
                        drawn[m as usize] += 1;
                    }
                }
            }
            assert!(
                drawn.iter().all(|&d| d == 1),
                "eye {eye:?}, residency {r}: meshes drawn {:?} times",
                drawn.iter().filter(|&&d| d != 1).collect::<Vec<_>>()
            );
        }
    }
    // The eyes exercise both kinds of draw.
    assert!(
        atlas_draws > 0 && original_draws > 0,
        "{atlas_draws} atlas, {original_draws} original draws"
    );
}

#[test]
fn atlas_tree_leaf_atlases_hold_the_texel_per_pixel_bound_at_their_distance() {
    let (city, tree_dir, summary) = tiny_tree("bound", 256);
    assert_eq!(summary.leaves_scaled_down, 0, "{summary:?}");
    let source = Dataset::open(&city).expect("city");
    let dataset = Dataset::open(&tree_dir).expect("tree dataset");
    let tree = AtlasTree::open(&dataset).expect("tree");
    let scene = &dataset.scene;
    let p = tree.params;
    // Texels per metre a surface needs at the leaves' distance.
    let node_needed = |distance: f32| {
        texels_per_metre_at_unit_distance(p.screen_height as f32, p.fov_y, p.texel_per_pixel) / f64::from(distance)
    };
    let needed = node_needed(p.leaf_min_distance);
    let extent = p.atlas_extent as f32;
    let original_base = tree.nodes.len() as u32;
    let mut checked = 0;
    for node in tree.nodes.iter().filter(|n| n.is_leaf()) {
        for mesh in &scene.meshes[node.first_mesh as usize..(node.first_mesh + node.mesh_count) as usize] {
            let info = source.textures.info(mesh.texture - original_base).expect("original");
            let indices = &scene.indices[mesh.first_index as usize..(mesh.first_index + mesh.index_count) as usize];
            for tri in indices.chunks_exact(3) {
                let v = [0, 1, 2].map(|k| (mesh.first_vertex + tri[k]) as usize);
                let positions = v.map(|i| scene.positions[i]);
                // In the leaf's own atlas, in texels.
                let atlas = v.map(|i| {
                    let uv = tree.atlas_uvs[i];
                    [0, 1].map(|a| (uv[a] * node.uv_scale - node.uv_offset[a]) * extent)
                });
                assert!(
                    atlas.iter().flatten().all(|c| (-0.01..=extent + 0.01).contains(c)),
                    "leaf coordinates outside its atlas: {atlas:?}"
                );
                let (Some((metres_u, metres_v)), Some((repeat_u, repeat_v))) = (
                    world_length_of_texture_axes(positions, atlas),
                    world_length_of_texture_axes(positions, v.map(|i| scene.uvs[i])),
                ) else {
                    continue;
                };
                // Metres per atlas texel: at most what the distance needs, unless the
                // original texture itself has no more texels to give.
                let allowed_u = (1.0 / needed).max(repeat_u / f64::from(info.width()));
                let allowed_v = (1.0 / needed).max(repeat_v / f64::from(info.height()));
                assert!(
                    metres_u <= allowed_u * 1.001 && metres_v <= allowed_v * 1.001,
                    "{metres_u} / {metres_v} m per atlas texel, allowed {allowed_u} / {allowed_v}"
                );
                // From the leaf's own distance on, the atlas has every texel the view needs,
                // whatever the original holds (nearer, the originals are drawn).
                let at_leaf = node_needed(node.min_distance);
                assert!(
                    metres_u * at_leaf <= 1.001 && metres_v * at_leaf <= 1.001,
                    "{metres_u} / {metres_v} m per atlas texel at {} m, which needs {at_leaf} texels per metre",
                    node.min_distance
                );
                assert!(node.min_distance >= p.leaf_min_distance);
                checked += 1;
            }
        }
    }
    assert!(checked > 100, "{checked} triangles checked");
}

#[test]
fn atlas_tree_paper_distances_put_every_leaf_at_d_min_and_full_density_ones_no_nearer() {
    let (city, full_dir, full) = tiny_tree("distances", 128);
    let paper_dir = full_dir.with_file_name("paper");
    let run = citystream_into(
        "atlas-tree",
        &city,
        &paper_dir,
        &["--atlas-extent", "128", "--distances", "paper", "--quiet"],
    );
    assert!(run.status.success(), "{}", stderr(&run));
    let open = |dir: &Path| AtlasTree::open(&Dataset::open(dir).expect("dataset")).expect("tree");
    let (paper, full_tree) = (open(&paper_dir), open(&full_dir));
    // The same quadtree; only the distances differ.
    assert_eq!(paper.nodes.len(), full_tree.nodes.len());
    let d_min = paper.params.leaf_min_distance;
    for (a, b) in paper.nodes.iter().zip(&full_tree.nodes) {
        assert_eq!((a.bounds, a.parent, a.first_mesh), (b.bounds, b.parent, b.first_mesh));
        if a.is_leaf() {
            assert_eq!(a.min_distance, d_min);
            assert!(b.min_distance >= d_min);
        }
        assert!(b.min_distance >= a.min_distance);
    }
    // The tiny city's originals fall short of d_min somewhere, so the two differ.
    assert!(full.root_min_distance_m > paper.nodes[0].min_distance, "{full:?}");
}

#[test]
fn atlas_tree_bad_input_is_refused_clearly() {
    let (_city, tree_dir, _) = tiny_tree("bad_input", 128);
    let dir = tree_dir.parent().expect("parent").to_path_buf();
    let out = dir.join("never");
    let out_arg = out.to_str().expect("utf-8");
    let city = dir.join("city");
    let city_arg = city.to_str().expect("utf-8");
    for (args, expected) in [
        (
            vec!["atlas-tree", city_arg, "--out", out_arg, "--atlas-extent", "100"],
            "--atlas-extent",
        ),
        (
            vec!["atlas-tree", city_arg, "--out", out_arg, "--texel-per-pixel", "0"],
            "--texel-per-pixel",
        ),
        (
            vec!["atlas-tree", city_arg, "--out", out_arg, "--min-distance", "0"],
            "--min-distance",
        ),
        (
            vec!["atlas-tree", "/nonexistent/city", "--out", out_arg],
            "/nonexistent/city",
        ),
    ] {
        let run = citystream(&args);
        assert!(!run.status.success(), "{args:?} succeeded");
        let text = stderr(&run);
        assert!(
            text.contains(expected) && !text.contains("panicked"),
            "{args:?}: {text}"
        );
    }
    assert!(!out.exists(), "a refused build left {}", out.display());

    // A damaged or truncated tree file: info and verify name it.
    let file = tree_file(&tree_dir);
    let good = std::fs::read(&file).expect("tree file");
    let mut flipped = good.clone();
    flipped[100] ^= 0x40;
    for (damage, what) in [(flipped, "checksum"), (good[..good.len() - 9].to_vec(), "")] {
        std::fs::write(&file, &damage).expect("damage");
        for command in ["info", "verify"] {
            let run = citystream(&[command, tree_dir.to_str().expect("utf-8")]);
            assert!(!run.status.success(), "{command} accepted a damaged tree");
            let text = stderr(&run);
            assert!(
                text.contains(TREE_FILE) && text.contains(what) && !text.contains("panicked"),
                "{command}: {text}"
            );
        }
    }
    std::fs::write(&file, &good).expect("restore");

    // A file whose nodes each list the next four as children and name the one before as
    // parent passes every per-node check, but is no tree (walks over it would explode):
    // refused.
    let dataset = Dataset::open(&tree_dir).expect("dataset");
    let mut chain = AtlasTree::open(&dataset).expect("tree");
    let n = chain.nodes.len() as u32;
    let meshes = dataset.scene.meshes.len() as u32;
    for (k, node) in chain.nodes.iter_mut().enumerate() {
        let k = k as u32;
        node.parent = if k == 0 { u32::MAX } else { k - 1 };
        node.child_count = (n - 1 - k).min(4);
        node.first_child = if node.child_count > 0 { k + 1 } else { 0 };
        (node.first_mesh, node.mesh_count) = if k == n - 1 { (0, meshes) } else { (0, 0) };
    }
    let bytes = chain.encode(dataset.files().write_id());
    let error = AtlasTree::decode(&file, &bytes, &dataset).expect_err("a chain of overlapping children");
    assert!(error.to_string().contains("listed as a child"), "{error}");
    let run = citystream(&["verify", tree_dir.to_str().expect("utf-8")]);
    assert!(run.status.success(), "{}", stderr(&run));
    assert!(String::from_utf8_lossy(&run.stdout).contains("atlas tree of"));
}

/// The tree file of the dataset in `dir`.
fn tree_file(dir: &Path) -> PathBuf {
    Dataset::open(dir).expect("dataset").files().path(TREE_FILE)
}
