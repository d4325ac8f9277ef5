//! A map seen from above, coloured by robot, with the robots' trajectories.

use std::ops::Range;

use plotters::backend::BitMapBackend;
use plotters::coord::Shift;
use plotters::prelude::{DrawingArea, IntoDrawingArea};
use plotters::series::{DashedLineSeries, LineSeries};
use plotters::style::ShapeStyle;

use crate::axes::{self, AxisNames, Chart, View};
use crate::legend::{self, Entry, Sample};
use crate::{Palette, PictureError, Rgb, draw_error, encode, font};

/// What to draw: one layer per robot.
#[derive(Clone, Debug, Default)]
pub struct TopDown {
    /// Title above the chart.
    pub title: String,
    /// The robots, in legend order; the `i`-th takes the palette's `i`-th colour.
    pub robots: Vec<RobotLayer>,
}

/// One robot's part of the picture, all in the same frame (metres).
#[derive(Clone, Debug, Default)]
pub struct RobotLayer {
    /// Legend label, e.g. `robot 1`.
    pub label: String,
    /// Its map points (x, y, z); only x and y are drawn.
    pub points: Vec<[f32; 3]>,
    /// Its estimated trajectory, positions in order (empty: none).
    pub estimated: Vec<[f64; 3]>,
    /// Its true trajectory (empty: unknown).
    pub truth: Vec<[f64; 3]>,
}

/// Keeps map points whose z lies in `min_m..=max_m` (cuts ceilings that hide a building's
/// walls from above).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeightBand {
    /// Lowest z kept, metres.
    pub min_m: f64,
    /// Highest z kept, metres.
    pub max_m: f64,
}

/// How [`top_down`] draws.
#[derive(Clone, Debug, PartialEq)]
pub struct TopDownConfig {
    /// Image width in pixels (default 1400).
    pub width: u32,
    /// Image height in pixels (default 1000).
    pub height: u32,
    /// Robot colours (default [`Palette::default`]).
    pub palette: Palette,
    /// Side of a map density cell in pixels (default 2): points are counted per cell, not drawn
    /// one by one, so a million points cost a million additions.
    pub cell_px: u32,
    /// Tint of the sparsest map cell, 0 (white) to 1 (the robot's colour) (default 0.4: a
    /// lone point stays visible).
    pub map_tint_min: f64,
    /// Tint of the densest map cells (default 0.75): below the trajectories' full colour so
    /// these stand out.
    pub map_tint_max: f64,
    /// Map points kept by height (default: all).
    pub height_band: Option<HeightBand>,
    /// Estimated trajectories: the robot's colour darkened by this factor (default 0.8).
    pub track_shade: f64,
    /// Estimated trajectory line width in pixels (default 3).
    pub track_px: u32,
    /// True trajectory line colour (default black), drawn dashed over the estimate.
    pub truth_colour: Rgb,
    /// True trajectory line width in pixels (default 1: thinner than the estimate, which shows
    /// on both sides of it where they agree).
    pub truth_px: u32,
    /// Text size in pixels (default 20; the title 1.2 times that).
    pub font_px: u32,
    /// Width of the legend panel right of the chart, pixels (default 280).
    pub legend_px: u32,
    /// Empty border around the data, as a fraction of its extent (default 0.03).
    pub pad: f64,
}

impl Default for TopDownConfig {
    fn default() -> Self {
        TopDownConfig {
            width: 1400,
            height: 1000,
            palette: Palette::default(),
            cell_px: 2,
            map_tint_min: 0.4,
            map_tint_max: 0.75,
            height_band: None,
            track_shade: 0.8,
            track_px: 3,
            truth_colour: Rgb::BLACK,
            truth_px: 1,
            font_px: 20,
            legend_px: 280,
            pad: 0.03,
        }
    }
}

impl TopDownConfig {
    /// The colour robot `i`'s trajectory is drawn in.
    pub fn track_colour(&self, i: usize) -> Rgb {
        self.palette.colour(i).shade(self.track_shade)
    }
}

/// A rendered top-down picture.
#[derive(Clone, Debug)]
pub struct TopDownPicture {
    /// The PNG file's bytes.
    pub png: Vec<u8>,
    /// Where the world landed.
    pub view: View,
}

/// Renders `scene` as a PNG.
pub fn top_down(scene: &TopDown, config: &TopDownConfig) -> Result<TopDownPicture, PictureError> {
    axes::check_size(config.width, config.height, config.legend_px)?;
    let bounds = bounds(scene, config)?;
    font::ensure_registered()?;
    let (w, h) = (config.width, config.height);
    let mut rgb = vec![255u8; w as usize * h as usize * 3];
    let view = {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        let title_px = config.font_px * 2;
        let (title_area, body) = root.split_vertically(title_px);
        let (plot_area, legend_area) = body.split_horizontally(w - config.legend_px);
        let ranges = equal_aspect(&bounds, axes::plot_size(&plot_area)?, config.pad);
        let mut chart = axes::chart(&plot_area, ranges)?;
        axes::draw_mesh(&mut chart, &AxisNames { x: "x (m)", y: "y (m)" }, config.font_px)?;
        let view = axes::view_of(&chart);
        draw_map(&root, scene, config, &view)?;
        draw_tracks(&mut chart, scene, config)?;
        axes::draw_title(&title_area, &scene.title, config.font_px)?;
        let bar = legend::scale_bar(view.px_per_unit()[0], config.legend_px as i32 - 60);
        let entries = legend_entries(scene, config);
        legend::draw(&legend_area, &entries, bar.as_ref(), axes::MARGIN_PX as i32, config.font_px)?;
        root.present().map_err(draw_error)?;
        view
    };
    Ok(TopDownPicture { png: encode::png_rgb(&rgb, w, h)?, view })
}

/// The x and y extent of everything drawn.
struct Bounds {
    x: Range<f64>,
    y: Range<f64>,
}

fn bounds(scene: &TopDown, config: &TopDownConfig) -> Result<Bounds, PictureError> {
    let mut b = Bounds { x: f64::INFINITY..f64::NEG_INFINITY, y: f64::INFINITY..f64::NEG_INFINITY };
    let mut grow = |x: f64, y: f64| {
        b.x = b.x.start.min(x)..b.x.end.max(x);
        b.y = b.y.start.min(y)..b.y.end.max(y);
    };
    for r in &scene.robots {
        for p in r.points.iter().filter(|p| in_band(p, config.height_band)) {
            check_finite(&[f64::from(p[0]), f64::from(p[1]), f64::from(p[2])], &r.label, "map")?;
            grow(f64::from(p[0]), f64::from(p[1]));
        }
        for (p, what) in
            r.estimated.iter().map(|p| (p, "estimated trajectory")).chain(r.truth.iter().map(|p| (p, "truth")))
        {
            check_finite(p, &r.label, what)?;
            grow(p[0], p[1]);
        }
    }
    if b.x.start > b.x.end {
        return Err(PictureError::Empty(format!("top-down view '{}': no map point, no trajectory", scene.title)));
    }
    Ok(b)
}

fn check_finite(p: &[f64], label: &str, what: &str) -> Result<(), PictureError> {
    if p.iter().all(|v| v.is_finite()) { Ok(()) } else { Err(PictureError::NotFinite(format!("{label}: {what}"))) }
}

fn in_band(p: &[f32; 3], band: Option<HeightBand>) -> bool {
    band.is_none_or(|b| (b.min_m..=b.max_m).contains(&f64::from(p[2])))
}

/// Ranges holding `bounds` (plus `pad`) centred, stretched so 1 m spans as many pixels in x as in y.
fn equal_aspect(bounds: &Bounds, plot_px: [f64; 2], pad: f64) -> [Range<f64>; 2] {
    // A single point still gets a metre around it.
    let span = |r: &Range<f64>| ((r.end - r.start) * (1.0 + 2.0 * pad)).max(1.0);
    let m_per_px = (span(&bounds.x) / plot_px[0]).max(span(&bounds.y) / plot_px[1]);
    let around = |r: &Range<f64>, px: f64| {
        let (mid, half) = ((r.start + r.end) / 2.0, m_per_px * px / 2.0);
        mid - half..mid + half
    };
    [around(&bounds.x, plot_px[0]), around(&bounds.y, plot_px[1])]
}

/// Paints the map: each cell takes the colour of the robot with most points in it, tinted by
/// how many (log scale, up to the 95th percentile of cells).
fn draw_map(
    root: &DrawingArea<BitMapBackend<'_>, Shift>,
    scene: &TopDown,
    config: &TopDownConfig,
    view: &View,
) -> Result<(), PictureError> {
    let grid = DensityGrid::count(scene, config, view);
    let Some(reference) = grid.reference_count() else { return Ok(()) };
    let scale = (1.0 + f64::from(reference)).ln();
    for (cell, winner) in grid.winners() {
        let Some((robot, count)) = winner else { continue };
        let level = ((1.0 + f64::from(count)).ln() / scale).min(1.0);
        let tint = config.map_tint_min + (config.map_tint_max - config.map_tint_min) * level;
        let colour = config.palette.colour(robot).tint(tint).plotters();
        for (col, row) in grid.pixels(cell) {
            root.draw_pixel((col, row), &colour).map_err(draw_error)?;
        }
    }
    Ok(())
}

/// Map points counted per robot and per cell of the plot.
struct DensityGrid {
    cell_px: i32,
    origin: (i32, i32),
    plot_end: (i32, i32),
    cols: usize,
    /// Per robot, per cell (row-major).
    counts: Vec<Vec<u32>>,
}

impl DensityGrid {
    fn count(scene: &TopDown, config: &TopDownConfig, view: &View) -> Self {
        let cell_px = config.cell_px.max(1) as i32;
        let [cols_px, rows_px] = &view.plot_px;
        let cols = cols_px.len().div_ceil(cell_px as usize);
        let rows = rows_px.len().div_ceil(cell_px as usize);
        let origin = (cols_px.start, rows_px.start);
        let counts = scene
            .robots
            .iter()
            .map(|r| {
                let mut c = vec![0u32; cols * rows];
                for p in r.points.iter().filter(|p| in_band(p, config.height_band)) {
                    let px = view.pixel(f64::from(p[0]), f64::from(p[1]));
                    if view.contains(px) {
                        let (i, j) = (((px.0 - origin.0) / cell_px) as usize, ((px.1 - origin.1) / cell_px) as usize);
                        c[j * cols + i] += 1;
                    }
                }
                c
            })
            .collect();
        DensityGrid { cell_px, origin, plot_end: (cols_px.end, rows_px.end), cols, counts }
    }

    /// Per cell, the robot with most points there and its count.
    fn winners(&self) -> impl Iterator<Item = (usize, Option<(usize, u32)>)> + '_ {
        let cells = self.counts.first().map_or(0, Vec::len);
        (0..cells).map(|cell| {
            let best = (0..self.counts.len())
                .map(|r| (r, self.counts[r][cell]))
                .filter(|&(_, n)| n > 0)
                .max_by_key(|&(r, n)| (n, std::cmp::Reverse(r)));
            (cell, best)
        })
    }

    /// The count that gets the full tint: the 95th percentile of occupied cells, so a few very
    /// dense cells (a wall seen from everywhere) do not wash out the rest.
    fn reference_count(&self) -> Option<u32> {
        let mut occupied: Vec<u32> = self.winners().filter_map(|(_, w)| w.map(|(_, n)| n)).collect();
        if occupied.is_empty() {
            return None;
        }
        let k = (occupied.len() - 1) * 95 / 100;
        Some(*occupied.select_nth_unstable(k).1)
    }

    fn pixels(&self, cell: usize) -> impl Iterator<Item = (i32, i32)> + use<'_> {
        let (i, j) = ((cell % self.cols) as i32, (cell / self.cols) as i32);
        let (c0, r0) = (self.origin.0 + i * self.cell_px, self.origin.1 + j * self.cell_px);
        let cols = c0..(c0 + self.cell_px).min(self.plot_end.0);
        let rows = r0..(r0 + self.cell_px).min(self.plot_end.1);
        rows.flat_map(move |r| cols.clone().map(move |c| (c, r)))
    }
}

fn draw_tracks(chart: &mut Chart<'_, '_>, scene: &TopDown, config: &TopDownConfig) -> Result<(), PictureError> {
    let xy = |t: &[[f64; 3]]| t.iter().map(|p| (p[0], p[1])).collect::<Vec<_>>();
    for (i, r) in scene.robots.iter().enumerate() {
        let style = ShapeStyle::from(config.track_colour(i).plotters()).stroke_width(config.track_px);
        chart.draw_series(LineSeries::new(xy(&r.estimated), style)).map_err(draw_error)?;
    }
    // Truths go over every estimate: a dashed line stays visible over a solid one.
    let truth_style = ShapeStyle::from(config.truth_colour.plotters()).stroke_width(config.truth_px);
    for r in scene.robots.iter().filter(|r| !r.truth.is_empty()) {
        chart.draw_series(DashedLineSeries::new(xy(&r.truth), 8, 6, truth_style)).map_err(draw_error)?;
    }
    Ok(())
}

fn legend_entries(scene: &TopDown, config: &TopDownConfig) -> Vec<Entry> {
    let mut entries: Vec<Entry> = scene
        .robots
        .iter()
        .enumerate()
        .map(|(i, r)| Entry {
            label: r.label.clone(),
            sample: Sample::Robot {
                map: config.palette.colour(i).tint(config.map_tint_max),
                track: (!r.estimated.is_empty()).then(|| config.track_colour(i)),
            },
        })
        .collect();
    if scene.robots.iter().any(|r| !r.estimated.is_empty()) {
        let colour = Rgb(90, 90, 90);
        entries.push(Entry {
            label: "estimated".into(),
            sample: Sample::Line { colour, width: config.track_px, dashed: false },
        });
    }
    if scene.robots.iter().any(|r| !r.truth.is_empty()) {
        let sample = Sample::Line { colour: config.truth_colour, width: config.truth_px, dashed: true };
        entries.push(Entry { label: "truth".into(), sample });
    }
    entries
}
