//! Position error against distance travelled, one line per robot.

use plotters::backend::BitMapBackend;
use plotters::prelude::IntoDrawingArea;
use plotters::series::LineSeries;
use plotters::style::ShapeStyle;

use crate::axes::{self, AxisNames, View};
use crate::legend::{self, Entry, Sample};
use crate::{Palette, PictureError, draw_error, encode, font};

/// One robot's error at one pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ErrorSample {
    /// Distance travelled along the true trajectory up to this pose, metres.
    pub distance_m: f64,
    /// Distance between the estimated and the true position, metres.
    pub error_m: f64,
}

/// One robot's line.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ErrorCurve {
    /// Legend label, e.g. `robot 1 (global frame)`.
    pub label: String,
    /// Samples in order of distance.
    pub samples: Vec<ErrorSample>,
}

impl ErrorCurve {
    /// The curve of an estimate against the truth, pose by pose (the shorter length of the two).
    pub fn from_positions(label: impl Into<String>, truth: &[[f64; 3]], estimate: &[[f64; 3]]) -> Self {
        let mut travelled = 0.0;
        let samples = truth
            .iter()
            .zip(estimate)
            .enumerate()
            .map(|(i, (t, e))| {
                if i > 0 {
                    travelled += distance(&truth[i - 1], t);
                }
                ErrorSample { distance_m: travelled, error_m: distance(t, e) }
            })
            .collect();
        ErrorCurve { label: label.into(), samples }
    }
}

fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>().sqrt()
}

/// How [`error_over_distance`] draws.
#[derive(Clone, Debug, PartialEq)]
pub struct ErrorPlotConfig {
    /// Image width in pixels (default 1200).
    pub width: u32,
    /// Image height in pixels (default 700).
    pub height: u32,
    /// Line colours: the `i`-th curve takes the `i`-th (default [`Palette::default`], as the
    /// top-down view, so a robot keeps its colour when both list robots in the same order).
    pub palette: Palette,
    /// Lines darkened by this factor, as the top-down view's trajectories (default 0.8).
    pub line_shade: f64,
    /// Line width in pixels (default 1: plotters draws thicker polylines as polygons per
    /// segment, which break up on steep, jittery error curves).
    pub line_px: u32,
    /// Text size in pixels (default 20).
    pub font_px: u32,
    /// Width of the legend panel right of the chart, pixels (default 340: labels are longer
    /// here).
    pub legend_px: u32,
}

impl Default for ErrorPlotConfig {
    fn default() -> Self {
        ErrorPlotConfig {
            width: 1200,
            height: 700,
            palette: Palette::default(),
            line_shade: 0.8,
            line_px: 1,
            font_px: 20,
            legend_px: 340,
        }
    }
}

/// A rendered error plot.
#[derive(Clone, Debug)]
pub struct ErrorPicture {
    /// The PNG file's bytes.
    pub png: Vec<u8>,
    /// Where (distance, error) landed.
    pub view: View,
}

/// Renders the curves as a PNG titled `title`.
pub fn error_over_distance(
    title: &str,
    curves: &[ErrorCurve],
    config: &ErrorPlotConfig,
) -> Result<ErrorPicture, PictureError> {
    axes::check_size(config.width, config.height, config.legend_px)?;
    let [max_distance, max_error] = extent(title, curves)?;
    font::ensure_registered()?;
    let (w, h) = (config.width, config.height);
    let mut rgb = vec![255u8; w as usize * h as usize * 3];
    let view = {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        let (title_area, body) = root.split_vertically(config.font_px * 2);
        let (plot_area, legend_area) = body.split_horizontally(w - config.legend_px);
        // Headroom over the largest error so its peak does not touch the frame.
        let ranges = [0.0..max_distance.max(1e-3), 0.0..(max_error * 1.08).max(1e-3)];
        let mut chart = axes::chart(&plot_area, ranges)?;
        let names = AxisNames { x: "distance travelled (m)", y: "position error (m)" };
        axes::draw_mesh(&mut chart, &names, config.font_px)?;
        let mut entries = Vec::new();
        for (i, curve) in curves.iter().enumerate() {
            let colour = config.palette.colour(i).shade(config.line_shade);
            let style = ShapeStyle::from(colour.plotters()).stroke_width(config.line_px);
            let points = thinned(&chart, &curve.samples);
            chart.draw_series(LineSeries::new(points, style)).map_err(draw_error)?;
            let sample = Sample::Line { colour, width: config.line_px.max(3), dashed: false };
            entries.push(Entry { label: curve.label.clone(), sample });
        }
        axes::draw_title(&title_area, title, config.font_px)?;
        legend::draw(&legend_area, &entries, None, axes::MARGIN_PX as i32, config.font_px)?;
        root.present().map_err(draw_error)?;
        axes::view_of(&chart)
    };
    Ok(ErrorPicture { png: encode::png_rgb(&rgb, w, h)?, view })
}

/// The samples, less those within 2 px of the previous one kept: thick lines made of sub-pixel
/// segments come out broken.
fn thinned(chart: &axes::Chart<'_, '_>, samples: &[ErrorSample]) -> Vec<(f64, f64)> {
    let mut kept: Vec<(f64, f64)> = Vec::new();
    let mut last_px: Option<(i32, i32)> = None;
    for (i, s) in samples.iter().enumerate() {
        let px = chart.backend_coord(&(s.distance_m, s.error_m));
        let near = last_px.is_some_and(|l| (l.0 - px.0).abs() < 2 && (l.1 - px.1).abs() < 2);
        if !near || i + 1 == samples.len() {
            kept.push((s.distance_m, s.error_m));
            last_px = Some(px);
        }
    }
    kept
}

/// The largest distance and error over all curves; fails on none or on a non-finite value.
fn extent(title: &str, curves: &[ErrorCurve]) -> Result<[f64; 2], PictureError> {
    let mut max = [f64::NEG_INFINITY; 2];
    for c in curves {
        for s in &c.samples {
            if !(s.distance_m.is_finite() && s.error_m.is_finite()) {
                return Err(PictureError::NotFinite(format!("{}: error sample", c.label)));
            }
            max = [max[0].max(s.distance_m), max[1].max(s.error_m)];
        }
    }
    if max[0].is_finite() { Ok(max) } else { Err(PictureError::Empty(format!("error plot '{title}': no sample"))) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn curve_measures_distance_along_the_truth() {
        let truth = [[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [3.0, 4.0, 2.0]];
        let estimate = [[0.0, 0.0, 0.0], [3.0, 4.0, 1.0], [0.0, 0.0, 2.0]];
        let c = ErrorCurve::from_positions("r", &truth, &estimate);
        let got: Vec<(f64, f64)> = c.samples.iter().map(|s| (s.distance_m, s.error_m)).collect();
        assert_eq!(got, vec![(0.0, 0.0), (5.0, 1.0), (7.0, 5.0)]);
    }
}
