//! Segment files: their names, and the file wrapper the MCAP writer writes through.

use std::fs::File;
use std::io::{self, Seek, SeekFrom, Write};
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;

pub(crate) const PREFIX: &str = "sunjitter-";
pub(crate) const EXTENSION: &str = ".mcap";

/// The ordering key of a segment name: UTC start stamp and per-run counter.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) struct SegmentKey {
    pub stamp: String,
    pub number: u32,
}

impl SegmentKey {
    pub fn file_name(&self) -> String {
        format!("{PREFIX}{}-{:04}{EXTENSION}", self.stamp, self.number)
    }

    /// Parses `sunjitter-YYYYMMDDTHHMMSSZ-NNNN.mcap`; `None` for any other name.
    pub fn parse(name: &str) -> Option<SegmentKey> {
        let rest = name.strip_prefix(PREFIX)?.strip_suffix(EXTENSION)?;
        let (stamp, number) = rest.split_once('-')?;
        let b = stamp.as_bytes();
        let stamp_ok = b.len() == 16
            && b[8] == b'T'
            && b[15] == b'Z'
            && b[..8].iter().chain(&b[9..15]).all(u8::is_ascii_digit);
        if !stamp_ok || number.len() < 4 || !number.bytes().all(|c| c.is_ascii_digit()) {
            return None;
        }
        Some(SegmentKey {
            stamp: stamp.to_string(),
            number: number.parse().ok()?,
        })
    }
}

/// `YYYYMMDDTHHMMSSZ` of a time in ns since the Unix epoch (UTC, proleptic Gregorian).
pub(crate) fn utc_stamp(ns: u64) -> String {
    let secs = ns / 1_000_000_000;
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    let (y, m, d) = civil_from_days(days);
    format!(
        "{y:04}{m:02}{d:02}T{:02}{:02}{:02}Z",
        rem / 3600,
        (rem / 60) % 60,
        rem % 60
    )
}

/// Days since 1970-01-01 to (year, month, day); H. Hinnant's `civil_from_days`.
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let y = yoe + era * 400 + i64::from(m <= 2);
    (y, m, d)
}

/// The largest segment key among the files already in `dir` (so new names sort after them).
pub(crate) fn newest_existing(dir: &Path) -> io::Result<Option<SegmentKey>> {
    let mut newest: Option<SegmentKey> = None;
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        if let Some(key) = entry.file_name().to_str().and_then(SegmentKey::parse) {
            if newest.as_ref().is_none_or(|n| key > *n) {
                newest = Some(key);
            }
        }
    }
    Ok(newest)
}

/// Unlimited write budget (see [`SegmentFile`]).
pub(crate) const UNLIMITED: u64 = u64::MAX;

/// Buffered bytes beyond which they go to the file before a flush (bounds memory).
const SPILL_BYTES: usize = 4 << 20;

/// The file under one MCAP writer, buffered: the writer emits many small records (indexes,
/// summary) and asks for its position often; both stay in memory until `flush`.
///
/// * `poisoned`: once set, every write fails, so dropping an abandoned `mcap::Writer` (whose
///   `Drop` tries to finish the file) cannot append anything after the last good flush.
/// * `budget`: bytes that may still reach the file, shared by all segments of a sink; a test
///   hook to simulate a full disk (a short write, then `StorageFull`). `UNLIMITED` normally.
/// * `sync_on_flush`: `fsync` on every flush, for durability beyond a process crash.
pub(crate) struct SegmentFile {
    file: File,
    buffer: Vec<u8>,
    /// Logical position: file position plus buffered bytes.
    position: u64,
    poisoned: Arc<AtomicBool>,
    budget: Arc<AtomicU64>,
    sync_on_flush: bool,
}

impl SegmentFile {
    pub fn new(
        file: File,
        poisoned: Arc<AtomicBool>,
        budget: Arc<AtomicU64>,
        sync_on_flush: bool,
    ) -> SegmentFile {
        SegmentFile {
            file,
            buffer: Vec::new(),
            position: 0,
            poisoned,
            budget,
            sync_on_flush,
        }
    }

    fn check_poisoned(&self) -> io::Result<()> {
        if self.poisoned.load(Ordering::SeqCst) {
            Err(io::Error::other("segment abandoned after an earlier error"))
        } else {
            Ok(())
        }
    }

    /// Writes the buffer to the file, within the budget.
    fn spill(&mut self) -> io::Result<()> {
        let mut data = self.buffer.as_slice();
        let result = loop {
            if data.is_empty() {
                break Ok(());
            }
            let budget = self.budget.load(Ordering::SeqCst);
            let allowed = data
                .len()
                .min(usize::try_from(budget).unwrap_or(usize::MAX));
            if allowed == 0 {
                break Err(io::Error::new(
                    io::ErrorKind::StorageFull,
                    "no space left on device (injected)",
                ));
            }
            match self.file.write(&data[..allowed]) {
                Ok(0) => break Err(io::ErrorKind::WriteZero.into()),
                Ok(n) => {
                    if budget != UNLIMITED {
                        self.budget.fetch_sub(n as u64, Ordering::SeqCst);
                    }
                    data = &data[n..];
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => break Err(e),
            }
        };
        let written = self.buffer.len() - data.len();
        self.buffer.drain(..written);
        result
    }
}

impl Write for SegmentFile {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.check_poisoned()?;
        self.buffer.extend_from_slice(buf);
        self.position += buf.len() as u64;
        if self.buffer.len() > SPILL_BYTES {
            self.spill()?;
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        self.check_poisoned()?;
        self.spill()?;
        self.file.flush()?;
        if self.sync_on_flush {
            self.file.sync_data()?;
        }
        Ok(())
    }
}

impl Seek for SegmentFile {
    fn seek(&mut self, pos: SeekFrom) -> io::Result<u64> {
        self.check_poisoned()?;
        if pos == SeekFrom::Current(0) {
            return Ok(self.position);
        }
        self.spill()?;
        self.position = self.file.seek(pos)?;
        Ok(self.position)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamps_match_known_utc_times() {
        // `date -u -d @0 +%Y%m%dT%H%M%SZ` → 19700101T000000Z
        assert_eq!(utc_stamp(0), "19700101T000000Z");
        // `date -u -d @1396102178 +%Y%m%dT%H%M%SZ` → 20140329T140938Z (the IRIS SJI start)
        assert_eq!(utc_stamp(1_396_102_178_999_999_999), "20140329T140938Z");
        // `date -u -d @951782400` → 2000-02-29 00:00:00 (leap day)
        assert_eq!(utc_stamp(951_782_400_000_000_000), "20000229T000000Z");
        // `date -u -d @4107542399` → 2100-02-28 23:59:59 (2100 is not a leap year)
        assert_eq!(utc_stamp(4_107_542_399_000_000_000), "21000228T235959Z");
    }

    #[test]
    fn names_round_trip_and_sort_in_time_order() {
        let a = SegmentKey {
            stamp: "20140329T140938Z".into(),
            number: 9,
        };
        let b = SegmentKey {
            stamp: "20140329T140938Z".into(),
            number: 10,
        };
        let c = SegmentKey {
            stamp: "20140329T140939Z".into(),
            number: 0,
        };
        assert_eq!(a.file_name(), "sunjitter-20140329T140938Z-0009.mcap");
        for k in [&a, &b, &c] {
            assert_eq!(SegmentKey::parse(&k.file_name()).as_ref(), Some(k));
        }
        assert!(a.file_name() < b.file_name() && b.file_name() < c.file_name());
        assert!(a < b && b < c);
        for bad in [
            "sunjitter-20140329T140938Z-009.mcap",
            "sunjitter-20140329T140938-0009.mcap",
            "sunjitter-20140329T140938Z-0009.mcap.recovering",
            "other-20140329T140938Z-0009.mcap",
        ] {
            assert_eq!(SegmentKey::parse(bad), None, "{bad}");
        }
    }
}
