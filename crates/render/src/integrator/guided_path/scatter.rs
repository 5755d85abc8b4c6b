//! What guiding does at a pixel's first hit: directions drawn there by BSDF sampling alone
//! and by the guided mixture, beside the learned quadtree (`pathfarm guide scatter`, and the
//! farm dashboard's guide panel).

use glam::{Vec2, Vec3};
use pathfarm_guide::SdTree;
use pathfarm_scene::GuidedParams;

use super::{guide_region, sample_mixture, VertexGuide};
use crate::rng::Rng;
use crate::scene::Scene;

/// The directions drawn at a pixel's first hit.
#[derive(Clone, Debug)]
pub struct Scatter {
    /// The first hit.
    pub point: Vec3,
    /// Its shape's index.
    pub shape: u32,
    /// The BSDF-sampling fraction of the mixture there (1 where the vertex is not guided).
    pub bsdf_fraction: f32,
    /// Directions (world space) drawn by sampling the BSDF.
    pub from_bsdf: Vec<Vec3>,
    /// Directions (world space) drawn from the guided mixture.
    pub from_mixture: Vec<Vec3>,
}

/// Draws `samples` directions each way at the first hit of the ray through the centre of
/// `pixel`, with `tree` as the guide; `None` if that ray hits nothing. The random numbers
/// are fixed, so the same inputs give the same directions.
pub fn scatter_at(
    scene: &Scene,
    params: &GuidedParams,
    tree: &SdTree,
    pixel: Vec2,
    samples: u32,
) -> Option<Scatter> {
    let ray = scene.camera.ray(pixel.floor() + Vec2::splat(0.5));
    let hit = scene.world().accel.intersect::<true>(&ray)?;
    let si = scene.world().accel.interaction(&ray, &hit);
    let (bsdf, frame) = scene.bsdf_at(&si, hit.prim, ray.d);
    let wi = frame.to_local(-ray.d);
    let guide = match bsdf.flags().smooth {
        true => {
            let (hemisphere, cosine) = (params.guide_hemisphere, params.guide_cosine);
            let region = guide_region(hemisphere, cosine, bsdf.flags(), &frame, wi);
            VertexGuide::at(tree, si.p, region)
        }
        false => VertexGuide::unguided(),
    };
    let mut rng = Rng::new(7, 11);
    let (mut from_bsdf, mut from_mixture) = (Vec::new(), Vec::new());
    for _ in 0..samples {
        if let Some(s) = bsdf.sample(wi, rng.next_f32(), rng.next_2d()) {
            from_bsdf.push(frame.to_world(s.wo));
        }
        if let Some(s) = sample_mixture(tree, &guide, &bsdf, &frame, wi, &mut rng) {
            from_mixture.push(s.wo_world);
        }
    }
    Some(Scatter {
        point: si.p,
        shape: si.shape,
        bsdf_fraction: if guide.guided { guide.alpha } else { 1.0 },
        from_bsdf,
        from_mixture,
    })
}

/// The three panels side by side, `width` pixels each and `width / 2` high, `gap` apart on
/// grey: the BSDF's directions, the mixture's (as [`pathfarm_guide::viz::histogram`]s) and
/// the quadtree learned at the hit ([`pathfarm_guide::viz::rasterize_pdf`]). RGB floats, row
/// major; returns the picture's width too.
pub fn scatter_panels(s: &Scatter, tree: &SdTree, width: usize, gap: usize) -> (usize, Vec<f32>) {
    use pathfarm_guide::viz;
    let h = width / 2;
    let leaf = tree.leaf(tree.leaf_index(s.point));
    let panels = [
        viz::histogram(&s.from_bsdf, width),
        viz::histogram(&s.from_mixture, width),
        viz::rasterize_pdf(&leaf.sampling, width, h, true),
    ];
    let total = 3 * width + 2 * gap;
    let mut img = vec![0.5f32; total * h * 3];
    for (i, panel) in panels.iter().enumerate() {
        let x0 = i * (width + gap);
        for y in 0..h {
            let dst = (y * total + x0) * 3;
            img[dst..dst + width * 3].copy_from_slice(&panel[y * width * 3..(y + 1) * width * 3]);
        }
    }
    (total, img)
}
