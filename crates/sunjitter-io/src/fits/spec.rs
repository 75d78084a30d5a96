//! What to read: a file or one frame of a cube, and the frame keys that name it in the log.

use std::fmt;
use std::path::{Path, PathBuf};

/// One image to read: a file, and for a 3-D cube the frame index (`FILE.fits[N]`).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct FrameSpec {
    pub path: PathBuf,
    pub frame: Option<usize>,
}

impl FrameSpec {
    /// Parse a command-line argument: `FILE.fits[N]` for frame N of a cube, else a plain path.
    ///
    /// An argument naming an existing file is always a plain path, so file names that
    /// themselves contain `[…]` keep working.
    pub fn parse(arg: &str) -> FrameSpec {
        if !Path::new(arg).is_file() {
            if let Some((path, frame)) = split_frame_suffix(arg) {
                return FrameSpec {
                    path: PathBuf::from(path),
                    frame: Some(frame),
                };
            }
        }
        FrameSpec::file(arg)
    }

    /// A whole file (a 2-D image, or a cube of one frame).
    pub fn file(path: impl Into<PathBuf>) -> FrameSpec {
        FrameSpec {
            path: path.into(),
            frame: None,
        }
    }

    /// Frame `frame` of a cube.
    pub fn cube_frame(path: impl Into<PathBuf>, frame: usize) -> FrameSpec {
        FrameSpec {
            path: path.into(),
            frame: Some(frame),
        }
    }
}

impl fmt::Display for FrameSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.frame {
            Some(n) => write!(f, "{}[{n}]", sunjitter_core::text::path(&self.path)),
            None => write!(f, "{}", sunjitter_core::text::path(&self.path)),
        }
    }
}

/// The identity of a frame in logs: `PATH` for a 2-D image, `PATH[N]` for frame N of a cube.
pub fn frame_key(path: &std::path::Path, frame: Option<usize>) -> String {
    match frame {
        Some(n) => format!("{}[{n}]", sunjitter_core::text::path(path)),
        None => sunjitter_core::text::path(path).into_owned(),
    }
}

/// Inverse of [`frame_key`].
pub fn parse_frame_key(key: &str) -> FrameSpec {
    if let Some(stripped) = key.strip_suffix(']') {
        if let Some((path, n)) = stripped.rsplit_once('[') {
            if let Ok(n) = n.parse::<usize>() {
                return FrameSpec {
                    path: sunjitter_core::text::unescape_path(path),
                    frame: Some(n),
                };
            }
        }
    }
    FrameSpec {
        path: sunjitter_core::text::unescape_path(key),
        frame: None,
    }
}

/// `name[12]` → (`name`, 12).
fn split_frame_suffix(arg: &str) -> Option<(&str, usize)> {
    let inner = arg.strip_suffix(']')?;
    let open = inner.rfind('[')?;
    let (path, digits) = (&inner[..open], &inner[open + 1..]);
    if path.is_empty() || digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some((path, digits.parse().ok()?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_spec_parsing() {
        assert_eq!(
            FrameSpec::parse("cube.fits[3]"),
            FrameSpec::cube_frame("cube.fits", 3)
        );
        assert_eq!(
            FrameSpec::parse("a b/c[1].fits"),
            FrameSpec::file("a b/c[1].fits")
        );
        assert_eq!(FrameSpec::parse("x.fits[]"), FrameSpec::file("x.fits[]"));
        assert_eq!(
            FrameSpec::parse("x.fits[-1]"),
            FrameSpec::file("x.fits[-1]")
        );
        assert_eq!(FrameSpec::parse("[2]"), FrameSpec::file("[2]"));
        assert_eq!(FrameSpec::cube_frame("c.fits", 7).to_string(), "c.fits[7]");
        // An existing file whose name ends in [N] is a plain path.
        let dir = tempfile::tempdir().unwrap();
        let odd = dir.path().join("frame[2]");
        std::fs::write(&odd, b"x").unwrap();
        assert_eq!(
            FrameSpec::parse(odd.to_str().unwrap()),
            FrameSpec::file(&odd)
        );
    }
}
