//! Reconstruction filters (Mitsuba `box`, `tent`, `gaussian`).
//!
//! Camera samples are placed uniformly inside their pixel and every sample
//! is splatted, with the filter's weight, into all pixels whose filter
//! support covers it; a pixel's value is the weight-normalised sum (as
//! Mitsuba's image block does). Spreading each sample over several pixels
//! lowers per-pixel variance (about 2.25x for the tent) compared with
//! putting it in one pixel.

use pathfarm_scene::RFilter;

/// A separable reconstruction filter: a sample at offset (dx, dy) from a pixel centre weighs
/// `eval(dx) * eval(dy)`. Weights need not integrate to 1 (pixels divide by their weight sum).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Filter {
    /// Constant weight 1 within `radius` of the centre.
    Box {
        /// Half-width of the support, in pixels (Mitsuba's default 0.5 keeps samples in their
        /// pixel).
        radius: f32,
    },
    /// Weight falling linearly from 1 at the centre to 0 at `radius`.
    Tent {
        /// Radius of the support, in pixels.
        radius: f32,
    },
    /// Mitsuba's windowed gaussian: support 4 standard deviations.
    Gaussian {
        /// Standard deviation, in pixels.
        stddev: f32,
    },
}

impl Filter {
    /// The filter the scene's film asks for.
    pub fn new(desc: RFilter) -> Self {
        match desc {
            RFilter::Box { radius } => Filter::Box { radius },
            RFilter::Tent { radius } => Filter::Tent { radius },
            RFilter::Gaussian { stddev } => Filter::Gaussian { stddev },
        }
    }

    /// Support radius in pixels.
    pub fn radius(&self) -> f32 {
        match *self {
            Filter::Box { radius } | Filter::Tent { radius } => radius,
            Filter::Gaussian { stddev } => 4.0 * stddev,
        }
    }

    /// Weight at offset `x` (in pixels) from a pixel centre, one axis.
    #[inline]
    pub fn eval(&self, x: f32) -> f32 {
        match *self {
            Filter::Box { radius } => {
                if x.abs() <= radius {
                    1.0
                } else {
                    0.0
                }
            }
            Filter::Tent { radius } => (1.0 - x.abs() / radius).max(0.0),
            Filter::Gaussian { stddev } => {
                let alpha = -1.0 / (2.0 * stddev * stddev);
                let r = 4.0 * stddev;
                ((alpha * x * x).exp() - (alpha * r * r).exp()).max(0.0)
            }
        }
    }

    /// How many neighbouring pixels (per axis and side) a sample can reach.
    pub fn reach(&self) -> i32 {
        (self.radius() - 0.5).ceil().max(0.0) as i32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filters_have_mitsubas_shapes_and_supports() {
        let t = Filter::Tent { radius: 1.0 };
        assert_eq!((t.eval(0.0), t.eval(0.5), t.eval(1.0)), (1.0, 0.5, 0.0));
        assert_eq!(t.reach(), 1);
        let b = Filter::Box { radius: 0.5 };
        assert_eq!((b.eval(0.49), b.eval(0.51), b.reach()), (1.0, 0.0, 0));
        let g = Filter::Gaussian { stddev: 0.5 };
        assert!(g.eval(0.0) > 0.99 && g.eval(2.0) == 0.0 && g.eval(1.0) > 0.0);
        assert_eq!(g.reach(), 2);
    }
}
