//! What the guide learned at a pixel, for a job's latest tree, as `pathfarm guide scatter`
//! draws it: at the pixel's first hit, directions drawn by BSDF sampling alone, directions
//! drawn from the guided mixture, and the directional distribution (quadtree) the guide
//! learned there. For the dashboard: a person clicks the preview and sees where the farm
//! learned the light comes from there, and how that changes where paths go.
//!
//! The coordinator renders nothing else, so it builds the job's scene (with its BVH) only
//! for this, once, and keeps the last one asked for with its decoded tree.

use std::sync::Arc;

use glam::Vec2;
use pathfarm_guide::SdTree;
use pathfarm_proto::v1;
use pathfarm_render::integrator::guided_path::{scatter_at, scatter_panels};
use pathfarm_render::{Purpose, Scene};

use super::{manifest_from_proto, overrides_of, Shared};
use crate::bundle::Digest;

/// A panel's width in pixels (its height is half: the sphere of directions, unrolled).
pub(crate) const WIDTH: usize = 256;
/// The grey between panels.
const GAP: usize = 8;
/// Directions drawn each way for the two sampling panels.
const SAMPLES: u32 = 50_000;

/// The scene and tree the last picture was drawn from.
#[derive(Default)]
pub(crate) struct GuideCache {
    scene: Option<(u64, Arc<Scene>)>,
    tree: Option<(Digest, Arc<SdTree>)>,
}

/// Why there is no picture.
#[derive(Debug, thiserror::Error)]
pub(crate) enum GuideViewError {
    #[error("no job {0}")]
    NoJob(u64),
    #[error("the job has no tree yet (its first iteration trains one)")]
    NoTree,
    #[error("pixel {0},{1} is outside the {2}x{3} image")]
    Outside(u32, u32, u32, u32),
    #[error("the ray through pixel {0},{1} hits nothing")]
    Miss(u32, u32),
    #[error("{0}")]
    Scene(String),
}

impl Shared {
    /// The PNG of the three panels (BSDF sampling, guided mixture, learned quadtree) at the
    /// first hit of pixel (`x`, `y`) of job `n`, from its latest tree. Slow (it may build the
    /// scene): call off the executor.
    pub(crate) fn guide_picture(&self, n: u64, x: u32, y: u32) -> Result<Vec<u8>, GuideViewError> {
        let (request, tree_digest) = self.job_tree(n)?;
        let scene = self.guide_scene(n, &request)?;
        if x >= scene.width || y >= scene.height {
            return Err(GuideViewError::Outside(x, y, scene.width, scene.height));
        }
        let tree = self.guide_tree(tree_digest)?;
        let params = scene.guided.clone().unwrap_or_default();
        let pixel = Vec2::new(x as f32, y as f32);
        let s =
            scatter_at(&scene, &params, &tree, pixel, SAMPLES).ok_or(GuideViewError::Miss(x, y))?;
        let (width, rgb) = scatter_panels(&s, &tree, WIDTH, GAP);
        let bytes: Vec<u8> = (rgb.iter())
            .map(|&c| (c.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
            .collect();
        pathfarm_render::output::encode_png_rgb8(width as u32, WIDTH as u32 / 2, &bytes)
            .map_err(|e| GuideViewError::Scene(e.to_string()))
    }

    /// Job `n`'s submission and its latest tree: the final one once done, else the one its
    /// workers render with now.
    fn job_tree(&self, n: u64) -> Result<(v1::SubmitJobRequest, Digest), GuideViewError> {
        let st = self.lock();
        let job = st.jobs.get(&n).ok_or(GuideViewError::NoJob(n))?;
        let request = job.record.request.clone().ok_or(GuideViewError::NoJob(n))?;
        let running = job.active().and_then(|a| a.tree_digest).map(|(_, d)| d);
        let done = <[u8; 32]>::try_from(job.record.tree.as_slice())
            .ok()
            .map(Digest);
        Ok((request, running.or(done).ok_or(GuideViewError::NoTree)?))
    }

    fn guide_scene(
        &self,
        n: u64,
        req: &v1::SubmitJobRequest,
    ) -> Result<Arc<Scene>, GuideViewError> {
        if let Some(s) = cached(&self.guide_cache, |c| &c.scene, &n) {
            return Ok(s);
        }
        let scene = Arc::new(self.build_job_scene(req).map_err(GuideViewError::Scene)?);
        let mut c = self.guide_cache.lock().unwrap_or_else(|e| e.into_inner());
        c.scene = Some((n, scene.clone()));
        Ok(scene)
    }

    /// The job's scene as its workers build it, from the blobs of its bundle.
    fn build_job_scene(&self, req: &v1::SubmitJobRequest) -> Result<Scene, String> {
        let bundle_msg = req.bundle.as_ref().ok_or("the job has no bundle")?;
        let manifest = manifest_from_proto(bundle_msg).map_err(|s| s.message().to_string())?;
        let settings = (req.settings.clone().unwrap_or_default().scene).unwrap_or_default();
        let overrides = overrides_of(&settings).map_err(|s| s.message().to_string())?;
        (self.load_bundle(&manifest, &settings, &overrides, Purpose::Render))
            .map_err(|e| format!("the job's scene: {e}"))
    }

    fn guide_tree(&self, d: Digest) -> Result<Arc<SdTree>, GuideViewError> {
        if let Some(t) = cached(&self.guide_cache, |c| &c.tree, &d) {
            return Ok(t);
        }
        let bytes = std::fs::read(self.blobs.path(&d))
            .map_err(|e| GuideViewError::Scene(format!("the tree: {e}")))?;
        let tree = Arc::new(
            SdTree::decode(&bytes).map_err(|e| GuideViewError::Scene(format!("the tree: {e}")))?,
        );
        self.guide_cache
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .tree = Some((d, tree.clone()));
        Ok(tree)
    }
}

/// The value in `slot` of the cache if it was kept for `key`.
fn cached<K: PartialEq, V: Clone>(
    cache: &std::sync::Mutex<GuideCache>,
    slot: impl Fn(&GuideCache) -> &Option<(K, V)>,
    key: &K,
) -> Option<V> {
    let c = cache.lock().unwrap_or_else(|e| e.into_inner());
    slot(&c)
        .as_ref()
        .filter(|(k, _)| k == key)
        .map(|(_, v)| v.clone())
}
