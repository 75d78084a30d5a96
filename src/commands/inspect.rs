//! `sunjitter inspect` (not yet implemented).

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Print one JSON document on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(_args: &Args) -> crate::Result<i32> {
    Err(crate::Error::Usage(
        "`inspect` is not implemented yet".into(),
    ))
}
