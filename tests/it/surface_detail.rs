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
    assert!(!scene.features.pass_through);
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
