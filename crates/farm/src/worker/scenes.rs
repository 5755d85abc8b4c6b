//! The worker's built scenes, kept across leases and jobs within a memory budget (least
//! recently used out first) and shared by every job of the same scene: the same bundle and
//! settings, seed aside ([`prefetch::scene_key`]). A worker that switches between the jobs
//! of a farm then builds each scene once, however the coordinator interleaves their tiles.
//! Scenes that share a world (the frames of a shot: [`super::worlds`]) count its bytes once.

use std::collections::HashMap;
use std::sync::Arc;

use super::prefetch::SceneKey;
use super::JobScene;

/// The default budget: enough for the scenes of several production jobs at once.
pub const DEFAULT_BUDGET_BYTES: u64 = 4 << 30;

/// Built scenes by key, most recently used last, and the scene each job uses.
pub(super) struct SceneCache {
    budget: u64,
    entries: Vec<Entry>,
    jobs: HashMap<String, SceneKey>,
}

struct Entry {
    key: SceneKey,
    scene: Arc<JobScene>,
    bytes: u64,
}

impl SceneCache {
    pub fn new(budget: u64) -> Self {
        Self {
            budget,
            entries: Vec::new(),
            jobs: HashMap::new(),
        }
    }

    /// The scene of `key`, marked most recently used and remembered as `job`'s.
    pub fn get(&mut self, key: &SceneKey, job: &str) -> Option<Arc<JobScene>> {
        let scene = self.touch(key)?;
        self.jobs.insert(job.to_string(), *key);
        Some(scene)
    }

    fn touch(&mut self, key: &SceneKey) -> Option<Arc<JobScene>> {
        let i = self.entries.iter().position(|e| e.key == *key)?;
        let e = self.entries.remove(i);
        let scene = e.scene.clone();
        self.entries.push(e);
        Some(scene)
    }

    /// Keeps `scene` as the scene of `key` and `job`, dropping the least recently used scenes
    /// beyond the budget (never the one just kept). Returns the jobs whose scene was
    /// dropped, whose trees and estimates go with it.
    pub fn insert(&mut self, key: SceneKey, job: &str, scene: Arc<JobScene>) -> Vec<String> {
        self.entries.retain(|e| e.key != key);
        let bytes = scene.scene.memory_bytes();
        self.entries.push(Entry { key, scene, bytes });
        self.jobs.insert(job.to_string(), key);
        let mut dropped = Vec::new();
        while self.entries.len() > 1 && self.total() > self.budget {
            let old = self.entries.remove(0);
            let gone: Vec<String> = (self.jobs.iter())
                .filter(|(_, k)| **k == old.key)
                .map(|(j, _)| j.clone())
                .collect();
            for j in &gone {
                self.jobs.remove(j);
            }
            dropped.extend(gone);
        }
        dropped
    }

    /// The bytes of the entries' worlds, each world once.
    fn total(&self) -> u64 {
        let mut worlds: Vec<*const pathfarm_render::World> = Vec::new();
        let mut total = 0;
        for e in &self.entries {
            let w: *const _ = e.scene.scene.world();
            if !worlds.contains(&w) {
                worlds.push(w);
                total += e.bytes;
            }
        }
        total
    }

    /// Whether `job`'s scene is here.
    #[cfg(test)]
    pub fn holds_job(&self, job: &str) -> bool {
        self.jobs.contains_key(job)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pathfarm_render::Scene;
    use pathfarm_scene::load_scene;

    fn desc(sensor: &str, xml_body: &str) -> pathfarm_scene::SceneDesc {
        static DIRS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = DIRS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir =
            std::env::temp_dir().join(format!("pathfarm-scene-cache-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("scene.xml");
        let xml = format!("<scene version=\"3.0.0\">{sensor}{xml_body}</scene>");
        std::fs::write(&path, xml).unwrap();
        let desc = load_scene(&path, &[]).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        desc
    }

    fn job_scene(scene: Scene) -> Arc<JobScene> {
        Arc::new(JobScene {
            scene,
            params: Default::default(),
        })
    }

    fn scene(xml_body: &str) -> Arc<JobScene> {
        let desc = desc("<sensor type=\"perspective\"/>", xml_body);
        job_scene(Scene::build(&desc).unwrap())
    }

    fn key(n: u8) -> SceneKey {
        SceneKey([n; 32])
    }

    #[test]
    fn jobs_of_one_scene_share_it_and_the_least_recently_used_goes_over_budget() {
        let a = scene("<shape type=\"cube\"/>");
        let b = scene("<shape type=\"cube\"/><shape type=\"rectangle\"/>");
        let d = scene("<shape type=\"sphere\"/><shape type=\"cube\"/>");
        let (sa, sb, sd) = (
            a.scene.memory_bytes(),
            b.scene.memory_bytes(),
            d.scene.memory_bytes(),
        );
        assert!(sa > 0 && sb > sa && sd <= sb, "{sa} {sb} {sd}");
        let mut c = SceneCache::new(sa + sb);
        assert!(c.insert(key(1), "j1", a.clone()).is_empty());
        // A second job of the same scene takes it from the cache.
        assert!(Arc::ptr_eq(&c.get(&key(1), "j2").unwrap(), &a));
        assert!(c.holds_job("j2"));
        assert!(c.insert(key(2), "j3", b).is_empty());
        // j1's scene is used again: j3's is now the least recently used.
        assert!(c.get(&key(1), "j1").is_some());
        assert_eq!(c.insert(key(3), "j4", d), vec!["j3".to_string()]);
        assert!(!c.holds_job("j3") && c.get(&key(2), "j3").is_none());
        assert!(c.holds_job("j1") && c.holds_job("j2") && c.holds_job("j4"));
        assert_eq!(c.total(), sa + sd);
    }

    #[test]
    fn a_scene_larger_than_the_budget_is_still_kept_alone() {
        let a = scene("<shape type=\"cube\"/>");
        let mut c = SceneCache::new(1);
        assert!(c.insert(key(1), "j1", a.clone()).is_empty());
        assert_eq!(c.insert(key(2), "j2", a), vec!["j1".to_string()]);
        assert!(c.holds_job("j2") && !c.holds_job("j1"));
    }

    #[test]
    fn frames_on_one_world_count_its_bytes_once() {
        let body = "<shape type=\"cube\"/><shape type=\"sphere\"/>";
        let a = scene(body);
        let moved = desc(
            "<sensor type=\"perspective\"><float name=\"fov\" value=\"30\"/></sensor>",
            body,
        );
        let b = job_scene(Scene::with_world(&moved, a.scene.shared_world()).unwrap());
        let world = a.scene.memory_bytes();
        let mut c = SceneCache::new(world);
        assert!(c.insert(key(1), "j1", a).is_empty());
        assert!(c.insert(key(2), "j2", b).is_empty(), "both frames kept");
        assert_eq!(c.total(), world);
        let other = scene("<shape type=\"cube\"/>");
        assert_eq!(c.insert(key(3), "j3", other), vec!["j1", "j2"]);
    }
}
