//! The paper's four systems side by side (`emr-eval report`): MR-ALOAM and MR-FLOAM (odometry
//! only), EMR-ALOAM and EMR-FLOAM (each robot closes its loops), each run through the demo
//! ([`demo::run`]) on the simulated scenarios, judged against the simulator's truth.
//!
//! The paper (its Tables 5-10) compares trajectory error, time and map size; here per system and
//! scenario: ATE RMSE per robot (odometry and loop-closed, SE(3)-aligned in the robot's own frame;
//! global, unaligned, in the merged frame), the median odometry time per scan, the global map's
//! points and bytes, the merge time and the loops. [`markdown`] and [`json`] render the table; the
//! command writes them.

use std::path::PathBuf;

use cloud::stats::Spread;
use edge::odometry::Method;
use prost::Message;
use serde::Serialize;

use demo::{DemoConfig, DemoError, DemoReport};

/// One of the paper's systems: an odometry, with or without loop closure.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct System {
    /// The paper's name.
    pub name: &'static str,
    /// The robots' odometry.
    pub method: Method,
    /// Whether the robots close loops (EMR) or not (MR).
    pub loops: bool,
}

/// The four systems, in the paper's order.
pub const SYSTEMS: [System; 4] = [
    System { name: "MR-ALOAM", method: Method::Aloam, loops: false },
    System { name: "MR-FLOAM", method: Method::Floam, loops: false },
    System { name: "EMR-ALOAM", method: Method::Aloam, loops: true },
    System { name: "EMR-FLOAM", method: Method::Floam, loops: true },
];

/// The simulated scenarios the report runs by default: every multi-robot one of the catalogue.
pub const SCENARIOS: [&str; 4] = ["warehouse-small", "warehouse-large", "campus", "aisles"];

/// What the report runs.
#[derive(Clone, Debug)]
pub struct ReportConfig {
    /// Scenarios (default [`SCENARIOS`]); every robot of each runs.
    pub scenarios: Vec<String>,
    /// Scans per robot (default: the whole scenario).
    pub frames: Option<usize>,
    /// Where each run writes its demo results, as OUT/SCENARIO/SYSTEM (default `out/report`).
    pub out: PathBuf,
}

impl Default for ReportConfig {
    fn default() -> Self {
        ReportConfig {
            scenarios: SCENARIOS.iter().map(|s| s.to_string()).collect(),
            frames: None,
            out: PathBuf::from("out/report"),
        }
    }
}

/// Why the report failed.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// A scenario is not in the simulator's catalogue.
    #[error(transparent)]
    Scenario(#[from] sim::UnknownScenario),
    /// A run failed.
    #[error("{scenario}, {system}: {source}")]
    Run {
        /// The scenario.
        scenario: String,
        /// The system.
        system: &'static str,
        /// What went wrong.
        source: DemoError,
    },
}

/// One robot of one run.
#[derive(Clone, Debug, Serialize)]
pub struct RobotRow {
    /// Robot id.
    pub robot: u32,
    /// Scans registered.
    pub scans: usize,
    /// Loops in its pose graph at the end.
    pub loops: usize,
    /// Odometry ATE RMSE after SE(3) alignment, own frame (m).
    pub odometry_ate_m: f64,
    /// The same after its loop closure (m; the odometry's without loops).
    pub loop_closed_ate_m: f64,
    /// ATE RMSE in the global frame, unaligned (m), when merged.
    pub global_ate_m: Option<f64>,
    /// Median odometry time per scan (ms).
    pub median_scan_ms: f64,
}

/// One system on one scenario.
#[derive(Clone, Debug, Serialize)]
pub struct Row {
    /// The scenario.
    pub scenario: String,
    /// The system.
    pub system: System,
    /// Per robot.
    pub robots: Vec<RobotRow>,
    /// Median odometry time per scan over every robot's scans (ms).
    pub median_scan_ms: f64,
    /// Points of the final global map.
    pub map_points: u64,
    /// Bytes of the final global map message as the station publishes it.
    pub map_bytes: usize,
    /// Merges the station ran.
    pub merges: usize,
    /// Wall time of the last merge, the one that made the final map (ms).
    pub last_merge_ms: f64,
    /// Loops over all robots.
    pub loops: usize,
    /// Wall time of the run (s).
    pub wall_s: f64,
    /// Where the run wrote its results.
    pub out: PathBuf,
}

impl Row {
    /// The row of a finished run.
    pub fn of(scenario: &str, system: System, demo: &DemoReport, out: PathBuf) -> Row {
        let robots: Vec<RobotRow> = demo
            .robots
            .iter()
            .map(|r| RobotRow {
                robot: r.robot,
                scans: r.frames,
                loops: r.loops,
                odometry_ate_m: r.odometry_ate.0.rmse,
                loop_closed_ate_m: r.corrected_ate.0.rmse,
                global_ate_m: r.global_ate.map(|a| a.rmse),
                median_scan_ms: Spread::of(&r.odometry_ms).median,
            })
            .collect();
        let all_ms: Vec<f64> = demo.robots.iter().flat_map(|r| r.odometry_ms.iter().copied()).collect();
        Row {
            scenario: scenario.to_owned(),
            system,
            median_scan_ms: Spread::of(&all_ms).median,
            map_points: demo.global_map.cloud.as_ref().map_or(0, |c| c.points),
            map_bytes: demo.global_map.encoded_len(),
            merges: demo.merge_ms.len(),
            last_merge_ms: demo.merge_ms.last().copied().unwrap_or(f64::NAN),
            loops: robots.iter().map(|r| r.loops).sum(),
            wall_s: demo.wall_s,
            robots,
            out,
        }
    }
}

/// Every run's row.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    /// Scans per robot, when the runs were shortened.
    pub frames: Option<usize>,
    /// One per scenario and system, scenario by scenario.
    pub rows: Vec<Row>,
}

/// The robots of a scenario, 1-based.
fn robots_of(scenario: &str) -> Result<Vec<u32>, ReportError> {
    let n = sim::Scenario::by_name(scenario)?.robots().len();
    Ok((1..=n as u32).collect())
}

/// Runs every system on every scenario, telling `progress` as it goes; stops with
/// [`DemoError::Interrupted`] when `interrupt` resolves.
pub async fn run(
    config: &ReportConfig,
    interrupt: impl Future<Output = ()>,
    mut progress: impl FnMut(&str),
) -> Result<Report, ReportError> {
    let mut interrupt = std::pin::pin!(interrupt);
    let mut rows = Vec::new();
    for scenario in &config.scenarios {
        let robots = robots_of(scenario)?;
        for system in SYSTEMS {
            let out = config.out.join(scenario).join(system.name);
            progress(&format!("{scenario}, {}: {} robots running", system.name, robots.len()));
            let demo = DemoConfig {
                scenario: scenario.clone(),
                robots: robots.clone(),
                frames: config.frames,
                out: out.clone(),
                method: system.method,
                loops: system.loops,
                ..DemoConfig::new()
            };
            let report = demo::run(demo, &mut interrupt).await.map_err(|source| ReportError::Run {
                scenario: scenario.clone(),
                system: system.name,
                source,
            })?;
            let row = Row::of(scenario, system, &report, out);
            progress(&format!(
                "{scenario}, {}: done in {:.0} s, {:.1} ms per scan, {} loops",
                system.name, row.wall_s, row.median_scan_ms, row.loops
            ));
            rows.push(row);
        }
    }
    Ok(Report { frames: config.frames, rows })
}

/// Centimetres, or a dash.
fn cm(m: Option<f64>) -> String {
    m.filter(|m| m.is_finite()).map_or("-".into(), |m| format!("{:.1}", m * 100.0))
}

/// Per-robot values joined with " / ".
fn per_robot(robots: &[RobotRow], value: impl Fn(&RobotRow) -> Option<f64>) -> String {
    robots.iter().map(|r| cm(value(r))).collect::<Vec<_>>().join(" / ")
}

/// The report as a Markdown table, one row per scenario and system.
pub fn markdown(report: &Report) -> String {
    let mut md = String::from("# The paper's four systems on the simulated scenarios\n\n");
    if let Some(frames) = report.frames {
        md.push_str(&format!("Runs shortened to {frames} scans per robot.\n\n"));
    }
    md.push_str(
        "ATE RMSE in cm per robot (robot 1 / robot 2 / ...): odometry and loop-closed after SE(3) \
         alignment in the robot's own frame, global unaligned in the merged frame (- : not merged). \
         ms/scan: median odometry time per scan. Map: the final global map.\n\n",
    );
    md.push_str("| scenario | system | odometry ATE | loop-closed ATE | global ATE | ms/scan | map points | map bytes | merges | last merge ms | loops |\n");
    md.push_str("|---|---|---|---|---|---:|---:|---:|---:|---:|---:|\n");
    for row in &report.rows {
        md.push_str(&format!(
            "| {} | {} | {} | {} | {} | {:.1} | {} | {} | {} | {:.0} | {} |\n",
            row.scenario,
            row.system.name,
            per_robot(&row.robots, |r| Some(r.odometry_ate_m)),
            per_robot(&row.robots, |r| Some(r.loop_closed_ate_m)),
            per_robot(&row.robots, |r| r.global_ate_m),
            row.median_scan_ms,
            row.map_points,
            row.map_bytes,
            row.merges,
            row.last_merge_ms,
            row.loops,
        ));
    }
    md
}

/// The report as pretty JSON.
pub fn json(report: &Report) -> String {
    serde_json::to_string_pretty(report).expect("the report serialises")
}
