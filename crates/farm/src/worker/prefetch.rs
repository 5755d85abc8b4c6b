//! Building a new job's scene before its first lease, on the coordinator's `Prefetch`
//! advice: the coordinator sends it to idle workers when a job arrives and validates the job
//! meanwhile, so the workers' scene loading (fetching the files, parsing meshes, decoding
//! textures, building the BVH: seconds) overlaps the coordinator's validation instead of
//! following it.
//!
//! Invariant: a prefetched scene is used only by a lease whose bundle and scene settings
//! (the seed aside, which no part of building reads) encode to exactly the bytes it was
//! built from ([`scene_key`]), so it is the scene the lease would have built itself: the
//! bits cannot depend on whether a prefetch happened.
//!
//! At most one prefetched scene is kept. It serves one job (its first lease takes it into
//! the job's scene cache); one nobody takes (the job was refused) is dropped after
//! [`PREFETCH_KEEP`] or by the next `Prefetch`.

use std::sync::Arc;
use std::time::{Duration, Instant};

use pathfarm_proto::v1;
use prost::Message;

use super::{build_scene, ensure_blob, manifest_of, Api, JobScene, Shared};

/// How long a built scene that no lease took is kept.
pub(super) const PREFETCH_KEEP: Duration = Duration::from_secs(60);

/// What a scene is built from: a digest of the bundle and the scene settings, seed unset.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(super) struct SceneKey(pub(super) [u8; 32]);

/// The scene built (`Ok`), or why it could not be (`Err`); `None` while being built (the
/// builder holds the lock until it is done, so a lease waiting for it waits for the build).
type Slot = Arc<tokio::sync::Mutex<Option<Result<Arc<JobScene>, String>>>>;

/// The scene of the last `Prefetch`.
pub(super) struct Prefetched {
    key: SceneKey,
    slot: Slot,
    asked: Instant,
}

pub(super) fn scene_key(bundle: &v1::Bundle, settings: Option<&v1::SceneSettings>) -> SceneKey {
    let mut settings = settings.cloned().unwrap_or_default();
    settings.seed = None;
    let bundle = bundle.encode_to_vec();
    let mut h = blake3::Hasher::new();
    h.update(&(bundle.len() as u64).to_le_bytes());
    h.update(&bundle);
    h.update(&settings.encode_to_vec());
    SceneKey(*h.finalize().as_bytes())
}

/// Starts building the scene `p` names, unless it is the one already prefetched or another
/// prefetch is still being built (a worker builds one scene at a time).
pub(super) fn start(shared: &Arc<Shared>, api: &Api, p: v1::Prefetch) {
    let Some(bundle) = p.bundle else { return };
    let key = scene_key(&bundle, p.settings.as_ref());
    let slot: Slot = Arc::new(tokio::sync::Mutex::new(None));
    let mut guard = slot.clone().try_lock_owned().expect("a new mutex is free");
    {
        let mut c = shared.caches.lock().expect("cache lock");
        if let Some(old) = &c.prefetched {
            if old.key == key || old.slot.try_lock().is_err() {
                return;
            }
        }
        let asked = Instant::now();
        c.prefetched = Some(Prefetched { key, slot, asked });
    }
    let (shared, mut api) = (shared.clone(), api.clone());
    tokio::spawn(async move {
        let t0 = Instant::now();
        let built = build(&shared, &mut api, &bundle, p.settings, key).await;
        match &built {
            Ok(_) => tracing::info!(
                "scene {} built ahead in {:.3} s",
                bundle.root,
                t0.elapsed().as_secs_f64()
            ),
            Err(e) => tracing::info!("building scene {} ahead failed: {e}", bundle.root),
        }
        *guard = Some(built);
    });
}

async fn build(
    shared: &Arc<Shared>,
    api: &mut Api,
    bundle: &v1::Bundle,
    settings: Option<v1::SceneSettings>,
    key: SceneKey,
) -> Result<Arc<JobScene>, String> {
    let manifest = manifest_of(bundle).map_err(|f| f.reason)?;
    for e in &manifest.files {
        ensure_blob(shared, api, &e.digest)
            .await
            .map_err(|f| f.reason)?;
    }
    let sh = shared.clone();
    let dir = format!(
        "prefetch-{}",
        &blake3::Hash::from_bytes(key.0).to_hex()[..16]
    );
    let built = tokio::task::spawn_blocking(move || {
        sh.pool
            .install(|| build_scene(&sh, &manifest, settings.as_ref(), &dir))
    })
    .await
    .map_err(|e| format!("the build panicked: {e}"))?;
    built.map(Arc::new).map_err(|f| f.reason)
}

/// The prefetched scene of `key`, waiting for it if it is being built; taken (a prefetched
/// scene serves one job). `None` if there is none or its build failed (the lease then
/// builds the scene itself and reports its own error).
pub(super) async fn take(shared: &Shared, key: &SceneKey) -> Option<Arc<JobScene>> {
    let slot = {
        let c = shared.caches.lock().expect("cache lock");
        c.prefetched
            .as_ref()
            .filter(|p| p.key == *key)?
            .slot
            .clone()
    };
    let built = slot.lock().await.take();
    let mut c = shared.caches.lock().expect("cache lock");
    if c.prefetched
        .as_ref()
        .is_some_and(|p| Arc::ptr_eq(&p.slot, &slot))
    {
        c.prefetched = None;
    }
    built?.ok()
}

/// Drops a prefetched scene no lease took within [`PREFETCH_KEEP`] (its job was refused or
/// went to other workers): a built scene holds hundreds of MB.
pub(super) fn expire(shared: &Shared) {
    let mut c = shared.caches.lock().expect("cache lock");
    let stale = c.prefetched.as_ref().is_some_and(|p| {
        p.asked.elapsed() > PREFETCH_KEEP && p.slot.try_lock().is_ok_and(|s| s.is_some())
    });
    if stale {
        c.prefetched = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bundle(root: &str) -> v1::Bundle {
        v1::Bundle {
            root: root.into(),
            files: vec![v1::BundleFile {
                path: root.into(),
                digest: vec![7; 32],
                size: 10,
            }],
        }
    }

    fn settings(seed: Option<u64>, define: &str) -> v1::SceneSettings {
        v1::SceneSettings {
            integrator: Some("guided_path".into()),
            defines: vec![v1::Define {
                name: "spp".into(),
                value: define.into(),
            }],
            resolution: None,
            seed,
        }
    }

    #[test]
    fn a_scene_key_ignores_the_seed_and_nothing_else() {
        let b = bundle("scene.xml");
        let base = scene_key(&b, Some(&settings(Some(1), "8")));
        assert_eq!(base, scene_key(&b, Some(&settings(None, "8"))));
        assert_eq!(base, scene_key(&b, Some(&settings(Some(99), "8"))));
        assert_ne!(base, scene_key(&b, Some(&settings(Some(1), "16"))));
        assert_ne!(
            base,
            scene_key(&bundle("other.xml"), Some(&settings(Some(1), "8")))
        );
        let mut wider = settings(Some(1), "8");
        wider.resolution = Some(v1::Resolution {
            width: 64,
            height: 32,
        });
        assert_ne!(base, scene_key(&b, Some(&wider)));
        assert_eq!(
            scene_key(&b, None),
            scene_key(&b, Some(&v1::SceneSettings::default()))
        );
    }
}
