//! One module per subcommand: its arguments (clap) and its `run`.
//! `run` returns the process exit code for work that ran (0 or 1); errors carry their own
//! code through [`crate::Error::exit_code`].

pub mod align;
pub mod info;
pub mod inspect;
pub mod replay;
pub mod simulate;
pub mod synth;
pub mod watch;
