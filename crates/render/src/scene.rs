//! The renderer's view of a scene: acceleration structure, materials,
//! lights, camera, built once from a [`SceneDesc`].

use pathfarm_bsdf::{frame::Frame, Bsdf};
use pathfarm_scene::{
    EmitterDesc, Features, Geometry, GuidedParams, IntegratorDesc, PathParams, SceneDesc,
    TextureDesc,
};

use crate::camera::Camera;
use crate::filter::Filter;
use crate::geometry::{Accel, Analytic, ShapeGeom, SurfaceInteraction};
use crate::light::{AreaLight, EnvMap, Light, Lights};
use crate::material::Material;
use crate::RenderError;

pub struct Scene {
    pub accel: Accel,
    pub lights: Lights,
    /// Area light index of each shape (None for non-emitters).
    pub shape_light: Vec<Option<u32>>,
    /// Material index of each shape.
    shape_material: Vec<u32>,
    materials: Vec<Material>,
    textures: Vec<TextureDesc>,
    pub camera: Camera,
    pub filter: Filter,
    pub path: PathParams,
    /// The `guided_path` parameters when the scene asks for that integrator
    /// (render it with [`crate::guided::render_guided`]).
    pub guided: Option<GuidedParams>,
    pub features: Features,
    pub width: u32,
    pub height: u32,
    /// Samples per pixel the scene asks for (`sampler.sample_count`).
    pub sample_count: u32,
    pub seed: u64,
    pub triangle_count: usize,
}

impl Scene {
    pub fn build(desc: &SceneDesc) -> Result<Self, RenderError> {
        let geoms: Vec<ShapeGeom> = desc
            .shapes
            .iter()
            .map(|s| match &s.geometry {
                Geometry::Mesh(m) => ShapeGeom::Mesh(m.clone()),
                Geometry::Sphere {
                    center,
                    radius,
                    flip_normals,
                } => ShapeGeom::Analytic(Analytic::Sphere {
                    center: *center,
                    radius: *radius,
                    flip: *flip_normals,
                }),
                Geometry::Disk {
                    to_world,
                    flip_normals,
                } => ShapeGeom::Analytic(Analytic::disk(*to_world, *flip_normals)),
            })
            .collect();
        let triangle_count = desc
            .shapes
            .iter()
            .map(|s| {
                if let Geometry::Mesh(m) = &s.geometry {
                    m.indices.len()
                } else {
                    0
                }
            })
            .sum();
        let accel = Accel::build(geoms);

        let mut lights = Vec::new();
        let mut shape_light = vec![None; desc.shapes.len()];
        for (i, s) in desc.shapes.iter().enumerate() {
            if let Some(e) = &s.emitter {
                shape_light[i] = Some(lights.len() as u32);
                lights.push(Light::Area(AreaLight::new(&accel, i as u32, e.radiance)));
            }
        }
        let mut env_count = 0;
        for e in &desc.emitters {
            lights.push(match e {
                EmitterDesc::Point {
                    position,
                    intensity,
                } => Light::Point {
                    position: *position,
                    intensity: *intensity,
                },
                EmitterDesc::Directional {
                    direction,
                    irradiance,
                } => Light::Directional {
                    direction: direction.normalize(),
                    irradiance: *irradiance,
                },
                EmitterDesc::Constant { radiance } => {
                    env_count += 1;
                    Light::Constant {
                        radiance: *radiance,
                    }
                }
                EmitterDesc::EnvMap {
                    width,
                    height,
                    texels,
                    scale,
                    to_world,
                } => {
                    env_count += 1;
                    Light::EnvMap(EnvMap::new(
                        *width,
                        *height,
                        texels.clone(),
                        *scale,
                        *to_world,
                    ))
                }
            });
        }
        if env_count > 1 {
            return Err(RenderError::Unsupported(format!(
                "{}: more than one environment emitter (Mitsuba allows one)",
                desc.source.display()
            )));
        }

        let materials = desc
            .bsdfs
            .iter()
            .map(|b| Material::new(b, &desc.bsdfs, &desc.textures))
            .collect();
        let shape_material = desc.shapes.iter().map(|s| s.bsdf as u32).collect();
        let path = desc.integrator.path_params();
        let guided = match &desc.integrator {
            IntegratorDesc::Path(_) => None,
            IntegratorDesc::GuidedPath(g) => Some(g.clone()),
        };
        Ok(Self {
            accel,
            lights: Lights::new(lights),
            shape_light,
            shape_material,
            materials,
            textures: desc.textures.clone(),
            camera: Camera::new(&desc.sensor),
            filter: Filter::new(desc.sensor.film.rfilter),
            path,
            guided,
            features: desc.features,
            width: desc.sensor.film.width,
            height: desc.sensor.film.height,
            sample_count: desc.sensor.sample_count,
            seed: desc.sensor.seed,
            triangle_count,
        })
    }

    /// The BSDF at a hit and the shading frame to evaluate it in; `ray_d` is
    /// the incoming ray direction (two-sided materials pick their side by it).
    #[inline(always)]
    pub fn bsdf_at(&self, si: &SurfaceInteraction, ray_d: glam::Vec3) -> (Bsdf<'_>, Frame) {
        let m = &self.materials[self.shape_material[si.shape as usize] as usize];
        m.bsdf(&self.textures, si, ray_d)
    }
}
