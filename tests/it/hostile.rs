//! Hostile input through the real `pathfarm` binary, run under resource limits: scene files and
//! flags built to crash it, to make it allocate or compute without bound, or to be accepted
//! although they make no sense. Each must be refused with exit code 1 or 2 and a message that
//! names what is wrong (the file and line, the parameter or flag, the value and the limit),
//! without a panic, an allocation failure or a flood of digits, and without writing a file.
//! A few large but legitimate inputs must still load.
//!
//! The child runs with `RLIMIT_AS` (2 GiB unless a case asks for more), `RLIMIT_CPU`
//! (`CPU_SECONDS`) and `RLIMIT_CORE` 0, and is killed after a wall-clock timeout (also when the
//! test itself panics), so a case that crashes, allocates without bound or never ends is
//! reported as such instead of taking the machine or the suite down.
//!
//! `PATHFARM_TEST_BIN=/path/to/pathfarm` runs the suite against another build (e.g. an old one,
//! to show that the cases catch its bugs). Each test runs all of its cases and reports every
//! failure at once; `cargo test ... hostile -- --nocapture` prints one line per case.

use std::io::Read;
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use crate::common::*;

const GIB: u64 = 1 << 30;
/// CPU seconds before the kernel stops the child (SIGXCPU, then SIGKILL 5 s later).
const CPU_SECONDS: u64 = 60;
/// Wall-clock seconds a case may take unless it says otherwise.
const TIMEOUT_SECONDS: u64 = 30;
/// Output kept per stream; the rest is read and dropped, so a flood cannot block the child.
const KEEP_BYTES: usize = 256 << 10;
/// What no message may contain.
const FORBIDDEN: [&str; 3] = ["panicked", "memory allocation", "overflow"];
/// The longest run of digits a line of stderr may hold.
const MAX_DIGIT_RUN: usize = 25;

// ---------------------------------------------------------------------------------------------
// Running the child under limits

/// How a child run ended.
struct Run {
    /// `None` when the child was killed at the wall-clock timeout.
    status: Option<ExitStatus>,
    stdout: String,
    stderr: String,
    elapsed: Duration,
}

/// Kills and reaps the child when dropped, unless it was reaped already: a failing test never
/// leaves a process behind.
struct KillOnDrop(Option<Child>);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        if let Some(mut c) = self.0.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// Reads `r` to its end on a thread, keeping the first `KEEP_BYTES`.
fn drain(mut r: impl Read + Send + 'static) -> std::thread::JoinHandle<String> {
    std::thread::spawn(move || {
        let (mut kept, mut buf) = (Vec::new(), [0u8; 8192]);
        while let Ok(n) = r.read(&mut buf) {
            if n == 0 {
                break;
            }
            let room = KEEP_BYTES.saturating_sub(kept.len());
            kept.extend_from_slice(&buf[..n.min(room)]);
        }
        String::from_utf8_lossy(&kept).into_owned()
    })
}

/// Sets a resource limit (soft and hard) in the child, between fork and exec.
fn set_limit(resource: i32, soft: u64, hard: u64) -> std::io::Result<()> {
    let lim = libc::rlimit {
        rlim_cur: soft as libc::rlim_t,
        rlim_max: hard as libc::rlim_t,
    };
    // SAFETY: setrlimit is async-signal-safe and `lim` outlives the call. The cast covers
    // the resource type, which differs between libcs.
    if unsafe { libc::setrlimit(resource as _, &lim) } == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// Runs the binary with `args` under `memory` bytes of address space, the CPU limit and
/// `timeout` of wall-clock time.
fn run_limited(args: &[String], memory: u64, timeout: Duration) -> Run {
    let mut cmd = Command::new(pathfarm_bin());
    cmd.args(args)
        .env("RUST_LOG", "warn")
        .env("NO_COLOR", "1")
        // glibc reserves 64 MiB of address space per malloc arena and makes up to 8 per core:
        // on a big machine that alone would eat the RLIMIT_AS budget.
        .env("MALLOC_ARENA_MAX", "2")
        .env_remove("RUST_BACKTRACE")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    // SAFETY: the closure only calls setrlimit (async-signal-safe) and allocates nothing.
    unsafe {
        cmd.pre_exec(move || {
            set_limit(libc::RLIMIT_AS as i32, memory, memory)?;
            set_limit(libc::RLIMIT_CPU as i32, CPU_SECONDS, CPU_SECONDS + 5)?;
            set_limit(libc::RLIMIT_CORE as i32, 0, 0)?;
            Ok(())
        });
    }
    let start = Instant::now();
    let mut child = cmd
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", pathfarm_bin().display()));
    let out = drain(child.stdout.take().expect("stdout"));
    let err = drain(child.stderr.take().expect("stderr"));
    let mut guard = KillOnDrop(Some(child));
    let status = loop {
        let c = guard.0.as_mut().expect("child");
        if let Some(s) = c.try_wait().expect("wait for pathfarm") {
            guard.0 = None;
            break Some(s);
        }
        if start.elapsed() > timeout {
            drop(guard); // kills and reaps it
            break None;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    Run {
        status,
        stdout: out.join().unwrap_or_default(),
        stderr: err.join().unwrap_or_default(),
        elapsed: start.elapsed(),
    }
}

// ---------------------------------------------------------------------------------------------
// Cases

enum Expect {
    /// Exit code 1 or 2; stderr holds every piece; no file written.
    Refused(Vec<String>),
    /// Exit code 0; stdout holds every piece; `render` wrote its EXR.
    Succeeds(Vec<String>),
}

type Check = Box<dyn Fn(&Run) -> Option<String>>;

struct Case {
    name: String,
    args: Vec<String>,
    /// Directories whose contents must not change (refused cases).
    watch: Vec<PathBuf>,
    /// The EXR a `render` case writes when it succeeds.
    output: Option<PathBuf>,
    expect: Expect,
    memory: u64,
    timeout: Duration,
    /// Further checks: each returns a problem, if any.
    checks: Vec<Check>,
}

fn strings(v: &[&str]) -> Vec<String> {
    v.iter().map(|s| s.to_string()).collect()
}

impl Case {
    fn new(name: &str, args: Vec<String>, watch: Vec<PathBuf>, output: Option<PathBuf>) -> Self {
        Case {
            name: name.to_string(),
            args,
            watch,
            output,
            expect: Expect::Refused(Vec::new()),
            memory: 2 * GIB,
            timeout: Duration::from_secs(TIMEOUT_SECONDS),
            checks: Vec::new(),
        }
    }

    /// `pathfarm render SCENE -o DIR/out.exr --threads 1 FLAGS`. DIR is the scene's own
    /// temporary directory, or a fresh one for a shipped scene.
    fn render(name: &str, scene: &Path, flags: &[&str]) -> Self {
        let scene_dir = scene.parent().expect("scene dir").to_path_buf();
        let dir = if is_test_dir(&scene_dir) {
            scene_dir.clone()
        } else {
            temp_dir(name)
        };
        let out = dir.join("out.exr");
        let mut args = strings(&["render", path_str(scene), "-o", path_str(&out)]);
        args.extend(strings(&["--threads", "1"]));
        args.extend(strings(flags));
        let mut watch = vec![dir.clone()];
        if scene_dir != dir {
            watch.push(scene_dir);
        }
        Self::new(name, args, watch, Some(out))
    }

    /// [`Case::render`] of `xml`, written to a fresh scene directory. The directory's name
    /// holds no part of the case's name, so the expected message pieces cannot be found in
    /// the scene's path instead of the message.
    fn render_xml(name: &str, xml: &str, flags: &[&str]) -> Self {
        Self::render(name, &write_scene("hostile-case", xml), flags)
    }

    /// `pathfarm info SCENE FLAGS`.
    fn info(name: &str, scene: &Path, flags: &[&str]) -> Self {
        let mut args = strings(&["info", path_str(scene)]);
        args.extend(strings(flags));
        let watch = vec![scene.parent().expect("scene dir").to_path_buf()];
        Self::new(name, args, watch, None)
    }

    fn refused(mut self, pieces: &[&str]) -> Self {
        self.expect = Expect::Refused(strings(pieces));
        self
    }

    fn refused_with(mut self, pieces: Vec<String>) -> Self {
        self.expect = Expect::Refused(pieces);
        self
    }

    fn succeeds(mut self, stdout_pieces: &[&str]) -> Self {
        self.expect = Expect::Succeeds(strings(stdout_pieces));
        self
    }

    fn memory_gib(mut self, gib: u64) -> Self {
        self.memory = gib * GIB;
        self
    }

    fn timeout_s(mut self, s: u64) -> Self {
        self.timeout = Duration::from_secs(s);
        self
    }

    fn check(mut self, f: impl Fn(&Run) -> Option<String> + 'static) -> Self {
        self.checks.push(Box::new(f));
        self
    }
}

/// A directory `common::temp_dir` made for a test (never a shipped scene's directory, even
/// when the repository itself lies under the temporary directory, as a CI clone may).
fn is_test_dir(d: &Path) -> bool {
    d.parent() == Some(std::env::temp_dir().as_path())
        && d.file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| n.starts_with("pathfarm-it-"))
}

/// Every file and directory under `dir`, relative, sorted (directories end in '/').
fn listing(dir: &Path) -> Vec<String> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<String>) {
        let Ok(rd) = std::fs::read_dir(dir) else {
            return;
        };
        for e in rd.flatten() {
            let p = e.path();
            let rel = p.strip_prefix(root).unwrap_or(&p).display().to_string();
            if p.is_dir() {
                out.push(format!("{rel}/"));
                walk(root, &p, out);
            } else {
                out.push(rel);
            }
        }
    }
    let mut v = Vec::new();
    walk(dir, dir, &mut v);
    v.sort();
    v
}

/// The longest run of ASCII digits in `s`.
fn longest_digit_run(s: &str) -> usize {
    s.split(|c: char| !c.is_ascii_digit())
        .map(str::len)
        .max()
        .unwrap_or(0)
}

/// The end of `s`, for failure messages.
fn tail(s: &str, n: usize) -> String {
    let s = s.trim_end();
    let cut = s.len().saturating_sub(n);
    let cut = (cut..=s.len())
        .find(|&i| s.is_char_boundary(i))
        .unwrap_or(0);
    let t = &s[cut..];
    // Keep the failure list readable: no line longer than 1000 characters.
    t.lines()
        .map(|l| {
            if l.len() > 1000 {
                let end = (0..=300)
                    .rev()
                    .find(|&i| l.is_char_boundary(i))
                    .unwrap_or(0);
                format!("{}... ({} characters)", &l[..end], l.len())
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n        ")
}

fn describe_status(run: &Run, case: &Case) -> String {
    match run.status {
        None => format!(
            "did not finish within {} s (killed)",
            case.timeout.as_secs()
        ),
        Some(s) => match (s.code(), s.signal()) {
            (Some(c), _) => format!("exit code {c}"),
            (None, Some(sig)) => {
                let name = match sig {
                    libc::SIGSEGV => " (SIGSEGV: stack overflow or bad access)",
                    libc::SIGABRT => " (SIGABRT: allocation failure or stack overflow)",
                    libc::SIGKILL => " (SIGKILL)",
                    libc::SIGXCPU => " (SIGXCPU: CPU limit)",
                    libc::SIGBUS => " (SIGBUS)",
                    _ => "",
                };
                format!("killed by signal {sig}{name}")
            }
            _ => format!("{s}"),
        },
    }
}

/// Runs one case; returns its problems (empty when it behaved).
fn run_case(case: &Case) -> (Vec<String>, Run) {
    let before: Vec<(PathBuf, Vec<String>)> =
        case.watch.iter().map(|d| (d.clone(), listing(d))).collect();
    let run = run_limited(&case.args, case.memory, case.timeout);
    let mut problems = Vec::new();
    let code = run.status.and_then(|s| s.code());
    let status = describe_status(&run, case);
    match &case.expect {
        Expect::Refused(pieces) => {
            if !matches!(code, Some(1) | Some(2)) {
                problems.push(format!("expected exit code 1 or 2, got {status}"));
            }
            for p in pieces {
                if !run.stderr.contains(p.as_str()) {
                    problems.push(format!("stderr lacks {p:?}"));
                }
            }
            for (dir, files) in &before {
                let after = listing(dir);
                if &after != files {
                    let new: Vec<_> = after.iter().filter(|f| !files.contains(f)).collect();
                    let gone: Vec<_> = files.iter().filter(|f| !after.contains(f)).collect();
                    problems.push(format!(
                        "{} changed: new {new:?}, removed {gone:?}",
                        dir.display()
                    ));
                }
            }
        }
        Expect::Succeeds(pieces) => {
            if code != Some(0) {
                problems.push(format!("expected success, got {status}"));
            } else {
                for p in pieces {
                    if !run.stdout.contains(p.as_str()) {
                        problems.push(format!("stdout lacks {p:?}: {}", tail(&run.stdout, 400)));
                    }
                }
                if let Some(out) = &case.output {
                    if !out.is_file() {
                        problems.push(format!("{} was not written", out.display()));
                    }
                }
            }
        }
    }
    for f in FORBIDDEN {
        if run.stderr.contains(f) {
            problems.push(format!("stderr contains {f:?}"));
        }
    }
    if let Some(l) = run
        .stderr
        .lines()
        .find(|l| longest_digit_run(l) > MAX_DIGIT_RUN)
    {
        problems.push(format!(
            "a line of stderr holds a run of {} digits (at most {MAX_DIGIT_RUN}): {}",
            longest_digit_run(l),
            tail(l, 200)
        ));
    }
    for c in &case.checks {
        if let Some(p) = c(&run) {
            problems.push(p);
        }
    }
    (problems, run)
}

/// Runs every case and fails once, listing every case that misbehaved. The directories of
/// cases that passed are removed; those of failures are kept for inspection.
fn run_all(cases: Vec<Case>) {
    let t0 = Instant::now();
    let mut failures = Vec::new();
    let n = cases.len();
    for case in &cases {
        let (problems, run) = run_case(case);
        let verdict = if problems.is_empty() { "ok" } else { "FAILED" };
        println!(
            "hostile case {}: {verdict} ({}, {:.2} s)\n    {}",
            case.name,
            describe_status(&run, case),
            run.elapsed.as_secs_f64(),
            tail(run.stderr.lines().last().unwrap_or(""), 300)
        );
        if problems.is_empty() {
            for d in &case.watch {
                if is_test_dir(d) {
                    let _ = std::fs::remove_dir_all(d);
                }
            }
        } else {
            failures.push(format!(
                "{} [{}; {:.2} s]\n    `pathfarm {}`\n    - {}\n    stderr: {}",
                case.name,
                describe_status(&run, case),
                run.elapsed.as_secs_f64(),
                case.args.join(" "),
                problems.join("\n    - "),
                tail(&run.stderr, 2000)
            ));
        }
    }
    println!("{n} hostile cases in {:.1} s", t0.elapsed().as_secs_f64());
    assert!(
        failures.is_empty(),
        "{} of {n} cases failed (binary {}):\n\n{}",
        failures.len(),
        pathfarm_bin().display(),
        failures.join("\n\n")
    );
}

// ---------------------------------------------------------------------------------------------
// Scenes

/// The integrator block of the small scenes: `$integrator`, path tracing unless `-D` says
/// otherwise.
const INTEGRATOR: &str = r#"<default name="integrator" value="path"/>
    <integrator type="$integrator"/>"#;
const LIGHT: &str = r#"<emitter type="constant"><rgb name="radiance" value="1"/></emitter>"#;
/// What `scene_xml` writes for the filter, camera and version (replaced by some cases).
const BOX_FILTER: &str = r#"<rfilter type="box"/>"#;
const LOOKAT_UP: &str = r#"up="0, 1, 0""#;
const VERSION: &str = r#"<scene version="3.0.0">"#;

/// An 8x8 scene: constant light plus `body`, integrator `$integrator`.
fn tiny(body: &str) -> String {
    scene_xml(8, 8, 40.0, 4.0, INTEGRATOR, &format!("{LIGHT}\n    {body}"))
}

/// `xml` with `from` replaced by `to` (which must be there).
fn swap(xml: &str, from: &str, to: &str) -> String {
    assert!(xml.contains(from), "{from:?} not in the scene template");
    xml.replacen(from, to, 1)
}

/// The location prefix of an error at line `line` of a scene file named scene.xml.
fn at_line(line: usize) -> String {
    format!("scene.xml:{line}:")
}

fn sphere_with(inner: &str) -> String {
    format!(r#"<shape type="sphere"><float name="radius" value="0.5"/>{inner}</shape>"#)
}

/// A chunk for a hand-written PNG: length, type, data, CRC-32 of type and data.
fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    fn crc32(bytes: impl Iterator<Item = u8>) -> u32 {
        let mut c = !0u32;
        for b in bytes {
            c ^= b as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    0xEDB8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                };
            }
        }
        !c
    }
    out.extend((data.len() as u32).to_be_bytes());
    out.extend(kind);
    out.extend(data);
    out.extend(crc32(kind.iter().chain(data).copied()).to_be_bytes());
}

/// A PNG whose (valid) header says `w` x `h` RGB, followed by the start of an image data
/// chunk and nothing more.
fn truncated_png(w: u32, h: u32) -> Vec<u8> {
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend(w.to_be_bytes());
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 2, 0, 0, 0]); // 8-bit RGB, deflate, adaptive filtering, no interlace
    png_chunk(&mut png, b"IHDR", &ihdr);
    png_chunk(&mut png, b"IDAT", &[0x78, 0x01, 0x00, 0x10]);
    png.truncate(png.len() - 2); // cut inside the IDAT chunk's CRC
    png
}

fn textured(file: &str) -> String {
    sphere_with(&format!(
        r#"<bsdf type="diffuse"><texture name="reflectance" type="bitmap"><string name="filename" value="{file}"/></texture></bsdf>"#
    ))
}

fn obj_shape(file: &str) -> String {
    format!(r#"<shape type="obj"><string name="filename" value="{file}"/></shape>"#)
}

// ---------------------------------------------------------------------------------------------
// Tests

#[test]
fn hostile_expansion_and_nesting_are_refused_at_their_line_naming_the_limit() {
    let mut cases = Vec::new();

    // Ten <default>s, each ten copies of the previous: 10^11 bytes if expanded. The line is
    // that of the first <default> whose expansion takes the substituted text past 16 MiB.
    let mut defaults = String::from(r#"<default name="d0" value="0123456789"/>"#);
    for k in 1..10 {
        defaults.push_str(&format!(
            "\n    <default name=\"d{k}\" value=\"{}\"/>",
            format!("$d{}", k - 1).repeat(10)
        ));
    }
    let limit = 16u64 << 20; // Limits::max_substituted_bytes
    let (mut len, mut total) = (10u64, 0u64);
    let over = (1..10)
        .find(|_| {
            len *= 10;
            total += len;
            total > limit
        })
        .expect("the expansion passes the limit");
    for (name, body) in [
        ("exponential-defaults-used", obj_shape("$d9")),
        ("exponential-defaults-unused", String::new()),
    ] {
        let xml = scene_xml(
            8,
            8,
            40.0,
            4.0,
            &format!("{defaults}\n    {INTEGRATOR}"),
            &format!("{LIGHT}\n    {body}"),
        );
        let line = line_of(&xml, &format!("name=\"d{over}\""));
        cases.push(
            Case::render_xml(name, &xml, &["--spp", "1"])
                .refused_with(vec![at_line(line), "max_substituted_bytes".into()]),
        );
    }

    // 8,000 nested two-sided BSDFs in a shape, on one line.
    let nested = format!(
        r#"<shape type="sphere">{}<bsdf type="diffuse"/>{}</shape>"#,
        r#"<bsdf type="twosided">"#.repeat(8000),
        "</bsdf>".repeat(8000)
    );
    let xml = tiny(&nested);
    let line = line_of(&xml, "twosided");
    cases.push(
        Case::render_xml("nested-twosided-8000", &xml, &["--spp", "1"])
            .refused_with(vec![at_line(line), "max_xml_depth".into()]),
    );

    // 20,000 nested plain elements.
    let xml = tiny(&format!("{}{}", "<a>".repeat(20000), "</a>".repeat(20000)));
    let line = line_of(&xml, "<a><a>");
    cases.push(
        Case::render_xml("nested-plain-20000", &xml, &["--spp", "1"])
            .refused_with(vec![at_line(line), "max_xml_depth".into()]),
    );

    run_all(cases);
}

#[test]
fn hostile_budgets_are_refused_naming_the_flag_or_parameter_and_the_limit() {
    let mut cases = Vec::new();
    let guided = ["-D", "integrator=guided_path"];

    cases.push(
        Case::render_xml("time-1e20-path", &tiny(""), &["--time", "1e20"])
            .refused(&["--time", "604800"]),
    );
    // The small scene with guided_path: each case's flags and what its message must name.
    for (name, flags, pieces) in [
        (
            "time-1e20-guided",
            &["--time", "1e20"][..],
            &["--time", "604800"][..],
        ),
        (
            "spp-per-pass-1024-over-spp-4",
            &["--spp", "4", "-D", "spp_per_pass=1024"],
            &["spp_per_pass", "1024", "4"],
        ),
        (
            "budget-1e300",
            &["-D", "budget=1e300"],
            &["budget", "16777216"],
        ),
    ] {
        let flags = [&guided[..], flags].concat();
        cases.push(Case::render_xml(name, &tiny(""), &flags).refused(pieces));
    }

    // A threshold of 0 (or nearly) refines the quadtrees without bound: at 32x32 and 64 spp
    // the renderer of old builds asks for gigabytes after the first iteration.
    for t in ["0", "1e-12"] {
        let define = format!("d_tree_threshold={t}");
        cases.push(
            Case::render(
                &format!("d-tree-threshold-{t}"),
                &project_scene("cornell-box"),
                &[
                    &guided[..],
                    &[
                        "-D", &define, "-D", "resx=32", "-D", "resy=32", "--spp", "64",
                    ],
                ]
                .concat(),
            )
            .refused(&["d_tree_threshold"]),
        );
    }

    // A time budget that ends before one pass: nothing rendered, so nothing written. (1 ns:
    // it has ended by the first check on any machine; 0.1 ms did not on an idle one, where
    // the first 64x64 pass starts sooner.)
    cases.push(
        Case::render(
            "guided-time-1e-9",
            &project_scene("cornell-box"),
            &[
                &guided[..],
                &["-D", "resx=64", "-D", "resy=64", "--time", "1e-9"],
            ]
            .concat(),
        )
        .refused(&["--time"]),
    );

    run_all(cases);
}

#[test]
fn hostile_sizes_are_refused_naming_the_value_and_the_limit() {
    let mut cases = Vec::new();
    let cornell = project_scene("cornell-box");
    let big = ["-D", "resx=30000", "-D", "resy=30000"];
    let side = ["30000", "16384", "max_film_side"];
    cases.push(
        Case::render(
            "film-30000-render",
            &cornell,
            &[&big[..], &["--spp", "1"]].concat(),
        )
        .refused(&side),
    );
    cases.push(Case::info("film-30000-info", &cornell, &big).refused(&side));
    cases.push(
        Case::info(
            "film-1000000-info",
            &cornell,
            &["-D", "resx=1000000", "-D", "resy=1000000"],
        )
        .refused(&["1000000", "16384", "max_film_side"]),
    );

    for r in ["1e6", "100"] {
        let filter =
            format!(r#"<rfilter type="tent"><float name="radius" value="{r}"/></rfilter>"#);
        let xml = swap(&tiny(""), BOX_FILTER, &filter);
        let line = line_of(&xml, "rfilter");
        let name = format!("tent-radius-{r}");
        cases.push(
            Case::render_xml(&name, &xml, &["--spp", "1"]).refused_with(vec![
                "radius".into(),
                "16".into(),
                "max_filter_radius".into(),
                at_line(line),
            ]),
        );
    }

    let scene = write_scene("texture-header-100000", &tiny(&textured("huge.png")));
    std::fs::write(
        scene.with_file_name("huge.png"),
        truncated_png(100_000, 100_000),
    )
    .unwrap();
    cases.push(
        Case::render("texture-header-100000x100000", &scene, &["--spp", "1"])
            .refused(&["100000x100000", "max_texture_pixels"]),
    );

    run_all(cases);
}

#[test]
fn hostile_values_are_refused_naming_the_parameter() {
    let mut cases = Vec::new();
    let mut add = |name: &str, xml: String, pieces: Vec<String>| {
        cases.push(Case::render_xml(name, &xml, &["--spp", "1"]).refused_with(pieces));
    };
    let s = |v: &[&str]| strings(v);

    let zero = format!(r#"<matrix value="{}"/>"#, ["0"; 16].join(" "));
    let xml = tiny("");
    // The camera's <lookat .../> element, replaced by the matrix inside the same <transform>.
    let start = xml.find("<lookat").expect("lookat");
    let end = start + xml[start..].find("/>").expect("end of lookat") + 2;
    let lookat = xml[start..end].to_string();
    add(
        "camera-to-world-zero",
        swap(&xml, &lookat, &zero),
        s(&["to_world"]),
    );

    let point = r#"<emitter type="point"><point name="position" value="nan, 0, 0"/></emitter>"#;
    let xml = tiny(point);
    let line = line_of(&xml, "nan, 0, 0");
    add("point-light-nan", xml, vec![at_line(line), "finite".into()]);

    add(
        "area-radiance-negative",
        tiny(
            r#"<shape type="rectangle"><emitter type="area"><rgb name="radiance" value="-1, 1, 1"/></emitter></shape>"#,
        ),
        s(&["negative", "radiance"]),
    );
    add(
        "diffuse-reflectance-negative",
        tiny(&sphere_with(
            r#"<bsdf type="diffuse"><rgb name="reflectance" value="-0.5, 0.5, 0.5"/></bsdf>"#,
        )),
        s(&["negative", "reflectance"]),
    );
    add(
        "sphere-radius-negative",
        tiny(r#"<shape type="sphere"><float name="radius" value="-1"/></shape>"#),
        s(&["radius"]),
    );
    add(
        "sphere-radius-zero",
        tiny(r#"<shape type="sphere"><float name="radius" value="0"/></shape>"#),
        s(&["radius must be positive"]),
    );
    add(
        "lookat-up-zero",
        swap(&tiny(""), LOOKAT_UP, r#"up="0, 0, 0""#),
        s(&["up"]),
    );
    add(
        "shape-projective-matrix",
        tiny(
            r#"<shape type="cube"><transform name="to_world"><matrix value="1 0 0 0 0 1 0 0 0 0 1 0 0 0 1 1"/></transform></shape>"#,
        ),
        s(&["projective"]),
    );
    add(
        "shape-scaled-1e20",
        tiny(
            r#"<shape type="cube"><transform name="to_world"><scale value="1e20"/></transform></shape>"#,
        ),
        s(&["1e18"]),
    );
    add(
        "scene-version-banana",
        swap(&tiny(""), VERSION, r#"<scene version="banana">"#),
        s(&["version"]),
    );

    run_all(cases);
}

#[test]
fn hostile_files_are_refused_with_one_clear_message() {
    let mut cases = Vec::new();

    let scene = write_scene("obj-directory", &tiny(&obj_shape("mesh.obj")));
    std::fs::create_dir(scene.with_file_name("mesh.obj")).unwrap();
    cases.push(
        Case::render("obj-is-a-directory", &scene, &["--spp", "1"]).refused(&["is a directory"]),
    );

    cases.push(
        Case::render_xml(
            "mesh-missing",
            &tiny(&obj_shape("nowhere.obj")),
            &["--spp", "1"],
        )
        .refused(&["nowhere.obj", "os error 2"])
        .check(|r| {
            let n = r.stderr.matches("os error 2").count();
            (n > 1).then(|| format!("\"os error 2\" appears {n} times (at most once)"))
        }),
    );

    // The scene file itself missing: the OS error once, not once per layer of context.
    let scene = write_scene("scene-missing", "").with_file_name("nothere.xml");
    cases.push(
        Case::render("scene-file-missing", &scene, &[])
            .refused(&["nothere.xml", "os error 2"])
            .check(|r| {
                let n = r.stderr.matches("os error 2").count();
                (n > 1).then(|| format!("\"os error 2\" appears {n} times (at most once)"))
            }),
    );

    let scene = write_scene("obj-bad-line", &tiny(&obj_shape("bad.obj")));
    std::fs::write(
        scene.with_file_name("bad.obj"),
        "v 0 0 0\nv 1 0 0\nv 1 2 x\nf 1 2 3\n",
    )
    .unwrap();
    cases.push(Case::render("obj-bad-line-3", &scene, &["--spp", "1"]).refused(&["line 3"]));

    let scene = write_scene("utf16", "");
    let mut bytes = vec![0xFF, 0xFE];
    bytes.extend(tiny("").encode_utf16().flat_map(u16::to_le_bytes));
    std::fs::write(&scene, bytes).unwrap();
    cases.push(Case::render("scene-in-utf16", &scene, &["--spp", "1"]).refused(&["UTF-16"]));

    run_all(cases);
}

#[test]
fn large_but_legitimate_inputs_load_within_the_limits() {
    let mut cases = Vec::new();

    // The small scene itself renders: the limits leave room for a normal run.
    cases.push(
        Case::render_xml(
            "control-tiny-scene",
            &tiny(&sphere_with("")),
            &["--spp", "1"],
        )
        .succeeds(&["summary:"]),
    );

    // The smallest allowed threshold, with the guide's memory capped, fits in 2 GiB.
    cases.push(
        Case::render(
            "d-tree-threshold-1e-5-in-64-mb",
            &project_scene("cornell-box"),
            &[
                "-D",
                "integrator=guided_path",
                "-D",
                "resx=32",
                "-D",
                "resy=32",
                "-D",
                "d_tree_threshold=1e-5",
                "-D",
                "max_memory_mb=64",
                "--spp",
                "16",
            ],
        )
        .succeeds(&["summary:"]),
    );

    // One OBJ face of 30,000 corners (a convex polygon) loads in time: 30,000 triangles take
    // milliseconds, so 3 s catches work that grows with the square of the polygon's size
    // (a face may have up to Limits::max_polygon_vertices = 2^20 corners).
    let scene = write_scene("obj-face-30000", &tiny(&obj_shape("disc.obj")));
    let n = 30_000;
    let mut obj = String::new();
    for i in 0..n {
        let a = i as f64 / n as f64 * std::f64::consts::TAU;
        obj.push_str(&format!("v {:.7} {:.7} 0\n", a.cos(), a.sin()));
    }
    obj.push('f');
    for i in 1..=n {
        obj.push_str(&format!(" {i}"));
    }
    obj.push('\n');
    std::fs::write(scene.with_file_name("disc.obj"), obj).unwrap();
    cases.push(
        Case::info("obj-face-30000-info", &scene, &[])
            .succeeds(&["triangles: 29998"])
            .timeout_s(3),
    );

    // A real 16384 x 16384 texture (the largest film side) loads given the memory.
    let scene = write_scene("texture-16384", &tiny(&textured("big.png")));
    write_big_png(&scene.with_file_name("big.png"), 16384);
    cases.push(
        Case::info("texture-16384x16384-info", &scene, &[])
            .succeeds(&["textures: 1"])
            .memory_gib(8)
            .timeout_s(120),
    );

    run_all(cases);
}

/// A valid `side` x `side` RGB PNG, one colour but for a gradient along the first row. The
/// Sub filter turns each row into zeros, which the fast compressor squeezes to a few MB (without
/// a filter it writes about 770 MB).
fn write_big_png(path: &Path, side: u32) {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder;
    let n = side as usize * side as usize;
    let mut rgb = [180u8, 120, 60].repeat(n);
    for (x, px) in rgb.chunks_exact_mut(3).take(side as usize).enumerate() {
        px[0] = (x % 256) as u8;
    }
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    PngEncoder::new_with_quality(file, CompressionType::Fast, FilterType::Sub)
        .write_image(&rgb, side, side, image::ExtendedColorType::Rgb8)
        .expect("write the big PNG");
}
