//! The plain scene description the loader produces and the renderer consumes.
//!
//! Everything here is already resolved: `$name` substitutions applied, `ref`s
//! followed, transforms baked into world-space geometry, meshes and images
//! loaded and validated. Colours are linear RGB (`Vec3`), as in Mitsuba 3's
//! `scalar_rgb` variant. Nothing in this module knows about rays or sampling.

use std::path::PathBuf;
use std::sync::Arc;

use glam::{Mat4, Vec2, Vec3};

/// Where a plugin was declared: used in error messages and diagnostics.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Location {
    pub file: PathBuf,
    /// 1-based line number.
    pub line: u32,
}

impl std::fmt::Display for Location {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}:{}", self.file.display(), self.line)
    }
}

/// A whole scene, ready to render.
#[derive(Clone, Debug)]
pub struct SceneDesc {
    /// The XML file the scene was loaded from.
    pub source: PathBuf,
    pub integrator: IntegratorDesc,
    pub sensor: SensorDesc,
    /// Shapes; each references a BSDF by index into `bsdfs`.
    pub shapes: Vec<ShapeDesc>,
    /// BSDF arena. `TwoSided` refers to other entries by index.
    pub bsdfs: Vec<BsdfDesc>,
    /// Texture arena, referenced by `TexRef::Texture`.
    pub textures: Vec<TextureDesc>,
    /// Emitters that are not attached to a shape (point, constant, envmap,
    /// directional). Area emitters live on their shape.
    pub emitters: Vec<EmitterDesc>,
    /// Which effects the scene uses, so the renderer can skip the rest.
    pub features: Features,
    /// Non-fatal notes from loading (e.g. a stratified sampler treated as
    /// independent), each prefixed with `file:line`. The loader does not log;
    /// the caller decides how to show these.
    pub warnings: Vec<String>,
    /// The limits it was loaded with; the renderer checks its own allocations against them.
    pub limits: crate::Limits,
    /// Every file the loader read: `source` first, then each file the scene references
    /// (meshes, textures, environment maps) as resolved (a relative name joined to `source`'s
    /// directory, an absolute one as written), each once, in the order first read.
    pub files: Vec<PathBuf>,
}

impl SceneDesc {
    /// Bytes of mesh and texture data the description holds.
    pub fn data_bytes(&self) -> u64 {
        let meshes: u64 = self
            .shapes
            .iter()
            .map(|s| match &s.geometry {
                Geometry::Mesh(m) => m.data_bytes(),
                _ => 0,
            })
            .sum();
        let texels = |t: &Texels| match t {
            Texels::Bytes { rgb, .. } => rgb.len() as u64 * 4,
            Texels::Float(v) => v.len() as u64 * 12,
        };
        let textures: u64 = self
            .textures
            .iter()
            .map(|t| match t {
                TextureDesc::Bitmap(b) => texels(&b.texels),
                _ => 0,
            })
            .sum();
        let envmaps: u64 = self
            .emitters
            .iter()
            .map(|e| match e {
                EmitterDesc::EnvMap { texels, .. } => texels.len() as u64 * 12,
                _ => 0,
            })
            .sum();
        meshes + textures + envmaps
    }
}

/// The effects a scene calls for. The renderer selects code paths from this
/// so that a scene pays nothing for what it does not contain.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Features {
    /// At least one bitmap or checkerboard texture is referenced.
    pub textures: bool,
    /// At least one BSDF transmits light (dielectric, roughdielectric, thindielectric).
    pub transmission: bool,
    /// At least one BSDF has a delta (perfectly specular) lobe.
    pub delta_bsdfs: bool,
    /// At least one microfacet BSDF (rough conductor / dielectric / plastic).
    pub microfacets: bool,
    /// At least one shape carries an area emitter.
    pub area_lights: bool,
    /// At least one point or directional emitter.
    pub delta_lights: bool,
    /// A constant or envmap emitter surrounds the scene.
    pub environment: bool,
    /// At least one analytic (non-triangle) shape: sphere or disk.
    pub analytic_shapes: bool,
    /// At least one surface light passes straight through (`mask`, `null`): shadow rays
    /// carry a transmittance and paths step through such surfaces.
    pub pass_through: bool,
    /// At least one shading normal is perturbed by a texture (`bumpmap`, `normalmap`).
    pub perturbed_normals: bool,
}

impl Features {
    /// The effects the scene uses, in words (for logs: "area lights, analytic shapes").
    pub fn names(&self) -> Vec<&'static str> {
        let all = [
            (self.area_lights, "area lights"),
            (self.delta_lights, "point or directional lights"),
            (self.environment, "environment light"),
            (self.textures, "textures"),
            (self.transmission, "transmission"),
            (self.delta_bsdfs, "perfectly specular surfaces"),
            (self.microfacets, "rough (microfacet) surfaces"),
            (self.analytic_shapes, "analytic shapes"),
            (self.pass_through, "cut-outs (mask, null)"),
            (self.perturbed_normals, "bump or normal maps"),
        ];
        all.into_iter()
            .filter(|(on, _)| *on)
            .map(|(_, n)| n)
            .collect()
    }
}

impl std::fmt::Display for Features {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.names().as_slice() {
            [] => f.write_str("none"),
            names => f.write_str(&names.join(", ")),
        }
    }
}

/// Integrator choice and its parameters (Mitsuba's meaning of each).
#[derive(Clone, Debug, PartialEq)]
pub enum IntegratorDesc {
    Path(PathParams),
    /// `guided_path`: path tracing guided by an SD-tree (Müller et al. 2017 + 2019).
    GuidedPath(GuidedParams),
}

impl IntegratorDesc {
    /// The Mitsuba path-tracing parameters (shared by every integrator).
    pub fn path_params(&self) -> PathParams {
        match self {
            IntegratorDesc::Path(p) => *p,
            IntegratorDesc::GuidedPath(g) => g.path,
        }
    }
}

/// Unit of [`GuidedParams::budget`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GuidedBudgetType {
    /// Samples per pixel (training + final).
    Spp,
    /// Wall-clock seconds (training + final).
    Seconds,
}

/// Next-event estimation mode of `guided_path`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GuidedNee {
    /// No light sampling (the 2017 paper's results).
    Never,
    /// Light sampling at every smooth vertex; the guide learns indirect light only.
    Always,
    /// Light sampling while fewer than 128 spp have been rendered.
    Kickstart,
}

/// Russian roulette of `guided_path`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GuidedRoulette {
    /// Mitsuba's: survival `min(max(throughput) eta^2, 0.95)` from `rr_depth` on.
    Throughput,
    /// Müller's reference implementation ([G] in `ppg-algorithm.md`), from `rr_depth` on at
    /// vertices with a smooth BSDF whose sampled lobe is not delta: survival
    /// `clamp(max(throughput) eta^2, 0.1, 0.99)` until the tree is built, 0.99 after (roulette
    /// effectively off); no roulette at other vertices. Default of the 2017 and 2019 presets.
    Ppg,
    /// Once the tree is built, at guided vertices from `guided_rr_depth` on: survival
    /// `clamp(E / (0.25 I), 0.2, 1)` where `E` = throughput x the guide's incident-radiance
    /// estimate along the sampled direction (the path's expected remaining contribution) and
    /// `I` = the pixel's value estimated by the previous iterations (the lower edge of a
    /// weight window after Vorba and Křivánek 2016; `splitting` is its upper edge).
    /// Elsewhere as `Throughput`, from `rr_depth` on. Default of the pathfarm preset.
    Guided,
}

/// How the training iterations' images become the final image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GuidedCombination {
    /// The last iteration only.
    Discard,
    /// Stop training when the extrapolated variance worsens; render the rest.
    Automatic,
    /// Inverse-variance weighted mean of the last (up to) 4 iterations.
    InverseVar,
}

/// Spatial recording filter of `guided_path`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GuidedSpatialFilter {
    Nearest,
    Stochastic,
    Box,
}

/// Directional recording filter of `guided_path`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GuidedDirectionalFilter {
    Nearest,
    Box,
}

/// How the BSDF-sampling fraction is chosen.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GuidedFractionLoss {
    /// Fixed at `bsdf_sampling_fraction`.
    None,
    /// Learned per spatial leaf (Adam on the KL-divergence gradient).
    Kl,
    /// Learned per spatial leaf (Adam on the variance gradient).
    Var,
}

/// Parameters of `guided_path` (snake_case names after Müller's plugin). A `preset`
/// ("2017" or "2019") sets defaults; explicit parameters override it.
#[derive(Clone, Debug, PartialEq)]
pub struct GuidedParams {
    /// `max_depth`, `rr_depth`, `hide_emitters` with the `path` meaning.
    pub path: PathParams,
    /// `budget`: seconds or spp per `budget_type`; `None` = the sensor's
    /// sample_count (spp) or 300 (seconds).
    pub budget: Option<f64>,
    /// `budget_type`: "spp" (default) or "seconds".
    pub budget_type: GuidedBudgetType,
    /// `spp_per_pass` (4; 2019 preset 1).
    pub spp_per_pass: u32,
    /// `s_tree_threshold` c (12000; 2019 preset 4000, pathfarm preset 2000).
    pub s_tree_threshold: f64,
    /// `d_tree_threshold` rho (0.01).
    pub d_tree_threshold: f64,
    /// `carry_over`: the fraction of an iteration's guide statistics the next iteration's
    /// starts with, in [0, 1] (applied in 1/256ths). 0 in the 2017 and 2019 presets (each
    /// iteration learns from its own records alone, as in the papers), 0.5 in pathfarm's:
    /// the tree built after iteration k then learns from every earlier record with weight
    /// 0.5^age. Records are unbiased whichever guide sampled them, only noisier when older;
    /// 3-7 % lower relMSE at short budgets for 30 % more tree memory
    /// (`docs/decisions/carry-over.md`).
    pub carry_over: f64,
    /// `nee`: "never" | "always" (default) | "kickstart".
    pub nee: GuidedNee,
    /// `sample_combination`: "discard" | "automatic" (default) | "inversevar" (2019).
    pub sample_combination: GuidedCombination,
    /// `spatial_filter`: "nearest" (default) | "stochastic" (2019) | "box".
    ///
    /// "box" splats every record into all the leaves a box of its leaf's size overlaps, the
    /// noise-free form of "stochastic": a better tree per sample, but recording is 3-4x
    /// slower and loses at equal time (`docs/decisions/spatial-filter-box.md`).
    pub spatial_filter: GuidedSpatialFilter,
    /// `directional_filter`: "nearest" (default) | "box" (2019).
    pub directional_filter: GuidedDirectionalFilter,
    /// `bsdf_sampling_fraction` (0.5), used when the loss is "none".
    pub bsdf_sampling_fraction: f32,
    /// `bsdf_sampling_fraction_loss`: "none" (default) | "kl" (2019) | "var".
    pub bsdf_sampling_fraction_loss: GuidedFractionLoss,
    /// `russian_roulette`: "throughput" (Mitsuba's) | "ppg" (the reference implementation's;
    /// 2017 and 2019 presets) | "guided" (pathfarm preset).
    pub russian_roulette: GuidedRoulette,
    /// `guided_rr_depth`: the path depth from which guided roulette applies at guided
    /// vertices, with `russian_roulette` "guided" (3; `rr_depth` keeps its `path` meaning
    /// everywhere else). The guide's radiance estimate knows which paths are worth
    /// continuing long before Mitsuba's default `rr_depth` of 5, where a throughput-based
    /// roulette does not (`docs/decisions/guided-rr-depth.md`).
    pub guided_rr_depth: u32,
    /// `splitting`: with guided Russian roulette, split paths whose expected contribution is
    /// well above the pixel's estimated value (the weight window's upper edge), in the passes
    /// that record nothing. true in the pathfarm preset, false in 2017 and 2019.
    pub splitting: bool,
    /// `light_splitting`: in the same passes as `splitting`, take several light (next-event)
    /// samples at a guided vertex whose light sample is noisy compared with the pixel's
    /// estimated value: `throughput x` the standard deviation of a light sample's value learned
    /// in the vertex's spatial leaf, over the pixel's value, stochastically rounded, at most
    /// 4 samples (the weight window of `splitting`, applied to the light sample; MIS
    /// weighs the n samples as one technique with pdf `n p_light`). The light samples of the
    /// quadtrees' "indirect only" learning are otherwise invisible to the guide. true in the
    /// pathfarm preset, false in 2017 and 2019.
    pub light_splitting: bool,
    /// `path_fallback`: while training, compare the efficiency (variance x cost per sample) of
    /// guided sampling with an unguided probe and render the rest of the budget as plain path
    /// tracing when guiding does not pay. false in the 2017 and 2019 presets, true in pathfarm's.
    pub path_fallback: bool,
    /// `guide_hemisphere`: at BSDFs that cannot transmit, sample the guide only in the
    /// hemisphere they reflect into (exactly for axis-aligned normals, else the cells of the
    /// 4x4 direction grid that reach above the surface), so no guide sample is spent below an
    /// opaque surface. false in the 2017 and 2019 presets (as the papers), true in pathfarm's.
    pub guide_hemisphere: bool,
    /// `guide_cosine`: with `guide_hemisphere`, weight the hemisphere's cells by the surface's
    /// clamped cosine (the cell's mean of it), so the guide samples incident radiance x cosine,
    /// the product a diffuse surface integrates, instead of incident radiance alone. false in
    /// the 2017 and 2019 presets, true in pathfarm's.
    pub guide_cosine: bool,
    /// `max_memory_mb`: approximate cap on the tree's memory (default none).
    pub max_memory_mb: Option<f64>,
    /// `max_nodes`: cap on the number of spatial nodes (default none).
    pub max_nodes: Option<u64>,
}

impl GuidedParams {
    /// Defaults of the 2017 paper (with `nee` = always, `sample_combination` = automatic).
    pub fn preset_2017() -> Self {
        Self {
            path: PathParams::default(),
            budget: None,
            budget_type: GuidedBudgetType::Spp,
            spp_per_pass: 4,
            s_tree_threshold: 12000.0,
            d_tree_threshold: 0.01,
            carry_over: 0.0,
            nee: GuidedNee::Always,
            sample_combination: GuidedCombination::Automatic,
            spatial_filter: GuidedSpatialFilter::Nearest,
            directional_filter: GuidedDirectionalFilter::Nearest,
            bsdf_sampling_fraction: 0.5,
            bsdf_sampling_fraction_loss: GuidedFractionLoss::None,
            russian_roulette: GuidedRoulette::Ppg,
            guided_rr_depth: 3,
            splitting: false,
            light_splitting: false,
            path_fallback: false,
            guide_hemisphere: false,
            guide_cosine: false,
            max_memory_mb: None,
            max_nodes: None,
        }
    }

    /// The 2019 improvements: inversevar, stochastic spatial and box directional filters,
    /// learned fraction (KL), `s_tree_threshold` 4000, `spp_per_pass` 1.
    pub fn preset_2019() -> Self {
        Self {
            spp_per_pass: 1,
            s_tree_threshold: 4000.0,
            sample_combination: GuidedCombination::InverseVar,
            spatial_filter: GuidedSpatialFilter::Stochastic,
            directional_filter: GuidedDirectionalFilter::Box,
            bsdf_sampling_fraction_loss: GuidedFractionLoss::Kl,
            ..Self::preset_2017()
        }
    }

    /// pathfarm's default: the 2019 configuration (its box directional filter included) with
    /// guided Russian roulette ([`GuidedRoulette::Guided`]), splitting and the fallback to path
    /// tracing where guiding does not pay (`path_fallback`). With splitting, the box filter
    /// beats the nearest one end to end: 30 CPU-s relMSE 0.085-0.095 vs 0.102-0.107 on
    /// veach-ajar and 0.00049-0.00054 vs 0.00061-0.00063 on door-ajar (3 seeds each), the
    /// Cornell box unchanged (it falls back to path tracing either way).
    ///
    /// Its spatial threshold is 2000 rather than 4000: at the benchmark resolution (320x180)
    /// a pass records 16x fewer paths than at the 1280x720 the paper's values were set for,
    /// so 4000 left the spatial tree coarse (`docs/decisions/s-tree-threshold.md`).
    pub fn preset_pathfarm() -> Self {
        Self {
            s_tree_threshold: 2000.0,
            russian_roulette: GuidedRoulette::Guided,
            splitting: true,
            light_splitting: true,
            carry_over: 0.5,
            path_fallback: true,
            guide_hemisphere: true,
            guide_cosine: true,
            ..Self::preset_2019()
        }
    }
}

impl Default for GuidedParams {
    fn default() -> Self {
        Self::preset_pathfarm()
    }
}

/// Parameters of Mitsuba's `path` integrator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PathParams {
    /// Longest path depth in the output (-1 = unbounded). 1 renders only
    /// directly visible emitters, 2 direct illumination. Default -1.
    pub max_depth: i32,
    /// Depth from which Russian roulette starts. Default 5.
    pub rr_depth: u32,
    /// Hide directly visible emitters. Default false.
    pub hide_emitters: bool,
    /// Mitsuba 0.x's `strictNormals`: a vertex, a light sample or a scattered direction on
    /// which the shading and the geometric normal disagree about the side is dropped.
    /// Default false.
    pub strict_normals: bool,
}

impl Default for PathParams {
    fn default() -> Self {
        Self {
            max_depth: -1,
            rr_depth: 5,
            hide_emitters: false,
            strict_normals: false,
        }
    }
}

/// The camera, film and sampler.
#[derive(Clone, Debug, PartialEq)]
pub struct SensorDesc {
    /// Camera-to-world. Camera space looks down +z, +y up, +x left (Mitsuba).
    pub to_world: Mat4,
    /// Field of view in degrees along `fov_axis`.
    pub fov: f32,
    pub fov_axis: FovAxis,
    pub near_clip: f32,
    pub far_clip: f32,
    pub film: FilmDesc,
    /// `sampler.sample_count` (samples per pixel). Default 4.
    pub sample_count: u32,
    /// `sampler.seed`. Default 0.
    pub seed: u64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FovAxis {
    X,
    Y,
    Diagonal,
    Smaller,
    Larger,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FilmDesc {
    pub width: u32,
    pub height: u32,
    pub rfilter: RFilter,
}

/// Reconstruction filter. Mitsuba's defaults: box radius 0.5, tent radius 1,
/// gaussian stddev 0.5 (support 4 stddev).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RFilter {
    Box { radius: f32 },
    Tent { radius: f32 },
    Gaussian { stddev: f32 },
}

/// A colour parameter: a constant or a texture index.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TexRef {
    Const(Vec3),
    Texture(usize),
}

#[derive(Clone, Debug, PartialEq)]
pub enum TextureDesc {
    Bitmap(BitmapDesc),
    Checkerboard {
        color0: Vec3,
        color1: Vec3,
        /// Applied to the surface uv before lookup.
        to_uv: UvTransform,
    },
}

/// 2D affine transform of texture coordinates: `uv' = m * uv + t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UvTransform {
    pub m: glam::Mat2,
    pub t: Vec2,
}

impl Default for UvTransform {
    fn default() -> Self {
        Self {
            m: glam::Mat2::IDENTITY,
            t: Vec2::ZERO,
        }
    }
}

impl UvTransform {
    pub fn apply(&self, uv: Vec2) -> Vec2 {
        self.m * uv + self.t
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct BitmapDesc {
    pub width: u32,
    pub height: u32,
    /// Linear RGB texels, row-major, row 0 is the top of the image file.
    pub texels: Texels,
    pub filter: TexFilter,
    pub wrap: WrapMode,
    pub to_uv: UvTransform,
}

/// The linear RGB texels of a bitmap, row-major, row 0 at the top of the image file.
///
/// 8-bit images keep their bytes, 4 per texel (R, G, B, unused), with a 256-entry table of
/// each byte's linear value: [`Texels::get`] returns exactly what converting every texel at
/// load would have stored, in a third of the memory (the shared veach-ajar scene's three
/// photographs take 39 MB instead of 117 MB), so lookups miss the cache less. Other images
/// (16-bit, float, EXR) keep f32 texels.
#[derive(Clone, Debug, PartialEq)]
pub enum Texels {
    Bytes {
        rgb: Arc<Vec<[u8; 4]>>,
        /// Linear value of each byte (the sRGB curve, or `b / 255` for `raw` textures).
        table: Arc<[f32; 256]>,
    },
    Float(Arc<Vec<Vec3>>),
}

impl Texels {
    /// Number of texels.
    pub fn len(&self) -> usize {
        match self {
            Texels::Bytes { rgb, .. } => rgb.len(),
            Texels::Float(t) => t.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Texel `i` (row-major) in linear RGB.
    #[inline]
    pub fn get(&self, i: usize) -> Vec3 {
        match self {
            Texels::Bytes { rgb, table } => byte_texel(table, rgb[i]),
            Texels::Float(t) => t[i],
        }
    }

    /// Every texel in order, in linear RGB.
    pub fn iter(&self) -> impl Iterator<Item = Vec3> + '_ {
        (0..self.len()).map(|i| self.get(i))
    }
}

/// The linear RGB of an 8-bit texel through its table.
#[inline(always)]
pub fn byte_texel(table: &[f32; 256], b: [u8; 4]) -> Vec3 {
    Vec3::new(
        table[b[0] as usize],
        table[b[1] as usize],
        table[b[2] as usize],
    )
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TexFilter {
    Nearest,
    Bilinear,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WrapMode {
    Repeat,
    Mirror,
    Clamp,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MicrofacetDistribution {
    Beckmann,
    Ggx,
}

/// Microfacet roughness parameters (Mitsuba: `distribution`, `alpha` or
/// `alpha_u`/`alpha_v`, `sample_visible`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Roughness {
    pub distribution: MicrofacetDistribution,
    pub alpha_u: f32,
    pub alpha_v: f32,
    pub sample_visible: bool,
}

/// BSDF plugins with their (resolved) parameters.
#[derive(Clone, Debug, PartialEq)]
pub enum BsdfDesc {
    Diffuse {
        reflectance: TexRef,
    },
    /// Front and back materials (indices into `SceneDesc::bsdfs`). With one
    /// nested BSDF both are the same.
    TwoSided {
        front: usize,
        back: usize,
    },
    /// Mitsuba's `mask`: the nested BSDF (an index into `SceneDesc::bsdfs`) where the surface
    /// is opaque, and light passes straight through with probability `1 - opacity` (the
    /// opacity texture's luminance, clamped to [0, 1]).
    Mask {
        opacity: TexRef,
        nested: usize,
    },
    /// Mitsuba's `null`: the surface does not scatter; light passes straight through.
    Null,
    /// Mitsuba's `bumpmap`: the nested BSDF under the shading normal that the height field
    /// `height` (a texture index; its luminance times `scale`) perturbs.
    BumpMap {
        height: usize,
        scale: f32,
        nested: usize,
        normals: PerturbOptions,
    },
    /// Mitsuba's `normalmap`: the nested BSDF under the shading normal the texture
    /// `normals_texture` gives (`2 rgb - 1`, in the tangent frame of the surface's `u`
    /// direction).
    NormalMap {
        normals_texture: usize,
        nested: usize,
        normals: PerturbOptions,
    },
    Conductor {
        eta: Vec3,
        k: Vec3,
        specular_reflectance: TexRef,
    },
    RoughConductor {
        roughness: Roughness,
        eta: Vec3,
        k: Vec3,
        specular_reflectance: TexRef,
    },
    Dielectric {
        int_ior: f32,
        ext_ior: f32,
        specular_reflectance: TexRef,
        specular_transmittance: TexRef,
    },
    RoughDielectric {
        roughness: Roughness,
        int_ior: f32,
        ext_ior: f32,
        specular_reflectance: TexRef,
        specular_transmittance: TexRef,
    },
    ThinDielectric {
        int_ior: f32,
        ext_ior: f32,
        specular_reflectance: TexRef,
        specular_transmittance: TexRef,
    },
    Plastic {
        int_ior: f32,
        ext_ior: f32,
        diffuse_reflectance: TexRef,
        specular_reflectance: TexRef,
        nonlinear: bool,
    },
    RoughPlastic {
        /// Mitsuba's roughplastic is isotropic: alpha_u == alpha_v.
        roughness: Roughness,
        int_ior: f32,
        ext_ior: f32,
        diffuse_reflectance: TexRef,
        specular_reflectance: TexRef,
        nonlinear: bool,
    },
}

/// The options Mitsuba's `bumpmap` and `normalmap` share.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PerturbOptions {
    /// Mirror a perturbed normal that faces away from the incident direction (default on).
    pub flip_invalid_normals: bool,
    /// Attenuate the BSDF by the microfacet shadowing term of Estevez et al. (2019) against
    /// the bump terminator (default on).
    pub use_shadowing_function: bool,
}

/// A shape with its material and optional area emitter.
#[derive(Clone, Debug)]
pub struct ShapeDesc {
    pub id: Option<String>,
    pub geometry: Geometry,
    /// Index into `SceneDesc::bsdfs`. Shapes without a BSDF get Mitsuba 3's
    /// default: a diffuse BSDF with reflectance 0.5, or 0 on an emitting shape.
    pub bsdf: usize,
    pub emitter: Option<AreaEmitterDesc>,
    pub location: Location,
}

#[derive(Clone, Debug)]
pub enum Geometry {
    /// World-space triangle mesh (obj, ply, rectangle, cube, ...).
    Mesh(Arc<TriangleMesh>),
    /// Analytic sphere (Mitsuba `sphere`: `center`, `radius`, or a
    /// similarity `to_world`).
    Sphere {
        center: Vec3,
        radius: f32,
        flip_normals: bool,
    },
    /// Analytic unit disk in the local xy plane (normal +z), mapped by
    /// `to_world`.
    Disk { to_world: Mat4, flip_normals: bool },
    /// Analytic open cylinder (no caps) of radius 1 around the local z axis from z = 0 to
    /// z = 1, mapped by `to_world` (which keeps it circular: Mitsuba's `cylinder` with its
    /// `p0`, `p1` and `radius` folded in).
    Cylinder { to_world: Mat4, flip_normals: bool },
}

/// A triangle mesh in world space. Invariant (checked by the loader): all
/// positions, normals and uvs are finite, indices are in range, normals
/// (when present) are unit length.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriangleMesh {
    pub positions: Vec<Vec3>,
    /// Per-vertex shading normals; `None` for face normals
    /// (`face_normals=true` or none in the file).
    pub normals: Option<Vec<Vec3>>,
    /// Per-vertex texture coordinates, as Mitsuba exposes them to textures.
    pub uvs: Option<Vec<Vec2>>,
    pub indices: Vec<[u32; 3]>,
    /// Geometric (and shading) normals are negated (`flip_normals`).
    pub flip_normals: bool,
}

impl TriangleMesh {
    /// Bytes of its vertex and index arrays.
    pub fn data_bytes(&self) -> u64 {
        let v = self.positions.len() as u64;
        let normals = self.normals.as_ref().map_or(0, |n| n.len() as u64 * 12);
        let uvs = self.uvs.as_ref().map_or(0, |u| u.len() as u64 * 8);
        v * 12 + normals + uvs + self.indices.len() as u64 * 12
    }
}

/// Mitsuba `area` emitter: emits `radiance` from the front side (the side
/// the surface normal points to).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AreaEmitterDesc {
    pub radiance: Vec3,
}

#[derive(Clone, Debug, PartialEq)]
pub enum EmitterDesc {
    Point {
        position: Vec3,
        /// Radiant intensity (W/sr).
        intensity: Vec3,
    },
    /// Mitsuba's `spot`: a point light at `to_world`'s origin shining along its +z, at full
    /// intensity within `beam_width` of the axis, falling off linearly in angle to zero at
    /// `cutoff_angle` (radians).
    Spot {
        to_world: Mat4,
        intensity: Vec3,
        cutoff_angle: f32,
        beam_width: f32,
    },
    Constant {
        radiance: Vec3,
    },
    EnvMap {
        width: u32,
        height: u32,
        /// Linear RGB, row-major, row 0 at the top (latitude-longitude map).
        texels: Arc<Vec<Vec3>>,
        scale: f32,
        to_world: Mat4,
    },
    Directional {
        /// World-space direction the light travels in (normalised).
        direction: Vec3,
        irradiance: Vec3,
    },
}
