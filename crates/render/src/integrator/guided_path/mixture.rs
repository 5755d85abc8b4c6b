//! Sampling a vertex's direction from the one-sample mixture of the BSDF and the guide, and
//! restricting the guide to the part of the sphere the BSDF can scatter into.

// `!(x > 0.0)` is used on purpose: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use super::*;

/// The mixture pdf `alpha p_bsdf + (1 - alpha) p_guide` (just `p_bsdf` when unguided).
#[inline]
pub fn mixture_pdf(guided: bool, alpha: f32, p_bsdf: f32, p_guide: f32) -> f32 {
    if guided {
        alpha * p_bsdf + (1.0 - alpha) * p_guide
    } else {
        p_bsdf
    }
}

/// The shading normal on the side of `wi` (local) at a BSDF that cannot transmit: the
/// hemisphere around it is where alone the BSDF is nonzero. None for transmissive BSDFs.
#[inline]
pub(super) fn reflecting_normal(flags: BsdfFlags, frame: &Frame, wi: Vec3) -> Option<Vec3> {
    (!flags.transmission).then(|| if wi.z < 0.0 { -frame.n } else { frame.n })
}

/// The cells the guide samples from at a vertex (see [`pathfarm_guide::region`]): with
/// `hemisphere`, at a BSDF that cannot transmit, the hemisphere of the shading normal on the
/// side of `wi` (local), where alone the BSDF is nonzero; else everything.
#[inline]
pub fn guide_mask(hemisphere: bool, flags: BsdfFlags, frame: &Frame, wi: Vec3) -> CellMask {
    match reflecting_normal(flags, frame, wi) {
        Some(n) if hemisphere => CellMask::hemisphere(n),
        _ => CellMask::ALL,
    }
}

/// [`guide_mask`], and with `cosine` the mask's cells weighted by the clamped cosine of the
/// same normal ([`CellWeights::cosine`]): the guide then samples incident radiance x cosine.
#[inline]
pub fn guide_region(
    hemisphere: bool,
    cosine: bool,
    flags: BsdfFlags,
    frame: &Frame,
    wi: Vec3,
) -> CellWeights {
    match reflecting_normal(flags, frame, wi) {
        Some(n) if hemisphere && cosine => CellWeights::cosine(n),
        Some(n) if hemisphere => CellMask::hemisphere(n).into(),
        _ => CellWeights::ALL,
    }
}

/// The unrestricted guide's density in the direction of `ms` (its `p_guide` is the restricted
/// one): what guided roulette's radiance estimate (flux x pdf) needs. 0 where the restriction
/// leaves the direction out. The cell's weight is looked up by [`CellMask::cell_of_dir`] (no
/// arctangent; 1.7 % of a veach-ajar render with `dir_to_uv`), which may pick the neighbouring
/// quarter within rounding of its edge: that only moves a survival probability. (Unweighted
/// cells have weight exactly 1, so a plain mask divides by 1.)
#[inline]
pub(super) fn unrestricted_guide_pdf(r: &Restriction, ms: &MixtureSample) -> f32 {
    ms.p_guide * r.mass / r.weight[CellMask::cell_of_dir(ms.wo_world) as usize]
}

/// Power-heuristic weight of the strategy with pdf `a` against the one with `b` (light
/// sample: `mis_weight(p_light, p_mix)`; emitter hit: `mis_weight(p_mix, p_light)`).
#[inline]
pub fn mis_weight(a: f32, b: f32) -> f32 {
    power_heuristic(a, b)
}

/// Guide state at one vertex: the leaf, whether guiding applies, and alpha.
#[derive(Clone, Copy, Debug)]
pub struct VertexGuide {
    /// The spatial leaf of the vertex (with its box, which recording reuses).
    pub at: SLookup,
    /// Guiding applies here: the tree is built and the BSDF has a smooth component. False: the
    /// BSDF alone is sampled and `alpha` is 1.
    pub guided: bool,
    /// The leaf's learned BSDF-sampling fraction: the probability of sampling the BSDF rather than
    /// the guide (1 when unguided).
    pub alpha: f32,
    /// The part of the sphere the guide samples from (see [`pathfarm_guide::region`]):
    /// everything, or the hemisphere an opaque surface reflects into.
    pub region: Restriction,
}

impl VertexGuide {
    /// Looks the leaf up once, at a vertex with a smooth BSDF. Guiding applies once the tree
    /// is built.
    #[inline]
    pub fn at(tree: &SdTree, p: Vec3, region: impl Into<CellWeights>) -> Self {
        let mut g = Self::lookup(tree, p);
        g.resolve(tree, region);
        g
    }

    /// The first half of [`VertexGuide::at`]: the leaf, with its payload requested from
    /// memory ([`SdTree::prefetch_leaf`]) but not read. [`VertexGuide::resolve`] must run
    /// before the guide is used (sampling, pdf).
    #[inline]
    pub fn lookup(tree: &SdTree, p: Vec3) -> Self {
        let at = tree.lookup(p);
        let guided = tree.is_built();
        if guided {
            tree.prefetch_leaf(LeafHandle(at.leaf));
        }
        Self {
            at,
            guided,
            alpha: 1.0,
            region: Restriction::NONE,
        }
    }

    /// The second half of [`VertexGuide::at`]: reads the leaf's sampling fraction, restricts
    /// the guide to `region`, a mask or weighted cells ([`CellWeights::ALL`]: no restriction;
    /// see [`guide_region`]), and requests its quadtree's top nodes
    /// ([`SdTree::prefetch_sampling`]).
    #[inline]
    pub fn resolve(&mut self, tree: &SdTree, region: impl Into<CellWeights>) {
        if self.guided {
            tree.prefetch_sampling(self.leaf());
            self.alpha = tree.bsdf_sampling_fraction_leaf(self.leaf());
            self.region = tree.restriction_leaf(self.leaf(), region);
        }
    }

    /// The vertex's spatial leaf.
    #[inline]
    pub fn leaf(&self) -> LeafHandle {
        LeafHandle(self.at.leaf)
    }

    /// No guiding at this vertex (a BSDF without smooth components): the BSDF alone.
    pub fn unguided() -> Self {
        Self {
            at: SLookup::default(),
            guided: false,
            alpha: 1.0,
            region: Restriction::NONE,
        }
    }

    /// `p_mix` of the world direction `wo_world` (local `wo`) and its parts
    /// `(p_mix, p_bsdf, p_guide)`: what NEE weighs against.
    #[inline]
    pub fn pdf(
        &self,
        tree: &SdTree,
        bsdf: &ShadedBsdf,
        wi: Vec3,
        wo: Vec3,
        wo_world: Vec3,
    ) -> (f32, f32, f32) {
        let p_bsdf = bsdf.pdf(wi, wo);
        let p_guide = if self.guided {
            tree.pdf_leaf_restricted(self.leaf(), self.region, wo_world)
        } else {
            0.0
        };
        (
            mixture_pdf(self.guided, self.alpha, p_bsdf, p_guide),
            p_bsdf,
            p_guide,
        )
    }
}

/// A direction drawn from the BSDF/guide mixture.
#[derive(Clone, Copy, Debug, Default)]
pub struct MixtureSample {
    /// Local (shading-frame) direction.
    pub wo: Vec3,
    /// World direction.
    pub wo_world: Vec3,
    /// Throughput factor: `f cos / p_mix`, or `f / (alpha p_bsdf)` for a delta lobe.
    pub weight: Vec3,
    /// `f cos` (zero for delta lobes).
    pub fcos: Vec3,
    /// Mixture pdf (for a delta lobe `alpha` times the lobe probability).
    pub p_mix: f32,
    /// The BSDF's solid-angle pdf of `wo` (for a delta lobe, its lobe probability).
    pub p_bsdf: f32,
    /// The guide's solid-angle pdf of `wo_world` (0 when unguided or for a delta lobe).
    pub p_guide: f32,
    /// The direction came from a delta lobe of the BSDF: it takes no part in MIS and is not
    /// recorded.
    pub delta: bool,
    /// Relative IOR of the crossing (1 for reflection), from the actual direction.
    pub eta: f32,
}

/// Relative IOR of the crossing from local `wi` to `wo` (1 for reflection). Only the rough
/// dielectric has smooth transmission, so only it can get a guide-sampled refraction.
#[inline]
pub(super) fn crossing_eta(bsdf: &ShadedBsdf, wi: Vec3, wo: Vec3) -> f32 {
    if wi.z * wo.z >= 0.0 {
        return 1.0;
    }
    match bsdf.model {
        Bsdf::RoughDielectric(b) => {
            if wi.z > 0.0 {
                b.eta
            } else {
                1.0 / b.eta
            }
        }
        _ => 1.0,
    }
}

/// [`Scene::bsdf_at`] kept out of line here. The path integrator inlines it (its shading
/// loop is small and the call's stack round trip stalled it), but inlined into this much
/// larger loop body it cost guided rendering: out of line is 1.3 % faster on veach-ajar
/// (bench/ab.py, 6 reps, 1.006-1.017, images identical).
#[inline(never)]
pub(super) fn bsdf_at_outlined<'s>(
    scene: &'s Scene,
    si: &crate::geometry::SurfaceInteraction,
    prim: u32,
    d: Vec3,
) -> (ShadedBsdf<'s>, Frame) {
    scene.bsdf_at(si, prim, d)
}

/// [`sample_mixture`] into `out` (false: absorbed, `out` unchanged). The integrator's form:
/// an `Option<MixtureSample>` returned through memory was written field by field and read
/// back in 32-byte blocks, a store-forwarding stall at every vertex; written into the
/// caller's variable, its fields are read one by one.
#[inline(never)]
pub(super) fn sample_mixture_into(
    tree: &SdTree,
    g: &VertexGuide,
    bsdf: &ShadedBsdf,
    frame: &Frame,
    wi: Vec3,
    rng: &mut Rng,
    out: &mut MixtureSample,
) -> bool {
    sample_mixture(tree, g, bsdf, frame, wi, rng)
        .map(|ms| *out = ms)
        .is_some()
}

/// Samples the mixture at one vertex. `None` means the path is absorbed.
#[inline]
pub fn sample_mixture(
    tree: &SdTree,
    g: &VertexGuide,
    bsdf: &ShadedBsdf,
    frame: &Frame,
    wi: Vec3,
    rng: &mut Rng,
) -> Option<MixtureSample> {
    let use_bsdf = !g.guided || rng.next_f32() < g.alpha;
    if use_bsdf {
        let bs = bsdf.sample(wi, rng.next_f32(), rng.next_2d())?;
        let wo_world = frame.to_world(bs.wo);
        if bs.lobe.delta {
            return Some(MixtureSample {
                wo: bs.wo,
                wo_world,
                weight: bs.weight / g.alpha,
                fcos: Vec3::ZERO,
                p_mix: g.alpha * bs.pdf,
                p_bsdf: bs.pdf,
                p_guide: 0.0,
                delta: true,
                eta: bs.eta,
            });
        }
        if !g.guided {
            return Some(MixtureSample {
                wo: bs.wo,
                wo_world,
                weight: bs.weight,
                fcos: bs.weight * bs.pdf,
                p_mix: bs.pdf,
                p_bsdf: bs.pdf,
                p_guide: 0.0,
                delta: false,
                eta: bs.eta,
            });
        }
        // A non-delta BSDF sample carries its own pdf and f cos / pdf (the bsdf crate's
        // tests check that they equal `pdf` and `eval / pdf`), so only the guide's pdf is new.
        let fcos = bs.weight * bs.pdf;
        let p_guide = tree.pdf_leaf_restricted(g.leaf(), g.region, wo_world);
        let p_mix = mixture_pdf(true, g.alpha, bs.pdf, p_guide);
        finish(bs.wo, wo_world, fcos, p_mix, bs.pdf, p_guide, bs.eta)
    } else {
        // The guide's sampler returns the same pdf `pdf_leaf` gives for that direction.
        let (wo_world, p_guide) =
            tree.sample_leaf_restricted(g.leaf(), g.region, &mut || rng.next_f32())?;
        let wo = frame.to_local(wo_world);
        let fcos = bsdf.eval(wi, wo);
        let p_bsdf = bsdf.pdf(wi, wo);
        let p_mix = mixture_pdf(true, g.alpha, p_bsdf, p_guide);
        finish(
            wo,
            wo_world,
            fcos,
            p_mix,
            p_bsdf,
            p_guide,
            crossing_eta(bsdf, wi, wo),
        )
    }
}

#[inline]
pub(super) fn finish(
    wo: Vec3,
    wo_world: Vec3,
    fcos: Vec3,
    p_mix: f32,
    p_bsdf: f32,
    p_guide: f32,
    eta: f32,
) -> Option<MixtureSample> {
    if !(p_mix > 0.0) || !(fcos.max_element() > 0.0) {
        return None;
    }
    let weight = fcos / p_mix;
    if !weight.is_finite() {
        return None;
    }
    Some(MixtureSample {
        wo,
        wo_world,
        weight,
        fcos,
        p_mix,
        p_bsdf,
        p_guide,
        delta: false,
        eta,
    })
}
