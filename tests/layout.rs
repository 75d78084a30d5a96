//! The layering docs/architecture.md states: core ← io ← runtime ← cli (and the Python
//! package on top), and within each crate no module importing one that imports it back, at
//! any depth: paths through `crate::`, `super::` and `self::` are resolved to the module they
//! name, and the children of every module are checked for a cycle among themselves. Read from
//! the sources, comments and `#[cfg(test)]` modules left out.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const CRATES: [(&str, &str); 5] = [
    ("sunjitter_core", "crates/sunjitter-core/src"),
    ("sunjitter_io", "crates/sunjitter-io/src"),
    ("sunjitter_runtime", "crates/sunjitter-runtime/src"),
    ("sunjitter", "src"),
    ("_sunjitter", "python/src"),
];

/// A module's path from its crate's root (`[]` for the root).
type Module = Vec<String>;

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

/// The module a file holds: `engine/refine/mod.rs` → `engine::refine`.
fn file_module(base: &Path, file: &Path) -> Module {
    let rel = file.strip_prefix(base).unwrap().with_extension("");
    let mut parts: Module = rel
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    if parts.len() == 1 && ["lib", "main"].contains(&parts[0].as_str())
        || parts.last().is_some_and(|p| p == "mod")
    {
        parts.pop();
    }
    parts
}

fn without_comments(text: &str) -> String {
    text.lines()
        .map(|l| l.find("//").map_or(l, |i| &l[..i]))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The end of the block whose `{` is at `open`: its matching `}`.
fn block_end(text: &str, open: usize) -> usize {
    let mut depth = 0usize;
    for (i, c) in text[open..].char_indices() {
        match c {
            '{' => depth += 1,
            '}' => {
                depth -= 1;
                if depth == 0 {
                    return open + i;
                }
            }
            _ => {}
        }
    }
    text.len()
}

fn is_ident(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// `text` split into the code of its own module and of each inline `mod name { … }`, test
/// modules (`#[cfg(test)] mod …`) dropped.
fn split_inline(module: &Module, text: &str, out: &mut Vec<(Module, String)>) {
    let mut own = String::new();
    let mut rest = text;
    loop {
        let found = rest.match_indices("mod ").find(|(i, _)| {
            rest[..*i].chars().next_back().is_none_or(|c| !is_ident(c))
                && rest[i + 4..]
                    .trim_start()
                    .starts_with(|c: char| is_ident(c))
                && rest[i + 4..]
                    .trim_start()
                    .trim_start_matches(is_ident)
                    .trim_start()
                    .starts_with('{')
        });
        let Some((at, _)) = found else {
            own.push_str(rest);
            break;
        };
        let name: String = rest[at + 4..]
            .trim_start()
            .chars()
            .take_while(|&c| is_ident(c))
            .collect();
        let open = at + rest[at..].find('{').unwrap();
        let end = block_end(rest, open);
        let before = &rest[..at];
        let mut head = before.trim_end();
        for vis in ["pub(crate)", "pub(super)", "pub"] {
            head = head.strip_suffix(vis).unwrap_or(head).trim_end();
        }
        let is_test = head.ends_with("#[cfg(test)]");
        own.push_str(before);
        if !is_test {
            let mut inner = module.clone();
            inner.push(name);
            split_inline(&inner, &rest[open + 1..end.min(rest.len())], out);
        }
        rest = &rest[(end + 1).min(rest.len())..];
    }
    out.push((module.clone(), own));
}

/// Skips whitespace from `at`.
fn skip_space(s: &[char], mut at: usize) -> usize {
    while at < s.len() && s[at].is_whitespace() {
        at += 1;
    }
    at
}

/// The paths of the use tree (or expression path) starting at `at`, as segment lists, and
/// where it ends: `super::{a, b::{c, self}}` → `super::a`, `super::b::c`, `super::b`.
fn use_tree(s: &[char], mut at: usize, prefix: &[String], out: &mut Vec<Vec<String>>) -> usize {
    let mut path = prefix.to_vec();
    loop {
        at = skip_space(s, at);
        if at < s.len() && s[at] == '{' {
            at += 1;
            loop {
                at = skip_space(s, at);
                if at >= s.len() {
                    return at;
                }
                if s[at] == '}' {
                    return at + 1;
                }
                if s[at] == ',' {
                    at += 1;
                    continue;
                }
                let before = at;
                at = use_tree(s, at, &path, out);
                // `as name` and anything else the tree does not read.
                while at < s.len() && !matches!(s[at], ',' | '}') {
                    at += 1;
                }
                if at == before {
                    at += 1;
                }
            }
        }
        let start = at;
        while at < s.len() && is_ident(s[at]) {
            at += 1;
        }
        if at == start {
            break;
        }
        let segment: String = s[start..at].iter().collect();
        if segment != "self" || path.is_empty() {
            path.push(segment);
        }
        let next = skip_space(s, at);
        if s.get(next) == Some(&':') && s.get(next + 1) == Some(&':') {
            at = next + 2;
            if s.get(skip_space(s, at)) == Some(&'*') {
                return skip_space(s, at) + 1; // a glob: only what it brings is named
            }
        } else {
            break;
        }
    }
    out.push(path);
    at
}

/// `tree`'s segments from `module`: `crate`, `super` and `self` resolved.
fn absolute(module: &Module, tree: Vec<String>) -> Vec<String> {
    let mut path = module.clone();
    let mut segments = tree.into_iter().peekable();
    loop {
        match segments.peek().map(String::as_str) {
            Some("crate") => path.clear(),
            Some("super") => {
                path.pop();
            }
            Some("self") => {}
            _ => break,
        }
        segments.next();
    }
    path.extend(segments);
    path
}

/// Where `code` starts a path with one of `starts` (a word, not the tail of another path).
fn path_starts(code: &[char], starts: &[&str]) -> Vec<(usize, usize)> {
    let mut found = Vec::new();
    for at in 0..code.len() {
        let free = at == 0 || !(is_ident(code[at - 1]) || code[at - 1] == ':');
        if !free {
            continue;
        }
        if let Some(p) = starts
            .iter()
            .find(|p| code[at..].iter().take(p.len()).copied().eq(p.chars()))
        {
            found.push((at, p.len()));
        }
    }
    found
}

/// Every path in `code` that starts `crate::`, `super::` or `self::`, resolved from `module`
/// to the absolute path it names.
fn paths_named(module: &Module, code: &str) -> Vec<Vec<String>> {
    let s: Vec<char> = code.chars().collect();
    let mut found = Vec::new();
    for (at, _) in path_starts(&s, &["crate::", "super::", "self::"]) {
        let mut trees = Vec::new();
        use_tree(&s, at, &[], &mut trees);
        found.extend(trees.into_iter().map(|t| absolute(module, t)));
    }
    found
}

/// The names `code`'s `use` declarations bring into `module` (re-exports among them), and the
/// absolute path each stands for; names from other crates left out.
fn imports(
    module: &Module,
    code: &str,
    modules: &BTreeSet<Module>,
    out: &mut BTreeMap<(Module, String), Vec<String>>,
) {
    let s: Vec<char> = code.chars().collect();
    for (at, len) in path_starts(&s, &["use "]) {
        let mut trees = Vec::new();
        use_tree(&s, at + len, &[], &mut trees);
        for tree in trees.into_iter().filter(|t| !t.is_empty()) {
            let relative = !["crate", "super", "self"].contains(&tree[0].as_str());
            let mut child = module.clone();
            child.push(tree[0].clone());
            if relative && !modules.contains(&child) {
                continue; // another crate's
            }
            let name = tree.last().unwrap().clone();
            out.insert((module.clone(), name), absolute(module, tree));
        }
    }
}

/// The longest start of `path` that is a module of `modules`.
fn module_of<'a>(modules: &'a BTreeSet<Module>, path: &[String]) -> &'a Module {
    (0..=path.len())
        .rev()
        .find_map(|n| modules.get(&path[..n].to_vec()))
        .expect("the root is a module")
}

/// For every module, the graph among its children: `a → b` when anything inside child `a`
/// names anything inside child `b`.
fn sibling_graphs(edges: &BTreeSet<(Module, Module)>) -> BTreeMap<Module, Graph> {
    let mut graphs: BTreeMap<Module, Graph> = BTreeMap::new();
    for (from, to) in edges {
        let common = from.iter().zip(to).take_while(|(a, b)| a == b).count();
        if common == from.len() || common == to.len() {
            continue; // a module and one of its ancestors: not siblings at any level
        }
        graphs
            .entry(from[..common].to_vec())
            .or_default()
            .entry(from[common].clone())
            .or_default()
            .insert(to[common].clone());
    }
    graphs
}

type Graph = BTreeMap<String, BTreeSet<String>>;

/// The modules of the crate in `files` (path, source) and the edges between them: a path
/// through a re-export (`pub use`, or a `use` the module's children read) counts as naming
/// the module it comes from.
fn module_edges(files: &[(Module, String)]) -> (BTreeSet<Module>, BTreeSet<(Module, Module)>) {
    let mut code = Vec::new();
    for (module, text) in files {
        split_inline(module, &without_comments(text), &mut code);
    }
    let mut modules: BTreeSet<Module> = code.iter().map(|(m, _)| m.clone()).collect();
    modules.insert(Vec::new());
    let mut imported = BTreeMap::new();
    for (module, text) in &code {
        imports(module, text, &modules, &mut imported);
    }
    let mut edges = BTreeSet::new();
    for (module, text) in &code {
        for mut path in paths_named(module, text) {
            // Followed through re-exports, a few deep at most.
            for _ in 0..8 {
                let at = module_of(&modules, &path);
                let Some(name) = path.get(at.len()) else {
                    break;
                };
                match imported.get(&(at.clone(), name.clone())) {
                    Some(source) if source != &path[..=at.len()] => {
                        path = [source.clone(), path[at.len() + 1..].to_vec()].concat();
                    }
                    _ => break,
                }
            }
            let to = module_of(&modules, &path);
            if to != module {
                edges.insert((module.clone(), to.clone()));
            }
        }
    }
    (modules, edges)
}

/// The sources of one crate, by module.
fn sources(dir: &str) -> Vec<(Module, String)> {
    let base = Path::new(env!("CARGO_MANIFEST_DIR")).join(dir);
    let mut files = Vec::new();
    rust_files(&base, &mut files);
    files
        .iter()
        .map(|f| (file_module(&base, f), std::fs::read_to_string(f).unwrap()))
        .collect()
}

/// The cycles among the children of each module, each named by that module.
fn cycles(files: &[(Module, String)]) -> Vec<(String, Vec<String>)> {
    let (_, edges) = module_edges(files);
    sibling_graphs(&edges)
        .into_iter()
        .filter_map(|(parent, g)| cycle(&g).map(|c| (parent.join("::"), c)))
        .collect()
}

fn first_cycle(files: &[(Module, String)]) -> Option<(String, Vec<String>)> {
    cycles(files).into_iter().next()
}

/// The crates of [`CRATES`] that the sources in `dir` name, other than `name`.
fn crates_named(name: &str, dir: &str) -> BTreeSet<String> {
    let mut crates = BTreeSet::new();
    for (_, text) in sources(dir) {
        let text = without_comments(&text);
        for (other, _) in CRATES {
            let named = text
                .match_indices(&format!("{other}::"))
                .any(|(i, _)| text[..i].chars().next_back().is_none_or(|c| !is_ident(c)));
            if other != name && named {
                crates.insert(other.to_string());
            }
        }
    }
    crates
}

/// A cycle in `g`, if there is one.
fn cycle(g: &Graph) -> Option<Vec<String>> {
    fn visit(
        g: &Graph,
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
        let files = sources(dir);
        assert!(files.len() >= 3, "{name}: sources not found under {dir}");
        assert_eq!(
            cycles(&files),
            [],
            "{name}: import cycles (module, cycle among its children)"
        );
    }
}

#[test]
fn crates_depend_one_way() {
    for (rank, (name, dir)) in CRATES.iter().enumerate() {
        let named = crates_named(name, dir);
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
    let g: Graph = [
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

/// A crate of a few files, `(path from the root, source)`.
fn toy(files: &[(&str, &str)]) -> Vec<(Module, String)> {
    files
        .iter()
        .map(|(m, text)| {
            let module = m
                .split("::")
                .filter(|p| !p.is_empty())
                .map(String::from)
                .collect();
            (module, text.to_string())
        })
        .collect()
}

#[test]
fn cycles_through_super_self_and_groups_are_found_at_any_depth() {
    let lib = ("", "pub mod engine; pub mod stats;");
    let engine = ("engine", "mod align; mod seed; pub use align::run;");
    // align → seed through a group, seed → align through `super::super::engine::`.
    let cycle = toy(&[
        lib,
        engine,
        (
            "engine::align",
            "use super::{seed::{self, SEED}, Image};
fn f() {}",
        ),
        (
            "engine::seed",
            "pub const SEED: u8 = 1;
fn g() { super::super::engine::align::f() }",
        ),
    ]);
    assert_eq!(
        first_cycle(&cycle),
        Some((
            "engine".to_string(),
            vec!["align".to_string(), "seed".to_string()]
        ))
    );
    // The same through `crate::` and `self::` from an inline module.
    let inline = toy(&[
        lib,
        engine,
        ("engine::align", "use crate::engine::seed::SEED;"),
        (
            "engine::seed",
            "mod inner { use self::super::super::align::f; }",
        ),
    ]);
    assert!(first_cycle(&inline).is_some());
    // One way only, tests and comments left out, a child naming its parent: no cycle.
    let acyclic = toy(&[
        lib,
        engine,
        ("engine::align", "use super::seed::SEED;"),
        (
            "engine::seed",
            "// super::align::f
use super::Image;
#[cfg(test)]
mod tests { use super::super::align::f; }",
        ),
        ("stats", "use crate::engine::run;"),
    ]);
    assert_eq!(first_cycle(&acyclic), None);
    // Through a re-export of the parent: seed names `engine::run`, which is align's.
    let reexport = toy(&[
        lib,
        engine,
        ("engine::align", "use super::seed::SEED; pub fn run() {}"),
        (
            "engine::seed",
            "pub const SEED: u8 = 1; fn g() { crate::engine::run() }",
        ),
    ]);
    assert_eq!(
        first_cycle(&reexport),
        Some((
            "engine".to_string(),
            vec!["align".to_string(), "seed".to_string()]
        ))
    );
    // Between top-level modules.
    let top = toy(&[
        lib,
        engine,
        ("stats", "use crate::engine::run;"),
        ("engine::align", "fn f() { crate::stats::x() }"),
    ]);
    assert_eq!(
        first_cycle(&top),
        Some((
            String::new(),
            vec!["engine".to_string(), "stats".to_string()]
        ))
    );
}
