//! The dataset a flythrough flies through: where it lies (the default city made on first
//! run), opened with its city geometry, and the scale of its scene.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Result;
use glam::Vec3;

use citystream_dataset::Dataset;
use citystream_engine::city::city_geometry;
use citystream_gen::default_city::{ensure_default_city, DEFAULT_CITY_DIR};

use super::args::Args;
use super::city_gpu::CityGeometry;

/// The dataset directory: `--dataset`, or the default city (created on first run).
pub(crate) fn dataset_dir(args: &Args) -> Result<PathBuf> {
    match &args.dataset {
        Some(dir) => Ok(dir.clone()),
        None => {
            let dir = PathBuf::from(DEFAULT_CITY_DIR);
            ensure_default_city(&dir, false)?;
            Ok(dir)
        }
    }
}

/// The dataset (with the remote settings of `args` where it is a URL) with its vertices and
/// meshes in the engine's layout.
pub(crate) fn open_city(args: &Args, dir: &std::path::Path) -> Result<(Arc<Dataset>, CityGeometry)> {
    let options = args.remote.options_with_cache(&args.mip_cache)?;
    let dataset = Arc::new(citystream_gen::location::open_dataset_with(dir, &options)?);
    let city = city_geometry(&dataset)?;
    Ok((dataset, city))
}

/// The scene's largest side (at least 1): the scale of the camera's depth range.
pub(crate) fn scene_extent(scene: &citystream_dataset::Scene) -> f32 {
    let size = Vec3::from(scene.bounds.max) - Vec3::from(scene.bounds.min);
    size.x.max(size.y).max(size.z).max(1.0)
}
