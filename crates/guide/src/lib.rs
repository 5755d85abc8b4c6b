//! # pathfarm-guide
//!
//! A renderer-agnostic SD-tree for Practical Path Guiding (Müller, Gross, Novák 2017) with the
//! 2019 production improvements (filtered splatting, learned BSDF-sampling fraction,
//! inverse-variance combination of iterations).
//!
//! * [`SdTree`]: spatial binary tree of double-buffered directional quadtrees. Sample and pdf
//!   read the frozen `sampling` trees ([`SamplingDTree`]); [`SdTree::record`] (thread safe,
//!   `&self`) adds to the `building` trees ([`DTree`]); [`SdTree::refine`] ends an iteration,
//!   freezing each built tree ([`DTree::freeze`]).
//! * Statistics are exact fixed-point integers ([`stats`]): recording is bit-identical for any
//!   thread count and order, and worker statistics merge exactly ([`IterationStats`], in
//!   [`iteration_stats`]); trees fingerprint their structure with [`hash::Hasher64`].
//! * [`wire`]: versioned, CRC-checked binary forms of a tree and of one iteration's statistics.
//!   It depends on the domain types; nothing else in the crate depends on it.
//! * [`schedule`]: iteration schedule, the weights that combine iteration images, and the
//!   path fallback's rule.
//! * [`viz`]: rasterise a quadtree's pdf into an RGB image.
//!
//! Typical renderer loop (iteration k, pass loop inside):
//! ```
//! use pathfarm_guide::{GuideConfig, SdTree, Record};
//! use glam::Vec3;
//! let mut tree = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), GuideConfig::default());
//! let mut r = 0.25f32;
//! let mut rng = move || { r = (r * 7.31 + 0.137).fract(); r };
//! for k in 0..2 {
//!     // per vertex: let h = tree.leaf_index(p); tree.sample_leaf(h, &mut rng) ... pdf_leaf ...
//!     let rec = Record::radiance_only(Vec3::ZERO, Vec3::Z, 1.0, 0.5, 1.0);
//!     tree.record(&rec, &mut rng);
//!     tree.step_fractions(); // end of every pass
//!     tree.refine(k);        // end of the iteration
//! }
//! assert!(tree.sample(Vec3::ZERO, &mut rng).is_some());
//! ```

#![warn(missing_docs)]
// `!(x > 0.0)` is used on purpose: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

pub mod carry;
pub mod config;
pub mod dtree;
pub mod filter;
pub mod fraction;
pub mod hash;
pub mod iteration_stats;
pub mod light;
pub mod mapping;
pub mod record;
pub mod region;
pub mod schedule;
pub mod sdtree;
pub mod stats;
pub mod stree;
pub mod viz;
pub mod wire;

pub use config::{
    AdamConfig, DirectionalFilter, FractionLoss, FractionMode, GuideConfig, SpatialFilter,
};
pub use dtree::{Cell, DTree, SamplingDTree};
pub use iteration_stats::{IterationStats, LeafStats, StatsError};
pub use light::LightStats;
pub use mapping::{dir_to_uv, uv_to_dir};
pub use record::Record;
pub use region::{CellMask, CellWeights, Restriction};
pub use sdtree::{GradTarget, HeldSlot, Leaf, LeafHandle, SdTree, TreeStats};
pub use stree::{SLookup, STree};
pub use wire::WireError;

#[cfg(test)]
mod test_support;
