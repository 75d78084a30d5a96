//! Thin binary: parse the command line, run the library, map errors to exit codes.

use clap::{Parser, Subcommand};
use sunjitter::commands;

#[derive(Debug, Parser)]
#[command(
    name = "sunjitter",
    version,
    about = "Pointing-jitter monitor for solar telescopes"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Print the normalised header metadata of FITS files.
    Info(commands::info::Args),
    /// Align one frame to one reference.
    Align(commands::align::Args),
    /// Watch a directory and log every new frame's alignment to MCAP.
    Watch(commands::watch::Args),
    /// Run the same pipeline over archived files, directories, globs or cubes.
    Replay(commands::replay::Args),
    /// Summarise MCAP logs: statistics, spectrum, CSV, plots.
    Inspect(commands::inspect::Args),
    /// The paper's Monte Carlo accuracy test on one image.
    Simulate(commands::simulate::Args),
    /// Write a synthetic FITS sequence with known jitter.
    Synth(commands::synth::Args),
    /// Print a running (or stopped) daemon's health status.
    Status(commands::status::Args),
}

/// Log fields as the default format writes them, with control characters escaped: a value
/// (a file name, a reason) cannot start a fake log line or reach the terminal raw.
fn escaped_fields() -> impl for<'w> tracing_subscriber::fmt::FormatFields<'w> {
    use tracing_subscriber::field::MakeExt;
    tracing_subscriber::fmt::format::debug_fn(|w, field, value| {
        let text = format!("{value:?}");
        let text = sunjitter::text::escape(&text);
        match field.name() {
            "message" => write!(w, "{text}"),
            name => write!(w, "{name}={text}"),
        }
    })
    .delimited(" ")
}

fn main() {
    // Colour only for a person at a terminal, and never when NO_COLOR is set (no-color.org).
    let colour = std::io::IsTerminal::is_terminal(&std::io::stderr())
        && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    tracing_subscriber::fmt()
        .with_ansi(colour)
        .with_writer(sunjitter::commands::replay::BarAwareStderr)
        .fmt_fields(escaped_fields())
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("SUNJITTER_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();

    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            let code = if e.use_stderr() { 2 } else { 0 };
            let _ = e.print();
            std::process::exit(code);
        }
    };
    // Decompressed copies a killed run left behind (their names carry the dead process's id).
    sunjitter::fits::remove_stale_gunzipped_copies();
    let outcome = match &cli.command {
        Command::Info(a) => commands::info::run(a),
        Command::Align(a) => commands::align::run(a),
        Command::Watch(a) => commands::watch::run(a),
        Command::Replay(a) => commands::replay::run(a),
        Command::Inspect(a) => commands::inspect::run(a),
        Command::Simulate(a) => commands::simulate::run(a),
        Command::Synth(a) => commands::synth::run(a),
        Command::Status(a) => commands::status::run(a),
    };
    match outcome {
        Ok(code) => std::process::exit(code),
        Err(e) => {
            eprintln!("sunjitter: {}", sunjitter::text::escape(&e.to_string()));
            std::process::exit(e.exit_code());
        }
    }
}
