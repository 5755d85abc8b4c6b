//! Materials: a BSDF description with its textures, turned into a concrete
//! [`Bsdf`] at each shading point. Everything that does not depend on the
//! hit (Fresnel integrals, rough-plastic tables, sampling weights) is
//! computed once here.

use glam::Vec3;
use pathfarm_bsdf::frame::Frame;
use pathfarm_bsdf::{
    specular_sampling_weight, Bsdf, Conductor, Dielectric, Diffuse, MicrofacetType, Plastic,
    RoughConductor, RoughDielectric, RoughPlastic, RoughPlasticTable, ThinDielectric,
};
use pathfarm_scene::{BsdfDesc, MicrofacetDistribution, TexRef, TextureDesc};

use crate::geometry::SurfaceInteraction;
use crate::texture;

/// One side of a material.
pub enum Side {
    Diffuse {
        reflectance: TexRef,
    },
    Conductor {
        eta: Vec3,
        k: Vec3,
        specular: TexRef,
    },
    RoughConductor {
        kind: MicrofacetType,
        alpha_u: f32,
        alpha_v: f32,
        sample_visible: bool,
        eta: Vec3,
        k: Vec3,
        specular: TexRef,
    },
    Dielectric {
        eta: f32,
        reflect: TexRef,
        transmit: TexRef,
    },
    RoughDielectric {
        kind: MicrofacetType,
        alpha_u: f32,
        alpha_v: f32,
        sample_visible: bool,
        eta: f32,
        reflect: TexRef,
        transmit: TexRef,
    },
    ThinDielectric {
        eta: f32,
        reflect: TexRef,
        transmit: TexRef,
    },
    Plastic {
        eta: f32,
        diffuse: TexRef,
        specular: TexRef,
        nonlinear: bool,
        ssw: f32,
    },
    RoughPlastic {
        table: Box<RoughPlasticTable>,
        diffuse: TexRef,
        specular: TexRef,
        nonlinear: bool,
        ssw: f32,
        sample_visible: bool,
    },
}

pub enum Material {
    OneSided(Side),
    /// Mitsuba `twosided`: the back side is seen through a flipped frame.
    TwoSided(Side, Side),
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
                kind: kind(r.distribution),
                alpha_u: r.alpha_u,
                alpha_v: r.alpha_v,
                sample_visible: r.sample_visible,
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
                kind: kind(r.distribution),
                alpha_u: r.alpha_u,
                alpha_v: r.alpha_v,
                sample_visible: r.sample_visible,
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
                ssw: specular_sampling_weight(
                    mean(textures, *diffuse_reflectance),
                    mean(textures, *specular_reflectance),
                ),
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
                ssw: specular_sampling_weight(
                    mean(textures, *diffuse_reflectance),
                    mean(textures, *specular_reflectance),
                ),
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
                kind,
                alpha_u,
                alpha_v,
                sample_visible,
                eta,
                k,
                specular,
            } => Bsdf::RoughConductor(RoughConductor::new(
                *kind,
                *alpha_u,
                *alpha_v,
                *sample_visible,
                *eta,
                *k,
                t(*specular),
            )),
            Side::Dielectric {
                eta,
                reflect,
                transmit,
            } => Bsdf::Dielectric(Dielectric::new(*eta, t(*reflect), t(*transmit))),
            Side::RoughDielectric {
                kind,
                alpha_u,
                alpha_v,
                sample_visible,
                eta,
                reflect,
                transmit,
            } => Bsdf::RoughDielectric(RoughDielectric::new(
                *kind,
                *alpha_u,
                *alpha_v,
                *sample_visible,
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
