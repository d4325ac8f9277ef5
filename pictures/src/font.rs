//! The one font every picture uses, compiled in.

use std::sync::OnceLock;

use plotters::style::{FontStyle, register_font};

use crate::PictureError;

/// DejaVu Sans cut down to Latin-1 punctuation, digits and letters (see `fonts/LICENSE`): headless
/// containers have no system fonts, and plotters' `ab_glyph` text draws only registered ones.
const SANS: &[u8] = include_bytes!("../fonts/DejaVuSans-subset.ttf");

/// Registers the font as plotters' `sans-serif` (once per process).
pub(crate) fn ensure_registered() -> Result<(), PictureError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| register_font("sans-serif", FontStyle::Normal, SANS).is_ok());
    if ok { Ok(()) } else { Err(PictureError::Draw("the compiled-in font does not parse".into())) }
}
