//! `citystream info`: totals of a dataset, as text or JSON.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use citystream_dataset::{Crs, Dataset, FORMAT_VERSION};
use serde::Serialize;

/// Options of `citystream info`.
#[derive(Debug, clap::Args)]
pub struct InfoArgs {
    /// Dataset directory, or its URL (`http(s)://host/path/`, `s3://bucket/prefix/`).
    pub dir: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub remote: citystream_gen::location::RemoteArgs,
}

/// Textures of one extent.
/// The origin of a local east-north-up frame a dataset's CRS names.
#[derive(Debug, Serialize)]
struct LocalFrame {
    /// Earth-centred (EPSG:4978) metres.
    ecef: [f64; 3],
    latitude_deg: f64,
    longitude_deg: f64,
    /// Above the WGS 84 ellipsoid.
    height_m: f64,
}

impl LocalFrame {
    fn of(crs: &Crs) -> Option<Self> {
        let ecef = citystream_import::tiles::local_frame_origin(crs)?;
        let g = citystream_import::tiles::geodesy::to_geodetic(ecef)?;
        Some(Self {
            ecef,
            latitude_deg: g.latitude.to_degrees(),
            longitude_deg: g.longitude.to_degrees(),
            height_m: g.height,
        })
    }
}

#[derive(Debug, Serialize)]
struct ExtentTotals {
    width: u32,
    height: u32,
    textures: u64,
    bytes: u64,
}

/// Everything `info` reports; also the JSON schema of `info --json`.
#[derive(Debug, Serialize)]
struct Info {
    dir: String,
    format_version: u32,
    meshes: u64,
    triangles: u64,
    vertices: u64,
    textures: u64,
    mips: u64,
    textures_by_extent: Vec<ExtentTotals>,
    textures_by_format: BTreeMap<String, u64>,
    bytes_by_format: BTreeMap<String, u64>,
    pack_bytes: u64,
    scene_bytes: u64,
    origin: [f64; 3],
    /// The CRS the origin is in (`EPSG:<code>` or WKT); `None`: a local frame.
    crs: Option<String>,
    /// The origin in the CRS's axes: easting, northing, height (with a CRS only).
    origin_crs: Option<[f64; 3]>,
    /// Where the CRS is a local east-north-up frame (a 3D Tiles import): its origin.
    local_frame: Option<LocalFrame>,
    bounds_min: [f32; 3],
    bounds_max: [f32; 3],
    host_bytes_per_texture: usize,
    open_seconds: f64,
    /// The texture-atlas tree, where the dataset is one (`citystream atlas-tree`).
    atlas_tree: Option<citystream_gen::atlas_tree::TreeInfo>,
    /// Where `citystream import` wrote the dataset: how many meshes and textures came from
    /// each encoding of its input (`draco`, `meshopt+quantized`, `ktx2-uastc` …).
    import_encodings: Option<citystream_import::encodings::EncodingCounts>,
}

/// Runs `citystream info`.
pub fn run(args: &InfoArgs) -> Result<()> {
    let start = Instant::now();
    let dataset = citystream_gen::location::open_dataset_with(&args.dir, &args.remote.options()?)?;
    let open_seconds = start.elapsed().as_secs_f64();
    let info = collect(args, &dataset, open_seconds)?;
    let mut text = Vec::new();
    if args.json {
        writeln!(text, "{}", serde_json::to_string_pretty(&info)?)?;
    } else {
        print_text(&mut text, &info)?;
    }
    citystream_gen::files::print_stdout(&String::from_utf8_lossy(&text))
}

fn collect(args: &InfoArgs, dataset: &Dataset, open_seconds: f64) -> Result<Info> {
    let mut by_extent: BTreeMap<(u32, u32), (u64, u64)> = BTreeMap::new();
    let mut textures_by_format = BTreeMap::new();
    let mut bytes_by_format = BTreeMap::new();
    let mut mips = 0u64;
    for t in dataset.textures.textures() {
        let bytes = t.chain_len();
        let e = by_extent.entry((t.width(), t.height())).or_default();
        e.0 += 1;
        e.1 += bytes;
        *textures_by_format.entry(t.format().name().to_string()).or_insert(0) += 1;
        *bytes_by_format.entry(t.format().name().to_string()).or_insert(0) += bytes;
        mips += u64::from(t.mip_count());
    }
    let scene = &dataset.scene;
    let scene_bytes = dataset.scene_file_len();
    Ok(Info {
        dir: args.dir.display().to_string(),
        format_version: FORMAT_VERSION,
        meshes: scene.meshes.len() as u64,
        triangles: scene.triangle_count(),
        vertices: scene.positions.len() as u64,
        textures: u64::from(dataset.textures.len()),
        mips,
        textures_by_extent: by_extent
            .into_iter()
            .map(|((width, height), (textures, bytes))| ExtentTotals {
                width,
                height,
                textures,
                bytes,
            })
            .collect(),
        textures_by_format,
        bytes_by_format,
        pack_bytes: dataset.textures.pack_len(),
        scene_bytes,
        origin: scene.origin,
        crs: scene.crs.as_ref().map(|crs| crs.to_string()),
        origin_crs: scene.crs.as_ref().map(|_| Crs::from_scene(scene.origin)),
        local_frame: scene.crs.as_ref().and_then(LocalFrame::of),
        bounds_min: scene.bounds.min,
        bounds_max: scene.bounds.max,
        host_bytes_per_texture: Dataset::metadata_bytes_per_texture(),
        open_seconds,
        atlas_tree: citystream_gen::atlas_tree::open_if_tree(dataset)?
            .as_ref()
            .map(citystream_gen::atlas_tree::TreeInfo::of),
        import_encodings: citystream_import::encodings::EncodingCounts::read(dataset)?,
    })
}

fn print_text(out: &mut impl Write, info: &Info) -> std::io::Result<()> {
    writeln!(out, "dataset {} (format version {})", info.dir, info.format_version)?;
    writeln!(out, "meshes     {:>12}", info.meshes)?;
    writeln!(out, "triangles  {:>12}", info.triangles)?;
    writeln!(out, "vertices   {:>12}", info.vertices)?;
    writeln!(out, "textures   {:>12}  ({} mips)", info.textures, info.mips)?;
    writeln!(out, "textures by extent:")?;
    for e in &info.textures_by_extent {
        writeln!(
            out,
            "  {:>5} x {:<5} {:>10} textures {:>14} bytes",
            e.width, e.height, e.textures, e.bytes
        )?;
    }
    writeln!(out, "bytes by format:")?;
    for (format, bytes) in &info.bytes_by_format {
        let count = info.textures_by_format.get(format).copied().unwrap_or(0);
        writeln!(out, "  {format:<6} {count:>10} textures {bytes:>14} bytes")?;
    }
    writeln!(out, "pack       {:>12} bytes", info.pack_bytes)?;
    if let Some(tree) = &info.atlas_tree {
        writeln!(
            out,
            "atlas tree {:>12} nodes ({} leaves, depth {}), atlases {}x{}; distances {:.1} m (leaves) to {:.1} m (root) for {} px at {} texel/px",
            tree.nodes,
            tree.leaves,
            tree.depth,
            tree.atlas_extent,
            tree.atlas_extent,
            tree.leaf_min_distance_m,
            tree.root_min_distance_m,
            tree.screen_height,
            tree.texel_per_pixel
        )?;
    }
    if let Some(encodings) = &info.import_encodings {
        writeln!(out, "imported   {}", encodings.summary())?;
    }
    writeln!(out, "scene      {:>12} bytes", info.scene_bytes)?;
    writeln!(
        out,
        "origin     ({:.3}, {:.3}, {:.3}); bounds {:?} .. {:?} (relative, metres)",
        info.origin[0], info.origin[1], info.origin[2], info.bounds_min, info.bounds_max
    )?;
    match (&info.crs, info.origin_crs) {
        (Some(crs), Some([e, n, h])) => {
            // WKT can run to kilobytes over many lines: its first line names it.
            let name = crs.lines().next().unwrap_or_default();
            let more = if crs.contains('\n') { " …" } else { "" };
            writeln!(
                out,
                "crs        {name}{more}; origin easting {e:.3} northing {n:.3} height {h:.3} (x east, y up, z south)"
            )?;
        }
        _ => writeln!(out, "crs        none (a local frame, not georeferenced)")?,
    }
    if let Some(frame) = &info.local_frame {
        writeln!(
            out,
            "frame      east-north-up at latitude {:.7}°, longitude {:.7}°, height {:.3} m (WGS 84); EPSG:4978 ({:.3}, {:.3}, {:.3})",
            frame.latitude_deg, frame.longitude_deg, frame.height_m, frame.ecef[0], frame.ecef[1], frame.ecef[2]
        )?;
    }
    writeln!(
        out,
        "opened in {:.3} s; {} host bytes of metadata per texture",
        info.open_seconds, info.host_bytes_per_texture
    )?;
    Ok(())
}
