//! `citystream gen`: deterministic synthetic cities.
//!
//! The layout (single-threaded, cheap) decides every mesh and the description of its
//! texture; textures are then synthesised, mip-mapped and block-compressed in parallel with
//! rayon, a chunk at a time, and appended to the pack in texture-id order so the output is
//! byte-identical for a given seed whatever the thread count.

use anyhow::{bail, Context, Result};
use citystream_dataset::{DatasetWriter, TextureFormat, WriteSummary};
use rayon::prelude::*;

use crate::files::print_stdout;
use crate::layout::{self, LayoutParams};
use crate::library;
use crate::options::{free_bytes, gb, GenArgs};
use crate::progress::Progress;
use crate::rng;
use crate::texture;

pub(crate) fn generate(args: &GenArgs, params: LayoutParams, format: TextureFormat) -> Result<WriteSummary> {
    let mut city = layout::layout(params, args.seed)?;
    // The procedural textures' chains; user images (`--textures-from`) come on top.
    let pack_bytes: u64 = city
        .textures
        .iter()
        .map(|t| {
            let (w, h) = (1u32 << t.width_log2, 1u32 << t.height_log2);
            let mips = u32::from(t.width_log2.max(t.height_log2)) + 1;
            (0..mips)
                .map(|l| format.mip_bytes((w >> l).max(1), (h >> l).max(1)))
                .sum::<u64>()
        })
        .sum();
    let scene_bytes = city.scene.encoded_len();
    let needed = pack_bytes + scene_bytes;
    let free = free_bytes(&args.out)?;
    if args.dry_run {
        print_stdout(&format!(
            "{} meshes, {} triangles, {} textures; needs {} of disk in {} (pack {}, scene {}); {} free\n",
            city.scene.meshes.len(),
            city.scene.triangle_count(),
            city.textures.len(),
            gb(needed),
            args.out.display(),
            gb(pack_bytes),
            gb(scene_bytes),
            gb(free)
        ))?;
        return Ok(WriteSummary {
            textures: city.textures.len() as u32,
            mips: 0,
            meshes: city.scene.meshes.len() as u32,
            triangles: city.scene.triangle_count(),
            pack_bytes,
            scene_bytes,
            metadata_bytes: 0,
        });
    }
    if needed > free {
        bail!(
            "{} needs {} of free disk (pack {}, scene {}), but only {} is free there",
            args.out.display(),
            gb(needed),
            gb(pack_bytes),
            gb(scene_bytes),
            gb(free)
        );
    }
    let mut writer = DatasetWriter::create(&args.out)?;

    // User images become textures 0..n; facades pick one of them by a hash of their seed.
    let library = match &args.textures_from {
        Some(dir) => library::load(dir, params.max_extent_log2)?,
        None => Vec::new(),
    };
    if !args.quiet && !library.is_empty() {
        eprintln!("gen: dressing facades with {} images:", library.len());
        for image in &library {
            eprintln!("  {} -> {}x{}", image.path.display(), image.width, image.height);
        }
    }
    let encoded: Vec<_> = library
        .into_par_iter()
        .map(|image| texture::encode_chain(image.rgba, image.width, image.height, format))
        .collect();
    let shared = encoded.len() as u64;
    for texture in encoded {
        let t = texture?;
        writer.add_texture(format, t.width, t.height, t.mip_count, &t.chain, t.mean)?;
    }
    let mut procedural = Vec::with_capacity(city.textures.len());
    for (mesh, spec) in city.scene.meshes.iter_mut().zip(&city.textures) {
        if shared > 0 && matches!(spec.content, layout::Content::Facade(_)) {
            mesh.texture = (rng::mix(&[args.seed, spec.seed]) % shared) as u32;
        } else {
            mesh.texture = (shared + procedural.len() as u64) as u32;
            procedural.push(*spec);
        }
    }

    let mut progress = Progress::new(procedural.len(), args.quiet);
    // Large enough to keep both cores busy, small enough to bound memory (~100 MB at 512²).
    const CHUNK: usize = 1024;
    for chunk in procedural.chunks(CHUNK) {
        let encoded: Vec<_> = chunk.par_iter().map(|spec| texture::generate(spec, format)).collect();
        for texture in encoded {
            let t = texture?;
            writer.add_texture(format, t.width, t.height, t.mip_count, &t.chain, t.mean)?;
        }
        progress.advance(chunk.len());
    }
    progress.finish();
    writer
        .finish(&city.scene)
        .with_context(|| format!("writing {}", args.out.display()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::options::Preset;

    /// The presets promise sizes (tests use `tiny`, the benchmark uses `large`, `city` must
    /// reach the paper's scale); check them on the layout, which is cheap.
    /// Written, reopened, every mip byte-identical to what the generator produced.
    #[test]
    fn tiny_city_round_trips_every_mip() -> Result<()> {
        let out = std::env::temp_dir().join(format!("citystream-gen-roundtrip-{}", std::process::id()));
        let args = GenArgs {
            quiet: true,
            ..GenArgs::new(Preset::Tiny, 3, out.clone())
        };
        let summary = generate(&args, Preset::Tiny.params(), TextureFormat::Bc1)?;
        let dataset = citystream_dataset::Dataset::open(&out)?;
        let city = layout::layout(Preset::Tiny.params(), 3)?;
        assert_eq!(dataset.scene, city.scene);
        assert_eq!(summary.textures as usize, city.textures.len());
        let mut buf = Vec::new();
        for (id, spec) in city.textures.iter().enumerate() {
            let expected = texture::generate(spec, TextureFormat::Bc1)?;
            let mut offset = 0;
            for level in 0..expected.mip_count {
                dataset.textures.read_mip(id as u32, level, &mut buf)?;
                assert_eq!(
                    buf,
                    expected.chain[offset..offset + buf.len()],
                    "texture {id} level {level}"
                );
                offset += buf.len();
            }
            assert_eq!(offset, expected.chain.len());
            assert_eq!(dataset.colormap.get(id as u32), Some(expected.mean));
        }
        std::fs::remove_dir_all(&out)?;
        Ok(())
    }

    #[test]
    fn presets_have_their_documented_texture_counts() {
        let count = |p: Preset| layout::layout(p.params(), 1).expect("layout").textures.len();
        let tiny = count(Preset::Tiny);
        assert!((50..=1_000).contains(&tiny), "tiny has {tiny}");
        let small = count(Preset::Small);
        assert!((2_000..=10_000).contains(&small), "small has {small}");
        let large = count(Preset::Large);
        assert!((90_000..=130_000).contains(&large), "large has {large}");
        let city = count(Preset::City);
        assert!(city >= 1_000_000, "city has {city}");
        eprintln!("textures: tiny {tiny}, small {small}, large {large}, city {city}");
    }
}
