//! Scenes whose radiance is known in closed form.

use crate::common::*;

/// Per-pixel test of an image against a known value: [`assert_pixels_agree`] (0.001 per
/// pixel and channel, zero-variance pixels exact, image mean within 4 standard errors) with
/// at most 1 % of the pixels failing (about 0.3 % fail under the null hypothesis).
fn assert_matches_constant(film: &pathfarm_render::Film, expected: [f32; 3], what: &str) {
    let diffs = PixelDiff::against(film, |_| expected, 0.0);
    assert_pixels_agree(&diffs, FailureCap::OnePercent, MeanTest::PerChannel, what);
}

/// A one-sided diffuse plane of albedo `albedo` (20 x 20, facing +z at z = 0) lit by
/// `light`.
fn lit_plane(light: &str, albedo: f32) -> String {
    format!(
        r#"
        {light}
        <shape type="rectangle"><transform name="to_world"><scale value="10"/></transform>
            <bsdf type="diffuse"><rgb name="reflectance" value="{albedo}"/></bsdf></shape>"#
    )
}

/// Renders `body` seen from (0, 0, `cam_z`) on a `res` x `res` film with direct lighting
/// only (`path`, max_depth 2).
fn render_direct(
    tag: &str,
    res: u32,
    fov: f32,
    cam_z: f32,
    body: &str,
    spp: u32,
    seed: u64,
) -> pathfarm_render::Film {
    let integrator =
        r#"<integrator type="path"><integer name="max_depth" value="2"/></integrator>"#;
    render_xml(
        tag,
        &scene_xml(res, res, fov, cam_z, integrator, body),
        spp,
        seed,
    )
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
    let film = render_direct("sky-plane", 12, 20.0, 3.0, PLANE_UNDER_SKY, 64, 3);
    assert_matches_constant(&film, [1.0, 0.25, 0.4], "plane under sky");
}

#[test]
fn point_light_over_diffuse_plane_matches_inverse_square_law() {
    // Centre pixel of a narrow view straight down the light's axis:
    // L = albedo / pi * I / h^2 (footprint effects below 1e-4).
    let body = lit_plane(
        r#"<emitter type="point"><point name="position" x="0" y="0" z="2"/><rgb name="intensity" value="10"/></emitter>"#,
        0.5,
    );
    let film = render_direct("point", 5, 0.5, 10.0, &body, 16, 1);
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
    let body = lit_plane(
        r#"<emitter type="directional"><vector name="direction" x="0.8660254" y="0" z="-0.5"/><rgb name="irradiance" value="4"/></emitter>"#,
        0.6,
    );
    let film = render_direct("sun", 5, 10.0, 5.0, &body, 4, 1);
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
    let body = lit_plane(
        r#"<shape type="disk"><transform name="to_world"><rotate x="1" angle="180"/><scale value="0.5"/><translate z="1"/></transform>
            <emitter type="area"><rgb name="radiance" value="5"/></emitter></shape>"#,
        0.5,
    );
    // The camera looks at the plane's centre from the side, below the disk.
    let xml = cam_scene_xml(
        r#"<integrator type="path"><integer name="max_depth" value="2"/></integrator>"#,
        Cam::new([3.0, 0.0, 0.6], [0.0; 3], 0.5, 3),
        &body,
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
    let film = render_direct("envmap-scene", 8, 20.0, 3.0, &body, 64, 9);
    assert_matches_constant(&film, [0.4, 0.2, 0.8], "envmap sky");
}
