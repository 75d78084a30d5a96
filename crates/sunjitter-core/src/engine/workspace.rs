//! The working memory alignments share, and where the caller keeps references' self-tests.

use super::refine;
use crate::flow::Farneback;

/// What alignments share from one to the next: working memory, and where the caller keeps
/// them, references' self-test cases.
///
/// The working memory is the flow solver, whose buffers (≈ 35 bytes per pixel of the crop)
/// are the largest of an alignment. Faulting them in again for every frame costs more than
/// the flow's arithmetic on the coarse levels, so a caller aligning many frames, against one
/// reference or many, shares one `Workspace` between its prepared references
/// ([`PreparedReference::sharing`]). It holds one solver; an alignment that finds it taken
/// makes its own.
#[derive(Default)]
pub struct Workspace {
    spare: std::sync::Mutex<Option<Farneback>>,
    /// Self-test cases kept between runs ([`Workspace::keeping_self_tests`]).
    self_tests: Option<std::sync::Arc<dyn refine::SelfTestStore>>,
}

impl Workspace {
    /// A workspace whose alignments look up a new reference's self-test cases in `store`
    /// before running them, and save the cases they run there: a reference seen before (the
    /// same pixels, mask, configuration and build) skips its self-test.
    pub fn keeping_self_tests(store: std::sync::Arc<dyn refine::SelfTestStore>) -> Workspace {
        Workspace {
            self_tests: Some(store),
            ..Workspace::default()
        }
    }

    pub(super) fn self_tests(&self) -> Option<&dyn refine::SelfTestStore> {
        self.self_tests.as_deref()
    }

    pub(super) fn take(&self) -> Option<Farneback> {
        match self.spare.lock() {
            Ok(mut g) => g.take(),
            Err(poisoned) => poisoned.into_inner().take(),
        }
    }

    pub(super) fn give(&self, solver: Farneback) {
        match self.spare.lock() {
            Ok(mut g) => *g = Some(solver),
            Err(poisoned) => *poisoned.into_inner() = Some(solver),
        }
    }
}

impl std::fmt::Debug for Workspace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Workspace")
    }
}
