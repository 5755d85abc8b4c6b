//! Simulated rendering, for measuring the farm at more workers than a machine has cores
//! (`bench/farm_swarm.py`): the worker does everything it does for a lease (fetches the
//! inputs, builds the scene, keeps the tree, takes its statistics, uploads, hands in records)
//! except the render itself, which is a sleep as long as the tile would take and zero
//! radiance of the tile's real size and form. The coordinator cannot tell the difference
//! in the work it does per upload; the images are black and the guide learns nothing.

use std::time::Duration;

use pathfarm_render::pass::{PassSpec, TileOutput, TilePixels};
use pathfarm_render::{Film, Region};

/// How a worker renders its tiles.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Rendering {
    /// The path tracer: the farm's product.
    Real,
    /// A sleep of this many seconds a sample, then zero radiance (benchmarks only).
    Simulated { seconds_per_sample: f64 },
}

/// A tile of `region` of `spec` as a simulated render gives it, after sleeping for its
/// samples' time.
pub(super) fn simulate_unit(
    spec: &PassSpec,
    region: Region,
    seconds_per_sample: f64,
) -> TileOutput {
    let samples = region.pixels() as u64 * spec.unit_spp();
    std::thread::sleep(Duration::from_secs_f64(samples as f64 * seconds_per_sample));
    let pixels = match spec.sample_form() {
        true => TilePixels::Samples(vec![glam::Vec3::ZERO; samples as usize]),
        false => TilePixels::Sums(Film::new(region.width(), region.height())),
    };
    TileOutput {
        region,
        pixels,
        rays: 0,
        invalid_samples: 0,
        nonfinite_records: 0,
        split_paths: 0,
        extra_light_samples: 0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pathfarm_render::pass::PassKind;

    #[test]
    fn a_simulated_tile_has_the_form_and_size_its_unit_asks_for() {
        let region = Region {
            x0: 8,
            y0: 4,
            x1: 24,
            y1: 12,
        };
        for spp in [1, 64] {
            let spec = PassSpec {
                unit: 3,
                iteration: 1,
                kind: PassKind::Guided,
                first_sample: 0,
                spp,
                passes: 1,
                spp_before: 0,
                split: false,
                tree_version: 1,
                fraction_version: 0,
            };
            let out = simulate_unit(&spec, region, 0.0);
            assert!(out.pixels.fits(&spec, region), "spp {spp}");
            assert_eq!(out.region, region);
        }
    }
}
