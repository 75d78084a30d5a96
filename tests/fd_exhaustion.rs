//! Out of file descriptors (EMFILE) while a frame arrives: the `watch` daemon must wait and
//! measure it once descriptors are back, not report it unreadable for good. The fault is
//! real: the test lowers the soft `RLIMIT_NOFILE` of its own process (daemon included) to
//! the lowest free descriptor, so every open fails, exactly as long as the test wants. That
//! limit is process-wide, hence this test is alone in its binary.

mod support;

use std::sync::Arc;
use sunjitter_io::records::MemorySink;
use sunjitter_io::sink::LogLevel;
use sunjitter_runtime::pipeline::FitsReader;
use support::faults::*;

/// The soft descriptor limit lowered so that no new descriptor can be opened; restored on
/// drop (a failing assertion included).
struct NoNewDescriptors(libc::rlimit);

impl NoNewDescriptors {
    fn now() -> NoNewDescriptors {
        let mut saved = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: plain system calls on a local struct.
        assert_eq!(
            unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut saved) },
            0
        );
        // Descriptors are handed out lowest first: every one below this is in use.
        let lowest_free = {
            use std::os::fd::AsRawFd;
            std::fs::File::open("/dev/null").unwrap().as_raw_fd()
        };
        let lowered = libc::rlimit {
            rlim_cur: lowest_free as libc::rlim_t,
            rlim_max: saved.rlim_max,
        };
        // SAFETY: as above.
        assert_eq!(unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &lowered) }, 0);
        NoNewDescriptors(saved)
    }
}

impl Drop for NoNewDescriptors {
    fn drop(&mut self) {
        // SAFETY: as above.
        unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &self.0) };
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frame_arriving_without_file_descriptors_is_measured_once_they_return() {
    let src = source();
    let frames = crops(&src, "fd", 3, 64, 8);
    let dir = tempfile::tempdir().unwrap();
    let staging = tempfile::tempdir_in(dir.path().parent().unwrap()).unwrap();
    let root = canonical(dir.path());
    let sink = MemorySink::default();
    let daemon = start(
        &root,
        quick_config(),
        Arc::new(FitsReader::default()),
        Arc::new(HeaderShiftAligner),
        Box::new(sink.clone()),
    );
    daemon.watching().await;
    publish(&root, &frames[0]);
    daemon
        .wait_for("the first frame", |p| p.finished >= 1)
        .await;

    // Written beforehand: while descriptors are out, the test cannot open a file either.
    let victim = &frames[1];
    let staged = staging.path().join(&victim.name);
    std::fs::write(&staged, &victim.bytes).unwrap();
    let fault = NoNewDescriptors::now();
    let refused = std::fs::File::open("/dev/null").unwrap_err();
    assert_eq!(refused.raw_os_error(), Some(libc::EMFILE), "{refused}");
    std::fs::rename(&staged, root.join(&victim.name)).unwrap();
    daemon
        .wait_for("a /log entry on the unreadable frame", |p| {
            p.notes + p.skipped >= 1
        })
        .await;
    drop(fault);
    publish(&root, &frames[2]);
    daemon.wait_for("3 inputs", |p| p.finished >= 3).await;
    let progress = daemon.shutdown().await;

    let records = sink.records();
    let split = split(&records);
    assert_each_once_and_true(&split, &frames);
    assert_eq!((progress.frames, progress.skipped), (3, 0));
    let logs: Vec<_> = split
        .logs
        .iter()
        .filter(|l| !l.2.contains("out of time order"))
        .collect();
    assert_eq!(logs.len(), 1, "{logs:?}");
    let (level, file, message) = logs[0];
    assert_eq!(
        (*level, file.as_str()),
        (LogLevel::Warning, victim.name.as_str())
    );
    assert!(
        message.starts_with("cannot be read for now, retrying")
            && message.contains("Too many open files"),
        "{message}"
    );
}
