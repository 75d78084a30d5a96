//! Names and messages as printed: every control character escaped, so a file name or a header
//! value cannot write a fake log line or drive the terminal.
//!
//! - [`escape`] for any text: `\n`, `\r`, `\t`, other C0 and DEL as `\x1b`, C1 and bidirectional
//!   controls as `\u{9b}`; everything else, backslash included, as is (so text already escaped
//!   prints unchanged).
//! - [`name`] and [`path`] for file-system names: as [`escape`], plus bytes that are not UTF-8
//!   as `\xff` and a backslash as `\\`, so two distinct names never render alike (frame keys
//!   rely on this). A name without backslash, control character or invalid byte is unchanged.
//!   [`unescape_path`] is the inverse.
//! - [`value_pm`] for a measurement with its σ.

use std::borrow::Cow;
use std::ffi::{OsStr, OsString};
use std::path::{Path, PathBuf};

fn needs_escape(c: char) -> bool {
    c.is_control()
        || matches!(c, '\u{200e}' | '\u{200f}' | '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}')
}

fn push_char(out: &mut String, c: char) {
    use std::fmt::Write;
    match c {
        '\n' => out.push_str("\\n"),
        '\r' => out.push_str("\\r"),
        '\t' => out.push_str("\\t"),
        c if (c as u32) < 0x80 && needs_escape(c) => {
            let _ = write!(out, "\\x{:02x}", c as u32);
        }
        c if needs_escape(c) => {
            let _ = write!(out, "\\u{{{:x}}}", c as u32);
        }
        c => out.push(c),
    }
}

/// `s` with its control characters escaped (backslashes kept as they are).
pub fn escape(s: &str) -> Cow<'_, str> {
    if !s.chars().any(needs_escape) {
        return Cow::Borrowed(s);
    }
    let mut out = String::with_capacity(s.len() + 8);
    for c in s.chars() {
        push_char(&mut out, c);
    }
    Cow::Owned(out)
}

/// A file-system name as text: control characters and bytes that are not UTF-8 escaped, and
/// backslashes doubled, so that distinct names stay distinct.
pub fn name(s: &OsStr) -> Cow<'_, str> {
    let bytes = os_bytes(s);
    match std::str::from_utf8(&bytes) {
        Ok(text) if !text.chars().any(|c| c == '\\' || needs_escape(c)) => match bytes {
            Cow::Borrowed(_) => Cow::Borrowed(s.to_str().unwrap_or_default()),
            Cow::Owned(_) => Cow::Owned(text.to_string()),
        },
        _ => Cow::Owned(escape_bytes(&bytes)),
    }
}

/// [`name`] of a whole path.
pub fn path(p: &Path) -> Cow<'_, str> {
    name(p.as_os_str())
}

fn escape_bytes(mut bytes: &[u8]) -> String {
    use std::fmt::Write;
    let mut out = String::with_capacity(bytes.len() + 8);
    loop {
        let (valid, rest) = match std::str::from_utf8(bytes) {
            Ok(all) => (all, &[][..]),
            Err(e) => {
                let (valid, rest) = bytes.split_at(e.valid_up_to());
                (std::str::from_utf8(valid).unwrap_or_default(), rest)
            }
        };
        for c in valid.chars() {
            if c == '\\' {
                out.push_str("\\\\");
            } else {
                push_char(&mut out, c);
            }
        }
        let Some((&bad, rest)) = rest.split_first() else {
            return out;
        };
        let _ = write!(out, "\\x{bad:02x}");
        bytes = rest;
    }
}

#[cfg(unix)]
fn os_bytes(s: &OsStr) -> Cow<'_, [u8]> {
    use std::os::unix::ffi::OsStrExt;
    Cow::Borrowed(s.as_bytes())
}

#[cfg(not(unix))]
fn os_bytes(s: &OsStr) -> Cow<'_, [u8]> {
    match s.to_string_lossy() {
        Cow::Borrowed(t) => Cow::Borrowed(t.as_bytes()),
        Cow::Owned(t) => Cow::Owned(t.into_bytes()),
    }
}

/// The path a [`path`] rendering stands for. Text without a backslash is taken as it is;
/// an escape this module does not write is kept literally.
pub fn unescape_path(s: &str) -> PathBuf {
    if !s.contains('\\') {
        return PathBuf::from(s);
    }
    let mut out: Vec<u8> = Vec::with_capacity(s.len());
    let mut rest = s;
    while let Some(i) = rest.find('\\') {
        out.extend_from_slice(&rest.as_bytes()[..i]);
        let tail = &rest[i..];
        let (decoded, used): (Option<Vec<u8>>, usize) = if tail.starts_with("\\\\") {
            (Some(b"\\".to_vec()), 2)
        } else if tail.starts_with("\\n") {
            (Some(b"\n".to_vec()), 2)
        } else if tail.starts_with("\\r") {
            (Some(b"\r".to_vec()), 2)
        } else if tail.starts_with("\\t") {
            (Some(b"\t".to_vec()), 2)
        } else if let Some(hex) = tail.strip_prefix("\\x").and_then(|h| h.get(..2)) {
            (u8::from_str_radix(hex, 16).ok().map(|b| vec![b]), 4)
        } else if let Some((hex, _)) = tail.strip_prefix("\\u{").and_then(|h| h.split_once('}')) {
            let c = u32::from_str_radix(hex, 16).ok().and_then(char::from_u32);
            (
                c.map(|c| c.to_string().into_bytes()),
                hex.len() + 4, // `\u{` + hex + `}`
            )
        } else {
            (None, 1)
        };
        match decoded {
            Some(bytes) => out.extend_from_slice(&bytes),
            None => out.extend_from_slice(&tail.as_bytes()[..used]),
        }
        rest = &tail[used..];
    }
    out.extend_from_slice(rest.as_bytes());
    PathBuf::from(os_string(out))
}

/// `value ± σ` in one notation, to the σ's second significant digit (`0.0770 ± 0.0957 px`);
/// the bare value when there is no usable σ.
pub fn value_pm(value: f64, sigma: Option<f64>, unit: &str) -> String {
    match sigma {
        Some(s) if s.is_finite() && s > 0.0 => {
            let decimals = (1 - s.log10().floor() as i32).clamp(0, 12) as usize;
            format!("{value:.decimals$} ± {s:.decimals$}{unit}")
        }
        _ => format!("{value}{unit}"),
    }
}

#[cfg(unix)]
fn os_string(bytes: Vec<u8>) -> OsString {
    use std::os::unix::ffi::OsStringExt;
    OsString::from_vec(bytes)
}

#[cfg(not(unix))]
fn os_string(bytes: Vec<u8>) -> OsString {
    OsString::from(String::from_utf8_lossy(&bytes).into_owned())
}

/// What a caught panic said (`"unknown"` when it carried no text).
pub fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(unix)]
    fn os(bytes: &[u8]) -> &OsStr {
        use std::os::unix::ffi::OsStrExt;
        OsStr::from_bytes(bytes)
    }

    #[test]
    fn control_characters_are_escaped_and_plain_text_is_not() {
        assert_eq!(escape("aia_171.fits"), "aia_171.fits");
        assert_eq!(escape("a\nb"), "a\\nb");
        assert_eq!(escape("\u{1b}[31mred"), "\\x1b[31mred");
        assert_eq!(escape("\u{7f}\u{9b}\u{202e}"), "\\x7f\\u{9b}\\u{202e}");
        assert_eq!(escape("C:\\x"), "C:\\x", "text keeps its backslashes");
        assert_eq!(escape("Ångström 1400 Å"), "Ångström 1400 Å");
    }

    #[cfg(unix)]
    #[test]
    fn names_render_invalid_bytes_as_hex_and_stay_distinct() {
        assert_eq!(name(os(b"b\xffd.fits")), "b\\xffd.fits");
        assert_eq!(name(os(b"a\nb.fits")), "a\\nb.fits");
        assert_eq!(name(os(b"plain.fits")), "plain.fits");
        // A literal backslash sequence is not confused with the byte it spells.
        assert_ne!(name(os(b"b\\xffd.fits")), name(os(b"b\xffd.fits")));
        // Names whose lossy UTF-8 renderings are identical stay distinct.
        assert_ne!(name(os(b"a\xfe.fits")), name(os(b"a\xff.fits")));
        for raw in [
            &b"b\xffd.fits"[..],
            b"a\nb\x1b[2J.fits",
            b"back\\slash\\xff\xfe",
            b"\xc3\x85ngstr\xc3\xb6m\xe2\x80\xae.fits",
            b"plain.fits",
            b"trail\\",
        ] {
            let shown = name(os(raw));
            assert_eq!(unescape_path(&shown).as_os_str(), os(raw), "{shown}");
            assert!(!shown.chars().any(needs_escape), "{shown}");
        }
    }

    #[test]
    fn value_and_sigma_share_a_notation_to_the_sigmas_second_digit() {
        assert_eq!(value_pm(0.07701, Some(0.09573), " px"), "0.077 ± 0.096 px");
        assert_eq!(value_pm(-376.855, Some(800.4), "″"), "-377 ± 800″");
        assert_eq!(value_pm(0.9978772, Some(3.87e-3), ""), "0.9979 ± 0.0039");
        assert_eq!(
            value_pm(0.25008, Some(5.96e-4), " px"),
            "0.25008 ± 0.00060 px"
        );
        assert_eq!(value_pm(0.0, Some(0.0), " px"), "0 px");
    }
}
