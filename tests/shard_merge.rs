//! `replay --shard K/N` and `merge` against a single replay of the same inputs: the bundled
//! IRIS slit-jaw cubes (SJI 1400 on its keyframes, SJI 2796 aligned to the nearest SJI 1400
//! frame), with keyframes every 8 frames so that chains cross every shard boundary.

mod support;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use sunjitter_core::error::ExitCode;
use sunjitter_core::record::FrameAlignment;
use support::sunjitter;

const SJI_1400: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";
const SJI_2796: &str =
    "data/real/iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits";
/// Frames in the cubes (astropy: NAXIS3).
const FRAMES: [(&str, usize); 2] = [("SJI_1400", 54), ("SJI_2796", 72)];

const CONFIG: &str = r#"
[reference]
keyframe_every_frames = 8

[channels.SJI_2796]
policy = "channel:SJI_1400"
tolerance_s = 150.0
"#;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn input(p: &str) -> String {
    root().join(p).display().to_string()
}

fn run_ok(args: &[String]) -> String {
    let (code, out, err) = sunjitter(args);
    assert_eq!(code, ExitCode::Ok.code(), "sunjitter {args:?}: {err}");
    out
}

/// A single run, four shards and their merge, made once for the tests of this file.
struct Fixture {
    dir: PathBuf,
    config: PathBuf,
    single: PathBuf,
    shards: Vec<PathBuf>,
    merged: PathBuf,
}

fn replay_args(config: &Path, out: &Path, extra: &[&str]) -> Vec<String> {
    let mut args: Vec<String> = vec!["replay".into(), input(SJI_1400), input(SJI_2796)];
    args.extend(["--config".into(), config.display().to_string()]);
    args.extend(["--out".into(), out.display().to_string()]);
    args.extend(extra.iter().map(|s| s.to_string()));
    args
}

fn merge_args(shards: &[PathBuf], out: &Path) -> Vec<String> {
    let mut args = vec!["merge".to_string()];
    args.extend(shards.iter().map(|s| s.display().to_string()));
    args.extend(["--out".into(), out.display().to_string(), "--json".into()]);
    args
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let dir = root().join("target/tmp/shard_merge");
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let config = dir.join("config.toml");
        std::fs::write(&config, CONFIG).unwrap();
        let single = dir.join("single");
        run_ok(&replay_args(&config, &single, &[]));
        let shards: Vec<PathBuf> = (0..4).map(|k| dir.join(format!("shard-{k}"))).collect();
        for (k, out) in shards.iter().enumerate() {
            run_ok(&replay_args(&config, out, &["--shard", &format!("{k}/4")]));
        }
        let merged = dir.join("merged");
        // Given in another order than 0..4: the merge sorts them.
        let mut given = shards.clone();
        given.reverse();
        run_ok(&merge_args(&given, &merged));
        Fixture {
            dir,
            config,
            single,
            shards,
            merged,
        }
    })
}

fn frames(dir: &Path) -> Vec<FrameAlignment> {
    let log = sunjitter_io::sink::read_logs(&[dir.to_path_buf()]).expect("log reads");
    log.jitter.into_iter().map(|m| m.record).collect()
}

/// How a merged log compares with the single run.
#[derive(Debug, Default)]
struct Comparison {
    same_reference: usize,
    chained: usize,
    within_1_sigma: usize,
}

fn compare(single: &[FrameAlignment], merged: &[FrameAlignment]) -> Comparison {
    let one: HashMap<&str, &FrameAlignment> =
        single.iter().map(|m| (m.align.frame.as_str(), m)).collect();
    let mut counts: HashMap<&str, usize> = HashMap::new();
    for m in merged {
        *counts.entry(m.align.frame.as_str()).or_default() += 1;
    }
    assert!(
        counts.values().all(|&c| c == 1),
        "a frame logged twice: {:?}",
        counts.iter().find(|(_, &c)| c > 1)
    );
    assert_eq!(
        counts.len(),
        one.len(),
        "every frame of the single run, once"
    );
    let mut c = Comparison::default();
    for m in merged {
        let s = one.get(m.align.frame.as_str()).expect("frame of the run");
        assert_eq!(m.channel, s.channel);
        if (&m.align.reference, &m.reference_kind) == (&s.align.reference, &s.reference_kind) {
            c.same_reference += 1;
            let numbers = |f: &FrameAlignment| {
                let a = &f.align;
                (
                    [
                        a.scale,
                        a.rotation_arcsec,
                        a.dx_px,
                        a.dy_px,
                        a.sigma_dx_px,
                        a.sigma_dy_px,
                    ],
                    a.status,
                    f.sequence,
                )
            };
            assert_eq!(numbers(m), numbers(s), "{}", m.align.frame);
        }
        let (Some(sx), Some(sy)) = (s.chained_dx_px, s.chained_dy_px) else {
            continue;
        };
        c.chained += 1;
        let (sig_x, sig_y) = (
            s.sigma_chained_dx_px.unwrap().max(1e-9),
            s.sigma_chained_dy_px.unwrap().max(1e-9),
        );
        if let (Some(mx), Some(my)) = (m.chained_dx_px, m.chained_dy_px) {
            if (mx - sx).abs() <= sig_x && (my - sy).abs() <= sig_y {
                c.within_1_sigma += 1;
            }
        }
    }
    c
}

#[test]
fn four_shards_merged_equal_the_single_run() {
    let f = fixture();
    let single = frames(&f.single);
    let merged = frames(&f.merged);
    for (channel, n) in FRAMES {
        assert_eq!(
            merged.iter().filter(|m| m.channel == channel).count(),
            n,
            "{channel}"
        );
    }
    let c = compare(&single, &merged);
    // Every SJI 1400 frame keeps its reference (keyframes predicted exactly); SJI 2796 frames
    // keep their partner frame.
    assert_eq!(c.same_reference, single.len(), "{c:?}");
    let chained = single.iter().filter(|m| m.chained_dx_px.is_some()).count();
    assert_eq!(c.chained, chained, "{c:?}");
    assert!(chained >= 100, "most frames have a chained value: {c:?}");
    assert!(
        c.within_1_sigma as f64 >= 0.95 * c.chained as f64,
        "chained within 1σ: {c:?}"
    );
    // Sequence numbers run 0.. per channel in time order, as in one run.
    let mut by_channel: BTreeMap<&str, Vec<u64>> = BTreeMap::new();
    for m in &merged {
        by_channel.entry(&m.channel).or_default().push(m.sequence);
    }
    for seqs in by_channel.values_mut() {
        seqs.sort();
        assert_eq!(*seqs, (0..seqs.len() as u64).collect::<Vec<_>>());
    }
}

#[test]
fn each_shard_logs_only_its_own_range_and_the_merge_names_them() {
    let f = fixture();
    let mut total = 0;
    for (k, shard) in f.shards.iter().enumerate() {
        let log = sunjitter_io::sink::read_logs(std::slice::from_ref(shard)).unwrap();
        let meta = log
            .metadata
            .iter()
            .find(|m| m.name == "sunjitter.shard")
            .expect("shard metadata");
        assert_eq!(meta.metadata["shard"], format!("{k}/4"));
        assert_eq!(meta.metadata["total_frames"], "126");
        assert_eq!(meta.metadata["inputs_digest"].len(), 64);
        assert_eq!(meta.metadata["config_digest"].len(), 64);
        let own: usize = meta.metadata["end"].parse::<usize>().unwrap()
            - meta.metadata["start"].parse::<usize>().unwrap();
        assert_eq!(log.jitter.len(), own, "shard {k} logs its own frames only");
        total += own;
    }
    assert_eq!(total, 126);
    let log = sunjitter_io::sink::read_logs(std::slice::from_ref(&f.merged)).unwrap();
    let meta = log
        .metadata
        .iter()
        .find(|m| m.name == "sunjitter.merge")
        .expect("merge metadata");
    let named: Vec<String> = serde_json::from_str(&meta.metadata["shards"]).unwrap();
    assert_eq!(named.len(), 4);
    assert!(log.segments.iter().all(|s| s.complete));
}

#[test]
fn previous_policy_shards_merge_to_the_single_run() {
    let f = fixture();
    let dir = f.dir.join("previous");
    let one = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "replay".to_string(),
            input(SJI_1400),
            "--reference".into(),
            "previous".into(),
            "--out".into(),
            out.display().to_string(),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        run_ok(&args);
    };
    one(&dir.join("single"), &[]);
    let shards: Vec<PathBuf> = (0..3).map(|k| dir.join(format!("s{k}"))).collect();
    for (k, s) in shards.iter().enumerate() {
        one(s, &["--shard", &format!("{k}/3")]);
    }
    run_ok(&merge_args(&shards, &dir.join("merged")));
    let single = frames(&dir.join("single"));
    let c = compare(&single, &frames(&dir.join("merged")));
    assert_eq!(c.same_reference, 54, "{c:?}");
    assert!(c.within_1_sigma as f64 >= 0.95 * c.chained as f64, "{c:?}");
}

/// The refusal contract: exit 2, one line naming the problem, nothing written.
fn assert_refused(args: &[String], out: &Path, needle: &str) {
    let (code, stdout, stderr) = sunjitter(args);
    assert_eq!(code, ExitCode::BadInput.code(), "{args:?}: {stderr}");
    assert!(stdout.is_empty(), "{stdout}");
    let lines: Vec<&str> = stderr.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "one line: {stderr}");
    assert!(lines[0].contains(needle), "{needle:?} in {stderr}");
    assert!(!out.exists(), "nothing written at {}", out.display());
}

#[test]
fn merge_refuses_a_missing_shard() {
    let f = fixture();
    let out = f.dir.join("refused-missing");
    assert_refused(
        &merge_args(&f.shards[..3], &out),
        &out,
        "shard 3/4 is missing",
    );
    let mut gone = f.shards.clone();
    gone[2] = f.dir.join("no-such-shard");
    assert_refused(&merge_args(&gone, &out), &out, "no-such-shard");
}

#[test]
fn merge_refuses_a_doubled_shard() {
    let f = fixture();
    let out = f.dir.join("refused-doubled");
    let mut doubled = f.shards.clone();
    doubled.push(f.shards[1].clone());
    assert_refused(
        &merge_args(&doubled, &out),
        &out,
        "shard 1/4 is given twice",
    );
    // A copy of a shard in place of another: its range (and frames) twice.
    let copy = f.dir.join("copy-of-1");
    copy_dir(&f.shards[1], &copy);
    let mut swapped = f.shards.clone();
    swapped[2] = copy;
    assert_refused(&merge_args(&swapped, &out), &out, "given twice");
}

#[test]
fn merge_refuses_shards_of_other_inputs_or_configuration() {
    let f = fixture();
    let out = f.dir.join("refused-mismatch");
    // Shard 1 of the SJI 1400 cube alone: other inputs.
    let other_inputs = f.dir.join("other-inputs-1");
    run_ok(&[
        "replay".into(),
        input(SJI_1400),
        "--config".into(),
        f.config.display().to_string(),
        "--shard".into(),
        "1/4".into(),
        "--out".into(),
        other_inputs.display().to_string(),
    ]);
    let mut set = f.shards.clone();
    set[1] = other_inputs.clone();
    assert_refused(&merge_args(&set, &out), &out, "other inputs");
    // Shard 0 with keyframes every 9 frames: another configuration.
    let config = f.dir.join("other.toml");
    std::fs::write(&config, CONFIG.replace("= 8", "= 9")).unwrap();
    let other_config = f.dir.join("other-config-0");
    run_ok(&replay_args(&config, &other_config, &["--shard", "0/4"]));
    let mut set = f.shards.clone();
    set[3] = other_config;
    assert_refused(&merge_args(&set, &out), &out, "another configuration");
    // Shard 0 of 3 among shards of 4.
    let of_three = f.dir.join("one-of-three");
    run_ok(&replay_args(&f.config, &of_three, &["--shard", "0/3"]));
    let mut set = f.shards.clone();
    set[1] = of_three;
    assert_refused(&merge_args(&set, &out), &out, "is one of 3");
    // A log that is not a shard's.
    let mut set = f.shards.clone();
    set[0] = f.single.clone();
    assert_refused(&merge_args(&set, &out), &out, "not a shard's log");
}

fn copy_dir(from: &Path, to: &Path) {
    let _ = std::fs::remove_dir_all(to);
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.path().extension().is_some_and(|x| x == "mcap") {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

#[test]
fn a_shard_run_again_after_a_crash_replaces_its_output() {
    let f = fixture();
    // Shard 0 killed mid-way: its segment cut short (no summary, no completion record).
    let requeued = f.dir.join("requeued-0");
    copy_dir(&f.shards[0], &requeued);
    let segment = std::fs::read_dir(&requeued)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|x| x == "mcap"))
        .unwrap();
    let len = std::fs::metadata(&segment).unwrap().len();
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(&segment)
        .unwrap();
    file.set_len(len * 2 / 3).unwrap();
    drop(file);
    let mut set = f.shards.clone();
    set[0] = requeued.clone();
    let out = f.dir.join("requeued-merge");
    let _ = std::fs::remove_dir_all(&out);
    assert_refused(&merge_args(&set, &out), &out, "shard 0/4");

    // The requeued job runs the shard again into the same directory: replaced, not added to.
    run_ok(&replay_args(&f.config, &requeued, &["--shard", "0/4"]));
    run_ok(&replay_args(&f.config, &requeued, &["--shard", "0/4"]));
    let again = frames(&requeued);
    assert_eq!(again.len(), frames(&f.shards[0]).len());
    run_ok(&merge_args(&set, &out));
    let c = compare(&frames(&f.single), &frames(&out));
    assert_eq!(c.same_reference, 126, "{c:?}");
    // The merge run again replaces its own output.
    run_ok(&merge_args(&set, &out));
    assert_eq!(frames(&out).len(), 126);
}

#[test]
fn a_shard_never_replaces_a_log_that_is_not_its_own() {
    let f = fixture();
    let out = f.dir.join("foreign");
    copy_dir(&f.single, &out);
    let before = frames(&out).len();
    let (code, _, err) = sunjitter(&replay_args(&f.config, &out, &["--shard", "0/4"]));
    assert_eq!(code, ExitCode::BadInput.code(), "{err}");
    assert!(err.contains("refusing to replace"), "{err}");
    assert_eq!(frames(&out).len(), before);
    // Nor the output of another shard.
    let (code, _, err) = sunjitter(&replay_args(&f.config, &f.shards[1], &["--shard", "0/4"]));
    assert_eq!(code, ExitCode::BadInput.code(), "{err}");
    // And the merge never writes over a log either.
    let (code, _, err) = sunjitter(&merge_args(&f.shards, &f.single));
    assert_eq!(code, ExitCode::BadInput.code(), "{err}");
    let (code, _, err) = sunjitter(&merge_args(&f.shards, &f.shards[0]));
    assert_eq!(code, ExitCode::BadInput.code(), "{err}");
}

#[test]
fn shard_flags_are_checked_before_any_work() {
    let f = fixture();
    let out = f.dir.join("bad-flags");
    for bad in ["4/4", "1/0", "x/4"] {
        let (code, _, err) = sunjitter(&replay_args(&f.config, &out, &["--shard", bad]));
        assert_eq!(code, ExitCode::BadInput.code(), "{bad}: {err}");
        assert!(!out.exists());
    }
}
