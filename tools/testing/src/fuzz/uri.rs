//! URI shapes the glTF and tileset harnesses put where a buffer, image or tile content
//! names its file, and the decoy files that make their naive readings exist.

use std::ops::Range;
use std::path::Path;

use anyhow::{Context, Result};

use super::{base64, quad_buffer};

/// A URI a glTF buffer or image or a tile's content is given in place of its own and, for
/// some data URIs, the `byteLength` its object then declares.
#[derive(Clone, Debug)]
pub(crate) struct UriShape {
    pub(crate) uri: String,
    pub(crate) byte_length: Option<&'static str>,
}

/// URI shapes that broke the import or that a resolver must refuse or keep inside: schemes
/// (`file:` of a device, of a file outside, of a name a decoy has), escapes that are not
/// UTF-8 or decode to a separator, paths outside or absolute, drive letters and UNC names,
/// queries and fragments, data URIs (valid, truncated, bad base64, a declared length far
/// beyond their bytes), empty, very long, NUL and control characters, U+FFFD, and names of
/// the tileset's own files (cycles). [`write_uri_decoys`] makes the naive readings exist.
pub(crate) fn uri_shapes() -> Vec<UriShape> {
    let fixed = [
        "file:/dev/zero",
        "file:///dev/zero",
        "FILE:/dev/zero",
        "file:/etc/passwd",
        "file:///etc/passwd",
        "file:/citystream-fuzz/outside.bin",
        "file:x.bin",
        "file:",
        "file://",
        "%FF.bin",
        "%C3%28.bin",
        "%EF%BF%BD.bin",
        "%2F..%2Fx.bin",
        "%2e%2e/outside.bin",
        "..%2Foutside.bin",
        "%00.bin",
        "%",
        "a%2",
        "../outside.bin",
        "../../outside.bin",
        "escape.bin",
        "zero.bin",
        "/abs/path.bin",
        "/dev/zero",
        "//server/share/x.bin",
        "\\\\server\\share\\x.bin",
        "C:\\x.bin",
        "C:/x.bin",
        "c:x.bin",
        "http://example.com/a.glb",
        "https://example.com/a.glb?token=abc",
        "a.glb?token=abc#frag",
        "a.glb#frag",
        "?",
        "#",
        "",
        ".",
        "..",
        "./",
        "sub/../a.glb",
        "a.glb",
        "tileset.json",
        "ext.json",
        "BoxTextured0.bin",
        "CesiumLogoFlat.png",
        "c.bin",
        "c.png",
        "a\0.bin",
        "a\u{1}.bin",
        "a\n.bin",
        "\t",
        "a\u{7f}.bin",
        "\u{fffd}.bin",
        "data:",
        "data:,",
        "data:,not base64",
        "data:;base64,",
        "data:application/octet-stream;base64,!!!!",
        "data:application/octet-stream;base64,A",
        "data:application/octet-stream;base64,====",
    ];
    let mut shapes: Vec<UriShape> = fixed
        .into_iter()
        .map(|uri| UriShape {
            uri: uri.to_owned(),
            byte_length: None,
        })
        .collect();
    let buffer = format!(
        "data:application/octet-stream;base64,{}",
        base64(&quad_buffer(1.0, 2.0).bytes)
    );
    let png = format!(
        "data:image/png;base64,{}",
        base64(&citystream_import::tiles::write::gradient_png(4, 4, 3))
    );
    let generated = [
        buffer.clone(),
        png.clone(),
        // Truncated within a base64 quantum, and by half.
        buffer[..buffer.len() - 7].to_owned(),
        png[..png.len() / 2].to_owned(),
        format!("data:application/octet-stream;base64,{}", "A".repeat(1 << 16)),
        format!("{}.bin", "x".repeat(5000)),
        format!("{}x.bin", "a/".repeat(2100)),
        format!("{}a.glb", "./".repeat(2100)),
        format!("{}outside.bin", "../".repeat(64)),
    ];
    shapes.extend(generated.into_iter().map(|uri| UriShape { uri, byte_length: None }));
    for length in ["4294967296", "18446744073709551615", "9007199254740993", "2147483647"] {
        shapes.push(UriShape {
            uri: buffer.clone(),
            byte_length: Some(length),
        });
    }
    shapes
}

/// Files in `dir` (and `../outside.bin`), each holding `bytes`, that make the naive readings
/// of some URI shapes exist: a `file:` or `http:` URI taken as a relative path, the name
/// `%FF` once decoded to (U+FFFD), a drive letter, a query taken literally; and links to a
/// device and to the file outside. Without them an import that reads such a path instead
/// of refusing the URI would stop at "missing file", and the escape would go unexercised.
pub(crate) fn write_uri_decoys(dir: &Path, bytes: &[u8]) -> Result<()> {
    for name in [
        "file:/dev/zero",
        "file:/etc/passwd",
        "file:/citystream-fuzz/outside.bin",
        "file:x.bin",
        "http:/example.com/a.glb",
        "https:/example.com/a.glb?token=abc",
        "C:\\x.bin",
        "c:x.bin",
        "\u{fffd}.bin",
        "a.glb?token=abc#frag",
    ] {
        let path = dir.join(name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
        }
        std::fs::write(&path, bytes).with_context(|| format!("writing the decoy {}", path.display()))?;
    }
    let outside = dir
        .parent()
        .context("a harness directory has a parent")?
        .join("outside.bin");
    std::fs::write(&outside, bytes).with_context(|| format!("writing {}", outside.display()))?;
    for (link, target) in [("zero.bin", "/dev/zero"), ("escape.bin", "../outside.bin")] {
        std::os::unix::fs::symlink(target, dir.join(link)).with_context(|| format!("linking {link}"))?;
    }
    Ok(())
}

/// Where a URI goes in glTF or tileset JSON: the string of a `"uri"` key, or, in a document
/// without one (a GLB's), the first object of `"buffers"` and of `"images"`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) enum UriSite {
    /// The string token, quotes included.
    Value(Range<usize>),
    /// Just inside the object's `{`.
    Object(usize),
}

pub(crate) fn uri_sites(json: &[u8]) -> Vec<UriSite> {
    let value_of = |key_end: usize| {
        let i = skip_whitespace(json, key_end);
        (json.get(i) == Some(&b':')).then(|| skip_whitespace(json, i + 1))
    };
    let mut sites = Vec::new();
    for at in find_all(json, b"\"uri\"") {
        let Some(i) = value_of(at + 5).filter(|&i| json.get(i) == Some(&b'"')) else {
            continue;
        };
        let mut j = i + 1;
        while j < json.len() && json[j] != b'"' {
            j += if json[j] == b'\\' { 2 } else { 1 };
        }
        if j < json.len() {
            sites.push(UriSite::Value(i..j + 1));
        }
    }
    if sites.is_empty() {
        for key in [&b"\"buffers\""[..], b"\"images\""] {
            for at in find_all(json, key) {
                let Some(i) = value_of(at + key.len()).filter(|&i| json.get(i) == Some(&b'[')) else {
                    continue;
                };
                let i = skip_whitespace(json, i + 1);
                if json.get(i) == Some(&b'{') {
                    sites.push(UriSite::Object(i + 1));
                }
            }
        }
    }
    sites
}

fn find_all(hay: &[u8], needle: &[u8]) -> Vec<usize> {
    hay.windows(needle.len())
        .enumerate()
        .filter(|(_, w)| *w == needle)
        .map(|(i, _)| i)
        .collect()
}

fn skip_whitespace(b: &[u8], mut i: usize) -> usize {
    while b.get(i).is_some_and(u8::is_ascii_whitespace) {
        i += 1;
    }
    i
}

/// Puts `shape` at the URI site `site` (modulo their count) of JSON text, or of the JSON
/// chunk of a GLB (a b3dm's too) whose chunk and file lengths are then kept consistent, so
/// that the shape reaches the resolver rather than the header checks.
pub(crate) fn put_uri(b: &mut Vec<u8>, site: usize, shape: &UriShape) {
    let Some(embedded) = embedded_json(b) else {
        put_uri_in_json(b, site, shape);
        return;
    };
    let mut json = b[embedded.json.clone()].to_vec();
    put_uri_in_json(&mut json, site, shape);
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let grown = json.len() as i64 - embedded.json.len() as i64;
    b.splice(embedded.json, json);
    for at in embedded.lengths {
        let old = u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]]);
        if let Ok(new) = u32::try_from(i64::from(old) + grown) {
            b[at..at + 4].copy_from_slice(&new.to_le_bytes());
        }
    }
}

/// The JSON chunk of a GLB or of the GLB inside a b3dm, and the offsets of the lengths that
/// cover it (the chunk's, the GLB's, the b3dm's).
struct EmbeddedJson {
    json: Range<usize>,
    lengths: Vec<usize>,
}

fn embedded_json(b: &[u8]) -> Option<EmbeddedJson> {
    let u32_at = |i: usize| {
        b.get(i..i + 4)
            .and_then(|s| <[u8; 4]>::try_from(s).ok())
            .map(|s| u32::from_le_bytes(s) as usize)
    };
    let (glb, mut lengths) = if b.starts_with(b"b3dm") {
        // Feature table and batch table, JSON and binary, before the GLB.
        let tables: usize = [12, 16, 20, 24].into_iter().map(u32_at).sum::<Option<usize>>()?;
        (28 + tables, vec![8])
    } else {
        (0, Vec::new())
    };
    if b.get(glb..glb + 4)? != b"glTF" || b.get(glb + 16..glb + 20)? != b"JSON" {
        return None;
    }
    let start = glb + 20;
    let end = start + u32_at(glb + 12)?;
    if end > b.len() {
        return None;
    }
    lengths.extend([glb + 8, glb + 12]);
    Some(EmbeddedJson {
        json: start..end,
        lengths,
    })
}

fn put_uri_in_json(json: &mut Vec<u8>, site: usize, shape: &UriShape) {
    let sites = uri_sites(json);
    if sites.is_empty() {
        return;
    }
    let quoted = serde_json::Value::from(shape.uri.as_str()).to_string();
    let at = match &sites[site % sites.len()] {
        UriSite::Value(range) => {
            json.splice(range.clone(), quoted.bytes());
            range.start
        }
        UriSite::Object(at) => {
            json.splice(*at..*at, format!("\"uri\":{quoted},").bytes());
            *at
        }
    };
    if let Some(length) = shape.byte_length {
        set_byte_length(json, at, length);
    }
}

/// Sets the `byteLength` of the object around `at` (naively: between the nearest braces).
fn set_byte_length(json: &mut Vec<u8>, at: usize, value: &str) {
    let Some(open) = json[..at].iter().rposition(|&c| c == b'{') else {
        return;
    };
    let close = json[at..]
        .iter()
        .position(|&c| c == b'}')
        .map_or(json.len(), |p| at + p);
    let key = b"\"byteLength\"";
    let Some(k) = find_all(&json[open..close], key).first().map(|p| open + p) else {
        return;
    };
    let i = skip_whitespace(json, k + key.len());
    if json.get(i) != Some(&b':') {
        return;
    }
    let i = skip_whitespace(json, i + 1);
    let len = json[i..]
        .iter()
        .take_while(|c| c.is_ascii_digit() || b"-+.eE".contains(c))
        .count();
    json.splice(i..i + len, value.bytes());
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uri_shapes_go_inside_glb_and_b3dm_with_their_lengths_kept() {
        use citystream_import::tiles::{content, write};
        let u32_at = |b: &[u8], at: usize| u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"));
        let (gltf, bin) = write::textured_quad(
            [[0.0; 3], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]],
            &write::gradient_png(4, 4, 1),
            serde_json::json!({}),
            None,
        );
        let glb = write::glb(&gltf, &bin);
        let b3dm = write::b3dm(&glb, &serde_json::json!({"BATCH_LENGTH": 0}), None, &[]);
        let shape = UriShape {
            uri: "file:/dev/zero\u{0}".into(),
            byte_length: None,
        };
        for mut b in [glb, b3dm] {
            // A GLB's JSON has no URI: site 0 is the first buffer's object.
            put_uri(&mut b, 0, &shape);
            let glb = if b.starts_with(b"b3dm") {
                assert_eq!(u32_at(&b, 8) as usize, b.len(), "b3dm byteLength");
                content::parse_b3dm(&b).expect("b3dm").glb
            } else {
                &b[..]
            };
            assert_eq!(u32_at(glb, 8) as usize, glb.len(), "GLB length");
            assert_eq!(u32_at(glb, 12) % 4, 0, "JSON chunk padded");
            let json = content::gltf_json(glb).expect("GLB JSON");
            assert_eq!(json["buffers"][0]["uri"], serde_json::json!(shape.uri));
            assert_eq!(json["images"][0]["bufferView"], serde_json::json!(3));
        }
    }

    #[test]
    fn uri_shapes_replace_uris_and_declared_lengths() {
        let text = br#"{"buffers": [ {"byteLength": 840, "uri": "a.bin"}, {"uri": "b\"q.bin", "byteLength": 8} ],
            "images": [{"uri": "c.png"}]}"#;
        assert_eq!(uri_sites(text).len(), 3);
        let huge = UriShape {
            uri: "data:application/octet-stream;base64,AAAA".into(),
            byte_length: Some("18446744073709551615"),
        };
        for (site, pointer) in [(0, "/buffers/0"), (1, "/buffers/1")] {
            let mut b = text.to_vec();
            put_uri(&mut b, site, &huge);
            let json: serde_json::Value = serde_json::from_slice(&b).expect("still JSON");
            assert_eq!(
                json.pointer(&format!("{pointer}/uri")),
                Some(&serde_json::json!(huge.uri))
            );
            assert_eq!(
                json.pointer(&format!("{pointer}/byteLength")),
                Some(&serde_json::json!(u64::MAX))
            );
        }
        // NUL and control characters go in escaped: the JSON stays valid and carries them.
        let control = UriShape {
            uri: "a\u{0}\u{1}\n\u{fffd}.bin".into(),
            byte_length: None,
        };
        let mut b = text.to_vec();
        put_uri(&mut b, 2, &control);
        let json: serde_json::Value = serde_json::from_slice(&b).expect("still JSON");
        assert_eq!(json["images"][0]["uri"], serde_json::json!(control.uri));
    }
}
