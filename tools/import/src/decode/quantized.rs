//! Accessor values as floats whatever their component type: glTF's own floats and the
//! integer types `KHR_mesh_quantization` allows for positions, normals and texture
//! coordinates, normalized or not (dequantized as the glTF specification says:
//! `max(c / 127, -1)` for signed bytes, `c / 255` for unsigned, likewise for shorts).

use gltf::accessor::DataType;

use super::DecodeError;

/// Whether an accessor of this type holds quantized (integer) values.
pub fn is_quantized(data_type: DataType) -> bool {
    data_type != DataType::F32
}

/// The `N`-component elements of `accessor` as floats. The caller has checked that every
/// element lies inside its view and buffer; an element that does not is an error all the
/// same. An accessor without a buffer view is all zeros.
pub fn read<const N: usize>(
    accessor: &gltf::Accessor,
    buffers: &[gltf::buffer::Data],
    what: &str,
) -> Result<Vec<[f32; N]>, DecodeError> {
    let count = accessor.count();
    let Some(view) = accessor.view() else {
        return Ok(vec![[0.0; N]; count]);
    };
    let data_type = accessor.data_type();
    let component = data_type.size();
    let element = accessor.size();
    if element < component * N {
        return Err(DecodeError::invalid(
            what,
            format!("{element}-byte elements cannot hold {N} components"),
        ));
    }
    let stride = view.stride().unwrap_or(element);
    let buffer = buffers
        .get(view.buffer().index())
        .map(|d| &d.0[..])
        .ok_or_else(|| DecodeError::invalid(what, format!("buffer {} is missing", view.buffer().index())))?;
    let start = view.offset() + accessor.offset();
    let normalized = accessor.normalized();
    let value = |bytes: &[u8]| -> f32 {
        match data_type {
            DataType::F32 => f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]),
            DataType::I8 => scale(f32::from(bytes[0] as i8), normalized, 127.0),
            DataType::U8 => scale(f32::from(bytes[0]), normalized, 255.0),
            DataType::I16 => scale(f32::from(i16::from_le_bytes([bytes[0], bytes[1]])), normalized, 32767.0),
            DataType::U16 => scale(f32::from(u16::from_le_bytes([bytes[0], bytes[1]])), normalized, 65535.0),
            DataType::U32 => u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) as f32,
        }
    };
    let mut out = Vec::with_capacity(count);
    for i in 0..count {
        let at = i.checked_mul(stride).and_then(|o| o.checked_add(start));
        let bytes = at
            .and_then(|at| buffer.get(at..at.checked_add(component * N)?))
            .ok_or_else(|| DecodeError::invalid(what, format!("element {i} lies outside its buffer")))?;
        out.push(std::array::from_fn(|c| value(&bytes[c * component..])));
    }
    Ok(out)
}

/// A normalized integer `c` of largest magnitude `max` as a float (signed values clamp at −1,
/// as the most negative integer has no positive counterpart).
fn scale(c: f32, normalized: bool, max: f32) -> f32 {
    if normalized {
        (c / max).max(-1.0)
    } else {
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normalized_integers_dequantize_as_the_specification_says() {
        assert_eq!(scale(127.0, true, 127.0), 1.0);
        assert_eq!(scale(-128.0, true, 127.0), -1.0);
        assert_eq!(scale(-64.0, true, 127.0), -64.0 / 127.0);
        assert_eq!(scale(65535.0, true, 65535.0), 1.0);
        assert_eq!(scale(300.0, false, 65535.0), 300.0);
        assert!(is_quantized(DataType::U16) && !is_quantized(DataType::F32));
    }
}
