//! One glTF triangle primitive read into a pending mesh, whatever its encoding: plain
//! floats, quantized integers (`KHR_mesh_quantization`), meshopt-compressed views or a Draco
//! stream (both decoded before the document is read: [`crate::decode`]); texture
//! coordinates through the base-colour texture's
//! `KHR_texture_transform` where it has one (gltfpack dequantizes UVs with it).
//!
//! Accessors are checked before any reader touches them: the `gltf` crate's reader panics on
//! component types an attribute does not allow and yields nothing for data outside its
//! buffer.

use std::collections::HashSet;

use anyhow::{bail, Context, Result};

use crate::decode::quantized;
use crate::transform::{normal_matrix, transform_normal, transform_point, Mat4};

/// A primitive read from a document: positions placed in f64, its texture by index.
pub(crate) struct PendingMesh {
    pub(crate) texture: usize,
    pub(crate) positions: Vec<[f64; 3]>,
    pub(crate) normals: Vec<[f32; 3]>,
    pub(crate) uvs: Vec<[f32; 2]>,
    pub(crate) indices: Vec<u32>,
    /// How its geometry was stored.
    pub(crate) encoding: MeshEncoding,
}

/// How a primitive's geometry was stored, as `info` counts meshes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum MeshEncoding {
    /// Float attributes in plain buffer views.
    Plain,
    /// Integer attributes (`KHR_mesh_quantization`) in plain views.
    Quantized,
    /// Float attributes in meshopt-compressed views.
    Meshopt,
    /// Integer attributes in meshopt-compressed views.
    MeshoptQuantized,
    /// A Draco stream.
    Draco,
}

impl MeshEncoding {
    /// Name in `info`'s counts.
    pub fn name(self) -> &'static str {
        match self {
            MeshEncoding::Plain => "plain",
            MeshEncoding::Quantized => "quantized",
            MeshEncoding::Meshopt => "meshopt",
            MeshEncoding::MeshoptQuantized => "meshopt+quantized",
            MeshEncoding::Draco => "draco",
        }
    }
}

/// The document's buffers and which of its buffer views hold decoded data.
pub(crate) struct Buffers<'a> {
    pub(crate) data: &'a [gltf::buffer::Data],
    pub(crate) decoded: &'a DecodedViews,
}

/// Buffer views whose data was decoded from compressed geometry.
#[derive(Debug, Default)]
pub(crate) struct DecodedViews {
    /// Decoded in place from `EXT_meshopt_compression` views.
    pub(crate) meshopt: HashSet<usize>,
    /// Added with the data of `KHR_draco_mesh_compression` primitives.
    pub(crate) draco: HashSet<usize>,
}

/// `KHR_texture_transform` of a texture reference: `uv' = T · R · S · uv`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct UvTransform {
    offset: [f32; 2],
    rotation: f32,
    scale: [f32; 2],
}

impl UvTransform {
    /// The transform and texture coordinate set of the base-colour texture `info` uses.
    pub(crate) fn of(info: &gltf::texture::Info) -> Result<(Option<Self>, u32)> {
        let Some(ext) = info.extension_value("KHR_texture_transform") else {
            return Ok((None, info.tex_coord()));
        };
        let pair = |key: &str, default: [f32; 2]| -> Result<[f32; 2]> {
            match ext.get(key) {
                None => Ok(default),
                Some(v) => {
                    let values: Vec<f32> = v
                        .as_array()
                        .map(|a| a.iter().filter_map(|x| x.as_f64()).map(|x| x as f32).collect())
                        .unwrap_or_default();
                    match values[..] {
                        [a, b] if a.is_finite() && b.is_finite() => Ok([a, b]),
                        _ => bail!("KHR_texture_transform {key} is {v}, not two finite numbers"),
                    }
                }
            }
        };
        let rotation = match ext.get("rotation") {
            None => 0.0,
            Some(v) => match v.as_f64() {
                Some(r) if r.is_finite() => r as f32,
                _ => bail!("KHR_texture_transform rotation is {v}, not a finite number"),
            },
        };
        let set = match ext.get("texCoord") {
            None => info.tex_coord(),
            Some(v) => v
                .as_u64()
                .and_then(|s| u32::try_from(s).ok())
                .with_context(|| format!("KHR_texture_transform texCoord is {v}"))?,
        };
        let transform = Self {
            offset: pair("offset", [0.0, 0.0])?,
            rotation,
            scale: pair("scale", [1.0, 1.0])?,
        };
        Ok((Some(transform), set))
    }

    fn apply(&self, [u, v]: [f32; 2]) -> [f32; 2] {
        let (s, c) = self.rotation.sin_cos();
        let (su, sv) = (u * self.scale[0], v * self.scale[1]);
        [c * su + s * sv + self.offset[0], -s * su + c * sv + self.offset[1]]
    }
}

/// A primitive's attributes in its node's own coordinates, before placement.
struct Local {
    positions: Vec<[f32; 3]>,
    normals: Option<Vec<[f32; 3]>>,
    uvs: Option<Vec<[f32; 2]>>,
    /// As stored (strips and fans not yet turned into lists); `None`: not indexed.
    indices: Option<Vec<u32>>,
    encoding: MeshEncoding,
}

/// Reads `primitive`, placed by `world`; its texture coordinates are set `uv_set` through
/// `uv_transform`.
pub(crate) fn read_primitive(
    primitive: &gltf::Primitive,
    buffers: &Buffers,
    world: &Mat4,
    (uv_transform, uv_set): (Option<UvTransform>, u32),
    texture: usize,
) -> Result<PendingMesh> {
    let local = plain_attributes(primitive, buffers, uv_set)?;
    let count = local.positions.len();
    if count > u32::MAX as usize {
        bail!("{count} vertices exceed 2^32");
    }
    if let Some((i, p)) = local
        .positions
        .iter()
        .enumerate()
        .find(|(_, p)| p.iter().any(|v| !v.is_finite()))
    {
        bail!("vertex {i} has non-finite position {p:?}");
    }
    let raw = local.indices.unwrap_or_else(|| (0..count as u32).collect());
    let mut indices = triangle_list(primitive.mode(), raw);
    if !indices.len().is_multiple_of(3) {
        bail!("{} indices do not form whole triangles", indices.len());
    }
    if let Some((i, &index)) = indices.iter().enumerate().find(|(_, &v)| v as usize >= count) {
        bail!("index {i} is {index}, out of range (the primitive has {count} vertices)");
    }
    let (n3, det) = normal_matrix(world);
    if det < 0.0 {
        // A mirroring transform flips the winding; restore counter-clockwise front faces.
        for tri in indices.chunks_exact_mut(3) {
            tri.swap(1, 2);
        }
    }
    let positions: Vec<[f64; 3]> = local.positions.iter().map(|p| transform_point(world, *p)).collect();
    let normals: Vec<[f32; 3]> = match local.normals {
        Some(normals) => normals.into_iter().map(|n| transform_normal(&n3, det, n)).collect(),
        None => flat_normals(&positions, &indices),
    };
    let mut uvs = local.uvs.unwrap_or_else(|| vec![[0.0, 0.0]; count]);
    if let Some(transform) = uv_transform {
        for uv in &mut uvs {
            *uv = transform.apply(*uv);
        }
    }
    if normals.len() != count || uvs.len() != count {
        bail!(
            "attribute counts differ: {count} positions, {} normals, {} uvs",
            normals.len(),
            uvs.len()
        );
    }
    if let Some((i, uv)) = uvs.iter().enumerate().find(|(_, uv)| uv.iter().any(|v| !v.is_finite())) {
        bail!("vertex {i} has non-finite uv {uv:?}");
    }
    Ok(PendingMesh {
        texture,
        positions,
        normals,
        uvs,
        indices,
        encoding: local.encoding,
    })
}

fn plain_attributes(primitive: &gltf::Primitive, buffers: &Buffers, uv_set: u32) -> Result<Local> {
    use gltf::accessor::{DataType, Dimensions};
    use gltf::Semantic;
    let data = buffers.data;
    let position = primitive.get(&Semantic::Positions).context("no POSITION attribute")?;
    let integers = [DataType::I8, DataType::U8, DataType::I16, DataType::U16];
    let any = [DataType::F32, integers[0], integers[1], integers[2], integers[3]];
    check_accessor(&position, data, "POSITION", &any, Dimensions::Vec3)?;
    let normal = primitive.get(&Semantic::Normals);
    if let Some(normal) = &normal {
        let types = [DataType::F32, DataType::I8, DataType::I16];
        check_accessor(normal, data, "NORMAL", &types, Dimensions::Vec3)?;
    }
    let uv = primitive.get(&Semantic::TexCoords(uv_set));
    if let Some(uv) = &uv {
        check_accessor(uv, data, &format!("TEXCOORD_{uv_set}"), &any, Dimensions::Vec2)?;
    }
    if let Some(indices) = primitive.indices() {
        let types = [DataType::U8, DataType::U16, DataType::U32];
        check_accessor(&indices, data, "indices", &types, Dimensions::Scalar)?;
    }
    let accessors = [Some(&position), normal.as_ref(), uv.as_ref()];
    let quantized = accessors
        .iter()
        .flatten()
        .any(|a| quantized::is_quantized(a.data_type()));
    let indices = primitive.indices();
    let from = |views: &HashSet<usize>| {
        let mut all = accessors.into_iter().flatten().chain(indices.as_ref());
        all.any(|a| a.view().is_some_and(|v| views.contains(&v.index())))
    };
    let encoding = match (from(&buffers.decoded.draco), from(&buffers.decoded.meshopt), quantized) {
        (true, _, _) => MeshEncoding::Draco,
        (false, false, false) => MeshEncoding::Plain,
        (false, false, true) => MeshEncoding::Quantized,
        (false, true, false) => MeshEncoding::Meshopt,
        (false, true, true) => MeshEncoding::MeshoptQuantized,
    };
    let reader = primitive.reader(|b| data.get(b.index()).map(|d| &d.0[..]));
    let positions = quantized::read(&position, data, "POSITION")?;
    if matches!(
        encoding,
        MeshEncoding::Draco | MeshEncoding::Meshopt | MeshEncoding::MeshoptQuantized
    ) {
        check_position_bounds(&position, &positions, encoding)?;
    }
    Ok(Local {
        positions,
        normals: normal.map(|n| quantized::read(&n, data, "NORMAL")).transpose()?,
        uvs: uv.map(|uv| quantized::read(&uv, data, "TEXCOORD")).transpose()?,
        indices: reader.read_indices().map(|indices| indices.into_u32().collect()),
        encoding,
    })
}

/// Checks decoded positions of compressed geometry against the POSITION accessor's `min`
/// and `max` (which glTF requires): a damaged Draco or meshopt stream can decode to
/// positions of any size, and the bounds the encoder wrote are the one independent record
/// of where they lie. The tolerance is one step of an 8-bit quantization of the largest
/// extent (Draco quantizes every axis over that one range), plus float rounding. Bounds of
/// a normalized integer accessor are read as normalized when they lie within ±1, as the
/// raw integers otherwise (files write either).
fn check_position_bounds(accessor: &gltf::Accessor, positions: &[[f32; 3]], encoding: MeshEncoding) -> Result<()> {
    let bound = |value: Option<gltf::json::Value>| -> Option<[f64; 3]> {
        let array = value?;
        let array = array.as_array()?;
        if array.len() != 3 {
            return None;
        }
        let mut out = [0.0; 3];
        for (o, v) in out.iter_mut().zip(array) {
            *o = v.as_f64().filter(|v| v.is_finite())?;
        }
        Some(out)
    };
    let (Some(mut min), Some(mut max)) = (bound(accessor.min()), bound(accessor.max())) else {
        return Ok(());
    };
    if accessor.normalized() && min.iter().chain(&max).any(|b| b.abs() > 1.0) {
        use gltf::accessor::DataType;
        let largest = match accessor.data_type() {
            DataType::I8 => 127.0,
            DataType::U8 => 255.0,
            DataType::I16 => 32767.0,
            DataType::U16 => 65535.0,
            _ => 1.0,
        };
        for b in min.iter_mut().chain(max.iter_mut()) {
            *b = (*b / largest).max(-1.0);
        }
    }
    let extent = (0..3).map(|c| max[c] - min[c]).fold(0.0, f64::max);
    let magnitude = min.iter().chain(&max).map(|b| b.abs()).fold(0.0, f64::max);
    let tolerance = extent / 255.0 + magnitude * 1e-6;
    if let Some((i, p)) = positions.iter().enumerate().find(|(_, p)| {
        (0..3).any(|c| {
            let v = f64::from(p[c]);
            !(min[c] - tolerance..=max[c] + tolerance).contains(&v)
        })
    }) {
        bail!(
            "accessor {} (POSITION): vertex {i} decodes to {p:?}, outside the accessor's bounds {min:?} to {max:?}: \
             the {} data is damaged",
            accessor.index(),
            encoding.name()
        );
    }
    Ok(())
}

/// Checks an accessor before the `gltf` crate reads it, which panics on a
/// component type the attribute does not allow and yields nothing for
/// data outside its buffer: its type and shape must be among `allowed`, and
/// every element must lie inside its buffer view and the view inside its
/// buffer. Errors name the accessor and what it is for.
fn check_accessor(
    accessor: &gltf::Accessor,
    buffers: &[gltf::buffer::Data],
    what: &str,
    allowed: &[gltf::accessor::DataType],
    dimensions: gltf::accessor::Dimensions,
) -> Result<()> {
    let name = format!("accessor {} ({what})", accessor.index());
    if !allowed.contains(&accessor.data_type()) || accessor.dimensions() != dimensions {
        bail!(
            "{name} is {:?} {:?}; {what} must be {dimensions:?} of {allowed:?}",
            accessor.dimensions(),
            accessor.data_type()
        );
    }
    if accessor.sparse().is_some() {
        bail!("{name} is sparse, which the importer does not support");
    }
    if accessor.count() == 0 {
        // The `gltf` crate's reader computes `count - 1` unchecked.
        bail!("{name} has count 0; glTF requires at least 1 element");
    }
    let Some(view) = accessor.view() else {
        return Ok(()); // No view: every element is zero.
    };
    let buffer_len = buffers
        .get(view.buffer().index())
        .map(|data| data.0.len())
        .with_context(|| format!("{name}: buffer {} is missing", view.buffer().index()))?;
    let view_end = view.offset().checked_add(view.length());
    if view_end.is_none_or(|end| end > buffer_len) {
        bail!(
            "{name}: buffer view {} (bytes {}..+{}) lies outside buffer {} of {buffer_len} bytes",
            view.index(),
            view.offset(),
            view.length(),
            view.buffer().index()
        );
    }
    let element = accessor.size();
    // The `gltf` crate's reader steps by the view's stride and asserts each step holds an
    // element: a smaller stride would panic there.
    if let Some(stride) = view.stride().filter(|&s| s < element) {
        bail!(
            "{name}: buffer view {} has byteStride {stride}, smaller than the {element}-byte element",
            view.index()
        );
    }
    let stride = view.stride().unwrap_or(element);
    let end = (accessor.count() - 1)
        .checked_mul(stride)
        .and_then(|n| n.checked_add(accessor.offset()))
        .and_then(|n| n.checked_add(element));
    if end.is_none_or(|end| end > view.length()) {
        bail!(
            "{name}: {} elements of {element} bytes from byte {} overrun buffer view {} of {} bytes",
            accessor.count(),
            accessor.offset(),
            view.index(),
            view.length()
        );
    }
    Ok(())
}

/// Converts strips and fans to a triangle list (keeping counter-clockwise winding).
fn triangle_list(mode: gltf::mesh::Mode, raw: Vec<u32>) -> Vec<u32> {
    use gltf::mesh::Mode;
    let triangles = raw.len().saturating_sub(2);
    match mode {
        Mode::TriangleStrip => (0..triangles)
            .flat_map(|i| {
                if i % 2 == 0 {
                    [raw[i], raw[i + 1], raw[i + 2]]
                } else {
                    [raw[i + 1], raw[i], raw[i + 2]]
                }
            })
            .collect(),
        Mode::TriangleFan => (0..triangles).flat_map(|i| [raw[0], raw[i + 1], raw[i + 2]]).collect(),
        _ => raw,
    }
}

/// Per-vertex normals averaged from the faces that use them (glTF says: flat shading).
fn flat_normals(positions: &[[f64; 3]], indices: &[u32]) -> Vec<[f32; 3]> {
    let mut sum = vec![[0.0f64; 3]; positions.len()];
    for tri in indices.chunks_exact(3) {
        let [a, b, c] = [tri[0], tri[1], tri[2]].map(|i| positions[i as usize]);
        let (u, v) = (
            [b[0] - a[0], b[1] - a[1], b[2] - a[2]],
            [c[0] - a[0], c[1] - a[1], c[2] - a[2]],
        );
        let n = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        for &i in tri {
            for k in 0..3 {
                sum[i as usize][k] += n[k];
            }
        }
    }
    sum.into_iter()
        .map(|n| {
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if len > 0.0 {
                n.map(|x| (x / len) as f32)
            } else {
                [0.0, 1.0, 0.0]
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_transforms_scale_rotate_then_offset() {
        let t = UvTransform {
            offset: [0.5, 0.25],
            rotation: 0.0,
            scale: [40.0, 64.0],
        };
        assert_eq!(t.apply([0.5, 0.25]), [20.5, 16.25]);
        let quarter = UvTransform {
            offset: [0.0, 0.0],
            rotation: std::f32::consts::FRAC_PI_2,
            scale: [1.0, 1.0],
        };
        let [u, v] = quarter.apply([1.0, 0.0]);
        assert!(u.abs() < 1e-6 && (v + 1.0).abs() < 1e-6, "{u} {v}");
    }
}
