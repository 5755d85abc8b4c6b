//! The training record the renderer deposits into the SD-tree.

use glam::Vec3;

/// One path vertex's training sample (doc section 2).
///
/// **Convention:** `radiance` is the incident radiance estimate `L_i` (mean over RGB) *not*
/// divided by any pdf; the guide divides it by `pdf_mix` itself. The deposited value is
/// `weight * radiance / pdf_mix`.
///
/// Validity rules applied by [`crate::SdTree::record`]:
/// * records with a non-finite or non-positive `weight`, a non-finite or non-positive
///   `pdf_mix`, or a non-finite `radiance`/`position`/`direction` are skipped entirely; those
///   skipped for a NaN or infinity are counted ([`crate::SdTree::take_nonfinite_records`]);
/// * otherwise W gains `weight`; the sum gains `weight * radiance / pdf_mix` only when that value
///   is > 0 and below [`crate::sdtree::MAX_RECORD_VALUE`] (zero, negative or absurdly large
///   values change W only);
/// * the learned fraction uses the record when it is not `is_delta` and `product > 0`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Record {
    /// World-space position x_i of the vertex.
    pub position: Vec3,
    /// World-space (unit) direction w_i that was sampled at x_i.
    pub direction: Vec3,
    /// Incident radiance `L_i` along `direction` (mean over RGB), not divided by a pdf.
    pub radiance: f32,
    /// Solid-angle pdf with which `direction` was actually sampled (the mixture pdf
    /// `alpha p_bsdf + (1 - alpha) p_guide`, with the clamped alpha used for sampling). Also
    /// used as `p_sample` in the fraction gradient.
    pub pdf_mix: f32,
    /// Statistical weight w (1, or 0.5 for kick-start NEE vertices).
    pub weight: f32,
    /// `product` = mean over RGB of `L_i * f * cos` (only used to learn the fraction).
    pub product: f32,
    /// BSDF solid-angle pdf of `direction`.
    pub pdf_bsdf: f32,
    /// Guide (sampling D-tree) solid-angle pdf of `direction`.
    pub pdf_guide: f32,
    /// The direction came from a delta lobe (no fraction gradient).
    pub is_delta: bool,
}

impl Record {
    /// A record with only the radiance part (fraction fields zero: no fraction gradient).
    pub fn radiance_only(
        position: Vec3,
        direction: Vec3,
        radiance: f32,
        pdf_mix: f32,
        weight: f32,
    ) -> Self {
        Self {
            position,
            direction,
            radiance,
            pdf_mix,
            weight,
            product: 0.0,
            pdf_bsdf: 0.0,
            pdf_guide: 0.0,
            is_delta: false,
        }
    }
}
