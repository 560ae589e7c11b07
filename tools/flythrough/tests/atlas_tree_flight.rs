//! `flythrough --strategy atlas-tree`: a tree built from a generated city flies with its
//! nodes drawn and atlases streamed, and a dataset that is no tree is refused.

mod flight_support;

use std::path::{Path, PathBuf};

use citystream_gen::atlas_tree::TreeSummary;
use citystream_testing::tool_tests::full_density_tree;
use flight_support::{fresh_dir, stderr, tiny_city};

/// A tiny generated city and its tree (`extent`² atlases), in `name`'s own directory.
fn tiny_tree(name: &str, extent: u32) -> (PathBuf, PathBuf, TreeSummary) {
    let dir = fresh_dir("atlas_tree", name);
    let city = tiny_city(&dir);
    let tree = dir.join("tree");
    let summary = full_density_tree(&city, &tree, extent);
    (city, tree, summary)
}

#[test]
fn atlas_tree_strategy_flies_the_tree_and_refuses_a_plain_dataset() {
    let (city, tree_dir, _) = tiny_tree("flythrough", 256);
    let out = tree_dir.with_file_name("flight");
    let fly = |dataset: &Path, out: &Path| {
        // Two frames in flight by default: synchronization validation too.
        std::process::Command::new(env!("CARGO_BIN_EXE_flythrough"))
            .env("CITYSTREAM_VALIDATION", "sync")
            .arg("--dataset")
            .arg(dataset)
            .args(["--strategy", "atlas-tree", "--clock", "fixed", "--frames", "90"])
            .args(["--width", "160", "--height", "96", "--psnr-interval", "30"])
            .args(["--frame-interval", "0", "--validation=true", "--out"])
            .arg(out)
            .output()
            .expect("flythrough runs")
    };
    let run = fly(&tree_dir, &out);
    assert!(run.status.success(), "{}", stderr(&run));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).expect("summary")).expect("JSON");
    assert_eq!(summary["strategy"], "atlas-tree");
    assert_eq!(summary["validation_errors"], 0);
    assert_eq!(summary["textures_failed"], 0);
    // Nodes are drawn every frame and their atlases streamed through the shared loader.
    assert!(
        summary["nodes_drawn"]["min"].as_f64().is_some_and(|n| n >= 1.0),
        "{summary}"
    );
    assert!(
        summary["draw_calls"]["mean"].as_f64().is_some_and(|n| n >= 1.0),
        "{summary}"
    );
    assert!(summary["mips_streamed"].as_u64().is_some_and(|n| n > 0), "{summary}");
    assert!(summary["atlas_tree"]["ideal_blocks"]["max"]
        .as_f64()
        .is_some_and(|n| n >= 1.0));
    // PSNR against the originals, measured on frames 0, 30 and 60.
    assert!(
        summary["psnr_db"]["mean"].as_f64().is_some_and(|p| p > 10.0),
        "{summary}"
    );

    // A dataset that is no tree is refused, naming the way to make one.
    let run = fly(&city, &tree_dir.with_file_name("no-tree"));
    assert!(!run.status.success());
    let text = stderr(&run);
    assert!(
        text.contains("is not a texture-atlas tree") && text.contains("citystream atlas-tree"),
        "{text}"
    );
}
