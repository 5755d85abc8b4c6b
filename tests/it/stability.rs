//! Numerical stability: scenes that break renderers (issue 27, part 2).
//!
//! Every case renders with both `path` and `guided_path`, asserts that the image is
//! finite everywhere with no sample rejected as non-finite, and compares it with a
//! closed-form value or a reference image by a per-pixel test (see [`assert_pixels_agree`]
//! in tests/common.rs for the significance levels). Unit cases of the guide (zero-energy
//! cells, poles and seam of the mapping, NaN/Inf records) live in
//! `crates/guide/src/sdtree/tests/stability.rs`.

use pathfarm_render::guided::{render_guided, Budget};
use pathfarm_render::{render, Film, RenderSettings, Scene};
use pathfarm_scene::load_scene;

use crate::common::*;

/// The two estimators under test.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Method {
    Path,
    Guided,
}

const METHODS: [Method; 2] = [Method::Path, Method::Guided];

impl Method {
    /// The `<integrator>` element with `max_depth` and `extra` parameters. Guided: the
    /// default (pathfarm) preset with guiding forced on (no fallback to path tracing, so the
    /// guide is what is tested) and only the last iteration kept (`discard`: inverse-variance
    /// combination is consistent but not unbiased at low spp, see tests/it/guided.rs).
    fn integrator(self, max_depth: i32, extra: &str) -> String {
        match self {
            Method::Path => format!(
                r#"<integrator type="path"><integer name="max_depth" value="{max_depth}"/>{extra}</integrator>"#
            ),
            Method::Guided => format!(
                r#"<integrator type="guided_path"><integer name="max_depth" value="{max_depth}"/>
                   <boolean name="path_fallback" value="false"/><string name="sample_combination" value="discard"/>{extra}</integrator>"#
            ),
        }
    }
}

/// A render's image and how many camera samples were rejected as non-finite.
struct Rendered {
    film: Film,
    invalid: u64,
}

fn build(tag: &str, xml: &str) -> Scene {
    let desc = load_scene(&write_scene(tag, xml), &[]).unwrap_or_else(|e| panic!("{tag}: {e}"));
    Scene::build(&desc).expect("build")
}

/// Renders `xml` with its integrator at `spp` (guided: a budget of `spp`, training
/// included).
fn render_xml_stats(tag: &str, xml: &str, spp: u32, seed: u64) -> Rendered {
    render_scene(&build(tag, xml), spp, seed)
}

fn render_scene(scene: &Scene, spp: u32, seed: u64) -> Rendered {
    let settings = RenderSettings::new(Some(spp), None, seed);
    match &scene.guided {
        None => {
            let (film, stats) = render(scene, &settings, &|_| {});
            Rendered {
                film,
                invalid: stats.invalid_samples,
            }
        }
        Some(params) => {
            let (film, stats, tree) = render_guided(
                scene,
                params,
                Budget::Spp(spp),
                &settings,
                Default::default(),
            );
            assert_eq!(stats.spp, spp);
            assert!(
                stats.iterations.len() >= 2,
                "the guide was trained and used: {stats:?}"
            );
            assert!(tree.is_built());
            Rendered {
                film,
                invalid: stats.invalid_samples,
            }
        }
    }
}

/// Every accumulator of every pixel is finite and no camera sample was rejected as
/// non-finite (the renderer zeroes such samples and counts them: a count above zero means
/// NaN/Inf was produced, even though the image looks finite).
fn assert_finite(r: &Rendered, what: &str) {
    assert_eq!(r.invalid, 0, "{what}: samples rejected as non-finite");
    let bad = film_bits(&r.film)
        .into_iter()
        .filter(|b| !f64::from_bits(*b).is_finite())
        .count();
    assert_eq!(bad, 0, "{what}: non-finite pixel accumulators");
    for m in r.film.mean_rgb() {
        assert!(m.iter().all(|c| c.is_finite()), "{what}: pixel mean {m:?}");
    }
}

/// Each pixel of `r` against `expected(pixel index)` ([`assert_pixels_agree`] with the
/// binomial failure cap).
fn assert_matches(r: &Rendered, expected: impl Fn(usize) -> [f32; 3], what: &str) {
    assert_matches_within(r, expected, 0.0, what)
}

/// [`assert_matches`] tolerating a known relative bias of up to `slack`.
fn assert_matches_within(
    r: &Rendered,
    expected: impl Fn(usize) -> [f32; 3],
    slack: f64,
    what: &str,
) {
    assert_finite(r, what);
    let diffs = PixelDiff::against(&r.film, expected, slack);
    assert_pixels_agree(
        &diffs,
        FailureCap::Binomial,
        MeanTest::PerChannelAndPooled,
        what,
    );
}

/// Two renders of the same expected image agree pixel by pixel ([`assert_pixels_agree`]
/// with the binomial failure cap).
fn assert_agree(a: &Rendered, b: &Rendered, what: &str) {
    assert_finite(a, what);
    assert_finite(b, what);
    let diffs = PixelDiff::between(&a.film, &b.film);
    assert_pixels_agree(
        &diffs,
        FailureCap::Binomial,
        MeanTest::PerChannelAndPooled,
        what,
    );
}

/// The seed of every render (renders in one test use it and the seeds just above it): 1, or
/// `PATHFARM_STABILITY_SEED` to run the suite with other seeds (it passed for 1, 2 and 3).
static SEED: std::sync::LazyLock<u64> = std::sync::LazyLock::new(|| {
    std::env::var("PATHFARM_STABILITY_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1)
});

#[test]
fn allowed_failures_is_the_binomial_tail_quantile() {
    // n = 256: P(X >= 7) = 1.8e-5 < 1e-4 <= P(X >= 6) = 1.3e-4 for Binomial(256, 0.003).
    assert_eq!(binomial_failure_cap(256), 6);
    assert_eq!(binomial_failure_cap(10_000), 100, "1 % floor");
}

// ---- 1. lights hidden inside fixtures -------------------------------------------------

/// A sphere lamp of radiance 10 sealed inside a closed two-sided diffuse cube ([-1, 1]^3).
const SEALED_LAMP: &str = r#"
    <shape type="cube"><bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf></bsdf></shape>
    <shape type="sphere"><float name="radius" value="0.2"/><emitter type="area"><rgb name="radiance" value="10"/></emitter></shape>"#;

#[test]
fn light_sealed_inside_a_closed_box_leaves_the_outside_exactly_black() {
    // No light path leaves the box: every light sample from outside is occluded and the
    // guide learns zero energy everywhere (its quadtrees stay empty). Exact: every pixel
    // is 0 with zero variance (seeds 1-3).
    let cam = Cam::new([3.0, -4.0, 2.5], [0.0; 3], 40.0, 16);
    for method in METHODS {
        let xml = cam_scene_xml(&method.integrator(-1, ""), cam, SEALED_LAMP);
        let r = render_xml_stats("sealed", &xml, 32, *SEED);
        assert_finite(&r, &format!("{method:?}"));
        for (i, p) in r.film.pixels.iter().enumerate() {
            assert!(
                p.sum_wl == [0.0; 3] && p.sum_w > 0.0,
                "{method:?}: pixel {i} is lit: {:?}",
                p.mean()
            );
        }
    }
}

#[test]
fn camera_inside_the_sealed_box_sees_its_lit_interior_as_both_estimators_agree() {
    // The same box seen from inside: the interior is lit (direct light on the walls and
    // inter-reflections). Path and guided must agree (statistics of `assert_pixels_agree`: 0.001 per
    // pixel, binomial count at 1e-4, image mean within 4 se; seeds 1-3).
    let cam = Cam::new([0.5, -0.9, 0.6], [0.0, 1.0, -0.5], 90.0, 16);
    let [path, guided] = METHODS.map(|m| {
        let xml = cam_scene_xml(&m.integrator(-1, ""), cam, SEALED_LAMP);
        render_xml_stats("sealed-inside", &xml, 256, *SEED + m as u64)
    });
    let lit = path.film.mean_rgb().iter().filter(|p| p[0] > 0.1).count();
    assert!(lit * 2 > path.film.pixels.len(), "the interior is lit");
    assert_agree(&path, &guided, "path vs guided inside the sealed box");
}

/// A lamp (sphere of radiance 50) inside a box ([-1, 1]^2 x [0, 2], two-sided diffuse
/// panels) whose only opening is a 0.3 x 0.3 hole in its floor, 1.5 above a diffuse ground.
fn fixture_with_hole() -> String {
    let panel = |transform: String| {
        format!(
            r#"<shape type="rectangle"><transform name="to_world">{transform}</transform><ref id="white"/></shape>"#
        )
    };
    let floor = |sx: f32, sy: f32, tx: f32, ty: f32| {
        panel(format!(
            r#"<scale x="{sx}" y="{sy}"/><translate x="{tx}" y="{ty}"/>"#
        ))
    };
    let panels = [
        // the floor: two full-depth strips beside the hole, two short ones before and behind it
        floor(0.425, 1.0, -0.575, 0.0),
        floor(0.425, 1.0, 0.575, 0.0),
        floor(0.15, 0.425, 0.0, -0.575),
        floor(0.15, 0.425, 0.0, 0.575),
        panel(r#"<translate z="2"/>"#.into()),
        panel(r#"<rotate x="1" angle="90"/><translate y="-1" z="1"/>"#.into()),
        panel(r#"<rotate x="1" angle="90"/><translate y="1" z="1"/>"#.into()),
        panel(r#"<rotate y="1" angle="90"/><translate x="-1" z="1"/>"#.into()),
        panel(r#"<rotate y="1" angle="90"/><translate x="1" z="1"/>"#.into()),
    ]
    .concat();
    format!(
        r#"<bsdf type="twosided" id="white"><bsdf type="diffuse"><rgb name="reflectance" value="0.7"/></bsdf></bsdf>
    {panels}
    <shape type="sphere"><point name="center" x="0" y="0" z="1"/><float name="radius" value="0.1"/>
        <emitter type="area"><rgb name="radiance" value="50"/></emitter></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="10"/><translate z="-1.5"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>"#
    )
}

#[test]
fn light_escaping_a_fixture_through_a_small_hole_renders_the_same_with_both_estimators() {
    // Light reaches the ground only through the hole (a bright spot below it, the rest
    // lit by inter-reflection). Path and guided must agree (statistics of `assert_pixels_agree`;
    // seeds 1-3).
    let cam = Cam::new([0.0, -5.0, -0.8], [0.0, 0.0, -1.5], 45.0, 16);
    let [path, guided] = METHODS.map(|m| {
        let xml = cam_scene_xml(&m.integrator(-1, ""), cam, &fixture_with_hole());
        render_xml_stats("fixture", &xml, 256, *SEED + m as u64)
    });
    let spot = path.film.mean_rgb().iter().fold(0.0f32, |a, p| a.max(p[0]));
    assert!(
        spot > 0.05,
        "light leaves through the hole: brightest {spot}"
    );
    assert_agree(&path, &guided, "path vs guided below the fixture");
}

// ---- 2. a tiny, very bright light ------------------------------------------------------

/// A diffuse ground and back wall lit by a black sphere lamp of radius `r` and radiance
/// `radiance` at (0, 0, 1).
fn sphere_lamp_room(r: f32, radiance: f32) -> String {
    format!(
        r#"<bsdf type="diffuse" id="grey"><rgb name="reflectance" value="0.6, 0.5, 0.4"/></bsdf>
    <shape type="rectangle"><transform name="to_world"><scale value="4"/></transform><ref id="grey"/></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="4"/><rotate x="1" angle="90"/><translate y="1.5"/></transform><ref id="grey"/></shape>
    <shape type="sphere"><point name="center" x="0" y="0" z="1"/><float name="radius" value="{r:e}"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>
        <emitter type="area"><rgb name="radiance" value="{radiance:e}"/></emitter></shape>"#
    )
}

#[test]
fn tiny_bright_light_renders_the_image_of_a_large_one_of_the_same_power() {
    // A Lambertian sphere of radius r and radiance L irradiates every point that sees all
    // of it (the sphere above the horizon, h = 1 > r) exactly like a point source of
    // intensity pi r^2 L, so a lamp of radius 1e-4 and radiance 1e7 must render what one
    // of radius 0.1 and radiance 10 does. The only difference in expectation is the large
    // lamp's silhouette occluding inter-reflected light (< 0.03 sr of the hemisphere, under
    // 0.1 % of the image, far below the test's resolution). The camera passes through
    // emitters (`hide_emitters`), so neither lamp is seen directly. Statistics of `assert_pixels_agree`
    // (seeds 1-3).
    let cam = Cam::new([0.0, -4.0, 2.0], [0.0, 0.0, 0.4], 50.0, 16);
    for method in METHODS {
        let integrator = method.integrator(4, r#"<boolean name="hide_emitters" value="true"/>"#);
        let render_lamp = |r: f32, l: f32, seed: u64| {
            let xml = cam_scene_xml(&integrator, cam, &sphere_lamp_room(r, l));
            render_xml_stats("lamp", &xml, 128, seed)
        };
        let large = render_lamp(0.1, 10.0, *SEED);
        let tiny = render_lamp(1e-4, 1e7, *SEED + 10);
        assert_agree(&tiny, &large, &format!("{method:?}: tiny vs large lamp"));
    }
}

// ---- 3. grazing incidence, a camera just above a surface -------------------------------

#[test]
fn camera_a_hair_above_a_plane_at_grazing_angles_sees_albedo_times_sky() {
    // The camera 1e-4 above a one-sided diffuse plane under a constant sky, looking 1 to 5
    // degrees below the horizon: every ray hits the plane at a grazing angle, within 7e-3
    // of the camera. The plane reflects L = albedo * sky whatever the depth (the light it
    // reflects escapes), so every pixel's expectation is known. Statistics of `assert_pixels_agree`
    // (seeds 1-3).
    let body = PLANE_UNDER_SKY;
    // (Mitsuba's default near_clip, 0.01, would clip every hit: 1e-6 here.)
    let cam = Cam {
        near: 1e-6,
        ..Cam::new([0.0, 0.0, 1e-4], [1.0, 0.0, -0.05], 4.0, 16)
    };
    for method in METHODS {
        let xml = cam_scene_xml(&method.integrator(-1, ""), cam, body);
        let r = render_xml_stats("grazing", &xml, 64, *SEED);
        assert_matches(&r, |_| [1.0, 0.25, 0.4], &format!("{method:?}: grazing"));
    }
}

// ---- 4. near-specular roughness ---------------------------------------------------------

/// Furnace objects: a sphere of `bsdf` (lossless) in a constant environment of radiance 1.
fn furnace_sphere(bsdf: &str) -> String {
    format!(
        r#"<emitter type="constant"><rgb name="radiance" value="1"/></emitter>
    <shape type="sphere"><float name="radius" value="1"/>{bsdf}</shape>"#
    )
}

#[test]
fn near_specular_rough_mirror_and_glass_vanish_in_the_white_furnace() {
    // alpha 1e-4 GGX: the microfacet density peaks at 1 / (pi alpha^2) = 3e7 and
    // evaluations away from the mirror direction underflow. A lossless mirror
    // (`material` none) and glass are invisible in a furnace: every pixel is 1 (the energy
    // a single-scattering microfacet model loses at this roughness is below 1e-6).
    // Statistics of `assert_pixels_agree` (seeds 1-3).
    let cases = [
        (
            "roughconductor",
            r#"<bsdf type="roughconductor"><string name="material" value="none"/><float name="alpha" value="1e-4"/></bsdf>"#,
        ),
        (
            "roughdielectric",
            r#"<bsdf type="roughdielectric"><float name="int_ior" value="1.5"/><float name="alpha" value="1e-4"/></bsdf>"#,
        ),
        (
            "roughdielectric-beckmann",
            r#"<bsdf type="roughdielectric"><string name="distribution" value="beckmann"/><float name="int_ior" value="1.5"/><float name="alpha" value="1e-4"/></bsdf>"#,
        ),
    ];
    assert_invisible_in_the_furnace(&cases);
}

/// Each `(tag, bsdf)` on a sphere in the white furnace, with both integrators: every pixel
/// must be 1 (statistics of `assert_pixels_agree`).
fn assert_invisible_in_the_furnace(cases: &[(&str, &str)]) {
    let cam = Cam::new([0.0, -4.0, 0.0], [0.0; 3], 35.0, 16);
    for &(tag, bsdf) in cases {
        for method in METHODS {
            let xml = cam_scene_xml(&method.integrator(-1, ""), cam, &furnace_sphere(bsdf));
            let r = render_xml_stats(tag, &xml, 64, *SEED);
            assert_matches(&r, |_| [1.0; 3], &format!("{method:?}: {tag} furnace"));
        }
    }
}

/// Three spheres on a diffuse ground under a sky and a disk lamp: a gold mirror, a plastic
/// and a glass, `rough` (alpha 1e-4) or smooth.
fn three_spheres(rough: bool) -> String {
    let (conductor, plastic, dielectric) = if rough {
        (
            r#"<bsdf type="roughconductor"><string name="material" value="Au"/><float name="alpha" value="1e-4"/></bsdf>"#,
            r#"<bsdf type="roughplastic"><rgb name="diffuse_reflectance" value="0.2, 0.4, 0.7"/><float name="alpha" value="1e-4"/></bsdf>"#,
            r#"<bsdf type="roughdielectric"><float name="int_ior" value="1.5"/><float name="alpha" value="1e-4"/></bsdf>"#,
        )
    } else {
        (
            r#"<bsdf type="conductor"><string name="material" value="Au"/></bsdf>"#,
            r#"<bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.2, 0.4, 0.7"/></bsdf>"#,
            r#"<bsdf type="dielectric"><float name="int_ior" value="1.5"/></bsdf>"#,
        )
    };
    format!(
        r#"<emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
    <shape type="disk"><transform name="to_world"><rotate x="1" angle="180"/><scale value="0.7"/><translate x="1" y="-1" z="3"/></transform>
        <emitter type="area"><rgb name="radiance" value="8"/></emitter></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="10"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.5, 0.3"/></bsdf></shape>
    <shape type="sphere"><point name="center" x="-1.1" y="0" z="0.5"/><float name="radius" value="0.5"/>{conductor}</shape>
    <shape type="sphere"><point name="center" x="0" y="0" z="0.5"/><float name="radius" value="0.5"/>{plastic}</shape>
    <shape type="sphere"><point name="center" x="1.1" y="0" z="0.5"/><float name="radius" value="0.5"/>{dielectric}</shape>"#
    )
}

#[test]
fn near_specular_conductor_plastic_and_glass_render_like_their_smooth_versions() {
    // alpha 1e-4 is a mirror to within far less than a pixel's footprint here, so each
    // rough BSDF must render the smooth one's image. Statistics of `assert_pixels_agree` (seeds 1-3).
    let cam = Cam::new([0.0, -5.0, 1.5], [0.0, 0.0, 0.4], 40.0, 24);
    for method in METHODS {
        let [smooth, rough] = [false, true].map(|rough| {
            let xml = cam_scene_xml(&method.integrator(-1, ""), cam, &three_spheres(rough));
            render_xml_stats("near-specular", &xml, 128, *SEED + rough as u64)
        });
        assert_agree(
            &rough,
            &smooth,
            &format!("{method:?}: alpha 1e-4 vs smooth"),
        );
    }
}

// ---- 5. index-matched dielectric -----------------------------------------------------------

/// Dielectrics whose interior and exterior IOR are equal (1.33 both, or 1 both).
const INDEX_MATCHED: [(&str, &str); 4] = [
    (
        "dielectric-1",
        r#"<bsdf type="dielectric"><float name="int_ior" value="1"/><float name="ext_ior" value="1"/></bsdf>"#,
    ),
    (
        "dielectric-water",
        r#"<bsdf type="dielectric"><float name="int_ior" value="1.33"/><float name="ext_ior" value="1.33"/></bsdf>"#,
    ),
    (
        "roughdielectric-1",
        r#"<bsdf type="roughdielectric"><float name="int_ior" value="1"/><float name="ext_ior" value="1"/><float name="alpha" value="0.3"/></bsdf>"#,
    ),
    (
        "thindielectric-1",
        r#"<bsdf type="thindielectric"><float name="int_ior" value="1"/><float name="ext_ior" value="1"/></bsdf>"#,
    ),
];

#[test]
fn index_matched_dielectrics_vanish_in_the_white_furnace() {
    // Equal IORs: no reflection, no refraction, light passes straight through, so the
    // sphere is invisible: every pixel is 1. Statistics of `assert_pixels_agree` (seeds 1-3).
    assert_invisible_in_the_furnace(&INDEX_MATCHED);
}

#[test]
fn index_matched_dielectrics_in_a_lit_scene_leave_its_image_unchanged() {
    // A ground and a wall under a sky and a large lamp, with and without an index-matched
    // sphere between them and the camera: the images must agree. The sphere's surface is
    // a delta (or, rough, a near-delta) interface, so light through it is found only by
    // BSDF sampling: the sky and a large lamp keep that estimator's tails light enough for
    // per-pixel variance estimates. Statistics of `assert_pixels_agree` (seeds 1-3).
    let lit = r#"<emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
        <bsdf type="diffuse" id="grey"><rgb name="reflectance" value="0.6, 0.5, 0.4"/></bsdf>
        <shape type="rectangle"><transform name="to_world"><scale value="4"/></transform><ref id="grey"/></shape>
        <shape type="rectangle"><transform name="to_world"><scale value="4"/><rotate x="1" angle="90"/><translate y="1.5"/></transform><ref id="grey"/></shape>
        <shape type="sphere"><point name="center" x="1" y="0" z="2.5"/><float name="radius" value="0.6"/>
            <emitter type="area"><rgb name="radiance" value="3"/></emitter></shape>"#;
    let cam = Cam::new([0.0, -4.0, 2.0], [0.0, 0.0, 0.4], 50.0, 16);
    for method in METHODS {
        let integrator = method.integrator(-1, "");
        let empty = render_xml_stats(
            "matched-empty",
            &cam_scene_xml(&integrator, cam, lit),
            128,
            *SEED,
        );
        for (tag, bsdf) in INDEX_MATCHED {
            let body = format!(
                r#"{lit}<shape type="sphere"><point name="center" x="0.2" y="-0.8" z="0.8"/><float name="radius" value="0.6"/>{bsdf}</shape>"#
            );
            let r = render_xml_stats(tag, &cam_scene_xml(&integrator, cam, &body), 128, *SEED + 1);
            assert_agree(&r, &empty, &format!("{method:?}: {tag} in the lit scene"));
        }
    }
}

// ---- 6. degenerate and zero-area triangles -------------------------------------------------

/// An OBJ of the unit quad [-1, 1]^2 at height `z` (two triangles), followed by `extra`.
fn quad_obj(z: f32, extra: &str) -> String {
    format!("v -1 -1 {z}\nv 1 -1 {z}\nv 1 1 {z}\nv -1 1 {z}\nf 1 2 3\nf 1 3 4\n{extra}")
}

/// Zero-area triangles laid across the quad's view, 0.1 in front of it (vertices 5-9):
/// a point (one vertex three times), repeated indices, and two collinear segments (one
/// along each diagonal, through the centre), so a ray that "hit" one would show it.
const DEGENERATE: &str =
    "v -0.9 -0.9 0.1\nv 0.9 0.9 0.1\nv 0 0 0.1\nv 0.9 -0.9 0.1\nv -0.9 0.9 0.1\n\
f 7 7 7\nf 5 5 6\nf 5 7 6\nf 8 7 9\nf 8 9 8\n";

/// Renders `xml` whose `<shape type="obj">` reads `mesh.obj` (written with `obj`).
fn render_with_obj(tag: &str, xml: &str, obj: &str, spp: u32, seed: u64) -> Rendered {
    let path = write_scene(tag, xml);
    std::fs::write(path.with_file_name("mesh.obj"), obj).unwrap();
    let desc = load_scene(&path, &[]).unwrap_or_else(|e| panic!("{tag}: {e}"));
    render_scene(&Scene::build(&desc).expect("build"), spp, seed)
}

#[test]
fn degenerate_triangles_in_a_mesh_are_never_hit_and_change_nothing() {
    // A diffuse quad under a sky, with and without zero-area triangles in the same mesh
    // file (the loader keeps them; they must be invisible, never intersected). The quad's
    // pixels must match: the plane reflects albedo * sky (0.5) and the sky shows around
    // it (1). Statistics of `assert_pixels_agree` (seeds 1-3).
    let body = r#"<emitter type="constant"><rgb name="radiance" value="1"/></emitter>
        <shape type="obj"><string name="filename" value="mesh.obj"/>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>"#;
    let cam = Cam::new([0.0, 0.0, 3.0], [0.0; 3], 30.0, 16);
    let cam = Cam {
        up: [0.0, 1.0, 0.0],
        ..cam
    };
    for method in METHODS {
        let xml = cam_scene_xml(&method.integrator(-1, ""), cam, body);
        let clean = render_with_obj("quad", &xml, &quad_obj(0.0, ""), 64, *SEED);
        let degenerate = render_with_obj("degenerate", &xml, &quad_obj(0.0, DEGENERATE), 64, *SEED);
        let (mc, md) = (clean.film.mean_rgb(), degenerate.film.mean_rgb());
        assert_matches(
            &degenerate,
            |i| mc[i].map(|c| if c > 0.99 { 1.0 } else { 0.5 }),
            &format!("{method:?}: degenerate mesh"),
        );
        // Identical geometry, so identical hits: the same image to the bit (checked per
        // pixel mean; the BVH differs, the closest hits and random numbers do not).
        assert_eq!(mc, md, "{method:?}: degenerate triangles changed the image");
    }
}

#[test]
fn emitting_mesh_with_zero_area_triangles_lights_like_the_clean_mesh() {
    // An area light whose OBJ mixes the lamp quad with zero-area triangles: light
    // sampling picks triangles by area, so a zero-area one must never be picked (its
    // solid-angle pdf would be infinite). Floor below, lit only by the lamp; the image
    // must agree with the clean lamp's. Statistics of `assert_pixels_agree` (seeds 1-3).
    let body = r#"<shape type="obj"><string name="filename" value="mesh.obj"/>
            <transform name="to_world"><scale value="0.5"/><rotate x="1" angle="180"/><translate z="2"/></transform>
            <emitter type="area"><rgb name="radiance" value="4"/></emitter></shape>
        <shape type="rectangle"><transform name="to_world"><scale value="5"/></transform>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf></shape>"#;
    let cam = Cam::new([0.0, -4.0, 3.0], [0.0; 3], 45.0, 16);
    for method in METHODS {
        let xml = cam_scene_xml(&method.integrator(-1, ""), cam, body);
        let clean = render_with_obj("lamp-clean", &xml, &quad_obj(0.0, ""), 64, *SEED);
        let degenerate = render_with_obj(
            "lamp-degenerate",
            &xml,
            &quad_obj(0.0, DEGENERATE),
            64,
            *SEED + 1,
        );
        assert_agree(
            &degenerate,
            &clean,
            &format!("{method:?}: lamp with zero-area triangles"),
        );
    }
}

#[test]
fn mesh_of_only_zero_area_triangles_loads_and_renders_nothing() {
    // Every triangle degenerate: the mesh loads (or is refused with a message naming it)
    // and, as an emitter, emits nothing; the image is the black background. Exact.
    let body = r#"<shape type="obj"><string name="filename" value="mesh.obj"/>
            <emitter type="area"><rgb name="radiance" value="4"/></emitter></shape>
        <shape type="rectangle"><transform name="to_world"><scale value="5"/><translate z="-1"/></transform>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf></shape>"#;
    let obj = format!("v 0 0 0\nv 0 0 0\nv 0 0 0\nv 0 0 0\n{DEGENERATE}");
    assert_eq!(obj.matches("\nf ").count(), 5, "only the degenerate faces");
    let cam = Cam::new([0.0, -4.0, 3.0], [0.0; 3], 45.0, 16);
    for method in METHODS {
        let xml = cam_scene_xml(&method.integrator(-1, ""), cam, body);
        let path = write_scene("only-degenerate", &xml);
        std::fs::write(path.with_file_name("mesh.obj"), &obj).unwrap();
        let scene = match load_scene(&path, &[]) {
            Ok(desc) => Scene::build(&desc).expect("build"),
            Err(e) => {
                assert!(e.to_string().contains("mesh.obj"), "{e}");
                continue;
            }
        };
        let r = render_scene(&scene, 16, *SEED);
        assert_finite(&r, &format!("{method:?}"));
        assert!(
            r.film.mean_rgb().iter().all(|p| *p == [0.0; 3]),
            "{method:?}: a zero-area emitter lit the scene"
        );
    }
}

// ---- 8. a camera inside an object ------------------------------------------------------------

/// The inside of a closed sphere of radius 1 (normals flipped inwards) that emits `le`
/// and reflects diffusely with albedo `albedo`.
fn glowing_sphere_interior(le: f32, albedo: f32) -> String {
    format!(
        r#"<shape type="sphere"><float name="radius" value="1"/><boolean name="flip_normals" value="true"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="{albedo}"/></bsdf>
        <emitter type="area"><rgb name="radiance" value="{le}"/></emitter></shape>"#
    )
}

/// A camera at `origin` inside the unit sphere, looking sideways.
fn inside_cam(res: u32) -> Cam {
    Cam::new([0.2, -0.3, 0.1], [1.0, 0.5, 0.3], 60.0, res)
}

/// Found, not fixed: inside the glowing sphere every path's value is the same
/// Le (1 + a + ...) (the MIS weights of light and BSDF samples are 1/2 each there, every
/// term deterministic), yet 17 % of samples come out low by 5e-5 or more (at most 0.1, a
/// continuum, never high), scalar and wavefront estimators alike: over 100000 samples the
/// mean is low by 5.2e-5 relative with albedo 0.6 (about 1.3e-4 for 1000 bounces at
/// 0.999). Not occlusion: in 200000 probes from hit points on the sphere no shadow ray was
/// occluded and no continuation ray missed. Probable cause (an estimate, not verified): a
/// continuation ray starts 4e-5 off the surface, so one leaving at a grazing elevation
/// theta below about sqrt(2 * 4e-5) = 9e-3 meets the concave wall far beyond the point its
/// direction from the surface point reaches, and the BSDF side's MIS weight, which
/// evaluates the light pdf at the point actually hit, drops from 1/2 towards 0 while the
/// light side kept 1/2; such directions have probability theta^2 = 8e-5 per bounce, the
/// size of the deficit. The tests tolerate a relative deficit of about twice the measured
/// one, and no more.
const SPHERE_DEFICIT: f64 = 1e-4;
const SPHERE_DEFICIT_1000: f64 = 3e-4;

/// Integrator parameters that turn Russian roulette off (for paths shorter than 100000).
fn no_roulette(method: Method) -> &'static str {
    match method {
        Method::Path => r#"<integer name="rr_depth" value="100000"/>"#,
        Method::Guided => {
            r#"<integer name="rr_depth" value="100000"/><integer name="guided_rr_depth" value="100000"/>"#
        }
    }
}

#[test]
fn camera_inside_a_closed_glowing_sphere_sees_emission_over_one_minus_albedo() {
    // Every wall point of a closed sphere that emits Le and reflects with albedo a
    // receives the same radiance: L = Le (1 + a + ... + a^(D-1)) for max_depth D, here
    // D = 60 so L = Le / (1 - a) to 1e-13, in every pixel. Without Russian roulette: with
    // it, paths inside the sphere survive depth 5 with probability a^5 = 8 %, and at 64
    // spp the pixels where few survived have both a low mean and a low variance estimate,
    // which fails per-pixel tests without any bias (the roulette's unbiasedness is tested
    // in analytic.rs and guided.rs). Statistics of `assert_pixels_agree` (seeds 1-3).
    let (le, a) = (0.5f32, 0.6f32);
    for method in METHODS {
        let integrator = method.integrator(60, no_roulette(method));
        let xml = cam_scene_xml(&integrator, inside_cam(16), &glowing_sphere_interior(le, a));
        let r = render_xml_stats("inside-sphere", &xml, 64, *SEED);
        let what = format!("{method:?}: inside the sphere");
        assert_matches_within(&r, |_| [le / (1.0 - a); 3], SPHERE_DEFICIT, &what);
    }
}

#[test]
fn camera_inside_a_closed_sphere_facing_away_from_its_light_sees_black() {
    // The same sphere with its normals outwards: it emits only outwards and nothing else
    // is inside, so the camera inside sees exactly black (one-sided emitter).
    let body = r#"<shape type="sphere"><float name="radius" value="1"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf>
        <emitter type="area"><rgb name="radiance" value="1"/></emitter></shape>
        <emitter type="constant"><rgb name="radiance" value="1"/></emitter>"#;
    for method in METHODS {
        let xml = cam_scene_xml(&method.integrator(-1, ""), inside_cam(16), body);
        let r = render_xml_stats("inside-outward", &xml, 16, *SEED);
        assert_finite(&r, &format!("{method:?}"));
        assert!(
            r.film.mean_rgb().iter().all(|p| *p == [0.0; 3]),
            "{method:?}: light inside a closed outward-facing sphere"
        );
    }
}

#[test]
fn camera_inside_a_glass_sphere_in_the_furnace_sees_eta_squared() {
    // A lossless glass sphere (IOR 1.5) in a furnace of radiance 1: at equilibrium the
    // radiance inside a medium of index n is n^2 times that outside (radiance / n^2 is
    // conserved across the interface), so a camera inside sees 2.25 in every pixel.
    // Statistics of `assert_pixels_agree` (seeds 1-3).
    // (ext_ior 1: Mitsuba's default exterior is air, 1.000277, which makes it 2.24875.)
    let body = furnace_sphere(
        r#"<bsdf type="dielectric"><float name="int_ior" value="1.5"/><float name="ext_ior" value="1"/></bsdf>"#,
    );
    for method in METHODS {
        let xml = cam_scene_xml(&method.integrator(-1, ""), inside_cam(16), &body);
        let r = render_xml_stats("inside-glass", &xml, 64, *SEED);
        assert_matches(&r, |_| [2.25; 3], &format!("{method:?}: inside glass"));
    }
}

// ---- 9. paths of 1000 bounces ----------------------------------------------------------------

#[test]
fn thousand_bounce_paths_stay_finite_on_a_small_stack_and_sum_the_geometric_series() {
    // Inside the glowing sphere with albedo 0.999, no Russian roulette (rr_depth and
    // guided_rr_depth beyond max_depth) and max_depth 1000: every path makes 999 bounces
    // and emission found after k bounces counts for k < 1000, so every pixel's expectation
    // is Le (1 - a^1000) / (1 - a). The render runs on threads with 256 KiB stacks (the
    // caller and the rayon workers): per-bounce stack growth would overflow them.
    // Statistics of `assert_pixels_agree` (seeds 1-3).
    let (le, a, depth) = (0.01f32, 0.999f32, 1000);
    let expected = (le as f64 * (1.0 - (a as f64).powi(depth)) / (1.0 - a as f64)) as f32;
    for method in METHODS {
        // Guided with the guide's share at 0 (BSDF sampling fraction 1): the guided code
        // path's depth handling (1000-vertex paths into a 32-vertex recorder, splitting,
        // light splitting) with a per-path value as deterministic as `path`'s. With guide
        // samples each bounce's weight f cos / p_mix varies, and the mean of a product of
        // 1000 of them is log-normally heavy-tailed: 16 spp say nothing about it.
        let extra = match method {
            Method::Path => no_roulette(method).to_string(),
            Method::Guided => format!(
                r#"{}<string name="bsdf_sampling_fraction_loss" value="none"/><float name="bsdf_sampling_fraction" value="1"/>"#,
                no_roulette(method)
            ),
        };
        let integrator = method.integrator(depth, &extra);
        let xml = cam_scene_xml(&integrator, inside_cam(8), &glowing_sphere_interior(le, a));
        let scene = build("deep", &xml);
        let r = std::thread::Builder::new()
            .stack_size(256 << 10)
            .spawn(move || {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(2)
                    .stack_size(256 << 10)
                    .build()
                    .unwrap()
                    .install(|| render_scene(&scene, 16, *SEED))
            })
            .unwrap()
            .join()
            .expect("the render thread survives");
        let what = format!("{method:?}: 1000 bounces");
        assert_matches_within(&r, |_| [expected; 3], SPHERE_DEFICIT_1000, &what);
    }
}

// ---- 7. very large and very small scene scales ------------------------------------------------

/// A closed room ([-1, 1]^3, two-sided diffuse walls) with a sphere on its floor, a rug
/// (`rug.obj`, over 64 triangles: traced through the BVH, which smaller scenes skip) and a
/// ceiling lamp, every length multiplied by `s` (area-light radiance unchanged).
fn scaled_room(s: f32) -> String {
    format!(
        r#"<bsdf type="twosided" id="wall"><bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.6, 0.5"/></bsdf></bsdf>
    <shape type="cube"><transform name="to_world"><scale value="{s:e}"/></transform><ref id="wall"/></shape>
    <shape type="sphere"><transform name="to_world"><scale value="0.4"/><translate x="0.3" y="0.2" z="-0.6"/><scale value="{s:e}"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.3, 0.5, 0.8"/></bsdf></shape>
    <shape type="obj"><string name="filename" value="rug.obj"/><transform name="to_world"><scale value="{s:e}"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.3, 0.2"/></bsdf></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="0.3"/><rotate x="1" angle="180"/><translate z="0.99"/><scale value="{s:e}"/></transform>
        <emitter type="area"><rgb name="radiance" value="10"/></emitter></shape>"#
    )
}

/// A rug of 8 x 8 quads (128 triangles) over [-0.9, 0.1] x [-0.9, 0.9], 1e-3 above the
/// room's floor, facing up.
fn rug_obj() -> String {
    let n = 8;
    let mut obj = String::new();
    for j in 0..=n {
        for i in 0..=n {
            let (x, y) = (-0.9 + i as f32 / n as f32, -0.9 + 1.8 * j as f32 / n as f32);
            obj += &format!("v {x} {y} -0.999\n");
        }
    }
    for j in 0..n {
        for i in 0..n {
            let v = |i: usize, j: usize| j * (n + 1) + i + 1;
            obj += &format!(
                "f {} {} {}\nf {} {} {}\n",
                v(i, j),
                v(i + 1, j),
                v(i + 1, j + 1),
                v(i, j),
                v(i + 1, j + 1),
                v(i, j + 1)
            );
        }
    }
    obj
}

fn scaled_cam(s: f32) -> Cam {
    Cam {
        near: 1e-2 * s,
        far: 1e4 * s,
        ..Cam::new(
            [-0.6 * s, -0.9 * s, 0.3 * s],
            [0.2 * s, 0.3 * s, -0.4 * s],
            60.0,
            16,
        )
    }
}

#[test]
fn uniformly_scaled_scenes_from_1e_minus_4_to_1e4_render_the_unscaled_image() {
    // Radiance does not depend on the unit of length: scaling geometry, camera and lamp by
    // s leaves the image's expectation unchanged. Scales 1e-4 and 1e4 against 1, for both
    // estimators. Statistics of `assert_pixels_agree` (seeds 1-3).
    for method in METHODS {
        let integrator = method.integrator(-1, "");
        let at = |s: f32, seed: u64| {
            let xml = cam_scene_xml(&integrator, scaled_cam(s), &scaled_room(s));
            let path = write_scene("scaled", &xml);
            std::fs::write(path.with_file_name("rug.obj"), rug_obj()).unwrap();
            let desc = load_scene(&path, &[]).unwrap_or_else(|e| panic!("{e}"));
            let scene = Scene::build(&desc).expect("build");
            assert!(scene.world().triangle_count > 64, "the BVH is under test");
            render_scene(&scene, 64, seed)
        };
        let unit = at(1.0, *SEED);
        for (k, s) in [1e-4f32, 1e4].into_iter().enumerate() {
            let scaled = at(s, *SEED + 1 + k as u64);
            assert_agree(&scaled, &unit, &format!("{method:?}: scale {s:e} vs 1"));
        }
    }
}
