//! Is the odometry still on track? A fit at the right pose finds most features' lines and planes
//! within the neighbour radius; a fit that settled on the wrong structure (a fast turn, a jump the
//! prediction did not foresee) finds a fraction of them. How many a scene allows depends on the
//! sensor and the place, so a fit is judged against the fits before it, not against a constant.

use std::collections::VecDeque;

use serde::{Deserialize, Serialize};

/// Settings of the failed-fit detection.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct HealthConfig {
    /// A fit is suspect when its share of matched features falls below this fraction of the
    /// recent median. Default 0.5: on track the share varies by ±20 % between scans (KITTI
    /// 0.25-0.28, the simulated warehouse 0.17-0.28); a fit on the wrong structure keeps 0.1-0.4
    /// of it.
    pub suspect_fraction: f64,
    /// Accepted fits the median is taken over. Default 20 (2 s at 10 Hz).
    pub history: usize,
    /// Fewest accepted fits before any is judged. Default 3.
    pub min_history: usize,
    /// Re-localise by global registration (FPFH + RANSAC) when the coarse alignment did not
    /// recover a suspect fit. Default true.
    pub relocalise: bool,
}

impl Default for HealthConfig {
    fn default() -> Self {
        HealthConfig { suspect_fraction: 0.5, history: 20, min_history: 3, relocalise: true }
    }
}

/// The shares of matched features of the recent accepted fits.
#[derive(Clone, Debug)]
pub struct Health {
    config: HealthConfig,
    recent: VecDeque<f64>,
    /// The typical share before there is a history, if the measure has a natural one.
    prior: Option<f64>,
}

impl Health {
    /// No fit seen yet: nothing is suspect until [`HealthConfig::min_history`] fits were accepted.
    pub fn new(config: HealthConfig) -> Self {
        Health { recent: VecDeque::with_capacity(config.history + 1), config, prior: None }
    }

    /// Judged against `prior` until there is a history: for a share whose right value is known
    /// beforehand (the whole scan on the map it is fitted to), so that a run that is wrong from its
    /// second scan on is not taken for the norm.
    pub fn with_prior(config: HealthConfig, prior: f64) -> Self {
        Health { prior: Some(prior), ..Health::new(config) }
    }

    /// The settings.
    pub fn config(&self) -> &HealthConfig {
        &self.config
    }

    /// The median share of the recent accepted fits, once there are enough of them.
    pub fn typical(&self) -> Option<f64> {
        if self.recent.len() < self.config.min_history.max(1) {
            return self.prior;
        }
        let mut v: Vec<f64> = self.recent.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        Some(v[v.len() / 2])
    }

    /// True when a fit matching `share` of its features is well below the recent ones.
    pub fn is_suspect(&self, share: f64) -> bool {
        self.typical().is_some_and(|t| share < self.config.suspect_fraction * t)
    }

    /// Records an accepted fit.
    pub fn accept(&mut self, share: f64) {
        if self.recent.len() == self.config.history.max(1) {
            self.recent.pop_front();
        }
        self.recent.push_back(share);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_prior_judges_the_first_fits() {
        let mut health = Health::with_prior(HealthConfig { history: 4, ..HealthConfig::default() }, 1.0);
        assert!(health.is_suspect(0.49) && !health.is_suspect(0.5));
        for share in [0.2, 0.2, 0.2] {
            health.accept(share);
        }
        assert!(!health.is_suspect(0.11), "the history judges once there is one");
    }

    #[test]
    fn a_fit_is_judged_against_the_recent_median() {
        let mut health = Health::new(HealthConfig { history: 4, ..HealthConfig::default() });
        assert!(!health.is_suspect(0.0), "nothing to judge against yet");
        for share in [0.30, 0.20, 0.25] {
            health.accept(share);
        }
        assert_eq!(health.typical(), Some(0.25));
        assert!(health.is_suspect(0.12) && !health.is_suspect(0.13));
        // The window slides: old fits are forgotten.
        for share in [0.1, 0.1, 0.1] {
            health.accept(share);
        }
        assert_eq!(health.typical(), Some(0.1));
    }
}
