//! Thin binary: parse the command line, run the library, map errors to exit codes.

mod allocator;

use clap::{Parser, Subcommand};
use std::io::Write;
use sunjitter::cli;
use sunjitter_core::error::ExitCode;

#[derive(Debug, Parser)]
#[command(
    name = "sunjitter",
    version,
    about = "Pointing-jitter monitor for solar telescopes",
    after_help = EXAMPLES
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

const EXAMPLES: &str = "\
Examples:
  sunjitter info data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits
  sunjitter replay data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits --out out/sji1400
  sunjitter inspect out/sji1400 --plot jitter.png
Each command's --help has its own examples.

Environment:
  SUNJITTER_LOG        what is logged to stderr (default info; e.g. warn, sunjitter_core=debug)
  SUNJITTER_CACHE_DIR  where references' self-tests are kept between runs
                       (default $XDG_CACHE_HOME/sunjitter or ~/.cache/sunjitter; empty: nowhere)
  NO_COLOR             no colour in the log
  SUNJITTER_PORTABLE_KERNELS
                       1: the portable numeric kernels on any CPU, not the AVX2 ones";

#[derive(Debug, Subcommand)]
enum Command {
    /// Print the header metadata sunjitter uses, one line per image or frame of a cube.
    #[command(after_help = cli::info::EXAMPLES)]
    Info(cli::info::Args),
    /// Align one frame to one reference: shift, rotation and scale with 1-σ errors.
    #[command(after_help = cli::align::EXAMPLES)]
    Align(cli::align::Args),
    /// Watch a directory and log every new frame's alignment to MCAP (the daemon).
    #[command(after_help = cli::watch::EXAMPLES)]
    Watch(cli::watch::Args),
    /// Run the watch pipeline over archived files, directories, globs or cubes.
    #[command(after_help = cli::replay::EXAMPLES)]
    Replay(cli::replay::Args),
    /// Join the logs of `replay --shard K/N` into one, chained series stitched across shards.
    #[command(after_help = cli::merge::EXAMPLES)]
    Merge(cli::merge::Args),
    /// Summarise MCAP logs: statistics, jitter spectrum, outliers, CSV and plots.
    #[command(after_help = cli::inspect::EXAMPLES)]
    Inspect(cli::inspect::Args),
    /// Wang et al.'s Monte Carlo accuracy test on one image.
    ///
    /// Applies random similarities (scale, rotation, shift) to the image, aligns each copy back
    /// with the engine (Farnebäck flow, RANSAC similarity fit, errors from the Jacobian
    /// covariance, "UABJM") and reports the residuals against the truth and how often they
    /// fall within 1σ and 3σ; a translation-only run compares with cross-correlation.
    #[command(after_help = cli::simulate::EXAMPLES)]
    Simulate(cli::simulate::Args),
    /// Write a synthetic FITS sequence with known jitter, and its truth.csv.
    #[command(after_help = cli::synth::EXAMPLES)]
    Synth(cli::synth::Args),
    /// Print a running (or stopped) daemon's health status.
    #[command(after_help = cli::status::EXAMPLES)]
    Status(cli::status::Args),
}

/// Log fields as the default format writes them, with control characters escaped: a value
/// (a file name, a reason) cannot start a fake log line or reach the terminal raw.
fn escaped_fields() -> impl for<'w> tracing_subscriber::fmt::FormatFields<'w> {
    use tracing_subscriber::field::MakeExt;
    tracing_subscriber::fmt::format::debug_fn(|w, field, value| {
        let text = format!("{value:?}");
        let text = sunjitter_core::text::escape(&text);
        match field.name() {
            "message" => write!(w, "{text}"),
            name => write!(w, "{name}={text}"),
        }
    })
    .delimited(" ")
}

fn main() {
    allocator::tune();
    // Colour only for a person at a terminal, and never when NO_COLOR is set (no-color.org).
    let colour = std::io::IsTerminal::is_terminal(&std::io::stderr())
        && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    tracing_subscriber::fmt()
        .with_ansi(colour)
        .with_writer(sunjitter::cli::BarAwareStderr)
        .fmt_fields(escaped_fields())
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("SUNJITTER_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();

    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            let code = if e.use_stderr() {
                ExitCode::BadInput
            } else {
                ExitCode::Ok
            };
            let _ = e.print();
            std::process::exit(code.code());
        }
    };
    // Decompressed copies a killed run left behind (their names carry the dead process's id).
    sunjitter_io::fits::remove_stale_gunzipped_copies();
    let outcome = match &cli.command {
        Command::Info(a) => cli::info::run(a),
        Command::Align(a) => cli::align::run(a),
        Command::Watch(a) => cli::watch::run(a),
        Command::Replay(a) => cli::replay::run(a),
        Command::Merge(a) => cli::merge::run(a),
        Command::Inspect(a) => cli::inspect::run(a),
        Command::Simulate(a) => cli::simulate::run(a),
        Command::Synth(a) => cli::synth::run(a),
        Command::Status(a) => cli::status::run(a),
    };
    match outcome {
        Ok(code) => std::process::exit(code.code()),
        Err(e) => {
            // Not eprintln!: a stderr that cannot be written (a full disk) must not turn the
            // error into a panic.
            let _ = writeln!(
                std::io::stderr(),
                "sunjitter: {}",
                sunjitter_core::text::escape(&e.to_string())
            );
            std::process::exit(e.exit_code().code());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Cli;
    use clap::{CommandFactory, Parser};

    /// The command lines of a help text's `Examples:` block: lines that start `  sunjitter `,
    /// with ` \` continuations joined, split into words as a shell would (single quotes only).
    fn examples(help: &str) -> Vec<Vec<String>> {
        let block = help.split_once("Examples:\n").map_or("", |(_, b)| b);
        let joined = block.replace(" \\\n", " ");
        joined
            .lines()
            .filter(|l| l.starts_with("  sunjitter "))
            .map(|l| {
                let mut words = Vec::new();
                for (i, part) in l.trim().split('\'').enumerate() {
                    if i % 2 == 1 {
                        words.push(part.to_string());
                    } else {
                        words.extend(part.split_whitespace().map(String::from));
                    }
                }
                words
            })
            .collect()
    }

    #[test]
    fn every_command_shows_examples_that_parse() {
        let mut cli = Cli::command();
        cli.build();
        let top = examples(&cli.render_help().to_string());
        assert!(top.len() >= 2, "{top:?}");
        for sub in cli.get_subcommands_mut().filter(|s| s.get_name() != "help") {
            let name = sub.get_name().to_string();
            let help = sub.render_help().to_string();
            let lines = examples(&help);
            assert!((2..=3).contains(&lines.len()), "{name}: {help}");
            for words in lines.iter().chain(&top).filter(|w| w[1] == name) {
                if let Err(e) = Cli::try_parse_from(words) {
                    panic!("{words:?} does not parse: {e}");
                }
            }
        }
    }

    #[test]
    fn shared_flags_read_the_same_in_every_command() {
        let cli = Cli::command();
        for flag in ["config", "out", "reference", "recursive", "json"] {
            let helps: std::collections::BTreeSet<String> = cli
                .get_subcommands()
                .filter(|s| s.get_name() != "synth" || flag != "out")
                .flat_map(|s| s.get_arguments())
                .filter(|a| a.get_long() == Some(flag))
                .map(|a| a.get_help().map(|h| h.to_string()).unwrap_or_default())
                .collect();
            assert_eq!(helps.len(), 1, "--{flag}: {helps:#?}");
            assert!(!helps.iter().any(String::is_empty), "--{flag} is described");
        }
    }

    #[test]
    fn every_argument_is_described_in_one_line_and_its_default_shown_once() {
        let cli = Cli::command();
        for sub in cli.get_subcommands() {
            for arg in sub.get_arguments() {
                let what = format!("{} {}", sub.get_name(), arg.get_id());
                let help = arg.get_help().map(|h| h.to_string()).unwrap_or_default();
                assert!(!help.is_empty(), "{what} is not described");
                assert!(!help.contains('\n'), "{what}: {help}");
                if !arg.get_default_values().is_empty() {
                    // clap appends `[default: …]` itself.
                    assert!(!help.contains("default"), "{what}: {help}");
                }
            }
        }
    }
}
