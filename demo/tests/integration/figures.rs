//! The demo's figures on a short run: both PNGs are written, decode, have the configured size
//! and show what they should (the map, every robot's colours), not a blank frame.

use demo::DemoConfig;
use pictures::{ErrorPlotConfig, Rgb, TopDownConfig};

struct Image {
    width: u32,
    height: u32,
    rgb: Vec<u8>,
}

fn decode(path: &std::path::Path) -> Image {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().expect("PNG header");
    let mut rgb = vec![0; reader.output_buffer_size().expect("buffer size")];
    let info = reader.next_frame(&mut rgb).expect("PNG data");
    assert_eq!(info.color_type, png::ColorType::Rgb, "{}", path.display());
    rgb.truncate(info.buffer_size());
    Image { width: info.width, height: info.height, rgb }
}

impl Image {
    fn count(&self, colour: Rgb) -> usize {
        self.rgb.chunks_exact(3).filter(|p| p == &[colour.0, colour.1, colour.2]).count()
    }

    fn count_tints(&self, colour: Rgb) -> usize {
        self.rgb.chunks_exact(3).filter(|p| Rgb(p[0], p[1], p[2]).is_tint_of(colour)).count()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_demo_draws_its_map_trajectories_and_errors() {
    let out = tempfile::tempdir().unwrap();
    let config = DemoConfig { frames: Some(100), out: out.path().to_owned(), ..DemoConfig::new() };
    let report = demo::run(config, std::future::pending()).await.expect("demo runs");
    // The reference robot is always merged; on a short run the other may not be.
    assert!(report.robots.iter().any(|r| r.merged));

    let top = TopDownConfig::default();
    let image = decode(&out.path().join("top_down.png"));
    assert_eq!((image.width, image.height), (top.width, top.height));
    for (i, r) in report.robots.iter().enumerate().filter(|(_, r)| r.merged) {
        // Its part of the map: walls and racks over a hall, not a blank frame.
        let n = image.count_tints(top.palette.colour(i));
        assert!(n > 5_000, "robot {}'s map: {n} pixels", r.robot);
        // Ten metres of trajectory, 3 px wide, beyond its 120 px legend sample.
        let n = image.count(top.track_colour(i));
        assert!(n > 300, "robot {}'s trajectory colour: {n} pixels", r.robot);
    }

    let errors = ErrorPlotConfig::default();
    let image = decode(&out.path().join("error_over_distance.png"));
    assert_eq!((image.width, image.height), (errors.width, errors.height));
    for i in 0..2 {
        let n = image.count(errors.palette.colour(i).shade(errors.line_shade));
        // Beyond its 120 px legend sample: a 1 px line, partly under the other one.
        assert!(n > 250, "robot {}'s error line: {n} pixels", i + 1);
    }
    assert!(report.written.iter().any(|p| p.ends_with("top_down.png")));
    assert!(report.written.iter().any(|p| p.ends_with("error_over_distance.png")));
}
