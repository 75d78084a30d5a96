//! Which files are frames: names wanted by the configuration, directory trees, and the
//! files, directories and shell globs `replay` is given. Shared by the daemon and replay.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use sunjitter_core::{Error, Result};

use crate::config::{canonical_file_path, Config, DaemonConfig};

/// Whether a file name is taken as a frame: not ignored, and with a configured extension.
pub fn wanted_file(name: &str, d: &DaemonConfig) -> bool {
    if d.ignore.iter().any(|p| name_matches(p, name)) {
        return false;
    }
    if d.extensions.is_empty() {
        return true;
    }
    let lower = name.to_ascii_lowercase();
    d.extensions.iter().any(|ext| {
        lower.ends_with(&format!(
            ".{}",
            ext.trim_start_matches('.').to_ascii_lowercase()
        ))
    })
}

/// Whether a directory is entered: its name is not ignored.
pub fn wanted_dir(path: &Path, d: &DaemonConfig) -> bool {
    path.file_name()
        .map(|n| n.to_string_lossy())
        .is_some_and(|n| !d.ignore.iter().any(|p| name_matches(p, &n)))
}

/// Every wanted file under `root` (recursively if asked), sorted. Symbolic links to files
/// are listed (the pipeline reports them when not followed); linked directories are entered
/// only when `follow_symlinks`. Directories that are, or lie inside, one of `excluded` (the
/// run's own outputs, compared by identity whatever the link that leads there) are not
/// entered.
pub fn scan_tree(
    root: &Path,
    recursive: bool,
    follow_symlinks: bool,
    d: &DaemonConfig,
    excluded: &[sunjitter_io::outputs::FileId],
) -> Result<Vec<PathBuf>> {
    let mut found = Vec::new();
    let mut dirs = vec![root.to_path_buf()];
    let mut visited = std::collections::HashSet::new();
    while let Some(dir) = dirs.pop() {
        if let Ok(canon) = dir.canonicalize() {
            if !visited.insert(canon) {
                continue; // a link cycle
            }
        }
        let entries = std::fs::read_dir(&dir).map_err(|e| Error::io(&dir, e))?;
        for entry in entries.flatten() {
            let path = entry.path();
            let Ok(file_type) = entry.file_type() else {
                continue;
            };
            let is_dir =
                file_type.is_dir() || (file_type.is_symlink() && follow_symlinks && path.is_dir());
            if is_dir {
                if recursive && wanted_dir(&path, d) {
                    if let Some(output) = excluded_output(&path, excluded) {
                        tracing::warn!(
                            dir = %sunjitter_core::text::path(&path),
                            "leads into {}, where this run writes: not entered",
                            sunjitter_core::text::path(&output)
                        );
                        continue;
                    }
                    dirs.push(path);
                }
                continue;
            }
            if let Some(name) = path.file_name().map(|n| n.to_string_lossy()) {
                if wanted_file(&name, d) {
                    found.push(path);
                }
            }
        }
    }
    found.sort();
    Ok(found)
}

/// The real path of `path` when it is, or lies inside, one of the `excluded` directories.
pub fn excluded_output(path: &Path, excluded: &[sunjitter_io::outputs::FileId]) -> Option<PathBuf> {
    if excluded.is_empty() {
        return None;
    }
    excluded
        .iter()
        .any(|id| sunjitter_io::outputs::is_within(path, *id))
        .then(|| path.canonicalize().unwrap_or_else(|_| path.to_path_buf()))
}

/// Shell-style wildcard match of one file name: `*`, `?`, `[abc]`, `[a-z]`, `[!x]`.
pub fn name_matches(pattern: &str, name: &str) -> bool {
    fn class(p: &[char], c: char) -> Option<(bool, usize)> {
        // p starts after '['; returns (matched, length consumed including ']').
        let mut i = 0;
        let negate = matches!(p.first(), Some('!') | Some('^'));
        if negate {
            i += 1;
        }
        let mut matched = false;
        let mut first = true;
        while i < p.len() {
            if p[i] == ']' && !first {
                return Some((matched != negate, i + 1));
            }
            first = false;
            if i + 2 < p.len() && p[i + 1] == '-' && p[i + 2] != ']' {
                if p[i] <= c && c <= p[i + 2] {
                    matched = true;
                }
                i += 3;
            } else {
                if p[i] == c {
                    matched = true;
                }
                i += 1;
            }
        }
        None
    }
    fn go(p: &[char], s: &[char]) -> bool {
        match p.first() {
            None => s.is_empty(),
            Some('*') => (0..=s.len()).any(|k| go(&p[1..], &s[k..])),
            Some('?') => !s.is_empty() && go(&p[1..], &s[1..]),
            Some('[') => match (s.first(), class(&p[1..], *s.first().unwrap_or(&'\0'))) {
                (Some(_), Some((true, used))) => go(&p[1 + used..], &s[1..]),
                (Some(_), Some((false, _))) | (None, _) => false,
                (Some(c), None) => *c == '[' && go(&p[1..], &s[1..]),
            },
            Some(c) => s.first() == Some(c) && go(&p[1..], &s[1..]),
        }
    }
    let p: Vec<char> = pattern.chars().collect();
    let s: Vec<char> = name.chars().collect();
    go(&p, &s)
}

/// Expand `replay` arguments (files, directories, shell globs) to canonical file paths,
/// each with whether it was named explicitly (explicit symbolic links are followed).
/// An argument that matches nothing is a usage error (exit code 2).
pub fn expand_inputs(args: &[String], config: &Config) -> Result<Vec<(std::path::PathBuf, bool)>> {
    let d = &config.daemon;
    let mut out: Vec<(std::path::PathBuf, bool)> = Vec::new();
    let mut seen = HashSet::new();
    let mut push = |path: std::path::PathBuf, explicit: bool, out: &mut Vec<_>| -> Result<()> {
        let canon = canonical_file_path(&path)?;
        if seen.insert(canon.clone()) {
            out.push((canon, explicit));
        }
        Ok(())
    };
    for arg in args {
        let path = Path::new(arg);
        if !path.exists() {
            let spec = sunjitter_io::fits::parse_frame_key(arg);
            if let (Some(n), true) = (spec.frame, spec.path.is_file()) {
                return Err(Error::Usage(format!(
                    "{}: replay takes whole files, and this names frame {n} of {}: give the file (replay measures every frame of a cube), or measure one frame with `sunjitter align`",
                    sunjitter_core::text::escape(arg),
                    sunjitter_core::text::path(&spec.path)
                )));
            }
        }
        let matches: Vec<std::path::PathBuf> = if path.exists() || !has_wildcards(arg) {
            vec![path.to_path_buf()]
        } else {
            glob(arg)?
        };
        if matches.is_empty() || (matches.len() == 1 && !matches[0].exists()) {
            return Err(Error::bad_input(path, "no such file or directory"));
        }
        for m in matches {
            if m.is_dir() {
                for f in scan_tree(&m, d.recursive, d.follow_symlinks, d, &[])? {
                    push(f, false, &mut out)?;
                }
            } else {
                push(m, true, &mut out)?;
            }
        }
    }
    Ok(out)
}

fn has_wildcards(s: &str) -> bool {
    s.contains(['*', '?', '['])
}

/// Shell-style glob over path components (for quoted patterns the shell did not expand).
fn glob(pattern: &str) -> Result<Vec<std::path::PathBuf>> {
    use std::path::{Component, PathBuf};
    let mut current: Vec<PathBuf> = vec![PathBuf::new()];
    for component in Path::new(pattern).components() {
        let mut next = Vec::new();
        match component {
            Component::Normal(part) => {
                let part = part.to_string_lossy();
                if !has_wildcards(&part) {
                    next = current.iter().map(|c| c.join(&*part)).collect();
                } else {
                    for base in &current {
                        let dir = if base.as_os_str().is_empty() {
                            Path::new(".")
                        } else {
                            base
                        };
                        let Ok(entries) = std::fs::read_dir(dir) else {
                            continue;
                        };
                        // Matched by their lossy rendering: names that are not UTF-8 are taken too.
                        let mut names: Vec<std::ffi::OsString> = entries
                            .flatten()
                            .map(|e| e.file_name())
                            .filter(|n| {
                                let n = n.to_string_lossy();
                                (!n.starts_with('.') || part.starts_with('.'))
                                    && name_matches(&part, &n)
                            })
                            .collect();
                        names.sort();
                        next.extend(names.into_iter().map(|n| base.join(n)));
                    }
                }
            }
            other => next = current.iter().map(|c| c.join(other.as_os_str())).collect(),
        }
        current = next;
    }
    Ok(current.into_iter().filter(|p| p.exists()).collect())
}
