//! XML semantics and plugin conventions, on small generated scenes.

mod common;

use common::*;
use glam::{Vec2, Vec3};
use pathfarm_scene::*;

fn only_mesh(s: &SceneDesc) -> &TriangleMesh {
    match &s.shapes[0].geometry {
        Geometry::Mesh(m) => m,
        g => panic!("not a mesh: {g:?}"),
    }
}

fn ov(pairs: &[(&str, &str)]) -> Vec<(String, String)> {
    pairs
        .iter()
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .collect()
}

const SPP_SCENE: &str = r#"<scene version="3.0.0">
<default name="spp" value="16"/>
<sensor type="perspective">
  <sampler type="independent"><integer name="sample_count" value="$spp"/><integer name="seed" value="$seed"/></sampler>
</sensor>
</scene>
"#;

#[test]
fn command_line_override_beats_default_and_may_define_new_names() {
    let p = write_scene("override", SPP_SCENE);
    let s = load_scene(&p, &ov(&[("seed", "7")])).unwrap();
    assert_eq!((s.sensor.sample_count, s.sensor.seed), (16, 7));
    let s = load_scene(&p, &ov(&[("seed", "1"), ("spp", "3")])).unwrap();
    assert_eq!((s.sensor.sample_count, s.sensor.seed), (3, 1));
}

#[test]
fn undefined_dollar_parameter_is_an_error_at_its_line() {
    let p = write_scene("undefined-param", SPP_SCENE);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(SPP_SCENE, "$seed"), &["$seed"]);
}

#[test]
fn transform_ops_compose_in_document_order() {
    // (1,1,0) -> scale(2,3,4) -> (2,3,0) -> rotate z 90 -> (-3,2,0) -> translate -> (-2,4,3)
    let xml = scene(
        r#"<shape type="rectangle"><transform name="to_world">
  <scale x="2" y="3" z="4"/>
  <rotate z="1" angle="90"/>
  <translate value="1 2 3"/>
</transform></shape>"#,
    );
    let s = load_scene(&write_scene("compose", &xml), &[]).unwrap();
    let m = only_mesh(&s);
    let corner = m.positions[3]; // Mitsuba's rectangle vertex 3 is (1,1,0)
    assert!(
        (corner - Vec3::new(-2.0, 4.0, 3.0)).length() < 1e-5,
        "{corner:?}"
    );
    assert_eq!(m.uvs.as_ref().unwrap()[3], Vec2::ONE);
    for n in m.normals.as_ref().unwrap() {
        assert!((*n - Vec3::Z).length() < 1e-6);
    }
}

#[test]
fn matrix_is_row_major_and_normals_use_inverse_transpose() {
    // Row-major: "1 0 1 5" is the first row, x' = x + z + 5.
    let xml = scene(
        r#"<shape type="rectangle"><transform name="to_world"><rotate x="1" angle="90"/><matrix value="1 0 1 5  0 1 0 0  0 0 1 0  0 0 0 1"/></transform></shape>"#,
    );
    let s = load_scene(&write_scene("matrix", &xml), &[]).unwrap();
    let m = only_mesh(&s);
    // rotate x 90: (1,1,0) -> (1,0,1); shear+translate: (1+1+5, 0, 1) = (7,0,1)
    assert!(
        (m.positions[3] - Vec3::new(7.0, 0.0, 1.0)).length() < 1e-5,
        "{:?}",
        m.positions[3]
    );
    // rotated normal (0,-1,0); shear's inverse transpose leaves it (0,-1,0).
    assert!((m.normals.as_ref().unwrap()[0] - Vec3::new(0.0, -1.0, 0.0)).length() < 1e-5);
    let xml = scene(
        r#"<shape type="rectangle"><transform name="to_world"><matrix value="1 0 0 0  0 1 0 0  1 0 1 0  0 0 0 1"/></transform></shape>"#,
    );
    // Shear z' = z + x maps the z=0 square onto the plane z = x, whose
    // normal is the inverse transpose applied to +z: (-1, 0, 1)/sqrt2.
    let s = load_scene(&write_scene("matrix2", &xml), &[]).unwrap();
    let n = only_mesh(&s).normals.as_ref().unwrap()[0];
    assert!(
        (n - Vec3::new(-1.0, 0.0, 1.0).normalize()).length() < 1e-6,
        "{n:?}"
    );
}

#[test]
fn lookat_sensor_looks_at_target_with_left_handed_x() {
    let xml = r#"<scene version="3.0.0"><sensor type="perspective">
<float name="fov" value="45"/><string name="fov_axis" value="y"/>
<transform name="to_world"><lookat origin="0, 0, 5" target="0 0 0" up="0 1 0"/></transform>
</sensor></scene>"#;
    let s = load_scene(&write_scene("lookat", xml), &[]).unwrap();
    let m = s.sensor.to_world;
    assert!((m.transform_point3(Vec3::ZERO) - Vec3::new(0.0, 0.0, 5.0)).length() < 1e-6);
    assert!((m.transform_vector3(Vec3::Z) - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-6);
    assert!((m.transform_vector3(Vec3::Y) - Vec3::Y).length() < 1e-6);
    // Mitsuba camera space: +x is "left" = cross(up, dir) = -x here.
    assert!((m.transform_vector3(Vec3::X) - Vec3::new(-1.0, 0.0, 0.0)).length() < 1e-6);
    assert_eq!((s.sensor.fov, s.sensor.fov_axis), (45.0, FovAxis::Y));
    // Defaults when film/sampler are absent: Mitsuba's hdrfilm 768x576 with a gaussian, 4 spp.
    assert_eq!(
        s.sensor.film,
        FilmDesc {
            width: 768,
            height: 576,
            rfilter: RFilter::Gaussian { stddev: 0.5 }
        }
    );
    assert_eq!((s.sensor.sample_count, s.sensor.seed), (4, 0));
    assert_eq!((s.sensor.near_clip, s.sensor.far_clip), (1e-2, 1e4));
}

#[test]
fn focal_length_converts_to_diagonal_fov() {
    let xml = r#"<scene version="3.0.0"><sensor type="perspective"><string name="focal_length" value="50mm"/></sensor></scene>"#;
    let s = load_scene(&write_scene("focal", xml), &[]).unwrap();
    assert_eq!(s.sensor.fov_axis, FovAxis::Diagonal);
    let expected = 2.0 * (43.266615f32 / 100.0).atan().to_degrees();
    assert!((s.sensor.fov - expected).abs() < 1e-3, "{}", s.sensor.fov);
}

#[test]
fn colours_parse_commas_spaces_single_values_and_uniform_spectra() {
    let xml = scene(
        r#"<bsdf type="diffuse" id="a"><rgb name="reflectance" value="0.1, 0.2,0.3"/></bsdf>
<bsdf type="diffuse" id="b"><rgb name="reflectance" value="0.1 0.2 0.3"/></bsdf>
<bsdf type="diffuse" id="c"><rgb name="reflectance" value="0.25"/></bsdf>
<bsdf type="diffuse" id="d"><spectrum name="reflectance" value="0.75"/></bsdf>
<bsdf type="diffuse" id="e"><float name="reflectance" value="0.125"/></bsdf>
<shape type="sphere"><ref id="a"/></shape><shape type="sphere"><ref id="b"/></shape>
<shape type="sphere"><ref id="c"/></shape><shape type="sphere"><ref id="d"/></shape><shape type="sphere"><ref id="e"/></shape>"#,
    );
    let s = load_scene(&write_scene("colours", &xml), &[]).unwrap();
    let refl: Vec<TexRef> = s
        .shapes
        .iter()
        .map(|sh| match s.bsdfs[sh.bsdf] {
            BsdfDesc::Diffuse { reflectance } => reflectance,
            _ => panic!(),
        })
        .collect();
    let c = |x: f32, y: f32, z: f32| TexRef::Const(Vec3::new(x, y, z));
    assert_eq!(
        refl,
        vec![
            c(0.1, 0.2, 0.3),
            c(0.1, 0.2, 0.3),
            c(0.25, 0.25, 0.25),
            c(0.75, 0.75, 0.75),
            c(0.125, 0.125, 0.125)
        ]
    );
    assert!(s.features.analytic_shapes);
}

#[test]
fn referenced_bsdf_is_shared_and_missing_bsdf_gets_default_diffuse() {
    let xml = scene(
        r#"<bsdf type="roughplastic" id="p"><float name="alpha" value="0.3"/></bsdf>
<shape type="cube"><ref id="p"/></shape>
<shape type="cube"><ref name="bsdf" id="p"/></shape>
<shape type="cube"/>"#,
    );
    let s = load_scene(&write_scene("refs", &xml), &[]).unwrap();
    assert_eq!(s.shapes[0].bsdf, s.shapes[1].bsdf);
    let BsdfDesc::RoughPlastic {
        roughness,
        int_ior,
        ext_ior,
        diffuse_reflectance,
        specular_reflectance,
        nonlinear,
    } = &s.bsdfs[s.shapes[0].bsdf]
    else {
        panic!()
    };
    assert_eq!(roughness.distribution, MicrofacetDistribution::Beckmann);
    assert_eq!((roughness.alpha_u, roughness.alpha_v), (0.3, 0.3));
    assert_eq!((*int_ior, *ext_ior), (1.49, 1.000277));
    assert_eq!(*diffuse_reflectance, TexRef::Const(Vec3::splat(0.5)));
    assert_eq!(*specular_reflectance, TexRef::Const(Vec3::ONE));
    assert!(!nonlinear);
    assert_eq!(
        s.bsdfs[s.shapes[2].bsdf],
        BsdfDesc::Diffuse {
            reflectance: TexRef::Const(Vec3::splat(0.5))
        }
    );
    assert!(s.features.microfacets && !s.features.delta_bsdfs);
}

#[test]
fn named_conductors_iors_and_mitsuba_defaults() {
    let xml = scene(
        r#"<shape type="disk"><bsdf type="conductor"><string name="material" value="Au"/></bsdf></shape>
<shape type="disk"><bsdf type="conductor"/></shape>
<shape type="disk"><bsdf type="dielectric"><string name="int_ior" value="water"/></bsdf></shape>
<shape type="disk"><bsdf type="thindielectric"/></shape>
<shape type="disk"><bsdf type="roughconductor"><float name="alpha_u" value="0.2"/><float name="alpha_v" value="0.4"/><boolean name="sample_visible" value="false"/></bsdf></shape>"#,
    );
    let s = load_scene(&write_scene("named", &xml), &[]).unwrap();
    let b = |i: usize| &s.bsdfs[s.shapes[i].bsdf];
    let BsdfDesc::Conductor { eta, k, .. } = b(0) else {
        panic!()
    };
    assert!((eta.x - 0.143036).abs() < 1e-5 && (k.x - 3.982997).abs() < 1e-5);
    assert_eq!(
        b(1),
        &BsdfDesc::Conductor {
            eta: Vec3::ZERO,
            k: Vec3::ONE,
            specular_reflectance: TexRef::Const(Vec3::ONE)
        }
    );
    let BsdfDesc::Dielectric {
        int_ior, ext_ior, ..
    } = b(2)
    else {
        panic!()
    };
    assert_eq!((*int_ior, *ext_ior), (1.333, 1.000277));
    let BsdfDesc::ThinDielectric { int_ior, .. } = b(3) else {
        panic!()
    };
    assert_eq!(*int_ior, 1.5046);
    let BsdfDesc::RoughConductor { roughness, .. } = b(4) else {
        panic!()
    };
    assert_eq!(
        (
            roughness.alpha_u,
            roughness.alpha_v,
            roughness.sample_visible
        ),
        (0.2, 0.4, false)
    );
    assert!(s.features.transmission && s.features.delta_bsdfs && s.features.analytic_shapes);
}

#[test]
fn obj_v_is_flipped_but_ply_v_is_not() {
    let d = temp_dir("uv-convention");
    std::fs::write(
        d.join("tri.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0.25 0.1\nvt 0.5 0.2\nvt 0.75 0.3\nf 1/1 2/2 3/3\n",
    )
    .unwrap();
    std::fs::write(
        d.join("tri.ply"),
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty float u\nproperty float v\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 0.25 0.1\n1 0 0 0.5 0.2\n0 1 0 0.75 0.3\n3 0 1 2\n",
    )
    .unwrap();
    let (p, _) = write_scene_in(
        &d,
        r#"<shape type="obj"><string name="filename" value="tri.obj"/></shape>
<shape type="ply"><string name="filename" value="tri.ply"/></shape>"#,
    );
    let s = load_scene(&p, &[]).unwrap();
    let uv_at = |i: usize, pos: Vec3| {
        let Geometry::Mesh(m) = &s.shapes[i].geometry else {
            panic!()
        };
        let v = m.positions.iter().position(|p| *p == pos).unwrap();
        m.uvs.as_ref().unwrap()[v]
    };
    assert!((uv_at(0, Vec3::ZERO) - Vec2::new(0.25, 0.9)).length() < 1e-6);
    assert!((uv_at(0, Vec3::Y) - Vec2::new(0.75, 0.7)).length() < 1e-6);
    assert!((uv_at(1, Vec3::ZERO) - Vec2::new(0.25, 0.1)).length() < 1e-6);
    // No normals in the files and face_normals=false: smooth normals are computed (+z here).
    let Geometry::Mesh(m) = &s.shapes[0].geometry else {
        panic!()
    };
    assert!(m
        .normals
        .as_ref()
        .unwrap()
        .iter()
        .all(|n| (*n - Vec3::Z).length() < 1e-6));
}

#[test]
fn png_bytes_are_linearised_with_the_srgb_curve_unless_raw() {
    let d = temp_dir("srgb");
    let img = image::RgbImage::from_pixel(2, 1, image::Rgb([128, 0, 255]));
    img.save(d.join("c.png")).unwrap();
    let img16 =
        image::ImageBuffer::<image::Luma<u16>, _>::from_pixel(1, 1, image::Luma([32896u16]));
    img16.save(d.join("g16.png")).unwrap();
    let (p, _) = write_scene_in(
        &d,
        r#"<texture type="bitmap" id="t"><string name="filename" value="c.png"/><string name="filter_type" value="nearest"/><string name="wrap_mode" value="clamp"/></texture>
<texture type="bitmap" id="raw"><string name="filename" value="c.png"/><boolean name="raw" value="true"/></texture>
<texture type="bitmap" id="g"><string name="filename" value="g16.png"/></texture>"#,
    );
    let s = load_scene(&p, &[]).unwrap();
    let TextureDesc::Bitmap(b) = &s.textures[0] else {
        panic!()
    };
    assert_eq!(
        (b.width, b.height, b.filter, b.wrap),
        (2, 1, TexFilter::Nearest, WrapMode::Clamp)
    );
    assert!(
        (b.texels.get(0) - Vec3::new(0.215_860_5, 0.0, 1.0))
            .abs()
            .max_element()
            < 1e-6,
        "{:?}",
        b.texels.get(0)
    );
    assert!((srgb_to_linear(128.0 / 255.0) - 0.215_860_5).abs() < 1e-6);
    let TextureDesc::Bitmap(r) = &s.textures[1] else {
        panic!()
    };
    assert!((r.texels.get(0).x - 128.0 / 255.0).abs() < 1e-6);
    let TextureDesc::Bitmap(g) = &s.textures[2] else {
        panic!()
    };
    // 16-bit grey 32896/65535 == 128/255 expands to RGB and is linearised too.
    assert!(
        (g.texels.get(0) - Vec3::splat(0.215_860_5))
            .abs()
            .max_element()
            < 1e-5,
        "{:?}",
        g.texels.get(0)
    );
    // Unreferenced textures do not switch the feature on.
    assert!(!s.features.textures);
}

#[test]
fn sphere_takes_center_and_radius_through_a_similarity() {
    let xml = scene(
        r#"<shape type="sphere"><point name="center" x="1" y="0" z="0"/><float name="radius" value="0.5"/>
<transform name="to_world"><scale value="2"/><translate x="0" y="3" z="0"/></transform></shape>"#,
    );
    let s = load_scene(&write_scene("sphere", &xml), &[]).unwrap();
    let Geometry::Sphere {
        center,
        radius,
        flip_normals,
    } = s.shapes[0].geometry
    else {
        panic!()
    };
    assert!((center - Vec3::new(2.0, 3.0, 0.0)).length() < 1e-6);
    assert!((radius - 1.0).abs() < 1e-6);
    assert!(!flip_normals);
}

#[test]
fn scene_level_emitters_and_their_features() {
    let xml = scene(
        r#"<emitter type="point"><point name="position" value="1 2 3"/><rgb name="intensity" value="5"/></emitter>
<emitter type="directional"><vector name="direction" x="0" y="-2" z="0"/></emitter>
<emitter type="constant"><rgb name="radiance" value="0.5 0.6 0.7"/></emitter>
<shape type="rectangle"><emitter type="area"/></shape>"#,
    );
    let s = load_scene(&write_scene("emitters", &xml), &[]).unwrap();
    assert_eq!(
        s.emitters[0],
        EmitterDesc::Point {
            position: Vec3::new(1.0, 2.0, 3.0),
            intensity: Vec3::splat(5.0)
        }
    );
    assert_eq!(
        s.emitters[1],
        EmitterDesc::Directional {
            direction: Vec3::new(0.0, -1.0, 0.0),
            irradiance: Vec3::ONE
        }
    );
    assert_eq!(
        s.emitters[2],
        EmitterDesc::Constant {
            radiance: Vec3::new(0.5, 0.6, 0.7)
        }
    );
    assert_eq!(
        s.shapes[0].emitter,
        Some(AreaEmitterDesc {
            radiance: Vec3::ONE
        })
    );
    assert!(s.features.delta_lights && s.features.environment && s.features.area_lights);
}

#[test]
fn stratified_sampler_is_accepted_with_a_warning() {
    let xml = r#"<scene version="3.0.0"><sensor type="perspective"><sampler type="stratified"><integer name="sample_count" value="9"/></sampler></sensor></scene>"#;
    let s = load_scene(&write_scene("stratified", xml), &[]).unwrap();
    assert_eq!(s.sensor.sample_count, 9);
    assert_eq!(s.warnings.len(), 1);
    assert!(s.warnings[0].contains("stratified"));
}

#[test]
fn defaults_can_use_earlier_defaults_and_the_first_definition_wins() {
    let xml = r#"<scene version="3.0.0">
<default name="a" value="5"/>
<default name="b" value="1$a"/>
<default name="a" value="9"/>
<sensor type="perspective"><sampler type="independent"><integer name="sample_count" value="$b"/><integer name="seed" value="$a"/></sampler></sensor>
</scene>"#;
    let p = write_scene("default-chain", xml);
    let s = load_scene(&p, &[]).unwrap();
    assert_eq!((s.sensor.sample_count, s.sensor.seed), (15, 5));
    let s = load_scene(&p, &ov(&[("a", "2")])).unwrap();
    assert_eq!((s.sensor.sample_count, s.sensor.seed), (12, 2));
}

#[test]
fn escaped_dollar_is_kept_literally() {
    let xml = scene(r#"<shape type="cube" id="price\$5"/>"#);
    let s = load_scene(&write_scene("escaped-dollar", &xml), &[]).unwrap();
    assert_eq!(s.shapes[0].id.as_deref(), Some("price$5"));
}

#[test]
fn envmap_loads_linear_exr_with_scale_and_transform() {
    let d = temp_dir("envmap");
    exr::prelude::write_rgb_file(d.join("sky.exr"), 4, 3, |x, y| (x as f32, y as f32, 2.5))
        .unwrap();
    let (p, _) = write_scene_in(
        &d,
        r#"<emitter type="envmap"><string name="filename" value="sky.exr"/><float name="scale" value="3"/>
<transform name="to_world"><rotate y="1" angle="90"/></transform></emitter>"#,
    );
    let s = load_scene(&p, &[]).unwrap();
    let EmitterDesc::EnvMap {
        width,
        height,
        texels,
        scale,
        to_world,
    } = &s.emitters[0]
    else {
        panic!()
    };
    assert_eq!((*width, *height, *scale), (4, 3, 3.0));
    // Row-major, row 0 at the top, values untouched (EXR is linear).
    assert_eq!(texels[4 + 3], Vec3::new(3.0, 1.0, 2.5));
    assert!((to_world.transform_vector3(Vec3::X) - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-6);
    assert!(s.features.environment);
}

#[test]
fn an_envmap_of_fewer_than_2x3_pixels_is_refused_as_mitsuba_does() {
    let d = temp_dir("envmap-small");
    exr::prelude::write_rgb_file(d.join("sky.exr"), 4, 2, |_, _| (1.0, 1.0, 1.0)).unwrap();
    let body = r#"<emitter type="envmap"><string name="filename" value="sky.exr"/></emitter>"#;
    let (p, xml) = write_scene_in(&d, body);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "sky.exr"),
        &["sky.exr", "4x2", "at least 2x3"],
    );
}

/// An integrator block written like Bitterli's scenes: only `max_depth`, through `$max_depth`.
const GUIDED_SCENE: &str = r#"<scene version="3.0.0">
<default name="max_depth" value="5"/>
<integrator type="guided_path"><integer name="max_depth" value="$max_depth"/><integer name="rr_depth" value="3"/></integrator>
<sensor type="perspective"/>
</scene>
"#;

fn guided(s: &SceneDesc) -> &GuidedParams {
    match &s.integrator {
        IntegratorDesc::GuidedPath(g) => g,
        other => panic!("not guided_path: {other:?}"),
    }
}

#[test]
fn command_line_names_the_file_does_not_use_become_integrator_parameters() {
    let p = write_scene("cl-guided", GUIDED_SCENE);
    let plain = load_scene(&p, &[]).unwrap();
    assert_eq!(
        guided(&plain).splitting,
        GuidedParams::preset_pathfarm().splitting
    );
    let s = load_scene(
        &p,
        &ov(&[
            ("preset", "2019"),
            ("max_depth", "7"),
            ("spp_per_pass", "2"),
            ("d_tree_threshold", "0.02"),
            ("splitting", "true"),
            ("light_splitting", "true"),
            ("carry_over", "0.25"),
            // the command line beats a literal value in the file
            ("rr_depth", "9"),
        ]),
    )
    .unwrap();
    let g = guided(&s);
    let expect = GuidedParams::preset_2019();
    assert_eq!(g.russian_roulette, expect.russian_roulette);
    assert_eq!(g.sample_combination, expect.sample_combination);
    assert_eq!(g.directional_filter, expect.directional_filter);
    assert_eq!((g.path.max_depth, g.path.rr_depth), (7, 9));
    assert_eq!(
        (g.spp_per_pass, g.d_tree_threshold, g.splitting),
        (2, 0.02f32 as f64, true)
    );
    assert!(g.light_splitting && !expect.light_splitting);
    assert!(GuidedParams::preset_pathfarm().light_splitting);
    assert_eq!((g.carry_over, expect.carry_over), (0.25, 0.0));
    assert_eq!(GuidedParams::preset_pathfarm().carry_over, 0.5);
}

#[test]
fn command_line_name_no_one_uses_is_an_error_naming_it() {
    let p = write_scene("cl-unknown", GUIDED_SCENE);
    let line = line_of(GUIDED_SCENE, "<integrator");
    let err = load_scene(&p, &ov(&[("presset", "2019")])).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line,
        &["-D presset=2019", "$presset", "guided_path integrator"],
    );
    let err = load_scene(&p, &ov(&[("spp_per_pass", "four")])).unwrap_err();
    assert_invalid_at(&err, &p, line, &["-D spp_per_pass=four", "an integer"]);
    let err = load_scene(&p, &ov(&[("splitting", "yes")])).unwrap_err();
    assert_invalid_at(&err, &p, line, &["-D splitting=yes", "true or false"]);
    let err = load_scene(&p, &ov(&[("preset", "2018")])).unwrap_err();
    assert_invalid_at(&err, &p, line, &["preset", "2018"]);
    // The path integrator has no guide parameters.
    let path_scene = GUIDED_SCENE.replace("guided_path", "path");
    let p = write_scene("cl-path", &path_scene);
    let err = load_scene(&p, &ov(&[("preset", "2019")])).unwrap_err();
    assert_invalid_at(&err, &p, line, &["-D preset=2019", "path integrator"]);
    // Without an <integrator> block nothing can take it.
    let p = write_scene("cl-none", &scene(""));
    let err = load_scene(&p, &ov(&[("preset", "2019")])).unwrap_err();
    assert_invalid_at(&err, &p, 1, &["-D preset=2019", "no <integrator>"]);
}

#[test]
fn an_emitting_shape_without_a_bsdf_is_black_and_others_get_diffuse_half() {
    let xml = scene(
        r#"<shape type="sphere"><emitter type="area"><rgb name="radiance" value="1"/></emitter></shape>
<shape type="sphere"/>"#,
    );
    let s = load_scene(&write_scene("emitter-no-bsdf", &xml), &[]).unwrap();
    let reflectance = |i: usize| match &s.bsdfs[s.shapes[i].bsdf] {
        BsdfDesc::Diffuse {
            reflectance: TexRef::Const(c),
        } => *c,
        b => panic!("not a constant diffuse: {b:?}"),
    };
    assert_eq!(
        reflectance(0),
        Vec3::ZERO,
        "Mitsuba 3: an emitter's default BSDF is black"
    );
    assert_eq!(reflectance(1), Vec3::splat(0.5));
}

#[test]
fn a_rotation_axis_is_used_as_given_and_warned_about() {
    // Axis (0, 0, 2), 90 degrees: c I + s [a]x + (1 - c) a a^T maps (1, 0, 0) to (0, 2, 0)
    // (Mitsuba 3 does not normalise the axis), and the z axis to (0, 0, 4).
    let xml = scene(
        r#"<shape type="rectangle"><transform name="to_world">
  <rotate z="2" angle="90"/>
</transform></shape>"#,
    );
    let p = write_scene("rotate-long-axis", &xml);
    let s = load_scene(&p, &[]).unwrap();
    let m = only_mesh(&s);
    let corner = m.positions[3]; // Mitsuba's rectangle vertex 3 is (1,1,0)
    assert!(
        (corner - Vec3::new(-2.0, 2.0, 0.0)).length() < 1e-5,
        "{corner}"
    );
    let line = line_of(&xml, "<rotate");
    let warned = s
        .warnings
        .iter()
        .any(|w| w.contains("not of unit length") && w.contains(&format!(":{line}")));
    assert!(warned, "a warning naming the line: {:?}", s.warnings);
    let unit = scene(
        r#"<shape type="rectangle"><transform name="to_world"><rotate z="1" angle="90"/></transform></shape>"#,
    );
    let s = load_scene(&write_scene("rotate-unit-axis", &unit), &[]).unwrap();
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
}

#[test]
fn a_conductors_index_of_refraction_may_be_negative_and_a_colour_may_not() {
    // Bitterli's living-room-2 gives eta with a negative channel; only its square matters.
    let xml = scene(
        r#"<bsdf type="conductor" id="metal"><rgb name="eta" value="-0.0485226, 4.14275, 4.66977"/><rgb name="k" value="1, 2, 3"/></bsdf>
<shape type="sphere"><ref id="metal"/></shape>"#,
    );
    let s = load_scene(&write_scene("negative-eta", &xml), &[]).unwrap();
    match &s.bsdfs[s.shapes[0].bsdf] {
        BsdfDesc::Conductor { eta, .. } => assert_eq!(eta.x, -0.0485226),
        b => panic!("not a conductor: {b:?}"),
    }
    let xml = scene(
        r#"<shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="-0.1, 0.5, 0.5"/></bsdf></shape>"#,
    );
    let p = write_scene("negative-colour", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "reflectance"),
        &["negative", "colours must be >= 0"],
    );
}

/// A PNG of `w x h` grey pixels with a `tEXt` chunk of `text_bytes` before its data.
fn png_with_metadata(w: u32, h: u32, text_bytes: usize) -> Vec<u8> {
    let mut plain = Vec::new();
    let img = image::GrayImage::from_pixel(w, h, image::Luma([128]));
    img.write_to(
        &mut std::io::Cursor::new(&mut plain),
        image::ImageFormat::Png,
    )
    .unwrap();
    let mut body = b"Comment\0".to_vec();
    body.extend(std::iter::repeat_n(b'x', text_bytes));
    let mut chunk = (body.len() as u32).to_be_bytes().to_vec();
    let typed: Vec<u8> = b"tEXt".iter().chain(&body).copied().collect();
    chunk.extend(&typed);
    chunk.extend(crc32fast::hash(&typed).to_be_bytes());
    // after the signature (8 bytes) and the IHDR chunk (25 bytes)
    let mut out = plain[..33].to_vec();
    out.extend(chunk);
    out.extend(&plain[33..]);
    out
}

#[test]
fn a_small_png_with_large_metadata_loads() {
    let dir = temp_dir("png-metadata");
    std::fs::write(dir.join("t.png"), png_with_metadata(10, 9, 6 * 1024)).unwrap();
    let body = r#"<shape type="sphere"><bsdf type="diffuse">
  <texture type="bitmap" name="reflectance"><string name="filename" value="t.png"/></texture>
</bsdf></shape>"#;
    let p = write_xml_in(&dir, &scene(body));
    let s = load_scene(&p, &[]).unwrap();
    assert_eq!(s.shapes.len(), 1);
}

#[test]
fn radiance_hdr_and_bmp_images_load_the_hdr_as_linear() {
    let d = temp_dir("hdr-bmp");
    let hdr = image::Rgb32FImage::from_pixel(4, 3, image::Rgb([2.5f32, 0.5, 8.0]));
    image::DynamicImage::ImageRgb32F(hdr)
        .save(d.join("sky.hdr"))
        .unwrap();
    image::RgbImage::from_pixel(2, 2, image::Rgb([255, 128, 0]))
        .save(d.join("wall.bmp"))
        .unwrap();
    let body = r#"<emitter type="envmap"><string name="filename" value="sky.hdr"/></emitter>
<shape type="sphere"><bsdf type="diffuse">
  <texture type="bitmap" name="reflectance"><string name="filename" value="wall.bmp"/></texture>
</bsdf></shape>"#;
    let (p, _) = write_scene_in(&d, body);
    let s = load_scene(&p, &[]).unwrap();
    let EmitterDesc::EnvMap { texels, .. } = &s.emitters[0] else {
        panic!("not an envmap")
    };
    // RGBE keeps 8 bits of mantissa: exact for these values, and not sRGB-decoded.
    assert_eq!(texels[0], Vec3::new(2.5, 0.5, 8.0));
}

/// The Radiance format names the writing program on its first line; Mitsuba writes
/// `#?RGBE`, and the image crate's decoder knows only `#?RADIANCE`.
#[test]
fn radiance_files_signed_by_another_program_load_as_the_same_pixels() {
    let d = temp_dir("hdr-rgbe");
    let hdr = image::Rgb32FImage::from_pixel(4, 3, image::Rgb([2.5f32, 0.5, 8.0]));
    image::DynamicImage::ImageRgb32F(hdr)
        .save(d.join("radiance.hdr"))
        .unwrap();
    let bytes = std::fs::read(d.join("radiance.hdr")).unwrap();
    assert!(bytes.starts_with(b"#?RADIANCE\n"));
    let mut rgbe = b"#?RGBE\n".to_vec();
    rgbe.extend_from_slice(&bytes[b"#?RADIANCE\n".len()..]);
    std::fs::write(d.join("sky.hdr"), rgbe).unwrap();
    let body = r#"<emitter type="envmap"><string name="filename" value="sky.hdr"/></emitter>"#;
    let (p, _) = write_scene_in(&d, body);
    let s = load_scene(&p, &[]).unwrap();
    let EmitterDesc::EnvMap {
        texels,
        width,
        height,
        ..
    } = &s.emitters[0]
    else {
        panic!("not an envmap")
    };
    assert_eq!((*width, *height), (4, 3));
    assert!(texels.iter().all(|t| *t == Vec3::new(2.5, 0.5, 8.0)));
    // A file that only looks like one is still refused, naming the file.
    std::fs::write(d.join("sky.hdr"), b"#?RGBE\ngarbage").unwrap();
    let e = load_scene(&p, &[]).unwrap_err().to_string();
    assert!(e.contains("sky.hdr"), "{e}");
}

#[test]
fn mitsuba_0_6_files_are_upgraded_as_mitsuba_3_does() {
    let d = temp_dir("v06");
    std::fs::create_dir_all(d.join("textures")).unwrap();
    image::RgbImage::from_pixel(2, 2, image::Rgb([255, 255, 255]))
        .save(d.join("textures/wood.png"))
        .unwrap();
    let xml = r#"<scene version="0.6.0">
<path value="textures"/>
<integrator type="path"><integer name="maxDepth" value="7"/><integer name="rrDepth" value="3"/></integrator>
<sensor type="perspective">
  <string name="fovAxis" value="smaller"/><float name="fov" value="40"/>
  <transform name="toWorld"><lookat origin="0 0 5" target="0 0 0" up="0 1 0"/></transform>
  <sampler type="independent"><integer name="sampleCount" value="16"/></sampler>
  <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film>
</sensor>
<bsdf type="diffuse" id="wood">
  <texture type="bitmap" name="diffuseReflectance">
    <string name="filename" value="wood.png"/>
    <float name="uscale" value="4"/><float name="voffset" value="0.5"/>
  </texture>
</bsdf>
<bsdf type="dielectric" id="glass"><float name="intIOR" value="1.33"/></bsdf>
<shape type="sphere"><ref id="wood"/></shape>
<shape type="sphere"><ref id="glass"/></shape>
</scene>
"#;
    let p = write_xml_in(&d, xml);
    let s = load_scene(&p, &[]).unwrap();
    assert_eq!(
        (
            s.sensor.sample_count,
            s.sensor.film.width,
            s.sensor.film.height
        ),
        (16, 32, 24)
    );
    match &s.bsdfs[s.shapes[1].bsdf] {
        BsdfDesc::Dielectric { int_ior, .. } => assert_eq!(*int_ior, 1.33),
        b => panic!("not a dielectric: {b:?}"),
    }
    assert!(
        s.files.iter().any(|f| f.ends_with("textures/wood.png")),
        "the texture is found through <path>: {:?}",
        s.files
    );
    // A Mitsuba 3 file is not upgraded: camelCase names are unknown parameters there.
    let v3 = xml
        .replace("0.6.0", "3.0.0")
        .replace("<path value=\"textures\"/>", "");
    let err = load_scene(&write_xml_in(&d, &v3), &[]).unwrap_err();
    assert!(err.to_string().contains("maxDepth"), "{err}");
}

#[test]
fn a_path_that_is_not_a_directory_is_an_error_at_its_line() {
    let xml = "<scene version=\"3.0.0\">\n<path value=\"nowhere\"/>\n<sensor type=\"perspective\"/>\n</scene>\n";
    let p = write_scene("path-missing", xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, 2, &["nowhere", "no such directory"]);
}

#[test]
fn an_include_adds_its_scene_or_object_in_place_and_is_listed_among_the_files() {
    let d = temp_dir("include");
    std::fs::create_dir_all(d.join("parts")).unwrap();
    std::fs::write(
        d.join("parts/materials.xml"),
        r#"<scene version="0.6.0"><bsdf type="dielectric" id="glass"><float name="intIOR" value="1.4"/></bsdf>
<include filename="sphere.xml"/></scene>"#,
    )
    .unwrap();
    std::fs::write(
        d.join("parts/sphere.xml"),
        r#"<shape type="sphere"><ref id="glass"/></shape>"#,
    )
    .unwrap();
    let body = r#"<default name="part" value="parts/materials.xml"/>
<include filename="$part"/>
<shape type="cube"><ref id="glass"/></shape>"#;
    let (p, _) = write_scene_in(&d, body);
    let s = load_scene(&p, &[]).unwrap();
    assert_eq!(s.shapes.len(), 2, "the included sphere and the cube");
    match &s.bsdfs[s.shapes[1].bsdf] {
        // the included file is of Mitsuba 0.6: upgraded on its own
        BsdfDesc::Dielectric { int_ior, .. } => assert_eq!(*int_ior, 1.4),
        b => panic!("not a dielectric: {b:?}"),
    }
    for f in ["parts/materials.xml", "parts/sphere.xml"] {
        assert!(
            s.files.iter().any(|x| x.ends_with(f)),
            "{f} in {:?}",
            s.files
        );
    }
    assert_eq!(
        s.files[0], *p,
        "the scene file first: a bundle's root is its first file"
    );
}

#[test]
fn includes_are_bounded_in_depth_and_an_error_names_the_included_file() {
    let d = temp_dir("include-loop");
    std::fs::write(
        d.join("loop.xml"),
        "<scene version=\"3.0.0\">\n<include filename=\"loop.xml\"/>\n</scene>\n",
    )
    .unwrap();
    let (p, _) = write_scene_in(&d, r#"<include filename="loop.xml"/>"#);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &d.join("loop.xml"), 2, &["Limits::max_include_depth"]);
    std::fs::write(
        d.join("bad.xml"),
        "<scene version=\"3.0.0\">\n\n<shape type=\"teapot\"/>\n</scene>\n",
    )
    .unwrap();
    let (p, _) = write_scene_in(&d, r#"<include filename="bad.xml"/>"#);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &d.join("bad.xml"), 3, &["teapot"]);
    let (p, xml) = write_scene_in(&d, r#"<include filename="missing.xml"/>"#);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "missing.xml"),
        &["missing.xml", "no such file"],
    );
}

#[test]
fn spectra_become_the_colours_mitsuba_3_gives_them() {
    // Mitsuba 3.9.1 scalar_rgb, mi.traverse of the loaded scene.
    let xml = scene(
        r#"<shape type="sphere"><emitter type="area"><spectrum name="radiance" value="2"/></emitter></shape>
<shape type="sphere"><bsdf type="diffuse"><spectrum name="reflectance" value="400:0.1, 500:0.5, 600:0.8, 700:0.3"/></bsdf></shape>
<emitter type="constant"><spectrum name="radiance" value="400:1, 700:2"/></emitter>"#,
    );
    let s = load_scene(&write_scene("spectra", &xml), &[]).unwrap();
    let close = |a: Vec3, b: [f32; 3]| (a - Vec3::from(b)).abs().max_element() < 2e-5;
    let radiance = s.shapes[0].emitter.as_ref().unwrap().radiance;
    assert!(close(radiance, [2.40959, 1.89658, 1.81783]), "{radiance}");
    let BsdfDesc::Diffuse {
        reflectance: TexRef::Const(r),
    } = &s.bsdfs[s.shapes[1].bsdf]
    else {
        panic!("a constant diffuse")
    };
    assert!(close(*r, [0.752187, 0.645269, 0.271706]), "{r}");
    let EmitterDesc::Constant { radiance } = &s.emitters[0] else {
        panic!("constant")
    };
    assert!(close(*radiance, [2.14, 1.40424, 1.01714]), "{radiance}");
}

#[test]
fn the_integrator_flag_replaces_the_integrator_keeping_what_means_the_same() {
    let xml = scene(
        r#"<integrator type="sppm"><integer name="max_depth" value="6"/><integer name="photon_count" value="1000"/><boolean name="hide_emitters" value="true"/></integrator>"#,
    );
    let p = write_scene("integrator-flag", &xml);
    assert!(
        load_scene(&p, &[]).is_err(),
        "sppm is not an integrator pathfarm has"
    );
    let s = load_scene_as(&p, &[], &Limits::default(), Some("path")).unwrap();
    let IntegratorDesc::Path(pp) = &s.integrator else {
        panic!("path")
    };
    assert_eq!((pp.max_depth, pp.hide_emitters), (6, true));
    let w = s.warnings.join("\n");
    assert!(
        w.contains("integrator 'sppm' replaced by 'path'") && w.contains("dropped photon_count"),
        "{w}"
    );
    // -D parameters the scene does not use go to the replacement.
    let s = load_scene_as(
        &p,
        &ov(&[("preset", "2019")]),
        &Limits::default(),
        Some("guided_path"),
    )
    .unwrap();
    assert!(matches!(s.integrator, IntegratorDesc::GuidedPath(_)));
    // A scene without an integrator gets one; an unknown name is refused naming it.
    let bare = write_scene("integrator-flag-bare", &scene(""));
    let s = load_scene_as(&bare, &[], &Limits::default(), Some("guided_path")).unwrap();
    assert!(matches!(s.integrator, IntegratorDesc::GuidedPath(_)));
    let err = load_scene_as(&p, &[], &Limits::default(), Some("bdpt")).unwrap_err();
    assert!(err.to_string().contains("bdpt"), "{err}");
    // `direct` reads only hide_emitters of the three: the others are dropped, not refused.
    let s = load_scene_as(&p, &[], &Limits::default(), Some("direct")).unwrap();
    let IntegratorDesc::Path(pp) = &s.integrator else {
        panic!("direct renders as path")
    };
    assert_eq!((pp.max_depth, pp.hide_emitters), (2, true));
    // A `moment` wrapper's settings are its nested integrator's.
    let wrapped = scene(
        r#"<integrator type="moment"><integrator type="path"><integer name="max_depth" value="8"/></integrator></integrator>"#,
    );
    let p = write_scene("integrator-flag-moment", &wrapped);
    let s = load_scene_as(&p, &[], &Limits::default(), Some("guided_path")).unwrap();
    let IntegratorDesc::GuidedPath(g) = &s.integrator else {
        panic!("guided")
    };
    assert_eq!(
        g.path.max_depth, 8,
        "the nested integrator's max_depth is kept"
    );
}

#[test]
fn an_area_emitter_declared_at_the_top_and_referenced_by_a_shape_is_the_shapes() {
    let xml = scene(
        r#"<emitter type="area" id="light"><rgb name="radiance" value="5"/></emitter>
<shape type="sphere"><ref id="light"/></shape>"#,
    );
    let s = load_scene(&write_scene("area-ref", &xml), &[]).unwrap();
    assert!(s.emitters.is_empty(), "not a scene-level emitter");
    assert_eq!(
        s.shapes[0].emitter.as_ref().unwrap().radiance,
        Vec3::splat(5.0)
    );
    // Not referenced by any shape: still an error at its line.
    let xml =
        scene(r#"<emitter type="area" id="light"><rgb name="radiance" value="5"/></emitter>"#);
    let p = write_scene("area-unref", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "area"),
        &["nested inside a <shape>"],
    );
}

#[test]
fn a_cylinder_folds_p0_p1_and_radius_into_a_circular_transform() {
    let xml = scene(
        r#"<shape type="cylinder"><point name="p0" x="1" y="0" z="0"/><point name="p1" x="1" y="3" z="0"/><float name="radius" value="0.5"/></shape>
<shape type="cylinder"><transform name="to_world"><scale x="1" y="2" z="1"/></transform></shape>"#,
    );
    let p = write_scene("cylinder-squashed", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "scale x"),
        &["cylinder", "circular"],
    );
    let ok = scene(
        r#"<shape type="cylinder"><point name="p0" x="1" y="0" z="0"/><point name="p1" x="1" y="3" z="0"/><float name="radius" value="0.5"/></shape>"#,
    );
    let s = load_scene(&write_scene("cylinder", &ok), &[]).unwrap();
    let Geometry::Cylinder { to_world, .. } = &s.shapes[0].geometry else {
        panic!("cylinder")
    };
    // the unit cylinder's axis runs from p0 to p1, its radius is 0.5
    let end = to_world.transform_point3(Vec3::Z);
    assert!((end - Vec3::new(1.0, 3.0, 0.0)).length() < 1e-6, "{end}");
    assert!((to_world.transform_vector3(Vec3::X).length() - 0.5).abs() < 1e-6);
    assert!(s.features.analytic_shapes);
}

#[test]
fn instances_place_copies_of_their_group_and_a_group_is_not_rendered_itself() {
    let xml = scene(
        r#"<shape type="shapegroup" id="g">
  <shape type="rectangle"/>
  <shape type="sphere"><float name="radius" value="0.5"/></shape>
</shape>
<shape type="instance"><ref id="g"/><transform name="to_world"><translate x="2"/></transform></shape>
<shape type="instance"><ref id="g"/><transform name="to_world"><scale value="2"/></transform></shape>"#,
    );
    let s = load_scene(&write_scene("instances", &xml), &[]).unwrap();
    assert_eq!(
        s.shapes.len(),
        4,
        "two shapes, two instances; the group itself is not rendered"
    );
    let Geometry::Mesh(m) = &s.shapes[0].geometry else {
        panic!("mesh")
    };
    assert_eq!(
        m.positions[3],
        Vec3::new(3.0, 1.0, 0.0),
        "the rectangle's corner moved by 2"
    );
    let Geometry::Sphere { radius, .. } = &s.shapes[3].geometry else {
        panic!("sphere")
    };
    assert_eq!(*radius, 1.0, "scaled by 2");
    let bad = scene(
        r#"<shape type="shapegroup" id="g">
  <shape type="sphere"><emitter type="area"/></shape>
</shape>
<shape type="instance"><ref id="g"/></shape>"#,
    );
    let p = write_scene("instances-emitter", &bad);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&bad, "<emitter"), &["cannot emit light"]);
    let lone = scene(r#"<shape type="instance"><shape type="sphere"/></shape>"#);
    let p = write_scene("instance-no-group", &lone);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&lone, "instance"),
        &["needs one shapegroup"],
    );
}

#[test]
fn a_moment_integrator_renders_its_nested_integrator() {
    let xml = scene(
        r#"<integrator type="moment"><integrator type="path"><integer name="max_depth" value="2"/></integrator></integrator>"#,
    );
    let s = load_scene(&write_scene("moment", &xml), &[]).unwrap();
    let IntegratorDesc::Path(p) = &s.integrator else {
        panic!("path")
    };
    assert_eq!(p.max_depth, 2);
    let two = scene(
        r#"<integrator type="moment"><integrator type="path"/><integrator type="path"/></integrator>"#,
    );
    let p = write_scene("moment-two", &two);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&two, "moment"), &["2 nested integrators"]);
}

#[test]
fn look_at_is_read_in_mitsuba_0_x_files_only() {
    let body = r#"<sensor type="perspective"><transform name="toWorld">
  <lookAt origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/>
</transform></sensor>"#;
    let old = format!("<scene version=\"0.6.0\">\n{body}\n</scene>\n");
    let s = load_scene(&write_scene("lookat-06", &old), &[]).unwrap();
    let eye = s.sensor.to_world.transform_point3(Vec3::ZERO);
    assert_eq!(eye, Vec3::new(0.0, 0.0, 5.0));
    let new = format!(
        "<scene version=\"3.0.0\">\n{}\n</scene>\n",
        body.replace("toWorld", "to_world")
    );
    let p = write_scene("lookat-3", &new);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&new, "lookAt"), &["unexpected <lookAt>"]);
}

#[test]
fn a_corrupt_radiance_hdr_file_is_an_error_naming_it() {
    let d = temp_dir("hdr-garbage");
    // A valid header, then run-length scanlines that overrun the row and end early.
    let mut bytes = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4 +X 16\n".to_vec();
    bytes.extend([2, 2, 0, 16, 0xff, 7, 0x80, 0xff, 3, 1]);
    std::fs::write(d.join("sky.hdr"), &bytes).unwrap();
    let body = r#"<emitter type="envmap"><string name="filename" value="sky.hdr"/></emitter>"#;
    let (p, xml) = write_scene_in(&d, body);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "sky.hdr"),
        &["sky.hdr", "cannot decode image"],
    );
}

#[test]
fn mask_null_bumpmap_and_normalmap_wrap_their_nested_bsdf_with_mitsuba_defaults() {
    let dir = temp_dir("wrappers");
    write_png_grey(&dir.join("h.png"));
    let (path, _) = write_scene_in(
        &dir,
        r#"<shape type="cube"><bsdf type="mask"><bsdf type="diffuse"/></bsdf></shape>
<shape type="cube"><bsdf type="null"/></shape>
<shape type="cube"><bsdf type="bumpmap">
  <texture type="bitmap"><string name="filename" value="h.png"/><boolean name="raw" value="true"/></texture>
  <float name="scale" value="2"/><bsdf type="diffuse"/></bsdf></shape>
<shape type="cube"><bsdf type="normalmap">
  <texture type="bitmap" name="normalmap"><string name="filename" value="h.png"/></texture>
  <boolean name="use_shadowing_function" value="false"/><bsdf type="diffuse"/></bsdf></shape>"#,
    );
    let s = load_scene(&path, &[]).unwrap();
    let b = |i: usize| &s.bsdfs[s.shapes[i].bsdf];
    let BsdfDesc::Mask { opacity, nested } = b(0) else {
        panic!("{:?}", b(0))
    };
    assert_eq!(*opacity, TexRef::Const(Vec3::splat(0.5)));
    assert!(matches!(s.bsdfs[*nested], BsdfDesc::Diffuse { .. }));
    assert_eq!(*b(1), BsdfDesc::Null);
    let BsdfDesc::BumpMap { scale, normals, .. } = b(2) else {
        panic!("{:?}", b(2))
    };
    assert_eq!(*scale, 2.0);
    assert!(normals.flip_invalid_normals && normals.use_shadowing_function);
    let BsdfDesc::NormalMap { normals, .. } = b(3) else {
        panic!("{:?}", b(3))
    };
    assert!(normals.flip_invalid_normals && !normals.use_shadowing_function);
    assert!(s.features.pass_through && s.features.perturbed_normals && s.features.textures);
}

#[test]
fn wrappers_without_their_nested_bsdf_or_texture_are_errors_at_their_line() {
    for (body, needle) in [
        (r#"<bsdf type="mask" id="m"/>"#, "exactly one nested bsdf"),
        (
            r#"<bsdf type="bumpmap" id="m"><bsdf type="diffuse"/></bsdf>"#,
            "nested texture",
        ),
        (
            r#"<bsdf type="normalmap" id="m"><bsdf type="diffuse"/></bsdf>"#,
            "'normalmap' texture",
        ),
        (
            r#"<bsdf type="mask" id="m"><bsdf type="diffuse"/><bsdf type="diffuse"/></bsdf>"#,
            "found 2",
        ),
    ] {
        let xml = scene(&format!(
            "{body}\n<shape type=\"cube\"><ref id=\"m\"/></shape>"
        ));
        let p = write_scene("wrapper-errors", &xml);
        let e = load_scene(&p, &[]).unwrap_err();
        assert_invalid_at(
            &e,
            &p,
            line_of(&xml, "id=\"m\"/>").min(line_of(&xml, body)),
            &[needle],
        );
    }
}

/// A 2x2 grey PNG.
fn write_png_grey(path: &std::path::Path) {
    let img = image::GrayImage::from_raw(2, 2, vec![0, 64, 128, 255]).unwrap();
    img.save(path).unwrap();
}
