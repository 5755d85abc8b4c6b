//! The test suites' one random-number generator.

/// A small seeded generator (PCG-XSH-RR 64/32, O'Neill 2014) for the test suites: random
/// schedules, fuzzed inputs, sample sets of statistical tests. Not the renderer's generator
/// (`pathfarm_render::rng`), whose streams are part of the image: a test's draws stay
/// independent of what it checks.
#[derive(Clone, Debug)]
pub struct TestRng(u64);

impl TestRng {
    /// The generator for `seed`; nearby seeds give unrelated sequences.
    pub fn new(seed: u64) -> Self {
        let mut r = TestRng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0xDA3E_39CB_94B9_5BDB);
        r.next_u32();
        r
    }

    /// 32 uniform bits.
    pub fn next_u32(&mut self) -> u32 {
        let old = self.0;
        self.0 = old
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// 64 uniform bits (two draws).
    pub fn next_u64(&mut self) -> u64 {
        let hi = u64::from(self.next_u32());
        (hi << 32) | u64::from(self.next_u32())
    }

    /// Uniform in [0, 1) with 24 bits.
    pub fn f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
    }

    /// Uniform in [0, 1) with 53 bits.
    pub fn f64(&mut self) -> f64 {
        let a = (self.next_u32() >> 5) as u64;
        let b = (self.next_u32() >> 6) as u64;
        ((a << 26) | b) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }

    /// Uniform in `0..n` (0 for `n = 0`), without modulo bias for `n` below 2^32.
    pub fn below(&mut self, n: u64) -> u64 {
        match u32::try_from(n) {
            Ok(0) => 0,
            Ok(n) => (u64::from(self.next_u32()) * u64::from(n)) >> 32,
            Err(_) => self.next_u64() % n,
        }
    }

    /// An index into a slice of `len` items (0 for `len = 0`).
    pub fn index(&mut self, len: usize) -> usize {
        self.below(len as u64) as usize
    }

    /// Uniform in `lo..=hi` (`lo <= hi`).
    pub fn range(&mut self, lo: u64, hi: u64) -> u64 {
        lo + self.below(hi - lo + 1)
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        self.f64() < p
    }

    /// One of `items` (not empty), uniformly.
    pub fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        &items[self.index(items.len())]
    }

    /// Puts `items` in a random order (Fisher-Yates).
    pub fn shuffle<T>(&mut self, items: &mut [T]) {
        for i in (1..items.len()).rev() {
            items.swap(i, self.index(i + 1));
        }
    }

    /// Standard normal (Box-Muller).
    pub fn gauss(&mut self) -> f64 {
        let u1 = 1.0 - self.f64();
        let u2 = self.f64();
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }

    /// The generator as a `FnMut() -> f32` source of uniform numbers.
    pub fn f32_source(&mut self) -> impl FnMut() -> f32 + '_ {
        move || self.f32()
    }
}

#[cfg(test)]
mod tests {
    use super::TestRng;

    /// Each value of `below(6)` comes up within 4 standard deviations of 1/6 of 60,000 draws
    /// (a failure probability of about 1e-4 per value), and never outside `0..6`.
    #[test]
    fn below_is_uniform_and_in_range() {
        let mut r = TestRng::new(3);
        let mut counts = [0u32; 6];
        for _ in 0..60_000 {
            counts[r.below(6) as usize] += 1;
        }
        let sd = (60_000.0f64 * (1.0 / 6.0) * (5.0 / 6.0)).sqrt();
        for c in counts {
            assert!((f64::from(c) - 10_000.0).abs() < 4.0 * sd, "{counts:?}");
        }
        assert_eq!(r.below(0), 0);
        assert!((0..1000).all(|_| r.below(1 << 40) < 1 << 40));
    }

    #[test]
    fn seeds_give_different_sequences_and_a_seed_the_same() {
        let draw = |s| {
            let mut r = TestRng::new(s);
            [r.next_u64(), r.next_u64()]
        };
        assert_eq!(draw(1), draw(1));
        assert_ne!(draw(1), draw(2));
    }
}
