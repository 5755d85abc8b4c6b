//! Integrators: estimate the radiance arriving along a camera ray.

pub mod path;
pub mod guided_path;
