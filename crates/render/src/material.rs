//! Materials: a BSDF description with its textures, turned into a concrete
//! [`Bsdf`] at each shading point. Everything that does not depend on the
//! hit (Fresnel integrals, rough-plastic tables, sampling weights) is
//! computed once here.

use glam::Vec3;
use pathfarm_bsdf::frame::Frame;
use pathfarm_bsdf::{
    specular_sampling_weight, Bsdf, Conductor, Dielectric, Diffuse, Microfacet, MicrofacetType,
    Plastic, RoughConductor, RoughDielectric, RoughPlastic, RoughPlasticTable, ThinDielectric,
};
use pathfarm_scene::{BsdfDesc, MicrofacetDistribution, Roughness, TexRef, TextureDesc};

use crate::geometry::SurfaceInteraction;
use crate::shading::{BumpCorrection, Perturb, ShadedBsdf};
use crate::texture;

/// One side of a material.
pub enum Side {
    /// Lambertian reflector (Mitsuba `diffuse`).
    Diffuse {
        /// Albedo (linear RGB), constant or textured.
        reflectance: TexRef,
    },
    /// Smooth conductor: a perfect mirror with complex-IOR Fresnel (Mitsuba `conductor`).
    Conductor {
        /// Real part of the complex index of refraction per RGB channel, relative to the exterior.
        eta: Vec3,
        /// Imaginary part of the complex index of refraction (absorption coefficient) per RGB
        /// channel.
        k: Vec3,
        /// Factor on the Fresnel reflectance (Mitsuba `specular_reflectance`); not physically
        /// based, 1 by default.
        specular: TexRef,
    },
    /// Microfacet conductor (Mitsuba `roughconductor`).
    RoughConductor {
        /// Microfacet distribution (Beckmann or GGX) and its roughness along the shading
        /// frame's tangent axes. The frame is built from the shading normal alone, so for
        /// anisotropic roughness its first axis is not the surface's `u` direction.
        distr: Microfacet,
        /// Real part of the complex index of refraction per RGB channel, relative to the exterior.
        eta: Vec3,
        /// Imaginary part of the complex index of refraction (absorption coefficient) per RGB
        /// channel.
        k: Vec3,
        /// Factor on the Fresnel reflectance (Mitsuba `specular_reflectance`).
        specular: TexRef,
    },
    /// Smooth dielectric interface: delta reflection and refraction (Mitsuba `dielectric`).
    Dielectric {
        /// Relative index of refraction, `int_ior / ext_ior`; the normal points to the exterior.
        eta: f32,
        /// Factor on the reflected lobe (Mitsuba `specular_reflectance`).
        reflect: TexRef,
        /// Factor on the transmitted lobe (Mitsuba `specular_transmittance`).
        transmit: TexRef,
    },
    /// Microfacet dielectric interface with rough reflection and refraction (Mitsuba
    /// `roughdielectric`).
    RoughDielectric {
        /// Microfacet distribution (Beckmann or GGX) and its roughness (see
        /// [`Side::RoughConductor`]).
        distr: Microfacet,
        /// Relative index of refraction, `int_ior / ext_ior`.
        eta: f32,
        /// Factor on the reflected lobe (Mitsuba `specular_reflectance`).
        reflect: TexRef,
        /// Factor on the transmitted lobe (Mitsuba `specular_transmittance`).
        transmit: TexRef,
    },
    /// Thin dielectric sheet: delta reflection with the slab's multiple internal bounces, and
    /// undeviated transmission (Mitsuba `thindielectric`).
    ThinDielectric {
        /// Relative index of refraction of the sheet, `int_ior / ext_ior`.
        eta: f32,
        /// Factor on the reflected lobe (Mitsuba `specular_reflectance`).
        reflect: TexRef,
        /// Factor on the transmitted lobe (Mitsuba `specular_transmittance`).
        transmit: TexRef,
    },
    /// Diffuse base under a smooth dielectric coating (Mitsuba `plastic`).
    Plastic {
        /// Relative index of refraction of the coating, `int_ior / ext_ior`.
        eta: f32,
        /// Albedo of the diffuse base (Mitsuba `diffuse_reflectance`).
        diffuse: TexRef,
        /// Factor on the coating's specular reflection (Mitsuba `specular_reflectance`).
        specular: TexRef,
        /// Mitsuba's `nonlinear`: account for the colour shift of light scattered repeatedly
        /// between the base and the coating (divide by `1 - diffuse * Fdr` instead of `1 - Fdr`).
        nonlinear: bool,
        /// Probability of sampling the specular lobe rather than the diffuse one, computed once
        /// from the textures' means by [`specular_sampling_weight`].
        ssw: f32,
    },
    /// Diffuse base under a rough dielectric coating (Mitsuba `roughplastic`); isotropic roughness
    /// only.
    RoughPlastic {
        /// Precomputed coating transmittance and internal reflectance; also holds the distribution,
        /// the roughness and the relative IOR.
        table: Box<RoughPlasticTable>,
        /// Albedo of the diffuse base (Mitsuba `diffuse_reflectance`).
        diffuse: TexRef,
        /// Factor on the coating's specular reflection (Mitsuba `specular_reflectance`).
        specular: TexRef,
        /// Mitsuba's `nonlinear`, as in [`Side::Plastic`].
        nonlinear: bool,
        /// Probability of sampling the specular lobe, computed once from the textures' means by
        /// [`specular_sampling_weight`].
        ssw: f32,
        /// Sample only the microfacet normals visible from the incident direction.
        sample_visible: bool,
    },
}

/// A surface material: its sides (a single BSDF, or Mitsuba's `twosided` pair), how much light
/// passes straight through it (`mask`, `null`), and the texture that perturbs its shading
/// normal (`bumpmap`, `normalmap`).
pub struct Material {
    sides: Sides,
    opacity: Opacity,
    perturb: Option<Perturb>,
}

/// The BSDFs of a material's two sides.
enum Sides {
    /// A plain BSDF, always evaluated in the unflipped frame of the shading normal: the
    /// reflective models are black seen from the back, the dielectrics handle both sides
    /// themselves.
    One(Side),
    /// Mitsuba `twosided`: the back side is seen through a flipped frame.
    Two(Side, Side),
}

/// How much of a surface is there (Mitsuba's `mask` and `null` wrappers).
#[derive(Clone, Copy, Debug)]
pub enum Opacity {
    /// Every ray that meets the surface scatters.
    Opaque,
    /// A ray passes straight through with probability `1 - opacity` (the luminance of the
    /// texture, clamped to [0, 1]).
    Mask(TexRef),
    /// Every ray passes straight through (Mitsuba `null`).
    Null,
}

/// The distribution a rough model samples and evaluates (roughness clamped as Mitsuba's).
fn microfacet(r: &Roughness) -> Microfacet {
    Microfacet::new(kind(r.distribution), r.alpha_u, r.alpha_v, r.sample_visible)
}

fn kind(d: MicrofacetDistribution) -> MicrofacetType {
    match d {
        MicrofacetDistribution::Beckmann => MicrofacetType::Beckmann,
        MicrofacetDistribution::Ggx => MicrofacetType::Ggx,
    }
}

/// Average over the texture (Mitsuba's `Texture::mean`), as a scalar.
fn mean(textures: &[TextureDesc], r: TexRef) -> f32 {
    let c = match r {
        TexRef::Const(c) => c,
        TexRef::Texture(i) => match &textures[i] {
            TextureDesc::Bitmap(b) => b.texels.iter().sum::<Vec3>() / b.texels.len().max(1) as f32,
            TextureDesc::Checkerboard { color0, color1, .. } => (*color0 + *color1) * 0.5,
        },
    };
    (c.x + c.y + c.z) / 3.0
}

/// The specular sampling weight of a (rough) plastic: both share Mitsuba's rule, from the
/// means of the diffuse and specular reflectances.
fn plastic_ssw(textures: &[TextureDesc], diffuse: TexRef, specular: TexRef) -> f32 {
    specular_sampling_weight(mean(textures, diffuse), mean(textures, specular))
}

impl Side {
    fn new(desc: &BsdfDesc, textures: &[TextureDesc]) -> Result<Self, String> {
        Ok(match desc {
            BsdfDesc::Diffuse { reflectance } => Side::Diffuse {
                reflectance: *reflectance,
            },
            BsdfDesc::Conductor {
                eta,
                k,
                specular_reflectance,
            } => Side::Conductor {
                eta: *eta,
                k: *k,
                specular: *specular_reflectance,
            },
            BsdfDesc::RoughConductor {
                roughness: r,
                eta,
                k,
                specular_reflectance,
            } => Side::RoughConductor {
                distr: microfacet(r),
                eta: *eta,
                k: *k,
                specular: *specular_reflectance,
            },
            BsdfDesc::Dielectric {
                int_ior,
                ext_ior,
                specular_reflectance,
                specular_transmittance,
            } => Side::Dielectric {
                eta: int_ior / ext_ior,
                reflect: *specular_reflectance,
                transmit: *specular_transmittance,
            },
            BsdfDesc::RoughDielectric {
                roughness: r,
                int_ior,
                ext_ior,
                specular_reflectance,
                specular_transmittance,
            } => Side::RoughDielectric {
                distr: microfacet(r),
                eta: int_ior / ext_ior,
                reflect: *specular_reflectance,
                transmit: *specular_transmittance,
            },
            BsdfDesc::ThinDielectric {
                int_ior,
                ext_ior,
                specular_reflectance,
                specular_transmittance,
            } => Side::ThinDielectric {
                eta: int_ior / ext_ior,
                reflect: *specular_reflectance,
                transmit: *specular_transmittance,
            },
            BsdfDesc::Plastic {
                int_ior,
                ext_ior,
                diffuse_reflectance,
                specular_reflectance,
                nonlinear,
            } => Side::Plastic {
                eta: int_ior / ext_ior,
                diffuse: *diffuse_reflectance,
                specular: *specular_reflectance,
                nonlinear: *nonlinear,
                ssw: plastic_ssw(textures, *diffuse_reflectance, *specular_reflectance),
            },
            BsdfDesc::RoughPlastic {
                roughness: r,
                int_ior,
                ext_ior,
                diffuse_reflectance,
                specular_reflectance,
                nonlinear,
            } => Side::RoughPlastic {
                table: Box::new(RoughPlasticTable::new(
                    kind(r.distribution),
                    r.alpha_u,
                    int_ior / ext_ior,
                )),
                diffuse: *diffuse_reflectance,
                specular: *specular_reflectance,
                nonlinear: *nonlinear,
                ssw: plastic_ssw(textures, *diffuse_reflectance, *specular_reflectance),
                sample_visible: r.sample_visible,
            },
            BsdfDesc::TwoSided { .. }
            | BsdfDesc::Mask { .. }
            | BsdfDesc::Null
            | BsdfDesc::BumpMap { .. }
            | BsdfDesc::NormalMap { .. } => {
                return Err(format!(
                    "a {} inside another wrapper in this combination (nested twosided, two \
                     masks or two normal perturbations on one surface, or a twosided whose \
                     two sides are wrapped differently)",
                    wrapper_name(desc)
                ))
            }
        })
    }

    #[inline(always)]
    fn bsdf<'a>(&'a self, textures: &[TextureDesc], uv: glam::Vec2) -> Bsdf<'a> {
        let t = |r: TexRef| texture::eval(textures, r, uv);
        match self {
            Side::Diffuse { reflectance } => Bsdf::Diffuse(Diffuse::new(t(*reflectance))),
            Side::Conductor { eta, k, specular } => {
                Bsdf::Conductor(Conductor::new(*eta, *k, t(*specular)))
            }
            Side::RoughConductor {
                distr,
                eta,
                k,
                specular,
            } => Bsdf::RoughConductor(RoughConductor::new(
                *distr,
                Conductor::new(*eta, *k, t(*specular)),
            )),
            Side::Dielectric {
                eta,
                reflect,
                transmit,
            } => Bsdf::Dielectric(Dielectric::new(*eta, t(*reflect), t(*transmit))),
            Side::RoughDielectric {
                distr,
                eta,
                reflect,
                transmit,
            } => Bsdf::RoughDielectric(RoughDielectric::new(
                *distr,
                *eta,
                t(*reflect),
                t(*transmit),
            )),
            Side::ThinDielectric {
                eta,
                reflect,
                transmit,
            } => Bsdf::ThinDielectric(ThinDielectric::new(*eta, t(*reflect), t(*transmit))),
            Side::Plastic {
                eta,
                diffuse,
                specular,
                nonlinear,
                ssw,
            } => Bsdf::Plastic(Plastic::new(
                *eta,
                t(*diffuse),
                t(*specular),
                *nonlinear,
                *ssw,
            )),
            Side::RoughPlastic {
                table,
                diffuse,
                specular,
                nonlinear,
                ssw,
                sample_visible,
            } => Bsdf::RoughPlastic(RoughPlastic::new(
                table,
                t(*diffuse),
                t(*specular),
                *nonlinear,
                *ssw,
                *sample_visible,
            )),
        }
    }
}

fn wrapper_name(desc: &BsdfDesc) -> &'static str {
    match desc {
        BsdfDesc::TwoSided { .. } => "twosided",
        BsdfDesc::Mask { .. } => "mask",
        BsdfDesc::Null => "null",
        BsdfDesc::BumpMap { .. } => "bumpmap",
        BsdfDesc::NormalMap { .. } => "normalmap",
        _ => "bsdf",
    }
}

/// The black BSDF a `null` surface never scatters with.
const NO_SIDE: Side = Side::Diffuse {
    reflectance: TexRef::Const(Vec3::ZERO),
};

impl Material {
    /// Builds the material for `desc`; `all` is the scene's BSDF list, which the indices of
    /// wrapper descs refer to, and `textures` is used for the plastic sampling weights. The
    /// wrappers (`twosided`, `mask`, `bumpmap`, `normalmap`) may nest in any order, at most
    /// one of each; `Err` names a combination that is not supported.
    pub fn new(
        desc: &BsdfDesc,
        all: &[BsdfDesc],
        textures: &[TextureDesc],
    ) -> Result<Self, String> {
        let mut opacity = Opacity::Opaque;
        let mut perturb = None;
        let mut two_sided = false;
        let mut d = desc;
        loop {
            let next = match d {
                BsdfDesc::Mask { opacity: o, nested } if matches!(opacity, Opacity::Opaque) => {
                    opacity = Opacity::Mask(*o);
                    *nested
                }
                BsdfDesc::Null if matches!(opacity, Opacity::Opaque) => {
                    return Ok(Self {
                        sides: Sides::One(NO_SIDE),
                        opacity: Opacity::Null,
                        perturb: None,
                    });
                }
                BsdfDesc::BumpMap {
                    height,
                    scale,
                    nested,
                    normals,
                } if perturb.is_none() => {
                    perturb = Some(Perturb::Bump {
                        height: *height,
                        scale: *scale,
                        options: *normals,
                    });
                    *nested
                }
                BsdfDesc::NormalMap {
                    normals_texture,
                    nested,
                    normals,
                } if perturb.is_none() => {
                    perturb = Some(Perturb::Normal {
                        texture: *normals_texture,
                        options: *normals,
                    });
                    *nested
                }
                BsdfDesc::TwoSided { front, back } if !two_sided && front == back => {
                    two_sided = true;
                    *front
                }
                BsdfDesc::TwoSided { front, back } if !two_sided => {
                    let sides = Sides::Two(
                        Side::new(&all[*front], textures)?,
                        Side::new(&all[*back], textures)?,
                    );
                    return Ok(Self {
                        sides,
                        opacity,
                        perturb,
                    });
                }
                d => {
                    let side = Side::new(d, textures)?;
                    let sides = if two_sided {
                        Sides::Two(Side::new(d, textures)?, side)
                    } else {
                        Sides::One(side)
                    };
                    return Ok(Self {
                        sides,
                        opacity,
                        perturb,
                    });
                }
            };
            d = &all[next];
        }
    }

    /// The probability that a ray meeting the surface at `si` passes straight through it.
    #[inline(always)]
    pub fn pass_probability(&self, textures: &[TextureDesc], si: &SurfaceInteraction) -> f32 {
        match self.opacity {
            Opacity::Opaque => 0.0,
            Opacity::Null => 1.0,
            Opacity::Mask(r) => 1.0 - texture::eval_scalar(textures, r, si.uv).clamp(0.0, 1.0),
        }
    }

    /// The side a ray travelling along `ray_d` sees, the frame `base` flipped for a back side,
    /// and whether it is the back.
    #[inline(always)]
    fn side(&self, si: &SurfaceInteraction, ray_d: Vec3, base: Frame) -> (&Side, Frame, bool) {
        match &self.sides {
            Sides::One(s) => (s, base, false),
            Sides::Two(front, back) => {
                if si.ns.dot(ray_d) > 0.0 {
                    (back, base.flipped(), true)
                } else {
                    (front, base, false)
                }
            }
        }
    }

    /// The BSDF at hit `si` for a ray travelling along `ray_d`, and its frame; `tangents`
    /// gives the surface's `(dp/du, dp/dv)`, which only a perturbed normal needs.
    ///
    /// The model is built in one place for both cases: built in an out-of-line call for the
    /// perturbed one, the whole returned pair was copied on every hit of every scene.
    #[inline(always)]
    pub fn bsdf<'a>(
        &'a self,
        textures: &[TextureDesc],
        si: &SurfaceInteraction,
        ray_d: Vec3,
        tangents: impl FnOnce() -> (Vec3, Vec3),
    ) -> (ShadedBsdf<'a>, Frame) {
        let (side, frame, bump) = match &self.perturb {
            None => {
                let (side, frame, _) = self.side(si, ray_d, Frame::from_normal(si.ns));
                (side, frame, None)
            }
            // `si` by value: a reference escaping into the out-of-line call would keep the
            // interaction in memory on every hit, perturbed or not.
            Some(p) => {
                let (side, (frame, bump)) = self.perturbed(p, textures, *si, ray_d, tangents());
                (side, frame, Some(bump))
            }
        };
        let model = side.bsdf(textures, si.uv);
        (ShadedBsdf { model, bump }, frame)
    }

    /// The side, frame and bump correction of [`Material::bsdf`] under a bump or normal map:
    /// the perturbed normal is found in the unperturbed frame (first axis along `dp/du`, as
    /// Mitsuba's), and seen mirrored in the surface from a `twosided` back side (Mitsuba's
    /// `twosided` around a `bumpmap`).
    #[inline(never)]
    fn perturbed(
        &self,
        p: &Perturb,
        textures: &[TextureDesc],
        si: SurfaceInteraction,
        ray_d: Vec3,
        tangents: (Vec3, Vec3),
    ) -> (&Side, (Frame, BumpCorrection)) {
        let base = Frame::from_normal_tangent(si.ns, tangents.0);
        let n = p.local_normal(textures, &si, &base, tangents);
        let (side, frame, back) = self.side(&si, ray_d, base);
        let n = if back { Vec3::new(n.y, n.x, n.z) } else { n };
        (side, p.perturbed_frame(&frame, n, frame.to_local(-ray_d)))
    }
}
