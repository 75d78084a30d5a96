//! The layering docs/architecture.md states: core ← io ← runtime ← cli, and within each crate
//! no module that imports one importing it back. Read from the sources, comments left out.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const CRATES: [(&str, &str); 4] = [
    ("sunjitter_core", "crates/sunjitter-core/src"),
    ("sunjitter_io", "crates/sunjitter-io/src"),
    ("sunjitter_runtime", "crates/sunjitter-runtime/src"),
    ("sunjitter", "src"),
];

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap().flatten() {
        let path = entry.path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The top-level module a file belongs to (`""` for the crate root).
fn top_module(base: &Path, file: &Path) -> String {
    let rel = file.strip_prefix(base).unwrap().with_extension("");
    let first = rel
        .components()
        .next()
        .unwrap()
        .as_os_str()
        .to_string_lossy();
    match first.as_ref() {
        "lib" | "main" => String::new(),
        m => m.to_string(),
    }
}

fn without_comments(text: &str) -> String {
    text.lines()
        .map(|l| l.find("//").map_or(l, |i| &l[..i]))
        .collect::<Vec<_>>()
        .join("\n")
}

/// Identifiers following `prefix::` in `text`.
fn paths_after<'a>(text: &'a str, prefix: &str) -> Vec<&'a str> {
    let mut found = Vec::new();
    let mut rest = text;
    while let Some(i) = rest.find(prefix) {
        let before = rest[..i].chars().next_back();
        rest = &rest[i + prefix.len()..];
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
            continue;
        }
        let end = rest
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .unwrap_or(rest.len());
        found.push(&rest[..end]);
    }
    found
}

/// Module → modules of the same crate it names, for one crate; and the crates it names.
fn graph(name: &str, dir: &str) -> (BTreeMap<String, BTreeSet<String>>, BTreeSet<String>) {
    let base = Path::new(env!("CARGO_MANIFEST_DIR")).join(dir);
    let mut files = Vec::new();
    rust_files(&base, &mut files);
    let mut modules: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut crates = BTreeSet::new();
    for file in files {
        let module = top_module(&base, &file);
        let text = without_comments(&std::fs::read_to_string(&file).unwrap());
        let deps = modules.entry(module.clone()).or_default();
        for dep in paths_after(&text, "crate::") {
            if dep != module && dep.chars().next().is_some_and(|c| c.is_lowercase()) {
                deps.insert(dep.to_string());
            }
        }
        for (other, _) in CRATES {
            if other != name && !paths_after(&text, &format!("{other}::")).is_empty() {
                crates.insert(other.to_string());
            }
        }
    }
    (modules, crates)
}

/// A cycle in `g`, if there is one.
fn cycle(g: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        g: &BTreeMap<String, BTreeSet<String>>,
        m: &str,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(at) = path.iter().position(|p| p == m) {
            return Some(path[at..].to_vec());
        }
        if done.contains(m) {
            return None;
        }
        path.push(m.to_string());
        for dep in g.get(m).into_iter().flatten() {
            if let Some(c) = visit(g, dep, path, done) {
                return Some(c);
            }
        }
        path.pop();
        done.insert(m.to_string());
        None
    }
    let mut done = BTreeSet::new();
    g.keys()
        .find_map(|m| visit(g, m, &mut Vec::new(), &mut done))
}

#[test]
fn no_module_imports_one_that_imports_it_back() {
    for (name, dir) in CRATES {
        let (modules, _) = graph(name, dir);
        assert!(modules.len() >= 3, "{name}: sources not found under {dir}");
        assert_eq!(cycle(&modules), None, "{name}: import cycle");
    }
}

#[test]
fn crates_depend_one_way() {
    for (rank, (name, dir)) in CRATES.iter().enumerate() {
        let (_, named) = graph(name, dir);
        let later: Vec<&str> = CRATES[rank + 1..].iter().map(|(n, _)| *n).collect();
        let upward: Vec<&String> = named
            .iter()
            .filter(|c| later.contains(&c.as_str()))
            .collect();
        assert!(
            upward.is_empty(),
            "{name} names {upward:?}, which depend on it"
        );
    }
}

#[test]
fn the_cycle_check_finds_a_cycle() {
    let g: BTreeMap<String, BTreeSet<String>> = [
        ("a", vec!["b"]),
        ("b", vec!["c"]),
        ("c", vec!["a"]),
        ("d", vec!["a"]),
    ]
    .into_iter()
    .map(|(m, d)| (m.into(), d.into_iter().map(String::from).collect()))
    .collect();
    assert_eq!(cycle(&g).map(|c| c.len()), Some(3));
}
