//! `citystream gen --preset berlin`: a city of the paper's Berlin (atlas) size, generated
//! straight into 512² atlases.
//!
//! Generating the per-mesh city first and packing it with `citystream atlas` afterwards
//! would need the textures twice on disk (about 41 GB each); here every atlas is composed
//! from its member textures as they are synthesised, with the same packing plan and the same
//! composition as `citystream atlas --atlas-extent 512` (a test checks that both give the
//! same dataset), so the only large file is the atlas pack itself.
//!
//! The write takes an hour or more, so it is resumable: a checkpoint after every batch of
//! atlases, and a rerun of the same command continues after the last one (see
//! [`DatasetWriter::create_resumable`]). The disk it needs is computed from the plan and
//! checked before any texel is synthesised.

use std::time::Instant;

use anyhow::{bail, Context, Result};
use citystream_dataset::{DatasetWriter, TextureFormat, WriteSummary};
use rayon::prelude::*;

use crate::atlas::{self, AtlasPart, AtlasPlan, Packing};
use crate::city::{free_bytes, gb, GenArgs, Progress};
use crate::layout::{self, City, LayoutParams};
use crate::texture;

/// Atlas side of the paper's Berlin (atlas) dataset.
pub const ATLAS_EXTENT: u32 = 512;
/// Grid regions atlases are grouped by, metres (as `citystream atlas`'s default).
const REGION_M: f64 = 512.0;
/// Memory for atlases composed and not yet written (as `citystream atlas`'s default).
const BUFFER_MB: u64 = 256;
/// Changes whenever the generator would write other bytes for the same arguments, so that a
/// write started by another build is not continued.
const GENERATOR_VERSION: u32 = 1;

/// What the plan says the write needs, before anything is synthesised.
#[derive(Clone, Copy, Debug)]
pub struct DiskPlan {
    pub atlases: usize,
    pub standalone: usize,
    pub pack_bytes: u64,
    pub scene_bytes: u64,
    pub metadata_bytes: u64,
}

impl DiskPlan {
    pub fn total(&self) -> u64 {
        self.pack_bytes + self.scene_bytes + self.metadata_bytes
    }
}

/// A laid-out city and its atlas plan.
struct Planned {
    city: City,
    sizes: Vec<[u32; 2]>,
    plan: AtlasPlan,
    /// Textures kept as they are (not in an atlas), in id order; they follow the atlases.
    standalone: Vec<usize>,
    disk: DiskPlan,
    format: TextureFormat,
}

fn plan(params: LayoutParams, seed: u64, format: TextureFormat) -> Result<Planned> {
    let city = layout::layout(params, seed)?;
    let sizes: Vec<[u32; 2]> = city
        .textures
        .iter()
        .map(|t| [1u32 << t.width_log2, 1u32 << t.height_log2])
        .collect();
    let eligible = sizes
        .iter()
        .map(|s| s[0] <= ATLAS_EXTENT && s[1] <= ATLAS_EXTENT)
        .collect();
    let plan = atlas::plan_atlases(&city.scene, &sizes, eligible, REGION_M, ATLAS_EXTENT, Packing::Shelves);
    let standalone: Vec<usize> = (0..sizes.len()).filter(|&t| plan.placements[t].is_none()).collect();
    let (levels, chain_bytes) = atlas::atlas_chain(ATLAS_EXTENT, format);
    let chain = |[w, h]: [u32; 2]| -> (u64, u64) {
        let mips = w.trailing_zeros().max(h.trailing_zeros()) + 1;
        let bytes = (0..mips)
            .map(|l| format.mip_bytes((w >> l).max(1), (h >> l).max(1)))
            .sum();
        (bytes, u64::from(mips))
    };
    let (standalone_bytes, standalone_mips) = standalone
        .iter()
        .map(|&t| chain(sizes[t]))
        .fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    let atlases = plan.atlas_count();
    let textures = (atlases + standalone.len()) as u64;
    let mips = atlases as u64 * u64::from(levels) + standalone_mips;
    let scene = &city.scene;
    let disk = DiskPlan {
        atlases,
        standalone: standalone.len(),
        pack_bytes: citystream_dataset::PACK_HEADER_BYTES + atlases as u64 * chain_bytes + standalone_bytes,
        scene_bytes: scene.encoded_len(),
        // Texture table, colormap, mip checksums, the resume journal's copy of them.
        metadata_bytes: 2 * (textures * (10 + 4) + mips * 4) + 4096,
    };
    Ok(Planned {
        city,
        sizes,
        plan,
        standalone,
        disk,
        format,
    })
}

/// A fingerprint of the layout and the plan, part of the resume job: a rerun continues only
/// a write of exactly this city.
fn fingerprint(planned: &Planned) -> u32 {
    let mut hasher = crc32fast::Hasher::new();
    let scene = &planned.city.scene;
    hasher.update(&(scene.meshes.len() as u64).to_le_bytes());
    for p in scene.positions.iter().step_by(97) {
        for v in p {
            hasher.update(&v.to_le_bytes());
        }
    }
    for members in planned.plan.members.iter().step_by(31) {
        hasher.update(&(members.len() as u64).to_le_bytes());
        if let Some(&first) = members.first() {
            hasher.update(&(first as u64).to_le_bytes());
        }
    }
    hasher.update(&(planned.standalone.len() as u64).to_le_bytes());
    hasher.finalize()
}

/// Composes atlas `a` of the plan: synthesises its member textures and lays them out.
fn build_atlas(planned: &Planned, a: usize) -> Result<(Vec<u8>, [u8; 4])> {
    let members = &planned.plan.members[a];
    let encoded: Vec<texture::EncodedTexture> = members
        .iter()
        .map(|&t| texture::generate(&planned.city.textures[t], planned.format))
        .collect::<Result<_>>()?;
    let parts: Vec<AtlasPart> = members
        .iter()
        .zip(&encoded)
        .map(|(&t, e)| {
            let p = planned.plan.placements[t].context("atlas member without a placement")?;
            Ok(AtlasPart {
                x: p.x,
                y: p.y,
                width: e.width,
                height: e.height,
                mip_count: e.mip_count,
                format: e.format,
                colour: e.mean,
            })
        })
        .collect::<Result<_>>()?;
    let (levels, _) = atlas::atlas_chain(ATLAS_EXTENT, planned.format);
    atlas::compose_atlas(&parts, ATLAS_EXTENT, levels, planned.format, |part, level, buf| {
        let e = &encoded[part];
        let mip = |l: u32| e.format.mip_bytes((e.width >> l).max(1), (e.height >> l).max(1)) as usize;
        let start: usize = (0..level).map(mip).sum();
        buf.clear();
        buf.extend_from_slice(&e.chain[start..start + mip(level)]);
        Ok(())
    })
}

/// How a generation run reports and stops (tests stop it early to exercise resuming).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct RunControl {
    /// Atlases composed and written between checkpoints (`None`: what the buffer holds).
    pub batch: Option<usize>,
    /// Stop with an error after this many batches (a simulated crash).
    pub stop_after_batches: Option<usize>,
    /// Free disk to assume instead of asking the file system.
    pub free_bytes: Option<u64>,
}

/// Generates the city of `params` straight into atlases (see the module docs).
pub(crate) fn generate(args: &GenArgs, params: LayoutParams, control: RunControl) -> Result<WriteSummary> {
    let start = Instant::now();
    let format = args.format.texture_format();
    if format != TextureFormat::Bc1 {
        bail!(
            "--preset berlin writes BC1 atlases (as the paper's Berlin (atlas)); --format {} is not supported",
            format.name()
        );
    }
    if args.textures_from.is_some() {
        bail!("--preset berlin synthesises its textures; --textures-from is not supported with it");
    }
    let say = |line: String| {
        if !args.quiet {
            eprintln!("gen: {line}");
        }
    };
    let planned = plan(params, args.seed, format)?;
    let scene = &planned.city.scene;
    let disk = planned.disk;
    // A building (or a setback tower on one) has one roof.
    let buildings = planned
        .city
        .textures
        .iter()
        .filter(|t| matches!(t.content, layout::Content::Roof { .. }))
        .count();
    let extent_km = |a: usize| f64::from(scene.bounds.max[a] - scene.bounds.min[a]) / 1000.0;
    say(format!(
        "laid out {buildings} buildings over {:.1} x {:.1} km: {} meshes, {} triangles; {} textures into {} atlases of {ATLAS_EXTENT}x{ATLAS_EXTENT} (fill ratio {:.1}%){}; {:.0} s",
        extent_km(0),
        extent_km(2),
        scene.meshes.len(),
        scene.triangle_count(),
        planned.sizes.len(),
        disk.atlases,
        100.0 * planned.plan.fill_ratio(&planned.sizes, ATLAS_EXTENT),
        if disk.standalone > 0 {
            format!(" + {} kept as they are", disk.standalone)
        } else {
            String::new()
        },
        start.elapsed().as_secs_f64()
    ));
    let free = match control.free_bytes {
        Some(free) => free,
        None => free_bytes(&args.out)?,
    };
    say(format!(
        "needs {} of disk in {}: pack {}, scene {}, tables {}; {} free",
        gb(disk.total()),
        args.out.display(),
        gb(disk.pack_bytes),
        gb(disk.scene_bytes),
        gb(disk.metadata_bytes),
        gb(free)
    ));
    if args.dry_run {
        return Ok(WriteSummary {
            textures: (disk.atlases + disk.standalone) as u32,
            mips: 0,
            meshes: scene.meshes.len() as u32,
            triangles: scene.triangle_count(),
            pack_bytes: disk.pack_bytes,
            scene_bytes: disk.scene_bytes,
            metadata_bytes: disk.metadata_bytes,
        });
    }
    let job = format!(
        "citystream gen, generator {GENERATOR_VERSION}, layout {:?}, seed {}, format {}, atlases of {ATLAS_EXTENT}, plan {:08x}",
        params,
        args.seed,
        format.name(),
        fingerprint(&planned)
    );
    let mut writer = DatasetWriter::create_resumable(&args.out, &job)
        .with_context(|| format!("starting the write of {}", args.out.display()))?;
    let (levels, chain_bytes) = atlas::atlas_chain(ATLAS_EXTENT, format);
    let done = writer.texture_count() as usize;
    let written = done.min(disk.atlases) as u64 * chain_bytes;
    if writer.resumed() {
        say(format!(
            "resuming an earlier run: {done} of {} atlases are written ({})",
            disk.atlases,
            gb(written)
        ));
    }
    let needed = disk.total().saturating_sub(written);
    if needed > free {
        bail!(
            "{} needs {} more of free disk ({} in all: pack {}, scene {}, tables {}), but only {} is free there; \
             free some space or choose another --out (what was written so far is kept: rerun the same command to continue)",
            args.out.display(),
            gb(needed),
            gb(disk.total()),
            gb(disk.pack_bytes),
            gb(disk.scene_bytes),
            gb(disk.metadata_bytes),
            gb(free)
        );
    }

    let batch = control
        .batch
        .unwrap_or_else(|| atlas::atlas_batch(ATLAS_EXTENT, format, BUFFER_MB).0)
        .max(1);
    let mut progress = Progress::resumed(disk.atlases, done, "atlases", 1, args.quiet);
    let mut batches = 0usize;
    let mut next = done.min(disk.atlases);
    while next < disk.atlases {
        if control.stop_after_batches == Some(batches) {
            bail!("stopped after {batches} batches (as asked)");
        }
        let end = (next + batch).min(disk.atlases);
        let built: Vec<Result<(Vec<u8>, [u8; 4])>> =
            (next..end).into_par_iter().map(|a| build_atlas(&planned, a)).collect();
        for (a, atlas) in (next..end).zip(built) {
            let (chain, mean) = atlas.with_context(|| format!("composing atlas {a}"))?;
            writer.add_texture(format, ATLAS_EXTENT, ATLAS_EXTENT, levels, &chain, mean)?;
        }
        writer.checkpoint()?;
        batches += 1;
        progress.advance(end - next);
        next = end;
    }
    // Textures that stay out of the atlases follow them, in id order.
    let mut new_id: Vec<u32> = vec![0; planned.sizes.len()];
    for (t, p) in planned.plan.placements.iter().enumerate() {
        if let Some(p) = p {
            new_id[t] = p.atlas as u32;
        }
    }
    for (k, &t) in planned.standalone.iter().enumerate() {
        let id = (disk.atlases + k) as u32;
        new_id[t] = id;
        if id < writer.texture_count() {
            continue;
        }
        let e = texture::generate(&planned.city.textures[t], format)?;
        writer.add_texture(format, e.width, e.height, e.mip_count, &e.chain, e.mean)?;
    }
    writer.checkpoint()?;
    progress.finish();
    say("writing the scene and tables, checking the dataset reads back".into());
    let out_scene = atlas::remap_scene(scene, &planned.sizes, &planned.plan.placements, &new_id, ATLAS_EXTENT)?;
    writer
        .finish(&out_scene)
        .with_context(|| format!("writing {}", args.out.display()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::city::Preset;
    use citystream_dataset::Dataset;
    use std::path::Path;

    /// A few blocks with textures up to 256²: a handful of atlases in a second.
    const PARAMS: LayoutParams = LayoutParams {
        blocks: 3,
        max_extent_log2: 8,
        density_scale: 1.5,
    };

    fn args(out: &Path) -> GenArgs {
        GenArgs {
            quiet: true,
            ..GenArgs::new(Preset::Berlin, 7, out.to_path_buf())
        }
    }

    fn test_dir(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("citystream-berlin-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    /// Every texture's every mip, its colour and the scene are the same in both datasets.
    fn assert_same_dataset(a: &Path, b: &Path) -> Result<()> {
        let (a, b) = (Dataset::open(a)?, Dataset::open(b)?);
        assert_eq!(a.textures.len(), b.textures.len());
        assert_eq!(a.textures.pack_len(), b.textures.pack_len());
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for t in 0..a.textures.len() {
            assert_eq!(a.textures.info(t)?, b.textures.info(t)?, "texture {t}");
            for level in 0..a.textures.info(t)?.mip_count() {
                a.textures.read_mip(t, level, &mut x)?;
                b.textures.read_mip(t, level, &mut y)?;
                assert!(x == y, "texture {t} level {level} differs");
            }
            assert_eq!(a.colormap.get(t), b.colormap.get(t), "colour of {t}");
        }
        assert_eq!(a.scene, b.scene);
        Ok(())
    }

    #[test]
    fn straight_into_atlases_equals_gen_then_atlas() -> Result<()> {
        let (per_mesh, atlased, direct) = (test_dir("per-mesh"), test_dir("atlased"), test_dir("direct"));
        crate::city::generate(&args(&per_mesh), PARAMS, TextureFormat::Bc1)?;
        crate::atlas::run(&crate::atlas::AtlasArgs {
            input: per_mesh.clone(),
            out: atlased.clone(),
            region: REGION_M,
            atlas_extent: ATLAS_EXTENT,
            packing: Packing::Shelves,
            buffer_mb: BUFFER_MB,
            quiet: true,
        })?;
        let control = RunControl {
            batch: Some(2),
            ..RunControl::default()
        };
        let summary = generate(&args(&direct), PARAMS, control)?;
        assert!(summary.textures >= 4, "a few atlases: {summary:?}");
        assert_same_dataset(&atlased, &direct)?;
        for dir in [per_mesh, atlased, direct] {
            std::fs::remove_dir_all(dir)?;
        }
        Ok(())
    }

    #[test]
    fn an_interrupted_run_resumes_where_it_stopped() -> Result<()> {
        let (whole, resumed) = (test_dir("whole"), test_dir("resumed"));
        let control = RunControl {
            batch: Some(1),
            ..RunControl::default()
        };
        generate(&args(&whole), PARAMS, control)?;
        let stop = RunControl {
            stop_after_batches: Some(2),
            ..control
        };
        let err = generate(&args(&resumed), PARAMS, stop).expect_err("stops");
        assert!(err.to_string().contains("stopped after 2 batches"), "{err}");
        assert!(Dataset::open(&resumed).is_err(), "no dataset until the write finishes");
        // Resumes after the two atlases written: stopping after one more batch leaves three.
        let stop = RunControl {
            stop_after_batches: Some(1),
            ..control
        };
        generate(&args(&resumed), PARAMS, stop).expect_err("stops again");
        let writer = DatasetWriter::create_resumable(&resumed, "another job")?;
        assert_eq!(writer.texture_count(), 0, "another job does not resume");
        drop(writer);
        // That removed the write; stop once more, then finish.
        generate(&args(&resumed), PARAMS, stop).expect_err("stops");
        generate(&args(&resumed), PARAMS, control)?;
        assert_same_dataset(&whole, &resumed)?;
        for dir in [whole, resumed] {
            std::fs::remove_dir_all(dir)?;
        }
        Ok(())
    }

    #[test]
    fn too_little_disk_is_refused_before_writing() -> Result<()> {
        let out = test_dir("no-disk");
        let planned = plan(PARAMS, 7, TextureFormat::Bc1)?;
        let control = RunControl {
            free_bytes: Some(planned.disk.total() - 1),
            ..RunControl::default()
        };
        let err = generate(&args(&out), PARAMS, control).expect_err("refused");
        let text = err.to_string();
        assert!(
            text.contains("more of free disk") && text.contains("is free there"),
            "{text}"
        );
        assert!(Dataset::open(&out).is_err());
        let control = RunControl {
            free_bytes: Some(planned.disk.total()),
            ..RunControl::default()
        };
        generate(&args(&out), PARAMS, control)?;
        let written = std::fs::read_dir(citystream_dataset::DatasetFiles::resolve(&out)?.data_dir())?
            .map(|e| Ok(e?.metadata()?.len()))
            .sum::<Result<u64>>()?;
        assert!(
            written <= planned.disk.total(),
            "wrote {written}, planned {}",
            planned.disk.total()
        );
        std::fs::remove_dir_all(out)?;
        Ok(())
    }

    #[test]
    fn berlin_preset_has_the_papers_table_1_figures() -> Result<()> {
        // The layout and the plan only (seconds); `docs/BERLIN.md` has the written city.
        let planned = plan(Preset::Berlin.params(), 1, TextureFormat::Bc1)?;
        let within = |ours: f64, paper: f64| (ours / paper - 1.0).abs() <= 0.1;
        let triangles = planned.city.scene.triangle_count() as f64;
        assert!(within(triangles, 15_363_486.0), "{triangles} triangles");
        assert!(
            within(planned.disk.atlases as f64, 233_110.0),
            "{} atlases",
            planned.disk.atlases
        );
        assert!(
            within(planned.disk.pack_bytes as f64, 40.8e9),
            "{} bytes",
            planned.disk.pack_bytes
        );
        assert_eq!(planned.disk.standalone, 0);
        Ok(())
    }
}
