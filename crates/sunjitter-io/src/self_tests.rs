//! References' self-test cases kept on disk between runs, so that a reference seen before
//! (the same pixels, mask, configuration and build: [`SelfTestKey`]) skips its self-test.
//!
//! One small JSON file per reference under `DIR/self-test/`, where `DIR` is
//! `SUNJITTER_CACHE_DIR`, else `$XDG_CACHE_HOME/sunjitter`, else `$HOME/.cache/sunjitter`.
//! Files are written whole and renamed into place, so runs side by side (a cluster's shards
//! on a shared directory) never read a partial one. Nothing here can fail an alignment: a
//! directory that cannot be read or written, or a file that does not parse, only means the
//! cases are run.

use serde::{Deserialize, Serialize};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use sunjitter_core::engine::refine::{SelfTestCases, SelfTestKey, SelfTestStore};

/// The environment variable naming the cache directory; empty, nothing is kept.
pub const CACHE_DIR_VAR: &str = "SUNJITTER_CACHE_DIR";

/// Files kept; saving one more removes the least recently used beyond these (a file is a
/// few kB).
const KEPT: usize = 1024;

/// Larger files are not read: no cases take more than a few kB.
const MAX_FILE_BYTES: u64 = 1 << 20;

/// The files' layout; files of another are not read.
const FORMAT: u32 = 1;

/// The cases of one reference as a file holds them.
#[derive(Serialize, Deserialize)]
struct Entry {
    format: u32,
    key: String,
    cases: SelfTestCases,
}

/// Self-test cases kept in a directory.
#[derive(Debug, Clone)]
pub struct SelfTestCache {
    dir: PathBuf,
    /// Files kept ([`KEPT`]).
    kept: usize,
}

impl SelfTestCache {
    /// The cases kept in `dir/self-test/`.
    pub fn at(dir: impl Into<PathBuf>) -> SelfTestCache {
        SelfTestCache {
            dir: dir.into().join("self-test"),
            kept: KEPT,
        }
    }

    /// The user's cache ([`CACHE_DIR_VAR`], else the XDG cache directory); `None` when the
    /// variable is set empty, or no directory is known.
    pub fn from_env() -> Option<SelfTestCache> {
        let var = |name: &str| std::env::var_os(name).map(PathBuf::from);
        let dir = match var(CACHE_DIR_VAR) {
            Some(dir) => dir,
            None => var("XDG_CACHE_HOME")
                .filter(|d| d.is_absolute())
                .or_else(|| var("HOME").map(|h| h.join(".cache")))?
                .join("sunjitter"),
        };
        (!dir.as_os_str().is_empty()).then(|| SelfTestCache::at(dir))
    }

    /// The engine's shared working memory for a run's alignments, keeping references'
    /// self-test cases in the user's cache ([`SelfTestCache::from_env`]) where there is one.
    pub fn workspace_from_env() -> sunjitter_core::engine::Workspace {
        match SelfTestCache::from_env() {
            Some(cache) => {
                sunjitter_core::engine::Workspace::keeping_self_tests(std::sync::Arc::new(cache))
            }
            None => Default::default(),
        }
    }

    /// The directory the files are in.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn path(&self, key: &SelfTestKey) -> PathBuf {
        self.dir.join(format!("{}.json", key.hex()))
    }

    fn read(&self, key: &SelfTestKey) -> std::io::Result<Option<SelfTestCases>> {
        let path = self.path(key);
        let file = match std::fs::File::open(&path) {
            Ok(file) => file,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(e),
        };
        let mut text = String::new();
        file.take(MAX_FILE_BYTES + 1).read_to_string(&mut text)?;
        if text.len() as u64 > MAX_FILE_BYTES {
            return Ok(None);
        }
        let entry: Entry = serde_json::from_str(&text).map_err(std::io::Error::other)?;
        if entry.format != FORMAT || entry.key != key.hex() {
            return Ok(None);
        }
        // Recently used: the last to be removed.
        let _ = std::fs::File::options()
            .append(true)
            .open(&path)
            .and_then(|f| f.set_modified(std::time::SystemTime::now()));
        Ok(Some(entry.cases))
    }

    fn write(&self, key: &SelfTestKey, cases: &SelfTestCases) -> std::io::Result<()> {
        std::fs::create_dir_all(&self.dir)?;
        let entry = Entry {
            format: FORMAT,
            key: key.hex(),
            cases: cases.clone(),
        };
        let text = serde_json::to_vec(&entry).map_err(std::io::Error::other)?;
        let mut file = tempfile::Builder::new()
            .prefix(".partial-")
            .tempfile_in(&self.dir)?;
        file.write_all(&text)?;
        file.persist(self.path(key)).map_err(|e| e.error)?;
        self.prune()
    }

    /// Remove the least recently used files beyond those kept.
    fn prune(&self) -> std::io::Result<()> {
        let mut files: Vec<(std::time::SystemTime, PathBuf)> = std::fs::read_dir(&self.dir)?
            .filter_map(|e| {
                let e = e.ok()?;
                let path = e.path();
                (path.extension()? == "json").then_some(())?;
                Some((e.metadata().ok()?.modified().ok()?, path))
            })
            .collect();
        if files.len() <= self.kept {
            return Ok(());
        }
        files.sort();
        for (_, path) in &files[..files.len() - self.kept] {
            let _ = std::fs::remove_file(path);
        }
        Ok(())
    }
}

impl SelfTestStore for SelfTestCache {
    fn load(&self, key: &SelfTestKey) -> Option<SelfTestCases> {
        self.read(key).unwrap_or_else(|e| {
            tracing::debug!(path = %self.path(key).display(), "kept self-test not read: {e}");
            None
        })
    }

    fn save(&self, key: &SelfTestKey, cases: &SelfTestCases) {
        if let Err(e) = self.write(key, cases) {
            tracing::debug!(dir = %self.dir.display(), "self-test not kept: {e}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;
    use sunjitter_core::engine::refine::RefineSettings;

    /// Cases as a run writes them (figures of a 1024² TRACE reference), one bit changed per
    /// `variant` in the first bias.
    fn cases(variant: u32) -> SelfTestCases {
        let case = |b: f64| {
            serde_json::json!({"bias": [b, 2.6396187429627085e-8, 0.000015817206622914526,
                2.4089957886275215e-6], "variance": [5.6272209097110085e-15, 4.3293968387290736e-15,
                2.489315454302621e-10, 2.76988543038964e-10], "flat_sigma": 0.6170485534053954})
        };
        let first = f64::from_bits((-6.131186913727049e-8f64).to_bits() + variant as u64);
        serde_json::from_value(serde_json::json!({
            "key": {"shape": [1024, 1024], "tiles": 1, "pixels": 407188,
                "lever": 254.57018540479623, "structure_px": null,
                "settings": RefineSettings::default()},
            "cases": [case(first), case(1e-7), case(-3e-9), case(0.1 + 0.2)],
            "next_quarter": 3
        }))
        .unwrap()
    }

    fn key(seed: f32) -> SelfTestKey {
        let image = Array2::from_shape_fn((8, 8), |(y, x)| seed + (x * 8 + y) as f32);
        let mask = Array2::from_elem((8, 8), true);
        SelfTestKey::new(image.view(), &mask, 4, &RefineSettings::default(), None, "")
    }

    fn files(cache: &SelfTestCache) -> Vec<PathBuf> {
        let mut files: Vec<_> = std::fs::read_dir(cache.dir())
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        files.sort();
        files
    }

    #[test]
    fn saved_cases_are_read_back_bit_for_bit_under_their_key_only() {
        let dir = tempfile::tempdir().unwrap();
        let cache = SelfTestCache::at(dir.path());
        let saved = cases(0);
        assert!(saved.is_sound());
        assert_eq!(cache.load(&key(0.0)), None);
        cache.save(&key(0.0), &saved);
        let read = cache.load(&key(0.0)).expect("kept");
        // Exact: the same f64 bits, the NaN structure length included (as `null`).
        assert_eq!(format!("{read:?}"), format!("{saved:?}"));
        assert_eq!(cache.load(&key(1.0)), None, "another reference's key");
        // One file per key, no partial file left beside it.
        assert_eq!(
            files(&cache),
            vec![cache.dir().join(format!("{}.json", key(0.0).hex()))]
        );
        // Saved again (a run side by side): replaced whole.
        cache.save(&key(0.0), &cases(1));
        assert_eq!(
            format!("{:?}", cache.load(&key(0.0)).unwrap()),
            format!("{:?}", cases(1))
        );
        assert_eq!(files(&cache).len(), 1);
    }

    #[test]
    fn a_broken_or_foreign_file_is_not_read() {
        let dir = tempfile::tempdir().unwrap();
        let cache = SelfTestCache::at(dir.path());
        cache.save(&key(0.0), &cases(0));
        let path = cache.dir().join(format!("{}.json", key(0.0).hex()));
        let whole = std::fs::read_to_string(&path).unwrap();
        let foreign = [
            whole[..whole.len() / 2].to_string(),
            "\u{0}\u{1}garbage".to_string(),
            whole.replace("\"format\":1", "\"format\":2"),
            whole.replace(&key(0.0).hex(), &key(1.0).hex()),
            // Larger than any cases: not read.
            format!("{whole}{}", " ".repeat(MAX_FILE_BYTES as usize)),
        ];
        for text in foreign {
            std::fs::write(&path, &text).unwrap();
            assert_eq!(
                cache.load(&key(0.0)),
                None,
                "{}",
                &text[..text.len().min(80)]
            );
        }
    }

    #[test]
    fn a_directory_that_cannot_be_written_keeps_nothing_and_fails_nothing() {
        let dir = tempfile::tempdir().unwrap();
        // A file where the directory would be.
        std::fs::write(dir.path().join("self-test"), b"").unwrap();
        let cache = SelfTestCache::at(dir.path());
        cache.save(&key(0.0), &cases(0));
        assert_eq!(cache.load(&key(0.0)), None);
    }

    #[test]
    fn the_least_recently_used_files_beyond_those_kept_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let cache = SelfTestCache {
            kept: 2,
            ..SelfTestCache::at(dir.path())
        };
        let at = |path: &Path, secs: u64| {
            let t = std::time::UNIX_EPOCH + std::time::Duration::from_secs(secs);
            let f = std::fs::File::options().append(true).open(path).unwrap();
            f.set_modified(t).unwrap();
        };
        let path = |k: f32| cache.dir().join(format!("{}.json", key(k).hex()));
        cache.save(&key(0.0), &cases(0));
        at(&path(0.0), 1_000);
        cache.save(&key(1.0), &cases(1));
        at(&path(1.0), 2_000);
        // Reading the older one makes it the most recently used.
        assert!(cache.load(&key(0.0)).is_some());
        cache.save(&key(2.0), &cases(2));
        assert!(
            cache.load(&key(1.0)).is_none(),
            "least recently used: removed"
        );
        assert!(cache.load(&key(0.0)).is_some());
        assert!(cache.load(&key(2.0)).is_some());
        assert_eq!(files(&cache).len(), 2);
    }
}
