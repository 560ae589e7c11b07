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
use super::camera::camera_path;
use super::city_gpu::CityGeometry;
use super::depth_slabs::DepthSlabs;

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
/// meshes in the engine's layout, and the `--depth-slabs` probe placed in it.
pub(crate) fn open_city(
    args: &Args,
    dir: &std::path::Path,
) -> Result<(Arc<Dataset>, CityGeometry, Option<DepthSlabs>)> {
    let options = args.remote.options_with_cache(&args.mip_cache)?;
    let mut dataset = citystream_gen::location::open_dataset_with(dir, &options)?;
    let slabs = match args.depth_slabs {
        Some(distance_m) => {
            // Placed from the path's first pose over the city alone.
            let path = camera_path(args.path.as_deref().unwrap_or("standard"), &dataset.scene)?;
            Some(DepthSlabs::add(&mut dataset, path, distance_m)?)
        }
        None => None,
    };
    let city = city_geometry(&dataset)?;
    Ok((Arc::new(dataset), city, slabs))
}

/// The scene's largest side (at least 1): the scale of the camera's depth range.
pub(crate) fn scene_extent(scene: &citystream_dataset::Scene) -> f32 {
    let size = Vec3::from(scene.bounds.max) - Vec3::from(scene.bounds.min);
    size.x.max(size.y).max(size.z).max(1.0)
}
