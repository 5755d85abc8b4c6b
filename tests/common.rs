//! Helpers shared by the integration tests.

#![allow(dead_code)]

use std::fs;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Output, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

use pathfarm_render::{render, Film, RenderSettings, Scene};
use pathfarm_scene::load_scene;

/// The repository root (tests run from the cli crate's directory).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .canonicalize()
        .expect("repo root")
}

/// `../shared/scenes/NAME/scene.xml`, beside the repository.
pub fn shared_scene(name: &str) -> PathBuf {
    repo_root()
        .join("../shared/scenes")
        .join(name)
        .join("scene.xml")
}

pub fn project_scene(name: &str) -> PathBuf {
    repo_root().join("scenes").join(name).join("scene.xml")
}

/// A fresh, empty directory for one test.
pub fn temp_dir(tag: &str) -> PathBuf {
    static N: AtomicU32 = AtomicU32::new(0);
    let d = std::env::temp_dir().join(format!(
        "pathfarm-it-{}-{}-{}",
        std::process::id(),
        tag,
        N.fetch_add(1, Ordering::Relaxed)
    ));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// Writes `xml` to a temporary scene file and returns its path.
pub fn write_scene(tag: &str, xml: &str) -> PathBuf {
    let p = temp_dir(tag).join("scene.xml");
    std::fs::write(&p, xml).expect("write scene");
    p
}

/// Loads and renders a scene file in-process.
pub fn render_file(path: &Path, defines: &[(&str, &str)], spp: u32, seed: u64) -> Film {
    let defs: Vec<(String, String)> = defines
        .iter()
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .collect();
    let desc = load_scene(path, &defs).unwrap_or_else(|e| panic!("{e}"));
    let scene = Scene::build(&desc).expect("build");
    render(&scene, &RenderSettings::new(Some(spp), None, seed), &|_| {}).0
}

pub fn render_xml(tag: &str, xml: &str, spp: u32, seed: u64) -> Film {
    render_file(&write_scene(tag, xml), &[], spp, seed)
}

/// Runs the `pathfarm` binary (warnings and errors logged).
pub fn pathfarm(args: &[&str]) -> Output {
    pathfarm_logging(args, "warn")
}

/// Runs the `pathfarm` binary with log level `level` and no colour codes in the log.
pub fn pathfarm_logging(args: &[&str], level: &str) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pathfarm"))
        .args(args)
        .env("RUST_LOG", level)
        .env("NO_COLOR", "1")
        .output()
        .expect("run pathfarm")
}

/// A one-sided diffuse plane (albedo 0.5, 0.25, 0.8) facing +z under a constant sky of
/// radiance (2, 1, 0.5): it reflects albedo x sky at any depth.
pub const PLANE_UNDER_SKY: &str = r#"
        <emitter type="constant"><rgb name="radiance" value="2, 1, 0.5"/></emitter>
        <shape type="rectangle"><transform name="to_world"><scale value="100"/></transform>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.5, 0.25, 0.8"/></bsdf></shape>"#;

/// A minimal scene: camera at (0,0,`cam_z`) looking down -z, given body.
pub fn scene_xml(
    width: u32,
    height: u32,
    fov: f32,
    cam_z: f32,
    integrator: &str,
    body: &str,
) -> String {
    format!(
        r#"<scene version="3.0.0">
    {integrator}
    <sensor type="perspective">
        <float name="fov" value="{fov}"/>
        <transform name="to_world"><lookat origin="0, 0, {cam_z}" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="{width}"/>
            <integer name="height" value="{height}"/>
            <rfilter type="box"/>
        </film>
    </sensor>
    {body}
</scene>"#
    )
}

/// Two-sided normal quantile for significance `alpha`, for the few levels the
/// tests use.
pub fn z_two_sided(alpha: f64) -> f64 {
    if alpha == 0.01 {
        2.5758
    } else if alpha == 0.001 {
        3.2905
    } else if alpha == 1e-4 {
        3.8906
    } else {
        panic!("no quantile tabulated for {alpha}")
    }
}

/// Every accumulator of every pixel as raw bits, for bit-identity checks.
pub fn film_bits(film: &pathfarm_render::Film) -> Vec<u64> {
    film.pixels
        .iter()
        .flat_map(|p| {
            [p.sum_w, p.sum_w2]
                .into_iter()
                .chain(p.sum_wl)
                .chain(p.sum_w2l)
                .chain(p.sum_w2l2)
                .map(|x| x.to_bits())
        })
        .collect()
}

/// White-furnace objects: two touching albedo-1 diffuse spheres, a lossless
/// glass sphere and a two-sided albedo-1 cube in a constant environment of
/// radiance 1. Every pixel must render as 1.
pub const FURNACE_BODY: &str = r#"
        <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
        <shape type="sphere"><point name="center" x="-0.6" y="0" z="0"/><float name="radius" value="0.6"/>
            <bsdf type="diffuse"><rgb name="reflectance" value="1"/></bsdf></shape>
        <shape type="sphere"><point name="center" x="0.6" y="0" z="0"/><float name="radius" value="0.6"/>
            <bsdf type="diffuse"><rgb name="reflectance" value="1"/></bsdf></shape>
        <shape type="sphere"><point name="center" x="0" y="0.9" z="0.2"/><float name="radius" value="0.4"/>
            <bsdf type="dielectric"><float name="int_ior" value="1.5"/></bsdf></shape>
        <shape type="cube"><transform name="to_world"><scale value="0.3"/><translate x="0" y="-0.9" z="0"/></transform>
            <bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="1"/></bsdf></bsdf></shape>"#;

/// The `pathfarm` binary under test: `PATHFARM_TEST_BIN` (e.g. an older build, to see a
/// test fail on it), else the one cargo built.
pub fn pathfarm_bin() -> PathBuf {
    std::env::var_os("PATHFARM_TEST_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_BIN_EXE_pathfarm")))
}

/// A child `pathfarm`, killed and reaped when dropped unless it was reaped already
/// (so a failing test leaves no process behind, and a pid is never signalled after
/// it was reaped).
pub struct Running {
    child: Option<Child>,
    pub stdout: PathBuf,
    pub stderr: PathBuf,
}

/// How a run ended.
pub struct Ended {
    pub status: ExitStatus,
    pub stdout: String,
    pub stderr: String,
}

impl Ended {
    pub fn describe(&self) -> String {
        format!(
            "{:?}\nstdout: {}\nstderr: {}",
            self.status, self.stdout, self.stderr
        )
    }
}

impl Running {
    /// Starts `pathfarm ARGS` (log level info, so "loaded ..." shows that the scene was
    /// read) with SIGINT and SIGTERM at their default disposition, `extra_env` set and
    /// its output sent to files outside the directories the tests watch.
    pub fn start(args: &[&str], extra_env: &[(&str, &str)]) -> Self {
        let logs = temp_dir("outputs-logs");
        let (stdout, stderr) = (logs.join("stdout"), logs.join("stderr"));
        let mut cmd = Command::new(pathfarm_bin());
        cmd.args(args)
            .env("RUST_LOG", "info")
            .env("NO_COLOR", "1")
            .env_remove("PATHFARM_NO_O_TMPFILE")
            .stdin(Stdio::null())
            .stdout(fs::File::create(&stdout).expect("stdout file"))
            .stderr(fs::File::create(&stderr).expect("stderr file"));
        for (k, v) in extra_env {
            cmd.env(k, v);
        }
        // SAFETY: signal() is async-signal-safe, as pre_exec requires.
        unsafe {
            cmd.pre_exec(|| {
                libc::signal(libc::SIGINT, libc::SIG_DFL);
                libc::signal(libc::SIGTERM, libc::SIG_DFL);
                Ok(())
            });
        }
        let child = cmd.spawn().expect("run pathfarm");
        Running {
            child: Some(child),
            stdout,
            stderr,
        }
    }

    /// Sends `sig` to the child unless it has been reaped.
    pub fn signal(&mut self, sig: libc::c_int) {
        if let Some(c) = &self.child {
            // SAFETY: the pid is our unreaped child's (at worst a zombie).
            unsafe { libc::kill(c.id() as libc::pid_t, sig) };
        }
    }

    /// Whether the child has ended (it is reaped then, and its status kept).
    pub fn poll(&mut self) -> Option<ExitStatus> {
        let c = self.child.as_mut()?;
        c.try_wait().expect("try_wait")
    }

    /// Waits at most `timeout` for the child to end; panics (killing it) on timeout.
    pub fn wait(mut self, timeout: Duration) -> Ended {
        let t0 = Instant::now();
        let status = loop {
            if let Some(s) = self.poll() {
                break s;
            }
            if t0.elapsed() > timeout {
                panic!(
                    "pathfarm did not end within {timeout:?}; stderr: {}",
                    fs::read_to_string(&self.stderr).unwrap_or_default()
                );
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        self.child = None;
        Ended {
            status,
            stdout: fs::read_to_string(&self.stdout).unwrap_or_default(),
            stderr: fs::read_to_string(&self.stderr).unwrap_or_default(),
        }
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Running {
    /// The child's pid, while it has not been reaped.
    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(|c| c.id())
    }

    /// Its stderr so far.
    pub fn stderr_text(&self) -> String {
        std::fs::read_to_string(&self.stderr).unwrap_or_default()
    }
}

/// The shipped door-ajar scene with `guided_path` (its pathfarm preset) at `res`.
pub fn door_ajar(res: (u32, u32)) -> Scene {
    let defs: Vec<(String, String)> = [
        ("integrator", "guided_path".to_string()),
        ("resx", res.0.to_string()),
        ("resy", res.1.to_string()),
    ]
    .into_iter()
    .map(|(a, b)| (a.to_string(), b))
    .collect();
    let desc = load_scene(&project_scene("door-ajar"), &defs).unwrap_or_else(|e| panic!("{e}"));
    Scene::build(&desc).expect("build")
}

/// A small seeded generator (splitmix64) for test schedules.
pub struct TestRng(pub u64);

impl TestRng {
    pub fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `0..n` (0 for n = 0).
    pub fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }

    /// True with probability `percent` / 100.
    pub fn chance(&mut self, percent: u64) -> bool {
        self.below(100) < percent
    }
}
