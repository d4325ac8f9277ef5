//! Robust kernels on an edge's squared Mahalanobis norm `s = eᵀ Ω e`, in GTSAM's convention: the
//! edge costs `½ ρ(s)`, and iteratively reweighted least squares weighs it by `w = ρ'(s)`.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

/// How an edge's squared Mahalanobis norm `s` counts in the cost. `k` is in units of the
/// whitened residual `r = √s`, i.e. standard deviations of the edge's own noise.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Kernel {
    /// Least squares: `ρ(s) = s`.
    None,
    /// Huber: quadratic up to `r = k`, linear beyond; `ρ(s) = 2k r − k²` there.
    Huber(f64),
    /// Cauchy (Lorentzian): `ρ(s) = k² ln(1 + s / k²)`; a far outlier's pull fades like `1/r`.
    Cauchy(f64),
}

impl Kernel {
    /// `ρ(s)`, so that the edge costs `½ ρ(s)` (GTSAM's `mEstimator::loss` of `r = √s`, times 2).
    pub fn rho(&self, s: f64) -> f64 {
        match *self {
            Kernel::None => s,
            Kernel::Huber(k) if s <= k * k => s,
            Kernel::Huber(k) => 2.0 * k * s.sqrt() - k * k,
            Kernel::Cauchy(k) => k * k * (s / (k * k)).ln_1p(),
        }
    }

    /// `w = ρ'(s)`: the weight of `Jᵀ Ω J` and `Jᵀ Ω e` at the linearisation point (IRLS).
    pub fn weight(&self, s: f64) -> f64 {
        match *self {
            Kernel::None => 1.0,
            Kernel::Huber(k) if s <= k * k => 1.0,
            Kernel::Huber(k) => k / s.sqrt(),
            Kernel::Cauchy(k) => k * k / (k * k + s),
        }
    }

    /// Whether the scale is usable: finite and positive.
    pub fn is_valid(&self) -> bool {
        match *self {
            Kernel::None => true,
            Kernel::Huber(k) | Kernel::Cauchy(k) => k.is_finite() && k > 0.0,
        }
    }
}

/// Why a kernel could not be read from text.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("invalid kernel {0:?}: expected none, huber:K or cauchy:K with K > 0")]
pub struct KernelParseError(String);

impl FromStr for Kernel {
    type Err = KernelParseError;

    /// `none`, `huber:K` or `cauchy:K` (the command line's form).
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let error = || KernelParseError(text.to_owned());
        let kernel = match text.split_once(':') {
            None if text == "none" => Kernel::None,
            Some(("huber", k)) => Kernel::Huber(k.parse().map_err(|_| error())?),
            Some(("cauchy", k)) => Kernel::Cauchy(k.parse().map_err(|_| error())?),
            _ => return Err(error()),
        };
        kernel.is_valid().then_some(kernel).ok_or_else(error)
    }
}

impl fmt::Display for Kernel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Kernel::None => write!(f, "none"),
            Kernel::Huber(k) => write!(f, "huber:{k}"),
            Kernel::Cauchy(k) => write!(f, "cauchy:{k}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_are_the_derivative_of_rho() {
        for kernel in [Kernel::None, Kernel::Huber(1.5), Kernel::Cauchy(2.0)] {
            for s in [0.01, 0.5, 2.0, 2.25, 3.0, 40.0, 1e4] {
                let h = 1e-6 * s;
                let numeric = (kernel.rho(s + h) - kernel.rho(s - h)) / (2.0 * h);
                assert!((kernel.weight(s) - numeric).abs() < 1e-6, "{kernel} at {s}");
            }
        }
    }

    #[test]
    fn small_residuals_cost_as_least_squares() {
        assert_eq!(Kernel::Huber(2.0).rho(3.9), 3.9);
        // Cauchy departs from s by s² / 2k² at first order (ln(1 + x) = x − x²/2 + ...).
        let (k, s) = (10.0, 0.01);
        assert!((Kernel::Cauchy(k).rho(s) - s).abs() <= s * s / (2.0 * k * k));
        // Beyond the threshold Huber grows linearly in r: 2k r − k² at r = 4, k = 2.
        assert_eq!(Kernel::Huber(2.0).rho(16.0), 12.0);
    }

    #[test]
    fn parses_the_command_line_form() {
        assert_eq!("none".parse::<Kernel>(), Ok(Kernel::None));
        assert_eq!("huber:1.5".parse::<Kernel>(), Ok(Kernel::Huber(1.5)));
        assert_eq!("cauchy:2".parse::<Kernel>(), Ok(Kernel::Cauchy(2.0)));
        for bad in ["", "cauchy", "cauchy:", "cauchy:-1", "tukey:1", "huber:nan", "none:1"] {
            assert!(bad.parse::<Kernel>().is_err(), "{bad}");
        }
        assert_eq!(Kernel::Cauchy(2.5).to_string().parse::<Kernel>(), Ok(Kernel::Cauchy(2.5)));
    }
}
