//! Integrators: estimate the radiance arriving along a camera ray.

pub mod guided_path;
pub mod path;
