//! Every relative link in the project's Markdown (README, CHANGELOG, CONTRIBUTING, `docs/`, model
//! cards, examples) points to a file that exists, and a `#anchor` into a Markdown file to one of its
//! headings (GitHub's heading ids). Web links are not fetched.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// Folders never searched for Markdown: build outputs, environments, run outputs, VCS.
const SKIPPED_DIRS: [&str; 6] = ["target", "out", "node_modules", "runs", "__pycache__", "build"];

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The Markdown files under `dir`, skipping hidden and build folders.
fn markdown_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') || SKIPPED_DIRS.contains(&name.as_str()) {
            continue;
        }
        // A link to a file (the Python package's copy of the model card) is checked where the
        // file itself lives: its relative links are written from there.
        let is_link = entry.file_type().is_ok_and(|t| t.is_symlink());
        if path.is_dir() && !is_link {
            markdown_files(&path, out);
        } else if name.ends_with(".md") && !is_link {
            out.push(path);
        }
    }
}

/// The lines of `text` outside fenced code blocks.
fn prose_lines(text: &str) -> Vec<&str> {
    let mut inside = false;
    text.lines()
        .filter(|line| {
            if line.trim_start().starts_with("```") {
                inside = !inside;
                return false;
            }
            !inside
        })
        .collect()
}

/// GitHub's id of a heading: lower case, punctuation dropped, spaces as hyphens.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || *c == ' ' || *c == '-' || *c == '_')
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The heading ids of a Markdown text, with GitHub's `-1`, `-2` suffixes for repeated headings.
fn anchors(text: &str) -> BTreeSet<String> {
    let mut seen = BTreeSet::new();
    for line in prose_lines(text) {
        let hashes = line.chars().take_while(|c| *c == '#').count();
        if hashes == 0 || hashes > 6 || !line[hashes..].starts_with(' ') {
            continue;
        }
        let base = slug(&line[hashes..]);
        let mut id = base.clone();
        let mut k = 0;
        while seen.contains(&id) {
            k += 1;
            id = format!("{base}-{k}");
        }
        seen.insert(id);
    }
    seen
}

/// The targets of inline links and images `[text](target)` in prose.
fn link_targets(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    for line in prose_lines(text) {
        // Inline code spans are not links.
        let prose: String = line.split('`').step_by(2).collect::<Vec<_>>().join(" ");
        let mut rest = prose.as_str();
        while let Some(at) = rest.find("](") {
            rest = &rest[at + 2..];
            let Some(end) = rest.find(')') else { break };
            let target = rest[..end].trim();
            let target = target.split_whitespace().next().unwrap_or("");
            out.push(target.trim_matches(|c| c == '<' || c == '>').to_owned());
            rest = &rest[end..];
        }
    }
    out
}

/// The broken relative links of the Markdown file `file`, as "file: target (why)".
fn broken_links(file: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(file).unwrap_or_default();
    let mut broken = Vec::new();
    for target in link_targets(&text) {
        if target.is_empty() || target.contains("://") || target.starts_with("mailto:") {
            continue;
        }
        let (path_part, anchor) = match target.split_once('#') {
            Some((p, a)) => (p, Some(a)),
            None => (target.as_str(), None),
        };
        let resolved = if path_part.is_empty() {
            file.to_path_buf()
        } else {
            file.parent().unwrap_or(Path::new(".")).join(path_part)
        };
        if !resolved.exists() {
            broken.push(format!("{}: {target} (no such file)", file.display()));
            continue;
        }
        if let Some(anchor) = anchor.filter(|_| resolved.extension().is_some_and(|e| e == "md")) {
            let heading_ids = anchors(&std::fs::read_to_string(&resolved).unwrap_or_default());
            if !heading_ids.contains(anchor) {
                broken.push(format!(
                    "{}: {target} (no heading with id '{anchor}')",
                    file.display()
                ));
            }
        }
    }
    broken
}

#[test]
fn every_relative_link_in_the_docs_resolves() {
    let root = repo_root();
    let mut files = Vec::new();
    markdown_files(&root, &mut files);
    files.sort();
    for required in [
        "README.md",
        "CHANGELOG.md",
        "docs/design.md",
        "docs/benchmarks.md",
    ] {
        assert!(files.contains(&root.join(required)), "{required} is missing");
    }
    let broken: Vec<String> = files.iter().flat_map(|f| broken_links(f)).collect();
    assert!(broken.is_empty(), "broken links:\n{}", broken.join("\n"));
}

#[test]
fn the_checker_finds_missing_files_and_anchors() {
    let dir = std::env::temp_dir().join(format!("gelstereo-doc-links-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("docs")).unwrap();
    std::fs::write(
        dir.join("docs/guide.md"),
        "# Guide\n\n## Grids that overfill the view (`placed`)\n\n## Limits\n## Limits\n",
    )
    .unwrap();
    let readme = dir.join("README.md");
    std::fs::write(
        &readme,
        "[ok](docs/guide.md#grids-that-overfill-the-view-placed) [ok](docs/guide.md#limits-1) \
         [web](https://example.org/x) [self](#title)\n# Title\n\
         [gone](docs/missing.md) ![gone too](docs/images/none.png) [bad](docs/guide.md#nowhere)\n\
         ```\n[in code](not/checked.md)\n```\n`[in a code span](not/checked.md)`\n",
    )
    .unwrap();
    let broken = broken_links(&readme);
    std::fs::remove_dir_all(&dir).unwrap();
    assert_eq!(broken.len(), 3, "{broken:#?}");
    assert!(broken[0].contains("docs/missing.md (no such file)"));
    assert!(broken[1].contains("docs/images/none.png (no such file)"));
    assert!(broken[2].contains("no heading with id 'nowhere'"));
}
