//! The identity of this crate's code, for keys of results it computes that callers keep
//! between runs (a reference's self-test cases): a digest of every source file, so that
//! results kept by one build are never taken for another's.

use std::hash::{Hash, Hasher};
use std::path::{Path, PathBuf};

fn main() {
    println!("cargo:rerun-if-changed=src");
    let mut files = Vec::new();
    sources(Path::new("src"), &mut files);
    files.sort();
    let mut digest = std::collections::hash_map::DefaultHasher::new();
    for file in &files {
        file.to_string_lossy().hash(&mut digest);
        std::fs::read(file)
            .expect("source file readable")
            .hash(&mut digest);
    }
    println!(
        "cargo:rustc-env=SUNJITTER_CORE_CODE={:016x}",
        digest.finish()
    );
}

fn sources(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("source directory readable") {
        let path = entry.expect("directory entry").path();
        if path.is_dir() {
            sources(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}
