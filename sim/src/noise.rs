//! Counter-based random numbers: every ray gets its own generator seeded from
//! (seed, robot, frame, ray), so scans are bit-identical whatever the thread count or order.
//!
//! SplitMix64 (Steele, Lea & Flood 2014) is small, passes BigCrush when used as a hash of a counter,
//! and needs no dependency; Box–Muller turns two uniforms into a Gaussian.

/// SplitMix64's increment (the golden ratio in 64-bit fixed point).
const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;

/// SplitMix64's output function: a bijective 64-bit mixer.
fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A SplitMix64 stream keyed by a few words.
#[derive(Clone, Debug)]
pub struct SplitMix(u64);

impl SplitMix {
    /// The stream for ray `ray` of frame `frame` of robot `robot` under `seed`.
    pub fn for_ray(seed: u64, robot: u64, frame: u64, ray: u64) -> Self {
        // Chained mixing: each key word is mixed in after the previous ones are fully diffused,
        // so (robot, frame, ray) triples that differ in any word give unrelated streams.
        let mut state = mix(seed.wrapping_add(GOLDEN));
        for word in [robot, frame, ray] {
            state = mix(state ^ word.wrapping_mul(GOLDEN));
        }
        Self(state)
    }

    /// A stream from a single seed (world layouts).
    pub fn new(seed: u64) -> Self {
        Self::for_ray(seed, 0, 0, 0)
    }

    /// Next 64 random bits.
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(GOLDEN);
        mix(self.0)
    }

    /// Uniform in [0, 1), 53 bits.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        self.uniform() < p
    }

    /// Standard normal (Box–Muller, cosine branch).
    pub fn gaussian(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform(); // (0, 1]: ln never sees 0
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussian_moments() {
        let n = 200_000;
        let samples: Vec<f64> = (0..n).map(|i| SplitMix::for_ray(7, 0, 0, i).gaussian()).collect();
        let mean = samples.iter().sum::<f64>() / n as f64;
        let var = samples.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 0.01, "mean {mean}");
        assert!((var - 1.0).abs() < 0.01, "variance {var}");
    }

    #[test]
    fn streams_differ_by_every_key_word() {
        let base = SplitMix::for_ray(1, 2, 3, 4).next_u64();
        for other in [
            SplitMix::for_ray(0, 2, 3, 4),
            SplitMix::for_ray(1, 0, 3, 4),
            SplitMix::for_ray(1, 2, 0, 4),
            SplitMix::for_ray(1, 2, 3, 0),
        ] {
            assert_ne!(other.clone().next_u64(), base);
        }
    }
}
