//! The mutations every harness applies to its seeds: bit flips, extreme fields, splices,
//! truncations; number tokens for text; dataset checksums recomputed.

use citystream_dataset::{MANIFEST_FILE, PACK_FILE, TILES_FILE};
use citystream_streaming::rng::SplitMix64;

use super::uri::{put_uri, UriShape};

pub(crate) fn below(rng: &mut SplitMix64, n: usize) -> usize {
    (rng.next_u64() % n.max(1) as u64) as usize
}

/// Values that break careless arithmetic, as little-endian 4- and 8-byte fields.
const EXTREME_U32: [u32; 9] = [
    0,
    1,
    u32::MAX,
    0x8000_0000,
    0x7fff_ffff,
    0x7fc0_0000, // f32 NaN
    0x7f80_0000, // f32 +inf
    0xff80_0000, // f32 -inf
    0x7149_f2ca, // f32 1e30
];
const EXTREME_U64: [u64; 6] = [
    0,
    u64::MAX,
    1 << 32,
    1 << 63,
    0x7ff8_0000_0000_0000, // f64 NaN
    0x7ff0_0000_0000_0000, // f64 +inf
];
const EXTREME_NUMBERS: [&str; 14] = [
    "0",
    "-0",
    "-1",
    "1e308",
    "-1e308",
    "1e999",
    "NaN",
    "Infinity",
    "4294967296",
    "18446744073709551616",
    "2147483648",
    "1e-320",
    "0.5",
    "99999999999999999999999999999",
];

/// One to four mutations of `original`; `donor` provides spliced bytes, `uris` the URI
/// shapes (none: no URI mutation, and the same inputs as before it existed).
pub(crate) fn mutate(rng: &mut SplitMix64, original: &[u8], donor: &[u8], text: bool, uris: &[UriShape]) -> Vec<u8> {
    let mut b = original.to_vec();
    let count = 1 + below(rng, 4);
    for _ in 0..count {
        let kinds = if text { 10 } else { 8 } + usize::from(!uris.is_empty());
        let kind = below(rng, kinds);
        // Binary inputs skip the two text mutations (8, 9).
        let kind = if !text && kind >= 8 { kind + 2 } else { kind };
        match kind {
            0 if !b.is_empty() => {
                let i = below(rng, b.len());
                b[i] ^= 1 << below(rng, 8);
            }
            1 if !b.is_empty() => {
                let i = below(rng, b.len());
                b[i] = [0u8, 0xff, 0x7f, 0x80, b'0', b'"'][below(rng, 6)];
            }
            2 if b.len() >= 4 => {
                // Aligned fields: headers are made of them.
                let i = below(rng, b.len() / 4) * 4;
                let v = EXTREME_U32[below(rng, EXTREME_U32.len())];
                b[i..i + 4].copy_from_slice(&v.to_le_bytes());
            }
            3 if b.len() >= 8 => {
                let i = below(rng, b.len() / 8) * 8;
                let v = EXTREME_U64[below(rng, EXTREME_U64.len())];
                b[i..i + 8].copy_from_slice(&v.to_le_bytes());
            }
            4 => {
                let keep = below(rng, b.len() + 1);
                b.truncate(keep);
            }
            5 if !donor.is_empty() => {
                // Splice: a run of the donor over a run of the input.
                let from = below(rng, donor.len());
                let len = 1 + below(rng, (donor.len() - from).min(256));
                let at = below(rng, b.len() + 1);
                let end = (at + len).min(b.len());
                b.splice(at..end, donor[from..from + len].iter().copied());
            }
            6 if !b.is_empty() => {
                let at = below(rng, b.len());
                let len = 1 + below(rng, (b.len() - at).min(64));
                if below(rng, 2) == 0 {
                    b.drain(at..at + len);
                } else {
                    let copy: Vec<u8> = b[at..at + len].to_vec();
                    b.splice(at..at, copy);
                }
            }
            7 => {
                let extra: Vec<u8> = (0..1 + below(rng, 32)).map(|_| rng.next_u64() as u8).collect();
                let at = below(rng, b.len() + 1);
                b.splice(at..at, extra);
            }
            8 => replace_number(rng, &mut b),
            9 if !b.is_empty() => {
                // Remove a structural character of JSON.
                let positions: Vec<usize> = b
                    .iter()
                    .enumerate()
                    .filter(|(_, c)| b"{}[],:\"".contains(c))
                    .map(|(i, _)| i)
                    .collect();
                if !positions.is_empty() {
                    b.remove(positions[below(rng, positions.len())]);
                }
            }
            10 if !uris.is_empty() => {
                let shape = &uris[below(rng, uris.len())];
                let site = rng.next_u64() as usize;
                put_uri(&mut b, site, shape);
            }
            _ => {}
        }
    }
    b
}

/// Replaces one number token of JSON text with an extreme one.
fn replace_number(rng: &mut SplitMix64, b: &mut Vec<u8>) {
    let is_number_byte = |c: u8| c.is_ascii_digit() || b"-+.eE".contains(&c);
    let starts: Vec<usize> = (0..b.len())
        .filter(|&i| b[i].is_ascii_digit() && (i == 0 || !is_number_byte(b[i - 1])))
        .collect();
    if starts.is_empty() {
        return;
    }
    let start = starts[below(rng, starts.len())];
    let start = if start > 0 && b[start - 1] == b'-' {
        start - 1
    } else {
        start
    };
    let mut end = start + 1;
    while end < b.len() && is_number_byte(b[end]) {
        end += 1;
    }
    let replacement = EXTREME_NUMBERS[below(rng, EXTREME_NUMBERS.len())];
    b.splice(start..end, replacement.bytes());
}

/// Recomputes the checksum of a dataset file (layout of `docs/DATASET.md`), so that mutated
/// fields reach the checks behind it.
pub(crate) fn fix_dataset_checksum(name: &str, b: &mut [u8]) {
    let crc_of = |parts: &[&[u8]]| {
        let mut hasher = crc32fast::Hasher::new();
        for part in parts {
            hasher.update(part);
        }
        hasher.finalize()
    };
    let (covered_to, crc_at, body_from) = match name {
        TILES_FILE => (44, 44, 48),
        PACK_FILE => (40, 40, usize::MAX),
        MANIFEST_FILE => (24, 24, usize::MAX),
        _ => (32, 32, 40),
    };
    if b.len() < crc_at + 4 || (body_from != usize::MAX && b.len() < body_from) {
        return;
    }
    let crc = if body_from == usize::MAX {
        crc_of(&[&b[..covered_to]])
    } else {
        crc_of(&[&b[..covered_to], &b[body_from..]])
    };
    b[crc_at..crc_at + 4].copy_from_slice(&crc.to_le_bytes());
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn number_tokens_are_replaced_whole() {
        let mut rng = SplitMix64::new(1);
        let mut text = br#"{"t": -12.5e3, "x": [1, 2]}"#.to_vec();
        replace_number(&mut rng, &mut text);
        let text = String::from_utf8(text).expect("utf-8");
        assert!(!text.contains("12.5e3") || !text.contains("[1, 2]"), "{text}");
        assert!(text.starts_with("{\"t\": "), "{text}");
    }
}
