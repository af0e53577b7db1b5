//! The documentation's relative links and pictures point at files that
//! exist: README.md, ARCHITECTURE.md and every markdown file under docs/
//! (run logs under docs/results/logs excepted).

use crate::common;

use std::path::{Path, PathBuf};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The targets of `[text](target)` and `![alt](target)` outside code spans
/// and fenced blocks.
fn link_targets(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut fenced = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced {
            continue;
        }
        // Drop inline code spans: `a](b)` inside backticks is not a link.
        let mut plain = String::new();
        for (i, part) in line.split('`').enumerate() {
            if i % 2 == 0 {
                plain.push_str(part);
            }
        }
        let mut rest = plain.as_str();
        while let Some(at) = rest.find("](") {
            let after = &rest[at + 2..];
            let Some(end) = after.find(')') else { break };
            out.push(after[..end].to_string());
            rest = &after[end..];
        }
    }
    out
}

#[test]
fn relative_links_and_pictures_resolve() {
    let mut broken = Vec::new();
    let files = common::markdown_files();
    assert!(files.len() >= 10, "found only {files:?}");
    for md in &files {
        let text = std::fs::read_to_string(md).expect("markdown");
        for target in link_targets(&text) {
            let path = target.split('#').next().unwrap_or_default();
            if path.is_empty() || path.contains("://") || path.starts_with("mailto:") {
                continue;
            }
            let resolved = md.parent().expect("parent").join(path);
            if !resolved.exists() {
                broken.push(format!("{}: {target}", md.display()));
            }
        }
    }
    assert!(broken.is_empty(), "broken links:\n{}", broken.join("\n"));
}

#[test]
fn the_readme_stays_short_and_names_every_guide() {
    let readme = std::fs::read_to_string(repo().join("README.md")).expect("README");
    let lines = readme.lines().count();
    assert!(
        lines <= 200,
        "README.md has {lines} lines: move detail to docs/guide/"
    );
    for guide in std::fs::read_dir(repo().join("docs/guide")).expect("docs/guide") {
        let name = guide.expect("entry").file_name();
        let name = name.to_string_lossy();
        assert!(
            readme.contains(&format!("docs/guide/{name}")),
            "README.md does not link docs/guide/{name}"
        );
    }
}

#[test]
fn the_link_scanner_finds_links_and_skips_code() {
    let text =
        "see [a](x.md) and ![p](img/p.png#top)\n`[not](code.md)`\n```\n[no](fenced.md)\n```\n";
    assert_eq!(link_targets(text), vec!["x.md", "img/p.png#top"]);
}
