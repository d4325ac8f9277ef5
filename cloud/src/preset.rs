//! The environment class a configuration is tuned for, shared by the edge's odometry and the
//! station's merge so that one word means the same on both sides.

use std::fmt;
use std::str::FromStr;

/// Indoor (warehouses, ranges under ~40 m, fine structure) or outdoor (streets, campuses, ranges
/// to 100 m and more). Each component maps it to its own defaults.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Preset {
    /// Warehouses and buildings.
    Indoor,
    /// Streets and open spaces.
    Outdoor,
}

impl Preset {
    /// Every preset, in the order the help text lists them.
    pub const ALL: [Preset; 2] = [Preset::Indoor, Preset::Outdoor];

    /// The lower-case name used on command lines and in files.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Indoor => "indoor",
            Preset::Outdoor => "outdoor",
        }
    }
}

impl fmt::Display for Preset {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A preset name that is none of [`Preset::ALL`].
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("unknown preset {0:?}: expected indoor or outdoor")]
pub struct UnknownPreset(pub String);

impl FromStr for Preset {
    type Err = UnknownPreset;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Preset::ALL.into_iter().find(|p| p.name().eq_ignore_ascii_case(s)).ok_or_else(|| UnknownPreset(s.to_owned()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_unknown_names_are_refused() {
        for p in Preset::ALL {
            assert_eq!(p.to_string().parse::<Preset>(), Ok(p));
        }
        assert_eq!("Outdoor".parse::<Preset>(), Ok(Preset::Outdoor));
        assert_eq!("garage".parse::<Preset>(), Err(UnknownPreset("garage".into())));
    }
}
