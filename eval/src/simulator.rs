//! `emr-eval sim`: scans per second of the simulator, on one core and on all cores.

use std::fmt;
use std::time::Instant;

use sim::{Scenario, SensorKind, SimConfig, SimError, Simulator};

/// Why the benchmark could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The simulator rejected the setup.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// A rayon pool could not be created.
    #[error("cannot create a thread pool: {0}")]
    Threads(#[from] rayon::ThreadPoolBuildError),
}

/// Timing of one sensor model in one scenario.
#[derive(Clone, Debug)]
pub struct SimBench {
    /// Scenario name.
    pub scenario: String,
    /// Sensor model name.
    pub sensor: String,
    /// Rays per sweep.
    pub rays: usize,
    /// Mean returned points per sweep.
    pub points: f64,
    /// Median seconds per sweep on one core.
    pub one_core: f64,
    /// Median seconds per sweep on all cores.
    pub all_cores: f64,
    /// Threads in the all-cores pool.
    pub threads: usize,
}

impl fmt::Display for SimBench {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let line = |f: &mut fmt::Formatter<'_>, label: &str, s: f64| {
            writeln!(
                f,
                "  {label:<12} {:7.2} ms/scan  {:7.1} scans/s  {:6.2} Mrays/s",
                s * 1e3,
                1.0 / s,
                self.rays as f64 / s / 1e6
            )
        };
        writeln!(f, "{} in {}: {} rays/scan, {:.0} points/scan", self.sensor, self.scenario, self.rays, self.points)?;
        line(f, "1 core", self.one_core)?;
        line(f, &format!("{} threads", self.threads), self.all_cores)
    }
}

/// Times `frames` sweeps of robot 0, spread over the whole sequence, once on a one-thread pool and
/// once on the global pool.
pub fn run(scenario: &Scenario, sensor: SensorKind, frames: usize) -> Result<SimBench, BenchError> {
    let config = SimConfig { sensor: sensor.model(), ..SimConfig::default() };
    let sim = Simulator::new(scenario.clone(), 0, config)?;
    let frames = frames.max(1);
    let picks: Vec<usize> = (0..frames).map(|i| i * sim.frames() / frames).collect();
    // Median time per sweep: robust to other processes taking the CPU for a moment.
    let time_all = |picks: &[usize]| {
        let mut seconds = Vec::with_capacity(picks.len());
        let mut points = 0;
        for &f in picks {
            let start = Instant::now();
            points += sim.scan(f).cloud.len();
            seconds.push(start.elapsed().as_secs_f64());
        }
        seconds.sort_by(f64::total_cmp);
        (seconds[seconds.len() / 2], points as f64 / picks.len() as f64)
    };
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    // Warm-up: page in the world and the allocator before timing.
    let _ = sim.scan(picks[0]);
    let (one_core, points) = one.install(|| time_all(&picks));
    let (all_cores, _) = time_all(&picks);
    Ok(SimBench {
        scenario: scenario.name().to_owned(),
        sensor: sensor.name().to_owned(),
        rays: sim.config().sensor.rays_per_scan(),
        points,
        one_core,
        all_cores,
        threads: rayon::current_num_threads(),
    })
}
