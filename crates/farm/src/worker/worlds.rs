//! The worlds (geometry with its BVH, lights, materials, textures) of the scenes this worker
//! holds, by [`crate::bundle::world_key`]: a scene whose world is one of them (a frame of the same
//! shot with its camera moved) is built on it, from a scan of its text (milliseconds), not
//! from its files (seconds: meshes parsed, images decoded, the BVH built).
//!
//! Held weakly: a world lives as long as a scene in the scene cache (or a lease) uses it, so
//! the cache's budget alone decides what the worker keeps.

use std::sync::{Arc, Weak};

use pathfarm_render::World;

use crate::bundle::Digest;

#[derive(Default)]
pub(super) struct Worlds {
    entries: Vec<(Digest, Weak<World>)>,
}

impl Worlds {
    /// The world of `key`, if a scene still holds it.
    pub fn get(&mut self, key: &Digest) -> Option<Arc<World>> {
        self.entries.retain(|(_, w)| w.strong_count() > 0);
        (self.entries.iter())
            .find(|(k, _)| k == key)
            .and_then(|(_, w)| w.upgrade())
    }

    /// Remembers `world` as the world of `key` (replacing a dead or concurrently built one).
    pub fn insert(&mut self, key: Digest, world: &Arc<World>) {
        self.entries
            .retain(|(k, w)| *k != key && w.strong_count() > 0);
        self.entries.push((key, Arc::downgrade(world)));
    }
}
