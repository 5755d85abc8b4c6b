//! The farm with real processes on 127.0.0.1: a coordinator, worker processes and
//! `pathfarm submit`, against `pathfarm render` of the same job. Every process is killed
//! and reaped when its guard drops (also when a test fails), every wait is bounded.

use std::collections::BTreeSet;
use std::fs;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::common::*;

pub(super) const TOKEN: &str = "farm-test-token-7f3a";

/// A free loopback port (bound, read, released; the coordinator binds it right after).
pub(super) fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port()
}

/// A coordinator and its workers.
pub(super) struct Farm {
    pub(super) url: String,
    pub(super) data: PathBuf,
    coordinator: Option<Running>,
    pub(super) workers: Vec<Running>,
    port: u16,
    /// With TLS: the CA certificate, the coordinator's certificate and key (PEM files).
    tls: Option<TlsFiles>,
}

pub(super) struct TlsFiles {
    pub(super) ca: PathBuf,
    pub(super) cert: PathBuf,
    pub(super) key: PathBuf,
}

impl TlsFiles {
    /// A CA and a certificate it signs for localhost and 127.0.0.1, made now, written to `dir`.
    pub(super) fn make(dir: &Path) -> TlsFiles {
        use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, KeyPair};
        let mut ca_params = CertificateParams::new(Vec::<String>::new()).unwrap();
        ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        // (a name of its own: OpenSSL, curl's, takes a leaf whose issuer is named as the
        // leaf itself for a self-signed one)
        (ca_params.distinguished_name).push(DnType::CommonName, "pathfarm test CA");
        let ca_key = KeyPair::generate().unwrap();
        let ca = ca_params.self_signed(&ca_key).unwrap();
        let names = vec!["localhost".to_string(), "127.0.0.1".to_string()];
        let key = KeyPair::generate().unwrap();
        let cert = CertificateParams::new(names)
            .unwrap()
            .signed_by(&key, &ca, &ca_key)
            .unwrap();
        let files = TlsFiles {
            ca: dir.join("ca.pem"),
            cert: dir.join("coordinator.pem"),
            key: dir.join("coordinator-key.pem"),
        };
        fs::write(&files.ca, ca.pem()).unwrap();
        fs::write(&files.cert, cert.pem()).unwrap();
        fs::write(&files.key, key.serialize_pem()).unwrap();
        files
    }
}

impl Farm {
    pub(super) fn start(tag: &str, workers: usize) -> Farm {
        Farm::start_with(tag, workers, Security::Plain)
    }

    fn start_with(tag: &str, workers: usize, security: Security) -> Farm {
        Farm::start_full(tag, workers, security, &[])
    }

    /// A farm whose coordinator is started with `extra` arguments.
    pub(super) fn start_args(tag: &str, workers: usize, extra: &[&str]) -> Farm {
        Farm::start_full(tag, workers, Security::Plain, extra)
    }

    fn start_full(tag: &str, workers: usize, security: Security, extra: &[&str]) -> Farm {
        let data = temp_dir(&format!("farm-{tag}"));
        let port = free_port();
        let tls = (security == Security::Tls).then(|| TlsFiles::make(&data));
        let scheme = if tls.is_some() {
            "https://localhost"
        } else {
            "http://127.0.0.1"
        };
        let mut farm = Farm {
            url: format!("{scheme}:{port}"),
            data,
            coordinator: None,
            workers: Vec::new(),
            port,
            tls,
        };
        farm.start_coordinator_with(extra);
        for _ in 0..workers {
            farm.add_worker();
        }
        farm
    }

    fn start_coordinator_with(&mut self, extra: &[&str]) {
        let listen = format!("127.0.0.1:{}", self.port);
        let data = self.data.join("coordinator");
        let mut args = vec![
            "coordinator",
            "--listen",
            &listen,
            "--data",
            path_str(&data),
        ];
        args.extend_from_slice(extra);
        if let Some(t) = &self.tls {
            args.extend([
                "--tls-cert",
                path_str(&t.cert),
                "--tls-key",
                path_str(&t.key),
            ]);
        }
        self.coordinator = Some(Running::start(&args, &[("PATHFARM_TOKEN", TOKEN)]));
        self.wait_listening();
    }

    /// The environment of a process talking to the coordinator: the token, and the CA
    /// certificate with TLS.
    fn client_env(&self) -> Vec<(&'static str, String)> {
        let mut env = vec![("PATHFARM_TOKEN", TOKEN.to_string())];
        if let Some(t) = &self.tls {
            env.push(("PATHFARM_TLS_CA", path_str(&t.ca).to_string()));
        }
        env
    }

    /// Starts `pathfarm ARGS` talking to this farm ([`Farm::client_env`], with `extra_env`
    /// replacing or adding variables).
    pub(super) fn start_client(&self, args: &[&str], extra_env: &[(&str, &str)]) -> Running {
        let base = self.client_env();
        let mut env: Vec<(&str, &str)> = base.iter().map(|(k, v)| (*k, v.as_str())).collect();
        for (k, v) in extra_env {
            env.retain(|(key, _)| key != k);
            env.push((k, v));
        }
        Running::start(args, &env)
    }

    pub(super) fn add_worker(&mut self) {
        self.add_worker_env(&[]);
    }

    /// Starts another worker, with `extra_env` in its environment.
    fn add_worker_env(&mut self, extra_env: &[(&str, &str)]) {
        let n = self.workers.len();
        let cache = self.data.join(format!("worker-{n}"));
        let args = [
            "worker",
            "--coordinator",
            &self.url,
            "--threads",
            "1",
            "--cache",
            path_str(&cache),
        ];
        let worker = self.start_client(&args, extra_env);
        self.workers.push(worker);
    }

    /// Waits (at most 30 s) until the coordinator has registered `n` workers (from its log).
    pub(super) fn wait_registered(&self, n: usize) {
        let t0 = Instant::now();
        let c = self.coordinator.as_ref().expect("a running coordinator");
        while c.stderr_text().matches("worker registered").count() < n {
            let late = t0.elapsed() > Duration::from_secs(30);
            assert!(
                !late,
                "{n} workers not registered after 30 s\n{}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Waits (at most 30 s) until the coordinator accepts connections.
    fn wait_listening(&mut self) {
        let t0 = Instant::now();
        while std::net::TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            let c = self.coordinator.as_mut().unwrap();
            if let Some(status) = c.poll() {
                panic!("coordinator exited: {status:?}\n{}", c.stderr_text());
            }
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "coordinator not listening after 30 s:\n{}",
                c.stderr_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    pub(super) fn logs(&self) -> String {
        let mut out = String::new();
        if let Some(c) = &self.coordinator {
            out += &format!("--- coordinator\n{}\n", c.stderr_text());
        }
        for (i, w) in self.workers.iter().enumerate() {
            out += &format!("--- worker {i}\n{}\n", w.stderr_text());
        }
        out
    }

    /// Blobs in the coordinator's store.
    fn blob_count(&self) -> usize {
        fs::read_dir(self.data.join("coordinator").join("blobs"))
            .map(|d| d.count())
            .unwrap_or(0)
    }
}

impl Drop for Farm {
    fn drop(&mut self) {
        self.workers.clear();
        self.coordinator = None;
        let _ = fs::remove_dir_all(&self.data);
    }
}

/// The job the tests render: the shipped door-ajar scene (gaussian filter: tiles need their
/// halo) with guided_path's pathfarm preset, small, an spp budget.
pub(super) fn job_args(spp: u32) -> Vec<String> {
    job_args_seeded(spp, 5)
}

/// [`job_args`] with another seed.
fn job_args_seeded(spp: u32, seed: u64) -> Vec<String> {
    let scene = project_scene("door-ajar");
    let mut v: Vec<String> = vec![scene.to_str().unwrap().to_string()];
    for d in ["integrator=guided_path", "resx=40", "resy=24"] {
        v.push("-D".into());
        v.push(d.into());
    }
    v.extend([
        "--spp".into(),
        spp.to_string(),
        "--seed".into(),
        seed.to_string(),
    ]);
    v
}

/// `pathfarm render` of the job: the reference EXR's bytes.
fn render_reference(dir: &Path, spp: u32) -> Vec<u8> {
    render_reference_seeded(dir, spp, 5)
}

/// [`render_reference`] with another seed.
fn render_reference_seeded(dir: &Path, spp: u32, seed: u64) -> Vec<u8> {
    let out = dir.join(format!("render-{seed}.exr"));
    let mut args: Vec<String> = vec!["render".into()];
    args.extend(job_args_seeded(spp, seed));
    args.extend(["--no-png".into(), "-o".into(), path_str(&out).to_string()]);
    let argv = as_strs(&args);
    let r = Running::start(&argv, &[]).wait(Duration::from_secs(300));
    assert!(r.status.success(), "render: {}", r.describe());
    fs::read(&out).expect("reference EXR")
}

/// Runs `pathfarm ARGS` (at most 60 s) with the farm's token and nothing else from the farm's
/// client environment (no TLS CA certificate).
fn with_token(args: &[&str]) -> Ended {
    Running::start(args, &[("PATHFARM_TOKEN", TOKEN)]).wait(Duration::from_secs(60))
}

pub(super) fn submit(farm: &Farm, spp: u32, out: &Path, extra_env: &[(&str, &str)]) -> Running {
    submit_seeded(farm, spp, 5, out, extra_env)
}

/// [`submit`] with another seed.
fn submit_seeded(
    farm: &Farm,
    spp: u32,
    seed: u64,
    out: &Path,
    extra_env: &[(&str, &str)],
) -> Running {
    let mut args: Vec<String> = vec!["submit".into()];
    args.extend(job_args_seeded(spp, seed));
    args.extend([
        "--coordinator".into(),
        farm.url.clone(),
        "--tile".into(),
        "8".into(),
        "--wait".into(),
        "-o".into(),
        path_str(out).to_string(),
    ]);
    let argv = as_strs(&args);
    farm.start_client(&argv, extra_env)
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Security {
    Plain,
    Tls,
}

/// Tiles worker `i` has had accepted so far (from its log: "... N tiles accepted" per
/// upload).
fn tiles_accepted(farm: &Farm, i: usize) -> usize {
    let log = farm.workers[i].stderr_text();
    let count = |line: &str| -> Option<usize> {
        let (head, _) = line.split_once(" tiles accepted")?;
        head.rsplit(' ').next()?.parse().ok()
    };
    log.lines().filter_map(count).sum()
}

/// Checkpoints the coordinator has recorded so far (from its log).
fn checkpoints_recorded(farm: &Farm) -> usize {
    let c = farm.coordinator.as_ref().expect("a running coordinator");
    c.stderr_text().matches("checkpoint recorded").count()
}

/// Waits (at most 120 s) until worker 0 has had `n` tiles accepted, failing if the job
/// `run` ends first (then the fault would come too late to test anything).
fn wait_for_tiles(farm: &Farm, run: &mut Running, n: usize, what: &str) {
    let t0 = Instant::now();
    while tiles_accepted(farm, 0) < n {
        assert!(run.poll().is_none(), "the job ended before {what}");
        let late = t0.elapsed() > Duration::from_secs(120);
        assert!(!late, "no tiles\n{}", farm.logs());
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Waits (at most 300 s) for `pathfarm submit --wait` to end, and checks it succeeded.
pub(super) fn wait_for_job(mut run: Running, farm: &Farm) {
    let t0 = Instant::now();
    while run.poll().is_none() {
        let late = t0.elapsed() > Duration::from_secs(300);
        assert!(!late, "job did not finish\n{}", farm.logs());
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_submitted(&run.wait(Duration::from_secs(1)), farm, "submit");
}

/// Checks that a `pathfarm submit` run (`what`) succeeded, showing the farm's logs if not.
fn assert_submitted(ended: &Ended, farm: &Farm, what: &str) {
    let ok = ended.status.success();
    assert!(ok, "{what}: {}\n{}", ended.describe(), farm.logs());
}

/// Submits the job (at `spp`, into `out`), waits for it (at most 300 s) and checks that it
/// succeeded.
pub(super) fn submit_ok(farm: &Farm, spp: u32, out: &Path, what: &str) -> Ended {
    let ended = submit(farm, spp, out, &[]).wait(Duration::from_secs(300));
    assert_submitted(&ended, farm, what);
    ended
}

/// Renders the job's reference (`spp`), submits the job to `farm` into `out_name` in the
/// farm's directory, and waits until worker 0 has had `tiles` more tiles accepted (`what`:
/// the fault about to be injected). Returns the reference's bytes, the output path and the
/// running `submit`.
fn job_under_way(
    farm: &Farm,
    spp: u32,
    out_name: &str,
    tiles: usize,
    what: &str,
) -> (Vec<u8>, PathBuf, Running) {
    let reference = render_reference(&farm.data, spp);
    let out = farm.data.join(out_name);
    let mut run = submit(farm, spp, &out, &[]);
    let before = tiles_accepted(farm, 0);
    wait_for_tiles(farm, &mut run, before + tiles, what);
    (reference, out, run)
}

fn assert_same_exr(got: &Path, reference: &[u8], farm: &Farm) {
    let bytes = fs::read(got).unwrap_or_else(|e| panic!("{}: {e}\n{}", got.display(), farm.logs()));
    // The EXR encoding is deterministic: equal files mean equal pixel bits.
    if bytes != reference {
        let kept = got.with_extension("reference.exr");
        fs::write(&kept, reference).expect("the reference beside the farm's EXR");
        panic!(
            "the farm's EXR differs from pathfarm render's: {}\n{}",
            pixels_that_differ(got, &kept),
            farm.logs()
        );
    }
}

/// Which pixels of two EXRs differ: their count and bounding box, so a failure tells one
/// tile's bits apart from a whole image's (another tree or estimate).
fn pixels_that_differ(a: &Path, b: &Path) -> String {
    let read = |p: &Path| pathfarm_render::output::read_exr_rgb(p).map_err(|e| e.to_string());
    let ((w, h, x), (w2, h2, y)) = match (read(a), read(b)) {
        (Ok(a), Ok(b)) => (a, b),
        (a, b) => return format!("unreadable: {:?} {:?}", a.err(), b.err()),
    };
    if (w, h) != (w2, h2) {
        return format!("sizes {w}x{h} and {w2}x{h2}");
    }
    let bits = |p: &[f32; 3]| p.map(f32::to_bits);
    let differ: Vec<(u32, u32)> = (x.iter().zip(&y).enumerate())
        .filter(|(_, (p, q))| bits(p) != bits(q))
        .map(|(i, _)| (i as u32 % w, i as u32 / w))
        .collect();
    let (xs, ys) = (differ.iter().map(|d| d.0), differ.iter().map(|d| d.1));
    let (x0, x1) = (xs.clone().min(), xs.max());
    let (y0, y1) = (ys.clone().min(), ys.max());
    format!(
        "{} of {w}x{h} pixels differ, in x {x0:?}..={x1:?}, y {y0:?}..={y1:?} ({} beside it)",
        differ.len(),
        b.display()
    )
}

#[test]
fn three_worker_cluster_renders_bit_identical_to_render() {
    let mut farm = Farm::start("three", 3);
    let reference = render_reference(&farm.data, 24);
    // The job must come to a farm whose workers are all there: a worker that registers
    // later has no scene to build ahead.
    farm.wait_registered(3);
    let out = farm.data.join("farm.exr");
    submit_ok(&farm, 24, &out, "submit");
    assert_same_exr(&out, &reference, &farm);
    assert!(
        out.with_extension("png").exists(),
        "a PNG preview beside the EXR"
    );
    // the workers all took part, and none died
    for w in &mut farm.workers {
        assert!(w.poll().is_none(), "a worker exited");
    }
    // The job came to an idle farm: every worker built its scene on the coordinator's
    // Prefetch while the job was validated, and its first lease took that scene (the
    // image above is bit-identical all the same). The bundle's files were laid out only
    // to be read: nothing is left of them in the workers' caches.
    for (i, w) in farm.workers.iter().enumerate() {
        let log = w.stderr_text();
        assert!(
            log.contains("built ahead in") && log.contains("its scene was built ahead"),
            "worker {i} built the scene ahead and used it:\n{}",
            farm.logs()
        );
        let bundles = farm.data.join(format!("worker-{i}")).join("bundles");
        let left: Vec<_> = fs::read_dir(&bundles).unwrap().collect();
        assert!(left.is_empty(), "{}: {left:?}", bundles.display());
    }
}

/// Four jobs of one scene (seeds 1 to 4) submitted together to two workers: the coordinator
/// interleaves their tiles, and each worker builds the scene once and serves every job from
/// it (the jobs share it: same bundle and settings, seed aside); every image is the one
/// `pathfarm render` gives for its seed.
#[test]
fn workers_serving_several_jobs_at_once_build_each_scene_once_and_every_image_is_exact() {
    // (With checkpoints an hour apart, none is written: the restart test checks that one is
    // written with checkpoints at every iteration's end.)
    let farm = Farm::start_args("several", 2, &["--checkpoint-interval-s", "3600"]);
    let seeds = [1u64, 2, 3, 4];
    let spp = 16;
    let refs: Vec<Vec<u8>> = (seeds.iter())
        .map(|&s| render_reference_seeded(&farm.data, spp, s))
        .collect();
    let outs: Vec<PathBuf> = (seeds.iter())
        .map(|s| farm.data.join(format!("several-{s}.exr")))
        .collect();
    let runs: Vec<Running> = (seeds.iter().zip(&outs))
        .map(|(&s, out)| submit_seeded(&farm, spp, s, out, &[]))
        .collect();
    for run in runs {
        wait_for_job(run, &farm);
    }
    for (out, reference) in outs.iter().zip(&refs) {
        assert_same_exr(out, reference, &farm);
    }
    assert_eq!(checkpoints_recorded(&farm), 0, "{}", farm.logs());
    let mut jobs_served = 0;
    for (i, w) in farm.workers.iter().enumerate() {
        let log = w.stderr_text();
        let builds = log.matches("built ahead in").count() + log.matches("scene built in").count();
        assert!(
            builds <= 1,
            "worker {i} built the scene {builds} times:\n{}",
            farm.logs()
        );
        let served: BTreeSet<&str> = (log.lines())
            .filter(|l| l.contains(": rendered unit"))
            .filter_map(|l| l.split("(job ").nth(1)?.split(')').next())
            .collect();
        jobs_served += served.len();
    }
    assert!(
        jobs_served > seeds.len(),
        "a worker served more than one job ({jobs_served} job-worker pairs)\n{}",
        farm.logs()
    );
}

/// A batch of frames (door-ajar with the camera moved, sharing its mesh): `pathfarm submit
/// DIR --wait -o OUT` submits every `*.xml` in DIR as a frame, uploads the shared mesh once,
/// writes each frame's EXR, equal to `pathfarm render`'s, and `pathfarm status` shows the
/// batch.
#[test]
fn a_batch_of_frames_is_submitted_together_and_every_frame_is_exact() {
    let farm = Farm::start("batch", 2);
    let frames = farm.data.join("shot-7");
    fs::create_dir_all(&frames).unwrap();
    let src = project_scene("door-ajar");
    let dir = src.parent().unwrap();
    fs::copy(dir.join("icosphere.obj"), frames.join("icosphere.obj")).unwrap();
    let xml = fs::read_to_string(&src).unwrap();
    let origin = r#"origin="0.4, 1.3, 3.6""#;
    assert!(xml.contains(origin));
    let (spp, seed) = (16, 5);
    let defines = ["integrator=guided_path", "resx=40", "resy=24"];
    let mut refs = Vec::new();
    for (i, x) in ["0.4", "0.5", "0.6"].iter().enumerate() {
        let frame = frames.join(format!("frame-{}.xml", i + 1));
        fs::write(
            &frame,
            xml.replace(origin, &format!(r#"origin="{x}, 1.3, 3.6""#)),
        )
        .unwrap();
        let out = farm.data.join(format!("ref-{}.exr", i + 1));
        let mut args: Vec<String> = vec!["render".into(), path_str(&frame).into()];
        for d in defines {
            args.extend(["-D".into(), d.into()]);
        }
        args.extend(
            [
                "--spp",
                &spp.to_string(),
                "--seed",
                &seed.to_string(),
                "--no-png",
                "-o",
            ]
            .map(String::from),
        );
        args.push(path_str(&out).into());
        let r = Running::start(&as_strs(&args), &[]).wait(Duration::from_secs(300));
        assert!(r.status.success(), "render: {}", r.describe());
        refs.push(fs::read(&out).unwrap());
    }
    assert_ne!(refs[0], refs[1], "the frames differ");
    let out = farm.data.join("shot-7-out");
    let mut args: Vec<String> = vec!["submit".into(), path_str(&frames).into()];
    for d in defines {
        args.extend(["-D".into(), d.into()]);
    }
    args.extend(["--spp", &spp.to_string(), "--seed", &seed.to_string()].map(String::from));
    args.extend([
        "--coordinator".into(),
        farm.url.clone(),
        "--tile".into(),
        "8".into(),
    ]);
    args.extend(["--wait".into(), "-o".into(), path_str(&out).into()]);
    let ended = farm
        .start_client(&as_strs(&args), &[])
        .wait(Duration::from_secs(300));
    assert_submitted(&ended, &farm, "submit of a batch");
    assert!(
        ended.stderr.contains("batch shot-7: 3 frames submitted"),
        "{}",
        ended.describe()
    );
    // The mesh the frames share went up with the first frame only.
    let uploads: Vec<&str> = (ended.stderr.lines())
        .filter(|l| l.contains("uploaded") && l.contains("of 2 files"))
        .collect();
    assert_eq!(uploads.len(), 3, "{}", ended.describe());
    assert!(uploads[0].contains("uploaded 2 of 2"), "{uploads:?}");
    assert!(
        uploads[1..].iter().all(|l| l.contains("uploaded 1 of 2")),
        "{uploads:?}"
    );
    for (i, reference) in refs.iter().enumerate() {
        assert_same_exr(&out.join(format!("frame-{}.exr", i + 1)), reference, &farm);
    }
    // The frames share a world: a worker builds it from the files once and each other frame
    // on it (a second build can only race with a build ahead of the lease).
    let (mut worlds, mut on_held) = (0, 0);
    for (i, w) in farm.workers.iter().enumerate() {
        let log = w.stderr_text();
        let built = log.matches("world built in").count();
        assert!(
            built <= 2,
            "worker {i} built the world {built} times\n{}",
            farm.logs()
        );
        worlds += built;
        on_held += log.matches("built on the world of a scene held").count();
    }
    assert!(
        on_held >= 1 && worlds <= farm.workers.len() + 1,
        "{worlds} worlds built, {on_held} frames on a held world\n{}",
        farm.logs()
    );
    let coordinator = farm.coordinator.as_ref().unwrap().stderr_text();
    assert_eq!(
        coordinator
            .matches("validated on the world validated last")
            .count(),
        2,
        "frames 2 and 3 are validated on frame 1's world\n{}",
        farm.logs()
    );
    let status = with_token(&["status", "--coordinator", &farm.url]);
    assert!(status.status.success(), "{}", status.describe());
    assert!(
        status.stdout.contains("batch shot-7: 3 frames (3 done)"),
        "{}",
        status.describe()
    );
    // The same frames again as a long batch: its priority changed and cancelled batch-wide.
    let mut args: Vec<String> = vec!["submit".into(), path_str(&frames).into()];
    for d in defines {
        args.extend(["-D".into(), d.into()]);
    }
    args.extend(["--spp", "100000", "--batch", "long-7", "--coordinator"].map(String::from));
    args.push(farm.url.clone());
    let submitted = with_token(&as_strs(&args));
    assert!(submitted.status.success(), "{}", submitted.describe());
    let batch = |verb: &[&str]| {
        let mut a = verb.to_vec();
        a.extend(["--batch", "long-7", "--coordinator", &farm.url]);
        with_token(&a)
    };
    let p = batch(&["priority", "3"]);
    assert!(p.status.success(), "{}", p.describe());
    assert_eq!(
        p.stdout.matches(": priority 3").count(),
        3,
        "{}",
        p.describe()
    );
    let c = batch(&["cancel"]);
    assert!(c.status.success(), "{}", c.describe());
    assert_eq!(
        c.stdout.matches(": cancelled").count(),
        3,
        "{}",
        c.describe()
    );
    let status = with_token(&["status", "--coordinator", &farm.url]);
    assert!(
        status
            .stdout
            .contains("batch long-7: 3 frames (3 cancelled)"),
        "{}",
        status.describe()
    );
    // Nothing left to cancel; an unknown batch is an error naming it.
    let again = batch(&["cancel"]);
    assert!(
        again.status.success() && again.stdout.is_empty(),
        "{}",
        again.describe()
    );
    let unknown = with_token(&["cancel", "--batch", "nope", "--coordinator", &farm.url]);
    assert!(!unknown.status.success());
    assert!(
        unknown.stderr.contains("--batch nope: no such batch"),
        "{}",
        unknown.describe()
    );
}

/// The benchmark swarm (`bench/farm_swarm.py`): one process of three simulated workers
/// (`--instances 3 --simulate-seconds-per-sample 0`) registers three workers that take the
/// job's tiles between them (each its own control stream and upload key), and the job
/// completes with every tile accepted, its image black (the simulation renders nothing).
#[test]
fn a_swarm_of_simulated_workers_in_one_process_completes_a_job() {
    let mut farm = Farm::start("swarm", 0);
    let cache = farm.data.join("swarm");
    let args = [
        "worker",
        "--coordinator",
        &farm.url,
        "--threads",
        "1",
        "--cache",
        path_str(&cache),
        "--instances",
        "3",
        "--simulate-seconds-per-sample",
        "0",
    ];
    let swarm = farm.start_client(&args, &[("RUST_LOG", "info")]);
    farm.workers.push(swarm);
    farm.wait_registered(3);
    let out = farm.data.join("swarm.exr");
    submit_ok(&farm, 8, &out, "the swarm's job");
    let log = farm.workers[0].stderr_text();
    let names: BTreeSet<&str> = (log.lines())
        .filter(|l| l.contains("tiles accepted"))
        .filter_map(|l| {
            l.split("name=sim-")
                .nth(1)?
                .split(|c: char| !c.is_ascii_digit())
                .next()
        })
        .collect();
    assert_eq!(names.len(), 3, "tiles from every instance\n{}", farm.logs());
    let (_, _, image) = pathfarm_render::output::read_exr_rgb(&out).expect("the result");
    assert!(
        image.iter().all(|p| *p == [0.0; 3]),
        "a simulated render is black\n{}",
        farm.logs()
    );
}

#[test]
fn worker_killed_mid_iteration_still_gives_bit_identical_image() {
    let mut farm = Farm::start("kill", 2);
    // Kill one worker in the middle of the job, once it has delivered tiles (its leases in
    // flight must go to the others).
    let (reference, out, mut run) =
        job_under_way(&farm, 64, "farm.exr", 5, "a worker could be killed");
    assert!(
        run.poll().is_none(),
        "the job must still be running when the worker dies"
    );
    farm.workers[0].signal(libc::SIGKILL);
    farm.add_worker();
    wait_for_job(run, &farm);
    assert_same_exr(&out, &reference, &farm);
}

#[test]
fn a_worker_paused_past_the_heartbeat_timeout_registers_again_and_the_job_completes_bit_identical()
{
    // SIGSTOP for twice the heartbeat timeout is what a VM stall, a long swap or a network
    // partition does: the coordinator declares the worker lost and ends its stream; once
    // resumed, the worker registers again, is offered work, and the one-worker farm
    // finishes the job with the one-process bits.
    let mut farm = Farm::start("pause", 0);
    farm.coordinator = None;
    farm.start_coordinator_with(&["--heartbeat-timeout-s", "2"]);
    farm.add_worker();
    let (reference, out, run) = job_under_way(&farm, 64, "pause.exr", 3, "the worker paused");
    farm.workers[0].signal(libc::SIGSTOP);
    std::thread::sleep(Duration::from_secs(4));
    farm.workers[0].signal(libc::SIGCONT);
    wait_for_job(run, &farm);
    assert_same_exr(&out, &reference, &farm);
    let w = farm.workers[0].stderr_text();
    assert!(w.contains("declared lost"), "the coordinator told it\n{w}");
    assert!(
        w.matches("registered with").count() >= 2,
        "registered again\n{w}"
    );
}

#[test]
fn a_worker_that_lost_its_records_rolls_the_job_back_and_the_image_stays_bit_identical() {
    // Worker 0 answers its first FlushRecords with "lost" (fault injection), as a worker
    // whose kept quadtree records were spoiled would: the coordinator starts the job again
    // from its last checkpoint under a new records epoch, and the result is still exact.
    let mut farm = Farm::start("lose", 0);
    farm.add_worker_env(&[("PATHFARM_FAULT_LOSE_RECORDS", "1")]);
    farm.add_worker();
    let reference = render_reference(&farm.data, 24);
    let out = farm.data.join("lose.exr");
    wait_for_job(submit(&farm, 24, &out, &[]), &farm);
    assert_same_exr(&out, &reference, &farm);
    let c = farm.coordinator.as_ref().expect("a running coordinator");
    assert!(
        c.stderr_text()
            .contains("rolling back to the last checkpoint"),
        "the job rolled back\n{}",
        farm.logs()
    );
    let w = farm.workers[0].stderr_text();
    assert!(
        w.contains("told the coordinator the records are lost"),
        "{w}"
    );
    assert!(
        w.contains("records uploaded"),
        "later flushes were answered\n{w}"
    );
}

#[test]
fn records_that_miss_an_accepted_upload_are_refused_by_their_coverage_and_the_image_stays_bit_identical(
) {
    // The one worker forgets the records of one accepted recording upload that joins
    // records it keeps and hands in the rest as if complete (fault injection), as a worker
    // with a bookkeeping slip would: the sums decode, only the leases they cover tell. The
    // coordinator refuses them, blames the worker (one bad result, under the limit) and
    // rolls the job back; the result is still exact.
    let mut farm = Farm::start("forget", 0);
    farm.add_worker_env(&[("PATHFARM_FAULT_FORGET_RECORDS", "1")]);
    // (64 spp: iterations of several recorded passes, so a worker keeps several uploads')
    let reference = render_reference(&farm.data, 64);
    let out = farm.data.join("forget.exr");
    wait_for_job(submit(&farm, 64, &out, &[]), &farm);
    assert_same_exr(&out, &reference, &farm);
    let c = farm.coordinator.as_ref().expect("a running coordinator");
    let log = c.stderr_text();
    let refused = log
        .lines()
        .find(|l| l.contains("rolling back to the last checkpoint"))
        .unwrap_or_else(|| panic!("the job rolled back\n{}", farm.logs()));
    assert!(
        refused.contains("records of worker") && refused.contains("accepted from it"),
        "the roll back names the coverage: {refused}"
    );
    let w = farm.workers[0].stderr_text();
    assert!(w.contains("records forgotten (fault injection)"), "{w}");
    assert!(w.contains("records refused"), "the worker was told\n{w}");
}

#[test]
fn submit_with_a_wrong_token_or_a_malformed_scene_is_refused_and_nothing_is_kept() {
    let farm = Farm::start("bad", 0);
    let out = farm.data.join("never.exr");
    let r = submit(&farm, 8, &out, &[("PATHFARM_TOKEN", "wrong")]).wait(Duration::from_secs(60));
    assert!(!r.status.success(), "a wrong token must fail");
    assert!(
        r.stderr.to_lowercase().contains("token"),
        "the error says the token is wrong: {}",
        r.stderr
    );
    let bad = write_scene(
        "farm-malformed",
        "<scene version=\"3.0.0\"><shape type=\"obj\">",
    );
    let url = farm.url.clone();
    let argv = ["submit", path_str(&bad), "--coordinator", &url];
    let r = with_token(&argv);
    assert!(!r.status.success(), "a malformed scene must fail");
    assert!(
        r.stderr
            .contains(bad.file_name().unwrap().to_str().unwrap()),
        "the error names the file: {}",
        r.stderr
    );
    assert!(!out.exists());
    assert_eq!(farm.blob_count(), 0, "nothing was stored");

    // A mesh with a NaN position: the client bundles without decoding meshes, so the
    // coordinator's validation refuses it, naming the mesh by the scene's own path for it
    // and not by the coordinator's directory; its uploaded blobs are not kept.
    let nan = write_scene(
        "farm-nan-mesh",
        r#"<scene version="3.0.0">
  <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
  <shape type="obj"><string name="filename" value="meshes/nan.obj"/></shape>
</scene>"#,
    );
    let mesh = nan.with_file_name("meshes").join("nan.obj");
    fs::create_dir_all(mesh.parent().unwrap()).unwrap();
    fs::write(&mesh, "v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
    let argv = ["submit", path_str(&nan), "--coordinator", &url];
    let r = with_token(&argv);
    assert!(!r.status.success(), "a NaN mesh must be refused");
    let coordinator_dir = farm.data.join("coordinator");
    assert!(
        r.stderr.contains("'meshes/nan.obj'")
            && !r.stderr.contains(coordinator_dir.to_str().unwrap()),
        "the error names the mesh by its bundle path: {}",
        r.stderr
    );
    // Its blobs stay for the grace period (another client may have uploaded the same
    // files for a job of its own); a coordinator with a grace period of a second then
    // deletes them.
    assert_eq!(
        farm.blob_count(),
        2,
        "the refused bundle's blobs wait out the grace period"
    );
    let mut farm = farm;
    farm.coordinator = None;
    farm.start_coordinator_with(&["--blob-grace-s", "1"]);
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    while farm.blob_count() > 0 {
        assert!(std::time::Instant::now() < deadline, "never swept");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// A PNG of `w x h` whose header is intact and whose pixel data (the IDAT chunk's) is not.
fn png_with_bad_pixels(w: u32, h: u32) -> Vec<u8> {
    let mut png = Vec::new();
    let image = image::RgbImage::from_pixel(w, h, image::Rgb([200, 100, 50]));
    (image.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png))
        .expect("encode a PNG");
    let idat = png
        .windows(4)
        .position(|c| c == b"IDAT")
        .expect("an IDAT chunk");
    png[idat + 4..idat + 10].fill(0xff);
    png
}

#[test]
fn an_image_with_bad_pixels_passes_validation_by_its_header_and_fails_the_job_on_the_worker() {
    // The coordinator's validation reads images' headers, not their pixels (it needs the
    // scene's bounds, and renders nothing): the job is accepted, and its worker, which
    // decodes the image, fails it, naming the image by the scene's own path for it.
    let farm = Farm::start("bad-image", 1);
    let scene = write_scene(
        "farm-bad-image",
        r#"<scene version="3.0.0">
  <integrator type="guided_path"/>
  <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
  <emitter type="constant"/>
  <shape type="sphere"><bsdf type="diffuse"><texture name="reflectance" type="bitmap"><string name="filename" value="textures/bad.png"/></texture></bsdf></shape>
</scene>"#,
    );
    let png = scene.with_file_name("textures").join("bad.png");
    fs::create_dir_all(png.parent().unwrap()).unwrap();
    fs::write(&png, png_with_bad_pixels(4, 4)).unwrap();
    let limits = pathfarm_scene::Limits::default();
    let geometry = pathfarm_scene::load_scene_geometry_as(&scene, &[], &limits, None);
    assert!(geometry.is_ok(), "its header is good: {:?}", geometry.err());
    let full = pathfarm_scene::load_scene(&scene, &[])
        .map(|_| ())
        .unwrap_err();
    assert!(
        full.to_string().contains("bad.png"),
        "its pixels are not: {full}"
    );
    let out = farm.data.join("bad-image.exr");
    let argv = [
        "submit",
        path_str(&scene),
        "--spp",
        "4",
        "--coordinator",
        &farm.url,
        "--wait",
        "-o",
        path_str(&out),
    ];
    let r = farm.start_client(&argv, &[]).wait(Duration::from_secs(120));
    assert!(!r.status.success(), "the job must fail: {}", r.describe());
    let worker_dir = farm.data.join("worker-0");
    // Accepted (a job id), then failed by the worker's lease (not refused at submission).
    let accepted = r.stdout.trim_start().starts_with("job-");
    assert!(
        accepted && r.stderr.contains("failed lease") && r.stderr.contains("cannot decode"),
        "accepted, then failed on the worker: {}\n{}",
        r.describe(),
        farm.logs()
    );
    assert!(
        r.stderr.contains("'textures/bad.png'") && !r.stderr.contains(worker_dir.to_str().unwrap()),
        "the failure names the image by its bundle path: {}",
        r.describe(),
    );
    assert!(!out.exists());
}

#[test]
fn coordinator_killed_mid_job_resumes_bit_identical_and_keeps_finished_results() {
    // Checkpoints at every iteration's end, so one is durable early in the job.
    let every = ["--checkpoint-interval-s", "0"];
    let mut farm = Farm::start_args("restart", 2, &every);
    // A job finished before the kill.
    let small = render_reference(&farm.data, 24);
    let first = farm.data.join("first.exr");
    let run = submit_ok(&farm, 24, &first, "submit");
    let first_id = run
        .stdout
        .split_whitespace()
        .find(|w| w.starts_with("job-"));
    let first_id = first_id
        .unwrap_or_else(|| panic!("a job id in: {}", run.stdout))
        .to_string();
    // A job in flight when the coordinator is killed, after its first iterations.
    let what = "the coordinator could be killed";
    let recorded = checkpoints_recorded(&farm);
    let (reference, out, mut run) = job_under_way(&farm, 256, "resumed.exr", 2, what);
    // The kill must come after a checkpoint of this job is durable (written in the
    // background), or there would be nothing to resume from.
    let t0 = Instant::now();
    while checkpoints_recorded(&farm) <= recorded {
        assert!(run.poll().is_none(), "the job ended before {what}");
        let late = t0.elapsed() > Duration::from_secs(120);
        assert!(!late, "no checkpoint recorded\n{}", farm.logs());
        std::thread::sleep(Duration::from_millis(10));
    }
    assert!(
        run.poll().is_none(),
        "the job must still be running at the kill"
    );
    farm.coordinator.as_mut().unwrap().signal(libc::SIGKILL);
    let dead = farm
        .coordinator
        .take()
        .unwrap()
        .wait(Duration::from_secs(10));
    assert!(!dead.status.success());
    farm.start_coordinator_with(&every);
    wait_for_job(run, &farm);
    assert_same_exr(&out, &reference, &farm);
    assert!(
        farm.logs().contains("resumed from its checkpoint"),
        "the job resumed from a checkpoint, not from the start\n{}",
        farm.logs()
    );
    // The result finished before the kill is still there.
    let fetched = farm.data.join("fetched.exr");
    let url = farm.url.clone();
    let argv = [
        "fetch",
        &first_id,
        "--coordinator",
        &url,
        "-o",
        path_str(&fetched),
    ];
    let r = with_token(&argv);
    assert!(r.status.success(), "fetch: {}", r.describe());
    assert_same_exr(&fetched, &small, &farm);
}

#[test]
fn tls_farm_renders_bit_identical_and_refuses_plain_text() {
    // A certificate made by the test: coordinator, worker and client speak TLS only.
    let mut farm = Farm::start_with("tls", 1, Security::Tls);
    let reference = render_reference(&farm.data, 8);
    let out = farm.data.join("farm.exr");
    submit_ok(&farm, 8, &out, "submit over TLS");
    assert_same_exr(&out, &reference, &farm);
    assert!(
        farm.workers[0].poll().is_none(),
        "the TLS worker is still connected"
    );
    // a plain-text client cannot talk to the TLS port
    let plain = format!("http://127.0.0.1:{}", farm.port);
    let argv = ["status", "--coordinator", &plain];
    let r = with_token(&argv);
    assert!(
        !r.status.success(),
        "plain text against TLS must fail: {}",
        r.describe()
    );
    // https without the CA certificate is refused before connecting, with the reason
    let argv = ["status", "--coordinator", &farm.url];
    let r = with_token(&argv);
    assert!(!r.status.success());
    assert!(
        r.stderr.contains("--tls-ca"),
        "names the missing flag: {}",
        r.stderr
    );
}

/// Files in the coordinator's data directory other than the job database (blobs, temporaries).
fn stored_files(farm: &Farm) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![farm.data.join("coordinator")];
    while let Some(d) = stack.pop() {
        for e in fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if !p.ends_with("jobs.redb") {
                out.push(p.display().to_string());
            }
        }
    }
    out
}

#[test]
fn bundle_over_the_size_limit_is_refused_before_anything_is_uploaded() {
    // the coordinator takes bundles of at most 2 KB: door-ajar's is larger
    let mut farm = Farm::start("limit", 0);
    farm.coordinator = None;
    let _ = fs::remove_dir_all(farm.data.join("coordinator"));
    farm.start_coordinator_with(&["--max-bundle-bytes", "2000"]);
    let out = farm.data.join("never.exr");
    let r = submit(&farm, 8, &out, &[]).wait(Duration::from_secs(60));
    assert!(!r.status.success(), "an oversized bundle must be refused");
    assert!(
        r.stderr.contains("more than") && r.stderr.contains("2000 bytes"),
        "the error names the limit: {}",
        r.stderr
    );
    assert!(
        stored_files(&farm).is_empty(),
        "stored: {:?}",
        stored_files(&farm)
    );
    assert!(!out.exists());
}

/// Registers a worker named `worker_name` of `protocol_version` and build "another-build" with
/// the coordinator at `channel`, which must refuse it; returns the reason given.
async fn refused_registration(
    channel: tonic::transport::Channel,
    protocol_version: u32,
    worker_name: &str,
) -> String {
    use pathfarm_proto::v1;
    let mut workers = v1::workers_client::WorkersClient::new(channel);
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(v1::WorkerMessage {
        msg: Some(v1::worker_message::Msg::Register(v1::Register {
            protocol_version,
            build_id: "another-build".into(),
            threads: 1,
            host_name: "test".into(),
            worker_name: worker_name.into(),
        })),
    })
    .await
    .unwrap();
    let mut req = tonic::Request::new(tokio_stream::wrappers::ReceiverStream::new(rx));
    req.metadata_mut()
        .insert("authorization", format!("Bearer {TOKEN}").parse().unwrap());
    let mut inbound = workers.control(req).await.unwrap().into_inner();
    // `tx` stays open until the answer, as a live worker's stream would.
    let first = inbound.message().await.unwrap().unwrap();
    drop(tx);
    match first.msg {
        Some(v1::coordinator_message::Msg::Refused(r)) => r.reason,
        other => panic!("{worker_name}: expected Refused, got {other:?}"),
    }
}

#[test]
fn a_client_or_worker_of_another_protocol_version_or_build_is_refused_and_nothing_is_stored() {
    use pathfarm_proto::v1;
    let farm = Farm::start("protocol", 0);
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let channel = tonic::transport::Endpoint::from_shared(farm.url.clone())
            .unwrap()
            .connect()
            .await
            .unwrap();
        let token: tonic::metadata::MetadataValue<_> = format!("Bearer {TOKEN}").parse().unwrap();
        let stamp = move |mut req: tonic::Request<()>| {
            req.metadata_mut().insert("authorization", token.clone());
            req.metadata_mut()
                .insert(pathfarm_proto::PROTOCOL_HEADER, "999".parse().unwrap());
            Ok(req)
        };
        let mut jobs = v1::jobs_client::JobsClient::with_interceptor(channel.clone(), stamp);
        let err = jobs
            .submit_job(v1::SubmitJobRequest::default())
            .await
            .expect_err("another protocol version is refused");
        assert_eq!(err.code(), tonic::Code::FailedPrecondition, "{err:?}");
        assert!(
            err.message().contains("client protocol 999"),
            "says which: {}",
            err.message()
        );
        // a worker of another protocol version is refused on Register, with the reason
        let reason = refused_registration(channel.clone(), 999, "old").await;
        assert!(reason.contains("worker protocol 999"), "{reason}");
        // the right protocol but another build: refused, saying so
        let reason = refused_registration(channel, pathfarm_proto::PROTOCOL_VERSION, "other").await;
        assert!(
            reason.contains("build mismatch") && reason.contains("another-build"),
            "{reason}"
        );
    });
    assert!(
        stored_files(&farm).is_empty(),
        "stored: {:?}",
        stored_files(&farm)
    );
}

#[test]
fn worker_on_sigterm_hands_back_its_leases_and_the_job_completes_bit_identical() {
    let mut farm = Farm::start("drain", 2);
    let (reference, out, run) =
        job_under_way(&farm, 64, "farm.exr", 3, "the worker could be stopped");
    farm.workers[0].signal(libc::SIGTERM);
    let t0 = Instant::now();
    while farm.workers[0].poll().is_none() {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "SIGTERM: the worker did not exit\n{}",
            farm.logs()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let status = farm.workers[0].poll().unwrap();
    assert!(
        status.success(),
        "a drained worker exits 0: {status:?}\n{}",
        farm.logs()
    );
    assert!(
        farm.workers[0].stderr_text().contains("drained"),
        "{}",
        farm.logs()
    );
    wait_for_job(run, &farm);
    assert_same_exr(&out, &reference, &farm);
}

#[test]
fn fault_soak_jobs_complete_bit_identical_while_workers_are_killed_and_restarted() {
    // Three jobs at once on three workers; every 100-350 ms (seeded) a random worker is
    // killed with SIGKILL and a new one started, at most 10 times. Bounded: 300 s. (The jobs
    // are sized to outlast at least three kills on a fast, idle machine.)
    let mut farm = Farm::start("soak", 3);
    let specs = [(256u32, 3u64), (384, 9), (192, 21)];
    let mut runs = Vec::new();
    for (i, &(spp, seed)) in specs.iter().enumerate() {
        let out = farm.data.join(format!("soak-{i}.exr"));
        runs.push((submit_seeded(&farm, spp, seed, &out, &[]), out, spp, seed));
    }
    let mut rng = TestRng::new(0x5eed_50a4);
    let mut kills = 0;
    let t0 = Instant::now();
    while runs.iter_mut().any(|r| r.0.poll().is_none()) {
        assert!(
            t0.elapsed() < Duration::from_secs(300),
            "soak did not finish\n{}",
            farm.logs()
        );
        std::thread::sleep(Duration::from_millis(100 + rng.below(250)));
        if kills < 10 && runs.iter_mut().any(|r| r.0.poll().is_none()) {
            let alive: Vec<usize> = (0..farm.workers.len())
                .filter(|&i| farm.workers[i].poll().is_none())
                .collect();
            let victim = alive[rng.below(alive.len() as u64) as usize];
            farm.workers[victim].signal(libc::SIGKILL);
            farm.add_worker();
            kills += 1;
        }
    }
    eprintln!(
        "soak: {kills} workers killed, jobs done in {:.1} s",
        t0.elapsed().as_secs_f64()
    );
    assert!(kills >= 3, "the soak killed {kills} workers");
    for (run, out, spp, seed) in runs {
        assert_submitted(&run.wait(Duration::from_secs(5)), &farm, "submit");
        // the reference: pathfarm render of the same job
        let reference = render_reference_seeded(&farm.data, spp, seed);
        assert_same_exr(&out, &reference, &farm);
    }
}

#[test]
fn cluster_leaves_no_process_or_directory_behind_on_success_and_on_interrupt() {
    let dir = temp_dir("cluster");
    let out = dir.join("cluster.exr");
    let mut args: Vec<String> = vec!["cluster".into(), "--workers".into(), "2".into()];
    args.extend(["--threads-per-worker".into(), "1".into()]);
    args.extend(job_args(8));
    args.extend(["-o".into(), path_str(&out).to_string()]);
    let argv = as_strs(&args);
    let tmp = dir.join("tmp");
    fs::create_dir_all(&tmp).unwrap();
    let env = [("TMPDIR", path_str(&tmp))];
    let run = Running::start(&argv, &env);
    let pid = run.pid().expect("running");
    let r = run.wait(Duration::from_secs(300));
    assert!(r.status.success(), "cluster: {}", r.describe());
    assert!(out.exists() && out.with_extension("png").exists());
    assert!(
        children_of(pid).is_empty(),
        "children left: {:?}",
        children_of(pid)
    );
    assert_eq!(
        fs::read_dir(&tmp).unwrap().count(),
        0,
        "the cluster's directory is removed"
    );
    // interrupted (Ctrl-C) once the processes are up: everything is torn down
    let out2 = dir.join("interrupted.exr");
    let n = argv.len();
    let mut argv2 = argv.clone();
    argv2[n - 1] = path_str(&out2);
    let mut run = Running::start(&argv2, &env);
    let pid = run.pid().expect("running");
    let t0 = Instant::now();
    while children_of(pid).len() < 3 {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "the cluster did not start its processes"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let kids = children_of(pid);
    run.signal(libc::SIGINT);
    let r = run.wait(Duration::from_secs(60));
    assert!(!r.status.success(), "an interrupted cluster fails");
    for k in kids {
        assert!(
            !Path::new(&format!("/proc/{k}")).exists() || is_zombie(k),
            "process {k} left behind"
        );
    }
    assert!(!out2.exists(), "no output from an interrupted cluster");
    assert_eq!(
        fs::read_dir(&tmp).unwrap().count(),
        0,
        "the cluster's directory is removed"
    );
    let _ = fs::remove_dir_all(&dir);
}

/// Pids whose parent is `pid` (from /proc).
fn children_of(pid: u32) -> Vec<u32> {
    let mut out = Vec::new();
    for e in fs::read_dir("/proc").into_iter().flatten().flatten() {
        let Ok(p) = e.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let stat = fs::read_to_string(format!("/proc/{p}/stat")).unwrap_or_default();
        // pid (comm) state ppid ...
        let after = stat.rsplit_once(')').map(|x| x.1).unwrap_or("");
        let ppid = after
            .split_whitespace()
            .nth(1)
            .and_then(|x| x.parse::<u32>().ok());
        if ppid == Some(pid) {
            out.push(p);
        }
    }
    out
}

fn is_zombie(pid: u32) -> bool {
    let stat = fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    stat.rsplit_once(')')
        .map(|x| x.1.trim_start().starts_with('Z'))
        .unwrap_or(true)
}

/// A scene naming an integrator pathfarm does not have, in a block `-D` cannot reach (no
/// `$integrator`): `--integrator guided_path` replaces it in `render` and `cluster` alike,
/// keeping `max_depth` and saying what it dropped, and the farm's image is render's.
#[test]
fn integrator_flag_replaces_the_scenes_integrator_in_render_and_cluster_alike() {
    let dir = temp_dir("integrator-flag");
    let src = project_scene("door-ajar");
    let xml = fs::read_to_string(&src).unwrap();
    let start = xml.find("<integrator").expect("an integrator block");
    let end = xml[start..].find("</integrator>").expect("closed") + start + "</integrator>".len();
    let sppm = "<integrator type=\"sppm\"><integer name=\"max_depth\" value=\"6\"/>\
                <integer name=\"photon_count\" value=\"100000\"/></integrator>";
    // The scene's directory copied (its mesh beside it), the integrator block replaced.
    for e in fs::read_dir(src.parent().unwrap()).unwrap() {
        let e = e.unwrap();
        fs::copy(e.path(), dir.join(e.file_name())).unwrap();
    }
    let scene = dir.join("scene.xml");
    fs::write(&scene, format!("{}{sppm}{}", &xml[..start], &xml[end..])).unwrap();
    let common = [
        "--integrator",
        "guided_path",
        "-D",
        "resx=40",
        "-D",
        "resy=24",
    ];
    let flags = ["--spp", "8", "--seed", "3"];
    let render_out = dir.join("render.exr");
    let mut args = vec![
        "render",
        path_str(&scene),
        "--no-png",
        "-o",
        path_str(&render_out),
    ];
    args.extend(common.iter().chain(&flags));
    let r = Running::start(&args, &[]).wait(Duration::from_secs(300));
    assert!(r.status.success(), "render: {}", r.describe());
    let cluster_out = dir.join("cluster.exr");
    let mut args = vec!["cluster", "--workers", "2", "--threads-per-worker", "1"];
    args.extend([path_str(&scene), "-o", path_str(&cluster_out)]);
    args.extend(common.iter().chain(&flags));
    let c = Running::start(&args, &[]).wait(Duration::from_secs(300));
    assert!(c.status.success(), "cluster: {}", c.describe());
    for (what, run) in [("render", &r), ("cluster", &c)] {
        let err = run.describe();
        assert!(
            err.contains("integrator 'sppm' replaced by 'guided_path'")
                && err.contains("dropped photon_count"),
            "{what} says what it replaced and dropped: {err}"
        );
    }
    assert!(
        fs::read(&cluster_out).unwrap() == fs::read(&render_out).unwrap(),
        "the cluster's image is render's"
    );
}
