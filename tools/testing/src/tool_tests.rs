//! What the tools' test crates share (the `citystream` command's and the flythrough's: each
//! test file is its own crate, and their support modules are not shared between packages):
//! scratch directories, the setup script's stamp, the servers the remote tests start, and
//! the inputs both cut and fly.

use std::path::{Path, PathBuf};
use std::process::Output;

use citystream_gen::atlas_tree::{build, AtlasTreeArgs, LeafDistances, TreeSummary};

use crate::nginx::{self, Nginx};
use crate::s3_emulator::{self, S3Emulator};

/// `tmp/group/name`, removed if it exists; its parent exists, it does not (for commands
/// that must create their output themselves). `tmp` is the test crate's
/// `CARGO_TARGET_TMPDIR`.
pub fn fresh_path(tmp: &Path, group: &str, name: &str) -> PathBuf {
    let dir = tmp.join(group).join(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.parent().expect("parent")).expect("create parent");
    dir
}

/// [`fresh_path`], created empty.
pub fn fresh_dir(tmp: &Path, group: &str, name: &str) -> PathBuf {
    let dir = fresh_path(tmp, group, name);
    std::fs::create_dir_all(&dir).expect("create dir");
    dir
}

/// The command's standard error, as text.
pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Whether `tools/scripts/setup.sh` ran to the end on this machine (its stamp exists): tests of
/// what it installs (Xvfb, nginx) fail rather than skip once it has.
pub fn setup_ran() -> bool {
    let dir = std::env::var_os("CITYSTREAM_SETUP_STAMP_DIR").unwrap_or_else(|| "/var/lib/citystream".into());
    Path::new(&dir).join("setup-v6").exists()
}

/// Starts nginx serving `root`.
pub fn start_nginx(work: &Path, root: &Path) -> Nginx {
    assert!(
        nginx::binary().is_some() || !setup_ran(),
        "nginx is missing although the setup script ran: it should have installed nginx-light"
    );
    Nginx::start(work, root).expect("start nginx (`make setup` installs nginx-light)")
}

/// Where [`city_in_s3`] uploads the city.
pub const S3_CITY: &str = "s3://citystream/cities/tiny/";

/// Starts the S3 emulator in `dir` and uploads `city` to [`S3_CITY`].
pub fn city_in_s3(dir: &Path, city: &Path) -> S3Emulator {
    assert!(
        s3_emulator::binary().is_some() || !setup_ran(),
        "the S3 emulator is missing although the setup script ran: it should have installed it"
    );
    let s3 = S3Emulator::start(dir).expect("start the S3 emulator (`make setup` installs it)");
    let files = s3.upload_dir("citystream", "cities/tiny", city).expect("upload");
    assert!(files >= 6, "{files} files uploaded");
    s3
}

/// An environment's variables borrowed, as `Command::envs` and the runners take them.
pub fn env_refs<'a>(env: &'a [(&'static str, String)]) -> Vec<(&'static str, &'a str)> {
    env.iter().map(|(k, v)| (*k, v.as_str())).collect()
}

/// A 300 × 200 image whose colour encodes where a pixel is, written to `dir/source.png`:
/// what the clipmap tests cut into patches; its path.
pub fn gradient_in(dir: &Path) -> PathBuf {
    let path = dir.join("source.png");
    let image = image::RgbaImage::from_fn(300, 200, |x, y| {
        image::Rgba([(x % 256) as u8, (y % 256) as u8, 128, 255])
    });
    image.save(&path).expect("write the source image");
    path
}

/// The arguments of `citystream patches` of `image` over `city` into `out`: twelve patches
/// of at most 256 texels a side, from `seed`.
pub fn patches_args<'a>(city: &'a Path, image: &'a Path, out: &'a Path, seed: &'a str) -> [&'a str; 13] {
    [
        "patches",
        image.to_str().expect("utf-8"),
        "--dataset",
        city.to_str().expect("utf-8"),
        "--out",
        out.to_str().expect("utf-8"),
        "--count",
        "12",
        "--seed",
        seed,
        "--max-texels",
        "256",
        "--quiet",
    ]
}

/// The texture-atlas tree of `city` in `tree` (`extent`² atlases, every leaf at full
/// density), built as `citystream atlas-tree` builds it.
pub fn full_density_tree(city: &Path, tree: &Path, extent: u32) -> TreeSummary {
    build(&AtlasTreeArgs {
        dataset: city.to_path_buf(),
        out: tree.to_path_buf(),
        atlas_extent: extent,
        texel_per_pixel: 1.0,
        screen_height: 1080,
        min_distance: None,
        distances: LeafDistances::FullDensity,
        buffer_mb: 256,
        quiet: true,
    })
    .expect("build the tree")
}
