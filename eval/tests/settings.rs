//! docs/settings.md is rendered from the code: every setting of the odometry, the loop closure, the
//! station's merge and joint pose graph, the keyframe codec and the simulator, with its value in
//! each preset and its doc comment. The page in the repository must be what the code renders, every
//! field must be documented, and every default a doc comment quotes must be the code's.
//!
//! After changing a setting or its doc comment: `EMR_WRITE_SETTINGS=1 cargo test -p eval --test
//! settings` writes the page again.

use cloud::preset::Preset;
use eval::settings::{Section, Source, check_quoted_defaults, field_docs, render};

macro_rules! sources {
    ($($path:literal),* $(,)?) => {
        [$(Source { path: $path, text: include_str!(concat!("../../", $path)) }),*]
    };
}

const SOURCES: [Source; 30] = sources![
    "cloud/src/confidence.rs",
    "cloud/src/global/config.rs",
    "cloud/src/global/fpfh.rs",
    "cloud/src/global/harris.rs",
    "cloud/src/global/matching.rs",
    "cloud/src/global/normals.rs",
    "cloud/src/global/polish.rs",
    "cloud/src/global/preprocess.rs",
    "cloud/src/global/ransac.rs",
    "cloud/src/pose_graph/mod.rs",
    "cloud/src/registration/mod.rs",
    "cloud/src/scan_context.rs",
    "cloud/src/visibility.rs",
    "edge/src/loops/consistency.rs",
    "edge/src/loops/graph.rs",
    "edge/src/loops/mod.rs",
    "edge/src/loops/verify.rs",
    "edge/src/odometry/aloam.rs",
    "edge/src/odometry/coarse.rs",
    "edge/src/odometry/config.rs",
    "edge/src/odometry/health.rs",
    "edge/src/odometry/motion_model.rs",
    "proto/src/codec.rs",
    "sim/src/simulator.rs",
    "sim/src/trajectory.rs",
    "sim/src/sensor.rs",
    "station/src/joint/mod.rs",
    "station/src/merge/mod.rs",
    "station/src/merge/places.rs",
    "station/src/pairwise/mod.rs",
];

const HEADER: &str = "# Settings

Every setting of the edge's odometry and loop closure, the station's merge and joint pose graph,
the keyframe codec and the simulator, with its value in each preset and the first sentence of its
meaning; the link leads to the field in the code, where the rest of its documentation (its unit and
why its default is what it is) stands. A user picks a preset (`--preset indoor|outdoor`); the rest
is set here. `emr-edge odometry --print-config` prints the odometry's settings as a run uses them.

This page is rendered from the code by `EMR_WRITE_SETTINGS=1 cargo test -p eval --test settings`;
the same test fails when the page, a doc comment's quoted default or a field's documentation
disagrees with the code.

";

fn sections() -> Vec<Section<'static>> {
    let both = |f: &dyn Fn(Preset) -> String| vec![("indoor", f(Preset::Indoor)), ("outdoor", f(Preset::Outdoor))];
    vec![
        Section {
            title: "The edge's odometry and loop closure (`edge::odometry::OdometryConfig`)",
            intro: "`emr-edge odometry` and `emr-edge run`, `--preset indoor` (the default) or `outdoor`.",
            presets: both(&|p| format!("{:#?}", edge::odometry::OdometryConfig::preset(p))),
        },
        Section {
            title: "The station's merge (`station::merge::MergeConfig`)",
            intro: "`emr-station run`, `merge` and `align`, `--preset outdoor` (the default) or `indoor`.",
            presets: both(&|p| format!("{:#?}", station::merge::MergeConfig::preset(p))),
        },
        Section {
            title: "The station's joint pose graph (`station::joint::JointConfig`)",
            intro: "The fleet's pose graph the station optimises over every placed robot's keyframes.",
            presets: vec![("default", format!("{:#?}", station::joint::JointConfig::default()))],
        },
        Section {
            title: "The keyframe codec (`proto::codec::CodecConfig`)",
            intro: "How the edge compresses the clouds it publishes.",
            presets: vec![("default", format!("{:#?}", proto::codec::CodecConfig::default()))],
        },
        Section {
            title: "The simulator (`sim::SimConfig`)",
            intro: "`emr-edge sim` and `sim:` sources; the sensor is chosen with `--sensor`.",
            presets: vec![("default", format!("{:#?}", sim::SimConfig::default()))],
        },
        Section {
            title: "The simulated robots' paths (`sim::TrajectoryConfig`)",
            intro: "How the simulator drives a robot along its world's route.",
            presets: vec![("default", format!("{:#?}", sim::TrajectoryConfig::default()))],
        },
    ]
}

/// Types used at several places with different values: the defaults their doc comments quote are
/// their `Default`'s.
fn type_defaults() -> Vec<String> {
    vec![
        format!("{:#?}", cloud::registration::RegistrationConfig::default()),
        format!("{:#?}", cloud::pose_graph::PoseGraphConfig::default()),
        format!("{:#?}", cloud::global::GlobalConfig::default()),
        format!("{:#?}", cloud::global::preprocess::PreprocessConfig::default()),
        format!("{:#?}", cloud::global::normals::NormalConfig::default()),
        format!("{:#?}", cloud::global::harris::HarrisConfig::default()),
        format!("{:#?}", cloud::global::fpfh::FpfhConfig::default()),
        format!("{:#?}", cloud::global::matching::MatchingConfig::default()),
        format!("{:#?}", cloud::global::ransac::RansacConfig::default()),
        format!("{:#?}", cloud::global::polish::PolishConfig::default()),
        format!("{:#?}", cloud::confidence::ConfidenceConfig::default()),
        format!("{:#?}", cloud::visibility::VisibilityConfig::default()),
        format!("{:#?}", station::pairwise::PairwiseConfig::default()),
        format!("{:#?}", station::merge::places::PlaceConfig::default()),
        format!("{:#?}", cloud::scan_context::ScanContextConfig::default()),
        format!("{:#?}", edge::loops::LoopConfig::default()),
        format!("{:#?}", edge::loops::verify::VerifyConfig::default()),
        format!("{:#?}", edge::loops::consistency::ConsistencyConfig::default()),
        format!("{:#?}", edge::loops::graph::GraphConfig::default()),
        format!("{:#?}", edge::odometry::config::FeatureConfig::default()),
        format!("{:#?}", edge::odometry::config::SolverConfig::default()),
        format!("{:#?}", edge::odometry::config::KeyframeConfig::default()),
        format!("{:#?}", edge::odometry::health::HealthConfig::default()),
        format!("{:#?}", edge::odometry::motion_model::MotionModelConfig::default()),
        format!("{:#?}", edge::odometry::aloam::AloamConfig::default()),
        format!("{:#?}", edge::odometry::coarse::CoarseConfig::default()),
    ]
}

#[test]
fn the_settings_page_is_what_the_code_renders() {
    let docs = field_docs(&SOURCES);
    let sections = sections();
    let (body, undocumented) = render(&sections, &docs, "../");
    let quoted = check_quoted_defaults(&sections, &type_defaults(), &docs);
    let problems: Vec<String> = undocumented.iter().chain(&quoted).map(ToString::to_string).collect();
    assert!(problems.is_empty(), "{} problems:\n{}", problems.len(), problems.join("\n"));

    let page = format!("{HEADER}{body}");
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/settings.md");
    if std::env::var_os("EMR_WRITE_SETTINGS").is_some() {
        std::fs::write(path, &page).expect("write docs/settings.md");
    }
    let written = std::fs::read_to_string(path).unwrap_or_default();
    assert!(
        written == page,
        "docs/settings.md is not what the code renders: run `EMR_WRITE_SETTINGS=1 cargo test -p eval --test settings`"
    );
}
