//! Every command's `--help` ends with examples, and the examples that finish quickly run as
//! printed: through `sh`, in a directory where `data/` and `examples/` are the bundled ones.
//! Their stderr goes to a pipe, where no progress bar may be drawn.

use std::path::Path;
use std::process::Command;
use sunjitter_core::error::ExitCode;

const COMMANDS: [&str; 8] = [
    "info", "align", "watch", "replay", "inspect", "simulate", "synth", "status",
];

fn help(command: &str) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args([command, "--help"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{command} --help");
    String::from_utf8(out.stdout).unwrap()
}

/// The command lines of the `Examples:` block, continuation lines joined.
fn examples(help: &str) -> Vec<String> {
    let block = help.split_once("Examples:\n").map_or("", |(_, b)| b);
    block
        .replace(" \\\n", " ")
        .lines()
        .filter(|l| l.starts_with("  sunjitter "))
        .map(|l| l.split_whitespace().collect::<Vec<_>>().join(" "))
        .collect()
}

#[test]
fn every_command_help_ends_with_examples() {
    for command in COMMANDS {
        let text = help(command);
        let lines = examples(&text);
        assert!(
            (2..=3).contains(&lines.len()),
            "{command}: two or three examples:\n{text}"
        );
        for line in &lines {
            assert!(line.starts_with(&format!("sunjitter {command} ")), "{line}");
        }
    }
}

/// Runs `line` with `sh` in `dir`, the binary first on `PATH`; exit code and stderr.
fn run(dir: &Path, bin: &Path, line: &str) -> (i32, String) {
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let out = Command::new("sh")
        .args(["-c", line])
        .current_dir(dir)
        .env("PATH", path)
        .env("SUNJITTER_LOG", "warn")
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn the_quick_examples_run_as_printed_and_draw_no_bar_on_a_pipe() {
    let tmp = tempfile::tempdir().unwrap();
    let (dir, bin) = (tmp.path().join("work"), tmp.path().join("bin"));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::create_dir_all(&bin).unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for linked in ["data", "examples"] {
        std::os::unix::fs::symlink(root.join(linked), dir.join(linked)).unwrap();
    }
    std::os::unix::fs::symlink(env!("CARGO_BIN_EXE_sunjitter"), bin.join("sunjitter")).unwrap();

    // In this order: inspect reads what replay wrote.
    let mut ran = Vec::new();
    for command in ["info", "align", "synth", "replay", "inspect", "simulate"] {
        for line in examples(&help(command)) {
            let slow = line.contains("--realtime")
                || line.contains("trace_171")
                || line.contains("--trials 50")
                || line.contains("SJI_2796")
                || line.contains("SJI_*")
                || (command == "synth" && !line.contains("--size 256"));
            if slow {
                continue;
            }
            let (code, stderr) = run(&dir, &bin, &line);
            assert_eq!(code, ExitCode::Ok.code(), "{line}: {stderr}");
            assert!(
                !stderr.contains('\r') && !stderr.contains('\u{1b}'),
                "{line}: terminal control on a pipe: {stderr:?}"
            );
            ran.push(line);
        }
    }
    for command in ["info", "align", "synth", "replay", "inspect", "simulate"] {
        assert!(
            ran.iter()
                .any(|l| l.starts_with(&format!("sunjitter {command} "))),
            "no {command} example ran: {ran:#?}"
        );
    }
    assert!(dir.join("out/sji1400").is_dir());
    assert!(dir.join("synth/truth.csv").is_file());
    assert!(dir.join("jitter.png").is_file() && dir.join("jitter.csv").is_file());
    assert!(dir.join("pair.png").is_file() && dir.join("eit_195_on_171.fits").is_file());
}

/// On a terminal (a pseudo-terminal from `script`, where installed) `simulate` draws its bar.
#[test]
fn simulate_draws_its_bar_on_a_terminal() {
    let Ok(which) = Command::new("sh")
        .args(["-c", "command -v script"])
        .output()
    else {
        return;
    };
    if !which.status.success() {
        eprintln!("no `script` here to give the run a terminal; skipped");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let typescript = tmp.path().join("typescript");
    let image =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("data/real/aia_171_20110215T000000_128.fits");
    let line = format!(
        "'{}' simulate '{}' --trials 2 --cc-trials 0 >/dev/null",
        env!("CARGO_BIN_EXE_sunjitter"),
        image.display()
    );
    let status = Command::new("script")
        .args(["-qfec", &line])
        .arg(&typescript)
        .stdout(std::process::Stdio::null())
        .status()
        .unwrap();
    assert!(status.success());
    let seen = std::fs::read_to_string(&typescript).unwrap();
    assert!(seen.contains("/2 trials"), "{seen:?}");
}
