//! Deterministic random numbers.
//!
//! Every camera sample owns an independent stream derived from
//! `(seed, pixel index, sample index)`, so an image does not depend on tiling,
//! thread count, or which machine rendered which tile.

/// SplitMix64 finaliser: a bijective 64-bit mixer.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// PCG32 (O'Neill): small state, good statistical quality, fast.
#[derive(Clone, Debug)]
pub struct Rng {
    state: u64,
    inc: u64,
}

impl Rng {
    const MUL: u64 = 6_364_136_223_846_793_005;

    /// A stream for one camera sample.
    #[inline]
    pub fn for_sample(seed: u64, pixel: u64, sample: u64) -> Self {
        let a = mix64(seed ^ 0x9e37_79b9_7f4a_7c15);
        let b = mix64(a ^ pixel.wrapping_mul(0xd6e8_feb8_6659_fd93));
        let s = mix64(b ^ sample.wrapping_mul(0xa076_1d64_78bd_642f));
        Self::new(s, mix64(s ^ 0x5851_f42d_4c95_7f2d))
    }

    /// The PCG32 generator seeded with `init_state` on stream `init_seq` (O'Neill's
    /// `pcg32_srandom`); different `init_seq` values give independent sequences.
    #[inline]
    pub fn new(init_state: u64, init_seq: u64) -> Self {
        let mut r = Rng {
            state: 0,
            inc: (init_seq << 1) | 1,
        };
        r.next_u32();
        r.state = r.state.wrapping_add(init_state);
        r.next_u32();
        r
    }

    /// The next uniformly distributed 32-bit integer.
    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(Self::MUL).wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in [0, 1): 24 random mantissa bits.
    #[inline]
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
    }

    /// Two uniform numbers in [0, 1): x is drawn first, then y.
    #[inline]
    pub fn next_2d(&mut self) -> glam::Vec2 {
        let x = self.next_f32();
        glam::Vec2::new(x, self.next_f32())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_are_reproducible_and_distinct() {
        let mut a = Rng::for_sample(7, 12, 3);
        let mut b = Rng::for_sample(7, 12, 3);
        let mut c = Rng::for_sample(7, 12, 4);
        let va: Vec<u32> = (0..8).map(|_| a.next_u32()).collect();
        let vb: Vec<u32> = (0..8).map(|_| b.next_u32()).collect();
        let vc: Vec<u32> = (0..8).map(|_| c.next_u32()).collect();
        assert_eq!(va, vb);
        assert_ne!(va, vc);
    }

    #[test]
    fn uniform_floats_have_the_right_mean_and_range() {
        let mut r = Rng::for_sample(1, 2, 3);
        let n = 200_000;
        let mut sum = 0.0f64;
        for _ in 0..n {
            let x = r.next_f32();
            assert!((0.0..1.0).contains(&x));
            sum += x as f64;
        }
        // Std of the mean is sqrt(1/12/n) ~ 6.5e-4; 5 sigma.
        assert!((sum / n as f64 - 0.5).abs() < 3.3e-3);
    }
}
