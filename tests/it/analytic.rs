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
    assert!(fails as f64 <= 0.01 * n, "{what}: {fails} of {n} pixels differ from {expected:?} at the 0.001 level: {examples:?}");
    for c in 0..3 {
        let m = sum[c] / n;
        let se = (sum_var[c]).sqrt() / n;
        assert!((m - expected[c] as f64).abs() <= 4.0 * se + 1e-6, "{what}: image mean {m} vs {} (se {se})", expected[c]);
    }
}

#[test]
fn white_furnace_diffuse_and_glass_are_invisible() {
    // Albedo-1 diffuse spheres (touching, so light inter-reflects) and a
    // lossless glass sphere in a uniform environment of radiance 1: every
    // pixel must be 1, however the paths bounce.
    let body = r#"
        <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
        <shape type="sphere"><point name="center" x="-0.6" y="0" z="0"/><float name="radius" value="0.6"/>
            <bsdf type="diffuse"><rgb name="reflectance" value="1"/></bsdf></shape>
        <shape type="sphere"><point name="center" x="0.6" y="0" z="0"/><float name="radius" value="0.6"/>
            <bsdf type="diffuse"><rgb name="reflectance" value="1"/></bsdf></shape>
        <shape type="sphere"><point name="center" x="0" y="0.9" z="0.2"/><float name="radius" value="0.4"/>
            <bsdf type="dielectric"><float name="int_ior" value="1.5"/></bsdf></shape>
        <shape type="cube"><transform name="to_world"><scale value="0.3"/><translate x="0" y="-0.9" z="0"/></transform>
            <bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="1"/></bsdf></bsdf></shape>"#;
    let xml = scene_xml(24, 24, 40.0, 5.0, r#"<integrator type="path"><integer name="max_depth" value="-1"/></integrator>"#, body);
    let film = render_xml("furnace", &xml, 64, 7);
    assert_matches_constant(&film, [1.0; 3], "white furnace");
}

#[test]
fn diffuse_plane_under_uniform_sky_reflects_albedo_times_sky() {
    // Direct lighting only (max_depth 2): L = albedo * L_sky for a one-sided
    // diffuse plane facing up into a constant environment.
    let body = r#"
        <emitter type="constant"><rgb name="radiance" value="2, 1, 0.5"/></emitter>
        <shape type="rectangle"><transform name="to_world"><scale value="100"/></transform>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.5, 0.25, 0.8"/></bsdf></shape>"#;
    let xml = scene_xml(12, 12, 20.0, 3.0, r#"<integrator type="path"><integer name="max_depth" value="2"/></integrator>"#, body);
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
    let xml = scene_xml(5, 5, 0.5, 10.0, r#"<integrator type="path"><integer name="max_depth" value="2"/></integrator>"#, body);
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
    let xml = scene_xml(9, 9, 30.0, 4.0, r#"<integrator type="path"><integer name="max_depth" value="1"/></integrator>"#, body);
    let film = render_xml("depth1", &xml, 4, 1);
    let m = film.mean_rgb();
    assert_eq!(m[4 * 9 + 4], [3.0, 2.0, 1.0], "the emitter itself");
    assert_eq!(m[0], [0.0; 3], "a lit diffuse wall is black at max_depth 1");

    let hidden = scene_xml(9, 9, 30.0, 4.0, r#"<integrator type="path"><boolean name="hide_emitters" value="true"/></integrator>"#, body);
    let film = render_xml("hidden", &hidden, 16, 1);
    let c = film.mean_rgb()[4 * 9 + 4];
    assert!(c[0] < 1.0 && c[0] > 0.0, "the emitter is hidden and the wall behind it shows through: {c:?}");
}
