//! The texture-array strategy's start without a budget: the whole city loaded before the
//! first frame where it fits.

use anyhow::{bail, Result};

use citystream_engine::commands::CommandContext;

use super::city_gpu::CityGpu;

/// The texture-array strategy's fully resident start.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub(crate) struct Preload {
    /// Mips and their bytes loaded before the first frame (every level of every texture).
    pub(crate) mips: u32,
    pub(crate) bytes: u64,
    /// Wall time it took.
    pub(crate) seconds: f64,
}

/// The texture-array strategy's start without a budget given: where the cache's arrays
/// hold the whole city within the device's memory, every texture is loaded now, before
/// the first frame, as Trapp and Döllner's batching has it; otherwise nothing is, and the
/// feedback streams into the arrays (said on standard error).
pub(crate) fn preload_city(gpu: &mut CityGpu, commands: &mut CommandContext) -> Result<Option<Preload>> {
    let cache = gpu.streamer.cache();
    if !cache.holds_every_texture() {
        eprintln!(
            "texture arrays: the city does not fit the device's memory ({:.1} MB of layers); its textures stream into them",
            cache.texel_memory_bytes() as f64 / f64::from(1 << 20)
        );
        return Ok(None);
    }
    let started = std::time::Instant::now();
    let report = gpu.streamer.load_everything_now(commands)?;
    if !report.invalidated_textures.is_empty() {
        bail!(
            "loading the whole city into texture arrays sized for it evicted {} textures",
            report.invalidated_textures.len()
        );
    }
    let preload = Preload {
        mips: report.mips_uploaded,
        bytes: report.bytes_uploaded,
        seconds: started.elapsed().as_secs_f64(),
    };
    eprintln!(
        "texture arrays: every texture resident before the first frame: {} mips, {:.1} MB in {:.1} s ({:.1} MB of layers)",
        preload.mips,
        preload.bytes as f64 / f64::from(1 << 20),
        preload.seconds,
        gpu.streamer.bound_bytes() as f64 / f64::from(1 << 20)
    );
    Ok(Some(preload))
}
