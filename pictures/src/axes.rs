//! What both pictures share: a title strip, a chart with labelled axes, and where data lands.

use std::ops::Range;

use plotters::backend::BitMapBackend;
use plotters::chart::{ChartBuilder, ChartContext};
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::element::Text;
use plotters::prelude::{Cartesian2d, DrawingArea};
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::{IntoFont, RGBColor, TextStyle, WHITE};

use crate::{PictureError, draw_error};

/// Where data lies in a picture: the pixel of any (x, y), as the chart draws it.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    /// Data x and y at the plot's lower-left corner.
    pub origin: [f64; 2],
    /// Data extent of the plot along x and y.
    pub span: [f64; 2],
    /// Pixel (column, row) of `origin`.
    pub origin_px: [i32; 2],
    /// Pixels that `span` covers along x (right) and y (up; the image's rows go down).
    pub span_px: [i32; 2],
    /// The plot's pixel columns and rows.
    pub plot_px: [Range<i32>; 2],
}

impl View {
    /// The pixel (column, row) of data point (x, y).
    pub fn pixel(&self, x: f64, y: f64) -> (i32, i32) {
        // As plotters maps a value: the fraction of the span times its pixels, floored.
        let along = |v: f64, axis: usize| {
            let fraction = (v - self.origin[axis]) / self.span[axis];
            (f64::from(self.span_px[axis]) * fraction + 1e-3).floor() as i32
        };
        (self.origin_px[0] + along(x, 0), self.origin_px[1] - along(y, 1))
    }

    /// Pixels per data unit along x and y. The top-down view keeps them equal: 1 m in x is
    /// as long as 1 m in y.
    pub fn px_per_unit(&self) -> [f64; 2] {
        [f64::from(self.span_px[0]) / self.span[0], f64::from(self.span_px[1]) / self.span[1]]
    }

    /// Whether a pixel lies in the plot.
    pub fn contains(&self, (col, row): (i32, i32)) -> bool {
        self.plot_px[0].contains(&col) && self.plot_px[1].contains(&row)
    }
}

pub(crate) type Chart<'a, 'b> = ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// Pixels of the chart's axis labels: left of the plot and under it.
pub(crate) const Y_LABEL_PX: u32 = 90;
pub(crate) const X_LABEL_PX: u32 = 60;
/// Empty border around the chart, pixels.
pub(crate) const MARGIN_PX: u32 = 12;

/// Fails unless `width` x `height` holds a legend of `legend_px` and a usable plot.
pub(crate) fn check_size(width: u32, height: u32, legend_px: u32) -> Result<(), PictureError> {
    let min_width = legend_px + Y_LABEL_PX + 2 * MARGIN_PX + 100;
    let min_height = 300;
    if width < min_width || height < min_height {
        return Err(PictureError::TooSmall { width, height, min_width, min_height });
    }
    Ok(())
}

/// A chart over `ranges` in `area`, leaving room for the axis labels.
pub(crate) fn chart<'a, 'b>(
    area: &'a DrawingArea<BitMapBackend<'b>, Shift>,
    ranges: [Range<f64>; 2],
) -> Result<Chart<'a, 'b>, PictureError> {
    let [x, y] = ranges;
    ChartBuilder::on(area)
        .margin(MARGIN_PX)
        .x_label_area_size(X_LABEL_PX)
        .y_label_area_size(Y_LABEL_PX)
        .build_cartesian_2d(x, y)
        .map_err(draw_error)
}

/// The plot's size in pixels, read off a chart that draws nothing.
pub(crate) fn plot_size(area: &DrawingArea<BitMapBackend<'_>, Shift>) -> Result<[f64; 2], PictureError> {
    let probe = chart(area, [0.0..1.0, 0.0..1.0])?;
    let (a, b) = (probe.backend_coord(&(0.0, 0.0)), probe.backend_coord(&(1.0, 1.0)));
    Ok([f64::from(b.0 - a.0), f64::from(a.1 - b.1)])
}

/// Axis names of a chart.
pub(crate) struct AxisNames<'a> {
    pub x: &'a str,
    pub y: &'a str,
}

/// Grid, ticks, tick labels and axis names.
pub(crate) fn draw_mesh(chart: &mut Chart<'_, '_>, names: &AxisNames<'_>, font_px: u32) -> Result<(), PictureError> {
    let x_label = decimals_for(chart.x_range());
    let y_label = decimals_for(chart.y_range());
    let fx = |v: &f64| format!("{v:.x_label$}");
    let fy = |v: &f64| format!("{v:.y_label$}");
    chart
        .configure_mesh()
        .x_desc(names.x)
        .y_desc(names.y)
        .label_style(("sans-serif", font_px))
        .axis_desc_style(("sans-serif", font_px))
        .x_label_formatter(&fx)
        .y_label_formatter(&fy)
        .x_labels(8)
        .y_labels(8)
        .bold_line_style(RGBColor(230, 230, 230))
        .light_line_style(WHITE)
        .draw()
        .map_err(draw_error)
}

/// Decimals enough to tell about eight ticks over `range` apart.
fn decimals_for(range: Range<f64>) -> usize {
    let step = (range.end - range.start) / 8.0;
    if step >= 1.0 || !step.is_finite() || step <= 0.0 { 0 } else { (-step.log10().floor()) as usize }
}

/// Where the chart puts data.
pub(crate) fn view_of(chart: &Chart<'_, '_>) -> View {
    let (x, y) = (chart.x_range(), chart.y_range());
    let (a, b) = (chart.backend_coord(&(x.start, y.start)), chart.backend_coord(&(x.end, y.end)));
    let (cols, rows) = chart.plotting_area().get_pixel_range();
    View {
        origin: [x.start, y.start],
        span: [x.end - x.start, y.end - y.start],
        origin_px: [a.0, a.1],
        span_px: [b.0 - a.0, a.1 - b.1],
        plot_px: [cols, rows],
    }
}

/// The title, centred in its strip.
pub(crate) fn draw_title(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    title: &str,
    font_px: u32,
) -> Result<(), PictureError> {
    let size = f64::from(font_px) * 1.2;
    let style = TextStyle::from(("sans-serif", size).into_font()).pos(Pos::new(HPos::Center, VPos::Center));
    let (w, h) = area.dim_in_pixel();
    area.draw(&Text::new(title.to_owned(), (w as i32 / 2, h as i32 / 2), style)).map_err(draw_error)
}
