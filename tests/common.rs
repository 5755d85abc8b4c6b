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

/// The 1-based line of `xml` holding `needle` (the first one).
pub fn line_of(xml: &str, needle: &str) -> usize {
    xml.lines()
        .position(|l| l.contains(needle))
        .unwrap_or_else(|| panic!("{needle:?} not in the scene"))
        + 1
}

/// Loads a scene file with `defines` (`-D name=value`) and builds it.
pub fn build_scene(path: &Path, defines: &[(&str, &str)]) -> Scene {
    let defs: Vec<(String, String)> = defines
        .iter()
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .collect();
    let desc = load_scene(path, &defs).unwrap_or_else(|e| panic!("{e}"));
    Scene::build(&desc).expect("build")
}

/// Loads and renders a scene file in-process.
pub fn render_file(path: &Path, defines: &[(&str, &str)], spp: u32, seed: u64) -> Film {
    let scene = build_scene(path, defines);
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

/// Runs `pathfarm render SCENE -o OUT EXTRA...` (warnings and errors logged).
pub fn pathfarm_render(scene: &Path, out: &Path, extra: &[&str]) -> Output {
    pathfarm_render_logging(scene, out, extra, "warn")
}

/// [`pathfarm_render`] with log level `level`.
pub fn pathfarm_render_logging(scene: &Path, out: &Path, extra: &[&str], level: &str) -> Output {
    pathfarm_logging(&render_args(scene, out, extra), level)
}

/// `render SCENE -o OUT EXTRA...`.
pub fn render_args<'a>(scene: &'a Path, out: &'a Path, extra: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec!["render", path_str(scene), "-o", path_str(out)];
    args.extend_from_slice(extra);
    args
}

/// `guide train SCENE -o TREE --spp SPP`: trains a guide tree and saves it.
pub fn guide_train_args<'a>(scene: &'a Path, tree: &'a Path, spp: &'a str) -> Vec<&'a str> {
    let (scene, tree) = (path_str(scene), path_str(tree));
    vec!["guide", "train", scene, "-o", tree, "--spp", spp]
}

/// `guide show TREE --point POINT -o OUT --width WIDTH`: a picture of the directional
/// distribution the tree holds at a point.
pub fn guide_show_args<'a>(
    tree: &'a Path,
    point: &'a str,
    out: &'a Path,
    width: &'a str,
) -> Vec<&'a str> {
    let (tree, out) = (path_str(tree), path_str(out));
    vec![
        "guide", "show", tree, "--point", point, "-o", out, "--width", width,
    ]
}

/// `guide scatter SCENE --tree TREE --pixel PIXEL -o OUT --width WIDTH --samples SAMPLES`:
/// a picture of the directions sampled at a pixel's first hit.
pub fn guide_scatter_args<'a>(
    scene: &'a Path,
    tree: &'a Path,
    pixel: &'a str,
    out: &'a Path,
    width: &'a str,
    samples: &'a str,
) -> Vec<&'a str> {
    let (scene, tree, out) = (path_str(scene), path_str(tree), path_str(out));
    let mut args = vec!["guide", "scatter", scene, "--tree", tree, "--pixel", pixel];
    args.extend(["-o", out, "--width", width, "--samples", samples]);
    args
}

/// Asserts that a run succeeded (else fails showing its stderr); returns its stdout.
pub fn assert_success(o: &Output) -> String {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Asserts that a run failed cleanly: a non-zero exit and no panic (`what` names the case in
/// the failure message); returns its stderr.
pub fn assert_clean_failure(o: &Output, what: &str) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(
        !o.status.success(),
        "{what}: expected failure, got success; stderr: {err}"
    );
    assert!(!err.contains("panicked"), "{what}: panic: {err}");
    err
}

/// `p` as a `&str` (the tests' paths are UTF-8).
pub fn path_str(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

/// Owned arguments as the `&str`s [`pathfarm`] and [`Running::start`] take.
pub fn as_strs(args: &[String]) -> Vec<&str> {
    args.iter().map(String::as_str).collect()
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

/// A square perspective camera for [`cam_scene_xml`].
#[derive(Clone, Copy)]
pub struct Cam {
    pub origin: [f32; 3],
    pub target: [f32; 3],
    pub up: [f32; 3],
    pub fov: f32,
    pub res: u32,
    /// Mitsuba's `near_clip` and `far_clip` (lengths: scaled scenes scale them too).
    pub near: f32,
    pub far: f32,
}

impl Cam {
    /// Up +z, and Mitsuba's default clip distances (1e-2, 1e4).
    pub fn new(origin: [f32; 3], target: [f32; 3], fov: f32, res: u32) -> Self {
        Cam {
            origin,
            target,
            up: [0.0, 0.0, 1.0],
            fov,
            res,
            near: 1e-2,
            far: 1e4,
        }
    }
}

/// A scene document: `integrator`, the camera `cam` with a box filter (independent pixels,
/// so per-pixel tests apply), and `body`.
pub fn cam_scene_xml(integrator: &str, cam: Cam, body: &str) -> String {
    let Cam {
        origin: [ox, oy, oz],
        target: [tx, ty, tz],
        up: [ux, uy, uz],
        fov,
        res,
        near,
        far,
    } = cam;
    format!(
        r#"<scene version="3.0.0">
    {integrator}
    <sensor type="perspective">
        <float name="fov" value="{fov}"/>
        <float name="near_clip" value="{near:e}"/>
        <float name="far_clip" value="{far:e}"/>
        <transform name="to_world"><lookat origin="{ox:e}, {oy:e}, {oz:e}" target="{tx:e}, {ty:e}, {tz:e}" up="{ux}, {uy}, {uz}"/></transform>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
        <film type="hdrfilm"><integer name="width" value="{res}"/><integer name="height" value="{res}"/><rfilter type="box"/></film>
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

/// One pixel's comparison for [`assert_pixels_agree`]: per channel the difference, its
/// estimated variance and a tolerated known bias (0 but for documented deficits), and the
/// pixel's magnitude.
pub struct PixelDiff {
    pub d: [f64; 3],
    pub var: [f64; 3],
    pub slack: [f64; 3],
    pub scale: f64,
}

impl PixelDiff {
    /// Each pixel of `film` against `expected(pixel index)`, tolerating a known relative
    /// bias of up to `slack`.
    pub fn against(film: &Film, expected: impl Fn(usize) -> [f32; 3], slack: f64) -> Vec<Self> {
        let (m, v) = (film.mean_rgb(), film.variance_rgb());
        (0..m.len())
            .map(|i| {
                let e = expected(i);
                PixelDiff {
                    d: [0, 1, 2].map(|c| (m[i][c] - e[c]) as f64),
                    var: [0, 1, 2].map(|c| v[i][c] as f64),
                    slack: e.map(|x| slack * x.abs() as f64),
                    scale: e.iter().fold(0.0f32, |a, b| a.max(b.abs())) as f64,
                }
            })
            .collect()
    }

    /// Two films of the same expected image, pixel by pixel (the variances add).
    pub fn between(a: &Film, b: &Film) -> Vec<Self> {
        let (ma, va, mb, vb) = (
            a.mean_rgb(),
            a.variance_rgb(),
            b.mean_rgb(),
            b.variance_rgb(),
        );
        assert_eq!(ma.len(), mb.len());
        (0..ma.len())
            .map(|i| PixelDiff {
                d: [0, 1, 2].map(|c| (ma[i][c] - mb[i][c]) as f64),
                var: [0, 1, 2].map(|c| (va[i][c] + vb[i][c]) as f64),
                slack: [0.0; 3],
                scale: ma[i]
                    .iter()
                    .chain(&mb[i])
                    .fold(0.0f32, |x, y| x.max(y.abs())) as f64,
            })
            .collect()
    }
}

/// How many pixels may fail the per-pixel test of [`assert_pixels_agree`].
#[derive(Clone, Copy, Debug)]
pub enum FailureCap {
    /// 1 % of the pixels (about ten times the 0.3 % expected under the null hypothesis).
    OnePercent,
    /// [`binomial_failure_cap`]: the count itself tested at the 1e-4 level, never below 1 %.
    Binomial,
}

impl FailureCap {
    pub fn of(self, pixels: usize) -> usize {
        match self {
            FailureCap::OnePercent => pixels / 100,
            FailureCap::Binomial => binomial_failure_cap(pixels),
        }
    }
}

/// Largest number of pixels that may fail the per-pixel test: the smallest `k` with
/// P(X > k) < 1e-4 for X ~ Binomial(n, 0.003) (3 channels at the 0.001 level), so the count
/// itself is tested at the 1e-4 level; never below 1 % of the pixels (low-spp variance
/// estimates of heavy-tailed estimators run small).
pub fn binomial_failure_cap(n: usize) -> usize {
    let p = 0.003f64;
    let mut pmf = (1.0 - p).powi(n as i32); // P(X = 0)
    let mut cdf = pmf;
    let mut k = 0usize;
    while 1.0 - cdf >= 1e-4 {
        pmf *= (n - k) as f64 / (k + 1) as f64 * p / (1.0 - p);
        cdf += pmf;
        k += 1;
    }
    k.max(n / 100)
}

/// Which image-mean tests [`assert_pixels_agree`] makes, each at 4 standard errors.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum MeanTest {
    /// Each channel's mean difference (two-sided ~6.3e-5 per channel).
    PerChannel,
    /// Also the mean over all channels against the standard error of the sum, which treats
    /// the channels as independent: where they are correlated (grey scenes) that test is
    /// stricter (down to ~2.3 standard errors of one channel).
    PerChannelAndPooled,
}

/// The per-pixel statistical test of an image against a known image or another render.
///
/// Significance levels: per pixel and channel, a difference `d` (less the tolerated bias)
/// with estimated variance `v` fails when |d| / sqrt(v) exceeds the two-sided **0.001**
/// quantile (differences at float-rounding level, 1e-5 relative to the pixel's magnitude or
/// 1, pass; beyond that a zero variance cannot explain them, so zero-variance pixels must be
/// exact). At most `cap` pixels may fail (1 % of them, or a count tested at the **1e-4**
/// level, see [`FailureCap`]). The image mean of the differences must be within **4
/// standard errors** (two-sided ~6.3e-5) plus the mean tolerated bias (and 1e-6 for
/// rounding), per channel and, with [`MeanTest::PerChannelAndPooled`], over all channels.
pub fn assert_pixels_agree(diffs: &[PixelDiff], cap: FailureCap, mean: MeanTest, what: &str) {
    let z = z_two_sided(0.001);
    let (mut fails, mut examples) = (0usize, Vec::new());
    // Per channel: sums of the differences, variances and tolerated biases.
    let (mut dsum, mut vsum, mut slack) = ([0.0f64; 3], [0.0f64; 3], [0.0f64; 3]);
    for (i, p) in diffs.iter().enumerate() {
        let mut bad = false;
        for c in 0..3 {
            let (v, s) = (p.var[c], p.slack[c]);
            let d = p.d[c].signum() * (p.d[c].abs() - s).max(0.0);
            dsum[c] += p.d[c];
            vsum[c] += v;
            slack[c] += s;
            bad |= d.abs() > 1e-5 * p.scale.max(1.0) && (v <= 0.0 || d.abs() / v.sqrt() > z);
        }
        if bad && examples.len() < 8 {
            examples.push(format!(
                "pixel {i}: d {:?} sd {:?}",
                p.d,
                p.var.map(f64::sqrt)
            ));
        }
        fails += bad as usize;
    }
    let k = cap.of(diffs.len());
    assert!(
        fails <= k,
        "{what}: {fails} of {} pixels fail at the 0.001 level (at most {k}, {cap:?}): {examples:?}",
        diffs.len()
    );
    let n = diffs.len() as f64;
    let mut sums: Vec<(String, f64, f64, f64, f64)> = (0..3)
        .map(|c| (format!("channel {c}"), dsum[c], vsum[c], slack[c], n))
        .collect();
    if mean == MeanTest::PerChannelAndPooled {
        let total = |x: [f64; 3]| x.iter().sum::<f64>();
        let all = (
            "all channels".to_string(),
            total(dsum),
            total(vsum),
            total(slack),
            3.0 * n,
        );
        sums.push(all);
    }
    for (which, d, v, s, count) in sums {
        let se = v.sqrt();
        assert!(
            d.abs() <= 4.0 * se + s + 1e-6 * count,
            "{what}: {which}: mean difference {} (se {}, tolerated bias {})",
            d / count,
            se / count,
            s / count
        );
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
    let (resx, resy) = (res.0.to_string(), res.1.to_string());
    let defines = [
        ("integrator", "guided_path"),
        ("resx", resx.as_str()),
        ("resy", resy.as_str()),
    ];
    build_scene(&project_scene("door-ajar"), &defines)
}

pub use pathfarm_testkit::TestRng;
