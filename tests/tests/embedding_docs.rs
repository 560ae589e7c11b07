//! docs/EMBEDDING.md against what it describes: its Rust and GLSL snippets
//! are excerpts of the example host (`engine/examples/embed_host`), and the
//! include directory a host's build script reads is citystream's.

use std::path::{Path, PathBuf};

fn repository() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()))
}

/// The fenced blocks of `markdown` whose info string is exactly `language`
/// (`rust,ignore` and other variants are not excerpts), with their first line.
fn snippets(markdown: &str, language: &str) -> Vec<(usize, Vec<String>)> {
    let mut found = Vec::new();
    let mut open: Option<(usize, Vec<String>)> = None;
    for (number, line) in markdown.lines().enumerate() {
        let fence = line.trim_start().strip_prefix("```");
        match (&mut open, fence) {
            (None, Some(info)) if info.trim() == language => open = Some((number + 2, Vec::new())),
            (None, Some(_)) => open = Some((0, Vec::new())),
            (Some(_), Some(_)) => {
                if let Some((first, lines)) = open.take() {
                    if first > 0 {
                        found.push((first, lines));
                    }
                }
            }
            (Some((_, lines)), None) => lines.push(line.to_owned()),
            (None, None) => {}
        }
    }
    found
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
        let at =
            (from..=source.len().saturating_sub(run.len())).find(|&start| source[start..start + run.len()] == *run);
        match at {
            Some(start) => from = start + run.len(),
            None => return Some(run.join("\n")),
        }
    }
    None
}

#[test]
fn every_rust_and_glsl_snippet_of_embedding_md_is_an_excerpt_of_the_example_host() {
    let root = repository();
    let doc = read(&root.join("docs/EMBEDDING.md"));
    let example = root.join("engine/examples/embed_host");
    let rust = read(&example.join("main.rs"));
    let glsl: String = ["host_feedback.frag", "host_visible.frag"]
        .iter()
        .map(|name| read(&example.join("shaders").join(name)))
        .collect::<Vec<_>>()
        .join("\n");
    let mut checked = 0;
    for (language, source) in [("rust", &rust), ("glsl", &glsl)] {
        for (line, snippet) in snippets(&doc, language) {
            if let Some(missing) = mismatch(&snippet, source) {
                panic!("docs/EMBEDDING.md line {line}: this {language} is not in the example host:\n{missing}");
            }
            checked += 1;
        }
    }
    assert!(checked >= 5, "only {checked} snippets checked: the markers changed?");
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
    let doc = "```rust\nx\n```\n```rust,ignore\ny\n```\n```glsl\nz\n```\n";
    assert_eq!(snippets(doc, "rust"), vec![(2, vec!["x".to_owned()])]);
    assert_eq!(snippets(doc, "glsl"), vec![(8, vec!["z".to_owned()])]);
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
