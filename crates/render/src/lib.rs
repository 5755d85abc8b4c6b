//! The pathfarm CPU renderer.
//!
//! [`Scene::build`] turns a [`pathfarm_scene::SceneDesc`] into render-ready
//! data (BVH, materials, lights, camera); [`render()`] runs an integrator over
//! the image in tiles on the rayon pool; [`output`] writes EXR and PNG files.
//!
//! Invariants:
//! - Determinism: a sample's random numbers depend only on (seed, pixel,
//!   sample index), and each pixel sums its samples in index order, so the
//!   image is bit-identical for any tile size, thread count or pass split.
//! - This crate does no network I/O.

#![warn(missing_docs)]
// Checks are written `!(x > 0.0)` on purpose: they also reject NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod camera;
pub mod checkpoint;
pub mod counter;
pub mod film;
pub mod filter;
pub mod geometry;
pub mod guided;
pub mod integrator;
pub mod light;
pub mod material;
pub mod output;
pub mod pass;
mod render;
pub mod rng;
pub mod sampling;
pub mod scene;
pub mod session;
pub mod shading;
pub mod splat;
pub mod texture;

pub use film::Film;
pub use render::{
    path_estimator, render, render_into, render_region_into, sample_region, CameraSample,
    Estimator, PathEstimator, Progress, Region, RenderSettings, RenderStats, DEFAULT_TILE,
};
pub use scene::{Purpose, Scene, World};
pub use splat::{RegionSplat, SplatPlan, UnitFilm, UnitSplat};

/// Errors of the renderer (scene loading has its own, in pathfarm-scene).
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// Something the renderer cannot handle (the message says what): an unsupported scene
    /// feature, geometry the BVH builder failed on, or an image the encoder refused.
    #[error("unsupported: {0}")]
    Unsupported(String),
    /// The render would exceed a resource limit (the message names it).
    #[error("{0}")]
    TooLarge(String),
    /// An image file could not be written.
    #[error("{path}: cannot write image: {message}")]
    Output {
        /// The file being written.
        path: std::path::PathBuf,
        /// What went wrong (the encoder's or the file system's error).
        message: String,
    },
}
