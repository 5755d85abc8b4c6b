//! The farm with real processes on 127.0.0.1: a coordinator, worker processes and
//! `pathfarm submit`, against `pathfarm render` of the same job. Every process is killed
//! and reaped when its guard drops (also when a test fails), every wait is bounded.

use std::fs;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::common::*;

const TOKEN: &str = "farm-test-token-7f3a";

/// A free loopback port (bound, read, released; the coordinator binds it right after).
fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port()
}

/// A coordinator and its workers.
struct Farm {
    url: String,
    data: PathBuf,
    coordinator: Option<Running>,
    workers: Vec<Running>,
    port: u16,
}

impl Farm {
    fn start(tag: &str, workers: usize) -> Farm {
        let data = temp_dir(&format!("farm-{tag}"));
        let port = free_port();
        let mut farm = Farm {
            url: format!("http://127.0.0.1:{port}"),
            data,
            coordinator: None,
            workers: Vec::new(),
            port,
        };
        farm.start_coordinator();
        for _ in 0..workers {
            farm.add_worker();
        }
        farm
    }

    fn start_coordinator(&mut self) {
        let listen = format!("127.0.0.1:{}", self.port);
        let data = self.data.join("coordinator");
        let args = ["coordinator", "--listen", &listen, "--data", s(&data)];
        self.coordinator = Some(Running::start(&args, &[("PATHFARM_TOKEN", TOKEN)]));
        self.wait_listening();
    }

    fn add_worker(&mut self) {
        let n = self.workers.len();
        let cache = self.data.join(format!("worker-{n}"));
        let args = [
            "worker",
            "--coordinator",
            &self.url,
            "--threads",
            "1",
            "--cache",
            s(&cache),
        ];
        self.workers
            .push(Running::start(&args, &[("PATHFARM_TOKEN", TOKEN)]));
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

    fn logs(&self) -> String {
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

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// The job the tests render: the shipped door-ajar scene (gaussian filter: tiles need their
/// halo) with guided_path's pathfarm preset, small, an spp budget.
fn job_args(spp: u32) -> Vec<String> {
    let scene = project_scene("door-ajar");
    let mut v: Vec<String> = vec![scene.to_str().unwrap().to_string()];
    for d in ["integrator=guided_path", "resx=40", "resy=24"] {
        v.push("-D".into());
        v.push(d.into());
    }
    v.extend(["--spp".into(), spp.to_string(), "--seed".into(), "5".into()]);
    v
}

/// `pathfarm render` of the job: the reference EXR's bytes.
fn render_reference(dir: &Path, spp: u32) -> Vec<u8> {
    let out = dir.join("render.exr");
    let mut args: Vec<String> = vec!["render".into()];
    args.extend(job_args(spp));
    args.extend(["--no-png".into(), "-o".into(), s(&out).to_string()]);
    let argv: Vec<&str> = args.iter().map(|a| a.as_str()).collect();
    let r = Running::start(&argv, &[]).wait(Duration::from_secs(300));
    assert!(r.status.success(), "render: {}", r.describe());
    fs::read(&out).expect("reference EXR")
}

fn submit(farm: &Farm, spp: u32, out: &Path, extra_env: &[(&str, &str)]) -> Running {
    let mut args: Vec<String> = vec!["submit".into()];
    args.extend(job_args(spp));
    args.extend([
        "--coordinator".into(),
        farm.url.clone(),
        "--tile".into(),
        "8".into(),
        "--wait".into(),
        "-o".into(),
        s(out).to_string(),
    ]);
    let argv: Vec<&str> = args.iter().map(|a| a.as_str()).collect();
    let mut env = vec![("PATHFARM_TOKEN", TOKEN)];
    env.extend_from_slice(extra_env);
    Running::start(&argv, &env)
}

/// Tiles worker `i` has had accepted so far (from its log).
fn tiles_accepted(farm: &Farm, i: usize) -> usize {
    farm.workers[i]
        .stderr_text()
        .matches("tile accepted")
        .count()
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
fn wait_for_job(mut run: Running, farm: &Farm) {
    let t0 = Instant::now();
    while run.poll().is_none() {
        let late = t0.elapsed() > Duration::from_secs(300);
        assert!(!late, "job did not finish\n{}", farm.logs());
        std::thread::sleep(Duration::from_millis(50));
    }
    let ended = run.wait(Duration::from_secs(1));
    let ok = ended.status.success();
    assert!(ok, "submit: {}\n{}", ended.describe(), farm.logs());
}

fn assert_same_exr(got: &Path, reference: &[u8], farm: &Farm) {
    let bytes = fs::read(got).unwrap_or_else(|e| panic!("{}: {e}\n{}", got.display(), farm.logs()));
    // The EXR encoding is deterministic: equal files mean equal pixel bits.
    assert!(
        bytes == reference,
        "the farm's EXR differs from pathfarm render's ({} vs {} bytes)",
        bytes.len(),
        reference.len()
    );
}

#[test]
fn three_worker_cluster_renders_bit_identical_to_render() {
    let mut farm = Farm::start("three", 3);
    let reference = render_reference(&farm.data, 24);
    let out = farm.data.join("farm.exr");
    let run = submit(&farm, 24, &out, &[]).wait(Duration::from_secs(300));
    assert!(
        run.status.success(),
        "submit: {}\n{}",
        run.describe(),
        farm.logs()
    );
    assert_same_exr(&out, &reference, &farm);
    assert!(
        out.with_extension("png").exists(),
        "a PNG preview beside the EXR"
    );
    // the workers all took part, and none died
    for w in &mut farm.workers {
        assert!(w.poll().is_none(), "a worker exited");
    }
}

#[test]
fn worker_killed_mid_iteration_still_gives_bit_identical_image() {
    let mut farm = Farm::start("kill", 2);
    let reference = render_reference(&farm.data, 64);
    let out = farm.data.join("farm.exr");
    let mut run = submit(&farm, 64, &out, &[]);
    // Kill one worker in the middle of the job, once it has delivered tiles (its leases in
    // flight must go to the others).
    let before = tiles_accepted(&farm, 0);
    wait_for_tiles(&farm, &mut run, before + 5, "a worker could be killed");
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
fn submit_with_a_wrong_token_or_a_malformed_scene_is_refused_and_nothing_is_stored() {
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
    let argv = ["submit", s(&bad), "--coordinator", &url];
    let r = Running::start(&argv, &[("PATHFARM_TOKEN", TOKEN)]).wait(Duration::from_secs(60));
    assert!(!r.status.success(), "a malformed scene must fail");
    assert!(
        r.stderr
            .contains(bad.file_name().unwrap().to_str().unwrap()),
        "the error names the file: {}",
        r.stderr
    );
    assert!(!out.exists());
    assert_eq!(farm.blob_count(), 0, "nothing was stored");
}

#[test]
fn coordinator_killed_mid_job_resumes_bit_identical_and_keeps_finished_results() {
    let mut farm = Farm::start("restart", 2);
    // A job finished before the kill.
    let small = render_reference(&farm.data, 24);
    let first = farm.data.join("first.exr");
    let run = submit(&farm, 24, &first, &[]).wait(Duration::from_secs(300));
    assert!(
        run.status.success(),
        "submit: {}\n{}",
        run.describe(),
        farm.logs()
    );
    let first_id = run
        .stdout
        .split_whitespace()
        .find(|w| w.starts_with("job-"));
    let first_id = first_id
        .unwrap_or_else(|| panic!("a job id in: {}", run.stdout))
        .to_string();
    // A job in flight when the coordinator is killed, after its first iterations.
    let reference = render_reference(&farm.data, 128);
    let out = farm.data.join("resumed.exr");
    let mut run = submit(&farm, 128, &out, &[]);
    let before = tiles_accepted(&farm, 0);
    wait_for_tiles(
        &farm,
        &mut run,
        before + 20,
        "the coordinator could be killed",
    );
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
    farm.start_coordinator();
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
    let argv = ["fetch", &first_id, "--coordinator", &url, "-o", s(&fetched)];
    let r = Running::start(&argv, &[("PATHFARM_TOKEN", TOKEN)]).wait(Duration::from_secs(60));
    assert!(r.status.success(), "fetch: {}", r.describe());
    assert_same_exr(&fetched, &small, &farm);
}
