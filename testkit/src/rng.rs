//! Deterministic test data without a `rand` dependency, whose sequences never change under a
//! dependency upgrade: a test's synthetic scene is the same on every run and every machine.

/// The state transition; both are Marsaglia xorshift generators on one 64-bit word.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Variant {
    /// Shifts 13, 7, 17; the output is the state.
    XorShift64,
    /// Shifts 12, 25, 27 and a multiplied output (Vigna's xorshift64*), whose low bits are better.
    XorShift64Star,
}

/// A seeded xorshift generator.
#[derive(Clone, Debug)]
pub struct Rng {
    state: u64,
    variant: Variant,
}

impl Rng {
    /// Spreads small consecutive seeds (0, 1, 2, ...) over the whole state; never zero.
    const SPREAD: u64 = 0x9E37_79B9_7F4A_7C15;
    const STAR_MULTIPLIER: u64 = 0x2545_F491_4F6C_DD1D;

    /// xorshift64 (13, 7, 17) from `seed`, which must not be zero (zero is a fixed point).
    pub fn new(seed: u64) -> Self {
        Self::with_variant(seed, Variant::XorShift64)
    }

    /// xorshift64* from `seed`, which must not be zero (zero is a fixed point).
    pub fn xorshift64_star(seed: u64) -> Self {
        Self::with_variant(seed, Variant::XorShift64Star)
    }

    /// The seed for [`Rng::new`] or [`Rng::xorshift64_star`] made from an index, so that nearby
    /// indices (and zero) give unrelated streams.
    pub fn spread(index: u64) -> u64 {
        index.wrapping_mul(Self::SPREAD) | 1
    }

    fn with_variant(seed: u64, variant: Variant) -> Self {
        assert_ne!(seed, 0, "a xorshift generator seeded with 0 yields only zeros");
        Self { state: seed, variant }
    }

    pub fn next_u64(&mut self) -> u64 {
        match self.variant {
            Variant::XorShift64 => {
                self.state ^= self.state << 13;
                self.state ^= self.state >> 7;
                self.state ^= self.state << 17;
                self.state
            }
            Variant::XorShift64Star => {
                self.state ^= self.state >> 12;
                self.state ^= self.state << 25;
                self.state ^= self.state >> 27;
                self.state.wrapping_mul(Self::STAR_MULTIPLIER)
            }
        }
    }

    /// Uniform in `[0, 1)`, from the top 53 bits.
    pub fn f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in `[0, 1)`, from the top 24 bits.
    pub fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in `[lo, hi)`.
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.f64()
    }

    /// Uniform in `[lo, hi)`, in single precision.
    pub fn uniform_f32(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f32()
    }

    /// An index in `0..n` (modulo bias is irrelevant at test sizes).
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }

    /// Roughly Gaussian with standard deviation `sigma`: the sum of twelve uniforms, so bounded
    /// at six sigma, which keeps noisy test scenes free of wild outliers.
    pub fn gaussian(&mut self, sigma: f64) -> f64 {
        ((0..12).map(|_| self.f64()).sum::<f64>() - 6.0) * sigma
    }

    /// Fisher-Yates, from the back.
    pub fn shuffle<T>(&mut self, items: &mut [T]) {
        for i in (1..items.len()).rev() {
            items.swap(i, self.below(i + 1));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // Reference values from an independent big-integer implementation of both recurrences.

    #[test]
    fn xorshift64_matches_the_reference_sequence() {
        let mut rng = Rng::new(1);
        let got: Vec<u64> = (0..4).map(|_| rng.next_u64()).collect();
        assert_eq!(got, [0x4082_2041, 0x1000_4106_0c01_1441, 0x9b1e_842f_6e86_2629, 0xf554_f503_555d_8025]);
    }

    #[test]
    fn xorshift64_star_matches_the_reference_sequence() {
        let mut rng = Rng::xorshift64_star(1);
        let got: Vec<u64> = (0..4).map(|_| rng.next_u64()).collect();
        assert_eq!(got, [0x47e4_ce4b_896c_dd1d, 0xabcf_a6a8_e079_651d, 0xb9d1_0d8f_eb73_1f57, 0x4db4_18a0_bb1b_019d]);
    }

    #[test]
    fn floats_take_the_top_bits() {
        let mut a = Rng::new(7);
        let mut b = a.clone();
        let x = b.next_u64();
        assert_eq!(a.clone().f64(), (x >> 11) as f64 / (1u64 << 53) as f64);
        assert_eq!(a.f32(), (x >> 40) as f32 / (1u64 << 24) as f32);
    }

    #[test]
    fn draws_stay_in_range() {
        let mut rng = Rng::xorshift64_star(Rng::spread(0));
        for _ in 0..10_000 {
            let (u, v, i) = (rng.uniform(-2.0, 3.0), rng.uniform_f32(1.0, 1.5), rng.below(7));
            assert!((-2.0..3.0).contains(&u) && (1.0..1.5).contains(&v) && i < 7, "{u} {v} {i}");
            assert!(rng.gaussian(0.1).abs() <= 0.6);
        }
    }

    #[test]
    fn shuffle_permutes() {
        let mut items: Vec<u32> = (0..100).collect();
        Rng::new(5).shuffle(&mut items);
        assert_ne!(items, (0..100).collect::<Vec<_>>());
        items.sort();
        assert_eq!(items, (0..100).collect::<Vec<_>>());
    }

    #[test]
    #[should_panic(expected = "seeded with 0")]
    fn a_zero_seed_is_refused() {
        Rng::new(0);
    }
}
