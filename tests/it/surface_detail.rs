//! Surfaces that let light through (`mask`, `null`) and perturbed shading normals
//! (`bumpmap`, `normalmap`), through the public scene API. Their images are checked against
//! Mitsuba 3 in `crosscheck`.

use glam::Vec3;
use pathfarm_render::geometry::Ray;
use pathfarm_render::Scene;
use pathfarm_scene::load_scene;

use crate::common::*;

/// Three parallel panels across the z axis at z = 1, 2, 3, with the BSDFs given.
fn panels(tag: &str, bsdfs: [&str; 3]) -> std::path::PathBuf {
    let dir = temp_dir(tag);
    let shapes: String = bsdfs
        .iter()
        .enumerate()
        .map(|(i, b)| {
            format!(
                r#"<shape type="rectangle"><transform name="to_world"><translate z="{}"/></transform>{b}</shape>"#,
                i + 1
            )
        })
        .collect();
    let xml =
        format!("<scene version=\"3.0.0\"><sensor type=\"perspective\"/>\n{shapes}\n</scene>\n");
    let path = dir.join("scene.xml");
    std::fs::write(&path, xml).unwrap();
    path
}

fn shadow_ray(to_z: f32) -> Ray {
    Ray {
        o: Vec3::new(0.1, 0.2, 0.0),
        d: Vec3::Z,
        tmin: 0.0,
        tmax: to_z,
    }
}

#[test]
fn shadow_rays_carry_the_product_of_the_pass_probabilities_they_cross() {
    let mask = |o: f32| {
        format!(
            r#"<bsdf type="mask"><float name="opacity" value="{o}"/><bsdf type="diffuse"/></bsdf>"#
        )
    };
    let (m04, m075) = (mask(0.4), mask(0.75));
    let null = r#"<bsdf type="null"/>"#;
    let scene = build_scene(&panels("transmit", [&m04, null, &m075]), &[]);
    let t = |z: f32| scene.transmittance::<false>(&shadow_ray(z));
    assert_eq!(t(0.5), 1.0, "nothing crossed");
    assert!(
        (t(1.5) - 0.6).abs() < 1e-6,
        "one mask of opacity 0.4: {}",
        t(1.5)
    );
    assert!(
        (t(2.5) - 0.6).abs() < 1e-6,
        "and a null surface: {}",
        t(2.5)
    );
    assert!(
        (t(3.5) - 0.15).abs() < 1e-6,
        "and a mask of opacity 0.75: {}",
        t(3.5)
    );

    let opaque = r#"<bsdf type="diffuse"/>"#;
    let scene = build_scene(&panels("blocked", [null, opaque, null]), &[]);
    assert_eq!(scene.transmittance::<false>(&shadow_ray(1.5)), 1.0);
    assert_eq!(scene.transmittance::<false>(&shadow_ray(3.5)), 0.0);
}

#[test]
fn a_scene_without_mask_or_null_surfaces_never_lets_light_through() {
    let opaque = r#"<bsdf type="diffuse"/>"#;
    let scene = build_scene(&panels("opaque", [opaque, opaque, opaque]), &[]);
    assert!(!scene.world().features.pass_through);
    assert_eq!(scene.transmittance::<false>(&shadow_ray(0.5)), 1.0);
    assert_eq!(scene.transmittance::<false>(&shadow_ray(1.5)), 0.0);
}

#[test]
fn unsupported_wrapper_combinations_are_refused_naming_the_scene() {
    let twice = r#"<bsdf type="mask"><bsdf type="mask"><bsdf type="diffuse"/></bsdf></bsdf>"#;
    let opaque = r#"<bsdf type="diffuse"/>"#;
    let path = panels("twice", [twice, opaque, opaque]);
    let desc = load_scene(&path, &[]).unwrap();
    let err = Scene::build(&desc)
        .err()
        .expect("two masks on one surface are refused");
    let shown = err.to_string();
    assert!(
        shown.contains(&path.display().to_string()) && shown.contains("mask"),
        "{shown}"
    );
}

/// A triangle facing the camera (+z) with its vertex normals pointing away, under a constant
/// sky, as `obj` with `strict_normals` on or off; `flip` gives the normals the triangle's side.
fn strict_normals_scene(tag: &str, strict: bool, flip: bool) -> Scene {
    let dir = temp_dir(tag);
    let n = if flip { "0 0 1" } else { "0 0 -1" };
    std::fs::write(
        dir.join("t.obj"),
        format!("v -2 -2 0\nv 2 -2 0\nv 0 2 0\nvn {n}\nf 1//1 2//1 3//1\n"),
    )
    .unwrap();
    let xml = format!(
        r#"<scene version="3.0.0">
<integrator type="path"><boolean name="strict_normals" value="{strict}"/></integrator>
<sensor type="perspective"><float name="fov" value="30"/>
  <transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
  <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
  <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
</sensor>
<emitter type="constant"/>
<shape type="obj"><string name="filename" value="t.obj"/><bsdf type="twosided"><bsdf type="diffuse"/></bsdf></shape>
</scene>"#
    );
    let path = dir.join("scene.xml");
    std::fs::write(&path, xml).unwrap();
    build_scene(&path, &[])
}

fn centre_pixel(scene: &Scene) -> f32 {
    let settings = pathfarm_render::RenderSettings::new(Some(16), None, 1);
    let film = pathfarm_render::render(scene, &settings, &|_| {}).0;
    let rgb = film.mean_rgb();
    rgb[4 * 8 + 4][0]
}

#[test]
fn strict_normals_drop_vertices_whose_shading_normal_disagrees_with_the_surface() {
    // Normals on the triangle's side: strict or not, the same image.
    let lenient = centre_pixel(&strict_normals_scene("strict-agree-off", false, true));
    let strict = centre_pixel(&strict_normals_scene("strict-agree-on", true, true));
    assert!(lenient > 0.1, "the lit triangle: {lenient}");
    assert_eq!(lenient.to_bits(), strict.to_bits());
    // Normals reversed: the camera's hit is inconsistent, and strict normals drop it.
    let lenient = centre_pixel(&strict_normals_scene("strict-flip-off", false, false));
    let strict = centre_pixel(&strict_normals_scene("strict-flip-on", true, false));
    assert!(
        lenient > 0.1,
        "without strict normals the triangle is lit: {lenient}"
    );
    // (Not exactly 0: the Gaussian filter reaches the sky beside the triangle.)
    assert!(
        strict < lenient * 1e-4,
        "with strict normals its vertex is dropped: {strict} against {lenient}"
    );
}
