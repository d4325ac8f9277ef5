//! Pictures of maps, trajectories and errors, rendered into PNG bytes in memory.
//!
//! [`top_down`] draws a global map seen from above, coloured by robot, with each robot's
//! trajectory (estimated, and the truth where known), axes in metres at equal aspect, a legend
//! and a scale bar. [`error_over_distance`] draws each robot's position error against the
//! distance it travelled. Both render with `plotters` into an RGB buffer and encode it with
//! `png`; text uses a font compiled into the crate, so no system fonts are needed. Neither does
//! any file I/O: the caller writes the bytes.

mod axes;
mod encode;
mod error_plot;
mod font;
mod legend;
pub mod palette;
mod top_down;

pub use axes::View;
pub use error_plot::{ErrorCurve, ErrorPicture, ErrorPlotConfig, ErrorSample, error_over_distance};
pub use palette::{Palette, Rgb};
pub use top_down::{HeightBand, RobotLayer, TopDown, TopDownConfig, TopDownPicture, top_down};

/// Why a picture could not be drawn.
#[derive(Debug, thiserror::Error)]
pub enum PictureError {
    /// The requested image is too small to hold the axes, legend and title.
    #[error("picture size {width}x{height} px is too small (at least {min_width}x{min_height} px)")]
    TooSmall {
        /// Requested width.
        width: u32,
        /// Requested height.
        height: u32,
        /// Smallest width that fits.
        min_width: u32,
        /// Smallest height that fits.
        min_height: u32,
    },
    /// Nothing to draw: no point and no trajectory (or no error sample).
    #[error("nothing to draw in {0}")]
    Empty(String),
    /// A coordinate is NaN or infinite.
    #[error("{0}: coordinate is not finite")]
    NotFinite(String),
    /// plotters failed.
    #[error("drawing: {0}")]
    Draw(String),
    /// The PNG encoder failed.
    #[error("PNG encoding: {0}")]
    Encode(#[from] png::EncodingError),
}

fn draw_error(e: impl std::fmt::Display) -> PictureError {
    PictureError::Draw(e.to_string())
}
