//! The same job and seed give the same bits however the work is split.

use glam::Vec3;
use pathfarm_render::film::PixelStats;
use pathfarm_render::{
    path_estimator, render, render_into, sample_region, Film, Region, RenderSettings, Scene,
    UnitSplat,
};
use pathfarm_scene::{
    load_scene, load_scene_as, load_scene_geometry_as, scan_scene_as, world_source, Limits,
};
use pathfarm_testkit::TestRng;
use std::fs;
use std::path::{Path, PathBuf};

use crate::common::*;

#[test]
fn image_is_bit_identical_across_threads_and_work_splits() {
    let scene = build_scene(
        &shared_scene("cornell-box"),
        &[("resx", "40"), ("resy", "30")],
    );
    let base = RenderSettings::new(Some(6), None, 11);
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    let one = pool(1).install(|| render(&scene, &base, &|_| {}).0);
    let two = pool(2).install(|| render(&scene, &base, &|_| {}).0);
    assert_eq!(film_bits(&one), film_bits(&two), "1 vs 2 threads");
    let odd_tiles = RenderSettings {
        tile_size: 7,
        ..base.clone()
    };
    assert_eq!(
        film_bits(&one),
        film_bits(&render(&scene, &odd_tiles, &|_| {}).0),
        "tile size 16 vs 7"
    );
    // Passes are part of the job: splitting 6 spp into 6 passes adds the same
    // samples in another order, so the image agrees to rounding, not bits.
    let passes = RenderSettings {
        pass_spp: Some(1),
        ..base.clone()
    };
    let split = render(&scene, &passes, &|_| {}).0;
    for (a, b) in one.mean_rgb().iter().zip(split.mean_rgb()) {
        for c in 0..3 {
            assert!(
                (a[c] - b[c]).abs() <= 1e-5 * a[c].abs().max(1e-3),
                "one pass vs six: {a:?} {b:?}"
            );
        }
    }
    let other_seed = RenderSettings { seed: 12, ..base };
    assert_ne!(
        film_bits(&one),
        film_bits(&render(&scene, &other_seed, &|_| {}).0),
        "a different seed changes the image"
    );
}

#[test]
fn samples_rendered_by_tile_and_splatted_as_they_arrive_give_the_whole_image_bits() {
    // The farm's few-spp units travel as samples: each tile renders its own pixels' samples
    // (no halo), a UnitSplat gathers each tile's pixels out of its neighbours' reach as it
    // arrives and the bands along the tiles' edges at the end. That must be the film a
    // whole-image render gives, bit for bit, however the image was cut and in whatever
    // order the tiles arrive, also with several render calls (passes) and when the samples
    // are splatted in several passes of a call (a small pass size).
    let scene = build_scene(
        &shared_scene("cornell-box"),
        &[("resx", "37"), ("resy", "23")],
    );
    let (w, h) = (scene.width, scene.height);
    let est = path_estimator(&scene);
    for (spp, calls, pass_spp) in [(1, 1, None), (3, 1, None), (3, 1, Some(2)), (2, 3, None)] {
        let settings = RenderSettings {
            pass_spp,
            ..RenderSettings::new(Some(spp), None, 5)
        };
        let firsts: Vec<u64> = (0..calls).map(|c| 100 + c * spp as u64).collect();
        let mut whole = Film::new(w, h);
        for &first in &firsts {
            render_into(&scene, &settings, &|_| {}, first, &mut whole, &est);
        }
        for (tile, order_seed) in [(5, 1), (16, 2), (64, 3), (7, 4)] {
            let mut tiles = Region::tiles(w, h, tile);
            TestRng::new(order_seed).shuffle(&mut tiles);
            let new =
                |firsts: &[u64]| UnitSplat::new(scene.filter, (w, h), (&settings, spp), firsts);
            let (mut splat, mut shifted) = (new(&firsts), new(&[firsts[0] + 1]));
            // A farm coordinator's way: a splat reused from another unit, over a film that
            // still holds that unit's pixels, each region prepared apart by the plan; and a
            // one-process render's way over such a film.
            let mut dirty = Film::new(w, h);
            let smudge = |p: &mut PixelStats| p.add(0.75, Vec3::splat(2.0));
            dirty.pixels.iter_mut().for_each(smudge);
            let dirty_film = dirty.clone();
            let (mut reused, mut reused_added) = (new(&[firsts[0] + 7]), new(&[firsts[0] + 7]));
            let mut early = new(&[firsts[0] + 7]);
            for s in [&mut reused, &mut reused_added, &mut early] {
                // (an earlier unit's samples left in the buffers)
                for &r in &tiles {
                    s.add(r, &vec![Vec3::splat(3.0); s.plan().samples(r)]);
                }
                s.finish(&tiles);
            }
            reused.reuse((&settings, spp), &firsts, dirty.clone());
            reused_added.reuse((&settings, spp), &firsts, dirty.clone());
            // and one whose interiors are merged into the target as they come in (the oldest
            // unit's, in a session), over a film whose stale pixels must not be merged again
            early.reuse((&settings, spp), &firsts, dirty);
            let mut merged_early = dirty_film.clone();
            let plan = reused.plan().clone();
            for &r in &tiles {
                let mut values = Vec::new();
                for &first in &firsts {
                    let (v, stats) = sample_region(&scene, &settings, &|_| {}, first, r, &est);
                    assert_eq!((v.len(), stats.spp), (r.pixels() * spp as usize, spp));
                    values.extend(v);
                }
                splat.add(r, &values);
                reused.add_prepared(&plan.prepare(r, &values));
                early.add_prepared(&plan.prepare(r, &values));
                if r.x0 % 2 == 0 {
                    early.merge_interiors(&mut merged_early);
                }
                reused_added.add(r, &values);
                if calls == 1 {
                    shifted.add(r, &values);
                }
            }
            let what =
                format!("{spp} spp x {calls} calls, passes {pass_spp:?}, {tile}-pixel tiles");
            assert_eq!(
                film_bits(&splat.finish(&tiles).into_film()),
                film_bits(&whole),
                "{what}"
            );
            // The prepared interiors are held apart: merged into a film as if in place.
            let reused = reused.finish(&tiles);
            let mut merged = dirty_film.clone();
            reused.merge_into(&mut merged);
            let mut expected = dirty_film.clone();
            expected.merge(&whole);
            assert_eq!(film_bits(&merged), film_bits(&expected), "merged: {what}");
            early.finish(&tiles).merge_into(&mut merged_early);
            assert_eq!(
                film_bits(&merged_early),
                film_bits(&expected),
                "merged early: {what}"
            );
            assert_eq!(
                film_bits(&reused.into_film()),
                film_bits(&whole),
                "reused: {what}"
            );
            let reused = reused_added.finish(&tiles).into_film();
            assert_eq!(
                film_bits(&reused),
                film_bits(&whole),
                "reused, added: {what}"
            );
            if calls == 1 {
                // positions drawn from other streams give another film: they are really drawn
                let other = shifted.finish(&tiles).into_film();
                assert_ne!(film_bits(&other), film_bits(&whole), "{what}");
            }
        }
    }
}

#[test]
fn cli_output_is_identical_for_one_and_two_threads() {
    let dir = temp_dir("cli-threads");
    let scene = shared_scene("cornell-box");
    let mut outs = Vec::new();
    for t in ["1", "2"] {
        let out = dir.join(format!("t{t}.exr"));
        let extra = [
            "--spp",
            "4",
            "--threads",
            t,
            "-D",
            "resx=32",
            "-D",
            "resy=32",
            "--aovs",
        ];
        let stdout = assert_success(&pathfarm_render(&scene, &out, &extra));
        assert!(
            stdout.contains("summary: resolution=32x32 spp=4"),
            "{stdout}"
        );
        outs.push(std::fs::read(&out).unwrap());
        assert!(out.with_extension("png").exists());
    }
    assert_eq!(outs[0], outs[1]);
}

/// `render` runs the path integrator over batches of paths side by side; the one-path
/// estimator (`path::li`, one camera sample at a time) must give the same bits, on scenes
/// covering meshes and analytic shapes, every BSDF, textures, area and environment lights,
/// surfaces paths step through (`mask`, `null`) and perturbed normals.
#[test]
fn batched_path_integrator_equals_the_one_path_estimator_bit_for_bit() {
    use pathfarm_render::integrator::{path, specialised, Specialise};
    use pathfarm_render::{geometry::Ray, rng::Rng};
    /// `path::li` for a scene's features.
    struct PathLi;
    impl Specialise for PathLi {
        type Output = fn(&Scene, Ray, &mut Rng) -> glam::Vec3;
        fn call<const ENV: bool, const ANALYTIC: bool>(self) -> Self::Output {
            path::li::<ENV, ANALYTIC>
        }
    }
    use pathfarm_render::{render_into, Film};
    for (name, file) in [
        ("cornell-box", shared_scene("cornell-box")),
        ("materials", project_scene("materials")),
        ("caustic", project_scene("caustic")),
        ("white-furnace", project_scene("white-furnace")),
        ("cutouts", project_scene("cutouts")),
        ("bumps", project_scene("bumps")),
    ] {
        let scene = build_scene(&file, &[("resx", "24"), ("resy", "18")]);
        let settings = RenderSettings::new(Some(5), None, 3);
        let batched = render(&scene, &settings, &|_| {}).0;
        let li = specialised(&scene, PathLi);
        let one_path = |ray, rng: &mut _, _pixel| li(&scene, ray, rng);
        let mut single = Film::new(scene.width, scene.height);
        render_into(&scene, &settings, &|_| {}, 0, &mut single, &one_path);
        assert_eq!(film_bits(&batched), film_bits(&single), "{name}");
        assert!(
            batched.mean_rgb().iter().any(|p| p[0] > 0.0),
            "{name}: the image is not black"
        );
    }
}

/// The frames of a shot share one world: veach-ajar (PLY and OBJ meshes, JPEG textures, an
/// area light) with its camera moved, built on the first frame's world from a scan of its
/// text, renders the bits of the same frame built from its files, and the world sources of
/// the two frames are equal.
#[test]
fn a_frame_built_on_another_frames_world_renders_the_bits_of_its_own_build() {
    let src = shared_scene("veach-ajar");
    let dir = temp_dir("shared-world");
    for sub in ["models", "textures"] {
        fs::create_dir_all(dir.join(sub)).unwrap();
        for f in fs::read_dir(src.parent().unwrap().join(sub)).unwrap() {
            let f = f.unwrap().path();
            fs::copy(&f, dir.join(sub).join(f.file_name().unwrap())).unwrap();
        }
    }
    let xml = fs::read_to_string(&src).unwrap();
    let eye = "4.05402 2.71355e-008";
    assert!(xml.contains(eye));
    let (first, moved) = (dir.join("frame-1.xml"), dir.join("frame-2.xml"));
    fs::write(&first, &xml).unwrap();
    fs::write(&moved, xml.replace(eye, "3.95402 2.71355e-008")).unwrap();
    let defines: Vec<(String, String)> = [("resx", "48"), ("resy", "27")]
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .to_vec();
    let limits = Limits::default();
    let world_of = |p: &Path| world_source(p, &defines, &limits).unwrap();
    assert_eq!(world_of(&first), world_of(&moved));
    let build = |p: &Path| Scene::build(&load_scene(p, &defines).unwrap()).unwrap();
    let a = build(&first);
    let own = build(&moved);
    let scan = scan_scene_as(&moved, &defines, &limits, None).unwrap();
    let shared = Scene::with_world(&scan, a.shared_world()).unwrap();
    assert!(std::ptr::eq(shared.world(), a.world()));
    let settings = RenderSettings::new(Some(4), None, 3);
    let image = |s: &Scene| film_bits(&render(s, &settings, &|_| {}).0);
    let own_bits = image(&own);
    assert_eq!(own_bits, image(&shared), "the frame on a shared world");
    assert_ne!(own_bits, image(&a), "the cameras differ");
    // A world is not another scene's: the shape count is checked.
    let other = load_scene(&shared_scene("cornell-box"), &[]).unwrap();
    assert!(Scene::with_world(&other, a.shared_world()).is_err());
}

/// The coordinator validates a submission from a read of its scene that leaves the images
/// undecoded (`load_scene_geometry_as`: headers checked, stand-ins in their place), and
/// starts the job's session from it: for every scene shipped (envmaps, textures, masks and
/// bump maps among them), that read builds, and has the full load's files, film, filter,
/// sample count, bounds and fresh guide, so the session is the one a full load would start.
#[test]
fn a_scene_read_without_its_images_starts_the_session_a_full_load_would() {
    let mut scenes: Vec<PathBuf> = fs::read_dir(repo_root().join("scenes"))
        .unwrap()
        .map(|e| e.unwrap().path().join("scene.xml"))
        .filter(|p| p.exists())
        .collect();
    scenes.sort();
    scenes.extend(["cornell-box", "veach-ajar"].map(shared_scene));
    assert!(scenes.len() >= 10, "{scenes:?}");
    let limits = Limits::default();
    let guided = Some("guided_path");
    for path in &scenes {
        let full = load_scene_as(path, &[], &limits, guided).unwrap();
        let read = load_scene_geometry_as(path, &[], &limits, guided).unwrap();
        assert_eq!(read.files, full.files, "{}", path.display());
        let inspect = pathfarm_render::Purpose::Inspect;
        let (a, b) = (
            Scene::build_for(&full, inspect).unwrap(),
            Scene::build_for(&read, inspect).unwrap(),
        );
        let settings = |s: &Scene| (s.width, s.height, s.filter, s.sample_count, s.seed);
        assert_eq!(settings(&a), settings(&b), "{}", path.display());
        let params = a.guided.clone().expect("guided_path");
        let tree = |s: &Scene| {
            let (lo, hi) = s.world().accel.bounds();
            let config = pathfarm_render::guided::guide_config(&params, s);
            pathfarm_guide::SdTree::new(lo, hi, config).encode()
        };
        assert_eq!(tree(&a), tree(&b), "{}: the fresh guide", path.display());
    }
}
