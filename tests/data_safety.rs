//! No setting, rerun, merge or link destroys data: the status file is never written over an
//! input, a reference or the configuration, nor inside the watched tree; a merge run again is
//! written beside its earlier output and replaces it in one step, so a kill at any moment
//! leaves the earlier one whole; the daemon never takes its own products, whatever link leads
//! to them; an `--out` holds one run (a rerun of it resumes, another is refused); a product
//! that cannot be written leaves no temporary file behind.
//!
//! Truths: the files' bytes before and after, frame counts read back by the project's MCAP
//! reader, exit codes and one-line messages (the contract).

mod support;

use std::collections::BTreeMap;
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use sunjitter_core::error::ExitCode;
use sunjitter_runtime::fake::{split_cube, SplitFrame};
use support::{logged, publish, sunjitter, WatchProcess, QUICK_DAEMON_CONFIG};

const SJI_1400: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";
const AIA: &str = "data/real/aia_171_20110215T000000_128.fits";

fn real(p: &str) -> PathBuf {
    support::repo_file(p)
}

/// The first `n` frames of the SJI 1400 cube, written as files into `dir`.
fn frames_in(dir: &Path, n: usize) -> Vec<PathBuf> {
    support::cube_frames_into(SJI_1400, dir, n)
}

fn split(n: usize) -> Vec<SplitFrame> {
    let scratch = tempfile::tempdir().unwrap();
    let mut all = split_cube(&real(SJI_1400), scratch.path()).unwrap();
    all.truncate(n);
    all
}

fn os(parts: &[&dyn AsRef<OsStr>]) -> Vec<std::ffi::OsString> {
    parts.iter().map(|p| p.as_ref().to_os_string()).collect()
}

/// A refusal as the contract has it: exit 2, one line naming `path` and containing `why`.
fn assert_refused(run: (i32, String, String), path: &Path, why: &str) {
    let (code, _, stderr) = run;
    assert_eq!(code, ExitCode::BadInput.code(), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    let lines: Vec<&str> = stderr.lines().collect();
    assert_eq!(lines.len(), 1, "one line: {stderr}");
    assert!(
        lines[0].contains(&path.display().to_string()),
        "{} not named: {stderr}",
        path.display()
    );
    assert!(lines[0].contains(why), "{why:?} not in: {stderr}");
}

/// Bytes of every log segment in `dir`, by name.
fn segments(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .map(|e| e.unwrap().path())
                .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
                .map(|p| {
                    let name = p.file_name().unwrap().to_string_lossy().into_owned();
                    (name, std::fs::read(&p).unwrap())
                })
                .collect()
        })
        .unwrap_or_default()
}

fn jitter_count(dir: &Path) -> usize {
    sunjitter_io::sink::read_logs(&[dir.to_path_buf()])
        .unwrap()
        .jitter
        .len()
}

// ---------------------------------------------------------------------------------------------
// The status file

#[test]
fn a_status_file_on_an_input_a_reference_or_the_configuration_is_refused_and_nothing_changes() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().canonicalize().unwrap();
    let watched = base.join("in");
    let inputs = frames_in(&watched, 1);
    let reference = base.join("ref.fits");
    std::fs::copy(real(AIA), &reference).unwrap();
    let hard_link = base.join("ref-link.fits");
    std::fs::hard_link(&reference, &hard_link).unwrap();
    std::os::unix::fs::symlink(&watched, base.join("alias")).unwrap();
    let config = base.join("sunjitter.toml");
    let cases: Vec<(PathBuf, &str)> = vec![
        (inputs[0].clone(), "inside the watched directory"),
        (
            base.join("alias/status.json"),
            "inside the watched directory",
        ),
        (reference.clone(), "is an input"),
        (hard_link.clone(), "is an input"),
        (config.clone(), "is an input"),
    ];
    for (status_file, why) in cases {
        let text = format!(
            "[reference]\npolicy = \"fixed:{}\"\n[health]\nstatus_file = \"{}\"\n",
            reference.display(),
            status_file.display()
        );
        std::fs::write(&config, &text).unwrap();
        let protected: Vec<(PathBuf, Vec<u8>)> = [&inputs[0], &reference, &config]
            .iter()
            .map(|p| (p.to_path_buf(), std::fs::read(p).unwrap()))
            .collect();
        let out = base.join("out");
        assert_refused(
            sunjitter(&os(&[
                &"watch",
                &watched,
                &"--out",
                &out,
                &"--config",
                &config,
            ])),
            &status_file,
            why,
        );
        for (path, bytes) in protected {
            assert_eq!(std::fs::read(&path).unwrap(), bytes, "{path:?} changed");
        }
        assert!(!base.join("alias/status.json").exists());
        assert!(segments(&out).is_empty(), "no log was written");
    }
    // A status file whose directory does not exist: bad usage too, before any work.
    let missing = base.join("nowhere/status.json");
    std::fs::write(
        &config,
        format!("[health]\nstatus_file = \"{}\"\n", missing.display()),
    )
    .unwrap();
    let out = base.join("out2");
    assert_refused(
        sunjitter(&os(&[
            &"watch",
            &watched,
            &"--out",
            &out,
            &"--config",
            &config,
        ])),
        &base.join("nowhere"),
        "cannot write here",
    );
    assert!(segments(&out).is_empty());
}

// ---------------------------------------------------------------------------------------------
// Merge: a rerun never destroys the earlier output

/// Two shards of `inputs`, each in its own directory under `base`.
fn two_shards(base: &Path, inputs: &Path, config: &Path) -> Vec<PathBuf> {
    support::replay_shards(base, inputs, Some(config), 2)
}

fn merge_command(shards: &[PathBuf], out: &Path) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_sunjitter"));
    cmd.arg("merge")
        .args(shards)
        .arg("--out")
        .arg(out)
        .env("SUNJITTER_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    cmd
}

/// The parent's entries beside `out` that are not `out` or the shards: staging leftovers.
fn leftovers(base: &Path) -> Vec<String> {
    std::fs::read_dir(base)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".merge-"))
        .collect()
}

#[test]
fn a_merge_killed_while_replacing_its_earlier_output_leaves_it_whole() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().canonicalize().unwrap();
    let inputs = base.join("frames");
    frames_in(&inputs, 6);
    let config = base.join("config.toml");
    // Segments of two frames: the merge writes several files.
    std::fs::write(
        &config,
        "[reference]\nkeyframe_every_frames = 3\n[sink]\nsegment_frames = 2\n",
    )
    .unwrap();
    let shards = two_shards(&base, &inputs, &config);
    let merged = base.join("merged");
    let began = std::time::Instant::now();
    let first = merge_command(&shards, &merged).output().unwrap();
    let span_us = began.elapsed().as_micros() as u64;
    assert!(first.status.success(), "{:?}", first);
    let earlier = segments(&merged);
    assert!(earlier.len() >= 3, "{:?}", earlier.keys());
    assert_eq!(jitter_count(&merged), 6);

    // Killed at moments spread over a merge's run (seeded fractions of the first merge's
    // duration): reading the shards, writing beside, putting in place, cleaning up.
    let mut seed = 0x5eed_u64;
    let mut next = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 33) % 1000
    };
    let mut interrupted = 0;
    for _ in 0..24 {
        let mut child = merge_command(&shards, &merged).spawn().unwrap();
        std::thread::sleep(std::time::Duration::from_micros(span_us * next() / 1000));
        if child.try_wait().unwrap().is_none() {
            interrupted += 1;
        }
        let _ = child.kill();
        let _ = child.wait();
        // Whatever the moment: the earlier merge, or (killed after the swap) the new one,
        // finished files holding every frame once. Never a mix, never a part.
        let contents = sunjitter_io::sink::read_logs(std::slice::from_ref(&merged)).unwrap();
        assert!(
            contents.segments.iter().all(|s| s.complete),
            "{:?}",
            contents.segments
        );
        let frames: std::collections::BTreeSet<&str> = contents
            .jitter
            .iter()
            .map(|m| m.record.align.frame.as_str())
            .collect();
        assert_eq!((contents.jitter.len(), frames.len()), (6, 6));
        let now = segments(&merged);
        assert_eq!(
            now.keys().collect::<Vec<_>>(),
            earlier.keys().collect::<Vec<_>>(),
            "the same run merges into the same segments"
        );
    }
    assert!(
        interrupted >= 3,
        "only {interrupted} merges were killed while running"
    );
    // And the next merge works, cleaning up after the killed ones.
    let last = merge_command(&shards, &merged).output().unwrap();
    assert!(
        last.status.success(),
        "{}",
        String::from_utf8_lossy(&last.stderr)
    );
    assert_eq!(jitter_count(&merged), 6);
    let left: Vec<(String, Vec<String>)> = leftovers(&base)
        .into_iter()
        .map(|n| {
            let inside = std::fs::read_dir(base.join(&n))
                .map(|d| {
                    d.map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                        .collect()
                })
                .unwrap_or_default();
            (n, inside)
        })
        .collect();
    assert!(left.is_empty(), "{left:?}");
    let names: Vec<String> = std::fs::read_dir(&merged)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| !n.ends_with(".mcap") && n != sunjitter_io::outputs::LOCK_FILE)
        .collect();
    assert!(names.is_empty(), "{names:?}");
}

#[test]
fn merge_writes_only_into_a_new_or_empty_directory_or_over_its_own_merge() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().canonicalize().unwrap();
    let inputs = base.join("frames");
    frames_in(&inputs, 4);
    let config = base.join("config.toml");
    std::fs::write(&config, "[reference]\nkeyframe_every_frames = 2\n").unwrap();
    let shards = two_shards(&base, &inputs, &config);
    let merge = |out: &Path| {
        let mut args = vec!["merge".into()];
        args.extend(shards.iter().map(|s| s.as_os_str().to_os_string()));
        args.extend(os(&[&"--out", &out]));
        sunjitter(&args)
    };
    // The input directory, and a directory holding something else: refused, untouched.
    let before: Vec<(PathBuf, Vec<u8>)> = std::fs::read_dir(&inputs)
        .unwrap()
        .map(|e| e.unwrap().path())
        .map(|p| (p.clone(), std::fs::read(&p).unwrap()))
        .collect();
    assert_refused(merge(&inputs), &inputs, "other file(s)");
    let other = base.join("other");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::write(other.join("notes.txt"), "mine").unwrap();
    assert_refused(merge(&other), &other, "notes.txt");
    for (path, bytes) in &before {
        assert_eq!(&std::fs::read(path).unwrap(), bytes);
    }
    assert_eq!(std::fs::read_dir(&inputs).unwrap().count(), before.len());
    assert_eq!(
        std::fs::read_to_string(other.join("notes.txt")).unwrap(),
        "mine"
    );
    // A shard's own output: refused.
    assert_refused(merge(&shards[0]), &shards[0], "shard");
    // An empty directory, then over its own merge.
    let empty = base.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    assert_eq!(merge(&empty).0, ExitCode::Ok.code());
    assert_eq!(merge(&empty).0, ExitCode::Ok.code());
    assert_eq!(jitter_count(&empty), 4);
}

// ---------------------------------------------------------------------------------------------
// The daemon never takes its own products

#[test]
fn products_reached_through_a_link_in_the_watched_tree_are_never_taken() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().canonicalize().unwrap();
    let watched = base.join("in");
    let products = base.join("products");
    std::fs::create_dir_all(watched.join("frames")).unwrap();
    std::fs::create_dir_all(&products).unwrap();
    // A link under the watched tree to the product directory: the paths differ, the
    // directory is the same.
    std::os::unix::fs::symlink(&products, watched.join("corrected")).unwrap();
    let config = base.join("config.toml");
    std::fs::write(
        &config,
        format!("{QUICK_DAEMON_CONFIG}recursive = true\nfollow_symlinks = true\n"),
    )
    .unwrap();
    let out = base.join("out");
    let frames = split(5);
    let spawn = |name: &str| {
        let file = std::fs::File::create(base.join(name)).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
            .arg("watch")
            .arg(&watched)
            .args(["--out".as_ref(), out.as_os_str()])
            .args(["--config".as_ref(), config.as_os_str()])
            .args(["--aligned".as_ref(), products.as_os_str()])
            .env("SUNJITTER_LOG", "info")
            .stdout(Stdio::null())
            .stderr(file)
            .spawn()
            .unwrap();
        WatchProcess {
            child,
            stderr: base.join(name),
        }
    };
    let mut first = spawn("1.stderr");
    first.wait_watching();
    for f in &frames[..4] {
        publish(&watched.join("frames"), f);
    }
    first.wait_until("4 frames logged", |_| logged(&out).len() == 4);
    assert!(first.terminate().success());
    // A restart scans the whole tree, the link included, then takes one more frame.
    let mut second = spawn("2.stderr");
    second.wait_watching();
    publish(&watched.join("frames"), &frames[4]);
    second.wait_until("5 frames logged", |_| {
        logged(&out).values().sum::<usize>() >= 5
    });
    assert!(second.terminate().success());

    let counts = logged(&out);
    assert_eq!(counts.len(), 5, "{counts:?}");
    assert!(counts.values().all(|&n| n == 1), "{counts:?}");
    assert!(
        counts.keys().all(|k| !k.contains(".aligned.fits")),
        "a product was taken as a frame: {counts:?}"
    );
    let made: Vec<String> = walk(&products);
    assert_eq!(made.len(), 5, "one product per frame: {made:?}");
    assert!(
        made.iter().all(|p| p.ends_with(".aligned.fits")),
        "{made:?}"
    );
}

/// Files under `dir`, relative, recursively.
fn walk(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut dirs = vec![dir.to_path_buf()];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                dirs.push(p);
            } else {
                out.push(p.strip_prefix(dir).unwrap().display().to_string());
            }
        }
    }
    out.sort();
    out
}

// ---------------------------------------------------------------------------------------------
// One run per --out

#[test]
fn a_rerun_of_the_same_replay_resumes_and_another_run_is_refused_saying_why() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().canonicalize().unwrap();
    let a = base.join("a");
    frames_in(&a, 3);
    let b = base.join("b");
    std::fs::create_dir_all(&b).unwrap();
    std::fs::copy(real(AIA), b.join("aia.fits")).unwrap();
    let out = base.join("out");
    let replay = |extra: &[&dyn AsRef<OsStr>]| {
        let mut args = os(&[&"replay"]);
        args.extend(os(extra));
        args.extend(os(&[&"--out", &out]));
        sunjitter(&args)
    };
    let (code, _, err) = replay(&[&a]);
    assert_eq!(code, ExitCode::Ok.code(), "{err}");
    let logged = segments(&out);
    assert_eq!(jitter_count(&out), 3);

    // The same run again: nothing to do, and it says so.
    let (code, _, err) = replay(&[&a]);
    assert_eq!(code, ExitCode::Ok.code(), "{err}");
    assert!(err.contains("all 3 frames already logged"), "{err}");
    assert_eq!(segments(&out), logged);
    // Settings that change no measurement may differ between the runs of one log.
    let sink_only = base.join("sink.toml");
    std::fs::write(&sink_only, "[sink]\nflush_every_frames = 3\n").unwrap();
    let (code, _, err) = replay(&[&a, &"--config", &sink_only]);
    assert_eq!(code, ExitCode::Ok.code(), "{err}");
    assert!(err.contains("all 3 frames already logged"), "{err}");

    // Another policy, another engine setting, other inputs: refused, saying what differs.
    assert_refused(
        replay(&[&a, &"--reference", &"previous"]),
        &out,
        "reference.policy = \"keyframe\", this run has \"previous\"",
    );
    let engine = base.join("engine.toml");
    std::fs::write(&engine, "[engine]\nsample = 24\n").unwrap();
    assert_refused(
        replay(&[&a, &"--config", &engine]),
        &out,
        "engine.sample = 20, this run has 24",
    );
    assert_refused(
        replay(&[&a, &b]),
        &out,
        "other inputs (3 files there, 4 files here)",
    );
    assert_refused(replay(&[&b]), &out, "other inputs");
    // A watch into a replay's log, and a shard into it: refused too.
    let (code, _, err) = sunjitter(&os(&[&"watch", &b, &"--out", &out]));
    assert_eq!(code, ExitCode::BadInput.code(), "{err}");
    assert!(
        err.contains("it is a replay of 3 files, this is a watch"),
        "{err}"
    );
    assert_refused(replay(&[&a, &"--shard", &"0/2"]), &out, "not a shard's");
    // Every refusal left the log as it was.
    assert_eq!(segments(&out), logged);

    // A plain replay into a shard's output (forgot --shard): refused.
    let shard = base.join("shard");
    let (code, _, err) = sunjitter(&os(&[&"replay", &a, &"--out", &shard, &"--shard", &"1/2"]));
    assert_eq!(code, ExitCode::Ok.code(), "{err}");
    let shard_log = segments(&shard);
    let (code, _, err) = sunjitter(&os(&[&"replay", &a, &"--out", &shard]));
    assert_eq!(code, ExitCode::BadInput.code(), "{err}");
    assert!(err.contains("holds shard 1/2's log"), "{err}");
    assert_eq!(segments(&shard), shard_log);
}

#[test]
fn the_log_is_never_written_among_the_inputs() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().canonicalize().unwrap();
    let watched = base.join("in");
    frames_in(&watched, 1);
    let inside = watched.join("log");
    assert_refused(
        sunjitter(&os(&[&"watch", &watched, &"--out", &inside])),
        &inside,
        "inside the watched directory",
    );
    assert!(!inside.exists());
    // A replay's log beside its input files.
    assert_refused(
        sunjitter(&os(&[&"replay", &watched, &"--out", &watched])),
        &watched,
        "inside the input directory",
    );
}

// ---------------------------------------------------------------------------------------------
// A product that cannot be written

#[test]
fn a_product_that_cannot_be_written_leaves_no_temporary_file() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().canonicalize().unwrap();
    let inputs = base.join("frames");
    let files = frames_in(&inputs, 3);
    let products = base.join("products");
    let out = base.join("out");
    let config = base.join("config.toml");
    std::fs::write(&config, "[sink]\nsegment_frames = 1\n").unwrap();
    // Each product (the frame as 32-bit floats) is larger than any file may grow here, as
    // on a full disk; the log's segments (one frame each) are smaller.
    let limit = 40 * 1024;
    let product_size = files
        .iter()
        .map(|f| std::fs::metadata(f).unwrap().len())
        .min()
        .unwrap();
    assert!(product_size > limit, "{product_size}");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_sunjitter"));
    cmd.arg("replay")
        .arg(&inputs)
        .args(["--out".as_ref(), out.as_os_str()])
        .args(["--aligned".as_ref(), products.as_os_str()])
        .args(["--config".as_ref(), config.as_os_str()])
        .env("SUNJITTER_LOG", "warn")
        .env("SUNJITTER_CACHE_DIR", "");
    support::with_rlimit(&mut cmd, libc::RLIMIT_FSIZE, limit);
    let run = cmd.output().unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(ExitCode::Ok.code()), "{stderr}");
    let contents = sunjitter_io::sink::read_logs(std::slice::from_ref(&out)).unwrap();
    assert_eq!(contents.jitter.len(), 3, "{stderr}");
    let notes = contents
        .logs
        .iter()
        .filter(|m| m.entry.message.starts_with("product not written"))
        .count();
    assert_eq!(notes, 3, "{:?}", contents.logs);
    assert!(walk(&products).is_empty(), "{:?}", walk(&products));
}
