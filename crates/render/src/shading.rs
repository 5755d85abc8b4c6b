//! What a surface point scatters with: the BSDF model and, under a bump or normal map,
//! the correction Mitsuba applies for the perturbed shading normal; and how a material's
//! texture perturbs that normal.

use glam::{Vec2, Vec3};
use pathfarm_bsdf::{Bsdf, BsdfFlags, BsdfSample, Frame};
use pathfarm_scene::{PerturbOptions, TextureDesc};

use crate::geometry::SurfaceInteraction;
use crate::texture;

/// The BSDF at a shading point, evaluated in the (possibly perturbed) shading frame.
#[derive(Clone, Copy, Debug)]
pub struct ShadedBsdf<'a> {
    /// The scattering model.
    pub model: Bsdf<'a>,
    /// Set when a bump or normal map perturbed the frame.
    pub bump: Option<BumpCorrection>,
}

/// Mitsuba's `bumpmap`/`normalmap` rules for a direction `wo` of the perturbed frame: it
/// scatters only to directions on the same side of the unperturbed shading normal as of the
/// perturbed one, attenuated by the microfacet shadowing term of Estevez et al. (2019)
/// against the bump terminator.
#[derive(Clone, Copy, Debug)]
pub struct BumpCorrection {
    /// The unperturbed shading normal, in the perturbed frame.
    base: Vec3,
    /// `alpha^2` of the shadowing term (0: no shadowing function).
    alpha2: f32,
}

impl BumpCorrection {
    #[inline]
    fn valid(&self, wo: Vec3) -> bool {
        wo.z * self.base.dot(wo) > 0.0
    }

    /// The factor on the BSDF value towards `wo` (0 for directions the rule excludes).
    #[inline]
    fn factor(&self, wo: Vec3) -> f32 {
        if !self.valid(wo) {
            return 0.0;
        }
        if self.alpha2 == 0.0 {
            return 1.0;
        }
        let c2 = self.base.dot(wo).powi(2);
        let tan2 = (1.0 - c2).max(0.0) / c2;
        2.0 / (1.0 + (1.0 + self.alpha2 * tan2).sqrt())
    }
}

impl<'a> ShadedBsdf<'a> {
    /// A BSDF in the unperturbed shading frame.
    #[inline(always)]
    pub fn plain(model: Bsdf<'a>) -> Self {
        Self { model, bump: None }
    }

    /// The model's lobes.
    #[inline(always)]
    pub fn flags(&self) -> BsdfFlags {
        self.model.flags()
    }

    /// [`Bsdf::sample`], with the bump rules applied.
    #[inline(always)]
    pub fn sample(&self, wi: Vec3, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        let mut s = self.model.sample(wi, u_lobe, u)?;
        if let Some(b) = &self.bump {
            let f = b.factor(s.wo);
            if f <= 0.0 {
                return None;
            }
            s.weight *= f;
        }
        Some(s)
    }

    /// [`Bsdf::eval`], with the bump rules applied.
    #[inline(always)]
    pub fn eval(&self, wi: Vec3, wo: Vec3) -> Vec3 {
        match &self.bump {
            None => self.model.eval(wi, wo),
            Some(b) => match b.factor(wo) {
                f if f > 0.0 => self.model.eval(wi, wo) * f,
                _ => Vec3::ZERO,
            },
        }
    }

    /// [`Bsdf::pdf`], zero where the bump rules exclude `wo`.
    #[inline(always)]
    pub fn pdf(&self, wi: Vec3, wo: Vec3) -> f32 {
        match &self.bump {
            Some(b) if !b.valid(wo) => 0.0,
            _ => self.model.pdf(wi, wo),
        }
    }
}

/// How a material's texture perturbs its shading normal.
#[derive(Clone, Copy, Debug)]
pub enum Perturb {
    /// Mitsuba's `bumpmap`: a height field (texture index) scaled by `scale`.
    Bump {
        /// The height texture (its luminance).
        height: usize,
        /// Factor on the heights.
        scale: f32,
        /// Flip and shadowing options.
        options: PerturbOptions,
    },
    /// Mitsuba's `normalmap`: tangent-space normals (`2 rgb - 1`).
    Normal {
        /// The normal texture.
        texture: usize,
        /// Flip and shadowing options.
        options: PerturbOptions,
    },
}

impl Perturb {
    fn options(&self) -> PerturbOptions {
        match self {
            Perturb::Bump { options, .. } | Perturb::Normal { options, .. } => *options,
        }
    }

    /// The perturbed normal at `si` in the coordinates of `base` (the unperturbed shading
    /// frame whose first axis follows `dp_du`); not necessarily unit length.
    pub fn local_normal(
        &self,
        textures: &[TextureDesc],
        si: &SurfaceInteraction,
        base: &Frame,
        (dp_du, dp_dv): (Vec3, Vec3),
    ) -> Vec3 {
        match *self {
            Perturb::Normal { texture: t, .. } => {
                texture::eval_texture(&textures[t], si.uv) * 2.0 - Vec3::ONE
            }
            Perturb::Bump { height, scale, .. } => {
                let grad = scale * texture::luminance_gradient(&textures[height], si.uv);
                let n = base.n;
                let du = dp_du + n * (grad.x - n.dot(dp_du));
                let dv = dp_dv + n * (grad.y - n.dot(dp_dv));
                let nw = du.cross(dv).normalize_or_zero();
                let nw = if si.ng.dot(nw) < 0.0 { -nw } else { nw };
                base.to_local(nw)
            }
        }
    }

    /// The perturbed frame for a side frame `frame` (in which `wi`, towards the previous
    /// vertex, is given) and the perturbed normal `n` in its coordinates, with the correction
    /// its BSDF needs.
    pub fn perturbed_frame(&self, frame: &Frame, n: Vec3, wi: Vec3) -> (Frame, BumpCorrection) {
        let options = self.options();
        let n = if options.flip_invalid_normals && wi.z * wi.dot(n) <= 0.0 {
            Vec3::new(-n.x, -n.y, n.z)
        } else {
            n
        };
        let n = n.normalize_or_zero();
        if n == Vec3::ZERO || !n.is_finite() {
            let none = BumpCorrection {
                base: Vec3::Z,
                alpha2: 0.0,
            };
            return (*frame, none);
        }
        let n_world = frame.to_world(n);
        let perturbed = Frame::from_normal_tangent(n_world, frame.s);
        let alpha2 = if options.use_shadowing_function {
            let c2 = n.z * n.z;
            (0.125 * (1.0 - c2) / c2).min(1.0)
        } else {
            0.0
        };
        let correction = BumpCorrection {
            base: perturbed.to_local(frame.n),
            alpha2,
        };
        (perturbed, correction)
    }
}
