//! docs/EMBEDDING.md against what it describes: each of its Rust snippets is
//! an excerpt of code that is compiled (the example host,
//! `engine/examples/embed_host`; the host build script `tests/build.rs`; the
//! compiled doctests of `engine/src/present.rs`), its GLSL snippets are
//! excerpts of the example host's shaders, and the include directory and
//! Vulkan target a host's build script uses are citystream's.

use std::path::{Path, PathBuf};

fn repository() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()))
}

/// The fenced blocks of `markdown`: their info string (trimmed), first line
/// and lines.
fn fenced_blocks(markdown: &str) -> Vec<(String, usize, Vec<String>)> {
    let mut found = Vec::new();
    let mut open: Option<(String, usize, Vec<String>)> = None;
    for (number, line) in markdown.lines().enumerate() {
        let fence = line.trim_start().strip_prefix("```");
        match (&mut open, fence) {
            (None, Some(info)) => open = Some((info.trim().to_owned(), number + 2, Vec::new())),
            (Some(_), Some(_)) => found.extend(open.take()),
            (Some((_, _, lines)), None) => lines.push(line.to_owned()),
            (None, None) => {}
        }
    }
    found
}

/// The fenced blocks of `markdown` whose info string is exactly `language`,
/// with their first line.
fn snippets(markdown: &str, language: &str) -> Vec<(usize, Vec<String>)> {
    fenced_blocks(markdown)
        .into_iter()
        .filter(|(info, _, _)| info == language)
        .map(|(_, first, lines)| (first, lines))
        .collect()
}

/// The code of the doctests rustdoc compiles in the doc comments of `source`
/// (blocks marked `rust`, `no_run` or nothing), without their hidden (`# `) lines.
fn doctest_code(source: &str) -> String {
    let docs: String = source
        .lines()
        .filter_map(|line| {
            let line = line.trim_start();
            line.strip_prefix("//!").or_else(|| line.strip_prefix("///"))
        })
        .map(|line| format!("{}\n", line.strip_prefix(' ').unwrap_or(line)))
        .collect();
    fenced_blocks(&docs)
        .into_iter()
        .filter(|(info, _, _)| ["", "rust", "no_run", "rust,no_run"].contains(&info.as_str()))
        .flat_map(|(_, _, lines)| lines)
        .filter(|line| {
            let code = line.trim_start();
            code != "#" && !code.starts_with("# ")
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// The lines of `text`, trimmed, blank ones left out.
fn significant(text: &[String]) -> Vec<&str> {
    text.iter().map(|l| l.trim()).filter(|l| !l.is_empty()).collect()
}

/// Where `snippet` does not stand in `source`: each run of lines between
/// `// ...` elisions must appear there as consecutive lines (trimmed), the
/// runs in order.
fn mismatch(snippet: &[String], source: &str) -> Option<String> {
    let source_lines: Vec<String> = source.lines().map(str::to_owned).collect();
    let source = significant(&source_lines);
    let lines = significant(snippet);
    let mut from = 0;
    for run in lines.split(|l| *l == "// ...") {
        if run.is_empty() {
            continue;
        }
        // `windows` yields nothing where the run is longer than what is left.
        let at = source
            .get(from..)
            .and_then(|rest| rest.windows(run.len()).position(|window| window == run))
            .map(|offset| from + offset);
        match at {
            Some(start) => from = start + run.len(),
            None => return Some(run.join("\n")),
        }
    }
    None
}

#[test]
fn every_rust_and_glsl_snippet_of_embedding_md_is_an_excerpt_of_compiled_code() {
    let root = repository();
    let doc = read(&root.join("docs/EMBEDDING.md"));
    let example = root.join("engine/examples/embed_host");
    // Where a Rust snippet may come from: each of these is compiled by the tests.
    let rust_sources = [
        ("the example host", read(&example.join("main.rs"))),
        (
            "the host build script tests/build.rs",
            read(&root.join("tests/build.rs")),
        ),
        (
            "the doctests of engine/src/present.rs",
            doctest_code(&read(&root.join("engine/src/present.rs"))),
        ),
    ];
    let glsl: String = ["host_feedback.frag", "host_visible.frag"]
        .iter()
        .map(|name| read(&example.join("shaders").join(name)))
        .collect::<Vec<_>>()
        .join("\n");
    // A Rust block marked otherwise (`rust,ignore`) would go unchecked.
    for (info, line, _) in fenced_blocks(&doc) {
        assert!(
            !info.starts_with("rust") || info == "rust",
            "docs/EMBEDDING.md line {line}: a Rust snippet marked `{info}` is not checked; mark it `rust`"
        );
    }
    let mut checked = 0;
    for (line, snippet) in snippets(&doc, "rust") {
        if rust_sources
            .iter()
            .all(|(_, source)| mismatch(&snippet, source).is_some())
        {
            let names: Vec<&str> = rust_sources.iter().map(|(name, _)| *name).collect();
            let missing = rust_sources
                .iter()
                .filter_map(|(_, source)| mismatch(&snippet, source))
                .min_by_key(String::len)
                .unwrap_or_default();
            panic!(
                "docs/EMBEDDING.md line {line}: this Rust is in none of {}:\n{missing}",
                names.join(", ")
            );
        }
        checked += 1;
    }
    for (line, snippet) in snippets(&doc, "glsl") {
        if let Some(missing) = mismatch(&snippet, &glsl) {
            panic!("docs/EMBEDDING.md line {line}: this GLSL is not in the example host:\n{missing}");
        }
        checked += 1;
    }
    assert!(checked >= 8, "only {checked} snippets checked: the markers changed?");
}

#[test]
fn an_excerpt_that_differs_from_its_source_is_found() {
    let source = "let a = 1;\nlet b = 2;\n\nlet c = 3;\n";
    let lines = |text: &str| text.lines().map(str::to_owned).collect::<Vec<_>>();
    assert_eq!(mismatch(&lines("let a = 1;\n    let b = 2;"), source), None);
    assert_eq!(mismatch(&lines("let a = 1;\n// ...\nlet c = 3;"), source), None);
    // Lines out of order, or a run split by a line the source has between them.
    assert!(mismatch(&lines("let c = 3;\n// ...\nlet a = 1;"), source).is_some());
    assert!(mismatch(&lines("let a = 1;\nlet c = 3;"), source).is_some());
    assert!(mismatch(&lines("let a = 2;"), source).is_some());
    // A run longer than the source is missing, not out of bounds.
    assert!(mismatch(&lines("let a = 1;"), "").is_some());
    let doc = "```rust\nx\n```\n```rust,ignore\ny\n```\n```glsl\nz\n```\n";
    assert_eq!(snippets(doc, "rust"), vec![(2, vec!["x".to_owned()])]);
    assert_eq!(snippets(doc, "glsl"), vec![(8, vec!["z".to_owned()])]);
    // Doctests: visible lines of compiled blocks only.
    let source = "//! ```no_run\n//! # hidden\n//! let a = 1;\n//! ```\n/// ```ignore\n/// let b = 2;\n/// ```\n";
    assert_eq!(doctest_code(source), "let a = 1;");
}

#[test]
fn a_host_build_script_finds_citystream_s_glsl_includes() {
    // Set by this crate's build script from DEP_CITYSTREAM_INCLUDE, as a host's would read it.
    let include = Path::new(env!("CITYSTREAM_HOST_INCLUDE"));
    assert!(
        include.join("citystream_host.glsl").is_file(),
        "DEP_CITYSTREAM_INCLUDE = {include:?} does not hold citystream_host.glsl"
    );
    let engine_dir = Path::new(citystream_engine::shaders::INCLUDE_DIR);
    assert_eq!(
        include.canonicalize().expect("include dir"),
        engine_dir.canonicalize().expect("INCLUDE_DIR")
    );
}

#[test]
fn a_host_build_script_compiles_for_the_engine_s_vulkan_version() {
    // The SPIR-V the build script compiled with the include directory above.
    let spv = std::fs::read(env!("CITYSTREAM_HOST_SPV")).expect("the build script's SPIR-V");
    let word = |index: usize| u32::from_le_bytes(spv[index * 4..index * 4 + 4].try_into().expect("4 bytes"));
    assert!(spv.len() > 20, "{} bytes of SPIR-V", spv.len());
    assert_eq!(word(0), 0x0723_0203, "not SPIR-V");
    // `--target-env vulkan1.3` writes SPIR-V 1.6: the device the engine requires (Vulkan 1.3) reads it.
    assert_eq!(
        word(1),
        0x0001_0600,
        "SPIR-V version {:#x}, not vulkan1.3's 1.6",
        word(1)
    );
}
