//! Top-down SVG drawing of a scenario: the world's objects shaded by height, the ground's relief,
//! and every robot's path with its start (circle) and end (square).

use std::fmt::Write as _;

use nalgebra::Point2;

use crate::geometry::{Aabb, Shape};
use crate::scenario::Scenario;
use crate::world::Terrain;

/// Drawing width of the larger side, pixels.
const SIZE: f64 = 1000.0;
/// Path colours, robot 1 first.
const COLOURS: [&str; 6] = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf"];

/// World (x, y) to pixels: y flipped so north is up.
struct View {
    min: Point2<f64>,
    max_y: f64,
    scale: f64,
}

impl View {
    fn px(&self, x: f64, y: f64) -> (f64, f64) {
        ((x - self.min.x) * self.scale, (self.max_y - y) * self.scale)
    }
}

/// The SVG document of `scenario`.
pub fn render(scenario: &Scenario) -> String {
    let world = scenario.world();
    let mut area = world.extent();
    for robot in scenario.robots() {
        for p in robot.ground_samples(1.0) {
            area = area.grow(&p);
        }
    }
    let margin = 2.0;
    let (w, h) = (area.max.x - area.min.x + 2.0 * margin, area.max.y - area.min.y + 2.0 * margin);
    let scale = SIZE / w.max(h);
    let view = View { min: Point2::new(area.min.x - margin, area.min.y - margin), max_y: area.max.y + margin, scale };
    let (width, height) = (w * scale, h * scale + 60.0);
    let mut svg = String::new();
    let _ = writeln!(
        svg,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{width:.0}" height="{height:.0}" viewBox="0 0 {width:.0} {height:.0}" font-family="sans-serif">"#
    );
    let _ = writeln!(svg, r##"<rect width="100%" height="100%" fill="#f4f1ea"/>"##);
    relief(&mut svg, world.terrain(), &area, &view, margin);
    objects(&mut svg, scenario, &view);
    paths(&mut svg, scenario, &view);
    caption(&mut svg, scenario, h * scale, scale);
    svg.push_str("</svg>\n");
    svg
}

/// Hills as grey-green cells, lighter = higher (nothing for a flat floor).
fn relief(svg: &mut String, terrain: &Terrain, area: &Aabb, view: &View, margin: f64) {
    if matches!(terrain, Terrain::Flat(_)) {
        return;
    }
    let cell = 5.0;
    let (x0, y0) = (area.min.x - margin, area.min.y - margin);
    let nx = ((area.max.x - area.min.x + 2.0 * margin) / cell).ceil() as usize;
    let ny = ((area.max.y - area.min.y + 2.0 * margin) / cell).ceil() as usize;
    for i in 0..nx {
        for j in 0..ny {
            let (x, y) = (x0 + i as f64 * cell, y0 + j as f64 * cell);
            let z = terrain.height(x + cell / 2.0, y + cell / 2.0);
            let g = (200.0 + 8.0 * z).clamp(150.0, 250.0) as u8;
            let (px, py) = view.px(x, y + cell);
            let s = cell * view.scale + 0.5;
            let _ = writeln!(
                svg,
                r#"<rect x="{px:.1}" y="{py:.1}" width="{s:.1}" height="{s:.1}" fill="rgb({},{g},{})"/>"#,
                g - 20,
                g - 40
            );
        }
    }
}

/// Solid objects from the lowest to the tallest, darker when taller; canopies translucent green.
fn objects(svg: &mut String, scenario: &Scenario, view: &View) {
    let world = scenario.world();
    let mut drawn: Vec<(f64, String)> = Vec::new();
    for o in world.objects() {
        let top = o.shape.bounds().map_or(0.0, |b| b.max.z);
        let base = o.shape.bounds().map_or(0.0, |b| b.min.z);
        let ground = world
            .terrain()
            .height(o.shape.bounds().map_or(0.0, |b| b.centroid().x), o.shape.bounds().map_or(0.0, |b| b.centroid().y));
        let tall = (top - ground).clamp(0.0, 20.0);
        let grey = (200.0 - 7.0 * tall) as u8;
        // Roof structure and other things high overhead: outlines only, so the floor shows.
        let overhead = base - ground > 3.0 && !matches!(o.shape, Shape::Sphere(_));
        let fill = if overhead { "none".to_owned() } else { format!("rgb({grey},{grey},{})", grey.saturating_add(10)) };
        let element = match &o.shape {
            Shape::Cuboid(c) => {
                let pts: Vec<String> = c
                    .footprint()
                    .iter()
                    .map(|p| {
                        let (x, y) = view.px(p.x, p.y);
                        format!("{x:.1},{y:.1}")
                    })
                    .collect();
                format!(r##"<polygon points="{}" fill="{fill}" stroke="#555" stroke-width="0.3"/>"##, pts.join(" "))
            }
            Shape::Cylinder(c) => {
                let (x, y) = view.px(c.center.x, c.center.y);
                let r = (c.radius * view.scale).max(0.8);
                format!(
                    r##"<circle cx="{x:.1}" cy="{y:.1}" r="{r:.1}" fill="{fill}" stroke="#555" stroke-width="0.3"/>"##
                )
            }
            Shape::Sphere(s) => {
                let (x, y) = view.px(s.center.x, s.center.y);
                let r = s.radius * view.scale;
                format!(r##"<circle cx="{x:.1}" cy="{y:.1}" r="{r:.1}" fill="#3a8a3a" fill-opacity="0.45"/>"##)
            }
            Shape::Triangle(_) | Shape::Plane(_) => continue,
        };
        // Canopies above trunks; otherwise the higher-reaching object on top.
        let order = if matches!(o.shape, Shape::Sphere(_)) { f64::MAX } else { top - base.max(ground) };
        drawn.push((order, element));
    }
    drawn.sort_by(|a, b| a.0.total_cmp(&b.0));
    for (_, e) in drawn {
        svg.push_str(&e);
        svg.push('\n');
    }
}

/// Each robot's path as a coloured line with start and end marks and its length.
fn paths(svg: &mut String, scenario: &Scenario, view: &View) {
    for (i, robot) in scenario.robots().iter().enumerate() {
        let colour = COLOURS[i % COLOURS.len()];
        let samples = robot.ground_samples(0.5);
        let pts: Vec<String> = samples
            .iter()
            .map(|p| {
                let (x, y) = view.px(p.x, p.y);
                format!("{x:.1},{y:.1}")
            })
            .collect();
        let _ = writeln!(
            svg,
            r#"<polyline points="{}" fill="none" stroke="{colour}" stroke-width="2" stroke-opacity="0.85"/>"#,
            pts.join(" ")
        );
        if let (Some(a), Some(b)) = (samples.first(), samples.last()) {
            let (x, y) = view.px(a.x, a.y);
            let _ = writeln!(
                svg,
                r#"<circle cx="{x:.1}" cy="{y:.1}" r="6" fill="{colour}" stroke="white" stroke-width="1.5"/>"#
            );
            let _ = writeln!(
                svg,
                r#"<text x="{:.1}" y="{:.1}" font-size="13" font-weight="bold" fill="{colour}">{}</text>"#,
                x + 8.0,
                y - 6.0,
                i + 1
            );
            let (x, y) = view.px(b.x, b.y);
            let _ = writeln!(
                svg,
                r#"<rect x="{:.1}" y="{:.1}" width="10" height="10" fill="{colour}" stroke="white" stroke-width="1.5"/>"#,
                x - 5.0,
                y - 5.0
            );
        }
    }
}

/// Title, robot legend and scale bar under the drawing.
fn caption(svg: &mut String, scenario: &Scenario, top: f64, scale: f64) {
    let _ = writeln!(
        svg,
        r#"<text x="10" y="{:.0}" font-size="15" font-weight="bold">{} ({} frames at 10 Hz)</text>"#,
        top + 20.0,
        scenario.name(),
        scenario.frames()
    );
    let mut x = 10.0;
    for (i, robot) in scenario.robots().iter().enumerate() {
        let colour = COLOURS[i % COLOURS.len()];
        let label = format!("robot {}: {:.0} m, {:.0} s", i + 1, robot.length(), robot.duration());
        let _ =
            writeln!(svg, r#"<text x="{x:.0}" y="{:.0}" font-size="13" fill="{colour}">{label}</text>"#, top + 42.0);
        x += 175.0;
    }
    let bar = if scale > 10.0 { 5.0 } else { 20.0 };
    let right = SIZE.min(x + 200.0).max(x + 20.0);
    let _ = writeln!(
        svg,
        r#"<line x1="{right:.0}" y1="{y:.0}" x2="{:.0}" y2="{y:.0}" stroke="black" stroke-width="3"/><text x="{right:.0}" y="{:.0}" font-size="12">{bar} m</text>"#,
        right + bar * scale,
        top + 32.0,
        y = top + 40.0
    );
}
