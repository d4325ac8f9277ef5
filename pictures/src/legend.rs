//! The panel beside a chart: what each colour and line means, and a scale bar.

use plotters::coord::Shift;
use plotters::element::{PathElement, Rectangle, Text};
use plotters::prelude::{DrawingArea, DrawingBackend};
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::{Color, IntoFont, ShapeStyle, TextStyle};

use crate::{PictureError, Rgb, draw_error};

/// What a legend entry shows left of its label.
pub(crate) enum Sample {
    /// A robot: a square of its map tint, crossed by a line of its trajectory colour when it
    /// has one.
    Robot { map: Rgb, track: Option<Rgb> },
    /// A line of this colour and width, solid or dashed.
    Line { colour: Rgb, width: u32, dashed: bool },
}

/// One line of the legend.
pub(crate) struct Entry {
    pub label: String,
    pub sample: Sample,
}

/// A bar `pixels` long that stands for `metres`.
pub(crate) struct ScaleBar {
    pub metres: f64,
    pub pixels: i32,
}

/// Room left of each label for its sample, pixels.
const SAMPLE_PX: i32 = 40;
/// Gap between the panel's edge and its content, pixels.
const INSET_PX: i32 = 12;

/// Draws the entries top-down from `top` px, then the scale bar under them.
pub(crate) fn draw<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    entries: &[Entry],
    scale: Option<&ScaleBar>,
    top: i32,
    font_px: u32,
) -> Result<(), PictureError> {
    let row = (f64::from(font_px) * 1.6).round() as i32;
    let style = TextStyle::from(("sans-serif", font_px).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    for (i, entry) in entries.iter().enumerate() {
        let y = top + row / 2 + i as i32 * row;
        draw_sample(area, &entry.sample, y, font_px as i32)?;
        area.draw(&Text::new(entry.label.clone(), (INSET_PX + SAMPLE_PX + 8, y), style.clone())).map_err(draw_error)?;
    }
    if let Some(bar) = scale {
        let y = top + (entries.len() as i32 + 1) * row;
        draw_scale_bar(area, bar, y, font_px)?;
    }
    Ok(())
}

fn draw_sample<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    sample: &Sample,
    y: i32,
    font_px: i32,
) -> Result<(), PictureError> {
    let (x0, x1) = (INSET_PX, INSET_PX + SAMPLE_PX);
    match *sample {
        Sample::Robot { map, track } => {
            let half = font_px / 2;
            area.draw(&Rectangle::new([(x0, y - half), (x1, y + half)], map.plotters().filled()))
                .map_err(draw_error)?;
            match track {
                Some(track) => line(area, (x0, x1), y, track, 3, false),
                None => Ok(()),
            }
        }
        Sample::Line { colour, width, dashed } => line(area, (x0, x1), y, colour, width, dashed),
    }
}

fn line<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    (x0, x1): (i32, i32),
    y: i32,
    colour: Rgb,
    width: u32,
    dashed: bool,
) -> Result<(), PictureError> {
    let style = ShapeStyle::from(colour.plotters()).stroke_width(width);
    // Dashes as in the chart: 8 px on, 6 px off.
    let pieces: Vec<(i32, i32)> =
        if dashed { (x0..x1).step_by(14).map(|a| (a, (a + 8).min(x1))).collect() } else { vec![(x0, x1)] };
    for (a, b) in pieces {
        area.draw(&PathElement::new(vec![(a, y), (b, y)], style)).map_err(draw_error)?;
    }
    Ok(())
}

fn draw_scale_bar<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    bar: &ScaleBar,
    y: i32,
    font_px: u32,
) -> Result<(), PictureError> {
    let black = Rgb::BLACK.plotters();
    let (x0, x1) = (INSET_PX, INSET_PX + bar.pixels);
    area.draw(&Rectangle::new([(x0, y - 2), (x1, y + 2)], black.filled())).map_err(draw_error)?;
    for x in [x0, x1] {
        area.draw(&PathElement::new(vec![(x, y - 8), (x, y + 8)], ShapeStyle::from(black).stroke_width(2)))
            .map_err(draw_error)?;
    }
    let style = TextStyle::from(("sans-serif", font_px).into_font()).pos(Pos::new(HPos::Center, VPos::Top));
    area.draw(&Text::new(format_metres(bar.metres), ((x0 + x1) / 2, y + 12), style)).map_err(draw_error)
}

/// `20 m`, `0.5 m`.
fn format_metres(m: f64) -> String {
    if m >= 1.0 { format!("{m:.0} m") } else { format!("{m} m") }
}

/// The longest 1-2-5 length of at most `max_px` pixels at `px_per_m`.
pub(crate) fn scale_bar(px_per_m: f64, max_px: i32) -> Option<ScaleBar> {
    let max_m = f64::from(max_px) / px_per_m;
    if !(max_m.is_finite() && max_m > 0.0) {
        return None;
    }
    let decade = 10f64.powf(max_m.log10().floor());
    let metres = [5.0, 2.0, 1.0].iter().map(|k| k * decade).find(|&m| m <= max_m)?;
    Some(ScaleBar { metres, pixels: (metres * px_per_m).round() as i32 })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scale_bar_is_the_longest_round_length_that_fits() {
        let bar = scale_bar(10.0, 200).unwrap(); // at most 20 m
        assert_eq!(bar.metres, 20.0);
        assert_eq!(bar.pixels, 200);
        let bar = scale_bar(10.0, 190).unwrap(); // at most 19 m
        assert_eq!(bar.metres, 10.0);
        let bar = scale_bar(1000.0, 190).unwrap(); // at most 0.19 m
        assert!((bar.metres - 0.1).abs() < 1e-12);
        assert_eq!(format_metres(bar.metres), "0.1 m");
    }
}
