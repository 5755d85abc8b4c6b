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

/// A surface material: a single BSDF, or Mitsuba's `twosided` pair of a front and a back BSDF.
pub enum Material {
    /// A plain BSDF, always evaluated in the unflipped frame of the shading normal: the reflective
    /// models are black seen from the back, the dielectrics handle both sides themselves.
    OneSided(Side),
    /// Mitsuba `twosided`: the back side is seen through a flipped frame.
    TwoSided(Side, Side),
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
    fn new(desc: &BsdfDesc, textures: &[TextureDesc]) -> Self {
        match desc {
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
            // Nested twosided is resolved by Material::new; treat as its front.
            BsdfDesc::TwoSided { .. } => Side::Diffuse {
                reflectance: TexRef::Const(Vec3::splat(0.5)),
            },
        }
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

impl Material {
    /// Builds the material for `desc`; `all` is the scene's BSDF list, which the indices of a
    /// `twosided` desc refer to, and `textures` is used for the plastic sampling weights.
    pub fn new(desc: &BsdfDesc, all: &[BsdfDesc], textures: &[TextureDesc]) -> Self {
        match desc {
            BsdfDesc::TwoSided { front, back } => Material::TwoSided(
                Side::new(&all[*front], textures),
                Side::new(&all[*back], textures),
            ),
            d => Material::OneSided(Side::new(d, textures)),
        }
    }

    /// The BSDF at hit `si` for a ray travelling along `ray_d`, and its frame.
    #[inline(always)]
    pub fn bsdf<'a>(
        &'a self,
        textures: &[TextureDesc],
        si: &SurfaceInteraction,
        ray_d: Vec3,
    ) -> (Bsdf<'a>, Frame) {
        let frame = Frame::from_normal(si.ns);
        match self {
            Material::OneSided(s) => (s.bsdf(textures, si.uv), frame),
            Material::TwoSided(front, back) => {
                if si.ns.dot(ray_d) > 0.0 {
                    (back.bsdf(textures, si.uv), frame.flipped())
                } else {
                    (front.bsdf(textures, si.uv), frame)
                }
            }
        }
    }
}
