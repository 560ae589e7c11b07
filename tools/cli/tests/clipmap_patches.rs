//! `citystream patches`: a simulated survey cut from an image over a generated city is
//! deterministic, lies over the city, arrives within the path, reads back checked, and
//! feeds the flexible clipmap; bad input is refused clearly.

mod cli_support;

use std::path::{Path, PathBuf};

use citystream_dataset::Dataset;
use citystream_gen::patches::PatchSet;
use citystream_streaming::clipmap::{Clipmap, ClipmapOptions, Patch};
use citystream_testing::tool_tests::{gradient_in, patches_args};
use cli_support::{citystream, fresh_dir, stderr, tiny_city_at};

/// A tiny generated city and a gradient image in `name`'s own directory: what every test
/// here cuts; the directory, the city and the image.
fn tiny_city_and_image(name: &str) -> (PathBuf, PathBuf, PathBuf) {
    let dir = fresh_dir("clipmap_patches", name);
    let city = tiny_city_at(dir.join("city"));
    let image = gradient_in(&dir);
    (dir, city, image)
}

/// `citystream patches` of `image` over `city` into `out`.
fn cut(city: &Path, image: &Path, out: &Path, seed: &str) -> std::process::Output {
    citystream(&patches_args(city, image, out, seed))
}

#[test]
fn clipmap_patches_cut_a_survey_over_the_city_that_feeds_the_clipmap() {
    let (dir, city, image) = tiny_city_and_image("survey");

    let first = dir.join("first");
    let run = cut(&city, &image, &first, "7");
    assert!(run.status.success(), "patches: {}", stderr(&run));
    let set = PatchSet::open(&first).expect("the set reads back checked");
    assert_eq!(set.patches.len(), 12);
    // Deterministic: the same seed writes the same set, another seed another one.
    let again = dir.join("again");
    assert!(cut(&city, &image, &again, "7").status.success());
    let text = |d: &Path| std::fs::read_to_string(d.join("patches.json")).expect("patches.json");
    let strip = |t: String| {
        t.replace(first.to_str().unwrap_or(""), "")
            .replace(again.to_str().unwrap_or(""), "")
    };
    assert_eq!(strip(text(&first)), strip(text(&again)));
    let other = dir.join("other");
    assert!(cut(&city, &image, &other, "8").status.success());
    assert_ne!(PatchSet::open(&other).expect("other").patches, set.patches);

    // Over the city: the base layer covers its whole ground extent from the start; every
    // other patch is centred within it and arrives, in order, within the path.
    let dataset = Dataset::open(&city).expect("city");
    // Georeferenced in the city's CRS (generated cities: ETRS89 / UTM 33N), from its origin.
    assert_eq!(set.crs.as_deref(), Some("EPSG:25833"));
    assert_eq!(set.crs(), dataset.scene.crs);
    assert_eq!(set.origin, dataset.scene.origin);
    let b = dataset.scene.bounds;
    let (city_min, city_max) = (
        [f64::from(b.min[0]), f64::from(b.min[2])],
        [f64::from(b.max[0]), f64::from(b.max[2])],
    );
    let base = &set.patches[0];
    assert_eq!((base.id, base.arrival_s), (0, 0.0));
    assert!((0..2).all(|d| base.min[d] <= city_min[d] && base.max[d] >= city_max[d]));
    for pair in set.patches.windows(2) {
        assert!(pair[0].arrival_s <= pair[1].arrival_s);
    }
    for p in &set.patches[1..] {
        let centre = [0, 1].map(|d| (p.min[d] + p.max[d]) / 2.0);
        assert!(
            (0..2).all(|d| (city_min[d]..=city_max[d]).contains(&centre[d])),
            "{p:?}"
        );
        assert!((0.0..=set.duration_s).contains(&p.arrival_s));
        assert!(p.width >= 128 && p.width <= 256, "{p:?}");
        assert!(
            p.metres_per_texel < base.metres_per_texel,
            "survey patches are finer than the base"
        );
    }
    // A patch's texels come from where it lies on the source: red grows eastwards.
    let east = set.patches[1..]
        .iter()
        .max_by(|a, b| a.min[0].total_cmp(&b.min[0]))
        .expect("patches");
    let west = set.patches[1..]
        .iter()
        .min_by(|a, b| a.min[0].total_cmp(&b.min[0]))
        .expect("patches");
    let red = |p: &citystream_gen::patches::PatchRecord| {
        let image = image::open(first.join(&p.file)).expect("png").to_rgba8();
        image.get_pixel(0, image.height() / 2).0[0]
    };
    if east.min[0] > west.min[0] + 10.0 {
        assert!(red(east) > red(west), "{} <= {}", red(east), red(west));
    }

    // Into the clipmap, in arrival order: it grows finer as finer patches arrive.
    let mut clipmap = Clipmap::new(ClipmapOptions {
        origin: [0.0, 0.0],
        tile_texels: 256,
        cache_side: 4,
    })
    .expect("clipmap");
    let mut finer = 0;
    for p in &set.patches {
        let inserted = clipmap
            .insert(Patch {
                id: p.id,
                min: p.min,
                max: p.max,
                metres_per_texel: p.metres_per_texel,
                captured_s: p.arrival_s,
            })
            .expect("insert");
        finer += inserted.finer_levels_added;
    }
    assert!(finer >= 1 && clipmap.level_count() >= 2, "{clipmap:?}");

    // Replacing a set keeps nothing of the old one.
    assert!(cut(&city, &image, &first, "8").status.success());
    assert_eq!(
        PatchSet::open(&first).expect("replaced").patches,
        PatchSet::open(&other).expect("other").patches
    );
}

#[test]
fn clipmap_patches_bad_input_is_refused_clearly() {
    let (dir, city, image) = tiny_city_and_image("bad_input");
    let not_image = dir.join("notes.txt");
    std::fs::write(&not_image, "not an image").expect("write");
    let occupied = dir.join("occupied");
    std::fs::create_dir_all(&occupied).expect("dir");
    std::fs::write(occupied.join("keep.txt"), "user data").expect("write");
    let out = dir.join("out");
    let s = |p: &Path| p.to_str().expect("utf-8").to_string();
    for (args, expected) in [
        (
            vec![
                "patches",
                &s(&dir.join("missing.png")),
                "--dataset",
                &s(&city),
                "--out",
                &s(&out),
            ],
            "missing.png",
        ),
        (
            vec!["patches", &s(&not_image), "--dataset", &s(&city), "--out", &s(&out)],
            "notes.txt",
        ),
        (
            vec![
                "patches",
                &s(&image),
                "--dataset",
                &s(&dir.join("nocity")),
                "--out",
                &s(&out),
            ],
            "nocity",
        ),
        (
            vec![
                "patches",
                &s(&image),
                "--dataset",
                &s(&city),
                "--out",
                &s(&out),
                "--count",
                "0",
            ],
            "--count",
        ),
        (
            vec!["patches", &s(&image), "--dataset", &s(&city), "--out", &s(&occupied)],
            "is not a patch set",
        ),
    ] {
        let args: Vec<&str> = args.iter().map(|a| a.as_ref()).collect();
        let run = citystream(&args);
        assert!(!run.status.success(), "{args:?} succeeded");
        let text = stderr(&run);
        assert!(text.contains(expected), "{args:?}: {text}");
    }
    assert_eq!(
        std::fs::read_to_string(occupied.join("keep.txt")).expect("kept"),
        "user data"
    );
    assert!(!out.exists());

    // A set whose listing disagrees with its files is refused on open, naming the patch.
    let good = dir.join("good");
    assert!(cut(&city, &image, &good, "3").status.success());
    let json = std::fs::read_to_string(good.join("patches.json")).expect("json");
    let mut value: serde_json::Value = serde_json::from_str(&json).expect("json");
    value["patches"][2]["width"] = serde_json::json!(7);
    std::fs::write(good.join("patches.json"), value.to_string()).expect("write");
    let error = PatchSet::open(&good).expect_err("refused").to_string();
    assert!(error.contains("listed as 7x"), "{error}");
    value["version"] = serde_json::json!(99);
    std::fs::write(good.join("patches.json"), value.to_string()).expect("write");
    let error = format!("{:#}", PatchSet::open(&good).expect_err("refused"));
    assert!(error.contains("version 99"), "{error}");
}
