//! sunjitter's files: FITS frames in ([`fits`]), MCAP logs out and back ([`sink`], with the
//! messages a run writes in [`records`]), corrected frames ([`aligned`]) and the output
//! paths and checks every command shares ([`outputs`]), and how inputs are opened ([`input`]); references' self-test cases kept
//! between runs ([`self_tests`]).

pub mod aligned;
pub mod fits;
pub mod font;
pub mod input;
pub mod outputs;
pub mod records;
pub mod self_tests;
pub mod sink;
