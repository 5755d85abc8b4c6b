//! Loading the shared example scenes and checking concrete facts.

use std::path::Path;

use glam::{Mat3, Vec2, Vec3};
use pathfarm_scene::*;

fn cornell() -> &'static Path {
    Path::new("/work/shared/scenes/cornell-box/scene.xml")
}
fn veach() -> &'static Path {
    Path::new("/work/shared/scenes/veach-ajar/scene.xml")
}

fn shape<'a>(s: &'a SceneDesc, id: &str) -> &'a ShapeDesc {
    s.shapes
        .iter()
        .find(|x| x.id.as_deref() == Some(id))
        .unwrap_or_else(|| panic!("no shape {id}"))
}

fn mesh(s: &ShapeDesc) -> &TriangleMesh {
    match &s.geometry {
        Geometry::Mesh(m) => m,
        g => panic!("not a mesh: {g:?}"),
    }
}

fn area(m: &TriangleMesh) -> f32 {
    m.indices
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| m.positions[i as usize]);
            0.5 * (b - a).cross(c - a).length()
        })
        .sum()
}

#[test]
fn veach_ajar_loads_all_shapes_with_textures_and_a_dielectric() {
    let s = load_scene(veach(), &[]).unwrap();
    assert_eq!(s.shapes.len(), 22);
    assert!(s.bsdfs.iter().any(|b| matches!(b, BsdfDesc::Dielectric { int_ior, ext_ior, .. } if *int_ior == 1.5 && *ext_ior == 1.0)));
    assert!(
        s.features.textures
            && s.features.transmission
            && s.features.microfacets
            && s.features.area_lights
    );
    assert!(s.features.delta_bsdfs, "dielectric has delta lobes");
    assert!(!s.features.environment && !s.features.delta_lights && !s.features.analytic_shapes);
    // Three JPEG bitmaps (one with spaces in its file name) and a checkerboard.
    let bitmaps: Vec<_> = s
        .textures
        .iter()
        .filter_map(|t| {
            if let TextureDesc::Bitmap(b) = t {
                Some(b)
            } else {
                None
            }
        })
        .collect();
    assert_eq!(bitmaps.len(), 3);
    for b in bitmaps {
        assert_eq!(b.texels.len(), (b.width * b.height) as usize);
        assert!(b.width > 16 && b.height > 16);
        assert_eq!(b.filter, TexFilter::Bilinear);
        assert_eq!(b.wrap, WrapMode::Repeat);
    }
    let PathParams { max_depth, .. } = s.integrator.path_params();
    assert_eq!(max_depth, 13);
    assert_eq!((s.sensor.film.width, s.sensor.film.height), (1280, 720));
}

#[test]
fn veach_floor_checkerboard_has_to_uv_scale_20_by_80() {
    let s = load_scene(veach(), &[]).unwrap();
    let floor = shape(&s, "Floor");
    let BsdfDesc::TwoSided { front, back } = s.bsdfs[floor.bsdf] else {
        panic!("floor bsdf not twosided")
    };
    assert_eq!(front, back);
    let BsdfDesc::RoughConductor {
        roughness,
        specular_reflectance: TexRef::Texture(t),
        eta,
        k,
    } = &s.bsdfs[front]
    else {
        panic!(
            "floor is not a textured roughconductor: {:?}",
            s.bsdfs[front]
        )
    };
    assert_eq!(roughness.distribution, MicrofacetDistribution::Ggx);
    assert_eq!((roughness.alpha_u, roughness.alpha_v), (0.1, 0.1));
    assert!(roughness.sample_visible);
    assert!(
        (*eta - Vec3::new(1.65746, 0.880369, 0.521229))
            .abs()
            .max_element()
            < 1e-6
    );
    assert!(
        (*k - Vec3::new(9.22387, 6.26952, 4.837))
            .abs()
            .max_element()
            < 1e-6
    );
    let TextureDesc::Checkerboard {
        color0,
        color1,
        to_uv,
    } = &s.textures[*t]
    else {
        panic!()
    };
    assert_eq!(*color0, Vec3::splat(0.8));
    assert_eq!(*color1, Vec3::splat(0.2));
    assert_eq!(to_uv.apply(Vec2::new(1.0, 1.0)), Vec2::new(20.0, 80.0));
    assert_eq!(to_uv.apply(Vec2::ZERO), Vec2::ZERO);
}

#[test]
fn veach_light_rectangle_area_and_normal_follow_its_matrix() {
    let s = load_scene(veach(), &[]).unwrap();
    let light = shape(&s, "Light");
    assert_eq!(
        light.emitter,
        Some(AreaEmitterDesc {
            radiance: Vec3::splat(1000.0)
        })
    );
    let m = mesh(light);
    // Matrix columns: x -> (0.730445, 0, 0), y -> (0, -1.32136, 1.42138e-7).
    let cx = Vec3::new(0.730445, 0.0, 0.0);
    let cy = Vec3::new(0.0, -1.32136, 1.42138e-7);
    let cz = Vec3::new(0.0, -1.42138e-7, -1.93037);
    let expected_area = 4.0 * cx.cross(cy).length();
    assert!(
        (area(m) - expected_area).abs() < 1e-4 * expected_area,
        "{} vs {expected_area}",
        area(m)
    );
    // Normal = inverse transpose of the 3x3 applied to +z, normalised.
    let n = (Mat3::from_cols(cx, cy, cz).inverse().transpose() * Vec3::Z).normalize();
    for v in m.normals.as_ref().unwrap() {
        assert!((*v - n).length() < 1e-5, "{v:?} vs {n:?}");
    }
    // The centre of the light sits at the translation column.
    let c = m.positions.iter().copied().sum::<Vec3>() / 4.0;
    assert!((c - Vec3::new(-4.4391, 1.50656, -4.44377)).length() < 1e-5);
}

#[test]
fn veach_obj_meshes_get_mitsuba_flipped_texture_coordinates() {
    let s = load_scene(veach(), &[]).unwrap();
    // Mesh008.obj: "vt 0.991102 0.947976" on the first corner -> v = 1 - 0.947976.
    let m = mesh(shape(&s, "Landscape"));
    assert!(
        m.normals.is_none(),
        "face_normals=true drops vertex normals"
    );
    let uv = m.uvs.as_ref().unwrap()[m.indices[0][0] as usize];
    assert!(
        (uv - Vec2::new(0.991102, 1.0 - 0.947976)).length() < 1e-6,
        "{uv:?}"
    );
}

#[test]
fn cornell_box_has_eight_shapes_and_an_orange_light() {
    let s = load_scene(cornell(), &[]).unwrap();
    assert_eq!(s.shapes.len(), 8);
    let light = shape(&s, "Light");
    assert_eq!(light.emitter.unwrap().radiance, Vec3::new(17.0, 12.0, 4.0));
    assert_eq!(s.shapes.iter().filter(|x| x.emitter.is_some()).count(), 1);
    assert!(
        s.features.area_lights
            && !s.features.textures
            && !s.features.microfacets
            && !s.features.transmission
    );
    // Walls are twosided diffuse with their colours.
    let left = shape(&s, "LeftWall");
    let BsdfDesc::TwoSided { front, .. } = s.bsdfs[left.bsdf] else {
        panic!()
    };
    assert_eq!(
        s.bsdfs[front],
        BsdfDesc::Diffuse {
            reflectance: TexRef::Const(Vec3::new(0.63, 0.065, 0.05))
        }
    );
    // Boxes are Mitsuba cubes: 24 vertices, 12 triangles each.
    let tall = mesh(shape(&s, "TallBox"));
    assert_eq!((tall.positions.len(), tall.indices.len()), (24, 12));
    assert_eq!(s.sensor.fov, 19.5);
    assert_eq!(s.sensor.film.rfilter, RFilter::Tent { radius: 1.0 });
    assert_eq!(s.sensor.sample_count, 64);
    assert_eq!(
        s.integrator,
        IntegratorDesc::Path(PathParams {
            max_depth: 30,
            rr_depth: 5,
            hide_emitters: false,
            strict_normals: false,
        })
    );
}

#[test]
fn cornell_film_is_1024_square_by_default_and_follows_overrides() {
    let s = load_scene(cornell(), &[]).unwrap();
    assert_eq!((s.sensor.film.width, s.sensor.film.height), (1024, 1024));
    let o = [
        ("resx".to_string(), "64".to_string()),
        ("resy".to_string(), "48".to_string()),
    ];
    let s = load_scene(cornell(), &o).unwrap();
    assert_eq!((s.sensor.film.width, s.sensor.film.height), (64, 48));
}

#[test]
fn cornell_light_faces_down_into_the_box() {
    let s = load_scene(cornell(), &[]).unwrap();
    let m = mesh(shape(&s, "Light"));
    for n in m.normals.as_ref().unwrap() {
        assert!(n.y < -0.99, "{n:?}");
    }
    // Geometric winding agrees with the shading normal.
    let [a, b, c] = m.indices[0].map(|i| m.positions[i as usize]);
    assert!((b - a).cross(c - a).y < 0.0);
}
