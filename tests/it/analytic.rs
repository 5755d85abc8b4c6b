//! Scenes whose radiance is known in closed form.

use crate::common::*;

/// Per-pixel test of an image against a known value: a pixel fails when its
/// |Z| exceeds the two-sided 0.001 quantile. Under the null hypothesis about
/// 0.1 % of pixels fail; we allow 1 % (and require zero-variance pixels to be
/// exact), and the image mean must sit within 4 standard errors.
fn assert_matches_constant(film: &pathfarm_render::Film, expected: [f32; 3], what: &str) {
    let z_crit = z_two_sided(0.001);
    let mean = film.mean_rgb();
    let var = film.variance_rgb();
    let mut fails = 0;
    let mut examples = Vec::new();
    let (mut sum, mut sum_var) = ([0.0f64; 3], [0.0f64; 3]);
    for (m, v) in mean.iter().zip(&var) {
        let mut bad = false;
        for c in 0..3 {
            sum[c] += m[c] as f64;
            sum_var[c] += v[c] as f64;
            // Differences at float-rounding level pass; beyond that a pixel
            // needs a variance that explains them.
            let d = (m[c] - expected[c]) as f64;
            let rounding = 1e-5 * expected[c].max(1.0) as f64;
            bad |= d.abs() > rounding && (v[c] <= 0.0 || d.abs() / (v[c] as f64).sqrt() > z_crit);
        }
        if bad && examples.len() < 8 {
            examples.push(format!("{m:?}±{:?}", v.map(f32::sqrt)));
        }
        fails += bad as usize;
    }
    let n = mean.len() as f64;
    assert!(
        fails as f64 <= 0.01 * n,
        "{what}: {fails} of {n} pixels differ from {expected:?} at the 0.001 level: {examples:?}"
    );
    for c in 0..3 {
        let m = sum[c] / n;
        let se = (sum_var[c]).sqrt() / n;
        assert!(
            (m - expected[c] as f64).abs() <= 4.0 * se + 1e-6,
            "{what}: image mean {m} vs {} (se {se})",
            expected[c]
        );
    }
}

#[test]
fn white_furnace_diffuse_and_glass_are_invisible() {
    // Albedo-1 diffuse spheres (touching, so light inter-reflects) and a
    // lossless glass sphere in a uniform environment of radiance 1: every
    // pixel must be 1, however the paths bounce.
    let xml = scene_xml(
        24,
        24,
        40.0,
        5.0,
        r#"<integrator type="path"><integer name="max_depth" value="-1"/></integrator>"#,
        FURNACE_BODY,
    );
    let film = render_xml("furnace", &xml, 64, 7);
    assert_matches_constant(&film, [1.0; 3], "white furnace");
}

#[test]
fn diffuse_plane_under_uniform_sky_reflects_albedo_times_sky() {
    // Direct lighting only (max_depth 2): L = albedo * L_sky for a one-sided
    // diffuse plane facing up into a constant environment.
    let body = PLANE_UNDER_SKY;
    let xml = scene_xml(
        12,
        12,
        20.0,
        3.0,
        r#"<integrator type="path"><integer name="max_depth" value="2"/></integrator>"#,
        body,
    );
    let film = render_xml("sky-plane", &xml, 64, 3);
    assert_matches_constant(&film, [1.0, 0.25, 0.4], "plane under sky");
}

#[test]
fn point_light_over_diffuse_plane_matches_inverse_square_law() {
    // Centre pixel of a narrow view straight down the light's axis:
    // L = albedo / pi * I / h^2 (footprint effects below 1e-4).
    let body = r#"
        <emitter type="point"><point name="position" x="0" y="0" z="2"/><rgb name="intensity" value="10"/></emitter>
        <shape type="rectangle"><transform name="to_world"><scale value="10"/></transform>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>"#;
    let xml = scene_xml(
        5,
        5,
        0.5,
        10.0,
        r#"<integrator type="path"><integer name="max_depth" value="2"/></integrator>"#,
        body,
    );
    let film = render_xml("point", &xml, 16, 1);
    let c = film.mean_rgb()[2 * 5 + 2];
    let expected = 0.5 / std::f32::consts::PI * 10.0 / 4.0;
    for v in c {
        assert!((v - expected).abs() < 2e-4 * expected, "{v} vs {expected}");
    }
}

#[test]
fn max_depth_one_shows_only_emitters_and_hide_emitters_hides_them() {
    let body = r#"
        <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
        <shape type="rectangle"><transform name="to_world"><scale value="0.5"/></transform>
            <emitter type="area"><rgb name="radiance" value="3, 2, 1"/></emitter></shape>
        <shape type="rectangle"><transform name="to_world"><scale value="10"/><translate z="-1"/></transform>
            <bsdf type="diffuse"/></shape>"#;
    let xml = scene_xml(
        9,
        9,
        30.0,
        4.0,
        r#"<integrator type="path"><integer name="max_depth" value="1"/></integrator>"#,
        body,
    );
    let film = render_xml("depth1", &xml, 4, 1);
    let m = film.mean_rgb();
    assert_eq!(m[4 * 9 + 4], [3.0, 2.0, 1.0], "the emitter itself");
    assert_eq!(m[0], [0.0; 3], "a lit diffuse wall is black at max_depth 1");

    let hidden = scene_xml(
        9,
        9,
        30.0,
        4.0,
        r#"<integrator type="path"><boolean name="hide_emitters" value="true"/></integrator>"#,
        body,
    );
    let film = render_xml("hidden", &hidden, 16, 1);
    let c = film.mean_rgb()[4 * 9 + 4];
    assert!(
        c[0] < 1.0 && c[0] > 0.0,
        "the emitter is hidden and the wall behind it shows through: {c:?}"
    );
}

#[test]
fn directional_light_on_diffuse_plane_gives_lambert_cosine_law() {
    // L = albedo / pi * E * cos(theta) for a plane lit by a sun at 60 degrees.
    let body = r#"
        <emitter type="directional"><vector name="direction" x="0.8660254" y="0" z="-0.5"/><rgb name="irradiance" value="4"/></emitter>
        <shape type="rectangle"><transform name="to_world"><scale value="10"/></transform>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf></shape>"#;
    let xml = scene_xml(
        5,
        5,
        10.0,
        5.0,
        r#"<integrator type="path"><integer name="max_depth" value="2"/></integrator>"#,
        body,
    );
    let film = render_xml("sun", &xml, 4, 1);
    let expected = 0.6 / std::f32::consts::PI * 4.0 * 0.5;
    for p in film.mean_rgb() {
        for v in p {
            assert!((v - expected).abs() < 1e-4 * expected, "{v} vs {expected}");
        }
    }
}

#[test]
fn disk_light_over_diffuse_plane_matches_the_closed_form() {
    // Centre of a plane below a facing disk emitter of radius R at height h:
    // E = L pi R^2 / (h^2 + R^2), so L_o = albedo L R^2 / (h^2 + R^2). The disk
    // is hit both by NEE (area sampling) and by BSDF sampling (MIS).
    let body = r#"
        <shape type="disk"><transform name="to_world"><rotate x="1" angle="180"/><scale value="0.5"/><translate z="1"/></transform>
            <emitter type="area"><rgb name="radiance" value="5"/></emitter></shape>
        <shape type="rectangle"><transform name="to_world"><scale value="10"/></transform>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>"#;
    // The camera looks at the plane's centre from the side, below the disk.
    let xml = format!(
        r#"<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="2"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="0.5"/>
        <transform name="to_world"><lookat origin="3, 0, 0.6" target="0, 0, 0" up="0, 0, 1"/></transform>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
        <film type="hdrfilm"><integer name="width" value="3"/><integer name="height" value="3"/><rfilter type="box"/></film>
    </sensor>
    {body}
</scene>"#
    );
    let film = render_xml("disk", &xml, 4096, 5);
    let expected = 0.5 * 5.0 * 0.25 / (1.0 + 0.25);
    let m = film.mean_rgb()[4];
    let sd = film.variance_rgb()[4][0].sqrt();
    // The footprint of the centre pixel is ~1e-4 wide: its irradiance varies
    // by < 1e-6. Allow 4 standard errors (two-sided ~6e-5) plus that.
    assert!(
        (m[0] - expected).abs() < 4.0 * sd + 1e-5,
        "{} vs {expected} (sd {sd})",
        m[0]
    );
}

#[test]
fn envmap_of_constant_radiance_lights_like_a_constant_sky() {
    // A 16x8 EXR environment of radiance (1, 0.5, 2) and scale 0.5 must light
    // an upward plane exactly like a constant emitter: L = albedo * 0.5 * c.
    let dir = temp_dir("envmap");
    let env = dir.join("sky.exr");
    exr::prelude::write_rgb_file(&env, 16, 8, |_, _| (1.0f32, 0.5f32, 2.0f32)).unwrap();
    let body = format!(
        r#"<emitter type="envmap"><string name="filename" value="{}"/><float name="scale" value="0.5"/></emitter>
        <shape type="rectangle"><transform name="to_world"><scale value="100"/></transform>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf></shape>"#,
        env.display()
    );
    let xml = scene_xml(
        8,
        8,
        20.0,
        3.0,
        r#"<integrator type="path"><integer name="max_depth" value="2"/></integrator>"#,
        &body,
    );
    let path = dir.join("scene.xml");
    std::fs::write(&path, xml).unwrap();
    let film = render_file(&path, &[], 64, 9);
    assert_matches_constant(&film, [0.4, 0.2, 0.8], "envmap sky");
}
