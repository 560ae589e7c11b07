//! Reading a tile's content: b3dm (3D Tiles 1.0) headers and tables, and what a glTF
//! asks for (its required extensions, `CESIUM_RTC`), checked before the glTF reader sees it.

use anyhow::{bail, Context, Result};
use serde_json::Value;

/// Bytes of a b3dm header.
const B3DM_HEADER: usize = 28;
/// Feature and batch table JSON read at most (the rest of a b3dm is the glTF).
const MAX_TABLE_JSON: usize = 64 << 20;

/// A b3dm's glTF and its feature table's `RTC_CENTER`.
#[derive(Debug, PartialEq)]
pub struct Batched<'a> {
    pub glb: &'a [u8],
    pub rtc_center: Option<[f64; 3]>,
}

fn word(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

/// Parses a b3dm: version 1, the declared length equal to the file's, the four table
/// lengths inside it; the batch table is skipped, the feature table read for
/// `RTC_CENTER` (a JSON array or a reference into its binary body).
pub fn parse_b3dm(bytes: &[u8]) -> Result<Batched<'_>> {
    if bytes.len() < B3DM_HEADER || &bytes[..4] != b"b3dm" {
        bail!(
            "not a b3dm: {} bytes, magic {:?} (expected \"b3dm\" and a {B3DM_HEADER}-byte header)",
            bytes.len(),
            String::from_utf8_lossy(&bytes[..bytes.len().min(4)])
        );
    }
    let version = word(bytes, 4);
    if version != 1 {
        bail!("b3dm version {version} (only version 1 exists)");
    }
    let declared = word(bytes, 8) as usize;
    if declared != bytes.len() {
        bail!("b3dm header declares {declared} bytes but the file has {}", bytes.len());
    }
    let [feature_json, feature_bin, batch_json, batch_bin] = [12, 16, 20, 24].map(|at| word(bytes, at) as usize);
    // Headers written before 3D Tiles 1.0 put a batch length (and a table length) where
    // the table lengths are now; a glTF's magic then shows up as a huge length.
    if batch_json >= 0x2200_0000 || batch_bin >= 0x2200_0000 {
        bail!("a legacy b3dm header (written before 3D Tiles 1.0), which is not supported");
    }
    let tables = [feature_json, feature_bin, batch_json, batch_bin];
    let glb_start = tables.iter().try_fold(B3DM_HEADER, |at, &len| at.checked_add(len));
    let Some(glb_start) = glb_start.filter(|&start| start <= bytes.len()) else {
        bail!(
            "b3dm tables ({feature_json} + {feature_bin} + {batch_json} + {batch_bin} bytes) run past the file's {} bytes",
            bytes.len()
        );
    };
    if feature_json > MAX_TABLE_JSON {
        bail!("b3dm feature table JSON of {feature_json} bytes (at most {MAX_TABLE_JSON} are read)");
    }
    let json_bytes = &bytes[B3DM_HEADER..B3DM_HEADER + feature_json];
    let binary = &bytes[B3DM_HEADER + feature_json..B3DM_HEADER + feature_json + feature_bin];
    let rtc_center = if json_bytes.iter().all(u8::is_ascii_whitespace) {
        None
    } else {
        let table: Value = serde_json::from_slice(json_bytes).context("b3dm feature table JSON")?;
        rtc_center(&table, binary)?
    };
    Ok(Batched {
        glb: &bytes[glb_start..],
        rtc_center,
    })
}

fn rtc_center(table: &Value, binary: &[u8]) -> Result<Option<[f64; 3]>> {
    let Some(value) = table.get("RTC_CENTER") else {
        return Ok(None);
    };
    let center = match value {
        Value::Array(items) => finite_triple(items).context("b3dm RTC_CENTER")?,
        Value::Object(reference) => {
            let offset = reference
                .get("byteOffset")
                .and_then(Value::as_u64)
                .context("b3dm RTC_CENTER names no byteOffset")?;
            let at = usize::try_from(offset)
                .ok()
                .filter(|at| at.checked_add(12).is_some_and(|end| end <= binary.len()));
            let Some(at) = at else {
                bail!(
                    "b3dm RTC_CENTER at byte {offset} of a {}-byte feature table body",
                    binary.len()
                );
            };
            let c = [0, 4, 8].map(|o| {
                f64::from(f32::from_le_bytes(
                    binary[at + o..at + o + 4].try_into().expect("4 bytes"),
                ))
            });
            if c.iter().any(|v| !v.is_finite()) {
                bail!("b3dm RTC_CENTER {c:?} is not finite");
            }
            c
        }
        other => bail!("b3dm RTC_CENTER is {other}, not an array of three numbers"),
    };
    Ok(Some(center))
}

/// Three finite numbers.
pub fn finite_triple(items: &[Value]) -> Result<[f64; 3]> {
    let values: Vec<f64> = items.iter().filter_map(Value::as_f64).collect();
    match values[..] {
        [x, y, z] if values.len() == items.len() && values.iter().all(|v| v.is_finite()) => Ok([x, y, z]),
        _ => bail!("expected three finite numbers, found {}", Value::Array(items.to_vec())),
    }
}

/// The JSON of a glTF: a GLB's first chunk, or the whole file.
pub fn gltf_json(bytes: &[u8]) -> Result<Value> {
    let json = if bytes.starts_with(b"glTF") {
        if bytes.len() < 20 || &bytes[16..20] != b"JSON" {
            bail!("a GLB without a JSON chunk first");
        }
        let len = word(bytes, 12) as usize;
        bytes.get(20..20 + len).with_context(|| {
            format!(
                "GLB JSON chunk of {len} bytes runs past the {} bytes given",
                bytes.len()
            )
        })?
    } else {
        bytes
    };
    serde_json::from_slice(json).context("glTF JSON")
}

/// The extensions a glTF requires that the import does not decode (empty when it can be
/// imported): such content is skipped and counted, or refused under `--strict`.
pub fn undecoded_required(json: &Value) -> Vec<String> {
    let required = json.get("extensionsRequired").and_then(Value::as_array);
    crate::gltf::undecoded_extensions(required.into_iter().flatten().filter_map(Value::as_str))
}

/// A glTF's `CESIUM_RTC` centre (Earth-centred, z up), if it has one.
pub fn cesium_rtc(json: &Value) -> Result<Option<[f64; 3]>> {
    let Some(extension) = json.get("extensions").and_then(|e| e.get("CESIUM_RTC")) else {
        return Ok(None);
    };
    let center = extension
        .get("center")
        .and_then(Value::as_array)
        .context("CESIUM_RTC without a center array")?;
    Ok(Some(finite_triple(center).context("CESIUM_RTC center")?))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tiles::write;
    use serde_json::json;

    #[test]
    fn a_written_b3dm_reads_back_with_its_centre() {
        let glb = write::glb(&json!({"asset": {"version": "2.0"}}), &[]);
        let file = write::b3dm(
            &glb,
            &json!({"BATCH_LENGTH": 0, "RTC_CENTER": [1.5, -2.0, 6.4e6]}),
            Some(&json!({"name": []})),
            &[1, 2, 3],
        );
        let batched = parse_b3dm(&file).expect("b3dm");
        assert_eq!(batched.glb, &glb[..]);
        assert_eq!(batched.rtc_center, Some([1.5, -2.0, 6.4e6]));
    }

    #[test]
    fn the_centre_may_lie_in_the_binary_body() {
        let glb = write::glb(&json!({"asset": {"version": "2.0"}}), &[]);
        let mut file = write::b3dm(
            &glb,
            &json!({"BATCH_LENGTH": 0, "RTC_CENTER": {"byteOffset": 0}}),
            None,
            &[],
        );
        // Move 12 bytes of body into the feature table's binary section.
        let json_len = word(&file, 12) as usize;
        let body: Vec<u8> = [1.0f32, 2.0, 3.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .chain([0; 4])
            .collect();
        let at = B3DM_HEADER + json_len;
        file.splice(at..at, body.iter().copied());
        file[16..20].copy_from_slice(&16u32.to_le_bytes());
        let total = file.len() as u32;
        file[8..12].copy_from_slice(&total.to_le_bytes());
        assert_eq!(parse_b3dm(&file).expect("b3dm").rtc_center, Some([1.0, 2.0, 3.0]));
    }

    #[test]
    fn damaged_b3dm_headers_are_refused_with_the_reason() {
        let glb = write::glb(&json!({"asset": {"version": "2.0"}}), &[]);
        let good = write::b3dm(&glb, &json!({"BATCH_LENGTH": 0}), None, &[]);
        let error = |file: &[u8]| format!("{:#}", parse_b3dm(file).expect_err("refused"));
        assert!(error(&good[..20]).contains("header"));
        let mut longer = good.clone();
        longer.push(0);
        assert!(error(&longer).contains("declares"));
        let mut version = good.clone();
        version[4] = 2;
        assert!(error(&version).contains("version 2"));
        // Legacy headers: a glTF's magic where the batch table lengths are now.
        for at in [20, 24] {
            let mut legacy = good.clone();
            legacy[at..at + 4].copy_from_slice(b"glTF");
            assert!(error(&legacy).contains("legacy"), "{}", error(&legacy));
        }
        let mut past = good.clone();
        past[24..28].copy_from_slice(&100_000u32.to_le_bytes());
        assert!(error(&past).contains("run past"));
        let mut nan = write::b3dm(&glb, &json!({"RTC_CENTER": [1.0, 2.0]}), None, &[]);
        assert!(error(&nan).contains("three finite numbers"));
        nan = write::b3dm(&glb, &json!({"RTC_CENTER": {"byteOffset": 4}}), None, &[]);
        assert!(error(&nan).contains("byte 4"));
    }

    #[test]
    fn only_required_extensions_the_import_does_not_decode_are_named() {
        let gltf = json!({"asset": {"version": "2.0"}, "extensionsRequired": [
            "KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_mesh_quantization",
            "KHR_texture_basisu", "KHR_materials_pbrSpecularGlossiness"]});
        assert_eq!(undecoded_required(&gltf), ["KHR_materials_pbrSpecularGlossiness"]);
        assert!(undecoded_required(&json!({"extensionsUsed": ["EXT_texture_webp"]})).is_empty());
        let rtc = json!({"extensions": {"CESIUM_RTC": {"center": [1.0, 2.0, 3.0]}}});
        assert_eq!(cesium_rtc(&rtc).expect("centre"), Some([1.0, 2.0, 3.0]));
        assert!(cesium_rtc(&json!({"extensions": {"CESIUM_RTC": {"center": [1.0, "x", 3.0]}}})).is_err());
    }
}
