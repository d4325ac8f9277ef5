//! `emr-eval load`: a station under a simulated fleet's load.

use anyhow::Result;
use eval::load::{self, LoadConfig};
use station::joint::JointConfig;

/// The arguments of `emr-eval load`.
#[derive(clap::Args, Debug)]
pub struct LoadArgs {
    /// Robots publishing (at least 1).
    #[arg(long, default_value_t = 8)]
    robots: usize,
    /// Keyframes per second per robot (above 0).
    #[arg(long, default_value_t = 10.0)]
    rate_hz: f64,
    /// Seconds of publishing; each robot sends SECONDS × RATE_HZ keyframes (rounded, at least 1).
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
    /// Scenario the robots come from (robots beyond its own replay them from later in their runs).
    #[arg(long, default_value = "campus")]
    scenario: String,
    /// Print the figures as one JSON object on stdout's last line instead of text: robots, sent,
    /// received, mean_payload_bytes, received_per_s, max_backlog, queue_max, merges, merge_ms
    /// and latency_ms ({median, p95, max}, nearest rank), unmapped, catch_up_s, merged_robots,
    /// all_merged_s, rss_mb ({start, end, peak}), and joint with --joint.
    #[arg(long)]
    json: bool,
    /// Then run the station's joint pose graph on the final map's robots and report its time,
    /// edges and keyframe RMSE against the truth, rigid and joint (JSON: joint {ms, edges_ms,
    /// consistency_ms, optimise_ms, robots, keyframes, registered, kept, joined, rigid_rmse_m,
    /// joint_rmse_m, edge_error_m, edge_error_deg}).
    #[arg(long)]
    joint: bool,
}

/// `emr-eval load`.
pub fn load(args: LoadArgs) -> Result<()> {
    let LoadArgs { robots, rate_hz, seconds, scenario, json, joint } = args;
    let joint = joint.then(JointConfig::default);
    let config = LoadConfig { robots, rate_hz, seconds, scenario, joint, ..LoadConfig::new() };
    let report = super::runtime()?.block_on(load::run(config))?;
    if json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!("{report}");
    }
    Ok(())
}
