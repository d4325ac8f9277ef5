//! The default matrix: which cases, as recipes built only when run (`--case` filters
//! before anything is read or simulated), in two parts: the cases the odometry was tuned on, and
//! cases of classes it was never tuned on, held back to judge whether it generalises.

use std::path::{Path, PathBuf};

use cloud::Preset;
use sim::SensorKind;

use super::case::{Case, CaseError, Motion, SimCase, kitti_every, shuffled, simulated};

/// How a case's scans are made.
#[derive(Clone, Debug, PartialEq)]
pub enum Recipe {
    /// [`kitti_every`]`(dir, start, every)`.
    Kitti { dir: PathBuf, start: usize, every: usize },
    /// [`simulated`].
    Sim(SimCase),
    /// [`shuffled`] with `seed`; `derive_channels` false hands the odometry the bare points.
    Shuffled { of: Box<Recipe>, seed: u64, derive_channels: bool },
}

impl Recipe {
    /// The same recipe with noise drawn from `seed`: the simulator's range noise and dropouts, or
    /// the shuffle's order. `None` for real scans, which have one draw.
    pub fn seeded(&self, seed: u64) -> Option<Recipe> {
        match self {
            Recipe::Kitti { .. } => None,
            Recipe::Sim(spec) => Some(Recipe::Sim(SimCase { seed, ..spec.clone() })),
            Recipe::Shuffled { of, derive_channels, .. } => {
                let of = Box::new(of.seeded(seed).unwrap_or_else(|| (**of).clone()));
                Some(Recipe::Shuffled { of, seed, derive_channels: *derive_channels })
            }
        }
    }

    /// The case (named by its builder).
    pub fn build(&self) -> Result<Case, CaseError> {
        match self {
            Recipe::Kitti { dir, start, every } => kitti_every(dir, *start, *every),
            Recipe::Sim(spec) => simulated(spec),
            Recipe::Shuffled { of, seed, derive_channels } => {
                Ok(Case { derive_channels: *derive_channels, ..shuffled(of.build()?, *seed) })
            }
        }
    }
}

/// Which part of the matrix a case is in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum Part {
    /// Classes the odometry's settings were chosen on: KITTI 00's first scans, the warehouse,
    /// the campus car, spins, Ouster-like sensors, shuffled points.
    Tuned,
    /// Classes never tuned on, each run with the default settings (no preset, compensation on):
    /// a solid-state rosette, highway speed, a 16-beam car, 25° turns between scans, a
    /// recording written already compensated, rolling ground, 20 Hz. Judged, never tuned on.
    HeldBack,
}

impl Part {
    /// The name in tables.
    pub fn name(self) -> &'static str {
        match self {
            Part::Tuned => "tuned",
            Part::HeldBack => "held-back",
        }
    }
}

/// A case of the matrix, not built yet.
#[derive(Clone, Debug, PartialEq)]
pub struct Planned {
    /// The case's name in the table.
    pub name: String,
    /// Its class of hard input.
    pub class: &'static str,
    /// The part of the matrix it is in.
    pub part: Part,
    /// How to make it.
    pub recipe: Recipe,
}

impl Planned {
    /// Builds the case under the planned name and class.
    pub fn build(&self) -> Result<Case, CaseError> {
        Ok(Case { name: self.name.clone(), class: self.class.into(), ..self.recipe.build()? })
    }

    /// The case with its noise drawn from `seed` (see [`Recipe::seeded`]); seed 0 is the case
    /// itself, whatever its recipe.
    pub fn seeded(&self, seed: u64) -> Option<Planned> {
        if seed == 0 {
            return Some(self.clone());
        }
        Some(Planned { recipe: self.recipe.seeded(seed)?, ..self.clone() })
    }
}

/// Seconds of a simulated every-k or rate case: the same stretch of the route whatever k or rate.
const SPAN_S: f64 = 30.0;

/// The warehouse robot 1 (index 0, 1.5 m/s) from 40 s in, VLP-16.
fn warehouse(every: usize, rate_hz: f64, scans: usize) -> Recipe {
    Recipe::Sim(SimCase { every, rate_hz, scans, ..SimCase::default() })
}

/// The scans of a simulated case: `SPAN_S` seconds at `rate_hz` every `every`-th sweep, or
/// `quick` scans in a quick run.
fn count(rate_hz: f64, every: usize, quick: Option<usize>) -> usize {
    quick.unwrap_or((SPAN_S * rate_hz / every as f64).round() as usize)
}

/// The matrix: the [`Part::Tuned`] cases ([`tuned`]) and the [`Part::HeldBack`] ones
/// ([`held_back`]). `quick` keeps one case of most classes, with few scans.
pub fn matrix(kitti: &Path, quick: bool) -> Vec<Planned> {
    let mut cases = tuned(kitti, quick);
    cases.extend(held_back(quick));
    cases
}

/// The cases the odometry was tuned on: KITTI 00 (in `kitti`) every k-th, the simulated warehouse
/// every k-th and at three rates, a car on the campus, turning in place, Ouster-like sensors, and
/// shuffled points.
fn tuned(kitti: &Path, quick: bool) -> Vec<Planned> {
    let short = quick.then_some(40);
    let plan = |name: String, class, recipe| Planned { name, class, part: Part::Tuned, recipe };
    let kitti_case = |start, every| Recipe::Kitti { dir: kitti.to_owned(), start, every };
    let mut cases = vec![plan("kitti00-every-1".into(), "every-k", kitti_case(0, 1))];
    let kitti_k: &[usize] = if quick { &[3] } else { &[2, 3, 4, 5] };
    cases.extend(kitti_k.iter().map(|&k| plan(format!("kitti00-from-5-every-{k}"), "every-k", kitti_case(5, k))));
    let sim_k: &[usize] = if quick { &[5] } else { &[1, 2, 5, 10] };
    for &k in sim_k {
        cases.push(plan(format!("warehouse-every-{k}"), "every-k", warehouse(k, 10.0, count(10.0, k, short))));
    }
    let rates: &[f64] = if quick { &[2.0] } else { &[1.0, 2.0, 5.0] };
    for &hz in rates {
        cases.push(plan(format!("warehouse-{hz}hz"), "rate", warehouse(1, hz, count(hz, 1, short))));
    }
    let speeds: &[f64] = if quick { &[] } else { &[10.0, 20.0] };
    for &speed in speeds {
        cases.push(plan(format!("campus-car-{speed}ms"), "car", car(speed)));
    }
    let spins: &[f64] = if quick { &[180.0] } else { &[90.0, 180.0] };
    for &rate in spins {
        cases.push(plan(format!("spin-{rate}dps"), "spin", spin(rate, short.unwrap_or(100))));
    }
    let sensors: &[SensorKind] = if quick { &[] } else { &[SensorKind::Os64, SensorKind::Os128] };
    for &sensor in sensors {
        let recipe = Recipe::Sim(SimCase { sensor, scans: 150, ..SimCase::default() });
        cases.push(plan(format!("warehouse-{sensor}"), "sensor", recipe));
    }
    cases.extend(shuffled_cases(kitti, short));
    cases
}

/// The cases held back: classes the settings were never chosen on, built from the simulator, each
/// with the odometry's defaults (no preset, compensation on), as a user who knows nothing of the
/// recording would run it.
fn held_back(quick: bool) -> Vec<Planned> {
    let scans = if quick { 40 } else { 150 };
    let default = SimCase { scans, preset: Preset::Indoor, ..SimCase::default() };
    let route = |scenario: &str, robot| Motion::Route { scenario: scenario.into(), robot };
    let avia = |motion| SimCase { sensor: SensorKind::Avia, motion, ..default.clone() };
    let car = |speed, sensor| SimCase { motion: Motion::Car { speed }, sensor, start_s: 0.0, ..default.clone() };
    let turn = Motion::Spin { scenario: "warehouse-small".into(), at: [10.0, 12.0], deg_per_s: 250.0 };
    let plan = |name: &str, class, spec: SimCase| Planned {
        name: format!("heldback-{name}"),
        class,
        part: Part::HeldBack,
        recipe: Recipe::Sim(spec),
    };
    let mut cases = vec![
        plan("avia-warehouse", "solid-state", avia(route("warehouse-small", 0))),
        plan("turn-25deg", "fast-turn", SimCase { motion: turn, start_s: 0.0, ..default.clone() }),
        plan("compensated-warehouse", "compensated", SimCase { compensated: true, ..default.clone() }),
    ];
    if !quick {
        cases.extend([
            plan("avia-campus", "solid-state", avia(route("campus", 0))),
            plan("highway-28ms", "highway", car(28.0, SensorKind::Hdl64)),
            plan("vlp16-car-15ms", "sparse-outdoor", car(15.0, SensorKind::Vlp16)),
            plan("campus-rolling", "rolling", SimCase { motion: route("campus", 2), ..default.clone() }),
            plan("warehouse-20hz", "rate", SimCase { rate_hz: 20.0, scans: count(20.0, 1, None), ..default.clone() }),
        ]);
    }
    cases
}

/// A car on the campus roads from its start (already at speed), HDL-64, outdoor preset, 15 s.
fn car(speed: f64) -> Recipe {
    Recipe::Sim(SimCase {
        motion: Motion::Car { speed },
        sensor: SensorKind::Hdl64,
        start_s: 0.0,
        scans: 150,
        preset: Preset::Outdoor,
        ..SimCase::default()
    })
}

/// Turning in place on the west hall's middle aisle of `warehouse-small`, VLP-16, from the first scan.
fn spin(deg_per_s: f64, scans: usize) -> Recipe {
    let motion = Motion::Spin { scenario: "warehouse-small".into(), at: [10.0, 12.0], deg_per_s };
    Recipe::Sim(SimCase { motion, start_s: 0.0, scans, ..SimCase::default() })
}

/// KITTI 00 and the warehouse with shuffled points, channels derived as for a recording; and
/// KITTI 00 shuffled as the bare points, which the odometry registers with voxel-shape features.
fn shuffled_cases(kitti: &Path, short: Option<usize>) -> Vec<Planned> {
    let kitti_all = Box::new(Recipe::Kitti { dir: kitti.to_owned(), start: 0, every: 1 });
    let shuffle = |of: Box<Recipe>, derive_channels| Recipe::Shuffled { of, seed: 7, derive_channels };
    let warehouse_of = Box::new(warehouse(1, 10.0, short.unwrap_or(150)));
    let plan = |name: &str, recipe| Planned { name: name.into(), class: "shuffled", part: Part::Tuned, recipe };
    vec![
        plan("kitti00-shuffled", shuffle(kitti_all.clone(), true)),
        plan("warehouse-shuffled", shuffle(warehouse_of, true)),
        plan("kitti00-shuffled-bare", shuffle(kitti_all, false)),
    ]
}
