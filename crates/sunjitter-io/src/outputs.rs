//! Where a run may write, and how.
//!
//! * One writer per output directory: `watch`, `replay` and `merge` hold an exclusive `flock`
//!   on the output directory itself for as long as they write there, so removing or replacing
//!   any file inside it (the pid file `OUT/.sunjitter.lock` included) never lets a second
//!   writer in; and before each segment is created the holder checks that `OUT` is still the
//!   directory it locked (device and inode), so it never writes into one that replaced it. The
//!   kernel drops the lock when the process dies, even by SIGKILL: a pid file left behind
//!   means nothing, only the lock does.
//! * [`check_outputs`]: every file a command writes is checked against its inputs, the trees
//!   it must not write into, the log files, and directories a running daemon writes, before
//!   any work starts. Files are compared by identity (device and inode), never by spelling.
//! * [`write_atomically`]: every output file is written under a hidden temporary name in its
//!   directory and renamed into place; on any failure the temporary file is removed.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use sunjitter_core::{Error, Result};

/// The pid file of an output directory (the lock itself is on the directory).
pub const LOCK_FILE: &str = ".sunjitter.lock";

/// The first bytes of every MCAP file.
const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// A file's identity: device and inode (symbolic links followed).
pub type FileId = (u64, u64);

/// An exclusive lock on an output directory, held while this value lives.
#[derive(Debug)]
pub struct OutputLock {
    /// The directory itself, open and locked.
    dir: File,
    path: PathBuf,
    id: FileId,
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
        let handle = File::open(dir).map_err(|e| Error::unwritable(dir, e))?;
        match handle.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => return Err(held(dir, read_pid(dir))),
            Err(TryLockError::Error(e)) => {
                return Err(Error::output(dir, format!("cannot lock: {e}")))
            }
        }
        let id = handle_id(&handle).ok_or_else(|| Error::output(dir, "cannot stat"))?;
        let path = dir.join(LOCK_FILE);
        let mut options = OpenOptions::new();
        options.write(true).create(true).truncate(true);
        #[cfg(unix)]
        {
            // A link planted under the pid file's name is not followed (nor truncated through).
            use std::os::unix::fs::OpenOptionsExt;
            options.custom_flags(libc::O_NOFOLLOW);
        }
        let mut file = options
            .open(&path)
            .map_err(|e| Error::unwritable(&path, e))?;
        writeln!(file, "{}", std::process::id())
            .map_err(|e| Error::output(&path, format!("cannot write the lock file: {e}")))?;
        Ok(OutputLock {
            dir: handle,
            path: dir.to_path_buf(),
            id,
        })
    }

    /// The directory as it was named.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The locked directory's identity.
    pub fn id(&self) -> FileId {
        self.id
    }

    /// Refuse (an output error) when the path no longer leads to the locked directory: it was
    /// removed, moved or replaced while this process held it. Nothing is written elsewhere.
    pub fn verify(&self) -> Result<()> {
        if file_id(&self.path) == Some(self.id) {
            return Ok(());
        }
        Err(Error::output(
            &self.path,
            "the output directory was removed or replaced while this run held it: \
             nothing more is written there",
        ))
    }
}

impl Drop for OutputLock {
    fn drop(&mut self) {
        let _ = self.dir.unlock();
    }
}

fn handle_id(file: &File) -> Option<FileId> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        file.metadata().ok().map(|m| (m.dev(), m.ino()))
    }
    #[cfg(not(unix))]
    {
        let _ = file;
        None
    }
}

/// `Some(pid)` when another running process holds `dir`'s lock (`Some(None)`: pid unreadable).
fn holder(dir: &Path) -> Option<Option<u32>> {
    let handle = File::open(dir).ok()?;
    match handle.try_lock_shared() {
        Err(TryLockError::WouldBlock) => match read_pid(dir) {
            // This process: a daemon's own files (its status file) go there.
            Some(pid) if pid == std::process::id() => None,
            pid => Some(pid),
        },
        // Unlocked (the shared lock is released with the handle) or not lockable: no holder.
        _ => None,
    }
}

/// The holder's pid: from the pid file, or where that was removed, from the kernel's list
/// of locks (Linux `/proc/locks`: the `FLOCK` on the directory's inode).
fn read_pid(dir: &Path) -> Option<u32> {
    let mut text = String::new();
    let from_file = crate::input::open_regular(&dir.join(LOCK_FILE))
        .ok()
        .and_then(|f| f.take(64).read_to_string(&mut text).ok())
        .and_then(|_| text.trim().parse().ok());
    from_file.or_else(|| {
        let (_, inode) = file_id(dir)?;
        let locks = std::fs::read_to_string("/proc/locks").ok()?;
        locks.lines().find_map(|line| {
            let f: Vec<&str> = line.split_whitespace().collect();
            let at = f.iter().position(|w| *w == "FLOCK")?;
            let (pid, place) = (f.get(at + 3)?, f.get(at + 4)?);
            (place.rsplit(':').next()? == inode.to_string())
                .then(|| pid.parse().ok())
                .flatten()
        })
    })
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
    check_outputs_outside(outputs, inputs, &[])
}

/// [`check_outputs`], and also refuse an output inside (or being) one of `trees` (by
/// identity: a link or bind mount leading there counts), each with what it is for the
/// message, e.g. `(watched, "the watched directory")`.
pub fn check_outputs_outside(
    outputs: &[&Path],
    inputs: &[&Path],
    trees: &[(&Path, &str)],
) -> Result<()> {
    let input_ids: Vec<FileId> = inputs.iter().filter_map(|p| file_id(p)).collect();
    let tree_ids: Vec<(FileId, &Path, &str)> = trees
        .iter()
        .filter_map(|(p, what)| Some((file_id(p)?, *p, *what)))
        .collect();
    let mut seen: Vec<(PathBuf, Option<FileId>)> = Vec::new();
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
            return refuse(
                "is an input of this command (a frame, a reference or the configuration); choose another output path"
                    .into(),
            );
        }
        if let Some((_, tree, what)) = tree_ids.iter().find(|(t, _, _)| is_within(out, *t)) {
            return refuse(format!(
                "is inside {what} {}: nothing is written there; choose another output path",
                tree.display()
            ));
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

/// Device and inode of an existing file or directory (symbolic links followed).
pub fn file_id(path: &Path) -> Option<FileId> {
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

/// Whether `path` is the directory `dir` or lies below it, however either is spelled: the
/// nearest existing ancestor of `path` is resolved (links followed) and each directory on the
/// way up to `/` is compared with `dir` by identity.
pub fn is_within(path: &Path, dir: FileId) -> bool {
    let absolute = if path.is_absolute() {
        path.to_path_buf()
    } else {
        match std::env::current_dir() {
            Ok(cwd) => cwd.join(path),
            Err(_) => return false,
        }
    };
    let mut existing = absolute.as_path();
    let resolved = loop {
        if let Ok(c) = existing.canonicalize() {
            break c;
        }
        match existing.parent() {
            Some(parent) => existing = parent,
            None => return false,
        }
    };
    resolved
        .ancestors()
        .any(|a| file_id(a).is_some_and(|id| id == dir))
}

/// The hidden temporary name `path` is written under: `.NAME.PID.tmp`, plus `.EXT` when the
/// name has an extension (writers that choose the format by the extension still see it).
pub fn temp_path(path: &Path) -> Result<PathBuf> {
    let name = path
        .file_name()
        .ok_or_else(|| Error::output(path, "not a file path"))?
        .to_string_lossy();
    let ext = Path::new(&*name)
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    Ok(path.with_file_name(format!(".{name}.{}.tmp{ext}", std::process::id())))
}

/// Removes its file when dropped, unless [`TempFile::keep`] was called.
struct TempFile(Option<PathBuf>);

impl TempFile {
    fn keep(mut self) {
        self.0 = None;
    }
}

impl Drop for TempFile {
    fn drop(&mut self) {
        if let Some(p) = self.0.take() {
            let _ = std::fs::remove_file(p);
        }
    }
}

/// Write `path` whole or not at all: `write` writes the file at the temporary path it is
/// given ([`temp_path`], in `path`'s directory), which is then renamed onto `path`. On any
/// failure (an error, a panic) the temporary file is removed and `path` is left as it was.
pub fn write_atomically<T>(path: &Path, write: impl FnOnce(&Path) -> Result<T>) -> Result<T> {
    let tmp = temp_path(path)?;
    let _ = std::fs::remove_file(&tmp);
    let guard = TempFile(Some(tmp.clone()));
    let value = write(&tmp)?;
    std::fs::rename(&tmp, path).map_err(|e| {
        Error::output(
            path,
            format!("cannot move the written file into place: {e}"),
        )
    })?;
    guard.keep();
    Ok(value)
}

/// [`write_atomically`] for a writer of bytes: `write` fills a buffered file, which is flushed
/// and renamed into place.
pub fn write_file_atomically(
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<()> {
    write_atomically(path, |tmp| {
        let file = OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(tmp)
            .map_err(|e| Error::unwritable(path, e))?;
        let mut out = std::io::BufWriter::new(file);
        write(&mut out)
            .and_then(|()| out.flush())
            .map_err(|e| Error::output(path, format!("cannot write: {e}")))
    })
}

/// Put the directory `new` at `target`, in one step: renamed there when `target` does not
/// exist, else the two exchanged (Linux `renameat2(RENAME_EXCHANGE)`; elsewhere, or on a file
/// system without it, `target` is moved aside for the moment of the rename). Returns whether
/// the old `target` now sits at `new`'s path (for the caller to remove).
pub fn put_dir_in_place(new: &Path, target: &Path) -> Result<bool> {
    let fail = |e: std::io::Error| {
        Error::output(
            target,
            format!("cannot put {} in its place: {e}", new.display()),
        )
    };
    if std::fs::symlink_metadata(target).is_err() {
        std::fs::rename(new, target).map_err(fail)?;
        return Ok(false);
    }
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::ffi::OsStrExt;
        let c = |p: &Path| std::ffi::CString::new(p.as_os_str().as_bytes());
        if let (Ok(a), Ok(b)) = (c(new), c(target)) {
            // SAFETY: two NUL-terminated paths that outlive the call; the flags are the
            // kernel's.
            let r = unsafe {
                libc::syscall(
                    libc::SYS_renameat2,
                    libc::AT_FDCWD,
                    a.as_ptr(),
                    libc::AT_FDCWD,
                    b.as_ptr(),
                    libc::RENAME_EXCHANGE,
                )
            };
            if r == 0 {
                return Ok(true);
            }
            let e = std::io::Error::last_os_error();
            if !matches!(e.raw_os_error(), Some(libc::EINVAL | libc::ENOSYS)) {
                return Err(fail(e));
            }
        }
    }
    let mut aside = new.as_os_str().to_os_string();
    aside.push(".old");
    let aside = PathBuf::from(aside);
    std::fs::rename(target, &aside).map_err(fail)?;
    if let Err(e) = std::fs::rename(new, target) {
        let _ = std::fs::rename(&aside, target);
        return Err(fail(e));
    }
    std::fs::rename(&aside, new).map_err(fail)?;
    Ok(true)
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
        assert_eq!(err.exit_code(), sunjitter_core::error::ExitCode::BadInput);
        let pid = format!("pid {}", std::process::id());
        assert!(err.to_string().contains(&pid), "{err}");
        drop(lock);
        let _again = OutputLock::acquire(dir.path()).unwrap();
    }

    #[test]
    fn the_lock_holds_when_its_file_is_removed_and_notices_a_replaced_directory() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let lock = OutputLock::acquire(&out).unwrap();
        std::fs::remove_file(out.join(LOCK_FILE)).unwrap();
        let err = OutputLock::acquire(&out).unwrap_err();
        assert_eq!(err.exit_code(), sunjitter_core::error::ExitCode::BadInput);
        let pid = format!("held by sunjitter pid {}", std::process::id());
        assert!(err.to_string().contains(&pid), "{err}");
        lock.verify().unwrap();
        // The directory moved away and another put in its place: not the locked one.
        std::fs::rename(&out, dir.path().join("moved")).unwrap();
        std::fs::create_dir(&out).unwrap();
        let err = lock.verify().unwrap_err();
        assert!(err.to_string().contains("removed or replaced"), "{err}");
    }

    #[test]
    fn an_atomic_write_leaves_the_old_file_or_the_new_one_and_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("result.csv");
        std::fs::write(&path, "old\n").unwrap();
        let err = write_file_atomically(&path, |w| {
            w.write_all(b"half")?;
            Err(std::io::Error::from(std::io::ErrorKind::StorageFull))
        })
        .unwrap_err();
        assert!(err.to_string().contains("result.csv"), "{err}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "old\n");
        let panicked = std::panic::catch_unwind(|| {
            write_atomically(&path, |tmp| -> Result<()> {
                std::fs::write(tmp, "partial").unwrap();
                panic!("writer died");
            })
        });
        assert!(panicked.is_err());
        write_file_atomically(&path, |w| w.write_all(b"new\n")).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "new\n");
        let names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, vec!["result.csv".to_string()]);
        assert!(temp_path(&path)
            .unwrap()
            .to_string_lossy()
            .ends_with(".tmp.csv"));
    }

    #[test]
    #[cfg(unix)]
    fn an_output_reached_through_a_link_into_a_protected_tree_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let watched = d.join("watched");
        std::fs::create_dir_all(watched.join("sub")).unwrap();
        std::os::unix::fs::symlink(watched.join("sub"), d.join("link")).unwrap();
        let trees = [(watched.as_path(), "the watched directory")];
        for out in [
            watched.join("status.json"),
            d.join("link/new/status.json"),
            d.join("watched/sub/../x.json"),
        ] {
            let err = check_outputs_outside(&[&out], &[], &trees).unwrap_err();
            assert!(
                err.to_string().contains("inside the watched directory"),
                "{err}"
            );
        }
        check_outputs_outside(&[&d.join("status.json")], &[], &trees).unwrap();
        let id = file_id(&watched).unwrap();
        assert!(is_within(&d.join("link/a/b"), id));
        assert!(!is_within(d, id));
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
            assert_eq!(err.exit_code(), sunjitter_core::error::ExitCode::BadInput);
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
