//! `replay`/`watch --aligned DIR [--wcs-only]`: one FITS product per measured frame.
//!
//! Truth: synthetic frames with injected motion (`sunjitter synth`, its `truth.csv`), and the
//! bundled real files. The header-only products are checked by sunpy and astropy
//! (`tools/check_pointing_products.py`), not by sunjitter's own WCS code.

mod support;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use sunjitter_core::error::ExitCode;
use sunjitter_core::record::{ReferenceKind, Status};
use sunjitter_io::fits::{self, FrameSpec};
use support::{logged, sunjitter, sunjitter_ok, WatchProcess, QUICK_DAEMON_CONFIG};

/// Synthetic frames of 256² with a 1.5 px sinusoid, a random walk and a roll drift; the Sun
/// does not turn, so a feature's true coordinates do not change.
fn synth(dir: &Path, frames: usize) -> PathBuf {
    let out = dir.join("frames");
    sunjitter_ok(&[
        "synth",
        "--out",
        out.to_str().unwrap(),
        "--frames",
        &frames.to_string(),
        "--size",
        "256",
        "--seed",
        "11",
        "--jitter",
        "sine:1.5:60,walk:0.1,rot:7200",
        "--solar-rotation",
        "none",
    ]);
    out
}

/// Engine settings for a Sun that does not turn.
fn still_sun_config(dir: &Path) -> PathBuf {
    let path = dir.join("still.toml");
    std::fs::write(&path, "[engine]\nsolar_rotation = \"none\"\n").unwrap();
    path
}

/// Logged frames: key → (status, reference kind).
fn logged_frames(out: &Path) -> BTreeMap<String, (Status, ReferenceKind)> {
    let logs = sunjitter_io::sink::read_logs(&[out.to_path_buf()]).unwrap();
    logs.jitter
        .iter()
        .map(|m| {
            let r = &m.record;
            (r.align.frame.clone(), (r.align.status, r.reference_kind))
        })
        .collect()
}

/// A frame key's file name without `.fits` (and without `[N]`): its product's name stem.
fn stem(key: &str) -> String {
    let file = key.rsplit('/').next().unwrap();
    let file = file.split_once('[').map_or(file, |(f, _)| f);
    file.strip_suffix(".fits").unwrap().to_string()
}

/// Every file below `dir` (relative), sorted.
fn files_below(dir: &Path) -> Vec<String> {
    let mut found = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                found.push(p.strip_prefix(dir).unwrap().display().to_string());
            }
        }
    }
    found.sort();
    found
}

/// Run the independent Python checker; its output must end in `N passed, 0 failed`.
fn python_check(args: &[&str]) {
    let out = std::process::Command::new("python3")
        .arg("tools/check_pointing_products.py")
        .args(args)
        .output()
        .expect("python3 runs (the checker needs astropy, sunpy and scipy: see .ci/run)");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "checker failed:\n{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    println!("{text}");
}

#[test]
fn header_only_products_give_features_the_origins_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let frames = synth(dir.path(), 8);
    let out = dir.path().join("log");
    let products = dir.path().join("products");
    let config = still_sun_config(dir.path());
    sunjitter_ok(&[
        "replay",
        frames.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--reference",
        "previous",
        "--aligned",
        products.to_str().unwrap(),
        "--wcs-only",
    ]);
    let logged = logged_frames(&out);
    assert_eq!(logged.len(), 8);
    let expected: Vec<String> = logged
        .iter()
        .filter(|(_, (s, _))| *s != Status::Failed)
        .map(|(k, _)| format!("{}.wcs.fits", stem(k)))
        .collect();
    assert_eq!(files_below(&products), expected, "one product per frame");

    // The pixels are the frame's own.
    let first = frames.join("synth_0003.fits");
    let input = fits::read_frame(&FrameSpec::parse(first.to_str().unwrap())).unwrap();
    let product = fits::read_frame(&FrameSpec::parse(
        products.join("synth_0003.wcs.fits").to_str().unwrap(),
    ))
    .unwrap();
    assert_eq!(input.data, product.data);

    // `previous` chains every frame through all before it: the origin is the first frame.
    python_check(&[
        products.to_str().unwrap(),
        "--origin",
        frames.join("synth_0000.fits").to_str().unwrap(),
        "--truth",
        frames.join("truth.csv").to_str().unwrap(),
        "--expect",
        &expected.len().to_string(),
    ]);
}

/// RMS of `a − b` over the central half of the image, where both are finite.
fn central_rms(a: &ndarray::Array2<f32>, b: &ndarray::Array2<f32>) -> f64 {
    let (h, w) = a.dim();
    let (mut n, mut s) = (0.0, 0.0);
    for y in h / 4..3 * h / 4 {
        for x in w / 4..3 * w / 4 {
            let d = a[[y, x]] as f64 - b[[y, x]] as f64;
            if d.is_finite() {
                n += 1.0;
                s += d * d;
            }
        }
    }
    (s / n).sqrt()
}

#[test]
fn resampled_products_register_every_frame_on_the_origin() {
    let dir = tempfile::tempdir().unwrap();
    let frames = synth(dir.path(), 6);
    let out = dir.path().join("log");
    let products = dir.path().join("products");
    let config = still_sun_config(dir.path());
    sunjitter_ok(&[
        "replay",
        frames.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--aligned",
        products.to_str().unwrap(),
    ]);
    let read = |p: &Path| fits::read_frame(&FrameSpec::parse(p.to_str().unwrap())).unwrap();
    let origin = read(&frames.join("synth_0000.fits"));
    let (_, origin_header) = fits::read_image_header(&frames.join("synth_0000.fits")).unwrap();
    let truth = support::read_csv(&frames.join("truth.csv"));
    let motion = |k: usize| {
        let v = |k: usize, c: &str| truth[k][c].parse::<f64>().unwrap();
        (v(k, "dx_px") - v(0, "dx_px")).hypot(v(k, "dy_px") - v(0, "dy_px"))
    };
    let mut residuals = Vec::new();
    for k in 1..6 {
        let name = format!("synth_{k:04}.fits");
        let raw = read(&frames.join(&name));
        let product_path = products.join(format!("synth_{k:04}.aligned.fits"));
        let product = read(&product_path);
        let before = central_rms(&raw.data, &origin.data);
        let after = central_rms(&product.data, &origin.data);
        println!(
            "{name}: motion {:.3} px, rms vs origin {before:.2} → {after:.2}",
            motion(k)
        );
        assert!(after < before, "{name}: {after} after, {before} before");
        if motion(k) > 1.0 {
            assert!(
                after < 0.5 * before,
                "{name}: {after} after, {before} before"
            );
        }
        residuals.push(after);
        // On the origin's grid, with its WCS.
        let (_, h) = fits::read_image_header(&product_path).unwrap();
        for key in ["CRPIX1", "CRPIX2", "CDELT1", "CDELT2", "CRVAL1", "CRVAL2"] {
            assert_eq!(
                h.get(key).and_then(|v| v.as_f64()),
                origin_header.get(key).and_then(|v| v.as_f64()),
                "{name}: {key}"
            );
        }
        let history: Vec<String> = h
            .cards()
            .iter()
            .filter(|c| c.key == "HISTORY")
            .map(|c| c.comment.clone())
            .collect();
        assert!(
            history.iter().any(|l| l.contains("chain origin")),
            "{history:?}"
        );
    }
    // Registered, only the two frames' noise is left: the same whatever the motion.
    let (lo, hi) = residuals
        .iter()
        .fold((f64::MAX, 0.0f64), |(l, h), &r| (l.min(r), h.max(r)));
    assert!(hi < 1.15 * lo, "residuals {residuals:?}");
    // The origin's product is the origin's pixels.
    assert_eq!(
        read(&products.join("synth_0000.aligned.fits")).data,
        origin.data
    );
}

#[test]
fn a_failed_frame_has_no_product_and_the_others_do() {
    let dir = tempfile::tempdir().unwrap();
    let frames = synth(dir.path(), 4);
    // Frame 2 carries no image: its alignment fails.
    let blank = frames.join("synth_0002.fits");
    let image = fits::read_frame(&FrameSpec::parse(blank.to_str().unwrap())).unwrap();
    let (_, header) = fits::read_image_header(&blank).unwrap();
    let cards = fits::frame_header_cards(&header, &image.meta);
    let zeros = ndarray::Array2::<f32>::zeros(image.data.dim());
    fits::write_image(&blank, zeros.view(), &cards).unwrap();

    let out = dir.path().join("log");
    let products = dir.path().join("products");
    sunjitter_ok(&[
        "replay",
        frames.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--aligned",
        products.to_str().unwrap(),
        "--wcs-only",
    ]);
    let logged = logged_frames(&out);
    let failed: Vec<&String> = logged
        .iter()
        .filter(|(_, (s, _))| *s == Status::Failed)
        .map(|(k, _)| k)
        .collect();
    assert_eq!(failed.len(), 1, "{logged:?}");
    assert!(failed[0].ends_with("synth_0002.fits"));
    assert_eq!(
        files_below(&products),
        [
            "synth_0000.wcs.fits",
            "synth_0001.wcs.fits",
            "synth_0003.wcs.fits"
        ]
    );
}

#[test]
fn same_named_frames_in_different_directories_get_distinct_products() {
    let dir = tempfile::tempdir().unwrap();
    let frames = synth(dir.path(), 4);
    let tree = dir.path().join("tree");
    for sub in ["a", "b"] {
        std::fs::create_dir_all(tree.join(sub)).unwrap();
    }
    // Two frames named alike, one in each directory.
    for (k, sub) in [(0, "a"), (1, "b"), (2, "a/x"), (3, "b/x")] {
        std::fs::create_dir_all(tree.join(sub)).unwrap();
        let target = if sub.ends_with('x') {
            tree.join(sub).join("frame.fits")
        } else {
            tree.join(sub).join(format!("synth_{k:04}.fits"))
        };
        std::fs::copy(frames.join(format!("synth_{k:04}.fits")), target).unwrap();
    }
    let out = dir.path().join("log");
    let products = dir.path().join("products");
    sunjitter_ok(&[
        "replay",
        tree.to_str().unwrap(),
        "--recursive",
        "--out",
        out.to_str().unwrap(),
        "--aligned",
        products.to_str().unwrap(),
    ]);
    assert_eq!(
        files_below(&products),
        [
            "a/synth_0000.aligned.fits",
            "a/x/frame.aligned.fits",
            "b/synth_0001.aligned.fits",
            "b/x/frame.aligned.fits",
        ]
    );
}

#[test]
fn a_product_directory_inside_the_inputs_or_the_log_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let watched = dir.path().join("incoming");
    std::fs::create_dir_all(&watched).unwrap();
    let out = dir.path().join("log");
    let inside = watched.join("products");
    let (code, stdout, stderr) = sunjitter(&[
        "watch".as_ref(),
        watched.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--aligned".as_ref(),
        inside.as_os_str(),
    ]);
    assert_eq!(code, ExitCode::BadInput.code(), "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
    assert!(
        stderr.contains("products") && stderr.contains("inside"),
        "{stderr}"
    );
    assert!(stdout.is_empty());
    assert!(!inside.exists(), "nothing created");

    let file = "data/real/aia_171_20110215T000000_128.fits";
    for (products, why) in [
        (out.clone(), "log directory"),
        (out.join("p"), "log directory"),
        (PathBuf::from("data/real/products"), "inside"),
        (PathBuf::from("data"), "holds"),
    ] {
        let (code, _, stderr) = sunjitter(&[
            "replay".as_ref(),
            file.as_ref(),
            "--out".as_ref(),
            out.as_os_str(),
            "--aligned".as_ref(),
            products.as_os_str(),
        ]);
        assert_eq!(code, ExitCode::BadInput.code(), "{products:?}: {stderr}");
        assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
        assert!(stderr.contains(why), "{products:?}: {stderr}");
    }
    assert!(!Path::new("data/real/products").exists());

    // --wcs-only alone says what it needs.
    let (code, _, stderr) = sunjitter(&["replay", file, "--out", "x", "--wcs-only"]);
    assert_eq!(code, ExitCode::BadInput.code(), "{stderr}");
    assert!(stderr.contains("--aligned"), "{stderr}");

    // A shard's chains start at its own origin: products come from a single run only.
    let products = dir.path().join("shard_products");
    let shard_out = dir.path().join("shard_log");
    let (code, _, stderr) = sunjitter(&[
        "replay".as_ref(),
        file.as_ref(),
        "--out".as_ref(),
        shard_out.as_os_str(),
        "--shard".as_ref(),
        "0/2".as_ref(),
        "--aligned".as_ref(),
        products.as_os_str(),
    ]);
    assert_eq!(code, ExitCode::BadInput.code(), "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
    assert!(stderr.contains("--shard"), "{stderr}");
    assert!(!products.exists() && !shard_out.exists(), "nothing created");
}

#[test]
fn a_real_cube_gets_one_header_only_product_per_measured_frame_on_its_chain() {
    let dir = tempfile::tempdir().unwrap();
    let cube = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";
    let out = dir.path().join("log");
    let products = dir.path().join("products");
    sunjitter_ok(&[
        "replay",
        cube,
        "--out",
        out.to_str().unwrap(),
        "--aligned",
        products.to_str().unwrap(),
        "--wcs-only",
    ]);
    let logs = sunjitter_io::sink::read_logs(std::slice::from_ref(&out)).unwrap();
    let name = stem(cube);
    let mut expected = Vec::new();
    for m in &logs.jitter {
        let r = &m.record;
        let n = r
            .align
            .frame
            .rsplit_once('[')
            .unwrap()
            .1
            .trim_end_matches(']');
        let product = products.join(format!("{name}[{n}].wcs.fits"));
        if r.align.status == Status::Failed {
            assert!(!product.exists(), "{product:?}");
            continue;
        }
        // The product carries the chain the log holds.
        let (_, h) = fits::read_image_header(&product).unwrap();
        let card = |k: &str| h.get(k).and_then(|v| v.as_f64()).unwrap();
        // Cards hold 15 significant digits.
        let same = |a: f64, b: f64| (a - b).abs() <= 1e-12 * b.abs().max(1.0);
        assert!(same(card("SJ_DX"), r.chained_dx_px.unwrap()), "{n}");
        assert!(same(card("SJ_DY"), r.chained_dy_px.unwrap()), "{n}");
        assert!(same(card("SJ_SCALE"), r.chained_scale.unwrap()), "{n}");
        expected.push(format!("{name}[{n}].wcs.fits"));
    }
    expected.sort();
    assert!(expected.len() > 40, "{} products", expected.len());
    assert_eq!(files_below(&products), expected);
    // sunpy (independently of sunjitter's WCS code) puts each frame's chained pixels at the
    // origin's coordinates, across keyframe changes.
    let origin = products.join(format!("{name}[0].wcs.fits"));
    python_check(&[
        products.to_str().unwrap(),
        "--origin",
        origin.to_str().unwrap(),
        "--chain",
        "--expect",
        &expected.len().to_string(),
    ]);
}

#[test]
fn a_refused_plate_scale_is_not_the_one_products_state() {
    // EIT's header says 2.63″/px; the disk it shows says about 20.6″/px, which the alignment
    // used. Both kinds of product must state the latter.
    let reference = "data/real/eit_171_20040301T010016_128.fits";
    let frame = "data/real/eit_195_20040301T000010_128.fits";
    for wcs_only in [false, true] {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("log");
        let products = dir.path().join("products");
        let fixed = format!("fixed:{reference}");
        let mut args = vec![
            "replay",
            reference,
            frame,
            "--reference",
            &fixed,
            "--out",
            out.to_str().unwrap(),
            "--aligned",
            products.to_str().unwrap(),
        ];
        if wcs_only {
            args.push("--wcs-only");
        }
        sunjitter_ok(&args);
        let logs = sunjitter_io::sink::read_logs(std::slice::from_ref(&out)).unwrap();
        let m = logs
            .jitter
            .iter()
            .find(|m| {
                m.record
                    .align
                    .frame
                    .ends_with("eit_195_20040301T000010_128.fits")
            })
            .unwrap();
        let used = m.record.align.dx_arcsec.unwrap() / m.record.align.dx_px.unwrap();
        assert!((used - 20.6).abs() < 1.0, "plate scale used {used}");
        assert_eq!(files_below(&products).len(), 2);
        python_check(&[products.to_str().unwrap(), "--origin", reference, "--disk"]);
    }
}

/// A watch started with `--aligned … --wcs-only` on `watched`.
fn spawn_watch(watched: &Path, out: &Path, config: &Path, products: &Path) -> WatchProcess {
    spawn_watch_with(
        watched,
        out,
        config,
        &[
            "--aligned".as_ref(),
            products.as_os_str(),
            "--wcs-only".as_ref(),
        ],
    )
}

/// A watch started on `watched` with further arguments.
fn spawn_watch_with(
    watched: &Path,
    out: &Path,
    config: &Path,
    args: &[&std::ffi::OsStr],
) -> WatchProcess {
    let stderr = out.with_extension("stderr");
    let file = std::fs::File::create(&stderr).unwrap();
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("watch")
        .arg(watched)
        .args(["--out".as_ref(), out.as_os_str()])
        .args(["--config".as_ref(), config.as_os_str()])
        .args(args)
        .env("SUNJITTER_LOG", "info")
        .stdout(std::process::Stdio::null())
        .stderr(file)
        .spawn()
        .unwrap();
    WatchProcess { child, stderr }
}

/// Put a frame into the watched directory as instruments do (hidden name, then rename).
fn publish_file(watched: &Path, from: &Path) {
    let name = from.file_name().unwrap().to_str().unwrap();
    let tmp = watched.join(format!(".{name}.tmp"));
    std::fs::copy(from, &tmp).unwrap();
    std::fs::rename(&tmp, watched.join(name)).unwrap();
}

#[test]
fn after_a_kill_and_a_restart_every_logged_frame_has_exactly_one_product() {
    let dir = tempfile::tempdir().unwrap();
    let frames = synth(dir.path(), 6);
    let watched = dir.path().join("incoming");
    std::fs::create_dir_all(&watched).unwrap();
    let out = dir.path().join("log");
    let products = dir.path().join("products");
    let config = dir.path().join("watch.toml");
    std::fs::write(
        &config,
        format!("{QUICK_DAEMON_CONFIG}\n[engine]\nsolar_rotation = \"none\"\n"),
    )
    .unwrap();
    let frame = |k: usize| frames.join(format!("synth_{k:04}.fits"));

    let mut first = spawn_watch(&watched, &out, &config, &products);
    first.wait_watching();
    for k in 0..3 {
        publish_file(&watched, &frame(k));
    }
    first.wait_until("three frames logged", |_| logged(&out).len() >= 3);
    first.kill();

    let mut second = spawn_watch(&watched, &out, &config, &products);
    second.wait_watching();
    for k in 3..6 {
        publish_file(&watched, &frame(k));
    }
    second.wait_until("six frames logged", |_| logged(&out).len() >= 6);
    assert!(second.terminate().success());

    let counts = logged(&out);
    assert!(counts.values().all(|&n| n == 1), "{counts:?}");
    let statuses = logged_frames(&out);
    let expected: Vec<String> = statuses
        .iter()
        .filter(|(_, (s, _))| *s != Status::Failed)
        .map(|(k, _)| format!("{}.wcs.fits", stem(k)))
        .collect();
    assert_eq!(expected.len(), 6, "{statuses:?}");
    let visible: Vec<String> = files_below(&products)
        .into_iter()
        .filter(|f| !f.starts_with('.'))
        .collect();
    assert_eq!(visible, expected);
    // The frames measured after the restart are put on the chain's origin too.
    python_check(&[
        products.to_str().unwrap(),
        "--origin",
        frame(0).to_str().unwrap(),
        "--truth",
        frames.join("truth.csv").to_str().unwrap(),
        "--expect",
        "6",
    ]);
}

#[test]
fn a_product_that_cannot_be_written_is_one_log_warning_and_the_frame_is_still_logged() {
    let dir = tempfile::tempdir().unwrap();
    let frames = synth(dir.path(), 3);
    let out = dir.path().join("log");
    let products = dir.path().join("products");
    // A directory where frame 1's product would go: it cannot be put in place.
    std::fs::create_dir_all(products.join("synth_0001.wcs.fits")).unwrap();
    sunjitter_ok(&[
        "replay",
        frames.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--aligned",
        products.to_str().unwrap(),
        "--wcs-only",
    ]);
    let logs = sunjitter_io::sink::read_logs(std::slice::from_ref(&out)).unwrap();
    assert_eq!(logs.jitter.len(), 3, "every frame is logged");
    let notes: Vec<_> = logs
        .logs
        .iter()
        .filter(|m| m.entry.message.starts_with("product not written"))
        .collect();
    assert_eq!(notes.len(), 1, "{:?}", logs.logs);
    assert!(notes[0].entry.file.ends_with("synth_0001.fits"));
    assert_eq!(notes[0].entry.message.lines().count(), 1);
    for k in [0, 2] {
        assert!(products.join(format!("synth_{k:04}.wcs.fits")).is_file());
    }
}

#[test]
fn align_replay_and_watch_write_one_wcs_for_one_grid_with_the_roll_in_pc() {
    // EIT's headers give the roll only as SOHO's SC_ROLL = 180 (no CROTA, no PCi_j), which
    // astropy and sunpy ignore. The frame put on the reference's grid by each command must
    // carry the roll as PCi_j and the same WCS; astropy and sunpy are the judges.
    let reference = "data/real/eit_171_20040301T010016_128.fits";
    let frame = "data/real/eit_195_20040301T000010_128.fits";
    let fixed = format!("fixed:{reference}");
    let dir = tempfile::tempdir().unwrap();

    let paired = dir.path().join("pair.fits");
    sunjitter_ok(&[
        "align",
        reference,
        frame,
        "--aligned",
        paired.to_str().unwrap(),
    ]);

    let replayed = dir.path().join("replayed");
    sunjitter_ok(&[
        "replay",
        reference,
        frame,
        "--reference",
        &fixed,
        "--out",
        dir.path().join("replay_log").to_str().unwrap(),
        "--aligned",
        replayed.to_str().unwrap(),
    ]);
    assert_eq!(
        files_below(&replayed),
        [
            "eit_171_20040301T010016_128.aligned.fits",
            "eit_195_20040301T000010_128.aligned.fits"
        ]
    );

    let watched = dir.path().join("incoming");
    std::fs::create_dir_all(&watched).unwrap();
    let watch_out = dir.path().join("watch_log");
    let watched_products = dir.path().join("watched");
    let config = dir.path().join("watch.toml");
    std::fs::write(&config, QUICK_DAEMON_CONFIG).unwrap();
    let mut watch = spawn_watch_with(
        &watched,
        &watch_out,
        &config,
        &[
            "--reference".as_ref(),
            fixed.as_ref(),
            "--aligned".as_ref(),
            watched_products.as_os_str(),
        ],
    );
    watch.wait_watching();
    publish_file(&watched, Path::new(frame));
    watch.wait_until("the frame logged", |_| !logged(&watch_out).is_empty());
    assert!(watch.terminate().success());
    assert_eq!(
        files_below(&watched_products),
        ["eit_195_20040301T000010_128.aligned.fits"]
    );

    let product = "eit_195_20040301T000010_128.aligned.fits";
    let out = std::process::Command::new("python3")
        .arg("tools/check_aligned_wcs.py")
        .args(["--input", reference])
        .arg(&paired)
        .arg(replayed.join(product))
        .arg(watched_products.join(product))
        .output()
        .expect("python3 runs (the checker needs astropy and sunpy: see .ci/run)");
    let text = String::from_utf8_lossy(&out.stdout);
    println!("{text}");
    assert!(
        out.status.success(),
        "checker failed:\n{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("sunpy roll 180 deg"), "{text}");
    assert!(text.trim_end().ends_with("passed, 0 failed"), "{text}");
}

#[test]
fn two_inputs_differing_only_in_extension_never_share_a_product() {
    let dir = tempfile::tempdir().unwrap();
    let frames = synth(dir.path(), 3);
    let inputs = dir.path().join("inputs");
    std::fs::create_dir_all(&inputs).unwrap();
    std::fs::copy(frames.join("synth_0000.fits"), inputs.join("a.fits")).unwrap();
    std::fs::copy(frames.join("synth_0001.fits"), inputs.join("b.fits")).unwrap();
    // `b.fits.gz` holds another frame (synth_0002) under b's stem.
    let raw = std::fs::read(frames.join("synth_0002.fits")).unwrap();
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    std::io::Write::write_all(&mut gz, &raw).unwrap();
    std::fs::write(inputs.join("b.fits.gz"), gz.finish().unwrap()).unwrap();

    let out = dir.path().join("log");
    let products = dir.path().join("products");
    let config = still_sun_config(dir.path());
    sunjitter_ok(&[
        "replay",
        inputs.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--aligned",
        products.to_str().unwrap(),
        "--wcs-only",
    ]);
    let logs = sunjitter_io::sink::read_logs(std::slice::from_ref(&out)).unwrap();
    assert_eq!(logs.jitter.len(), 3, "every frame is logged");
    assert_eq!(files_below(&products), ["a.wcs.fits", "b.wcs.fits"]);
    // One of b.fits and b.fits.gz has the product; the other a note naming it.
    let (_, h) = fits::read_image_header(&products.join("b.wcs.fits")).unwrap();
    let source = h
        .get("SRCFILE")
        .and_then(|v| v.as_str())
        .unwrap()
        .to_string();
    let notes: Vec<_> = logs
        .logs
        .iter()
        .filter(|m| m.entry.message.starts_with("product not written"))
        .collect();
    assert_eq!(notes.len(), 1, "{:?}", logs.logs);
    let loser = if source.ends_with("b.fits.gz") {
        "b.fits"
    } else {
        "b.fits.gz"
    };
    assert!(
        source.ends_with("b.fits") || source.ends_with("b.fits.gz"),
        "{source}"
    );
    assert!(notes[0].entry.file.ends_with(loser), "{:?}", notes[0].entry);
    assert!(
        notes[0]
            .entry
            .message
            .contains("differs only in its extension"),
        "{}",
        notes[0].entry.message
    );
}
