//! Guided Russian roulette, splitting and light splitting: the weight window around a
//! pixel's estimated value, and the reference implementation's roulette.

use super::*;

/// Guided Russian roulette keeps every path whose expected remaining contribution is at least
/// this fraction of the pixel's estimated value (the weight window's lower edge).
pub const ROULETTE_WINDOW: f32 = 0.25;
/// Lowest survival probability of guided Russian roulette: bounds the weight of survivors where
/// the guide wrongly predicts no light.
pub const ROULETTE_MIN_SURVIVAL: f32 = 0.2;
/// Guided Russian roulette estimates the incident radiance along the sampled direction as
/// `flux * (b p_guide + (1 - b) / 4 pi)` with this `b`: half the guide's directional estimate,
/// half the leaf's mean, so that a young, noisy quadtree cannot predict "no light" outright
/// (white furnace: the standard error of the image mean is 1.5x lower than with b = 1;
/// veach-ajar variance x rays: b = 1: 0.119, 0.5: 0.122, 0 (leaf mean only): 0.126).
pub const ROULETTE_DIRECTIONAL: f32 = 0.5;

/// Survival probability of guided Russian roulette: the path's expected remaining contribution
/// `expected` (throughput x the guide's incident-radiance estimate) relative to
/// [`ROULETTE_WINDOW`] x the pixel's estimated value, clamped to
/// `[ROULETTE_MIN_SURVIVAL, 1]`; NaN survives. (Vorba and Křivánek 2016's weight window,
/// without splitting. Measured on veach-ajar 160x90, final iteration, variance x rays per
/// sample with minimum survival 0.1: window 1: 0.158, 0.5: 0.132, 0.25: 0.122, 0.1: 0.123;
/// window 0.25 with minimum 0.05: 0.133, 0.2: 0.119; Mitsuba's throughput roulette: 0.239.)
#[inline]
pub fn guided_survival(expected: f32, pixel_value: f32) -> f32 {
    let q = expected / (pixel_value * ROULETTE_WINDOW);
    if q >= ROULETTE_MIN_SURVIVAL {
        q.min(1.0)
    } else if q.is_nan() {
        1.0
    } else {
        ROULETTE_MIN_SURVIVAL
    }
}

/// Survival probability of Müller's reference roulette (see [`GuideCtx::ppg_roulette`]):
/// `guided_vertex` = smooth BSDF and a non-delta sampled lobe.
#[inline]
#[allow(clippy::manual_clamp)] // clamp would keep NaN; max/min map it to the lower bound
pub fn ppg_survival(guided_vertex: bool, built: bool, throughput_max: f32, eta: f32) -> f32 {
    if !guided_vertex {
        1.0
    } else if built {
        0.99
    } else {
        // NaN survives with the lower bound (max/min drop NaN operands).
        (throughput_max * eta * eta).max(0.1).min(0.99)
    }
}

/// Guided splitting (the upper edge of the weight window, Vorba and Křivánek 2016): at a
/// guided vertex from `rr_depth - 1` on, in a pass that records nothing, a path whose expected
/// contribution (throughput x the leaf's mean incident radiance) exceeds this multiple of the
/// pixel's estimated value is split into `expected / (SPLIT_WINDOW x value)` copies
/// (stochastically rounded, at most [`MAX_SPLIT`]), each sampling its own direction with
/// `1 / copies` of the throughput. Window 2 measured best (`docs/decisions/splitting.md`).
pub const SPLIT_WINDOW: f32 = 2.0;
/// Most copies one split makes.
pub const MAX_SPLIT: u32 = 4;
/// Most paths one camera sample may grow into by splitting.
pub const MAX_PATHS_PER_SAMPLE: u32 = 16;

/// Light splitting (`light_splitting`): at a guided vertex, in the passes that split paths,
/// the light sample is taken `n` times, `n` = throughput x the standard deviation of one
/// light sample's value learned in the vertex's leaf ([`SdTree::light_sample_stats_leaf`]),
/// over this multiple of the pixel's estimated value (stochastically rounded, at most
/// [`MAX_LIGHT_SAMPLES`]); each sample counts `1 / n`, and MIS weighs them as one technique
/// of pdf `n p_light` (also on the emitter-hit side). The deviation, not the mean, decides:
/// a bright but certain light sample gains nothing from repeats. Window 1 with at most 4
/// samples measured best (`docs/decisions/splitting.md`).
pub const LIGHT_SPLIT_WINDOW: f32 = 1.0;
/// Most light samples light splitting takes at one vertex.
pub const MAX_LIGHT_SAMPLES: u32 = 4;

/// `r` rounded stochastically by `u` in [0, 1), clamped to `[1, max]` (1 for NaN).
#[inline]
pub(super) fn window_count(r: f32, max: u32, u: f32) -> u32 {
    if !(r > 1.0) || !r.is_finite() {
        return 1;
    }
    let r = r.min(max as f32);
    let n = r.floor();
    (n as u32 + (u < r - n) as u32).clamp(1, max)
}

/// Number of copies a path splits into at a vertex (1: no split); `u` in [0, 1) rounds
/// stochastically. Depends on nothing the copies sample, so splitting stays unbiased.
#[inline]
pub fn split_count(expected: f32, pixel_value: f32, u: f32) -> u32 {
    window_count(expected / (pixel_value * SPLIT_WINDOW), MAX_SPLIT, u)
}

/// Number of light samples at a vertex (see [`LIGHT_SPLIT_WINDOW`]): `deviation` is the
/// throughput times the leaf's light-sample standard deviation. Depends on nothing the light
/// samples draw, so the estimate stays unbiased.
#[inline]
pub fn light_sample_count(deviation: f32, pixel_value: f32, u: f32) -> u32 {
    window_count(
        deviation / (pixel_value * LIGHT_SPLIT_WINDOW),
        MAX_LIGHT_SAMPLES,
        u,
    )
}

/// A path's expected remaining contribution at a guided vertex, the quantity both edges of
/// the weight window compare with the pixel's value: mean throughput x the leaf's incident
/// radiance estimate `flux x pdf` (see [`SdTree::incident_radiance_leaf`]).
#[inline]
pub(super) fn expected_contribution(
    tree: &SdTree,
    vg: &VertexGuide,
    throughput: Vec3,
    pdf: f32,
) -> f32 {
    let l = tree.incident_radiance_leaf(vg.leaf(), pdf);
    (throughput.x + throughput.y + throughput.z) / 3.0 * l
}
