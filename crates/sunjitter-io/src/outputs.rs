//! Where a run may write.
//!
//! * One writer per output directory: `watch` and `replay` hold an exclusive `flock` on
//!   `OUT/.sunjitter.lock` for as long as they write there (the file holds the holder's pid,
//!   for the message a second writer prints). The kernel drops the lock when the process dies,
//!   even by SIGKILL, so a lock file left behind never blocks a restart: the file's existence
//!   means nothing, only the lock does.
//! * [`check_outputs`]: every file a command writes is checked against its inputs, the log
//!   files, and directories a running daemon writes, before any work starts.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use sunjitter_core::{Error, Result};

/// The lock file of an output directory.
pub const LOCK_FILE: &str = ".sunjitter.lock";

/// The first bytes of every MCAP file.
const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// An exclusive lock on an output directory, held while this value lives.
#[derive(Debug)]
pub struct OutputLock {
    _file: File,
}

impl OutputLock {
    /// Lock `dir` (created if missing) for writing, or refuse (exit 2) naming the holder's pid.
    pub fn acquire(dir: &Path) -> Result<OutputLock> {
        std::fs::create_dir_all(dir).map_err(|e| Error::unwritable(dir, e))?;
        if !dir.is_dir() {
            return Err(Error::unwritable(
                dir,
                std::io::Error::from(std::io::ErrorKind::NotADirectory),
            ));
        }
        let path = dir.join(LOCK_FILE);
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| Error::unwritable(&path, e))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => return Err(held(dir, read_pid(&mut file))),
            Err(TryLockError::Error(e)) => {
                return Err(Error::output(&path, format!("cannot lock: {e}")))
            }
        }
        file.set_len(0)
            .and_then(|()| writeln!(file, "{}", std::process::id()))
            .map_err(|e| Error::output(&path, format!("cannot write the lock file: {e}")))?;
        Ok(OutputLock { _file: file })
    }
}

/// `Some(pid)` when another running process holds `dir`'s lock (`Some(None)`: pid unreadable).
fn holder(dir: &Path) -> Option<Option<u32>> {
    let mut file = File::open(dir.join(LOCK_FILE)).ok()?;
    match file.try_lock_shared() {
        Err(TryLockError::WouldBlock) => match read_pid(&mut file) {
            // This process: a daemon's own files (its status file) go there.
            Some(pid) if pid == std::process::id() => None,
            pid => Some(pid),
        },
        // Unlocked (the shared lock is released with the file) or not lockable: no holder.
        _ => None,
    }
}

fn read_pid(file: &mut File) -> Option<u32> {
    let mut text = String::new();
    file.read_to_string(&mut text).ok()?;
    text.trim().parse().ok()
}

fn held(dir: &Path, pid: Option<u32>) -> Error {
    Error::Refused {
        path: dir.to_path_buf(),
        reason: format!(
            "output directory held by {} (one watch or replay per directory)",
            holder_name(pid)
        ),
    }
}

fn holder_name(pid: Option<u32>) -> String {
    match pid {
        Some(pid) => format!("sunjitter pid {pid}"),
        None => "another sunjitter process".to_string(),
    }
}

/// Refuse (exit 2, naming the path and why) any of `outputs` that would destroy data the user
/// did not ask to lose: a file that is one of `inputs` (same file by device and inode, so other
/// spellings, symbolic and hard links count), a log segment or any `.mcap` name (readers take
/// every `*.mcap` in a directory as a segment), a lock file, a file inside a directory a
/// running `watch` or `replay` holds, or the same file named twice. Call it before any work.
pub fn check_outputs(outputs: &[&Path], inputs: &[&Path]) -> Result<()> {
    let input_ids: Vec<(u64, u64)> = inputs.iter().filter_map(|p| file_id(p)).collect();
    let mut seen: Vec<(PathBuf, Option<(u64, u64)>)> = Vec::new();
    for &out in outputs {
        let refuse = |reason: String| {
            Err(Error::Refused {
                path: out.to_path_buf(),
                reason,
            })
        };
        let name = out.file_name().unwrap_or_default();
        if name == LOCK_FILE {
            return refuse("is an output directory's lock file".into());
        }
        let id = file_id(out);
        if id.is_some_and(|id| input_ids.contains(&id)) {
            return refuse("is an input of this command; choose another output path".into());
        }
        if std::fs::metadata(out).is_ok_and(|m| m.is_file()) && starts_with_mcap_magic(out) {
            return refuse("is an MCAP log; choose another output path".into());
        }
        if Path::new(name)
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("mcap"))
        {
            return refuse("a .mcap name is read as a log segment; choose another name".into());
        }
        let parent = match out.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        let canonical = (!name.is_empty())
            .then(|| parent.canonicalize().ok().map(|p| p.join(name)))
            .flatten();
        if let Some(dir) = canonical.as_deref().and_then(Path::parent) {
            if let Some(pid) = holder(dir) {
                return refuse(format!(
                    "inside {}, the output directory held by {}; write elsewhere",
                    dir.display(),
                    holder_name(pid)
                ));
            }
        }
        let twice = seen.iter().any(|(path, seen_id)| {
            canonical.as_deref() == Some(path.as_path()) || (id.is_some() && *seen_id == id)
        });
        if twice {
            return refuse("is named twice as an output".into());
        }
        if let Some(path) = canonical {
            seen.push((path, id));
        }
    }
    Ok(())
}

/// Device and inode of an existing file (symbolic links followed).
fn file_id(path: &Path) -> Option<(u64, u64)> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        std::fs::metadata(path).ok().map(|m| (m.dev(), m.ino()))
    }
    #[cfg(not(unix))]
    {
        let _ = path;
        None
    }
}

fn starts_with_mcap_magic(path: &Path) -> bool {
    let mut head = [0u8; 8];
    File::open(path)
        .and_then(|mut f| f.read_exact(&mut head))
        .is_ok_and(|()| head == MCAP_MAGIC)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_on_one_directory_is_refused_and_freed_on_drop() {
        let dir = tempfile::tempdir().unwrap();
        let lock = OutputLock::acquire(dir.path()).unwrap();
        let err = OutputLock::acquire(dir.path()).unwrap_err();
        assert_eq!(err.exit_code(), 2);
        let pid = format!("pid {}", std::process::id());
        assert!(err.to_string().contains(&pid), "{err}");
        drop(lock);
        let _again = OutputLock::acquire(dir.path()).unwrap();
    }

    #[test]
    fn a_lock_file_left_behind_does_not_lock() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(LOCK_FILE), "999999\n").unwrap();
        assert!(holder(dir.path()).is_none());
        let _lock = OutputLock::acquire(dir.path()).unwrap();
    }

    #[test]
    fn outputs_that_are_inputs_logs_or_held_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let input = d.join("in.fits");
        std::fs::write(&input, b"SIMPLE").unwrap();
        std::fs::create_dir(d.join("sub")).unwrap();
        let other_spelling = d.join("sub").join("..").join("in.fits");
        let link = d.join("hard.fits");
        std::fs::hard_link(&input, &link).unwrap();
        for out in [&input, &other_spelling, &link] {
            let err = check_outputs(&[out], &[&input]).unwrap_err();
            assert_eq!(err.exit_code(), 2);
            assert!(err.to_string().contains("is an input"), "{err}");
        }
        let log = d.join("log.bin");
        std::fs::write(&log, [MCAP_MAGIC, b"rest"].concat()).unwrap();
        assert!(check_outputs(&[&log], &[]).is_err());
        assert!(check_outputs(&[&d.join("new.mcap")], &[]).is_err());
        assert!(check_outputs(&[&d.join(LOCK_FILE)], &[]).is_err());
        let (a, b) = (d.join("a.png"), d.join("sub/../a.png"));
        assert!(check_outputs(&[&a, &b], &[]).is_err());
        check_outputs(&[&a, &d.join("b.csv")], &[&input]).unwrap();

        let out = d.join("out");
        let lock = OutputLock::acquire(&out).unwrap();
        check_outputs(&[&out.join("status.json")], &[]).unwrap();
        // As another process would see it.
        std::fs::write(out.join(LOCK_FILE), "1\n").unwrap();
        let err = check_outputs(&[&out.join("x.csv")], &[]).unwrap_err();
        assert!(err.to_string().contains("held by sunjitter pid 1"), "{err}");
        drop(lock);
        check_outputs(&[&out.join("x.csv")], &[]).unwrap();
    }
}
