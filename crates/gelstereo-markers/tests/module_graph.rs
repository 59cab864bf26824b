//! The modules of this crate import each other without cycles: shared types live in leaf modules
//! (`layout`, `region`, `spacing`, ...) that the steps using them import, never the other way round.
//! The graph is read from the sources: every `crate::module` path and every name of a `crate::{...}`
//! group, a name the crate root re-exports (`pub use module::{...}` in `lib.rs`) counting as its module.
//! The crate root itself (errors, the `Localizer` trait) is left out: every module uses it.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

type Graph = BTreeMap<String, BTreeSet<String>>;

fn source_dir() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/src"))
}

/// `text` without its line comments (doc comments included).
fn without_comments(text: &str) -> String {
    text.lines()
        .map(|line| line.find("//").map_or(line, |at| &line[..at]))
        .collect::<Vec<_>>()
        .join("\n")
}

fn identifier_at(text: &str) -> &str {
    let end = text
        .find(|c: char| !(c.is_alphanumeric() || c == '_'))
        .unwrap_or(text.len());
    &text[..end]
}

/// The first name of each top-level item of a use group's body (`a::b, c, d::{e, f}` gives a, c, d).
fn group_heads(body: &str) -> Vec<&str> {
    let mut heads = Vec::new();
    let (mut depth, mut start) = (0usize, 0usize);
    for (at, c) in body.char_indices() {
        match c {
            '{' => depth += 1,
            '}' => depth = depth.saturating_sub(1),
            ',' if depth == 0 => {
                heads.push(identifier_at(body[start..at].trim_start()));
                start = at + 1;
            }
            _ => {}
        }
    }
    heads.push(identifier_at(body[start..].trim_start()));
    heads.into_iter().filter(|h| !h.is_empty()).collect()
}

/// The body of the brace group opening at `open` (the index just past `{`), up to its matching `}`.
fn group_body(text: &str, open: usize) -> &str {
    let mut depth = 1usize;
    for (at, c) in text[open..].char_indices() {
        match c {
            '{' => depth += 1,
            '}' => {
                depth -= 1;
                if depth == 0 {
                    return &text[open..open + at];
                }
            }
            _ => {}
        }
    }
    &text[open..]
}

/// The names `text` reaches through `crate::`: the first segment of each path, and the heads of
/// each `crate::{...}` group.
fn crate_names(text: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    for (at, _) in text.match_indices("crate::") {
        let rest = &text[at + "crate::".len()..];
        if rest.starts_with('{') {
            let open = at + "crate::{".len();
            names.extend(group_heads(group_body(text, open)).into_iter().map(str::to_owned));
        } else {
            names.insert(identifier_at(rest).to_owned());
        }
    }
    names
}

/// Names the crate root re-exports, with the module each comes from.
fn reexports(lib: &str) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    for (at, _) in lib.match_indices("pub use ") {
        let path = &lib[at + "pub use ".len()..];
        let module = identifier_at(path);
        let rest = &path[module.len()..];
        let Some(rest) = rest.strip_prefix("::") else {
            continue;
        };
        let names = if rest.starts_with('{') {
            group_heads(group_body(path, module.len() + "::{".len()))
        } else {
            vec![identifier_at(rest)]
        };
        for name in names {
            out.insert(name.to_owned(), module.to_owned());
        }
    }
    out
}

/// The module graph of the sources `files` (module name, source text) and the crate root's text.
fn module_graph(files: &BTreeMap<String, String>, lib: &str) -> Graph {
    let reexported = reexports(&without_comments(lib));
    files
        .iter()
        .map(|(module, text)| {
            let uses = crate_names(&without_comments(text))
                .into_iter()
                .filter_map(|name| {
                    if files.contains_key(&name) {
                        Some(name)
                    } else {
                        reexported.get(&name).cloned()
                    }
                })
                .filter(|used| used != module)
                .collect();
            (module.clone(), uses)
        })
        .collect()
}

/// A cycle of `graph` (its modules in import order, the first repeated at the end), if there is one.
fn find_cycle(graph: &Graph) -> Option<Vec<String>> {
    fn visit(
        graph: &Graph,
        node: &str,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(at) = path.iter().position(|n| n == node) {
            let mut cycle = path[at..].to_vec();
            cycle.push(node.to_owned());
            return Some(cycle);
        }
        if done.contains(node) {
            return None;
        }
        path.push(node.to_owned());
        for next in graph.get(node).into_iter().flatten() {
            if let Some(cycle) = visit(graph, next, path, done) {
                return Some(cycle);
            }
        }
        path.pop();
        done.insert(node.to_owned());
        None
    }
    let mut done = BTreeSet::new();
    graph
        .keys()
        .find_map(|start| visit(graph, start, &mut Vec::new(), &mut done))
}

fn this_crate() -> std::io::Result<(BTreeMap<String, String>, String)> {
    let mut files = BTreeMap::new();
    let mut lib = String::new();
    for entry in std::fs::read_dir(source_dir())? {
        let path = entry?.path();
        if path.extension().is_none_or(|e| e != "rs") {
            continue;
        }
        let text = std::fs::read_to_string(&path)?;
        let stem = path
            .file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned();
        if stem == "lib" {
            lib = text;
        } else {
            files.insert(stem, text);
        }
    }
    Ok((files, lib))
}

#[test]
fn the_modules_import_each_other_without_a_cycle() -> std::io::Result<()> {
    let (files, lib) = this_crate()?;
    let graph = module_graph(&files, &lib);
    // The reading itself works: edges known to exist are found.
    assert!(graph["marknet"].contains("layout"), "{graph:?}");
    assert!(graph["lattice"].contains("spacing"), "{graph:?}");
    if let Some(cycle) = find_cycle(&graph) {
        panic!(
            "modules of gelstereo-markers import each other in a cycle: {}; \
             move what they share into a module of its own",
            cycle.join(" -> ")
        );
    }
    Ok(())
}

#[test]
fn a_cycle_through_a_group_or_a_root_reexport_is_found() {
    let lib = "pub mod a;\npub use c::{Shared, other};\n";
    let files: BTreeMap<String, String> = [
        ("a", "use crate::{Error, b::{self, X}};\n"),
        (
            "b",
            "// crate::a in a comment is no import\nfn f() -> crate::Shared { todo!() }\n",
        ),
        ("c", "use crate::a::Thing;\n"),
        ("d", "use crate::c;\n"),
    ]
    .into_iter()
    .map(|(m, t)| (m.to_owned(), t.to_owned()))
    .collect();
    let graph = module_graph(&files, lib);
    assert_eq!(graph["a"], BTreeSet::from(["b".to_owned()]));
    assert_eq!(graph["b"], BTreeSet::from(["c".to_owned()]));
    assert_eq!(
        find_cycle(&graph),
        Some(["a", "b", "c", "a"].map(str::to_owned).to_vec())
    );

    let mut acyclic = files.clone();
    acyclic.insert("c".to_owned(), String::new());
    assert_eq!(find_cycle(&module_graph(&acyclic, lib)), None);
}
