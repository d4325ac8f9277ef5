//! Selective pallet racking: rows of bays made of upright posts, pairs of beams at each level, and
//! pallets with loads in the slots.

use super::{Builder, material};

/// Which way a rack row runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Run {
    /// Along x.
    X,
    /// Along y.
    Y,
}

/// The fixed dimensions of a rack type.
pub(super) struct RackType {
    /// Bay length along the row, metres.
    pub bay: f64,
    /// Top of each load level's beams above the floor; level 0 (the floor) has no beams.
    pub levels: [f64; 4],
    /// Height of the upright posts.
    pub height: f64,
}

/// Standard warehouse racking: 2.8 m bays, levels at 1.6 m intervals, 6.2 m uprights.
pub(super) const STANDARD: RackType = RackType { bay: 2.8, levels: [0.0, 1.6, 3.2, 4.8], height: 6.2 };

/// Pallet footprint along the row and its height.
const PALLET: (f64, f64) = (1.2, 0.15);
/// Post and beam cross-sections.
const POST: f64 = 0.1;
const BEAM: f64 = 0.12;
/// Depth of one pallet position across the row.
pub(super) const POSITION: f64 = 1.2;

/// What stands in one pallet position: a load of this size on a pallet, shifted within the slot.
#[derive(Clone, Copy, Debug)]
pub(super) struct Load {
    /// Size along the row, across it and up, metres.
    pub size: [f64; 3],
    /// Shift of the load's centre along the row from the pallet's centre.
    pub shift: f64,
    /// Reflectivity of the load.
    pub reflectivity: f32,
}

/// Where a load goes within its bay: level, slot (0 or 1 along the bay) and depth position (0 = the
/// face at the row's lower coordinate). The bay itself is not passed: identical rows must not vary.
#[derive(Clone, Copy, Debug)]
pub(super) struct Slot {
    /// Level index (0 = floor).
    pub level: usize,
    /// Slot within the bay along the row.
    pub slot: usize,
    /// Pallet position across the row.
    pub deep: usize,
}

/// A row of `bays` bays, `deep` pallet positions deep, starting at corner `(x0, y0)` and running
/// along `run`; `load` says what stands in each slot (`None`: empty).
pub(super) fn row(
    b: &mut Builder,
    rack: &RackType,
    (x0, y0): (f64, f64),
    run: Run,
    bays: usize,
    deep: usize,
    mut load: impl FnMut(Slot) -> Option<Load>,
) {
    let depth = deep as f64 * POSITION;
    // Local (u along the row, v across, z) box to world.
    let mut put = |u: [f64; 2], v: [f64; 2], z: [f64; 2], reflectivity: f32| match run {
        Run::X => b.block([x0 + u[0], y0 + v[0], z[0]], [x0 + u[1], y0 + v[1], z[1]], reflectivity),
        Run::Y => b.block([x0 + v[0], y0 + u[0], z[0]], [x0 + v[1], y0 + u[1], z[1]], reflectivity),
    };
    let h = POST / 2.0;
    for k in 0..=bays {
        let u = k as f64 * rack.bay;
        for v in [h, depth - h] {
            put([u - h, u + h], [v - h, v + h], [0.0, rack.height], material::STEEL);
        }
    }
    for bay in 0..bays {
        let u0 = bay as f64 * rack.bay;
        for (level, &top) in rack.levels.iter().enumerate() {
            if level > 0 {
                for v in [[0.0, POST], [depth - POST, depth]] {
                    put([u0 + h, u0 + rack.bay - h], v, [top - BEAM, top], material::STEEL);
                }
            }
            for slot in 0..2 {
                let centre = u0 + rack.bay * (0.25 + 0.5 * slot as f64);
                for d in 0..deep {
                    let Some(l) = load(Slot { level, slot, deep: d }) else {
                        continue;
                    };
                    let v = [d as f64 * POSITION + 0.1, (d + 1) as f64 * POSITION - 0.1];
                    let half = PALLET.0 / 2.0;
                    put([centre - half, centre + half], v, [top, top + PALLET.1], material::WOOD);
                    let (c, w) = (centre + l.shift, l.size[0] / 2.0);
                    let mid = (v[0] + v[1]) / 2.0;
                    let across = [mid - l.size[1] / 2.0, mid + l.size[1] / 2.0];
                    let base = top + PALLET.1;
                    put([c - w, c + w], across, [base, base + l.size[2]], l.reflectivity);
                }
            }
        }
    }
}
