//! The coordinate reference system (CRS) a dataset's origin is given in.
//!
//! A dataset's scene frame is metres, right-handed, +y up, +x east and +z south; a point's
//! absolute scene coordinates are the origin plus its position. When the dataset names a CRS
//! (a projected one: UTM, a national grid), those coordinates *are* that CRS's, axes
//! permuted: easting = x, northing = −z, height = y ([`Crs::from_scene`]). Ground imagery,
//! camera paths and anything else placed over a city is georeferenced in the same CRS.
//!
//! A CRS is stored as text: `EPSG:<code>` or OGC WKT (WKT1 or WKT2). This crate does not
//! reproject, so it only needs to recognise two texts that name the same CRS: equal EPSG
//! codes (a WKT's top-level `ID["EPSG",n]` or `AUTHORITY["EPSG","n"]` counts), or equal WKT
//! text up to whitespace outside quoted strings.

use std::fmt;

/// Longest CRS text a dataset stores: WKT2 of a projected CRS is 1–3 KB.
pub const MAX_CRS_BYTES: usize = 16 * 1024;

/// Why a text is not a CRS this crate accepts.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CrsError {
    /// Nothing but whitespace.
    #[error("the CRS is empty (expected EPSG:<code> or WKT)")]
    Empty,
    /// Longer than [`MAX_CRS_BYTES`].
    #[error("the CRS text is {0} bytes, more than the {MAX_CRS_BYTES} a dataset stores")]
    TooLong(usize),
    /// `EPSG:` followed by something other than a positive decimal code.
    #[error("`{0}` is not an EPSG code (expected EPSG:<positive integer>, e.g. EPSG:25833)")]
    BadEpsg(String),
    /// Neither `EPSG:<code>` nor well-formed WKT.
    #[error("not a CRS: {0} (expected EPSG:<code>, e.g. EPSG:25833, or OGC WKT such as PROJCRS[...])")]
    NotWkt(String),
}

/// A coordinate reference system, named by an EPSG code or described by WKT.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Crs {
    /// `EPSG:<code>` (normalised) or the WKT as given, trimmed.
    text: String,
}

impl Crs {
    /// Parses `EPSG:<code>` (any case; stored as `EPSG:<code>`) or OGC WKT: a keyword, then
    /// `[`…`]` with balanced brackets outside `"quoted"` strings, printable text only.
    pub fn parse(text: &str) -> Result<Self, CrsError> {
        let text = text.trim();
        if text.is_empty() {
            return Err(CrsError::Empty);
        }
        if text.len() > MAX_CRS_BYTES {
            return Err(CrsError::TooLong(text.len()));
        }
        if let Some(code) = strip_prefix_ignore_case(text, "EPSG:") {
            let code = parse_epsg_code(code).ok_or_else(|| CrsError::BadEpsg(text.to_owned()))?;
            return Ok(Self::epsg(code));
        }
        check_wkt(text).map_err(CrsError::NotWkt)?;
        Ok(Self { text: text.to_owned() })
    }

    /// The CRS `EPSG:<code>`.
    pub fn epsg(code: u32) -> Self {
        Self {
            text: format!("EPSG:{code}"),
        }
    }

    /// The text stored in a dataset: `EPSG:<code>` or the WKT.
    pub fn as_str(&self) -> &str {
        &self.text
    }

    /// The EPSG code naming this CRS: the code of `EPSG:<code>`, or a WKT's top-level
    /// identifier (`ID["EPSG",25833]` in WKT2, `AUTHORITY["EPSG","25833"]` in WKT1).
    pub fn epsg_code(&self) -> Option<u32> {
        match strip_prefix_ignore_case(&self.text, "EPSG:") {
            Some(code) => parse_epsg_code(code),
            None => top_level_epsg_id(&self.text),
        }
    }

    /// Whether both name the same CRS: equal EPSG codes, or (where either has none) equal
    /// WKT up to whitespace outside quoted strings. Two descriptions of one CRS written
    /// differently are not recognised; that errs on the side of refusing.
    pub fn same_as(&self, other: &Crs) -> bool {
        match (self.epsg_code(), other.epsg_code()) {
            (Some(a), Some(b)) => a == b,
            _ => normalised_wkt(&self.text) == normalised_wkt(&other.text),
        }
    }

    /// CRS coordinates (easting, northing, height) of a point at absolute scene coordinates
    /// `scene` (origin plus position: x east, y up, z south).
    pub fn from_scene(scene: [f64; 3]) -> [f64; 3] {
        [scene[0], -scene[2], scene[1]]
    }

    /// Absolute scene coordinates (x east, y up, z south) of CRS coordinates
    /// (easting, northing, height); the inverse of [`Crs::from_scene`].
    pub fn to_scene(crs: [f64; 3]) -> [f64; 3] {
        [crs[0], crs[2], -crs[1]]
    }
}

impl fmt::Display for Crs {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.text)
    }
}

impl std::str::FromStr for Crs {
    type Err = CrsError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        Self::parse(text)
    }
}

fn strip_prefix_ignore_case<'a>(text: &'a str, prefix: &str) -> Option<&'a str> {
    let head = text.get(..prefix.len())?;
    head.eq_ignore_ascii_case(prefix).then(|| &text[prefix.len()..])
}

fn parse_epsg_code(code: &str) -> Option<u32> {
    let code = code.trim();
    // Digits only: `u32::from_str` would also take a leading `+`.
    if code.is_empty() || !code.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    code.parse().ok().filter(|&c| c > 0)
}

/// Checks the WKT shape: `KEYWORD[ … ]` with balanced brackets outside quoted strings
/// (a quote inside a string is written twice), nothing after the final `]`.
fn check_wkt(text: &str) -> Result<(), String> {
    let keyword_len = text
        .bytes()
        .take_while(|b| b.is_ascii_alphanumeric() || *b == b'_')
        .count();
    let rest = &text[keyword_len..];
    if keyword_len == 0 || !text.as_bytes()[0].is_ascii_alphabetic() || !matches!(rest.chars().next(), Some('[' | '('))
    {
        return Err(format!("`{}` does not start with a WKT keyword and `[`", preview(text)));
    }
    if let Some(c) = text.chars().find(|c| c.is_control() && !c.is_whitespace()) {
        return Err(format!("control character {c:?} in WKT"));
    }
    let mut open = Vec::new();
    let mut in_string = false;
    for (at, c) in text.char_indices() {
        match c {
            '"' => in_string = !in_string,
            '[' | '(' if !in_string => open.push(if c == '[' { ']' } else { ')' }),
            ']' | ')' if !in_string => {
                if open.pop() != Some(c) {
                    return Err(format!("unbalanced `{c}` at byte {at} of the WKT"));
                }
                if open.is_empty() && !text[at + c.len_utf8()..].trim().is_empty() {
                    return Err(format!("text after the WKT's closing `{c}` at byte {at}"));
                }
            }
            _ => {}
        }
    }
    if in_string {
        return Err("unterminated quoted string in WKT".into());
    }
    if !open.is_empty() {
        return Err(format!("{} unclosed bracket(s) in WKT", open.len()));
    }
    Ok(())
}

fn preview(text: &str) -> String {
    let mut shown: String = text.chars().take(40).collect();
    if shown.len() < text.len() {
        shown.push('…');
    }
    shown
}

/// The WKT with whitespace outside quoted strings removed.
fn normalised_wkt(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut in_string = false;
    for c in text.chars() {
        if c == '"' {
            in_string = !in_string;
        }
        if in_string || !c.is_whitespace() {
            out.push(c);
        }
    }
    out
}

/// The EPSG code of the outermost element's own `ID[...]` / `AUTHORITY[...]` (depth 1), not
/// those of its components (a projected CRS's base CRS has its own).
fn top_level_epsg_id(wkt: &str) -> Option<u32> {
    let text = normalised_wkt(wkt);
    let mut depth = 0usize;
    let mut in_string = false;
    let mut found = None;
    for (at, c) in text.char_indices() {
        match c {
            '"' => in_string = !in_string,
            '[' | '(' if !in_string => {
                if depth == 1 {
                    let keyword_start = text[..at]
                        .rfind(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
                        .map_or(0, |i| i + 1);
                    let keyword = &text[keyword_start..at];
                    if keyword.eq_ignore_ascii_case("ID") || keyword.eq_ignore_ascii_case("AUTHORITY") {
                        found = epsg_in_id(&text[at + 1..]).or(found);
                    }
                }
                depth += 1;
            }
            ']' | ')' if !in_string => depth = depth.saturating_sub(1),
            _ => {}
        }
    }
    found
}

/// `"EPSG",25833]…` or `"EPSG","25833"]…` → 25833.
fn epsg_in_id(args: &str) -> Option<u32> {
    let (authority, rest) = args.split_once(',')?;
    if !authority.trim_matches('"').eq_ignore_ascii_case("EPSG") {
        return None;
    }
    let code = rest.split([',', ']', ')']).next()?;
    parse_epsg_code(code.trim_matches('"'))
}

#[cfg(test)]
mod tests {
    use super::*;

    const UTM33_WKT2: &str = r#"PROJCRS["ETRS89 / UTM zone 33N",
        BASEGEOGCRS["ETRS89", DATUM["European Terrestrial Reference System 1989",
            ELLIPSOID["GRS 1980",6378137,298.257222101]], ID["EPSG",4258]],
        CONVERSION["UTM zone 33N", METHOD["Transverse Mercator", ID["EPSG",9807]]],
        CS[Cartesian,2], AXIS["easting (E)",east], AXIS["northing (N)",north],
        ID["EPSG",25833]]"#;

    #[test]
    fn epsg_codes_are_normalised_and_checked() {
        assert_eq!(Crs::parse(" epsg:25833 ").expect("epsg").as_str(), "EPSG:25833");
        assert_eq!(Crs::parse("EPSG:32633").expect("epsg").epsg_code(), Some(32633));
        for bad in ["EPSG:", "EPSG:+5", "EPSG:0", "EPSG:12a", "EPSG:99999999999"] {
            assert!(matches!(Crs::parse(bad), Err(CrsError::BadEpsg(_))), "{bad}");
        }
        assert_eq!(Crs::parse("  "), Err(CrsError::Empty));
    }

    #[test]
    fn wkt_is_checked_for_shape_and_its_own_id_names_it() {
        let wkt = Crs::parse(UTM33_WKT2).expect("wkt");
        // The projected CRS's own ID, not its base CRS's (4258) or its method's (9807).
        assert_eq!(wkt.epsg_code(), Some(25833));
        assert!(wkt.same_as(&Crs::epsg(25833)));
        assert!(!wkt.same_as(&Crs::epsg(32633)));
        let wkt1 =
            Crs::parse(r#"PROJCS["x",GEOGCS["y",AUTHORITY["EPSG","4326"]],AUTHORITY["EPSG","32633"]]"#).expect("wkt1");
        assert_eq!(wkt1.epsg_code(), Some(32633));
        for bad in [
            "UTM 33N",
            "PROJCRS[\"a\"",
            "PROJCRS[\"a\"]]",
            "PROJCRS(\"a\"]",
            "PROJCRS[\"a]",
            "PROJCRS[\"a\"] trailing",
            "[\"no keyword\"]",
            "PROJCRS[\"a\u{7}\"]",
        ] {
            assert!(matches!(Crs::parse(bad), Err(CrsError::NotWkt(_))), "{bad}");
        }
        assert!(matches!(
            Crs::parse(&format!("LOCAL_CS[\"{}\"]", "a".repeat(MAX_CRS_BYTES))),
            Err(CrsError::TooLong(_))
        ));
    }

    #[test]
    fn wkt_without_ids_compares_by_text_up_to_whitespace() {
        let a = Crs::parse("ENGCRS[\"site grid\", EDATUM[\"a b\"]]").expect("a");
        let b = Crs::parse("ENGCRS[\"site grid\",\n  EDATUM[\"a b\"]]").expect("b");
        let c = Crs::parse("ENGCRS[\"site  grid\", EDATUM[\"a b\"]]").expect("c");
        assert!(a.same_as(&b));
        assert!(!a.same_as(&c), "whitespace inside a name matters");
        assert!(!a.same_as(&Crs::epsg(25833)));
    }

    #[test]
    fn scene_and_crs_axes_map_both_ways() {
        // Generated cities: origin at Berlin's ETRS89 / UTM 33N coordinates, +z south.
        let scene = [391_250.0, 34.0, -5_819_500.0];
        assert_eq!(Crs::from_scene(scene), [391_250.0, 5_819_500.0, 34.0]);
        assert_eq!(Crs::to_scene(Crs::from_scene(scene)), scene);
        // 10 m further south in the scene is 10 m less northing.
        assert_eq!(Crs::from_scene([391_250.0, 34.0, -5_819_490.0])[1], 5_819_490.0);
    }
}
