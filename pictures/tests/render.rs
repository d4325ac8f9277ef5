//! Pictures of known synthetic scenes, checked pixel by pixel against what was drawn.

use pictures::{
    ErrorCurve, ErrorPlotConfig, ErrorSample, HeightBand, PictureError, Rgb, RobotLayer, TopDown, TopDownConfig, View,
    error_over_distance, top_down,
};

/// A decoded RGB image.
struct Image {
    width: u32,
    height: u32,
    rgb: Vec<u8>,
}

impl Image {
    fn decode(png_bytes: &[u8]) -> Image {
        let mut reader = png::Decoder::new(std::io::Cursor::new(png_bytes)).read_info().expect("PNG header");
        let mut rgb = vec![0; reader.output_buffer_size().expect("buffer size")];
        let info = reader.next_frame(&mut rgb).expect("PNG data");
        assert_eq!(info.color_type, png::ColorType::Rgb);
        rgb.truncate(info.buffer_size());
        Image { width: info.width, height: info.height, rgb }
    }

    fn at(&self, (col, row): (i32, i32)) -> Rgb {
        let i = (row as usize * self.width as usize + col as usize) * 3;
        Rgb(self.rgb[i], self.rgb[i + 1], self.rgb[i + 2])
    }

    fn pixels(&self) -> impl Iterator<Item = ((i32, i32), Rgb)> + '_ {
        (0..self.height as i32).flat_map(move |r| (0..self.width as i32).map(move |c| ((c, r), self.at((c, r)))))
    }
}

/// Points filling the square [x0, x0 + side] x [y0, y0 + side] at height z every `step` metres.
fn square(x0: f32, y0: f32, side: f32, z: f32, step: f32) -> Vec<[f32; 3]> {
    let n = (side / step) as usize;
    (0..=n).flat_map(|i| (0..=n).map(move |j| [x0 + i as f32 * step, y0 + j as f32 * step, z])).collect()
}

fn line(from: [f64; 2], to: [f64; 2], n: usize) -> Vec<[f64; 3]> {
    (0..=n)
        .map(|k| {
            let t = k as f64 / n as f64;
            [from[0] + (to[0] - from[0]) * t, from[1] + (to[1] - from[1]) * t, 0.5]
        })
        .collect()
}

/// Robot A: a 10 m map square at the origin, driven along y = 5. Robot B: a square at x 20..30,
/// its estimate along y = 12 and its truth along y = 14, both off its map.
fn two_robots() -> TopDown {
    TopDown {
        title: "two squares".into(),
        robots: vec![
            RobotLayer {
                label: "robot A".into(),
                points: square(0.0, 0.0, 10.0, 0.0, 0.05),
                estimated: line([0.0, 5.0], [10.0, 5.0], 20),
                truth: vec![],
            },
            RobotLayer {
                label: "robot B".into(),
                points: square(20.0, 0.0, 10.0, 0.0, 0.05),
                estimated: line([20.0, 12.0], [30.0, 12.0], 20),
                truth: line([20.0, 14.0], [30.0, 14.0], 20),
            },
        ],
    }
}

fn small_config() -> TopDownConfig {
    TopDownConfig { width: 900, height: 600, ..TopDownConfig::default() }
}

#[test]
fn top_down_has_the_configured_size() {
    let config = small_config();
    let picture = top_down(&two_robots(), &config).unwrap();
    let image = Image::decode(&picture.png);
    assert_eq!((image.width, image.height), (900, 600));
}

#[test]
fn trajectories_are_drawn_in_their_robots_colours_where_they_lie() {
    let config = small_config();
    let picture = top_down(&two_robots(), &config).unwrap();
    let image = Image::decode(&picture.png);
    let view = &picture.view;
    // Sample between the line's vertices as well as on them (the last pixel of a thick line's
    // end is left out).
    for k in 0..40 {
        let x = k as f64 * 0.25;
        assert_eq!(image.at(view.pixel(x, 5.0)), config.track_colour(0), "robot A's track at x = {x}");
        assert_eq!(image.at(view.pixel(20.0 + x, 12.0)), config.track_colour(1), "robot B's track at x = {x}");
    }
    assert_ne!(config.track_colour(0), config.track_colour(1));
}

#[test]
fn truth_is_dashed_in_the_truth_colour() {
    let config = small_config();
    let picture = top_down(&two_robots(), &config).unwrap();
    let image = Image::decode(&picture.png);
    let (c0, row) = picture.view.pixel(20.0, 14.0);
    let c1 = picture.view.pixel(30.0, 14.0).0;
    let on = (c0..=c1).filter(|&c| image.at((c, row)) == config.truth_colour).count() as f64;
    let share = on / f64::from(c1 - c0 + 1);
    // Dashes 8 px on, 6 off: 57 % on.
    assert!((0.45..0.7).contains(&share), "share of the truth line drawn: {share:.2}");
}

#[test]
fn map_points_are_tinted_with_their_robots_colour_and_nothing_else_is() {
    let config = small_config();
    let picture = top_down(&two_robots(), &config).unwrap();
    let image = Image::decode(&picture.png);
    let view = &picture.view;
    let (a, b) = (config.palette.colour(0), config.palette.colour(1));
    for (x, y) in [(1.0, 1.0), (8.5, 2.0), (2.0, 8.0), (9.0, 9.0)] {
        let px = image.at(view.pixel(x, y));
        assert!(px.is_tint_of(a) && !px.is_tint_of(b), "A's map at ({x}, {y}): {px:?}");
        let px = image.at(view.pixel(20.0 + x, y));
        assert!(px.is_tint_of(b) && !px.is_tint_of(a), "B's map at ({}, {y}): {px:?}", 20.0 + x);
    }
    // Between the squares and above them: no map (white or a grey grid line).
    for (x, y) in [(15.0, 5.0), (5.0, 13.0), (12.0, 1.0)] {
        let px = image.at(view.pixel(x, y));
        assert!(px.0 == px.1 && px.1 == px.2, "empty place ({x}, {y}) is coloured: {px:?}");
    }
}

#[test]
fn a_metre_is_as_long_in_x_as_in_y() {
    let config = small_config();
    let picture = top_down(&two_robots(), &config).unwrap();
    let image = Image::decode(&picture.png);
    let [px_x, px_y] = picture.view.px_per_unit();
    assert!((px_x / px_y - 1.0).abs() < 0.01, "pixels per metre: x {px_x}, y {px_y}");
    // Robot A's map is square on screen: its tinted pixels span as many columns as rows.
    let a = config.palette.colour(0);
    let tinted: Vec<(i32, i32)> =
        image.pixels().filter(|&(p, c)| picture.view.contains(p) && c.is_tint_of(a)).map(|(p, _)| p).collect();
    let span = |f: fn(&(i32, i32)) -> i32| tinted.iter().map(f).max().unwrap() - tinted.iter().map(f).min().unwrap();
    let (cols, rows) = (span(|p| p.0), span(|p| p.1));
    let expected = 10.0 * px_x;
    for (name, got) in [("columns", cols), ("rows", rows)] {
        assert!((f64::from(got) - expected).abs() <= 3.0, "A's map spans {got} {name}, expected {expected:.1}");
    }
}

#[test]
fn legend_shows_each_robot_and_a_scale_bar_beside_the_plot() {
    let config = small_config();
    let picture = top_down(&two_robots(), &config).unwrap();
    let image = Image::decode(&picture.png);
    let right_of_plot = |p: (i32, i32)| p.0 >= picture.view.plot_px[0].end + 20;
    for i in 0..2 {
        let track = config.track_colour(i);
        let n = image.pixels().filter(|&(p, c)| right_of_plot(p) && c == track).count();
        assert!(n > 20, "robot {i}'s legend sample: {n} pixels");
    }
    // The scale bar: a black bar 5 px thick, more than 30 px long.
    let black = image.pixels().filter(|&(p, c)| right_of_plot(p) && c == Rgb::BLACK).count();
    assert!(black > 150, "black pixels in the legend: {black}");
}

#[test]
fn height_band_drops_points_outside_it() {
    let mut scene = two_robots();
    // A ceiling over robot A's square, 4 m up.
    scene.robots[1].points.extend(square(0.0, 0.0, 10.0, 4.0, 0.05));
    let config = TopDownConfig { height_band: Some(HeightBand { min_m: -1.0, max_m: 2.0 }), ..small_config() };
    let picture = top_down(&scene, &config).unwrap();
    let image = Image::decode(&picture.png);
    let px = image.at(picture.view.pixel(2.0, 2.0));
    assert!(px.is_tint_of(config.palette.colour(0)), "A's floor under a cut ceiling: {px:?}");
    // Without the band robot B's ceiling covers it (B has as many points there, and wins ties
    // only when it has more; add a second layer to be sure).
    scene.robots[1].points.extend(square(0.0, 0.0, 10.0, 4.5, 0.05));
    let picture = top_down(&scene, &small_config()).unwrap();
    let image = Image::decode(&picture.png);
    let px = image.at(picture.view.pixel(2.0, 2.0));
    assert!(px.is_tint_of(small_config().palette.colour(1)), "B's ceiling without a band: {px:?}");
}

#[test]
fn bad_input_is_refused_with_its_name() {
    let mut scene = two_robots();
    scene.robots[1].estimated[3][0] = f64::NAN;
    let err = top_down(&scene, &small_config()).unwrap_err();
    assert!(matches!(err, PictureError::NotFinite(_)) && err.to_string().contains("robot B"), "{err}");
    let empty = TopDown { title: "nothing".into(), robots: vec![RobotLayer::default()] };
    assert!(matches!(top_down(&empty, &small_config()), Err(PictureError::Empty(_))));
    let tiny = TopDownConfig { width: 200, height: 100, ..TopDownConfig::default() };
    assert!(matches!(top_down(&two_robots(), &tiny), Err(PictureError::TooSmall { .. })));
}

/// Robot 1 is off by 0.5 m all along 100 m, robot 2 by 1.5 m over 60 m.
fn two_curves() -> Vec<ErrorCurve> {
    let flat = |label: &str, error_m: f64, length: f64| ErrorCurve {
        label: label.into(),
        samples: (0..=20).map(|k| ErrorSample { distance_m: length * k as f64 / 20.0, error_m }).collect(),
    };
    vec![flat("robot 1", 0.5, 100.0), flat("robot 2", 1.5, 60.0)]
}

#[test]
fn error_plot_draws_each_curve_at_its_error() {
    let config = ErrorPlotConfig { width: 1000, height: 600, ..ErrorPlotConfig::default() };
    let picture = error_over_distance("errors", &two_curves(), &config).unwrap();
    let image = Image::decode(&picture.png);
    assert_eq!((image.width, image.height), (1000, 600));
    let colour = |i: usize| config.palette.colour(i).shade(config.line_shade);
    let view: &View = &picture.view;
    for k in 0..=10 {
        let d = k as f64 * 5.5;
        assert_eq!(image.at(view.pixel(d, 0.5)), colour(0), "robot 1 at {d} m");
        assert_eq!(image.at(view.pixel(d, 1.5)), colour(1), "robot 2 at {d} m");
    }
    // Robot 2's line ends at 60 m; robot 1's goes on to 100 m, the end of the axis.
    assert_ne!(image.at(view.pixel(80.0, 1.5)), colour(1));
    assert_eq!(image.at(view.pixel(99.0, 0.5)), colour(0));
    assert!(view.contains(view.pixel(100.0, 0.5)) || view.pixel(100.0, 0.5).0 == view.plot_px[0].end);
}

#[test]
fn error_plot_refuses_no_samples_and_non_finite_ones() {
    let config = ErrorPlotConfig::default();
    assert!(matches!(error_over_distance("none", &[], &config), Err(PictureError::Empty(_))));
    let mut curves = two_curves();
    curves[0].samples[2].error_m = f64::INFINITY;
    let err = error_over_distance("bad", &curves, &config).unwrap_err();
    assert!(err.to_string().contains("robot 1"), "{err}");
}
