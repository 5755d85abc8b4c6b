//! Spatial and directional recording filters (doc section 7).
//!
//! The filter kinds are configured with [`crate::SpatialFilter`] and
//! [`crate::DirectionalFilter`]; this module holds the geometry. Directional box splats live in
//! [`crate::DTree::splat_box`]. All box splats distribute *integer* fixed-point amounts with
//! [`crate::stats::split_exact`], so they conserve mass exactly.

use crate::stree::{SLookup, STree};
use glam::Vec3;

#[cfg(test)]
mod tests;

/// Stochastic spatial filter: the position jittered uniformly within +-1/2 of the extent of the
/// leaf `at` (the leaf containing `p`), using three caller-supplied random numbers in `[0, 1)`
/// (x, y, z in that order). The result may lie outside the domain; lookups clamp it onto the
/// domain.
pub fn stochastic_jitter(p: Vec3, at: &SLookup, rng: &mut impl FnMut() -> f32) -> Vec3 {
    let rx = rng() - 0.5;
    let ry = rng() - 0.5;
    let rz = rng() - 0.5;
    p + at.extent * Vec3::new(rx, ry, rz)
}

/// Spatial box filter: the leaves overlapped by a box of the size of the leaf `at` centred on
/// `p`, with their overlap volumes (normalised units). Faces of leaves on the domain border are
/// extended to infinity, so mass outside the domain lands in the border leaves (as clamping the
/// stochastic filter's jittered position does) and the overlaps always sum to the box volume.
/// `out` is cleared first.
pub fn spatial_box_overlaps(tree: &STree, p: Vec3, at: &SLookup, out: &mut Vec<(u32, f64)>) {
    out.clear();
    let c = tree.normalise(p);
    let e = at.extent / tree.domain_size() * 0.5;
    let lo = (c - e).to_array();
    let hi = (c + e).to_array();
    tree.for_each_overlap(lo, hi, |leaf, vol| out.push((leaf, vol)));
    if out.is_empty() {
        out.push((at.leaf, 1.0));
    }
}
