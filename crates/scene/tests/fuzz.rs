//! A bounded, seeded mutation fuzz of the shipped scenes through the loader: each case copies a
//! shipped scene's text, applies one to three mutations (byte flips, deleted and duplicated
//! lines and attributes, numbers replaced by hostile values, element and plugin names swapped
//! between categories, hostile `-D` overrides) and loads it with small limits. No case may
//! panic, and every error must read `FILE:LINE: message`, FILE the scene file (or a file it
//! includes) and LINE a line of it. The shipped scenes include a Mitsuba 0.6 one with
//! `<path>`, `<include>`, a serialized mesh and spectra, so their syntax is fuzzed too.
//!
//! `PATHFARM_FUZZ_SEED` sets the seed (printed on every run and with every failure),
//! `PATHFARM_FUZZ_CASES` the number of cases, `PATHFARM_FUZZ_CASE=i` reruns case `i` alone,
//! `PATHFARM_FUZZ_VERBOSE=1` prints every case and its outcome (with `--nocapture`).
//! Failing cases' files are kept under the printed directory.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use pathfarm_scene::{load_scene_with_limits, Limits};

const DEFAULT_SEED: u64 = 0x5EED_F0A2_2026;
const DEFAULT_CASES: u64 = 10_000;
/// A single load taking longer than this is a failure.
const SLOW_CASE: Duration = Duration::from_secs(2);
/// A load still running after this is reported and the process aborted (a hang).
const HUNG_CASE: Duration = Duration::from_secs(60);

use pathfarm_testkit::TestRng;

// ---------------------------------------------------------------------------------------------
// Mutations

/// Values a number is replaced by.
const HOSTILE_NUMBERS: &[&str] = &[
    "nan",
    "NaN",
    "inf",
    "-inf",
    "-1",
    "0",
    "-0",
    "1e308",
    "-1e308",
    "1e-320",
    "1e39",
    "99999999999",
    "2147483647",
    "2147483648",
    "-2147483649",
    "4294967296",
    "9223372036854775807",
    "9223372036854775808",
    "18446744073709551616",
    "1e400",
    "",
    " ",
    "1,",
    "0x10",
    "1e",
    "+",
    "-",
    ".",
    "$nope",
    "$",
    "\\$",
];

/// Plugin element names, swapped for each other.
const CATEGORIES: &[&str] = &[
    "shape",
    "bsdf",
    "texture",
    "emitter",
    "sensor",
    "film",
    "rfilter",
    "sampler",
    "integrator",
];

/// Property element names, swapped for each other.
const PROPERTIES: &[&str] = &[
    "float",
    "integer",
    "boolean",
    "string",
    "rgb",
    "spectrum",
    "point",
    "vector",
    "transform",
    "lookat",
    "scale",
    "rotate",
    "translate",
    "matrix",
    "ref",
    "default",
];

/// Plugin types put in place of a `type="..."`.
const TYPES: &[&str] = &[
    "sphere",
    "rectangle",
    "cube",
    "disk",
    "obj",
    "ply",
    "diffuse",
    "twosided",
    "dielectric",
    "thindielectric",
    "roughdielectric",
    "conductor",
    "roughconductor",
    "plastic",
    "roughplastic",
    "area",
    "point",
    "constant",
    "envmap",
    "directional",
    "bitmap",
    "checkerboard",
    "hdrfilm",
    "box",
    "tent",
    "gaussian",
    "independent",
    "perspective",
    "path",
    "guided_path",
    "teapot",
    "",
];

/// Override names tried with hostile values (the shipped scenes' `<default>`s and
/// guided_path parameters).
const OVERRIDE_NAMES: &[&str] = &[
    "integrator",
    "spp",
    "resx",
    "resy",
    "max_depth",
    "budget",
    "spp_per_pass",
    "d_tree_threshold",
    "s_tree_threshold",
    "max_memory_mb",
    "rr_depth",
];

/// An attribute ` name="value"` of the text: the span from the space to the closing quote,
/// and the span of its value.
struct Attr {
    start: usize,
    end: usize,
    value: (usize, usize),
}

fn is_name_byte(b: u8) -> bool {
    b.is_ascii_alphanumeric() || b == b'_' || b == b'-' || b == b':'
}

fn attributes(t: &[u8]) -> Vec<Attr> {
    let mut v = Vec::new();
    let mut i = 0;
    while i + 1 < t.len() {
        if t[i] == b'=' && t[i + 1] == b'"' {
            let mut s = i;
            while s > 0 && is_name_byte(t[s - 1]) {
                s -= 1;
            }
            if s < i && s > 0 && t[s - 1].is_ascii_whitespace() {
                if let Some(q) = t[i + 2..].iter().position(|&b| b == b'"') {
                    let vend = i + 2 + q;
                    v.push(Attr {
                        start: s - 1,
                        end: vend + 1,
                        value: (i + 2, vend),
                    });
                    i = vend + 1;
                    continue;
                }
            }
        }
        i += 1;
    }
    v
}

/// The numbers inside attribute values.
fn numbers(t: &[u8]) -> Vec<(usize, usize)> {
    let mut v = Vec::new();
    for a in attributes(t) {
        let (s, e) = a.value;
        let mut i = s;
        while i < e {
            let j = (i..e)
                .find(|&k| t[k] == b',' || t[k].is_ascii_whitespace())
                .unwrap_or(e);
            if j > i
                && std::str::from_utf8(&t[i..j])
                    .ok()
                    .is_some_and(|w| w.parse::<f64>().is_ok())
            {
                v.push((i, j));
            }
            i = j + 1;
        }
    }
    v
}

/// `<name` at `i` followed by a delimiter (not a longer name).
fn tag_at(t: &[u8], i: usize, name: &str) -> bool {
    let n = name.as_bytes();
    t[i..].starts_with(b"<")
        && t[i + 1..].starts_with(n)
        && t.get(i + 1 + n.len())
            .is_some_and(|&b| b.is_ascii_whitespace() || b == b'>' || b == b'/')
}

/// Spans of the names of an element `<name ...>` starting at `i` and of its matching
/// `</name>` (none when it closes itself or no match is found).
fn element_names(t: &[u8], i: usize, name: &str) -> Vec<(usize, usize)> {
    let n = name.len();
    let mut spans = vec![(i + 1, i + 1 + n)];
    let end_of_tag = |from: usize| t[from..].iter().position(|&b| b == b'>').map(|p| from + p);
    let Some(e) = end_of_tag(i) else {
        return spans;
    };
    if e > 0 && t[e - 1] == b'/' {
        return spans;
    }
    let (mut depth, mut k) = (1usize, e + 1);
    let close = format!("</{name}");
    while k < t.len() {
        if t[k..].starts_with(close.as_bytes())
            && t.get(k + close.len())
                .is_some_and(|&b| b == b'>' || b.is_ascii_whitespace())
        {
            depth -= 1;
            if depth == 0 {
                spans.push((k + 2, k + 2 + n));
                return spans;
            }
            k += close.len();
        } else if tag_at(t, k, name) {
            match end_of_tag(k) {
                Some(e2) if t[e2 - 1] == b'/' => k = e2 + 1,
                Some(e2) => {
                    depth += 1;
                    k = e2 + 1
                }
                None => return spans,
            }
        } else {
            k += 1;
        }
    }
    spans
}

fn line_at(t: &[u8], i: usize) -> usize {
    t[..i.min(t.len())].iter().filter(|&&b| b == b'\n').count() + 1
}

fn shown(b: &[u8]) -> String {
    let s = String::from_utf8_lossy(b);
    if s.len() > 60 {
        let end = (0..=60).rev().find(|&i| s.is_char_boundary(i)).unwrap_or(0);
        format!("{:?}...", &s[..end])
    } else {
        format!("{s:?}")
    }
}

/// Replaces `spans` (sorted, disjoint) of `t` by `with`.
fn replace_spans(t: &mut Vec<u8>, spans: &[(usize, usize)], with: &[u8]) {
    for &(s, e) in spans.iter().rev() {
        t.splice(s..e, with.iter().copied());
    }
}

/// Applies one random mutation to `t` (or adds an override); returns what it did.
fn mutate(rng: &mut TestRng, t: &mut Vec<u8>, overrides: &mut Vec<(String, String)>) -> String {
    for _ in 0..16 {
        if let Some(d) = try_mutate(rng, t, overrides) {
            return d;
        }
    }
    // Nothing applicable (the text was mostly deleted): flip a byte or append one.
    let b = rng.next_u32() as u8;
    t.push(b);
    format!("appended byte {b:#04x}")
}

fn try_mutate(
    rng: &mut TestRng,
    t: &mut Vec<u8>,
    overrides: &mut Vec<(String, String)>,
) -> Option<String> {
    let lines: Vec<(usize, usize)> = {
        let mut v = Vec::new();
        let mut s = 0;
        for (i, &b) in t.iter().enumerate() {
            if b == b'\n' {
                v.push((s, i + 1));
                s = i + 1;
            }
        }
        if s < t.len() {
            v.push((s, t.len()));
        }
        v
    };
    // Kinds by weight: most keep the XML well formed, so that the plugins' checks are reached.
    const WEIGHTS: [(u32, usize); 12] = [
        (6, 0),   // byte flip
        (6, 1),   // delete a line
        (6, 2),   // duplicate a line
        (8, 3),   // drop an attribute
        (2, 4),   // duplicate an attribute (malformed XML)
        (30, 5),  // hostile number
        (10, 8),  // hostile attribute value
        (10, 9),  // element renamed
        (10, 10), // plugin type replaced
        (12, 11), // -D override
        (0, 6),
        (0, 7),
    ];
    let total: u32 = WEIGHTS.iter().map(|w| w.0).sum();
    let mut r = rng.index(total as usize) as u32;
    let kind = WEIGHTS
        .iter()
        .find(|(w, _)| {
            let hit = r < *w;
            r = r.saturating_sub(*w);
            hit
        })
        .map_or(5, |w| w.1);
    match kind {
        0 => {
            if t.is_empty() {
                return None;
            }
            let i = rng.index(t.len());
            let old = t[i];
            let new = if rng.index(2) == 0 {
                old ^ (1 << rng.index(8))
            } else {
                *rng.pick(b"<>/\"'=&$;\\ \n\0\xff\xc3")
            };
            t[i] = new;
            Some(format!(
                "line {}: byte {i} {old:#04x} -> {new:#04x}",
                line_at(t, i)
            ))
        }
        1 | 2 => {
            if lines.is_empty() {
                return None;
            }
            let k = rng.index(lines.len());
            let (s, e) = lines[k];
            let text = t[s..e].to_vec();
            if kind == 1 {
                t.drain(s..e);
                Some(format!("deleted line {}: {}", k + 1, shown(&text)))
            } else {
                t.splice(s..s, text.iter().copied());
                Some(format!("duplicated line {}: {}", k + 1, shown(&text)))
            }
        }
        3 | 4 => {
            let attrs = attributes(t);
            if attrs.is_empty() {
                return None;
            }
            let a = rng.pick(&attrs);
            let text = t[a.start..a.end].to_vec();
            let line = line_at(t, a.start);
            if kind == 3 {
                t.drain(a.start..a.end);
                Some(format!("line {line}: dropped attribute {}", shown(&text)))
            } else {
                t.splice(a.end..a.end, text.iter().copied());
                Some(format!(
                    "line {line}: duplicated attribute {}",
                    shown(&text)
                ))
            }
        }
        5 => {
            let nums = numbers(t);
            if nums.is_empty() {
                return None;
            }
            let &(s, e) = rng.pick(&nums);
            let old = t[s..e].to_vec();
            let new = *rng.pick(HOSTILE_NUMBERS);
            let line = line_at(t, s);
            t.splice(s..e, new.bytes());
            Some(format!("line {line}: number {} -> {new:?}", shown(&old)))
        }
        8 => {
            let attrs = attributes(t);
            if attrs.is_empty() {
                return None;
            }
            let a = rng.pick(&attrs);
            let (s, e) = a.value;
            let old = t[s..e].to_vec();
            let new = if rng.index(2) == 0 {
                rng.pick(HOSTILE_NUMBERS).to_string()
            } else {
                rng.pick(TYPES).to_string()
            };
            let line = line_at(t, s);
            t.splice(s..e, new.bytes());
            Some(format!("line {line}: value {} -> {new:?}", shown(&old)))
        }
        9 => {
            // A plugin (or property) element renamed to another, with its closing tag.
            let names = if rng.index(3) == 0 {
                PROPERTIES
            } else {
                CATEGORIES
            };
            let from = *rng.pick(names);
            let to_names = if rng.index(4) == 0 {
                PROPERTIES
            } else {
                CATEGORIES
            };
            let to = *rng.pick(to_names);
            if from == to {
                return None;
            }
            let starts: Vec<usize> = (0..t.len()).filter(|&i| tag_at(t, i, from)).collect();
            if starts.is_empty() {
                return None;
            }
            let i = *rng.pick(&starts);
            let line = line_at(t, i);
            let spans = element_names(t, i, from);
            replace_spans(t, &spans, to.as_bytes());
            Some(format!("line {line}: <{from}> -> <{to}>"))
        }
        10 => {
            // A plugin type replaced by another's.
            let attrs: Vec<Attr> = attributes(t)
                .into_iter()
                .filter(|a| {
                    t[a.start..].starts_with(b" type=\"") || t[a.start..].starts_with(b"\ttype=\"")
                })
                .collect();
            if attrs.is_empty() {
                return None;
            }
            let a = rng.pick(&attrs);
            let (s, e) = a.value;
            let old = t[s..e].to_vec();
            let new = *rng.pick(TYPES);
            let line = line_at(t, s);
            t.splice(s..e, new.bytes());
            Some(format!("line {line}: type {} -> {new:?}", shown(&old)))
        }
        _ => {
            let name = *rng.pick(OVERRIDE_NAMES);
            let value = if rng.index(4) == 0 {
                rng.pick(TYPES).to_string()
            } else {
                rng.pick(HOSTILE_NUMBERS).to_string()
            };
            let guided = !matches!(name, "integrator" | "spp" | "resx" | "resy" | "max_depth");
            let mut what = String::new();
            if guided && rng.index(4) != 0 {
                // Guided parameters mean something only to guided_path.
                overrides.push(("integrator".into(), "guided_path".into()));
                what.push_str("-D integrator=guided_path ");
            }
            overrides.push((name.to_string(), value.clone()));
            Some(format!("{what}-D {name}={value}"))
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The fuzz

fn env_u64(name: &str) -> Option<u64> {
    let v = std::env::var(name).ok()?;
    let v = v.trim();
    let parsed = match v.strip_prefix("0x") {
        Some(h) => u64::from_str_radix(h, 16),
        None => v.parse(),
    };
    Some(parsed.unwrap_or_else(|_| panic!("{name}={v}: not a number")))
}

/// Copies each shipped scene directory (scene.xml with its meshes and textures) into `root`.
fn copy_shipped_scenes(root: &Path) -> Vec<(String, PathBuf, Vec<u8>)> {
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes");
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(&scenes)
        .expect("scenes directory")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("scene.xml").is_file())
        .collect();
    dirs.sort();
    assert!(!dirs.is_empty(), "no scenes under {}", scenes.display());
    dirs.iter()
        .map(|d| {
            let name = d.file_name().unwrap().to_string_lossy().into_owned();
            let to = root.join(&name);
            std::fs::create_dir_all(&to).unwrap();
            for f in std::fs::read_dir(d).unwrap().flatten() {
                if f.path().is_file() {
                    std::fs::copy(f.path(), to.join(f.file_name())).unwrap();
                }
            }
            let text = std::fs::read(d.join("scene.xml")).unwrap();
            (name, to.join("scene.xml"), text)
        })
        .collect()
}

/// The problem with an error's text, if any: it must be `PATH:LINE: message` with LINE a line
/// of the file (or one past its end). An error in a file the scene includes names that file
/// (beside the scene) and a line of it.
fn check_error(shown: &str, path: &Path, lines: usize) -> Option<String> {
    let dir = path.parent().expect("a scene directory");
    let included = std::fs::read_dir(dir).ok().and_then(|entries| {
        entries.flatten().map(|e| e.path()).find(|f| {
            f != path
                && f.extension().is_some_and(|x| x == "xml")
                && shown.starts_with(&format!("{}:", f.display()))
        })
    });
    if let Some(f) = included {
        let n = std::fs::read_to_string(&f).map_or(0, |t| t.lines().count());
        return check_error(shown, &f, n);
    }
    let prefix = format!("{}:", path.display());
    let Some(rest) = shown.strip_prefix(&prefix) else {
        return Some(format!("does not start with {prefix:?}"));
    };
    let digits = rest.bytes().take_while(u8::is_ascii_digit).count();
    if digits == 0 || !rest[digits..].starts_with(':') {
        return Some(format!("no ':LINE:' after {prefix:?}"));
    }
    match rest[..digits].parse::<usize>() {
        Ok(l) if l >= 1 && l <= lines + 1 => None,
        _ => Some(format!(
            "line {} is not a line of the file ({lines} lines)",
            &rest[..digits]
        )),
    }
}

#[test]
fn mutated_shipped_scenes_never_panic_and_every_error_names_the_file_and_line() {
    let seed = env_u64("PATHFARM_FUZZ_SEED").unwrap_or(DEFAULT_SEED);
    let cases = env_u64("PATHFARM_FUZZ_CASES").unwrap_or(DEFAULT_CASES);
    let only = env_u64("PATHFARM_FUZZ_CASE");
    let verbose = std::env::var_os("PATHFARM_FUZZ_VERBOSE").is_some();
    let root = std::env::temp_dir().join(format!("pathfarm-fuzz-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).unwrap();
    let scenes = copy_shipped_scenes(&root);
    println!(
        "fuzz: seed {seed:#x}, {cases} cases over {} scenes, in {}",
        scenes.len(),
        root.display()
    );
    let limits = Limits {
        max_memory_bytes: 512 << 20,
        max_guide_memory_bytes: 128 << 20,
        max_film_side: 2048,
        max_film_pixels: 1 << 22,
        ..Limits::default()
    };

    // A watchdog: a load that hangs is reported (with its case) and the process stopped.
    let current = Arc::new(Mutex::new(String::new()));
    let started_ms = Arc::new(AtomicU64::new(0));
    let t0 = Instant::now();
    {
        let (current, started_ms) = (current.clone(), started_ms.clone());
        std::thread::spawn(move || loop {
            std::thread::sleep(Duration::from_millis(500));
            let s = started_ms.load(Ordering::Relaxed);
            if s != 0
                && (t0.elapsed().as_millis() as u64).saturating_sub(s)
                    > HUNG_CASE.as_millis() as u64
            {
                use std::io::Write;
                let msg = format!(
                    "fuzz: a load hung for {} s: {}\n",
                    HUNG_CASE.as_secs(),
                    current.lock().map(|c| c.clone()).unwrap_or_default()
                );
                let _ = std::io::stderr().write_all(msg.as_bytes());
                std::process::abort();
            }
        });
    }

    let failed_dir = root.join("failed");
    let mut failures: Vec<String> = Vec::new();
    let mut failed = 0u64;
    let mut kinds = std::collections::HashMap::new();
    let (mut loaded, mut refused) = (0u64, 0u64);
    let mut slowest = (Duration::ZERO, 0u64);
    let range = match only {
        Some(i) => i..i + 1,
        None => 0..cases,
    };
    for i in range {
        let mut rng = TestRng::new(seed ^ i.wrapping_mul(0xD1B5_4A32_D192_ED03));
        let (name, path, original) = &scenes[(i % scenes.len() as u64) as usize];
        let mut text = original.clone();
        let mut overrides = Vec::new();
        let n = 1 + rng.index(3);
        let done: Vec<String> = (0..n)
            .map(|_| mutate(&mut rng, &mut text, &mut overrides))
            .collect();
        let what = format!("seed {seed:#x} case {i} ({name}): {}", done.join("; "));
        std::fs::write(path, &text).unwrap();
        *current.lock().unwrap() = what.clone();
        let start = Instant::now();
        started_ms.store(t0.elapsed().as_millis() as u64 + 1, Ordering::Relaxed);
        let result = catch_unwind(AssertUnwindSafe(|| {
            load_scene_with_limits(path, &overrides, &limits)
        }));
        started_ms.store(0, Ordering::Relaxed);
        let took = start.elapsed();
        if took > slowest.0 {
            slowest = (took, i);
        }
        let lines = text.iter().filter(|&&b| b == b'\n').count() + 1;
        if verbose {
            match &result {
                Ok(Ok(_)) => println!("{what}\n    loaded"),
                Ok(Err(e)) => println!("{what}\n    {e}"),
                Err(_) => println!("{what}\n    panicked"),
            }
        }
        let problem = match result {
            Err(p) => {
                let msg = p
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_default();
                Some(format!("panicked: {msg}"))
            }
            Ok(Ok(_)) => {
                loaded += 1;
                None
            }
            Ok(Err(e)) => {
                refused += 1;
                let shown = e.to_string();
                check_error(&shown, path, lines).map(|p| format!("error {p}: {shown}"))
            }
        };
        let problem = problem
            .or_else(|| (took > SLOW_CASE).then(|| format!("took {:.2} s", took.as_secs_f64())));
        if let Some(p) = problem {
            failed += 1;
            // Up to 5 examples of each kind of problem (its text without paths and numbers).
            let kind: String = p
                .replace(&root.display().to_string(), "")
                .chars()
                .filter(|c| !c.is_ascii_digit())
                .take(60)
                .collect();
            let seen = kinds.entry(kind).or_insert(0u32);
            *seen += 1;
            if *seen <= 5 && failures.len() < 50 {
                std::fs::create_dir_all(&failed_dir).unwrap();
                let keep = failed_dir.join(format!("case-{i}-{name}.xml"));
                std::fs::write(&keep, &text).unwrap();
                failures.push(format!("{what}\n    {p}\n    kept as {}", keep.display()));
            }
        }
    }
    // Restore the originals (the directory is removed below unless something failed).
    for (_, path, original) in &scenes {
        std::fs::write(path, original).unwrap();
    }
    println!(
        "fuzz: {} loaded, {} refused, in {:.1} s (slowest case {} at {:.3} s)",
        loaded,
        refused,
        t0.elapsed().as_secs_f64(),
        slowest.1,
        slowest.0.as_secs_f64()
    );
    if failures.is_empty() {
        let _ = std::fs::remove_dir_all(&root);
    }
    assert!(
        failures.is_empty(),
        "{failed} fuzz cases failed (seed {seed:#x}; rerun one with PATHFARM_FUZZ_SEED={seed:#x} \
         PATHFARM_FUZZ_CASE=i; {} of them below, at most 5 of a kind):\n{}",
        failures.len(),
        failures.join("\n")
    );
}
