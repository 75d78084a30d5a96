//! The one font of sunjitter's figures (plots and quicklooks), embedded so that they look
//! the same on every machine.
use plotters::style::FontStyle;

static FONT: &[u8] = include_bytes!("../../../assets/DejaVuSans.ttf");

/// The family name figures draw their text in.
pub const FAMILY: &str = "sans-serif";

/// Registers the embedded DejaVu Sans as [`FAMILY`] (once per process).
pub fn register() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        if plotters::style::register_font(FAMILY, FontStyle::Normal, FONT).is_err() {
            tracing::warn!("embedded font could not be registered; plot text may be missing");
        }
    });
}
