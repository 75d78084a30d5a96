//! Opening what a command reads. Only regular files are read: opening a FIFO blocks until a
//! writer comes, and a device (`/dev/zero`) or socket never ends; each is refused at once,
//! with the kind of file named. The file is opened without blocking and its type checked on
//! the open descriptor, so nothing swapped in between a check and the open slips through.

use std::fs::File;
use std::io::Read;
use std::path::Path;
use sunjitter_core::{Error, Result};

/// What a file that is not a regular file is, for the message (`None`: a regular file).
pub fn special_kind(meta: &std::fs::Metadata) -> Option<&'static str> {
    let t = meta.file_type();
    if t.is_file() {
        return None;
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return Some("a FIFO (named pipe)");
        }
        if t.is_char_device() {
            return Some("a character device");
        }
        if t.is_block_device() {
            return Some("a block device");
        }
        if t.is_socket() {
            return Some("a socket");
        }
    }
    if t.is_dir() {
        return Some("a directory");
    }
    Some("not a regular file")
}

/// Open `path` for reading if it is a regular file; anything else is an
/// [`std::io::ErrorKind::InvalidInput`] error saying what it is.
pub fn open_regular(path: &Path) -> std::io::Result<File> {
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        // A FIFO opens at once instead of waiting for a writer; no effect on regular files.
        options.custom_flags(libc::O_NONBLOCK);
    }
    let file = options.open(path)?;
    let meta = file.metadata()?;
    match special_kind(&meta) {
        None => Ok(file),
        Some(kind) => Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("is {kind}, not a regular file"),
        )),
    }
}

/// Refuse `path` (exit 2, naming it) when it exists and is not a regular file.
pub fn refuse_special(path: &Path) -> Result<()> {
    match std::fs::metadata(path) {
        Ok(meta) if !meta.is_dir() => match special_kind(&meta) {
            Some(kind) => Err(Error::bad_input(
                path,
                format!("is {kind}, not a regular file"),
            )),
            None => Ok(()),
        },
        _ => Ok(()),
    }
}

/// The whole of a small regular file (`what`: "configuration file"), at most `limit` bytes,
/// as text. Not a regular file, larger than `limit` or not UTF-8: bad input (exit 2).
pub fn read_text(path: &Path, limit: u64, what: &str) -> Result<String> {
    let file = open_regular(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::InvalidInput => Error::bad_input(path, e.to_string()),
        _ => Error::io(path, e),
    })?;
    let mut bytes = Vec::new();
    file.take(limit + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| Error::io(path, e))?;
    if bytes.len() as u64 > limit {
        return Err(Error::bad_input(
            path,
            format!("larger than {limit} bytes: not a {what}"),
        ));
    }
    String::from_utf8(bytes).map_err(|e| {
        Error::bad_input(
            path,
            format!(
                "not text (byte {} is not UTF-8): not a {what}",
                e.utf8_error().valid_up_to()
            ),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[cfg(unix)]
    fn a_fifo_and_a_device_are_refused_without_blocking() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe.fits");
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let e = open_regular(&fifo).unwrap_err();
        assert!(e.to_string().contains("FIFO"), "{e}");
        assert!(refuse_special(&fifo).is_err());
        let e = open_regular(Path::new("/dev/zero")).unwrap_err();
        assert!(e.to_string().contains("character device"), "{e}");
        let e = read_text(Path::new("/dev/zero"), 1024, "configuration file").unwrap_err();
        assert_eq!(
            e.exit_code(),
            sunjitter_core::error::ExitCode::BadInput,
            "{e}"
        );
    }

    #[test]
    fn a_binary_or_huge_configuration_is_bad_input() {
        let dir = tempfile::tempdir().unwrap();
        let bin = dir.path().join("c.toml");
        std::fs::write(&bin, [0x80u8, 0xff, 0x00, 0x41]).unwrap();
        let e = read_text(&bin, 1024, "configuration file").unwrap_err();
        assert_eq!(e.exit_code(), sunjitter_core::error::ExitCode::BadInput);
        assert!(e.to_string().contains("UTF-8"), "{e}");
        std::fs::write(&bin, vec![b'#'; 2048]).unwrap();
        assert_eq!(
            read_text(&bin, 1024, "configuration file")
                .unwrap_err()
                .exit_code(),
            sunjitter_core::error::ExitCode::BadInput
        );
        std::fs::write(&bin, "[engine]\n").unwrap();
        assert_eq!(
            read_text(&bin, 1024, "configuration file").unwrap(),
            "[engine]\n"
        );
    }
}
