//! The renderer's view of a scene, built from a [`SceneDesc`]: its [`World`] (acceleration
//! structure, lights, materials, textures), which the frames of a shot share, and the
//! frame's camera, filter and integrator parameters ([`Scene`]).

use std::sync::Arc;

use pathfarm_bsdf::frame::Frame;
use pathfarm_scene::{
    EmitterDesc, Features, Geometry, GuidedParams, IntegratorDesc, PathParams, SceneDesc,
    TextureDesc,
};

use crate::camera::Camera;
use crate::filter::Filter;
use crate::geometry::{spawn_ray_to, Accel, Analytic, Bvh, Ray, ShapeGeom, SurfaceInteraction};
use crate::light::{AreaLight, EnvMap, Light, Lights, Spot};
use crate::material::Material;
use crate::shading::ShadedBsdf;
use crate::RenderError;
use pathfarm_scene::limits::{format_bytes, Limits};

/// What the frames of one scene share, whatever their camera: the geometry with its BVH,
/// the lights, the materials and textures. Built once and shared by the [`Scene`]s of its
/// frames through an `Arc` (a farm worker serving a shot's frames builds its world once:
/// [`Scene::with_world`]).
pub struct World {
    /// All shapes' geometry, in world space, with the ray-query structure over them.
    pub accel: Accel,
    /// Every emitter, for next-event estimation and for emission found by paths.
    pub lights: Lights,
    /// Area light index of each shape (None for non-emitters).
    pub shape_light: Vec<Option<u32>>,
    /// Material index of each shape.
    shape_material: Vec<u32>,
    materials: Vec<Material>,
    textures: Vec<TextureDesc>,
    /// The effects the scene calls for; [`crate::integrator::specialised`] picks code paths by
    /// them.
    pub features: Features,
    /// Number of triangles over all meshes (for reports and memory estimates).
    pub triangle_count: usize,
    /// The bytes of the scene's meshes and textures (its description's
    /// [`SceneDesc::data_bytes`]); with the BVH, [`World::memory_bytes`].
    data_bytes: u64,
    /// What it was built for ([`World::serves`]).
    purpose: Purpose,
}

/// Everything a render reads, immutable once built: its [`World`] (geometry, lights,
/// materials and textures), and the frame's camera, filter and integrator parameters.
pub struct Scene {
    world: Arc<World>,
    /// The sensor's camera, generating primary rays.
    pub camera: Camera,
    /// The film's reconstruction filter.
    pub filter: Filter,
    /// `max_depth`, `rr_depth` and `hide_emitters` of the scene's integrator (`path` or
    /// `guided_path`).
    pub path: PathParams,
    /// The `guided_path` parameters when the scene asks for that integrator
    /// (render it with [`crate::guided::render_guided`]).
    pub guided: Option<GuidedParams>,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Samples per pixel the scene asks for (`sampler.sample_count`).
    pub sample_count: u32,
    /// The sampler's seed from the scene file; drivers use it when no seed is given.
    pub seed: u64,
    /// The resource limits the scene was loaded with (the renderer checks its own
    /// allocations against them).
    pub limits: Limits,
}

/// What a [`Scene`] is built for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Purpose {
    /// Rendering: everything, the BVH included.
    Render,
    /// Reading its settings and checking it: no BVH, so no ray hits its triangles.
    Inspect,
}

impl Scene {
    /// Builds the render-ready scene from a loaded description: the BVH, the lights, the materials.
    /// Fails when the estimated memory exceeds the scene's limits, when the BVH cannot be built, or
    /// with more than one environment emitter.
    pub fn build(desc: &SceneDesc) -> Result<Self, RenderError> {
        Self::build_for(desc, Purpose::Render)
    }

    /// [`Scene::build`] for `purpose`: with [`Purpose::Inspect`] everything but the BVH is
    /// built and checked (settings, lights, materials, bounds), and no ray hits the scene's
    /// triangles; the farm's coordinator validates submitted scenes so, for a BVH is most of a
    /// large scene's build time.
    pub fn build_for(desc: &SceneDesc, purpose: Purpose) -> Result<Self, RenderError> {
        check_memory(desc, desc_triangles(desc), desc.data_bytes())?;
        let world = World::build(desc, purpose)?;
        Self::with_world(desc, Arc::new(world))
    }

    /// The scene of `desc` on `world`, which was built from a description that differs from
    /// `desc` at most in its sensor and integrator: the caller knows so from their equal
    /// [`pathfarm_scene::world_source`]s and the equal bytes of the files they name. Only
    /// `desc`'s sensor, integrator and limits are read, so it may be a scan
    /// ([`pathfarm_scene::scan_scene_as`]: files named, not decoded). The scene renders the
    /// bits a scene built from `desc` alone would. Fails as [`Scene::build`] does when the
    /// frame's films and the world exceed the limits, and when `desc` has another number of
    /// shapes than the world (not its scene).
    pub fn with_world(desc: &SceneDesc, world: Arc<World>) -> Result<Self, RenderError> {
        if desc.shapes.len() != world.shape_material.len() {
            return Err(RenderError::Unsupported(format!(
                "{}: {} shapes, but the world it was given has {}",
                desc.source.display(),
                desc.shapes.len(),
                world.shape_material.len()
            )));
        }
        check_memory(desc, world.triangle_count, world.data_bytes)?;
        Ok(Self {
            world,
            camera: Camera::new(&desc.sensor),
            filter: Filter::new(desc.sensor.film.rfilter),
            path: desc.integrator.path_params(),
            guided: match &desc.integrator {
                IntegratorDesc::Path(_) => None,
                IntegratorDesc::GuidedPath(g) => Some(g.clone()),
            },
            width: desc.sensor.film.width,
            height: desc.sensor.film.height,
            sample_count: desc.sensor.sample_count,
            seed: desc.sensor.seed,
            limits: desc.limits.clone(),
        })
    }

    /// The geometry, lights, materials and textures this frame renders.
    #[inline(always)]
    pub fn world(&self) -> &World {
        &self.world
    }

    /// [`Scene::world`], to share with another frame of the scene ([`Scene::with_world`]).
    pub fn shared_world(&self) -> Arc<World> {
        self.world.clone()
    }
}

impl World {
    /// The world of `desc` (everything but its sensor and integrator), for `purpose`.
    fn build(desc: &SceneDesc, purpose: Purpose) -> Result<Self, RenderError> {
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
                Geometry::Cylinder {
                    to_world,
                    flip_normals,
                } => ShapeGeom::Analytic(Analytic::cylinder(*to_world, *flip_normals)),
            })
            .collect();
        let triangle_count = desc_triangles(desc);
        // The BVH builder is third-party code: a failure there is an error, not a crash
        // (the loader bounds coordinates, so this is a second line of defence).
        let accel = std::panic::catch_unwind(move || {
            let bvh = match purpose {
                Purpose::Render => Bvh::Build,
                Purpose::Inspect => Bvh::Skip,
            };
            Accel::build_with(geoms, bvh)
        })
        .map_err(|_| {
            RenderError::Unsupported(format!(
                "{}: building the BVH failed on this geometry",
                desc.source.display()
            ))
        })?;

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
                EmitterDesc::Spot {
                    to_world,
                    intensity,
                    cutoff_angle,
                    beam_width,
                } => Light::Spot(Spot::new(*to_world, *intensity, *cutoff_angle, *beam_width)),
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
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| RenderError::Unsupported(format!("{}: {e}", desc.source.display())))?;
        let shape_material = desc.shapes.iter().map(|s| s.bsdf as u32).collect();
        Ok(World {
            accel,
            lights: Lights::new(lights),
            shape_light,
            shape_material,
            materials,
            textures: desc.textures.clone(),
            features: desc.features,
            triangle_count,
            data_bytes: desc.data_bytes(),
            purpose,
        })
    }

    /// What the world was built for.
    pub fn purpose(&self) -> Purpose {
        self.purpose
    }

    /// Whether a scene for `purpose` may be built on this world ([`Scene::with_world`]): a
    /// world built for rendering serves any purpose; one built for inspection has no BVH
    /// (and, from the farm's validation, stand-ins for its images), so it serves only
    /// inspection.
    pub fn serves(&self, purpose: Purpose) -> bool {
        self.purpose == Purpose::Render || purpose == Purpose::Inspect
    }

    /// What the world holds in memory, an upper estimate: its meshes, textures and BVH (what
    /// a worker's scene cache budgets).
    pub fn memory_bytes(&self) -> u64 {
        self.data_bytes + self.triangle_count as u64 * BVH_BYTES_PER_TRIANGLE
    }
}

impl Scene {
    /// The BSDF at a hit (`si`, on triangle `prim` of its shape) and the shading frame to
    /// evaluate it in; `ray_d` is the incoming ray direction (two-sided materials pick their
    /// side by it).
    #[inline(always)]
    pub fn bsdf_at(
        &self,
        si: &SurfaceInteraction,
        prim: u32,
        ray_d: glam::Vec3,
    ) -> (ShadedBsdf<'_>, Frame) {
        let m = &self.world.materials[self.world.shape_material[si.shape as usize] as usize];
        m.bsdf(&self.world.textures, si, ray_d, || {
            self.world.accel.uv_tangents(si, prim)
        })
    }

    /// What the scene holds in memory, an upper estimate: its meshes, textures and BVH (what a
    /// worker's scene cache budgets).
    pub fn memory_bytes(&self) -> u64 {
        self.world.memory_bytes()
    }

    /// The probability that a path meeting the surface at `si` passes straight through it
    /// (`mask`, `null`); 0 in scenes without such surfaces.
    #[inline(always)]
    pub fn pass_probability(&self, si: &SurfaceInteraction) -> f32 {
        if !self.world.features.pass_through {
            return 0.0;
        }
        let m = &self.world.materials[self.world.shape_material[si.shape as usize] as usize];
        m.pass_probability(&self.world.textures, si)
    }

    /// The fraction of light that reaches the end of shadow ray `ray`: 1 if nothing blocks
    /// it, 0 if an opaque surface does, else the product of the pass probabilities of the
    /// `mask` and `null` surfaces it crosses (the expected value of a path stepping through
    /// them, so that light sampling and direction sampling estimate the same light).
    #[inline(always)]
    pub fn transmittance<const ANALYTIC: bool>(&self, ray: &Ray) -> f32 {
        if self.world.accel.unoccluded::<ANALYTIC>(ray) {
            1.0
        } else if self.world.features.pass_through {
            self.transmittance_through::<ANALYTIC>(ray)
        } else {
            0.0
        }
    }

    /// [`Scene::transmittance`] of a blocked ray in a scene with pass-through surfaces: steps
    /// from surface to surface (at most [`MAX_PASSES`]).
    #[inline(never)]
    pub fn transmittance_through<const ANALYTIC: bool>(&self, ray: &Ray) -> f32 {
        let target = ray.o + ray.d * ray.tmax;
        let mut ray = *ray;
        let mut t = 1.0;
        for _ in 0..MAX_PASSES {
            let Some(hit) = self.world.accel.intersect::<ANALYTIC>(&ray) else {
                return t;
            };
            let si = self.world.accel.interaction(&ray, &hit);
            t *= self.pass_probability(&si);
            if t <= 0.0 {
                return 0.0;
            }
            ray = spawn_ray_to(si.p, si.ng, target, self.world.accel.offset_floor());
            // The step must make progress along the original direction.
            if ray.tmax <= 0.0 || ray.d.dot(target - si.p) <= 0.0 {
                return t;
            }
        }
        0.0
    }
}

/// The most surfaces a path or a shadow ray passes straight through in one segment: beyond
/// it the light is taken as blocked (a stack of thousands of cut-out leaves in one
/// direction is not a scene anyone renders; a ray caught on one surface by rounding is).
pub const MAX_PASSES: u32 = 256;

/// Bytes of acceleration structure per triangle (CWBVH nodes, SoA triangle blocks, the build's
/// temporaries), an upper estimate.
const BVH_BYTES_PER_TRIANGLE: u64 = 256;
/// Films a render keeps at once (the guided driver keeps an image per iteration it combines,
/// the pixel estimate, the fallback's films and the films of two units in flight and two
/// ended ones kept for reuse; a path render one).
const GUIDED_FILMS: u64 = 10;
/// Bytes a pixel of the samples of two few-spp units (in flight, or kept for reuse) that a
/// guided session splats itself: `SAMPLES_MAX_SPP` records of a position and a value.
const GUIDED_SAMPLE_BYTES: u64 =
    2 * crate::pass::SAMPLES_MAX_SPP * std::mem::size_of::<crate::splat::SampleRec>() as u64;
/// The renderer's pass buffer cap (`render::PASS_BUFFER_BYTES`) and other per-render scratch.
const SCRATCH_BYTES: u64 = 512 << 20;

/// What a guided session's films and samples take for a `width` x `height` image, an
/// upper estimate: what a farm coordinator, which holds sessions but no scene, budgets a job.
pub fn guided_session_bytes(width: u32, height: u32) -> u64 {
    let sums = std::mem::size_of::<crate::film::PixelStats>() as u64;
    width as u64 * height as u64 * (GUIDED_FILMS * sums + GUIDED_SAMPLE_BYTES)
}

/// Refuses, before the BVH or any film is allocated, a render whose estimated memory (the
/// scene's meshes and textures, the BVH, the films) exceeds `Limits::max_memory_bytes`.
/// `triangles` and `data_bytes` are the world's (the description's when it is built from it).
fn check_memory(desc: &SceneDesc, triangles: usize, data_bytes: u64) -> Result<(), RenderError> {
    let film = &desc.sensor.film;
    let pixels = film.width as u64 * film.height as u64;
    let sums = std::mem::size_of::<crate::film::PixelStats>() as u64;
    let per_pixel = match desc.integrator {
        IntegratorDesc::Path(_) => sums,
        IntegratorDesc::GuidedPath(_) => GUIDED_FILMS * sums + GUIDED_SAMPLE_BYTES,
    };
    let film_bytes = pixels * per_pixel;
    let bvh_bytes = triangles as u64 * BVH_BYTES_PER_TRIANGLE;
    let total = film_bytes + bvh_bytes + data_bytes + SCRATCH_BYTES;
    let limit = desc.limits.max_memory_bytes;
    if total > limit {
        return Err(RenderError::TooLarge(format!(
            "{}: the render needs about {} (films of {}x{}: {}; BVH of {triangles} triangles: \
             {}; meshes and textures: {}), more than the memory limit of {} \
             (Limits::max_memory_bytes)",
            desc.source.display(),
            format_bytes(total),
            film.width,
            film.height,
            format_bytes(film_bytes),
            format_bytes(bvh_bytes),
            format_bytes(data_bytes),
            format_bytes(limit)
        )));
    }
    Ok(())
}

/// The triangles of `desc`'s meshes.
fn desc_triangles(desc: &SceneDesc) -> usize {
    (desc.shapes.iter())
        .map(|s| match &s.geometry {
            Geometry::Mesh(m) => m.indices.len(),
            _ => 0,
        })
        .sum()
}
