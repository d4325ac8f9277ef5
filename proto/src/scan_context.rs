//! Conversions between the wire `ScanContext` and [`cloud::scan_context::ScanContext`].

use cloud::scan_context::{RINGS, ScanContext as Descriptor};

use crate::v1::ScanContext;

/// A wire descriptor that cannot be compared with ours.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum InvalidScanContext {
    /// Not [`RINGS`] rings, or no sector.
    #[error("scan context has {rings} rings and {sectors} sectors, expected {RINGS} rings and at least one sector")]
    Shape { rings: u32, sectors: u32 },
    /// The cells do not fill the grid.
    #[error("scan context has {cells} cells for {rings} x {sectors}")]
    Cells { cells: usize, rings: u32, sectors: u32 },
    /// A cell or the range is NaN, infinite or negative.
    #[error("scan context has a non-finite or negative value")]
    Value,
}

impl From<&Descriptor> for ScanContext {
    fn from(d: &Descriptor) -> Self {
        ScanContext {
            rings: d.rings as u32,
            sectors: d.sectors as u32,
            max_range: d.max_range as f32,
            cells: d.cells.clone(),
        }
    }
}

impl TryFrom<&ScanContext> for Descriptor {
    type Error = InvalidScanContext;

    fn try_from(m: &ScanContext) -> Result<Self, InvalidScanContext> {
        let (rings, sectors) = (m.rings, m.sectors);
        if rings as usize != RINGS || sectors == 0 {
            return Err(InvalidScanContext::Shape { rings, sectors });
        }
        if m.cells.len() as u64 != u64::from(rings) * u64::from(sectors) {
            return Err(InvalidScanContext::Cells { cells: m.cells.len(), rings, sectors });
        }
        let finite = |v: f32| v.is_finite() && v >= 0.0;
        if !(finite(m.max_range) && m.max_range > 0.0 && m.cells.iter().all(|&c| finite(c))) {
            return Err(InvalidScanContext::Value);
        }
        Ok(Descriptor {
            rings: RINGS,
            sectors: sectors as usize,
            max_range: f64::from(m.max_range),
            cells: m.cells.clone(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_descriptor_survives_the_wire_and_a_bad_one_is_refused() {
        let d =
            Descriptor { rings: RINGS, sectors: 3, max_range: 80.0, cells: (0..RINGS * 3).map(|i| i as f32).collect() };
        let m = ScanContext::from(&d);
        assert_eq!(Descriptor::try_from(&m).unwrap(), d);
        let short = ScanContext { cells: vec![1.0; 5], ..m.clone() };
        assert!(matches!(Descriptor::try_from(&short), Err(InvalidScanContext::Cells { .. })));
        let rings = ScanContext { rings: 2, ..m.clone() };
        assert!(matches!(Descriptor::try_from(&rings), Err(InvalidScanContext::Shape { .. })));
        let mut nan = m.clone();
        nan.cells[4] = f32::NAN;
        assert_eq!(Descriptor::try_from(&nan), Err(InvalidScanContext::Value));
    }
}
