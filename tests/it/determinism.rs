//! The same job and seed give the same bits however the work is split.

use pathfarm_render::{render, RenderSettings, Scene};

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
/// covering meshes and analytic shapes, every BSDF, textures, area and environment lights.
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
