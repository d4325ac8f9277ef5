fn main() {
    use pictures::*;
    let sq = |x0: f32, y0: f32, side: f32, z: f32, step: f32| -> Vec<[f32; 3]> {
        let n = (side / step) as usize;
        (0..=n).flat_map(|i| (0..=n).map(move |j| [x0 + i as f32 * step, y0 + j as f32 * step, z])).collect()
    };
    let line = |a: [f64; 2], b: [f64; 2]| -> Vec<[f64; 3]> {
        (0..=20)
            .map(|k| {
                let t = k as f64 / 20.0;
                [a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, 0.0]
            })
            .collect()
    };
    let scene = TopDown {
        title: "two squares".into(),
        robots: vec![
            RobotLayer {
                label: "robot A".into(),
                points: sq(0.0, 0.0, 10.0, 0.0, 0.05),
                estimated: line([0.0, 5.0], [10.0, 5.0]),
                truth: vec![],
            },
            RobotLayer {
                label: "robot B".into(),
                points: sq(20.0, 0.0, 10.0, 0.0, 0.05),
                estimated: line([20.0, 12.0], [30.0, 12.0]),
                truth: line([20.0, 14.0], [30.0, 14.0]),
            },
        ],
    };
    let p = top_down(&scene, &TopDownConfig { width: 900, height: 600, ..Default::default() }).unwrap();
    std::fs::write("/tmp/pic_td.png", &p.png).unwrap();
    let curves = vec![ErrorCurve {
        label: "robot 1".into(),
        samples: (0..=20).map(|k| ErrorSample { distance_m: k as f64 * 5.0, error_m: 0.5 + 0.02 * k as f64 }).collect(),
    }];
    let e = error_over_distance("errors", &curves, &ErrorPlotConfig::default()).unwrap();
    std::fs::write("/tmp/pic_err.png", &e.png).unwrap();
}
