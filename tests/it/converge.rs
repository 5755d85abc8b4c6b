//! `pathfarm converge`: the files it writes, their agreement with the images, and its
//! reference cache.

use std::path::Path;
use std::process::Output;

use pathfarm_render::output::read_exr_rgb;

use crate::common::*;

/// relMSE of `img` against `reference`, as the issue defines it (recomputed here
/// independently of the command).
fn relmse(img: &[[f32; 3]], reference: &[[f32; 3]]) -> f64 {
    let mut s = 0.0;
    for (v, r) in img.iter().zip(reference) {
        for c in 0..3 {
            let d = v[c] as f64 - r[c] as f64;
            s += d * d / ((r[c] as f64).powi(2) + 0.01);
        }
    }
    s / (img.len() * 3) as f64
}

struct CsvRow {
    method: String,
    budget: String,
    repeat: u32,
    seed: u64,
    relmse: f64,
    nonfinite: u64,
    tree_mb: f64,
}

fn read_csv(path: &Path) -> Vec<CsvRow> {
    let text = std::fs::read_to_string(path).expect("results.csv");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).expect(name);
    let expected = "method,budget,repeat,seed,wall_s,cpu_s,spp,relmse,mse,mean,nonfinite,\
                    training_fraction,tree_memory_mb";
    assert_eq!(header.join(","), expected);
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            assert_eq!(f.len(), header.len(), "{l}");
            CsvRow {
                method: f[col("method")].into(),
                budget: f[col("budget")].into(),
                repeat: f[col("repeat")].parse().unwrap(),
                seed: f[col("seed")].parse().unwrap(),
                relmse: f[col("relmse")].parse().unwrap(),
                nonfinite: f[col("nonfinite")].parse().unwrap(),
                tree_mb: f[col("tree_memory_mb")].parse().unwrap(),
            }
        })
        .collect()
}

/// `pathfarm converge` on door-ajar at `resx` x `resy` into `out`, caching references in
/// `cache`, with `extra` arguments.
fn converge(out: &Path, cache: &Path, (resx, resy): (u32, u32), extra: &[&str]) -> Output {
    let scene = project_scene("door-ajar");
    let (resx, resy) = (format!("resx={resx}"), format!("resy={resy}"));
    let mut args = vec![
        "converge",
        scene.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "-D",
        &resx,
        "-D",
        &resy,
        "--cache",
        cache.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    pathfarm(&args)
}

#[test]
fn converge_writes_every_run_its_image_and_an_error_that_matches_the_image() {
    let dir = temp_dir("converge");
    let (out, cache) = (dir.join("out"), dir.join("cache"));
    let o = converge(
        &out,
        &cache,
        (64, 36),
        &[
            "--spp-budgets",
            "4,16",
            "--methods",
            "path,guided",
            "--sweep",
            "s_tree_threshold=500,8000",
            "--repeats",
            "2",
            "--reference-budget",
            "128",
            "--threads",
            "2",
        ],
    );
    assert_success(&o);
    let rows = read_csv(&out.join("results.csv"));
    // 2 methods + 2 swept values of guided, 2 budgets, 2 repeats.
    assert_eq!(rows.len(), 16);
    let (_, _, reference) = read_exr_rgb(&out.join("reference.exr")).expect("reference.exr");
    for r in &rows {
        assert_eq!(r.seed, 1 + r.repeat as u64, "seeds follow the repeats");
        assert_eq!(r.nonfinite, 0, "{}", r.method);
        let stem: String = r
            .method
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '-' {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        let img = out.join(format!("images/{stem}-{}-{}.exr", r.budget, r.repeat));
        let (w, h, px) = read_exr_rgb(&img).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((w, h), (64, 36));
        // The CSV's error is the image's (6 significant digits are printed).
        let e = relmse(&px, &reference);
        assert!(
            r.relmse > 0.0 && (r.relmse / e - 1.0).abs() < 1e-5,
            "{} {e}",
            r.relmse
        );
    }
    // Four times the samples: path's error must fall in every repeat (its expected
    // relMSE falls about 4x; a rise would need a firefly worth 3x the whole 4-spp error).
    for repeat in 0..2 {
        let at = |b: &str| {
            rows.iter()
                .find(|r| r.method == "path" && r.budget == b && r.repeat == repeat)
                .expect("path row")
                .relmse
        };
        assert!(
            at("16") < 0.6 * at("4"),
            "path: {} then {}",
            at("4"),
            at("16")
        );
    }
    // A lower subdivision threshold makes more spatial leaves, so a bigger tree.
    let mb = |label: &str| {
        rows.iter()
            .find(|r| r.method == label && r.budget == "16" && r.repeat == 0)
            .expect(label)
            .tree_mb
    };
    assert!(
        mb("guided[s_tree_threshold=500]") > mb("guided[s_tree_threshold=8000]"),
        "tree memory {} vs {}",
        mb("guided[s_tree_threshold=500]"),
        mb("guided[s_tree_threshold=8000]")
    );
    for png in ["error-vs-time.png", "crops.png"] {
        let img = image::open(out.join(png)).unwrap_or_else(|e| panic!("{png}: {e}"));
        assert!(img.width() > 300 && img.height() > 100, "{png}");
    }
    let svg = std::fs::read_to_string(out.join("error-vs-time.svg")).expect("svg");
    let summary = std::fs::read_to_string(out.join("summary.md")).expect("summary.md");
    for label in ["path", "guided", "guided[s_tree_threshold=500]"] {
        assert!(svg.contains(label), "{label} not in the chart");
        assert!(
            summary.contains(&format!("| {label} |")),
            "{label} not in the summary"
        );
    }
    assert!(summary.contains("Time to reach an error level"));
    assert!(summary.contains("reference's own relMSE"));
}

#[test]
fn converge_reuses_its_cached_reference_and_refuses_bad_arguments() {
    let dir = temp_dir("converge-cache");
    let cache = dir.join("cache");
    let run = |out: &str, extra: &[&str]| {
        let mut args = vec![
            "--spp-budgets",
            "2",
            "--methods",
            "path",
            "--repeats",
            "1",
            "--reference-budget",
            "16",
        ];
        args.extend_from_slice(extra);
        converge(&dir.join(out), &cache, (32, 18), &args)
    };
    let o = run("a", &[]);
    assert_success(&o);
    let cached: Vec<_> = std::fs::read_dir(&cache)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(cached.len(), 2, "two halves: {cached:?}");
    let stamps: Vec<_> = cached
        .iter()
        .map(|p| p.metadata().unwrap().modified().unwrap())
        .collect();
    let o = run("b", &[]);
    assert_success(&o);
    let again: Vec<_> = cached
        .iter()
        .map(|p| p.metadata().unwrap().modified().unwrap())
        .collect();
    assert_eq!(stamps, again, "the second run re-rendered the reference");
    assert_eq!(
        std::fs::read(dir.join("a/reference.exr")).unwrap(),
        std::fs::read(dir.join("b/reference.exr")).unwrap()
    );
    // Another override is another scene: a new reference.
    let o = run("c", &["-D", "max_depth=3"]);
    assert_success(&o);
    assert_eq!(std::fs::read_dir(&cache).unwrap().count(), 4);
    for (extra, needle) in [
        (&["--methods", "mlt"][..], "unknown method"),
        (&["--sweep", "max_depth=1,2"][..], "cannot be swept"),
        (&["--crop", "0,0,64,64"][..], "--crop"),
        (
            &["--reference", "/nonexistent/ref.exr"][..],
            "/nonexistent/ref.exr",
        ),
    ] {
        let err = assert_clean_failure(&run("bad", extra), &format!("{extra:?}"));
        assert!(err.contains(needle), "{extra:?}: {err}");
    }
}
