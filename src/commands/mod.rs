//! One module per subcommand: its arguments (clap) and its `run`.
//! `run` returns the process exit code for work that ran (0 or 1); errors carry their own
//! code through [`crate::Error::exit_code`].

pub mod align;
pub mod info;
pub mod inspect;
pub mod replay;
pub mod simulate;
pub mod status;
pub mod synth;
pub mod watch;

/// A progress bar on stderr that hides itself when stderr is not a terminal.
pub fn progress_bar(len: u64, what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    if let Ok(style) =
        indicatif::ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} ({eta})")
    {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_prefix(what.to_string());
    if !std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    bar
}
